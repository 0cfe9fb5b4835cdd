"""Stage 4 of the HSH solver: per-pixel refinement of the normals (and mixing weights).

Takes the observations, the start normals and, for the shared model, the
calibrated basis BRDFs; returns a :class:`Refinement` (normals, robust
weights, and the mixing weights or the ridge of the independent model),
processed in chunks of pixels so memory is bounded by the chunk size.

* Shared model (:func:`refine_shared_chunk`): per pixel, Cauchy IRLS on the
  mixing weights (closed form) alternating with one variable-projection LM
  step of the normal, with a coarse cone search at the first iteration; a
  pixel stops once its normal is still.
* Independent model (:func:`refine_independent_chunk`): free coefficients per
  pixel; IRLS stages on the coefficients at the start normal, cone search,
  then LM stages.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ._chunks import for_chunks
from .design import MixedDesign
from .optim import (
    PixelProblem,
    _ridge_diag,
    active_rows,
    cone_search,
    fd_step,
    irls_weights,
    lm_independent,
    lm_normals,
    reduced_cost,
    robust_coefficient_weights,
    solve_weights,
)
from .design import ridge_profile
from .observations import Observations
from .settings import Settings

__all__ = ["Refinement", "refine", "refine_independent_chunk", "refine_shared_chunk"]

_PIXEL_IRLS = 2  # reweighting passes per iteration of the per-pixel pass



def refine_independent_chunk(y, w0, n, lights, view, order, profile, ridge, robust, robust_iters, search_angles,
                       search_azimuths, lm_iters, sigma_y):
    """Independent per-pixel model on one batch: returns normals, the :class:`PixelProblem` and LM iterations."""
    ch = PixelProblem(y, w0, lights, view, order, profile, ridge)
    n = n.clone()
    ch.set_ridge_scale(n)
    iters = 0
    floor = None
    if robust:
        yscale = ch.y.mean(-1).abs().amax(-1)
        floor = torch.maximum(torch.full_like(yscale, 3 * sigma_y), 1e-3 * yscale).clamp(min=1e-12)
        # IRLS on the coefficients at the start normal: observations the basis
        # cannot explain (sharp highlights, interreflections) lose their weight
        # before the normal moves
        for _ in range(robust_iters + 1):
            ch.set_weights(robust_coefficient_weights(ch, n, w0, floor))
    n = cone_search(n, ch.cost, search_angles, search_azimuths)  # coarse search over a cone of candidates
    n, _, k = lm_independent(ch, n, lm_iters)
    iters += k
    if robust:
        for _ in range(robust_iters):
            ch.set_weights(robust_coefficient_weights(ch, n, w0, floor))
            n, _, k = lm_independent(ch, n, lm_iters)
            iters += k
    return n, ch, iters


def refine_shared_chunk(B, y, w0, n, lights, order, scale, c, iters, irls, search_angles, search_azimuths, wdt,
                          step_tol: float = 2e-4):
    """Per-pixel IRLS + Levenberg–Marquardt on the normals with the basis BRDFs fixed.

    Every iteration: ``irls`` Cauchy reweighting steps (mixing weights in
    closed form at the current normal), then one LM step of the normal. A
    pixel stops once its normal moves less than ``step_tol`` radians (after at
    least three iterations), so results do not depend on the chunking.

    Returns normals, robust weights, mixing weights ``(p, M, C)`` (in ``y``'s dtype) and the iterations used.
    """
    out_dt = y.dtype
    des = MixedDesign(B.to(wdt), lights.to(wdt), order)
    yd, w0d, nd = y.to(wdt).transpose(1, 2).contiguous(), w0.to(wdt), n.to(wdt)  # yd (p, C, L)
    h = fd_step(wdt)
    Psi = des(nd)
    w = w0d.clone()

    active = torch.ones(nd.shape[0], dtype=torch.bool, device=nd.device)
    used = 0
    for it, idx in enumerate(active_rows(active, iters)):
        used += 1
        yi, ni, Pi = yd[idx], nd[idx], Psi[idx]
        wi, _ = irls_weights(Pi, yi, w[idx], w0d[idx], scale, c, irls)
        rd = _ridge_diag(Pi, wi, 1e-4)
        searched = it == 0 and len(search_angles) > 0 and search_azimuths > 0
        if searched:
            ni = cone_search(
                ni, lambda m, wi=wi, yi=yi, rd=rd: reduced_cost(des(m), wi, yi, rd)[0], search_angles, search_azimuths,
                base_cost=reduced_cost(Pi, wi, yi, rd)[0],
            )
        # the design at the current normals is known unless the search moved them
        n_new, _, P_new = lm_normals(des, yi, wi, rd, ni, 1, h, Psi=None if searched else Pi)
        step = (n_new - nd[idx]).norm(dim=-1)
        nd[idx] = n_new
        Psi[idx] = P_new
        w[idx] = wi
        if it >= 2:
            active[idx] = ~(step < step_tol)  # every idx was active: no boolean indexing (no host sync); NaN stays active
    w, _ = irls_weights(Psi, yd, w, w0d, scale, c, irls)
    rd = _ridge_diag(Psi, w, 1e-4)
    Wt, _, _ = solve_weights(Psi, w, yd, rd)
    return nd.to(out_dt), w.to(out_dt), Wt.to(out_dt), used


@dataclass
class Refinement:
    """State after stage 4.

    Attributes:
        normals: ``(N, 3)`` unit normals.
        weights: ``(N, L)`` final robust weights of the normal estimation.
        fit_weights: ``(N, L)`` weights of the final coefficient fit: the
            observation weights for the shared model (the coefficients fit every
            valid observation), the robust weights for the independent model.
        mixing: shared model: ``(N, M, C)`` mixing weights; else ``None``.
        ridge_diag: independent model: ``(N, K)`` per-pixel ridge; else ``None``.
        iterations: LM iterations summed over the chunks.
        moved: number of pixels whose normal left its start.
        chunks: number of chunks processed.
    """

    normals: torch.Tensor
    weights: torch.Tensor
    fit_weights: torch.Tensor
    mixing: Optional[torch.Tensor]
    ridge_diag: Optional[torch.Tensor]
    iterations: int
    moved: int
    chunks: int


def refine(obs: Observations, n_start: torch.Tensor, cfg: Settings, basis: Optional[torch.Tensor] = None,
           scale: Optional[float] = None) -> Refinement:
    """Stage 4: refine every pixel's normal in chunks of ``cfg.chunk`` pixels.

    ``basis (M, K)`` and the robust ``scale`` come from the calibration (shared
    model); with ``basis=None`` the independent model runs.
    """
    d, w0 = obs.data, obs.weights
    N, L, C = d.y.shape
    dev, dt = d.y.device, d.dtype
    wdt = cfg.work(dt)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=dt, device=dev)
    profile = ridge_profile(cfg.order, dt, dev)
    shared = basis is not None
    normals = torch.empty(N, 3, dtype=dt, device=dev)
    wfin = torch.empty(N, L, dtype=d.y.dtype, device=dev)  # storage dtype: weights need no float64
    mixing = torch.empty(N, basis.shape[0], C, dtype=dt, device=dev) if basis is not None else None
    ridge_diag = None if shared else torch.empty(N, profile.shape[0], dtype=dt, device=dev)
    bar = None
    if cfg.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=N, desc="HSH photometric stereo", unit="px")
    acc = {"iters": 0, "moved": 0}

    def run(sl: slice) -> None:
        if shared:
            n, w, Wt, k = refine_shared_chunk(
                basis, d.y[sl].to(dt), w0[sl].to(dt), n_start[sl], d.lights, cfg.order, scale, cfg.cauchy_c, cfg.iterations,
                _PIXEL_IRLS, cfg.search_angles, cfg.search_azimuths, wdt,
            )
            n = torch.nn.functional.normalize(n, dim=-1)
            assert mixing is not None
            mixing[sl] = Wt
        else:
            n, ch, k = refine_independent_chunk(
                d.y[sl].to(dt), w0[sl].to(dt), n_start[sl], d.lights, view, cfg.order, profile, cfg.ridge, cfg.robust,
                cfg.robust_iters, cfg.search_angles, cfg.search_azimuths, cfg.iterations, obs.sigma_y,
            )
            w = ch.w
            assert ridge_diag is not None
            ridge_diag[sl] = ch.ridge_diag
        normals[sl] = n
        wfin[sl] = w
        acc["iters"] += k
        acc["moved"] += int(((n_start[sl] - n).norm(dim=-1) > 1e-6).sum())

    with torch.no_grad():
        chunks, _ = for_chunks(N, cfg.chunk, run, shrink=cfg.chunk_auto, progress=bar)
    total_iters, moved = acc["iters"], acc["moved"]
    return Refinement(
        normals=normals, weights=wfin, fit_weights=w0 if shared else wfin, mixing=mixing, ridge_diag=ridge_diag,
        iterations=total_iters, moved=moved, chunks=chunks,
    )
