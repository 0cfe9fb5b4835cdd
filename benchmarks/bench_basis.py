"""Benchmark of the HSH / Helmholtz basis evaluation against e3nn and sphericart.

Times, on ``--threads`` CPU threads (default 2) in float32:

* :func:`torch_hsh.hsh` for ``--n`` directions (default 200,000) at orders 2, 4, 8, 12,
  forward and forward+backward (gradient with respect to the directions), next to
  e3nn's ``o3.spherical_harmonics`` (all degrees 0..L, ``normalize=True``) and
  sphericart-torch's ``SphericalHarmonics(L)`` on the same directions (same number
  of outputs, ``(L+1)**2``), with the ratio ours / theirs;
* :func:`torch_hsh.helmholtz_isotropic` for the same directions (as ``wi``, paired
  with a second set ``wo``) at the same orders;
* :func:`torch_hsh.helmholtz_isotropic` at order 8 for ``--pairs`` pairs (default
  100,000, 165 outputs per pair) against a plain elementwise multiply ``a * b``
  over a ``(pairs, 165)`` output, the cost floor of writing that output once.

Each number is the median over ``--repeats`` runs after ``--warmup`` untimed runs.
A missing optional package (e3nn, sphericart-torch) is reported and skipped.

Usage::

    python benchmarks/bench_basis.py [--threads 2] [--n 200000] [--pairs 100000]
"""
from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable, Optional

import torch

import torch_hsh


def timeit(fn: Callable[[], object], repeats: int, warmup: int) -> float:
    """Median wall time in seconds of ``fn()`` over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def fwd_bwd(make: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> Callable[[], None]:
    """Closure timing forward + backward of ``make(x).sum()`` w.r.t. ``x``."""
    xg = x.detach().clone().requires_grad_(True)

    def run() -> None:
        xg.grad = None
        make(xg).sum().backward()

    return run


def fwd(make: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> Callable[[], None]:
    def run() -> None:
        with torch.no_grad():
            make(x)

    return run


def load_e3nn():
    try:
        from e3nn import o3  # noqa: F401
    except Exception as exc:  # pragma: no cover - optional dependency
        print(f"e3nn not available ({type(exc).__name__}: {exc}); skipping e3nn timings")
        return None
    return o3


def load_sphericart():
    try:
        import sphericart.torch as sct
    except Exception as exc:  # pragma: no cover - optional dependency
        print(f"sphericart-torch not available ({type(exc).__name__}: {exc}); skipping sphericart timings")
        return None
    return sct


def fmt_ratio(ours: float, theirs: Optional[float]) -> str:
    return "   n/a" if theirs is None else f"{ours / theirs:6.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--n", type=int, default=200_000, help="directions for the HSH timings")
    ap.add_argument("--pairs", type=int, default=100_000, help="pairs for the isotropic-vs-multiply timing")
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 4, 8, 12])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    dt = torch.float32
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float32, "
          f"median of {args.repeats} after {args.warmup} warm-up runs")

    o3 = load_e3nn()
    sct = load_sphericart()

    # directions on the upper hemisphere (all valid for the HSH basis)
    d = torch.nn.functional.normalize(torch.randn(args.n, 3, dtype=dt), dim=-1)
    d[:, 2] = d[:, 2].abs()
    d2 = torch.nn.functional.normalize(torch.randn(args.n, 3, dtype=dt), dim=-1)
    d2[:, 2] = d2[:, 2].abs()

    print(f"\n== {args.n} directions: times in ms (ratio = torch_hsh / other) ==")
    head = (f"{'order':>5} {'pass':>8} {'hsh':>9} {'e3nn':>9} {'sphcart':>9} "
            f"{'hsh/e3nn':>9} {'hsh/sph':>8} {'iso(wi,wo)':>11}")
    print(head)
    for L in args.orders:
        sph = sct.SphericalHarmonics(L) if sct is not None else None
        e3_ls = list(range(L + 1))
        for mode, wrap in (("fwd", fwd), ("fwd+bwd", fwd_bwd)):
            t_ours = timeit(wrap(lambda x, L=L: torch_hsh.hsh(x, L), d), args.repeats, args.warmup)
            t_e3 = None
            if o3 is not None:
                t_e3 = timeit(wrap(lambda x, ls=e3_ls: o3.spherical_harmonics(ls, x, normalize=True), d),
                              args.repeats, args.warmup)
            t_sc = None
            if sph is not None:
                t_sc = timeit(wrap(sph, d), args.repeats, args.warmup)
            t_iso = timeit(wrap(lambda x, L=L: torch_hsh.helmholtz_isotropic(x, d2, L), d), args.repeats, args.warmup)
            e3s = "      n/a" if t_e3 is None else f"{1e3 * t_e3:9.2f}"
            scs = "      n/a" if t_sc is None else f"{1e3 * t_sc:9.2f}"
            print(f"{L:>5} {mode:>8} {1e3 * t_ours:9.2f} {e3s} {scs} "
                  f"{fmt_ratio(t_ours, t_e3):>9} {fmt_ratio(t_ours, t_sc):>8} {1e3 * t_iso:11.2f}")

    # isotropic Helmholtz at P = 8 vs a plain multiply over the same output size
    P = 8
    K = torch_hsh.num_isotropic(P)
    wi = torch.nn.functional.normalize(torch.randn(args.pairs, 3, dtype=dt), dim=-1)
    wi[:, 2] = wi[:, 2].abs()
    wo = torch.nn.functional.normalize(torch.randn(args.pairs, 3, dtype=dt), dim=-1)
    wo[:, 2] = wo[:, 2].abs()
    a = torch.randn(args.pairs, K, dtype=dt)
    b = torch.randn(args.pairs, K, dtype=dt)
    with torch.no_grad():
        t_iso = timeit(lambda: torch_hsh.helmholtz_isotropic(wi, wo, P), args.repeats, args.warmup)
        t_iso_same = timeit(lambda: torch_hsh.helmholtz_isotropic(wi, wi, P), args.repeats, args.warmup)
        t_mul = timeit(lambda: a * b, args.repeats, args.warmup)
    print(f"\n== isotropic Helmholtz P={P}, {args.pairs} pairs x {K} outputs ==")
    print(f"helmholtz_isotropic(wi, wo): {1e3 * t_iso:8.2f} ms")
    print(f"helmholtz_isotropic(w, w):   {1e3 * t_iso_same:8.2f} ms")
    print(f"a * b over ({args.pairs}, {K}): {1e3 * t_mul:8.2f} ms")
    print(f"ratio isotropic / multiply:  {t_iso / t_mul:8.2f}  (target <= 4)")


if __name__ == "__main__":
    main()
