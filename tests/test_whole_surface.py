"""The whole-surface stage of the HSH solver (torch_hsh.ps.whole_surface)."""
import dataclasses
import math

import pytest
import torch

from torch_hsh import ps

from torch_hsh.render import scenes
from torch_hsh.ps import Settings
from torch_hsh.ps import whole_surface as ws
from torch_hsh.surface import depth_to_normals


# --------------------------------------------------------------------------- #
# the depth side
# --------------------------------------------------------------------------- #
def test_dct_matrix_is_orthonormal():
    for n in (1, 2, 7, 16):
        D = ws._dct_matrix(n, torch.float64, "cpu")
        assert torch.allclose(D @ D.T, torch.eye(n, dtype=torch.float64), atol=1e-12)


def _bumps(S=24):
    z = scenes.bumpy_heightfield(S, n_bumps=5, seed=3, smoothness=0.2, dtype=torch.float64) * 3.0
    yy, xx = torch.meshgrid(torch.arange(S), torch.arange(S), indexing="ij")
    m = ((yy - S / 2 + 0.5) ** 2 + (xx - S / 2 + 0.5) ** 2) < (0.45 * S) ** 2
    return z, m


def test_depth_normals_with_even_weights_are_the_central_differences_of_depth_to_normals():
    z, m = _bumps()
    half = torch.full_like(z, 0.5)
    n = ws.depth_normals(z, m, (half, half))
    ref = depth_to_normals(z, m)  # central inside, one-sided at the mask edge
    assert torch.allclose(n[m], ref[m], atol=1e-12)


def test_depth_normals_see_a_jump_from_its_smooth_side():
    # a plane of slope 0.5 px/px with a 10 px step between columns 7 and 8
    S = 16
    col = torch.arange(S, dtype=torch.float64)
    z = (0.5 * col + 10.0 * (col >= 8)).expand(S, S).clone()
    m = torch.ones(S, S, dtype=torch.bool)
    w = ws.discontinuity_weights(z, m)
    n = ws.depth_normals(z, m, w)
    want = torch.nn.functional.normalize(torch.tensor([-0.5, 0.0, 1.0], dtype=torch.float64), dim=0)
    assert torch.allclose(n[:, 1:-1], want.expand(S, S - 2, 3), atol=1e-6)  # the jump's columns too
    central = ws.depth_normals(z, m, (torch.full_like(z, 0.5),) * 2)
    assert not torch.allclose(central[:, 7], want.expand(S, 3), atol=1e-2)  # what central differences would give


def test_depth_normals_gradcheck():
    z, m = _bumps(10)
    w = ws.discontinuity_weights(z, m)
    zz = z.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ws.depth_normals(t, m, w)[m], (zz,))


def test_depth_parameterisation_starts_at_the_integrated_normals():
    z, m = _bumps()
    n = depth_to_normals(z, m)
    dep = ws._Depth.start(n, m, torch.float64)
    zc = dep.depth(torch.zeros_like(dep.z0))
    assert torch.equal(zc, dep.z0)
    # the crop is the mask's bounding box, the rows follow the solver's pixel order (row-major in the mask)
    assert dep.m.shape == (int(m.any(1).sum()), int(m.any(0).sum()))
    assert torch.equal(dep.full(zc, m.shape)[m], zc.reshape(-1)[dep.rows])
    assert torch.isnan(dep.full(zc, m.shape)[~m]).all()


# --------------------------------------------------------------------------- #
# the stage on a rendered scene
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def demo():
    s = scenes.demo_scene(32, n_lights=24, seed=0, dtype=torch.float64)
    res = ps.solve_hsh(s["images"], s["lights"], s["intensities"], s["mask"], seed=0)
    return s, res


def _err(n, s):
    return float(ps.angular_error(n, s["normals_gt"].to(n), s["mask"])[s["mask"]].mean())


def test_noisy_start_normals_are_cleaned_by_the_depth(demo):
    # a start whose errors are random per pixel (not integrable): one surface removes most of them
    s, res = demo
    g = torch.Generator().manual_seed(0)
    noisy = s["normals_gt"].to(res.normals) + 0.15 * torch.randn(res.normals.shape, generator=g, dtype=res.normals.dtype)
    noisy = torch.nn.functional.normalize(noisy, dim=-1) * s["mask"].unsqueeze(-1)
    start = dataclasses.replace(res, normals=noisy)
    out = ps.refine_surface(start, s["images"], s["lights"], s["intensities"], surface_safeguard=False)
    assert out.info["surface_kept"] == 1.0
    assert out.info["surface_cost_after"] < 0.8 * out.info["surface_cost_before"]
    e0, e1 = _err(noisy, s), _err(out.normals, s)
    assert e1 < 0.6 * e0, (e0, e1)
    # the outputs are consistent maps
    m = s["mask"]
    assert torch.isfinite(out.depth[m]).all() and torch.isnan(out.depth[~m]).all()
    assert torch.allclose(out.normals[m].norm(dim=-1), torch.ones(int(m.sum()), dtype=out.normals.dtype))
    assert (out.normals[~m] == 0).all() and out.coefficients.shape == res.coefficients.shape
    assert torch.isfinite(out.coefficients).all() and torch.isfinite(out.albedo).all()
    assert out.mixing.shape == res.mixing.shape and torch.equal(out.basis_brdfs, res.basis_brdfs)
    relit = out.relight(s["lights"][:3], s["intensities"][:3])
    assert torch.isfinite(relit).all()


def test_the_polish_starts_from_the_depth_and_removes_its_grid_floor(demo):
    # surface_polish re-estimates each normal per pixel from the depth's normals; the depth is the same either way
    s, res = demo
    m = s["mask"]
    g = torch.Generator().manual_seed(0)
    noisy = s["normals_gt"].to(res.normals) + 0.15 * torch.randn(res.normals.shape, generator=g, dtype=res.normals.dtype)
    start = dataclasses.replace(res, normals=torch.nn.functional.normalize(noisy, dim=-1) * m.unsqueeze(-1))
    kw = dict(surface_safeguard=False)
    pol = ps.refine_surface(start, s["images"], s["lights"], s["intensities"], **kw)
    raw = ps.refine_surface(start, s["images"], s["lights"], s["intensities"], surface_polish=False, **kw)
    assert torch.equal(pol.depth[m], raw.depth[m])
    e_start, e_raw, e_pol, e_solve = _err(start.normals, s), _err(raw.normals, s), _err(pol.normals, s), _err(res.normals, s)
    # measured: 10.8 deg noisy start, 4.0 the depth's normals, 1.57 polished, 1.62 the per-pixel solve itself
    assert e_pol < 0.6 * e_raw and e_pol < 1.1 * e_solve, (e_start, e_raw, e_pol, e_solve)
    assert torch.allclose(pol.normals[m].norm(dim=-1), torch.ones(int(m.sum()), dtype=pol.normals.dtype))


def test_a_worse_surface_is_not_returned(demo, monkeypatch):
    s, res = demo
    real = ws._depth_step

    def ruin(data, dep, c, W, w, iters, wts):  # a depth step that wrecks the surface
        c, a, b = real(data, dep, c, W, w, 1, wts)
        g = torch.Generator().manual_seed(1)
        return c + 30.0 * torch.randn(c.shape, generator=g, dtype=c.dtype), a, b

    monkeypatch.setattr(ws, "_depth_step", ruin)
    out = ps.refine_surface(res, s["images"], s["lights"], s["intensities"], refine_surface=1)
    assert out.info["surface_accepted"] == 0.0
    assert out.info["surface_heldout_after"] > out.info["surface_heldout_before"]
    assert torch.equal(out.normals, res.normals) and torch.equal(out.coefficients, res.coefficients)
    assert out.depth is not None and torch.isfinite(out.depth[s["mask"]]).all()


def test_solve_hsh_runs_the_stage_and_the_result_keeps_the_depth(demo, tmp_path):
    s, res = demo
    out = ps.solve_hsh(s["images"], s["lights"], s["intensities"], s["mask"], seed=0, refine_surface=1,
                       surface_iterations=3)
    for k in ("surface_heldout_before", "surface_heldout_after", "surface_accepted", "surface_time_s",
              "surface_shadowed_fraction"):
        assert k in out.info and math.isfinite(out.info[k])
    assert out.info["surface_rounds"] == 1.0
    assert out.info["interreflection_rounds"] in (0.0, 1.0)  # one safeguarded round comes with the stage
    out.write(tmp_path / "r.npz")
    back = ps.HSHResult.read(tmp_path / "r.npz")
    assert torch.equal(back.depth.isnan(), out.depth.isnan())
    assert torch.equal(back.depth[s["mask"]], out.depth[s["mask"]])
    assert res.depth is None  # off by default


def test_without_shadows_nothing_is_shadowed(demo):
    s, res = demo
    out = ps.refine_surface(res, s["images"], s["lights"], s["intensities"], refine_surface=1, surface_iterations=2,
                            surface_shadows=False)
    assert math.isnan(out.info["surface_shadowed_fraction"])


def test_arguments_are_checked(demo):
    s, res = demo
    with pytest.raises(ValueError, match="refine_surface"):
        Settings(refine_surface=-1)
    with pytest.raises(ValueError, match="refine_surface"):
        Settings(refine_surface=1.5)
    assert Settings(refine_surface=True).refine_surface == ps.settings.SURFACE_ROUNDS
    # the interreflection round comes with the stage unless it is set
    assert Settings().interreflections == 0 and Settings(refine_surface=True).interreflections == 1
    assert Settings(refine_surface=True, interreflections=0).interreflections == 0
    assert Settings(interreflections=2).interreflections == 2
    assert Settings(refine_surface=False).refine_surface == 0
    with pytest.raises(ValueError, match="surface_iterations"):
        Settings(surface_iterations=0)
    with pytest.raises(ValueError, match="surface_holdout"):
        Settings(surface_holdout=0.7)
    with pytest.raises(ValueError, match="shared model"):
        ps.refine_surface(dataclasses.replace(res, basis_brdfs=None), s["images"], s["lights"])
    with pytest.raises(ValueError, match="`refine_surface` needs the shared model"):  # refused before any solve
        ps.solve_hsh(s["images"], s["lights"], None, s["mask"], materials=None, refine_surface=True)
    with pytest.raises(ValueError, match=r"default with `refine_surface`\) needs images of shape \(L, H, W, C\)"):
        ps.solve_hsh(s["images"].reshape(s["images"].shape[0], -1, 3), s["lights"], None, refine_surface=True)
    with pytest.raises(ValueError, match="images"):
        ps.refine_surface(res, s["images"].reshape(24, -1, 3), s["lights"])
    with pytest.raises(ValueError, match="images"):
        ps.refine_surface(res, s["images"][:, :16], s["lights"])
    with pytest.raises(TypeError, match="result"):
        ps.refine_surface(res.normals, s["images"], s["lights"])
    with pytest.raises(ValueError, match="lights"):
        ps.refine_surface(res, s["images"][:5], s["lights"][:5])
