"""Speed of the HSH photometric-stereo solver, with stage shares and the ratio to a baseline measured in the same run.

Usage:
    python benchmarks/bench_ps.py --synthetic-size 16000 --lights 96 --repeat 3
    python benchmarks/bench_ps.py --data ../shared/data/bunny_specular --baseline-tree /path/to/old/checkout
    python benchmarks/bench_ps.py --stack 1024 --lights 96          # memory: peak RSS of a solve from a float32 stack

``--synthetic-size N``: a DiLiGenT-sized problem (N pixels, ``--lights``
lights, RGB, Blinn–Phong with random albedo, random normals, read noise).
``--data DIR``: a DiLiGenT-layout folder (errors against its ground truth).
``--baseline-tree DIR``: also run the solver of the ``torch_hsh`` package in
``DIR`` (an older checkout; ``research/baseline_6d85856.py`` prints the folder
of the speed issue's baseline), alternating runs with the working tree, and
print the speed-up. Every run is its own process;
both wall and CPU time are reported (on a shared, oversubscribed machine the
CPU time is the fairer clock). ``--stack S``: solve an S x S, ``--lights``-light
float32 RGB stack written to and loaded from disk (a sphere rendered by the
library; cached in ``--stack-dir``, default the system's temporary folder), and
report the peak RSS against the stack size.

Every solve prints a line as soon as it ends (``flush``), then each problem a
summary. ``--quick`` (the CI smoke run, seconds): one run per solver, one thread,
and the built-in synthetic problem at 400 pixels x 20 lights unless a problem is given.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _runner import ROOT, baseline_tree_arg, run_worker  # noqa: E402

STAGES = ("observations", "initialisation", "calibration", "refinement", "coefficients", "result")


def _summary(label, runs):
    h = [r["methods"]["hsh"] for r in runs]
    wall = statistics.median(x["time_s"] for x in h)
    cpu = statistics.median(x["cpu_s"] for x in h)
    err = statistics.mean(x["mean"] for x in h) if "mean" in h[0] else float("nan")
    walls = ", ".join(f"{x['time_s']:.1f}" for x in h)
    print(f"{label:28s} wall {wall:7.2f} s (runs {walls})  cpu {cpu:7.2f} s  "
          f"mean error {err:.2f} deg  peak RSS {max(r['peak_rss_mb'] for r in runs):.0f} MB", flush=True)
    info = h[0]["info"]
    if any(f"time_{s}_s" in info for s in STAGES):
        tot = sum(info.get(f"time_{s}_s", 0.0) for s in STAGES)
        print("    stage shares: " + ", ".join(f"{s} {100 * info.get(f'time_{s}_s', 0.0) / tot:.0f}%" for s in STAGES
                                              if f"time_{s}_s" in info), flush=True)
    return wall, cpu, err


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--synthetic-size", type=int, default=0)
    ap.add_argument("--stack", type=int, default=0, help="S: memory run on an S x S float32 stack from disk")
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--order", type=int, default=None)
    ap.add_argument("--materials", default="default")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads of every solve (default 2; 1 with --quick). More threads than free cores "
                         "make a solve many times slower, not faster")
    ap.add_argument("--repeat", type=int, default=3, help="runs per solver (alternating with the baseline)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--baseline-tree", type=baseline_tree_arg, default=None, metavar="DIR",
                    help="also time the torch_hsh package in DIR (an older checkout), alternating with the working tree")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--basis-ridge", type=float, default=None,
                    help="relative ridge on the basis BRDFs of the working tree's solver (default: the solver's)")
    ap.add_argument("--stack-dir", default=None,
                    help="folder of the --stack cache (default: the system's temporary folder)")
    ap.add_argument("--quick", action="store_true",
                    help="CI smoke run: --repeat 1, and --synthetic-size 400 --lights 20 unless a problem is given")
    args = ap.parse_args(argv)
    if args.threads is None:
        args.threads = 1 if args.quick else 2
    if args.quick:
        args.repeat = 1
        if not (args.data or args.synthetic_size or args.stack):
            args.synthetic_size, args.lights = 400, 20
    if not (args.data or args.synthetic_size or args.stack):
        ap.error("give --data DIR, --synthetic-size N and/or --stack S")
    common = ["--threads", args.threads, "--device", args.device, "--materials", args.materials]
    if args.order is not None:
        common += ["--order", args.order]
    problems = []
    if args.synthetic_size:
        problems.append((f"synthetic {args.synthetic_size} px x {args.lights} lights",
                         ["--synthetic", args.synthetic_size, "--lights", args.lights], False))
    if args.data:
        problems.append((str(args.data), ["--data", args.data], False))
    if args.stack:
        problems.append((f"{args.stack}x{args.stack} x {args.lights} stack",
                         _stack_args(args.stack, args.lights, args.stack_dir), True))
    trees = [("working tree", ROOT)] + ([("baseline", args.baseline_tree)] if args.baseline_tree else [])
    for name, pargs, is_stack in problems:
        print(f"\n{name}, {args.threads} threads, device {args.device}", flush=True)
        runs = {label: [] for label, _ in trees}
        for i in range(max(1, args.repeat)):
            for s in args.seeds:
                for label, tree in trees:
                    # an older tree may predate materials="auto"
                    mat = common if tree is ROOT else [a if a != "auto" else "default" for a in common]
                    if tree is ROOT and args.basis_ridge is not None:
                        mat = [*mat, "--basis-ridge", args.basis_ridge]
                    r = run_worker([*pargs, "--methods", "hsh", "--seed", s, *mat], tree)
                    runs[label].append(r)
                    h = r["methods"]["hsh"]
                    print(f"  run {i + 1}/{max(1, args.repeat)} {label}, seed {s}: wall {h['time_s']:.2f} s, "
                          f"cpu {h['cpu_s']:.2f} s, mean error {h.get('mean', float('nan')):.2f} deg, "
                          f"peak RSS {r['peak_rss_mb']:.0f} MB", flush=True)
        res = {label: _summary(label, r) for label, r in runs.items()}
        if args.baseline_tree:
            (w1, c1, e1), (w0, c0, e0) = res["working tree"], res["baseline"]
            print(f"    speed-up over the baseline: wall {w0 / w1:.2f}x, cpu {c0 / c1:.2f}x; "
                  f"error {e1:.2f} vs {e0:.2f} deg", flush=True)
        if is_stack:  # the memory run
            r = runs["working tree"][0]
            stack_mb = args.stack * args.stack * args.lights * 3 * 4 / 2**20
            extra = r["peak_rss_mb"] - r["rss_import_mb"]
            print(f"    stack {stack_mb:.0f} MB (float32); RSS after import {r['rss_import_mb']:.0f} MB, after load "
                  f"{r['rss_loaded_mb']:.0f} MB, peak {r['peak_rss_mb']:.0f} MB: peak - import = {extra:.0f} MB = "
                  f"{extra / stack_mb:.2f}x the stack (target <= 3x)", flush=True)


def _stack_args(size, lights, folder=None):
    from _stack import ensure_stack

    return ["--data", ensure_stack(size, lights, folder)]


if __name__ == "__main__":
    main()
