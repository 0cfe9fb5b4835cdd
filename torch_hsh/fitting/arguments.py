"""Arguments shared by the fitting functions: basis lookup, order inference, quadrature sizes, BRDF calls."""
from __future__ import annotations

import math
from typing import Tuple, Union

import torch

from .._checks import check_shape, validation_enabled
from ..bases import Basis, get_basis

__all__ = ["BasisLike", "infer_order", "default_quadrature_sizes"]

BasisLike = Union[str, Basis]
_DEFAULT = "helmholtz_isotropic"
_TWO_PI = 2.0 * math.pi


def _basis(basis) -> Basis:
    return get_basis(basis)


def infer_order(basis: BasisLike, num_functions: int) -> int:
    """The order ``P`` with ``basis.num_functions(P) == num_functions``.

    Raises ``ValueError`` listing the nearest valid counts when none matches.

    Example:
        >>> infer_order("helmholtz_isotropic", 20)
        3
    """
    b = _basis(basis)
    k = int(num_functions)
    mx = b.max_order if b.max_order is not None else 40
    counts = []
    for p in range(mx + 1):
        c = b.num_functions(p)
        counts.append(c)
        if c == k:
            return p
        if c > k:
            break
    raise ValueError(
        f"the last dimension of `coefficients` ({k}) matches no order of basis '{b.name}'; "
        f"valid sizes start {counts[:8]}{' ...' if len(counts) > 8 else ''}"
    )


def _order_of(b: Basis, K: int, order) -> int:
    if order is None:
        return infer_order(b, K)
    P = b.check_order(order)
    if b.num_functions(P) != K:
        raise ValueError(
            f"`coefficients` has {K} functions in its last dimension but basis '{b.name}' has "
            f"{b.num_functions(P)} functions up to order {P}"
        )
    return P


def default_quadrature_sizes(order: int) -> Tuple[int, int]:
    """Default ``(n_theta, n_phi) = (2 (P + 1), 2 (2P + 1))`` for order ``P``.

    Exact for projecting any function band-limited to order ``<= 3P + 1`` onto the
    basis up to order ``P`` (see the module docstring).

    Example:
        >>> default_quadrature_sizes(3)
        (8, 14)
    """
    P = int(order)
    return 2 * (P + 1), 2 * (2 * P + 1)


def _check_callable(brdf, name="brdf"):
    if not callable(brdf):
        raise TypeError(f"`{name}` must be callable as {name}(wi, wo) -> (M,) or (M, C), got {type(brdf).__name__}")


def _check_dtype(dtype):
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"`dtype` must be torch.float32 or torch.float64, got {dtype!r}")


def _call_brdf(brdf, wi, wo, name="brdf"):
    v = brdf(wi, wo)
    if not isinstance(v, torch.Tensor):
        raise TypeError(f"`{name}` must return a torch.Tensor, got {type(v).__name__}")
    # called with (M, 3) directions, it must return (M,) or (M, C)
    check_shape(v, f"{name}(wi, wo)", ("M",), ("M", "C"), sizes={"M": wi.shape[0]})
    if not v.is_floating_point():
        v = v.to(wi.dtype)
    if validation_enabled() and not bool(torch.isfinite(v).all()):
        raise ValueError(
            f"`{name}` returned NaN/Inf values (it is evaluated at interior quadrature nodes, z > 0); "
            "make it finite there"
        )
    return v.to(wi.dtype)


def _chunk(chunk_size, K) -> int:
    if chunk_size is None:
        return max(256, (1 << 22) // max(K, 1))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}")
    return chunk_size


def _sizes(P, n_theta, n_phi):
    dt, dp = default_quadrature_sizes(P)
    nt = dt if n_theta is None else n_theta
    npf = dp if n_phi is None else n_phi
    for nm, v in (("n_theta", nt), ("n_phi", npf)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"`{nm}` must be a positive integer, got {v!r}")
    return nt, npf
