"""Every benchmark runs in CI in its quick mode, prints parseable lines with sane values, as it goes (issue 23, part 3).

Each script runs in its own process (``tests/_scripts.py``) on built-in scenes only: the synthetic
problems of the scripts themselves, and a small DiLiGenT-layout folder of the library's demo scene
written by ``torch_hsh.io.save_diligent`` into a temporary folder (no shared data). ``bench_cuda``
runs with ``--device cpu``. ``bench_basis`` and ``bench_envmap`` are tested elsewhere.

"As it goes": stdout is a pipe, so a script that does not flush shows its lines only when it exits.
Where a script makes several measurements, the test checks that the first one could be read well
before its last line (not before the exit: the interpreter's teardown can take seconds on a loaded
machine, which once let a script without flushes pass).
"""
from __future__ import annotations

import json
import math
import re

import pytest

from _scripts import run_script, tiny_diligent

NUM = r"([-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|nan|inf))"


@pytest.fixture(scope="module")
def sphere_folder(tmp_path_factory):
    """A 32 x 32, 20-light DiLiGenT-layout folder of the demo scene (648 mask pixels)."""
    return tiny_diligent(tmp_path_factory.mktemp("diligent") / "demo_sphere")


def _floats(pattern: str, text: str):
    out = [tuple(float(x) for x in m.groups()) for m in re.finditer(pattern, text, re.M)]
    assert out, f"no line matches {pattern!r}:\n{text[-3000:]}"
    return out


@pytest.mark.slow
def test_bench_ps_quick(sphere_folder, tmp_path):
    """A line per solve as it ends (the first one well before the script ends), then a summary per problem;
    the memory run's stack is cached where ``--stack-dir`` says."""
    stack_dir = tmp_path / "stacks"
    stack_dir.mkdir()
    r = run_script("benchmarks/bench_ps.py", "--quick", "--data", sphere_folder, "--synthetic-size", 200,
                   "--lights", 20, "--stack", 32, "--stack-dir", stack_dir)
    runs = _floats(rf"run 1/1 working tree, seed 0: wall {NUM} s, cpu {NUM} s, mean error {NUM} deg, "
                   rf"peak RSS {NUM} MB", r.stdout)
    assert len(runs) == 3  # synthetic, the folder, the stack
    for wall, cpu, err, rss in runs:
        assert wall > 0 and cpu > 0 and 0 < err < 30 and rss > 50, runs
    assert runs[1][2] < 5.0  # the demo scene: the HSH solver's error is small
    summary = _floats(rf"working tree\s+wall\s+{NUM} s \(runs [^)]*\)\s+cpu\s+{NUM} s\s+mean error {NUM} deg", r.stdout)
    assert [s[2] for s in summary] == pytest.approx([x[2] for x in runs], abs=0.006)
    assert len(re.findall(r"stage shares: observations", r.stdout)) == 3
    (mem,) = _floats(rf"stack {NUM} MB \(float32\); RSS after import {NUM} MB, after load {NUM} MB, peak {NUM} MB: "
                     rf"peak - import = {NUM} MB", r.stdout)
    assert mem[3] - mem[1] == pytest.approx(mem[4], abs=1.0) and mem[1] < mem[3]
    assert (stack_dir / "torch_hsh_stack_32_20" / "images.npy").is_file()  # cached where asked, not in /tmp
    # printed as it goes: the first solve's line came while the other two problems were still to run
    assert r.last - r.first(r"run 1/1 working tree") > 1.0, r.lines


def test_bench_ps_baseline_tree_is_checked():
    """``--baseline-tree DIR`` names a folder holding a ``torch_hsh`` package: any other folder is refused at once."""
    import subprocess
    import sys

    from _scripts import ROOT

    p = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_ps.py"), "--quick", "--baseline-tree",
                        str(ROOT / "docs")], capture_output=True, text=True, timeout=120, cwd=str(ROOT))
    assert p.returncode == 2 and "--baseline-tree" in p.stderr and "no torch_hsh/__init__.py" in p.stderr, p.stderr


@pytest.mark.slow
def test_bench_ps_baseline_tree_quick():
    """``--baseline-tree`` with the working tree itself as the other tree: both are timed, alternating, and the
    speed-up line compares the two (the same solver: the same error)."""
    from _scripts import ROOT

    r = run_script("benchmarks/bench_ps.py", "--quick", "--synthetic-size", 100, "--lights", 12,
                   "--baseline-tree", ROOT)
    assert r.first(r"run 1/1 working tree, seed 0") < r.first(r"run 1/1 baseline, seed 0")
    (line,) = _floats(rf"speed-up over the baseline: wall {NUM}x, cpu {NUM}x; error {NUM} vs {NUM} deg", r.stdout)
    assert line[0] > 0 and line[1] > 0 and line[2] == pytest.approx(line[3], abs=1e-9)


@pytest.mark.slow
def test_bench_diligent_quick(sphere_folder, tmp_path):
    """Per-solve lines as they end, the object table, and a JSON record whose errors match the printed ones;
    on the demo scene the HSH solver beats both Lambertian methods."""
    out = tmp_path / "records.json"
    r = run_script("benchmarks/bench_diligent.py", sphere_folder, "--quick", "--json", out)
    rec = json.loads(out.read_text())["demo_sphere"]
    lam = rec["lambertian"]
    assert lam["pixels"] == 400 and lam["lights"] == 20  # --quick: 400 random mask pixels
    ls, tr = lam["methods"]["ls"]["mean"], lam["methods"]["trimmed"]["mean"]
    (hsh,) = [x["methods"]["hsh"]["mean"] for x in rec["HSH"]]
    assert 0 < hsh < tr < ls < 30, (hsh, tr, ls)
    (line,) = _floats(rf"demo_sphere HSH seed 0: mean {NUM} median {NUM} time {NUM} s", r.stdout)
    assert line[0] == pytest.approx(hsh, abs=0.006)
    (row,) = _floats(rf"^\s+Lambertian LS\s+{NUM}\s+{NUM}", r.stdout)
    assert row[0] == pytest.approx(ls, abs=0.006)
    assert r.first(r"demo_sphere Lambertian LS: mean") < r.first(r"demo_sphere HSH seed 0") < r.first(r"^demo_sphere: ")


def test_bench_surface_quick(sphere_folder):
    """Every solver reaches the tolerance, agrees with plain CG on the analytic surface, and the rows appear as
    they are measured; the folder's ground-truth normals are integrated too."""
    r = run_script("benchmarks/bench_surface.py", "--quick", "--data", sphere_folder)
    rows = {}
    for m in re.finditer(rf"^\s*(\d+)\^2 (plain CG \(ref\)|poisson/scipy|poisson/torch|bilateral/scipy \(\d+ rw\))"
                         rf"\s+(\d+)\s+(\d+)\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}", r.stdout, re.M):
        size, name = int(m.group(1)), m.group(2).split(" (")[0]
        rows[(size, name)] = tuple(float(x) for x in m.groups()[2:])
    assert set(rows) == {(48, "plain CG"), (48, "poisson/scipy"), (48, "poisson/torch"), (48, "bilateral/scipy"),
                         (96, "plain CG"), (96, "poisson/scipy"), (96, "poisson/torch")}, r.stdout
    for (size, name), (unknowns, iters, resid, rms, wall, cpu) in rows.items():
        assert unknowns > 0.6 * size * size and iters > 0 and resid <= 1.01e-6 and wall >= 0, (size, name)
        if name != "bilateral/scipy":  # the same Poisson system: the same surface
            assert rms == pytest.approx(rows[(size, "plain CG")][3], abs=2e-4) and rms < 0.1, (size, name, rms)
    data = _floats(r"demo_sphere: (?:poisson|bilateral): (\d+) px, (\d+) part\(s\), (\d+) CG iterations", r.stdout)
    assert [d[:2] for d in data] == [(648, 1), (648, 1)]


@pytest.mark.slow
def test_bench_cuda_on_cpu_quick(tmp_path):
    """``--device cpu --quick``: every part that runs on a CPU writes its record, the device solve agrees with
    the CPU reference (the same device here: exactly), and each measurement prints a line as it ends."""
    out = tmp_path / "cuda"
    r = run_script("benchmarks/bench_cuda.py", "--device", "cpu", "--quick", "--out", out)
    rec = json.loads((out / "bench_cuda.json").read_text())
    assert rec["device"] == "cpu" and "syncs" not in rec
    ds = rec["diligent_sized"]
    assert set(ds) == {"default", "chunk 8192", "one pass, 8 iter"}
    for name, t in ds.items():
        assert t["wall_s"] > 0 and 0 < t["mean_err_deg"] < 30 and set(t["stages_s"]) >= {"calibration", "refinement"}
    assert ds["default"]["mean_err_deg"] == pytest.approx(ds["chunk 8192"]["mean_err_deg"], abs=1e-6)
    ref = rec["cpu_reference"]
    assert ref["device_vs_cpu_max_deg"] < 1e-3 and ref["mean_err_deg"] == pytest.approx(ds["default"]["mean_err_deg"])
    large = rec["large"]
    assert large["pixels"] > 500 and 0 < large["default"]["mean_err_deg"] < 10
    lines = _floats(rf"^(?:300 px x 20 L, [^\n]*?|same, CPU 1 threads|32\^2 x 20 L, default)\s+{NUM} s, "
                    rf"mean error {NUM} deg", r.stdout)
    assert len(lines) == 5 and all(w > 0 and math.isfinite(e) for w, e in lines)
    assert r.last - r.first(r"300 px x 20 L, default\s+\S+ s,") > 1.0
