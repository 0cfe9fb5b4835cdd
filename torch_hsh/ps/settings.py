"""Validated settings of the HSH solver, shared by its stages (see :func:`~torch_hsh.ps.solve_hsh`)."""
from __future__ import annotations

from dataclasses import dataclass
import math
import numbers
from typing import Optional, Tuple, Union

import torch

from .._checks import check_order

__all__ = ["Settings", "DEFAULT_ORDER", "DEFAULT_MATERIALS", "DEFAULT_BASIS_RIDGE", "CAUCHY_C", "AUTO"]

#: Default basis order: 3 (K = 20 functions per channel). With the view fixed
#: (orthographic camera) only (P+1)(P+2)/2 = 10 combinations per channel are
#: identifiable from one pixel, comfortably fewer than the 50-100 lights of a
#: typical capture even after shadows and highlights are removed.
DEFAULT_ORDER = 3

#: Default number of shared basis BRDFs ("materials") of the shared model.
#: Two cover the common dichromatic case (a coloured body reflection and a
#: specular reflection with its own colour) with free RGB weights per pixel.
DEFAULT_MATERIALS = 2

#: Default relative ridge on the shared basis BRDFs (``solve_hsh(basis_ridge=...)``): a
#: smoothness penalty, ``basis_ridge`` x the mean diagonal of the basis normal equations x
#: the order profile. The normals' elevations and the basis BRDFs trade off along a nearly
#: flat valley of the calibration loss, and this ridge is what picks the point on it. With
#: 1e-3 (earlier versions) the point depended on the calibration subset: the built-in
#: bumpy height field flipped between two basins (15.4 / 18.2 deg, 2.8 deg over 5 seeds).
#: 3e-3 is the smallest half-decade step up that removes that flip on the built-in scenes;
#: every larger value costs accuracy on sharp specular lobes (docs/photometric_stereo.md).
DEFAULT_BASIS_RIDGE = 3e-3

#: Value of ``materials`` that selects the number of basis BRDFs from the data
#: (held-out-light cross-validation, :mod:`torch_hsh.ps.materials`).
AUTO = "auto"

#: Cauchy constant of every robust reweighting (95 % efficiency at Gaussian noise).
CAUCHY_C = 2.385


@dataclass(frozen=True)
class Settings:
    """Every option of :func:`~torch_hsh.ps.solve_hsh`, validated (see its docstring for the meaning)."""

    order: int
    materials: Union[int, str, None]
    ridge: float
    search_angles: Tuple[float, ...]
    search_azimuths: int
    max_iter: int
    robust: bool
    robust_iters: int
    calibration_pixels: int
    calibration_rounds: int
    calibration_starts: Tuple[str, ...]
    nonneg: bool
    chunk_size: Optional[int]
    work_dtype: Optional[torch.dtype]
    seed: int
    progress: bool
    cauchy_c: float = CAUCHY_C
    refinement_passes: int = 2
    #: Relative ridge on the shared basis BRDFs (see :data:`DEFAULT_BASIS_RIDGE`).
    basis_ridge: float = DEFAULT_BASIS_RIDGE
    #: True when ``chunk_size`` was chosen by :func:`resolve_chunk` (it may then shrink on out-of-memory).
    chunk_auto: bool = False

    @property
    def chunk(self) -> int:
        """Pixels per chunk; ``solve_hsh`` resolves ``chunk_size=None`` per device (:func:`resolve_chunk`) first."""
        if self.chunk_size is None:
            raise RuntimeError("chunk_size=None must be resolved with resolve_chunk() before the per-pixel stages")
        return self.chunk_size

    @classmethod
    def validated(
        cls,
        order,
        materials,
        ridge,
        search_angles,
        search_azimuths,
        max_iter,
        robust,
        robust_iters,
        calibration_pixels,
        calibration_rounds,
        calibration_starts,
        nonneg,
        chunk_size,
        work_dtype,
        seed,
        progress,
        refinement_passes=2,
        basis_ridge=DEFAULT_BASIS_RIDGE,
    ) -> "Settings":
        order = check_order(order)
        materials = _check_materials(materials)
        if not ridge > 0:
            raise ValueError(f"`ridge` must be > 0 (it keeps the rank-deficient normal equations solvable), got {ridge}")
        if chunk_size is not None and (isinstance(chunk_size, bool) or not isinstance(chunk_size, numbers.Integral)
                                       or chunk_size < 1):
            raise ValueError(f"`chunk_size` must be an integer >= 1 or None (chosen per device), got {chunk_size!r}")
        if max_iter is None:
            max_iter = 15 if materials is None else 16
        if isinstance(max_iter, bool) or int(max_iter) != max_iter or max_iter < 0:
            raise ValueError(f"`max_iter` must be an integer >= 0, got {max_iter!r}")
        bad = [s_ for s_ in calibration_starts if s_ not in CALIBRATION_STARTS]
        if isinstance(calibration_starts, str) or bad:
            raise ValueError(
                f"`calibration_starts` must be a sequence of 'lambertian' / 'independent' / 'flattened', "
                f"got {calibration_starts!r}"
            )
        if isinstance(refinement_passes, bool) or not isinstance(refinement_passes, int) or not 1 <= refinement_passes <= 5:
            raise ValueError(f"`refinement_passes` must be an integer in [1, 5], got {refinement_passes!r}")
        if isinstance(basis_ridge, bool) or not isinstance(basis_ridge, numbers.Real) \
                or not math.isfinite(basis_ridge) or not 0 < float(basis_ridge) <= 1:
            raise ValueError(f"`basis_ridge` must be a number in (0, 1] (relative to the mean diagonal of the "
                             f"basis BRDFs' normal equations), got {basis_ridge!r}")
        if work_dtype is not None and work_dtype not in (torch.float32, torch.float64):
            raise ValueError(f"`work_dtype` must be torch.float32, torch.float64 or None, got {work_dtype!r}")
        if int(calibration_pixels) < 1 or int(calibration_rounds) < 0:
            raise ValueError(
                f"`calibration_pixels` must be >= 1 and `calibration_rounds` >= 0, got {calibration_pixels}, "
                f"{calibration_rounds}"
            )
        return cls(
            order=order,
            materials=materials,
            ridge=ridge,
            search_angles=tuple(search_angles),
            search_azimuths=search_azimuths,
            max_iter=int(max_iter),
            robust=robust,
            robust_iters=robust_iters,
            calibration_pixels=int(calibration_pixels),
            calibration_rounds=int(calibration_rounds),
            calibration_starts=tuple(calibration_starts),
            nonneg=nonneg,
            chunk_size=None if chunk_size is None else int(chunk_size),
            work_dtype=work_dtype,
            seed=seed,
            progress=progress,
            refinement_passes=int(refinement_passes),
            basis_ridge=float(basis_ridge),
        )


def _check_materials(materials):
    """``materials``: an integer in [1, 8], ``"auto"`` or ``None``; anything else is a ValueError naming it."""
    if materials is None or (isinstance(materials, str) and materials == AUTO):
        return materials
    if (
        isinstance(materials, (bool, str))
        or not isinstance(materials, numbers.Real)
        or not math.isfinite(materials)
        or int(materials) != materials
        or not 1 <= int(materials) <= 8
    ):
        raise ValueError(
            f"`materials` must be an integer in [1, 8], 'auto' (chosen from the data) or None (independent "
            f"BRDFs), got {materials!r}"
        )
    return int(materials)


#: Accepted names in ``calibration_starts`` (see :func:`~torch_hsh.ps.solve_hsh`).
CALIBRATION_STARTS = ("lambertian", "independent", "flattened")

#: Pixels per chunk of the per-pixel passes on the CPU (``chunk_size=None``).
CPU_CHUNK = 8192
#: Bounds of the chunk chosen on other devices from their free memory.
DEVICE_CHUNK_RANGE = (8192, 262144)
#: Bytes per pixel and light of the shared model's per-pixel refinement in a 4-byte work dtype,
#: with headroom (measured on an H200: about 290 at 96 lights, float32, order 3).
_SHARED_BYTES_PER_PIXEL_LIGHT = 384
#: Numbers per pixel, light (real or virtual) and basis function held by the K-sized designs of the
#: independent model and of the final coefficients, with headroom (measured on the CPU: 10-12 at
#: orders 3 and 6, 96 lights, float64).
_NUMBERS_PER_PIXEL_LIGHT_K = 14
#: Virtual lights of the non-negativity safeguard (:func:`~torch_hsh.ps.coefficients.final_coefficients`).
_VIRTUAL_LIGHTS = 48


def resolve_chunk(chunk_size: Optional[int], device: torch.device, n_lights: int, n_basis: int, independent: bool,
                  work_itemsize: int, itemsize: int) -> int:
    """Pixels per chunk: ``chunk_size`` if given, else :data:`CPU_CHUNK` on the CPU, else sized from free memory.

    On a GPU the solver is bound by kernel launches, not arithmetic, so fewer,
    larger chunks are faster: the chunk is the largest that keeps one chunk's
    temporaries within a quarter of the device's free memory, clipped to
    :data:`DEVICE_CHUNK_RANGE`. Results do not depend on the chunk.

    Per pixel, the estimate counts ``n_lights`` real and 48 virtual lights:

    * independent model (``independent=True``): the ``(lights, K)`` designs of
      ``K = n_basis`` basis functions in the output dtype (``itemsize`` bytes);
    * shared model: the larger of the refinement's ``(M, lights)`` arrays in
      the work dtype (``work_itemsize``) and the final coefficients' ``(lights,
      K)`` designs, which run in an eighth of the chunk.
    """
    if chunk_size is not None:
        return int(chunk_size)
    if device.type != "cuda":
        return CPU_CHUNK
    free, _ = torch.cuda.mem_get_info(device)
    L = max(1, int(n_lights))
    k_term = _NUMBERS_PER_PIXEL_LIGHT_K * max(1, int(n_basis)) * (L + _VIRTUAL_LIGHTS) * itemsize
    if independent:
        per_pixel = k_term
    else:
        per_pixel = max(_SHARED_BYTES_PER_PIXEL_LIGHT * L * work_itemsize // 4, k_term // 8)
    lo, hi = DEVICE_CHUNK_RANGE
    return int(min(hi, max(lo, free // 4 // per_pixel)))
