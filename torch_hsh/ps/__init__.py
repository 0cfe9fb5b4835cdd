"""Photometric stereo: Lambertian baselines and the Helmholtz HSH solver.

* :func:`lambertian_ls` — Woodham least squares.
* :func:`robust_lambertian` — trimmed least squares (drop darkest 25 %, brightest 10 % by default).
* :func:`solve_hsh` — per-pixel normal + isotropic Helmholtz BRDF coefficients (variable projection,
  Levenberg–Marquardt, coarse cone search, adaptive shadow/saturation handling).
* :func:`holdout_evaluation` — fit on a subset of the lights, relighting error on the rest.
* :func:`angular_error` — per-pixel angular error in degrees.

Inputs everywhere: ``images (L, H, W, C)`` or ``(L, P, C)``, ``lights (L, 3)`` in the DiLiGenT frame
(x right, y up, z toward the camera), optional ``intensities (L,)``/``(L, C)`` and ``mask (H, W)``.

Example:
    >>> from torch_hsh import ps
    >>> res = ps.solve_hsh(images, lights, mask=mask)  # doctest: +SKIP
"""
from ._common import angular_error
from .hsh import (
    DEFAULT_MATERIALS,
    DEFAULT_ORDER,
    HoldoutResult,
    HSHResult,
    directional_albedo_view,
    holdout_evaluation,
    observation_weights,
    solve_hsh,
)
from .lambertian import LambertianResult, lambertian_ls, robust_lambertian, trimmed_weights

__all__ = [
    "DEFAULT_MATERIALS",
    "DEFAULT_ORDER",
    "HSHResult",
    "HoldoutResult",
    "LambertianResult",
    "angular_error",
    "directional_albedo_view",
    "holdout_evaluation",
    "lambertian_ls",
    "observation_weights",
    "robust_lambertian",
    "solve_hsh",
    "trimmed_weights",
]
