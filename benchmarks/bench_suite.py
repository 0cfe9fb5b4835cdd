"""The issue-21 benchmark suite: per scene, the photometric-stereo stages, their errors and times.

Usage:
    python benchmarks/bench_suite.py                                  # the whole suite, solver seeds 0-4
    python benchmarks/bench_suite.py --shared ../shared/data          # captures read in place from here
    python benchmarks/bench_suite.py --kinds mitsuba synthetic --seeds 0 --json /tmp/suite.json
    python benchmarks/bench_suite.py --only bowl_principled --seeds 0 1
    python benchmarks/bench_suite.py --stages per-pixel --seeds 0 --basis-ridge 1e-3   # a default's sweep
    python benchmarks/bench_suite.py --quick                          # CI: tiny scenes, seed 0, 1 thread

The scenes are defined in ``benchmarks/suite.py`` (fixed before tuning): Mitsuba 3 path-traced
scenes (rendered on demand into the cache by ``benchmarks/mitsuba_scenes.py``; needs the ``bench``
extra), the library's synthetic cast-shadow scenes and the shared captures (``--shared``, default
``../shared/data`` beside the repository; read in place, never copied; missing ones are skipped
with a message).

Columns (stages). Each runs in its own process (``_ps_worker.py``), once per solver seed:

* ``LS``: Lambertian least squares (reference, seed-free);
* ``per-pixel``: ``solve_hsh`` with the defaults;
* ``per-pixel + cast_shadows=1``: ``solve_hsh(cast_shadows=1)``, one round of the cast-shadow loop;
* ``+surface``, ``+surface +shadows``: the whole-surface stage (:func:`torch_hsh.ps.refine_surface`)
  after the per-pixel solve of the same seed, without and with its cast shadows. The mean is what
  the stage returns with its safeguard (the start when the held-out-light error rises); ``forced``
  is the refined surface's own error, ``kept`` how many seeds the safeguard accepted, and the time
  is the stage's alone.
* ``+interreflection``: ``solve_hsh(interreflections=1)``: one bounce between pixels estimated from the
  first solve's surface (:mod:`torch_hsh.ps.interreflections`), removed from the images, the per-pixel
  stages run again with the first solve's calibration;
  the time is the whole run's (both solves and the bounce).
* ``+interreflection +surface +shadows``: the two together, as ``solve_hsh(interreflections=1,
  refine_surface=True)`` runs them: the whole-surface stage refines the interreflection loop's result on
  the images without the bounce (mean with the safeguard, ``forced``, ``kept`` as above; the time is the
  stage's alone, the start is the loop's result).

Every solve prints a line as soon as it ends (flushed); then one summary line per scene, and a
Markdown table at the end. Errors are the mean angular error (degrees) over the mask; ``spread``
is max - min of the per-seed means; time is the median wall time of one solve (CPU time in
brackets: the fairer clock on a shared machine).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import List, Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))
import suite as suite_mod  # noqa: E402
from _runner import run_worker  # noqa: E402

#: (column, worker arguments or None when the stage does not exist yet, what it is)
STAGES = [
    ("per-pixel", [], "solve_hsh, defaults"),
    ("per-pixel + cast_shadows=1", ["--cast-shadows", 1], "solve_hsh(cast_shadows=1)"),
    ("+surface", ["--surface", "plain"], "solve_hsh, then refine_surface(surface_shadows=False)"),
    ("+surface +shadows", ["--surface", "shadows"], "solve_hsh, then refine_surface() (shadows from its depth)"),
    ("+interreflection", ["--interreflections", 1], "solve_hsh(interreflections=1): one bounce removed, per-pixel stages again"),
    ("+interreflection +surface +shadows", ["--interreflections", 1, "--surface", "shadows"],
     "solve_hsh(interreflections=1), then refine_surface() on the images without the bounce"),
]

#: --stages names of the columns
_STAGE_KEYS = {"per-pixel": "per-pixel", "per-pixel + cast_shadows=1": "shadows", "+surface": "surface",
               "+surface +shadows": "surface-shadows", "+interreflection": "interreflection",
               "+interreflection +surface +shadows": "interreflection-surface"}


def _fmt(x: Optional[float], nd: int = 2) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


def summarize(runs: List[dict]) -> dict:
    means = [r["mean"] for r in runs]
    extra = {}
    if runs and "forced_mean" in runs[0]:
        extra = {"forced_mean": statistics.fmean(r["forced_mean"] for r in runs),
                 "start_mean": statistics.fmean(r["start_mean"] for r in runs),
                 "kept": sum(r["kept"] for r in runs)}
    return {**extra, "seeds": [r["seed"] for r in runs], "means": means, "mean": statistics.fmean(means),
            "spread": max(means) - min(means), "median_err": statistics.fmean(r["median"] for r in runs),
            "time_s": statistics.median(r["time_s"] for r in runs),
            "cpu_s": statistics.median(r["cpu_s"] for r in runs)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="CI smoke run: the suite's quick scenes, seed 0, 1 thread, at most 400 mask pixels; "
                         "captures only with an explicit --shared")
    ap.add_argument("--shared", default=None, help="folder holding the shared captures (default ../shared/data)")
    ap.add_argument("--only", nargs="+", default=None, help="run only these scenes (names of suite.py)")
    ap.add_argument("--kinds", nargs="+", default=None, choices=["mitsuba", "synthetic", "capture"])
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="solver seeds (default 0 1 2 3 4; quick 0)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads per solve (default 2; quick 1)")
    ap.add_argument("--render-threads", type=int, default=1, help="Mitsuba's threads when a scene is rendered")
    ap.add_argument("--max-pixels", type=int, default=None, help="random subset of the mask (quick: 400)")
    ap.add_argument("--mitsuba-root", default=None, help="cache root of the Mitsuba scenes (default: its cache)")
    ap.add_argument("--no-shadows", action="store_true", help="skip the cast_shadows=1 column")
    ap.add_argument("--stages", nargs="+", default=None, choices=sorted(set(_STAGE_KEYS.values())),
                    help="run only these columns (per-pixel: solve_hsh; shadows: cast_shadows=1; surface / "
                         "surface-shadows: the whole-surface stage); default all")
    ap.add_argument("--interreflection-radius", type=int, default=None,
                    help="solve_hsh(interreflection_radius=...) of the interreflection columns (default: the library's)")
    ap.add_argument("--basis-ridge", type=float, default=None,
                    help="solve_hsh(basis_ridge=...) of every solve (default: the library's default)")
    ap.add_argument("--json", default=None, help="write every record to this JSON file")
    args = ap.parse_args(argv)
    threads = args.threads or (1 if args.quick else 2)
    seeds = args.seeds if args.seeds is not None else ([0] if args.quick else list(suite_mod.SEEDS))
    max_pixels = args.max_pixels if args.max_pixels is not None else (400 if args.quick else None)
    if args.json is not None and not Path(args.json).resolve().parent.is_dir():
        ap.error(f"--json {args.json!r}: the folder does not exist")
    shared = Path(args.shared) if args.shared else (None if args.quick else suite_mod.default_shared())
    scenes = suite_mod.QUICK if args.quick else suite_mod.SUITE
    if args.only:
        known = {s.name for s in scenes}
        bad = [n for n in args.only if n not in known]
        if bad:
            ap.error(f"unknown scene(s) {bad}; known: {', '.join(sorted(known))}")
        scenes = [s for s in scenes if s.name in args.only]
    if args.kinds:
        scenes = [s for s in scenes if s.kind in args.kinds]
    want = set(args.stages or _STAGE_KEYS.values()) - ({"shadows"} if args.no_shadows else set())
    stages = [s for s in STAGES if s[1] is None or _STAGE_KEYS[s[0]] in want]
    common = ["--threads", threads] + (["--max-pixels", max_pixels] if max_pixels else [])
    if args.basis_ridge is not None:
        common += ["--basis-ridge", args.basis_ridge]
    if args.interreflection_radius is not None:
        common += ["--interreflection-radius", args.interreflection_radius]
    print(f"suite: {len(scenes)} scene(s), solver seeds {' '.join(map(str, seeds))}, {threads} thread(s) per solve"
          + (f", at most {max_pixels} mask px" if max_pixels else ""), flush=True)
    records = {}
    for sc in scenes:
        t0 = time.perf_counter()
        folder, why = suite_mod.available_folder(sc, shared=shared, mitsuba_root=args.mitsuba_root,
                                                 threads=args.render_threads, progress=suite_mod.render_progress)
        if folder is None:
            print(f"  {sc.name}: skipped ({why})", flush=True)
            continue
        prep = time.perf_counter() - t0
        rec = {"kind": sc.kind, "params": sc.params, "folder": str(folder), "prepare_s": prep, "stages": {}}
        ls = run_worker(["--data", folder, "--methods", "ls", *common])
        m = ls["methods"]["ls"]
        rec.update(pixels=ls["pixels"], lights=ls["lights"], ls={"mean": m["mean"], "median": m["median"]})
        print(f"  {sc.name} ({sc.kind}, {ls['pixels']} px x {ls['lights']} lights, ready in {prep:.1f} s) "
              f"LS: mean {m['mean']:.2f} median {m['median']:.2f}", flush=True)
        for label, extra, what in stages:
            if extra is None:
                rec["stages"][label] = None
                continue
            runs = []
            for s in seeds:
                r = run_worker(["--data", folder, "--methods", "hsh", "--seed", s, *extra, *common])
                h = r["methods"]["surface" if "--surface" in extra else "hsh"]
                run = {"seed": s, "mean": h["mean"], "median": h["median"], "time_s": h["time_s"],
                       "cpu_s": h.get("cpu_s", 0.0), "peak_rss_mb": r["peak_rss_mb"]}
                more = ""
                if "--interreflections" in extra:
                    i = h["info"]
                    run.update(bounce_fraction=i.get("interreflection_fraction"),
                               bounce_time_s=i.get("interreflection_time_s"),
                               accepted=i.get("interreflection_accepted"),
                               confidence_before=i.get("interreflection_confidence_before"),
                               confidence_after=i.get("interreflection_confidence_after"))
                    more = f" (bounce {100 * run['bounce_fraction']:.2f} % of the light, {run['bounce_time_s']:.1f} s"
                    if run["accepted"] is not None:
                        more += (f", {'kept' if run['accepted'] else 'rejected'}: confidence "
                                 f"{run['confidence_before']:.4f} -> {run['confidence_after']:.4f}")
                    more += ")"
                if "--surface" in extra:
                    i = h["info"]
                    run.update(start_mean=r["methods"]["hsh"]["mean"], forced_mean=h["forced_mean"],
                               kept=bool(i.get("surface_accepted")), heldout_before=i.get("surface_heldout_before"),
                               heldout_after=i.get("surface_heldout_after"), start_time_s=r["methods"]["hsh"]["time_s"])
                    more = (f" (start {run['start_mean']:.2f}, forced {run['forced_mean']:.2f}, "
                            f"{'kept' if run['kept'] else 'rejected'}; held-out {_fmt(run['heldout_before'], 4)} -> "
                            f"{_fmt(run['heldout_after'], 4)})")
                runs.append(run)
                print(f"  {sc.name} {label} seed {s}: mean {h['mean']:.2f} median {h['median']:.2f} "
                      f"time {h['time_s']:.1f} s (cpu {h.get('cpu_s', 0):.1f} s){more}", flush=True)
            rec["stages"][label] = {"runs": runs, **summarize(runs)} if runs else None
        records[sc.name] = rec
        cells = []
        for label, extra, _ in stages:
            st = rec["stages"][label]
            cells.append(f"{label} n/a" if st is None else
                         f"{label} {st['mean']:.2f} (spread {st['spread']:.2f}, {st['time_s']:.1f} s"
                         + (f", forced {st['forced_mean']:.2f}, kept {st['kept']}/{len(st['runs'])})"
                            if "forced_mean" in st else ")"))
        print(f"{sc.name}: LS {rec['ls']['mean']:.2f} | " + " | ".join(cells), flush=True)
    _print_table(records, stages, seeds)
    if args.json:
        Path(args.json).write_text(json.dumps({"seeds": seeds, "threads": threads, "max_pixels": max_pixels,
                                               "scenes": records}, indent=1))
    return 0


def _print_table(records, stages, seeds):
    heads = ["scene", "kind", "px x lights", "LS"]
    for label, extra, _ in stages:
        heads += [label] if extra is None else [f"{label}: mean (spread)", "time"] + (
            ["forced", "kept"] if "--surface" in extra else [])
    print("\n| " + " | ".join(heads) + " |")
    print("|" + "---|" * len(heads))
    for name, rec in records.items():
        row = [name, rec["kind"], f"{rec['pixels']:,} x {rec['lights']}", _fmt(rec["ls"]["mean"])]
        for label, extra, _ in stages:
            st = rec["stages"][label]
            if extra is None:
                row.append("n/a")
            else:
                row += [f"{st['mean']:.2f} ({st['spread']:.2f})", f"{st['time_s']:.1f} s"]
                if "--surface" in extra:
                    row += [f"{st['forced_mean']:.2f}", f"{st['kept']}/{len(st['runs'])}"]
        print("| " + " | ".join(row) + " |")
    print(f"\nsolver seeds {' '.join(map(str, seeds))}; +surface columns: mean with the safeguard, forced = the refined surface, kept = seeds the safeguard accepted, time = the stage alone; +interreflection time = both solves and the bounce", flush=True)


if __name__ == "__main__":
    sys.exit(main())
