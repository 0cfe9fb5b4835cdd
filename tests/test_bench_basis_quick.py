"""benchmarks/bench_basis.py runs in its quick mode and prints every measurement it promises."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_bench_basis_quick_prints_every_row():
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_basis.py"), "--quick", "--threads", "1"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    for backend in ("auto", "torch"):
        assert f"== [{backend}] hsh" in text and f"== [{backend}] Helmholtz bases" in text
    # hsh rows: order, pass, three times (sphericart / e3nn may be n/a only where not installed)
    hsh_rows = re.findall(r"^\s+(\d+)\s+(fwd|fwd\+bwd)\s+([\d.]+)\s+([\d.]+|n/a)\s+([\d.]+|n/a)", text, re.M)
    assert len(hsh_rows) == 2 * 2 * 2  # backends x orders (2, 4) x passes
    for _, _, ours, sph, e3 in hsh_rows:
        assert float(ours) > 0
        if "sphericart-torch not available" not in text:
            assert sph != "n/a" and float(sph) > 0
        if "e3nn not available" not in text:
            assert e3 != "n/a" and float(e3) > 0
    base_rows = re.findall(r"^\s*(isotropic|anisotropic)\s+(\d+)\s+(\d+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)"
                           r"\s+([\d.]+)", text, re.M)
    assert len(base_rows) == 2 * 4
    for name, P, K, mul, f, fb, r1, r2 in base_rows:
        P, K = int(P), int(K)
        assert K == ((P + 1) * (P + 2) * (P + 3) // 6 if name == "isotropic" else (P + 1) ** 2 * ((P + 1) ** 2 + 1) // 2)
        assert min(float(mul), float(f), float(fb)) > 0
        lo = (float(f) - 5e-4) / (float(mul) + 5e-4)  # the times are printed to 1e-3 ms
        hi = (float(f) + 5e-4) / max(float(mul) - 5e-4, 1e-9)
        assert 0.99 * lo - 0.01 <= float(r1) <= 1.01 * hi + 0.01
    assert len(re.findall(r"ms per step", text)) == 4
    assert "speed-up of the default (auto) over the pure-torch kernels" in text


@pytest.mark.slow
def test_bench_basis_sections_select_rows():
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_basis.py"), "--quick", "--threads", "1",
                          "--backend", "auto", "--sections", "hsh", "bases", "--orders", "2", "--iso-orders", "2",
                          "--aniso-orders"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    assert "== [auto] hsh" in text and "== [torch]" not in text and "ms per step" not in text
    assert len(re.findall(r"^\s+2\s+(fwd|fwd\+bwd)\s+[\d.]+", text, re.M)) == 2
    assert len(re.findall(r"^\s*isotropic\s+2\s", text, re.M)) == 1 and "anisotropic" not in text.split("Helmholtz")[1]
