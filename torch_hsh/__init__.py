"""torch_hsh: differentiable Helmholtz hemispherical-harmonic BRDF bases for PyTorch."""
from ._version import __version__  # noqa: F401

from ._checks import MAX_ANISOTROPIC_ORDER, MAX_ORDER, set_validation
from .kernel import (
    anisotropic_indices,
    backend_status,
    get_backend,
    set_backend,
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
)
from .frames import isotropic_triple, local_frame, reflect, to_local, to_world
from . import bases, frames, io, kernel  # noqa: F401
from .bases import available_bases, get_basis
from .nn import HSH, HelmholtzBRDF
from .quadrature import direction_quadrature, gauss_legendre, isotropic_quadrature, monte_carlo_directions
from .fitting import (
    ConvergenceError,
    ConvergenceWarning,
    brdf_accuracy,
    brdf_energy,
    directional_albedo,
    energy_accuracy,
    evaluate,
    fit,
    normal_exitance_energy,
    normal_exitance_to_isotropic,
    project,
    project_normal_exitance,
    reconstruct,
    truncate,
)
from .spectra import lambertian_spectrum, mirror_spectrum, mirror_spectrum_printed
from . import brdf  # noqa: E402,F401  (analytic BRDF models: torch_hsh.brdf.get_model)
from . import scenes  # noqa: E402,F401  (synthetic photometric-stereo scenes: torch_hsh.scenes)
from . import render  # noqa: E402,F401  (differentiable photometric-stereo image formation)
from . import surface  # noqa: E402,F401  (normal integration, visibility, depth/mesh export: torch_hsh.surface)
from . import ps  # noqa: E402,F401  (photometric-stereo solvers: ps.solve_hsh, ps.robust_lambertian, ...)
from .ps import solve_hsh  # noqa: E402,F401
from . import envmap  # noqa: E402,F401  (environment lighting: EnvironmentMap, render_envmap)
from .envmap import EnvironmentLighting, EnvironmentMap, render_envmap, render_envmap_reference  # noqa: E402,F401


#: Old module paths, still importable with a DeprecationWarning (see the module named by each).
_DEPRECATED_MODULES = {"basis": "kernel"}


def __getattr__(name):
    if name in _DEPRECATED_MODULES:
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
