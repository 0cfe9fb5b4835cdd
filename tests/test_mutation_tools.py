"""The pure parts of the mutation tools (tools/mutate.py, tools/mutation_sample.py): the Wilson interval,
the seeded sample, the parser of mutmut's results and the tally. No mutmut run."""
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import mutate  # noqa: E402
import mutation_sample as ms  # noqa: E402

Z = 1.959963984540054


def test_wilson_closed_forms_at_the_ends():
    # all successes: [n / (n + z^2), 1]; no success: [0, z^2 / (n + z^2)]
    lo, hi = ms.wilson(40, 40)
    assert lo == pytest.approx(40 / (40 + Z * Z), rel=1e-12) and hi == 1.0
    lo, hi = ms.wilson(0, 40)
    assert lo == 0.0 and hi == pytest.approx(Z * Z / (40 + Z * Z), rel=1e-12)
    assert ms.wilson(60, 60)[0] == pytest.approx(0.9398, abs=1e-4)


def test_wilson_known_value_symmetry_and_coverage():
    lo, hi = ms.wilson(57, 60)  # scipy.stats.binomtest(57, 60).proportion_ci(method="wilson")
    assert (lo, hi) == (pytest.approx(0.862995, abs=1e-6), pytest.approx(0.982850, abs=1e-6))
    for k, n in [(3, 10), (17, 30), (250, 300)]:
        lo, hi = ms.wilson(k, n)
        lo2, hi2 = ms.wilson(n - k, n)
        assert (lo, hi) == (pytest.approx(1 - hi2, abs=1e-12), pytest.approx(1 - lo2, abs=1e-12))
        assert lo < k / n < hi
    assert ms.wilson(9, 10)[1] - ms.wilson(9, 10)[0] > ms.wilson(90, 100)[1] - ms.wilson(90, 100)[0]
    assert all(math.isnan(x) for x in ms.wilson(0, 0))
    with pytest.raises(ValueError, match="k <= n"):
        ms.wilson(5, 4)


def test_sample_is_seeded_sorted_and_independent_of_input_order():
    names = [f"m__mutmut_{i}" for i in range(500)]
    a = ms.sample_names(names, 60, seed=1)
    assert a == ms.sample_names(reversed(names), 60, seed=1) == ms.sample_names(names + names[:10], 60, seed=1)
    assert len(a) == len(set(a)) == 60 and a == sorted(a) and set(a) <= set(names)
    assert a != ms.sample_names(names, 60, seed=2)
    assert ms.sample_names(names[:5], 60, seed=1) == sorted(names[:5])


MUTMUT_RESULTS = """\
⠋ Generating mutants
    done in 757ms (0 files mutated, 72 ignored, 1 unmodified)
    torch_hsh.ps.optim.x_small_solve__mutmut_1: killed
    torch_hsh.ps.optim.x_small_solve__mutmut_62: survived
    torch_hsh.ps.optim.xǁPixelProblemǁjacobian__mutmut_131: timeout
    torch_hsh.ps.optim.x_lm_accept__mutmut_9: no tests
    torch_hsh.ps.optim.x_lm_accept__mutmut_10: suspicious
    torch_hsh.ps.optim.x_lm_accept__mutmut_11: segfault
    torch_hsh.ps.optim.x_lm_accept__mutmut_12: not checked
"""


def test_results_parser_and_tally():
    got = mutate.parse_results(MUTMUT_RESULTS)
    assert len(got) == 7 and got["torch_hsh.ps.optim.x_small_solve__mutmut_62"] == "survived"
    assert got["torch_hsh.ps.optim.xǁPixelProblemǁjacobian__mutmut_131"] == "timeout"
    assert got["torch_hsh.ps.optim.x_lm_accept__mutmut_9"] == "no tests"
    t = ms.tally(got)
    assert (t["sampled"], t["reached"], t["killed"], t["timeout"]) == (7, 4, 1, 1)
    assert (t["survived"], t["suspicious"], t["no_tests"], t["other"]) == (1, 1, 1, 2)
    assert t["score"] == 0.5 and t["wilson95"] == list(ms.wilson(2, 4))
    assert t["survivors"] == ["torch_hsh.ps.optim.x_lm_accept__mutmut_10", "torch_hsh.ps.optim.x_small_solve__mutmut_62"]
