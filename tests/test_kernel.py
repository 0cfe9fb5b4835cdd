"""Tests of torch_hsh.kernel: values, orthonormality, symmetries, gradients and input checks."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import eval_jacobi, lpmv

import torch_hsh
from torch_hsh import (
    anisotropic_indices,
    helmholtz_anisotropic,
    helmholtz_isotropic,
    helmholtz_isotropic_cosines,
    helmholtz_isotropic_world,
    hsh,
    hsh_index,
    isotropic_indices,
    num_anisotropic,
    num_hsh,
    num_isotropic,
)
from torch_hsh.frames import to_local

F64 = torch.float64


@pytest.fixture(autouse=True, params=["auto", "torch"])
def backend(request):
    """Every test here runs on both kernel paths: "auto" (sphericart for the HSH where it is
    installed, the fused C kernels for the isotropic basis) and "torch" (the pure-torch fallback)."""
    torch_hsh.set_backend(request.param)
    yield request.param
    torch_hsh.set_backend("auto")


# --------------------------------------------------------------------------
# Independent reference (scipy.special.lpmv), straight from the math notes
# --------------------------------------------------------------------------
def _theta_ref(n: int, m: int, z: np.ndarray) -> np.ndarray:
    """N~_n^m P~_n^m(z), P without Condon-Shortley phase, shifted argument 2z - 1."""
    norm = math.sqrt((2 * n + 1) / (2 * math.pi) * math.factorial(n - m) / math.factorial(n + m))
    return norm * (-1.0) ** m * lpmv(m, n, 2.0 * z - 1.0)


def _theta_jacobi(n: int, m: int, z: np.ndarray) -> np.ndarray:
    """The same function through d^m P_n / dt^m = (n+m)! / (2^m n!) P_{n-m}^{(m,m)}(t) and
    sqrt(1 - t^2) = 2 sqrt(z (1 - z)): accurate next to the horizon, where lpmv's 1 - t^2 cancels."""
    norm = math.sqrt((2 * n + 1) / (2 * math.pi) * math.factorial(n - m) / math.factorial(n + m))
    scale = math.factorial(n + m) / (2.0**m * math.factorial(n))
    return norm * scale * (2.0 * np.sqrt(z * (1.0 - z))) ** m * eval_jacobi(n - m, m, m, 2.0 * z - 1.0)


def _phi_ref(m: int, phi: np.ndarray) -> np.ndarray:
    if m > 0:
        return math.sqrt(2.0) * np.cos(m * phi)
    if m == 0:
        return np.ones_like(phi)
    return (-1.0) ** m * math.sqrt(2.0) * np.sin(-m * phi)


def hsh_ref(d: np.ndarray, order: int, theta=_theta_ref) -> np.ndarray:
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    z = d[:, 2]
    phi = np.arctan2(d[:, 1], d[:, 0])
    cols = []
    for n in range(order + 1):
        for m in range(-n, n + 1):
            cols.append(theta(n, abs(m), z) * _phi_ref(m, phi))
    return np.stack(cols, axis=-1)


def iso_ref(wi: np.ndarray, wo: np.ndarray, order: int, theta=_theta_ref) -> np.ndarray:
    wi = wi / np.linalg.norm(wi, axis=-1, keepdims=True)
    wo = wo / np.linalg.norm(wo, axis=-1, keepdims=True)
    dphi = np.arctan2(wo[:, 1], wo[:, 0]) - np.arctan2(wi[:, 1], wi[:, 0])
    cols = []
    for p in range(order + 1):
        for r in range(p + 1):
            for q in range(r + 1):
                norm = 1.0 / math.sqrt(2.0 + 2.0 * (p == r))
                ang = 1.0 if q == 0 else math.sqrt(2.0) * np.cos(q * dphi)
                th = (theta(p, q, wi[:, 2]) * theta(r, q, wo[:, 2])
                      + theta(r, q, wi[:, 2]) * theta(p, q, wo[:, 2]))
                cols.append(norm * th * ang)
    return np.stack(cols, axis=-1)


def _gram(B: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return B.T @ (B * w[:, None])


def _hemi(n, seed=0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g, dtype=F64) * 0.9 + 0.05
    phi = torch.rand(n, generator=g, dtype=F64) * 2 * math.pi
    s = torch.sqrt(1 - z * z)
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], -1).to(dtype)


# --------------------------------------------------------------------------
# Counting and index tables
# --------------------------------------------------------------------------
def test_counts_and_index_tables():
    for P in range(6):
        assert num_hsh(P) == (P + 1) ** 2
        assert num_isotropic(P) == isotropic_indices(P).shape[0] == (P + 1) * (P + 2) * (P + 3) // 6
        assert num_anisotropic(P) == anisotropic_indices(P).shape[0]
    assert num_isotropic(3) == 20 and num_isotropic(8) == 165
    idx = isotropic_indices(4)
    assert bool((idx[:, 0] >= idx[:, 1]).all() and (idx[:, 1] >= idx[:, 2]).all() and (idx[:, 2] >= 0).all())
    assert len({tuple(r) for r in idx.tolist()}) == idx.shape[0]
    an = anisotropic_indices(2)
    flat_j = an[:, 0] ** 2 + an[:, 0] + an[:, 1]
    flat_k = an[:, 2] ** 2 + an[:, 2] + an[:, 3]
    assert bool((flat_j <= flat_k).all())
    assert an.shape[0] == 9 * 10 // 2
    assert hsh_index(3, -2) == 10 and hsh_index(0, 0) == 0
    with pytest.raises(ValueError):
        hsh_index(1, 2)


# --------------------------------------------------------------------------
# Values against the independent formula
# --------------------------------------------------------------------------
@pytest.mark.parametrize("order", [0, 1, 2, 5, 8, 12])
def test_hsh_matches_lpmv_reference(order):
    d = _hemi(64, seed=order)
    d[0] = torch.tensor([0.0, 0.0, 1.0], dtype=F64)  # pole
    d[1] = torch.tensor([0.6, -0.8, 0.0], dtype=F64)  # horizon
    d[2] = 2.5 * d[2]  # non-unit input
    ours = hsh(d, order).numpy()
    ref = hsh_ref(d.numpy(), order)
    assert ours.shape == (64, (order + 1) ** 2)
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-9)


def test_hsh_all_orders_0_to_12_prefix_consistent():
    d = _hemi(32, seed=3)
    full = hsh(d, 12)
    ref = hsh_ref(d.numpy(), 12)
    np.testing.assert_allclose(full.numpy(), ref, rtol=1e-9, atol=1e-9)
    for P in range(13):
        torch.testing.assert_close(hsh(d, P), full[:, : (P + 1) ** 2], rtol=1e-12, atol=1e-12)


def test_hsh_constant_term():
    d = _hemi(10)
    torch.testing.assert_close(hsh(d, 0)[:, 0], torch.full((10,), 1 / math.sqrt(2 * math.pi), dtype=F64))


@pytest.mark.parametrize("order", [0, 3, 6])
def test_isotropic_matches_reference(order):
    wi, wo = _hemi(40, seed=1), _hemi(40, seed=2)
    np.testing.assert_allclose(helmholtz_isotropic(wi, wo, order).numpy(),
                               iso_ref(wi.numpy(), wo.numpy(), order), rtol=1e-9, atol=1e-10)


def test_anisotropic_matches_hsh_products():
    P = 3
    wi, wo = _hemi(30, seed=4), _hemi(30, seed=5)
    Hi, Ho = hsh_ref(wi.numpy(), P), hsh_ref(wo.numpy(), P)
    idx = anisotropic_indices(P).tolist()
    ref = []
    for p, q, r, s in idx:
        j, k = hsh_index(p, q), hsh_index(r, s)
        nrm = 1 / math.sqrt(2 + 2 * (j == k))
        ref.append(nrm * (Hi[:, j] * Ho[:, k] + Hi[:, k] * Ho[:, j]))
    np.testing.assert_allclose(helmholtz_anisotropic(wi, wo, P).numpy(), np.stack(ref, -1), rtol=1e-9, atol=1e-10)


# --------------------------------------------------------------------------
# Orthonormality by product quadrature
# --------------------------------------------------------------------------
def test_hsh_orthonormal_order_12(hemi_quadrature):
    d, w = hemi_quadrature(16, 28)
    G = _gram(hsh(d, 12), w)
    err = (G - torch.eye(G.shape[0], dtype=F64)).abs().max().item()
    assert err < 1e-10, err


def test_isotropic_orthonormal_order_6(pair_quadrature):
    wi, wo, w = pair_quadrature(8, 14)
    G = _gram(helmholtz_isotropic(wi, wo, 6), w)
    err = (G - torch.eye(G.shape[0], dtype=F64)).abs().max().item()
    assert err < 1e-10, err


def test_anisotropic_orthonormal_order_3(pair_quadrature):
    wi, wo, w = pair_quadrature(5, 8)
    G = _gram(helmholtz_anisotropic(wi, wo, 3), w)
    assert G.shape == (136, 136)
    err = (G - torch.eye(136, dtype=F64)).abs().max().item()
    assert err < 1e-10, err


def test_erratum1_printed_eq21_normalisation_gives_norm_2(pair_quadrature):
    """Eq. 21 as printed multiplies every q > 0 function by Phi_q(0) = sqrt(2): squared norm 2."""
    wi, wo, w = pair_quadrature(6, 10)
    P = 4
    B = helmholtz_isotropic(wi, wo, P)
    q = isotropic_indices(P)[:, 2]
    printed = B * torch.where(q > 0, torch.tensor(math.sqrt(2.0), dtype=F64), torch.tensor(1.0, dtype=F64))
    norms = (printed * printed * w[:, None]).sum(0)
    torch.testing.assert_close(norms[q > 0], torch.full_like(norms[q > 0], 2.0), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(norms[q == 0], torch.ones_like(norms[q == 0]), rtol=1e-10, atol=1e-10)
    # and the library's choice is orthonormal
    torch.testing.assert_close((B * B * w[:, None]).sum(0), torch.ones(B.shape[1], dtype=F64), rtol=1e-10, atol=1e-10)


# --------------------------------------------------------------------------
# Symmetries
# --------------------------------------------------------------------------
def _rotz(d, ang):
    c, s = math.cos(ang), math.sin(ang)
    R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=d.dtype)
    return d @ R.T


@pytest.mark.parametrize("fn,order", [(helmholtz_isotropic, 6), (helmholtz_anisotropic, 3)])
def test_reciprocity(fn, order):
    wi, wo = _hemi(50, seed=6), _hemi(50, seed=7)
    torch.testing.assert_close(fn(wi, wo, order), fn(wo, wi, order), rtol=1e-12, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6), st.floats(0.0, 2 * math.pi))
def test_reciprocity_and_rotation_property(v, ang):
    wi = torch.tensor(v[:3], dtype=F64)
    wo = torch.tensor(v[3:], dtype=F64)
    wi[2] = wi[2].abs() + 0.01
    wo[2] = wo[2].abs() + 0.01
    B = helmholtz_isotropic(wi, wo, 4)
    torch.testing.assert_close(B, helmholtz_isotropic(wo, wi, 4), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(B, helmholtz_isotropic(_rotz(wi, ang), _rotz(wo, ang), 4), rtol=1e-9, atol=1e-9)
    A = helmholtz_anisotropic(wi, wo, 2)
    torch.testing.assert_close(A, helmholtz_anisotropic(wo, wi, 2), rtol=1e-10, atol=1e-10)


def test_isotropic_rotation_invariant_anisotropic_not():
    wi, wo = _hemi(20, seed=8), _hemi(20, seed=9)
    ang = 0.7
    torch.testing.assert_close(helmholtz_isotropic(_rotz(wi, ang), _rotz(wo, ang), 5),
                               helmholtz_isotropic(wi, wo, 5), rtol=1e-10, atol=1e-10)
    A0 = helmholtz_anisotropic(wi, wo, 2)
    A1 = helmholtz_anisotropic(_rotz(wi, ang), _rotz(wo, ang), 2)
    assert (A0 - A1).abs().max().item() > 0.05
    # a specific function that changes: H_1^1(wi) H_0^0(wo) symmetrised
    col = anisotropic_indices(2).tolist().index([0, 0, 1, 1])
    assert (A0[:, col] - A1[:, col]).abs().max().item() > 0.05


def test_isotropic_is_combination_of_anisotropic():
    P = 3
    wi, wo = _hemi(25, seed=10), _hemi(25, seed=11)
    iso = helmholtz_isotropic(wi, wo, P)
    an = helmholtz_anisotropic(wi, wo, P)
    rows = {tuple(r): c for c, r in enumerate(anisotropic_indices(P).tolist())}
    for c, (p, r, q) in enumerate(isotropic_indices(P).tolist()):
        if q == 0:
            expect = an[:, rows[(r, 0, p, 0)]]
        else:
            expect = (an[:, rows[(r, q, p, q)]] + an[:, rows[(r, -q, p, -q)]]) / math.sqrt(2.0)
        torch.testing.assert_close(iso[:, c], expect, rtol=1e-11, atol=1e-12)


def test_cosines_and_world_agree_with_local():
    P = 5
    g = torch.Generator().manual_seed(12)
    n = torch.nn.functional.normalize(torch.randn(30, 3, generator=g, dtype=F64), dim=-1)
    li, lo = _hemi(30, seed=13), _hemi(30, seed=14)
    # build world directions from local ones with the frame of n, so both are on n's hemisphere
    from torch_hsh.frames import to_world

    wi, wo = to_world(li, n), to_world(lo, n)
    ref = helmholtz_isotropic(to_local(wi, n), to_local(wo, n), P)
    torch.testing.assert_close(helmholtz_isotropic(li, lo, P), ref, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(helmholtz_isotropic_world(wi, wo, n, P), ref, rtol=1e-10, atol=1e-10)
    cd = torch.cos(torch.atan2(lo[:, 1], lo[:, 0]) - torch.atan2(li[:, 1], li[:, 0]))
    torch.testing.assert_close(helmholtz_isotropic_cosines(li[:, 2], lo[:, 2], cd, P), ref, rtol=1e-10, atol=1e-10)
    # world version with non-unit inputs and a directional below-horizon case
    torch.testing.assert_close(helmholtz_isotropic_world(3 * wi, 0.5 * wo, 2 * n, P), ref, rtol=1e-10, atol=1e-10)
    below = helmholtz_isotropic_world(-wi, wo, n, P)
    assert bool((below == 0).all())


def test_isotropic_same_tensor_for_wi_and_wo():
    w = _hemi(20, seed=15)
    torch.testing.assert_close(helmholtz_isotropic(w, w, 6), helmholtz_isotropic(w, w.clone(), 6), rtol=0, atol=0)
    torch.testing.assert_close(helmholtz_isotropic(w, w, 6), torch.tensor(iso_ref(w.numpy(), w.numpy(), 6)),
                               rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(helmholtz_anisotropic(w, w, 2), helmholtz_anisotropic(w, w.clone(), 2),
                               rtol=0, atol=0)
    x = w.clone().requires_grad_(True)
    (g_same,) = torch.autograd.grad(helmholtz_isotropic(x, x, 3).sum(), x)
    y = w.clone().requires_grad_(True)
    (g_sep,) = torch.autograd.grad(helmholtz_isotropic(y, y.clone(), 3).sum(), y)
    torch.testing.assert_close(g_same, g_sep, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------
# Horizon, zero vectors, normalisation
# --------------------------------------------------------------------------
def test_below_horizon_and_zero_vectors_give_zero():
    d = torch.tensor([[0.3, 0.4, -0.5], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=F64, requires_grad=True)
    H = hsh(d, 4)
    assert bool((H == 0).all())
    H.sum().backward()
    assert bool((d.grad == 0).all())
    good = _hemi(3)
    assert bool((helmholtz_isotropic(d, good, 3) == 0).all())
    assert bool((helmholtz_isotropic(good, d, 3) == 0).all())
    assert bool((helmholtz_anisotropic(d, good, 2) == 0).all())
    assert bool((helmholtz_isotropic_cosines(torch.tensor([-0.2, 0.5]), torch.tensor([0.5, -0.1]),
                                             torch.tensor([0.3, 0.3]), 3) == 0).all())
    # exactly on the horizon is valid (z >= 0): H_0^0 is not zero there
    h = hsh(torch.tensor([1.0, 0.0, 0.0], dtype=F64), 2)
    assert h[0].item() == pytest.approx(1 / math.sqrt(2 * math.pi))


def test_inputs_are_normalised():
    d = _hemi(10)
    torch.testing.assert_close(hsh(3.7 * d, 6), hsh(d, 6), rtol=1e-12, atol=1e-12)
    wo = _hemi(10, seed=1)
    torch.testing.assert_close(helmholtz_isotropic(0.2 * d, 5 * wo, 4), helmholtz_isotropic(d, wo, 4),
                               rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(helmholtz_anisotropic(0.2 * d, 5 * wo, 2), helmholtz_anisotropic(d, wo, 2),
                               rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------
def test_gradcheck_hsh():
    d = _hemi(4, seed=20).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: hsh(x, 5), (d,))


def test_gradcheck_hsh_at_pole():
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: hsh(x, 5), (d,))


def test_gradcheck_isotropic_and_anisotropic():
    wi = _hemi(3, seed=21).requires_grad_(True)
    wo = _hemi(3, seed=22).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: helmholtz_isotropic(a, b, 4), (wi, wo))
    assert torch.autograd.gradcheck(lambda a, b: helmholtz_anisotropic(a, b, 2), (wi, wo))
    # the same tensor for both arguments
    assert torch.autograd.gradcheck(lambda a: helmholtz_isotropic(a, a, 4), (wi,))


def test_gradcheck_isotropic_at_pole():
    wi = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64, requires_grad=True)
    wo = _hemi(1, seed=23).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: helmholtz_isotropic(a, b, 4), (wi, wo))


def test_gradcheck_cosines():
    ci = torch.tensor([0.3, 0.8], dtype=F64, requires_grad=True)
    co = torch.tensor([0.6, 0.2], dtype=F64, requires_grad=True)
    cd = torch.tensor([0.1, -0.7], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: helmholtz_isotropic_cosines(a, b, c, 4), (ci, co, cd))


def test_gradcheck_world():
    g = torch.Generator().manual_seed(24)
    n = torch.nn.functional.normalize(torch.randn(3, 3, generator=g, dtype=F64), dim=-1)
    from torch_hsh.frames import to_world

    wi = to_world(_hemi(3, seed=25), n).requires_grad_(True)
    wo = to_world(_hemi(3, seed=26), n).requires_grad_(True)
    n = n.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, c: helmholtz_isotropic_world(a, b, c, 4), (wi, wo, n))


SPECIAL = [
    [0.0, 0.0, 1.0],  # pole
    [0.6, 0.8, 0.0],  # horizon
    [0.0, 0.0, 0.0],  # zero vector
    [0.3, -0.4, -0.5],  # below the horizon
    [1e-9, 0.0, 1.0],  # next to the pole
    [0.8, 0.6, 1e-9],  # next to the horizon
]


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("order", [3, 6])
def test_gradients_finite_at_special_points(dtype, order):
    sp = torch.tensor(SPECIAL, dtype=dtype, requires_grad=True)
    H = hsh(sp, order)
    assert bool(torch.isfinite(H).all())
    (g,) = torch.autograd.grad(H.sum(), sp)
    assert bool(torch.isfinite(g).all())
    assert bool((g[2:4] == 0).all())  # zero vector and below horizon: zero gradient
    # every pairing of special points, both argument orders
    n = len(SPECIAL)
    wi = sp[:, None, :].expand(n, n, 3)
    wo = sp[None, :, :].expand(n, n, 3)
    for fn, P in ((helmholtz_isotropic, order), (helmholtz_anisotropic, min(order, 3))):
        B = fn(wi, wo, P)
        assert bool(torch.isfinite(B).all())
        (g,) = torch.autograd.grad((B * torch.linspace(0.5, 1.5, B.shape[-1], dtype=dtype)).sum(), sp)
        assert bool(torch.isfinite(g).all()), fn.__name__
    ci = torch.tensor([1.0, 0.0, 1.0, 0.0, 0.5], dtype=dtype, requires_grad=True)
    co = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.5], dtype=dtype, requires_grad=True)
    cd = torch.tensor([1.0, -1.0, 0.3, 0.3, 1.0], dtype=dtype, requires_grad=True)
    B = helmholtz_isotropic_cosines(ci, co, cd, order)
    grads = torch.autograd.grad(B.sum(), (ci, co, cd))
    assert all(bool(torch.isfinite(t).all()) for t in grads)


@pytest.mark.parametrize("order", [3, 5])
def test_world_gradients_finite_when_normal_parallel(order):
    light = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0]], dtype=F64)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    n = light.clone().requires_grad_(True)  # normal parallel to the light
    B = helmholtz_isotropic_world(light, view, n, order)
    (g,) = torch.autograd.grad(B.sum(), n)
    assert bool(torch.isfinite(g).all())
    n2 = view.expand(3, 3).clone().requires_grad_(True)  # normal parallel to the view
    B = helmholtz_isotropic_world(light, view, n2, order)
    (g,) = torch.autograd.grad(B.sum(), n2)
    assert bool(torch.isfinite(g).all())


# --------------------------------------------------------------------------
# Precision, shapes, broadcasting
# --------------------------------------------------------------------------
def test_float32_matches_float64():
    d = _hemi(200, seed=30)
    wo = _hemi(200, seed=31)
    for P in (4, 12):
        h64 = hsh(d, P)
        h32 = hsh(d.float(), P)
        assert h32.dtype == torch.float32
        torch.testing.assert_close(h32.double(), h64, rtol=1e-4, atol=2e-5 * h64.abs().max().item())
    b64 = helmholtz_isotropic(d, wo, 8)
    b32 = helmholtz_isotropic(d.float(), wo.float(), 8)
    torch.testing.assert_close(b32.double(), b64, rtol=1e-4, atol=2e-5 * b64.abs().max().item())
    a64 = helmholtz_anisotropic(d, wo, 3)
    a32 = helmholtz_anisotropic(d.float(), wo.float(), 3)
    torch.testing.assert_close(a32.double(), a64, rtol=1e-4, atol=2e-5 * a64.abs().max().item())


def test_leading_shapes_and_broadcasting():
    d = _hemi(24, seed=32)
    assert hsh(d[0], 3).shape == (16,)
    torch.testing.assert_close(hsh(d.reshape(2, 3, 4, 3), 3).reshape(24, 16), hsh(d, 3))
    wi = _hemi(5, seed=33).reshape(5, 1, 3)
    wo = _hemi(4, seed=34).reshape(1, 4, 3)
    for fn, P, K in ((helmholtz_isotropic, 3, 20), (helmholtz_anisotropic, 1, 10)):
        B = fn(wi, wo, P)
        assert B.shape == (5, 4, K)
        torch.testing.assert_close(B, fn(wi.expand(5, 4, 3), wo.expand(5, 4, 3), P))
        assert fn(wi[0, 0], wo[0, 0], P).shape == (K,)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    assert helmholtz_isotropic_world(wi, wo, n, 3).shape == (5, 4, 20)
    torch.testing.assert_close(helmholtz_isotropic_world(wi, wo, n, 3), helmholtz_isotropic(wi, wo, 3))
    c = torch.tensor([0.5, 0.6], dtype=F64)
    assert helmholtz_isotropic_cosines(c.reshape(2, 1), c, torch.tensor(0.2, dtype=F64), 2).shape == (2, 2, 10)


def test_flat_rows_broadcast_and_keep_no_views(backend):
    # one row dimension: an input that broadcasts (even when its 3 components equal the row count) is expanded,
    # and its gradient sums over the rows; an input that is already (N, 3) goes to the kernel as it is, with no
    # view node between the leaf and the basis's own autograd node
    wi = _hemi(3, seed=35).requires_grad_(True)
    wo = _hemi(1, seed=36)[0].clone().requires_grad_(True)  # (3,): broadcasts against (3, 3)
    B = helmholtz_isotropic(wi, wo, 2)
    ref = helmholtz_isotropic(wi.detach(), wo.detach().expand(3, 3), 2)
    torch.testing.assert_close(B.detach(), ref)
    B.sum().backward()
    wo2 = wo.detach().expand(3, 3).clone().requires_grad_(True)
    helmholtz_isotropic(wi.detach(), wo2, 2).sum().backward()
    torch.testing.assert_close(wo.grad, wo2.grad.sum(0))
    c = torch.tensor([0.3, 0.5, 0.7], dtype=F64)
    torch.testing.assert_close(helmholtz_isotropic_cosines(c, torch.tensor(0.4, dtype=F64), c, 2),
                               helmholtz_isotropic_cosines(c, torch.full((3,), 0.4, dtype=F64), c, 2))
    leaf = _hemi(8, seed=37).requires_grad_(True)
    if not torch_hsh.kernel._native_ok(leaf):  # the torch kernels work feature-major: their nodes differ
        return
    out = helmholtz_isotropic(leaf, _hemi(8, seed=38), 2)
    assert out.grad_fn.next_functions[0][0].variable is leaf  # no ViewBackward between them
    out = hsh(leaf, 2)
    assert out.grad_fn.next_functions[0][0].variable is leaf


def test_empty_batch():
    e = torch.zeros(0, 3, requires_grad=True)
    assert hsh(e, 3).shape == (0, 16)
    assert hsh(torch.zeros(2, 0, 3), 2).shape == (2, 0, 9)
    assert helmholtz_isotropic(e, e, 3).shape == (0, 20)
    assert helmholtz_anisotropic(e, e, 1).shape == (0, 10)
    assert helmholtz_isotropic_world(e, e, e, 2).shape == (0, 10)
    helmholtz_isotropic(e, e, 3).sum().backward()
    assert e.grad.shape == (0, 3)


# --------------------------------------------------------------------------
# Bad inputs
# --------------------------------------------------------------------------
def test_bad_order():
    d = _hemi(2)
    for bad in (2.0, True, "3", None, torch.tensor(2.0)):
        with pytest.raises(TypeError, match="order"):
            hsh(d, bad)
    for bad in (-1, 41, 10**9):
        with pytest.raises(ValueError, match="order"):
            hsh(d, bad)
    with pytest.raises(ValueError, match="order"):
        helmholtz_isotropic(d, d, -2)
    with pytest.raises(ValueError, match="order"):
        helmholtz_anisotropic(d, d, 17)
    with pytest.raises(ValueError, match="order"):
        num_anisotropic(17)
    assert hsh(d, np.int64(2)).shape == (2, 9)
    assert hsh(d, torch.tensor(2)).shape == (2, 9)


def test_bad_tensors():
    d = _hemi(2)
    with pytest.raises(ValueError, match="dirs"):
        hsh(torch.zeros(4, 2, dtype=F64), 2)
    with pytest.raises(ValueError, match="dirs"):
        hsh(torch.zeros((), dtype=F64), 2)
    with pytest.raises(TypeError, match="dirs"):
        hsh(torch.zeros(4, 3, dtype=torch.int64), 2)
    with pytest.raises(TypeError, match="dirs"):
        hsh([[0.0, 0.0, 1.0]], 2)
    for bad in (float("nan"), float("inf")):
        x = d.clone()
        x[0, 1] = bad
        with pytest.raises(ValueError, match="dirs"):
            hsh(x, 2)
        with pytest.raises(ValueError, match="wo"):
            helmholtz_isotropic(d, x, 2)
        with pytest.raises(ValueError, match="`wo`"):
            helmholtz_anisotropic(d, x, 1)
        with pytest.raises(ValueError, match="normal"):
            helmholtz_isotropic_world(d, d, x, 2)
    with pytest.raises(ValueError, match="wo"):
        helmholtz_isotropic(d, torch.zeros(2, 4, dtype=F64), 2)
    with pytest.raises(TypeError, match="wi"):
        helmholtz_anisotropic(np.zeros((2, 3)), d, 2)
    with pytest.raises(TypeError, match="dtype"):
        helmholtz_isotropic(d, d.float(), 2)
    with pytest.raises(TypeError, match="dtype"):
        helmholtz_isotropic_world(d, d, d.float(), 2)
    with pytest.raises(TypeError, match="cos_dphi"):
        helmholtz_isotropic_cosines(d[:, 0], d[:, 1], torch.zeros(2, dtype=torch.int32), 2)
    with pytest.raises(ValueError, match="broadcast"):
        helmholtz_isotropic(_hemi(3), _hemi(2), 2)


def test_mismatched_devices():
    d = _hemi(2)
    m = torch.empty(2, 3, dtype=F64, device="meta")
    with pytest.raises(ValueError, match="device"):
        helmholtz_isotropic(d, m, 2)
    with pytest.raises(ValueError, match="device"):
        helmholtz_isotropic(m, d, 2)
    with pytest.raises(ValueError, match="device"):
        helmholtz_anisotropic(d, m, 1)
    with pytest.raises(ValueError, match="device"):
        helmholtz_isotropic_world(d, d, m, 2)
    with pytest.raises(ValueError, match="device"):
        helmholtz_isotropic_cosines(d[:, 0], m[:, 0], d[:, 1], 2)


def test_validation_switch_skips_value_checks_only():
    d = _hemi(2)
    x = d.clone()
    x[0, 0] = float("nan")
    torch_hsh.set_validation(False)
    try:
        hsh(x, 2)  # no scan for NaN
        with pytest.raises(ValueError, match="dirs"):
            hsh(torch.zeros(2, 4, dtype=F64), 2)
    finally:
        torch_hsh.set_validation(True)
    with pytest.raises(ValueError):
        hsh(x, 2)


# --------------------------------------------------------------------------
# Row-chunked evaluation path (large batches): same values and gradients
# --------------------------------------------------------------------------
@pytest.fixture
def tiny_chunks(monkeypatch):
    import torch_hsh.kernel as basis_mod

    monkeypatch.setattr(basis_mod, "_CHUNK_ELEMS", 1)  # one-row chunks
    return basis_mod


def test_chunked_path_matches_plain(tiny_chunks):
    d = _hemi(40, seed=40)
    wo = _hemi(40, seed=41)
    ref_h = torch.tensor(hsh_ref(d.numpy(), 6))
    ref_i = torch.tensor(iso_ref(d.numpy(), wo.numpy(), 4))
    torch.testing.assert_close(hsh(d, 6), ref_h, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(helmholtz_isotropic(d, wo, 4), ref_i, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(helmholtz_isotropic(d, d, 4), torch.tensor(iso_ref(d.numpy(), d.numpy(), 4)),
                               rtol=1e-9, atol=1e-10)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    torch.testing.assert_close(helmholtz_isotropic_world(d, wo, n, 4), ref_i, rtol=1e-9, atol=1e-10)
    cd = torch.cos(torch.atan2(wo[:, 1], wo[:, 0]) - torch.atan2(d[:, 1], d[:, 0]))
    torch.testing.assert_close(helmholtz_isotropic_cosines(d[:, 2], wo[:, 2], cd, 4), ref_i, rtol=1e-9, atol=1e-10)
    Hi, Ho = ref_h[:, :4], torch.tensor(hsh_ref(wo.numpy(), 1))
    an = helmholtz_anisotropic(d, wo, 1)
    torch.testing.assert_close(an[:, 0], Hi[:, 0] * Ho[:, 0], rtol=1e-9, atol=1e-10)


def test_chunked_path_gradients(tiny_chunks):
    wi = _hemi(30, seed=42)
    wi[0] = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    wi[1] = torch.tensor([0.3, 0.1, -0.5], dtype=F64)
    wi.requires_grad_(True)
    wo = _hemi(30, seed=43).requires_grad_(True)
    w = torch.linspace(-1, 1, 20, dtype=F64)
    g_chunk = torch.autograd.grad((helmholtz_isotropic(wi, wo, 3) * w).sum(), (wi, wo))
    tiny_chunks._CHUNK_ELEMS = 1 << 30  # plain path
    g_plain = torch.autograd.grad((helmholtz_isotropic(wi, wo, 3) * w).sum(), (wi, wo))
    for a, b in zip(g_chunk, g_plain):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    tiny_chunks._CHUNK_ELEMS = 1
    x = _hemi(3, seed=44).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: hsh(a, 3), (x,))
    assert torch.autograd.gradcheck(lambda a, b: helmholtz_isotropic(a, b, 2), (x, x.detach().flip(0).clone()))
    assert torch.autograd.gradgradcheck(lambda a: hsh(a, 2), (x,))


def test_chunked_create_graph_with_shared_inputs(tiny_chunks):
    # the caller's own tensors reach the chunked kernel: an input passed twice, or computed from another, must
    # not count the first derivative twice in a create_graph backward (the docstrings' own patterns)
    c = torch.linspace(0.1, 0.9, 6, dtype=F64, requires_grad=True)
    d = torch.zeros(6, dtype=F64)
    w = _hemi(6, seed=47).requires_grad_(True)
    n = torch.nn.functional.normalize(_hemi(6, seed=48) + torch.tensor([0.0, 0.0, 2.0], dtype=F64), dim=-1)
    n.requires_grad_(True)
    cases = [
        (lambda: helmholtz_isotropic_cosines(c, c, d, 3), (c,)),
        (lambda: helmholtz_isotropic_world(w, n, n, 2), (w, n)),
        (lambda: helmholtz_isotropic(w, w * torch.tensor([-1.0, -1.0, 1.0], dtype=F64), 2), (w,)),
    ]
    for make, xs in cases:
        plain = torch.autograd.grad(make().sum(), xs)
        graph = torch.autograd.grad(make().sum(), xs, create_graph=True)
        for a, b in zip(graph, plain):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_trace_keeps_the_shape_ops(backend):
    # a trace taken at (N, 3) and called at another rank fails loudly (its shapes are constants), never silently
    d = _hemi(5, seed=49)
    f = torch.jit.trace(lambda x: hsh(x, 2), (d,), check_trace=False)
    torch.testing.assert_close(f(d), hsh(d, 2))
    with pytest.raises(RuntimeError):
        f(_hemi(8, seed=50).reshape(2, 4, 3))


def test_gradgradcheck_plain_path():
    x = _hemi(3, seed=45).requires_grad_(True)
    y = _hemi(3, seed=46).requires_grad_(True)
    assert torch.autograd.gradgradcheck(lambda a, b: helmholtz_isotropic(a, b, 3), (x, y))


# --------------------------------------------------------------------------
# Behaviour pinned down by mutation testing (make mutate): counts, index
# tables, exact horizon/pole geometry, deep leading shapes, partial gradients
# --------------------------------------------------------------------------
def test_counts_are_python_ints_and_index_tables_are_long():
    from torch_hsh.kernel import MAX_ANISOTROPIC_ORDER

    for P in range(0, 9):
        assert type(num_isotropic(P)) is int and type(num_anisotropic(min(P, 4))) is int
    assert isotropic_indices(3).dtype == torch.long and anisotropic_indices(2).dtype == torch.long
    with pytest.raises(ValueError, match="order"):
        anisotropic_indices(MAX_ANISOTROPIC_ORDER + 1)
    with pytest.raises(ValueError, match="n=2, m=3"):
        hsh_index(2, 3)


def _local(z, phi):
    s = math.sqrt(max(0.0, 1.0 - z * z))
    return [s * math.cos(phi), s * math.sin(phi), z]


def test_exact_horizon_and_pole_agree_across_entry_points():
    """cos = 0 (in the tangent plane) and cos = 1 (the normal) are valid inputs of every entry point and give
    the reference values; a cosine above 1 is outside the hemisphere (zero), cos_dphi is clamped to [-1, 1]."""
    P = 4
    pts = [(0.0, 0.0), (0.0, 2.0), (1.0, 0.0), (0.6, 1.0), (0.0, -2.5), (1.0, 3.0)]
    pairs = [(a, b) for a in pts for b in pts]
    wi = torch.tensor([_local(*a) for a, _ in pairs], dtype=F64)
    wo = torch.tensor([_local(*b) for _, b in pairs], dtype=F64)
    ref = torch.tensor(iso_ref(wi.numpy(), wo.numpy(), P))
    assert float(ref.abs().max()) > 0.1
    torch.testing.assert_close(helmholtz_isotropic(wi, wo, P), ref, rtol=1e-9, atol=1e-10)
    zi = torch.tensor([a[0] for a, _ in pairs], dtype=F64)
    zo = torch.tensor([b[0] for _, b in pairs], dtype=F64)
    cd = torch.tensor([math.cos(b[1] - a[1]) for a, b in pairs], dtype=F64)
    torch.testing.assert_close(helmholtz_isotropic_cosines(zi, zo, cd, P), ref, rtol=1e-9, atol=1e-10)
    # world frame: a tilted normal, directions built from its explicit tangent frame
    n = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=F64), dim=0)
    t = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=F64), n, dim=0), dim=0)
    b = torch.linalg.cross(n, t, dim=0)
    R = torch.stack([t, b, n], -1)  # columns: local -> world
    # (rows with a direction exactly in the tangent plane are left out: after the rotation their n . w is
    # +-1e-17, and the hemisphere test then keeps or drops them by rounding)
    ok = (zi > 0) & (zo > 0)
    world = helmholtz_isotropic_world(wi @ R.T, wo @ R.T, n, P)
    torch.testing.assert_close(world[ok], ref[ok], rtol=1e-9, atol=1e-10)
    # outside [0, 1] in a cosine: zero; cos_dphi beyond [-1, 1] acts as +-1
    one, half = torch.tensor([1.0], dtype=F64), torch.tensor([0.5], dtype=F64)
    for bad_i, bad_o in ((1.0 + 1e-6, 0.5), (0.5, 1.0 + 1e-6), (1.5, 0.5), (0.5, 1.5)):
        out = helmholtz_isotropic_cosines(torch.tensor([bad_i], dtype=F64), torch.tensor([bad_o], dtype=F64), one, P)
        assert bool((out == 0).all()), (bad_i, bad_o)
    torch.testing.assert_close(helmholtz_isotropic_cosines(half, half, torch.tensor([1.7], dtype=F64), P),
                               helmholtz_isotropic_cosines(half, half, one, P), rtol=0, atol=0)
    torch.testing.assert_close(helmholtz_isotropic_cosines(half, half, torch.tensor([-1.7], dtype=F64), P),
                               helmholtz_isotropic_cosines(half, half, -one, P), rtol=0, atol=0)


def test_exact_horizon_gradients_match_the_local_path():
    """Gradients at cos = 0 and 1 through the cosines and world entry points equal those of the local path."""
    P = 3
    zs = torch.tensor([0.0, 1.0, 0.4, 0.0], dtype=F64)
    zo = torch.tensor([0.7, 0.0, 1.0, 0.0], dtype=F64)
    cd = torch.tensor([0.3, -0.6, 0.9, -1.0], dtype=F64)
    w = torch.linspace(-1.0, 1.0, num_isotropic(P), dtype=F64)
    for z1, z2 in ((zs, zo), (zo, zs)):
        a, b = z1.clone().requires_grad_(True), z2.clone().requires_grad_(True)
        ga = torch.autograd.grad((helmholtz_isotropic_cosines(a, b, cd, P) * w).sum(), (a, b))
        assert all(bool(torch.isfinite(g).all()) for g in ga)
        # interior points: compare with central differences
        inner = (z1 > 0) & (z1 < 1)
        h = 1e-6
        fp = (helmholtz_isotropic_cosines(z1 + h, z2, cd, P) * w).sum(-1)
        fm = (helmholtz_isotropic_cosines(z1 - h, z2, cd, P) * w).sum(-1)
        torch.testing.assert_close(ga[0][inner], ((fp - fm) / (2 * h))[inner], rtol=1e-5, atol=1e-6)


def test_deep_leading_shapes_and_broadcast_normals():
    g = torch.Generator().manual_seed(60)
    wi = torch.nn.functional.normalize(torch.randn(2, 3, 4, 3, generator=g, dtype=F64).abs(), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(2, 3, 4, 3, generator=g, dtype=F64).abs(), dim=-1)
    flat_i, flat_o = wi.reshape(-1, 3), wo.reshape(-1, 3)
    assert helmholtz_isotropic(wi, wo, 3).shape == (2, 3, 4, 20)
    assert helmholtz_isotropic(wi, wi, 3).shape == (2, 3, 4, 20)  # the shared-table path (wo is wi)
    torch.testing.assert_close(helmholtz_isotropic(wi, wi, 3).reshape(-1, 20), helmholtz_isotropic(flat_i, flat_i, 3))
    assert helmholtz_anisotropic(wi, wi, 1).shape == (2, 3, 4, num_anisotropic(1))
    torch.testing.assert_close(helmholtz_isotropic(wi, wo, 3).reshape(-1, 20), helmholtz_isotropic(flat_i, flat_o, 3))
    assert helmholtz_anisotropic(wi, wo, 1).shape == (2, 3, 4, num_anisotropic(1))
    torch.testing.assert_close(helmholtz_anisotropic(wi, wo, 1).reshape(24, -1), helmholtz_anisotropic(flat_i, flat_o, 1))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    nb = n.expand(3, 1, 3)  # broadcasts against (2, 3, 4)
    out = helmholtz_isotropic_world(wi, wo, nb, 3)
    assert out.shape == (2, 3, 4, 20)
    torch.testing.assert_close(out, helmholtz_isotropic(wi, wo, 3))
    assert helmholtz_isotropic_world(wi[0, 0], wo[0, 0], torch.stack([n] * 5)[:, None], 2).shape == (5, 4, 10)


@pytest.mark.parametrize("chunked", [True, False])
def test_gradients_when_only_some_inputs_require_grad(tiny_chunks, chunked):
    """d/d(normal) alone, d/d(wi) alone (wo constant): the same as with every input requiring grad."""
    if not chunked:
        tiny_chunks._CHUNK_ELEMS = 1 << 30
    wi, wo = _hemi(12, seed=61), _hemi(12, seed=62)
    n = torch.nn.functional.normalize(torch.tensor([[0.1, 0.2, 1.0]], dtype=F64).expand(12, 3), dim=-1)
    w = torch.linspace(-1, 1, 20, dtype=F64)
    a, b, c = (t.clone().requires_grad_(True) for t in (wi, wo, n))
    full = torch.autograd.grad((helmholtz_isotropic_world(a, b, c, 3) * w).sum(), (a, b, c))
    cn = n.clone().requires_grad_(True)
    (g_n,) = torch.autograd.grad((helmholtz_isotropic_world(wi, wo, cn, 3) * w).sum(), (cn,))
    torch.testing.assert_close(g_n, full[2], rtol=1e-12, atol=1e-12)
    ai = wi.clone().requires_grad_(True)
    (g_i,) = torch.autograd.grad((helmholtz_isotropic(ai, wo, 3) * w).sum(), (ai,))
    ai2, bo2 = wi.clone().requires_grad_(True), wo.clone().requires_grad_(True)
    ref = torch.autograd.grad((helmholtz_isotropic(ai2, bo2, 3) * w).sum(), (ai2, bo2))
    torch.testing.assert_close(g_i, ref[0], rtol=1e-12, atol=1e-12)
    # a second derivative through the chunked backward (create_graph)
    x = _hemi(3, seed=63).requires_grad_(True)
    assert torch.autograd.gradgradcheck(lambda u: helmholtz_isotropic(u, wo[:3], 2), (x,))


@pytest.mark.parametrize("order", [0, 1, 2])
def test_low_orders_match_reference_through_every_entry_point(order):
    wi, wo = _hemi(25, seed=70), _hemi(25, seed=71)
    ref = torch.tensor(iso_ref(wi.numpy(), wo.numpy(), order))
    assert ref.shape == (25, num_isotropic(order))
    torch.testing.assert_close(helmholtz_isotropic(wi, wo, order), ref, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(helmholtz_isotropic(wi, wi, order), torch.tensor(iso_ref(wi.numpy(), wi.numpy(), order)),
                               rtol=1e-9, atol=1e-10)
    cd = torch.cos(torch.atan2(wo[:, 1], wo[:, 0]) - torch.atan2(wi[:, 1], wi[:, 0]))
    torch.testing.assert_close(helmholtz_isotropic_cosines(wi[:, 2], wo[:, 2], cd, order), ref, rtol=1e-9, atol=1e-10)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    torch.testing.assert_close(helmholtz_isotropic_world(wi, wo, n, order), ref, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("chunked", [True, False])
def test_gradient_of_an_input_the_basis_does_not_use_is_zero(tiny_chunks, chunked):
    """At order 0 the basis is a constant on the hemisphere: the gradients are zero (not an error), in the
    chunked path too (where the rows are evaluated inside an autograd Function)."""
    if not chunked:
        tiny_chunks._CHUNK_ELEMS = 1 << 30
    zi = torch.tensor([0.3, 0.7, 1.0], dtype=F64, requires_grad=True)
    zo = torch.tensor([0.5, 0.2, 0.9], dtype=F64, requires_grad=True)
    cd = torch.tensor([0.1, -0.4, 0.8], dtype=F64, requires_grad=True)
    out = helmholtz_isotropic_cosines(zi, zo, cd, 0)
    torch.testing.assert_close(out, torch.full((3, 1), 1.0 / (2.0 * math.pi), dtype=F64))
    y = out.sum() + 0.0 * (zi.sum() + zo.sum() + cd.sum())  # a graph in either path
    for create_graph in (False, True):  # the Function's backward has a path for each
        g = torch.autograd.grad(y, (zi, zo, cd), retain_graph=True, create_graph=create_graph)
        for gi in g:
            assert torch.equal(gi.detach(), torch.zeros(3, dtype=F64))


# --------------------------------------------------------------------------
# Horizon: exact values within eps of z = 0, and the derivative cut (module docstring: the derivative
# through the sqrt(z) factor is cut to zero within eps = 1e-12 (float64) / 1e-6 (float32) of the
# horizon, and only there)
# --------------------------------------------------------------------------
_EPS_CASES = [  # dtype, z clearly above eps (live derivative), z below eps (cut)
    (F64, 1e-9, 1e-14),
    (torch.float32, 1e-4, 1e-8),
]


def _dz_central(f, z, h):
    return (f(z + h) - f(z - h)) / (2.0 * h)


@pytest.mark.parametrize("dtype,z_live,z_cut", _EPS_CASES)
def test_horizon_derivative_is_exact_above_eps_and_cut_below(dtype, z_live, z_cut):
    """d H_1^1 / d z and d H_{11}^1 / d cos_i next to the horizon: the true (large, ~1/sqrt z) derivative
    above eps, finite and small below it."""
    def h11(z):  # H_1^1 of the unnormalised input (1, 0, z), float64 values
        return hsh(torch.tensor([1.0, 0.0, z], dtype=F64), 1)[3].item()

    def iso111(z):  # the (p, r, q) = (1, 1, 1) function at cos_i = z, cos_o = 0.5, cos_dphi = 0.3
        return helmholtz_isotropic_cosines(torch.tensor([z], dtype=F64), torch.tensor([0.5], dtype=F64),
                                           torch.tensor([0.3], dtype=F64), 1)[0, 3].item()

    for f, call in ((h11, lambda t: hsh(torch.stack([torch.ones_like(t), torch.zeros_like(t), t]), 1)[3]),
                    (iso111, lambda t: helmholtz_isotropic_cosines(t.reshape(1), torch.tensor([0.5], dtype=dtype),
                                                                   torch.tensor([0.3], dtype=dtype), 1)[0, 3])):
        ref = _dz_central(f, z_live, 1e-3 * z_live)
        assert abs(ref) > 10.0  # the sqrt(z) factor dominates: a large derivative
        t = torch.tensor(z_live, dtype=dtype, requires_grad=True)
        (g,) = torch.autograd.grad(call(t), t)
        assert g.item() == pytest.approx(ref, rel=1e-3 if dtype == torch.float32 else 1e-6)
        t = torch.tensor(z_cut, dtype=dtype, requires_grad=True)
        (g,) = torch.autograd.grad(call(t), t)
        assert math.isfinite(g.item()) and abs(g.item()) < 1.0, g.item()


@pytest.mark.parametrize("dtype,z_live,z_cut", _EPS_CASES)
def test_values_stay_exact_within_eps_of_the_horizon(dtype, z_live, z_cut):
    """Inside the cut zone only the derivative changes: H and the isotropic basis still equal the reference."""
    P = 3
    zs = [z_cut, 0.5 * z_cut, z_live]
    d = torch.tensor([[math.cos(0.4 + k), math.sin(0.4 + k), z] for k, z in enumerate(zs)], dtype=F64)
    ref = torch.tensor(hsh_ref(d.numpy(), P, theta=_theta_jacobi))
    tol = dict(rtol=1e-9, atol=1e-12) if dtype == F64 else dict(rtol=1e-4, atol=1e-6)
    assert float(ref[:, 3].abs().min()) > 0  # the odd-m functions are not zero there
    torch.testing.assert_close(hsh(d.to(dtype), P).double(), ref, **tol)
    wo = _hemi(3, seed=80)
    iref = torch.tensor(iso_ref(d.numpy(), wo.numpy(), P, theta=_theta_jacobi))
    torch.testing.assert_close(helmholtz_isotropic(d.to(dtype), wo.to(dtype), P).double(), iref, **tol)
    dn = d / d.norm(dim=-1, keepdim=True)
    cd = torch.cos(torch.atan2(wo[:, 1], wo[:, 0]) - torch.atan2(dn[:, 1], dn[:, 0]))
    torch.testing.assert_close(helmholtz_isotropic_cosines(dn[:, 2].to(dtype), wo[:, 2].to(dtype), cd.to(dtype), P)
                               .double(), iref, **tol)


def test_pole_derivative_of_the_cosines_entry_point():
    """Next to the pole (cos_i = 1 - 1e-9) the derivative through sin_i sin_o is large and exact."""
    def f(z):
        return helmholtz_isotropic_cosines(torch.tensor([z], dtype=F64), torch.tensor([0.4], dtype=F64),
                                           torch.tensor([0.7], dtype=F64), 2)[0]

    z0 = 1.0 - 1e-9
    t = torch.tensor([z0], dtype=F64, requires_grad=True)
    w = torch.linspace(0.5, 1.5, num_isotropic(2), dtype=F64)
    (g,) = torch.autograd.grad((helmholtz_isotropic_cosines(t, torch.tensor([0.4], dtype=F64),
                                                            torch.tensor([0.7], dtype=F64), 2) * w).sum(), t)
    h = 1e-12
    ref = ((f(z0 + h) - f(z0 - h)) * w).sum() / (2 * h)
    assert abs(ref.item()) > 100.0
    assert g.item() == pytest.approx(ref.item(), rel=1e-3)


# --------------------------------------------------------------------------
# World entry point: exactly-tangent directions, zero vectors
# --------------------------------------------------------------------------
@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.6, 0.0, 0.8)])
def test_world_direction_exactly_in_the_tangent_plane_is_valid(normal):
    """n . wi == 0 exactly is on the hemisphere (z >= 0): the values are those of the local reference, not 0."""
    P = 4
    n = torch.tensor(normal, dtype=F64)
    if normal[0] == 0.0:
        t, b = torch.tensor([1.0, 0.0, 0.0], dtype=F64), torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    else:
        t, b = torch.tensor([0.8, 0.0, -0.6], dtype=F64), torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    R = torch.stack([t, b, n], -1)  # local -> world
    li = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)  # wi = +-b: n . wi = 0 exactly
    lo = torch.tensor([_local(0.7, 1.1), _local(0.2, -2.0), [0.0, -1.0, 0.0]], dtype=F64)
    wi, wo = li @ R.T, lo @ R.T
    assert bool(((wi * n).sum(-1) == 0).all())
    ref = torch.tensor(iso_ref(li.numpy(), lo.numpy(), P))
    assert bool((ref.abs().amax(-1) > 0.05).all())
    torch.testing.assert_close(helmholtz_isotropic_world(wi, wo, n, P), ref, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(helmholtz_isotropic_world(wo, wi, n, P), ref, rtol=1e-9, atol=1e-10)


def test_world_zero_vectors_give_zero_with_zero_gradient():
    """A zero normal, light or view is invalid: 0 (not the value at n . w = 0), with zero finite gradients."""
    P = 3
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=F64)
    wi = torch.tensor([[0.6, 0.0, 0.8], [0.6, 0.0, 0.8], [0.0, 0.0, 0.0], [0.6, 0.0, 0.8]], dtype=F64)
    wo = torch.tensor([[0.0, 0.6, 0.8], [0.0, 0.6, 0.8], [0.0, 0.6, 0.8], [0.0, 0.0, 0.0]], dtype=F64)
    a, b, c = (x.clone().requires_grad_(True) for x in (wi, wo, n))
    out = helmholtz_isotropic_world(a, b, c, P)
    torch.testing.assert_close(out[0], helmholtz_isotropic(wi[0], wo[0], P), rtol=1e-12, atol=1e-12)
    assert bool((out[1:] == 0).all())
    grads = torch.autograd.grad((out * torch.linspace(0.5, 1.5, out.shape[-1], dtype=F64)).sum(), (a, b, c))
    for g in grads:
        assert bool(torch.isfinite(g).all()) and bool((g[1:] == 0).all())


# --------------------------------------------------------------------------
# Kernel paths: where the C kernels are unavailable (no compiler), and double backward
# --------------------------------------------------------------------------
@pytest.fixture
def no_native(monkeypatch):
    """As on a machine without a C compiler: torch_hsh._native.library() gives None."""
    import torch_hsh.kernel as kernel_mod

    monkeypatch.setattr(kernel_mod._native, "library", lambda: None)
    return kernel_mod


def test_without_the_c_kernels_values_and_gradients_are_unchanged(no_native):
    """Without the C kernels hsh runs sphericart on the pure-torch remap d -> (2 s x, 2 s y, 2 z - 1), and the
    Helmholtz bases run the torch recurrences: the same reference values, exact gradients."""
    d = _hemi(20, seed=90)
    d[0] = torch.tensor([0.6, -0.8, 0.0], dtype=F64)  # horizon
    d[1] = torch.tensor([0.0, 0.0, 3.0], dtype=F64)  # pole, non-unit
    torch.testing.assert_close(hsh(d, 5), torch.tensor(hsh_ref(d.numpy(), 5)), rtol=1e-9, atol=1e-10)
    wo = _hemi(20, seed=91)
    torch.testing.assert_close(helmholtz_isotropic(d, wo, 3), torch.tensor(iso_ref(d.numpy(), wo.numpy(), 3)),
                               rtol=1e-9, atol=1e-10)
    x = _hemi(3, seed=92).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: hsh(a, 4), (x,))


def _cosines_entry(zi, zo, cd, order):
    return helmholtz_isotropic_cosines(zi[:, 2], zo[:, 2], 0.5 * (cd[:, 0] - cd[:, 1]), order)


@pytest.mark.parametrize("fn,order,nargs,linked", [
    (hsh, 4, 1, False), (helmholtz_isotropic, 3, 2, False), (helmholtz_anisotropic, 2, 2, False),
    (helmholtz_isotropic, 3, 1, True), (helmholtz_anisotropic, 2, 1, True),
    (helmholtz_isotropic_world, 3, 3, True), (_cosines_entry, 3, 3, True),
])
def test_first_derivative_is_the_same_with_and_without_create_graph(backend, fn, order, nargs, linked):
    """create_graph=True (double backward) re-derives the first derivative on another path: it must be the same.
    ``nargs == 1``: the same tensor for wi and wo. ``linked``: the kernel's saved inputs depend on each other
    (``wi is wo``; the cosines computed from one normal), which once counted the first derivative twice."""
    xs = [_hemi(6, seed=93 + k) for k in range(nargs)]
    xs[0][0] = torch.tensor([0.3, -0.4, -0.5], dtype=F64)  # below the horizon: zero, with zero gradient
    xs = [x.requires_grad_(True) for x in xs]
    out = fn(*xs, order) if fn is hsh or nargs > 1 else fn(xs[0], xs[0], order)
    w = torch.linspace(-1.0, 1.0, out.shape[-1], dtype=F64)
    plain = torch.autograd.grad((out * w).sum(), xs, retain_graph=True)
    graph = torch.autograd.grad((out * w).sum(), xs, create_graph=True)
    for a, b in zip(plain, graph):
        assert b.requires_grad
        torch.testing.assert_close(b.detach(), a, rtol=1e-10, atol=1e-10)


def test_torch_func_transforms_match_autograd():
    """torch.func (vmap, jacrev) runs the plain pure-torch path: same values, same Jacobian as autograd."""
    d = _hemi(5, seed=97)
    f = lambda x: hsh(x, 3)  # noqa: E731
    torch.testing.assert_close(torch.func.vmap(f)(d), hsh(d, 3), rtol=1e-12, atol=1e-12)
    J = torch.func.jacrev(f)(d[0])
    torch.testing.assert_close(J, torch.autograd.functional.jacobian(f, d[0]), rtol=1e-12, atol=1e-12)
    wo = _hemi(5, seed=98)
    g = lambda a, b: helmholtz_isotropic(a, b, 2)  # noqa: E731
    torch.testing.assert_close(torch.func.vmap(g)(d, wo), g(d, wo), rtol=1e-12, atol=1e-12)


def test_chunks_of_several_rows_with_a_partial_last_chunk(tiny_chunks):
    """Row chunks of 7 rows over 40 rows (the last chunk holds 5): values and gradients as the plain path."""
    P, K = 4, 25
    tiny_chunks._CHUNK_ELEMS = 7 * K
    d = _hemi(40, seed=99)
    d[39] = torch.tensor([0.2, 0.1, -0.4], dtype=F64)  # last row of the partial chunk: below the horizon
    torch.testing.assert_close(hsh(d, P), torch.tensor(np.where(d[:, 2:].numpy() < 0, 0.0, hsh_ref(d.numpy(), P))),
                               rtol=1e-9, atol=1e-10)
    x = d.clone().requires_grad_(True)
    w = torch.linspace(-1.0, 1.0, K, dtype=F64)
    (g_chunk,) = torch.autograd.grad((hsh(x, P) * w).sum(), x)
    tiny_chunks._CHUNK_ELEMS = 1 << 30
    (g_plain,) = torch.autograd.grad((hsh(x, P) * w).sum(), x)
    torch.testing.assert_close(g_chunk, g_plain, rtol=1e-12, atol=1e-12)
    assert bool((g_chunk[39] == 0).all()) and bool((g_chunk[35:39] != 0).any())

