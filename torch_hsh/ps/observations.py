"""Stage 1 of the HSH solver: observations.

Takes ``images (L, *S, C)``, ``lights (L, 3)``, optional ``intensities`` and
``mask``; returns an :class:`Observations` state: the pixels inside the mask
flattened to ``(N, L, C)`` (divided by the light intensities, and raw), the
unit lights, the temporal noise sample of the dark background, and the
``(N, L)`` observation weights in {0, 1} from adaptive noise, saturation and
shadow thresholds (:func:`observation_weights`), with the noise level in the
units of the normalised observations.

:func:`prepare_inputs` (validation and flattening) is shared with the
Lambertian baselines.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import torch

from .._checks import check_dirs, check_shape, check_tensor, warn_user
from ..render.images import _intensities
from ._chunks import row_sum
from .settings import Settings, check_dark_fraction, check_noise_sigma, check_saturation

__all__ = ["PSInput", "Observations", "check_inputs", "prepare_inputs", "observation_weights", "observe", "robust_sigma"]


@dataclass
class PSInput:
    """Flattened photometric-stereo data.

    Attributes:
        y: ``(N, L, C)`` observations divided by the light intensities (only
            pixels inside the mask), in the *storage* dtype: float32 for float32
            (or lower-precision / integer) images, else ``dtype``. Invalid
            observations (non-finite, negative, or excluded by the caller) are 0.
        valid: ``(N, L)`` bool, False for the invalid observations.
        lights: ``(L, 3)`` unit light directions, in ``dtype``.
        intensities: ``(L, C)``, in ``dtype``.
        mask: ``(*S)`` bool mask of the pixels in ``y``.
        pixel_shape: ``S``.
        background: ``(Q, C)`` temporal deviations (value minus the pixel's median over the lights) of the
            dark pixels around the mask, for the noise estimate; may be empty.
        dtype: the compute (and output) dtype.
    """

    y: torch.Tensor
    valid: torch.Tensor
    lights: torch.Tensor
    intensities: torch.Tensor
    mask: torch.Tensor
    pixel_shape: Tuple[int, ...]
    background: torch.Tensor
    dtype: torch.dtype


#: Background ring used for the noise estimate: pixels at most ``_RING_OUTER``
#: and more than ``_RING_INNER`` pixels (Chebyshev distance) from the mask.
#: The ring, not the whole frame, so that the estimate does not depend on how
#: much background a capture or a crop leaves around the object; the inner gap
#: skips the mask's boundary pixels, which blend object and background.
_RING_INNER = 2
_RING_OUTER = 16
# (with fewer than 64 ring pixels, every pixel outside the mask is used)


def _dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Binary dilation of an ``(H, W)`` bool mask by a ``(2r+1)^2`` square."""
    if radius <= 0:
        return mask
    m = mask.to(torch.float32)[None, None]
    m = torch.nn.functional.max_pool2d(m, (2 * radius + 1, 1), stride=1, padding=(radius, 0))
    m = torch.nn.functional.max_pool2d(m, (1, 2 * radius + 1), stride=1, padding=(0, radius))
    return m[0, 0] > 0


def background_ring(mask: torch.Tensor, inner: int = _RING_INNER, outer: int = _RING_OUTER) -> torch.Tensor:
    """Bool map of the background pixels in a ring around ``mask (H, W)`` (all of ``~mask`` for other shapes)."""
    if mask.dim() != 2:
        return ~mask
    return _dilate(mask, outer) & ~_dilate(mask, inner)


def _storage_dtype(images: torch.Tensor, dtype: torch.dtype) -> torch.dtype:
    if images.dtype == torch.float64:
        return dtype
    return torch.float32 if dtype in (torch.float32, torch.float64) else dtype


def check_inputs(images, lights, intensities=None, mask=None, valid=None, min_lights: int = 3) -> Dict[str, int]:
    """Check the inputs of every photometric-stereo solver; returns the sizes ``L`` and ``C``.

    ``images (L, *S, C)`` (float; at least 3 dimensions: lights, pixel shape ``S``, channels),
    ``lights (L, 3)`` on the images' device, at least ``min_lights`` of them; ``intensities (L,)``,
    ``(L, 1)`` or ``(L, C)``; ``mask`` of shape ``S``; ``valid`` of shape ``(L, *S)``. Values (zero
    lights, non-positive intensities, an empty mask) are checked where they are read.
    """
    check_tensor(images, "images", allow_nonfinite=True)
    if images.dim() < 3:  # any pixel shape S: a rank check, not a fixed pattern
        raise ValueError(
            f"`images` must have shape (L, H, W, C) or (L, N, C) (a trailing channel axis, C = 1 or 3), "
            f"got {tuple(images.shape)}"
        )
    L, S, C = images.shape[0], tuple(images.shape[1:-1]), images.shape[-1]
    check_dirs(lights, "lights")
    if lights.dim() == 2 and lights.shape[0] != L:  # say which layout `images` must have, not only the count
        where = [i for i, n in enumerate(images.shape[1:-1], 1) if n == lights.shape[0]]  # not the channel axis
        hint = (f" (if its axis {where[0]}, of size {lights.shape[0]}, holds the lights, move it first)"
                if where else "")
        raise ValueError(
            f"`lights` has {lights.shape[0]} rows but `images` {tuple(images.shape)} has {L} along its first axis, "
            f"the lights axis of the (L, H, W, C) or (L, N, C) layout: the counts disagree{hint}"
        )
    if isinstance(mask, torch.Tensor) and tuple(mask.shape) == tuple(images.shape[1:]):
        raise ValueError(
            f"`images` {tuple(images.shape)} has no channel axis (its pixel shape equals `mask`'s "
            f"{tuple(mask.shape)}): grey images are (L, H, W, 1); use images[..., None]"
        )
    sizes = check_shape(lights, "lights", ("L", 3), sizes={"L": L, "C": C})
    if L < min_lights:
        raise ValueError(f"photometric stereo needs at least {min_lights} lights, got {L}")
    if images.device != lights.device:
        raise ValueError(f"`lights` is on {lights.device} but `images` is on {images.device}")
    if not (images.is_floating_point() or images.dtype in (torch.uint8, torch.int16, torch.int32, torch.uint16)):
        raise TypeError(f"`images` must be a floating-point or unsigned-integer tensor, got {images.dtype}")
    if intensities is not None:
        check_tensor(intensities, "intensities")
        check_shape(intensities, "intensities", ("L",), ("L", "C"), ("L", 1), sizes=sizes)
    if mask is not None:
        if not isinstance(mask, torch.Tensor):
            raise TypeError(f"`mask` must be a torch.Tensor, got {type(mask).__name__}")
        check_shape(mask, "mask", S)  # the pixel shape of `images`
    if valid is not None:
        check_shape(valid, "valid", (L, *S))
    return sizes


def prepare_inputs(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    min_lights: int = 3,
    dtype: Optional[torch.dtype] = None,
    valid: Optional[torch.Tensor] = None,
) -> PSInput:
    """Validate and flatten ``images (L, *S, C)``, ``lights (L, 3)``, ``intensities``, ``mask (*S)``, ``valid (L, *S)``.

    Memory: the pixels inside the mask are gathered one image at a time into
    one ``(N, L, C)`` buffer of the storage dtype (see :class:`PSInput`); the
    input stack is never converted as a whole.
    """
    L = check_inputs(images, lights, intensities, mask, valid, min_lights)["L"]
    dtype = dtype or (images.dtype if images.is_floating_point() else torch.float32)
    store = _storage_dtype(images, dtype)
    dev = images.device
    lights = lights.to(dtype)
    S = tuple(images.shape[1:-1])
    C = images.shape[-1]
    nrm = lights.norm(dim=-1)
    if bool((nrm < 1e-6).any()):
        raise ValueError("`lights` contains a zero-length direction")
    lights = lights / nrm.unsqueeze(-1)
    below = int((lights[:, 2] <= 0).sum())
    if below:  # legal (steep normals can face them) but rare in a capture: most often a flipped frame
        warn_user(f"{below} of the {L} `lights` are at or below the horizon (z <= 0; z points toward the camera): "
                  "they light only normals that face them. If that is not the capture, check the lights' frame "
                  "(a sign flip of z, or of x / y).")
    e = _intensities(intensities, L, C, torch.empty(0, dtype=dtype, device=dev)).to(dev)  # (L, C), as the renderer
    if intensities is not None and bool((e <= 0).any()):
        raise ValueError("`intensities` must be > 0")
    mask_t = torch.ones(S, dtype=torch.bool, device=dev) if mask is None else mask.to(device=dev).bool()
    if not bool(mask_t.any()):
        raise ValueError("`mask` selects no pixel")
    if valid is not None:
        valid = valid.to(device=dev).bool().reshape(L, -1)
    flat = images.reshape(L, -1, C)
    m = mask_t.reshape(-1)
    idx = m.nonzero().squeeze(1)  # int64 pixel indices
    N = idx.numel()
    y = torch.empty(N, L, C, dtype=store, device=dev)
    ok = torch.empty(N, L, dtype=torch.bool, device=dev)
    e_store = e.to(store)
    for j in range(L):  # one image at a time: no full-stack temporaries
        v = flat[j].index_select(0, idx).to(store)
        good = torch.isfinite(v).all(-1) & (v >= 0).all(-1)
        if valid is not None:
            good &= valid[j].index_select(0, idx)
        y[:, j] = torch.where(good.unsqueeze(-1), v / e_store[j], torch.zeros((), dtype=store, device=dev))
        ok[:, j] = good
    ring = background_ring(mask_t).reshape(-1)
    if int(ring.sum()) < 64:  # too small a ring (tiny images): the whole background
        ring = ~m
    bg = _dark_background(flat[:, ring]) if bool(ring.any()) else flat.new_zeros(0, C)
    return PSInput(y=y, valid=ok, lights=lights, intensities=e, mask=mask_t, pixel_shape=S, background=bg, dtype=dtype)


def _dark_background(bg: torch.Tensor) -> torch.Tensor:
    """Temporal deviations ``(Q, C)`` of the background pixels that are really background.

    ``bg (L, Qp, C)``: every pixel outside the mask. A mask may leave parts of
    the object outside (a region of interest, a random subset): their values
    change with the light and would inflate the noise estimate. Kept: pixels
    whose brightest value over all lights is at most 4x the 10th percentile of
    that maximum over the background (true background is the darkest part of
    the frame). Returned: each kept value minus its pixel's median over the
    lights, so a static but spatially varying dark background (a table, a
    wall) does not count as noise.
    """
    L, Qp, C = bg.shape
    if Qp == 0:
        return bg.reshape(-1, C)
    fin = torch.where(torch.isfinite(bg), bg, torch.zeros_like(bg))
    tmax = fin.abs().amax(dim=(0, 2))  # (Qp,)
    q10 = float(torch.quantile(strided_sample(tmax, 1_000_000).to(torch.float64), 0.1))
    keep = tmax <= 4.0 * q10 + torch.finfo(tmax.dtype).tiny
    sel = bg[:, keep]  # (L, Qk, C)
    if L >= 3:
        sel = sel - sel.nanmedian(dim=0, keepdim=True).values
    return sel.reshape(-1, C)


#: Largest input of ``torch.quantile`` (it refuses more than 2**24 elements).
QUANTILE_MAX_ELEMENTS = 2**24


def strided_sample(x: torch.Tensor, n: int) -> torch.Tensor:
    """At most ``n`` evenly spaced elements of a 1-D tensor, first and last included (deterministic).

    Indices are computed in int64 (``i * (N - 1) // (n - 1)``): a float32
    ``linspace`` rounds the last index past the end once ``N > 2**24``.
    """
    N = x.numel()
    if N <= n:
        return x
    idx = torch.arange(n, dtype=torch.int64, device=x.device) * (N - 1) // (n - 1)
    return x[idx]


def row_quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    """``torch.quantile(x, q, dim=1, keepdim=True)`` for ``x (N, L)`` of any size (row chunks below 2**24 elements)."""
    N, L = x.shape
    rows = max(1, QUANTILE_MAX_ELEMENTS // max(L, 1))
    if N <= rows:
        return torch.quantile(x, q, dim=1, keepdim=True)
    return torch.cat([torch.quantile(x[s : s + rows], q, dim=1, keepdim=True) for s in range(0, N, rows)])


def robust_sigma(x: torch.Tensor) -> float:
    """1.4826 * median absolute deviation of a 1-D sample (0 for an empty sample)."""
    if x.numel() == 0:
        return 0.0
    x = strided_sample(x.reshape(-1), 2_000_000)
    med = x.median()
    return float(1.4826 * (x - med).abs().median())


def detect_saturation(raw_max: float, count_near_max: int, total: int) -> Optional[float]:
    """The saturation level if the largest raw value is a plateau (>= 3 and >= 0.01 % of the values within 0.1 %)."""
    if raw_max > 0 and count_near_max >= max(3, int(1e-4 * total)):
        return raw_max
    return None


def observation_weights(
    y: torch.Tensor,
    raw: torch.Tensor,
    background: Optional[torch.Tensor] = None,
    dark_fraction: float = 0.05,
    noise_sigma: Optional[float] = None,
    saturation: Optional[float] = None,
):
    """Weights ``(N, L)`` in {0, 1} from validity and adaptive dark / saturation thresholds.

    Args:
        y: ``(N, L, C)`` observations divided by the light intensities.
        raw: ``(N, L, C)`` raw observations (same values before the division).
        background: ``(Q, C)`` temporal deviations of background pixels, used for
            the robust noise estimate ``sigma = 1.4826 MAD`` (ignored if fewer than
            64 pixels or if ``noise_sigma`` is given).
        dark_fraction: an observation is dark if its channel mean is below
            ``dark_fraction`` times the pixel's 75th-percentile brightness
            (attached/cast shadows, grazing light), or below ``3 sigma`` in raw units.
        noise_sigma: raw noise level; ``None``: estimated.
        saturation: raw saturation level; ``None``: detected as a plateau at the
            largest raw value present (at least 3 and at least 0.01% of the
            observations within 0.1% of the maximum); observations with a channel
            at or above 99% of that level are dropped.

    Observations with a non-finite or negative channel are invalid (weight 0)
    and do not enter any statistic.

    Returns:
        ``(weights (N, L), info dict)``.

    Raises:
        ValueError: ``dark_fraction`` outside ``[0, 1)``, a negative or
            non-finite ``noise_sigma``, a non-positive or non-finite ``saturation``.

    Example:
        >>> y = torch.rand(4, 10, 3)
        >>> w, info = observation_weights(y, y)
        >>> w.shape
        torch.Size([4, 10])
    """
    check_dark_fraction(dark_fraction), check_noise_sigma(noise_sigma), check_saturation(saturation)
    finite = (torch.isfinite(raw) & (raw >= 0)).all(-1) & torch.isfinite(y).all(-1)
    rawf = torch.where(finite.unsqueeze(-1), raw, torch.zeros_like(raw))
    info = {}
    if saturation is None:
        mx = float(rawf.max())
        saturation = detect_saturation(mx, int((rawf >= mx * (1 - 1e-3)).sum()) if mx > 0 else 0, rawf.numel())
    sat = torch.zeros_like(finite)
    if saturation is not None:
        sat = (rawf >= 0.99 * float(saturation)).any(-1)
        info["saturation_level"] = float(saturation)
    if noise_sigma is None:
        noise_sigma = 0.0
        if background is not None and background.shape[0] >= 64:
            bg = background[torch.isfinite(background).all(-1)]
            noise_sigma = robust_sigma(bg)
    info["noise_sigma"] = float(noise_sigma)
    g = torch.where(finite, y.mean(-1), torch.zeros_like(y[..., 0]))
    q75 = row_quantile(g, 0.75)
    dark = (g <= dark_fraction * q75) | (rawf.mean(-1) <= 3.0 * noise_sigma)
    w = (finite & ~sat & ~dark).to(y.dtype)
    info["saturated_fraction"] = float(sat.to(y.dtype).mean())
    info["dark_fraction"] = float(dark.to(y.dtype).mean())
    return w, info


def _warn_bright_background(d: PSInput, e: torch.Tensor, chunks, noise_sigma: float, dark: float) -> None:
    """Warn when the noise level estimated around the mask is of the order of the signal (at least 20 % of the
    median valid observation: observations count as dark up to 3x that level). On the shared captures the
    estimate is 3-6 % of the median observation; renderings with a lit background gave 30-52 %."""
    per = max(1, 200_000 // max(len(chunks), 1))
    parts = [strided_sample((d.y[sl] * e).mean(-1)[d.valid[sl]], per) for sl in chunks]
    vals = torch.cat(parts) if parts else d.y.new_zeros(0)
    med = float(vals.median()) if vals.numel() else 0.0
    if med > 0 and noise_sigma < 0.2 * med:
        return  # the signal is well above the noise: the pixels are dark for another reason
    warnings.warn(
        f"the noise level estimated from the pixels around the mask ({noise_sigma:.3g}) is "
        f"{noise_sigma / med if med > 0 else float('inf'):.0%} of the median observation, so {dark:.0%} of the "
        "observations count as dark and are dropped. "
        "The background around `mask` is not dark (a rendering without a dark background, or a mask that "
        "leaves part of the object out?): pass `noise_sigma` (0 for noise-free renderings) or set the images "
        "to 0 outside `mask`.", RuntimeWarning, stacklevel=4)


@dataclass
class Observations:
    """State after stage 1: the data every later stage reads.

    Attributes:
        data: :class:`PSInput` (``y (N, L, C)`` divided by the light intensities
            *and by* ``scale``, ``valid``, ``lights (L, 3)``, ``intensities (L,
            C)``, ``mask``, ``pixel_shape``, ``background``, ``dtype``).
        weights: ``(N, L)`` observation weights in {0, 1} (0: invalid,
            saturated or dark), in the storage dtype of ``data.y``.
        sigma_y: noise level in the units of ``data.y``.
        scale: the global scale divided out of ``data.y`` (a power of two near
            the median valid observation, so the division is exact): the solver
            works at unit brightness whatever the units of the images, and the
            result's coefficients are multiplied back by it.
        typical: median valid observation after the division (close to 1).
        info: diagnostics (noise estimate, saturation level, fractions dropped).
    """

    data: PSInput
    weights: torch.Tensor
    sigma_y: float
    scale: float = 1.0
    typical: float = 1.0
    info: Dict[str, float] = field(default_factory=dict)


#: Pixels per chunk of the stage-1 passes (bounded temporaries).
_CHUNK = 16384


def observe(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor],
    mask: Optional[torch.Tensor],
    cfg: Settings,
) -> Observations:
    """Validate, flatten, weight and normalise the observations (stage 1 of :func:`~torch_hsh.ps.solve_hsh`).

    Processed in chunks of pixels; the saturation plateau and the noise are
    global statistics, the dark threshold is per pixel. Reads ``dtype``, ``valid`` and the thresholds of ``cfg``.
    """
    noise_sigma, saturation = cfg.noise_sigma, cfg.saturation
    d = prepare_inputs(images, lights, intensities, mask, min_lights=3, dtype=cfg.dtype, valid=cfg.valid)
    N, L, C = d.y.shape
    e = d.intensities.to(d.y.dtype).unsqueeze(0)  # (1, L, C)
    chunks = [slice(s, min(N, s + _CHUNK)) for s in range(0, N, _CHUNK)]
    if saturation is None:
        mx = max(float((d.y[sl] * e).max()) for sl in chunks)
        near = sum(int((d.y[sl] * e >= mx * (1 - 1e-3)).sum()) for sl in chunks) if mx > 0 else 0
        saturation = detect_saturation(mx, near, d.y.numel())
    if noise_sigma is None:
        noise_sigma = 0.0
        bg = d.background
        if bg.shape[0] >= 64:
            noise_sigma = robust_sigma(bg[torch.isfinite(bg).all(-1)])
    w0 = torch.empty(N, L, dtype=d.y.dtype, device=d.y.device)
    n_sat = n_dark = 0
    for sl in chunks:
        w, inf = observation_weights(d.y[sl], d.y[sl] * e, None, cfg.dark_fraction, noise_sigma, saturation)
        w0[sl] = w * d.valid[sl]
        n_sat += inf["saturated_fraction"] * w.numel()
        n_dark += inf["dark_fraction"] * w.numel()
    info: Dict[str, float] = {}
    if saturation is not None:
        info["saturation_level"] = float(saturation)
    info["noise_sigma"] = float(noise_sigma)
    info["noise_background_pixels"] = float(d.background.shape[0] // max(L, 1))
    info["saturated_fraction"] = n_sat / max(N * L, 1)
    info["dark_fraction"] = n_dark / max(N * L, 1)
    info["invalid_fraction"] = (N * L - int(row_sum(d.valid).sum())) / max(N * L, 1)  # no (N, L) negation
    info["underdetermined_pixels"] = int((w0.sum(-1) < 3).sum())
    if cfg.noise_sigma is None and noise_sigma > 0:
        _warn_bright_background(d, e, chunks, noise_sigma, info["dark_fraction"])
    # global scale: a power of two near the median valid observation (exact division)
    # (sampled chunk by chunk: a full (N, L) channel mean would be the largest temporary of the solve)
    per = max(1, 2_000_000 // max(len(chunks), 1))
    parts = [strided_sample(d.y[sl].mean(-1)[w0[sl] > 0], per) for sl in chunks]
    g = torch.cat(parts) if parts and sum(p.numel() for p in parts) > 0 else d.y.new_ones(1)
    med = float(g.abs().median())
    scale = 2.0 ** round(math.log2(med)) if med > 0 and math.isfinite(med) else 1.0
    if scale != 1.0:
        d.y.div_(scale)
    info["image_scale"] = scale
    sigma_y = info["noise_sigma"] / d.intensities.mean().item() / scale
    return Observations(data=d, weights=w0, sigma_y=sigma_y, scale=scale, typical=med / scale if med > 0 else 1.0, info=info)
