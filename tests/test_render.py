"""Tests of the differentiable photometric-stereo renderer (torch_hsh.render)."""
import math

import pytest
import torch

import torch_hsh
from torch_hsh import render as R
from torch_hsh.brdf import BlinnPhong, CookTorranceGGX, Lambertian

DT = torch.float64


def _normals(p, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(p, 3, generator=g, dtype=DT) * torch.tensor([0.5, 0.5, 0.3], dtype=DT)
    n[:, 2] += 1.0
    return torch.nn.functional.normalize(n, dim=-1)


def _lights(l, seed=1):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(l, 3, generator=g, dtype=DT) * torch.tensor([0.6, 0.6, 0.2], dtype=DT)
    d[:, 2] += 0.8
    return torch.nn.functional.normalize(d, dim=-1)


def test_lambertian_coefficients_render_rho_over_pi():
    n, l = _normals(30), _lights(12)
    rho = torch.rand(30, 3, dtype=DT)
    a = torch.zeros(30, 3, 10, dtype=DT)
    a[..., 0] = 2.0 * rho  # a_00^0 = 2 rho (math notes section 4)
    e = torch.rand(12, 3, dtype=DT) + 0.5
    img = R.render_coefficients(n, l, a, e)
    ref = e[:, None, :] * rho[None] / math.pi * (l @ n.T).clamp(min=0).unsqueeze(-1)
    assert torch.allclose(img, ref, atol=1e-12)
    # the analytic Lambertian model gives the same image
    img2 = R.render_model(n, l, Lambertian(rho), e)
    assert torch.allclose(img2, ref, atol=1e-12)


def test_coefficient_path_matches_local_frame_basis():
    """World-space shading basis == local-frame basis evaluated in the frame of n."""
    n, l = _normals(20, 3), _lights(9, 4)
    a = torch.randn(20, 3, 20, dtype=DT)

    def model(wi, wo):
        return torch.einsum("...k,...ck->...c", torch_hsh.helmholtz_isotropic(wi, wo, 3), a.expand(wi.shape[0], *a.shape))

    img = R.render_coefficients(n, l, a)
    img2 = R.render_model(n, l, model)
    assert torch.allclose(img, img2, atol=1e-10)


def test_analytic_model_matches_manual_shading():
    n, l = _normals(16, 5), _lights(7, 6)
    m = CookTorranceGGX(albedo=torch.rand(16, 3, dtype=DT), specular=torch.full((16, 1), 0.5, dtype=DT),
                        roughness=torch.full((16, 1), 0.3, dtype=DT))
    img = R.render(n, l, m)
    v = torch.tensor([0.0, 0.0, 1.0], dtype=DT)
    for j in (0, 3, 6):
        for p in (0, 7, 15):
            frame = torch_hsh.frames.local_frame(n[p])
            wi, wo = frame @ l[j], frame @ v
            f = m(wi.expand(16, 3), wo.expand(16, 3))[p]
            ref = f * max(0.0, float(n[p] @ l[j]))
            assert torch.allclose(img[j, p], ref, atol=1e-12)


def test_attached_shadow_and_visibility():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=DT)
    l = torch.tensor([[0.0, 0.6, -0.8], [0.0, 0.6, 0.8]], dtype=DT)
    img = R.render(n, l, BlinnPhong(0.7, 0.3, 20.0))
    assert torch.all(img[0] == 0) and torch.all(img[1] > 0)
    vis = torch.tensor([[1.0, 1.0], [1.0, 0.0]], dtype=DT)
    img2 = R.render(n, l, BlinnPhong(0.7, 0.3, 20.0), visibility=vis)
    assert torch.all(img2[1, 1] == 0) and torch.equal(img2[1, 0], img[1, 0])


def test_image_maps_shape_and_mask():
    n = _normals(12).reshape(3, 4, 3)
    a = torch.zeros(3, 4, 3, 4, dtype=DT)
    a[..., 0] = 1.0
    mask = torch.zeros(3, 4, dtype=torch.bool)
    mask[1] = True
    img = R.render(n, _lights(5), a, mask=mask)
    assert img.shape == (5, 3, 4, 3)
    assert torch.all(img[:, 0] == 0) and torch.all(img[:, 1] >= 0) and float(img[:, 1].sum()) > 0


def test_noise_seeded_and_statistics():
    x = torch.full((200_000,), 0.5, dtype=DT)
    a = R.add_sensor_noise(x, read_std=0.01, shot_gain=0.0008, seed=3)
    b = R.add_sensor_noise(x, read_std=0.01, shot_gain=0.0008, seed=3)
    c = R.add_sensor_noise(x, read_std=0.01, shot_gain=0.0008, seed=4)
    assert torch.equal(a, b) and not torch.equal(a, c)
    expected = math.sqrt(0.01 ** 2 + 0.0008 * 0.5)
    assert abs(float((a - x).std()) - expected) < 0.02 * expected
    assert abs(float((a - x).mean())) < 5 * expected / math.sqrt(x.numel())


def test_render_noise_names_match_add_sensor_noise():
    n, l = _normals(40), _lights(6)
    a = torch.zeros(40, 3, 10, dtype=DT)
    a[..., 0] = 1.0
    clean = R.render(n, l, a)
    got = R.render(n, l, a, read_std=0.01, shot_gain=0.002, seed=5)
    assert torch.equal(got, R.add_sensor_noise(clean, read_std=0.01, shot_gain=0.002, seed=5))
    with pytest.raises(TypeError, match="read_noise"):  # one name per thing: the old names are gone
        R.render(n, l, a, read_noise=0.01)


def test_quantize_and_saturation():
    x = torch.tensor([-0.1, 0.3, 0.50001, 2.0], dtype=DT, requires_grad=True)
    q = R.quantize(x, bits=2, max_value=1.0)
    assert torch.allclose(q, torch.tensor([0.0, 1 / 3, 2 / 3, 1.0], dtype=DT))
    q.sum().backward()  # straight-through inside the range, zero outside
    assert torch.equal(x.grad, torch.tensor([0.0, 1.0, 1.0, 0.0], dtype=DT))
    n, l = _normals(10), _lights(6)
    img = R.render(n, l, BlinnPhong(0.9, 2.0, 50.0), saturation=0.2, bits=16)
    assert float(img.max()) <= 0.2 + 1e-15
    codes = img / 0.2 * 65535
    assert torch.allclose(codes, codes.round(), atol=1e-6)


def test_gradients_wrt_normals_and_coefficients():
    n = _normals(4, 9).requires_grad_(True)
    a = torch.randn(4, 3, 10, dtype=DT, requires_grad=True)
    l = _lights(6, 2)
    assert torch.autograd.gradcheck(lambda nn_, aa: R.render_coefficients(nn_, l, aa), (n, a))
    m_alb = torch.rand(4, 3, dtype=DT, requires_grad=True)
    img = R.render(n, l, CookTorranceGGX(m_alb, 0.5, 0.4))
    img.sum().backward()
    assert torch.isfinite(n.grad).all() and m_alb.grad.abs().sum() > 0


def _local_frame_reference(n, l, a, e, order):
    """I = e sum_k a_k B_k(l_loc, v_loc) max(0, n.l), with the light and the view (0, 0, 1) expressed in an
    explicit tangent frame (t, b, n) of each normal and the local-frame basis ``helmholtz_isotropic``:
    independent of ``helmholtz_isotropic_world``, which the renderer uses."""
    helper = torch.where((n[:, :1].abs() < 0.9), torch.tensor([1.0, 0.0, 0.0], dtype=DT),
                         torch.tensor([0.0, 1.0, 0.0], dtype=DT))
    t = torch.nn.functional.normalize(torch.linalg.cross(helper, n, dim=-1), dim=-1)
    b = torch.linalg.cross(n, t, dim=-1)
    frame = torch.stack([t, b, n], -2)  # (P, 3, 3): rows t, b, n
    v = torch.tensor([0.0, 0.0, 1.0], dtype=DT)
    P, L = n.shape[0], l.shape[0]
    l_loc = torch.einsum("pij,lj->lpi", frame, l)  # (L, P, 3)
    v_loc = torch.einsum("pij,j->pi", frame, v).expand(L, P, 3)
    B = torch_hsh.helmholtz_isotropic(l_loc.reshape(-1, 3), v_loc.reshape(-1, 3), order).reshape(L, P, -1)
    cos = (l @ n.T).clamp(min=0.0)  # (L, P)
    return torch.einsum("lpk,pck->lpc", B * cos[..., None], a) * e[:, None]


def test_shading_basis_linear_model():
    n, l = _normals(7), _lights(5)
    Phi = R.shading_basis(n, l, 2)
    a = torch.randn(7, 3, 10, dtype=DT)
    e = torch.rand(5, 3, dtype=DT) + 0.1
    img = torch.einsum("lpk,pck->lpc", Phi, a) * e[:, None]
    assert torch.allclose(img, R.render_coefficients(n, l, a, e), atol=1e-12)
    # both rest on helmholtz_isotropic_world: compare with explicit local frames as well
    ref = _local_frame_reference(n, l, a, e, 2)
    assert float(ref.abs().max()) > 0.1 and bool(((l @ n.T) > 0).any())
    assert torch.allclose(img, ref, atol=1e-12)
    assert torch.allclose(R.render_coefficients(n, l, a, e), ref, atol=1e-12)


def test_bad_inputs():
    n, l = _normals(5), _lights(3)
    with pytest.raises(ValueError, match="coefficients"):
        R.render(n, l, torch.zeros(4, 3, 10, dtype=DT))
    with pytest.raises(ValueError, match="isotropic Helmholtz basis"):
        R.render(n, l, torch.zeros(5, 3, 11, dtype=DT))
    with pytest.raises(TypeError, match="brdf"):
        R.render(n, l, "ggx")
    with pytest.raises(ValueError, match="lights"):
        R.render(n, l[:, :2], torch.zeros(5, 3, 10, dtype=DT))
    with pytest.raises(ValueError, match="intensities"):
        R.render(n, l, torch.zeros(5, 3, 10, dtype=DT), intensities=torch.ones(4, 3, dtype=DT))
    with pytest.raises(ValueError, match="visibility"):
        R.render(n, l, torch.zeros(5, 3, 10, dtype=DT), visibility=torch.ones(3, 4))
    with pytest.raises(ValueError, match="bits"):
        R.quantize(torch.ones(3), bits=0)
    with pytest.raises(ValueError, match="read_std"):
        R.add_sensor_noise(torch.ones(3), read_std=-1.0)


def test_ambient_fraction_in_cast_shadows():
    n = _normals(6)
    l = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.2, 0.84], [0.0, 0.6, -0.8]], dtype=DT)
    brdf = BlinnPhong(0.7, 0.3, 20.0)
    vis = torch.ones(3, 6, dtype=torch.bool)
    vis[0, :3] = False
    vis[1, 4] = False
    vis[2, :] = False
    lit = R.render(n, l, brdf)
    img0 = R.render(n, l, brdf, visibility=vis)
    assert torch.equal(R.render(n, l, brdf, visibility=vis, ambient=0.0), img0)  # default unchanged
    img = R.render(n, l, brdf, visibility=vis, ambient=0.2)
    assert torch.equal(img[vis], lit[vis])  # lit observations untouched
    assert torch.allclose(img[~vis], 0.2 * lit[~vis], rtol=1e-12)  # shadows keep 20 % of the light
    assert bool((img[0, :3] > 0).all()) and bool((img[2] == 0).all())  # attached shadows stay black
    soft = torch.full((3, 6), 0.5, dtype=DT)
    assert torch.allclose(R.render(n, l, brdf, visibility=soft, ambient=0.2), 0.6 * lit)
    assert torch.equal(R.render(n, l, brdf, ambient=0.5), lit)  # no visibility: nothing to fill
    with pytest.raises(ValueError, match="ambient"):
        R.render(n, l, brdf, visibility=vis, ambient=1.5)
