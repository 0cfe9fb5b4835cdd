"""The research scripts' tests: ``research/`` and ``tests/`` (for the script helpers of ``tests/_scripts.py``)
on the import path, and the same global torch seed for every test as in ``tests/conftest.py``."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
for _p in (ROOT / "tests", ROOT / "research"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))


@pytest.fixture(autouse=True)
def _seed_torch():
    torch.manual_seed(0)
    yield
