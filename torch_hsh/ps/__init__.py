"""Photometric stereo: Lambertian baselines and the Helmholtz HSH solver.

* :func:`lambertian_ls` — Woodham least squares.
* :func:`robust_lambertian` — trimmed least squares (drop darkest 25 %, brightest 10 % by default).
* :func:`solve_hsh` — normals + isotropic Helmholtz BRDF coefficients per pixel, with a few basis
  BRDFs shared by the object (default) or independent BRDFs per pixel; its options are the fields of
  :class:`Settings` (each with its default, check and doc).
* :func:`refine_surface` — the whole-surface stage after the solve: one depth map, the shared BRDFs and
  the shadows it casts (``solve_hsh(..., refine_surface=True)``).
* :func:`one_bounce` — one bounce of interreflection between the pixels of a surface, under every light
  (``solve_hsh(..., interreflections=1)`` removes it from the images and solves again).
* :func:`holdout_evaluation` — fit on a subset of the lights, relighting error on the rest.
* :func:`angular_error` — per-pixel angular error in degrees.

The HSH solver is a pipeline of stages, one module each (see :mod:`torch_hsh.ps.pipeline`):
:mod:`~torch_hsh.ps.observations` → :mod:`~torch_hsh.ps.initialisation` →
:mod:`~torch_hsh.ps.calibration` → :mod:`~torch_hsh.ps.refinement` →
:mod:`~torch_hsh.ps.coefficients` → :mod:`~torch_hsh.ps.result`; the forward model is in
:mod:`~torch_hsh.ps.design` and the numerical kernels in :mod:`~torch_hsh.ps.optim`. Above the
pipeline: the cast-shadow loop (:mod:`~torch_hsh.ps.shadows`), the interreflection loop
(:mod:`~torch_hsh.ps.interreflections`) and the held-out-light evaluation
(:mod:`~torch_hsh.ps.evaluation`).

Inputs everywhere: ``images (L, H, W, C)`` or ``(L, N, C)``, ``lights (L, 3)`` in the DiLiGenT frame
(x right, y up, z toward the camera), optional ``intensities (L,)``/``(L, C)`` and ``mask (H, W)``.

Example:
    >>> from torch_hsh import ps
    >>> res = ps.solve_hsh(images, lights, mask=mask)  # doctest: +SKIP
"""
from ._geometry import angular_error
from .evaluation import holdout_evaluation
from .interreflections import one_bounce
from .lambertian import LambertianResult, lambertian_ls, robust_lambertian, trimmed_weights
from .observations import observation_weights
from .pipeline import solve_hsh
from .result import HoldoutResult, HSHResult, directional_albedo_view
from .settings import DEFAULT_BASIS_RIDGE, DEFAULT_MATERIALS, DEFAULT_ORDER, Settings
from .whole_surface import refine_surface

__all__ = [
    "DEFAULT_BASIS_RIDGE",
    "DEFAULT_MATERIALS",
    "DEFAULT_ORDER",
    "HSHResult",
    "HoldoutResult",
    "LambertianResult",
    "Settings",
    "angular_error",
    "directional_albedo_view",
    "holdout_evaluation",
    "lambertian_ls",
    "observation_weights",
    "one_bounce",
    "refine_surface",
    "robust_lambertian",
    "solve_hsh",
    "trimmed_weights",
]
