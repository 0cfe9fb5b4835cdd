"""Real-capture benchmark: Lambertian LS, trimmed LS and the HSH solver on DiLiGenT-layout objects.

Usage:
    python benchmarks/bench_diligent.py ../shared/data/diligent_cat ../shared/data/diligent_harvest
    python benchmarks/bench_diligent.py /path/to/DiLiGenT/pmsData --drop-first 20 --seeds 0 1 2 3 4
    python benchmarks/bench_diligent.py ../shared/data/diligent_cat --baseline-tree DIR   # + an older solver
    python benchmarks/bench_diligent.py ../shared/data/diligent_harvest --cast-shadows 1  # + the shadow loop
    python benchmarks/bench_diligent.py ../shared/data/diligent_cat --flattened-starts     # + the opt-in starts
    python benchmarks/bench_diligent.py ../shared/data/diligent_cat --seeds 0 1 2 3 4 --basis-ridge 1e-3 1e-2

Arguments are object folders (``light_directions.txt``, images, ``mask.png``,
``Normal_gt.mat``) or the root of a DiLiGenT download (every ``*PNG`` folder
under it, or under its ``pmsData``). Per object it prints the mean and median
angular error (degrees, over the mask) and the wall time of each method; the
HSH solver runs once per seed and the table shows the mean over the seeds and
their spread (max - min of the mean error). Published mean errors of the
DiLiGenT benchmark (Shi et al., TPAMI 2019: baseline least squares, ST14 and
IA14, as quoted in the project's issue tracker) are printed beside objects
whose name matches. Every solve runs in its own process (``_ps_worker.py``),
so peak memory per solve is reported too. ``--cast-shadows R`` adds a row
for the solver with ``R`` rounds of the cast-shadow loop (``solve_hsh(...,
cast_shadows=R)``) beside the default solver, with the same seeds;
``--basis-ridge R [R ...]`` a row per relative ridge on the shared basis
BRDFs (``solve_hsh(basis_ridge=R)``), the knob that trades accuracy on
specular objects against the seed spread (docs/photometric_stereo.md).

Every solve prints a line as soon as it ends (``flush``). ``--quick`` (the CI smoke
run): one thread, at most 400 random mask pixels per object, seed 0 only (unless given).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _runner import ROOT, baseline_tree_arg, run_worker  # noqa: E402

#: Mean angular error (deg) published in the DiLiGenT benchmark (Shi et al., TPAMI 2019).
PUBLISHED = {
    "LS": dict(ball=4.10, bear=8.39, buddha=14.92, cat=8.41, cow=25.60, goblet=18.50, harvest=30.62, pot1=8.89,
               pot2=14.65, reading=19.80),
    "ST14": dict(ball=1.74, bear=6.12, buddha=10.60, cat=6.12, cow=13.93, goblet=10.09, harvest=25.44, pot1=6.51,
                 pot2=8.78, reading=13.63),
    "IA14": dict(ball=3.34, bear=7.11, buddha=10.47, cat=6.74, cow=13.05, goblet=9.71, harvest=25.95, pot1=6.64,
                 pot2=8.77, reading=14.19),
}


def object_name(path: Path) -> str:
    n = path.name.lower()
    for pre in ("diligent_",):
        n = n[len(pre):] if n.startswith(pre) else n
    return n[:-3] if n.endswith("png") else n


def expand(paths):
    out = []
    for p in map(Path, paths):
        if not p.is_dir():
            raise SystemExit(f"error: {p}: not a folder")
        if (p / "light_directions.txt").is_file():
            out.append(p)
            continue
        root = p / "pmsData" if (p / "pmsData").is_dir() else p
        objs = sorted(q for q in root.iterdir() if q.is_dir() and (q / "light_directions.txt").is_file())
        if not objs:
            raise SystemExit(f"error: {p}: neither an object folder (light_directions.txt) nor a DiLiGenT root")
        out.extend(objs)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="+", help="object folders or DiLiGenT roots")
    ap.add_argument("--drop-first", type=int, default=0, help="skip the first N images of every object")
    ap.add_argument("--max-images", type=int, default=None)
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="seeds of the HSH solver (default 0)")
    ap.add_argument("--materials", default="default", help="HSH materials: default, auto, none or an integer")
    ap.add_argument("--order", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads of every solve (default 2; 1 with --quick). More threads than free cores "
                         "make a solve many times slower, not faster")
    ap.add_argument("--max-pixels", type=int, default=None, help="random subset of the mask (quick runs)")
    ap.add_argument("--baseline-tree", type=baseline_tree_arg, default=None, metavar="DIR",
                    help="also run the solver of the torch_hsh package in DIR (an older checkout; "
                         "research/baseline_6d85856.py prints the speed issue's baseline)")
    ap.add_argument("--baseline-seeds", type=int, nargs="+", default=None,
                    help="seeds of the baseline runs (default: the same as --seeds)")
    ap.add_argument("--flattened-starts", action="store_true",
                    help="add a row: the HSH solver with the opt-in flattened calibration starts, same seeds")
    ap.add_argument("--basis-ridge", type=float, nargs="+", default=[],
                    help="add a row per value: the HSH solver with this relative ridge on the basis BRDFs, same seeds")
    ap.add_argument("--cast-shadows", type=int, default=0,
                    help="R > 0: also run the solver with R rounds of the cast-shadow loop")
    ap.add_argument("--json", default=None, help="write every record to this JSON file")
    ap.add_argument("--quick", action="store_true",
                    help="CI smoke run: --threads 1 --max-pixels 400 --seeds 0 (unless given)")
    args = ap.parse_args(argv)
    if args.threads is None:
        args.threads = 1 if args.quick else 2
    if args.seeds is None:
        args.seeds = [0]
    if args.quick and args.max_pixels is None:
        args.max_pixels = 400
    if args.json is not None and not Path(args.json).resolve().parent.is_dir():
        ap.error(f"--json {args.json!r}: the folder does not exist")
    if args.drop_first < 0:
        ap.error("--drop-first must be >= 0")
    common = ["--threads", args.threads, "--drop-first", args.drop_first]
    if args.max_images:
        common += ["--max-images", args.max_images]
    if args.max_pixels:
        common += ["--max-pixels", args.max_pixels]
    if args.order is not None:
        common += ["--order", args.order]
    if args.cast_shadows < 0:
        ap.error("--cast-shadows must be >= 0")
    trees = [("HSH", ROOT, [])]
    if args.cast_shadows:
        trees.append((f"HSH + shadows x{args.cast_shadows}", ROOT, ["--cast-shadows", args.cast_shadows]))
    if args.flattened_starts:
        trees.append(("HSH + flattened starts", ROOT, ["--flattened-starts"]))
    for r in args.basis_ridge:
        if not 0 < r <= 1:
            ap.error(f"--basis-ridge values must be in (0, 1], got {r}")
        trees.append((f"HSH basis ridge {r:g}", ROOT, ["--basis-ridge", r]))
    if args.baseline_tree:
        trees.append(("HSH baseline", args.baseline_tree, []))
    records = {}
    for obj in expand(args.paths):
        name = object_name(obj)
        rec = {"lambertian": run_worker(["--data", obj, "--methods", "ls,trimmed", *common])}
        for key, label in (("ls", "Lambertian LS"), ("trimmed", "trimmed LS")):
            m = rec["lambertian"]["methods"][key]
            print(f"  {name} {label}: mean {m['mean']:.2f} median {m['median']:.2f} time {m['time_s']:.1f} s",
                  flush=True)
        for label, tree, extra in trees:
            runs = []
            seeds = args.seeds if tree is ROOT or args.baseline_seeds is None else args.baseline_seeds
            for s in seeds:
                # an older tree may predate materials="auto"
                mat = args.materials if tree is ROOT else ("default" if args.materials == "auto" else args.materials)
                r = run_worker(["--data", obj, "--methods", "hsh", "--seed", s, "--materials", mat, *extra, *common], tree)
                runs.append(r)
                m = r["methods"]["hsh"]
                print(f"  {name} {label} seed {s}: mean {m['mean']:.2f} median {m['median']:.2f} "
                      f"time {m['time_s']:.1f} s (cpu {m.get('cpu_s', 0):.1f} s), peak RSS {r['peak_rss_mb']:.0f} MB", flush=True)
            rec[label] = runs
        records[name] = rec
        _print_object(name, rec, [t[0] for t in trees])
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1))


def _print_object(name, rec, labels):
    lam = rec["lambertian"]
    print(f"\n{name}: {lam['pixels']} pixels, {lam['lights']} lights")
    print(f"  {'method':24s} {'mean':>7s} {'median':>7s} {'spread':>7s} {'time s':>7s} {'cpu s':>7s}  {'MB':>6s}")
    for key, label in (("ls", "Lambertian LS"), ("trimmed", "trimmed LS")):
        m = lam["methods"][key]
        print(f"  {label:24s} {m['mean']:7.2f} {m['median']:7.2f} {'':>7s} {m['time_s']:7.2f} {m.get('cpu_s', 0):7.2f}")
    for label in labels:
        runs = rec[label]
        means = [r["methods"]["hsh"]["mean"] for r in runs]
        med = statistics.mean(r["methods"]["hsh"]["median"] for r in runs)
        t = statistics.median(r["methods"]["hsh"]["time_s"] for r in runs)
        cpu = statistics.median(r["methods"]["hsh"].get("cpu_s", 0.0) for r in runs)
        rss = max(r["peak_rss_mb"] for r in runs)
        spread = max(means) - min(means)
        extra = ""
        info = runs[0]["methods"]["hsh"]["info"]
        if "materials_chosen" in info:
            extra = f"  M = {', '.join(str(int(r['methods']['hsh']['info']['materials_chosen'])) for r in runs)}"
        print(f"  {label:24s} {statistics.mean(means):7.2f} {med:7.2f} {spread:7.2f} {t:7.2f} {cpu:7.2f}  {rss:6.0f}{extra}")
    for pub, vals in PUBLISHED.items():
        if name in vals:
            print(f"  {'published ' + pub:24s} {vals[name]:7.2f}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
