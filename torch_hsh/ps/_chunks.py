"""Pixel chunking of the photometric-stereo solvers: row sums and passes in bounded chunks, pixel scatter."""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch

__all__ = ["ROW_CHUNK", "MIN_CHUNK", "scatter_pixels", "row_sum", "for_chunks"]

#: Rows per chunk of :func:`row_sum` (and of other per-pixel passes over ``(N, L)`` tensors).
ROW_CHUNK = 65536


def row_sum(x: torch.Tensor, dtype: Optional[torch.dtype] = None, chunk: int = ROW_CHUNK) -> torch.Tensor:
    """``x.to(dtype).sum(-1)`` for ``x (N, L)``, in row chunks.

    A bool sum upcasts to int64 and ``sum(dtype=...)`` copies its input, so on the
    whole ``(N, L)`` tensor either would allocate a temporary several times the
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
    """Put ``(N, ...)`` per-pixel values back into a ``(*S, ...)`` map, zero outside ``mask``."""
    out = torch.zeros(mask.numel(), *values.shape[1:], dtype=values.dtype, device=values.device)
    out[mask.reshape(-1)] = values
    return out.reshape(*mask.shape, *values.shape[1:])
