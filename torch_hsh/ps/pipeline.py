r"""Non-Lambertian photometric stereo with the isotropic Helmholtz HSH basis: the solver pipeline.

Model, per pixel (one unit normal ``n`` shared by the channels, one set of
isotropic Helmholtz coefficients per channel):

.. math::
    y_{jc} = I_{jc} / e_{jc} = \sum_k a_{ck}\, \Phi_{jk}(n), \qquad
    \Phi_{jk}(n) = B_k(l_j, v, n)\, \max(0, n\cdot l_j),

with ``v = (0, 0, 1)`` and :math:`B_k` from
:func:`torch_hsh.helmholtz_isotropic_world` (zero below the horizon).

Two models (see ``docs/photometric_stereo.md``):

* **shared basis BRDFs** (default, ``materials=M``): :math:`a_{pc} = \sum_m
  W_{pcm} B_m` (+ a ridge-shrunk per-pixel residual fitted at the end), with
  ``M`` basis BRDFs shared by the object and free per-pixel RGB mixing
  weights. Sharing removes the single-view elevation ambiguity of a BRDF
  that is free at every pixel.
* **independent** (``materials=None``): ``K`` free coefficients per pixel and
  channel with a ridge that grows with order.

:func:`solve_hsh` is a pipeline of six stages, each in its own module, with
small state objects between them (data flows one way):

1. :mod:`~torch_hsh.ps.observations` -> ``Observations``: flatten, normalise, noise / saturation / shadow weights
2. :mod:`~torch_hsh.ps.initialisation` -> ``(N, 3)`` normals: robust Lambertian start
3. (``materials="auto"`` only) :mod:`~torch_hsh.ps.materials` -> ``M``: the number of basis BRDFs by held-out-light
   cross-validation; then :mod:`~torch_hsh.ps.calibration` -> ``Calibration``: shared basis BRDFs on a pixel subset
4. :mod:`~torch_hsh.ps.refinement` -> ``Refinement``: per-pixel normals (and mixing weights), in chunks
5. :mod:`~torch_hsh.ps.coefficients` -> ``Coefficients``: final coefficients, non-negativity safeguard
6. :mod:`~torch_hsh.ps.result` -> ``HSHResult``: maps, albedo, relighting, holdout evaluation

Around the stages, all opt-in: the cast-shadow loop (:mod:`.shadows`), the removal of one
bounce of interreflection (:mod:`.interreflections`) and the whole-surface stage
(:mod:`.whole_surface`), in that order. The whole-surface stage brings one (safeguarded) round
of the interreflection loop unless ``interreflections`` is set.

The forward model lives in :mod:`.design`, the numerical kernels (LM, IRLS,
small solves) in :mod:`.optim`, the validated options in :mod:`.settings`.
Memory is bounded by ``O(chunk_size * L * K)`` in stages 4 and 5.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Dict, Optional

import torch

from .._checks import warn_user
from ._chunks import ROW_CHUNK, row_sum, scatter_pixels
from .calibration import calibrate, fixed_calibration
from .coefficients import fit_coefficients
from .initialisation import initial_normals
from .interreflections import interreflection_loop
from .lambertian import _solve_flat
from .observations import observe
from .materials import select_materials
from .refinement import refine
from .result import HSHResult, confidence, directional_albedo_view
from .settings import AUTO, Settings, option_docs
from .shadows import shadow_loop
from .whole_surface import refine_surface

__all__ = ["solve_hsh", "run_stages", "confidence", "MIN_VALID_OBSERVATIONS"]


def solve_hsh(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    *,
    settings: Optional[Settings] = None,
    **overrides,
) -> HSHResult:
    r"""Photometric stereo with isotropic Helmholtz HSH BRDFs.

    Two models (see ``docs/photometric_stereo.md``):

    * ``materials=M`` (default ``M = 2``): **shared basis BRDFs**. The
      coefficients of pixel ``p``, channel ``c`` are
      :math:`a_{pc} = \sum_m W_{pcm} B_m + \delta_{pc}`: ``M`` basis BRDFs
      ``B (M, K)`` shared by the whole object (Goldman et al. 2005; Alldrin
      et al. 2008) with free per-pixel RGB mixing weights ``W``, plus a small
      per-pixel residual ``delta`` (ridge-shrunk toward 0, fitted once the
      normal is fixed). Sharing is what makes the normal's elevation
      identifiable: with one viewpoint a BRDF free at every pixel only fixes
      the normal's azimuth (Alldrin & Kriegman 2007). Steps: robust Lambertian
      start; on a random subset of pixels (its size is an option), alternate
      Cauchy-IRLS fits of ``(B, W)`` with Levenberg–Marquardt on the normals
      (for a set number of rounds); then, with ``B`` fixed, every pixel
      runs IRLS + variable-projection LM on its normal (the mixing weights
      are linear, solved in closed form), with a coarse cone search at the
      first iteration. The robust scale is estimated from the data.
    * ``materials=None``: an **independent** BRDF per pixel (``K``
      coefficients per channel, ridge growing with order), VP-LM from the
      robust Lambertian start. Fits the data as closely, but the elevation of
      the normal is then set by the ridge, not by the data.

    Args:
        images: ``(L, H, W, C)`` or ``(L, N, C)`` linear images (trailing channel axis).
        lights: ``(L, 3)`` directions toward the lights (DiLiGenT frame).
        intensities: ``None``, ``(L,)`` or ``(L, C)`` light intensities (images are divided by them).
        mask: ``(H, W)`` / ``(N,)`` bool object mask (default: every pixel).
        settings: a :class:`~torch_hsh.ps.Settings` with the options below
            (default: every option at its default).
        **overrides: options by name, applied on top of ``settings``
            (``Settings(**overrides)`` or ``dataclasses.replace(settings,
            **overrides)``): the fields of :class:`~torch_hsh.ps.Settings`,
            listed here from their definitions.

    Options (the fields of :class:`~torch_hsh.ps.Settings`):

        {options}

    Real captures: the solver runs at unit brightness (the images are divided
    by a power of two near their median), so the normals do not depend on the
    images' units; every pixel inside the mask gets a finite unit normal (a
    pixel with fewer than 4 valid observations keeps a Lambertian normal and
    confidence 0); images are held in float32 when they are float32 (the
    per-pixel fits convert chunk by chunk), so memory stays a small multiple
    of the stack.

    Returns:
        :class:`HSHResult` (normals, coefficient maps, directional albedo,
        confidence, and for the shared model the basis BRDFs and mixing
        weights), in ``dtype`` on the images' device (``weights`` in the
        images' storage dtype). ``info`` holds the diagnostics, including the
        wall time of each stage (``time_<stage>_s``).

    Raises:
        ValueError: shape mismatches, fewer than 3 lights (6 for
            ``materials="auto"``), empty mask, bad order or number of materials.

    Example:
        >>> res = solve_hsh(images, lights, mask=mask, order=3)  # doctest: +SKIP
        >>> res.normals.shape, res.coefficients.shape  # doctest: +SKIP
        (torch.Size([64, 64, 3]), torch.Size([64, 64, 3, 20]))
    """
    cfg = Settings(**overrides) if settings is None else dataclasses.replace(settings, **overrides)
    if cfg.refine_surface and cfg.materials is None:  # before any solve: the stage would refuse its result
        raise ValueError("`refine_surface` needs the shared model (`materials` >= 1 or 'auto'), got materials=None")
    solve = functools.partial(shadow_loop, run_stages) if cfg.cast_shadows else run_stages
    if cfg.interreflections:  # the later stages see the images without the bounce
        res, images, intensities = interreflection_loop(solve, images, lights, intensities, mask, cfg)
    else:
        res = solve(images, lights, intensities, mask, cfg)
    if cfg.refine_surface:
        res = refine_surface(res, images, lights, intensities, settings=cfg)
    return res


if solve_hsh.__doc__:  # None under python -OO
    solve_hsh.__doc__ = solve_hsh.__doc__.replace("{options}", option_docs("        "))


def run_stages(images: torch.Tensor, lights: torch.Tensor, intensities: Optional[torch.Tensor],
               mask: Optional[torch.Tensor], cfg: Settings) -> HSHResult:
    """The six stages of :func:`solve_hsh` (without the cast-shadow loop), with the options ``cfg``."""
    t_start = time.perf_counter()
    obs = observe(images, lights, intensities, mask, cfg)  # 1
    clock = _StageClock(t_start, obs.data.y.device)
    cfg = cfg.chunked(obs.data.y, obs.data.dtype)
    obs.info["chunk_size"] = float(cfg.chunk)
    clock.lap("observations")
    n_init = initial_normals(obs, cfg)  # 2
    clock.lap("initialisation")
    cfg, cal, n_start = _calibration(obs, n_init, cfg, clock)  # 3a, 3
    basis, scale = (None, None) if cal is None else (cal.basis, cal.scale)
    ref = _refinement(obs, n_start, cfg, basis, scale)  # 4
    clock.lap("refinement")
    fit = fit_coefficients(obs, ref, cfg, basis)  # 5
    clock.lap("coefficients")
    res = _result(obs, n_init, ref, fit, cal, cfg, t_start)  # 6
    clock.lap("result")
    res.info.update(clock.info())
    return res


def _calibration(obs, n_start, cfg: Settings, clock):
    """Stages 3a and 3 (shared model): ``materials="auto"`` resolved, then the basis BRDFs (given or calibrated).

    Returns the settings (``materials`` resolved), the calibration (None for the independent model) and the
    start normals of the refinement."""
    cal = None
    if cfg.materials == AUTO:
        sel = select_materials(obs, n_start, cfg)  # 3a
        obs.info.update(sel.info())
        cfg = dataclasses.replace(cfg, materials=sel.chosen)
        clock.lap("materials")
    if cfg.basis is not None:
        # the solve runs at unit brightness
        scale_u = None if cfg.robust_scale is None else float(cfg.robust_scale) / obs.scale
        cal = fixed_calibration(obs, n_start, cfg, cfg.basis, scale_u)  # 3, with the basis given
        clock.lap("calibration")
    elif cfg.materials is not None:
        cal = calibrate(obs, n_start, cfg)  # 3
        n_start = cal.start_normals(n_start)
        clock.lap("calibration")
    return cfg, cal, n_start


def _refinement(obs, n_start, cfg: Settings, basis, scale):
    """Stage 4: the per-pixel refinement; the shared model runs ``refinement_passes`` passes."""
    ref = refine(obs, n_start, cfg, basis, scale)
    if basis is not None:
        iters = ref.iterations
        for _ in range(1, cfg.refinement_passes):  # restart from the refined normals (fresh robust weights, cone search)
            n_prev = ref.normals
            ref.weights = ref.weights.new_empty(0)  # release the (N, L) weights before the next pass allocates its own
            ref = refine(obs, n_prev, cfg, basis, scale)
            iters += ref.iterations
        ref.iterations = iters
        obs.info["refinement_passes"] = float(cfg.refinement_passes)
    return ref


class _StageClock:
    """Wall time of each stage, reported in ``info`` as ``time_<stage>_s``.

    On CUDA each lap waits for the device (one synchronisation per stage), so
    a stage's time is its own and not that of the queued kernels before it.
    """

    def __init__(self, t0: float, device: torch.device):
        self.t = t0
        self.device = device
        self.laps: Dict[str, float] = {}
        self.rss: Dict[str, Optional[float]] = {}

    def lap(self, name: str) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        now = time.perf_counter()
        self.laps[name] = now - self.t
        self.t = now
        self.rss[name] = _peak_rss_mb()

    def info(self):
        out = {f"time_{k}_s": v for k, v in self.laps.items()}
        out.update({f"peak_rss_after_{k}_mb": v for k, v in self.rss.items() if v is not None})
        return out


def _peak_rss_mb() -> Optional[float]:
    """Peak resident set size of the process so far, MB (None where ``resource`` is unavailable)."""
    try:
        import resource
        import sys

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return r / (2**20 if sys.platform == "darwin" else 1024.0)
    except (ImportError, OSError):
        return None


#: A pixel needs this many valid observations for the HSH model; with fewer it
#: keeps the robust Lambertian normal (and gets confidence 0).
MIN_VALID_OBSERVATIONS = 4


def _result(obs, n_init, ref, fit, cal, cfg, t_start) -> HSHResult:
    d, info = obs.data, obs.info
    n_valid = row_sum(obs.weights > 0)
    normals = ref.normals
    bad = (n_valid < MIN_VALID_OBSERVATIONS) | ~torch.isfinite(normals).all(-1) | (normals.norm(dim=-1) < 0.5)
    if bool(bad.any()):
        normals = normals.clone()
        normals[bad] = _fallback_normals(obs, n_init, bad)
    n_bad = int(bad.sum())
    info["fallback_pixels"] = float(n_bad)
    if 2 * n_bad > bad.numel():
        few = int((n_valid < MIN_VALID_OBSERVATIONS).sum())
        failed = n_bad - few
        warn_user(
            f"{n_bad} of {bad.numel()} pixels keep a Lambertian normal and confidence 0 "
            f"(info['fallback_pixels']): {few} have fewer than {MIN_VALID_OBSERVATIONS} valid observations of "
            f"{d.lights.shape[0]} lights" + (f", {failed} a failed fit" if failed else "") + ". Give more lights, "
            "or fewer dark or saturated observations.")
    scale_c = cal.scale if cal is not None else float(fit.residual.median())
    conf = confidence(ref.weights, fit.residual, scale_c, cfg.order, cfg.cauchy_c)
    conf = torch.where(bad, torch.zeros_like(conf), conf)
    # the observations are no longer needed: release the largest buffers before the output maps exist
    # (ref.fit_weights is the observation-weight tensor for the shared model), and build the two large
    # maps one at a time, dropping each flat source as soon as its map exists
    obs.data.y = obs.data.y.new_empty(0)
    obs.data.valid = obs.data.valid.new_empty(0)
    obs.weights = obs.weights.new_empty(0)
    ref.fit_weights = ref.fit_weights.new_empty(0)
    weights_map = scatter_pixels(ref.weights, d.mask)
    ref.weights = ref.weights.new_empty(0)
    s = obs.scale  # the solver ran at unit brightness: coefficients are linear in the images
    # the coefficients are either compact (N, C, K) rows or the map's rows, written in place by stage 5
    coef_rows = fit.coefficients.mul_(s)
    pix = fit.pixels
    albedo = coef_rows.new_empty(normals.shape[0], coef_rows.shape[1])
    for i in range(0, normals.shape[0], ROW_CHUNK):
        rows = coef_rows[i:i + ROW_CHUNK] if pix is None else coef_rows[pix[i:i + ROW_CHUNK]]
        albedo[i:i + ROW_CHUNK] = directional_albedo_view(rows, normals[i:i + ROW_CHUNK, 2])
    if pix is None:
        coef_map = scatter_pixels(coef_rows, d.mask)
    else:
        coef_map = coef_rows.reshape(*d.mask.shape, *coef_rows.shape[1:])
    fit.coefficients = coef_rows = coef_rows.new_empty(0)
    info["lm_iterations"] = float(ref.iterations)
    info["chunks"] = float(ref.chunks)
    info["moved_pixels"] = float(ref.moved)
    if "robust_scale" in info:
        info["robust_scale"] = info["robust_scale"] * s
    return HSHResult(
        normals=scatter_pixels(normals, d.mask),
        coefficients=coef_map,
        albedo=scatter_pixels(albedo, d.mask),
        residual=scatter_pixels(fit.residual * s, d.mask),
        weights=weights_map,
        mask=d.mask,
        order=cfg.order,
        lights=d.lights,
        runtime_s=time.perf_counter() - t_start,
        info=info,
        basis_brdfs=None if cal is None else cal.basis,
        mixing=None if ref.mixing is None else scatter_pixels(ref.mixing.transpose(1, 2) * s, d.mask),
        confidence=scatter_pixels(conf, d.mask),
    )


def _fallback_normals(obs, n_init, bad) -> torch.Tensor:
    """Normals of the pixels the HSH model cannot serve: Lambertian least squares on their valid observations
    where there are at least 3 of them (exactly determined for a Lambertian surface), else the stage-2 start."""
    d = obs.data
    idx = bad.nonzero().squeeze(1)
    y, w = d.y[idx].to(d.dtype), obs.weights[idx].to(d.dtype)
    n_ls, _ = _solve_flat(y, d.lights, w)
    three = (w > 0).sum(-1) >= 3
    return torch.where(three.unsqueeze(-1), n_ls, n_init[idx])
