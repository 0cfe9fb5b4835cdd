"""The kernel paths behind the bases agree: sphericart + fused C kernels ("auto") and pure torch.

What is checked here (test_kernel.py runs all its value/gradient tests on both paths as well):

* values in float64 to 1e-12 and gradients to 1e-10 between the paths, on random directions and
  on the special points (pole, horizon, just above the horizon, below it, zero vectors);
* float32 no further from the float64 values than the pure-torch float32 kernel is;
* the multi-threaded row split and high orders (heap scratch tables);
* torch.func (vmap, jacrev), double backward and torch.compile (inductor) on both paths;
* the fallbacks: without sphericart, and with the C kernels switched off (a subprocess with
  ``TORCH_HSH_NATIVE=0``), with a status that says why.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys

import pytest
import torch

import torch_hsh
from torch_hsh import kernel as basis
from conftest import edge_case_dirs

F64 = torch.float64
HAS_SPHERICART = basis._sphericart_module() is not None
HAS_NATIVE = torch_hsh.backend_status()["isotropic_cpu"] == "native"


@pytest.fixture
def restore_backend():
    yield
    torch_hsh.set_backend("auto")


_dirs = edge_case_dirs



def _both(fn, *args):
    """(auto result, torch result) of fn(*args) with gradients of a weighted sum."""
    outs = []
    for be in ("auto", "torch"):
        torch_hsh.set_backend(be)
        xs = [a.detach().clone().requires_grad_(a.is_floating_point()) for a in args]
        y = fn(*xs)
        w = torch.linspace(-1.0, 2.0, y.shape[-1], dtype=y.dtype)
        if y.requires_grad:
            grads = torch.autograd.grad((y * w).sum(), [x for x in xs if x.requires_grad], allow_unused=True)
        else:  # order 0: a constant
            grads = (None,) * len(xs)
        outs.append((y.detach(), [torch.zeros_like(x) if g is None else g for x, g in zip(xs, grads)]))
    torch_hsh.set_backend("auto")
    return outs


CASES = {
    "hsh": (lambda a, b, c, P: torch_hsh.hsh(a, P)),
    "isotropic": (lambda a, b, c, P: torch_hsh.helmholtz_isotropic(a, b, P)),
    "isotropic_same": (lambda a, b, c, P: torch_hsh.helmholtz_isotropic(a, a, P)),
    "anisotropic": (lambda a, b, c, P: torch_hsh.helmholtz_anisotropic(a, b, min(P, 4))),
    "cosines": (lambda a, b, c, P: torch_hsh.helmholtz_isotropic_cosines(a[:, 2].clamp(-0.2, 1.0), b[:, 2],
                                                                         torch.cos(3.0 * c[:, 0]), P)),
    "world": (lambda a, b, c, P: torch_hsh.helmholtz_isotropic_world(a, b, c, P)),
}


def test_status_and_bad_backend(restore_backend):
    st = torch_hsh.backend_status()
    assert st["backend"] == "auto"
    assert st["hsh"] in ("sphericart", "torch") and st["isotropic_cpu"] in ("native", "torch")
    assert (st["hsh"] == "sphericart") == HAS_SPHERICART
    assert st["hsh_cpu"] == ("native" if HAS_NATIVE else st["hsh"])
    torch_hsh.set_backend("torch")
    st = torch_hsh.backend_status()
    assert (st["hsh"], st["hsh_cpu"], st["isotropic_cpu"]) == ("torch", "torch", "torch")
    with pytest.raises(ValueError, match="`name` must be one of"):
        torch_hsh.set_backend("cuda")
    with pytest.raises(ValueError, match="`name`"):
        torch_hsh.set_backend(None)  # type: ignore[arg-type]


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("order", [0, 1, 2, 5, 9])
def test_paths_agree_float64_values_and_gradients(case, order):
    a, b, c = _dirs(300, 1), _dirs(300, 2), _dirs(300, 3, special=False)
    (ya, ga), (yt, gt) = _both(lambda x, y, z: CASES[case](x, y, z, order), a, b, c)
    torch.testing.assert_close(ya, yt, rtol=0, atol=1e-12 * max(1.0, float(yt.abs().max())))
    for g1, g2 in zip(ga, gt):
        assert torch.isfinite(g1).all()
        torch.testing.assert_close(g1, g2, rtol=0, atol=1e-10 * max(1.0, float(g2.abs().max())))


@pytest.mark.parametrize("case", ["hsh", "isotropic", "isotropic_same", "anisotropic"])
@pytest.mark.parametrize("order", [4, 8, 12])
def test_float32_no_worse_than_the_torch_kernel(case, order, restore_backend):
    if case == "anisotropic" and order > 4:
        pytest.skip("anisotropic output grows as order**4")
    a64, b64 = _dirs(2000, 4, special=False), _dirs(2000, 5, special=False)
    ref = CASES[case](a64, b64, a64, order)
    errs = {}
    for be in ("auto", "torch"):
        torch_hsh.set_backend(be)
        y = CASES[case](a64.float(), b64.float(), a64.float(), order).double()
        errs[be] = float((y - ref).abs().max() / ref.abs().max())
    assert errs["auto"] <= 1.5 * errs["torch"] + 1e-7, errs


def test_thread_split_matches_single_thread(restore_backend):
    n = 40_000  # several row ranges of the thread pool
    a, b = _dirs(n, 6), _dirs(n, 7)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = [torch_hsh.helmholtz_isotropic(a, b, 4), torch_hsh.hsh(a, 6), torch_hsh.helmholtz_anisotropic(a, b, 2)]
        torch.set_num_threads(4)
        many = [torch_hsh.helmholtz_isotropic(a, b, 4), torch_hsh.hsh(a, 6), torch_hsh.helmholtz_anisotropic(a, b, 2)]
        torch_hsh.set_backend("torch")
        ref = [torch_hsh.helmholtz_isotropic(a, b, 4), torch_hsh.hsh(a, 6), torch_hsh.helmholtz_anisotropic(a, b, 2)]
    finally:
        torch.set_num_threads(old)
    for x, y, r in zip(one, many, ref):
        assert torch.equal(x, y)
        torch.testing.assert_close(x, r, rtol=0, atol=1e-12)


def _values_and_grads(a, b):
    a, b = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    ys = [torch_hsh.helmholtz_isotropic(a, b, 4), torch_hsh.hsh(a, 6), torch_hsh.helmholtz_anisotropic(a, b, 2)]
    w = [torch.linspace(-1, 1, y.numel(), dtype=y.dtype).reshape(y.shape) for y in ys]
    grads = torch.autograd.grad(sum((y * v).sum() for y, v in zip(ys, w)), [a, b])
    return [y.detach() for y in ys] + list(grads)


@pytest.mark.skipif(not HAS_NATIVE, reason="needs the C kernels")
def test_openmp_team_and_thread_pool_agree_bitwise(monkeypatch):
    """The kernels run on torch's OpenMP threads where they can (one runtime, loaded by torch), and on a
    Python thread pool otherwise: the same row ranges, so the same bits, values and gradients."""
    from torch_hsh import _native

    status = _native.native_status()["threads"]
    if sys.platform.startswith("linux") and "OpenMP" in torch.__config__.parallel_info():
        assert status == "openmp", status  # torch's Linux wheels ship libgomp; gcc builds with -fopenmp
    a, b = _dirs(30_000, 8).float(), _dirs(30_000, 9).float()
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        team = _values_and_grads(a, b)
        monkeypatch.setitem(_native._state, "threads", "pool (test)")
        pool = _values_and_grads(a, b)
        torch.set_num_threads(1)
        one = _values_and_grads(a, b)
    finally:
        torch.set_num_threads(old)
    for x, y, z in zip(team, pool, one):
        assert torch.equal(x, y) and torch.equal(x, z)


@pytest.mark.skipif(not HAS_NATIVE, reason="needs the C kernels")
@pytest.mark.parametrize("order", sorted(basis._ISO_SMALL_ORDERS))
def test_generated_low_order_kernels_match_the_general_kernel(order, monkeypatch):
    """The straight-line isotropic kernels (``tools/generate_iso_kernels.py``) against the general C kernel that takes
    the same tables at run time: float64 values and gradients to rounding, on the special points too, and
    float32 no further from float64 than the general kernel's float32."""
    a, b = _dirs(3000, 20), _dirs(3000, 21)

    def run(x, y, small):
        monkeypatch.setattr(basis, "_ISO_SMALL_ORDERS", frozenset({order}) if small else frozenset())
        x, y = x.clone().requires_grad_(True), y.clone().requires_grad_(True)
        out = torch_hsh.helmholtz_isotropic(x, y, order)
        w = torch.linspace(-1.0, 2.0, out.numel(), dtype=out.dtype).reshape(out.shape)
        return [out.detach()] + list(torch.autograd.grad((out * w).sum(), [x, y]))

    gen, ref = run(a, b, True), run(a, b, False)
    for u, v in zip(gen, ref):
        assert torch.isfinite(u).all()
        torch.testing.assert_close(u, v, rtol=0, atol=1e-13 * max(1.0, float(v.abs().max())))
    a, b = _dirs(3000, 22, special=False), _dirs(3000, 23, special=False)
    exact = run(a, b, False)
    for small in (True, False):
        got = run(a.float(), b.float(), small)
        errs = [float((g.double() - e).abs().max() / e.abs().max()) for g, e in zip(got, exact)]
        if small:
            gen_errs = errs
    assert all(g <= 2.0 * e + 1e-7 for g, e in zip(gen_errs, errs)), (gen_errs, errs)


def test_forward_mode_ad_is_not_silently_dropped():
    """Without gradients recorded the kernels skip ``autograd.Function``; inside a forward-AD level they may not, so a
    dual input gets a derivative or an error, never a silent plain tensor."""
    import torch.autograd.forward_ad as fwAD

    a, b = _dirs(8, 30, special=False), _dirs(8, 31, special=False)
    with fwAD.dual_level():
        x = fwAD.make_dual(a, torch.ones_like(a))
        try:
            y = torch_hsh.helmholtz_isotropic(x, b, 2)
        except (NotImplementedError, RuntimeError):
            return
        assert fwAD.unpack_dual(y).tangent is not None


def test_generated_kernel_file_is_up_to_date():
    """``kernels_iso_small.h`` is what ``python tools/generate_iso_kernels.py`` writes from today's tables."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "tools" / "generate_iso_kernels.py"
    spec = importlib.util.spec_from_file_location("generate_iso_kernels", path)
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert gen.TARGET.read_text() == gen.source(), "run: python tools/generate_iso_kernels.py"


def test_high_order_and_empty_and_leading_shapes():
    a, b = _dirs(50, 8), _dirs(50, 9)
    (ya, ga), (yt, gt) = _both(lambda x, y: torch_hsh.helmholtz_isotropic(x, y, 30), a, b)
    assert ya.shape == (50, 5456)
    torch.testing.assert_close(ya, yt, rtol=0, atol=1e-10 * float(yt.abs().max()))
    torch.testing.assert_close(ga[0], gt[0], rtol=0, atol=1e-8 * float(gt[0].abs().max()))
    e = torch.empty(0, 3, dtype=F64)
    assert torch_hsh.helmholtz_isotropic(e, e, 3).shape == (0, 20)
    assert torch_hsh.hsh(e, 3).shape == (0, 16)
    assert torch_hsh.helmholtz_anisotropic(e, e, 1).shape == (0, 10)
    x = _dirs(24, 10).reshape(2, 3, 4, 3)
    y = _dirs(4, 11, special=False)
    out = torch_hsh.helmholtz_isotropic(x, y, 3)
    assert out.shape == (2, 3, 4, 20) and out.is_contiguous()
    torch.testing.assert_close(out.reshape(-1, 20)[:4], torch_hsh.helmholtz_isotropic(x.reshape(-1, 3)[:4], y, 3))


def test_gradcheck_native_kernels_float64():
    """The hand-written backward kernels against finite differences (auto path)."""
    a = _dirs(6, 12, special=False).requires_grad_(True)
    b = _dirs(6, 13, special=False).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, y: torch_hsh.helmholtz_isotropic(x, y, 4), (a, b))
    assert torch.autograd.gradcheck(lambda x: torch_hsh.helmholtz_isotropic(x, x, 3), (a,))
    assert torch.autograd.gradcheck(lambda x, y: torch_hsh.helmholtz_anisotropic(x, y, 2), (a, b))
    assert torch.autograd.gradcheck(lambda x: torch_hsh.hsh(x, 5), (a,))
    # Away from z = 0 and |cos| = 1: there the HSH carry sqrt(z (1 - z)) and the finite differences
    # of gradcheck (eps 1e-6) no longer see a smooth function (CI drew z = 1.1e-5 once).
    g = torch.Generator().manual_seed(15)
    zi = (0.05 + 0.9 * torch.rand(6, generator=g, dtype=F64)).requires_grad_(True)
    cd = (torch.rand(6, generator=g, dtype=F64) * 1.8 - 0.9).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda u, v: torch_hsh.helmholtz_isotropic_cosines(u, u.flip(0), v, 3), (zi, cd))


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_double_backward(backend, restore_backend):
    torch_hsh.set_backend(backend)
    a = _dirs(4, 14, special=False).requires_grad_(True)
    b = _dirs(4, 15, special=False).requires_grad_(True)
    assert torch.autograd.gradgradcheck(lambda x, y: torch_hsh.helmholtz_isotropic(x, y, 3), (a, b))
    assert torch.autograd.gradgradcheck(lambda x: torch_hsh.hsh(x, 3), (a,))
    assert torch.autograd.gradgradcheck(lambda x, y: torch_hsh.helmholtz_anisotropic(x, y, 1), (a, b))
    # one input without grad: the create_graph fallback differentiates only what is asked
    assert torch.autograd.gradgradcheck(lambda x: torch_hsh.helmholtz_isotropic(x, b.detach(), 2), (a,))


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("name", ["hsh", "isotropic", "anisotropic"])
def test_torch_func_transforms(backend, name, restore_backend):
    torch_hsh.set_backend(backend)
    fns = {
        "hsh": lambda x, y: torch_hsh.hsh(x, 3),
        "isotropic": lambda x, y: torch_hsh.helmholtz_isotropic(x, y, 3),
        "anisotropic": lambda x, y: torch_hsh.helmholtz_anisotropic(x, y, 1),
    }
    f = fns[name]
    a, b = _dirs(12, 16, special=False), _dirs(12, 17, special=False)
    ref = f(a, b)
    v = torch.func.vmap(f)(a.reshape(3, 4, 3), b.reshape(3, 4, 3))
    torch.testing.assert_close(v.reshape(12, -1), ref)
    J = torch.func.jacrev(f)(a, b)  # (12, K, 12, 3): block-diagonal over the rows
    xa = a.clone().requires_grad_(True)
    w = torch.zeros_like(ref)
    w[5, 1] = 1.0
    (g,) = torch.autograd.grad((f(xa, b) * w).sum(), xa)
    torch.testing.assert_close(J[5, 1], g)
    assert float(J[5, 1, 5].abs().sum()) > 0 and float(J[5, 1, 4].abs().sum()) == 0


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_torch_compile_inductor(backend, restore_backend):
    torch_hsh.set_backend(backend)
    torch._dynamo.reset()
    a, b = _dirs(16, 18, special=False), _dirs(16, 19, special=False)
    for f in (lambda x, y: torch_hsh.hsh(x, 3), lambda x, y: torch_hsh.helmholtz_isotropic(x, y, 3),
              lambda x, y: torch_hsh.helmholtz_anisotropic(x, y, 1)):
        cf = torch.compile(f, backend="inductor")
        torch.testing.assert_close(cf(a, b), f(a, b), rtol=1e-12, atol=1e-12)
        xa = a.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(cf(xa, b).sum(), xa)
        (gr,) = torch.autograd.grad(f(xa, b).sum(), xa)
        torch.testing.assert_close(g, gr, rtol=1e-10, atol=1e-10)


def test_without_sphericart_hsh_falls_back(monkeypatch):
    monkeypatch.setitem(basis._SPHERICART, "mod", None)
    monkeypatch.setitem(basis._SPHERICART, "error", "ImportError: simulated")
    assert torch_hsh.backend_status()["hsh"] == "torch"
    assert torch_hsh.backend_status()["sphericart_error"] == "ImportError: simulated"
    d = _dirs(100, 20)
    torch.testing.assert_close(torch_hsh.hsh(d, 4)[:, 0], torch.full((100,), 1 / math.sqrt(2 * math.pi), dtype=F64)
                               * (torch.arange(100) != 4).double() * (torch.arange(100) != 5).double())


def test_native_switched_off_in_a_subprocess(tmp_path):
    code = (
        "import torch, torch_hsh;"
        "s = torch_hsh.backend_status(); print(s['isotropic_cpu'], '|', s['native_error']);"
        "d = torch.tensor([[0.3, 0.1, 0.9]], dtype=torch.float64);"
        "print(float(torch_hsh.helmholtz_isotropic(d, d, 2).sum()))"
    )
    env = dict(os.environ, TORCH_HSH_NATIVE="0", TORCH_HSH_CACHE=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    line, value = out.stdout.strip().splitlines()
    assert line.startswith("torch |") and "TORCH_HSH_NATIVE=0" in line
    d = torch.tensor([[0.3, 0.1, 0.9]], dtype=F64)
    assert abs(float(value) - float(torch_hsh.helmholtz_isotropic(d, d, 2).sum())) < 1e-12
    assert not list(tmp_path.iterdir())  # nothing compiled


@pytest.mark.skipif(not HAS_NATIVE, reason="no C compiler: the fused kernels are not built here")
def test_native_build_is_cached_and_atomic(tmp_path):
    code = "import torch_hsh._native as n; print(n.native_status()['path'])"
    env = dict(os.environ, TORCH_HSH_CACHE=str(tmp_path))
    paths = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        paths.append(out.stdout.strip())
    assert paths[0] == paths[1] and paths[0].startswith(str(tmp_path))
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == 1 and files[0].endswith(".so")  # no temporary left behind


def test_bad_compiler_is_reported(tmp_path):
    code = "import torch_hsh; print(torch_hsh.backend_status()['native_error'])"
    env = dict(os.environ, CC="/nonexistent/cc", TORCH_HSH_CACHE=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "no C compiler" in out.stdout


@pytest.mark.skipif(not HAS_NATIVE or sys.platform == "win32", reason="needs the C kernels and a POSIX shell")
def test_compiler_without_openmp_builds_for_the_thread_pool(tmp_path):
    """A compiler that rejects -fopenmp still gives the kernels (on the Python pool), and the failed
    OpenMP build is remembered instead of retried at every start."""
    import shlex
    import sysconfig

    real = shlex.split(os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc")[0]
    cc = tmp_path / "cc-no-openmp"
    cc.write_text("#!/bin/sh\nfor a in \"$@\"; do [ \"$a\" = -fopenmp ] && { echo 'no OpenMP' >&2; exit 1; }; done\n"
                  f'exec {shlex.quote(real)} "$@"\n')
    cc.chmod(0o755)
    code = ("import torch, torch_hsh\nfrom torch_hsh import _native\n"
            "torch.set_num_threads(2)\n"
            "torch.manual_seed(0)\n"
            "d = torch.nn.functional.normalize(torch.rand(20000, 3), dim=-1)\n"
            "y = torch_hsh.helmholtz_isotropic(d, d.flip(0), 3)\n"
            "torch_hsh.set_backend('torch')\n"
            "err = (y - torch_hsh.helmholtz_isotropic(d, d.flip(0), 3)).abs().nan_to_num(float('inf'))\n"
            "print(_native.native_status()['threads'], bool(err.max() <= 1e-5))\n"
            "print('max error', float(err.max()), 'rows above 1e-5:', int((err > 1e-5).any(1).sum()))\n")
    env = dict(os.environ, CC=str(cc), TORCH_HSH_CACHE=str(tmp_path / "cache"))
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        # (CI failed here once on 2026-12-03 with an unseeded draw; 3,000 seeds and 100 fresh processes
        # here stayed below 3e-6, so the second line is there to tell what a next failure is)
        assert out.stdout.splitlines()[0].split() == ["pool", "(compiled", "without", "OpenMP)", "True"], out.stdout
    files = sorted(p.suffix for p in (tmp_path / "cache").iterdir())
    assert files == [".no-openmp", ".so"]


def _remap(d):
    """The documented map to the sphere: d' = (s x, s y, 2z - 1), s = 2 sqrt(z / (1 + z))."""
    d = torch.nn.functional.normalize(d, dim=-1)
    s = 2.0 * torch.sqrt(d[:, 2] / (1.0 + d[:, 2]))
    return torch.stack([s * d[:, 0], s * d[:, 1], 2.0 * d[:, 2] - 1.0], dim=-1)


def _signs(order):
    return torch.tensor([-1.0 if (m < 0 and (-m) % 2) else 1.0 for n in range(order + 1) for m in range(-n, n + 1)],
                        dtype=F64)


@pytest.mark.skipif(not HAS_SPHERICART, reason="sphericart-torch is not installed")
def test_documented_mapping_to_sphericart(restore_backend):
    """docs/conventions_and_errata.md: hsh(d)[:, k] = sqrt(2) sign_k Y_k(d') with sphericart's real SH."""
    torch_hsh.set_backend("torch")  # the independent pure-torch kernel against sphericart itself
    d = _dirs(500, 30, special=False)
    Y = basis._sphericart_module().SphericalHarmonics(6)(_remap(d))
    torch.testing.assert_close(torch_hsh.hsh(d, 6), math.sqrt(2.0) * _signs(6) * Y, rtol=0, atol=1e-12)


def test_documented_mapping_to_e3nn():
    """docs/conventions_and_errata.md: e3nn's spherical_harmonics (normalize=True, normalization='integral')
    of the components (y', z', x') of d' equal sphericart's Y(d'), so hsh = sqrt(2) sign_k e3nn_k."""
    o3 = pytest.importorskip("e3nn.o3")
    d = _dirs(500, 31, special=False)
    dp = _remap(d)
    E = o3.spherical_harmonics(list(range(7)), dp[:, [1, 2, 0]], normalize=True, normalization="integral")
    torch.testing.assert_close(torch_hsh.hsh(d, 6), math.sqrt(2.0) * _signs(6) * E, rtol=0, atol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_cuda_matches_cpu(backend, restore_backend):
    """On CUDA: sphericart's CUDA kernel for hsh (auto), the pure-torch kernels for the Helmholtz bases."""
    torch_hsh.set_backend(backend)
    a, b = _dirs(3000, 40), _dirs(3000, 41)
    for case in sorted(CASES):
        c = _dirs(3000, 42, special=False)
        cpu = [x.clone().requires_grad_(True) for x in (a, b, c)]
        gpu = [x.cuda().requires_grad_(True) for x in (a, b, c)]
        y_cpu, y_gpu = CASES[case](*cpu, 4), CASES[case](*gpu, 4)
        torch.testing.assert_close(y_gpu.cpu(), y_cpu, rtol=0, atol=1e-11)
        if y_cpu.requires_grad:
            g_cpu = torch.autograd.grad(y_cpu.sum(), cpu, allow_unused=True)
            g_gpu = torch.autograd.grad(y_gpu.sum(), gpu, allow_unused=True)
            for u, v in zip(g_cpu, g_gpu):
                if u is not None:
                    torch.testing.assert_close(v.cpu(), u, rtol=0, atol=1e-9 * max(1.0, float(u.abs().max())))


@pytest.mark.skipif(not hasattr(os, "fork") or not HAS_NATIVE, reason="needs fork() and the C kernels")
def test_thread_pool_survives_fork():
    """A forked child splits the rows on its own thread pool: neither the parent's OpenMP team (which
    the kernels share with torch) nor an inherited pool has threads there, and either would hang.

    The child calls the kernel through ``parallel_rows`` only: torch's own OpenMP regions are not
    fork-safe (which is why DataLoader workers run on one torch thread)."""
    code = (
        "import os, numpy as np, torch, torch_hsh\n"
        "from torch_hsh import _native, kernel as basis\n"
        "torch.set_num_threads(2)\n"
        "n = 20000\n"
        "d = torch.nn.functional.normalize(torch.rand(n, 3), dim=-1); e = d.flip(0).contiguous()\n"
        "K, tab = basis._iso_core_args(3, torch.float32)\n"
        "fn = _native.library().iso_dirs_fwd_f32\n"
        "ref = torch.zeros(n, K)\n"  # the same kernel on the parent's threads (the split does not change values)
        "_native.parallel_rows(fn, n, d.data_ptr(), e.data_ptr(), 1e-30, 1e-6, *tab, ref.data_ptr())\n"
        "ref = ref.numpy().copy()\n"
        "out = torch.zeros(n, K)\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    _native.parallel_rows(fn, n, d.data_ptr(), e.data_ptr(), 1e-30, 1e-6, *tab, out.data_ptr())\n"
        "    pool = _native.native_status()['threads'].startswith('pool')\n"
        "    os._exit(0 if np.array_equal(out.numpy(), ref) and pool else 3)\n"
        "_, status = os.waitpid(pid, 0)\n"
        "print(os.waitstatus_to_exitcode(status))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "0"


def test_order0_double_backward_is_zero():
    """Order 0 is a constant: the create_graph fallbacks of the C kernels return zeros, not an error."""
    a = _dirs(10, 50, special=False).requires_grad_(True)
    b = _dirs(10, 51, special=False).requires_grad_(True)
    for f in (lambda: torch_hsh.helmholtz_isotropic(a, b, 0), lambda: torch_hsh.helmholtz_isotropic(a, a, 0)):
        y = f().sum() + 0.0 * (a.sum() + b.sum())
        g = torch.autograd.grad(y, (a, b), create_graph=True)
        assert all(torch.equal(x.detach(), torch.zeros_like(x)) for x in g)
