"""benchmarks/bench_training.py runs in its quick mode and prints what it promises: one row per mode with its
steps/s, first and final loss and ratio against eager; the losses fall; the ratios agree with the printed
rates; the compiled and bfloat16 runs end near the eager loss; the basis-only timing rows."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_bench_training_quick_prints_its_claims():
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_training.py"), "--quick", "--threads", "1"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    text = out.stdout
    assert "torch.compile backend aot_eager" in text and "(2048 basis rows per step)" in text
    rows = {m: tuple(float(x) for x in vals) for m, *vals in re.findall(
        r"^\s*(eager|compiled|bf16)\s+([\d.]+)\s+([\d.]+)\s+([\d.e+-]+)\s+([\d.e+-]+)\s+([\d.]+)$", text, re.M)}
    assert set(rows) == {"eager", "compiled", "bf16"}, text
    eager_rate = rows["eager"][0]
    for m, (rate, warm, first, final, ratio) in rows.items():
        assert rate > 0 and warm >= 0
        assert final < 0.5 * first, (m, first, final)  # the network learns the images
        assert abs(ratio - rate / eager_rate) <= 0.01 + 0.01 * ratio  # the ratio is that of the printed rates
        assert f"loss {m}: " in text
    assert "DOES NOT FALL" not in text
    # the same initial weights and data: compiled follows eager closely, bfloat16 ends at a similar loss
    assert abs(rows["compiled"][3] / rows["eager"][3] - 1) < 0.05
    assert 0.5 < rows["bf16"][3] / rows["eager"][3] < 2.0
    basis = re.findall(r"^\s*(\d+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+(\d+)%$", text, re.M)
    assert [int(b[0]) for b in basis] == [3]
    for _, te, tc, ratio, _ in basis:
        assert abs(float(ratio) - float(te) / float(tc)) <= 0.01 + 0.02 * float(ratio)
