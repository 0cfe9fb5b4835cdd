r"""Operations on coefficient vectors: reconstruction, truncation, energy accuracy Acc(P)."""
from __future__ import annotations

from typing import Optional, Union

import torch

from .._checks import broadcast_shapes, check_dirs, check_same, check_tensor, validation_enabled
from .arguments import _DEFAULT, BasisLike, _basis, _order_of

__all__ = ["reconstruct", "truncate", "energy_accuracy", "ENERGY_EXCESS_TOLERANCE"]


def reconstruct(
    coefficients: torch.Tensor,
    wi: torch.Tensor,
    wo: torch.Tensor,
    order: Optional[int] = None,
    basis: BasisLike = _DEFAULT,
    channels: bool = False,
) -> torch.Tensor:
    r"""Evaluate :math:`f(\omega_i, \omega_o) = \sum_k a_k B_k(\omega_i, \omega_o)`.

    Broadcasting is element-wise over leading dimensions:

    * ``channels=False``: ``coefficients`` ``(..., K)`` -> result ``(...)``, where the
      leading shapes of ``coefficients``, ``wi`` ``(..., 3)`` and ``wo`` ``(..., 3)``
      broadcast together. One BRDF at ``N`` points: ``(K,)`` with ``(N, 3)`` ->
      ``(N,)``; ``B`` BRDFs from a batched fit, ``(B, K)``, at per-BRDF points
      ``(B, N, 3)``: pass ``coefficients[:, None]``.
    * ``channels=True``: ``coefficients`` ``(..., C, K)`` -> ``(..., C)``; e.g. ``(C, K)``
      from :func:`project`/:func:`fit` with ``(N, 3)`` directions -> ``(N, C)``.

    Args:
        coefficients: coefficients in the column order of ``basis.evaluate``.
        wi, wo: local directions ``(..., 3)``.
        order: basis order; inferred from ``K`` when omitted (``ValueError`` when
            ``K`` matches no order).
        basis: basis name or object.
        channels: whether the second-to-last dimension of ``coefficients`` is a channel axis.

    Returns:
        Values in the dtype of ``coefficients``; differentiable with respect to
        ``coefficients`` and the directions.

    Example:
        >>> import math
        >>> a = torch.zeros(20, dtype=torch.float64); a[0] = 2 * 0.5  # Lambertian rho = 0.5
        >>> w = torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64)
        >>> round(float(reconstruct(a, w, w)[0] * math.pi), 12)
        0.5
    """
    check_tensor(coefficients, "coefficients", min_dims=2 if channels else 1)
    check_dirs(wi, "wi")
    check_dirs(wo, "wo")
    check_same([("coefficients", coefficients), ("wi", wi), ("wo", wo)])
    b = _basis(basis)
    P = _order_of(b, coefficients.shape[-1], order)
    B = b.evaluate(wi, wo, P)  # (..., K)
    if channels:
        broadcast_shapes([("coefficients[..., C, K]", coefficients.shape[:-2]), ("wi/wo", B.shape[:-1])])
        return (B.unsqueeze(-2) * coefficients).sum(-1)
    broadcast_shapes([("coefficients[..., K]", coefficients.shape[:-1]), ("wi/wo", B.shape[:-1])])
    return (B * coefficients).sum(-1)



def truncate(
    coefficients: torch.Tensor,
    order: int,
    basis: BasisLike = _DEFAULT,
    source_order: Optional[int] = None,
    zero_fill: bool = False,
) -> torch.Tensor:
    """Keep the functions up to ``order`` (those with ``basis.function_orders <= order``).

    Args:
        coefficients: ``(..., K)`` coefficients of order ``source_order`` (inferred from ``K``).
        order: target order ``P <= source_order``.
        basis: basis name or object.
        zero_fill: keep the shape ``(..., K)`` and zero the dropped functions
            instead of removing them.

    Returns:
        ``(..., K_P)`` in the column order of ``basis.evaluate(..., P)`` (the
        selected columns keep their relative order, which is how every
        registered basis lays out its lower orders), or ``(..., K)`` with
        ``zero_fill``.

    Example:
        >>> truncate(torch.arange(20.0), 1).tolist()
        [0.0, 1.0, 2.0, 3.0]
    """
    check_tensor(coefficients, "coefficients", min_dims=1)
    b = _basis(basis)
    Ps = _order_of(b, coefficients.shape[-1], source_order)
    P = b.check_order(order)
    if P > Ps:
        raise ValueError(f"`order` ({P}) must be <= the order of `coefficients` ({Ps})")
    keep = b.function_orders(Ps).to(coefficients.device) <= P
    if zero_fill:
        return coefficients * keep.to(coefficients.dtype)
    return coefficients[..., keep]


#: Relative excess of sum(a_k^2) over ``total_energy`` that :func:`energy_accuracy` tolerates
#: (quadrature / rounding error of the two estimates); beyond it the energy is wrong.
ENERGY_EXCESS_TOLERANCE = 1e-2


def energy_accuracy(
    coefficients: torch.Tensor,
    total_energy: Union[torch.Tensor, float],
    basis: BasisLike = _DEFAULT,
    order: Optional[int] = None,
) -> torch.Tensor:
    r"""Acc(P') for every truncation order ``P' = 0..P`` (paper Eq. 17).

    .. math:: \mathrm{Acc}(P') = \frac{\sum_{k:\,L_k \le P'} a_k^2}{\iint f^2}

    with :math:`L_k` = ``basis.function_orders``.

    Args:
        coefficients: ``(..., K)`` coefficients of order ``P`` (inferred from ``K``).
        total_energy: :math:`\iint f^2` (e.g. :func:`brdf_energy`), a positive
            number or a tensor broadcasting with ``coefficients.shape[:-1]``.
        basis: basis name or object.
        order: order of ``coefficients`` (checked against ``K``).

    Returns:
        ``(..., P + 1)``, non-decreasing in the last dimension; equals 1 at
        ``P`` for a function band-limited to ``P`` (Parseval).

    Raises:
        ValueError: ``total_energy <= 0``, or smaller than the energy the
            coefficients hold (``Acc(P) > 1 + ENERGY_EXCESS_TOLERANCE``):
            by Bessel's inequality that energy is not the function's.

    Example:
        >>> a = torch.zeros(4, dtype=torch.float64); a[0], a[2] = 3.0, 4.0
        >>> energy_accuracy(a, 25.0).tolist()
        [0.36, 1.0]
    """
    check_tensor(coefficients, "coefficients", min_dims=1)
    b = _basis(basis)
    P = _order_of(b, coefficients.shape[-1], order)
    if not isinstance(total_energy, torch.Tensor):
        if isinstance(total_energy, bool) or not isinstance(total_energy, (int, float)):
            raise TypeError(f"`total_energy` must be a number or a tensor, got {type(total_energy).__name__}")
        total_energy = torch.tensor(float(total_energy), dtype=coefficients.dtype, device=coefficients.device)
    check_tensor(total_energy, "total_energy")
    if validation_enabled() and bool((total_energy <= 0).any()):
        raise ValueError("`total_energy` must be > 0")
    broadcast_shapes([("coefficients[..., K]", coefficients.shape[:-1]), ("total_energy", total_energy.shape)])
    labels = b.function_orders(P).to(coefficients.device)
    onehot = (labels[:, None] == torch.arange(P + 1, device=coefficients.device)[None, :]).to(coefficients.dtype)
    # onehot: (K, P+1)
    per_order = (coefficients * coefficients) @ onehot
    acc = torch.cumsum(per_order, dim=-1) / total_energy.to(coefficients.dtype).unsqueeze(-1)
    if validation_enabled() and bool((acc[..., -1] > 1.0 + ENERGY_EXCESS_TOLERANCE).any()):
        worst = float(acc[..., -1].max())
        raise ValueError(
            f"`total_energy` is below the energy the coefficients hold (Acc(P) = {worst:.6g} > 1): pass the "
            "full energy of the function (e.g. brdf_energy), not a truncated or mismatched one"
        )
    return acc
