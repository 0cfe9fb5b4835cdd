"""Render a synthetic RTI capture: photographs of an object beside a glossy black sphere, plus an .lp file.

The object is the photometric-stereo demo scene (``torch_hsh.render.scenes.demo_scene``: a bumpy sphere with
GGX and Blinn-Phong regions over a texture, cast shadows); the sphere on its right is a glossy black
Blinn-Phong ball for highlight RTI. The images are written as 8-bit sRGB PNGs (``--format jpg`` for
JPEGs) with ``mask.png`` (the object), ``sphere_mask.png`` (the sphere, outside the object mask),
``lights.lp`` (the true directions; ``torch-hsh lights`` replaces them by the estimated ones) and
``true_lights.txt``.

Then, as in docs/rti.md::

    python examples/rti_capture.py --out results/rti_capture
    torch-hsh lights results/rti_capture --sphere-mask results/rti_capture/sphere_mask.png \\
        --out results/rti_capture/lights.lp --overwrite
    torch-hsh ps results/rti_capture --out results/rti_ps
    torch-hsh rti results/rti_ps --terms 9 --rti results/rti_capture.rti --relight results/rti_relight
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from torch_hsh.render import scenes
from torch_hsh.brdf import BlinnPhong
from torch_hsh.io.diligent import _write_png
from torch_hsh.rti.io import save_rti
from torch_hsh.render import render


def make_capture(size: int = 96, n_lights: int = 48, seed: int = 0):
    """``(images (L, H, 2W, 3) linear in [0, 1], lights (L, 3), object mask, sphere mask)``."""
    d = scenes.demo_scene(size, n_lights=n_lights, seed=seed, dtype=torch.float64)
    obj = d["images"] / d["intensities"][:, None, None, :]
    lights = d["lights"]
    n, sm = scenes.sphere_normals(size, radius=0.8, dtype=torch.float64)
    one = torch.ones(size, size, 1, dtype=torch.float64)
    sph = render(n, lights, BlinnPhong(0.03 * one.expand(-1, -1, 3), one, 400 * one)) * sm[None, ..., None]
    imgs = torch.cat([obj / obj.max(), sph / sph.max()], dim=2)
    mask = torch.cat([d["mask"], torch.zeros_like(sm)], dim=1)
    smask = torch.cat([torch.zeros_like(sm), sm], dim=1)
    return imgs, lights, mask, smask


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/rti_capture", help="capture folder (must be empty or absent)")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--lights", type=int, default=48)
    ap.add_argument("--format", choices=("png", "jpg"), default="png")
    a = ap.parse_args(argv)
    imgs, lights, mask, smask = make_capture(a.size, a.lights)
    out = save_rti(a.out, imgs, lights, mask=mask, fmt=a.format)
    _write_png(Path(out) / "sphere_mask.png", smask.numpy().astype(np.uint8) * 255)
    np.savetxt(Path(out) / "true_lights.txt", lights.numpy(), fmt="%.6f")
    print(f"wrote {out}: {len(lights)} images {imgs.shape[2]}x{imgs.shape[1]}, mask.png, sphere_mask.png, "
          "lights.lp, true_lights.txt")


if __name__ == "__main__":
    main()
