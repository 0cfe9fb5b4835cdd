"""Tests of the nn.Module layers :class:`torch_hsh.HSH` and :class:`torch_hsh.HelmholtzBRDF`."""
from __future__ import annotations

import io
import math
import warnings

import numpy as np
import pytest
import torch

import torch_hsh
from torch_hsh import HSH, HelmholtzBRDF
from torch_hsh.frames import to_local


def _hemi(n, *lead, dtype=torch.float64, seed=0):
    """Random unit directions on the upper hemisphere, shape (*lead, n, 3) or (n, 3)."""
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(*lead, n, 3, generator=g, dtype=dtype)
    v = torch.nn.functional.normalize(v, dim=-1)
    return torch.cat([v[..., :2], v[..., 2:].abs()], dim=-1)


def _basis(isotropic: bool) -> str:
    return "helmholtz_isotropic" if isotropic else "helmholtz_anisotropic"


def _random_model(order=3, isotropic=True, channels=2, dtype=torch.float64, seed=1, **kw):
    k = torch_hsh.num_isotropic(order) if isotropic else torch_hsh.num_anisotropic(order)
    g = torch.Generator().manual_seed(seed)
    init = torch.randn(channels, k, generator=g, dtype=dtype)
    return HelmholtzBRDF(order, basis=_basis(isotropic), channels=channels, init=init, dtype=dtype, **kw)


# --------------------------------------------------------------------------- HSH
def test_hsh_module_matches_functional():
    layer = HSH(3)
    d = _hemi(7, 2)
    out = layer(d)
    assert out.shape == (2, 7, 16)
    torch.testing.assert_close(out, torch_hsh.hsh(d, 3), rtol=0, atol=0)
    assert layer.num_functions == 16
    assert list(layer.parameters()) == []
    assert "order=3" in repr(layer)


def test_hsh_module_bad_order():
    with pytest.raises(ValueError, match="order"):
        HSH(-1)
    with pytest.raises(TypeError, match="order"):
        HSH(2.0)


# ----------------------------------------------------------- shapes / broadcasting
@pytest.mark.parametrize("isotropic", [True, False])
def test_forward_shapes_and_linearity(isotropic):
    m = _random_model(order=2, isotropic=isotropic, channels=3)
    wi, wo = _hemi(11, seed=2), _hemi(11, seed=3)
    out = m(wi, wo)
    assert out.shape == (11, 3) and out.dtype == torch.float64
    # forward == basis @ coefficients.T, basis from the functional API
    fun = torch_hsh.helmholtz_isotropic if isotropic else torch_hsh.helmholtz_anisotropic
    B = fun(wi, wo, 2)
    torch.testing.assert_close(out, B @ m.coefficients.T)
    torch.testing.assert_close(m.basis(wi, wo), B)
    # broadcasting of leading dimensions between wi and wo
    out2 = m(wi[:4, None, :], wo[None, :5, :])
    assert out2.shape == (4, 5, 3)
    torch.testing.assert_close(out2[2, 3], m(wi[2], wo[3]))


def test_per_call_per_pixel_coefficients():
    m = HelmholtzBRDF(2, channels=3, dtype=torch.float64)
    H, W, K = 4, 5, m.num_functions
    g = torch.Generator().manual_seed(5)
    coeffs = torch.randn(H, W, 3, K, generator=g, dtype=torch.float64)
    wi = _hemi(W, H, seed=6)  # (H, W, 3)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # shared view direction
    out = m(wi, wo, coeffs)
    assert out.shape == (H, W, 3)
    for h in range(H):
        for w in range(W):
            ref = torch_hsh.helmholtz_isotropic(wi[h, w], wo, 2) @ coeffs[h, w].T
            torch.testing.assert_close(out[h, w], ref)
    # (H, 1, C, K) coefficients broadcast over the W axis of the directions
    out_row = m(wi, wo, coeffs[:, :1])
    torch.testing.assert_close(out_row[:, 3], m(wi[:, 3], wo, coeffs[:, 0]))
    # (C, K) per-call coefficients behave like module coefficients
    with torch.no_grad():
        m.coefficients.copy_(coeffs[1, 2])
    torch.testing.assert_close(m(wi, wo, coeffs[1, 2]), m(wi, wo))
    # gradients reach per-call coefficients (e.g. predicted by a network)
    c = coeffs.clone().requires_grad_(True)
    m(wi, wo, c).sum().backward()
    assert c.grad is not None and c.grad.abs().sum() > 0


# ------------------------------------------------------------------- init values
@pytest.mark.parametrize("isotropic", [True, False])
def test_lambertian_init_equals_rho_over_pi(isotropic):
    rho = [0.2, 0.5, 0.9]
    m = HelmholtzBRDF(3, basis=_basis(isotropic), channels=3, albedo=rho, dtype=torch.float64)
    wi, wo = _hemi(200, seed=7), _hemi(200, seed=8)
    out = m(wi, wo)
    expected = torch.tensor(rho, dtype=torch.float64) / math.pi
    torch.testing.assert_close(out, expected.expand(200, 3), rtol=1e-12, atol=1e-12)
    # only a_00^0 = 2 rho is non-zero
    assert torch.count_nonzero(m.coefficients[:, 1:]) == 0
    torch.testing.assert_close(m.coefficients[:, 0], 2 * torch.tensor(rho, dtype=torch.float64))
    # default rho = 0.5, float32
    m32 = HelmholtzBRDF(2, basis=_basis(isotropic))
    torch.testing.assert_close(m32(wi.float(), wo.float()), torch.full((200, 1), 0.5 / math.pi))
    # below the horizon: 0
    below = torch.tensor([[0.3, 0.0, -0.9]], dtype=torch.float64)
    assert torch.all(m(below, wo[:1]) == 0)


def test_zeros_and_tensor_init():
    m = HelmholtzBRDF(2, channels=2, init="zeros")
    assert torch.all(m.coefficients == 0)
    v = torch.arange(10, dtype=torch.float32)
    m2 = HelmholtzBRDF(2, channels=2, init=v)
    assert m2.coefficients.shape == (2, 10)
    torch.testing.assert_close(m2.coefficients, v.expand(2, 10))
    v[0] = 100.0  # the module keeps its own copy
    assert m2.coefficients[0, 0] == 0


# ------------------------------------------------------------------- reciprocity
@pytest.mark.parametrize("isotropic", [True, False])
def test_reciprocity(isotropic):
    m = _random_model(order=3, isotropic=isotropic, channels=2)
    wi, wo = _hemi(300, seed=9), _hemi(300, seed=10)
    a, b = m(wi, wo), m(wo, wi)
    assert a.abs().max() > 0.1  # non-trivial values
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------ world space
def test_forward_world_matches_local():
    m = _random_model(order=3, channels=2)
    g = torch.Generator().manual_seed(11)
    n = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    wi_l, wo_l = _hemi(50, seed=12), _hemi(50, seed=13)
    from torch_hsh.frames import to_world

    wi_w, wo_w = to_world(wi_l, n), to_world(wo_l, n)
    torch.testing.assert_close(m.forward_world(wi_w, wo_w, n), m(wi_l, wo_l), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(m(to_local(wi_w, n), to_local(wo_w, n)), m(wi_l, wo_l), rtol=1e-10, atol=1e-10)
    # per-pixel coefficients in world space, gradient to the normal
    nn_ = n.clone().requires_grad_(True)
    c = torch.randn(50, 2, m.num_functions, generator=g, dtype=torch.float64)
    out = m.forward_world(wi_w, wo_w, nn_, c)
    assert out.shape == (50, 2)
    torch.testing.assert_close(out, m(wi_l, wo_l, c), rtol=1e-10, atol=1e-10)
    out.sum().backward()
    assert torch.isfinite(nn_.grad).all()


def test_forward_world_rejects_anisotropic():
    m = HelmholtzBRDF(2, basis="helmholtz_anisotropic")
    d = torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="isotropic"):
        m.forward_world(d, d, d)


# ------------------------------------------------------------------ nonnegative
def test_nonnegative_straight_through():
    m = _random_model(order=2, channels=1, nonnegative=True)
    ref = _random_model(order=2, channels=1, nonnegative=False)
    wi, wo = _hemi(400, seed=14), _hemi(400, seed=15)
    out, raw = m(wi, wo), ref(wi, wo)
    assert (raw < 0).any() and (raw > 0).any()
    torch.testing.assert_close(out, raw.clamp(min=0), rtol=0, atol=0)
    # straight-through: the gradient is that of the unclamped expansion
    m(wi, wo).sum().backward()
    ref(wi, wo).sum().backward()
    torch.testing.assert_close(m.coefficients.grad, ref.coefficients.grad)
    # Lambertian init is unchanged by the clamp
    lam = HelmholtzBRDF(2, nonnegative=True, dtype=torch.float64)
    torch.testing.assert_close(lam(wi, wo), torch.full((400, 1), 0.5 / math.pi, dtype=torch.float64))


# ---------------------------------------------------------------------- training
def test_adam_fits_band_limited_target():
    torch.manual_seed(0)
    target = _random_model(order=2, channels=2, dtype=torch.float32, seed=21)
    wi, wo = _hemi(2048, dtype=torch.float32, seed=16), _hemi(2048, dtype=torch.float32, seed=17)
    with torch.no_grad():
        y = target(wi, wo)
    model = HelmholtzBRDF(2, channels=2)
    opt = torch.optim.Adam(model.parameters(), lr=0.1)
    losses = []
    for step in range(150):
        idx = torch.randint(0, 2048, (256,))
        loss = torch.mean((model(wi[idx], wo[idx]) - y[idx]) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    with torch.no_grad():
        final = torch.mean((model(wi, wo) - y) ** 2).item()
        initial = torch.mean((HelmholtzBRDF(2, channels=2)(wi, wo) - y) ** 2).item()
    assert final < 1e-4 * initial
    assert losses[-1] < 1e-3 * losses[0]
    # the fitted coefficients approach the target's (the basis is orthonormal)
    torch.testing.assert_close(model.coefficients.detach(), target.coefficients.detach(), rtol=0, atol=0.01)


# ------------------------------------------------------ state_dict, dtype, device
@pytest.mark.parametrize("learnable", [True, False])
def test_state_dict_round_trip(learnable):
    m = _random_model(order=2, channels=3, learnable=learnable, dtype=torch.float32)
    assert ("coefficients" in dict(m.named_parameters())) == learnable
    assert ("coefficients" in dict(m.named_buffers())) != learnable
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    buf.seek(0)
    m2 = HelmholtzBRDF(2, channels=3, init="zeros", learnable=learnable)
    m2.load_state_dict(torch.load(buf))
    wi, wo = _hemi(20, dtype=torch.float32, seed=18), _hemi(20, dtype=torch.float32, seed=19)
    torch.testing.assert_close(m2(wi, wo), m(wi, wo), rtol=0, atol=0)
    # a state_dict of another order does not load, and says why
    m3 = HelmholtzBRDF(3, channels=3, learnable=learnable)
    with pytest.raises(ValueError, match=r"order=2 \(module has 3\)"):
        m3.load_state_dict(m.state_dict())
    # a checkpoint from before the configuration was kept still loads (strict), or fails on shapes
    old = {k: v for k, v in m.state_dict().items() if k != "_extra_state"}
    m2.load_state_dict(old)
    with pytest.raises(RuntimeError, match="size mismatch"):
        m3.load_state_dict(old)


def test_hsh_module_state_dict_keeps_the_order():
    """HSH has no parameters; its order is in the state_dict, so a checkpoint of another order does not load."""
    from torch_hsh import HSH

    buf = io.BytesIO()
    torch.save(HSH(5).state_dict(), buf)
    buf.seek(0)
    sd = torch.load(buf)
    assert sd["_extra_state"] == {"order": 5}
    HSH(5).load_state_dict(sd)
    with pytest.raises(ValueError, match=r"order=5 \(module has order=2\)"):
        HSH(2).load_state_dict(sd)
    # inside a model, and a checkpoint from before the order was kept (empty) still loads, strict
    net = torch.nn.Sequential(HSH(3), torch.nn.Linear(16, 1))
    with pytest.raises(ValueError, match="order=3"):
        torch.nn.Sequential(HSH(4), torch.nn.Linear(16, 1)).load_state_dict(net.state_dict())
    HSH(2).load_state_dict({})
    old = {k: v for k, v in net.state_dict().items() if not k.endswith("_extra_state")}
    torch.nn.Sequential(HSH(3), torch.nn.Linear(16, 1)).load_state_dict(old)


@pytest.mark.parametrize("isotropic", [True, False])
def test_checkpoint_keeps_order_channels_isotropy(isotropic):
    m = HelmholtzBRDF(2, basis=_basis(isotropic), channels=3, nonnegative=True, learnable=False, dtype=torch.float64)
    with torch.no_grad():
        m.coefficients.copy_(torch.randn(m.coefficients.shape, generator=torch.Generator().manual_seed(3),
                                         dtype=torch.float64))
    sd = m.state_dict()
    assert sd["_extra_state"]["order"] == 2 and sd["_extra_state"]["basis"] == _basis(isotropic)
    buf = io.BytesIO()
    torch.save(sd, buf)
    buf.seek(0)
    m2 = HelmholtzBRDF.from_state_dict(torch.load(buf))  # no order/channels/isotropic repeated
    assert (m2.order, m2.basis_name, m2.channels, m2.nonnegative, m2.learnable) == (2, _basis(isotropic), 3, True, False)
    assert m2.coefficients.dtype == torch.float64 and torch.equal(m2.coefficients, m.coefficients)
    # inside a bigger model: the prefix selects it
    net = torch.nn.Sequential(torch.nn.Linear(2, 2), m)
    m3 = HelmholtzBRDF.from_state_dict(net.state_dict(), prefix="1.")
    assert torch.equal(m3.coefficients, m.coefficients)
    with pytest.raises(KeyError, match="_extra_state"):
        HelmholtzBRDF.from_state_dict({"coefficients": m.coefficients})
    # a 0.1 checkpoint kept `isotropic: bool`: it loads as the same basis
    old = dict(sd, _extra_state={k: v for k, v in sd["_extra_state"].items() if k != "basis"})
    old["_extra_state"].update(version=1, isotropic=isotropic)
    m4 = HelmholtzBRDF.from_state_dict(old)
    assert m4.basis_name == _basis(isotropic) and torch.equal(m4.coefficients, m.coefficients)
    m.load_state_dict(old)


def test_to_float64_and_dtype_mismatch():
    m = _random_model(order=3, channels=2, dtype=torch.float32)
    wi, wo = _hemi(30, seed=20), _hemi(30, seed=21)
    out32 = m(wi.float(), wo.float())
    m64 = m.to(torch.float64)
    assert m64.coefficients.dtype == torch.float64
    out64 = m64(wi, wo)
    assert out64.dtype == torch.float64
    torch.testing.assert_close(out64.float(), out32, rtol=1e-4, atol=1e-5)
    with pytest.raises(TypeError, match="dtype"):
        m64(wi.float(), wo.float())
    assert m64.albedo(wo).dtype == torch.float64


def test_to_device_keeps_buffers_and_params():
    m = HelmholtzBRDF(2, learnable=False)
    m = m.to(torch.device("cpu"), torch.float64)
    assert m.coefficients.device.type == "cpu" and m.coefficients.dtype == torch.float64
    assert not m.coefficients.requires_grad


# ------------------------------------------------------------- trace / compile
def test_jit_trace_equivalence():
    m = _random_model(order=3, channels=2, dtype=torch.float32)
    wi, wo = _hemi(64, dtype=torch.float32, seed=22), _hemi(64, dtype=torch.float32, seed=23)
    m(wi, wo)  # warm the constant cache so the two trace-check runs see identical graphs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        traced = torch.jit.trace(m, (wi, wo))
        h = HSH(3)
        h(wi)
        traced_h = torch.jit.trace(h, (wi,))
    torch.testing.assert_close(traced(wi, wo), m(wi, wo))
    wi2, wo2 = _hemi(9, dtype=torch.float32, seed=24), _hemi(9, dtype=torch.float32, seed=25)
    torch.testing.assert_close(traced(wi2, wo2), m(wi2, wo2))
    torch.testing.assert_close(traced_h(wi2), h(wi2))


def _compile_or_skip(mod, **kw):
    if not hasattr(torch, "compile"):
        pytest.skip("torch.compile is not available in this torch build")
    return torch.compile(mod, **kw)


def test_torch_compile_equivalence():
    m = _random_model(order=3, channels=2, dtype=torch.float32)
    wi, wo = _hemi(64, dtype=torch.float32, seed=26), _hemi(64, dtype=torch.float32, seed=27)
    c = torch.randn(64, 2, m.num_functions)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cm = _compile_or_skip(m, backend="eager", fullgraph=True)
        torch.testing.assert_close(cm(wi, wo), m(wi, wo))
        torch.testing.assert_close(cm(wi, wo, c), m(wi, wo, c))
        # gradients through the compiled module
        cm(wi, wo).pow(2).sum().backward()
    g = m.coefficients.grad.clone()
    m.coefficients.grad = None
    m(wi, wo).pow(2).sum().backward()
    torch.testing.assert_close(g, m.coefficients.grad)


def test_torch_compile_aot_eager():
    m = HSH(2)
    d = _hemi(16, dtype=torch.float32, seed=28)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cm = _compile_or_skip(m, backend="aot_eager")
        torch.testing.assert_close(cm(d), m(d))


# -------------------------------------------------------------------- bad input
def test_bad_coefficients():
    m = HelmholtzBRDF(2, channels=3)
    d = _hemi(4, dtype=torch.float32)
    K = m.num_functions
    with pytest.raises(ValueError, match=r"coefficients.*\(\.\.\., 3, 10\)"):
        m(d, d, torch.zeros(4, 2, K))  # wrong channels
    with pytest.raises(ValueError, match="coefficients"):
        m(d, d, torch.zeros(4, 3, K + 1))  # wrong K
    with pytest.raises(ValueError, match="coefficients"):
        m(d, d, torch.zeros(K))  # missing channel axis
    with pytest.raises(ValueError, match="broadcast"):
        m(d, d, torch.zeros(5, 3, K))  # leading shape does not broadcast
    with pytest.raises(TypeError, match="coefficients"):
        m(d, d, torch.zeros(4, 3, K, dtype=torch.float64))
    with pytest.raises(TypeError, match="coefficients"):
        m(d, d, np.zeros((3, K), dtype=np.float32))
    with pytest.raises(ValueError, match="NaN"):
        m(d, d, torch.full((3, K), float("nan")))


def test_bad_directions():
    m = HelmholtzBRDF(2)
    with pytest.raises(ValueError, match="wi"):
        m(torch.zeros(4, 2), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="broadcast"):
        m(torch.rand(4, 3), torch.rand(5, 3))
    with pytest.raises(TypeError, match="wo"):
        m(torch.rand(4, 3), torch.rand(4, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="wi"):
        m(torch.ones(4, 3, dtype=torch.int64), torch.rand(4, 3))


def test_bad_constructor_args():
    with pytest.raises(ValueError, match="init"):
        HelmholtzBRDF(2, channels=2, init=torch.zeros(2, 11))
    with pytest.raises(ValueError, match="init"):
        HelmholtzBRDF(2, init="gaussian")
    with pytest.raises(TypeError, match="init"):
        HelmholtzBRDF(2, init=3)
    with pytest.raises(ValueError, match="channels"):
        HelmholtzBRDF(2, channels=0)
    with pytest.raises(ValueError, match="albedo"):
        HelmholtzBRDF(2, channels=3, albedo=[0.1, 0.2])
    with pytest.raises(ValueError, match="order"):
        HelmholtzBRDF(17, basis="helmholtz_anisotropic")
    with pytest.raises(ValueError, match="order"):
        HelmholtzBRDF(-1)
    with pytest.raises(TypeError, match="dtype"):
        HelmholtzBRDF(2, dtype=torch.float16)
    with pytest.raises(ValueError, match="`basis` must be one of"):
        HelmholtzBRDF(2, basis="isotropic")
    with pytest.raises(TypeError, match="isotropic"):  # the 0.1 keyword is gone
        HelmholtzBRDF(2, isotropic=True)


def test_repr_and_properties():
    m = HelmholtzBRDF(3, channels=3)
    r = repr(m)
    assert "order=3" in r and "channels=3" in r and "num_functions=20" in r and "isotropic" in r
    assert m.num_functions == 20
    assert torch.equal(m.indices, torch_hsh.isotropic_indices(3))
    a = HelmholtzBRDF(2, basis="helmholtz_anisotropic")
    assert a.num_functions == 45 and "anisotropic" in repr(a)
    assert torch.equal(a.indices, torch_hsh.anisotropic_indices(2))


# ----------------------------------------------------------------------- albedo
def _albedo_quadrature(m, wo, coeffs=None, n_theta=24, n_phi=32):
    """Gauss-Legendre in cos(theta_i) x uniform phi_i: exact for these band-limited integrands."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    x = torch.tensor((x + 1) / 2, dtype=torch.float64)
    w = torch.tensor(w / 2, dtype=torch.float64)
    phi = torch.arange(n_phi, dtype=torch.float64) * (2 * math.pi / n_phi)
    s = torch.sqrt(1 - x * x)
    wi = torch.stack(
        [s[:, None] * torch.cos(phi)[None], s[:, None] * torch.sin(phi)[None], x[:, None].expand(-1, n_phi)], -1
    )  # (T, F, 3)
    weight = (w * x)[:, None] * (2 * math.pi / n_phi)  # cos(theta_i) dw
    f = m(wi[:, :, None, :], wo[None, None], coeffs)  # (T, F, N, C)
    return (f * weight[..., None, None]).sum((0, 1))


@pytest.mark.parametrize("isotropic,order", [(True, 0), (True, 1), (True, 4), (False, 1), (False, 3)])
def test_albedo_matches_quadrature(isotropic, order):
    m = _random_model(order=order, isotropic=isotropic, channels=2, seed=30 + order)
    wo = torch.cat([_hemi(12, seed=31), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)])
    with torch.no_grad():
        closed = m.albedo(wo)
        quad = _albedo_quadrature(m, wo)
    assert closed.shape == (14, 2)
    assert closed.abs().max() > 1e-2  # non-trivial
    torch.testing.assert_close(closed, quad, rtol=1e-10, atol=1e-10)


def test_albedo_lambertian_per_call_and_horizon():
    m = HelmholtzBRDF(3, channels=2, albedo=[0.3, 0.8], dtype=torch.float64)
    wo = _hemi(10, seed=32)
    torch.testing.assert_close(m.albedo(wo), torch.tensor([0.3, 0.8], dtype=torch.float64).expand(10, 2))
    # per-call per-sample coefficients
    g = torch.Generator().manual_seed(33)
    c = torch.randn(10, 2, m.num_functions, generator=g, dtype=torch.float64)
    out = m.albedo(wo, c)
    assert out.shape == (10, 2)
    for i in range(10):
        torch.testing.assert_close(out[i], m.albedo(wo[i], c[i]))
    with torch.no_grad():
        quad = torch.stack([_albedo_quadrature(m, wo[i : i + 1], c[i])[0] for i in range(3)])
    torch.testing.assert_close(out[:3], quad, rtol=1e-10, atol=1e-10)
    # below the horizon
    assert torch.all(m.albedo(torch.tensor([0.0, 0.6, -0.8], dtype=torch.float64)) == 0)


@pytest.mark.parametrize("isotropic", [True, False])
def test_albedo_agrees_with_fitting_module(isotropic):
    fitting = pytest.importorskip("torch_hsh.fitting")
    if not hasattr(fitting, "directional_albedo"):
        pytest.skip("torch_hsh.fitting.directional_albedo is not available")
    m = _random_model(order=3, isotropic=isotropic, channels=2, seed=40)
    wo = _hemi(9, seed=41)
    basis = "helmholtz_isotropic" if isotropic else "helmholtz_anisotropic"
    ref = torch.stack([fitting.directional_albedo(m.coefficients.detach()[c], wo, basis=basis) for c in range(2)], -1)
    torch.testing.assert_close(m.albedo(wo).detach(), ref, rtol=1e-12, atol=1e-12)
