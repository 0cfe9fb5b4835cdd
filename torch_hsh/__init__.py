"""torch_hsh: differentiable Helmholtz hemispherical-harmonic BRDF bases for PyTorch."""
__version__ = "0.1.0"

from ._checks import MAX_ANISOTROPIC_ORDER, MAX_ORDER, set_validation
from .basis import (
    anisotropic_indices,
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
