"""Tests of ``materials="auto"`` (torch_hsh.ps.materials): held-out-light cross-validation of the number of
shared basis BRDFs."""
import math

import pytest
import torch

from conftest import random_ps_scene
from torch_hsh import ps
from torch_hsh.brdf import BlinnPhong, CookTorranceGGX, Lambertian
from torch_hsh.ps.materials import light_folds, one_standard_error_choice
from torch_hsh.render import render

DT = torch.float64


def _materials_scene(n_materials, p=180, l=30, seed=0, noise=1e-3):
    """``n_materials`` analytic BRDF shapes (Lambertian, Blinn-Phong, GGX), each times a per-pixel RGB albedo.

    Pixel ``i`` has material ``i mod n_materials``; every material is one BRDF
    shape scaled per pixel and channel, so the scene is exactly ``n_materials``
    shared BRDFs with free RGB weights (the model's structure).
    """
    n, d, g = random_ps_scene(p, l, seed)
    one = torch.ones(p, 1, dtype=DT)
    shapes = [
        Lambertian(one),
        BlinnPhong(albedo=one, specular=0.4 * one, shininess=8.0 * one),
        CookTorranceGGX(albedo=0.3 * one, specular=one, roughness=0.5 * one, f0=0.9),
    ]
    tint = torch.tensor([[1.0, 0.8, 0.6], [0.5, 0.7, 1.0], [0.9, 0.4, 0.9]], dtype=DT)  # distinct colours
    albedo = 0.2 + 0.6 * torch.rand(p, 3, generator=g, dtype=DT)
    label = torch.arange(p) % n_materials
    img = torch.zeros(l, p, 3, dtype=DT)
    for k in range(n_materials):
        r = render(n, d, shapes[k])[..., :1] * albedo * tint[k]
        img = torch.where((label == k)[None, :, None], r, img)
    img = img + noise * float(img.max()) * torch.randn(img.shape, generator=g, dtype=DT)
    return img.clamp(min=0), d, n


def test_auto_picks_one_basis_brdf_for_one_material():
    img, l, _ = _materials_scene(1)
    res = ps.solve_hsh(img, l, materials="auto")
    info = res.info
    assert info["materials_chosen"] == 1
    assert res.basis_brdfs.shape[0] == 1 and info["materials"] == 1
    crit = info["materials_criterion"]
    assert len(crit) == 4 and all(math.isfinite(v) and v >= 0 for v in crit)
    assert info["materials_candidates"] == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize("n_materials", [2, 3])
def test_auto_picks_several_basis_brdfs_for_several_materials(n_materials):
    img, l, _ = _materials_scene(n_materials)
    info = ps.solve_hsh(img, l, materials="auto").info
    assert info["materials_chosen"] >= 2, info["materials_criterion"]
    crit, se = info["materials_criterion"], info["materials_criterion_se"]
    # one material is clearly worse than the best by more than its standard error
    assert crit[0] > min(crit) + se[0]


def test_one_standard_error_rule():
    # candidate 0 is far worse; 1 is within one standard error of the best (2); 3 is worse than 2
    totals = torch.tensor([[5.0, 5.0, 5.0, 5.0], [1.2, 0.8, 1.1, 0.9], [1.0, 1.0, 1.0, 0.9], [1.1, 1.1, 1.1, 1.0]])
    i, crit, se = one_standard_error_choice(totals, 8.0)
    assert crit == pytest.approx([2.5, 0.5, 0.4875, 0.5375])
    assert se[2] == 0.0
    # paired differences of candidate 1 to the best: (0.2, -0.2, 0.1, 0.0)
    d = torch.tensor([0.2, -0.2, 0.1, 0.0], dtype=totals.dtype)
    assert se[1] == pytest.approx(float(d.std()) * 2.0 / 8.0)
    assert i == 1
    # a clear winner is kept when the smaller candidates are worse beyond their standard error
    i, _, _ = one_standard_error_choice(torch.tensor([[2.0, 2.1, 1.9], [1.0, 1.05, 0.95]]), 3.0)
    assert i == 1


def test_light_folds_interleave_the_azimuths():
    az = torch.rand(31, generator=torch.Generator().manual_seed(1), dtype=DT) * 2 * math.pi - math.pi
    l = torch.nn.functional.normalize(torch.stack([az.cos(), az.sin(), torch.full_like(az, 2.0)], -1), dim=-1)
    f = light_folds(l, 3)
    assert sorted(torch.bincount(f).tolist()) == [10, 10, 11]
    # along the azimuth, consecutive lights are in different folds
    order = torch.argsort(az)
    assert bool((f[order][1:] != f[order][:-1]).all())


def test_auto_needs_enough_lights():
    img, l, _ = _materials_scene(1, p=30, l=5)
    # the specific refusal (not the generic "`materials` must be ..." of an unaccepted value)
    with pytest.raises(ValueError, match=r"materials='auto'` needs at least 6 lights .* got 5"):
        ps.solve_hsh(img, l, materials="auto")


def test_materials_argument_accepts_auto_and_names_itself_otherwise():
    img, l, _ = _materials_scene(1, p=12, l=8)
    for bad in ("Auto", "2", "two", 0, 9, 2.5, float("nan"), float("inf"), True, [2]):
        with pytest.raises(ValueError, match="materials"):
            ps.solve_hsh(img, l, materials=bad)
    for ok in (None, 1, 8, 3.0):
        ps.solve_hsh(img, l, materials=ok, calibration_rounds=1, max_iter=1)
