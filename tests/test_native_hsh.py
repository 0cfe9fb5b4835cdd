"""The fused C kernel of :func:`torch_hsh.hsh` (``kernels.c`` hsh_fwd / hsh_bwd) against the pure-torch kernel.

On the CPU with the C kernels built, ``hsh`` runs on this kernel at every order (test_backends.py compares
the default path with the torch path as a whole); here it is called directly, and the other CPU path
(sphericart, where the C kernels are off) is checked the same way, so both stay covered:

* float64 values to 1e-12 and gradients to 1e-10, at the special points (pole, horizon, within eps of
  it, below it, zero vectors) and at orders 0-12 and a high one;
* float32 relative error against float64 no worse than the torch kernel's;
* gradcheck in float64, strided / expanded / non-contiguous output gradients, the row split over
  threads, leading shapes;
* zero below the horizon with zero gradient, finite gradients at the horizon and the pole;
* create_graph / double backward and the fallbacks (torch.func, TORCH_HSH_NATIVE=0).
"""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

import torch_hsh
from torch_hsh import kernel as K
from conftest import edge_case_dirs

F64 = torch.float64
HAS_NATIVE = torch_hsh.backend_status()["isotropic_cpu"] == "native"
pytestmark = pytest.mark.skipif(not HAS_NATIVE, reason="no C compiler: the fused kernels are not built here")


_dirs = edge_case_dirs



def _native(d, order):
    return K._HshNative.apply(d, order)


def _torch(d, order):
    return K._hsh_flat_t(d, order).t()


def _value_and_grad(fn, d, order):
    x = d.detach().clone().requires_grad_(True)
    y = fn(x, order)
    w = torch.linspace(-1.0, 2.0, y.shape[-1], dtype=y.dtype)
    if not y.requires_grad:
        return y.detach(), torch.zeros_like(x)
    (g,) = torch.autograd.grad((y * w).sum(), x)
    return y.detach(), g


@pytest.mark.parametrize("order", [0, 1, 2, 3, 4, 5, 6, 8, 12, 20])
def test_native_hsh_matches_torch_float64(order):
    d = _dirs(700, order)  # more than one block of 64 rows, and a partial block
    (yn, gn), (yt, gt) = _value_and_grad(_native, d, order), _value_and_grad(_torch, d, order)
    torch.testing.assert_close(yn, yt, rtol=0, atol=1e-12 * max(1.0, float(yt.abs().max())))
    assert torch.isfinite(gn).all()
    torch.testing.assert_close(gn, gt, rtol=0, atol=1e-10 * max(1.0, float(gt.abs().max())))


@pytest.mark.parametrize("order", [1, 2, 4, 8, 12])
def test_native_hsh_float32_no_worse_than_torch(order):
    d64 = _dirs(3000, 40 + order, special=False)
    ref = _torch(d64, order)
    errs = {}
    for name, fn in (("native", _native), ("torch", _torch)):
        with torch.no_grad():
            y = fn(d64.float(), order).double()
        errs[name] = float((y - ref).abs().max() / ref.abs().max())
    assert errs["native"] <= 1.5 * errs["torch"] + 1e-7, errs
    # gradients in float32 against float64, relative
    _, g64 = _value_and_grad(_torch, d64, order)
    _, g32 = _value_and_grad(_native, d64.float(), order)
    _, gt32 = _value_and_grad(_torch, d64.float(), order)
    en = float((g32.double() - g64).abs().max() / g64.abs().max())
    et = float((gt32.double() - g64).abs().max() / g64.abs().max())
    assert en <= 1.5 * et + 1e-6, (en, et)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_native_hsh_horizon_pole_and_below(dtype):
    d = _dirs(8, 0, dtype=dtype)
    x = d.clone().requires_grad_(True)
    y = _native(x, 5)
    (g,) = torch.autograd.grad(y.sum() + (y * y).sum(), x)
    assert torch.isfinite(g).all()
    assert torch.equal(y[4], torch.zeros_like(y[4])) and torch.equal(y[5], torch.zeros_like(y[5]))
    assert torch.equal(g[4], torch.zeros_like(g[4])) and torch.equal(g[5], torch.zeros_like(g[5]))
    assert float(y[1].detach().abs().sum()) > 0  # on the horizon the basis is not zero


def test_native_hsh_gradcheck_float64():
    a = _dirs(70, 11, special=False).requires_grad_(True)
    for order in (1, 2, 4, 7):
        assert torch.autograd.gradcheck(lambda x, P=order: _native(x, P), (a,))
    assert torch.autograd.gradgradcheck(lambda x: _native(x, 3), (a[:5],))


def test_native_hsh_strided_output_gradients():
    d = _dirs(300, 12)
    x = d.clone().requires_grad_(True)
    y = _native(x, 4)
    _, gt = _value_and_grad(_torch, d, 4)
    ref = torch.autograd.grad((_torch(x, 4) * torch.linspace(-1.0, 2.0, 25, dtype=F64)).sum(), x)[0]
    torch.testing.assert_close(gt, ref)
    cases = [
        torch.linspace(-1.0, 2.0, 25, dtype=F64).expand(300, 25),  # stride (0, 1)
        torch.ones(1, dtype=F64).expand(300, 25),  # stride (0, 0)
        torch.randn(25, 300, dtype=F64).t(),  # non-contiguous
        torch.randn(300, 50, dtype=F64)[:, ::2],  # row stride 50, column stride 2
    ]
    for gout in cases:
        (gn,) = torch.autograd.grad(y, x, gout, retain_graph=True)
        (gr,) = torch.autograd.grad(_torch(x, 4), x, gout)
        torch.testing.assert_close(gn, gr, rtol=0, atol=1e-10 * float(gr.abs().max()))


def test_hsh_dispatch_and_thread_split(monkeypatch):
    assert torch_hsh.backend_status()["hsh_cpu"] == "native"
    calls = []
    real = K._HshNative.apply
    monkeypatch.setattr(K._HshNative, "apply", lambda *a: calls.append(a[1]) or real(*a))
    d = _dirs(40_000, 13, dtype=torch.float32)  # several row ranges of the thread pool
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = torch_hsh.hsh(d.reshape(2, 20_000, 3), 3)
        torch.set_num_threads(4)
        many = torch_hsh.hsh(d, 3)
    finally:
        torch.set_num_threads(old)
    assert calls == [3, 3] and one.shape == (2, 20_000, 16)
    assert torch.equal(one.reshape(-1, 16), many)
    with torch.no_grad():
        torch.testing.assert_close(many, _torch(d, 3), rtol=0, atol=1e-5)


def test_hsh_cpu_sphericart_path_when_native_is_off(monkeypatch):
    """Where the C kernels are off, hsh on the CPU runs on sphericart (if installed), else torch."""
    if K._sphericart_module() is None:
        pytest.skip("sphericart-torch is not installed")
    monkeypatch.setattr(K, "_native_ok", lambda t: False)
    d = _dirs(300, 14)
    for order in (0, 2, 4, 7):
        (ya, ga), (yt, gt) = _value_and_grad(lambda x, P: torch_hsh.hsh(x, P), d, order), _value_and_grad(
            _torch, d, order)
        torch.testing.assert_close(ya, yt, rtol=0, atol=1e-12 * max(1.0, float(yt.abs().max())))
        torch.testing.assert_close(ga, gt, rtol=0, atol=1e-10 * max(1.0, float(gt.abs().max())))


def test_hsh_under_torch_func_runs_the_torch_kernel(monkeypatch):
    monkeypatch.setattr(K._HshNative, "apply", None)  # would fail if called
    d = _dirs(12, 15, special=False)
    v = torch.func.vmap(lambda x: torch_hsh.hsh(x, 2))(d.reshape(3, 4, 3))
    torch.testing.assert_close(v.reshape(12, 9), _torch(d, 2))
    J = torch.func.jacrev(lambda x: torch_hsh.hsh(x, 2))(d)
    assert J.shape == (12, 9, 12, 3)


def test_hsh_native_switched_off_in_a_subprocess(tmp_path):
    code = (
        "import torch, torch_hsh;"
        "s = torch_hsh.backend_status(); print(s['hsh_cpu'], s['hsh']);"
        "d = torch.tensor([[0.3, 0.1, 0.9], [0.5, -0.2, 0.1]], dtype=torch.float64, requires_grad=True);"
        "y = torch_hsh.hsh(d, 3); g, = torch.autograd.grad((y * y).sum(), d);"
        "print(float(y.sum()), float(g.sum()))"
    )
    env = dict(os.environ, TORCH_HSH_NATIVE="0", TORCH_HSH_CACHE=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    status, values = out.stdout.strip().splitlines()
    assert status.split()[0] in ("sphericart", "torch") and status.split()[0] == status.split()[1]
    d = torch.tensor([[0.3, 0.1, 0.9], [0.5, -0.2, 0.1]], dtype=F64, requires_grad=True)
    y = _native(d, 3)
    (g,) = torch.autograd.grad((y * y).sum(), d)
    v, gs = (float(t) for t in values.split())
    assert abs(v - float(y.sum())) < 1e-12 and abs(gs - float(g.sum())) < 1e-10
    assert not list(tmp_path.iterdir())  # nothing compiled


def test_non_finite_inputs_flagged_by_the_kernels():
    """The C kernels flag non-finite inputs (the torch scan is skipped on that path) and the full check
    then names the argument; a finite input whose |d|^2 overflows is flagged but passes the check."""
    d = _dirs(20_000, 16, dtype=torch.float32)  # row 15_000 lies in the second thread's range
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        _check_flagged(d)
    finally:
        torch.set_num_threads(old)


def _check_flagged(d):
    for bad in (float("nan"), float("inf"), float("-inf")):
        x = d.clone()
        x[15_000, 2] = bad
        with pytest.raises(ValueError, match="`dirs` contains"):
            torch_hsh.hsh(x, 2)
        with pytest.raises(ValueError, match="`wo` contains"):
            torch_hsh.helmholtz_isotropic(d, x, 2)
        with pytest.raises(ValueError, match="`wi` contains"):
            torch_hsh.helmholtz_isotropic(x, x, 2)
    big = d.clone()
    big[3] = torch.tensor([0.0, 3e19, 4e19])  # |d|^2 overflows float32; the values are finite
    assert torch.isfinite(torch_hsh.hsh(big, 2)).all()
    assert torch.isfinite(torch_hsh.helmholtz_isotropic(big, d, 2)).all()
    torch_hsh.set_validation(False)
    try:
        x = d.clone()
        x[0, 0] = float("nan")
        torch_hsh.hsh(x, 2)  # no check
        torch_hsh.helmholtz_isotropic(x, d, 2)
    finally:
        torch_hsh.set_validation(True)


def test_native_path_skips_the_torch_scan(monkeypatch):
    scans = []
    real = torch.isfinite
    monkeypatch.setattr(torch, "isfinite", lambda t: scans.append(t.numel()) or real(t))
    d = _dirs(1000, 17)
    torch_hsh.hsh(d, 2)
    torch_hsh.helmholtz_isotropic(d, d.flip(0), 2)
    assert scans == []
    monkeypatch.setattr(K, "_native_ok", lambda t: False)
    torch_hsh.hsh(d, 2)
    assert scans  # the other paths scan first


def test_parallel_rows_covers_every_row_once_in_block_aligned_ranges():
    from torch_hsh import _native

    seen = []

    def fn(r0, r1, code):
        seen.append((r0, r1))
        return code if r0 == 0 else 0

    old = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        for n in (1, 2047, 5000, 100_003):
            seen.clear()
            assert _native.parallel_rows(fn, n, 0) is False
            rows = sorted(seen)
            assert rows[0][0] == 0 and rows[-1][1] == n
            assert all(a[1] == b[0] for a, b in zip(rows, rows[1:]))  # contiguous, no overlap
            assert all(r0 % _native._BLOCK == 0 for r0, _ in rows)
            if n >= 100_000:
                assert len(rows) > 3  # more ranges than threads: taken dynamically
        assert _native.parallel_rows(fn, 100_003, 2) is True
        with pytest.raises(MemoryError):
            _native.parallel_rows(fn, 100_003, 1)
    finally:
        torch.set_num_threads(old)
