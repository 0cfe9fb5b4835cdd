r"""From normals to surfaces: normal integration, light visibility, depth and mesh export.

Submodules::

    torch_hsh.surface.integrate   integrate_normals (Poisson / bilateral), connected_components,
                                  normals_to_slopes, depth_to_normals
    torch_hsh.surface.visibility  light_visibility (cast shadows of a depth map, per light and pixel)
    torch_hsh.surface.export      write_depth, depth_to_mesh, write_mesh, shade_depth

Frame everywhere: DiLiGenT (x right, y up, z toward the camera), orthographic,
pixel ``(row, col)`` at ``x = col, y = -row``; depth = height ``z`` in pixel units.
See ``docs/surfaces.md``.
"""
from .integrate import (  # noqa: F401
    INTEGRATION_METHODS,
    connected_components,
    depth_to_normals,
    integrate_normals,
    normals_to_slopes,
)
from .visibility import light_visibility  # noqa: F401
from .export import MESH_EXTRA_HINT, depth_to_mesh, write_depth, write_mesh, shade_depth  # noqa: F401

__all__ = [
    "INTEGRATION_METHODS",
    "connected_components",
    "depth_to_normals",
    "integrate_normals",
    "normals_to_slopes",
    "light_visibility",
    "MESH_EXTRA_HINT",
    "depth_to_mesh",
    "write_depth",
    "write_mesh",
    "shade_depth",
]
