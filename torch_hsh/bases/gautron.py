r"""Unsymmetrised HSH product bases of Gautron et al. (2004): ``gautron_hsh`` and ``gautron_hsh_isotropic``.

* ``gautron_hsh``: :math:`H_p^q(\omega_i) H_r^s(\omega_o)` for **every ordered** pair of
  flat HSH indices ``(j, k)``: :math:`(P+1)^4` functions, orthonormal over
  :math:`\Omega_i\times\Omega_o` but **not reciprocal** (``B_{jk}(wi, wo) = B_{kj}(wo, wi)``,
  a different column). Label ``max(p, r)``; columns sorted by label, then ``j``, then
  ``k`` (nested).
* ``gautron_hsh_isotropic``: the isotropic subspace of ``gautron_hsh``. Averaging
  :math:`H_p^q(\omega_i)H_r^s(\omega_o)` over a common rotation about the normal keeps
  only :math:`|q| = |s|`, and the surviving combinations are

  .. math::
      C_{pr}^q = \Theta_p^q(\theta_i)\Theta_r^q(\theta_o)\,\Phi_q(\Delta\phi)\quad (q \ge 0),\qquad
      S_{pr}^q = \Theta_p^q(\theta_i)\Theta_r^q(\theta_o)\,\sqrt2\sin(q\,\Delta\phi)\quad (q \ge 1),

  for all ordered ``p, r >= q`` (``Delta phi = phi_o - phi_i``). ``C`` is
  :math:`(B^{qq} + B^{-q,-q})/\sqrt2` and ``S`` is :math:`(B^{q,-q} - B^{-q,q})/\sqrt2`
  up to the sign convention of :math:`\Phi_{-q}`. The sine terms are needed for
  completeness on the isotropic subspace (isotropic functions that are odd in
  :math:`\Delta\phi`); a BRDF with bilateral symmetry (even in
  :math:`\Delta\phi`, every isotropic analytic model here) has zero coefficients on
  them, so they never change Acc(P) for such BRDFs. Count up to P:
  :math:`\sum_{q=0}^P (P+1-q)^2 + \sum_{q=1}^P (P+1-q)^2`. Columns sorted by
  label ``max(p, r)``, then ``p, r``, then cosine terms by ``q`` before sine terms.

Example:
    >>> from torch_hsh.bases import get_basis
    >>> get_basis("gautron_hsh").num_functions(2), get_basis("gautron_hsh_isotropic").num_functions(1)
    (81, 6)
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from ..kernel import _hsh_flat, _polar_consts, _polar_table, _safe_s
from ._base import register_basis
from ._isotropic import RowTableBasis, azimuth_table, product_rows
from ._products import MAX_PRODUCT_ORDER, PairProductBasis

__all__ = ["GautronHSH", "GautronHSHIsotropic"]


@lru_cache(maxsize=None)
def _hsh_labels(order: int):
    return tuple(int(math.isqrt(k)) for k in range((order + 1) ** 2))


class GautronHSH(PairProductBasis):
    """Plain products of HSH, ``gautron_hsh`` (not reciprocal).

    ``evaluate(wi, wo, P)``: ``(..., 3), (..., 3) -> (..., (P+1)**4)``; zero where a
    direction is below the horizon or zero.

    Example (swapping the two directions changes the values: not reciprocal):
        >>> import torch
        >>> from torch_hsh.bases import get_basis
        >>> b, wi, wo = get_basis("gautron_hsh"), torch.tensor([[0.0, 0.6, 0.8]]), torch.tensor([[0.6, 0.0, 0.8]])
        >>> b.evaluate(wi, wo, 1).shape, torch.allclose(b.evaluate(wi, wo, 1), b.evaluate(wo, wi, 1))
        (torch.Size([1, 16]), False)
    """

    name = "gautron_hsh"
    reciprocal = False
    symmetric = False
    domain = "hemisphere"
    max_order = MAX_PRODUCT_ORDER
    _cache_key = "gau"

    def labels(self, order):
        return _hsh_labels(order)

    def per_direction(self, d, order):
        return _hsh_flat(d, order)

    def num_functions(self, order):
        return (self.check_order(order) + 1) ** 4


@lru_cache(maxsize=None)
def _gautron_iso_rows(order: int):
    """Rows ``(label, p, r, q, kind)``, kind 0 = cosine, 1 = sine; sorted (nested by label)."""
    return product_rows(order, lambda p, r, q: True)


def gautron_isotropic_indices(order: int) -> torch.Tensor:
    """LongTensor ``(K, 4)`` of rows ``(p, r, q, kind)`` of ``gautron_hsh_isotropic`` (kind 0 = cos, 1 = sin).

    Example:
        >>> gautron_isotropic_indices(1).tolist()
        [[0, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0], [1, 1, 0, 0], [1, 1, 1, 0], [1, 1, 1, 1]]
    """
    from .._checks import check_order

    order = check_order(order, max_order=40)
    return torch.tensor([r[1:] for r in _gautron_iso_rows(order)], dtype=torch.long).reshape(-1, 4)


class GautronHSHIsotropic(RowTableBasis):
    """Isotropic subspace of the HSH product basis, ``gautron_hsh_isotropic`` (not reciprocal).

    ``evaluate(wi, wo, P)``: ``(..., 3), (..., 3) -> (..., K)`` with rows as
    :func:`gautron_isotropic_indices`.

    Example:
        >>> from torch_hsh.bases import get_basis
        >>> get_basis("gautron_hsh_isotropic").num_functions(2)
        19
    """

    name = "gautron_hsh_isotropic"
    reciprocal = False
    symmetric = False
    domain = "hemisphere"
    max_order = 40
    _cache_key = "gi"

    def rows(self, order):
        return _gautron_iso_rows(order)

    def tables(self, zi, zo, cr, ci, valid, order):
        zi_c, zo_c = zi.clamp(min=0.0), zo.clamp(min=0.0)
        Ti, To = _polar_table(zi_c, order), _polar_table(zo_c, order)
        # (s_i s_o)^q c^q: magnitude (sin_i sin_o)^q, phase q dphi (the polar tables carry 1/(s^q))
        AZ = azimuth_table(cr, ci, valid, order, True, _safe_s(zi_c) * _safe_s(zo_c))
        return Ti, To, AZ, _polar_consts(order)[3]

    def gather(self, row, col, order):
        _, p, r, q, kd = row
        return col[(p, q)], col[(r, q)], q if kd == 0 else order + q, 1.0 if q == 0 else math.sqrt(2.0)


register_basis(GautronHSH())
register_basis(GautronHSHIsotropic())
