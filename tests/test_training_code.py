"""The layers in real training code, on both backends (``"torch"`` and the default with the C kernels).

* mixed precision: ``torch.autocast`` (bfloat16) and half-precision modules and inputs compute in float32
  inside; the values against float32 eager within 2e-2 (bfloat16) and 5e-3 (float16) of the largest value;
* ``torch.compile(fullgraph=True)`` at row counts above the former chunking limit (2**20 / K rows), forward
  and backward against eager within 1e-5, and the whole graph captured at one million rows (orders 3 and 8);
* ``torch.jit.trace`` -> ``torch.jit.save`` -> ``torch.jit.load`` reproduces values and gradients;
* forward-mode AD (``torch.autograd.forward_ad``) against ``torch.func.jvp`` and central differences;
* ``torch.export`` with a dynamic batch dimension runs at other batch sizes;
* ``DistributedDataParallel`` on two processes (gloo) keeps the parameters equal on both ranks.
"""
from __future__ import annotations

import io
import os

import pytest
import torch
import torch.autograd.forward_ad as fwAD

import torch_hsh

BACKENDS = ["torch", "auto"]


@pytest.fixture(params=BACKENDS)
def backend(request):
    old = torch_hsh.get_backend()
    torch_hsh.set_backend(request.param)
    if request.param == "auto" and torch_hsh.backend_status()["isotropic_cpu"] != "native":
        torch_hsh.set_backend(old)
        pytest.skip("the C kernels are not available here")
    torch._dynamo.reset()
    yield request.param
    torch_hsh.set_backend(old)
    torch._dynamo.reset()


def _dirs(n: int, seed: int = 0, dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=torch.float64)
    v[:, 2] = v[:, 2].abs() + 0.05
    return torch.nn.functional.normalize(v, dim=-1).to(dtype)


def _rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    """Largest difference relative to the largest value of ``ref``."""
    return float((a.double() - ref.double()).abs().max() / ref.double().abs().max())


# --------------------------------------------------------------------------
# Mixed precision
# --------------------------------------------------------------------------
def test_autocast_bfloat16_head(backend):
    """The reproduction: coefficients from a Linear head under CPU autocast (bfloat16)."""
    torch.manual_seed(0)
    brdf = torch_hsh.HelmholtzBRDF(3, channels=3, learnable=False)
    head = torch.nn.Linear(16, 60)
    w, wo = _dirs(8, 1), _dirs(8, 2)
    x = torch.randn(8, 16)
    ref = brdf(w, wo, head(x).reshape(8, 3, 20))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        c = head(x).reshape(8, 3, 20)
        assert c.dtype == torch.bfloat16
        y = brdf(w, wo, c)
        same = brdf(w, w, c)  # one direction set
    assert y.dtype == torch.float32  # autocast's float32 operations return float32
    assert _rel(y, ref) <= 2e-2
    assert _rel(same, brdf(w, w, head(x).reshape(8, 3, 20))) <= 2e-2
    y.sum().backward()
    assert head.weight.grad is not None and torch.isfinite(head.weight.grad).all()


@pytest.mark.parametrize("dtype,tol", [(torch.float16, 5e-3), (torch.bfloat16, 2e-2)])
@pytest.mark.parametrize("isotropic", [True, False])
def test_half_module_and_inputs(backend, dtype, tol, isotropic):
    torch.manual_seed(0)
    order = 3 if isotropic else 2
    ref_m = torch_hsh.HelmholtzBRDF(order, basis="helmholtz_isotropic" if isotropic else "helmholtz_anisotropic", channels=3, init="zeros")
    with torch.no_grad():
        ref_m.coefficients.normal_()
    wi, wo = _dirs(500, 1), _dirs(500, 2)
    ref = ref_m(wi, wo)
    m = torch_hsh.HelmholtzBRDF(order, basis="helmholtz_isotropic" if isotropic else "helmholtz_anisotropic", channels=3, init="zeros")
    m.load_state_dict(ref_m.state_dict())
    m = m.to(dtype)
    y = m(wi.to(dtype), wo.to(dtype))
    assert y.dtype == dtype
    assert _rel(y, ref) <= tol
    y.float().sum().backward()
    assert m.coefficients.grad.dtype == dtype and torch.isfinite(m.coefficients.grad).all()
    assert _rel(m.albedo(wo.to(dtype)), ref_m.albedo(wo)) <= tol
    if isotropic:
        n = torch.tensor([0.0, 0.0, 1.0])
        yw = m.forward_world(wi.to(dtype), wo.to(dtype), n.to(dtype))
        assert yw.dtype == dtype and _rel(yw, ref_m.forward_world(wi, wo, n)) <= tol


@pytest.mark.parametrize("dtype,tol", [(torch.float16, 5e-3), (torch.bfloat16, 2e-2)])
def test_half_functions(backend, dtype, tol):
    """Half-precision inputs, against float32 on the unrounded inputs: the error is that of rounding the inputs
    (directions within 0.05 of the horizon stay on their side; a direction that the rounding moves across the
    horizon changes its value from H to 0)."""
    wi, wo = _dirs(300, 3), _dirs(300, 4)
    n = torch.tensor([0.0, 0.0, 1.0])
    h = lambda t: t.to(dtype)  # noqa: E731
    cases = [
        (torch_hsh.hsh(h(wi), 3), torch_hsh.hsh(wi, 3)),
        (torch_hsh.helmholtz_isotropic(h(wi), h(wo), 3), torch_hsh.helmholtz_isotropic(wi, wo, 3)),
        (torch_hsh.helmholtz_isotropic(h(wi), h(wi), 3), torch_hsh.helmholtz_isotropic(wi, wi, 3)),
        (torch_hsh.helmholtz_anisotropic(h(wi), h(wo), 2), torch_hsh.helmholtz_anisotropic(wi, wo, 2)),
        (torch_hsh.helmholtz_isotropic_world(h(wi), h(wo), h(n), 3), torch_hsh.helmholtz_isotropic_world(wi, wo, n, 3)),
        (torch_hsh.helmholtz_isotropic_cosines(h(wi[:, 2]), h(wo[:, 2]), h(wi[:, 0]), 3),
         torch_hsh.helmholtz_isotropic_cosines(wi[:, 2], wo[:, 2], wi[:, 0], 3)),
    ]
    for y, ref in cases:
        assert y.dtype == dtype
        assert _rel(y, ref) <= tol
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = torch_hsh.helmholtz_isotropic(h(wi), h(wo), 3)
    assert y.dtype == torch.float32


def test_half_refusals_still_name_the_argument():
    m = torch_hsh.HelmholtzBRDF(2)
    with pytest.raises(TypeError, match="`wi`"):
        m(_dirs(4).double(), _dirs(4))  # float64 against float32: still refused
    with pytest.raises(TypeError, match="`dirs` must be float32 or float64"):
        torch_hsh.hsh(torch.zeros(4, 3, dtype=torch.int32), 2)


# --------------------------------------------------------------------------
# torch.compile
# --------------------------------------------------------------------------
# (order, rows): above the former chunking limit of 2**20 // K rows (52,428 at order 3, 6,355 at order 8)
_ABOVE_LIMIT = [(3, 60_000), (8, 7_000)]


@pytest.mark.parametrize("order,n", _ABOVE_LIMIT)
def test_compile_fullgraph_above_old_limit(backend, order, n):
    brdf = torch_hsh.HelmholtzBRDF(order, channels=3, init="zeros")
    with torch.no_grad():
        brdf.coefficients.normal_(generator=torch.Generator().manual_seed(0))

    def loss_fn(wi, wo):
        return brdf(wi, wo).square().mean() + torch_hsh.hsh(wo, order).square().mean()

    wi, wo = _dirs(n, 1).requires_grad_(), _dirs(n, 2).requires_grad_()
    ref = loss_fn(wi, wo)
    ref_g = torch.autograd.grad(ref, [wi, wo, brdf.coefficients])
    compiled = torch.compile(loss_fn, fullgraph=True, backend="aot_eager", dynamic=True)
    out = compiled(wi, wo)
    g = torch.autograd.grad(out, [wi, wo, brdf.coefficients])
    assert _rel(out, ref) <= 1e-5
    for a, b in zip(g, ref_g):
        assert _rel(a, b) <= 1e-5


def _capture_only(graphs):
    """A torch.compile backend that keeps the captured graph and never runs it (a check of the capture only:
    its calls return empty tensors)."""
    def backend(gm, example_inputs):
        graphs.append(gm)
        n_out = len(next(n for n in gm.graph.nodes if n.op == "output").args[0])
        return lambda *args: tuple(torch.empty(0) for _ in range(n_out))
    return backend


@pytest.mark.parametrize("order", [3, 8])
def test_compile_fullgraph_one_million_rows(backend, order):
    """One graph, no break, at 1,000,000 rows (captured, not run: 165 million outputs at order 8)."""
    graphs = []
    brdf = torch_hsh.HelmholtzBRDF(order, channels=3)
    fn = torch.compile(lambda wi, wo: brdf(wi, wo).sum(), fullgraph=True, backend=_capture_only(graphs))
    w = torch.zeros(1_000_000, 3)
    w[:, 2] = 1.0
    fn(w, w.clone())
    assert len(graphs) == 1
    if backend == "auto":  # the C kernels are what the graph calls
        assert any("torch_hsh.isotropic" in str(n.target) for n in graphs[0].graph.nodes)


def test_compile_default_backend_runs_one_million_rows_order3():
    """Real execution of the compiled graph at 1,000,000 rows (order 3, default backend, forward)."""
    old = torch_hsh.get_backend()
    torch_hsh.set_backend("auto")
    try:
        torch._dynamo.reset()
        brdf = torch_hsh.HelmholtzBRDF(3, channels=3)
        fn = torch.compile(lambda wi, wo: brdf(wi, wo), fullgraph=True, backend="eager")
        wi, wo = _dirs(1_000_000, 1), _dirs(1_000_000, 2)
        with torch.no_grad():
            assert _rel(fn(wi, wo), brdf(wi, wo)) <= 1e-6
    finally:
        torch_hsh.set_backend(old)
        torch._dynamo.reset()


# --------------------------------------------------------------------------
# torch.jit.trace -> save -> load
# --------------------------------------------------------------------------
def test_jit_trace_save_load(backend):
    torch.manual_seed(0)

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.iso = torch_hsh.HelmholtzBRDF(3, channels=3, init=torch.randn(3, 20))
            self.aniso = torch_hsh.HelmholtzBRDF(1, basis="helmholtz_anisotropic", channels=3, init=torch.randn(3, 10))
            self.hsh = torch_hsh.HSH(2)

        def forward(self, wi, wo):
            return self.iso(wi, wo) + self.aniso(wi, wo) + self.hsh(wi)[..., 1:4]

    net = Net()
    wi, wo = _dirs(64, 1), _dirs(64, 2)
    net(wi, wo)
    traced = torch.jit.trace(net, (wi, wo))
    buf = io.BytesIO()
    torch.jit.save(traced, buf)
    buf.seek(0)
    loaded = torch.jit.load(buf)
    big_i, big_o = _dirs(60_000, 3).requires_grad_(), _dirs(60_000, 4)  # above the former chunk limit
    ref = net(big_i, big_o)
    out = loaded(big_i, big_o)
    assert _rel(out, ref) <= 1e-6
    g_ref, = torch.autograd.grad(ref.sum(), big_i)
    g, = torch.autograd.grad(out.sum(), big_i)
    assert float(g_ref.abs().max()) > 0.1
    assert _rel(g, g_ref) <= 1e-5


# --------------------------------------------------------------------------
# Forward-mode AD
# --------------------------------------------------------------------------
_FUNCS = {
    "hsh": lambda a, b: torch_hsh.hsh(a, 4),
    "isotropic": lambda a, b: torch_hsh.helmholtz_isotropic(a, b, 4),
    "isotropic_same": lambda a, b: torch_hsh.helmholtz_isotropic(a, a, 3),
    "anisotropic": lambda a, b: torch_hsh.helmholtz_anisotropic(a, b, 2),
    "world": lambda a, b: torch_hsh.helmholtz_isotropic_world(a, b, torch.tensor([0.1, 0.0, 1.0], dtype=a.dtype), 3),
    "cosines": lambda a, b: torch_hsh.helmholtz_isotropic_cosines(a[:, 2], b[:, 2], a[:, 0], 3),
}


@pytest.mark.parametrize("name", list(_FUNCS))
def test_forward_ad(backend, name):
    fn = _FUNCS[name]
    a, b = _dirs(200, 5, torch.float64), _dirs(200, 6, torch.float64)
    ta = torch.randn(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    with fwAD.dual_level():
        out = fn(fwAD.make_dual(a, ta), b)
        value, tangent = fwAD.unpack_dual(out)
    assert tangent is not None
    ref_value, ref_tangent = torch.func.jvp(lambda x: fn(x, b), (a,), (ta,))
    torch.testing.assert_close(value, ref_value, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(tangent, ref_tangent, rtol=1e-9, atol=1e-10)
    eps = 1e-6  # central differences
    fd = (fn(a + eps * ta, b) - fn(a - eps * ta, b)) / (2 * eps)
    assert _rel(tangent, fd) <= 1e-6


def test_forward_ad_module_and_large_batch(backend):
    """Through the module, at more rows than one chunk (the chunked path has no forward derivative)."""
    m = torch_hsh.HelmholtzBRDF(3, channels=3, init="zeros").double()
    with torch.no_grad():
        m.coefficients.normal_(generator=torch.Generator().manual_seed(0))
    a, b = _dirs(60_000, 1, torch.float64), _dirs(60_000, 2, torch.float64)
    ta = torch.randn_like(a)
    with fwAD.dual_level():
        tangent = fwAD.unpack_dual(m(fwAD.make_dual(a, ta), b)).tangent
    _, ref = torch.func.jvp(lambda x: m(x, b), (a,), (ta,))
    torch.testing.assert_close(tangent, ref, rtol=1e-9, atol=1e-10)


# --------------------------------------------------------------------------
# torch.export with a dynamic batch
# --------------------------------------------------------------------------
def test_export_dynamic_batch(backend):
    torch.manual_seed(0)

    class Svbrdf(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.brdf = torch_hsh.HelmholtzBRDF(3, channels=3, learnable=False)
            self.head = torch.nn.Linear(8, 60)

        def forward(self, x, wi, wo):
            return self.brdf(wi, wo, self.head(x).reshape(-1, 3, 20)) + torch_hsh.hsh(wi, 2)[..., :3]

    m = Svbrdf()
    B = torch.export.Dim("B")
    args = (torch.randn(64, 8), _dirs(64, 1), _dirs(64, 2))
    ep = torch.export.export(m, args, dynamic_shapes=({0: B}, {0: B}, {0: B}))
    for n in (5, 60_000):  # beyond the former limit of 52,428 rows
        x, wi, wo = torch.randn(n, 8), _dirs(n, 3), _dirs(n, 4)
        assert _rel(ep.module()(x, wi, wo), m(x, wi, wo)) <= 1e-6


# --------------------------------------------------------------------------
# DistributedDataParallel (two processes, gloo)
# --------------------------------------------------------------------------
def _ddp_worker(rank: int, world: int, store: str, out: str) -> None:
    import torch.distributed as dist

    def phase(name: str) -> None:  # where a stalled rank got to, for the failure message
        with open(f"{out}.{rank}.log", "a") as f:
            f.write(name + " ")

    torch.set_num_threads(1)
    phase("start")
    dist.init_process_group("gloo", init_method="file://" + store, rank=rank, world_size=world)
    phase("init")
    torch.manual_seed(0)  # the same initial parameters on both ranks
    head = torch.nn.Sequential(torch.nn.Linear(8, 32), torch.nn.ReLU(), torch.nn.Linear(32, 60))
    brdf = torch_hsh.HelmholtzBRDF(3, channels=3)

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.head, self.brdf = head, brdf

        def forward(self, x, wi, wo):
            return self.brdf(wi, wo, self.head(x).reshape(-1, 3, 20)) + self.brdf(wi, wo)

    model = torch.nn.parallel.DistributedDataParallel(Net())
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(100 + rank)  # different data on each rank
    losses = []
    for _ in range(3):
        x = torch.randn(256, 8, generator=g)
        wi, wo = _dirs(256, 10 + rank), _dirs(256, 20 + rank)
        loss = (model(x, wi, wo) - 0.3).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        phase(f"step{len(losses)}")
    flat = torch.cat([p.detach().reshape(-1) for p in model.parameters()])
    # each rank writes its own parameters (atomically): the test compares them; nothing after this is ours
    torch.save({"params": flat, "losses": losses}, f"{out}.{rank}.tmp")
    os.replace(f"{out}.{rank}.tmp", f"{out}.{rank}")
    dist.barrier()
    dist.destroy_process_group()


def test_ddp_two_processes(tmp_path):
    """Two gloo ranks train a model with a HelmholtzBRDF layer and end with identical parameters.

    The ranks see different data, so equal parameters mean DDP all-reduced the layer's gradients. gloo's
    rendezvous and teardown can stall on a loaded machine (pytorch/pytorch#75097): a rank that has written its
    result but has not exited 15 s later is killed, and a run where a rank never writes gets one fresh try.
    """
    import time

    import torch.multiprocessing as mp

    torch_hsh.hsh(torch.tensor([[0.0, 0.0, 1.0]]), order=1)  # the C kernels compiled before the workers start
    report: list[str] = []
    for attempt in range(2):
        out = str(tmp_path / f"result{attempt}.pt")
        ctx = mp.start_processes(_ddp_worker, args=(2, str(tmp_path / f"store{attempt}"), out), nprocs=2,
                                 join=False, start_method="spawn")
        written = lambda out=out: all(os.path.exists(f"{out}.{r}") for r in range(2))  # noqa: E731
        deadline = time.monotonic() + 150
        while not written() and time.monotonic() < deadline and any(p.is_alive() for p in ctx.processes):
            time.sleep(0.5)
        if written():
            exit_by = time.monotonic() + 15
            while any(p.is_alive() for p in ctx.processes) and time.monotonic() < exit_by:
                time.sleep(0.5)
        for proc in ctx.processes:
            if proc.is_alive():
                proc.kill()
            proc.join()
        if written():
            break
        codes = [proc.exitcode for proc in ctx.processes]
        logs = [open(f"{out}.{r}.log").read() if os.path.exists(f"{out}.{r}.log") else "" for r in range(2)]
        report.append(f"attempt {attempt}: exit codes {codes}, phases reached {logs}")
        assert all(c in (None, 0, -9) for c in codes), "a DDP worker failed: " + "; ".join(report)
    else:
        pytest.fail("the two DDP workers did not write their results within 150 s, twice: " + "; ".join(report))
    r0, r1 = (torch.load(f"{out}.{r}") for r in range(2))
    assert torch.equal(r0["params"], r1["params"])
    assert all(torch.isfinite(torch.tensor(r0["losses"] + r1["losses"])))
