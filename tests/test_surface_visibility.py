"""Tests for torch_hsh.surface.visibility (cast shadows of a depth map)."""
import math

import pytest
import torch

from torch_hsh.render.scenes import bumpy_heightfield, diligent_like_lights, heightfield_normals
from torch_hsh.render.visibility import cast_shadow_mask
from torch_hsh.surface import integrate_normals, light_visibility


def _light(elev_deg, azim_deg=0.0):
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    return [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]


def test_wall_shadow_length():
    z = torch.zeros(20, 60, dtype=torch.float64)
    z[:, 40:] = 10.0
    m = torch.ones(20, 60, dtype=torch.bool)
    lights = torch.tensor([_light(30.0), _light(30.0, 180.0), [0.0, 0.0, 1.0]], dtype=torch.float64)
    vis = light_visibility(z, m, lights)
    assert vis.shape == (3, 20, 60) and vis.dtype == torch.bool
    length = 10.0 / math.tan(math.radians(30.0))  # 17.3 px in front of the wall at col 40
    row = vis[0, 10]
    assert not bool(row[int(40 - length) + 1 : 40].any()) and bool(row[: int(40 - length) - 1].all())
    assert bool(row[40:].all())  # the top of the wall is lit
    assert bool(vis[1].all()) and bool(vis[2].all())  # light from the other side, overhead light


def test_only_the_mask_occludes_and_nan_outside():
    z = torch.zeros(20, 60, dtype=torch.float64)
    z[:, 40:] = 10.0
    lights = torch.tensor([_light(30.0)], dtype=torch.float64)
    m = torch.ones(20, 60, dtype=torch.bool)
    m[:, 40:] = False  # the wall is not part of the surface
    zn = z.clone()
    zn[~m] = float("nan")
    vis = light_visibility(zn, m, lights)
    assert bool(vis.all())  # nothing outside the mask occludes; outside pixels report True
    m2 = torch.ones(20, 60, dtype=torch.bool)
    m2[:, :5] = False
    assert torch.equal(light_visibility(z, m2, lights)[:, m2], light_visibility(z, None, lights)[:, m2])


def test_matches_cast_shadow_mask_and_chunking():
    hgt = bumpy_heightfield(40, n_bumps=8, seed=1, dtype=torch.float64)
    lights = diligent_like_lights(20, dtype=torch.float64, max_polar_deg=70.0)
    full = light_visibility(hgt, torch.ones(40, 40, dtype=torch.bool), lights, chunk_size=3)
    assert torch.equal(full, cast_shadow_mask(hgt, lights))
    assert torch.equal(full, light_visibility(hgt, None, lights, chunk_size=100))
    assert int((~full).sum()) > 100  # the test scene does have cast shadows
    fewer = light_visibility(hgt, None, lights, bias=0.5)
    assert bool((fewer | ~full).all()) and int((~fewer).sum()) < int((~full).sum())


def test_below_horizon_and_errors():
    z = torch.zeros(6, 7)
    m = torch.zeros(6, 7, dtype=torch.bool)
    m[2:4, 2:5] = True
    vis = light_visibility(z, m, torch.tensor([[0.6, 0.0, -0.8]]))
    assert not bool(vis[0][m].any()) and bool(vis[0][~m].all())
    with pytest.raises(ValueError, match="lights"):
        light_visibility(z, m, torch.tensor([0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="chunk"):
        light_visibility(z, m, torch.tensor([[0.0, 0.0, 1.0]]), chunk_size=0)
    with pytest.raises(ValueError, match="bias"):
        light_visibility(z, m, torch.tensor([[0.0, 0.0, 1.0]]), bias=-0.1)
    bad = z.clone()
    bad[3, 3] = float("nan")
    with pytest.raises(ValueError, match="inside `mask`"):
        light_visibility(bad, m, torch.tensor([[0.0, 0.0, 1.0]]))


def test_visibility_of_an_integrated_surface():
    """The loop the solver runs: normals -> depth -> visibility, against the true height field."""
    hgt = bumpy_heightfield(64, n_bumps=10, seed=3, dtype=torch.float64)
    n = heightfield_normals(hgt)
    m = torch.ones(64, 64, dtype=torch.bool)
    lights = diligent_like_lights(24, dtype=torch.float64, max_polar_deg=65.0)
    true_vis = light_visibility(hgt, m, lights)
    z = integrate_normals(n, m)
    est_vis = light_visibility(z, m, lights)
    agree = float((true_vis == est_vis).double().mean())
    shadowed = ~true_vis
    recall = float((~est_vis & shadowed).sum() / shadowed.sum())
    assert int(shadowed.sum()) > 500
    assert agree > 0.995 and recall > 0.9
    # most of these shadows are grazing; the ones an occluder covers by half a pixel or more are
    # all still found with a small bias against depth noise
    deep = ~light_visibility(hgt, m, lights, bias=0.5)
    assert int(deep.sum()) > 300
    assert bool((~light_visibility(z, m, lights, bias=0.1))[deep].all())
