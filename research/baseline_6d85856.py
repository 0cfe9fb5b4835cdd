"""The baseline of the speed issue: ``torch_hsh`` of commit 6d85856, extracted from git, with one crash fixed.

Commit 6d85856 with only its float32 ``linspace`` crash fixed (``robust_sigma`` indexed past the end
once the background held more than 2**24 values): :func:`baseline_tree` extracts the package with
``git archive`` into the system's temporary folder and applies exactly that one-line patch. It needs a
git checkout that holds the commit.

Running the script prints the folder, for the benchmarks' ``--baseline-tree``::

    python research/baseline_6d85856.py
    python benchmarks/bench_ps.py --synthetic-size 16000 --lights 96 --repeat 3 \\
        --baseline-tree "$(python research/baseline_6d85856.py)"
    python benchmarks/bench_diligent.py ../shared/data/diligent_cat --seeds 0 1 2 \\
        --baseline-tree "$(python research/baseline_6d85856.py)" --baseline-seeds 0
"""
from __future__ import annotations

import io
import subprocess
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
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


if __name__ == "__main__":
    print(baseline_tree())
