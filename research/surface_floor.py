"""The floor of a depth-map model of the normals: integrate the TRUE normals, differentiate the depth again.

Any method whose normals are the gradients of one depth map per pixel grid (the whole-surface stage,
:func:`torch_hsh.ps.refine_surface`, and every integrate-then-differentiate step) cannot be more
accurate on a scene than this: the mean angular error (degrees) between the ground-truth normals and
the normals of the depth integrated from them. Columns: the integrator
(:func:`torch_hsh.surface.integrate_normals`, Poisson / bilateral) times the difference scheme
(central differences, or the discontinuity-weighted one-sided mix of
:func:`torch_hsh.ps.whole_surface.depth_normals`).

Usage:
    python research/surface_floor.py                          # the suite's scenes (bench_suite.py)
    python research/surface_floor.py --only diligent_cat --shared ../shared/data
    python research/surface_floor.py --quick                  # CI: the quick scenes, Poisson only
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the suite's scenes
import suite as suite_mod  # noqa: E402


def floor_row(normals_gt: torch.Tensor, mask: torch.Tensor, methods) -> dict:
    """Mean angular error (deg) of the depth normals per (integrator, scheme), and the integration times."""
    from torch_hsh import ps
    from torch_hsh.ps import whole_surface as ws
    from torch_hsh.surface import integrate_normals

    gt = normals_gt.to(torch.float64)
    out = {}
    for method in methods:
        t = time.perf_counter()
        z = integrate_normals(gt, mask, method=method, fill=0.0)
        out[f"{method} time_s"] = time.perf_counter() - t
        for scheme in ("central", "one-sided mix"):
            w = (torch.full_like(z, 0.5),) * 2 if scheme == "central" else ws.discontinuity_weights(z, mask)
            n = ws.depth_normals(z, mask, w)
            out[f"{method} {scheme}"] = float(ps.angular_error(n, gt, mask)[mask].mean())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the suite's quick scenes, Poisson only")
    ap.add_argument("--shared", default=None, help="folder of the shared captures (default ../shared/data)")
    ap.add_argument("--only", nargs="+", default=None, help="these scenes only (names of suite.py)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from torch_hsh.io.diligent import load_diligent

    scenes = suite_mod.QUICK if args.quick else suite_mod.SUITE
    if args.only:
        scenes = [s for s in scenes if s.name in args.only]
    shared = Path(args.shared) if args.shared else (None if args.quick else suite_mod.default_shared())
    methods = ("poisson",) if args.quick else ("poisson", "bilateral")
    cols = [f"{m} {s}" for m in methods for s in ("central", "one-sided mix")]
    print("| scene | " + " | ".join(cols) + " |\n|" + "---|" * (len(cols) + 1), flush=True)
    for sc in scenes:
        folder, why = suite_mod.available_folder(sc, shared=shared)
        d = None if folder is None else load_diligent(folder)
        if d is None or d.normals_gt is None:
            print(f"| {sc.name} | skipped ({why or 'no ground-truth normals'}) |", flush=True)
            continue
        row = floor_row(d.normals_gt, d.mask, methods)
        print(f"| {sc.name} | " + " | ".join(f"{row[c]:.2f}" for c in cols) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
