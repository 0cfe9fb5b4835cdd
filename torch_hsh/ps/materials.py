r"""Stage 3a of the HSH solver (``materials="auto"``): the number of shared basis BRDFs from the data.

Takes the :class:`~torch_hsh.ps.observations.Observations`, the start
normals and the settings; returns a :class:`MaterialsSelection`: the chosen
``M`` in ``1..4`` and the criterion behind it, which :func:`solve_hsh` copies
into ``info``.

Criterion: **cross-validated held-out-light loss** on a pixel subset.

* Subset: the first ``min(calibration_pixels, 256)`` pixels of the
  calibration subset (same seeded permutation as stage 3).
* Folds of lights: the lights sorted by azimuth ``atan2(l_y, l_x)`` and dealt
  into ``F = 3`` folds (rank mod 3), so every fold spans the whole ring of
  lights and the held-out lights are interpolated, not extrapolated. No seed.
* For each ``M``: a shortened stage-3 alternation
  (:func:`~torch_hsh.ps.calibration._calibrate`, 2 rounds of 3 IRLS passes
  and 4 LM iterations, Lambertian start only) on every light gives the subset
  normals; then, for each fold, the basis ``B (M, K)`` and the per-pixel
  mixing weights are refitted (Cauchy IRLS) at those normals without the
  fold's lights, and predict them. The normals have seen the held-out lights
  (two parameters per pixel against ``L x C`` observations); ``B`` and the
  mixing weights, whose number grows with ``M``, have not.
* Loss: the Cauchy loss ``rho(r) = log(1 + (r / (c s))^2)`` of the held-out
  residuals (RMS over the channels), ``c = 2.385``, at one scale ``s`` common
  to every ``M`` (the smallest training scale, floored at the noise level like
  stage 3), averaged over the valid held-out observations. Every light is
  held out exactly once.
* Choice (**one-standard-error rule**, Hastie, Tibshirani & Friedman, *The
  Elements of Statistical Learning*, 7.10): the smallest ``M`` whose
  criterion is at most the best criterion plus one standard error of the
  difference to the best ``M``. The standard error treats the pixels as
  independent samples of the paired per-pixel loss differences.

Why cross-validation and not an information criterion: the model has per-pixel
parameters (normal, ``M x C`` mixing weights) whose number grows with the
image, a robust loss and ridge penalties; AIC / BIC parameter counts are not
defined for that (the effective degrees of freedom of the ridge and the
robust weights are data-dependent), and the number of parameters per pixel
grows with ``M``, the incidental-parameters setting in which BIC is not
consistent. Held-out lights test what a BRDF model is for — predicting other
lights — in the units of the data, and need no parameter count.

Cost: 4 shortened calibrations and 12 refits on at most 256 pixels, then the
one full calibration of the chosen ``M`` (stage 3). Measured with
``research/materials_auto.py`` (400 pixels, 40 lights, 1 thread, 5
scenes x 3 seeds): the selection takes 0.2-0.5 of the time of a whole
``materials=2`` solve, and a whole ``"auto"`` solve 0.75-1.54x (median 1.40)
the CPU time of ``materials=2`` (the upper end when it picks ``M = 4``, whose
calibration is dearer). On larger images the
ratio falls: the selection does not grow with the image (3,000 pixels of
the DiLiGenT cat and harvest, 96 lights: 1.25 and 1.16, the selection itself
0.07 of a ``materials=2`` solve).

What it measures: the number of basis BRDFs needed to *predict unseen
lights* at the basis order. That is the number of materials when the order
represents each material well (an exactly Lambertian texture gives 1).
With lobes that the order truncates, or normals that the short calibration
leaves biased, more basis BRDFs predict better although there is one physical
material (a Blinn-Phong material of shininess 8 with a textured albedo picks
4), and a better prediction is not always a better normal: the single-view
elevation ambiguity is invisible to held-out lights. On the bunny the
criterion is nearly flat in ``M`` and the choice follows the subset seed; on
the DiLiGenT cat and harvest it falls steadily with ``M`` (auto takes 4) while
harvest's normals are best at ``M = 2`` (docs/photometric_stereo.md). That is
why ``"auto"`` is not the default.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Tuple

import torch

from .calibration import _CAL_LM_ITERS, _calibrate, _calibration_subset, _fit_basis_brdfs, _initial_mixing
from .design import _design_factors
from .lambertian import _solve_flat, trimmed_weights
from .observations import Observations
from .optim import _ridge_diag, cauchy_rho, cauchy_weights, irls_weights, observation_residual, solve_weights
from .settings import Settings

__all__ = ["MaterialsSelection", "select_materials", "light_folds", "AUTO_CANDIDATES"]

#: Numbers of basis BRDFs that ``materials="auto"`` chooses from.
AUTO_CANDIDATES = (1, 2, 3, 4)
_SELECT_PIXELS = 256  # at most this many pixels of the calibration subset
_SELECT_FOLDS = 3  # folds of lights
_SELECT_ROUNDS = 2  # calibration rounds per M (stage 3 default: 8)
_SELECT_IRLS = 2  # IRLS passes (+1) per round (stage 3: 5)
_FOLD_PASSES = 2  # IRLS passes of the refit without a fold of lights
_MIN_LIGHTS = 6  # fewer lights: auto is refused (2 training lights per held-out one)


@dataclass
class MaterialsSelection:
    """Result of :func:`select_materials`.

    Attributes:
        chosen: the selected number of basis BRDFs.
        candidates: the ``M`` values tried.
        criterion: mean held-out Cauchy loss per valid observation, one per candidate.
        std_error: standard error of ``criterion[i] - criterion[best]`` (0 for the best).
        scale: the common Cauchy scale (units of the normalised observations).
        folds: number of light folds.
        pixels: number of subset pixels.
    """

    chosen: int
    candidates: Tuple[int, ...]
    criterion: List[float]
    std_error: List[float]
    scale: float
    folds: int
    pixels: int

    def info(self) -> dict:
        """The entries :func:`solve_hsh` writes into ``info``."""
        return {
            "materials_chosen": float(self.chosen),
            "materials_candidates": [float(m) for m in self.candidates],
            "materials_criterion": list(self.criterion),
            "materials_criterion_se": list(self.std_error),
            "materials_criterion_scale": float(self.scale),
            "materials_folds": float(self.folds),
            "materials_selection_pixels": float(self.pixels),
        }


def light_folds(lights: torch.Tensor, folds: int = _SELECT_FOLDS) -> torch.Tensor:
    """Fold index ``(L,)`` of each light: lights sorted by azimuth ``atan2(l_y, l_x)``, dealt round-robin.

    Example:
        >>> import torch
        >>> az = torch.tensor([0.5, -2.0, 3.0, 1.5, -1.0, 0.0, 2.5])
        >>> l = torch.stack([torch.cos(az), torch.sin(az), torch.ones(7)], -1)
        >>> light_folds(l, 3).tolist()  # azimuth ranks 3, 0, 6, 4, 1, 2, 5, mod 3
        [0, 0, 0, 1, 1, 2, 2]
    """
    az = torch.atan2(lights[:, 1], lights[:, 0])
    order = torch.argsort(az.cpu(), stable=True)
    f = torch.empty(lights.shape[0], dtype=torch.long)
    f[order] = torch.arange(lights.shape[0]) % folds
    return f.to(lights.device)


def one_standard_error_choice(totals: torch.Tensor, count: float) -> Tuple[int, List[float], List[float]]:
    """Apply the one-standard-error rule to per-pixel loss totals ``(n_candidates, p)``.

    ``count`` is the number of valid held-out observations. Returns the index of
    the chosen candidate (the first, i.e. smallest, within one standard error of
    the best), the criteria ``totals.sum(1) / count`` and the standard errors of
    the paired differences to the best.

    Example:
        >>> import torch
        >>> t = torch.tensor([[3.0, 3.0, 3.0, 3.0], [1.0, 1.1, 0.9, 1.0], [1.0, 1.0, 1.0, 0.95]])
        >>> one_standard_error_choice(t, 4.0)[0]
        1
    """
    crit = totals.sum(1) / count
    best = int(torch.argmin(crit))
    p = totals.shape[1]
    diff = totals - totals[best]
    se = diff.std(dim=1, unbiased=True) * math.sqrt(p) / count if p > 1 else torch.zeros_like(crit)
    se[best] = 0.0
    ok = crit <= crit[best] + se
    chosen = int(ok.nonzero()[0])
    return chosen, [float(v) for v in crit], [float(v) for v in se]


def _fold_residuals(yS, w0S, w_start, Phi, W, order, held, scale, c, passes, basis_ridge):
    """Refit ``B`` and the mixing weights without the lights ``held`` at fixed normals; residuals ``(p, L)``.

    ``Phi (p, L, K)`` design at the normals, ``W (p, C, M)`` start mixing weights,
    ``w_start (p, L)`` start robust weights (those of the fit on every light).
    ``passes`` Cauchy-IRLS passes of (basis fit, closed-form mixing weights,
    robust weights), as in a calibration round.
    """
    w_tr = w0S.clone()
    w_tr[:, held] = 0
    w = w_start.clone()
    w[:, held] = 0
    yT = yS.transpose(1, 2).contiguous()
    for _ in range(passes):
        B = _fit_basis_brdfs(Phi, w, yS, W, order, basis_ridge)
        Psi = (Phi @ B.T).transpose(1, 2).contiguous()  # (p, M, L)
        Wt, _, _ = solve_weights(Psi, w, yT, _ridge_diag(Psi, w_tr, 1e-4))
        W = Wt.transpose(1, 2)
        res = observation_residual(Psi, Wt, yT)
        w = cauchy_weights(res, w_tr, scale, c)
    return res


def select_materials(obs: Observations, n_start: torch.Tensor, cfg: Settings,
                     candidates: Tuple[int, ...] = AUTO_CANDIDATES) -> MaterialsSelection:
    """Choose the number of shared basis BRDFs by held-out-light cross-validation (see the module docstring).

    ``n_start (N, 3)`` are the stage-2 normals. Runs in the work dtype of the
    settings; writes nothing into ``obs.info`` (the caller copies
    :meth:`MaterialsSelection.info`).

    Raises:
        ValueError: fewer than 6 lights (too few to hold lights out).
    """
    d, w0 = obs.data, obs.weights
    L = d.lights.shape[0]
    if L < _MIN_LIGHTS:
        raise ValueError(f"`materials='auto'` needs at least {_MIN_LIGHTS} lights to hold some out, got {L}; "
                         "pass an integer `materials`")
    wdt = cfg.work(d.dtype)
    # the same seeded permutation as the calibration subset: its first pixels
    S = _calibration_subset(w0, min(cfg.calibration_pixels, _SELECT_PIXELS), cfg.seed)
    yS, w0S = d.y[S].to(wdt), w0[S].to(wdt)
    lights = d.lights.to(wdt)
    nS = n_start[S].to(wdt)
    fold = light_folds(d.lights, _SELECT_FOLDS)
    rounds = max(1, min(cfg.calibration_rounds, _SELECT_ROUNDS))
    _, alb = _solve_flat(yS, lights, trimmed_weights(yS, 0.25, 0.10))
    res_all, scales = [], []
    yT = yS.transpose(1, 2).contiguous()
    with torch.no_grad():
        for M in candidates:
            # the normals (and a start for B, W) from a shortened calibration on every light ...
            W0 = _initial_mixing(alb, M, cfg.seed).to(wdt)
            B, scale_M, n = _calibrate(yS, w0S, nS, lights, cfg.order, W0, rounds, _SELECT_IRLS, _CAL_LM_ITERS,
                                       cfg.cauchy_c, cfg.basis_ridge)
            n = torch.nn.functional.normalize(n, dim=-1)
            X, T = _design_factors(n, lights, cfg.order)
            Phi = X @ T
            Psi = (Phi @ B.T).transpose(1, 2).contiguous()
            w, _ = irls_weights(Psi, yT, w0S.clone(), w0S, scale_M, cfg.cauchy_c, 2)
            Wt, _, _ = solve_weights(Psi, w, yT, _ridge_diag(Psi, w0S, 1e-4))
            # ... then B and the mixing weights refitted without each fold of lights, which they predict
            res_M = torch.zeros_like(w0S)
            for f in range(_SELECT_FOLDS):
                held = (fold == f).nonzero().squeeze(1)
                if held.numel() == 0:
                    continue
                r = _fold_residuals(yS, w0S, w, Phi, Wt.transpose(1, 2), cfg.order, held, scale_M,
                                    cfg.cauchy_c, _FOLD_PASSES, cfg.basis_ridge)
                res_M[:, held] = r[:, held]
            scales.append(scale_M)
            res_all.append(res_M)
        floor = max(3.0 * obs.sigma_y, 1e-4 * obs.typical, 1e-12)
        scale = max(min(scales), floor)
        w = w0S.double()
        totals = torch.stack([(w * cauchy_rho(r.double(), scale, cfg.cauchy_c)).sum(-1) for r in res_all])
        count = float(w.sum().clamp(min=1.0))
        i, crit, se = one_standard_error_choice(totals, count)
    return MaterialsSelection(
        chosen=int(candidates[i]), candidates=tuple(candidates), criterion=crit, std_error=se, scale=scale,
        folds=_SELECT_FOLDS, pixels=int(S.numel()),
    )
