"""Input handling shared by the photometric-stereo solvers."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import torch

from .._checks import check_dirs, check_same, check_tensor

__all__ = ["PSInput", "prepare_inputs", "scatter_pixels", "angular_error", "tangent_frame"]


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


def scatter_pixels(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Put ``(P, ...)`` per-pixel values back into a ``(*S, ...)`` map, zero outside ``mask``."""
    out = torch.zeros(mask.numel(), *values.shape[1:], dtype=values.dtype, device=values.device)
    out[mask.reshape(-1)] = values
    return out.reshape(*mask.shape, *values.shape[1:])


def angular_error(
    normals: torch.Tensor, reference: torch.Tensor, mask: Optional[torch.Tensor] = None
) -> torch.Tensor:
    """Per-pixel angle in degrees between two normal maps: ``arccos(clamp(n . n_ref, -1, 1))``.

    Args:
        normals: ``(..., 3)`` (normalised here).
        reference: ``(..., 3)`` same shape.
        mask: optional ``(...)`` bool; the error is 0 outside.

    Returns:
        ``(...)`` angles in degrees.

    Example:
        >>> angular_error(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 1.0, 0.0]]))
        tensor([90.])
    """
    check_dirs(normals, "normals")
    check_dirs(reference, "reference")
    if normals.shape != reference.shape:
        raise ValueError(f"`normals` {tuple(normals.shape)} and `reference` {tuple(reference.shape)} must have the same shape")
    a = torch.nn.functional.normalize(normals, dim=-1)
    b = torch.nn.functional.normalize(reference.to(normals.dtype), dim=-1)
    ang = torch.rad2deg(torch.arccos((a * b).sum(-1).clamp(-1.0, 1.0)))
    if mask is not None:
        ang = torch.where(mask.to(ang.device).bool(), ang, torch.zeros_like(ang))
    return ang


def tangent_frame(n: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents orthogonal to unit normals ``n (P, 3)`` (Duff et al. 2017, branchless)."""
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    t2 = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t1, t2


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


def deg(x: float) -> float:
    return math.degrees(x)
