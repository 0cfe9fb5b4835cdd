"""Old public import paths keep working, with a DeprecationWarning, and forward to the new modules."""
import subprocess
import sys

import pytest

# (old path, new path, names that must be the same objects through both)
MOVED = [
    ("torch_hsh.basis", "torch_hsh.kernel", ["hsh", "helmholtz_isotropic", "set_backend", "_const"]),
    ("torch_hsh.ps.hsh", "torch_hsh.ps.pipeline", ["solve_hsh", "confidence", "MIN_VALID_OBSERVATIONS", "_result"]),
]


@pytest.mark.parametrize("old,new,names", MOVED, ids=[m[0] for m in MOVED])
def test_old_module_path_warns_and_forwards(old, new, names):
    # a fresh interpreter: the warning fires on the first import only
    code = (
        "import importlib, warnings\n"
        f"new = importlib.import_module({new!r})\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        f"    old = importlib.import_module({old!r})\n"
        "assert any(issubclass(x.category, DeprecationWarning) and " f"{new!r} in str(x.message) for x in w), "
        "[str(x.message) for x in w]\n"
        f"for n in {names!r}:\n"
        "    assert getattr(old, n) is getattr(new, n), n\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_package_attribute_of_an_old_module_warns():
    code = (
        "import warnings, torch_hsh\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    m = torch_hsh.basis\n"
        "assert m.hsh is torch_hsh.kernel.hsh\n"
        "assert any(issubclass(x.category, DeprecationWarning) for x in w)\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
