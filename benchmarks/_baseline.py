"""Extract a baseline version of ``torch_hsh`` from git and run the benchmark worker against it or the working tree.

The baseline of the speed issue is commit 6d85856 with only its float32
``linspace`` crash fixed (``robust_sigma`` indexed past the end once the
background held more than 2**24 values): :func:`baseline_tree` applies
exactly that one-line patch.
"""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).resolve().parent / "_ps_worker.py"
BASELINE_COMMIT = "6d85856"
_LINSPACE = "idx = torch.linspace(0, x.numel() - 1, 2_000_000, device=x.device).long()"
_LINSPACE_FIX = "idx = torch.arange(2_000_000, dtype=torch.int64, device=x.device) * (x.numel() - 1) // 1_999_999"


def baseline_tree(commit: str = BASELINE_COMMIT) -> Path:
    """``torch_hsh`` of ``commit`` (plus the linspace fix) in a temporary folder; returns the folder for PYTHONPATH."""
    out = Path(tempfile.gettempdir()) / f"torch_hsh_baseline_{commit}"
    if (out / "torch_hsh" / "__init__.py").is_file():
        return out
    data = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", commit, "torch_hsh"],
                          check=True, capture_output=True).stdout
    tmp = Path(tempfile.mkdtemp(prefix="torch_hsh_baseline_"))
    with tarfile.open(fileobj=io.BytesIO(data)) as tf:
        tf.extractall(tmp)
    common = tmp / "torch_hsh" / "ps" / "_common.py"
    src = common.read_text()
    if _LINSPACE in src:
        common.write_text(src.replace(_LINSPACE, _LINSPACE_FIX))
    tmp.rename(out) if not out.exists() else None
    return out


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
