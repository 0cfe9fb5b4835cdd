"""Mutation testing of the core modules with mutmut (``make mutate``; not part of CI).

Each module is mutated in its own scratch copy of the project (``build/mutmut/<module>/``) whose
``[tool.mutmut]`` section selects only that module's test file, so that a mutant of ``kernel.py`` is
judged by ``tests/test_kernel.py`` alone. mutmut's result cache lives in that copy: a second run only
re-tests mutants whose function or tests changed.

    python tools/mutate.py                 # all modules
    python tools/mutate.py kernel           # one module
    python tools/mutate.py kernel --max-children 2

The summary (killed / survived / timed out / ... and the score) is printed per module and written to
``build/mutmut/<module>/summary.txt``; ``mutmut results`` / ``mutmut show NAME`` run inside that folder
list and show the surviving mutants.

mutmut keeps a mutant's verdict until the mutated *function* changes: new or changed tests do not
re-judge the survivors. ``--retest-survivors`` runs every mutant that was not killed again (after adding
tests), ``--fresh`` drops the cache and starts over.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Dict, List

ROOT = Path(__file__).resolve().parents[1]
# module -> the tests that judge its mutants (slow end-to-end tests are left out: they cover the same
# functions and would multiply the run time)
MODULES = {
    "kernel": ("torch_hsh/kernel.py", ["tests/test_kernel.py"]),
    # the fitting package (torch_hsh/fitting.py before the split) and its product rules and their
    # refinement (torch_hsh/_integrate.py before the split)
    "fitting": (("torch_hsh/fitting/__init__.py", "torch_hsh/fitting/arguments.py", "torch_hsh/fitting/projection.py",
                 "torch_hsh/fitting/least_squares.py", "torch_hsh/fitting/coefficients.py",
                 "torch_hsh/fitting/normal_exitance.py", "torch_hsh/fitting/albedo.py"),
                ["tests/test_fitting.py", "-m", "not slow"]),
    "_integrate": (("torch_hsh/fitting/rules.py", "torch_hsh/fitting/convergence.py"),
                   ["tests/test_fitting.py", "-m", "not slow"]),
    # photometric stereo: the optimiser and the observation model, judged by the PS unit tests
    # (test_ps.py without its slow end-to-end runs; test_ps_shadows.py also drives the observation model)
    "ps_optim": ("torch_hsh/ps/optim.py", ["tests/test_ps.py", "-m", "not slow"]),
    # (the test of the warning's caller line is left out: mutmut's trampoline is one more frame)
    "ps_observations": ("torch_hsh/ps/observations.py",
                        ["tests/test_ps.py", "tests/test_ps_shadows.py", "-m", "not slow",
                         "--deselect", "tests/test_ps.py::test_horizon_warning_is_said_once_at_the_callers_line"]),
    # the readers and writers, judged by their own tests
    "io": (("torch_hsh/io/__init__.py", "torch_hsh/io/diligent.py", "torch_hsh/io/exr.py", "torch_hsh/io/merl.py"),
           ["tests/test_io_diligent.py", "tests/test_io_exr.py", "tests/test_io_rti.py", "tests/test_merl.py",
            "tests/test_fit_merl.py", "-m", "not slow"]),
}


def _toml_list(xs):
    return "[" + ", ".join('"' + x.replace('"', '\\"') + '"' for x in xs) + "]"


def prepare(name: str) -> Path:
    path, tests = MODULES[name]
    paths = [path] if isinstance(path, str) else list(path)
    work = ROOT / "build" / "mutmut" / name
    work.mkdir(parents=True, exist_ok=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for d in ("torch_hsh", "tests"):  # a fresh copy of the sources and tests; mutmut's cache (mutants/) is kept
        if (work / d).exists():
            shutil.rmtree(work / d)
        shutil.copytree(ROOT / d, work / d, ignore=ignore)
    text = (ROOT / "pyproject.toml").read_text()
    text += (
        "\n[tool.mutmut]\n"
        'source_paths = ["torch_hsh"]\n'
        f"only_mutate = {_toml_list(paths)}\n"
        f"pytest_add_cli_args_test_selection = {_toml_list(tests)}\n"
        'pytest_add_cli_args = ["-p", "no:cacheprovider", "-q"]\n'
        'process_isolation = "forkserver"\n'
    )
    (work / "pyproject.toml").write_text(text)
    return work


def parse_results(text: str) -> Dict[str, str]:
    """``mutmut results --all true`` output (``    name: status`` lines, indented) as {name: status};
    any other line (a progress message) is skipped."""
    out = {}
    for line in text.splitlines():
        if line.startswith(" ") and ":" in line:
            name, status = line.rsplit(":", 1)
            out[name.strip()] = status.strip()
    return out


def results(work: Path) -> Dict[str, str]:
    """The verdict of every mutant in the scratch copy ``work`` ({name: status}, "not checked" if never run)."""
    r = subprocess.run([sys.executable, "-m", "mutmut", "results", "--all", "true"], cwd=work,
                       capture_output=True, text=True)
    return parse_results(r.stdout)


def _not_killed(work: Path) -> List[str]:
    """Mutants that were run and not killed (a mutant never run, "not checked", is no survivor: naming it
    would turn a retest into a full run)."""
    return [m for m, status in results(work).items() if status not in ("killed", "not checked")]


def summarize(work: Path) -> str:
    counts = Counter(results(work).values())
    total = sum(counts.values())
    killed = counts.get("killed", 0)
    score = 100.0 * killed / total if total else float("nan")
    return f"{dict(counts)}  score {killed}/{total} = {score:.1f} % killed"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("modules", nargs="*", help=f"which modules to mutate: {', '.join(MODULES)} (default: all)")
    ap.add_argument("--max-children", type=int, default=os.cpu_count() or 1, help="parallel mutant workers")
    ap.add_argument("--retest-survivors", action="store_true",
                    help="run the mutants that were not killed again (new tests do not invalidate mutmut's cache)")
    ap.add_argument("--fresh", action="store_true", help="drop mutmut's cache (mutants/) and mutate from scratch")
    args = ap.parse_args(argv)
    bad = [m for m in args.modules if m not in MODULES]
    if bad:
        ap.error(f"unknown module(s) {', '.join(bad)}; choose from {', '.join(MODULES)}")
    for name in args.modules or list(MODULES):
        work = prepare(name)
        if args.fresh and (work / "mutants").exists():
            shutil.rmtree(work / "mutants")
        names = _not_killed(work) if args.retest_survivors and (work / "mutants").exists() else []
        if args.retest_survivors and not names:  # no names would make mutmut run every mutant
            print(f"{name}: no survivors to retest", flush=True)
            continue
        t0 = time.perf_counter()
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        rc = subprocess.run([sys.executable, "-m", "mutmut", "run", "--max-children", str(args.max_children), *names],
                            cwd=work, env=env).returncode
        line = f"{name}: {summarize(work)}  ({time.perf_counter() - t0:.0f} s, {args.max_children} workers, rc {rc})"
        print(line, flush=True)
        (work / "summary.txt").write_text(line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
