"""The run times quoted next to the paper scripts in docs/reproducing_the_paper.md agree with the times the
scripts themselves record in the tables they write (docs/tables/*.md)."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _quoted_seconds(script):
    """The ``# ~N s`` / ``# ~N min`` comment after ``python examples/paper/<script>``."""
    text = (ROOT / "docs" / "reproducing_the_paper.md").read_text(encoding="utf-8")
    m = re.search(rf"python examples/paper/{re.escape(script)}\S*[^\n#]*#\s*~(\d+(?:\.\d+)?)\s*(s|min)\b", text)
    assert m, f"no run time quoted for {script}"
    return float(m.group(1)) * (60.0 if m.group(2) == "min" else 1.0)


@pytest.mark.parametrize("script,table,pattern", [
    ("compactness.py", "compactness_summary.md", r"Runtime: (\d+) s"),
    ("reciprocity_filtering.py", "reciprocity_filtering.md", r"\(\d{4}-\d\d-\d\d, (\d+) s\)"),
])  # fmt: skip
def test_quoted_run_time_matches_the_recorded_one(script, table, pattern):
    recorded = float(re.search(pattern, (ROOT / "docs" / "tables" / table).read_text(encoding="utf-8")).group(1))
    quoted = _quoted_seconds(script)
    assert recorded / 1.5 <= quoted <= recorded * 1.5, (script, quoted, recorded)
