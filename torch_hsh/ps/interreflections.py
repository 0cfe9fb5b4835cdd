"""One bounce of interreflection, estimated from a solve's surface and removed from the images.

Around the solve (``solve_hsh(..., interreflections=R)``, ``torch-hsh ps --interreflections``):

1. solve;
2. the surface of that solve: its normals integrated with :func:`torch_hsh.surface.integrate_normals`
   (bilateral, so that the depth keeps its jumps; :data:`~torch_hsh.ps.settings.DEPTH_START_ITERATIONS`
   re-weightings, as for the whole-surface stage's start);
3. :func:`one_bounce`: the light that every pixel receives from the other pixels of the object, once
   reflected, under every light;
4. subtract it from the images and run the per-pixel stages again from the solve's normals, with its
   basis BRDFs and robust scale kept (shared model; as the cast-shadow loop does) and without the cone
   search (the first solve chose each pixel's basin);
5. the safeguard (``interreflection_safeguard``, on by default): keep that solve only if its mean
   confidence (:attr:`HSHResult.confidence`: the robust weights and the fit residuals, at the first
   solve's robust scale) did not fall. Images that really hold a bounce fit the local BRDF model better
   once it is removed; subtracting a bounce that is not there (a renderer without interreflections)
   makes them fit worse. Otherwise the first solve is returned.

Model of step 3 (orthographic view along ``v = +z``, pixel units, DiLiGenT frame; ``p`` receives,
``q`` emits). The surface point of pixel ``q`` is ``X_q = (x_q, y_q, z_q)`` with ``x`` to the right,
``y`` up and ``z = depth``. Its radiance toward ``p`` is taken to be its observed value ``I_l(q)``
(a Lambertian emitter: the value seen by the camera is the value seen by the neighbour). ``p``
reflects with the directional albedo ``A_p`` of the solve (:attr:`HSHResult.albedo`), as a diffuse
receiver::

    indirect_l(p) = A_p * sum_q F(p, q) I_l(q),
    F(p, q) = max(0, n_p . d) max(0, -n_q . d) dA_q / (pi r^4),    d = X_q - X_p,  r = |d|,

where ``dA_q = s^2 / max(n_q . v, 0.2)`` is the area of the surface that a cell of ``s x s`` pixels
around ``q`` covers (``s`` = ``stride``). ``q`` runs over the masked pixels of a disc of ``radius``
pixels around ``p``, every ``stride``-th row and column within ``near`` pixels and a stride that doubles
with every doubling of the distance beyond. By default there is no occlusion test between ``p`` and
``q``: inside a 16-pixel disc a concave surface mostly sees itself (``occlusion=True`` tests the depth
along the segment; it matters for larger discs). ``F`` is the point-to-area form factor.
For coplanar points both cosines vanish, so a plane receives nothing. The receiver is diffuse
(``A_p / pi`` times the incident irradiance), which underestimates a specular receiver's bounce
toward the camera, and the emitter is Lambertian. This is one bounce, from the observed radiance.

Measured on the suite (docs/photometric_stereo.md, "Interreflections"; 5 seeds, with the safeguard): the
folded plastic -0.81 deg, the grooved conductor -0.22, the cat -0.17, the bumpy field -0.08, harvest -0.04;
the bunny and the demo (renderers without interreflections) are rejected on every seed and keep their first
solve; the bowl +0.01. It costs about 1.7x the time of the solve, so on its own it is off by default; the
whole-surface stage (``refine_surface``) brings one round unless ``interreflections`` is set (the suite's mean
fell by 0.15 deg against the stage alone, the cat's from 5.04 to 4.88).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING, Callable, Optional, Tuple

import torch

from ._geometry import start_depth
from .calibration import report_first_calibration, reuse_calibration
from .settings import Settings
from .settings import MAX_INTERREFLECTION_RADIUS as MAX_RADIUS

if TYPE_CHECKING:  # pragma: no cover
    from .result import HSHResult

__all__ = ["MAX_OCCLUSION_SAMPLES", "MAX_RADIUS", "NEAR_RADIUS", "one_bounce",
           "interreflection_loop"]

#: Most depth samples per pair in :func:`one_bounce`'s occlusion test.
MAX_OCCLUSION_SAMPLES = 32
#: Pixels around a receiver within which :func:`one_bounce` samples every ``stride``-th row and column;
#: beyond them the stride doubles with the distance.
NEAR_RADIUS = 16


def _disc_samples(radius: int, stride: int, near: int):
    """``(dy, dx, weight)`` of the emitter samples around a receiver: the multiples of ``stride`` within
    ``near`` pixels, then of ``2 * stride`` up to ``2 * near``, of ``4 * stride`` up to ``4 * near``, ...,
    out to ``radius``; ``weight`` is the sample's cell area over ``stride**2``. Each grid is symmetric about
    the receiver."""
    out = []
    step, lo, hi = stride, 0, near
    while lo < radius:
        hi = min(hi, radius)
        grid = range(-(hi // step) * step, hi + 1, step)
        w = float((step // stride) ** 2)
        out += [(dy, dx, w) for dy in grid for dx in grid
                if (dy or dx) and lo * lo < dy * dy + dx * dx <= hi * hi]
        step, lo, hi = 2 * step, hi, 2 * hi
    return out


def one_bounce(
    images: torch.Tensor,
    normals: torch.Tensor,
    depth: torch.Tensor,
    mask: torch.Tensor,
    albedo: torch.Tensor,
    *,
    radius: int = 16,
    stride: int = 2,
    near: Optional[int] = NEAR_RADIUS,
    occlusion: bool = False,
    chunk_size: int = 16,
) -> torch.Tensor:
    """One bounce of interreflection under every light (see the module docstring for the model).

    Args:
        images: ``(L, H, W, C)`` images at unit light intensity (the emitted radiance of every pixel).
        normals: ``(H, W, 3)`` unit normals (DiLiGenT frame).
        depth: ``(H, W)`` height in pixel units (z toward the camera); non-finite values count as
            outside the mask.
        mask: ``(H, W)`` bool.
        albedo: ``(H, W, C)`` directional albedo of the receiving pixels.
        radius: pixels; the disc of emitters around every receiver.
        stride: every ``stride``-th row and column of that disc (each standing for ``stride**2`` pixels),
            within ``near`` pixels of the receiver.
        near: pixels; beyond them the stride doubles at every doubling of the distance (``2 * stride``
            up to ``2 * near``, ``4 * stride`` up to ``4 * near``, ...; each sample standing for its
            stride squared), so the work grows with the logarithm of ``radius`` instead of its square.
            The form factor falls off as ``1 / r**2`` there, and the emitters' sum is smooth. ``None``:
            ``stride`` everywhere.
        occlusion: test every pair for a surface between them: the depth at the pixels that the
            segment from ``p`` to ``q`` crosses (one per step along its longer axis, at most
            :data:`MAX_OCCLUSION_SAMPLES`) must not rise above the segment by more than half a pixel.
            Pixels outside the mask do not occlude.
        chunk_size: lights per pass (memory: about ``3 * chunk_size * H * W * C`` values besides the
            output; the form factors are recomputed per pass, one ``(H, W)`` map at a time).

    Non-finite image values (missing observations) emit nothing. Integer and half-precision images are
    computed in float32.

    Returns:
        ``(L, H, W, C)`` the estimated one-bounce radiance toward the camera, zero outside the mask,
        in float32 or float64 (the images' dtype where it is one of these).

    Example:
        >>> H = W = 8
        >>> flat = one_bounce(torch.ones(2, H, W, 1), torch.tensor([0.0, 0.0, 1.0]).expand(H, W, 3),
        ...                   torch.zeros(H, W), torch.ones(H, W, dtype=torch.bool), torch.ones(H, W, 1))
        >>> float(flat.abs().max())  # a plane does not light itself
        0.0
    """
    if images.dim() != 4:
        raise ValueError(f"`images` must be (L, H, W, C), got {tuple(images.shape)}")
    L, H, W, C = images.shape
    for name, t, shape in (("normals", normals, (H, W, 3)), ("depth", depth, (H, W)), ("mask", mask, (H, W)),
                           ("albedo", albedo, (H, W, C))):
        if tuple(t.shape) != shape:
            raise ValueError(f"`{name}` must have shape {shape} to match `images` {tuple(images.shape)}, "
                             f"got {tuple(t.shape)}")
    if isinstance(radius, bool) or int(radius) != radius or not 1 <= radius <= MAX_RADIUS:
        raise ValueError(f"`radius` must be an integer in [1, {MAX_RADIUS}], got {radius!r}")
    if isinstance(stride, bool) or int(stride) != stride or not 1 <= stride <= radius:
        raise ValueError(f"`stride` must be an integer in [1, radius], got {stride!r}")
    if near is not None and (isinstance(near, bool) or int(near) != near or near < 1):
        raise ValueError(f"`near` must be None or an integer >= 1, got {near!r}")
    if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be an integer >= 1, got {chunk_size!r}")
    dev = images.device
    dt = images.dtype if images.dtype in (torch.float32, torch.float64) else torch.float32  # ints, half: float32
    m = mask.to(dev).bool() & torch.isfinite(depth.to(dev))
    zero = torch.zeros((), device=dev, dtype=dt)
    z = torch.where(m, depth.to(dev, dt), zero)
    n = torch.where(m[..., None], normals.to(dev, dt), zero)
    area = (stride * stride) / n[..., 2].clamp_min(0.2) * m
    R, s = int(radius), int(stride)
    pad = (R, R, R, R)
    zp = torch.nn.functional.pad(z, pad)
    np_ = torch.nn.functional.pad(n.permute(2, 0, 1), pad)  # (3, H + 2R, W + 2R)
    ap = torch.nn.functional.pad(area, pad)
    offsets = _disc_samples(R, s, R if near is None else int(near))
    # occluders: the depth inside the mask; outside it nothing occludes
    zo = torch.nn.functional.pad(torch.where(m, z, torch.full_like(z, -torch.inf)), pad, value=-math.inf)

    def factor(dy: int, dx: int) -> torch.Tensor:
        """cos_p cos_q dA_q / (pi r^2) of every receiver p and its emitter q = p + (dy, dx) (rows, columns)."""
        sl = (slice(R + dy, R + dy + H), slice(R + dx, R + dx + W))
        dz = zp[sl] - z
        # d = X_q - X_p = (dx, -dy, dz): image rows grow downward, y grows upward
        dot_p = n[..., 0] * dx - n[..., 1] * dy + n[..., 2] * dz
        dot_q = -(np_[0][sl] * dx - np_[1][sl] * dy + np_[2][sl] * dz)
        r2 = dz * dz + float(dx * dx + dy * dy)
        f = dot_p.clamp_min(0) * dot_q.clamp_min(0) * ap[sl] / (math.pi * r2 * r2) * m
        if occlusion:  # the pixels that the segment crosses, one per row or column (its longer axis)
            steps = max(abs(dx), abs(dy))
            for i in sorted({round(j * steps / min(steps, MAX_OCCLUSION_SAMPLES)) for j in
                             range(1, min(steps, MAX_OCCLUSION_SAMPLES))}):
                oy, ox = round(i * dy / steps), round(i * dx / steps)
                tt = i / steps  # where that pixel sits along the segment
                f = f * (zo[R + oy:R + oy + H, R + ox:R + ox + W] <= z + tt * dz + 0.5)
        return f

    out = torch.zeros(images.shape, device=dev, dtype=dt)
    alb = albedo.to(dev, dt)
    for l0 in range(0, L, chunk_size):  # memory: the chunk's padded source and sum, one factor map at a time
        img = images[l0:l0 + chunk_size].to(dt)
        img = torch.where(m[None, ..., None] & torch.isfinite(img), img, zero)  # missing observations emit nothing
        k = img.shape[0]
        src = torch.nn.functional.pad(img.permute(1, 2, 0, 3).reshape(H, W, k * C).permute(2, 0, 1), pad)
        acc = torch.zeros((k * C, H, W), device=dev, dtype=dt)
        for dy, dx, w in offsets:
            f = factor(dy, dx)
            acc.addcmul_(src[:, R + dy:R + dy + H, R + dx:R + dx + W], f if w == 1 else f * w)
        out[l0:l0 + k] = acc.reshape(k, C, H, W).permute(0, 2, 3, 1) * alb
    return out


def interreflection_loop(solve: Callable, images: torch.Tensor, lights: torch.Tensor, intensities, mask,
                         cfg: Settings) -> Tuple["HSHResult", torch.Tensor, Optional[torch.Tensor]]:
    """``cfg.interreflections`` rounds of: solve, estimate one bounce from the solve's surface, subtract it.

    ``solve(images, lights, intensities, mask, cfg)`` runs the solver (the cast-shadow loop or the
    stages). Needs ``(L, H, W, C)`` images. The bounce is subtracted in the images' own units (times
    the light intensities), from the valid observations only: a missing (non-finite or negative) or
    saturated observation (at or above 0.99 of ``cfg.saturation`` or of the level the first solve
    detected) stays as it was, so the re-solve drops the same ones. Integer and half-precision images
    are corrected in float32. Returns ``(result, images, intensities)``: the last solve and the images
    it saw, for a later stage. With ``cfg.interreflection_safeguard`` a round is kept only if the mean
    confidence of its solve is not below that of the solve before it; the loop stops at the first round
    that is not kept, and returns the solve and images before it. The result's ``info`` gains
    ``interreflection_rounds`` (rounds kept), ``interreflection_fraction`` (the estimated bounce over
    the images' sum inside the mask, last round), ``interreflection_time_s``,
    ``interreflection_confidence_before`` (first solve) / ``_after`` (last round's solve) and
    ``interreflection_accepted`` (1 or 0: the last round's decision, also when the safeguard is off).
    """
    from ..render.images import _intensities
    if images.dim() != 4:
        raise ValueError("`interreflections` (one round by default with `refine_surface`) needs images of shape "
                         f"(L, H, W, C), got {tuple(images.shape)}")
    res = solve(images, lights, intensities, mask, cfg)
    dt = images.dtype if images.dtype in (torch.float32, torch.float64) else torch.float32
    L, C = images.shape[0], images.shape[-1]
    e = _intensities(intensities, L, C, torch.empty(0, dtype=dt, device=images.device))
    e = e.to(images.device, dt).reshape(L, 1, 1, C)
    raw = images.to(dt)
    keep = ~torch.isfinite(raw) | (raw < 0)  # missing observations: not corrected
    level = cfg.saturation if cfg.saturation is not None else res.info.get("saturation_level")
    if level is not None:
        keep |= raw >= 0.99 * float(level)
    unit = raw / e  # the emitted radiance at unit light intensity
    seen = images
    t_total, frac, rounds = 0.0, 0.0, 0
    conf_first = conf = _mean_confidence(res)
    conf_last, accepted = conf, True
    for _ in range(int(cfg.interreflections or 0)):  # None is resolved by Settings; 0 here only for mypy
        t0 = time.perf_counter()
        m = res.mask.to(images.device)
        box, depth = start_depth(res.normals, m)  # on the mask's box: nothing outside it emits or receives
        bounce = torch.zeros_like(unit)
        bounce[(slice(None),) + box] = one_bounce(unit[(slice(None),) + box], res.normals[box].detach(), depth,
                                                  m[box], res.albedo[box].detach(), radius=cfg.interreflection_radius)
        corrected = torch.where(keep, raw, (raw - bounce * e).clamp_min(0))
        ok = m[None] & torch.isfinite(unit).all(-1)
        frac = float(bounce[ok].sum() / unit[ok].sum().clamp_min(1e-30))
        del bounce
        t_total += time.perf_counter() - t0
        # the first solve's calibration is kept: a fresh one lands in another basin on some seeds, which moved
        # harvest by -0.6 to +2.5 deg while the bounce is 1.5 % of its light (docs/photometric_stereo.md)
        # and no cone search: the first solve chose every pixel's basin, and the bounce is a small change
        kw = dict(interreflections=0, init=res.normals.to(dt), search_angles=(), **reuse_calibration(res))
        first_info = dict(res.info)
        new = solve(corrected, lights, intensities, mask, dataclasses.replace(cfg, **kw))
        report_first_calibration(new, first_info)
        conf_last = _mean_confidence(new)
        accepted = conf_last >= conf  # the safeguard: the corrected images must fit the model no worse
        if accepted or not cfg.interreflection_safeguard:
            res, seen, conf, rounds = new, corrected, conf_last, rounds + 1
        if not accepted:
            break
    res.info["interreflection_rounds"] = float(rounds)
    res.info["interreflection_fraction"] = frac
    res.info["interreflection_time_s"] = t_total
    res.info["interreflection_confidence_before"] = conf_first
    res.info["interreflection_confidence_after"] = conf_last
    res.info["interreflection_accepted"] = float(accepted)
    return res, seen, intensities


def _mean_confidence(res: "HSHResult") -> float:
    """Mean of the result's confidence over its mask: the safeguard's measure of how well the model fits
    (NaN without a confidence map, so that the safeguard keeps the earlier solve)."""
    conf = res.confidence
    if conf is None:
        return float("nan")
    m = res.mask.to(conf.device)
    return float(conf[m].mean()) if bool(m.any()) else float("nan")
