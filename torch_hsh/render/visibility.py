r"""Cast shadows of a height field: which pixel sees which light, by ray marching.

Frame (the DiLiGenT frame): ``x`` to the right, ``y`` up, ``z`` toward the camera,
orthographic view; image row 0 is the **top**, pixel ``(row, col)`` is at
``x = col * pixel_size``, ``y = -row * pixel_size``; heights are ``z`` values in the
unit of ``pixel_size``. :func:`torch_hsh.surface.light_visibility` applies this to a
reconstructed depth map (chunked over lights, with a bias for noisy depth).
"""
from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F

from .._checks import check_count, check_dirs, check_shape, check_tensor

__all__ = ["cast_shadow_mask"]


def _positive(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise TypeError(f"`{name}` must be a positive number, got {x!r}")
    if not math.isfinite(x) or x <= 0:
        raise ValueError(f"`{name}` must be a positive finite number, got {x}")
    return float(x)


def cast_shadow_mask(
    height: torch.Tensor,
    lights: torch.Tensor,
    pixel_size: float = 1.0,
    n_steps: Optional[int] = None,
    bias: float = 0.0,
) -> torch.Tensor:
    r"""Light visibility of every pixel of a height field (cast shadows), by ray marching.

    For light ``l`` (DiLiGenT frame, pointing toward the light) the ray from
    the surface point of pixel ``p`` is marched in one-pixel steps along the
    light's projection onto the image plane (``d col = l_x / |l_xy|``,
    ``d row = -l_y / |l_xy|``, row 0 at the top); at step ``k`` the ray is
    ``k * pixel_size * l_z / |l_xy|`` above its start. The pixel is in shadow
    if the bilinearly interpolated height at some step exceeds the ray (by
    more than a relative tolerance of ``1e-6``, plus ``bias``). Samples whose bilinear
    footprint leaves the image never occlude. The march stops after
    ``ceil((max h - min h) / rise_per_step)`` steps (no occluder can be
    higher), at most the image diagonal, or ``n_steps`` if given.

    Lights at ``+z`` see everything; lights at or below the horizon
    (``l_z <= 0``) see nothing. Attached shadows (``n . l <= 0``) are not
    the purpose of this mask, though faces turned away from the light are
    usually found occluded by their own neighbourhood.

    Implementation: for one light and one step the sub-pixel offset is the
    same for every pixel, so the bilinear sample is a weighted sum of four
    shifted slices of the (padded) height field: memory ``O(H W)`` beyond the
    output, work ``O(L H W steps)``, vectorised over pixels, device agnostic.

    Args:
        height: ``(H, W)`` heights (same length unit as ``pixel_size``).
        lights: ``(L, 3)`` light directions (normalised here).
        pixel_size: distance between pixel centres.
        n_steps: optional cap on the number of march steps per light.
        bias: an occluder must rise this much (same unit as ``height``, >= 0)
            above the ray to count; absorbs noise of a reconstructed height
            field (default 0: exact).

    Returns:
        ``(L, H, W)`` bool, ``True`` where the light is **visible** (lit).

    Example:
        >>> hgt = torch.zeros(32, 32); hgt[12:20, 12:20] = 10.0
        >>> vis = cast_shadow_mask(hgt, torch.tensor([[0.6, 0.0, 0.8], [0.0, 0.0, 1.0]]))
        >>> bool(vis[0, 16, 8]), bool(vis[0, 16, 24]), bool(vis[1].all())
        (False, True, True)
    """
    check_tensor(height, "height")
    check_shape(height, "height", ("H", "W"))
    check_dirs(lights, "lights")
    check_shape(lights, "lights", ("L", 3))
    ps = _positive(pixel_size, "pixel_size")
    if n_steps is not None:
        n_steps = check_count(n_steps, "n_steps", minimum=0)
    if isinstance(bias, bool) or not isinstance(bias, (int, float)) or not math.isfinite(bias) or bias < 0:
        raise ValueError(f"`bias` must be a finite number >= 0, got {bias!r}")
    H, W = height.shape
    L = lights.shape[0]
    dev = height.device
    hgt = height.detach()
    lts = lights.detach().to(device="cpu", dtype=torch.float64)
    norm = torch.linalg.vector_norm(lts, dim=-1)
    if bool((norm == 0).any()):
        raise ValueError(f"`lights` row {int(torch.nonzero(norm == 0)[0])} is a zero vector")
    lts = (lts / norm[:, None]).tolist()
    vis = torch.ones(L, H, W, dtype=torch.bool, device=dev)
    if L == 0 or H * W == 0:
        return vis
    h_min, h_max = float(hgt.min()), float(hgt.max())
    h_range = h_max - h_min
    tol = 1e-6 * max(1.0, abs(h_min), abs(h_max)) + float(bias)
    cap = math.ceil(math.hypot(H, W))
    if n_steps is not None:
        cap = min(cap, n_steps)
    low = h_min - 1e3 * (h_range + 1.0)  # padding: far below every ray, never occludes
    for i, (lx, ly, lz) in enumerate(lts):
        if lz <= 0:
            vis[i] = False
            continue
        lxy = math.hypot(lx, ly)
        if lxy <= 1e-9 * lz or h_range <= 0:
            continue
        dr, dc = -ly / lxy, lx / lxy
        rise = ps * lz / lxy
        steps = min(cap, math.ceil(max(h_range - bias, 0.0) / rise))
        if steps <= 0:
            continue
        pad = math.ceil(steps * max(abs(dr), abs(dc))) + 2
        big = F.pad(hgt[None, None], (pad, pad, pad, pad), value=low)[0, 0]
        occ = torch.zeros(H, W, dtype=torch.bool, device=dev)
        for k in range(1, steps + 1):
            yr, yc = k * dr, k * dc
            r0, c0 = math.floor(yr), math.floor(yc)
            fr, fc = yr - r0, yc - c0
            r0 += pad
            c0 += pad
            top = big[r0 : r0 + H, c0 : c0 + W] * (1 - fc) + big[r0 : r0 + H, c0 + 1 : c0 + 1 + W] * fc
            bot = big[r0 + 1 : r0 + 1 + H, c0 : c0 + W] * (1 - fc) + big[r0 + 1 : r0 + 1 + H, c0 + 1 : c0 + 1 + W] * fc
            sample = top * (1 - fr) + bot * fr
            occ |= sample > hgt + (k * rise + tol)
        vis[i] = ~occ
    return vis


# --------------------------------------------------------------------------- #
# the demo scene
# --------------------------------------------------------------------------- #
