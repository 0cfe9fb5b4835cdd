"""Fitting a MERL table on its own samples (torch_hsh.io.merl.fit_merl, merl_solid_angle_weights).

The reference for the weights is the measure of Omega_i x Omega_o (4 pi^2); the reference for the fit
is the library's convergence-controlled projection of the analytic model that was tabulated (an
independent code path: quadrature in (cos theta_i, cos theta_o, dphi), no table, no weights).
Deliberate bug that these tests catch: dropping the cos(theta_d) factor of the Jacobian
(d omega_i d omega_o = 4 cos(theta_d) d omega_h d omega_d) in merl_solid_angle_weights, or using
uniform weights (test_wrong_weights_fail_the_same_bound shows the bound is not loose).
"""
import math

import pytest
import torch

import torch_hsh
from torch_hsh.brdf import BlinnPhong, CookTorranceGGX, Lambertian
from torch_hsh.io.merl import (
    MERLBRDF,
    fit_merl,
    half_diff_to_dirs,
    merl_bin_centers,
    merl_solid_angle_weights,
    read_merl,
    tabulate_merl,
    write_merl,
)

SHAPE = (30, 30, 60)


@pytest.mark.parametrize("shape, rel", [((8, 8, 16), 1e-4), ((30, 30, 60), 1e-4), ((90, 90, 180), 1e-5),
                                        ((7, 5, 9), 3e-3)])  # coarse bins: the horizon kink inside a bin costs more
def test_weights_add_up_to_the_measure_of_direction_pairs(shape, rel):
    w = merl_solid_angle_weights(shape)
    assert w.shape == shape and bool((w >= 0).all())
    assert float(w.sum()) == pytest.approx(4 * math.pi**2, rel=rel)
    assert float(merl_solid_angle_weights(shape, n_sub=8).sum()) == pytest.approx(4 * math.pi**2, rel=rel / 2)


def test_weights_against_monte_carlo_per_region():
    """Weights of a block of bins vs the Monte Carlo measure of the pairs that fall in it (an independent binning)."""
    shape = (6, 6, 8)
    w = merl_solid_angle_weights(shape)
    g = torch.Generator().manual_seed(0)
    n = 400_000
    wi, _ = torch_hsh.monte_carlo_directions(n, generator=g)
    wo, _ = torch_hsh.monte_carlo_directions(n, generator=g)
    ih, idd, ip = MERLBRDF(torch.zeros(3, *shape, dtype=torch.float64)).bin_indices(wi, wo)
    counts = torch.zeros(shape, dtype=torch.float64)
    counts.index_put_((ih, idd, ip), torch.ones(n, dtype=torch.float64), accumulate=True)
    mc = counts * (4 * math.pi**2 / n)
    for sel in [(slice(0, 2), slice(0, 3)), (slice(2, 6), slice(3, 6)), (slice(4, 6), slice(0, 6))]:
        exact, est = float(w[sel].sum()), float(mc[sel].sum())
        sigma = math.sqrt(est * 4 * math.pi**2 / n)
        assert abs(exact - est) < 5 * sigma + 1e-3 * exact, (sel, exact, est)


def test_lambertian_is_exact():
    t = tabulate_merl(Lambertian([0.2, 0.5, 0.8]), shape=(8, 8, 16))
    a, info = fit_merl(t, 3, return_info=True)
    torch.testing.assert_close(a[:, 0], torch.tensor([0.4, 1.0, 1.6], dtype=torch.float64), rtol=1e-10, atol=0)
    assert float(a[:, 1:].abs().max()) < 1e-10
    assert float(info["relative_error"].max()) < 1e-6 and float(info["relative_error_unweighted"].max()) < 1e-6


def _direct_errors(t, a, weights=None, cutoff=None):
    """Relative errors recomputed from scratch: reconstruct at every used bin centre."""
    th, td, pd = merl_bin_centers(t.shape)
    TH, TD, PD = torch.meshgrid(th, td, pd, indexing="ij")
    wi, wo = half_diff_to_dirs(TH, torch.zeros_like(TH), TD, PD)
    w = merl_solid_angle_weights(t.shape) if weights is None else weights
    zmin = torch.minimum(wi[..., 2], wo[..., 2])
    use = t.measured[0] & (w > 0) & (zmin >= 0)
    y = t.table[:, use].T  # (n, 3)
    if cutoff is not None:
        y = y * (zmin[use] >= cutoff)[:, None]
    f = torch_hsh.reconstruct(a, wi[use], wo[use], channels=True)
    ww = w[use][:, None]
    rel_w = ((ww * (f - y) ** 2).sum(0) / (ww * y**2).sum(0)).sqrt()
    rel_u = (((f - y) ** 2).sum(0) / (y**2).sum(0)).sqrt()
    return rel_w, rel_u


def test_blinn_phong_matches_the_projection_of_the_model():
    model = BlinnPhong(albedo=0.3, specular=0.5, shininess=50.0)
    t = tabulate_merl(model, shape=SHAPE)
    a, info = fit_merl(t, 6, return_info=True)
    ref = torch_hsh.project(lambda wi, wo: model(wi, wo), 6, tol=1e-4)
    rel = (a - ref).norm(dim=-1) / ref.norm(dim=-1)
    assert float(rel.max()) < 0.01  # measured 0.0016; uniform weights give 0.47, no cos(theta_d) 0.05
    # the reported error is the error on the samples (recomputed from the coefficients) ...
    rel_w, rel_u = _direct_errors(t, a)
    torch.testing.assert_close(info["relative_error"], rel_w, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(info["relative_error_unweighted"], rel_u, rtol=1e-4, atol=1e-6)
    # ... and the L2 error of the truncated model: sqrt(1 - Acc(6)) by the converged quadrature
    acc = torch_hsh.brdf_accuracy(lambda wi, wo: model(wi, wo), 6, tol=1e-4)
    expect = (1 - acc[:, -1]).sqrt()
    assert float((info["relative_error"] - expect).abs().max()) < 0.01, (info["relative_error"], expect)
    # per-order errors: non-increasing, the last one is the full fit
    e = info["relative_error_per_order"]
    assert e.shape == (3, 7) and bool((e[:, 1:] <= e[:, :-1] + 1e-12).all())
    torch.testing.assert_close(e[:, -1], info["relative_error"])
    torch.testing.assert_close(info["accuracy"], 1 - e**2)


@pytest.mark.parametrize("bad", ["uniform", "no_cos_theta_d"])
def test_wrong_weights_fail_the_same_bound(bad):
    model = BlinnPhong(albedo=0.3, specular=0.5, shininess=50.0)
    t = tabulate_merl(model, shape=SHAPE)
    w = merl_solid_angle_weights(SHAPE)
    th, td, pd = merl_bin_centers(SHAPE)
    w = torch.ones_like(w) if bad == "uniform" else w / td.cos()[None, :, None]
    a = fit_merl(t, 6, weights=w)
    ref = torch_hsh.project(lambda wi, wo: model(wi, wo), 6, tol=1e-4)
    assert float(((a - ref).norm(dim=-1) / ref.norm(dim=-1)).max()) > 0.03


def test_specular_ggx_table_with_cutoff_matches_the_projection():
    """A specular table (GGX roughness 0.3): its raw 1/cos grazing growth needs the cutoff in both methods."""
    model = CookTorranceGGX(albedo=0.5, specular=0.5, roughness=0.3)
    t = tabulate_merl(model, shape=SHAPE)
    a, info = fit_merl(t, 6, grazing_cutoff=0.2, return_info=True)
    ref = torch_hsh.project(lambda wi, wo: model(wi, wo), 6, grazing_cutoff=0.2, tol=1e-4)
    rel = (a - ref).norm(dim=-1) / ref.norm(dim=-1)
    assert float(rel.max()) < 0.05  # measured 0.026 (the cutoff is resolved by bin centres); no cos(theta_d): 0.15
    rel_w, _ = _direct_errors(t, a, cutoff=0.2)
    torch.testing.assert_close(info["relative_error"], rel_w, rtol=1e-4, atol=1e-6)
    # a sharp lobe at order 6: most of its norm is beyond the basis, and the fit says so
    assert 0.6 < float(info["relative_error"].max()) < 0.85  # measured 0.784


def test_raw_ggx_error_is_dominated_by_the_grazing_growth():
    model = CookTorranceGGX(albedo=0.5, specular=0.5, roughness=0.7)
    t = tabulate_merl(model, shape=SHAPE)
    e_raw = float(fit_merl(t, 6, return_info=True)[1]["relative_error"].max())
    e_cut = float(fit_merl(t, 6, grazing_cutoff=0.2, return_info=True)[1]["relative_error"].max())
    assert e_raw > 0.3 and e_cut < 0.25  # measured 0.380 and 0.217 (both of their own function)


def test_chunking_odd_phi_bins_and_file_input(tmp_path):
    model = CookTorranceGGX(albedo=0.4, specular=0.5, roughness=0.5)
    t = tabulate_merl(model, shape=(9, 7, 13))  # odd N_pd: the middle bin is its own mirror
    a1, i1 = fit_merl(t, 3, return_info=True)
    a2, i2 = fit_merl(t, 3, chunk_size=1, return_info=True)
    torch.testing.assert_close(a1, a2, rtol=1e-10, atol=1e-12)
    rel_w, rel_u = _direct_errors(t, a1)
    torch.testing.assert_close(i1["relative_error"], rel_w, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(i1["relative_error_unweighted"], rel_u, rtol=1e-4, atol=1e-6)
    p = write_merl(tmp_path / "g.binary", t)
    torch.testing.assert_close(fit_merl(p, 3), a1, rtol=0, atol=0)
    torch.testing.assert_close(fit_merl(read_merl(p), 3), a1, rtol=0, atol=0)


def test_unmeasured_channels_and_ridge():
    t = tabulate_merl(Lambertian([0.2, 0.5, 0.8]), shape=(8, 8, 16))
    raw = t.raw.clone()
    raw[1, :4] = -1.0  # the green channel loses half of its theta_h rows
    a, info = fit_merl(MERLBRDF(raw), 2, return_info=True)
    torch.testing.assert_close(a[:, 0], torch.tensor([0.4, 1.0, 1.6], dtype=torch.float64), rtol=1e-9, atol=0)
    a_r = fit_merl(MERLBRDF(raw), 2, ridge=0.1)
    assert float(a_r[1, 0]) < 1.0  # a ridge shrinks


def test_bad_arguments_name_themselves(tmp_path):
    t = tabulate_merl(Lambertian(0.5), shape=(4, 4, 8))
    with pytest.raises(ValueError, match="basis"):
        fit_merl(t, 2, basis="helmholtz_anisotropic")
    with pytest.raises(ValueError, match="ridge"):
        fit_merl(t, 2, ridge=-1.0)
    with pytest.raises(ValueError, match="grazing_cutoff"):
        fit_merl(t, 2, grazing_cutoff=1.0)
    with pytest.raises(ValueError, match="weights"):
        fit_merl(t, 2, weights=torch.ones(4, 4, 7, dtype=torch.float64))
    with pytest.raises(ValueError, match="weights"):
        fit_merl(t, 2, weights=-torch.ones(4, 4, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="chunk_size"):
        fit_merl(t, 2, chunk_size=0)
    with pytest.raises(TypeError, match="brdf"):
        fit_merl(torch.zeros(3, 4, 4, 8), 2)
    with pytest.raises(FileNotFoundError, match="missing.binary"):
        fit_merl(tmp_path / "missing.binary", 2)
    with pytest.raises(ValueError, match="n_sub"):
        merl_solid_angle_weights((4, 4, 8), n_sub=0)
    # too few samples for the order: the message says what to pass
    with pytest.raises(ValueError, match="ridge"):
        fit_merl(tabulate_merl(Lambertian(0.5), shape=(2, 2, 2)), 4)


def test_ill_conditioned_normal_equations_are_refused_even_when_cholesky_succeeds():
    from types import SimpleNamespace

    from torch_hsh.io.merl import _solve_orders

    G = torch.diag(torch.tensor([1.0, 1e-14], dtype=torch.float64)).unsqueeze(0)  # positive definite, condition 1e14
    S = SimpleNamespace(G=G, rhs=torch.ones(3, 2, dtype=torch.float64), nused=torch.tensor([5, 5, 5]))
    sel = torch.ones(2, dtype=torch.bool)
    with pytest.raises(ValueError, match="ill-conditioned.*ridge > 0"):
        _solve_orders(S, 0.0, torch.tensor([0, 1]), sel)
    a, cond = _solve_orders(S, 1e-3, torch.tensor([0, 1]), sel)
    assert cond < 1e4 and torch.isfinite(a).all()
