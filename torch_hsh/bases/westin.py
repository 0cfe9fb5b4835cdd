r"""Spherical-harmonic BRDF bases of Westin et al. (1992): ``westin_sh`` and ``westin_sh_isotropic``.

Real spherical harmonics on the **full** sphere (no Condon–Shortley phase, the same
azimuthal convention as the HSH of :func:`torch_hsh.hsh`):

.. math::
    Y_l^m(\omega) = N_l^{|m|} P_l^{|m|}(\cos\theta)\,\Phi_m(\phi),\qquad
    N_l^m = \sqrt{\frac{2l+1}{4\pi}\frac{(l-m)!}{(l+m)!}},

with :math:`\Phi_m = \sqrt2\cos(m\phi)` (m > 0), 1 (m = 0),
:math:`(-1)^m\sqrt2\sin(|m|\phi)` (m < 0), flat index ``l*l + l + m``. They are
orthonormal over the sphere. Evaluation is trigonometry-free:
:math:`P_l^m(z) = (1 - z^2)^{m/2} Q_l^m(z)` with a polynomial :math:`Q_l^m` from the
stable normalised three-term recurrence, and
:math:`(1-z^2)^{m/2}\{\cos,\sin\}(m\phi) = \{\mathrm{Re},\mathrm{Im}\}(x + iy)^m`.

BRDF bases (domain ``"sphere"``: orthonormal over :math:`S^2\times S^2`; a BRDF is
extended by zero below the horizon when it is projected):

* ``westin_sh``: one function per unordered pair ``j <= k`` of flat SH indices,
  :math:`\frac{1}{\sqrt{2+2\delta_{jk}}}[Y_j(\omega_i)Y_k(\omega_o) + Y_k(\omega_i)Y_j(\omega_o)]`
  (the symmetrisation of paper Eq. 9), label ``max(l_j, l_k)``. Columns are sorted by
  label, then ``j``, then ``k``, so the basis is nested: the first
  ``num_functions(P)`` columns are the basis up to order P.
* ``westin_sh_isotropic``: indices ``p >= r >= q >= 0``,
  :math:`\frac{1}{\sqrt{2+2\delta_{pr}}}[\Theta_p^q(\theta_i)\Theta_r^q(\theta_o) +
  \Theta_r^q(\theta_i)\Theta_p^q(\theta_o)]\Phi_q(\phi_o-\phi_i)` with
  :math:`\Theta_l^q = N_l^q P_l^q(\cos\theta)`; for q > 0 this equals
  :math:`(B^{qq} + B^{-q,-q})/\sqrt2` of ``westin_sh``. Same column order and count
  as ``helmholtz_isotropic`` ((P+1)(P+2)(P+3)/6).

Example:
    >>> import torch
    >>> from torch_hsh.bases import get_basis
    >>> b = get_basis("westin_sh")
    >>> w = torch.tensor([[0.0, 0.6, 0.8]])
    >>> b.evaluate(w, -w, 1).shape
    torch.Size([1, 10])
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import List

import torch

from .._checks import check_dirs, check_order
from ..kernel import _const
from ._base import register_basis
from ._isotropic import RowTableBasis, azimuth_table
from ._products import (  # noqa: F401  (MAX_PRODUCT_ORDER, broadcast_pair, product_basis: importable from here)
    MAX_PRODUCT_ORDER,
    PairProductBasis,
    broadcast_pair,
    complex_powers,
    pair_table,
    product_basis,
    unit_dirs,
)

__all__ = ["real_sh", "WestinSH", "WestinSHIsotropic", "pair_table", "unit_dirs"]


# --------------------------------------------------------------------------
# real spherical harmonics
# --------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _sh_consts(order: int):
    """Recurrence constants of the normalised polynomial Q_l^m, column per (l, m), l-major blocks by m."""
    P = order
    col = {}
    c = 0
    for m in range(P + 1):
        for l in range(m, P + 1):
            col[(l, m)] = c
            c += 1
    diag = []
    for m in range(P + 1):
        # sqrt((2m+1)/(4 pi) / (2m)!) * (2m-1)!!,  (2m-1)!! = (2m)! / (2^m m!)
        lg = 0.5 * math.log((2 * m + 1) / (4 * math.pi)) + 0.5 * math.lgamma(2 * m + 1) - m * math.log(2.0) - math.lgamma(m + 1)
        diag.append(math.exp(lg))
    return col, diag


def _sh_polar(z: torch.Tensor, order: int) -> torch.Tensor:
    """Table ``(N, (P+1)(P+2)/2)`` of the normalised polynomials Q_l^m(z) (column map of ``_sh_consts``)."""
    col, diag = _sh_consts(order)
    cols: List[torch.Tensor] = [None] * len(col)  # type: ignore[list-item]
    for m in range(order + 1):
        q_mm = torch.full_like(z, diag[m])
        cols[col[(m, m)]] = q_mm
        if m + 1 <= order:
            q_prev2, q_prev = q_mm, math.sqrt(2 * m + 3) * z * q_mm
            cols[col[(m + 1, m)]] = q_prev
            for l in range(m + 2, order + 1):
                a = math.sqrt((4 * l * l - 1) / (l * l - m * m))
                b = math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))
                q = a * (z * q_prev - b * q_prev2)
                cols[col[(l, m)]] = q
                q_prev2, q_prev = q_prev, q
    return torch.stack(cols, dim=-1)


@lru_cache(maxsize=None)
def _sh_gather(order: int):
    col, _ = _sh_consts(order)
    P = order
    pidx, aidx = [], []
    for l in range(P + 1):
        for m in range(-l, l + 1):
            pidx.append(col[(l, abs(m))])
            aidx.append(m if m >= 0 else P - m)  # Re c^0..c^P then Im c^1..c^P
    scale = [1.0] + [math.sqrt(2.0)] * P + [(-1.0) ** m * math.sqrt(2.0) for m in range(1, P + 1)]
    labels = tuple(int(math.isqrt(k)) for k in range((P + 1) ** 2))
    return pidx, aidx, scale, labels


def _sh_flat(d: torch.Tensor, order: int, hemisphere: bool = False) -> torch.Tensor:
    x, y, z, ok = unit_dirs(d)
    mask = ok & (z >= 0) if hemisphere else ok
    Q = _sh_polar(z, order)
    RE, IM = complex_powers(x, y, order)
    A = torch.cat([RE, IM], dim=-1) * mask.to(z.dtype).unsqueeze(-1)
    pidx, aidx, scale, _ = _sh_gather(order)
    dev = d.device
    A = A * _const(("sh_sc", order), scale, dev, d.dtype)
    return Q.index_select(-1, _const(("sh_p", order), pidx, dev, None)) * A.index_select(
        -1, _const(("sh_a", order), aidx, dev, None)
    )


def real_sh(dirs: torch.Tensor, order: int) -> torch.Tensor:
    r"""Real spherical harmonics on the full sphere up to ``order``.

    Args:
        dirs: ``(..., 3)`` directions (normalised here); zero vectors give 0.
            Directions below the horizon are **not** masked (full-sphere basis).
        order: maximum order ``L >= 0`` (at most 40).

    Returns:
        ``(..., (L+1)**2)`` tensor, entry ``l*l + l + m`` is :math:`Y_l^m` (no
        Condon–Shortley phase, azimuthal convention of the HSH). Differentiable,
        same dtype/device as ``dirs``. Orthonormal over the sphere.

    Example:
        >>> import torch
        >>> from torch_hsh.bases.westin import real_sh
        >>> y = real_sh(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 1)
        >>> [round(abs(float(v)), 6) for v in y]  # Y_0^0, Y_1^-1, Y_1^0, Y_1^1 at the pole
        [0.282095, 0.0, 0.488603, 0.0]
    """
    check_dirs(dirs, "dirs")
    order = check_order(order)
    lead = dirs.shape[:-1]
    return _sh_flat(dirs.reshape(-1, 3), order).reshape(*lead, (order + 1) ** 2)


# --------------------------------------------------------------------------
# bases
# --------------------------------------------------------------------------
class WestinSH(PairProductBasis):
    """Symmetrised product of full-sphere real SH (Westin et al. 1992), ``westin_sh``.

    ``evaluate(wi, wo, P)``: ``(..., 3), (..., 3) -> (..., K(K+1)/2)``, ``K = (P+1)**2``,
    columns sorted by label ``max(l_j, l_k)`` (nested). Domain ``"sphere"``:
    directions below the horizon are evaluated, not zeroed.

    Example:
        >>> from torch_hsh.bases import get_basis
        >>> get_basis("westin_sh").num_functions(2)
        45
    """

    name = "westin_sh"
    reciprocal = True
    domain = "sphere"
    max_order = MAX_PRODUCT_ORDER
    _cache_key = "westin"

    def labels(self, order):
        return _sh_gather(order)[3]

    def per_direction(self, d, order):
        return _sh_flat(d, order)

    def num_functions(self, order):
        k = (self.check_order(order) + 1) ** 2
        return k * (k + 1) // 2


@lru_cache(maxsize=None)
def iso_table(order: int):
    """Rows ``(p, r, q)``, ``p >= r >= q >= 0``, p-major (the order of :func:`torch_hsh.isotropic_indices`)."""
    return tuple((p, r, q) for p in range(order + 1) for r in range(p + 1) for q in range(r + 1))


class WestinSHIsotropic(RowTableBasis):
    """Isotropic reduction of ``westin_sh`` (full-sphere Legendre polar parts), ``westin_sh_isotropic``.

    ``evaluate(wi, wo, P)``: ``(..., 3), (..., 3) -> (..., (P+1)(P+2)(P+3)/6)``, rows
    ``(p, r, q)`` as :func:`torch_hsh.isotropic_indices`. Depends only on
    ``cos(theta_i), cos(theta_o), cos(phi_o - phi_i)``.

    Example:
        >>> from torch_hsh.bases import get_basis
        >>> get_basis("westin_sh_isotropic").num_functions(3)
        20
    """

    name = "westin_sh_isotropic"
    reciprocal = True
    domain = "sphere"  # full-sphere basis: no horizon mask
    max_order = 40
    _cache_key = "westin_iso"

    def rows(self, order):
        return iso_table(order)

    def tables(self, zi, zo, cr, ci, valid, order):
        col, _ = _sh_consts(order)
        RE = azimuth_table(cr, ci, valid, order, False)  # (sin_i sin_o)^q cos(q dphi)
        return _sh_polar(zi, order), _sh_polar(zo, order), RE, col

    def gather(self, row, col, order):
        p, r, q = row
        return col[(p, q)], col[(r, q)], q, (0.5 if p == r else 1.0 / math.sqrt(2.0)) * (1.0 if q == 0 else math.sqrt(2.0))


register_basis(WestinSH())
register_basis(WestinSHIsotropic())
