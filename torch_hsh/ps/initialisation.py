"""Stage 2 of the HSH solver: the start normals.

Takes the :class:`~torch_hsh.ps.observations.Observations` and optional
user normals ``init (*S, 3)``; returns ``(N, 3)`` unit start normals: the
robust (trimmed) Lambertian solution by default, always tilted in front of the
camera (``n_z >= 0.05`` before normalisation).
"""
from __future__ import annotations


import torch

from .._checks import check_shape

from .lambertian import _solve_flat, trimmed_weights
from .observations import _CHUNK, Observations
from .settings import Settings

__all__ = ["initial_normals"]


def initial_normals(obs: Observations, cfg: Settings) -> torch.Tensor:
    """Start normals ``(N, 3)``: robust Lambertian (25 % darkest, 10 % brightest dropped) or ``cfg.init``.

    ``cfg.progress``: a tqdm bar over the pixels of the Lambertian solve (like the later stages)."""
    init, progress = cfg.init, cfg.progress
    d = obs.data
    dev, dt = d.y.device, d.dtype
    if init is None:
        N = d.y.shape[0]
        n_start = torch.empty(N, 3, dtype=dt, device=dev)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=N, desc="HSH start normals (robust Lambertian)", unit="px")
        for s in range(0, N, _CHUNK):
            y = d.y[s : s + _CHUNK].to(dt)
            n_start[s : s + _CHUNK], _ = _solve_flat(y, d.lights, trimmed_weights(y, 0.25, 0.10))
            if bar is not None:
                bar.update(y.shape[0])
        if bar is not None:
            bar.close()
    else:
        check_shape(init, "init", (*d.pixel_shape, 3))
        n_start = torch.nn.functional.normalize(init.to(device=dev, dtype=dt).reshape(-1, 3)[d.mask.reshape(-1)], dim=-1)
    # keep the start in front of the camera
    nz = n_start[:, 2].clamp(min=0.05)
    return torch.nn.functional.normalize(torch.cat([n_start[:, :2], nz.unsqueeze(-1)], -1), dim=-1)
