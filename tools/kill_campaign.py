"""Kill campaign: every ``torch-hsh`` writer killed with SIGTERM / SIGKILL at random moments.

For each writer (``ps``, ``rti``, ``view``, ``fit``, ``lights``) on tiny inputs: one run to completion makes the
"old" result; then each round starts a run that writes a different result over it (``--overwrite``), kills it
after a delay drawn uniformly within the measured duration of a run, and checks that every output is either the
old one, byte for byte, or the new one complete (equal to what a complete run writes), and that a SIGTERM left no
temporary beside it. A normal run follows each kill; after it nothing but the outputs may be left.

    python tools/kill_campaign.py --kills 50        # make kill (ARGS="--kills 5 --writers ps fit")

Prints one table row per writer and signal; exits 1 if a result was lost or debris was left.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import os
import random
import signal
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Dict, List

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_NUM_THREADS", "1")
WRITERS = ("ps", "rti", "view", "fit", "lights")
OUTPUTS = {"ps": ["res"], "rti": ["x.rti", "x_relight"], "view": ["x.html"], "fit": ["x.npz"], "lights": ["x.lp"]}
_VOLATILE = ("manifest.json", "metrics.json")  # timings and dates: compared by name only


def make_inputs(work: Path, paths_only: bool = False) -> Dict[str, Path]:
    """The tiny inputs (in ``work``): an RTI capture, a ps result of it, a MERL table, a glossy-sphere capture."""
    paths = {"capture": work / "capture", "result": work / "result", "merl": work / "ggx.binary",
             "sphere": work / "sphere"}
    if paths_only:
        return paths
    import numpy as np
    import torch

    from torch_hsh import cli
    from torch_hsh.brdf import BlinnPhong, CookTorranceGGX
    from torch_hsh.io.merl import tabulate_merl, write_merl
    from torch_hsh.render import render, scenes
    from torch_hsh.rti.io import save_rti
    from torch_hsh.rti.synthetic import write_synthetic_capture

    cap = write_synthetic_capture(paths["capture"], 32, 24, 8)
    cli.run(["ps", str(cap), "--out", str(paths["result"]), "--quiet", "--threads", "1", "--order", "2"])
    write_merl(paths["merl"], tabulate_merl(CookTorranceGGX(albedo=0.5, specular=0.5, roughness=0.3),
                                                         shape=(12, 12, 24)))
    n, m = scenes.sphere_normals(64, radius=0.8, dtype=torch.float64)
    lights = scenes.cone_lights(16, max_angle_deg=70.0, seed=0, dtype=torch.float64)
    one = torch.ones(64, 64, 1, dtype=torch.float64)
    img = render(n, lights, BlinnPhong(0.05 * one.expand(-1, -1, 3), one, 400 * one)) * m[None, ..., None]
    save_rti(paths["sphere"], img, torch.tensor([[0.0, 0.0, 1.0]]).expand(len(lights), 3),
             mask=np.asarray(m))
    return paths


def argv(writer: str, inputs: Dict[str, Path], out: Path, variant: int) -> List[str]:
    """The ``torch-hsh`` arguments of ``writer`` writing into ``out``; variants 0 and 1 write different results."""
    common = ["--overwrite", "--quiet"]
    exposure = ["--exposure", ("1.0", "1.5")[variant]]
    return {
        "ps": ["ps", str(inputs["capture"]), "--out", str(out / "res"), "--threads", "1", "--order", "23"[variant]],
        "rti": ["rti", str(inputs["result"]), "--rti", str(out / "x.rti"), "--relight", str(out / "x_relight"),
                "--threads", "1", *exposure],
        "view": ["view", str(inputs["result"]), "--out", str(out / "x.html"), "--threads", "1", *exposure],
        "fit": ["fit", str(inputs["merl"]), "--out", str(out / "x.npz"), "--order", "24"[variant]],
        "lights": ["lights", str(inputs["sphere"]), "--out", str(out / "x.lp"), "--sphere-circle", "31.5", "31.5",
                   ("25.6", "24.0")[variant]],
    }[writer] + common


def _files(path: Path):
    return sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]


def exact_digest(path: Path) -> str:
    """SHA-256 of the names and bytes of a file or a folder tree (``"missing"`` if it does not exist)."""
    if not os.path.lexists(path):
        return "missing"
    h = hashlib.sha256()
    for f in _files(path):
        h.update(str(f.relative_to(path.parent)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()


def content_digest(path: Path) -> str:
    """Like :func:`exact_digest`, but ``.npz`` files by their arrays (not ``metadata``) and the timing files by name:
    what a complete run of the same arguments writes. ``"invalid"`` for a ``ps`` folder that is not a result."""
    from torch_hsh.cli.result_folder import MANIFEST, is_result_folder

    if not os.path.lexists(path):
        return "missing"
    if path.is_dir() and (path / MANIFEST).exists() and not is_result_folder(path):
        return "invalid"
    h = hashlib.sha256()
    for f in _files(path):
        h.update(str(f.relative_to(path.parent)).encode() + b"\0")
        if f.suffix == ".npz":
            with zipfile.ZipFile(io.BytesIO(f.read_bytes())) as z:
                for name in sorted(n for n in z.namelist() if n != "metadata.npy"):
                    h.update(name.encode() + z.read(name))
        elif f.name not in _VOLATILE:
            h.update(f.read_bytes())
    return h.hexdigest()


def debris(out: Path, writer: str) -> List[str]:
    """Entries of ``out`` that are not the writer's outputs."""
    return sorted(set(os.listdir(out)) - set(OUTPUTS[writer]))


def _start(args: List[str]) -> int:
    """Fork a process that runs ``torch-hsh ARGS`` (this interpreter has imported torch_hsh already, so a run is the
    command's own work, without Python's start-up); returns its pid."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        code = 1
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)
            from torch_hsh import cli

            code = cli.main(args)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 1
        finally:
            os._exit(code)
    return pid


def _wait(pid: int) -> int:
    """The exit status of ``pid`` as ``subprocess`` gives it (``-N`` when killed by signal ``N``)."""
    status = os.waitpid(pid, 0)[1]
    return -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)


def _run(args: List[str]) -> float:
    t = time.perf_counter()
    rc = _wait(_start(args))
    if rc != 0:
        raise RuntimeError(f"torch-hsh {' '.join(args)} failed ({rc})")
    return time.perf_counter() - t


def campaign(writer: str, inputs: Dict[str, Path], out: Path, kills: int, rng: random.Random) -> List[dict]:
    """``kills`` rounds of kill + check + normal run on ``writer``; one dict per kill."""
    out.mkdir(parents=True, exist_ok=True)
    duration = _run(argv(writer, inputs, out, 0))
    refs: Dict[int, Dict[str, str]] = {0: {t: content_digest(out / t) for t in OUTPUTS[writer]}}
    state, rows, pending = 0, [], []
    for i in range(kills):
        sig = (signal.SIGTERM, signal.SIGKILL)[i % 2] if kills > 1 else rng.choice((signal.SIGTERM, signal.SIGKILL))
        new = 1 - state
        old = {t: exact_digest(out / t) for t in OUTPUTS[writer]}
        pid = _start(argv(writer, inputs, out, new))
        time.sleep(rng.uniform(0.0, duration))
        os.kill(pid, sig)
        rc = _wait(pid)
        row = {"signal": sig.name, "rc": rc, "after_kill": debris(out, writer),
               "intact": all(exact_digest(out / t) == old[t] for t in OUTPUTS[writer]),
               "now": {t: content_digest(out / t) for t in OUTPUTS[writer]},
               "old_exact": old, "exact": {t: exact_digest(out / t) for t in OUTPUTS[writer]}, "new": new}
        _run(argv(writer, inputs, out, new))  # the next normal run: cleans up, and is the reference of `new`
        done = {t: content_digest(out / t) for t in OUTPUTS[writer]}
        if new in refs and refs[new] != done:
            raise RuntimeError(f"{writer}: two complete runs of the same arguments differ: {refs[new]} {done}")
        refs[new] = done
        row["after_run"] = debris(out, writer)
        pending.append(row)
        state = new
    if len(refs) == 2 and refs[0] == refs[1]:
        raise RuntimeError(f"{writer}: the two variants write the same result; the check cannot tell them apart")
    for row in pending:  # judged now that both references are known
        each = [row["exact"][t] == row["old_exact"][t] or row["now"][t] == refs[row["new"]][t] for t in OUTPUTS[writer]]
        row["complete"] = row["now"] == refs[row["new"]]
        row["lost"] = not all(each)
        rows.append(row)
    return rows


def table(results: Dict[str, List[dict]]) -> str:
    """The per-writer, per-signal table (Markdown); "run stopped": the kill came before the run ended (exit status
    not 0); "mixed": ``rti`` with one output old and the other new (each complete)."""
    lines = ["| writer | signal | kills | run stopped | old intact | new complete | mixed | lost | debris after kill | "
             "debris after next run | exit codes |", "|" + "---|" * 11]
    for writer, rows in results.items():
        for sig in ("SIGTERM", "SIGKILL"):
            rs = [r for r in rows if r["signal"] == sig]
            if not rs:
                continue
            codes = sorted({r["rc"] for r in rs})
            lines.append(
                f"| {writer} | {sig} | {len(rs)} | {sum(r['rc'] != 0 for r in rs)} | {sum(r['intact'] for r in rs)} | {sum(r['complete'] for r in rs)} | "
                f"{sum(not r['intact'] and not r['complete'] and not r['lost'] for r in rs)} | "
                f"{sum(r['lost'] for r in rs)} | {sum(bool(r['after_kill']) for r in rs)} | "
                f"{sum(bool(r['after_run']) for r in rs)} | {', '.join(map(str, codes))} |")
    return "\n".join(lines)


def failures(results: Dict[str, List[dict]]) -> List[str]:
    """What broke the guarantees: a lost result, debris after a SIGTERM, debris after the next normal run."""
    bad = []
    for writer, rows in results.items():
        for i, r in enumerate(rows):
            if r["lost"] or r["after_run"] or (r["signal"] == "SIGTERM" and r["after_kill"]):
                bad.append(f"{writer} kill {i} ({r['signal']}, exit {r['rc']}): lost={r['lost']} "
                           f"after kill {r['after_kill']} after the next run {r['after_run']}")
    return bad


def main(argv_: List[str] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=50, help="kills per writer (default 50), SIGTERM and SIGKILL alternating")
    ap.add_argument("--writers", nargs="+", choices=WRITERS, default=list(WRITERS))
    ap.add_argument("--seed", type=int, default=0, help="seed of the kill delays")
    ap.add_argument("--work", default=None, help="working folder (default: a temporary one, removed)")
    args = ap.parse_args(argv_)
    rng = random.Random(args.seed)
    import torch_hsh.io.merl  # noqa: F401  (imported once: every run is forked from this process)
    import torch_hsh.rti.fitting  # noqa: F401
    import torch_hsh.rti.viewer  # noqa: F401
    from torch_hsh import cli

    cli.build_parser()

    with tempfile.TemporaryDirectory(prefix="torch-hsh-kills-") as tmp:
        work = Path(args.work or tmp)
        pid = os.fork()
        if pid == 0:  # pragma: no cover (the child: torch's work stays out of the process that forks the runs)
            try:
                make_inputs(work)
            finally:
                os._exit(0)
        if _wait(pid) != 0:
            raise RuntimeError("making the inputs failed")
        inputs = make_inputs(work, paths_only=True)
        results = {}
        for w in args.writers:
            t = time.perf_counter()
            results[w] = campaign(w, inputs, work / f"out_{w}", args.kills, rng)
            print(f"{w}: {args.kills} kills in {time.perf_counter() - t:.0f} s", flush=True)
    print(table(results))
    bad = failures(results)
    print("\n".join(bad) if bad else f"{sum(map(len, results.values()))} kills: no result lost, no debris")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
