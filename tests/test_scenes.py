"""Tests for torch_hsh.render.scenes (synthetic geometry, materials, lights, cast shadows)."""
import math

import numpy as np
import pytest
import scipy.ndimage
import torch

from torch_hsh.render.scenes import (
    TEXTURE_SOURCES,
    albedo_texture,
    bumpy_heightfield,
    cone_lights,
    demo_scene,
    diligent_like_lights,
    heightfield_normals,
    light_intensities,
    material_regions,
    sphere_normals,
    srgb_to_linear,
)
from torch_hsh.render.visibility import cast_shadow_mask


def _grid(h, w, dtype=torch.float64):
    return torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")


# --------------------------------------------------------------------------- #
# sphere
# --------------------------------------------------------------------------- #
def test_sphere_normals_geometry():
    n, m = sphere_normals((40, 50), radius=0.8, dtype=torch.float64)
    assert n.shape == (40, 50, 3) and m.shape == (40, 50) and m.dtype == torch.bool
    assert torch.allclose(n[m].norm(dim=-1), torch.ones(()).double())
    assert bool((n[~m] == 0).all()) and bool((n[m][:, 2] > 0).all())
    r = 0.8 * 40 / 2
    assert abs(int(m.sum()) - math.pi * r * r) < 0.03 * math.pi * r * r
    # frame: right half has n_x > 0, top half (small rows) has n_y > 0
    rows, cols = _grid(40, 50)
    assert bool((n[..., 0][m & (cols > 25)] > 0).all()) and bool((n[..., 0][m & (cols < 24)] < 0).all())
    assert bool((n[..., 1][m & (rows < 19)] > 0).all()) and bool((n[..., 1][m & (rows > 20)] < 0).all())
    # explicit pixel: centre offset (x, y) = (col + .5 - 25, -(row + .5 - 20)) / r
    x, y = (30 + 0.5 - 25) / r, -(10 + 0.5 - 20) / r
    assert torch.allclose(n[10, 30], torch.tensor([x, y, math.sqrt(1 - x * x - y * y)], dtype=torch.float64))


def test_sphere_normals_match_heightfield_normals():
    size, radius = 64, 0.9
    n, m = sphere_normals(size, radius=radius, dtype=torch.float64)
    r = radius * size / 2
    rows, cols = _grid(size, size)
    x, y = cols + 0.5 - size / 2, -(rows + 0.5 - size / 2)
    h = torch.sqrt(torch.clamp(r * r - x * x - y * y, min=0))
    nh = heightfield_normals(h)
    inner = (x * x + y * y) < (0.7 * r) ** 2
    ang = torch.rad2deg(torch.acos((n * nh).sum(-1).clamp(-1, 1)))[inner]
    assert float(ang.max()) < 0.5  # both in the same frame (a sign error would give tens of degrees)


def test_sphere_errors():
    with pytest.raises(ValueError, match="radius"):
        sphere_normals(8, radius=1.5)
    with pytest.raises(TypeError, match="size"):
        sphere_normals(8.0)
    with pytest.raises(ValueError, match="size"):
        sphere_normals((8, 0))
    with pytest.raises(TypeError, match="dtype"):
        sphere_normals(8, dtype=torch.int64)


# --------------------------------------------------------------------------- #
# height fields
# --------------------------------------------------------------------------- #
def test_heightfield_normals_tilted_plane_sign_everywhere():
    rows, cols = _grid(9, 11)
    # x = col, y = -row: h = 0.3 x + 0.5 y
    h = 0.3 * cols - 0.5 * rows
    n = heightfield_normals(h)
    expected = torch.tensor([-0.3, -0.5, 1.0], dtype=torch.float64)
    expected = expected / expected.norm()
    assert torch.allclose(n, expected.expand_as(n), atol=1e-12)  # borders included
    # a surface higher at the top of the picture (rising toward +y) faces down (-y)
    n_up = heightfield_normals(-rows)
    assert bool((n_up[..., 1] < 0).all())


def test_heightfield_normals_paraboloid_and_pixel_size():
    ps = 0.5
    rows, cols = _grid(16, 20)
    x, y = (cols - 9.3) * ps, -(rows - 7.1) * ps
    c = 0.2
    h = c * (x * x + 2 * y * y) + 0.1 * x * y
    n = heightfield_normals(h, pixel_size=ps)
    gx, gy = 2 * c * x + 0.1 * y, 4 * c * y + 0.1 * x
    ref = torch.stack([-gx, -gy, torch.ones_like(gx)], -1)
    ref = ref / ref.norm(dim=-1, keepdim=True)
    assert torch.allclose(n[1:-1, 1:-1], ref[1:-1, 1:-1], atol=1e-12)  # Sobel is exact on quadratics
    assert torch.allclose(n, ref, atol=0.05)  # border: extrapolated, still close


def test_heightfield_normals_batch_dtype_grad():
    h = bumpy_heightfield((12, 10), n_bumps=4, seed=1, dtype=torch.float64)
    hb = torch.stack([h, 2 * h, -h]).reshape(3, 1, 12, 10).requires_grad_(True)
    n = heightfield_normals(hb)
    assert n.shape == (3, 1, 12, 10, 3) and n.dtype == torch.float64
    assert torch.allclose(n[0, 0], heightfield_normals(h))
    n.sum().backward()
    assert hb.grad is not None and bool(torch.isfinite(hb.grad).all())
    assert heightfield_normals(h.float()).dtype == torch.float32
    with pytest.raises(ValueError, match="2x2"):
        heightfield_normals(torch.zeros(1, 5))
    with pytest.raises(ValueError, match="at least 2"):
        heightfield_normals(torch.zeros(5))
    with pytest.raises(ValueError, match="pixel_size"):
        heightfield_normals(h, pixel_size=0.0)


def test_bumpy_heightfield_seed_and_smoothness():
    a = bumpy_heightfield((32, 40), n_bumps=10, seed=3)
    assert a.shape == (32, 40) and a.dtype == torch.float32
    assert torch.equal(a, bumpy_heightfield((32, 40), n_bumps=10, seed=3))
    assert torch.equal(a, bumpy_heightfield((32, 40), n_bumps=10, seed=torch.Generator().manual_seed(3)))
    assert not torch.equal(a, bumpy_heightfield((32, 40), n_bumps=10, seed=4))
    assert float(a.abs().max()) > 0.5
    assert torch.equal(bumpy_heightfield(8, n_bumps=0, seed=0), torch.zeros(8, 8))
    # smoother fields have smaller curvature relative to their amplitude
    def rough(s):
        h = bumpy_heightfield(64, n_bumps=12, seed=0, smoothness=s, dtype=torch.float64)
        lap = h[2:, 1:-1] + h[:-2, 1:-1] + h[1:-1, 2:] + h[1:-1, :-2] - 4 * h[1:-1, 1:-1]
        return float(lap.abs().max() / h.abs().max())

    assert rough(0.2) < rough(0.05) < 0.5
    with pytest.raises(ValueError, match="smoothness"):
        bumpy_heightfield(8, smoothness=-1.0)
    with pytest.raises(TypeError, match="seed"):
        bumpy_heightfield(8, seed="x")


# --------------------------------------------------------------------------- #
# materials / textures
# --------------------------------------------------------------------------- #
def test_material_regions_voronoi():
    lab = material_regions((30, 40), n_regions=7, seed=2, warp=0.0)
    assert lab.shape == (30, 40) and lab.dtype == torch.int64
    assert sorted(lab.unique().tolist()) == list(range(7))
    # plain Voronoi cells are convex, hence connected
    for k in range(7):
        _, ncomp = scipy.ndimage.label((lab == k).numpy())
        assert ncomp == 1
    assert torch.equal(lab, material_regions((30, 40), n_regions=7, seed=2, warp=0.0))


def test_material_regions_warped():
    lab = material_regions(48, n_regions=5, seed=0, warp=0.1)
    assert sorted(lab.unique().tolist()) == list(range(5))
    assert not torch.equal(lab, material_regions(48, n_regions=5, seed=0, warp=0.0))
    # regions are large smooth blobs: few label changes between neighbours
    changes = (lab[1:] != lab[:-1]).sum() + (lab[:, 1:] != lab[:, :-1]).sum()
    assert int(changes) < 0.15 * 2 * 48 * 48
    assert torch.equal(material_regions(4, n_regions=16, seed=1).flatten().sort().values, torch.arange(16))
    with pytest.raises(ValueError, match="n_regions"):
        material_regions(4, n_regions=17)
    with pytest.raises(ValueError, match="warp"):
        material_regions(4, n_regions=2, warp=-1.0)


def test_srgb_to_linear_values():
    x = torch.tensor([0.0, 0.04045, 0.5, 1.0], dtype=torch.float64)
    y = srgb_to_linear(x)
    assert torch.allclose(y, torch.tensor([0.0, 0.04045 / 12.92, ((0.555) / 1.055) ** 2.4, 1.0], dtype=torch.float64))
    assert abs(float(y[2]) - 0.214041) < 1e-6
    eps = 1e-9
    lo, hi = srgb_to_linear(torch.tensor([0.04045 - eps, 0.04045 + eps], dtype=torch.float64))
    assert abs(float(hi - lo)) < 1e-8  # continuous at the knee


def test_albedo_texture_matches_manual_pipeline():
    import skimage.data
    import skimage.transform

    tex = albedo_texture((40, 60), source="coffee", dtype=torch.float64)  # coffee is 400 x 600: no crop
    img = skimage.data.coffee() / 255.0
    ref = skimage.transform.resize(img, (40, 60, 3), order=1, anti_aliasing=True, mode="reflect")
    ref = torch.as_tensor(np.clip(ref, 0, 1))
    assert torch.allclose(tex, srgb_to_linear(ref))
    assert float(tex.mean()) < float(ref.mean())  # linearisation darkens mid-tones


def test_albedo_texture_sources_and_seed():
    a = albedo_texture(16, seed=5, source="astronaut")
    assert a.shape == (16, 16, 3) and a.dtype == torch.float32
    assert float(a.min()) >= 0 and float(a.max()) <= 1
    assert torch.equal(a, albedo_texture(16, seed=5, source="astronaut"))
    assert not torch.equal(a, albedo_texture(16, seed=6, source="astronaut"))
    g = albedo_texture((8, 12), source="brick")  # grey picture: equal channels
    assert torch.equal(g[..., 0], g[..., 1]) and torch.equal(g[..., 1], g[..., 2])
    assert "astronaut" in TEXTURE_SOURCES and "coffee" in TEXTURE_SOURCES
    with pytest.raises(ValueError, match="source"):
        albedo_texture(8, source="nonexistent")


# --------------------------------------------------------------------------- #
# lights
# --------------------------------------------------------------------------- #
def test_diligent_like_lights_layout():
    L = diligent_like_lights(96, dtype=torch.float64)
    assert L.shape == (96, 3)
    assert torch.allclose(L.norm(dim=-1), torch.ones(96, dtype=torch.float64))
    assert bool((L[:, 2] > 0).all())
    polar = torch.rad2deg(torch.acos(L[:, 2]))
    assert abs(float(polar.max()) - 55.0) < 1e-9 and float(polar.min()) > 3.0
    u, v = L[:, 0] / L[:, 2], L[:, 1] / L[:, 2]  # positions on the plane z = 1
    assert len(torch.unique(v.round(decimals=9))) == 8 and len(torch.unique(u.round(decimals=9))) == 12
    assert float(L[0, 0]) < 0 and float(L[0, 1]) > 0  # starts top-left
    jit = diligent_like_lights(96, seed=0, dtype=torch.float64)
    assert not torch.equal(jit, L) and torch.equal(jit, diligent_like_lights(96, seed=0, dtype=torch.float64))
    assert float(torch.rad2deg(torch.acos(jit[:, 2])).max()) <= 55.0 + 1e-9
    assert diligent_like_lights(10).shape == (10, 3)
    assert torch.allclose(diligent_like_lights(1), torch.tensor([[0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="max_polar_deg"):
        diligent_like_lights(8, max_polar_deg=95.0)
    with pytest.raises(ValueError, match="`n`"):
        diligent_like_lights(0)


def test_cone_lights_uniform_on_cap():
    ang = 40.0
    L = cone_lights(20000, ang, seed=0, dtype=torch.float64)
    cmin = math.cos(math.radians(ang))
    assert torch.allclose(L.norm(dim=-1), torch.ones(20000, dtype=torch.float64))
    assert float(L[:, 2].min()) >= cmin - 1e-12
    # uniform on the cap: z ~ U(cos max, 1) (mean and variance), azimuth symmetric
    z = L[:, 2]
    assert abs(float(z.mean()) - (1 + cmin) / 2) < 0.005
    assert abs(float(z.var()) - (1 - cmin) ** 2 / 12) < 0.0005
    assert abs(float(L[:, 0].mean())) < 0.01 and abs(float(L[:, 1].mean())) < 0.01
    full = cone_lights(20000, 180.0, seed=1)
    assert abs(float(full[:, 2].mean())) < 0.02
    assert torch.equal(cone_lights(5, 30.0, seed=2), cone_lights(5, 30.0, seed=2))
    with pytest.raises(ValueError, match="max_angle_deg"):
        cone_lights(5, 0.0)


def test_light_intensities():
    I = light_intensities(500, seed=0, variation=0.3, dtype=torch.float64)
    assert I.shape == (500, 3)
    assert float(I.min()) >= 0.7 and float(I.max()) <= 1.3
    assert float(I.min()) < 0.72 and float(I.max()) > 1.28  # spans the range
    assert torch.equal(light_intensities(4, seed=1, variation=0.0), torch.ones(4, 3))
    with pytest.raises(ValueError, match="variation"):
        light_intensities(4, variation=1.0)


# --------------------------------------------------------------------------- #
# cast shadows
# --------------------------------------------------------------------------- #
def _box(h=40, w=40, height=10.0):
    hgt = torch.zeros(h, w, dtype=torch.float64)
    hgt[15:25, 15:25] = height
    return hgt


def test_cast_shadow_box_directions():
    hgt = _box()
    s = math.sqrt(0.5)
    lights = torch.tensor(
        [[s, 0.0, s], [-s, 0.0, s], [0.0, s, s], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]],
        dtype=torch.float64,
    )
    vis = cast_shadow_mask(hgt, lights)
    assert vis.shape == (6, 40, 40) and vis.dtype == torch.bool
    # light from +x (right) at 45 degrees: shadow of length ~10 on the left of the box
    assert not bool(vis[0, 15:25, 6:15].any())
    assert bool(vis[0, 15:25, :4].all()) and bool(vis[0, :, 25:].all())
    assert bool(vis[0, 15:25, 15:25].all())  # box top lit
    assert bool(vis[0, :14].all()) and bool(vis[0, 26:].all())  # nothing above / below the box band
    # light from -x: mirrored
    assert not bool(vis[1, 15:25, 25:34].any()) and bool(vis[1, :, :15].all())
    # light from +y (up, i.e. toward row 0): the shadow falls below the box (larger rows)
    assert not bool(vis[2, 25:34, 15:25].any()) and bool(vis[2, :15].all())
    assert bool(vis[3].all())  # overhead light: nothing shadowed
    assert not bool(vis[4].any()) and not bool(vis[5].any())  # below / at the horizon


def test_cast_shadow_length_and_pixel_size():
    hgt = _box(height=8.0)
    elev = math.radians(30.0)  # shadow length = 8 / tan(30) = 13.86 length units
    light = torch.tensor([[math.cos(elev), 0.0, math.sin(elev)]], dtype=torch.float64)
    row = cast_shadow_mask(hgt, light)[0, 20]
    shadow = (~row).nonzero().flatten()
    assert int(shadow.max()) == 14 and int(shadow.min()) == 15 - 13  # cols 2..14
    row2 = cast_shadow_mask(hgt, light, pixel_size=2.0)[0, 20]  # pixels twice as large: half as many
    assert int((~row2).sum()) == 6  # floor(13.86 / 2)
    capped = cast_shadow_mask(hgt, light, n_steps=3)[0, 20]
    assert int((~capped).sum()) == 3


def test_cast_shadow_smooth_surface_and_flat():
    hgt = bumpy_heightfield(32, n_bumps=6, seed=0, dtype=torch.float64)
    lights = diligent_like_lights(12, dtype=torch.float64)
    vis = cast_shadow_mask(hgt, lights)
    assert vis.shape == (12, 32, 32)
    assert 0.0 < 1 - float(vis.double().mean()) < 0.5
    # shadowed points of a smooth field mostly face away from the light or lie behind a bump; lit points
    # whose normal faces the light directly (n.l > 0.9) can never be occluded by their neighbourhood
    n = heightfield_normals(hgt)
    ndotl = torch.einsum("hwc,lc->lhw", n, lights)
    assert bool(vis[ndotl < -0.05].logical_not().all())
    assert bool(cast_shadow_mask(torch.zeros(8, 8), lights.float()).all())
    assert torch.equal(cast_shadow_mask(hgt.float(), lights.float()), vis)


def test_cast_shadow_errors():
    with pytest.raises(ValueError, match="height"):
        cast_shadow_mask(torch.zeros(2, 3, 4), torch.tensor([[0.0, 0, 1]]))
    with pytest.raises(ValueError, match="lights"):
        cast_shadow_mask(torch.zeros(4, 4), torch.tensor([0.0, 0, 1]))
    with pytest.raises(ValueError, match="zero vector"):
        cast_shadow_mask(torch.zeros(4, 4), torch.zeros(1, 3))
    with pytest.raises(TypeError, match="height"):
        cast_shadow_mask(np.zeros((4, 4)), torch.tensor([[0.0, 0, 1]]))


def test_cast_shadow_bias():
    hgt = _box(height=8.0)
    elev = math.radians(30.0)
    light = torch.tensor([[math.cos(elev), 0.0, math.sin(elev)]], dtype=torch.float64)
    assert torch.equal(cast_shadow_mask(hgt, light, bias=0.0), cast_shadow_mask(hgt, light))
    # an occluder must now rise 2 units above the ray: the shadow of the 8-high box is 6 / tan(30) = 10.4 long
    row = cast_shadow_mask(hgt, light, bias=2.0)[0, 20]
    assert int((~row[:15]).sum()) == 10
    assert bool(cast_shadow_mask(hgt, light, bias=8.5).all())
    with pytest.raises(ValueError, match="bias"):
        cast_shadow_mask(hgt, light, bias=-1.0)


# --------------------------------------------------------------------------- #
# the demo scene
# --------------------------------------------------------------------------- #
_DEMO_KEYS = {"images", "lights", "intensities", "mask", "normals_gt", "labels", "name", "height", "albedo",
              "visibility", "full_scale"}


@pytest.fixture(scope="module")
def demo32():
    return demo_scene(32, seed=0, dtype=torch.float64)


def test_demo_scene_shapes_and_dtypes(demo32):
    s = demo32
    assert set(s) == _DEMO_KEYS and isinstance(s["name"], str)
    assert s["images"].shape == (96, 32, 32, 3) and s["images"].dtype == torch.float64
    assert s["lights"].shape == (96, 3) and s["intensities"].shape == (96, 3)
    assert s["mask"].shape == (32, 32) and s["mask"].dtype == torch.bool
    assert s["normals_gt"].shape == (32, 32, 3) and s["height"].shape == (32, 32)
    assert s["labels"].dtype == torch.int64 and s["visibility"].shape == (96, 32, 32)
    assert torch.allclose(s["lights"].norm(dim=-1), torch.ones(96, dtype=torch.float64))
    assert float(s["intensities"].min()) >= 0.8 and float(s["intensities"].max()) <= 1.2
    m = s["mask"]
    assert bool((s["images"][:, ~m] == 0).all()) and bool((s["normals_gt"][~m] == 0).all())
    assert set(s["labels"][m].unique().tolist()) == {0, 1}  # both materials on the object
    f = demo_scene(16, n_lights=5, seed=0)  # float32 by default
    assert f["images"].dtype == torch.float32 and f["normals_gt"].dtype == torch.float32
    assert f["images"].shape == (5, 16, 16, 3) and f["labels"].dtype == torch.int64
    rect = demo_scene((12, 20), n_lights=4, seed=1)
    assert rect["images"].shape == (4, 12, 20, 3) and bool(rect["mask"].any())


def test_demo_scene_normals_match_height_field():
    s = demo_scene(128, n_lights=3, seed=0, dtype=torch.float64)  # large enough for finite differences
    n, m, hgt = s["normals_gt"], s["mask"], s["height"]
    assert torch.allclose(n[m].norm(dim=-1), torch.ones(int(m.sum()), dtype=torch.float64), atol=1e-12)
    assert bool((n[m][:, 2] > 0).all())
    # independent finite differences: central differences of the sampled heights (x right, y up)
    dz_dx = (hgt[1:-1, 2:] - hgt[1:-1, :-2]) / 2
    dz_dy = -(hgt[2:, 1:-1] - hgt[:-2, 1:-1]) / 2
    fd = torch.stack([-dz_dx, -dz_dy, torch.ones_like(dz_dx)], dim=-1)
    fd = fd / fd.norm(dim=-1, keepdim=True)
    # away from the rim (where the slope diverges) and with a margin of 2 pixels inside the mask
    inner = m.clone()
    for _ in range(2):
        inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
    inner &= n[..., 2] > 0.5
    sel = inner[1:-1, 1:-1]
    ang = torch.rad2deg(torch.acos((fd * n[1:-1, 1:-1]).sum(-1).clamp(-1, 1)))[sel]
    assert int(sel.sum()) > 5000
    assert float(ang.median()) < 0.3 and float(ang.max()) < 2.0
    # a wrong sign on either axis would be tens of degrees off; the library's Sobel normals agree too
    sob = heightfield_normals(hgt)
    ang2 = torch.rad2deg(torch.acos((sob * n).sum(-1).clamp(-1, 1)))[inner]
    assert float(ang2.quantile(0.95)) < 0.5
    # the field is a bumpy sphere: not a plain hemisphere, but close to it on average
    sph, _ = sphere_normals(128, radius=0.9, dtype=torch.float64)
    dev = torch.rad2deg(torch.acos((sph * n).sum(-1).clamp(-1, 1)))[inner]
    assert 3.0 < float(dev.mean()) < 25.0 and float(dev.max()) > 15.0


def test_demo_scene_cast_shadows_and_noise(demo32):
    clean = demo_scene(32, seed=0, dtype=torch.float64, relative_read_std=0.0, relative_shot_gain=0.0)
    s, m = demo32, demo32["mask"]
    assert torch.equal(clean["visibility"], s["visibility"]) and torch.equal(clean["normals_gt"], s["normals_gt"])
    ndl = torch.einsum("hwc,lc->lhw", s["normals_gt"], s["lights"])
    cast = (~s["visibility"]) & (ndl > 0.1) & m  # facing the light, yet occluded by a bump
    assert int(cast.sum()) > 0
    assert bool((clean["images"][cast] == 0).all())  # exactly shadowed in the noise-free images
    lit = s["visibility"] & (ndl > 0.1) & m
    assert bool((clean["images"][lit] > 0).all())
    # noise: read noise 1e-3 of full scale (values clipped at 0: E[max(0, e)^2] = sigma^2 / 2) ...
    F_ = s["full_scale"]
    dark = ((ndl <= 0) | ~s["visibility"]) & m
    read = float((2 * (s["images"][dark] ** 2).mean()).sqrt()) / F_
    assert 0.9e-3 < read < 1.1e-3
    # ... plus shot noise of variance 1e-4 * F * I
    bright = lit & (clean["images"].mean(-1) > 0.2 * F_)
    d = (s["images"] - clean["images"])[bright]
    z2 = d ** 2 / ((1e-3 * F_) ** 2 + 1e-4 * F_ * clean["images"][bright])
    assert d.numel() > 1000 and 0.93 < float(z2.mean()) < 1.07


def test_demo_scene_quantised_to_16_bits(demo32):
    s = demo32
    codes = s["images"] / s["full_scale"] * (2 ** 16 - 1)
    assert float((codes - codes.round()).abs().max()) < 1e-6
    assert float(s["images"].min()) >= 0 and float(s["images"].max()) <= s["full_scale"] * (1 + 1e-12)
    assert len(s["images"].unique()) > 5000  # 16-bit, not a handful of levels
    s8 = demo_scene(32, n_lights=8, seed=0, dtype=torch.float64, bits=8)
    assert len(s8["images"].unique()) <= 256


def test_demo_scene_seed_and_options(demo32):
    a = demo_scene(24, n_lights=6, seed=3)
    b = demo_scene(24, n_lights=6, seed=3)
    for k in _DEMO_KEYS - {"name", "full_scale"}:
        assert torch.equal(a[k], b[k]), k
    c = demo_scene(24, n_lights=6, seed=4)
    assert not torch.equal(a["images"], c["images"]) and not torch.equal(a["height"], c["height"])
    # min_nz leaves the grazing rim out of the mask, nothing else changes
    rim = demo_scene(32, seed=0, dtype=torch.float64, min_nz=0.3)
    full = demo32["mask"]
    assert bool((rim["mask"] <= full).all()) and int(rim["mask"].sum()) < int(full.sum())
    assert bool((rim["normals_gt"][rim["mask"]][:, 2] > 0.3).all())
    assert bool((demo32["normals_gt"][full & ~rim["mask"]][:, 2] <= 0.3).all())
    assert torch.equal(rim["images"][:, rim["mask"]], demo32["images"][:, rim["mask"]])


def test_demo_scene_errors():
    with pytest.raises(ValueError, match="size"):
        demo_scene(4)
    with pytest.raises(ValueError, match="n_lights"):
        demo_scene(16, n_lights=2)
    with pytest.raises(TypeError, match="seed"):
        demo_scene(16, seed=1.5)
    with pytest.raises(TypeError, match="dtype"):
        demo_scene(16, dtype=torch.int32)
    with pytest.raises(ValueError, match="min_nz"):
        demo_scene(16, min_nz=1.0)
    with pytest.raises(ValueError, match="relative_read_std"):
        demo_scene(16, relative_read_std=-1.0)
    with pytest.raises(ValueError, match="bits"):
        demo_scene(16, bits=40)
