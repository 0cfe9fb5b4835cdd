"""Deprecated import path of :mod:`torch_hsh.kernel` (the HSH and Helmholtz basis kernel).

The module was renamed so that it no longer reads like :mod:`torch_hsh.bases` (the comparison bases).
Every name, public or private, is forwarded to :mod:`torch_hsh.kernel`; importing this module warns once.
"""
import warnings

from . import kernel as _kernel
from .kernel import *  # noqa: F401,F403
from .kernel import __all__  # noqa: F401

warnings.warn("torch_hsh.basis is deprecated: import torch_hsh.kernel instead (the same functions)",
              DeprecationWarning, stacklevel=2)


def __getattr__(name):
    return getattr(_kernel, name)
