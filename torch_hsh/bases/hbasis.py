r"""H-basis of Habel & Wimmer (2010) and the BRDF bases built from it: ``hbasis`` and ``hbasis_isotropic``.

Per direction (local frame, z >= 0; zero below the horizon), orthonormal over the
hemisphere:

==== ===================================== =====
 #    function                              order
==== ===================================== =====
 H1   1/sqrt(2 pi)                          0
 H2   -sqrt(3/(2 pi)) y                     1
 H3   sqrt(3/(2 pi)) (2z - 1)               1
 H4   -sqrt(3/(2 pi)) x                     1
 H5   sqrt(15/(2 pi)) x y                   2
 H6   (1/2) sqrt(15/(2 pi)) (x^2 - y^2)     2
==== ===================================== =====

**Only the 4-function (order 1) and 6-function (order 2) versions are published**, so
``max_order = 2`` and asking for a larger order raises a ``ValueError``; the order-0
truncation is H1 alone. Nothing beyond 6 functions is defined here.

The paper (Elhabian & Farag 2015) compares against "the H-basis" for BRDFs without
saying how a BRDF basis is built from it. We choose the same construction as the
Helmholtz basis (paper Eq. 9):

* ``hbasis``: for each unordered pair ``j <= k`` of the per-direction functions,
  :math:`\frac{1}{\sqrt{2 + 2\delta_{jk}}}[H_j(\omega_i)H_k(\omega_o) + H_k(\omega_i)H_j(\omega_o)]`;
  label ``max(order_j, order_k)``; 1, 10 and 21 functions at orders 0, 1, 2;
  reciprocal, orthonormal over :math:`\Omega_i\times\Omega_o`.
* ``hbasis_isotropic``: its isotropic reduction. H2/H4 and H5/H6 are the sine/cosine
  pairs of the polar parts :math:`\sqrt{3/(4\pi)}\sin\theta` (q = 1) and
  :math:`\frac12\sqrt{15/(4\pi)}\sin^2\theta` (q = 2); H1 and H3 are the q = 0 parts.
  The isotropic functions are
  :math:`\frac{1}{\sqrt{2+2\delta_{ab}}}[\Theta_a^q(\theta_i)\Theta_b^q(\theta_o) +
  \Theta_b^q(\theta_i)\Theta_a^q(\theta_o)]\Phi_q(\Delta\phi)`: rows (order, q, a, b) =
  (0, 0, H1, H1), (1, 0, H3, H1), (1, 0, H3, H3), (1, 1, -, -), (2, 2, -, -):
  1, 4 and 5 functions at orders 0, 1, 2.

Example:
    >>> from torch_hsh.bases import get_basis
    >>> [get_basis("hbasis").num_functions(p) for p in (0, 1, 2)]
    [1, 10, 21]
"""
from __future__ import annotations

import math

import torch

from .._checks import check_order
from ._base import register_basis
from ._products import PairProductBasis, broadcast_pair, unit_dirs

__all__ = ["h_basis", "HBasis", "HBasisIsotropic"]

_LABELS = (0, 1, 1, 1, 2, 2)
_COUNTS = {0: 1, 1: 4, 2: 6}
_C1 = math.sqrt(3.0 / (2.0 * math.pi))
_C2 = math.sqrt(15.0 / (2.0 * math.pi))


def _check_h_order(order, name="order") -> int:
    if isinstance(order, int) and not isinstance(order, bool) and order > 2:
        raise ValueError(
            f"`{name}`={order}: the H-basis of Habel & Wimmer (2010) is published with 4 functions "
            "(order 1) and 6 functions (order 2) only; orders above 2 are not defined"
        )
    return check_order(order, name, max_order=2)


def _h_flat(d: torch.Tensor, order: int) -> torch.Tensor:
    x, y, z, ok = unit_dirs(d)
    mask = (ok & (z >= 0)).to(z.dtype)
    cols = [torch.full_like(z, 1.0 / math.sqrt(2.0 * math.pi))]
    if order >= 1:
        cols += [-_C1 * y, _C1 * (2.0 * z - 1.0), -_C1 * x]
    if order >= 2:
        cols += [_C2 * x * y, 0.5 * _C2 * (x * x - y * y)]
    return torch.stack(cols, dim=-1) * mask.unsqueeze(-1)


def h_basis(dirs: torch.Tensor, order: int = 2) -> torch.Tensor:
    """Per-direction H-basis functions H1..H6 (Habel & Wimmer 2010).

    Args:
        dirs: ``(..., 3)`` directions in the local frame (normalised here); ``z < 0``
            and zero vectors give 0.
        order: 0 (H1), 1 (H1..H4) or 2 (H1..H6). Larger orders raise ``ValueError``.

    Returns:
        ``(..., 1 | 4 | 6)`` tensor, orthonormal over the hemisphere.

    Example:
        >>> import torch
        >>> h_basis(torch.tensor([0.0, 0.0, 1.0]), 1).shape
        torch.Size([4])
    """
    from .._checks import check_dirs

    check_dirs(dirs, "dirs")
    order = _check_h_order(order)
    lead = dirs.shape[:-1]
    return _h_flat(dirs.reshape(-1, 3), order).reshape(*lead, _COUNTS[order])


class HBasis(PairProductBasis):
    """Symmetrised product of the H-basis, ``hbasis`` (orders 0..2 only).

    ``evaluate(wi, wo, P)``: ``(..., 3), (..., 3) -> (..., K)``, K = 1, 10, 21; columns
    sorted by label (nested).

    Example (the H-basis stops at order 2; its 1, 10, 21 functions are nested):
        >>> from torch_hsh.bases import get_basis
        >>> b = get_basis("hbasis")
        >>> b.max_order, [b.num_functions(p) for p in range(3)]
        (2, [1, 10, 21])
    """

    name = "hbasis"
    reciprocal = True
    domain = "hemisphere"
    max_order = 2
    _cache_key = "hb"

    def check_order(self, order) -> int:
        try:
            return _check_h_order(order)
        except ValueError as e:
            raise ValueError(f"basis '{self.name}': {e}") from None

    def labels(self, order):
        return _LABELS[: _COUNTS[order]]

    def per_direction(self, d, order):
        return _h_flat(d, order)

    def num_functions(self, order):
        k = _COUNTS[self.check_order(order)]
        return k * (k + 1) // 2


# rows (label, q, kind) of the isotropic reduction; kind: "00" H1H1, "31" H3H1, "33" H3H3, "q" for q>0
_ISO_ROWS = ((0, 0, "00"), (1, 0, "31"), (1, 0, "33"), (1, 1, "q"), (2, 2, "q"))
_ISO_COUNTS = {0: 1, 1: 4, 2: 5}


class HBasisIsotropic(HBasis):
    """Isotropic reduction of ``hbasis``, ``hbasis_isotropic`` (orders 0..2 only; 1, 4, 5 functions).

    Example:
        >>> from torch_hsh.bases import get_basis
        >>> get_basis("hbasis_isotropic").num_functions(2)
        5
    """

    name = "hbasis_isotropic"
    isotropic = True

    def evaluate(self, wi, wo, order):
        lead, wi, wo = broadcast_pair(wi, wo)
        order = self.check_order(order)
        xi, yi, zi, oki = unit_dirs(wi)
        xo, yo, zo, oko = unit_dirs(wo)
        mask = (oki & oko & (zi >= 0) & (zo >= 0)).to(zi.dtype)
        t0 = 1.0 / math.sqrt(2.0 * math.pi)
        ai, ao = _C1 * (2.0 * zi - 1.0), _C1 * (2.0 * zo - 1.0)
        cols = [torch.full_like(zi, t0 * t0)]
        if order >= 1:
            a = xi * xo + yi * yo  # sin_i sin_o cos(dphi)
            cols += [
                (ai * t0 + ao * t0) / math.sqrt(2.0),
                ai * ao,
                math.sqrt(2.0) * (3.0 / (4.0 * math.pi)) * a,
            ]
        if order >= 2:
            b = xi * yo - yi * xo  # sin_i sin_o sin(dphi)
            cols.append(math.sqrt(2.0) * (15.0 / (16.0 * math.pi)) * (a * a - b * b))
        out = torch.stack(cols, dim=-1) * mask.unsqueeze(-1)
        return out.reshape(*lead, out.shape[-1])

    def num_functions(self, order):
        return _ISO_COUNTS[self.check_order(order)]

    def function_orders(self, order):
        order = self.check_order(order)
        return torch.tensor([r[0] for r in _ISO_ROWS[: _ISO_COUNTS[order]]], dtype=torch.long)


register_basis(HBasis())
register_basis(HBasisIsotropic())
