"""The cast-shadow loop of the HSH solver (torch_hsh.ps.shadows)."""
from types import SimpleNamespace

import pytest
import torch

from torch_hsh import ps, scenes
from torch_hsh.ps.shadows import shadow_loop


def _scene(S=48):
    hgt = scenes.bumpy_heightfield(S, n_bumps=8, seed=1, smoothness=0.12, dtype=torch.float64) * 1.6
    n = scenes.heightfield_normals(hgt)
    l = scenes.cone_lights(24, 65.0, seed=2, dtype=torch.float64)
    vis = scenes.cast_shadow_mask(hgt, l)
    img = torch.rand(24, S, S, 3, dtype=torch.float64)
    return img, l, n, vis


def test_loop_excludes_the_cast_shadows_of_the_integrated_surface_and_stops_at_the_fixed_point():
    img, l, n, vis = _scene()
    mask = torch.ones(n.shape[:2], dtype=torch.bool)
    calls = []

    def solve(images, lights, mask=None, valid=None, init=None, **kw):  # an oracle solver: the true normals
        calls.append(valid)
        return SimpleNamespace(normals=n.clone(), mask=mask, info={})

    res = shadow_loop(solve, img, l, mask, None, 3, 0.25, None)
    assert calls[0] is None and len(calls) == 2  # one re-solve, then the occlusion set no longer changes
    v = calls[1]
    agree = float((v == vis).double().mean())
    found = float((~v & ~vis).sum()) / max(int((~vis).sum()), 1)
    assert agree > 0.97 and found > 0.6, (agree, found)
    assert res.info["shadow_rounds"] == 1.0
    assert res.info["shadowed_fraction"] == pytest.approx(float((~v).double().mean()))


def test_loop_keeps_the_callers_exclusions():
    img, l, n, _ = _scene(32)
    mask = torch.ones(n.shape[:2], dtype=torch.bool)
    given = torch.ones(img.shape[:3], dtype=torch.bool)
    given[0] = False
    seen = []

    def solve(images, lights, mask=None, valid=None, init=None, **kw):
        seen.append(valid)
        return SimpleNamespace(normals=n.clone(), mask=mask, info={})

    shadow_loop(solve, img, l, mask, given, 1, 0.25, None)
    assert not bool(seen[-1][0].any())


def test_loop_keeps_the_first_solves_basis_brdfs():
    img, l, n, _ = _scene(32)
    mask = torch.ones(n.shape[:2], dtype=torch.bool)
    B = torch.nn.functional.normalize(torch.randn(2, 20, dtype=torch.float64), dim=-1)
    kws = []

    def solve(images, lights, mask=None, valid=None, init=None, **kw):
        kws.append(kw)
        return SimpleNamespace(normals=n.clone(), mask=mask, info={"robust_scale": 0.25}, basis_brdfs=B)

    shadow_loop(solve, img, l, mask, None, 1, 0.25, None, order=3)
    assert "basis" not in kws[0]
    assert kws[1]["basis"] is B and kws[1]["robust_scale"] == 0.25 and kws[1]["order"] == 3


def test_loop_reports_the_first_calibration_and_keeps_its_number_of_materials():
    img, l, n, _ = _scene(32)
    mask = torch.ones(n.shape[:2], dtype=torch.bool)
    B = torch.nn.functional.normalize(torch.randn(3, 20, dtype=torch.float64), dim=-1)
    kws = []
    first = {"robust_scale": 0.25, "calibration_start": 1.0, "calibration_pixels": 2048.0, "basis_ridge": 3e-3,
             "materials_chosen": 3.0}

    def solve(images, lights, mask=None, valid=None, init=None, **kw):
        kws.append(kw)
        info = dict(first) if len(kws) == 1 else {"robust_scale": 0.25, "basis_given": 1.0, "calibration_pixels": 0.0}
        return SimpleNamespace(normals=n.clone(), mask=mask, info=info, basis_brdfs=B)

    res = shadow_loop(solve, img, l, mask, None, 1, 0.25, None, materials="auto", basis_ridge=3e-3)
    assert kws[0]["materials"] == "auto" and kws[1]["materials"] == 3  # "auto" resolved by the first solve
    assert kws[1]["basis_ridge"] == 3e-3
    for k in ("calibration_start", "calibration_pixels", "basis_ridge", "materials_chosen"):
        assert res.info[k] == first[k], k
    assert "basis_given" not in res.info and res.info["shadow_rounds"] == 1.0


def test_cast_shadows_arguments_are_checked():
    img, l, _, _ = _scene(16)
    with pytest.raises(ValueError, match="cast_shadows"):
        ps.solve_hsh(img.reshape(24, -1, 3), l, cast_shadows=1)
    with pytest.raises(ValueError, match="cast_shadows"):
        ps.solve_hsh(img, l, cast_shadows=-1)
    with pytest.raises(ValueError, match="shadow_bias"):
        ps.solve_hsh(img, l, cast_shadows=1, shadow_bias=-1.0)


@pytest.mark.slow
def test_solve_hsh_with_cast_shadows_runs_end_to_end():
    img, l, n, vis = _scene(24)
    from torch_hsh.brdf import Lambertian
    from torch_hsh.render import render

    img = render(n, l, Lambertian(torch.full((24, 24, 3), 0.6, dtype=torch.float64)), visibility=vis, ambient=0.3)
    r = ps.solve_hsh(img.float(), l.float(), cast_shadows=1, calibration_pixels=256, calibration_rounds=3, max_iter=3)
    assert "shadow_rounds" in r.info and 0 <= r.info["shadowed_fraction"] < 1
    assert bool(torch.isfinite(r.normals).all())


def test_cast_shadows_with_automatic_materials_and_a_basis_ridge():
    img, l, n, vis = _scene(16)
    from torch_hsh.brdf import Lambertian
    from torch_hsh.render import render

    img = render(n, l, Lambertian(torch.full((16, 16, 3), 0.6, dtype=torch.float64)), visibility=vis, ambient=0.3)
    r = ps.solve_hsh(img.float(), l.float(), cast_shadows=1, materials="auto", basis_ridge=1e-2,
                     calibration_pixels=128, calibration_rounds=2, max_iter=2, refinement_passes=1)
    assert r.info["basis_ridge"] == 1e-2 and "materials_chosen" in r.info
    assert r.basis_brdfs.shape[0] == r.info["materials_chosen"]
    assert bool(torch.isfinite(r.normals).all())
