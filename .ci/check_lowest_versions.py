#!/usr/bin/env python3
"""Install the lowest versions that pyproject.toml allows and run the fast tests.

Every runtime dependency ``name>=X`` of ``[project] dependencies``, and of the
``examples`` extra (matplotlib, used by ``torch-hsh ps`` for its figures), is
pinned to ``name==X`` (as a pip constraint, so transitive dependencies resolve
normally; the test tools pytest and hypothesis are not our floors and resolve
normally too);
torch is pinned to the local CPU wheel (``$TORCH_SPEC``, default
``torch==2.13.0``) because a floor resolved from the index would pull the CUDA
build (``$TORCH_INDEX_URL``, when set, is the index it comes from, as in the
Makefile). Because torch is the same wheel in both environments, the test files of
the modules that call no third-party library but torch (:data:`TORCH_ONLY_TESTS`: the kernels, bases,
BRDF models, layers, frames, spectra and the checks of the repository's layout and docs) are left out;
numpy's one use in those modules, the Gauss-Legendre nodes of ``torch_hsh.quadrature``, is exercised by
the fitting tests, which run. Only wheels are accepted (``--only-binary=:all:``): a floor that has no
wheel for this Python fails the check instead of compiling from source.

Usage (from the repository root; ``make test-lowest`` does this)::

    python3 .ci/check_lowest_versions.py [--venv .venv-lowest] [-- pytest args]

Exit status: pip's or pytest's.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Test files whose modules import no third-party library but torch (numpy only through
#: ``torch_hsh.quadrature``, which ``tests/test_fitting.py`` covers): identical in both environments.
TORCH_ONLY_TESTS = (
    "test_architecture.py", "test_backends.py", "test_bases.py", "test_bench_basis_quick.py",
    "test_bench_training_quick.py", "test_brdf.py", "test_convergence_messages.py", "test_docs.py",
    "test_frames.py", "test_kernel.py", "test_native_hsh.py", "test_nn.py",
    "test_spectra.py", "test_training_code.py",
)


def _load_pyproject(path: Path) -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib  # type: ignore[no-redef]
    with open(path, "rb") as f:
        return tomllib.load(f)


def lowest_pins(deps, torch_spec: str) -> list:
    """``name>=X[,...]`` -> ``name==X``; torch -> ``torch_spec``; others verbatim."""
    pins = []
    for dep in deps:
        name = re.match(r"[A-Za-z0-9_.\-]+", dep).group(0)
        if name.lower() == "torch":
            pins.append(torch_spec)
            continue
        floor = re.search(r">=\s*([0-9][^,;\s]*)", dep)
        if floor is None:
            raise SystemExit(f"dependency {dep!r} has no '>=' floor; give it one")
        pins.append(f"{name}=={floor.group(1)}")
    return pins


def run(cmd, **kw):
    print("+", " ".join(map(str, cmd)), flush=True)
    return subprocess.run(cmd, **kw).returncode


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--venv", default=str(ROOT / ".venv-lowest"))
    ap.add_argument("--python", default=sys.executable, help="interpreter for the virtual environment")
    ap.add_argument("pytest_args", nargs="*", help="extra pytest arguments (after --)")
    args = ap.parse_args(argv)
    torch_spec = os.environ.get("TORCH_SPEC", "torch==2.13.0")
    meta = _load_pyproject(ROOT / "pyproject.toml")["project"]
    pins = lowest_pins(meta["dependencies"] + meta["optional-dependencies"]["examples"], torch_spec)
    venv = Path(args.venv).resolve()  # the tests run from tests/: a relative path would break
    py = venv / "bin" / "python"
    t0 = time.perf_counter()
    if not py.exists() and run([args.python, "-m", "venv", str(venv)]):
        return 1
    constraints = venv / "lowest-constraints.txt"
    constraints.write_text("".join(p + "\n" for p in pins))
    print("lowest pins:\n  " + "\n  ".join(pins), flush=True)
    pip = [str(py), "-m", "pip", "install", "-q"]
    index = os.environ.get("TORCH_INDEX_URL", "")
    if run(pip + (["--index-url", index] if index else []) + [torch_spec]):
        return 1
    # runtime floors exactly; the test tools resolve normally (they are not our floors)
    rc = run(pip + ["--only-binary=:all:", "-c", str(constraints), f"{ROOT}[examples]", "pytest", "hypothesis"])
    if rc:
        return rc
    run([str(py), "-m", "pip", "list", "--format=freeze"])
    t1 = time.perf_counter()
    # run the tests against the installed package, not the source tree
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"))
    ignore = [f"--ignore={ROOT / 'tests' / name}" for name in TORCH_ONLY_TESTS]
    rc = run([str(py), "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "not slow", *ignore,
              "--rootdir", str(ROOT), "-c", str(ROOT / "pyproject.toml"), *args.pytest_args],
             cwd=str(ROOT / "tests"), env=env)
    t2 = time.perf_counter()
    print(f"lowest-versions check: install {t1 - t0:.0f} s, tests {t2 - t1:.0f} s, exit {rc}", flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
