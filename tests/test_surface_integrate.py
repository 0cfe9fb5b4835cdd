"""Tests for torch_hsh.surface.integrate (normal integration on masks)."""
import math

import numpy as np
import pytest
import torch

from torch_hsh.render.scenes import sphere_normals
from torch_hsh.surface import (
    connected_components,
    depth_to_normals,
    integrate_normals,
    normals_to_slopes,
)

SOLVERS = ["scipy", "torch"]


def _grid(h, w):
    return torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")


def _normals_from_slopes(dz_dcol, dz_drow):
    """Unit normals of z(row, col): n ~ (-dz/dx, -dz/dy, 1) with x = col, y = -row."""
    n = torch.stack([-dz_dcol, dz_drow, torch.ones_like(dz_dcol)], dim=-1)
    return n / n.norm(dim=-1, keepdim=True)


def _aligned_error(z, z_true, m):
    e = (z - z_true)[m]
    return e - e.mean()


def _wavy(h=60, w=80):
    """An analytic height field with exact normals, on an ellipse with two holes."""
    r, c = _grid(h, w)
    z = 6 * torch.sin(2 * math.pi * c / 40) * torch.cos(2 * math.pi * r / 50) + 0.2 * c - 0.1 * r
    dzc = 6 * (2 * math.pi / 40) * torch.cos(2 * math.pi * c / 40) * torch.cos(2 * math.pi * r / 50) + 0.2
    dzr = -6 * (2 * math.pi / 50) * torch.sin(2 * math.pi * c / 40) * torch.sin(2 * math.pi * r / 50) - 0.1
    m = ((r - h / 2) / (0.48 * h)) ** 2 + ((c - w / 2) / (0.48 * w)) ** 2 < 1
    m &= ((r - 20) ** 2 + (c - 30) ** 2) >= 36
    m &= ~((r >= 35) & (r < 40) & (c >= 45) & (c < 60))
    return z, _normals_from_slopes(dzc, dzr), m


@pytest.mark.parametrize("solver", SOLVERS)
def test_sphere_depth(solver):
    size, radius = 96, 0.9
    n, m = sphere_normals(size, radius=radius, dtype=torch.float64)
    rr = radius * size / 2
    r, c = _grid(size, size)
    x, y = c + 0.5 - size / 2, -(r + 0.5 - size / 2)
    z_true = torch.sqrt((rr * rr - x * x - y * y).clamp(min=0))
    z = integrate_normals(n, m, solver=solver)
    e = _aligned_error(z, z_true, m)
    inner = (x * x + y * y < (0.8 * rr) ** 2)[m]
    # errors concentrate at the silhouette, where slopes are clamped at 1 / min_nz
    assert float(e.pow(2).mean().sqrt()) < 0.5  # of a 43 px high dome
    assert float(e[inner].pow(2).mean().sqrt()) < 0.15
    assert bool(torch.isnan(z[~m]).all())
    assert abs(float(z[m].mean())) < 1e-9  # one part: zero mean


@pytest.mark.parametrize("solver", SOLVERS)
def test_smooth_heightfield_with_holes(solver):
    z_true, n, m = _wavy()
    z, info = integrate_normals(n, m, solver=solver, return_info=True)
    e = _aligned_error(z, z_true, m)
    assert float(e.abs().max()) < 0.05  # trapezoidal rule, O(h^2) slope errors; the relief spans ~25 px
    assert info["residual"] < 1e-6 and info["components"] == 1
    # a sign error in either axis gives errors of pixels
    flipped = n * torch.tensor([1.0, -1.0, 1.0], dtype=n.dtype)
    e_bad = _aligned_error(integrate_normals(flipped, m, solver=solver), z_true, m)
    assert float(e_bad.abs().max()) > 5


def test_solvers_agree_and_tolerance():
    z_true, n, m = _wavy()
    za = integrate_normals(n, m, solver="scipy", tol=1e-10)
    zb = integrate_normals(n, m, solver="torch", tol=1e-10)
    assert float((za - zb)[m].abs().max()) < 1e-6


def _dense_lstsq(n, m):
    """Independent reference: the edge equations z_j - z_i = (g_i + g_j) / 2 solved densely."""
    gc, gr = normals_to_slopes(n)
    h, w = m.shape
    idx = -np.ones((h, w), dtype=int)
    pix = list(zip(*np.nonzero(m.numpy())))
    for k, (i, j) in enumerate(pix):
        idx[i, j] = k
    rows, rhs = [], []
    for i, j in pix:
        for di, dj, g in ((0, 1, gc), (1, 0, gr)):
            if i + di < h and j + dj < w and m[i + di, j + dj]:
                a = np.zeros(len(pix))
                a[idx[i + di, j + dj]], a[idx[i, j]] = 1.0, -1.0
                rows.append(a)
                rhs.append(0.5 * float(g[i, j] + g[i + di, j + dj]))
    rows.append(np.ones(len(pix)))  # zero mean
    rhs.append(0.0)
    sol = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    out = np.full((h, w), np.nan)
    for k, (i, j) in enumerate(pix):
        out[i, j] = sol[k]
    return torch.from_numpy(out)


@pytest.mark.parametrize("solver", SOLVERS)
def test_poisson_is_the_least_squares_minimiser(solver):
    g = torch.Generator().manual_seed(0)
    n = torch.randn(9, 11, 3, generator=g, dtype=torch.float64)
    n[..., 2] = n[..., 2].abs() + 0.5  # random, non-integrable normals
    m = torch.rand(9, 11, generator=g) > 0.25
    m[4, :] = True  # keep it mostly connected
    lab, k = connected_components(m)
    keep = lab == torch.bincount(lab[m]).argmax()
    z = integrate_normals(n, keep, solver=solver, tol=1e-12)
    ref = _dense_lstsq(n, keep)
    assert float((z - ref)[keep].abs().max()) < 1e-8


def test_disconnected_parts_are_zero_mean_each():
    z_true, n, _ = _wavy()
    r, c = _grid(*z_true.shape)
    m = ((c < 30) | (c > 45)) & (r > 5) & (r < 55)  # two slabs
    m[30, 60] = True
    m[30, 61] = False
    lab, k = connected_components(m)
    z = integrate_normals(n, m)
    assert k == 2
    for part in (1, 2):
        sel = lab == part
        assert abs(float(z[sel].mean())) < 1e-9
        assert float(_aligned_error(z, z_true, sel).abs().max()) < 0.05


def test_diagonal_contact_does_not_connect():
    m = torch.zeros(4, 4, dtype=torch.bool)
    m[:2, :2] = True
    m[2:, 2:] = True
    lab, k = connected_components(m)
    assert k == 2 and int(lab[0, 0]) != int(lab[3, 3])


def _crack():
    """A tilted quarter that tears away from a flat sheet along a crack: the jump grows from 0 to 20 px."""
    h, w, s, r0, c0 = 48, 64, 0.5, 24, 24
    r, c = _grid(h, w)
    up = (r < r0) & (c >= c0)
    z = torch.where(up, s * (c - c0), torch.zeros_like(c))
    n = _normals_from_slopes(torch.where(up, torch.full_like(c, s), torch.zeros_like(c)), torch.zeros_like(c))
    m = torch.ones(h, w, dtype=torch.bool) & (((r - 36) ** 2 + (c - 12) ** 2) >= 25)  # with a hole
    return z, n, m


@pytest.mark.slow
@pytest.mark.parametrize("solver", SOLVERS)
def test_bilateral_keeps_a_depth_jump(solver):
    z_true, n, m = _crack()
    e_p = _aligned_error(integrate_normals(n, m, "poisson", solver=solver), z_true, m)
    e_b = _aligned_error(integrate_normals(n, m, "bilateral", solver=solver, k=4.0), z_true, m)
    e_b2 = _aligned_error(integrate_normals(n, m, "bilateral", solver=solver), z_true, m)  # authors' k = 2
    rms = lambda e: float(e.pow(2).mean().sqrt())  # noqa: E731
    assert rms(e_p) > 3  # least squares spreads the jump over the whole surface
    assert rms(e_b) < 0.15 and float(e_b.abs().max()) < 0.4
    assert rms(e_b2) < rms(e_p) / 8


@pytest.mark.parametrize("method", ["poisson", "bilateral"])
def test_bilateral_equals_truth_without_jumps(method):
    z_true, n, m = _wavy(40, 48)
    e = _aligned_error(integrate_normals(n, m, method), z_true, m)
    assert float(e.abs().max()) < 0.1


def test_dtype_device_batch_and_fill():
    z_true, n, m = _wavy(30, 40)
    z32 = integrate_normals(n.float(), m, fill=0.0)
    assert z32.dtype == torch.float32 and bool((z32[~m] == 0).all())
    zb = integrate_normals(torch.stack([n, n.flip(-2) * torch.tensor([-1.0, 1, 1], dtype=n.dtype)]), m.flip(-1) & m)
    assert zb.shape == (2, 30, 40)
    single = integrate_normals(n, m.flip(-1) & m)
    assert torch.allclose(zb[0], single, equal_nan=True)
    # NaN outside the mask is fine (typical solver output)
    n_nan = n.clone()
    n_nan[~m] = float("nan")
    assert torch.allclose(integrate_normals(n_nan, m), integrate_normals(n, m), equal_nan=True)


def test_empty_mask_and_single_pixel_parts():
    n = torch.zeros(5, 6, 3, dtype=torch.float64)
    n[..., 2] = 1
    z = integrate_normals(n, torch.zeros(5, 6, dtype=torch.bool))
    assert bool(z.isnan().all())
    m = torch.zeros(5, 6, dtype=torch.bool)
    m[1, 1] = m[3, 4] = True
    z = integrate_normals(n, m, solver="torch")
    assert float(z[1, 1]) == 0.0 and float(z[3, 4]) == 0.0


def test_bad_input():
    n, m = sphere_normals(16, dtype=torch.float64)
    with pytest.raises(ValueError, match="method"):
        integrate_normals(n, m, method="fourier")
    with pytest.raises(ValueError, match="solver"):
        integrate_normals(n, m, solver="cuda")
    with pytest.raises(ValueError, match="mask"):
        integrate_normals(n, m[:8])
    with pytest.raises(TypeError, match="mask"):
        integrate_normals(n, m.double())
    with pytest.raises(ValueError, match="normals"):
        integrate_normals(n[..., :2], m)
    bad = n.clone()
    bad[8, 8, 0] = float("nan")
    with pytest.raises(ValueError, match="inside `mask`"):
        integrate_normals(bad, m)
    with pytest.raises(ValueError, match="tol"):
        integrate_normals(n, m, tol=0)


def test_depth_to_normals_inverts_slopes():
    r, c = _grid(12, 14)
    z = 0.05 * (c - 6) ** 2 - 0.03 * r * c + 0.4 * r  # quadratic: central differences are exact
    dzc, dzr = 0.1 * (c - 6) - 0.03 * r, -0.03 * c + 0.4
    m = torch.ones(12, 14, dtype=torch.bool)
    n = depth_to_normals(z, m)
    ref = _normals_from_slopes(dzc, dzr)
    assert torch.allclose(n[1:-1, 1:-1], ref[1:-1, 1:-1], atol=1e-12)
    gc, gr = normals_to_slopes(n[1:-1, 1:-1])
    assert torch.allclose(gc, dzc[1:-1, 1:-1]) and torch.allclose(gr, dzr[1:-1, 1:-1])
    # values outside the mask are never read
    m2 = m.clone()
    m2[:, 7] = False
    z2 = z.clone()
    z2[:, 7] = float("nan")
    n2 = depth_to_normals(z2, m2)
    assert bool(torch.isfinite(n2).all()) and bool((n2[:, 7] == 0).all())


@pytest.mark.slow
def test_megapixel_plane_int64_indices():
    """1024 x 1024 (a million unknowns): a tilted plane is integrated exactly (trapezoid rule)."""
    h = w = 1024
    n = torch.empty(h, w, 3, dtype=torch.float32)
    n[..., 0], n[..., 1], n[..., 2] = -0.3, 0.2, 1.0
    m = torch.ones(h, w, dtype=torch.bool)
    m[100:200, 300:700] = False
    z, info = integrate_normals(n, m, return_info=True)
    r, c = _grid(h, w)
    e = _aligned_error(z.double(), 0.3 * c + 0.2 * r, m)
    assert float(e.abs().max()) < 1e-2 and info["residual"] < 1e-6
