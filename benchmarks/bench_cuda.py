"""GPU numbers of the HSH photometric-stereo solver, in one call on a lent GPU.

Usage:
    python benchmarks/bench_cuda.py --out results/                 # on a machine with a CUDA device
    python benchmarks/bench_cuda.py --data ../shared/data/diligent_cat --size 1024
    python benchmarks/bench_cuda.py --device cpu --pixels 2000 --size 128   # dry run of the script itself

What it measures, in this order (each part is skipped once ``--budget-s``
seconds have passed, so a short device lease still returns the first parts):

1. **DiLiGenT-sized problem** (``--pixels`` px x ``--lights`` lights, RGB,
   the synthetic problem of ``bench_ps.py``): median wall time of
   ``--repeat`` solves after one warm-up, per stage, for the default settings
   (the chunk sized from the free device memory), the CPU's chunk of 8192
   pixels, and the one-pass setting
   (``refinement_passes=1, max_iter=8``); the mean angular error; the peak
   device memory; and the agreement with the same solve on this machine's
   CPU (all its cores), timed once.
2. **Host synchronisations**: the synchronising operations that
   ``torch.cuda.set_sync_debug_mode`` reports, per stage, and the counts of
   kernel launches and device-to-host copies from ``torch.profiler``, with
   the summed kernel time against the wall time (a solve whose kernels add up
   to much less than its wall time is bound by launches and synchronisations,
   not by the device's arithmetic).
3. **Real captures** given with ``--data`` (DiLiGenT layout): time and error.
4. **A large stack**: a ``--size`` x ``--size`` sphere with ``--lights``
   lights rendered on the device, solved with the default chunk (and with
   ``--large-chunk`` if given); time, peak device memory and error.
5. With ``--compile``: the DiLiGenT-sized problem again with the design
   kernels under ``torch.compile`` (an experiment; the first, compiling
   solve is timed separately).

Every measurement prints a line as soon as it ends (``flush``); the table is
printed again last. The full records go to ``--out`` as JSON, with the profiler's
table beside them. ``--quick`` (the CI smoke run, with ``--device cpu``: seconds):
``--pixels 300 --lights 20 --repeat 1 --size 32``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ps_worker import synthetic  # noqa: E402

STAGES = ("observations", "initialisation", "calibration", "refinement", "coefficients", "result")


def _sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _peak_reset(dev):
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)


def _peak_mb(dev):
    return torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else float("nan")


def _mean_err(ps, normals, gt, mask=None):
    e = ps.angular_error(normals.double(), gt.to(normals.device).double())
    e = e[mask] if mask is not None else e
    return float(e.mean())


def _timed(ps, dev, images, lights, repeat, mask=None, intensities=None, **kw):
    times, res, laps = [], None, []
    _peak_reset(dev)
    for _ in range(max(1, repeat)):
        _sync(dev)
        t = time.perf_counter()
        res = ps.solve_hsh(images, lights, intensities, mask, **kw)
        _sync(dev)
        times.append(time.perf_counter() - t)
        laps.append(res.info)
    stages = {s: statistics.median(i[f"time_{s}_s"] for i in laps) for s in STAGES if f"time_{s}_s" in res.info}
    return res, {"wall_s": statistics.median(times), "walls_s": times, "stages_s": stages, "peak_mb": _peak_mb(dev)}


def _sync_counts(ps, dev, images, lights, **kw):
    """Synchronising operations per stage (``set_sync_debug_mode``), CUDA only."""
    import torch_hsh.ps.pipeline as hsh

    per, orig = {}, hsh._StageClock.lap
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")

        def lap(self, name):
            torch.cuda.set_sync_debug_mode(0)  # the clock's own synchronisation is not counted
            per[name] = len(rec) - sum(per.values())
            orig(self, name)
            torch.cuda.set_sync_debug_mode("warn")

        hsh._StageClock.lap = lap
        try:
            torch.cuda.set_sync_debug_mode("warn")
            ps.solve_hsh(images, lights, **kw)
        finally:
            torch.cuda.set_sync_debug_mode(0)
            hsh._StageClock.lap = orig
    kinds = {}
    for w in rec:
        msg = str(w.message).split("\n")[0][:80]
        kinds[msg] = kinds.get(msg, 0) + 1
    return {"per_stage": per, "total": sum(per.values()), "kinds": kinds}


def _profile(ps, dev, images, lights, out: Path, **kw):
    from torch.profiler import ProfilerActivity, profile

    _sync(dev)
    t = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        ps.solve_hsh(images, lights, **kw)
        _sync(dev)
    wall = time.perf_counter() - t
    ka = prof.key_averages()
    counts = {e.key: e.count for e in ka if e.key.startswith("cuda") and e.key in (
        "cudaLaunchKernel", "cudaLaunchKernelExC", "cudaStreamSynchronize", "cudaMemcpyAsync", "cudaDeviceSynchronize")}
    attr = "self_device_time_total" if hasattr(ka[0], "self_device_time_total") else "self_cuda_time_total"
    kernel_us = sum(getattr(e, attr, 0) for e in ka if e.device_type is not None and "cuda" in str(e.device_type).lower())
    (out / "profile_16k.txt").write_text(ka.table(sort_by=attr, row_limit=40) + "\n\n" +
                                        ka.table(sort_by="cpu_time_total", row_limit=40))
    return {"wall_s_profiled": wall, "calls": counts, "kernel_time_s": kernel_us / 1e6}


def _compiled(ps, dev, images, lights, gt, repeat):
    """Time the solve with ``MixedDesign.__call__`` and ``_design_factors`` compiled (dynamic shapes)."""
    import torch_hsh.ps.calibration as cal
    import torch_hsh.ps.design as des
    import torch_hsh.ps.materials as mat
    import torch_hsh.ps.optim as opt

    orig_call, orig_f = des.MixedDesign.__call__, des._design_factors
    comp_f = torch.compile(orig_f, dynamic=True)
    mods = [m for m in (des, opt, cal, mat) if getattr(m, "_design_factors", None) is orig_f]
    try:
        des.MixedDesign.__call__ = torch.compile(orig_call, dynamic=True)
        for m in mods:
            m._design_factors = comp_f
        _sync(dev)
        t = time.perf_counter()
        ps.solve_hsh(images, lights, seed=0)
        _sync(dev)
        first = time.perf_counter() - t
        r, rec = _timed(ps, dev, images, lights, repeat, seed=0)
        rec["first_s"] = first
        rec["mean_err_deg"] = _mean_err(ps, r.normals, gt)
        return rec
    finally:
        des.MixedDesign.__call__ = orig_call
        for m in mods:
            m._design_factors = orig_f


def _large_stack(size, n_lights, dev):
    from torch_hsh.render import scenes
    from torch_hsh.brdf import BlinnPhong
    from torch_hsh.render import render

    n, mask = scenes.sphere_normals(size, radius=0.9, dtype=torch.float32, device=dev)
    lights = scenes.diligent_like_lights(n_lights, seed=0, dtype=torch.float32).to(dev)
    alb = (0.2 + 0.6 * scenes.albedo_texture(size, seed=0, dtype=torch.float32)).to(dev)
    ones = torch.ones(size, size, 1, device=dev)
    model = BlinnPhong(alb, 0.3 * ones, 30.0 * ones)
    g = torch.Generator().manual_seed(0)
    imgs = torch.empty(n_lights, size, size, 3, device=dev)
    for j in range(n_lights):
        im = render(n, lights[j:j + 1], model)[0]
        imgs[j] = (im + 1e-3 * torch.randn(im.shape, generator=g).to(dev)) * mask[..., None]
    return imgs, lights, mask, n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--pixels", type=int, default=16000)
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--data", nargs="*", default=[])
    ap.add_argument("--size", type=int, default=1024, help="side of the large stack (0: skip)")
    ap.add_argument("--large-chunk", type=int, default=0, help="also solve the large stack with this chunk")
    ap.add_argument("--compile", action="store_true",
                    help="last: also time the DiLiGenT-sized problem with the design kernels under torch.compile")
    ap.add_argument("--budget-s", type=float, default=330.0, help="start no new part after this many seconds")
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true", help="smoke run: --pixels 300 --lights 20 --repeat 1 --size 32")
    args = ap.parse_args(argv)
    if args.quick:
        args.pixels, args.lights, args.repeat, args.size = 300, 20, 1, 32
    t0 = time.perf_counter()
    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda, but torch sees no CUDA device")
    out = Path(args.out) if args.out else None
    if out:
        out.mkdir(parents=True, exist_ok=True)
    from torch_hsh import ps

    rec = {"torch": torch.__version__, "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
           "cpu_threads": torch.get_num_threads()}
    class Rows(list):
        def append(self, row):  # print each measurement as it ends
            super().append(row)
            name, w, e, m, stages = row
            print(f"{name:48s} {w:8.3f} s, mean error {e:.2f} deg, peak {m:.0f} MB", flush=True)

    rows = Rows()

    def over():
        return time.perf_counter() - t0 > args.budget_s

    def save():
        if out:
            (out / "bench_cuda.json").write_text(json.dumps(rec, indent=1, default=str))

    # 1. DiLiGenT-sized problem
    img, l, _, _, gt = synthetic(args.pixels, args.lights)
    img_d, l_d = img.to(dev), l.to(dev)
    ps.solve_hsh(img_d, l_d, seed=0)  # warm-up (CUDA context, kernels, allocator)
    configs = [("default", {}), ("chunk 8192", {"chunk_size": 8192}),
               ("one pass, 8 iter", {"refinement_passes": 1, "max_iter": 8})]
    rec["diligent_sized"] = {}
    for name, kw in configs:
        r, t = _timed(ps, dev, img_d, l_d, args.repeat, seed=0, **kw)
        t["mean_err_deg"] = _mean_err(ps, r.normals, gt)
        rec["diligent_sized"][name] = t
        rows.append((f"{args.pixels} px x {args.lights} L, {name}", t["wall_s"], t["mean_err_deg"], t["peak_mb"],
                     t["stages_s"]))
        if name == "default":
            n_dev = r.normals.detach().cpu().double()
        save()
    tc = time.perf_counter()
    r_cpu = ps.solve_hsh(img, l, seed=0)
    t_cpu = time.perf_counter() - tc
    agree = ps.angular_error(n_dev, r_cpu.normals.double())
    rec["cpu_reference"] = {"wall_s": t_cpu, "threads": torch.get_num_threads(),
                            "mean_err_deg": _mean_err(ps, r_cpu.normals, gt),
                            "device_vs_cpu_mean_deg": float(agree.mean()), "device_vs_cpu_max_deg": float(agree.max())}
    rows.append((f"same, CPU {torch.get_num_threads()} threads", t_cpu, rec["cpu_reference"]["mean_err_deg"], float("nan"),
                 {}))
    save()

    # 2. host synchronisations
    if dev.type == "cuda" and not over():
        try:
            rec["syncs"] = _sync_counts(ps, dev, img_d, l_d, seed=0)
            save()
            if out and not over():
                rec["profile"] = _profile(ps, dev, img_d, l_d, out, seed=0)
                save()
        except Exception as err:  # a measurement tool failing must not cost the parts after it
            rec["syncs_error"] = repr(err)
            print("part 2 failed:", repr(err), flush=True)

    # 3. real captures
    if args.data:
        from torch_hsh.io.diligent import load_diligent

        rec["real"] = {}
        for d in args.data:
            if over():
                break
            ds = load_diligent(d, dtype=torch.float32)
            im, li, m = ds.images.to(dev), ds.lights.to(dev), ds.mask.to(dev)
            r, t = _timed(ps, dev, im, li, 2, mask=m, seed=0)
            t["mean_err_deg"] = _mean_err(ps, r.normals, ds.normals_gt, m) if ds.normals_gt is not None else float("nan")
            t["pixels"] = int(m.sum())
            rec["real"][Path(d).name] = t
            rows.append((f"{Path(d).name} ({t['pixels']} px x {im.shape[0]} L)", t["wall_s"], t["mean_err_deg"],
                         t["peak_mb"], t["stages_s"]))
            save()
            del im, li, m, r

    # 4. a large stack
    if args.size and not over():
        imgs, lights, mask, n_gt = _large_stack(args.size, args.lights, dev)
        rec["large"] = {"pixels": int(mask.sum()), "stack_mb": imgs.numel() * 4 / 2**20}
        for name, kw in [("default", {})] + ([(f"chunk {args.large_chunk}", {"chunk_size": args.large_chunk})]
                                             if args.large_chunk else []):
            if over():
                break
            r, t = _timed(ps, dev, imgs, lights, 1, mask=mask, seed=0, **kw)
            t["mean_err_deg"] = _mean_err(ps, r.normals, n_gt, mask)
            rec["large"][name] = t
            rows.append((f"{args.size}^2 x {args.lights} L, {name}", t["wall_s"], t["mean_err_deg"], t["peak_mb"],
                         t["stages_s"]))
            save()
            del r

    # 5. experiment: the design kernels (a third of the launches) under torch.compile
    if args.compile and not over():
        try:
            rec["compiled_design"] = _compiled(ps, dev, img_d, l_d, gt, args.repeat)
            t = rec["compiled_design"]
            rows.append((f"{args.pixels} px, compiled design (1st {t['first_s']:.0f} s)", t["wall_s"],
                         t["mean_err_deg"], t["peak_mb"], t["stages_s"]))
        except Exception as err:
            rec["compiled_design_error"] = repr(err)[:2000]
            print("compile experiment failed:", repr(err)[:2000])
        save()

    rec["total_s"] = time.perf_counter() - t0
    save()
    print(json.dumps({k: rec[k] for k in ("syncs", "profile", "cpu_reference") if k in rec}, indent=1, default=str))
    print(f"\n{rec['device']}, torch {rec['torch']}")
    print(f"{'problem':48s} {'wall s':>8s} {'err deg':>8s} {'peak MB':>9s}  stages (s)")
    for name, w, e, m, stages in rows:
        st = ", ".join(f"{k[:5]} {v:.3f}" for k, v in stages.items())
        print(f"{name:48s} {w:8.3f} {e:8.2f} {m:9.0f}  {st}")


if __name__ == "__main__":
    main()
