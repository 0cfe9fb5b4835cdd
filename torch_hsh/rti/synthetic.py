r"""Synthetic RTI captures of any size, rendered by :mod:`torch_hsh.render` in bands of rows.

:func:`write_synthetic_capture` writes a capture folder in the layout
:func:`torch_hsh.rti.io.load_rti` reads: one 8-bit sRGB JPEG per light, a
``lights.lp`` file, and the ground truth ``normals_gt.npy`` (``(H, W, 3)``
float32, x right, y up, z toward the camera) and ``materials_gt.npy``
(``(H, W)`` uint8 region index).

The surface is a plane with smooth Gaussian bumps and a few spheres; three
materials by region (a matte red clay, a glossy blue plastic, a rough metal-like
grey), each a :class:`~torch_hsh.brdf.CookTorranceGGX`. Memory stays bounded
at any size: the lights are the outer loop and bands of rows the inner one, so
at most one ``uint8`` photograph plus one float band is held at a time
(the normals file is written band by band through a memory map).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import torch

__all__ = ["synthetic_lights", "synthetic_normals", "write_synthetic_capture"]

# (albedo rgb, specular, roughness, f0) per material
_MATERIALS = (
    ((0.60, 0.30, 0.20), 0.00, 0.60, 0.04),
    ((0.15, 0.25, 0.55), 0.50, 0.35, 0.04),
    ((0.40, 0.40, 0.40), 0.30, 0.55, 0.50),
)


def synthetic_lights(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` unit light directions on a spiral over the hemisphere (elevations 20 to 75 degrees)."""
    if n < 3:
        raise ValueError(f"need at least 3 lights, got {n}")
    i = np.arange(n) + 0.5
    elev = np.deg2rad(20.0 + 55.0 * (i / n))
    az = i * np.pi * (3.0 - np.sqrt(5.0)) + 0.1 * seed
    return np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], axis=1)


def _scene(width: int, height: int, seed: int):
    rng = np.random.default_rng(seed)
    s = float(min(width, height))
    bumps = [(rng.uniform(0, width), rng.uniform(0, height), rng.uniform(0.04, 0.09) * s,
              rng.uniform(-0.5, 0.5)) for _ in range(6)]
    spheres = [(0.28 * width, 0.35 * height, 0.18 * s), (0.72 * width, 0.62 * height, 0.22 * s),
               (0.55 * width, 0.22 * height, 0.10 * s)]
    return bumps, spheres


def synthetic_normals(width: int, height: int, rows: slice, seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """Normals ``(h, W, 3)`` float64 and material index ``(h, W)`` of the rows ``rows`` of the scene."""
    bumps, spheres = _scene(width, height, seed)
    r0, r1 = rows.start or 0, min(rows.stop if rows.stop is not None else height, height)
    x = np.arange(width, dtype=np.float64)[None, :] + 0.5
    y = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5
    gx = np.zeros((r1 - r0, width))
    gy = np.zeros((r1 - r0, width))
    for cx, cy, sig, amp in bumps:  # height h = amp*sig*exp(-r^2/2sig^2) (rows grow downward: y up = -row)
        e = amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sig * sig))
        gx += -e * (x - cx) / sig
        gy += e * (y - cy) / sig
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    mat = ((x // max(1.0, width / 4.0) + y // max(1.0, height / 3.0)) % 2).astype(np.uint8) * np.ones_like(gx, np.uint8)
    for cx, cy, r in spheres:
        dx, dy = np.broadcast_arrays(x - cx, -(y - cy))
        d2 = dx * dx + dy * dy
        inside = d2 < (0.98 * r) ** 2
        nz = np.sqrt(np.clip(r * r - d2, 0.0, None))
        sph = np.stack([dx, dy, nz], axis=-1) / r
        n = np.where(inside[..., None], sph, n)
        mat = np.where(inside, 2, mat).astype(np.uint8)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n, mat


def _render_band(n: np.ndarray, mat: np.ndarray, light: np.ndarray) -> np.ndarray:
    from ..brdf import CookTorranceGGX
    from ..render.images import render_model

    alb = np.asarray([m[0] for m in _MATERIALS])[mat]
    spec = np.asarray([m[1] for m in _MATERIALS])[mat][..., None].repeat(3, -1)
    rough = np.asarray([m[2] for m in _MATERIALS])[mat][..., None].repeat(3, -1)
    f0 = np.asarray([m[3] for m in _MATERIALS])[mat][..., None].repeat(3, -1)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    model = CookTorranceGGX(albedo=t(alb), specular=t(spec), roughness=t(rough), f0=t(f0))
    out = render_model(t(n).reshape(-1, 3), t(light[None]), _Flat(model, n.shape[:-1]))
    return out.reshape(*n.shape[:-1], 3).numpy()


class _Flat:
    """A model with ``(h, W, C)`` parameters evaluated on flattened ``(L, h*W, 3)`` directions."""

    def __init__(self, model, shape):
        self.model, self.shape = model, tuple(shape)

    def __call__(self, wi, wo):
        L = wi.shape[0]
        f = self.model(wi.reshape(L, *self.shape, 3), wo.reshape(L, *self.shape, 3))
        return f.reshape(L, -1, f.shape[-1])


def write_synthetic_capture(folder, width: int, height: int, n_lights: int, band_rows: int = 256,
                            seed: int = 0, quality: int = 95, exposure: float = 1.6,
                            lights: Optional[np.ndarray] = None) -> Path:
    """Render and write a synthetic RTI capture (see the module docstring); returns the folder.

    Example:
        >>> write_synthetic_capture(tmp / "cap", 64, 48, 8)  # doctest: +SKIP
    """
    from PIL import Image

    from .io import srgb_encode, write_lp

    if width < 1 or height < 1 or band_rows < 1:
        raise ValueError("width, height and band_rows must be >= 1")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    li = synthetic_lights(n_lights, seed) if lights is None else np.asarray(lights, dtype=np.float64)
    li = li / np.linalg.norm(li, axis=1, keepdims=True)
    gt = np.lib.format.open_memmap(folder / "normals_gt.npy", mode="w+", dtype=np.float32, shape=(height, width, 3))
    mg = np.lib.format.open_memmap(folder / "materials_gt.npy", mode="w+", dtype=np.uint8, shape=(height, width))
    bands = [slice(r, min(r + band_rows, height)) for r in range(0, height, band_rows)]
    for b in bands:
        n, m = synthetic_normals(width, height, b, seed)
        gt[b], mg[b] = n.astype(np.float32), m
    gt.flush()
    mg.flush()
    del gt, mg
    names = [f"img_{j + 1:04d}.jpg" for j in range(len(li))]
    for j, name in enumerate(names):
        img = np.empty((height, width, 3), dtype=np.uint8)
        for b in bands:
            n, m = synthetic_normals(width, height, b, seed)
            lin = np.clip(exposure * _render_band(n, m, li[j]), 0.0, 1.0)
            img[b] = np.round(srgb_encode(lin) * 255.0).astype(np.uint8)
        Image.fromarray(img).save(folder / name, quality=quality)
        del img
    write_lp(folder / "lights.lp", names, li, overwrite=True)
    return folder
