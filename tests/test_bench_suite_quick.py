"""``benchmarks/bench_suite.py --quick`` (the issue-21 suite runner) in CI, in the style of test_benchmarks_quick.py.

Runs in its own process on two quick scenes of the suite: the tiny Mitsuba dome (rendered into a
temporary cache; skipped without mitsuba) and the synthetic bumpy height field with cast shadows.
Checks the per-solve lines (printed as they end), the per-scene summary, the whole-surface columns
(safeguarded and forced errors, the safeguard's decision), the ``n/a`` column of the stage that does
not exist (interreflection), and that the JSON record matches the printed numbers.
"""
from __future__ import annotations

import importlib.util
import json
import re

import pytest

from _scripts import run_script

NUM = r"([-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|nan|inf))"


@pytest.mark.slow
def test_bench_suite_quick(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HSH_CACHE", str(tmp_path / "cache"))  # nothing rendered into ~/.cache
    has_mitsuba = importlib.util.find_spec("mitsuba") is not None
    out = tmp_path / "suite.json"
    r = run_script("benchmarks/bench_suite.py", "--quick", "--only", "dome_plastic", "bumpy_shadows", "--json", out)
    rec = json.loads(out.read_text())
    assert rec["seeds"] == [0] and rec["threads"] == 1 and rec["max_pixels"] == 400
    scenes = rec["scenes"]
    assert set(scenes) == ({"dome_plastic", "bumpy_shadows"} if has_mitsuba else {"bumpy_shadows"})
    if not has_mitsuba:
        assert re.search(r"dome_plastic: skipped \(mitsuba", r.stdout), r.stdout
    for name, s in scenes.items():
        assert s["pixels"] <= 400 and s["lights"] in (8, 20)
        st = s["stages"]
        for label in ("per-pixel", "per-pixel + cast_shadows=1", "+interreflection"):
            (run,) = st[label]["runs"]
            assert 0 < run["mean"] < 45 and run["time_s"] > 0, (name, label, run)
            m = re.search(rf"^  {name} {re.escape(label)} seed 0: mean {NUM} median {NUM} time {NUM} s", r.stdout, re.M)
            assert m and float(m.group(1)) == pytest.approx(run["mean"], abs=0.006), r.stdout
        (run,) = st["+interreflection"]["runs"]
        assert 0 <= run["bounce_fraction"] < 0.5 and run["bounce_time_s"] >= 0
        m = re.search(rf"^  {name} \+interreflection seed 0: .* \(bounce {NUM} % of the light, {NUM} s, "
                      rf"(kept|rejected): confidence {NUM} -> {NUM}\)$", r.stdout, re.M)
        assert m, r.stdout
        # the loop's safeguard keeps the corrected solve only when the mean confidence did not fall
        assert run["accepted"] == (run["confidence_after"] >= run["confidence_before"])
        assert (m.group(3) == "kept") == bool(run["accepted"])
        if not run["accepted"]:
            assert run["mean"] == pytest.approx(st["per-pixel"]["runs"][0]["mean"], abs=1e-9)  # the first solve
        start = st["per-pixel"]["runs"][0]["mean"]
        for label in ("+surface", "+surface +shadows"):
            (run,) = st[label]["runs"]
            assert run["start_mean"] == pytest.approx(start, abs=1e-9)  # the same solve, then the stage
            assert 0 < run["forced_mean"] < 90 and run["time_s"] > 0
            # the safeguard returns the refined surface only when the held-out error fell
            assert run["kept"] == (run["heldout_after"] < run["heldout_before"])
            assert run["mean"] == pytest.approx(run["forced_mean"] if run["kept"] else start, abs=1e-9)
            m = re.search(rf"^  {name} {re.escape(label)} seed 0: mean {NUM} median {NUM} time {NUM} s "
                          rf"\(cpu {NUM} s\) \(start {NUM}, forced {NUM}, (kept|rejected); held-out", r.stdout, re.M)
            assert m and float(m.group(6)) == pytest.approx(run["forced_mean"], abs=0.006), r.stdout
            assert (m.group(7) == "kept") == run["kept"]
        assert re.search(rf"^{name}: LS {NUM} \| per-pixel {NUM} \(spread 0.00, .*\| \+surface {NUM} \(spread 0.00, "
                         rf".*, forced {NUM}, kept [01]/1\) \| .* \| \+interreflection {NUM} \(spread 0.00, {NUM} s\) \| "
                         rf"\+interreflection \+surface \+shadows {NUM} \(spread 0.00, .*, kept [01]/1\)$", r.stdout,
                         re.M), r.stdout
        assert re.search(rf"^\| {name} \| \w+ \| [\d,]+ x \d+ \| {NUM} \| .* \| [01]/1 \| {NUM} \(0.00\) \| {NUM} s \| "
                         rf"{NUM} \(0.00\) \| {NUM} s \| {NUM} \| [01]/1 \|$",
                         r.stdout, re.M), r.stdout
    if has_mitsuba:
        assert scenes["dome_plastic"]["stages"]["per-pixel"]["mean"] < 10  # matte dome: a small error
    # printed as it goes: the first solve's line came well before the last scene was done
    assert r.last - r.first(r" per-pixel seed 0: mean") > 1.0, r.lines
