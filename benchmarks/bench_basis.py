"""Benchmark of the HSH / Helmholtz basis kernels against sphericart, e3nn and an elementwise multiply.

Everything is measured in one run, on ``--threads`` CPU threads (default 2) or on ``--device cuda``,
in float32, and printed one line per measurement as it goes. Each number is the median over
``--repeats`` runs after ``--warmup`` untimed runs; every ratio compares two numbers of the same run.

1. :func:`torch_hsh.hsh` for ``--n`` directions (default 200,000) at orders 2, 4, 8, 12, forward and
   forward+backward (gradient with respect to the directions), next to sphericart-torch's
   ``SphericalHarmonics(L)`` and e3nn's ``o3.spherical_harmonics`` (degrees 0..L, ``normalize=True``)
   on the same directions (the same number of outputs, ``(L+1)**2``): ratio ours / theirs.
2. :func:`torch_hsh.helmholtz_isotropic` (two direction sets, ``--pairs`` pairs, default 100,000) at
   P = 2, 4, 8 and :func:`torch_hsh.helmholtz_anisotropic` at P = 1, 2, 4 against ``a * b`` over an
   output of the same size, the cost floor of writing that output once. forward+backward is
   compared with the multiply's *forward*.
3. One Adam step of ``examples/train_brdf.py``'s model (``HelmholtzBRDF(order=4, channels=3)``,
   batch 1024) and a full-batch step (``--pairs`` samples).

Sections 1-3 run for each ``--backend`` (default ``auto torch``): ``auto`` is the library's default
(sphericart for the HSH where installed, the fused C kernels for the Helmholtz bases on the CPU),
``torch`` the pure-torch kernels, i.e. the library before these fast paths. A missing optional
package (e3nn, sphericart-torch) is reported and its column skipped.

Usage::

    python benchmarks/bench_basis.py [--threads 2] [--n 200000] [--pairs 100000]
    python benchmarks/bench_basis.py --quick        # seconds: small sizes, 3 repeats
    python benchmarks/bench_basis.py --device cuda  # with device synchronisation
    python benchmarks/bench_basis.py --backend auto --sections hsh --orders 2 4      # only some rows
    python benchmarks/bench_basis.py --backend auto --sections bases --iso-orders 2 4 --aniso-orders
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import Callable, List, Optional

import torch

import torch_hsh


def timeit(fn: Callable[[], object], repeats: int, warmup: int, device: torch.device) -> float:
    """Median wall time in seconds of ``fn()`` over ``repeats`` runs after ``warmup`` runs."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def fwd_bwd(make: Callable[..., torch.Tensor], *xs: torch.Tensor) -> Callable[[], None]:
    """Closure timing forward + backward of ``make(*xs).sum()`` with respect to the first input."""
    xg = xs[0].detach().clone().requires_grad_(True)
    rest = xs[1:]

    def run() -> None:
        xg.grad = None
        make(xg, *rest).sum().backward()

    return run


def fwd(make: Callable[..., torch.Tensor], *xs: torch.Tensor) -> Callable[[], None]:
    def run() -> None:
        with torch.no_grad():
            make(*xs)

    return run


def load_e3nn():
    try:
        from e3nn import o3  # noqa: F401
    except Exception as exc:  # pragma: no cover - optional dependency
        print(f"e3nn not available ({type(exc).__name__}: {exc}); skipping e3nn timings", flush=True)
        return None
    return o3


def load_sphericart():
    try:
        import sphericart.torch as sct
    except Exception as exc:  # pragma: no cover - optional dependency
        print(f"sphericart-torch not available ({type(exc).__name__}: {exc}); skipping sphericart timings", flush=True)
        return None
    return sct


def ratio(ours: float, theirs: Optional[float]) -> str:
    return "   n/a" if theirs is None else f"{ours / theirs:6.2f}"


def ms(t: Optional[float]) -> str:
    return "      n/a" if t is None else f"{1e3 * t:9.3f}"


def hemi(n: int, device: torch.device) -> torch.Tensor:
    d = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    d[:, 2] = d[:, 2].abs()
    return d.to(device)


def section_hsh(args, device, o3, sct, backend: str, results: List[dict]) -> None:
    d = hemi(args.n, device)
    print(f"\n== [{backend}] hsh, {args.n} directions: ms (ratio = torch_hsh / other) ==", flush=True)
    print(f"{'order':>5} {'pass':>8} {'hsh':>9} {'sphcart':>9} {'e3nn':>9} {'hsh/sph':>8} {'hsh/e3nn':>9}", flush=True)
    for L in args.orders:
        sph = sct.SphericalHarmonics(L) if sct is not None else None
        for mode, wrap in (("fwd", fwd), ("fwd+bwd", fwd_bwd)):
            t_ours = timeit(wrap(lambda x, L=L: torch_hsh.hsh(x, L), d), args.repeats, args.warmup, device)
            t_sc = timeit(wrap(sph, d), args.repeats, args.warmup, device) if sph is not None else None
            t_e3 = None
            if o3 is not None:
                t_e3 = timeit(wrap(lambda x, ls=list(range(L + 1)): o3.spherical_harmonics(ls, x, normalize=True), d),
                              args.repeats, args.warmup, device)
            print(f"{L:>5} {mode:>8} {ms(t_ours)} {ms(t_sc)} {ms(t_e3)} {ratio(t_ours, t_sc):>8} "
                  f"{ratio(t_ours, t_e3):>9}", flush=True)
            results.append(dict(backend=backend, kind="hsh", order=L, mode=mode, ours=t_ours, sphericart=t_sc,
                                e3nn=t_e3))


def section_bases(args, device, backend: str, results: List[dict]) -> None:
    wi, wo = hemi(args.pairs, device), hemi(args.pairs, device)
    print(f"\n== [{backend}] Helmholtz bases, {args.pairs} pairs, against a * b of the same output size ==",
          flush=True)
    print(f"{'basis':>11} {'P':>2} {'K':>5} {'mul fwd':>9} {'fwd':>9} {'fwd+bwd':>9} {'fwd/mul':>8} {'fb/mul':>7}",
          flush=True)
    for name, fn, orders in (("isotropic", torch_hsh.helmholtz_isotropic, args.iso_orders),
                             ("anisotropic", torch_hsh.helmholtz_anisotropic, args.aniso_orders)):
        for P in orders:
            K = torch_hsh.num_isotropic(P) if name == "isotropic" else torch_hsh.num_anisotropic(P)
            a = torch.randn(args.pairs, K, device=device)
            b = torch.randn(args.pairs, K, device=device)
            t_mul = timeit(lambda a=a, b=b: a * b, args.repeats, args.warmup, device)
            del a, b
            t_f = timeit(fwd(lambda x, y, P=P, fn=fn: fn(x, y, P), wi, wo), args.repeats, args.warmup, device)
            t_fb = timeit(fwd_bwd(lambda x, y, P=P, fn=fn: fn(x, y, P), wi, wo), args.repeats, args.warmup, device)
            print(f"{name:>11} {P:>2} {K:>5} {ms(t_mul)} {ms(t_f)} {ms(t_fb)} {t_f / t_mul:8.2f} {t_fb / t_mul:7.2f}",
                  flush=True)
            results.append(dict(backend=backend, kind=name, order=P, mul=t_mul, fwd=t_f, fwd_bwd=t_fb))


def section_training(args, device, backend: str, results: List[dict]) -> None:
    print(f"\n== [{backend}] one Adam step of examples/train_brdf.py's model (HelmholtzBRDF order 4, RGB) ==",
          flush=True)
    torch.manual_seed(0)
    for batch in (1024, args.pairs):
        model = torch_hsh.HelmholtzBRDF(order=4, channels=3).to(device)
        opt = torch.optim.Adam(model.parameters(), lr=0.05)
        wi, wo = hemi(batch, device), hemi(batch, device)
        target = torch.rand(batch, 3, device=device)

        def step(opt=opt, model=model, wi=wi, wo=wo, target=target) -> None:
            opt.zero_grad(set_to_none=True)
            loss = torch.mean((model(wi, wo) - target) ** 2)
            loss.backward()
            opt.step()

        t = timeit(step, args.repeats, args.warmup, device)
        print(f"batch {batch:>7}: {ms(t)} ms per step", flush=True)
        results.append(dict(backend=backend, kind="train_step", batch=batch, time=t))


def summary(results: List[dict]) -> None:
    """The before (torch) / after (auto) ratios of the same run."""
    by = {(r["backend"], r["kind"], r.get("order"), r.get("mode"), r.get("batch")): r for r in results}
    rows = [k for k in by if k[0] == "auto" and ("torch",) + k[1:] in by]
    if not rows:
        return
    print("\n== speed-up of the default (auto) over the pure-torch kernels (torch / auto time) ==", flush=True)
    for k in rows:
        a, t = by[k], by[("torch",) + k[1:]]
        if k[1] == "hsh":
            print(f"hsh P={k[2]:>2} {k[3]:>8}: {t['ours'] / a['ours']:6.2f}x", flush=True)
        elif k[1] == "train_step":
            print(f"train step batch {k[4]:>7}: {t['time'] / a['time']:6.2f}x", flush=True)
        else:
            print(f"{k[1]} P={k[2]}: fwd {t['fwd'] / a['fwd']:6.2f}x, fwd+bwd {t['fwd_bwd'] / a['fwd_bwd']:6.2f}x",
                  flush=True)


SECTIONS = ("hsh", "bases", "training")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--n", type=int, default=200_000, help="directions for the HSH timings")
    ap.add_argument("--pairs", type=int, default=100_000, help="direction pairs for the Helmholtz-basis timings")
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 4, 8, 12], help="HSH orders")
    ap.add_argument("--iso-orders", type=int, nargs="*", default=[2, 4, 8], help="none: skip the isotropic rows")
    ap.add_argument("--aniso-orders", type=int, nargs="*", default=[1, 2, 4], help="none: skip the anisotropic rows")
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=list(SECTIONS),
                    help="the sections to run (default all)")
    ap.add_argument("--backend", nargs="+", default=["auto", "torch"], choices=["auto", "torch"])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true",
                    help="a few seconds: small sizes, 3 repeats, orders 2 and 4 unless given")
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.pairs, args.repeats, args.warmup = 4000, 2000, 3, 1
        for name, quick in (("orders", [2, 4]), ("iso_orders", [2, 4]), ("aniso_orders", [1, 2])):
            if getattr(args, name) == ap.get_default(name):  # order lists given explicitly are kept
                setattr(args, name, quick)
    if min(args.n, args.pairs, args.repeats, args.threads) < 1 or args.warmup < 0:
        ap.error("--n, --pairs, --repeats and --threads must be positive, --warmup non-negative")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: no CUDA device is available")

    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    torch.manual_seed(args.seed)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {device}, float32, "
          f"median of {args.repeats} after {args.warmup} warm-up runs", flush=True)
    print(f"kernels: {torch_hsh.backend_status()}", flush=True)
    o3, sct = load_e3nn(), load_sphericart()

    results: List[dict] = []
    try:
        for backend in args.backend:
            torch_hsh.set_backend(backend)
            if "hsh" in args.sections:
                section_hsh(args, device, o3, sct, backend, results)
            if "bases" in args.sections:
                section_bases(args, device, backend, results)
            if "training" in args.sections:
                section_training(args, device, backend, results)
    finally:
        torch_hsh.set_backend("auto")
    summary(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
