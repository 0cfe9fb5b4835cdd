"""Tests of torch_hsh.frames: local frames, round trips, isotropic triple, reflection."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_hsh import helmholtz_isotropic, helmholtz_isotropic_cosines, helmholtz_isotropic_world
from torch_hsh.frames import isotropic_triple, local_frame, reflect, to_local, to_world

F64 = torch.float64

SPECIAL_NORMALS = [
    [0.0, 0.0, 1.0],
    [0.0, 0.0, -1.0],
    [1e-9, 0.0, -1.0],
    [0.0, 1e-12, -1.0],
    [-1e-7, 1e-7, -1.0],
    [1e-9, -1e-9, 1.0],
    [1.0, 0.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.3, -0.2, 0.9],
    [2.0, 1.0, -3.0],  # not unit
]


def _check_rotation(R, n, atol):
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=atol)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), rtol=0, atol=atol)
    # right-handed rows: t x b = n
    torch.testing.assert_close(torch.cross(R[..., 0, :], R[..., 1, :], dim=-1), R[..., 2, :], rtol=0, atol=atol)
    torch.testing.assert_close(R[..., 2, :], torch.nn.functional.normalize(n, dim=-1), rtol=0, atol=atol)


@pytest.mark.parametrize("dtype,atol", [(F64, 1e-12), (torch.float32, 2e-6)])
def test_local_frame_orthonormal_right_handed(dtype, atol):
    n = torch.tensor(SPECIAL_NORMALS, dtype=dtype)
    R = local_frame(n)
    assert R.shape == (len(SPECIAL_NORMALS), 3, 3)
    assert bool(torch.isfinite(R).all())
    _check_rotation(R, n, atol)
    g = torch.Generator().manual_seed(0)
    rnd = torch.randn(500, 3, generator=g, dtype=F64).to(dtype)
    _check_rotation(local_frame(rnd), rnd, atol * 5)


def test_local_frame_identity_at_z():
    torch.testing.assert_close(local_frame(torch.tensor([0.0, 0.0, 1.0], dtype=F64)), torch.eye(3, dtype=F64))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: sum(x * x for x in v) > 1e-6))
def test_local_frame_property(v):
    n = torch.tensor(v, dtype=F64)
    _check_rotation(local_frame(n), n, 1e-11)
    d = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    torch.testing.assert_close(to_world(to_local(d, n), n), d, rtol=1e-12, atol=1e-12)


def test_round_trip_and_normal_maps_to_z():
    g = torch.Generator().manual_seed(1)
    n = torch.randn(4, 1, 3, generator=g, dtype=F64)
    v = torch.randn(1, 6, 3, generator=g, dtype=F64)
    loc = to_local(v, n)
    assert loc.shape == (4, 6, 3)
    torch.testing.assert_close(to_world(loc, n), v.expand(4, 6, 3), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(loc.norm(dim=-1), v.norm(dim=-1).expand(4, 6), rtol=1e-12, atol=1e-12)
    nz = to_local(torch.nn.functional.normalize(n, dim=-1), n)
    torch.testing.assert_close(nz, torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(4, 1, 3), rtol=0, atol=1e-12)
    # dot products with the normal are the local z
    torch.testing.assert_close(loc[..., 2], (v * torch.nn.functional.normalize(n, dim=-1)).sum(-1),
                               rtol=1e-12, atol=1e-12)


def test_tangent_option():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.3, 0.4, 0.866]], dtype=F64)
    t = torch.tensor([[1.0, 1.0, 0.5], [1.0, 0.3, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    R = local_frame(n, t)
    _check_rotation(R, n, 1e-12)
    tl = to_local(t, n, t)
    # the tangent lies in the local x-z plane with positive x
    torch.testing.assert_close(tl[:, 1], torch.zeros(3, dtype=F64), rtol=0, atol=1e-12)
    assert bool((tl[:, 0] > 0).all())
    v = torch.tensor([0.2, -0.7, 0.4], dtype=F64)
    torch.testing.assert_close(to_world(to_local(v, n, t), n, t), v.expand(3, 3), rtol=1e-12, atol=1e-12)
    # a tangent parallel to the normal falls back to the default frame
    Rp = local_frame(n, 2.0 * n)
    _check_rotation(Rp, n, 1e-12)
    torch.testing.assert_close(Rp, local_frame(n), rtol=0, atol=1e-12)


def test_isotropic_triple_values_and_parallel_case():
    g = torch.Generator().manual_seed(2)
    n = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=F64), dim=-1)
    li = torch.nn.functional.normalize(torch.rand(20, 3, generator=g, dtype=F64) + 0.05, dim=-1)
    lo = torch.nn.functional.normalize(torch.rand(20, 3, generator=g, dtype=F64) + 0.05, dim=-1)
    wi, wo = to_world(li, n), to_world(lo, n)
    ci, co, cd = isotropic_triple(wi, wo, n)
    torch.testing.assert_close(ci, li[:, 2], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(co, lo[:, 2], rtol=1e-12, atol=1e-12)
    expect = torch.cos(torch.atan2(lo[:, 1], lo[:, 0]) - torch.atan2(li[:, 1], li[:, 0]))
    torch.testing.assert_close(cd, expect, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(helmholtz_isotropic_cosines(ci, co, cd, 4), helmholtz_isotropic(li, lo, 4),
                               rtol=1e-10, atol=1e-10)
    # a direction parallel to the normal: well defined, finite, and the basis is unaffected
    nz = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    wo1 = torch.tensor([0.6, 0.0, 0.8], dtype=F64)
    ci, co, cd = isotropic_triple(nz, wo1, nz)
    assert (ci.item(), co.item(), cd.item()) == pytest.approx((1.0, 0.8, 1.0))
    b1 = helmholtz_isotropic_cosines(ci, co, cd, 5)
    b2 = helmholtz_isotropic_cosines(ci, co, -cd, 5)
    torch.testing.assert_close(b1, b2, rtol=0, atol=1e-12)
    torch.testing.assert_close(b1, helmholtz_isotropic(nz, wo1, 5), rtol=1e-12, atol=1e-12)


def test_isotropic_triple_gradients_finite_when_normal_parallel():
    light = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 1.0, 0.0]], dtype=F64)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    for dtype in (F64, torch.float32):
        n = light.to(dtype).clone().requires_grad_(True)
        ci, co, cd = isotropic_triple(light.to(dtype), view.to(dtype), n)
        (g,) = torch.autograd.grad((ci + 2 * co + 3 * cd).sum(), n)
        assert bool(torch.isfinite(g).all())
        n2 = n.detach().clone().requires_grad_(True)
        B = helmholtz_isotropic_world(light.to(dtype), view.to(dtype), n2, 4)
        (g2,) = torch.autograd.grad(B.sum(), n2)
        assert bool(torch.isfinite(g2).all())
    # the world basis gradient wrt the normal matches finite differences away from degeneracy
    n = torch.tensor([[0.1, 0.2, 0.95]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda m: helmholtz_isotropic_world(light[1:2], view, m, 3), (n,))


def test_reflect():
    n = torch.tensor([0.0, 0.0, 2.0], dtype=F64)
    v = torch.tensor([[0.6, 0.0, 0.8], [0.0, -0.6, 0.8]], dtype=F64)
    r = reflect(v, n)
    torch.testing.assert_close(r, torch.tensor([[-0.6, 0.0, 0.8], [0.0, 0.6, 0.8]], dtype=F64))
    g = torch.Generator().manual_seed(3)
    nn_ = torch.randn(10, 3, generator=g, dtype=F64)
    vv = torch.nn.functional.normalize(torch.randn(10, 3, generator=g, dtype=F64), dim=-1)
    rr = reflect(vv, nn_)
    torch.testing.assert_close(reflect(rr, nn_), vv, rtol=1e-12, atol=1e-12)
    nh = torch.nn.functional.normalize(nn_, dim=-1)
    torch.testing.assert_close((rr * nh).sum(-1), (vv * nh).sum(-1), rtol=1e-12, atol=1e-12)


def test_frames_bad_inputs():
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    with pytest.raises(ValueError, match="normal"):
        local_frame(torch.zeros(2, dtype=F64))
    with pytest.raises(TypeError, match="normal"):
        local_frame(torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ValueError, match="normal"):
        local_frame(torch.tensor([math.nan, 0.0, 1.0]))
    with pytest.raises(TypeError, match="dtype"):
        to_local(torch.zeros(3, dtype=torch.float32), n)
    with pytest.raises(ValueError, match="tangent"):
        local_frame(n, torch.zeros(4, dtype=F64))
    with pytest.raises(TypeError, match="v"):
        to_local([0.0, 0.0, 1.0], n)
