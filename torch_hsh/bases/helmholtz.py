"""The Helmholtz HSH-based bases (ours), registered as ``helmholtz_isotropic`` and ``helmholtz_anisotropic``."""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Tuple

import torch

from .. import kernel as _b
from .._checks import MAX_ANISOTROPIC_ORDER
from ._base import DegreeBasis, register_basis

__all__ = ["HelmholtzIsotropic", "HelmholtzAnisotropic", "COS_MOMENTS", "albedo_terms"]


class _Helmholtz(DegreeBasis):
    """What the two Helmholtz bases share: reciprocal, on the hemispheres, registered by name, and
    evaluated by the kernel function ``_evaluate`` with ``_count(order)`` columns."""

    reciprocal = True
    domain = "hemisphere"
    _evaluate = staticmethod(_b.helmholtz_isotropic)
    _count = staticmethod(_b.num_isotropic)

    def __init__(self, name: str):
        self.name = name

    def evaluate(self, wi, wo, order):
        return self._evaluate(wi, wo, self.check_order(order))

    def num_functions(self, order):
        return self._count(self.check_order(order))


class HelmholtzIsotropic(_Helmholtz):
    """Isotropic Helmholtz HSH basis (erratum-1 normalisation), see :func:`torch_hsh.helmholtz_isotropic`."""

    isotropic = True
    max_order = 40

    def __init__(self, name: str = "helmholtz_isotropic"):
        super().__init__(name)

    def function_orders(self, order):
        return _b.isotropic_indices(self.check_order(order))[:, 0].clone()


class HelmholtzAnisotropic(_Helmholtz):
    """General Helmholtz HSH basis, see :func:`torch_hsh.helmholtz_anisotropic`.

    Note: columns are ordered j-major over HSH pairs, which is *not* nested by
    order; use :meth:`function_orders` (label = max(p, r)) to truncate.
    """

    isotropic = False
    max_order = MAX_ANISOTROPIC_ORDER
    _evaluate = staticmethod(_b.helmholtz_anisotropic)
    _count = staticmethod(_b.num_anisotropic)

    def __init__(self, name: str = "helmholtz_anisotropic"):
        super().__init__(name)

    def function_orders(self, order):
        idx = _b.anisotropic_indices(self.check_order(order))
        return torch.maximum(idx[:, 0], idx[:, 2])


#: Hemispherical cosine moments of the zonal HSH, :math:`I_n = \int_\Omega \Theta_n(\cos\theta)\cos\theta\,d\omega
#: = 2\pi\sqrt{(2n+1)/(2\pi)}\int_0^1 \tilde P_n(x)\,x\,dx`, the integral being 1/2 (n = 0), 1/6 (n = 1) and 0
#: for n >= 2 (absent here).
COS_MOMENTS = {n: 2.0 * math.pi * math.sqrt((2 * n + 1) / (2.0 * math.pi)) * integral
               for n, integral in ((0, 0.5), (1, 1.0 / 6.0))}

AlbedoTerm = Tuple[int, float, Tuple[Tuple[float, int, int], ...]]


@lru_cache(maxsize=None)
def albedo_terms(order: int, isotropic: bool) -> Tuple[AlbedoTerm, ...]:
    r"""The closed-form directional albedo of the Helmholtz bases as a sparse table, the one source of it.

    :math:`\rho(\omega_o) = \int_{\Omega_i} f\cos\theta_i\,d\omega_i = \sum_k a_k N_k \sum_t I_t H_{n_t}^{m_t}(\omega_o)`:
    only the HSH factors of :math:`\omega_i` with ``m = 0`` and ``n <= 1`` survive the integral
    (:data:`COS_MOMENTS`), so a function :math:`N_{jk}(H_j H_k + H_k H_j)` with flat HSH indices ``j <= k``
    (the isotropic functions: ``(p, r, q)`` with ``q = 0``) contributes
    :math:`N_{jk}(I_j H_k(\omega_o) + I_k H_j(\omega_o))`, :math:`N_{jk} = 1/\sqrt{2 + 2\delta_{jk}}`.

    Args:
        order: basis order ``P``.
        isotropic: the columns of ``helmholtz_isotropic`` (True) or ``helmholtz_anisotropic`` (False).

    Returns:
        One entry per coefficient column with a non-zero albedo, in column order:
        ``(k, N_k, ((I, n, m), ...))``, the terms in the order of the formula (the moment of the
        first factor first). :math:`H_n^m(\omega_o)` is the HSH of flat index ``n*n + n + m``
        (``m = 0`` for the isotropic basis: the zonal :math:`\Theta_n`).

    Example:
        >>> albedo_terms(1, True)[0]   # the constant function: a_0 N (I_0 Theta_0 + I_0 Theta_0), N = 1/2
        (0, 0.5, ((1.2533141373155003, 0, 0), (1.2533141373155003, 0, 0)))
    """
    out = []
    if isotropic:
        for k, (p, r, q) in enumerate(_b.isotropic_indices(order).tolist()):
            if q == 0:
                out.append((k, 1.0 / math.sqrt(2.0 + 2.0 * (p == r)), ((p, 0), (r, 0)), ((r, 0), (p, 0))))
    else:
        for k, (p, q, r, s) in enumerate(_b.anisotropic_indices(order).tolist()):
            out.append((k, 1.0 / math.sqrt(2.0 + 2.0 * (p * p + p + q == r * r + r + s)), ((p, q), (r, s)),
                        ((r, s), (p, q))))
    table = []
    for k, norm, first, second in out:
        terms = tuple((COS_MOMENTS[a], n, m) for (a, am), (n, m) in (first, second)
                      if am == 0 and a in COS_MOMENTS)
        if terms:
            table.append((k, norm, terms))
    return tuple(table)


register_basis(HelmholtzIsotropic("helmholtz_isotropic"))
register_basis(HelmholtzAnisotropic("helmholtz_anisotropic"))
