"""Stage 3 of the HSH solver (shared model): calibration of the shared basis BRDFs.

Takes the :class:`~torch_hsh.ps.observations.Observations` and the start
normals; returns a :class:`Calibration`: ``M`` unit-norm basis BRDFs ``B (M,
K)`` (isotropic Helmholtz coefficients), the robust residual scale, the
pixel subset used and its calibrated normals.

Method: on a seeded random subset of pixels, alternate Cauchy-IRLS fits of the
basis and the per-pixel mixing weights with variable-projection LM on the
normals (:func:`_calibrate`), from the robust Lambertian normals and
optionally from the independent model's normals on the subset; keep the
calibration with the smallest Cauchy loss at a common scale.
"""
from __future__ import annotations

import math

from dataclasses import dataclass
from typing import Optional

import torch

from .design import MixedDesign, _design_factors, ridge_profile
from .lambertian import _solve_flat, trimmed_weights
from .optim import (
    _ridge_diag,
    cauchy_rho,
    cauchy_weights,
    fd_step,
    irls_weights,
    lm_normals,
    observation_residual,
    solve_weights,
)
from .observations import Observations
from .refinement import refine_independent_chunk
from .settings import DEFAULT_BASIS_RIDGE, Settings

__all__ = ["Calibration", "calibrate", "fixed_calibration", "CALIBRATION_INFO", "reuse_calibration",
           "report_first_calibration"]

#: Prefixes of the ``info`` keys that describe the calibration (stages 3a and 3) of a solve.
CALIBRATION_INFO = ("calibration_", "materials", "basis_ridge")

def reuse_calibration(res) -> dict:
    """Options that make a re-solve keep the calibration of the solve ``res`` (an ``HSHResult``): its basis BRDFs,
    robust scale and number of materials (shared model; ``materials="auto"`` was resolved by that solve).
    Empty for the independent model. The loops around the stages (cast shadows, interreflections) change a
    few observations, not the object's materials, and a fresh calibration from other start normals would
    move the basis more than they do (docs/photometric_stereo.md)."""
    if getattr(res, "basis_brdfs", None) is None:
        return {}
    return dict(basis=res.basis_brdfs, robust_scale=float(res.info["robust_scale"]),
                materials=int(res.basis_brdfs.shape[0]))


def report_first_calibration(res, first_info: dict) -> None:
    """After re-solves that reused a calibration (:func:`reuse_calibration`): report the calibration of the first
    solve (``first_info``, its ``info``) in ``res.info``, not "basis given"."""
    for k, v in first_info.items():
        if k.startswith(CALIBRATION_INFO):
            res.info[k] = v
    res.info.pop("basis_given", None)


# Iteration budgets of the shared model (fixed, not set per dataset; see
# docs/photometric_stereo.md for how much the results depend on them).
_INDEPENDENT_START_ITERS = 8  # LM iterations of the independent-model start on the subset
_CAL_IRLS = 5  # IRLS passes (+1) per calibration round
_CAL_LM_ITERS = 4  # LM iterations of the subset normals per calibration round
_SCALE_ROUNDS = 3  # calibration rounds that re-estimate the robust scale; later rounds keep it (MM-style)
#: Slope factors of the ``"flattened"`` calibration starts: the robust Lambertian normals with
#: their (x, y) scaled by these and renormalised. Specular reflection biases a Lambertian fit
#: toward steeper normals (about +10 deg of elevation on a Blinn-Phong height field), and the
#: alternation keeps the basin it starts in; two flatter starts let the loss look along that bias.
FLATTEN_FACTORS = (0.6, 0.8)


def _initial_mixing(albedo: torch.Tensor, M: int, seed: int) -> torch.Tensor:
    """Start mixing weights ``(p, C, M)``: per-channel albedo, its grey level, then seeded positive perturbations."""
    cols = [albedo]
    if M >= 2:
        cols.append(albedo.mean(-1, keepdim=True).expand_as(albedo))
    g = torch.Generator().manual_seed(int(seed))
    for _ in range(2, M):
        f = 0.5 + torch.rand(albedo.shape[0], 1, generator=g, dtype=torch.float64).to(albedo)
        cols.append(albedo * f)
    return torch.stack(cols, dim=-1)


def _unit_rows(B: torch.Tensor) -> torch.Tensor:
    """``B`` with every non-zero row scaled to unit norm."""
    nb = B.norm(dim=-1, keepdim=True)
    return B / torch.where(nb > 0, nb, torch.ones_like(nb))


def _calibration_subset(w0: torch.Tensor, n_pixels: int, seed: int) -> torch.Tensor:
    """Seeded random subset of at most ``n_pixels`` pixels with at least 3 valid observations (any pixel if none has)."""
    dev = w0.device
    usable = (w0.sum(-1) >= 3).nonzero().squeeze(1)
    if usable.numel() == 0:
        usable = torch.arange(w0.shape[0], device=dev)
    g = torch.Generator().manual_seed(int(seed))
    return usable[torch.randperm(usable.numel(), generator=g)[:n_pixels].to(dev)]


def _median_scale(res: torch.Tensor, w: torch.Tensor) -> float:
    """``1.4826 x`` the median residual over the observations with ``w > 0`` (1.0 if there are none).

    The median is taken without boolean indexing (invalid entries become NaN
    for ``nanmedian``), so on CUDA it costs one host synchronisation.
    """
    med = torch.where(w > 0, res, torch.full_like(res, float("nan"))).flatten().nanmedian()
    s = float(1.4826 * med)  # NaN when no observation is valid
    return s if math.isfinite(s) else 1.0


def _fit_basis_brdfs(Phi, w, y, W, order, ridge_rel):
    """Shared basis BRDFs ``B (M, K)`` (unit rows) by weighted ridge LS over all pixels and channels."""
    M, K = W.shape[-1], Phi.shape[-1]
    Pw = Phi * w.unsqueeze(-1)
    G = Pw.transpose(1, 2) @ Phi
    A = torch.einsum("pcm,pcn,pkl->mknl", W, W, G).reshape(M * K, M * K)
    r = torch.einsum("pcm,pkc->mk", W, Pw.transpose(1, 2) @ y).reshape(-1)
    # the (M K, M K) system is tiny: solve it in float64 whatever the work dtype
    A, r = A.double(), r.double()
    prof = ridge_profile(order, torch.float64, y.device).repeat(M)
    tr = A.diagonal().mean().clamp(min=1e-300)
    A = A + torch.diag(ridge_rel * tr * prof) + 1e-12 * tr * torch.eye(M * K, dtype=A.dtype, device=A.device)
    return _unit_rows(torch.linalg.solve_ex(A, r)[0].reshape(M, K).to(y.dtype))  # SPD (ridge): no error check


def _calibrate(y, w0, n, lights, order, W, rounds, irls, lm_iter, c, basis_ridge=DEFAULT_BASIS_RIDGE, weight_ridge=1e-4):
    """Alternate (basis BRDFs, mixing weights, robust weights) and the normals on a pixel subset.

    Every round: ``irls + 1`` Cauchy-IRLS passes of (fit ``B`` over all
    pixels and channels, closed-form mixing weights, robust weights) at fixed
    normals, then ``lm_iter`` variable-projection LM iterations of the normals
    at fixed ``B`` and weights. Returns ``B (M, K)``, the robust residual scale
    and the subset normals.
    """
    w = w0.clone()
    scale = None
    B = None
    yT = y.transpose(1, 2).contiguous()  # (p, C, L): the layout of the mixed design
    for rnd in range(rounds):
        X, T = _design_factors(n, lights, order)
        Phi = X @ T
        for _ in range(irls + 1):
            B = _fit_basis_brdfs(Phi, w, y, W, order, basis_ridge)
            Psi = (Phi @ B.T).transpose(1, 2).contiguous()  # (p, M, L)
            rd = _ridge_diag(Psi, w0, weight_ridge)
            Wt, _, _ = solve_weights(Psi, w, yT, rd)  # (p, M, C)
            W = Wt.transpose(1, 2)
            res = observation_residual(Psi, Wt, yT)
            if rnd < _SCALE_ROUNDS:
                scale = max(_median_scale(res, w0), 1e-12)
            w = cauchy_weights(res, w0, scale, c)
        n, _, _ = lm_normals(MixedDesign(B, lights, order), yT, w, rd, n, lm_iter, fd_step(y.dtype))
    return B, scale, n


def _calibrate_shared(y, lights, w0, n_start, order, M, profile, ridge, sigma_y, n_pixels, rounds, starts, seed,
                      wdt, c, progress, info, basis_ridge=DEFAULT_BASIS_RIDGE):
    """Calibrate the shared basis BRDFs on a seeded random subset of ``n_pixels`` pixels.

    The alternation (:func:`_calibrate`) keeps the basin it starts in, so it
    runs from the robust Lambertian normals and, if ``"independent"`` is in
    ``starts``, from the independent-model normals on the subset (exact
    azimuth, biased elevation), and if ``"flattened"`` is in ``starts``, from
    the Lambertian normals with their slopes scaled by :data:`FLATTEN_FACTORS`
    (in this order; ``calibration_start`` is the index in it). The winner has the smallest Cauchy loss of the
    subset residuals at a common scale (the smaller of the scales): the scale
    alone would reward a basis bent to biased normals. Writes
    ``calibration_start`` / ``calibration_losses`` into ``info``.

    Returns ``B (M, K)``, the robust scale, the subset indices and their normals.
    """
    dt, dev = lights.dtype, y.device
    S = _calibration_subset(w0, n_pixels, seed)
    yS, w0S = y[S].to(dt), w0[S].to(dt)
    _, alb = _solve_flat(yS, lights, trimmed_weights(yS, 0.25, 0.10))
    W0 = _initial_mixing(alb, M, seed)
    starts_S = [n_start[S]]
    if "independent" in starts:
        view = torch.tensor([0.0, 0.0, 1.0], dtype=wdt, device=dev)
        n_ind, _, _ = refine_independent_chunk(
            yS.to(wdt), w0S.to(wdt), n_start[S].to(wdt), lights.to(wdt), view, order,
            profile.to(wdt), ridge, True, 1, (), 0, _INDEPENDENT_START_ITERS, sigma_y,
        )
        starts_S.append(torch.nn.functional.normalize(n_ind.to(dt), dim=-1))
    if "flattened" in starts:
        for f in FLATTEN_FACTORS:  # along the specular elevation bias of the Lambertian start
            q = n_start[S].clone()
            q[:, :2] *= f
            starts_S.append(torch.nn.functional.normalize(q, dim=-1))
    it_starts = list(enumerate(starts_S))
    if progress:
        from tqdm.auto import tqdm

        it_starts = tqdm(it_starts, desc="HSH calibration (basis BRDFs)", unit="start")
    cands = []
    for k_s, nS0 in it_starts:
        # in the work dtype (the (M K, M K) basis solve is always float64)
        B_k, scale_k, n_k = _calibrate(
            yS.to(wdt), w0S.to(wdt), nS0.to(wdt), lights.to(wdt), order,
            W0.to(wdt), rounds, _CAL_IRLS, _CAL_LM_ITERS, c, basis_ridge,
        )
        # unit rows in the output dtype, so that passing them back as `basis=` (which renormalises) changes nothing
        cands.append((_unit_rows(B_k.to(dt)), scale_k, k_s, n_k.to(dt)))
    sig = min(t[1] for t in cands)
    yT = yS.transpose(1, 2)
    losses = []
    for B_k, _, _, n_k in cands:
        X, T = _design_factors(n_k, lights, order)
        Psi = (X @ (T @ B_k.T)).transpose(1, 2)
        _, res = irls_weights(Psi, yT, w0S.clone(), w0S, sig, c, 3)
        losses.append(float((w0S * cauchy_rho(res, sig, c)).sum()))
    i_best = min(range(len(cands)), key=lambda i: losses[i])
    B, scale, chosen, n_cal = cands[i_best]
    info["calibration_losses"] = losses
    info["calibration_start"] = float(chosen)
    return B, scale, S, torch.nn.functional.normalize(n_cal, dim=-1)


@dataclass
class Calibration:
    """State after stage 3 (shared model).

    Attributes:
        basis: ``(M, K)`` unit-norm basis BRDFs (isotropic Helmholtz coefficients).
        scale: robust residual scale of the Cauchy weights (floored at the noise
            level and at 1e-4 of the typical brightness).
        subset: ``(S,)`` indices of the calibration pixels.
        subset_normals: ``(S, 3)`` their calibrated normals.
    """

    basis: torch.Tensor
    scale: float
    subset: torch.Tensor
    subset_normals: torch.Tensor

    def start_normals(self, n_start: torch.Tensor) -> torch.Tensor:
        """``n_start`` with the calibrated subset normals put in (the best start the per-pixel pass has for them)."""
        n = n_start.clone()
        n[self.subset] = self.subset_normals
        return n


def calibrate(obs: Observations, n_start: torch.Tensor, cfg: Settings) -> Calibration:
    """Stage 3: calibrate ``cfg.materials`` shared basis BRDFs; writes its diagnostics into ``obs.info``."""
    assert cfg.materials is not None  # only the shared model calibrates
    d, w0, info = obs.data, obs.weights, obs.info
    dt = d.dtype
    wdt = cfg.work(dt)
    profile = ridge_profile(cfg.order, dt, d.y.device)
    with torch.no_grad():
        B, scale, S, n_cal = _calibrate_shared(
            d.y, d.lights, w0, n_start, cfg.order, cfg.materials, profile, cfg.ridge, obs.sigma_y,
            cfg.calibration_pixels, cfg.calibration_rounds, cfg.calibration_starts, cfg.seed, wdt, cfg.cauchy_c,
            cfg.progress, info, cfg.basis_ridge,
        )
        # floor: the noise level, and 1e-4 of the typical brightness (quantisation,
        # float32 rounding) so that noise-free data do not get a zero scale
        typical = obs.typical
        scale = max(scale, 3.0 * obs.sigma_y, 1e-4 * typical, 1e-12)
    info["materials"] = float(cfg.materials)
    info["basis_ridge"] = cfg.basis_ridge
    info["robust_scale"] = scale
    info["calibration_pixels"] = float(S.numel())
    return Calibration(basis=B, scale=scale, subset=S, subset_normals=n_cal)


def fixed_calibration(obs: Observations, n_start: torch.Tensor, cfg: Settings, basis: torch.Tensor,
                      scale: Optional[float]) -> Calibration:
    """Stage 3 with the basis BRDFs given (``solve_hsh(basis=...)``): nothing is fitted.

    ``basis (M, K)`` is used as it is (rows normalised). ``scale`` is the
    robust residual scale at unit brightness; ``None`` estimates it as in the
    first calibration round: on the seeded calibration subset, closed-form
    mixing weights at the start normals with all valid observations, then
    ``1.4826 x`` the median residual. The same floors as :func:`calibrate` apply.
    """
    d, w0, info = obs.data, obs.weights, obs.info
    dt, dev = d.dtype, d.y.device
    B = _unit_rows(basis.to(device=dev, dtype=dt))
    if scale is None:
        with torch.no_grad():
            S = _calibration_subset(w0, cfg.calibration_pixels, cfg.seed)
            yT, wS = d.y[S].to(dt).transpose(1, 2), w0[S].to(dt)
            Psi = MixedDesign(B, d.lights, cfg.order)(n_start[S])
            Wt, _, _ = solve_weights(Psi, wS, yT, _ridge_diag(Psi, wS, 1e-4))
            scale = _median_scale(observation_residual(Psi, Wt, yT), wS)
        info["robust_scale_estimated"] = 1.0
    scale = max(float(scale), 3.0 * obs.sigma_y, 1e-4 * obs.typical, 1e-12)
    info["materials"] = float(B.shape[0])
    info["robust_scale"] = scale
    info["calibration_pixels"] = 0.0
    info["basis_given"] = 1.0
    empty = torch.empty(0, dtype=torch.long, device=dev)
    return Calibration(basis=B, scale=scale, subset=empty, subset_normals=n_start.new_empty(0, 3))
