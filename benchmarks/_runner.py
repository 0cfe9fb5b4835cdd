"""Run the benchmark worker (``_ps_worker.py``) in its own process, with ``torch_hsh`` imported from a given tree.

Used by ``bench_ps.py``, ``bench_diligent.py`` and ``bench_suite.py``. The tree is the working tree by
default, or any folder that holds a ``torch_hsh`` package (``--baseline-tree`` of ``bench_ps.py`` and
``bench_diligent.py``: an older version, timed the same way).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).resolve().parent / "_ps_worker.py"


def run_worker(args, tree: Path = ROOT, timeout: float = 3600) -> dict:
    """Run ``_ps_worker.py`` with ``torch_hsh`` imported from ``tree``; returns its JSON record."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OMP_NUM_THREADS", "2")
    p = subprocess.run([sys.executable, str(WORKER), *map(str, args)], env=env, capture_output=True, text=True,
                       timeout=timeout, cwd=str(ROOT))
    if p.returncode != 0:
        raise RuntimeError(f"benchmark worker failed ({tree}):\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def baseline_tree_arg(value: str) -> Path:
    """argparse type of ``--baseline-tree DIR``: a folder holding a ``torch_hsh`` package."""
    import argparse

    p = Path(value).resolve()
    if not (p / "torch_hsh" / "__init__.py").is_file():
        raise argparse.ArgumentTypeError(f"{value!r}: no torch_hsh/__init__.py in this folder")
    return p
