"""The options of the HSH solver, each defined once: :class:`Settings` (see :func:`~torch_hsh.ps.solve_hsh`).

Every field of :class:`Settings` holds its default, its check, its doc and (for
the few the command line exposes) its ``torch-hsh ps`` flag, in the field's
metadata; :class:`Settings` checks itself from that metadata when built, the
stages read it, and :func:`~torch_hsh.ps.solve_hsh` and the CLI build their
option lists from it. A new option is one field here plus the stage that reads it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
import math
import numbers
from typing import Optional, Tuple, Union

import torch

from .._checks import check_order, check_shape

__all__ = ["Settings", "option_docs", "DEFAULT_ORDER", "DEFAULT_MATERIALS", "DEFAULT_BASIS_RIDGE", "CAUCHY_C", "AUTO"]

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

#: Outer rounds of the whole-surface stage (:mod:`torch_hsh.ps.whole_surface`) when it is switched on.
SURFACE_ROUNDS = 2
#: L-BFGS iterations of the depth per round of that stage.
SURFACE_ITERATIONS = 10
#: Re-weighting iterations of the bilateral integration that turns a solve's normals into a depth map
#: for the stages after the solve (the whole-surface stage's start, the interreflection loop's surface).
#: On the cat 10 take 1.7 s where the integrator's own default (100, or an energy change below 1e-4)
#: takes 9.9 s; the loop's result moved by 0.003 deg (docs/photometric_stereo.md).
DEPTH_START_ITERATIONS = 10

#: Cauchy constant of every robust reweighting (95 % efficiency at Gaussian noise).
CAUCHY_C = 2.385


def _option(default, doc: str, check=None, cli=None, compare: bool = True, internal: bool = False):
    """One field of :class:`Settings`: its default, its doc, its check and its ``torch-hsh ps`` flag.

    ``check(value, settings) -> value`` raises ``ValueError`` naming the option (``settings``: the
    fields before this one already checked, the later ones as given); it returns the value to keep.
    ``cli``: ``flag``, ``help`` and ``type`` (``("int", lo, hi)``, ``("float", lo, hi, lo_open)``,
    ``("materials",)``) or ``const`` (a switch that sets the option to that value).
    ``internal``: set by the pipeline, not an option of :func:`~torch_hsh.ps.solve_hsh`.
    """
    return field(default=default, compare=compare,
                 metadata={"doc": doc, "check": check, "cli": cli, "internal": internal})


def _check_refinement_passes(v, s):
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or not 1 <= v <= 5:
        raise ValueError(f"`refinement_passes` must be an integer in [1, 5], got {v!r}")
    return int(v)


def _check_ridge(v, s):
    if not v > 0:
        raise ValueError(f"`ridge` must be > 0 (it keeps the rank-deficient normal equations solvable), got {v}")
    return v


def _check_max_iter(v, s):
    if v is not None and (isinstance(v, bool) or int(v) != v or v < 0):
        raise ValueError(f"`max_iter` must be an integer >= 0, got {v!r}")
    return None if v is None else int(v)


def _check_calibration_pixels(v, s):
    if int(v) < 1:
        raise ValueError(f"`calibration_pixels` must be >= 1, got {v}")
    return int(v)


def _check_calibration_rounds(v, s):
    if int(v) < 0:
        raise ValueError(f"`calibration_rounds` must be >= 0, got {v}")
    return int(v)


def _check_calibration_starts(v, s):
    if isinstance(v, str) or any(s_ not in CALIBRATION_STARTS for s_ in v):
        raise ValueError(f"`calibration_starts` must be a sequence of 'lambertian' / 'independent' / 'flattened', "
                         f"got {v!r}")
    return tuple(v)


def check_dark_fraction(v, s=None):
    """``dark_fraction``: a number in ``[0, 1)``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v < 1.0:
        raise ValueError(f"`dark_fraction` must be a number in [0, 1), got {v!r}")
    return v


def _level(name: str, bound: str):
    """A check: ``None`` (estimated from the data) or a finite number ``>= 0`` / ``> 0`` (``bound``)."""

    def check(v, s=None):
        if v is None:
            return v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"`{name}` must be None (estimated) or a finite number, got {v!r}")
        if (bound == ">= 0" and v < 0) or (bound == "> 0" and v <= 0):
            raise ValueError(f"`{name}` must be {bound}, got {v!r}")
        return v

    return check


check_noise_sigma = _level("noise_sigma", ">= 0")
check_saturation = _level("saturation", "> 0")


def _check_chunk_size(v, s):
    if v is not None and (isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1):
        raise ValueError(f"`chunk_size` must be an integer >= 1 or None (chosen per device), got {v!r}")
    return None if v is None else int(v)


def _check_work_dtype(v, s):
    if v is not None and v not in (torch.float32, torch.float64):
        raise ValueError(f"`work_dtype` must be torch.float32, torch.float64 or None, got {v!r}")
    return v


def _check_cast_shadows(v, s):
    if isinstance(v, bool) or int(v) != v or v < 0:
        raise ValueError(f"`cast_shadows` must be an integer >= 0 (rounds of the shadow loop), got {v!r}")
    return v


def _check_interreflections(v, s):
    if v is None:  # resolved in Settings.__post_init__, once refine_surface is known
        return None
    if isinstance(v, bool) or int(v) != v or v < 0:
        raise ValueError(f"`interreflections` must be an integer >= 0 (rounds of the loop), got {v!r}")
    return int(v)


#: Largest radius of the interreflection disc (``one_bounce``'s work grows as its square).
MAX_INTERREFLECTION_RADIUS = 64


def _check_interreflection_radius(v, s):
    if isinstance(v, bool) or int(v) != v or not 2 <= v <= MAX_INTERREFLECTION_RADIUS:
        raise ValueError(f"`interreflection_radius` must be an integer in [2, {MAX_INTERREFLECTION_RADIUS}] "
                         f"(pixels), got {v!r}")
    return int(v)


def _check_refine_surface(v, s):
    if v is True:
        return SURFACE_ROUNDS
    if v is False or v is None:
        return 0
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"`refine_surface` must be a bool or an integer >= 0 (rounds of the stage), got {v!r}")
    return v


def _check_surface_iterations(v, s):
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"`surface_iterations` must be an integer >= 1, got {v!r}")
    return v


def _check_surface_holdout(v, s):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 0.5:
        raise ValueError(f"`surface_holdout` must be a fraction of the lights in (0, 0.5), got {v!r}")
    return float(v)


def _check_shadow_bias(v, s):
    if not (isinstance(v, (int, float)) and v >= 0):
        raise ValueError(f"`shadow_bias` must be a number >= 0 (pixels), got {v!r}")
    return v


def _check_materials(materials, s=None):
    """``materials``: an integer in [1, 8], ``"auto"`` or ``None``; anything else is a ValueError naming it.

    With ``basis`` given, the basis decides (see :func:`_check_basis`).
    """
    if s is not None and s.basis is not None:
        return materials
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


def _check_basis(basis, s):
    """``basis``: ``(M, K)`` finite rows for the ``order``; it fixes the shared model (``materials`` not None/"auto")."""
    if basis is None:
        return basis
    from ..kernel import num_isotropic

    K = num_isotropic(s.order)
    M = check_shape(basis, "basis", ("M", K))["M"]  # K for the order
    if not 1 <= M <= 8:
        raise ValueError(f"`basis` must have M in 1..8 rows (basis BRDFs), got {M}")
    if not basis.is_floating_point() or not bool(torch.isfinite(basis).all()) or bool((basis.norm(dim=-1) == 0).any()):
        raise ValueError("`basis` must hold finite floating-point values and no zero row")
    if s.materials is None or isinstance(s.materials, str):
        raise ValueError(f"`basis` fixes the shared model with M = {M} basis BRDFs; `materials` must not be "
                         f"None or 'auto' with it, got {s.materials!r}")
    return basis


def _check_robust_scale(v, s):
    if v is None:
        return v
    if s.basis is None:
        raise ValueError("`robust_scale` is only used together with `basis`")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"`robust_scale` must be a finite number > 0 (image units), got {v!r}")
    return v


def _check_basis_ridge(v, s):
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or not 0 < float(v) <= 1:
        raise ValueError(f"`basis_ridge` must be a number in (0, 1] (relative to the mean diagonal of the "
                         f"basis BRDFs' normal equations), got {v!r}")
    return float(v)


@dataclass(frozen=True)
class Settings:
    """Every option of :func:`~torch_hsh.ps.solve_hsh`, checked when built.

    ``Settings(**options)`` raises ``ValueError`` (naming the option) for a
    bad value and ``TypeError`` for an unknown name. Use it to run several
    solves with the same options (``solve_hsh(..., settings=s)``) or to
    change one (``dataclasses.replace(s, order=4)``, checked again).

    Options (the same list as :func:`~torch_hsh.ps.solve_hsh`; the defaults are those of the fields):

    {options}
    """

    order: int = _option(DEFAULT_ORDER, "basis order ``P`` (default 3: ``K = 20`` coefficients per channel).",
                         lambda v, s: check_order(v),
                         cli={"flag": "--order", "type": ("int", 0, 12),
                              "help": f"HSH order (default {DEFAULT_ORDER}, torch_hsh.ps.DEFAULT_ORDER)"})
    materials: Union[int, str, None] = _option(
        DEFAULT_MATERIALS,
        """number ``M`` of shared basis BRDFs (1..8), ``"auto"`` to
        choose ``M`` in 1..4 from the data, or ``None`` for independent
        per-pixel BRDFs. ``"auto"`` (:mod:`torch_hsh.ps.materials`)
        cross-validates held-out lights on up to 256 pixels of the
        calibration subset: for each ``M``, a short calibration on every
        light fixes the subset normals, then the basis BRDFs and mixing
        weights are refitted without each of 3 folds of lights (interleaved
        in azimuth) and predict them; the criterion is the mean Cauchy loss
        ``log(1 + (r / (c s))^2)`` of the held-out residuals at one scale
        ``s`` for every ``M``. It keeps the smallest ``M`` within one
        standard error (over pixels) of the best (the one-standard-error
        rule), then calibrates that ``M`` as usual. ``info`` gets
        ``materials_chosen``, ``materials_criterion`` (one value per
        ``M = 1..4``, lower is better), ``materials_criterion_se``,
        ``materials_criterion_scale`` and ``time_materials_s``. It counts
        the basis BRDFs needed to predict other lights at this ``order``:
        more than the physical materials when the order truncates their
        lobes. Needs at least 6 lights.""",
        _check_materials,
        cli={"flag": "--materials", "type": ("materials",),
             "help": f"shared basis BRDFs of the HSH solver, 1-8 or auto (default {DEFAULT_MATERIALS}, "
                     "torch_hsh.ps.DEFAULT_MATERIALS; 0: independent BRDF per pixel)"})
    init: Optional[torch.Tensor] = _option(
        None, "optional ``(*S, 3)`` starting normals (default: robust Lambertian).", compare=False)
    ridge: float = _option(0.1, """relative ridge strength ``lambda`` on the per-pixel coefficients
        (independent model) or on the per-pixel residual ``delta``
        (shared model); see the module docstring.""", _check_ridge)
    search_angles: Tuple[float, ...] = _option(
        (8.0, 16.0), "cone angles in degrees of the coarse candidate search (empty: no search).",
        lambda v, s: tuple(v))
    search_azimuths: int = _option(6, "candidates per cone angle.")
    max_iter: Optional[int] = _option(None, """Levenberg–Marquardt iterations per stage (independent model,
        default 15) or IRLS-LM iterations of the per-pixel pass (shared
        model, default 16 per pass; a pixel stops earlier once its normal is still).""", _check_max_iter)
    robust: bool = _option(True, "independent model only: run Cauchy IRLS stages (``robust_iters`` of them).")
    robust_iters: int = _option(2, "independent model only: number of reweighting stages.")
    calibration_pixels: int = _option(2048, "shared model: size of the pixel subset used to fit ``B``.",
                                      _check_calibration_pixels)
    calibration_rounds: int = _option(8, "shared model: alternation rounds on that subset.",
                                      _check_calibration_rounds)
    calibration_starts: Tuple[str, ...] = _option(
        ("lambertian", "independent"),
        """shared model: starts of the calibration, any of
        ``"lambertian"`` (robust Lambertian normals, always used),
        ``"independent"`` (normals of the independent model on the subset)
        and ``"flattened"`` (opt-in: two more starts, the Lambertian normals
        with their slopes scaled by 0.6 and 0.8, against the steepening
        that specular reflection gives a Lambertian fit; about +25 % time,
        see ``docs/photometric_stereo.md`` for when it helps); the
        calibration with the smallest Cauchy loss of the subset residuals
        at a common scale is kept (``info["calibration_start"]``: its
        index in that order).""",
        _check_calibration_starts,
        cli={"flag": "--flattened-starts", "const": ("lambertian", "independent", "flattened"),
             "help": "two more calibration starts with flattened Lambertian normals (opt-in, about +25%% time; "
                     "helps objects whose highlights steepen a Lambertian fit)"})
    dark_fraction: float = _option(0.05, "dark threshold, see :func:`~torch_hsh.ps.observation_weights`.",
                                   check_dark_fraction)
    noise_sigma: Optional[float] = _option(
        None, "raw noise level (``None``: estimated), see :func:`~torch_hsh.ps.observation_weights`.",
        check_noise_sigma)
    saturation: Optional[float] = _option(
        None, "raw saturation level (``None``: detected), see :func:`~torch_hsh.ps.observation_weights`.",
        check_saturation)
    nonneg: bool = _option(True, "apply the non-negativity safeguard to the final coefficients.")
    chunk_size: Optional[int] = _option(None, """pixels per chunk of the per-pixel passes (bounded memory).
        ``None`` (default): 8192 on the CPU; on a GPU, where fewer and
        larger batches are faster, the largest that keeps a batch within a
        quarter of the free device memory (8192 to 262144, see
        :func:`~torch_hsh.ps.settings.resolve_chunk`), halved and retried
        if a batch still runs out of device memory. The results do not
        depend on it; ``info["chunk_size"]`` reports the one used.""", _check_chunk_size)
    dtype: Optional[torch.dtype] = _option(torch.float64, """dtype of the outputs and of the coefficient fits (default
        float64; ``None``: the images' dtype).""")
    work_dtype: Optional[torch.dtype] = _option(torch.float32, """shared model: dtype of the per-pixel normal
        iterations (default float32, about 3x faster than float64 with the same
        accuracy; ``None``: ``dtype``).""", _check_work_dtype)
    seed: int = _option(0, "seed of the calibration subset.")
    progress: bool = _option(False, """show tqdm progress bars (the robust Lambertian start normals, the
        calibration starts, the refinement's and the coefficient fit's chunks of pixels).""")
    valid: Optional[torch.Tensor] = _option(None, """optional ``(L, H, W)`` / ``(L, N)`` bool: False excludes an
        observation (for example one known to be in a cast shadow). Non-finite
        and negative observations are always excluded; an excluded
        observation never influences another pixel.""", compare=False)
    cast_shadows: int = _option(0, """rounds of the cast-shadow loop (default 0: off): integrate
        the normals, march the lights over the depth, mark the occluded
        observations invalid, solve again (see :mod:`torch_hsh.ps.shadows`;
        needs ``(L, H, W, C)`` images).""", _check_cast_shadows,
        cli={"flag": "--cast-shadows", "type": ("int", 0, 5),
             "help": "rounds of the cast-shadow loop of the HSH solver (default 0: off; see torch_hsh.ps.shadows)"})
    interreflections: Optional[int] = _option(None, """rounds of one-bounce interreflection removal: the
        solve's surface gives every pixel the light its neighbours within
        ``interreflection_radius`` pixels send it, once reflected; that is
        subtracted from the images and the per-pixel stages run again with
        the solve's calibration; a round is kept only where the fit improves
        (``interreflection_safeguard``; see
        :mod:`torch_hsh.ps.interreflections`; needs ``(L, H, W, C)`` images).
        Default ``None``: one round when the whole-surface stage runs
        (``refine_surface``), which then starts from its result; none
        otherwise. ``0`` switches it off.""", _check_interreflections,
        cli={"flag": "--interreflections", "type": ("int", 0, 3),
             "help": "rounds of one-bounce interreflection removal, each followed by the per-pixel stages with the "
                     "first solve's calibration and kept only if the fit's mean confidence does not fall (default: 1 "
                     "with --refine-surface, else 0; see torch_hsh.ps.interreflections)"})
    interreflection_radius: int = _option(16, "pixels: the disc of neighbours that light a pixel in that loop.",
                                          _check_interreflection_radius)
    interreflection_safeguard: bool = _option(True, """a round of that loop is kept only if the mean confidence of
        its solve (the robust weights and fit residuals, at the first
        solve's scale) does not fall (default); ``False`` keeps every round
        (for evaluations; ``info["interreflection_accepted"]`` still says
        what the safeguard would have done).""")
    shadow_bias: float = _option(0.25, """height in pixels an occluder must rise above a light ray
        to cast a shadow in that loop (depth-noise margin).""", _check_shadow_bias)
    refine_surface: int = _option(0, """rounds of the whole-surface stage after the solve (default 0: off;
        ``True``: :data:`SURFACE_ROUNDS`): one depth map whose normals, the
        shared BRDFs and the shadows it casts explain the images, then every
        normal re-estimated per pixel from it (``surface_polish``), accepted
        only if it lowers the error of held-out lights (see
        :mod:`torch_hsh.ps.whole_surface`; shared model, ``(L, H, W, C)`` images).""", _check_refine_surface,
        cli={"flag": "--refine-surface", "const": SURFACE_ROUNDS,
             "help": "run the whole-surface stage after the per-pixel solve (one depth map, shared BRDFs, cast "
                     "shadows; kept only if it lowers the held-out-light error; see torch_hsh.ps.whole_surface)"})
    surface_iterations: int = _option(SURFACE_ITERATIONS, "L-BFGS iterations of the depth per round of that stage.",
                                      _check_surface_iterations)
    surface_shadows: bool = _option(True, "that stage re-computes the cast shadows from its depth every round.")
    surface_polish: bool = _option(True, """that stage ends with the solver's per-pixel stage started from the
        depth's normals (every light, the depth's cast shadows): the returned
        normals are those, not the depth's own (``False``: the depth's).""")
    surface_holdout: float = _option(0.1, """fraction of the lights that stage holds out of its fits to
        decide whether the refined surface is kept.""", _check_surface_holdout)
    surface_safeguard: bool = _option(True, """that stage returns its start when the held-out error rises
        (default); ``False`` returns the refined surface either way (for
        evaluations against ground truth; ``info["surface_accepted"]`` still
        says what the safeguard would have done).""")
    basis: Optional[torch.Tensor] = _option(None, """optional ``(M, K)`` basis BRDFs of the shared model to use as
        they are, for example ``basis_brdfs`` of an earlier result on the
        same object (``K`` must match ``order``): the calibration (stage 3)
        is skipped and the number of materials is ``M`` (an integer
        ``materials`` is overridden; ``None`` and ``"auto"`` are errors).
        The cast-shadow loop uses it to keep the first solve's basis.""", _check_basis, compare=False)
    robust_scale: Optional[float] = _option(None, """with ``basis``: the robust residual scale in image units
        (``info["robust_scale"]`` of that earlier result); ``None``
        estimates it from the calibration subset at the start normals.""", _check_robust_scale)
    refinement_passes: int = _option(2, """shared model: passes of the per-pixel refinement
        (stage 4). Every pass after the first restarts from the previous
        pass's normals, with fresh robust weights and a new cone search
        around them (default 2; measured gains of 0.01–0.7 deg on every
        scene of ``docs/photometric_stereo.md``, for about 30–60 % more time;
        ``refinement_passes=1, max_iter=8`` is the single pass of earlier versions). Ignored by the
        independent model.""", _check_refinement_passes)
    basis_ridge: float = _option(DEFAULT_BASIS_RIDGE, """shared model: relative ridge on the basis BRDFs ``B``
        (``basis_ridge`` x the mean diagonal of their normal equations, times
        the order profile ``p(p+1)/2 + r(r+1)/2``: a smoothness penalty).
        It conditions the calibration: the normals' elevations and the
        basis BRDFs trade off along a nearly flat valley of the loss, and
        the ridge picks the point on it. Raising it from 1e-3 to 3e-3
        stopped the calibration flipping between basins with the subset
        (``seed``) on every scene measured; every larger value smooths the
        lobes more (less accurate on sharp specular objects), and beyond
        3e-3 the seed spread no longer falls steadily. Default ``3e-3`` (:data:`DEFAULT_BASIS_RIDGE`;
        ``1e-3`` before 2026-11-29); the measured trade-off is
        in ``docs/photometric_stereo.md``. ``info["basis_ridge"]`` records it.""", _check_basis_ridge,
        cli={"flag": "--basis-ridge", "type": ("float", 0.0, 1.0, True),
             "help": "relative ridge on the shared basis BRDFs (default torch_hsh.ps.DEFAULT_BASIS_RIDGE, 3e-3); "
                     "1e-3 fits sharp specular lobes better but lets the result depend on the calibration seed"})
    cauchy_c: float = _option(CAUCHY_C, "Cauchy constant of every robust reweighting.", internal=True)
    chunk_auto: bool = _option(False, "True when ``chunk_size`` was chosen by :func:`resolve_chunk` (it may then "
                                      "shrink on out-of-memory).", internal=True)

    def __post_init__(self):
        for f in fields(self):  # in field order: a check sees the earlier fields checked
            check = f.metadata["check"]
            if check is not None:
                object.__setattr__(self, f.name, check(getattr(self, f.name), self))
        if self.basis is not None:  # the basis fixes the number of materials
            object.__setattr__(self, "materials", int(self.basis.shape[0]))
        if self.interreflections is None:  # one safeguarded round before the whole-surface stage
            object.__setattr__(self, "interreflections", 1 if self.refine_surface else 0)

    @property
    def iterations(self) -> int:
        """``max_iter``, or its default for the model: 15 (independent) or 16 (shared)."""
        if self.max_iter is None:
            return 15 if self.materials is None else 16
        return self.max_iter

    def work(self, dtype: torch.dtype) -> torch.dtype:
        """The dtype of the per-pixel normal iterations for data in ``dtype``: ``work_dtype``, or ``dtype``."""
        return dtype if self.work_dtype is None else self.work_dtype

    def chunked(self, y: torch.Tensor, dtype: torch.dtype) -> "Settings":
        """These settings with ``chunk_size`` resolved for the observations ``y (N, L, C)`` computed in ``dtype``
        (:func:`resolve_chunk`; ``chunk_auto`` records whether it was chosen here)."""
        from ..kernel import num_isotropic

        chunk = resolve_chunk(self.chunk_size, y.device, y.shape[1], num_isotropic(self.order), self.materials is None,
                              torch.empty(0, dtype=self.work(dtype)).element_size(),
                              torch.empty(0, dtype=dtype).element_size())
        return replace(self, chunk_size=chunk, chunk_auto=self.chunk_size is None)

    @property
    def chunk(self) -> int:
        """Pixels per chunk; ``solve_hsh`` resolves ``chunk_size=None`` per device (:func:`resolve_chunk`) first."""
        if self.chunk_size is None:
            raise RuntimeError("chunk_size=None must be resolved with resolve_chunk() before the per-pixel stages")
        return self.chunk_size


def option_docs(indent: str = "    ") -> str:
    """The options of :class:`Settings` as a reST bullet list (for docstrings), one item per field."""
    out = []
    for f in fields(Settings):
        if f.metadata["internal"]:
            continue
        lines = [ln.strip() for ln in f.metadata["doc"].splitlines()]
        out.append(f"* ``{f.name}``: " + f"\n{indent}  ".join(lines))
    return f"\n{indent}".join(out)


if Settings.__doc__:  # None under python -OO
    Settings.__doc__ = Settings.__doc__.replace("{options}", option_docs())


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
