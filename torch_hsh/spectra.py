r"""Closed-form spectra of the Lambertian and the ideal-mirror BRDF (paper Section 5).

* Lambertian :math:`f = \rho/\pi`: in both Helmholtz bases the only non-zero
  coefficient is the constant function's, :math:`a_{00}^0 = 2\rho`
  (:math:`\mathcal H_{00}^0 = 1/(2\pi)` and :math:`\iint d\omega_i d\omega_o = 4\pi^2`).
* Ideal mirror, paper Eq. (28),
  :math:`f = \delta(\theta_i - \theta_o)\,\delta(\phi_i - \phi_o + \pi)/\sin\theta_i`,
  i.e. :math:`\int f(\omega_i, \omega_o) g(\omega_o)\,d\omega_o = g(R\omega_i)` with
  :math:`R(\theta, \phi) = (\theta, \phi + \pi)`. Then
  :math:`a_{jk} = \int_\Omega B_{jk}(\omega, R\omega)\,d\omega` and, since
  :math:`H_n^m(R\omega) = (-1)^m H_n^m(\omega)`,

  - anisotropic basis: :math:`a = (-1)^q` for the diagonal pairs ``p = r, q = s``
    and 0 otherwise. **ERRATUM 2**: the printed Eq. (37) gives
    :math:`(-1)^q/2` -- Eq. (33) drops the factor 2 from the two equal integrals
    of Eq. (31);
  - isotropic basis: ``p = r`` only, 1 for ``q = 0`` and :math:`\sqrt2(-1)^q` for
    ``q > 0`` (each isotropic ``q > 0`` function is
    :math:`(B^{qq} + B^{-q,-q})/\sqrt2` of the anisotropic basis).

:func:`mirror_spectrum_printed` returns the paper's printed values for
comparison only.
"""
from __future__ import annotations

import math
from typing import Optional, Union

import torch

from . import kernel as _hb
from ._checks import MAX_ANISOTROPIC_ORDER, check_order, check_tensor
from .bases import Basis, get_basis
from .bases.helmholtz import HelmholtzAnisotropic, HelmholtzIsotropic

__all__ = ["lambertian_spectrum", "mirror_spectrum", "mirror_spectrum_printed"]


def lambertian_spectrum(
    albedo: Union[float, torch.Tensor],
    order: int,
    basis: Union[str, Basis] = "helmholtz_isotropic",
    dtype: Optional[torch.dtype] = None,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r"""Coefficients of the Lambertian BRDF :math:`\rho/\pi`.

    For the Helmholtz bases (isotropic and anisotropic) the result is exact:
    ``2 * albedo`` at the constant function (column 0) and zero elsewhere. For
    any other registered basis the coefficients of :math:`1/\pi` are computed by
    :func:`torch_hsh.fitting.project` (full 4-D product rule, float64) and scaled
    by ``albedo``.

    Args:
        albedo: :math:`\rho`, a number or a tensor of any shape ``(...)`` (e.g. RGB ``(3,)``).
        order: truncation order ``P``.
        basis: basis name or object.
        dtype, device: used when ``albedo`` is a number (default float64, CPU);
            otherwise those of ``albedo``.

    Returns:
        ``(..., K)``.

    Example:
        >>> lambertian_spectrum(0.5, 1).tolist()
        [1.0, 0.0, 0.0, 0.0]
    """
    b = get_basis(basis)
    P = b.check_order(order)
    if isinstance(albedo, torch.Tensor):
        check_tensor(albedo, "albedo")
        rho = albedo
    else:
        if isinstance(albedo, bool) or not isinstance(albedo, (int, float)):
            raise TypeError(f"`albedo` must be a number or a tensor, got {type(albedo).__name__}")
        rho = torch.tensor(float(albedo), dtype=dtype or torch.float64, device=device)
    K = b.num_functions(P)
    if isinstance(b, (HelmholtzIsotropic, HelmholtzAnisotropic)):
        unit = torch.zeros(K, dtype=rho.dtype, device=rho.device)
        unit[0] = 2.0
    else:
        from .fitting import project

        unit = project(
            lambda wi, wo: torch.full(wi.shape[:1], 1.0 / math.pi, dtype=wi.dtype, device=wi.device),
            P,
            basis=b,
            reduced=False,
            device=rho.device,
        ).to(rho.dtype)
    return rho.unsqueeze(-1) * unit


_HELMHOLTZ = ("helmholtz_isotropic", "helmholtz_anisotropic")


def _is_isotropic(basis) -> bool:
    """True for the isotropic Helmholtz basis, False for the anisotropic one; ``ValueError`` otherwise."""
    if isinstance(basis, (HelmholtzIsotropic, HelmholtzAnisotropic)):
        return isinstance(basis, HelmholtzIsotropic)
    if isinstance(basis, str) and basis in _HELMHOLTZ:
        return basis == "helmholtz_isotropic"
    raise ValueError(f"`basis` must be 'helmholtz_isotropic' or 'helmholtz_anisotropic', got {basis!r}")


def _mirror(order: int, basis, scale: float, dtype, device) -> torch.Tensor:
    if _is_isotropic(basis):
        P = check_order(order)
        idx = _hb.isotropic_indices(P)
        p, r, q = idx.unbind(-1)
        sign = 1.0 - 2.0 * (q % 2).to(torch.float64)
        val = torch.where(q == 0, torch.ones_like(sign), math.sqrt(2.0) * sign)
        out = torch.where(p == r, val, torch.zeros_like(val))
    else:
        P = check_order(order, max_order=MAX_ANISOTROPIC_ORDER)
        idx = _hb.anisotropic_indices(P)
        p, q, r, s = idx.unbind(-1)
        sign = 1.0 - 2.0 * (q.abs() % 2).to(torch.float64)
        out = torch.where((p == r) & (q == s), sign, torch.zeros_like(sign))
    return (scale * out).to(dtype=dtype, device=device)


def mirror_spectrum(
    order: int,
    basis: Union[str, Basis] = "helmholtz_isotropic",
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r"""Spectrum of the ideal mirror (Eq. 28) with **erratum 2** applied.

    * ``basis="helmholtz_isotropic"``: ``p = r`` only,
      1 for ``q = 0`` and :math:`\sqrt2(-1)^q` for ``q > 0``.
    * ``basis="helmholtz_anisotropic"``: :math:`(-1)^q` for
      ``p = r`` and ``q = s``, 0 otherwise.

    The mirror is not square-integrable (its energy is infinite), so the
    coefficients do not decay with the order; ``Acc(P)`` is undefined.

    Args:
        order: truncation order ``P``.
        basis: which Helmholtz basis, ``"helmholtz_isotropic"`` (default) or
            ``"helmholtz_anisotropic"`` (or the basis object); any other value raises ``ValueError``.
        dtype, device: of the result.

    Returns:
        ``(K,)``.

    Example:
        >>> [round(float(x), 6) for x in mirror_spectrum(1)]
        [1.0, 0.0, 1.0, -1.414214]
    """
    return _mirror(order, basis, 1.0, dtype, device)


def mirror_spectrum_printed(
    order: int,
    basis: Union[str, Basis] = "helmholtz_isotropic",
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r"""**The paper's printed (wrong) mirror spectrum**, for documentation and tests only.

    Eq. (37) prints :math:`(-1)^q/2\,\delta_{pr}\delta_{qs}` for the anisotropic
    basis, half of the correct value (erratum 2). For ``basis="helmholtz_isotropic"`` this
    returns what Eq. (37) implies for the isotropic basis through
    :math:`(a^{qq} + a^{-q,-q})/\sqrt2`: 1/2 for ``q = 0`` and
    :math:`(-1)^q/\sqrt2` for ``q > 0`` (also half the correct values). Use
    :func:`mirror_spectrum` for actual work.

    Example:
        >>> mirror_spectrum_printed(0).tolist()
        [0.5]
    """
    return _mirror(order, basis, 0.5, dtype, device)
