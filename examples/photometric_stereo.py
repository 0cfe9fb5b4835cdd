"""Photometric stereo with the isotropic Helmholtz HSH basis: demo and driver.

Without arguments: renders a synthetic non-Lambertian scene (a sphere with
three materials from analytic BRDFs: GGX, Blinn-Phong and Torrance-Sparrow
regions over a textured albedo, DiLiGenT-like lights with RGB intensities,
sensor noise, 16-bit quantisation), solves it with Lambertian least squares,
robust (trimmed) Lambertian and the HSH solver, and prints a table.

With ``--data DIR`` it solves a DiLiGenT-layout folder instead.

Output folder policy (``--out``, default ``results/ps_demo``): the folder is
created if needed. The demo only ever writes the files listed in
``OUTPUT_FILES``; it refuses to run if the folder already contains any *other*
file (someone else's data) unless ``--overwrite`` is given, so re-running on
its own output folder simply replaces its own results.

Written files: ``normals.npy`` (H, W, 3) float32 in the DiLiGenT frame (zero
outside the mask), ``coefficients.exr`` (coefficient maps), ``metrics.json``,
``normal_map.png``, ``error_map.png`` (if ground truth), ``relighting.png``
(input / relit / error side by side).

Example:
    python examples/photometric_stereo.py --out results/ps_demo
    python examples/photometric_stereo.py --data ../shared/data/bunny_specular --holdout 5
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

OUTPUT_FILES = {
    "normals.npy",
    "coefficients.exr",
    "metrics.json",
    "normal_map.png",
    "error_map.png",
    "relighting.png",
}


def synthetic_scene(size: int = 48, n_lights: int = 40, seed: int = 0, dtype=torch.float64):
    """Sphere with three analytic-BRDF regions, textured albedo, DiLiGenT-like lights, noise."""
    from torch_hsh import scenes
    from torch_hsh.brdf import BlinnPhong, CookTorranceGGX, TorranceSparrow
    from torch_hsh.render import render

    normals, mask = scenes.sphere_normals(size, radius=0.95, dtype=dtype)
    mask = mask & (normals[..., 2] > 0.3)  # leave out grazing rim pixels (mostly attached shadow)
    labels = scenes.material_regions(size, n_regions=3, seed=seed)
    albedo = 0.15 + 0.7 * scenes.albedo_texture(size, seed=seed, dtype=dtype)  # (H, W, 3)
    lights = scenes.diligent_like_lights(n_lights, seed=seed, dtype=dtype)
    inten = scenes.light_intensities(n_lights, seed=seed, dtype=dtype)
    ones = torch.ones(size, size, 1, dtype=dtype)
    models = [
        CookTorranceGGX(albedo=albedo, specular=0.3 * ones, roughness=0.5 * ones, f0=0.3),
        BlinnPhong(kd=albedo, ks=0.3 * ones, shininess=20.0 * ones),
        TorranceSparrow(albedo, 0.15 * ones, 0.35 * ones, 1.5 * ones),
    ]
    img = torch.zeros(n_lights, size, size, 3, dtype=dtype)
    for k, m in enumerate(models):
        sel = (labels % len(models)) == k
        img = torch.where(sel[None, ..., None], render(normals, lights, m, intensities=inten), img)
    full = float(img[:, mask].max()) * 1.05
    from torch_hsh.render import add_sensor_noise, quantize

    img = quantize(add_sensor_noise(img, read_std=2e-3 * full, shot_gain=1e-4 * full, seed=seed), 16, full)
    img = img * mask[None, ..., None].to(dtype)
    return dict(images=img, lights=lights, intensities=inten, mask=mask, normals_gt=normals,
                labels=labels, name="synthetic sphere (GGX / Blinn-Phong / Torrance-Sparrow)")


def load_data(path, dtype=torch.float64):
    from torch_hsh.io.diligent import load_diligent

    d = load_diligent(path, dtype=dtype, normalize_intensities=True)
    return dict(images=d.images, lights=d.lights, intensities=None, mask=d.mask, normals_gt=d.normals_gt,
                name=str(path))


def check_out_dir(out: Path, overwrite: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    foreign = sorted(p.name for p in out.iterdir() if p.name not in OUTPUT_FILES)
    if foreign and not overwrite:
        sys.exit(
            f"error: --out {out} contains files this demo did not write ({', '.join(foreign[:5])}"
            f"{' ...' if len(foreign) > 5 else ''}); choose another folder or pass --overwrite"
        )


def save_figures(out: Path, data, res, err_map, relit_idx: int, figures_dir=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mask = data["mask"].cpu().numpy()
    n = res.normals.detach().cpu().numpy()
    written = []
    nm = np.where(mask[..., None], (n + 1) / 2, 1.0)
    plt.imsave(out / "normal_map.png", np.clip(nm, 0, 1))
    written.append("normal_map.png")
    if err_map is not None:
        fig, ax = plt.subplots(figsize=(4.2, 3.6))
        e = np.where(mask, err_map, np.nan)
        im = ax.imshow(e, cmap="magma", vmin=0, vmax=max(10.0, float(np.nanpercentile(e, 99))))
        ax.set_title("HSH angular error (deg)")
        ax.axis("off")
        fig.colorbar(im, ax=ax)
        fig.tight_layout()
        fig.savefig(out / "error_map.png", dpi=100)
        plt.close(fig)
        written.append("error_map.png")
    l = data["lights"][relit_idx : relit_idx + 1].to(res.normals)
    e = None if data["intensities"] is None else data["intensities"][relit_idx : relit_idx + 1].to(res.normals)
    relit = res.relight(l, e)[0].detach().cpu().numpy()
    inp = data["images"][relit_idx].detach().cpu().numpy()
    scale = float(np.percentile(inp[mask], 99.5)) or 1.0
    diff = np.abs(relit - inp).mean(-1) / scale
    fig, axes = plt.subplots(1, 3, figsize=(10, 3.4))
    axes[0].imshow(np.clip(inp / scale, 0, 1) ** (1 / 2.2))
    axes[0].set_title(f"input (light {relit_idx})")
    axes[1].imshow(np.clip(relit / scale, 0, 1) ** (1 / 2.2))
    axes[1].set_title("HSH relit")
    im = axes[2].imshow(np.where(mask, diff, np.nan), cmap="viridis", vmin=0, vmax=0.1)
    axes[2].set_title("|relit - input| / max")
    fig.colorbar(im, ax=axes[2])
    for a in axes:
        a.axis("off")
    fig.tight_layout()
    fig.savefig(out / "relighting.png", dpi=100)
    plt.close(fig)
    written.append("relighting.png")
    if figures_dir is not None:
        figures_dir = Path(figures_dir)
        figures_dir.mkdir(parents=True, exist_ok=True)
        for f in written:
            shutil.copyfile(out / f, figures_dir / f"ps_{f}")


def materials_arg(s: str):
    """``--materials``: ``auto`` or an integer."""
    return s if s == "auto" else int(s)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None, help="DiLiGenT-layout object folder (default: synthetic scene)")
    ap.add_argument("--out", default="results/ps_demo", help="output folder (default results/ps_demo)")
    ap.add_argument("--order", type=int, default=None, help="HSH order (default torch_hsh.ps.DEFAULT_ORDER)")
    ap.add_argument("--materials", type=materials_arg, default=None,
                    help="shared basis BRDFs of the HSH solver (default torch_hsh.ps.DEFAULT_MATERIALS; "
                         "0: independent BRDF per pixel; auto: chosen in 1..4 from the data)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--holdout", type=int, default=0, help="also fit on all but N lights and report relighting error")
    ap.add_argument("--size", type=int, default=48, help="synthetic image size")
    ap.add_argument("--lights", type=int, default=40, help="synthetic number of lights")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--overwrite", action="store_true", help="allow writing into a folder with foreign files")
    ap.add_argument("--figures", default=None, help="also copy the PNGs (prefixed ps_) into this folder")
    args = ap.parse_args(argv)

    torch.set_num_threads(args.threads)
    from torch_hsh import ps
    from torch_hsh.io.exr import write_coefficient_maps_exr

    order = ps.DEFAULT_ORDER if args.order is None else args.order
    if isinstance(args.materials, int) and args.materials < 0:
        ap.error(f"--materials must be >= 0, got {args.materials}")
    materials = ps.DEFAULT_MATERIALS if args.materials is None else (args.materials or None)
    out = Path(args.out)
    check_out_dir(out, args.overwrite)
    dev = torch.device(args.device)
    data = load_data(args.data) if args.data else synthetic_scene(args.size, args.lights, args.seed)
    data = {k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in data.items()}
    imgs, lights, inten, mask, gt = data["images"], data["lights"], data["intensities"], data["mask"], data["normals_gt"]
    P, L = int(mask.sum()), imgs.shape[0]
    print(f"data: {data['name']}  pixels={P} lights={L} order={order} "
          f"materials={materials if materials else 'independent'} device={dev}")

    rows = []

    def errs(n):
        if gt is None:
            return float("nan"), float("nan")
        e = ps.angular_error(n, gt.to(n))[mask]
        return float(e.mean()), float(e.median())

    t = time.perf_counter()
    lam = ps.lambertian_ls(imgs, lights, inten, mask)
    rows.append(("Lambertian LS", *errs(lam.normals), time.perf_counter() - t))
    t = time.perf_counter()
    rob = ps.robust_lambertian(imgs, lights, inten, mask)
    rows.append(("robust Lambertian (trimmed)", *errs(rob.normals), time.perf_counter() - t))
    t = time.perf_counter()
    res = ps.solve_hsh(imgs, lights, inten, mask, order=order, materials=materials, progress=True)
    t_hsh = time.perf_counter() - t
    rows.append((f"HSH (order {order})", *errs(res.normals), t_hsh))

    print(f"\n{'method':32s} {'mean (deg)':>10s} {'median (deg)':>12s} {'time (s)':>9s}")
    for name, mean, med, tt in rows:
        print(f"{name:32s} {mean:10.2f} {med:12.2f} {tt:9.2f}")

    metrics = {
        "method": "hsh",
        "order": order,
        "materials": materials,
        "materials_chosen": res.info.get("materials"),
        "pixels": P,
        "lights": L,
        "runtime_s": t_hsh,
        "data": data["name"],
        "methods": {name: {"mean_angular_error_deg": m, "median_angular_error_deg": md, "runtime_s": tt}
                    for name, m, md, tt in rows},
        "solver_info": res.info,
    }
    err_map = None
    if gt is not None:
        metrics["mean_angular_error_deg"] = rows[2][1]
        metrics["median_angular_error_deg"] = rows[2][2]
        metrics["lambertian_mean_angular_error_deg"] = rows[0][1]
        metrics["robust_lambertian_mean_angular_error_deg"] = rows[1][1]
        err_map = ps.angular_error(res.normals, gt.to(res.normals), mask).cpu().numpy()
    if args.holdout > 0:
        t = time.perf_counter()
        ho = ps.holdout_evaluation(imgs, lights, inten, mask, holdout=args.holdout, seed=args.seed, order=order,
                                   materials=materials)
        metrics["holdout"] = {
            "held_out_lights": ho.test_indices.tolist(),
            "relative_rmse": ho.relative_rmse,
            "rmse": ho.rmse,
            "lambertian_relative_rmse": ho.lambertian_relative_rmse,
            "runtime_s": time.perf_counter() - t,
        }
        print(f"\nheld-out relighting ({args.holdout} lights): HSH relative RMSE {ho.relative_rmse:.4f}, "
              f"robust Lambertian {ho.lambertian_relative_rmse:.4f}")

    normals = res.normals.detach().cpu().numpy().astype(np.float32)
    np.save(out / "normals.npy", normals)
    write_coefficient_maps_exr(out / "coefficients.exr", res.coefficients.detach().cpu().float(), overwrite=True)
    with open(out / "metrics.json", "w") as f:
        json.dump(metrics, f, indent=2)
    save_figures(out, data, res, err_map, relit_idx=L // 2, figures_dir=args.figures)
    print(f"\nwrote {out}/ ({', '.join(sorted(p.name for p in out.iterdir()))})")
    return metrics


if __name__ == "__main__":
    main()
