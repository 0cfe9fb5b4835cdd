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

Every test starts from the same global torch seed (the autouse fixture ``_seed_torch``), so a test
that draws without its own generator still sees the same numbers on every run and in any order; the
hypothesis tests are derandomized (the profile ``torch_hsh``) for the same reason.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

try:  # hypothesis draws the same examples on every run (CI must not depend on the draw)
    from hypothesis import settings as _hyp_settings

    _hyp_settings.register_profile("torch_hsh", derandomize=True, database=None, deadline=None)
    _hyp_settings.load_profile("torch_hsh")
except ImportError:  # pragma: no cover - hypothesis is in the test extra
    pass


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


def random_ps_scene(p: int, l: int, seed: int = 0, spread: float = 0.45, dtype=torch.float64):
    """Random photometric-stereo geometry, the one builder of the ``test_ps*`` files.

    ``p`` unit normals around the view direction (x, y spread ``spread``, z 0.2) and ``l`` lights in a
    DiLiGenT-like cone around it (x, y 0.45, z 0.1), drawn in that order from one generator seeded with
    ``seed``; returns ``(normals (p, 3), lights (l, 3), generator)`` (a test draws its albedo etc. next).
    """
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(p, 3, generator=g, dtype=dtype) * torch.tensor([spread, spread, 0.2], dtype=dtype)
    n[:, 2] += 1.0
    n = torch.nn.functional.normalize(n, dim=-1)
    d = torch.randn(l, 3, generator=g, dtype=dtype) * torch.tensor([0.45, 0.45, 0.1], dtype=dtype)
    d[:, 2] += 1.0
    return n, torch.nn.functional.normalize(d, dim=-1), g


def blinn_phong_ps_scene(p: int, l: int, seed: int = 0):
    """:func:`random_ps_scene` (spread 0.4) rendered with a Blinn-Phong BRDF over a random RGB albedo, with
    read noise 1e-3; returns ``(images (l, p, 3), lights (l, 3), normals (p, 3))`` in float64."""
    from torch_hsh.brdf import BlinnPhong
    from torch_hsh.render import render

    dt = torch.float64
    n, lights, g = random_ps_scene(p, l, seed, spread=0.4)
    alb = 0.2 + 0.6 * torch.rand(p, 3, generator=g, dtype=dt)
    model = BlinnPhong(alb, torch.full((p, 1), 0.3, dtype=dt), torch.full((p, 1), 20.0, dtype=dt))
    return render(n, lights, model, read_std=1e-3, seed=seed), lights, n


@pytest.fixture
def ps_scene():
    """The builder :func:`random_ps_scene` (for tests that take it as a fixture)."""
    return random_ps_scene


def edge_case_dirs(n: int, seed: int, dtype=torch.float64, special: bool = True) -> torch.Tensor:
    """``(n, 3)`` random upper-hemisphere directions; with ``special`` the first 8 rows are the kernels' edge
    cases (pole, horizon, within eps of it, zero vector, below the horizon, not normalised, near the pole)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d[:, 2] = d[:, 2].abs()
    if special:
        d[:8] = torch.tensor([
            [0.0, 0.0, 1.0],  # pole
            [1.0, 0.0, 0.0],  # horizon
            [0.6, -0.8, 1e-13],  # within eps of the horizon (float64)
            [0.6, 0.8, 3e-6],  # just above the float32 eps
            [0.0, 0.0, 0.0],  # zero vector
            [0.3, 0.1, -0.5],  # below the horizon
            [2.0, -1.0, 0.5],  # not normalised
            [1e-9, 0.0, 1.0],  # near the pole
        ], dtype=torch.float64)
    return d.to(dtype)


@pytest.fixture(autouse=True)
def _seed_torch():
    """Reset the global torch seed before each test: no test depends on which tests ran before it."""
    torch.manual_seed(0)
