r"""Isotropic reciprocal Zernike BRDF basis of Koenderink & van Doorn (1998): ``koenderink_zernike``.

Each hemisphere is mapped onto the unit disk by the area-preserving map
:math:`\rho = \sqrt2\sin(\theta/2) = \sqrt{1 - \cos\theta}` (so
:math:`\rho\,d\rho\,d\phi = d\Omega/2`). With the Zernike radial polynomials

.. math::
    R_n^l(\rho) = \sum_{s=0}^{(n-l)/2} \frac{(-1)^s (n-s)!}{s!\,((n+l)/2-s)!\,((n-l)/2-s)!}\rho^{n-2s}

the functions are, for ``n >= m >= l >= 0`` with ``n - l`` and ``m - l`` even,

.. math::
    K_{nm}^l = \frac{1}{2\pi}\sqrt{\frac{(n+1)(m+1)}{N}}
      [R_n^l(\rho_i)R_m^l(\rho_o) + R_m^l(\rho_i)R_n^l(\rho_o)]\cos(l\,\Delta\phi),

``N = 4`` if ``n = m`` and ``l = 0``; ``N = 2`` if (otherwise) ``n = m`` or ``l = 0``;
``N = 1`` otherwise. They are orthonormal over :math:`\Omega_i\times\Omega_o`,
reciprocal and isotropic. Order label = ``n``; columns sorted by ``n``, then ``m``,
then ``l`` (nested). 14 functions up to n = 4 (35 for the isotropic Helmholtz basis).

Evaluation is trigonometry-free: :math:`R_n^l(\rho)/\rho^l` is a polynomial in
:math:`\rho^2 = 1 - z`, and
:math:`\rho_i^l\rho_o^l\cos(l\Delta\phi) = \mathrm{Re}(c^l)/((1+z_i)(1+z_o))^{l/2}` with
:math:`c = (x_i - i y_i)(x_o + i y_o)`; everything is smooth on the closed hemisphere.

The ideal-mirror spectrum is the same as the Helmholtz one (erratum 2 of the notes):
``a = 1`` for ``n = m, l = 0``, :math:`\sqrt2(-1)^l` for ``n = m, l > 0``, 0 otherwise,
because :math:`\int_0^1 R_n^l R_m^l\, 2\rho\,d\rho = \delta_{nm}/(n+1)`
(see :func:`zernike_mirror_coefficients`).

Example:
    >>> from torch_hsh.bases import get_basis
    >>> get_basis("koenderink_zernike").num_functions(4)
    14
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from .._checks import check_order
from ._base import register_basis
from ._isotropic import RowTableBasis, azimuth_table, product_rows

__all__ = ["KoenderinkZernike", "KoenderinkZernikeProduct", "zernike_indices", "zernike_product_indices",
           "zernike_radial", "zernike_mirror_coefficients"]

#: Largest supported n (the radial sums cancel badly in float64 beyond about 30).
MAX_ZERNIKE_ORDER = 24


@lru_cache(maxsize=None)
def _rows(order: int):
    return tuple(
        (n, m, l)
        for n in range(order + 1)
        for m in range(n + 1)
        for l in range(m + 1)
        if (n - l) % 2 == 0 and (m - l) % 2 == 0
    )


def zernike_indices(order: int) -> torch.Tensor:
    """LongTensor ``(K, 3)`` of rows ``(n, m, l)`` of ``koenderink_zernike`` up to ``n = order``.

    Example:
        >>> zernike_indices(2).tolist()
        [[0, 0, 0], [1, 1, 1], [2, 0, 0], [2, 2, 0], [2, 2, 2]]
    """
    order = check_order(order, max_order=MAX_ZERNIKE_ORDER)
    return torch.tensor(_rows(order), dtype=torch.long).reshape(-1, 3)


@lru_cache(maxsize=None)
def _radial_coefficients(order: int):
    """For every (n, l) with n - l even: coefficients of R_n^l(rho)/rho^l in powers u^k of u = rho^2."""
    out = {}
    for n in range(order + 1):
        for l in range(n % 2, n + 1, 2):
            cs = [0.0] * ((n - l) // 2 + 1)
            for s in range((n - l) // 2 + 1):
                v = (-1) ** s * math.factorial(n - s) / (
                    math.factorial(s) * math.factorial((n + l) // 2 - s) * math.factorial((n - l) // 2 - s)
                )
                cs[(n - 2 * s - l) // 2] = float(v)
            out[(n, l)] = cs
    return out


def _radial_table(u: torch.Tensor, order: int):
    """``(N, L)`` table of R_n^l/rho^l at u = rho^2 and the column map."""
    table = _radial_coefficients(order)
    col = {}
    cols: list = []
    for key, cs in table.items():
        acc = torch.full_like(u, cs[-1])
        for c in reversed(cs[:-1]):  # Horner in u
            acc = acc * u + c
        col[key] = len(cols)
        cols.append(acc)
    return torch.stack(cols, dim=-1), col


def zernike_radial(rho: torch.Tensor, n: int, l: int) -> torch.Tensor:
    r"""Zernike radial polynomial :math:`R_n^l(\rho)` (zero when ``n - l`` is odd).

    Args:
        rho: tensor of radii in ``[0, 1]``, any shape.
        n, l: integers with ``0 <= l <= n``.

    Returns:
        Tensor of the same shape as ``rho``.

    Example:
        >>> import torch
        >>> zernike_radial(torch.tensor([1.0]), 4, 2)
        tensor([1.])
    """
    if not isinstance(rho, torch.Tensor):
        raise TypeError(f"`rho` must be a torch.Tensor, got {type(rho).__name__}")
    n = check_order(n, "n", MAX_ZERNIKE_ORDER)
    l = check_order(l, "l", n)
    if (n - l) % 2:
        return torch.zeros_like(rho)
    cs = _radial_coefficients(n)[(n, l)]
    u = rho * rho
    acc = torch.full_like(rho, cs[-1])
    for c in reversed(cs[:-1]):
        acc = acc * u + c
    return acc * rho**l


def _norm(n: int, m: int, l: int) -> float:
    if n == m and l == 0:
        N = 4.0
    elif n == m or l == 0:
        N = 2.0
    else:
        N = 1.0
    return math.sqrt((n + 1) * (m + 1) / N) / (2.0 * math.pi)


def zernike_mirror_coefficients(order: int, dtype=torch.float64) -> torch.Tensor:
    r"""Closed-form coefficients of the ideal mirror kernel (paper Eq. 28) in ``koenderink_zernike``.

    :math:`a_{nm}^l = \int_\Omega K_{nm}^l(\omega, R\omega)\,d\omega` with ``R`` the mirror
    reflection: ``1`` for ``n = m, l = 0``, :math:`\sqrt2(-1)^l` for ``n = m, l > 0``, else 0.

    Returns:
        ``(K,)`` tensor in the column order of :func:`zernike_indices`.

    Example:
        >>> zernike_mirror_coefficients(1).tolist()
        [1.0, -1.4142135623730951]
    """
    order = check_order(order, max_order=MAX_ZERNIKE_ORDER)
    vals = []
    for n, m, l in _rows(order):
        vals.append(0.0 if n != m else (1.0 if l == 0 else math.sqrt(2.0) * (-1) ** l))
    return torch.tensor(vals, dtype=dtype)


class _ZernikeTables(RowTableBasis):
    """The radial and azimuthal tables of both Koenderink--van Doorn bases."""

    domain = "hemisphere"
    max_order = MAX_ZERNIKE_ORDER
    _sines = False  # the symmetrised basis has cosine terms only

    def tables(self, zi, zo, cr, ci, valid, order):
        """Radial tables R_n^l/rho^l at u = 1 - z and the azimuthal table rho_i^l rho_o^l {cos, sin}(l dphi)."""
        zi_c, zo_c = zi.clamp(0.0, 1.0), zo.clamp(0.0, 1.0)
        Ti, col = _radial_table(1.0 - zi_c, order)
        To, _ = _radial_table(1.0 - zo_c, order)
        # rho_i^l rho_o^l cos(l dphi) = Re(c'^l), c' = c / sqrt((1+z_i)(1+z_o))
        A = azimuth_table(cr, ci, valid, order, self._sines, torch.rsqrt((1.0 + zi_c) * (1.0 + zo_c)))
        return Ti, To, A, col


class KoenderinkZernike(_ZernikeTables):
    """Isotropic reciprocal Zernike basis, ``koenderink_zernike`` (order label = n).

    ``evaluate(wi, wo, P)``: ``(..., 3), (..., 3) -> (..., K)``, rows as
    :func:`zernike_indices`; zero where a direction is below the horizon or zero.

    Example (reciprocal: swapping the two directions leaves every function unchanged):
        >>> import torch
        >>> from torch_hsh.bases import get_basis
        >>> w = torch.tensor([[0.0, 0.6, 0.8], [0.6, 0.0, 0.8]])
        >>> f = get_basis("koenderink_zernike").evaluate(w[:1], w[1:], 4)
        >>> f.shape, bool((f - get_basis("koenderink_zernike").evaluate(w[1:], w[:1], 4)).abs().max() < 1e-12)
        (torch.Size([1, 14]), True)
    """

    name = "koenderink_zernike"
    reciprocal = True
    _cache_key = "zk"

    def rows(self, order):
        return _rows(order)

    def gather(self, row, col, order):
        n, m, l = row
        return col[(n, l)], col[(m, l)], l, _norm(n, m, l)


@lru_cache(maxsize=None)
def _product_rows(order: int):
    """Rows ``(label, n, m, l, kind)`` of the unsymmetrised basis, kind 0 = cos, 1 = sin; nested by label."""
    return product_rows(order, lambda n, m, l: (n - l) % 2 == 0 and (m - l) % 2 == 0)


def zernike_product_indices(order: int) -> torch.Tensor:
    """LongTensor ``(K, 4)`` of rows ``(n, m, l, kind)`` of ``koenderink_zernike_product`` (kind 0 = cos, 1 = sin).

    Example:
        >>> zernike_product_indices(1).tolist()
        [[0, 0, 0, 0], [1, 1, 1, 0], [1, 1, 1, 1]]
    """
    order = check_order(order, max_order=MAX_ZERNIKE_ORDER)
    return torch.tensor([r[1:] for r in _product_rows(order)], dtype=torch.long).reshape(-1, 4)


class KoenderinkZernikeProduct(_ZernikeTables):
    r"""Unsymmetrised isotropic Zernike product basis, ``koenderink_zernike_product`` (**not** reciprocal).

    .. math::
        Z_{nm}^{l,c} = \frac{\sqrt{(n+1)(m+1)}}{2\pi}\,c_l\,R_n^l(\rho_i)R_m^l(\rho_o)\cos(l\Delta\phi),\qquad
        Z_{nm}^{l,s} = \frac{\sqrt{(n+1)(m+1)}}{2\pi}\sqrt2\,R_n^l(\rho_i)R_m^l(\rho_o)\sin(l\Delta\phi)

    for all **ordered** ``(n, m)`` with ``l <= min(n, m)``, ``n - l`` and ``m - l`` even
    (:math:`c_0 = 1`, :math:`c_l = \sqrt2`; sine terms for ``l >= 1``): the isotropic subspace
    of products of a Zernike function of :math:`\omega_i` and one of :math:`\omega_o`
    (the relation of ``koenderink_zernike`` to this basis is that of ``helmholtz_isotropic``
    to ``gautron_hsh_isotropic``). Orthonormal over :math:`\Omega_i\times\Omega_o`; label
    ``max(n, m)``; columns sorted by label, then ``n, m``, cosine before sine terms.

    Example:
        >>> from torch_hsh.bases import get_basis
        >>> [get_basis("koenderink_zernike_product").num_functions(p) for p in range(4)]
        [1, 3, 8, 16]
    """

    name = "koenderink_zernike_product"
    reciprocal = False
    symmetric = False
    _cache_key = "zkp"
    _sines = True

    def rows(self, order):
        return _product_rows(order)

    def gather(self, row, col, order):
        _, n, m, l, kd = row
        coef = math.sqrt((n + 1) * (m + 1)) / (2 * math.pi) * (1.0 if l == 0 else math.sqrt(2.0))
        return col[(n, l)], col[(m, l)], l if kd == 0 else order + l, coef


register_basis(KoenderinkZernike())
_helm = KoenderinkZernike()
_helm.name = "koenderink_helmholtz"
register_basis(_helm)  # the reciprocal (Helmholtz) basis of Koenderink & van Doorn (1998), same functions
register_basis(KoenderinkZernikeProduct())
