"""One photometric-stereo measurement in its own process (used by bench_ps.py and bench_diligent.py).

Runs with whatever ``torch_hsh`` is first on ``PYTHONPATH``: the working tree,
or an older tree given to ``--baseline-tree`` (``_runner.py``), so both are timed the same
way. Prints one JSON line: per method the mean / median angular error, the
wall time, selected ``info`` entries, and the process's peak RSS.

Usage (normally called by the benchmarks):
    python benchmarks/_ps_worker.py --data DIR --methods ls,trimmed,hsh --seed 0
    python benchmarks/_ps_worker.py --synthetic 16000 --lights 96 --methods hsh
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time
from pathlib import Path

import torch


def synthetic(n_pix: int, n_lights: int, seed: int = 0):
    """DiLiGenT-sized Blinn-Phong problem: random normals facing the camera, a cone of lights, RGB albedo, noise."""
    from torch_hsh.brdf import BlinnPhong
    from torch_hsh.render import render

    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    n = torch.randn(n_pix, 3, generator=g, dtype=dt) * torch.tensor([0.4, 0.4, 0.2], dtype=dt)
    n[:, 2] += 1.0
    n = torch.nn.functional.normalize(n, dim=-1)
    l = torch.randn(n_lights, 3, generator=g, dtype=dt) * torch.tensor([0.4, 0.4, 0.1], dtype=dt)
    l[:, 2] += 1.0
    l = torch.nn.functional.normalize(l, dim=-1)
    alb = 0.2 + 0.6 * torch.rand(n_pix, 3, generator=g, dtype=dt)
    img = render(n, l, BlinnPhong(alb, torch.full((n_pix, 1), 0.3, dtype=dt), torch.full((n_pix, 1), 20.0, dtype=dt)),
                 read_std=1e-3, seed=0)
    return img, l, None, None, n


def _rss_mb() -> float:
    """Current resident set size (Linux /proc), MB."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data")
    ap.add_argument("--synthetic", type=int, default=0)
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--methods", default="hsh")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--materials", default="default")
    ap.add_argument("--order", type=int, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--drop-first", type=int, default=0)
    ap.add_argument("--max-images", type=int, default=None)
    ap.add_argument("--max-pixels", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--cast-shadows", type=int, default=0)
    ap.add_argument("--interreflections", type=int, default=0)
    ap.add_argument("--flattened-starts", action="store_true")
    ap.add_argument("--basis-ridge", type=float, default=None)
    ap.add_argument("--interreflection-radius", type=int, default=None)
    ap.add_argument("--surface", choices=["plain", "shadows"], default=None,
                    help="after hsh: the whole-surface stage (refine_surface) without / with its cast shadows, "
                         "safeguard off; reported as method 'surface' (mean: what the safeguard returns, "
                         "forced_mean: the refined surface)")
    ap.add_argument("--surface-rounds", type=int, default=None)
    ap.add_argument("--surface-iterations", type=int, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from torch_hsh import ps

    t_load = time.perf_counter()
    rss_import = _rss_mb()
    if args.data and (Path(args.data) / "images.npy").is_file():  # a stack written by _stack.py
        import numpy as np

        f = Path(args.data)
        images = torch.from_numpy(np.load(f / "images.npy"))
        lights = torch.from_numpy(np.load(f / "lights.npy"))
        mask = torch.from_numpy(np.load(f / "mask.npy"))
        gt = torch.from_numpy(np.load(f / "normals.npy"))
        inten = None
    elif args.data:
        from torch_hsh.io.diligent import load_diligent

        kw = dict(dtype=torch.float32, drop_first=args.drop_first)
        if args.max_images:
            kw["max_images"] = args.max_images
        d = load_diligent(args.data, **kw)
        images, lights, inten, mask, gt = d.images, d.lights, None, d.mask, d.normals_gt
    else:
        images, lights, inten, mask, gt = synthetic(args.synthetic, args.lights)
    if args.max_pixels and mask is not None:
        idx = mask.reshape(-1).nonzero().squeeze(1)
        g = torch.Generator().manual_seed(0)
        keep = idx[torch.randperm(idx.numel(), generator=g)[: args.max_pixels]]
        m = torch.zeros(mask.numel(), dtype=torch.bool)
        m[keep] = True
        mask = m.reshape(mask.shape)
    dev = torch.device(args.device)
    images, lights = images.to(dev), lights.to(dev)
    mask = None if mask is None else mask.to(dev)
    load_s = time.perf_counter() - t_load
    kw = {}
    if args.order is not None:
        kw["order"] = args.order
    if args.cast_shadows:
        kw["cast_shadows"] = args.cast_shadows
    if args.interreflections:
        kw["interreflections"] = args.interreflections
    if args.flattened_starts:
        kw["calibration_starts"] = ("lambertian", "independent", "flattened")
    if args.basis_ridge is not None:
        kw["basis_ridge"] = args.basis_ridge
    if args.interreflection_radius is not None and args.interreflections:
        kw["interreflection_radius"] = args.interreflection_radius
    if args.materials != "default":
        kw["materials"] = None if args.materials == "none" else (args.materials if args.materials == "auto" else int(args.materials))
    import torch_hsh

    rss_loaded = _rss_mb()
    out = {"rss_import_mb": rss_import, "rss_loaded_mb": rss_loaded, "source": str(torch_hsh.__file__), "pixels": int(mask.sum()) if mask is not None else int(images[0].numel() // images.shape[-1]),
           "lights": int(images.shape[0]), "load_s": load_s, "methods": {}}
    results = {}
    seen = {"images": images, "intensities": inten}  # what the surface stage refines: the solve's own images

    def hsh():
        if not (args.surface and args.interreflections):
            return ps.solve_hsh(images, lights, inten, mask, seed=args.seed, **kw)
        # the surface stage after the interreflection loop fits the images without the bounce, as in
        # solve_hsh(interreflections=R, refine_surface=...): keep the loop's corrected images for it
        from torch_hsh.ps.interreflections import interreflection_loop
        from torch_hsh.ps.pipeline import run_stages

        res, seen["images"], seen["intensities"] = interreflection_loop(
            run_stages, images, lights, inten, mask, ps.Settings(seed=args.seed, **kw))
        return res

    solvers = {
        "ls": lambda: ps.lambertian_ls(images, lights, inten, mask),
        "trimmed": lambda: ps.robust_lambertian(images, lights, inten, mask),
        "hsh": hsh,
    }

    def surface():
        skw = dict(surface_shadows=args.surface == "shadows", surface_safeguard=False, seed=args.seed, **kw)
        if args.surface_rounds is not None:
            skw["refine_surface"] = args.surface_rounds
        if args.surface_iterations is not None:
            skw["surface_iterations"] = args.surface_iterations
        skw.pop("interreflections", None)
        return ps.refine_surface(results["hsh"], seen["images"], lights, seen["intensities"], **skw)

    solvers["surface"] = surface
    names = args.methods.split(",") + (["surface"] if args.surface else [])
    if args.surface and "hsh" not in names:
        names.insert(0, "hsh")
    for name in names:
        times, cpu = [], []
        for _ in range(max(1, args.repeat)):
            c0 = time.process_time()
            if dev.type == "cuda":
                torch.cuda.synchronize()
            t = time.perf_counter()
            r = solvers[name]()
            results[name] = r
            if dev.type == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c0)
        # CPU time (all threads) is the fairer clock on a shared, oversubscribed machine
        rec = {"time_s": sorted(times)[len(times) // 2], "times_s": times, "cpu_s": sorted(cpu)[len(cpu) // 2]}
        if gt is not None:
            m = mask if mask is not None else torch.ones(r.normals.shape[:-1], dtype=torch.bool, device=dev)
            e = ps.angular_error(r.normals.double(), gt.to(dev).double())[m]
            rec["mean"] = float(e.mean())
            rec["median"] = float(e.median())
            nz = (r.normals[m].norm(dim=-1) < 0.5) | ~torch.isfinite(r.normals[m]).all(-1)
            rec["bad_normals"] = int(nz.sum())
        info = getattr(r, "info", None) or {}
        rec["info"] = {k: (v if isinstance(v, (int, float, str)) and not (isinstance(v, float) and not math.isfinite(v)) else None)
                       for k, v in info.items() if not isinstance(v, (list, dict))}
        for k, v in info.items():
            if isinstance(v, (list, dict)):
                rec["info"][k] = v
        conf = getattr(r, "confidence", None)
        if conf is not None:
            c = conf[mask] if mask is not None else conf.reshape(-1)
            rec["confidence_mean"] = float(c.mean())
        if name == "surface" and "mean" in rec:
            start = out["methods"]["hsh"]
            rec["forced_mean"], rec["forced_median"] = rec["mean"], rec["median"]
            if not info.get("surface_accepted"):  # what the safeguard returns: the start
                rec["mean"], rec["median"] = start["mean"], start["median"]
        out["methods"][name] = rec
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if dev.type == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    json.dump(out, sys.stdout)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
