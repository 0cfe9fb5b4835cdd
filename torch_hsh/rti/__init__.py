r"""Reflectance transformation imaging (RTI): from a capture to a relightable file and a viewer.

Modules::

    torch_hsh.rti.fitting  light directions from a glossy sphere (sphere_light_directions), the RTI
                           HSH basis of RTIViewer / relight / OpenLIME (rti_hsh_basis, evaluate_rti),
                           projection of a photometric-stereo result onto it (project_to_rti, fit_rti)
    torch_hsh.rti.io       RTI captures (.lp light files and photographs: read_lp, write_lp, load_rti,
                           save_rti) and exports (write_rti_hsh, save_relight)
    torch_hsh.rti.viewer   the self-contained WebGL2 relighting page (write_viewer)
    torch_hsh.rti.cli      the ``torch-hsh lights``, ``torch-hsh rti`` and ``torch-hsh view`` commands

Example:
    >>> from torch_hsh.rti import read_lp, project_to_rti, write_rti_hsh  # doctest: +SKIP
"""
from . import fitting, io, viewer
from .fitting import *  # noqa: F401,F403
from .io import *  # noqa: F401,F403
from .viewer import *  # noqa: F401,F403

__all__ = ["fitting", "io", "viewer", *fitting.__all__, *io.__all__, *viewer.__all__]
