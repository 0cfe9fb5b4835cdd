"""From a normal map to a surface: integrate, export (depth .npy/.exr, mesh .ply/.obj) and picture it.

Usage:
    python examples/surface_from_normals.py --data ../shared/data/diligent_cat --out results/surface_cat
    python examples/surface_from_normals.py --data ../shared/data/diligent_cat --figure docs/images/surface_cat.png

Integrates the ground-truth normals (``Normal_gt.mat``) of a DiLiGenT-layout folder over its mask
(``--method poisson`` or ``bilateral``) and writes ``depth.npy``, ``depth.exr``, ``mesh.ply`` and
``mesh.obj`` (needs ``pip install torch-hsh[mesh]``) and ``shaded.png`` into ``--out``. ``--figure``
writes a three-panel picture: the normal map, the shaded depth (with cast shadows) and an oblique
view of the mesh. Existing files are never overwritten unless ``--overwrite``.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch


def oblique_view(ax, depth, mask, stride=2, elev=20, azim=-65):
    """Shaded oblique view of the masked mesh (matplotlib ``plot_trisurf``).

    Matplotlib's vertical axis shows the image's up direction (``y``) and the depth axis points
    toward the viewer (``azim=-90`` would be the camera's own view).
    """
    from matplotlib.colors import LightSource

    from torch_hsh.surface import depth_to_mesh

    d, m = depth[::stride, ::stride], mask[::stride, ::stride]
    mesh = depth_to_mesh(d, m)
    v = np.asarray(mesh.vertices) * np.array([stride, stride, 1.0])
    x, y, z = v[:, 0], -v[:, 2], v[:, 1]
    ax.plot_trisurf(x, y, z, triangles=np.asarray(mesh.faces), color="0.85", linewidth=0,
                    antialiased=False, shade=True, lightsource=LightSource(azdeg=225, altdeg=35))
    ax.view_init(elev=elev, azim=azim)
    ax.set_box_aspect((np.ptp(x), np.ptp(y), np.ptp(z)))
    ax.set_axis_off()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/data/diligent_cat")
    ap.add_argument("--method", default="poisson", choices=["poisson", "bilateral"])
    ap.add_argument("--out", default=None, help="output folder for depth, mesh and shaded picture")
    ap.add_argument("--figure", default=None, help="write a three-panel PNG here")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)

    from torch_hsh.io.diligent import load_diligent
    from torch_hsh.surface import integrate_normals, write_depth, write_mesh, shade_depth

    d = load_diligent(args.data, dtype=torch.float64)
    if d.normals_gt is None:
        raise SystemExit(f"{args.data} has no Normal_gt.mat")
    t = time.perf_counter()
    depth, info = integrate_normals(d.normals_gt, d.mask, args.method, return_info=True)
    print(f"{args.data}: {int(d.mask.sum())} pixels, {info['components']} part(s), {args.method}: "
          f"{time.perf_counter() - t:.2f} s, depth range {float(np.ptp(depth[d.mask].numpy())):.1f} px")
    shaded = shade_depth(depth, d.mask, shadows=True)
    if args.out:
        import matplotlib.pyplot as plt

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        for name in ("depth.npy", "depth.exr"):
            print("wrote", write_depth(out / name, depth, d.mask, overwrite=args.overwrite))
        for name in ("mesh.ply", "mesh.obj"):
            try:
                print("wrote", write_mesh(out / name, depth, d.mask, d.normals_gt, overwrite=args.overwrite))
            except ImportError as e:
                print(f"skipped {name}: {e}")
        png = out / "shaded.png"
        if png.exists() and not args.overwrite:
            raise SystemExit(f"{png} exists; pass --overwrite")
        plt.imsave(png, shaded.numpy(), cmap="gray", vmin=0, vmax=1)
        print("wrote", png)
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig_path = Path(args.figure)
        if fig_path.exists() and not args.overwrite:
            raise SystemExit(f"{fig_path} exists; pass --overwrite")
        fig = plt.figure(figsize=(13, 4.6))
        ax = fig.add_subplot(1, 3, 1)
        nm = ((d.normals_gt.numpy() + 1) / 2) * d.mask.numpy()[..., None] + (~d.mask.numpy())[..., None]
        ax.imshow(np.clip(nm, 0, 1))
        ax.set_title("ground-truth normals")
        ax.set_axis_off()
        ax = fig.add_subplot(1, 3, 2)
        ax.imshow(shaded.numpy(), cmap="gray", vmin=0, vmax=1)
        ax.set_title(f"integrated depth ({args.method}), shaded, cast shadows")
        ax.set_axis_off()
        ax = fig.add_subplot(1, 3, 3, projection="3d")
        oblique_view(ax, depth, d.mask)
        ax.set_title("mesh (oblique view)")
        fig.tight_layout()
        fig_path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(fig_path, dpi=90)
        print("wrote", fig_path)
    return depth


if __name__ == "__main__":
    main()
