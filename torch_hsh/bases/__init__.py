"""Named BRDF bases behind one interface.

Every basis is a :class:`Basis`: evaluate it on (wi, wo) pairs in the local frame,
count its functions, and label each function with its truncation order so that
:func:`torch_hsh.fitting.energy_accuracy` can compute Acc(P) for any basis.

Example:
    >>> from torch_hsh.bases import get_basis, available_bases
    >>> b = get_basis("helmholtz_isotropic")
    >>> b.num_functions(3)
    20
"""
from __future__ import annotations

from ._base import Basis, available_bases, get_basis, register_basis
from . import helmholtz  # noqa: F401  (registers the Helmholtz HSH bases)
from . import westin, gautron, zernike, hbasis  # noqa: F401,E402  (register the comparison bases)

__all__ = ["Basis", "available_bases", "get_basis", "register_basis"]
