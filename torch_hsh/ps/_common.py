"""Small helpers shared by the photometric-stereo solvers: pixel scatter, row sums, angular error, tangent frames."""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch

from .._checks import check_dirs

__all__ = ["scatter_pixels", "row_sum", "angular_error", "tangent_frame", "for_chunks"]

#: Rows per chunk of :func:`row_sum` (and of other per-pixel passes over ``(P, L)`` tensors).
ROW_CHUNK = 65536


def row_sum(x: torch.Tensor, dtype: Optional[torch.dtype] = None, chunk: int = ROW_CHUNK) -> torch.Tensor:
    """``x.to(dtype).sum(-1)`` for ``x (P, L)``, in row chunks.

    A bool sum upcasts to int64 and ``sum(dtype=...)`` copies its input, so on the
    whole ``(P, L)`` tensor either would allocate a temporary several times the
    size of ``x`` (512 MB at 1024^2 pixels x 96 lights); chunking bounds it.
    """
    if x.shape[0] == 0:
        return x.new_zeros(0, dtype=torch.int64 if dtype is None and x.dtype == torch.bool else (dtype or x.dtype))
    parts = [(x[i:i + chunk] if dtype is None else x[i:i + chunk].to(dtype)).sum(-1) for i in range(0, x.shape[0], chunk)]
    return torch.cat(parts)


#: Smallest chunk that :func:`for_chunks` halves down to after running out of device memory.
MIN_CHUNK = 256


def for_chunks(n: int, step: int, run: Callable[[slice], None], shrink: bool = False, progress=None) -> Tuple[int, int]:
    """Call ``run(slice)`` over ``[0, n)`` in chunks of ``step`` rows; returns (chunks run, final step).

    With ``shrink`` (a chunk size the solver chose, not the user), a chunk
    that raises ``torch.cuda.OutOfMemoryError`` is retried at half the size,
    down to :data:`MIN_CHUNK`: the device-memory estimate behind the automatic
    chunk is a model, and the per-pixel results do not depend on the chunk.
    ``run`` must write its outputs only once it has computed them. ``progress``
    (a tqdm bar over ``n``) is advanced per chunk.
    """
    start, chunks = 0, 0
    while start < n:
        sl = slice(start, min(n, start + step))
        try:
            run(sl)
        except torch.cuda.OutOfMemoryError:
            if not shrink or step <= MIN_CHUNK:
                raise
            if torch.cuda.is_available():
                torch.cuda.empty_cache()
            step = max(MIN_CHUNK, step // 2)
            continue
        chunks += 1
        start = sl.stop
        if progress is not None:
            progress.update(sl.stop - sl.start)
    if progress is not None:
        progress.close()
    return chunks, step


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
    sign = torch.where(z >= 0, 1.0, -1.0).to(z.dtype)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    t2 = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t1, t2
