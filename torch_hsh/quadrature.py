r"""Deterministic and Monte Carlo quadrature over (hemi)spheres and their products.

Three rules are provided, all returning tensors in the requested dtype/device:

* :func:`direction_quadrature` -- product rule on one (hemi)sphere:
  Gauss--Legendre in :math:`z = \cos\theta` (on ``[0, 1]`` for the hemisphere,
  ``[-1, 1]`` for the sphere) times the uniform (trapezoid) rule in
  :math:`\phi` on ``n_phi`` equispaced angles. With ``n_theta`` nodes the
  z-rule is exact for polynomials of degree ``<= 2 n_theta - 1``; the phi-rule
  is exact for trigonometric polynomials of degree ``<= n_phi - 1``. A product
  of two (hemi)spherical harmonics of orders ``<= L`` and ``<= P`` integrates
  exactly when ``n_theta >= (L + P)/2 + 1`` and ``n_phi >= L + P + 1``
  (after the phi-integration only equal ``|m|`` survive, and then the
  ``(1 - z^2)^{m/2}`` / ``(z (1 - z))^{m/2}`` factors pair up into
  polynomials).
* :func:`isotropic_quadrature` -- the reduced rule for an isotropic integrand
  :math:`F(\cos\theta_i, \cos\theta_o, \Delta\phi)`:

  .. math::
      \int_{\Omega_i}\int_{\Omega_o} F\, d\omega_i\, d\omega_o
      = 2\pi \int dz_i \int dz_o \int_0^{2\pi} F\, d\Delta\phi,

  placing :math:`\omega_i` at :math:`\phi = 0` and :math:`\omega_o` at
  :math:`\phi = \Delta\phi`. The factor :math:`2\pi` is folded into the weights.
* :func:`monte_carlo_directions` -- uniform samples with weight
  ``area / n`` (the estimator the paper used), from a seeded generator.

Gauss--Legendre nodes are strictly inside ``(0, 1)``: the horizon ``z = 0`` is
never sampled, so integrands with an (integrable) singularity there, such as
the :math:`1/\cos\theta_i` of the Torrance--Sparrow model, give finite sums.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Optional, Tuple

import numpy as np
import torch

__all__ = [
    "gauss_legendre",
    "direction_quadrature",
    "isotropic_quadrature",
    "isotropic_directions",
    "monte_carlo_directions",
]

_DOMAINS = ("hemisphere", "sphere")


def _check_count(n, name: str, minimum: int = 1) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"`{name}` must be an integer, got {n!r} ({type(n).__name__})")
    n = int(n)
    if n < minimum:
        raise ValueError(f"`{name}` must be >= {minimum}, got {n}")
    return n


def _check_domain(domain) -> str:
    if domain not in _DOMAINS:
        raise ValueError(f"`domain` must be one of {_DOMAINS}, got {domain!r}")
    return domain


def _check_dtype(dtype) -> torch.dtype:
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"`dtype` must be torch.float32 or torch.float64, got {dtype!r}")
    return dtype


@lru_cache(maxsize=64)
def _leggauss(n: int):
    """Cached float64 nodes/weights on [-1, 1] (numpy's eigenvalue method is O(n^3))."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def gauss_legendre(
    n: int,
    a: float = -1.0,
    b: float = 1.0,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Gauss--Legendre nodes and weights on ``[a, b]``.

    Computed in float64 (numpy) and converted. Exact for polynomials of degree
    ``<= 2n - 1``; all nodes lie strictly inside ``(a, b)``.

    Args:
        n: number of nodes (>= 1).
        a, b: interval end points, ``a < b``.
        dtype, device: of the returned tensors.

    Returns:
        ``(x, w)``, both ``(n,)``, with ``x`` ascending.

    Example:
        >>> x, w = gauss_legendre(3, 0.0, 1.0)
        >>> float((w * x**5).sum())  # doctest: +ELLIPSIS
        0.1666666666666...
    """
    n = _check_count(n, "n")
    dtype = _check_dtype(dtype)
    if not (math.isfinite(a) and math.isfinite(b) and a < b):
        raise ValueError(f"need finite a < b, got a={a}, b={b}")
    x, w = _leggauss(n)
    x = 0.5 * (b - a) * x + 0.5 * (b + a)
    w = 0.5 * (b - a) * w
    return (
        torch.tensor(x, dtype=dtype, device=device),
        torch.tensor(w, dtype=dtype, device=device),
    )


def _uniform_phi(n_phi: int, dtype, device):
    phi = torch.arange(n_phi, dtype=torch.float64) * (2.0 * math.pi / n_phi)
    w = torch.full((n_phi,), 2.0 * math.pi / n_phi, dtype=torch.float64)
    return phi.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device)


def direction_quadrature(
    n_theta: int,
    n_phi: int,
    domain: str = "hemisphere",
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    r"""Product quadrature on the hemisphere (``z >= 0``) or the sphere.

    Nodes: Gauss--Legendre in :math:`z=\cos\theta` (``n_theta`` nodes on ``[0,1]``
    or ``[-1,1]``) times ``n_phi`` equispaced azimuths :math:`\phi_j = 2\pi j/n_\phi`.
    :math:`\int f\,d\omega \approx \sum_k w_k f(\omega_k)`.

    Args:
        n_theta: Gauss--Legendre nodes in ``cos(theta)``.
        n_phi: azimuthal nodes.
        domain: ``"hemisphere"`` or ``"sphere"``.
        dtype, device: of the returned tensors.

    Returns:
        ``dirs`` ``(n_theta * n_phi, 3)`` unit vectors (z-major: all azimuths of the
        first z node first) and ``weights`` ``(n_theta * n_phi,)`` summing to the
        area (``2 pi`` or ``4 pi``).

    Example:
        >>> d, w = direction_quadrature(4, 8)
        >>> d.shape, round(float(w.sum()), 12) == round(2 * math.pi, 12)
        (torch.Size([32, 3]), True)
    """
    n_theta = _check_count(n_theta, "n_theta")
    n_phi = _check_count(n_phi, "n_phi")
    lo = 0.0 if _check_domain(domain) == "hemisphere" else -1.0
    z, wz = gauss_legendre(n_theta, lo, 1.0, dtype=torch.float64)
    phi, wp = _uniform_phi(n_phi, torch.float64, None)
    s = torch.sqrt((1.0 - z * z).clamp(min=0.0))
    d = torch.stack(
        [
            s[:, None] * torch.cos(phi)[None, :],
            s[:, None] * torch.sin(phi)[None, :],
            z[:, None].expand(n_theta, n_phi),
        ],
        dim=-1,
    ).reshape(-1, 3)
    w = (wz[:, None] * wp[None, :]).reshape(-1)
    return d.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device)


def isotropic_quadrature(
    n_theta: int,
    n_phi: int,
    domain: str = "hemisphere",
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""Reduced 3-D rule for isotropic integrands over :math:`\Omega_i\times\Omega_o`.

    .. math::
        \int_{\Omega_i}\int_{\Omega_o} F\,d\omega_i\,d\omega_o
        = 2\pi\int dz_i\int dz_o\int_0^{2\pi} F(z_i, z_o, \Delta\phi)\,d\Delta\phi

    valid whenever ``F`` depends on the azimuths only through
    :math:`\Delta\phi = \phi_o - \phi_i` (e.g. isotropic BRDF times isotropic basis
    function). Gauss--Legendre in ``z_i`` and ``z_o`` (``n_theta`` nodes each),
    ``n_phi`` equispaced ``dphi``.

    Args:
        n_theta, n_phi: node counts.
        domain: ``"hemisphere"`` (z in ``[0, 1]``) or ``"sphere"`` (``[-1, 1]``).
        dtype, device: of the returned tensors.

    Returns:
        ``cos_i, cos_o, dphi, weights``, each ``(n_theta**2 * n_phi,)``; the weights
        include the factor ``2 pi`` and sum to ``area**2``. To evaluate a basis,
        place ``wi = (sqrt(1 - cos_i^2), 0, cos_i)`` and
        ``wo = (sin_o cos(dphi), sin_o sin(dphi), cos_o)``.

    Example:
        >>> ci, co, dp, w = isotropic_quadrature(3, 5)
        >>> ci.shape, round(float(w.sum()), 10) == round(4 * math.pi**2, 10)
        (torch.Size([45]), True)
    """
    n_theta = _check_count(n_theta, "n_theta")
    n_phi = _check_count(n_phi, "n_phi")
    lo = 0.0 if _check_domain(domain) == "hemisphere" else -1.0
    z, wz = gauss_legendre(n_theta, lo, 1.0, dtype=torch.float64)
    phi, wp = _uniform_phi(n_phi, torch.float64, None)
    ci = z[:, None, None].expand(n_theta, n_theta, n_phi).reshape(-1)
    co = z[None, :, None].expand(n_theta, n_theta, n_phi).reshape(-1)
    dp = phi[None, None, :].expand(n_theta, n_theta, n_phi).reshape(-1)
    w = (2.0 * math.pi) * (wz[:, None, None] * wz[None, :, None] * wp[None, None, :]).reshape(-1)
    return tuple(t.to(dtype=dtype, device=device) for t in (ci, co, dp, w))  # type: ignore[return-value]


def isotropic_directions(cos_i: torch.Tensor, cos_o: torch.Tensor, dphi: torch.Tensor):
    """Directions ``wi`` at azimuth 0 and ``wo`` at azimuth ``dphi`` for the reduced rule.

    Args:
        cos_i, cos_o, dphi: ``(...)`` tensors of one shape.

    Returns:
        ``wi, wo``, each ``(..., 3)``.

    Example:
        >>> wi, wo = isotropic_directions(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([0.0]))
        >>> wo.tolist()
        [[1.0, 0.0, 0.0]]
    """
    si = torch.sqrt((1.0 - cos_i * cos_i).clamp(min=0.0))
    so = torch.sqrt((1.0 - cos_o * cos_o).clamp(min=0.0))
    wi = torch.stack([si, torch.zeros_like(si), cos_i], dim=-1)
    wo = torch.stack([so * torch.cos(dphi), so * torch.sin(dphi), cos_o], dim=-1)
    return wi, wo


def monte_carlo_directions(
    n: int,
    domain: str = "hemisphere",
    seed: Optional[int] = 0,
    generator: Optional[torch.Generator] = None,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    r"""Uniformly distributed random directions with equal weights ``area / n``.

    ``z`` is uniform in ``[0, 1]`` (hemisphere) or ``[-1, 1]`` (sphere) and
    :math:`\phi` uniform in :math:`[0, 2\pi)` (Archimedes), so
    :math:`\sum_k w_k f(\omega_k)` is an unbiased estimate of :math:`\int f\,d\omega`.

    Args:
        n: number of samples.
        domain: ``"hemisphere"`` or ``"sphere"``.
        seed: seed of a fresh CPU generator (ignored when ``generator`` is given);
            ``None`` uses the global RNG.
        generator: optional ``torch.Generator`` (CPU); samples are drawn on the CPU
            in float64 and moved, so results do not depend on the device.
        dtype, device: of the returned tensors.

    Returns:
        ``dirs`` ``(n, 3)`` and ``weights`` ``(n,)``.

    Example:
        >>> d, w = monte_carlo_directions(1000, seed=1)
        >>> bool((d[:, 2] >= 0).all()), round(float(w.sum()), 12) == round(2 * math.pi, 12)
        (True, True)
    """
    n = _check_count(n, "n")
    lo = 0.0 if _check_domain(domain) == "hemisphere" else -1.0
    if generator is None and seed is not None:
        generator = torch.Generator().manual_seed(int(seed))
    u = torch.rand(n, 2, generator=generator, dtype=torch.float64)
    z = lo + (1.0 - lo) * u[:, 0]
    phi = 2.0 * math.pi * u[:, 1]
    s = torch.sqrt((1.0 - z * z).clamp(min=0.0))
    d = torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], dim=-1)
    area = 2.0 * math.pi * (1.0 - lo)
    w = torch.full((n,), area / n, dtype=torch.float64)
    return d.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device)
