"""The fuzzer of the file readers (tools/fuzz.py): a short run of every target, and its classifier.

``make fuzz`` runs the long campaign; this is its short version (a few inputs a target, in one worker).
"""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import fuzz  # noqa: E402


def test_every_reader_ends_in_a_result_or_its_own_error():
    pool = fuzz._Pool1(list(fuzz.TARGETS), timeout=20.0, mem_mb=1024)
    try:
        rows = [fuzz.run_target(t, 2 if t == "normal_gt" else 6, seed=7, pool=pool) for t in fuzz.TARGETS]
    finally:
        pool.close()
    bad = {r["target"]: r["failures"] for r in rows if r["foreign"] or r["hang"] or r["crash"]}
    assert not bad, bad
    assert sum(r["inputs"] for r in rows) == sum(r["ok"] + r["lib"] for r in rows) == 14 * 6 + 2


def test_mutations_are_reproducible_and_change_the_seed():
    import random

    data = b"3\na.png 0 0 1\nb.png 0 0.6 0.8\nc.png 0.6 0 0.8\n"
    one = [fuzz.mutate(data, True, random.Random(5)) for _ in range(3)]
    assert one == [fuzz.mutate(data, True, random.Random(5)) for _ in range(3)]
    rng = random.Random(1)
    assert sum(fuzz.mutate(data, True, rng) != data for _ in range(50)) >= 45


@pytest.mark.parametrize("target, kind", [
    ("planted_lib", "lib"),  # read_merl's ValueError naming the file
    ("planted_foreign", "foreign"),  # numpy's ValueError, raised outside torch_hsh
    ("planted_hang", "hang"),  # a Python loop: the worker's alarm
    ("planted_hang_unalarmed", "hang"),  # the alarm blocked: the parent's deadline kills the worker
    ("planted_abort", "crash"),
    ("planted_segfault", "crash"),
])
def test_the_classifier(planted_pool, target, kind):
    r = fuzz.run_target(target, 1, pool=planted_pool)
    assert r[kind] == 1, r


@pytest.fixture(scope="module")
def planted_pool():
    """One worker for the planted targets (restarted after each hang or crash): a 1 s alarm, 2 s more to answer."""
    pool = fuzz._Pool1(list(fuzz.PLANTED), timeout=1.0, mem_mb=1024, grace=2.0)
    yield pool
    pool.close()
