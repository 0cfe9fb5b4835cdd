r"""Light visibility (cast shadows) of a reconstructed depth map.

Frame and units as in :mod:`torch_hsh.surface.integrate`: DiLiGenT frame
(x right, y up, z toward the camera), orthographic, depth = height ``z`` in
pixel units, lights ``(L, 3)`` pointing toward the light.

Method: the library's own ray marcher,
:func:`torch_hsh.render.visibility.cast_shadow_mask` (one-pixel steps along the light's
image-plane direction, bilinear height samples). Only the masked surface
occludes: pixels outside the mask are given the lowest masked height, which
is below every ray (rays start on the surface and rise), so nothing outside
the mask ever occludes and the march length is set by the masked height
range alone. Visibility of pixels outside the mask is reported as ``True``
(nothing known occludes them).

Memory is bounded: the output is one ``(L, H, W)`` bool tensor (96 MB for
96 lights at 1024^2); lights are marched ``chunk_size`` at a time (the marcher's
own temporaries are ``O(H W)``). Work is ``O(L H W steps)``. Device
agnostic (the depth's device).
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from .._checks import check_dirs, check_shape, check_tensor
from ..render.visibility import cast_shadow_mask
from .integrate import _check_mask

__all__ = ["light_visibility"]


def light_visibility(
    depth: torch.Tensor,
    mask: Optional[torch.Tensor],
    lights: torch.Tensor,
    bias: float = 0.0,
    n_steps: Optional[int] = None,
    chunk_size: int = 8,
) -> torch.Tensor:
    r"""Per-light, per-pixel visibility of a depth map (``False`` = cast shadow).

    Args:
        depth: ``(H, W)`` heights in pixel units (z toward the camera), e.g.
            from :func:`torch_hsh.surface.integrate_normals`; values outside
            ``mask`` are ignored (NaN allowed there).
        mask: ``(H, W)`` bool, the surface (``None``: every pixel).
        lights: ``(L, 3)`` directions toward the lights (normalised here).
        bias: an occluder must rise this many pixels above the ray to count
            (``>= 0``); a bias of a few tenths of a pixel keeps the noise of
            an integrated depth from shadowing pixels near grazing lights.
        n_steps: optional cap on the march length (pixels).
        chunk_size: lights marched per call of the marcher (memory bound).

    Returns:
        ``(L, H, W)`` bool on ``depth``'s device: ``True`` where light ``l``
        reaches pixel ``p`` (and everywhere outside the mask); lights at or
        below the horizon (``l_z <= 0``) reach no masked pixel.

    Example:
        >>> z = torch.zeros(16, 32); z[:, 16:] = 8.0  # a wall on the right half
        >>> m = torch.ones(16, 32, dtype=torch.bool)
        >>> vis = light_visibility(z, m, torch.tensor([[0.6, 0.0, 0.8], [-0.6, 0.0, 0.8]]))
        >>> bool(vis[0, 8, 12]), bool(vis[0, 8, 2]), bool(vis[1, 8, 12])  # wall shades its foot from the right
        (False, True, True)
    """
    check_tensor(depth, "depth", allow_nonfinite=True)
    check_shape(depth, "depth", ("H", "W"))
    m = _check_mask(mask, tuple(depth.shape), depth.device)
    check_dirs(lights, "lights")
    check_shape(lights, "lights", ("L", 3))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}")
    if isinstance(bias, bool) or not isinstance(bias, (int, float)) or not math.isfinite(bias) or bias < 0:
        raise ValueError(f"`bias` must be a finite number >= 0, got {bias!r}")
    L = lights.shape[0]
    H, W = depth.shape
    vis = torch.ones(L, H, W, dtype=torch.bool, device=depth.device)
    if not bool(m.any()) or L == 0:
        return vis
    d = depth.detach()
    inside = d[m]
    if not bool(torch.isfinite(inside).all()):
        raise ValueError("`depth` contains NaN or Inf inside `mask`")
    hgt = torch.where(m, d, inside.min().expand_as(d))
    lts = lights.detach().to(device=depth.device, dtype=depth.dtype)
    for s in range(0, L, chunk_size):
        v = cast_shadow_mask(hgt, lts[s : s + chunk_size], pixel_size=1.0, n_steps=n_steps, bias=float(bias))
        vis[s : s + chunk_size] = v | ~m
    return vis
