"""Shared test fixtures: deterministic hemisphere quadrature and random directions.

Fixtures return *factories* so each test picks its own sizes:

* ``hemi_quadrature(nz, nphi, dtype=torch.float64)`` -> ``(dirs (M, 3), weights (M,))``:
  Gauss–Legendre in ``cos(theta)`` on ``[0, 1]`` times the uniform rule in ``phi``.
  It integrates ``f(z) g(phi)`` exactly for polynomial ``f`` of degree ``< 2 nz`` and
  trigonometric ``g`` of degree ``< nphi``, with ``sum(weights) = 2 pi``.
* ``pair_quadrature(nz, nphi, dtype)`` -> ``(wi (M, 3), wo (M, 3), weights (M,))``: the
  product rule over ``Omega_i x Omega_o`` (``M = (nz nphi)**2``).
* ``random_dirs(shape, dtype, upper=True, seed=0)`` -> unit directions ``(*shape, 3)``,
  on the upper hemisphere by default, kept away from the horizon and the pole.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch


def _hemi_quadrature(nz: int, nphi: int, dtype=torch.float64):
    x, w = np.polynomial.legendre.leggauss(nz)
    z = 0.5 * (x + 1.0)
    wz = 0.5 * w
    phi = 2.0 * math.pi * (np.arange(nphi) + 0.5) / nphi
    wphi = np.full(nphi, 2.0 * math.pi / nphi)
    Z, PH = np.meshgrid(z, phi, indexing="ij")
    W = np.outer(wz, wphi)
    s = np.sqrt(1.0 - Z * Z)
    dirs = np.stack([s * np.cos(PH), s * np.sin(PH), Z], axis=-1).reshape(-1, 3)
    return torch.tensor(dirs, dtype=dtype), torch.tensor(W.reshape(-1), dtype=dtype)


@pytest.fixture
def hemi_quadrature():
    return _hemi_quadrature


@pytest.fixture
def pair_quadrature():
    def make(nz: int, nphi: int, dtype=torch.float64):
        d, w = _hemi_quadrature(nz, nphi, dtype)
        m = d.shape[0]
        wi = d[:, None, :].expand(m, m, 3).reshape(-1, 3)
        wo = d[None, :, :].expand(m, m, 3).reshape(-1, 3)
        ww = (w[:, None] * w[None, :]).reshape(-1)
        return wi, wo, ww

    return make


def _random_dirs(shape, dtype=torch.float64, upper: bool = True, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    shape = tuple(shape) if isinstance(shape, (tuple, list)) else (shape,)
    n = int(np.prod(shape)) if shape else 1
    z = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    if not upper:
        z = 2.0 * z - 1.0
    phi = torch.rand(n, generator=g, dtype=torch.float64) * 2.0 * math.pi
    s = torch.sqrt(1.0 - z * z)
    d = torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], dim=-1)
    return d.reshape(*shape, 3).to(dtype)


@pytest.fixture
def random_dirs():
    return _random_dirs
