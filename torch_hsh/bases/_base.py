"""Basis interface and registry."""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Dict, List, Optional

import torch

from .._checks import check_order

_REGISTRY: Dict[str, "Basis"] = {}


class Basis(ABC):
    """A BRDF basis on (a subset of) the product of two (hemi)spheres.

    Attributes:
        name: registry name.
        isotropic: True if the functions depend only on (theta_i, theta_o, dphi).
        reciprocal: True if every function satisfies B(wi, wo) = B(wo, wi).
        domain: ``"hemisphere"`` (functions live on z >= 0 for both directions,
            orthonormal there) or ``"sphere"`` (orthonormal over the full sphere;
            projecting a BRDF integrates over the full spheres with the BRDF
            extended by zero below the horizon).
        max_order: largest supported order, or None.

    Subclasses implement :meth:`evaluate`, :meth:`num_functions` and
    :meth:`function_orders`.
    """

    name: str = ""
    isotropic: bool = False
    reciprocal: bool = True
    domain: str = "hemisphere"
    max_order: Optional[int] = None

    def check_order(self, order) -> int:
        mx = self.max_order if self.max_order is not None else 40
        try:
            return check_order(order, max_order=mx)
        except ValueError as e:
            raise ValueError(f"basis '{self.name}': {e}") from None

    @abstractmethod
    def evaluate(self, wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
        """``(..., 3), (..., 3) -> (..., K)`` basis values in the local frame."""

    def azimuthal_degree(self, order: int) -> Optional[int]:
        """Largest azimuthal frequency of the functions up to ``order``, or ``None`` if unknown.

        A basis that returns ``D`` promises: at fixed polar angles every function up to
        ``order`` is a trigonometric polynomial of degree ``<= D`` in ``phi_i`` and in
        ``phi_o`` (for an isotropic basis: in ``phi_o - phi_i``). The convergence-controlled
        projection then low-passes the BRDF in azimuth and evaluates the basis on
        ``2D + 2`` azimuths only (see :mod:`torch_hsh.fitting.rules`). ``None`` (the
        default for user bases) disables that shortcut; results are the same.
        """
        return None

    def __call__(self, wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
        return self.evaluate(wi, wo, order)

    @abstractmethod
    def num_functions(self, order: int) -> int:
        """Number of functions up to ``order``."""

    @abstractmethod
    def function_orders(self, order: int) -> torch.Tensor:
        """LongTensor ``(K,)``: the smallest truncation order that contains each function.

        Functions up to order P are exactly those with label <= P, and the first
        ``num_functions(P)`` columns of ``evaluate(..., order)`` for any
        ``order >= P`` are the basis up to P (bases are nested).
        """

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


class DegreeBasis(Basis):
    """A basis whose functions up to order ``P`` have azimuthal degree ``<= P`` (every basis of the package)."""

    def azimuthal_degree(self, order: int) -> Optional[int]:
        return self.check_order(order)


def register_basis(basis: Basis) -> Basis:
    """Add a basis instance to the registry under ``basis.name``."""
    _REGISTRY[basis.name] = basis
    return basis


def get_basis(name) -> Basis:
    """Look up a basis by name (or pass a :class:`Basis` through)."""
    if isinstance(name, Basis):
        return name
    if not isinstance(name, str):
        raise TypeError(f"`basis` must be a name or a Basis, got {type(name).__name__}")
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown basis {name!r}; available: {sorted(_REGISTRY)}") from None


def available_bases() -> List[str]:
    """Sorted list of registered basis names."""
    return sorted(_REGISTRY)
