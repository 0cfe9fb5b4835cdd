"""A large float32 photometric-stereo stack on disk, for the memory benchmark (``bench_ps.py --stack S``).

A sphere filling most of an S x S frame, Blinn–Phong with a textured albedo,
DiLiGenT-like lights, rendered image by image (so making it never holds more
than the stack) and saved as ``images.npy`` ``(L, S, S, 3)`` float32 with
``lights.npy``, ``mask.npy`` and ``normals.npy`` beside it.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch


def ensure_stack(size: int, lights: int, folder=None) -> str:
    """The stack's folder (made once, then reused) under ``folder`` (default: the temporary folder)."""
    out = Path(folder or tempfile.gettempdir()) / f"torch_hsh_stack_{size}_{lights}"
    if (out / "images.npy").is_file():
        return str(out)
    from torch_hsh.render import scenes
    from torch_hsh.brdf import BlinnPhong
    from torch_hsh.render import render

    out.mkdir(parents=True, exist_ok=True)
    n, mask = scenes.sphere_normals(size, radius=0.9, dtype=torch.float32)
    ldirs = scenes.diligent_like_lights(lights, seed=0, dtype=torch.float32)
    alb = (0.2 + 0.6 * scenes.albedo_texture(size, seed=0, dtype=torch.float32))
    ones = torch.ones(size, size, 1)
    model = BlinnPhong(alb, 0.3 * ones, 30.0 * ones)
    imgs = np.lib.format.open_memmap(out / "images.npy", mode="w+", dtype=np.float32, shape=(lights, size, size, 3))
    g = torch.Generator().manual_seed(0)
    for j in range(lights):
        im = render(n, ldirs[j:j + 1], model)[0]
        im = im + 1e-3 * torch.randn(im.shape, generator=g)
        imgs[j] = (im * mask[..., None]).numpy()
    imgs.flush()
    del imgs
    np.save(out / "lights.npy", ldirs.numpy())
    np.save(out / "mask.npy", mask.numpy())
    np.save(out / "normals.npy", n.numpy())
    return str(out)
