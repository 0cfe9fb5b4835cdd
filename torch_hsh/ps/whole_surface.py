r"""Whole-surface refinement: one depth map, the shared BRDFs and cast shadows, after the per-pixel solve.

The per-pixel solver (:func:`~torch_hsh.ps.solve_hsh`) estimates every normal on its own. This stage
(:func:`refine_surface`, ``solve_hsh(..., refine_surface=True)``, ``torch-hsh ps --refine-surface``)
re-estimates them as the normals of **one height field** ``z`` over the mask, so they are integrable
by construction, with the shared-basis BRDF model of the solve and the cast shadows that ``z`` itself
casts; then (``surface_polish``, default) re-estimates every normal per pixel from that surface's.

Model (unit brightness, as in the solver; ``y_pjc`` the observations, ``Psi`` the mixed design of the
shared basis BRDFs ``B``, :class:`~torch_hsh.ps.design.MixedDesign`):

.. math::
    \min_{z}\; \sum_{p,j} \omega_{pj} \sum_c \big(y_{pjc} - \sum_m W_{pmc}\, \Psi_{pmj}(n_p(z))\big)^2,

with ``n_p(z)`` the normal of the depth gradient at pixel ``p`` and ``omega`` the observation weights
(valid, not dark, not saturated: stage 1 of the solver) times the visibility of light ``j`` from the
current depth, times Cauchy IRLS weights. The stage alternates ``rounds`` times:

1. normals of the current depth; visibility of every light by marching it over the depth
   (:func:`torch_hsh.surface.light_visibility`, re-computed between rounds, not differentiated);
2. the per-pixel mixing weights ``W`` in closed form at those normals, with Cauchy IRLS weights
   (the solver's own kernels, :mod:`~torch_hsh.ps.optim`);
3. the depth: ``iterations`` L-BFGS steps (strong-Wolfe line search) on the weighted least-squares
   cost above, with ``W`` and the weights fixed. The depth is parameterised as
   ``z = z_0 + D_h^T (S \odot c) D_w`` with orthonormal DCT-II matrices ``D`` and ``S = (\lambda_h +
   \lambda_w + \epsilon)^{-1/2}`` from the eigenvalues of the Neumann Laplacian of the mask's
   bounding box: a gradient step in ``c`` is a Poisson-preconditioned step in ``z``, so the smooth
   (low-frequency) shape, which is where the elevation bias lives, moves as fast as the detail.

Start: ``z_0`` integrates the per-pixel normals (:func:`torch_hsh.surface.integrate_normals`,
bilateral, at most 10 re-weighting iterations): Poisson integration smears the depth jumps of real
objects, and the normals of a Poisson depth of the *true* normals are 4.2 deg off on the cat and 16.5
deg on harvest, against 1.2 and 5.3 deg with the bilateral depth (``research/surface_floor.py``). Normals of the depth: per axis the forward or the backward difference, mixed with the
weight ``sigmoid(k (d_-^2 - d_+^2))`` of bilateral normal integration (Cao et al. 2022) from the
depth at the start of the round, so a jump inside the mask is seen from its smooth side; one-sided
at the mask edge. The loss is evaluated in chunks of pixels (the normals' gradient is accumulated
chunk by chunk, then pushed through the depth once): memory ``O(chunk L M)`` plus a few ``(H, W)``
maps.

**Polish** (``surface_polish``, default on). The depth's normals are a start, not the answer. From
them every pixel's normal is re-estimated on its own, with the solver's per-pixel stage: the shared
basis is fixed, there is no cone search, every light is used, and the cast shadows come from the final
depth. The returned normals are those, and the returned ``depth`` is the stage's surface. Why: the
normals of a depth map on the pixel grid cannot follow the true normals everywhere. Even the true
normals, integrated and differentiated again, are 1.2 deg off on the cat. The polish removes that
floor, and it keeps what the surface changed: the basin that each pixel starts in, and the shadows.
On the suite (seed 0) the surface alone was worse than the start on 5 of 9 scenes. With the polish,
over 9 scenes x 5 seeds, it was better in 36 runs and worse in 4 (the bowl, at most +0.04 deg).
The mean gains are small (harvest -0.55 deg, bumpy -0.23; docs/photometric_stereo.md).

**Safeguard.** A seeded tenth of the lights (``holdout``) is held out of every fit of this stage.
Before: the start normals; after: the refined ones. With the polish on, both are first re-estimated
per pixel (on a strided subset of at most 8,192 pixels) without the held-out lights, each from its
own start, so the test compares the two basins. The mixing weights are then fitted on the other lights,
and the error is the mean Cauchy loss of the held-out valid observations at the solver's robust scale.
The refined result is returned only if it lowers that error; otherwise the start is returned unchanged
(``info["surface_accepted"] = 0``). ``info`` reports both errors either way.

Interreflections are not modelled inside the stage. By default (``interreflections=None``) the solver
runs one safeguarded round of :mod:`~torch_hsh.ps.interreflections` before it, and the stage starts from
that round's result and images (one bounce removed).

Limits: the shared model only (``materials`` not ``None``); orthographic, distant lights; disconnected
parts of the mask keep the offsets of the start (only the shadows they cast on each other depend on them).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Dict, Optional, Tuple

import torch

from ._chunks import scatter_pixels
from ._geometry import start_depth
from .coefficients import fit_coefficients
from .design import MixedDesign
from .observations import Observations, observe
from .optim import _ridge_diag, cauchy_rho, cauchy_weights, combine, irls_weights, observation_residual, solve_weights
from .refinement import Refinement, refine_shared_chunk
from .result import HSHResult, confidence, directional_albedo_view
from .settings import SURFACE_ITERATIONS, SURFACE_ROUNDS, Settings

__all__ = ["refine_surface", "depth_normals", "discontinuity_weights", "SURFACE_ROUNDS", "SURFACE_ITERATIONS"]
#: Sharpness of the discontinuity weights (Cao et al.'s ``k``), per squared pixel of depth difference.
_K = 2.0
#: IRLS passes of the mixing weights per round.
_IRLS = 2
#: Integrator of the start depth, and its cap on re-weighting iterations (see the module docstring).
_START_METHOD = "bilateral"
#: Pixels (a strided subset) of the held-out-light comparison.
_HOLDOUT_PIXELS = 8192
#: Pixels per chunk of the loss evaluation.
_CHUNK = 8192


# --------------------------------------------------------------------------- #
# the depth: crop, parameterisation, normals
# --------------------------------------------------------------------------- #
def _dct_matrix(n: int, dtype, device) -> torch.Tensor:
    """Orthonormal DCT-II matrix ``(n, n)`` (rows: frequencies)."""
    i = torch.arange(n, dtype=torch.float64)
    D = torch.cos(math.pi * (i[None, :] + 0.5) * i[:, None] / n) * math.sqrt(2.0 / n)
    D[0] /= math.sqrt(2.0)
    return D.to(dtype=dtype, device=device)


@dataclasses.dataclass
class _Depth:
    """The depth on the mask's bounding box: ``z = z0 + Dh^T (S * c) Dw``; ``m`` the cropped mask."""

    z0: torch.Tensor
    m: torch.Tensor
    box: Tuple[slice, slice]
    Dh: torch.Tensor
    Dw: torch.Tensor
    S: torch.Tensor
    rows: torch.Tensor  # (N,) flat indices of the masked pixels in the crop, in the solver's pixel order

    @classmethod
    def start(cls, normals: torch.Tensor, mask: torch.Tensor, dtype, method: str = _START_METHOD) -> "_Depth":
        box, z0 = start_depth(normals, mask, method=method, fill=0.0)
        m = mask[box]
        dev = normals.device
        h, w = m.shape
        lam_h = 2.0 - 2.0 * torch.cos(math.pi * torch.arange(h, dtype=torch.float64) / h)
        lam_w = 2.0 - 2.0 * torch.cos(math.pi * torch.arange(w, dtype=torch.float64) / w)
        eps = 2.0 - 2.0 * math.cos(math.pi / max(h, w, 2))
        S = (lam_h[:, None] + lam_w[None, :] + eps).rsqrt()
        return cls(z0=z0.to(dtype=dtype, device=dev), m=m, box=box, Dh=_dct_matrix(h, dtype, dev),
                   Dw=_dct_matrix(w, dtype, dev), S=S.to(dtype=dtype, device=dev),
                   rows=m.reshape(-1).nonzero().squeeze(1))

    def depth(self, c: torch.Tensor) -> torch.Tensor:
        return self.z0 + self.Dh.T @ (self.S * c) @ self.Dw

    def full(self, z: torch.Tensor, shape) -> torch.Tensor:
        """``(H, W)`` depth of the whole frame, NaN outside the mask."""
        out = torch.full(shape, float("nan"), dtype=z.dtype, device=z.device)
        out[self.box] = torch.where(self.m, z.detach(), torch.full_like(z, float("nan")))
        return out


def _one_sided(z: torch.Tensor, m: torch.Tensor, dim: int):
    """Forward and backward differences along ``dim`` and whether each exists (both pixels in the mask)."""
    n = z.shape[dim]
    d = z.narrow(dim, 1, n - 1) - z.narrow(dim, 0, n - 1)
    e = m.narrow(dim, 1, n - 1) & m.narrow(dim, 0, n - 1)
    pad_f = [0, 0, 0, 1] if dim == 0 else [0, 1]
    pad_b = [0, 0, 1, 0] if dim == 0 else [1, 0]
    fwd = torch.nn.functional.pad(d, pad_f)
    bwd = torch.nn.functional.pad(d, pad_b)
    vf = torch.nn.functional.pad(e, pad_f)
    vb = torch.nn.functional.pad(e, pad_b)
    return fwd, bwd, vf, vb


def discontinuity_weights(z: torch.Tensor, m: torch.Tensor, k: float = _K) -> Tuple[torch.Tensor, torch.Tensor]:
    """Weights of the forward difference per axis, ``sigmoid(k (d_-^2 - d_+^2))``, from a depth.

    ``z (h, w)`` depth (pixel units), ``m (h, w)`` bool mask; returns two ``(h, w)`` maps (rows, cols)
    in ``[0, 1]``: near 1 where the backward difference is the larger (a jump behind the pixel), 0.5
    on a smooth surface. Not differentiated (computed from ``z.detach()``).

    Example:
        >>> z = torch.tensor([[0.0, 1.0, 2.0, 12.0, 13.0]])  # a jump between columns 2 and 3
        >>> wr, wc = discontinuity_weights(z, torch.ones(1, 5, dtype=torch.bool))
        >>> [round(float(v), 2) for v in wc[0, 1:4]]  # col 2 looks back, col 3 looks forward
        [0.5, 0.0, 1.0]
    """
    out = []
    for dim in (0, 1):
        fwd, bwd, _, _ = _one_sided(z.detach(), m, dim)
        out.append(torch.sigmoid(k * (bwd * bwd - fwd * fwd)))
    return out[0], out[1]


def depth_normals(z: torch.Tensor, m: torch.Tensor, weights: Tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """``(h, w, 3)`` unit normals of a depth map (DiLiGenT frame), differentiable in ``z``.

    Per axis the mix ``w d_+ + (1 - w) d_-`` of the forward and backward differences where both
    exist, the one that exists at the mask edge, 0 where none does; ``n = normalize(-dz/dcol,
    dz/drow, 1)`` as :func:`torch_hsh.surface.depth_to_normals`.

    Args:
        z: ``(h, w)`` depth in pixel units (values outside ``m`` are ignored).
        m: ``(h, w)`` bool mask.
        weights: ``(rows, cols)`` forward-difference weights, ``(h, w)`` each
            (:func:`discontinuity_weights`; ``0.5`` everywhere gives central differences).

    Returns:
        ``(h, w, 3)`` unit normals (DiLiGenT frame: x right, y up, z toward the camera).

    Example:
        >>> z = torch.arange(4.0).expand(3, 4) * 0.75  # rises to the right
        >>> half = torch.full((3, 4), 0.5)
        >>> depth_normals(z, torch.ones(3, 4, dtype=torch.bool), (half, half))[1, 1]
        tensor([-0.6000,  0.0000,  0.8000])
    """
    z = torch.where(m, z, torch.zeros_like(z))
    slopes = []
    for dim, wf in zip((0, 1), weights):
        fwd, bwd, vf, vb = _one_sided(z, m, dim)
        both = wf * fwd + (1.0 - wf) * bwd
        slopes.append(torch.where(vf & vb, both, torch.where(vf, fwd, torch.where(vb, bwd, torch.zeros_like(z)))))
    n = torch.stack([-slopes[1], slopes[0], torch.ones_like(z)], dim=-1)
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)


# --------------------------------------------------------------------------- #
# the BRDF side: mixing weights, losses
# --------------------------------------------------------------------------- #
@dataclasses.dataclass
class _Data:
    """The observations of the stage: ``y (N, C, L)``, weights ``w0 (N, L)``, the design, the robust scale."""

    y: torch.Tensor
    w0: torch.Tensor
    design: MixedDesign
    scale: float
    c: float
    train: torch.Tensor  # (L,) bool: lights the stage may fit
    basis: torch.Tensor  # (M, K) the shared basis BRDFs of ``design`` (the solve's)


def _chunks(N: int):
    return [slice(s, min(N, s + _CHUNK)) for s in range(0, N, _CHUNK)]


def _fit_chunks(data: _Data, n: torch.Tensor, w: torch.Tensor, rows: Optional[torch.Tensor] = None):
    """Per chunk of pixels: closed-form mixing weights ``(p, M, C)`` with Cauchy IRLS at normals ``n``, the robust
    weights and the residuals ``(p, L)`` after the fit. ``n`` and ``w`` are of the pixels ``rows`` (default: all)."""
    with torch.no_grad():
        for sl in _chunks(n.shape[0]):
            y = data.y[sl] if rows is None else data.y[rows[sl]]
            Psi = data.design(n[sl].to(data.y.dtype))
            wr, _ = irls_weights(Psi, y, w[sl], w[sl], data.scale, data.c, _IRLS)
            W, _, _ = solve_weights(Psi, wr, y, _ridge_diag(Psi, wr, 1e-4))
            res = observation_residual(Psi, W, y)
            yield sl, W, cauchy_weights(res, w[sl], data.scale, data.c), res


def _mixing(data: _Data, n: torch.Tensor, w: torch.Tensor):
    """Mixing weights ``(N, M, C)`` and robust weights ``(N, L)`` of every pixel at normals ``n`` (:func:`_fit_chunks`)."""
    fits = [(W, wr) for _, W, wr, _ in _fit_chunks(data, n, w)]
    return torch.cat([f[0] for f in fits]), torch.cat([f[1] for f in fits])


def _heldout_error(data: _Data, n: torch.Tensor, w: torch.Tensor, sub: torch.Tensor) -> float:
    """Mean Cauchy loss ``log(1 + (r / (c s))^2)`` of the held-out valid observations (``~train`` lights) of the
    pixels ``sub`` at normals ``n`` (of those pixels), the mixing weights fitted to the weights ``w`` (of those
    pixels; zero on the held-out lights)."""
    test = ~data.train
    tot, cnt = 0.0, 0.0
    for sl, _, _, res in _fit_chunks(data, n, w, sub):
        r = res[:, test]
        v = data.w0[sub[sl]][:, test] > 0
        rho = cauchy_rho(r, data.scale, data.c)
        tot += float(torch.where(v, rho, torch.zeros_like(rho)).sum())
        cnt += float(v.sum())
    return tot / max(cnt, 1.0)


def _per_pixel(data: _Data, n0: torch.Tensor, w: torch.Tensor, lights: torch.Tensor, cfg: Settings,
               rows: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The normals of the pixels ``rows`` (default: all) re-estimated one by one from ``n0`` (of those pixels) with
    the observation weights ``w`` (of those pixels): the solver's per-pixel stage with the basis fixed, no cone
    search, in chunks of pixels."""
    out = []
    with torch.no_grad():
        for sl in _chunks(n0.shape[0]):
            y = data.y[sl] if rows is None else data.y[rows[sl]]
            n, _, _, _ = refine_shared_chunk(data.basis, y.transpose(1, 2), w[sl], n0[sl], lights, data.design.order,
                                             data.scale, data.c, cfg.iterations, _IRLS, (), 0, cfg.work(data.y.dtype))
            out.append(n.to(n0.dtype))
    return torch.nn.functional.normalize(torch.cat(out), dim=-1)


def _holdout_start(data: _Data, n_start: torch.Tensor, w: torch.Tensor, sub: torch.Tensor, lights: torch.Tensor,
                   cfg: Settings) -> torch.Tensor:
    """The start normals of the pixels ``sub`` re-estimated without the held-out lights (the solver's per-pixel
    stage, from the start, no cone search), so that the start, like the refined surface, never saw them."""
    return _per_pixel(data, n_start[sub], w[sub], lights, cfg, sub)


def _depth_step(data: _Data, dep: _Depth, c: torch.Tensor, W: torch.Tensor, w: torch.Tensor, iters: int,
                wts) -> Tuple[torch.Tensor, float, float]:
    """``iters`` L-BFGS iterations on ``c`` (weighted LS in the depth, ``W`` and ``w`` fixed); returns ``c``,
    the cost before and after (normalised: mean weighted squared residual over ``scale^2``)."""
    norm = float(w.sum()) * data.y.shape[1] * data.scale ** 2
    c = c.detach().clone().requires_grad_(True)
    opt = torch.optim.LBFGS([c], lr=1.0, max_iter=iters, history_size=10, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)
    evals = []

    def closure():
        opt.zero_grad()
        z = dep.depth(c)
        n_img = depth_normals(z, dep.m, wts)
        n = n_img.reshape(-1, 3).index_select(0, dep.rows)
        leaf = n.detach().to(data.y.dtype).requires_grad_(True)
        total = 0.0
        for sl in _chunks(leaf.shape[0]):
            e = data.y[sl] - combine(W[sl], data.design(leaf[sl]))
            loss = (w[sl].unsqueeze(1) * e * e).sum() / norm
            loss.backward()
            total += float(loss.detach())
        n.backward(leaf.grad.to(n.dtype))
        evals.append(total)
        return torch.tensor(total, dtype=c.dtype)

    opt.step(closure)
    return c.detach(), evals[0], evals[-1]


# --------------------------------------------------------------------------- #
# the stage
# --------------------------------------------------------------------------- #
def _holdout_lights(L: int, holdout: float, seed: int, device) -> torch.Tensor:
    k = max(1, int(round(holdout * L)))
    if L - k < 6:
        raise ValueError(f"refine_surface needs at least {k + 6} lights with `surface_holdout`={holdout}, got {L}")
    g = torch.Generator().manual_seed(int(seed))
    train = torch.ones(L, dtype=torch.bool)
    train[torch.randperm(L, generator=g)[:k]] = False
    return train.to(device)


def _visibility(dep: _Depth, z: torch.Tensor, lights: torch.Tensor, bias: float) -> torch.Tensor:
    """``(N, L)`` visibility of every light from the depth (crop), in the solver's pixel order."""
    from ..surface import light_visibility

    vis = light_visibility(z.detach().to(torch.float64).cpu(), dep.m.cpu(), lights.detach().to(torch.float64).cpu(),
                           bias=bias)
    return vis.reshape(vis.shape[0], -1).index_select(1, dep.rows.cpu()).T.to(z.device)


def _check_result(result: HSHResult, images: torch.Tensor) -> None:
    if not isinstance(result, HSHResult):
        raise TypeError(f"`result` must be an HSHResult (from solve_hsh), got {type(result).__name__}")
    if result.basis_brdfs is None or result.mixing is None:
        raise ValueError("refine_surface needs the shared model (`result` has no basis_brdfs: solve with materials "
                         "set, not materials=None)")
    if images.dim() != 4:
        raise ValueError(f"`images` must have shape (L, H, W, C) for refine_surface, got {tuple(images.shape)}")
    if tuple(images.shape[1:3]) != tuple(result.mask.shape):
        raise ValueError(f"`images` pixel shape {tuple(images.shape[1:3])} does not match the result's mask "
                         f"{tuple(result.mask.shape)}")


def refine_surface(
    result: HSHResult,
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    *,
    settings: Optional[Settings] = None,
    **overrides,
) -> HSHResult:
    r"""Whole-surface refinement of a shared-model :class:`HSHResult` (see the module docstring).

    Args:
        result: the per-pixel solve (:func:`~torch_hsh.ps.solve_hsh`, shared model) of these images.
        images: ``(L, H, W, C)`` the images of that solve (the result's mask is used).
        lights: ``(L, 3)`` directions toward the lights.
        intensities: ``None``, ``(L,)`` or ``(L, C)``.
        settings, ``**overrides``: the solver's options (:class:`~torch_hsh.ps.Settings`), the same as
            the solve's; this stage reads ``refine_surface`` (rounds; ``True``: :data:`SURFACE_ROUNDS`),
            ``surface_iterations``, ``surface_shadows``, ``surface_polish``, ``surface_holdout``,
            ``surface_safeguard``, ``shadow_bias``, ``seed``,
            ``progress`` and the observation thresholds.

    Returns:
        A new :class:`HSHResult`: the normals (re-estimated per pixel from the depth's normals, see
        ``surface_polish``; the depth's own with ``surface_polish=False``), the coefficients fitted at
        them (stage 5 of the solver), ``depth`` (pixel units, NaN outside the mask) and in ``info``:
        ``surface_heldout_before`` / ``surface_heldout_after`` (mean Cauchy loss of the held-out
        lights), ``surface_accepted`` (1 or 0), ``surface_rounds``, ``surface_cost_before`` /
        ``surface_cost_after`` (the weighted cost of the fit lights), ``surface_shadowed_fraction``
        and ``surface_time_s``. If the held-out error does not fall, the start ``result`` (with
        ``depth`` = its integrated normals and the same ``info`` keys) is returned.

    Raises:
        ValueError: an independent-model result, images not ``(L, H, W, C)`` or of another frame size,
            too few lights for the held-out split.

    Example:
        >>> res = solve_hsh(images, lights, mask=mask)  # doctest: +SKIP
        >>> res2 = refine_surface(res, images, lights)  # doctest: +SKIP
        >>> res2.info["surface_heldout_after"] <= res2.info["surface_heldout_before"]  # doctest: +SKIP
        True
    """
    cfg = Settings(**overrides) if settings is None else dataclasses.replace(settings, **overrides)
    _check_result(result, images)
    t0 = time.perf_counter()
    rounds = int(cfg.refine_surface) or SURFACE_ROUNDS  # called directly: the stage runs
    obs = observe(images, lights, intensities, result.mask, cfg)
    d = obs.data
    dt = d.dtype
    assert result.basis_brdfs is not None  # _check_result
    basis = result.basis_brdfs.to(dt)
    scale_u = float(result.info.get("robust_scale", 0.0)) / obs.scale
    if not scale_u > 0:
        scale_u = max(float(result.residual[result.mask].median()) / obs.scale, 1e-6)
    train = _holdout_lights(d.lights.shape[0], cfg.surface_holdout, cfg.seed, d.y.device)
    wdt = cfg.work(dt)  # the per-pixel model in the solver's work dtype; the depth in ``dtype``
    data = _Data(y=d.y.to(wdt).transpose(1, 2).contiguous(), w0=obs.weights.to(wdt),
                 design=MixedDesign(basis.to(wdt), d.lights.to(wdt), result.order),
                 scale=scale_u, c=cfg.cauchy_c, train=train, basis=basis)
    dep = _Depth.start(result.normals.to(dt), result.mask, dt)
    n_start = result.normals.to(dt)[result.mask]
    log = _run_rounds(data, dep, n_start, d.lights, rounds, cfg)
    info = dict(result.info)
    info.update(log["info"])
    info["surface_time_s"] = time.perf_counter() - t0
    info["surface_kept"] = float(log["accepted"] or not cfg.surface_safeguard)
    if not info["surface_kept"]:
        return dataclasses.replace(result, info=info, depth=dep.full(dep.z0, tuple(result.mask.shape)))
    return _refined_result(result, obs, cfg, data, log, dep, info)


def _run_rounds(data: _Data, dep: _Depth, n_start: torch.Tensor, lights: torch.Tensor, rounds: int,
                cfg: Settings) -> Dict:
    """The alternation; returns the final normals, depth, visibility, mixing and the ``info`` entries."""
    fit_lights = data.train.to(data.w0.dtype)
    vis = _visibility(dep, dep.z0, lights, cfg.shadow_bias) if cfg.surface_shadows else None

    def weights(v):
        w = data.w0 * fit_lights
        return w if v is None else w * v.to(w.dtype)

    N = n_start.shape[0]
    sub = torch.arange(0, N, max(1, -(-N // _HOLDOUT_PIXELS)), device=n_start.device)
    w_start = weights(vis)
    before = _heldout_error(data, _holdout_start(data, n_start, w_start, sub, lights, cfg), w_start[sub], sub)
    c = torch.zeros_like(dep.z0)
    z = dep.z0
    costs = []
    bar = None
    if cfg.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=rounds, desc="whole-surface refinement", unit="round")
    for r in range(rounds):
        wts = discontinuity_weights(z, dep.m)
        n = depth_normals(z, dep.m, wts).reshape(-1, 3).index_select(0, dep.rows).detach()
        if cfg.surface_shadows and r > 0:
            vis = _visibility(dep, z, lights, cfg.shadow_bias)
        W, wr = _mixing(data, n, weights(vis))
        c, c0, c1 = _depth_step(data, dep, c, W, wr, cfg.surface_iterations, wts)
        costs.append((c0, c1))
        z = dep.depth(c).detach()
        if bar is not None:
            bar.update(1)
            bar.set_postfix(cost=f"{c1:.4g}")
    if bar is not None:
        bar.close()
    # (the visibility of the last round's start serves the final fits: a march costs as much as a round)
    n = depth_normals(z, dep.m, discontinuity_weights(z, dep.m)).reshape(-1, 3).index_select(0, dep.rows).detach()
    w_end = weights(vis)
    if cfg.surface_polish:  # both sides of the held-out test: per-pixel from their start, without those lights
        after = _heldout_error(data, _per_pixel(data, n[sub], w_end[sub], lights, cfg, sub), w_end[sub], sub)
    else:
        after = _heldout_error(data, n[sub], w_end[sub], sub)
    accepted = after < before
    if cfg.surface_polish and (accepted or not cfg.surface_safeguard):
        n = _per_pixel(data, n, data.w0 if vis is None else data.w0 * vis.to(data.w0.dtype), lights, cfg)
    info = {"surface_heldout_before": before, "surface_heldout_after": after, "surface_accepted": float(accepted),
            "surface_rounds": float(rounds), "surface_cost_before": costs[0][0] if costs else float("nan"),
            "surface_cost_after": costs[-1][1] if costs else float("nan"),
            "surface_shadowed_fraction": float("nan") if vis is None else float(
                ((~vis) & (data.w0 > 0)).sum()) / max(float((data.w0 > 0).sum()), 1.0)}
    return {"accepted": accepted, "normals": n, "depth": z, "visibility": vis, "info": info}


def _refined_result(result: HSHResult, obs: Observations, cfg: Settings, data: _Data, log: Dict, dep: _Depth,
                    info: Dict) -> HSHResult:
    """The result at the refined normals: mixing weights on every light, then the solver's stage 5 (coefficients)."""
    n = log["normals"]
    w = data.w0 if log["visibility"] is None else data.w0 * log["visibility"].to(data.w0.dtype)
    W, wr = _mixing(data, n, w)
    dt = n.dtype
    W, wr, w = W.to(dt), wr.to(dt), w.to(dt)
    ref = Refinement(normals=n, weights=wr, fit_weights=w, mixing=W, ridge_diag=None, iterations=0, moved=0,
                     chunks=0)
    cfg = cfg.chunked(obs.data.y, obs.data.dtype)
    fit = fit_coefficients(obs, ref, cfg, data.basis)
    mask = obs.data.mask
    s = obs.scale
    rows = fit.coefficients if fit.pixels is None else fit.coefficients[fit.pixels]
    rows = rows * s
    albedo = directional_albedo_view(rows, n[:, 2])
    conf = confidence(wr, fit.residual, data.scale, result.order, cfg.cauchy_c)
    return dataclasses.replace(
        result,
        normals=scatter_pixels(n, mask),
        coefficients=scatter_pixels(rows, mask),
        albedo=scatter_pixels(albedo, mask),
        residual=scatter_pixels(fit.residual * s, mask),
        weights=scatter_pixels(wr.to(result.weights.dtype), mask),
        mixing=scatter_pixels(W.transpose(1, 2) * s, mask),
        confidence=scatter_pixels(conf, mask),
        basis_brdfs=data.basis,
        depth=dep.full(log["depth"], tuple(mask.shape)),
        info=info,
    )
