"""Stage 1 of the HSH solver: observations.

Takes ``images (L, *S, C)``, ``lights (L, 3)``, optional ``intensities`` and
``mask``; returns an :class:`Observations` state: the pixels inside the mask
flattened to ``(P, L, C)`` (divided by the light intensities, and raw), the
unit lights, the temporal noise sample of the dark background, and the
``(P, L)`` observation weights in {0, 1} from adaptive noise, saturation and
shadow thresholds (:func:`observation_weights`), with the noise level in the
units of the normalised observations.

:func:`prepare_inputs` (validation and flattening) is shared with the
Lambertian baselines.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import torch

from .._checks import check_dirs, check_tensor

__all__ = ["PSInput", "Observations", "prepare_inputs", "observation_weights", "observe", "robust_sigma"]


@dataclass
class PSInput:
    """Flattened photometric-stereo data.

    Attributes:
        y: ``(P, L, C)`` observations divided by the light intensities (only
            pixels inside the mask).
        raw: ``(P, L, C)`` the same observations before the division (saturation
            is a property of the raw sensor values).
        lights: ``(L, 3)`` unit light directions.
        intensities: ``(L, C)``.
        mask: ``(*S)`` bool mask of the pixels in ``y``.
        pixel_shape: ``S``.
        background: ``(Q, C)`` temporal deviations (value minus the pixel's median over the lights) of the
            dark pixels outside the mask, for the noise estimate; may be empty.
    """

    y: torch.Tensor
    raw: torch.Tensor
    lights: torch.Tensor
    intensities: torch.Tensor
    mask: torch.Tensor
    pixel_shape: Tuple[int, ...]
    background: torch.Tensor


def prepare_inputs(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    min_lights: int = 3,
    dtype: Optional[torch.dtype] = None,
) -> PSInput:
    """Validate and flatten ``images (L, *S, C)``, ``lights (L, 3)``, ``intensities``, ``mask (*S)``."""
    check_tensor(images, "images", allow_nonfinite=True)
    if images.dim() < 3:
        raise ValueError(
            f"`images` must have shape (L, H, W, C) or (L, P, C) (a trailing channel axis, C = 1 or 3), "
            f"got {tuple(images.shape)}"
        )
    check_dirs(lights, "lights")
    if lights.dim() != 2:
        raise ValueError(f"`lights` must have shape (L, 3), got {tuple(lights.shape)}")
    L = images.shape[0]
    if lights.shape[0] != L:
        raise ValueError(
            f"`lights` has {lights.shape[0]} rows but `images` has {L} images (first axis); they must match"
        )
    if L < min_lights:
        raise ValueError(f"photometric stereo needs at least {min_lights} lights, got {L}")
    if images.device != lights.device:
        raise ValueError(f"`lights` is on {lights.device} but `images` is on {images.device}")
    dtype = dtype or images.dtype
    images = images.to(dtype)
    lights = lights.to(dtype)
    S = tuple(images.shape[1:-1])
    C = images.shape[-1]
    nrm = lights.norm(dim=-1)
    if bool((nrm < 1e-6).any()):
        raise ValueError("`lights` contains a zero-length direction")
    lights = lights / nrm.unsqueeze(-1)
    if intensities is None:
        e = torch.ones(L, C, dtype=dtype, device=images.device)
    else:
        check_tensor(intensities, "intensities")
        if intensities.dim() == 1:
            intensities = intensities.unsqueeze(-1)
        if intensities.dim() != 2 or intensities.shape[0] != L or intensities.shape[1] not in (1, C):
            raise ValueError(
                f"`intensities` must have shape (L,) or (L, C) = ({L},) or ({L}, {C}), got {tuple(intensities.shape)}"
            )
        e = intensities.to(dtype=dtype, device=images.device).expand(L, C)
        if bool((e <= 0).any()):
            raise ValueError("`intensities` must be > 0")
    if mask is None:
        mask_t = torch.ones(S, dtype=torch.bool, device=images.device)
    else:
        if not isinstance(mask, torch.Tensor):
            raise TypeError(f"`mask` must be a torch.Tensor, got {type(mask).__name__}")
        if tuple(mask.shape) != S:
            raise ValueError(f"`mask` must have the pixel shape of `images` {S}, got {tuple(mask.shape)}")
        mask_t = mask.to(device=images.device).bool()
    if not bool(mask_t.any()):
        raise ValueError("`mask` selects no pixel")
    flat = images.reshape(L, -1, C)
    m = mask_t.reshape(-1)
    raw = flat[:, m].transpose(0, 1).contiguous()  # (P, L, C)
    bg = _dark_background(flat[:, ~m])
    y = raw / e.unsqueeze(0)
    return PSInput(y=y, raw=raw, lights=lights, intensities=e, mask=mask_t, pixel_shape=S, background=bg)


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
    sample = tmax if Qp <= 1_000_000 else tmax[torch.randperm(Qp, device=tmax.device)[:1_000_000]]
    q10 = float(torch.quantile(sample.to(torch.float64), 0.1))
    keep = tmax <= 4.0 * q10 + torch.finfo(tmax.dtype).tiny
    sel = bg[:, keep]  # (L, Qk, C)
    if L >= 3:
        sel = sel - sel.nanmedian(dim=0, keepdim=True).values
    return sel.reshape(-1, C)


def robust_sigma(x: torch.Tensor) -> float:
    """1.4826 * median absolute deviation of a 1-D sample (0 for an empty sample)."""
    if x.numel() == 0:
        return 0.0
    x = x.reshape(-1)
    if x.numel() > 2_000_000:
        idx = torch.linspace(0, x.numel() - 1, 2_000_000, device=x.device).long()
        x = x[idx]
    med = x.median()
    return float(1.4826 * (x - med).abs().median())


def observation_weights(
    y: torch.Tensor,
    raw: torch.Tensor,
    background: Optional[torch.Tensor] = None,
    dark_fraction: float = 0.05,
    noise_sigma: Optional[float] = None,
    saturation: Optional[float] = None,
):
    """Weights ``(P, L)`` in {0, 1} from adaptive dark / saturation thresholds.

    Args:
        y: ``(P, L, C)`` observations divided by the light intensities.
        raw: ``(P, L, C)`` raw observations (same values before the division).
        background: ``(Q, C)`` raw values outside the object mask, used for the
            robust noise estimate ``sigma = 1.4826 MAD`` (ignored if fewer than
            64 pixels or if ``noise_sigma`` is given).
        dark_fraction: an observation is dark if its channel mean is below
            ``dark_fraction`` times the pixel's 75th-percentile brightness
            (attached/cast shadows, grazing light), or below ``3 sigma`` in raw units.
        noise_sigma: raw noise level; ``None``: estimated.
        saturation: raw saturation level; ``None``: detected as a plateau at the
            largest raw value present (at least 3 and at least 0.01% of the
            observations within 0.1% of the maximum); observations with a channel
            at or above 99% of that level are dropped.

    Returns:
        ``(weights (P, L), info dict)``.

    Example:
        >>> y = torch.rand(4, 10, 3)
        >>> w, info = observation_weights(y, y)
        >>> w.shape
        torch.Size([4, 10])
    """
    finite = torch.isfinite(raw).all(-1)
    rawf = torch.where(torch.isfinite(raw), raw, torch.zeros_like(raw))
    info = {}
    if saturation is None:
        mx = float(rawf.max())
        plateau = int((rawf >= mx * (1 - 1e-3)).sum()) if mx > 0 else 0
        if mx > 0 and plateau >= max(3, int(1e-4 * rawf.numel())):
            saturation = mx
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
    q75 = torch.quantile(g, 0.75, dim=1, keepdim=True)
    dark = (g <= dark_fraction * q75) | (rawf.mean(-1) <= 3.0 * noise_sigma)
    w = (finite & ~sat & ~dark).to(y.dtype)
    info["saturated_fraction"] = float(sat.to(y.dtype).mean())
    info["dark_fraction"] = float(dark.to(y.dtype).mean())
    return w, info


@dataclass
class Observations:
    """State after stage 1: the data every later stage reads.

    Attributes:
        data: :class:`PSInput` (``y (P, L, C)``, ``raw``, ``lights (L, 3)``,
            ``intensities (L, C)``, ``mask``, ``pixel_shape``, ``background``).
        weights: ``(P, L)`` observation weights in {0, 1} (0: non-finite,
            saturated or dark).
        sigma_y: noise level in the units of ``data.y`` (raw noise divided by the
            mean light intensity).
        info: diagnostics (noise estimate, saturation level, fractions dropped).
    """

    data: PSInput
    weights: torch.Tensor
    sigma_y: float
    info: Dict[str, float] = field(default_factory=dict)


def observe(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor],
    mask: Optional[torch.Tensor],
    dtype: Optional[torch.dtype],
    dark_fraction: float,
    noise_sigma: Optional[float],
    saturation: Optional[float],
) -> Observations:
    """Validate, flatten and weight the observations (stage 1 of :func:`~torch_hsh.ps.solve_hsh`)."""
    d = prepare_inputs(images, lights, intensities, mask, min_lights=3, dtype=dtype)
    w0, info = observation_weights(d.y, d.raw, d.background, dark_fraction, noise_sigma, saturation)
    info["underdetermined_pixels"] = int((w0.sum(-1) < 3).sum())
    sigma_y = info["noise_sigma"] / d.intensities.mean().item()
    return Observations(data=d, weights=w0, sigma_y=sigma_y, info=info)
