"""Readers and writers for third-party data formats.

Each format lives in its own submodule, imported below in its own block
(append new formats at the end of this file)::

    torch_hsh.io.merl      MERL BRDF ``.binary`` tables (read_merl, write_merl, MERLBRDF, tabulate_merl, fit_merl)
    torch_hsh.io.diligent  DiLiGenT-layout photometric-stereo folders (load_diligent, save_diligent)
    torch_hsh.io.exr       OpenEXR images, image stacks, normal / coefficient maps, environment maps

Naming rule: functions on a **folder** are ``load_*`` / ``save_*``
(``load_diligent``, ``save_diligent``); functions on a **single file** are
``read_*`` / ``write_*`` (``read_exr``, ``write_merl``, ...). Writers refuse to
replace existing files unless ``overwrite=True`` and then replace only the
files they write.

Example:
    >>> from torch_hsh.io import read_merl, write_merl  # doctest: +SKIP
"""
__all__ = []

from . import merl  # noqa: E402,F401
from .merl import (  # noqa: E402,F401
    MERL_SCALE,
    MERL_SHAPE,
    MERLBRDF,
    fit_merl,
    merl_solid_angle_weights,
    read_merl,
    tabulate_merl,
    write_merl,
)

__all__ += ["merl", "MERL_SCALE", "MERL_SHAPE", "MERLBRDF", "read_merl", "tabulate_merl", "write_merl", "fit_merl",
            "merl_solid_angle_weights"]

from . import diligent  # noqa: E402,F401
from .diligent import *  # noqa: E402,F401,F403

__all__ += ["diligent"] + list(diligent.__all__)

from . import exr  # noqa: E402,F401
from .exr import *  # noqa: E402,F401,F403

__all__ += ["exr"] + list(exr.__all__)
