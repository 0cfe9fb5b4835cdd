r"""Shared pieces of the isotropic comparison bases (Westin, Gautron, Koenderink--van Doorn).

Every isotropic basis here is a sum of products

.. math:: c_k\,T_{a_k}(\theta_i)\,T_{b_k}(\theta_o)\,A_{z_k}(\Delta\phi)

of per-direction polar tables ``T`` and an azimuthal table ``A`` of
:math:`\rho_i^q\rho_o^q\{\cos,\sin\}(q\Delta\phi)`-type columns built from the complex number
:math:`c = (x_i - i y_i)(x_o + i y_o)` (:math:`|c| = \sin\theta_i\sin\theta_o`,
:math:`\arg c = \phi_o - \phi_i`). :func:`pair_frame` does the validation, broadcasting,
normalisation and horizon mask that every ``evaluate`` starts with, and
:func:`gather_rows` the gather-multiply that every one ends with (symmetrised or not);
:class:`RowTableBasis` is that ``evaluate`` and the row bookkeeping, once.
"""
from __future__ import annotations

from abc import abstractmethod
from typing import Callable, List, Optional, Sequence, Tuple

import torch

from ..kernel import _const
from ._base import DegreeBasis
from ._products import broadcast_pair, complex_powers, unit_dirs

__all__ = ["pair_frame", "azimuth_table", "gather_rows", "product_rows", "RowTableBasis"]


def pair_frame(wi: torch.Tensor, wo: torch.Tensor, hemisphere: bool = True):
    """Validate and flatten a direction pair.

    Returns:
        ``lead, zi, zo, cr, ci, valid``: the broadcast leading shape, the cosines, the
        real and imaginary parts of ``c`` (all ``(N,)``) and the validity mask
        (non-zero vectors, and ``z >= 0`` for both when ``hemisphere``).
    """
    lead, wi, wo = broadcast_pair(wi, wo)
    xi, yi, zi, oki = unit_dirs(wi)
    xo, yo, zo, oko = unit_dirs(wo)
    valid = oki & oko
    if hemisphere:
        valid = valid & (zi >= 0) & (zo >= 0)
    return lead, zi, zo, xi * xo + yi * yo, xi * yo - yi * xo, valid


def azimuth_table(cr: torch.Tensor, ci: torch.Tensor, valid: torch.Tensor, order: int, sines: bool,
                  scale: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``[Re (s c)^q, q = 0..P] (+ [Im (s c)^q, q = 1..P] if sines)``, zero where not ``valid``."""
    if scale is not None:
        cr, ci = cr * scale, ci * scale
    RE, IM = complex_powers(cr, ci, order)
    A = torch.cat([RE, IM], -1) if sines else RE
    return A * valid.to(cr.dtype).unsqueeze(-1)


def gather_rows(Ti: torch.Tensor, To: torch.Tensor, A: torch.Tensor, ia: Sequence[int], ib: Sequence[int],
                iz: Sequence[int], coef: Sequence[float], key: tuple, symmetric: bool, lead) -> torch.Tensor:
    """``coef * (Ti[ia] To[ib] (+ Ti[ib] To[ia] if symmetric)) * A[iz]``, reshaped to ``(*lead, K)``."""
    dev, dt = Ti.device, Ti.dtype
    ta = _const(key + ("a",), list(ia), dev, None)
    tb = _const(key + ("b",), list(ib), dev, None)
    tz = _const(key + ("z",), list(iz), dev, None)
    out = Ti.index_select(-1, ta) * To.index_select(-1, tb)
    if symmetric:
        out = out.addcmul(Ti.index_select(-1, tb), To.index_select(-1, ta))
    out = out * A.index_select(-1, tz) * _const(key + ("c",), list(coef), dev, dt)
    return out.reshape(*lead, out.shape[-1])


def product_rows(order: int, admissible: Callable[[int, int, int], bool]) -> Tuple[Tuple[int, int, int, int, int], ...]:
    """Rows ``(label, a, b, q, kind)`` of an unsymmetrised isotropic product basis, nested by label.

    Every ordered pair ``(a, b) <= order`` with ``q <= min(a, b)`` and ``admissible(a, b, q)``; kind 0 =
    cosine, 1 = sine (``q >= 1``); label ``max(a, b)``; sorted by label, ``a``, ``b``, cosines first, ``q``.
    """
    rows = []
    for a in range(order + 1):
        for b in range(order + 1):
            for q in range(min(a, b) + 1):
                if not admissible(a, b, q):
                    continue
                rows.append((max(a, b), a, b, q, 0))
                if q >= 1:
                    rows.append((max(a, b), a, b, q, 1))
    rows.sort(key=lambda t: (t[0], t[1], t[2], t[4], t[3]))
    return tuple(rows)


class RowTableBasis(DegreeBasis):
    """An isotropic basis listed by a table of rows, each row a product ``c T_a(theta_i) T_b(theta_o) A_z(dphi)``.

    Subclasses give :meth:`rows` (order label first, nested by label), :meth:`tables` (the polar tables, the
    azimuthal table and the column map of the polar tables) and :meth:`gather` (the columns and factor of a
    row); ``symmetric`` adds the swapped product (reciprocal bases). ``evaluate`` validates and flattens the
    pair (no horizon mask for ``domain == "sphere"``), then gathers the rows.
    """

    isotropic = True
    symmetric = True
    _cache_key = ""

    @abstractmethod
    def rows(self, order: int) -> Tuple[tuple, ...]:
        """The basis functions' index tuples up to ``order``, order label first, nested by label."""

    @abstractmethod
    def tables(self, zi, zo, cr, ci, valid, order: int):
        """``(Ti, To, A, col)``: polar tables of both directions, azimuthal table, column map of ``Ti``/``To``."""

    @abstractmethod
    def gather(self, row: tuple, col: dict, order: int) -> Tuple[int, int, int, float]:
        """``(column of Ti, column of To, column of A, factor)`` of one row."""

    def evaluate(self, wi, wo, order):
        lead, zi, zo, cr, ci, valid = pair_frame(wi, wo, hemisphere=self.domain == "hemisphere")
        order = self.check_order(order)
        Ti, To, A, col = self.tables(zi, zo, cr, ci, valid, order)
        cols: List[Tuple[int, int, int, float]] = [self.gather(r, col, order) for r in self.rows(order)]
        ia, ib, iz, coef = (list(c) for c in zip(*cols))
        return gather_rows(Ti, To, A, ia, ib, iz, coef, (self._cache_key, order), self.symmetric, lead)

    def num_functions(self, order):
        return len(self.rows(self.check_order(order)))

    def function_orders(self, order):
        return torch.tensor([r[0] for r in self.rows(self.check_order(order))], dtype=torch.long)
