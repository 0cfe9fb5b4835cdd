"""Normal geometry of the photometric-stereo solvers: angular error between normal maps, tangent frames, the
bounding box of a mask and the depth map that the stages after the solve start from."""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from .._checks import check_dirs, check_shape

__all__ = ["angular_error", "tangent_frame", "mask_box", "start_depth"]


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
    check_shape(reference, "reference", tuple(normals.shape))  # the shape of `normals`
    a = torch.nn.functional.normalize(normals, dim=-1)
    b = torch.nn.functional.normalize(reference.to(normals.dtype), dim=-1)
    ang = torch.rad2deg(torch.arccos((a * b).sum(-1).clamp(-1.0, 1.0)))
    if mask is not None:
        ang = torch.where(mask.to(ang.device).bool(), ang, torch.zeros_like(ang))
    return ang


def tangent_frame(n: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents ``(t1, t2)`` orthogonal to unit normals ``n (N, 3)``, each ``(N, 3)``: the azimuthal frame.

    ``t1 = normalize(z x n) = (-sin phi, cos phi, 0)`` follows the azimuth ``phi`` of ``n`` and
    ``t2 = n x t1``, so ``(t1, t2, n)`` is right-handed. Convention: the frame is **covariant under
    rotations about the view axis** ``z``: for such a rotation ``R``, ``tangent_frame(R n) = (R t1, R t2)``.
    The solvers' steps, forward differences, damping and cone of candidates are taken in this frame, so
    rotating the lights and the scene about the view axis rotates the recovered normals. At the pole
    (``n_x = n_y = 0``, where no frame can be covariant) the frame is ``t1 = (0, 1, 0)``, the ``phi = 0`` limit.

    Example:
        >>> n = torch.nn.functional.normalize(torch.tensor([[0.3, 0.4, 0.8]]), dim=-1)
        >>> R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z
        >>> (t1, t2), (r1, r2) = tangent_frame(n), tangent_frame(n @ R.T)
        >>> torch.allclose(r1, t1 @ R.T), torch.allclose(r2, t2 @ R.T)
        (True, True)
    """
    x, y, z = n.unbind(-1)
    r = torch.hypot(x, y)
    pole = r == 0
    r = torch.where(pole, torch.ones_like(r), r)
    c = torch.where(pole, torch.ones_like(r), x / r)
    s = torch.where(pole, torch.zeros_like(r), y / r)
    t1 = torch.stack([-s, c, torch.zeros_like(s)], dim=-1)
    t2 = torch.stack([-z * c, -z * s, x * c + y * s], dim=-1)  # n x t1
    return t1, t2


def mask_box(mask: torch.Tensor) -> Tuple[slice, slice]:
    """Rows and columns of the smallest box that holds every ``True`` pixel of an ``(H, W)`` mask (the whole
    image when the mask is empty). The stages that work on a depth map crop to it.

    Example:
        >>> m = torch.zeros(5, 6, dtype=torch.bool); m[1:3, 2:5] = True
        >>> mask_box(m)
        (slice(1, 3, None), slice(2, 5, None))
    """
    rows, cols = mask.any(1).nonzero().squeeze(1), mask.any(0).nonzero().squeeze(1)
    if rows.numel() == 0:
        return slice(None), slice(None)
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def start_depth(normals: torch.Tensor, mask: torch.Tensor, method: str = "bilateral",
                fill: float = float("nan")) -> Tuple[Tuple[slice, slice], torch.Tensor]:
    """The depth of a solve's normals that the stages after the solve start from (the interreflection loop's
    surface, the whole-surface stage's start): :func:`torch_hsh.surface.integrate_normals` on the mask's box
    (:func:`mask_box`), with :data:`~torch_hsh.ps.settings.DEPTH_START_ITERATIONS` re-weightings.

    Args:
        normals: ``(H, W, 3)`` normals.
        mask: ``(H, W)`` bool.
        method: the integrator (``"bilateral"`` keeps the depth's jumps).
        fill: value outside the mask.

    Returns:
        ``(box, depth)``: the box and the ``(h, w)`` float64 CPU depth over it (pixel units).
    """
    from ..surface import integrate_normals
    from .settings import DEPTH_START_ITERATIONS

    box = mask_box(mask)
    depth = integrate_normals(normals[box].detach().to(torch.float64).cpu(), mask[box].cpu(), method=method,
                              fill=fill, iterations=DEPTH_START_ITERATIONS)
    return box, depth
