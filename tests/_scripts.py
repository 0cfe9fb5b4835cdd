"""Helpers of the tests that run the example and benchmark scripts (tests/test_*_quick.py).

Every script runs in its own process, as a user would start it: ``sys.executable``, the repository
root as the working folder, ``OMP_NUM_THREADS=1`` and matplotlib's ``Agg`` backend. Outputs go to
``tmp_path``; nothing is written into the repository.
"""
from __future__ import annotations

import csv
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

ROOT = Path(__file__).resolve().parents[1]
TABLES = ROOT / "docs" / "tables"


class Run:
    """What a script run left: ``returncode``, ``stdout``, ``stderr``, ``wall_s`` and ``lines``, every stdout
    line with the time (s after the start) at which this process could read it."""

    def __init__(self, returncode, stdout, stderr, wall_s, lines):
        self.returncode, self.stdout, self.stderr, self.wall_s, self.lines = returncode, stdout, stderr, wall_s, lines

    @property
    def last(self) -> float:
        """Time at which the last stdout line could be read (not the exit, which can come much later)."""
        return self.lines[-1][0] if self.lines else 0.0

    def first(self, pattern: str) -> float:
        """Time at which the first line matching ``pattern`` (regex) could be read."""
        for t, line in self.lines:
            if re.search(pattern, line):
                return t
        raise AssertionError(f"no line matches {pattern!r}:\n{self.stdout[-3000:]}")


def run_script(script: str, *args, timeout: float = 600) -> Run:
    """Run ``script`` (relative to the repository root) with ``args``; fail the test on a non-zero exit.

    stdout is read line by line as the script writes it (through a pipe, so a script that does not
    flush shows its lines only at exit), which lets a test check that measurements appear as they go.
    """
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg")
    env.pop("PYTHONUNBUFFERED", None)  # stdout to a pipe or a file is block-buffered unless the script flushes
    t0 = time.perf_counter()
    lines = []
    with tempfile.TemporaryFile(mode="w+") as err:
        p = subprocess.Popen([sys.executable, str(ROOT / script), *map(str, args)], cwd=str(ROOT), env=env,
                             stdout=subprocess.PIPE, stderr=err, text=True)
        try:
            assert p.stdout is not None
            for line in p.stdout:
                lines.append((time.perf_counter() - t0, line.rstrip("\n")))
                if time.perf_counter() - t0 > timeout:
                    raise subprocess.TimeoutExpired(script, timeout)
            p.wait(timeout=max(1.0, timeout - (time.perf_counter() - t0)))
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        err.seek(0)
        stderr = err.read()
    r = Run(p.returncode, "\n".join(line for _, line in lines) + "\n", stderr, time.perf_counter() - t0, lines)
    assert r.returncode == 0, (f"{script} {' '.join(map(str, args))} exited {r.returncode}\n"
                               f"--- stdout\n{r.stdout[-4000:]}\n--- stderr\n{r.stderr[-4000:]}")
    return r


def load_example(script: str):
    """Import the script ``script`` (relative to the repository root) as a module, in this process, without
    running it (its ``if __name__ == "__main__"`` block): a test then calls its ``main(argv)`` or helpers."""
    import importlib.util

    path = ROOT / script
    spec = importlib.util.spec_from_file_location(f"{path.stem}_example", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _last_digit(s: str) -> float:
    """One unit in the last printed digit of a number as written (``0.0216128`` -> 1e-7, ``4.4e-11`` -> 1e-12)."""
    m = re.fullmatch(r"[-+]?\d*(?:\.(\d*))?(?:[eE]([-+]?\d+))?", s.strip())
    if m is None:
        return 0.0
    return 10.0 ** (int(m.group(2) or 0) - len(m.group(1) or ""))


def same_value(new: str, committed: str, atol: float = 0.0) -> bool:
    """Do two printed values agree, given that the tables print rounded values?

    The values themselves agree to about 1e-12 relative when only the order of floating-point
    operations differs, but the tables hold them rounded (6 significant digits, or 4 decimals in the
    Markdown tables). A value close to a rounding boundary can then print one unit apart in the last
    digit, so that is allowed, and nothing more. Values below 1e-12 in magnitude on both sides are
    round-off (the error estimate of an exactly integrable BRDF, the reciprocity defect of a
    reciprocal basis) and agree whatever their digits. ``atol`` is an absolute tolerance on top (for
    values that are round-off-limited in absolute terms, like spectral coefficients far below the
    largest one: they come from sums of terms of the largest one's size).
    """
    new, committed = new.strip(), committed.strip()
    if new == committed:
        return True
    try:
        x, y = float(new), float(committed)
    except ValueError:
        return False
    if math.isnan(x) or math.isnan(y):
        return False
    if abs(x) < 1e-12 and abs(y) < 1e-12:
        return True
    unit = min(_last_digit(new), _last_digit(committed))
    return abs(x - y) <= 1.0001 * unit + 1e-9 * abs(y) + atol


def _number(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        return float("nan")


def read_csv(path: Path) -> Tuple[List[str], List[List[str]]]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def read_md_tables(path: Path) -> List[Tuple[List[str], List[List[str]]]]:
    """Every Markdown table of a file as ``(header, rows)`` (cells stripped)."""
    tables, cur = [], None
    for line in Path(path).read_text().splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if cur is None:
                cur = (cells, [])
            elif not all(set(c) <= set("-: ") for c in cells):
                cur[1].append(cells)
        elif cur is not None:
            tables.append(cur)
            cur = None
    if cur is not None:
        tables.append(cur)
    return tables


def compare_rows(new: Sequence[Sequence[str]], committed: Sequence[Sequence[str]], nkey: int,
                 skip_columns: Sequence[int] = (), row_atol: float = 0.0) -> Dict[tuple, List[str]]:
    """Every row of ``new`` must be a row of ``committed`` (matched on its first ``nkey`` cells), value for value.

    ``row_atol``: an absolute tolerance of ``row_atol`` times the row's largest magnitude (see
    :func:`same_value`).

    Returns the committed rows that were matched, by key. Raises an ``AssertionError`` naming every
    cell that differs.
    """
    by_key = {tuple(r[:nkey]): list(r) for r in committed}
    bad, matched = [], {}
    for r in new:
        key = tuple(r[:nkey])
        assert key in by_key, f"row {key} is not in the committed table"
        ref = by_key[key]
        assert len(r) == len(ref), (key, r, ref)
        atol = row_atol * max([abs(v) for v in map(_number, ref[nkey:]) if math.isfinite(v)], default=0.0)
        for j, (a, b) in enumerate(zip(r, ref)):
            if j >= nkey and j not in skip_columns and not same_value(a, b, atol):
                bad.append(f"{key} column {j}: {a} (now) vs {b} (committed)")
        matched[key] = ref
    assert not bad, "values differ from the committed table:\n  " + "\n  ".join(bad[:20])
    return matched


def tiny_diligent(folder: Path, size: int = 32, lights: int = 20, seed: int = 0) -> Path:
    """A small DiLiGenT-layout object folder of the library's demo scene (bumpy sphere, GGX and Blinn-Phong
    regions, cast shadows, noise), written by ``torch_hsh.io.save_diligent``; built in, no shared data."""
    from torch_hsh.io import save_diligent
    from torch_hsh.render.scenes import demo_scene

    s = demo_scene(size, n_lights=lights, seed=seed)
    inten = s["intensities"]
    images = s["images"] / inten[:, None, None, :]  # save_diligent takes unit-intensity images
    return save_diligent(folder, images, s["lights"], intensities=inten, mask=s["mask"], normals_gt=s["normals_gt"])
