"""The public API: every public module lists its names in ``__all__``, and ``import torch_hsh`` exposes the subpackages.

A module is public when no part of its dotted path starts with an underscore (``torch_hsh.ps.optim`` is
public, ``torch_hsh.ps._chunks`` and ``torch_hsh._native`` are not).
"""
import importlib
import pkgutil

import pytest

import torch_hsh

SUBPACKAGES = ("bases", "brdf", "cli", "fitting", "frames", "io", "kernel", "nn", "ps", "quadrature", "render",
               "rti", "spectra", "surface")


def _public_modules():
    names = ["torch_hsh"]
    for info in pkgutil.walk_packages(torch_hsh.__path__, "torch_hsh."):
        if not any(part.startswith("_") for part in info.name.split(".")):
            names.append(info.name)
    return sorted(names)


PUBLIC = _public_modules()


def test_the_walk_finds_the_modules():
    expected = {"torch_hsh.ps.result", "torch_hsh.rti.io", "torch_hsh.surface.export", "torch_hsh.fitting.arguments"}
    assert expected <= set(PUBLIC)
    assert not any("._" in name for name in PUBLIC)


@pytest.mark.parametrize("name", PUBLIC)
def test_public_module_lists_its_names(name):
    mod = importlib.import_module(name)
    assert hasattr(mod, "__all__"), f"{name} has no __all__"
    names = list(mod.__all__)
    assert all(isinstance(n, str) for n in names), f"{name}.__all__ holds a non-string"
    assert len(names) == len(set(names)), f"{name}.__all__ lists a name twice"
    missing = [n for n in names if not hasattr(mod, n)]
    assert not missing, f"{name}.__all__ lists names it does not define: {missing}"


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_import_torch_hsh_exposes_the_subpackage(sub):
    assert hasattr(torch_hsh, sub), f"`import torch_hsh` does not expose torch_hsh.{sub}"
    assert getattr(torch_hsh, sub) is importlib.import_module(f"torch_hsh.{sub}")
