"""Tests of environment lighting (torch_hsh.render.envmap)."""
import math

import numpy as np
import pytest
import scipy.special as sp
import torch

from torch_hsh import render as R
from torch_hsh.kernel import helmholtz_isotropic
from torch_hsh.bases.westin import real_sh
from torch_hsh.brdf import Lambertian
from torch_hsh.render.envmap import (
    EnvironmentMap,
    envmap_shading_table,
    equirect_directions,
    equirect_solid_angles,
    render_envmap,
    render_envmap_reference,
    sh_coefficients,
    sh_evaluate,
)
from torch_hsh.render.envmap import _rot_x, _rot_y, _rot_z, _sh_rotation_matrix

DT = torch.float64


def _normals(p, seed=0, zmin=0.05):
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(p, 3, generator=g, dtype=DT), dim=-1)
    n[:, 2] = n[:, 2].abs().clamp(min=zmin)
    return torch.nn.functional.normalize(n, dim=-1)


def _coefficients(p, c, order, seed=1):
    g = torch.Generator().manual_seed(seed)
    k = (order + 1) * (order + 2) * (order + 3) // 6
    a = 0.3 * torch.randn(p, c, k, generator=g, dtype=DT)
    a[..., 0] += 1.5
    return a


def _sky(h, w, seed=2):
    """A synthetic 'real-like' map: sky gradient, ground, a sun and some texture."""
    g = torch.Generator().manual_seed(seed)
    d = equirect_directions(h, w, dtype=DT)
    up = d[..., 1:2]
    sky = torch.tensor([0.4, 0.6, 1.0], dtype=DT) * (0.5 + 0.5 * up.clamp(min=0))
    ground = torch.tensor([0.3, 0.25, 0.2], dtype=DT) * (1.0 + 0.3 * torch.rand(h, w, 1, generator=g, dtype=DT))
    img = torch.where(up > 0, sky, ground)
    sun = torch.nn.functional.normalize(torch.tensor([0.5, 0.6, -0.4], dtype=DT), dim=0)
    img = img + 30.0 * ((d @ sun) > math.cos(math.radians(6.0))).to(DT).unsqueeze(-1)
    return EnvironmentMap(img)


# --------------------------------------------------------------------------- spherical harmonics
def _sph_harm_y(n, m, theta, phi):
    """scipy's complex SH, polar angle ``theta``; ``sph_harm_y`` (scipy >= 1.15) or the older ``sph_harm``."""
    if hasattr(sp, "sph_harm_y"):
        return sp.sph_harm_y(n, m, theta, phi)
    return sp.sph_harm(m, n, phi, theta)  # older argument order: (m, n, azimuth, polar)


def test_real_sh_matches_scipy_at_random_points():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(200, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    theta, phi = np.arccos(v[:, 2]), np.arctan2(v[:, 1], v[:, 0])
    N = 7
    ours = real_sh(torch.from_numpy(v), N).numpy()
    for l in range(N + 1):
        for m in range(-l, l + 1):
            y = _sph_harm_y(l, abs(m), theta, phi)  # complex, with the Condon-Shortley phase
            if m > 0:
                ref = math.sqrt(2) * (-1) ** m * y.real
            elif m < 0:
                ref = math.sqrt(2) * y.imag
            else:
                ref = y.real
            np.testing.assert_allclose(ours[:, l * l + l + m], ref, atol=1e-12, err_msg=f"l={l} m={m}")


def test_sh_rotation_matrix_rotates_functions():
    N = 5
    R3 = _rot_z(0.3) @ _rot_y(1.1) @ _rot_x(-0.7)
    D = _sh_rotation_matrix(R3, N)
    c = torch.randn(2, (N + 1) ** 2, dtype=DT)
    w = torch.nn.functional.normalize(torch.randn(50, 3, dtype=DT), dim=-1)
    f_rot = sh_evaluate(c, w @ torch.from_numpy(R3).T)  # f(R w)
    torch.testing.assert_close(sh_evaluate(c @ D.T, w), f_rot, atol=1e-12, rtol=0)
    # the factorisation used per pixel: R_z(a) R_y(b) R_z(pi) = S_pi J+ Z_b J- Z_a (composition reverses)
    a, b = 0.7, 1.1
    lhs = _sh_rotation_matrix(_rot_z(a) @ _rot_y(b) @ _rot_z(math.pi), N)
    Jm, Jp = _sh_rotation_matrix(_rot_x(-math.pi / 2), N), _sh_rotation_matrix(_rot_x(math.pi / 2), N)
    rhs = _sh_rotation_matrix(_rot_z(math.pi), N) @ Jp @ _sh_rotation_matrix(_rot_z(b), N) @ Jm @ _sh_rotation_matrix(_rot_z(a), N)
    torch.testing.assert_close(lhs, rhs, atol=1e-12, rtol=0)


def test_shading_table_selects_m_equal_q():
    N, P = 6, 3
    T = envmap_shading_table(N, P)
    pq = [(p, q) for p in range(P + 1) for q in range(p + 1)]
    for l in range(N + 1):
        for m in range(-l, l + 1):
            for j, (p, q) in enumerate(pq):
                if m != q:
                    assert abs(float(T[l * l + l + m, j])) < 1e-14
    # Y_1^0 H_0^0 cos: sqrt(3/4pi) / sqrt(2pi) * 2pi/3
    assert float(T[2, 0]) == pytest.approx(math.sqrt(3 / (4 * math.pi)) / math.sqrt(2 * math.pi) * 2 * math.pi / 3, abs=1e-14)


# --------------------------------------------------------------------------- the map
@pytest.mark.parametrize("hw", [(8, 16), (5, 7)])
@pytest.mark.parametrize("rotation", [0.0, 0.83])
def test_constant_map_has_no_higher_orders(hw, rotation):
    env = EnvironmentMap(torch.full((*hw, 2), 3.0, dtype=DT), rotation=rotation)
    c = env.sh_coefficients(10)
    torch.testing.assert_close(c[:, 0], torch.full((2,), 3.0 * math.sqrt(4 * math.pi), dtype=DT), atol=1e-13, rtol=0)
    assert float(c[:, 1:].abs().max()) < 1e-13


def test_sh_coefficients_are_exact_texel_integrals():
    """Independent check: Gauss-Legendre inside every texel with scipy's SH."""
    H, W, N = 4, 6, 4
    data = torch.rand(H, W, 1, generator=torch.Generator().manual_seed(3), dtype=DT)
    rot = 0.4
    ours = EnvironmentMap(data, rotation=rot).sh_coefficients(N)[0].numpy()
    x, w = np.polynomial.legendre.leggauss(12)
    ref = np.zeros((N + 1) ** 2)
    for i in range(H):
        th0, th1 = math.pi * i / H, math.pi * (i + 1) / H
        th = 0.5 * (th0 + th1) + 0.5 * (th1 - th0) * x
        for j in range(W):
            p0, p1 = 2 * math.pi * j / W - math.pi, 2 * math.pi * (j + 1) / W - math.pi
            ph = 0.5 * (p0 + p1) + 0.5 * (p1 - p0) * x
            TH, PH = np.meshgrid(th, ph, indexing="ij")
            d = np.stack([np.sin(TH) * np.sin(PH), np.cos(TH), -np.sin(TH) * np.cos(PH)], -1)
            d = d @ _rot_y(rot).T  # the documented layout, turned about +y
            wt = np.outer(0.5 * (th1 - th0) * w * np.sin(th), 0.5 * (p1 - p0) * w)
            Y = real_sh(torch.from_numpy(d.reshape(-1, 3)), N).numpy()
            ref += float(data[i, j, 0]) * (Y * wt.reshape(-1, 1)).sum(0)
    np.testing.assert_allclose(ours, ref, atol=1e-12)


def test_directions_layout_and_rotation():
    d = equirect_directions(4, 8, dtype=DT)
    # centre of the map looks along -z, a quarter to the right is +x, the edges are +z, the top row is near +y
    mid = d[1, 3] + d[1, 4]
    assert abs(float(mid[0])) < 1e-12 and float(mid[2]) < -0.7
    assert float((d[1, 0] + d[1, 7])[2]) > 0.7 and abs(float((d[1, 0] + d[1, 7])[0])) < 1e-12
    assert float(d[1, 5:7, 0].mean()) > 0.6 and float(d[0, :, 1].min()) > 0.9
    env = EnvironmentMap(torch.rand(4, 8, 1, dtype=DT))
    Ry = torch.from_numpy(_rot_y(0.3))
    torch.testing.assert_close(env.rotated(0.3).directions(), env.directions() @ Ry.T, atol=1e-14, rtol=0)
    # turning by one texel width equals shifting the columns
    shifted = EnvironmentMap(torch.roll(env.data, shifts=1, dims=1))
    step = -2 * math.pi / 8  # columns sweep the azimuth clockwise seen from above
    torch.testing.assert_close(env.rotated(step).sh_coefficients(5), shifted.sh_coefficients(5), atol=1e-13, rtol=0)
    # and the SH of a turned map are those of the turned function
    D = _sh_rotation_matrix(_rot_y(0.3).T, 5)
    torch.testing.assert_close(env.rotated(0.3).sh_coefficients(5), env.sh_coefficients(5) @ D.T, atol=1e-13, rtol=0)


def test_solid_angles_and_power_preserving_downsampling():
    om = equirect_solid_angles(6, 10, dtype=DT)
    assert float(om.sum()) == pytest.approx(4 * math.pi, abs=1e-13)
    env = _sky(16, 32)
    for f in (2, (4, 8), 16):
        small = env.downsample(f)
        torch.testing.assert_close(small.power(), env.power(), atol=1e-12, rtol=1e-13)
        torch.testing.assert_close(small.sh_coefficients(0), env.sh_coefficients(0), atol=1e-12, rtol=1e-13)
    with pytest.raises(ValueError, match="divisible"):
        env.downsample(3)


def test_from_sh_round_trip_converges():
    c = torch.randn(2, 16, generator=torch.Generator().manual_seed(4), dtype=DT)
    errs = [float((EnvironmentMap.from_sh(c, h, 2 * h).sh_coefficients(3) - c).abs().max()) for h in (16, 32, 64)]
    assert errs[2] < errs[1] < errs[0] and errs[2] < 5e-3  # midpoint sampling: second order in the texel size
    assert errs[0] / errs[1] > 3.0 and errs[1] / errs[2] > 3.0


# --------------------------------------------------------------------------- rendering
def test_constant_environment_lambertian_is_albedo_times_radiance():
    L = torch.tensor([0.7, 1.3, 2.0], dtype=DT)
    env = EnvironmentMap(L.expand(8, 16, 3).clone())
    rho = torch.tensor([0.2, 0.5, 0.9], dtype=DT)
    a = torch.zeros(3, 20, dtype=DT)
    a[:, 0] = 2 * rho
    n = torch.cat([_normals(200, zmin=1e-3), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1e-9]], dtype=DT)])
    for N in (0, 3, 8):
        out = render_envmap(n, a, env, light_order=N)
        assert float((out - rho * L).abs().max()) < 1e-6
    away = torch.tensor([[0.0, 0.6, -0.8]], dtype=DT)
    assert float(render_envmap(away, a, env, light_order=4).abs().max()) == 0.0


def _clamped_cosine_bands(N):
    """A_l = 2 pi int_0^1 t P_l(t) dt: max(cos g, 0) = sum_l (2l+1)/(4 pi) A_l P_l(cos g)."""
    x, w = np.polynomial.legendre.leggauss(N + 4)
    t, wt = 0.5 * (x + 1), 0.5 * w
    return np.array([2 * math.pi * np.sum(wt * t * sp.eval_legendre(l, t)) for l in range(N + 1)])


def test_spherical_cap_lambertian_matches_funk_hecke():
    """A cap given exactly in SH: the result is E rho/pi sum_l b_l(delta) A_l (2l+1)/4pi P_l(n.d)."""
    N, delta = 10, math.radians(12.0)
    d = torch.nn.functional.normalize(torch.tensor([0.3, 0.5, 0.8], dtype=DT), dim=0)
    cd = math.cos(delta)
    b = [1.0] + [(sp.eval_legendre(l - 1, cd) - sp.eval_legendre(l + 1, cd)) / ((2 * l + 1) * (1 - cd)) for l in range(1, N + 1)]
    E = 2.5
    Yd = real_sh(d, N)
    lvec = torch.tensor([b[int(math.isqrt(k))] for k in range((N + 1) ** 2)], dtype=DT)
    coefficients = (E * lvec * Yd).unsqueeze(0)  # a cap of power E: L_lm = E b_l Y_lm(d)
    a = torch.zeros(1, 4, dtype=DT)
    a[:, 0] = 2 * 0.6
    n = _normals(40, seed=5)
    A = _clamped_cosine_bands(N)
    cosg = (n @ d).numpy()
    ref = sum(E * 0.6 / math.pi * b[l] * A[l] * (2 * l + 1) / (4 * math.pi) * sp.eval_legendre(l, cosg) for l in range(N + 1))
    np.testing.assert_allclose(render_envmap(n, a, coefficients)[:, 0].numpy(), ref, atol=1e-12)


def test_bright_disc_matches_point_light_within_derived_tolerance():
    r"""A disc of texels within delta of d versus ``render()`` with one light d of the same power E.

    render_envmap(N) = int h_N dmu exactly (mu: the disc's radiance measure, h: BRDF x cosine,
    h_N: its SH projection), and render() = E h(d). So
    |error| <= E |h_N(d) - h(d)| + E delta' Lip(h_N), delta' = delta + half a texel diagonal.
    For a Lambertian BRDF h_N = rho/pi sum_l (2l+1)/(4pi) A_l P_l(n.w) (Funk-Hecke), so
    |h_N(d) - h(d)| is known exactly and Lip(h_N) <= rho/pi sum_l (2l+1)/(4pi) |A_l| P_l'(1).
    """
    H, W, N, delta, rho = 512, 1024, 8, math.radians(1.0), 0.7
    d = torch.nn.functional.normalize(torch.tensor([0.35, 0.45, 0.82], dtype=DT), dim=0)
    dirs = equirect_directions(H, W, dtype=DT)
    disc = ((dirs @ d) > math.cos(delta)).to(DT).unsqueeze(-1)
    env = EnvironmentMap(100.0 * disc)
    E = float(env.power()[0])
    a = torch.zeros(1, 4, dtype=DT)
    a[:, 0] = 2 * rho
    n = _normals(30, seed=6, zmin=0.3)
    n = n[(n @ d) > 0.2]  # keep the disc away from each pixel's horizon
    ours = render_envmap(n, a, env, light_order=N)[:, 0]
    point = R.render(n, d.unsqueeze(0), a.expand(n.shape[0], 1, 4), intensities=torch.tensor([E], dtype=DT))[0, :, 0]
    A = _clamped_cosine_bands(N)
    cosg = (n @ d).numpy()
    hN = rho / math.pi * sum(A[l] * (2 * l + 1) / (4 * math.pi) * sp.eval_legendre(l, cosg) for l in range(N + 1))
    trunc = np.abs(hN - rho / math.pi * np.clip(cosg, 0, None))
    lip = rho / math.pi * sum(abs(A[l]) * (2 * l + 1) / (4 * math.pi) * l * (l + 1) / 2 for l in range(N + 1))
    dprime = delta + 0.5 * math.hypot(math.pi / H, 2 * math.pi / W)
    tol = E * (trunc + dprime * lip)
    err = np.abs((ours - point).numpy())
    assert (err <= tol).all(), (err, tol)
    assert (tol < 0.15 * E * rho / math.pi).all()  # the bound is informative: ~10 % of the head-on signal


def test_converges_to_reference_as_light_order_grows():
    env = _sky(32, 64)
    n = _normals(24, seed=7, zmin=0.1)
    a = _coefficients(24, 3, 2)
    ref = render_envmap_reference(n, a, env, supersample=4)
    errs = [float((render_envmap(n, a, env, light_order=N) - ref).abs().max()) for N in (1, 2, 4, 8, 16)]
    scale = float(ref.abs().max())
    assert all(e1 > e2 for e1, e2 in zip(errs, errs[1:])), errs
    assert errs[-1] < 0.02 * scale and errs[-1] < 0.1 * errs[0], errs


def test_reference_converges_with_supersampling_and_accepts_models():
    env = _sky(16, 32)
    n = _normals(10, seed=8, zmin=0.1)
    a = _coefficients(10, 3, 2)
    exact = render_envmap(n, a, env, light_order=30)  # the piecewise-constant map, to SH order 30
    e = [float((render_envmap_reference(n, a, env, supersample=s) - exact).abs().max()) for s in (1, 2, 4)]
    assert e[0] > e[1] > e[2]
    # a callable evaluating the same expansion gives the same reference
    iso = lambda wi, wo: torch.einsum("...k,...ck->...c", helmholtz_isotropic(wi, wo, 2), a.expand(wi.shape[0], *a.shape))
    torch.testing.assert_close(render_envmap_reference(n, iso, env), render_envmap_reference(n, a, env), atol=1e-12, rtol=0)
    # an analytic model: Lambertian(rho) equals the coefficient a_000 = 2 rho
    rho = torch.tensor([0.3, 0.5, 0.8], dtype=DT)
    lam = Lambertian(rho.expand(10, 3))
    a0 = torch.zeros(10, 3, 4, dtype=DT)
    a0[..., 0] = 2 * rho
    torch.testing.assert_close(render_envmap_reference(n, lam, env), render_envmap_reference(n, a0, env), atol=1e-12, rtol=0)


def test_batched_shapes_shared_coefficients_and_chunks():
    env = _sky(8, 16)
    n = _normals(12, seed=9).reshape(3, 4, 3)
    a = _coefficients(1, 3, 2)[0]  # (C, K) shared
    out = render_envmap(n, a, env, light_order=4)
    assert out.shape == (3, 4, 3)
    full = render_envmap(n, a.expand(3, 4, 3, 10), env, light_order=4, chunk_size=5)
    torch.testing.assert_close(out, full, atol=1e-13, rtol=0)
    L = env.sh_coefficients(6)
    torch.testing.assert_close(render_envmap(n, a, L, light_order=4), out, atol=1e-13, rtol=0)
    out32 = render_envmap(n.float(), a.float(), env.to(torch.float32), light_order=4)
    torch.testing.assert_close(out32.double(), out, atol=2e-5, rtol=1e-5)
    grey = EnvironmentMap(env.data[..., :1])
    assert render_envmap(n, a, grey, light_order=2).shape == (3, 4, 3)


def test_gradcheck_normals_coefficients_environment():
    n = _normals(3, seed=10, zmin=0.2).requires_grad_()
    a = _coefficients(3, 2, 1).requires_grad_()
    data = torch.rand(4, 8, 2, generator=torch.Generator().manual_seed(11), dtype=DT).requires_grad_()
    f = lambda n_, a_, d_: render_envmap(n_, a_, EnvironmentMap(d_), light_order=3)
    assert torch.autograd.gradcheck(f, (n, a, data))
    L = torch.randn(2, 9, dtype=DT, requires_grad=True)
    assert torch.autograd.gradcheck(lambda L_: render_envmap(n, a, L_), (L,))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_finite_gradients_at_normals_parallel_to_the_view(dtype):
    env = _sky(8, 16).to(dtype)
    a = _coefficients(1, 3, 3)[0].to(dtype)
    for v in ([0.0, 0.0, 1.0], [1e-13, 0.0, 1.0], [0.0, 2.0, 0.0], [1.0, 0.0, 0.0]):
        n = torch.tensor([v], dtype=dtype, requires_grad=True)
        Lc = env.data.clone().requires_grad_()
        out = render_envmap(n, a, EnvironmentMap(Lc), light_order=6).sum()
        out.backward()
        assert torch.isfinite(out) and torch.isfinite(n.grad).all() and torch.isfinite(Lc.grad).all()
    # at and near the pole the gradient agrees with finite differences (taken in float64)
    env64 = env.to(DT)
    a64 = a.to(DT)
    for v in ([0.0, 0.0, 1.0], [1e-9, -2e-9, 1.0], [1e-4, -2e-4, 1.0], [0.3, 0.2, 0.9]):
        n0 = torch.tensor([v], dtype=dtype, requires_grad=True)
        render_envmap(n0, a, env, light_order=6).sum().backward()
        h = 1e-6
        for i in range(3):
            e = torch.zeros(1, 3, dtype=DT)
            e[0, i] = h
            nd = torch.tensor([v], dtype=DT)
            fd = (render_envmap(nd + e, a64, env64, light_order=6).sum() - render_envmap(nd - e, a64, env64, light_order=6).sum()) / (2 * h)
            tol = 1e-4 if dtype == torch.float64 else 2e-2
            assert float(n0.grad[0, i]) == pytest.approx(float(fd), rel=tol, abs=tol * float(n0.grad.abs().max()))


def test_bad_inputs_raise():
    env = EnvironmentMap(torch.ones(4, 8, 3))
    n = torch.tensor([[0.0, 0.0, 1.0]])
    a = torch.zeros(3, 4)
    with pytest.raises(ValueError, match="light_order"):
        render_envmap(n, a, env)
    with pytest.raises(ValueError, match="channel"):
        render_envmap(n, torch.zeros(2, 4), env, light_order=1)
    with pytest.raises(ValueError, match="isotropic"):
        render_envmap(n, torch.zeros(3, 5), env, light_order=1)
    with pytest.raises(TypeError, match="env"):
        render_envmap(n, a, "map.exr", light_order=1)
    with pytest.raises(TypeError, match="env"):
        render_envmap(n.double(), a.double(), env, light_order=1)
    with pytest.raises(ValueError, match="data"):
        EnvironmentMap(torch.ones(4, 8))
    with pytest.raises(ValueError, match="NaN"):
        EnvironmentMap(torch.full((2, 4, 3), float("nan")))
    with pytest.raises(ValueError, match="entries"):
        sh_evaluate(torch.ones(3, 5), n)
    with pytest.raises(TypeError, match="env"):
        sh_coefficients(torch.ones(4, 8, 3), 2)
    with pytest.raises(ValueError, match="supersample"):
        render_envmap_reference(n, a.unsqueeze(0), env, supersample=0)


def test_from_exr_reads_the_layout(tmp_path):
    from torch_hsh.io import write_exr

    rgb = np.random.default_rng(0).random((4, 8, 3)).astype(np.float32)
    path = write_exr(tmp_path / "env.exr", {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]})
    env = EnvironmentMap.from_exr(path, dtype=DT, rotation=0.5)
    assert env.shape == (4, 8, 3) and env.rotation == 0.5
    np.testing.assert_allclose(env.data.numpy(), rgb, rtol=0, atol=0)


def test_environment_lighting_module_learns_the_light():
    from torch_hsh.render.envmap import EnvironmentLighting

    env = _sky(8, 16)
    n = _normals(64, seed=12)
    a = _coefficients(1, 3, 1)[0]
    fixed = EnvironmentLighting(env, light_order=3, learnable=False)
    assert "coefficients" in dict(fixed.named_buffers())
    torch.testing.assert_close(fixed(n, a), render_envmap(n, a, env, light_order=3), atol=1e-13, rtol=0)
    target = fixed(n, a)
    light = EnvironmentLighting(torch.zeros(3, 16, dtype=DT))
    opt = torch.optim.Adam(light.parameters(), lr=0.05)
    losses = []
    for _ in range(20):
        opt.zero_grad()
        loss = ((light(n, a) - target) ** 2).mean()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.2 * losses[0]
    assert light.to_map(4, 8).shape == (4, 8, 3)
    with pytest.raises(ValueError, match="light_order"):
        EnvironmentLighting(env)
