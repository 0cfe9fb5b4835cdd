"""Shared pieces of the product bases (Westin, Gautron, H-basis) and of the isotropic ones built on them.

Direction normalisation (:func:`unit_dirs`), validation and broadcasting of a direction pair
(:func:`broadcast_pair`), the pair tables of the (symmetrised) product bases (:func:`pair_table`,
:func:`product_basis`) and the complex powers of the azimuthal factors (:func:`complex_powers`).
"""
from __future__ import annotations

import math
from functools import lru_cache
from abc import abstractmethod
from typing import Sequence, Tuple

import torch

from .._checks import broadcast_shapes, check_dirs, check_same
from ..kernel import _const
from ._base import DegreeBasis

__all__ = ["MAX_PRODUCT_ORDER", "unit_dirs", "broadcast_pair", "pair_table", "product_basis", "complex_powers",
           "PairProductBasis"]

#: Largest order of the anisotropic product bases (number of columns grows as P**4).
MAX_PRODUCT_ORDER = 16


def unit_dirs(d: torch.Tensor):
    """Normalise flat ``(N, 3)`` directions.

    Returns ``x, y, z, nonzero`` where ``nonzero`` flags vectors of non-zero
    length (zero vectors stay zero and give finite gradients).
    """
    n2 = (d * d).sum(-1)
    ok = n2 > torch.finfo(d.dtype).tiny * 1e6
    inv = torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
    u = d * inv.unsqueeze(-1)
    x, y, z = u.unbind(-1)
    return x, y, z, ok


def broadcast_pair(wi: torch.Tensor, wo: torch.Tensor):
    """Validate and broadcast two direction tensors; returns ``lead, wi (N,3), wo (N,3)``."""
    check_dirs(wi, "wi")
    check_dirs(wo, "wo")
    check_same([("wi", wi), ("wo", wo)])
    lead = broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1])])
    return lead, wi.expand(*lead, 3).reshape(-1, 3), wo.expand(*lead, 3).reshape(-1, 3)


@lru_cache(maxsize=None)
def pair_table(labels: Tuple[int, ...], order: int, symmetric: bool):
    """Pairs of per-direction functions forming a product BRDF basis, sorted by label.

    Args:
        labels: order label of every per-direction function (flat index -> label).
        order: truncation order; only functions with label <= order are used.
        symmetric: True for unordered pairs ``j <= k`` (Eq. 9 symmetrisation,
            coefficient ``1/sqrt(2 + 2 delta_jk)``), False for all ordered pairs
            (plain products, coefficient 1).

    Returns:
        ``(j, k, coef, pair_labels)`` tuples of equal length, sorted by
        ``(max(label_j, label_k), j, k)`` so that truncation is a prefix.
    """
    idx = [i for i, lab in enumerate(labels) if lab <= order]
    rows = []
    for j in idx:
        for k in idx:
            if symmetric and k < j:
                continue
            lab = max(labels[j], labels[k])
            c = (0.5 if j == k else 1.0 / math.sqrt(2.0)) if symmetric else 1.0
            rows.append((lab, j, k, c))
    rows.sort(key=lambda r: (r[0], r[1], r[2]))
    return (
        tuple(r[1] for r in rows),
        tuple(r[2] for r in rows),
        tuple(r[3] for r in rows),
        tuple(r[0] for r in rows),
    )


def product_basis(Fi: torch.Tensor, Fo: torch.Tensor, labels: Sequence[int], order: int, symmetric: bool, key: str):
    """Evaluate a (symmetrised) product basis from per-direction tables ``Fi, Fo`` of shape ``(N, L)``."""
    j, k, c, _ = pair_table(tuple(labels), order, symmetric)
    dev, dt = Fi.device, Fi.dtype
    jt = _const((key + "_j", order, symmetric), j, dev, None)
    kt = _const((key + "_k", order, symmetric), k, dev, None)
    out = Fi.index_select(-1, jt) * Fo.index_select(-1, kt)
    if symmetric:
        out = out.addcmul(Fi.index_select(-1, kt), Fo.index_select(-1, jt))
        out = out * _const((key + "_c", order), c, dev, dt)
    return out


def complex_powers(cr: torch.Tensor, ci: torch.Tensor, order: int):
    """``[Re c^q for q = 0..P]`` and ``[Im c^q for q = 1..P]`` as ``(N, P+1)``, ``(N, P)``."""
    re = [torch.ones_like(cr)]
    im = []
    pr, pi = torch.ones_like(cr), torch.zeros_like(cr)
    for _ in range(order):
        pr, pi = pr * cr - pi * ci, pr * ci + pi * cr
        re.append(pr)
        im.append(pi)
    RE = torch.stack(re, dim=-1)
    IM = torch.stack(im, dim=-1) if im else cr.new_zeros(cr.shape + (0,))
    return RE, IM


class PairProductBasis(DegreeBasis):
    """A basis of products of per-direction functions, all pairs (``symmetric``: unordered, Eq. 9) up to the order.

    Subclasses give :meth:`labels` (order label of each per-direction function) and :meth:`per_direction`
    (their ``(N, L)`` table); columns are sorted by label as :func:`pair_table`.
    """

    isotropic = False
    symmetric = True
    _cache_key = ""

    @abstractmethod
    def labels(self, order: int) -> Tuple[int, ...]:
        """The order label of each per-direction function up to ``order``."""

    @abstractmethod
    def per_direction(self, d: torch.Tensor, order: int) -> torch.Tensor:
        """``(N, 3) -> (N, L)``: the per-direction functions of unit directions ``d``."""

    def evaluate(self, wi, wo, order):
        lead, wi, wo = broadcast_pair(wi, wo)
        order = self.check_order(order)
        Fi, Fo = self.per_direction(wi, order), self.per_direction(wo, order)
        out = product_basis(Fi, Fo, self.labels(order), order, self.symmetric, self._cache_key)
        return out.reshape(*lead, out.shape[-1])

    def function_orders(self, order):
        order = self.check_order(order)
        return torch.tensor(pair_table(tuple(self.labels(order)), order, self.symmetric)[3], dtype=torch.long)
