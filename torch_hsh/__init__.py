"""torch_hsh: differentiable Helmholtz hemispherical-harmonic BRDF bases for PyTorch.

The core (directions -> basis values -> BRDF values) is at the top level; each application is a
subpackage with its own I/O and command line::

    torch_hsh.kernel      HSH and Helmholtz basis values (hsh, helmholtz_isotropic, ...), backends
    torch_hsh.nn          nn.Module layers (HSH, HelmholtzBRDF)
    torch_hsh.frames      local frames (local_frame, to_local, to_world, reflect)
    torch_hsh.quadrature  quadrature rules on the hemisphere
    torch_hsh.fitting     projection, least squares, reconstruction, energy and accuracy
    torch_hsh.spectra     closed-form spectra (Lambertian, mirror)
    torch_hsh.bases       the paper's comparison bases behind one interface
    torch_hsh.brdf        analytic BRDF models
    torch_hsh.io          EXR, MERL and DiLiGenT-folder readers and writers
    torch_hsh.render      images under point lights and environment maps, synthetic scenes, cast shadows
    torch_hsh.ps          photometric stereo (solve_hsh, Lambertian baselines) and ``torch-hsh ps``
    torch_hsh.surface     normal integration, light visibility, depth and mesh export
    torch_hsh.rti         RTI captures, RTI exports, the relighting viewer
    torch_hsh.cli         the ``torch-hsh`` command

Example:
    >>> import torch, torch_hsh
    >>> wi = torch.tensor([[0.0, 0.0, 1.0]]); wo = torch.tensor([[0.6, 0.0, 0.8]])
    >>> torch_hsh.helmholtz_isotropic(wi, wo, order=2).shape
    torch.Size([1, 10])
"""
from ._version import __version__

from ._checks import MAX_ANISOTROPIC_ORDER, MAX_ORDER, set_validation
from .kernel import (
    anisotropic_indices,
    backend_status,
    get_backend,
    helmholtz_anisotropic,
    helmholtz_isotropic,
    helmholtz_isotropic_cosines,
    helmholtz_isotropic_world,
    hsh,
    hsh_index,
    isotropic_indices,
    num_anisotropic,
    num_hsh,
    num_isotropic,
    set_backend,
)
from .frames import isotropic_triple, local_frame, reflect, to_local, to_world
from .nn import HSH, HelmholtzBRDF
from .quadrature import direction_quadrature, gauss_legendre, isotropic_quadrature, monte_carlo_directions
from .bases import available_bases, get_basis
from .fitting import (
    ConvergenceError,
    ConvergenceWarning,
    brdf_accuracy,
    brdf_energy,
    directional_albedo,
    energy_accuracy,
    fit,
    normal_exitance_energy,
    normal_exitance_to_isotropic,
    project,
    project_normal_exitance,
    reconstruct,
    truncate,
)
from .spectra import lambertian_spectrum, mirror_spectrum, mirror_spectrum_printed
from .render.envmap import EnvironmentLighting, EnvironmentMap, render_envmap, render_envmap_reference
from .ps import solve_hsh
from . import bases, brdf, cli, fitting, frames, io, kernel, nn, ps, quadrature, render, rti, spectra, surface

__all__ = [
    "__version__",
    # subpackages and modules
    "bases", "brdf", "cli", "fitting", "frames", "io", "kernel", "nn", "ps", "quadrature", "render", "rti",
    "spectra", "surface",
    # validation and limits
    "MAX_ANISOTROPIC_ORDER", "MAX_ORDER", "set_validation",
    # basis values (torch_hsh.kernel)
    "anisotropic_indices", "backend_status", "get_backend", "helmholtz_anisotropic", "helmholtz_isotropic",
    "helmholtz_isotropic_cosines", "helmholtz_isotropic_world", "hsh", "hsh_index", "isotropic_indices",
    "num_anisotropic", "num_hsh", "num_isotropic", "set_backend",
    # frames, layers, quadrature, named bases
    "isotropic_triple", "local_frame", "reflect", "to_local", "to_world", "HSH", "HelmholtzBRDF",
    "direction_quadrature", "gauss_legendre", "isotropic_quadrature", "monte_carlo_directions",
    "available_bases", "get_basis",
    # fitting and spectra
    "ConvergenceError", "ConvergenceWarning", "brdf_accuracy", "brdf_energy", "directional_albedo",
    "energy_accuracy", "fit", "normal_exitance_energy", "normal_exitance_to_isotropic", "project",
    "project_normal_exitance", "reconstruct", "truncate", "lambertian_spectrum", "mirror_spectrum",
    "mirror_spectrum_printed",
    # applications
    "EnvironmentLighting", "EnvironmentMap", "render_envmap", "render_envmap_reference", "solve_hsh",
]
