"""Benchmark the photometric-stereo solvers on 2 CPU threads.

Usage:
    python benchmarks/bench_ps.py --data ../shared/data/bunny_specular
    python benchmarks/bench_ps.py --synthetic-size 16000 --lights 96

``--data``: a DiLiGenT-layout folder with ground truth; prints mean / median
angular error and time of Lambertian LS, robust (trimmed) Lambertian and the
HSH solver (shared basis BRDFs, the default; ``--independent`` adds the
independent per-pixel model). ``--synthetic-size N``: times the HSH solver on a DiLiGenT-sized
synthetic problem (N pixels, ``--lights`` lights, RGB, Blinn-Phong + GGX).
"""
from __future__ import annotations

import argparse
import time

import torch


def run_data(path, order, threads, max_pixels=None, independent=False):
    from torch_hsh import ps
    from torch_hsh.io.diligent import load_diligent

    d = load_diligent(path, dtype=torch.float64)
    mask = d.mask
    if max_pixels:
        idx = mask.reshape(-1).nonzero().squeeze(1)
        g = torch.Generator().manual_seed(0)
        keep = idx[torch.randperm(idx.numel(), generator=g)[:max_pixels]]
        m = torch.zeros(mask.numel(), dtype=torch.bool)
        m[keep] = True
        mask = m.reshape(mask.shape)
    print(f"{path}: {int(mask.sum())} pixels, {d.images.shape[0]} lights, {threads} threads")
    rows = []
    for name, fn in (
        ("Lambertian LS", lambda: ps.lambertian_ls(d.images, d.lights, mask=mask)),
        ("robust Lambertian (25%/10%)", lambda: ps.robust_lambertian(d.images, d.lights, mask=mask)),
        (f"HSH order {order} (shared, default)", lambda: ps.solve_hsh(d.images, d.lights, mask=mask, order=order)),
    ) + ((
        (f"HSH order {order} (independent)",
         lambda: ps.solve_hsh(d.images, d.lights, mask=mask, order=order, materials=None)),
    ) if independent else ()):
        t = time.perf_counter()
        r = fn()
        dt = time.perf_counter() - t
        e = ps.angular_error(r.normals, d.normals_gt)[mask] if d.normals_gt is not None else torch.tensor([float("nan")])
        rows.append((name, float(e.mean()), float(e.median()), dt))
    print(f"{'method':34s} {'mean':>7s} {'median':>7s} {'time s':>8s}")
    for name, m, md, dt in rows:
        print(f"{name:34s} {m:7.2f} {md:7.2f} {dt:8.2f}")


def run_synthetic(n_pix, n_lights, order, repeat=3):
    from torch_hsh import ps
    from torch_hsh.brdf import BlinnPhong
    from torch_hsh.render import render

    g = torch.Generator().manual_seed(0)
    n = torch.randn(n_pix, 3, generator=g, dtype=torch.float64) * torch.tensor([0.4, 0.4, 0.2], dtype=torch.float64)
    n[:, 2] += 1.0
    n = torch.nn.functional.normalize(n, dim=-1)
    l = torch.randn(n_lights, 3, generator=g, dtype=torch.float64) * torch.tensor([0.4, 0.4, 0.1], dtype=torch.float64)
    l[:, 2] += 1.0
    l = torch.nn.functional.normalize(l, dim=-1)
    alb = 0.2 + 0.6 * torch.rand(n_pix, 3, generator=g, dtype=torch.float64)
    img = render(n, l, BlinnPhong(alb, torch.full((n_pix, 1), 0.3, dtype=torch.float64),
                                  torch.full((n_pix, 1), 20.0, dtype=torch.float64)), read_std=1e-3, seed=0)
    times = []
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        r = ps.solve_hsh(img, l, order=order, progress=repeat == 1)
        times.append(time.perf_counter() - t)
    times.sort()
    dt = times[len(times) // 2]
    e = ps.angular_error(r.normals, n)
    if len(times) > 1:
        print(f"runs: {', '.join(f'{x:.2f}' for x in times)} s (best {times[0]:.2f}, median {dt:.2f})")
    print(f"synthetic: {n_pix} pixels x {n_lights} lights x RGB, order {order}: {dt:.2f} s (median), "
          f"mean error {float(e.mean()):.2f} deg (Lambertian LS "
          f"{float(ps.angular_error(ps.lambertian_ls(img, l).normals, n).mean()):.2f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--synthetic-size", type=int, default=0)
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--order", type=int, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3, help="synthetic timing: runs (median and best reported)")
    ap.add_argument("--max-pixels", type=int, default=None, help="random subset of the mask (quick runs)")
    ap.add_argument("--independent", action="store_true", help="also run the independent per-pixel model (slow)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from torch_hsh.ps import DEFAULT_ORDER

    order = DEFAULT_ORDER if args.order is None else args.order
    if args.data:
        run_data(args.data, order, args.threads, args.max_pixels, args.independent)
    if args.synthetic_size:
        run_synthetic(args.synthetic_size, args.lights, order, args.repeat)
    if not args.data and not args.synthetic_size:
        ap.error("give --data DIR and/or --synthetic-size N")


if __name__ == "__main__":
    main()
