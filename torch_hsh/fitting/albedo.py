r"""Directional albedo of an expansion: closed form for the Helmholtz bases, quadrature otherwise."""
from __future__ import annotations

from typing import Optional

import torch

from .. import kernel as _hb
from .._checks import broadcast_shapes, check_dirs, check_same, check_tensor
from ..bases import Basis
from ..bases.helmholtz import HelmholtzAnisotropic, HelmholtzIsotropic, albedo_terms
from ..quadrature import direction_quadrature
from .arguments import _DEFAULT, BasisLike, _basis, _order_of

__all__ = ["directional_albedo"]


def _albedo_matrix(b: Basis, P: int, dtype, device):
    """(K, M) matrix S and a function wo -> (..., M) table T with albedo = (a @ S) . T(wo).

    ``S`` holds :func:`torch_hsh.bases.helmholtz.albedo_terms`; ``T`` is the zonal HSH ``Theta_n``, ``n <= P``
    (isotropic basis) or every HSH up to ``P`` (anisotropic basis).
    """
    if isinstance(b, HelmholtzIsotropic):
        K, M, table = _hb.num_isotropic(P), P + 1, (lambda wo: _theta_table_dirs(wo, P))
    elif isinstance(b, HelmholtzAnisotropic):
        K, M, table = _hb.num_anisotropic(P), (P + 1) ** 2, (lambda wo: _hb.hsh(wo, P))
    else:
        return None, None
    S = torch.zeros(K, M, dtype=torch.float64)
    for k, norm, terms in albedo_terms(P, b.isotropic):
        for moment, n, m in terms:
            S[k, n if b.isotropic else n * n + n + m] += norm * moment
    return S.to(dtype=dtype, device=device), table


def _theta_table_dirs(wo: torch.Tensor, P: int) -> torch.Tensor:
    H = _hb.hsh(wo, P)
    idx = torch.tensor([n * n + n for n in range(P + 1)], device=wo.device)
    return H.index_select(-1, idx)


def directional_albedo(
    coefficients: torch.Tensor,
    wo: torch.Tensor,
    order: Optional[int] = None,
    basis: BasisLike = _DEFAULT,
    channels: bool = False,
    n_theta: Optional[int] = None,
    n_phi: Optional[int] = None,
) -> torch.Tensor:
    r"""Directional albedo :math:`\rho(\omega_o) = \int_{\Omega_i} f(\omega_i, \omega_o)\cos\theta_i\,d\omega_i`.

    Closed form for the Helmholtz bases. Only ``q = 0`` functions survive the
    azimuthal integral, and with :math:`\Theta_n = \sqrt{(2n+1)/(2\pi)}\tilde P_n`,
    :math:`I_n = \int_\Omega \Theta_n(\cos\theta)\cos\theta\,d\omega
    = \sqrt{2\pi(2n+1)}\int_0^1 \tilde P_n(x)\,x\,dx` is
    :math:`\sqrt{2\pi}/2` (n = 0), :math:`\sqrt{\pi/6}` (n = 1), 0 (n >= 2). Hence

    .. math::
        \rho(\omega_o) = \sum_{p \ge r} a_{pr}^0 \frac{I_p\,\Theta_r(\cos\theta_o)
        + I_r\,\Theta_p(\cos\theta_o)}{\sqrt{2 + 2\delta_{pr}}}

    (isotropic basis; only ``p <= 1`` or ``r <= 1`` contribute), and the same
    with flat HSH indices ``j <= k`` and :math:`H_k(\omega_o)` for the anisotropic
    basis. Other bases: Gauss--Legendre x trapezoid quadrature over
    :math:`\omega_i` with ``n_theta = P + 2``, ``n_phi = 2P + 2`` by default
    (exact for polynomial-type bases of order ``P``).

    Args:
        coefficients: ``(..., K)`` or with ``channels=True`` ``(..., C, K)``.
        wo: ``(..., 3)`` outgoing local directions, broadcast element-wise with the
            leading dimensions of ``coefficients`` (as in :func:`reconstruct`).
        order: inferred from ``K`` when omitted.
        basis: basis name or object.
        channels: whether ``coefficients`` has a channel axis before ``K``.
        n_theta, n_phi: quadrature sizes for non-Helmholtz bases.

    Returns:
        ``(...)`` or ``(..., C)``; zero for ``wo`` below the horizon.

    Example:
        >>> a = torch.zeros(20, dtype=torch.float64); a[0] = 2 * 0.7  # Lambertian rho = 0.7
        >>> round(float(directional_albedo(a, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))), 12)
        0.7
    """
    check_tensor(coefficients, "coefficients", min_dims=2 if channels else 1)
    check_dirs(wo, "wo")
    check_same([("coefficients", coefficients), ("wo", wo)])
    b = _basis(basis)
    P = _order_of(b, coefficients.shape[-1], order)
    S, table = _albedo_matrix(b, P, coefficients.dtype, coefficients.device)
    if S is not None:
        T = table(wo)  # (..., M)
        cs = coefficients @ S  # (..., M) or (..., C, M)
        if channels:
            broadcast_shapes([("coefficients[..., C, K]", coefficients.shape[:-2]), ("wo", wo.shape[:-1])])
            return (cs * T.unsqueeze(-2)).sum(-1)
        broadcast_shapes([("coefficients[..., K]", coefficients.shape[:-1]), ("wo", wo.shape[:-1])])
        return (cs * T).sum(-1)
    nt = P + 2 if n_theta is None else n_theta
    npf = 2 * P + 2 if n_phi is None else n_phi
    d, w = direction_quadrature(nt, npf, "hemisphere", dtype=coefficients.dtype, device=coefficients.device)
    wo_e = wo.unsqueeze(-2)  # (..., 1, 3)
    Bv = b.evaluate(d, wo_e, P)  # (..., Q, K)
    kern = (Bv * (w * d[:, 2]).unsqueeze(-1)).sum(-2)  # (..., K)
    if channels:
        return (kern.unsqueeze(-2) * coefficients).sum(-1)
    return (kern * coefficients).sum(-1)
