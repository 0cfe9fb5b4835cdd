"""Deprecated import path of :mod:`torch_hsh.ps.pipeline` (the HSH solver pipeline).

The module was renamed after what it holds (the pipeline of stages, not the model). Every name, public or
private, is forwarded to :mod:`torch_hsh.ps.pipeline` (``holdout_evaluation`` to :mod:`torch_hsh.ps.evaluation`,
the result types to :mod:`torch_hsh.ps.result`); importing this module warns once.
"""
import warnings

from . import pipeline as _pipeline
from .evaluation import holdout_evaluation  # noqa: F401
from .observations import observation_weights  # noqa: F401
from .pipeline import *  # noqa: F401,F403
from .pipeline import solve_hsh  # noqa: F401
from .result import HoldoutResult, HSHResult, directional_albedo_view  # noqa: F401
from .settings import DEFAULT_MATERIALS, DEFAULT_ORDER  # noqa: F401

__all__ = ["HSHResult", "HoldoutResult", "DEFAULT_ORDER", "DEFAULT_MATERIALS", "solve_hsh", "holdout_evaluation",
           "directional_albedo_view", "observation_weights"]

warnings.warn("torch_hsh.ps.hsh is deprecated: import torch_hsh.ps.pipeline instead (the same functions)",
              DeprecationWarning, stacklevel=2)


def __getattr__(name):
    return getattr(_pipeline, name)
