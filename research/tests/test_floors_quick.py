"""The floor studies in CI: ``research/surface_floor.py`` and ``research/objective_floor.py``.

Their quick modes run in their own process (``tests/_scripts.py``) on the suite's quick synthetic scene
(``bumpy_shadows``, 32 x 32); the functions of ``objective_floor.py`` (the solver's per-pixel loss, the
whole-surface loss, the per-pixel choice) are checked in this process on small scenes.
"""
from __future__ import annotations

import re

import pytest
import torch

from _scripts import run_script

NUM = r"([-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|nan|inf))"


def test_surface_floor_quick(tmp_path, monkeypatch):
    # the floor of a depth-map model: true normals -> depth -> normals; small on a smooth field, 0 on a plane
    monkeypatch.setenv("TORCH_HSH_CACHE", str(tmp_path / "cache"))
    r = run_script("research/surface_floor.py", "--quick", "--only", "bumpy_shadows", "--threads", "1")
    m = re.search(rf"^\| bumpy_shadows \| {NUM} \| {NUM} \|$", r.stdout, re.M)
    assert m, r.stdout
    assert 0 < float(m.group(1)) < 3 and 0 < float(m.group(2)) < 3
    from surface_floor import floor_row  # research/ is on the path (conftest.py)

    n = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64), dim=0).expand(12, 12, 3)
    row = floor_row(n, torch.ones(12, 12, dtype=torch.bool), ("poisson",))
    assert row["poisson central"] < 1e-5 and row["poisson one-sided mix"] < 1e-5


def test_objective_floor_quick(tmp_path, monkeypatch):
    # solves started from the true normals: the row's numbers, and the verdict follows the two losses
    monkeypatch.setenv("TORCH_HSH_CACHE", str(tmp_path / "cache"))
    r = run_script("research/objective_floor.py", "--quick", "--only", "bumpy_shadows", "--threads", "1")
    m = re.search(rf"^\| bumpy_shadows \| {NUM} \| {NUM} \| {NUM} \| {NUM} \| {NUM} \| {NUM} \| (truth start|default) \| "
                  rf"{NUM} \| {NUM} \| {NUM} s \|$", r.stdout, re.M)
    assert m, r.stdout
    errs = [float(m.group(i)) for i in (1, 2, 3)]
    assert all(0 < e < 30 for e in errs), errs
    assert errs[1] < errs[0]  # the truth start keeps a better basin on this scene (3.1 against 4.1 deg at 1 thread)
    loss_def, loss_truth, loss_px = float(m.group(4)), float(m.group(5)), float(m.group(6))
    assert loss_def > 0 and loss_truth > 0 and loss_px > 0
    assert m.group(7) == ("truth start" if loss_truth < loss_def else "default")
    chosen, share = float(m.group(8)), float(m.group(9))
    assert 0 < chosen < 30 and 0 <= share <= 100


def test_objective_floor_quick_surface_and_interreflections(tmp_path, monkeypatch):
    # --surface adds the whole-surface losses, --interreflections runs on the corrected images and reports the bounce
    monkeypatch.setenv("TORCH_HSH_CACHE", str(tmp_path / "cache"))
    r = run_script("research/objective_floor.py", "--quick", "--only", "bumpy_shadows", "--threads", "1",
                   "--surface", "--interreflections")
    assert "| surface loss default | surface loss truth start | surface loss truth | bounce (% of the light) | time |" \
        in r.stdout, r.stdout
    m = re.search(r"^\| bumpy_shadows \| " + rf"{NUM} \| " * 6 + rf"(?:truth start|default) \| {NUM} \| {NUM} \| "
                  rf"{NUM} \| {NUM} \| {NUM} \| {NUM} \((kept|rejected: images unchanged)\) \| {NUM} s \|$", r.stdout, re.M)
    assert m, r.stdout
    surf = [float(m.group(i)) for i in (9, 10, 11)]
    assert all(v > 0 for v in surf), surf
    assert 0 <= float(m.group(12)) < 50  # this field has an ambient term and cast shadows: a few % of the light


def _objective_floor():
    """research/objective_floor.py as a module (research/ is on the path: conftest.py)."""
    import importlib

    return importlib.import_module("objective_floor")


def _rendered(g, normals, n_lights, order=2, spread=0.5, noise=0.0):
    """Observations that the shared model renders from ``normals (P, 3)``: a mostly diffuse random basis of two
    BRDFs, lights around the pole, random mixing weights (and Gaussian noise). Returns ``(obs, B)``."""
    from types import SimpleNamespace

    from torch_hsh import num_isotropic
    from torch_hsh.ps.design import MixedDesign
    from torch_hsh.ps.optim import combine

    P = normals.shape[0]
    B = torch.randn(2, num_isotropic(order), generator=g, dtype=torch.float64)
    B[:, 0] += 4.0  # positive on the hemisphere
    lights = torch.nn.functional.normalize(torch.randn(n_lights, 3, generator=g, dtype=torch.float64) * spread
                                           + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), dim=-1)
    W = torch.rand(P, 2, 3, generator=g, dtype=torch.float64) + 0.5
    y = combine(W, MixedDesign(B, lights, order)(normals)).transpose(1, 2)  # (P, L, C)
    if noise:
        y = y + noise * torch.randn(y.shape, generator=g, dtype=torch.float64)
    obs = SimpleNamespace(data=SimpleNamespace(y=y, lights=lights), weights=torch.ones(P, n_lights, dtype=torch.float64))
    return obs, B


def test_objective_floor_surface_loss_of_a_plane():
    # a tilted plane: its own depth gives its normals back and casts no shadow, so the surface loss is the
    # per-pixel loss at the plane's normals
    of = _objective_floor()
    g = torch.Generator().manual_seed(5)
    H = W = 12
    mask = torch.ones(H, W, dtype=torch.bool)
    n = torch.nn.functional.normalize(torch.tensor([0.2, -0.1, 1.0], dtype=torch.float64), dim=0).expand(H, W, 3)
    # a residual (noise), so the loss is not ~0
    obs, B = _rendered(g, n.reshape(-1, 3), 10, spread=0.3, noise=0.01)
    want = float(of.solution_loss(obs, B, n.reshape(-1, 3), 0.05, 2, 2.385).mean())
    assert want > 1e-3
    assert of.surface_loss(obs, B, n, mask, 0.05, 2, 2.385, 0.25) == pytest.approx(want, rel=1e-6)


def _small_scene():
    from types import SimpleNamespace

    from torch_hsh.render.scenes import demo_scene

    sc = demo_scene(24, n_lights=16, seed=0, dtype=torch.float64)
    return SimpleNamespace(images=sc["images"] / sc["intensities"][:, None, None, :], lights=sc["lights"],
                           mask=sc["mask"], normals_gt=sc["normals_gt"])


def test_objective_floor_loss_is_the_calibration_criterion(monkeypatch):
    # solution_loss summed over the calibration subset, at the candidates' common scale, is the loss by which
    # the calibration chose its start (info["calibration_losses"]); the scale of scene_row is the calibrations'
    from types import SimpleNamespace

    import torch_hsh.ps.calibration as cal_mod
    import torch_hsh.ps.pipeline as pipe
    from torch_hsh import ps

    d = _small_scene()
    seen, cals = [], []
    orig_cal, orig_calibrate = cal_mod._calibrate, pipe.calibrate

    def spy(y, w0, n0, lights, *rest):
        out = orig_cal(y, w0, n0, lights, *rest)
        seen.append((y, w0, lights, out))
        return out

    def spy_calibrate(*a, **k):
        c = orig_calibrate(*a, **k)
        cals.append(c)
        return c

    monkeypatch.setattr(cal_mod, "_calibrate", spy)
    r = ps.solve_hsh(d.images, d.lights, None, d.mask, seed=0, work_dtype=torch.float64)
    losses = r.info["calibration_losses"]
    assert len(seen) == len(losses) == 2  # the Lambertian and the independent start
    sig = min(float(o[1]) for *_, o in seen)
    for (y, w0, lights, (B, _, n)), want in zip(seen, losses):
        obs = SimpleNamespace(data=SimpleNamespace(y=y, lights=lights), weights=w0)
        got = float(_objective_floor().solution_loss(obs, cal_mod._unit_rows(B), n, sig, 3, 2.385).sum())
        assert got == pytest.approx(want, rel=1e-9)

    monkeypatch.setattr(pipe, "calibrate", spy_calibrate)
    row = _objective_floor().scene_row(d)
    assert len(cals) == 2  # the default and the truth-start solve calibrate; the third reuses the default's basis
    assert row["scale"] == pytest.approx(min(c.scale for c in cals), rel=1e-12)


def test_objective_floor_pixel_choice():
    choice = _objective_floor().pixel_choice
    a = torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=torch.float32)
    b = torch.tensor([[1.0, 0.0, 0.0]] * 3, dtype=torch.float32)
    n, took_b = choice(a, b, torch.tensor([1.0, 2.0, 3.0]), torch.tensor([2.0, 1.0, 3.0]))
    assert took_b.tolist() == [False, True, False]  # the lower loss; a tie keeps a
    assert n.dtype == torch.float64 and n.tolist() == [[0, 0, 1], [1, 0, 0], [0, 0, 1]]


def test_objective_floor_solution_loss():
    # the per-pixel Cauchy loss is 0 on data the shared model renders exactly, and grows away from the normals
    solution_loss = _objective_floor().solution_loss
    g = torch.Generator().manual_seed(3)
    order, P = 2, 40
    slopes = torch.randn(P, 2, generator=g, dtype=torch.float64) * 0.4
    n = torch.nn.functional.normalize(torch.cat([slopes, torch.ones(P, 1, dtype=torch.float64)], -1), dim=-1)
    obs, B = _rendered(g, n, 24, order)
    at_truth = solution_loss(obs, B, n, 0.05, order, 2.385, chunk_size=16)
    # only the tiny ridge of the mixing-weight solve (1e-4 of the Gram diagonal) leaves a residual
    assert at_truth.shape == (P,) and float(at_truth.max()) < 1e-3
    tilted = torch.nn.functional.normalize(n + torch.tensor([0.25, 0.0, 0.0], dtype=torch.float64), dim=-1)
    assert float(solution_loss(obs, B, tilted, 0.05, order, 2.385).min()) > 10 * float(at_truth.max())
