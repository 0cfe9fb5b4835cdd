"""The Helmholtz HSH-based bases (ours), registered as ``helmholtz_isotropic``
(alias ``helmholtz_hsh``) and ``helmholtz_anisotropic``."""
from __future__ import annotations


import torch

from .. import kernel as _b
from .._checks import MAX_ANISOTROPIC_ORDER
from ._base import Basis, register_basis


class HelmholtzIsotropic(Basis):
    """Isotropic Helmholtz HSH basis (erratum-1 normalisation), see :func:`torch_hsh.helmholtz_isotropic`."""

    isotropic = True
    reciprocal = True
    domain = "hemisphere"
    max_order = 40

    def __init__(self, name: str = "helmholtz_isotropic"):
        self.name = name

    def evaluate(self, wi, wo, order):
        return _b.helmholtz_isotropic(wi, wo, self.check_order(order))

    def azimuthal_degree(self, order):
        return self.check_order(order)

    def num_functions(self, order):
        return _b.num_isotropic(self.check_order(order))

    def function_orders(self, order):
        return _b.isotropic_indices(self.check_order(order))[:, 0].clone()


class HelmholtzAnisotropic(Basis):
    """General Helmholtz HSH basis, see :func:`torch_hsh.helmholtz_anisotropic`.

    Note: columns are ordered j-major over HSH pairs, which is *not* nested by
    order; use :meth:`function_orders` (label = max(p, r)) to truncate.
    """

    isotropic = False
    reciprocal = True
    domain = "hemisphere"
    max_order = MAX_ANISOTROPIC_ORDER

    def __init__(self, name: str = "helmholtz_anisotropic"):
        self.name = name

    def evaluate(self, wi, wo, order):
        return _b.helmholtz_anisotropic(wi, wo, self.check_order(order))

    def azimuthal_degree(self, order):
        return self.check_order(order)

    def num_functions(self, order):
        return _b.num_anisotropic(self.check_order(order))

    def function_orders(self, order):
        idx = _b.anisotropic_indices(self.check_order(order))
        return torch.maximum(idx[:, 0], idx[:, 2])


register_basis(HelmholtzIsotropic("helmholtz_isotropic"))
register_basis(HelmholtzIsotropic("helmholtz_hsh"))
register_basis(HelmholtzAnisotropic("helmholtz_anisotropic"))
