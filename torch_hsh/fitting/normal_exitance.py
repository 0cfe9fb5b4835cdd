r"""Single-index spectra of a BRDF known at normal exitance only (paper Eqs. 41--45)."""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from .. import kernel as _hb
from .._checks import check_shape, check_tensor, validation_enabled
from ..quadrature import gauss_legendre
from .arguments import _TWO_PI, _check_dtype

__all__ = ["project_normal_exitance", "normal_exitance_energy", "normal_exitance_to_isotropic"]


def _theta_table(z: torch.Tensor, P: int) -> torch.Tensor:
    """Zonal HSH Theta_p(z) = sqrt((2p+1)/(2 pi)) P~_p(z), ``(..., P+1)``."""
    s = torch.sqrt((1.0 - z * z).clamp(min=0.0))
    d = torch.stack([s, torch.zeros_like(s), z], dim=-1)
    H = _hb.hsh(d, P)
    idx = torch.tensor([n * n + n for n in range(P + 1)], device=z.device)
    return H.index_select(-1, idx)


def project_normal_exitance(
    brdf_1d: Callable[[torch.Tensor], torch.Tensor],
    order: int,
    n_theta: Optional[int] = None,
    normalization: str = "helmholtz",
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r"""Single-index spectrum of a BRDF at normal exitance (paper Eqs. 41--45).

    The paper expands a BRDF known only as a function ``g(cos theta_i)`` of the
    incident direction at fixed exitance :math:`\theta_o = 0` (e.g. its
    Torrance--Sparrow model, Eq. 38) in the zonal (``q = 0``) isotropic basis,
    treating ``g`` as a function on :math:`\Omega_i\times\Omega_o` that does not
    depend on :math:`\omega_o`, :math:`F(\omega_i, \omega_o) = g(\cos\theta_i)`.

    With the 1-D zonal HSH :math:`\Theta_p(z) = \sqrt{(2p+1)/(2\pi)}\,\tilde P_p(z)`
    (orthonormal on the hemisphere) and
    :math:`b_p = \int_{\Omega_i} g\,\Theta_p\,d\omega_i = 2\pi\int_0^1 g\,\Theta_p\,dz`,
    and using :math:`\int_{\Omega}\Theta_r\,d\omega = \sqrt{2\pi}\,\delta_{r0}`, the
    isotropic coefficients of ``F`` are exactly

    .. math::
        a_{p0}^0 = a_{0p}^0 = \begin{cases}\sqrt{2\pi}\,b_0 & p = 0\\
        \sqrt{\pi}\,b_p & p > 0\end{cases}, \qquad a_{pr}^q = 0 \text{ otherwise},

    which reproduces Eqs. (41), (42), (44) term by term (e.g. ``a_0 = 2 rho_d`` for
    a Lambertian part). Because every basis function is reciprocal, the
    expansion :math:`\sum_p a_p\,\mathcal H_{p0}^0` represents the *symmetrised*
    function :math:`(g(\cos\theta_i) + g(\cos\theta_o))/2`, not ``F``.

    Discrepancy with the paper: Eq. (45),
    :math:`f = a_0 + 2\sum_{p\ge1} a_p\mathcal H_{p0}^0`, is inconsistent with
    Eqs. (39)--(44): its first term lacks the factor
    :math:`\mathcal H_{00}^0 = 1/(2\pi)` and the factor 2 double counts the
    orthonormal functions :math:`\mathcal H_{p0}^0 = \mathcal H_{0p}^0`. The
    consistent reconstruction of ``g`` itself is
    :math:`g(z) = \sum_p b_p\,\Theta_p(z)` with ``b`` from
    ``normalization="hsh"``, and the energy fraction (Fig. 5) is
    ``cumsum(b**2) / normal_exitance_energy(g)`` (Parseval holds for ``b``, not
    for ``a``).

    Args:
        brdf_1d: callable ``g(cos_theta_i)``: ``(M,)`` -> ``(M,)`` or ``(M, C)``;
            evaluated at interior Gauss--Legendre nodes only (never at ``z = 0``).
        order: largest ``p``.
        n_theta: Gauss--Legendre nodes on ``[0, 1]``; default
            ``max(2 (P + 1), 256)`` (exact for polynomial ``g`` of degree
            ``<= 511 - P``).
        normalization: ``"helmholtz"`` -> the paper's :math:`a_p = a_{p0}^0`;
            ``"hsh"`` -> the orthonormal 1-D coefficients :math:`b_p`.
        dtype, device: working precision / device.

    Returns:
        ``(P + 1,)`` or ``(C, P + 1)``; see :func:`normal_exitance_to_isotropic`
        to place ``a_p`` into an isotropic coefficient vector.

    Example:
        >>> a = project_normal_exitance(lambda z: torch.full_like(z, 0.3 / math.pi), 3)
        >>> [round(float(x), 12) + 0.0 for x in a]  # Lambertian: a_0 = 2 rho_d
        [0.6, 0.0, 0.0, 0.0]
    """
    if not callable(brdf_1d):
        raise TypeError(f"`brdf_1d` must be callable as g(cos_theta_i), got {type(brdf_1d).__name__}")
    _check_dtype(dtype)
    P = _hb.check_order(order)
    if normalization not in ("helmholtz", "hsh"):
        raise ValueError(f"`normalization` must be 'helmholtz' or 'hsh', got {normalization!r}")
    nt = max(2 * (P + 1), 256) if n_theta is None else n_theta
    if isinstance(nt, bool) or not isinstance(nt, int) or nt < 1:
        raise ValueError(f"`n_theta` must be a positive integer, got {nt!r}")
    z, w = gauss_legendre(nt, 0.0, 1.0, dtype=dtype, device=device)
    g = _call_1d(brdf_1d, z)
    T = _theta_table(z, P) * (w * _TWO_PI)[:, None]  # (nt, P+1)
    bcoef = g.transpose(0, -1) @ T if g.dim() == 2 else g @ T
    if normalization == "hsh":
        return bcoef
    scale = torch.full((P + 1,), math.sqrt(math.pi), dtype=dtype, device=z.device)
    scale[0] = math.sqrt(_TWO_PI)
    return bcoef * scale


def _call_1d(brdf_1d, z):
    g = brdf_1d(z)
    if not isinstance(g, torch.Tensor):
        raise TypeError(f"`brdf_1d` must return a torch.Tensor, got {type(g).__name__}")
    # called with (M,) cosines, it must return (M,) or (M, C)
    check_shape(g, "brdf_1d(cos_theta_i)", ("M",), ("M", "C"), sizes={"M": z.shape[0]})
    g = g.to(z.dtype)
    if validation_enabled() and not bool(torch.isfinite(g).all()):
        raise ValueError("`brdf_1d` returned NaN/Inf values at interior Gauss-Legendre nodes")
    return g


def normal_exitance_energy(
    brdf_1d: Callable[[torch.Tensor], torch.Tensor],
    n_theta: int = 256,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r""":math:`\int_{\Omega_i} g(\cos\theta_i)^2 d\omega_i = 2\pi\int_0^1 g^2 dz` (Gauss--Legendre).

    Denominator of the 1-D accuracy ``cumsum(b**2) / E`` with ``b`` from
    ``project_normal_exitance(..., normalization="hsh")``.

    Returns:
        ``()`` or ``(C,)``.

    Example:
        >>> round(float(normal_exitance_energy(lambda z: torch.ones_like(z))), 12) == round(2 * math.pi, 12)
        True
    """
    if not callable(brdf_1d):
        raise TypeError(f"`brdf_1d` must be callable as g(cos_theta_i), got {type(brdf_1d).__name__}")
    _check_dtype(dtype)
    z, w = gauss_legendre(n_theta, 0.0, 1.0, dtype=dtype, device=device)
    g = _call_1d(brdf_1d, z)
    ww = w * _TWO_PI
    return ((g * g) * (ww if g.dim() == 1 else ww[:, None])).sum(0)


def normal_exitance_to_isotropic(a: torch.Tensor, order: Optional[int] = None) -> torch.Tensor:
    r"""Place the single-index spectrum ``a_p`` at the isotropic columns ``(p, 0, 0)``.

    Args:
        a: ``(..., P' + 1)`` from ``project_normal_exitance(normalization="helmholtz")``.
        order: isotropic order ``P`` of the result (default ``P'``); entries with
            ``p > P`` are dropped, missing ones are zero.

    Returns:
        ``(..., K)`` coefficients of ``helmholtz_isotropic`` (``K = num_isotropic(P)``),
        zero except ``[..., index of (p, 0, 0)] = a_p``.

    Example:
        >>> normal_exitance_to_isotropic(torch.tensor([1.0, 2.0])).tolist()
        [1.0, 2.0, 0.0, 0.0]
    """
    check_tensor(a, "a", min_dims=1)
    P = a.shape[-1] - 1 if order is None else _hb.check_order(order)
    idx = _hb.isotropic_indices(P)
    sel = ((idx[:, 1] == 0) & (idx[:, 2] == 0)).nonzero().squeeze(-1)  # p-major: p = 0..P
    n = min(P + 1, a.shape[-1])
    out = a.new_zeros(*a.shape[:-1], idx.shape[0])
    out[..., sel[:n].to(a.device)] = a[..., :n]
    return out
