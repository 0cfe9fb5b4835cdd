"""Stage 5 of the HSH solver: final coefficients with the non-negativity safeguard.

Takes the observations and the refined normals; returns per-pixel isotropic
Helmholtz coefficients (ridge least squares; for the shared model shrunk
toward the mix of the basis BRDFs and fitted to every valid observation) and
the weighted RMS residual. Memory: the coefficients go either into a compact
``(N, C, K)`` buffer (scattered into the output map by the result stage, once
the observations are released) or, when that gives the lower peak, straight
into the rows of the output map (:func:`_write_map_in_place`). The safeguard penalises the
rendered BRDF where it is negative at the lights and at a fixed hemisphere of
virtual lights.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from ._chunks import for_chunks
from .design import ridge_profile
from .observations import Observations
from .optim import PixelProblem
from .refinement import Refinement
from .settings import Settings

__all__ = ["Coefficients", "fit_coefficients", "final_coefficients", "COEFFICIENT_CHUNK"]

#: Largest number of pixels per chunk of the final coefficient fit.
COEFFICIENT_CHUNK = 2048



def _hemisphere_dirs(n: int, dtype, device) -> torch.Tensor:
    """Fibonacci set of ``n`` unit directions with z in (0, 1)."""
    i = torch.arange(n, dtype=dtype, device=device) + 0.5
    z = 1.0 - i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    s = torch.sqrt((1 - z * z).clamp(min=0))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], dim=-1)


def final_coefficients(ch: PixelProblem, n, nonneg: bool, prior=None, gamma: float = 10.0, iters: int = 4, virtual: int = 48,
                        Phi=None):
    """Per-pixel ridge coefficients ``(p, K, C)``, shrunk toward ``prior`` (default 0), with the non-negativity safeguard."""
    Phi = ch.design(n) if Phi is None else Phi
    a0 = torch.zeros(Phi.shape[0], Phi.shape[-1], ch.y.shape[-1], dtype=Phi.dtype, device=Phi.device) if prior is None else prior
    a = a0 + ch.solve(Phi, ch.w, ch.ridge_diag, ch.y - Phi @ a0)
    if not nonneg:
        return a
    vdirs = _hemisphere_dirs(virtual, n.dtype, n.device)
    Pv = ch.design(n, vdirs)  # (p, V, K)
    Pall = torch.cat([Phi, Pv], dim=1)
    Wv = Pall.new_zeros(Pall.shape[:2])
    scale = ch.w.sum(-1, keepdim=True).clamp(min=1.0) / Pall.shape[1]
    for _ in range(iters):
        pred = Pall @ a  # (p, L+V, C)
        neg = (pred < 0).any(-1)
        new = neg & (Wv == 0)
        if not bool(new.any()):
            break
        Wv = torch.where(neg, gamma * scale.expand_as(Wv), Wv)
        extra = (Pall * Wv.unsqueeze(-1)).transpose(1, 2) @ Pall
        # minimise |sqrt(w)(y - Phi a)|^2 + |sqrt(ridge)(a - a0)|^2 + |sqrt(Wv) Pall a|^2
        a = a0 + ch.solve(Phi, ch.w, ch.ridge_diag, ch.y - Phi @ a0, extra=extra, rhs_extra=-(extra @ a0))
    return a


@dataclass
class Coefficients:
    """State after stage 5.

    Attributes:
        coefficients: either ``(N, C, K)`` (one row per masked pixel, solver
            order; ``pixels`` is ``None``) or the ``(H W, C, K)`` rows of the
            output map (``H W = mask.numel()``, zero outside the mask).
        pixels: ``None``, or ``(N,)`` int64 rows of the masked pixels in that map.
        residual: ``(N,)`` weighted RMS residual of the fit.
    """

    coefficients: torch.Tensor
    pixels: Optional[torch.Tensor]
    residual: torch.Tensor


def _write_map_in_place(N: int, HW: int, L: int, C: int, K: int, obs_bytes: int, dt_bytes: int) -> bool:
    """Whether writing the ``(H W, C, K)`` output map directly gives a lower peak than a compact buffer.

    Compact: the stage holds ``F = N C K`` values and the result stage later
    holds the buffer and the map together, but without the observations ``(N,
    L, C)`` and their weights ``(N, L)`` (``obs_bytes`` per value), which it
    releases first: extra peak ``F + max(0, Map - Y - W0)``. In place: extra
    peak ``Map`` during this stage. With many lights the observations dominate
    and the compact buffer wins (1024^2 x 96); with few lights and a large
    frame the map wins (2048^2 x 16).
    """
    f = N * C * K * dt_bytes
    m = HW * C * K * dt_bytes
    y = N * L * (C + 1) * obs_bytes
    return m < f + max(0, m - y)


def fit_coefficients(obs: Observations, ref: Refinement, cfg: Settings,
                     basis: Optional[torch.Tensor] = None) -> Coefficients:
    """Stage 5: final per-pixel coefficients at the refined normals, in chunks of ``cfg.chunk`` pixels.

    Shared model (``basis (M, K)`` given): ridge-shrunk toward the mix
    ``basis^T W`` of the refined mixing weights, ridge scaled at the final
    normals. Independent model: shrunk toward 0 with the refinement's ridge.
    """
    d = obs.data
    N, L, C = d.y.shape
    dev, dt = d.y.device, d.dtype
    view = torch.tensor([0.0, 0.0, 1.0], dtype=dt, device=dev)
    profile = ridge_profile(cfg.order, dt, dev)
    K = profile.shape[0]
    itemsize = torch.empty(0, dtype=dt).element_size()
    pixels = None
    if _write_map_in_place(N, d.mask.numel(), L, C, K, d.y.element_size(), itemsize):
        pixels = d.mask.reshape(-1).nonzero().squeeze(1)  # int64 rows of the masked pixels in the map
        coefs = torch.zeros(d.mask.numel(), C, K, dtype=dt, device=dev)
    else:
        coefs = torch.empty(N, C, K, dtype=dt, device=dev)
    resid = torch.empty(N, dtype=dt, device=dev)
    # the safeguard's stacked designs (lights + 48 virtual lights, float64) are the largest
    # temporaries of the solve: a smaller chunk than the refinement's bounds them (on the CPU
    # a fixed one; on a GPU, where launches cost more than bytes, an eighth of the refinement's)
    step = min(cfg.chunk, COEFFICIENT_CHUNK if dev.type == "cpu" else max(COEFFICIENT_CHUNK, cfg.chunk // 8))

    def run(sl: slice) -> None:
        n = ref.normals[sl]
        ch = PixelProblem(d.y[sl].to(dt), ref.fit_weights[sl].to(dt), d.lights, view, cfg.order, profile, cfg.ridge)
        Phi = ch.design(n)
        if basis is not None:
            # the robust weights served the normals; the coefficients fit every valid
            # observation (shrunk toward the shared mix), which relights best
            ch.set_ridge_scale(n, Phi)
            assert ref.mixing is not None  # the shared model's refinement fills it
            a = final_coefficients(ch, n, cfg.nonneg, prior=basis.T.unsqueeze(0) @ ref.mixing[sl], Phi=Phi)
        else:
            assert ref.ridge_diag is not None  # the independent model's refinement fills it
            ch.ridge_diag = ref.ridge_diag[sl]
            a = final_coefficients(ch, n, cfg.nonneg, Phi=Phi)
        r = (ch.y - Phi @ a) * ch.sw.unsqueeze(-1)
        resid[sl] = ((r * r).sum((-1, -2)) / (ch.w.sum(-1).clamp(min=1e-12) * C)).sqrt()
        if pixels is None:
            coefs[sl] = a.transpose(1, 2)
        else:
            coefs[pixels[sl]] = a.transpose(1, 2)

    bar = None
    if cfg.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=N, desc="HSH coefficients", unit="px")
    with torch.no_grad():
        for_chunks(N, step, run, shrink=cfg.chunk_auto, progress=bar)
    return Coefficients(coefficients=coefs, pixels=pixels, residual=resid)
