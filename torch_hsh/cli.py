r"""The ``torch-hsh`` command (also ``python -m torch_hsh``).

Subcommands:

* ``torch-hsh ps`` — photometric stereo with the isotropic Helmholtz HSH basis on
  a DiLiGenT-layout folder (``--data DIR``) or, without ``--data``, on a built-in
  synthetic sphere with three analytic materials. Compares Lambertian least
  squares, robust (trimmed) Lambertian and the HSH solver and writes a result
  folder.
* ``torch-hsh fit`` — fit the isotropic Helmholtz basis to a MERL ``.binary`` BRDF
  (weighted least squares on the table's samples by default) and write the
  coefficients, the relative L2 error on the samples and a JSON summary (``.npz``).
* ``torch-hsh lights`` / ``rti`` / ``view`` — RTI captures: light directions from a
  glossy sphere, the HSH RTI export and a WebGL2 viewer of a result (:mod:`torch_hsh.cli_rti`).

Conventions: every argument and input file is checked before any folder is
created and before the solve. A bad argument gets an argparse message and exit
status 2; a bad input file (or any other failure) one line ``torch-hsh ps:
error: ...`` naming the file and exit status 1, with the traceback only under
``--debug``; Ctrl-C gives exit status 130.

Output folder of ``ps`` (``--out``, default ``results/ps_demo``): everything is
written into a temporary folder beside the target, ``manifest.json`` last; the
result is then committed by swapping folders (the old result renamed aside, the
new one renamed into place with Ctrl-C held off for the two renames, the old one
removed). At any moment the target holds either the previous complete result or
the new one, never a mix; a failed or interrupted run leaves the previous result
untouched. A folder is *ours* only if it holds our ``manifest.json`` and nothing
that the manifest does not list; anything else (a user's files, a result from
before manifests existed) is refused unless ``--overwrite`` is given, in which
case it is replaced as a whole. ``metrics.json`` is strict JSON (``null`` for
NaN / Inf).

Written files: ``normals.npy`` (H, W, 3) float32 in the DiLiGenT frame (zero
outside the mask), ``coefficients.exr`` (coefficient maps), ``metrics.json``,
``normal_map.png``, ``confidence.png`` (8-bit, when the solver reports a
confidence map), ``error_map.png`` (with ground truth) and ``relighting.png``
(input / relit / error; these two need matplotlib), ``result.npz`` (the whole
:class:`~torch_hsh.ps.HSHResult`, see ``HSHResult.load``), ``manifest.json``;
with ``--depth``: ``depth.npy``, ``depth.exr`` and ``surface.png`` (a shaded
rendering of the integrated depth); with ``--mesh``: ``mesh.ply`` (or
``mesh.obj``) and ``surface.png``.

Example::

    torch-hsh ps --out results/ps_demo
    torch-hsh ps --data ../shared/data/bunny_specular --holdout 5 --out results/bunny
    torch-hsh ps --data ../shared/data/diligent_cat --drop-first 0 --depth --mesh --out results/cat
    torch-hsh fit my_material.binary --order 6 --out my_material.npz
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from ._cli_common import InputError, _add_common, _int_in
from ._result_folder import (  # noqa: F401  (MANIFEST_VERSION, is_result_folder: importable from here as before)
    MANIFEST,
    MANIFEST_FORMAT,
    MANIFEST_VERSION,
    _check_out,
    _dump_json,
    _jsonable,
    _Staging,
    _umask,
    is_result_folder,
)

__all__ = ["main", "ps_main", "synthetic_scene", "MANIFEST", "MANIFEST_FORMAT", "is_result_folder"]

PROG = "torch-hsh"

# --------------------------------------------------------------------------- #
# argument types
# --------------------------------------------------------------------------- #
def _materials_arg(text: str):
    """``auto``, or an integer in [0, 8] (0: independent per-pixel BRDFs; the library takes 1 to 8 basis BRDFs)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return _int_in(0, 8)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer between 0 (independent BRDFs) and 8, "
                                         f"got {text!r}") from None


def _parse_device(ap: argparse.ArgumentParser, spec: str) -> torch.device:
    try:
        dev = torch.device(spec)
    except (RuntimeError, ValueError) as err:
        ap.error(f"argument --device: invalid device {spec!r} ({err})")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            ap.error(f"argument --device: {spec!r} requested but CUDA is not available (use --device cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            ap.error(f"argument --device: {spec!r} but only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps":
        if not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            ap.error(f"argument --device: {spec!r} requested but MPS is not available")
    elif dev.type != "cpu":
        ap.error(f"argument --device: unsupported device type {dev.type!r} (cpu, cuda, cuda:N or mps)")
    return dev



# --------------------------------------------------------------------------- #
# data
# --------------------------------------------------------------------------- #
def synthetic_scene(size: int = 48, n_lights: int = 40, seed: int = 0, dtype=torch.float64) -> Dict[str, Any]:
    """Sphere with three analytic-BRDF regions, textured albedo, DiLiGenT-like lights, noise.

    Returns a dict with ``images (L, H, W, 3)``, ``lights (L, 3)``,
    ``intensities (L, 3)``, ``mask (H, W)``, ``normals_gt (H, W, 3)``,
    ``labels`` and ``name``.

    Example:
        >>> d = synthetic_scene(16, 8)
        >>> tuple(d["images"].shape), tuple(d["lights"].shape)
        ((8, 16, 16, 3), (8, 3))
    """
    from . import scenes
    from .brdf import BlinnPhong, CookTorranceGGX, TorranceSparrow
    from .render import add_sensor_noise, quantize, render

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
    img = quantize(add_sensor_noise(img, read_std=2e-3 * full, shot_gain=1e-4 * full, seed=seed), 16, full)
    img = img * mask[None, ..., None].to(dtype)
    return dict(images=img, lights=lights, intensities=inten, mask=mask, normals_gt=normals,
                labels=labels, name="synthetic sphere (GGX / Blinn-Phong / Torrance-Sparrow)")


def _load_data(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    if args.data is not None:  # the synthetic scene's options would be ignored: say so instead
        given = [f"--{k}" for k in ("scene", "size", "lights") if getattr(args, k) is not None]
        if given:
            ap.error(f"argument {'/'.join(given)}: applies to the synthetic scene, not with --data")
    elif args.linear:
        ap.error("argument --linear: applies to RTI captures (--data) only")
    if args.data is None:
        d: Dict[str, Any]
        args.scene = args.scene or "demo"
        demo = args.scene == "demo"
        if args.size is None:
            args.size = 128 if demo else 48
        if args.lights is None:
            args.lights = 96 if demo else 40
        if args.drop_first >= args.lights:
            ap.error(f"argument --drop-first: {args.drop_first} leaves no image of the {args.lights} synthetic lights")
        left = args.lights - args.drop_first if args.max_images is None else min(
            args.max_images, args.lights - args.drop_first)
        if left < 3:
            ap.error(f"argument --drop-first/--max-images: {left} synthetic image(s) left; at least 3 are needed")
        if demo:
            from .scenes import demo_scene

            d = demo_scene(args.size, n_lights=args.lights, seed=args.seed, dtype=torch.float32)
        else:
            d = synthetic_scene(args.size, args.lights, args.seed)
        stop = None if args.max_images is None else args.drop_first + args.max_images
        sel = slice(args.drop_first, stop)
        d.update(images=d["images"][sel], lights=d["lights"][sel], intensities=d["intensities"][sel])
        return d
    from .io.diligent import load_diligent
    from .io.rti import is_rti_folder, load_rti

    folder = Path(args.data)
    rti = is_rti_folder(folder)  # an RTI capture: *.lp + photographs (torch_hsh.io.rti)
    if not folder.is_dir() and not rti:
        ap.error(f"argument --data: {folder} is not a folder")
    if args.linear and not rti:
        ap.error(f"argument --linear: applies to RTI captures only; {folder} is a DiLiGenT folder (linear 16-bit PNGs)")
    try:
        if rti:
            ds = load_rti(folder, linear=args.linear, dtype=torch.float32, drop_first=args.drop_first,
                          max_images=args.max_images)
        else:
            ds = load_diligent(folder, dtype=torch.float32, normalize_intensities=True,
                               drop_first=args.drop_first, max_images=args.max_images)
    except ValueError as err:
        if "images left after" in str(err):  # too few images left by --drop-first / --max-images
            ap.error(f"argument --drop-first/--max-images: {err}")
        raise InputError(str(err)) from err
    except (OSError, TypeError) as err:
        raise InputError(str(err)) from err
    return dict(images=ds.images, lights=ds.lights, intensities=None, mask=ds.mask, normals_gt=ds.normals_gt,
                name=str(folder))


# --------------------------------------------------------------------------- #
# figures
# --------------------------------------------------------------------------- #
def _to_png8(x: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(x, 0.0, 1.0) * 255).astype(np.uint8)


def _save_pictures(stage: _Staging, data, res, err_map, confidence, relit_idx: int, say) -> List[str]:
    """normal_map.png / confidence.png (kornia-rs) and error_map.png / relighting.png (matplotlib)."""
    from .io.diligent import _write_png

    mask = data["mask"].cpu().numpy()
    n = res.normals.detach().cpu().numpy()
    _write_png(stage.file("normal_map.png"), _to_png8(np.where(mask[..., None], (n + 1) / 2, 1.0)))
    if confidence is not None:
        _write_png(stage.file("confidence.png"), _to_png8(np.where(mask, confidence, 0.0)))
    try:
        import matplotlib
    except ImportError:
        say("matplotlib is not installed: error_map.png and relighting.png skipped "
            "(pip install 'torch-hsh[examples]')")
        return stage.files
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if err_map is not None:
        fig, ax = plt.subplots(figsize=(4.2, 3.6))
        e = np.where(mask, err_map, np.nan)
        im = ax.imshow(e, cmap="magma", vmin=0, vmax=max(10.0, float(np.nanpercentile(e, 99))))
        ax.set_title("HSH angular error (deg)")
        ax.axis("off")
        fig.colorbar(im, ax=ax)
        fig.tight_layout()
        fig.savefig(stage.file("error_map.png"), dpi=100)
        plt.close(fig)
    lt = data["lights"][relit_idx : relit_idx + 1].to(res.normals)
    ei = None if data["intensities"] is None else data["intensities"][relit_idx : relit_idx + 1].to(res.normals)
    relit = res.relight(lt, ei)[0].detach().cpu().numpy()
    inp = data["images"][relit_idx].detach().cpu().numpy()
    scale = float(np.percentile(inp[mask], 99.5)) if mask.any() else 1.0
    scale = scale or 1.0
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
    fig.savefig(stage.file("relighting.png"), dpi=100)
    plt.close(fig)
    return stage.files


def _confidence_map(res, mask: torch.Tensor) -> Optional[np.ndarray]:
    """The solver's ``confidence`` (H, W) in [0, 1] as a NumPy array, or None if it has none."""
    conf = getattr(res, "confidence", None)
    if conf is None:
        return None
    c = torch.as_tensor(conf).detach().to("cpu", torch.float64)
    if tuple(c.shape) != tuple(mask.shape):
        raise RuntimeError(f"solver confidence has shape {tuple(c.shape)}, expected {tuple(mask.shape)}")
    inside = c[mask.cpu()]
    if not bool(torch.isfinite(inside).all()) or bool((inside < 0).any()) or bool((inside > 1).any()):
        raise RuntimeError("solver confidence is not within [0, 1] inside the mask")
    return c.numpy()


def _confidence_summary(conf: np.ndarray, mask: np.ndarray) -> Dict[str, Any]:
    v = conf[mask]
    if v.size == 0:
        return {"pixels": 0}
    return {
        "mean": float(v.mean()), "median": float(np.median(v)), "min": float(v.min()), "max": float(v.max()),
        "fraction_below_0.5": float((v < 0.5).mean()), "pixels": int(v.size),
    }


# --------------------------------------------------------------------------- #
# ps
# --------------------------------------------------------------------------- #
def _ps_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "ps", help="photometric stereo (HSH solver vs Lambertian baselines)",
        description="Photometric stereo with the isotropic Helmholtz HSH basis on a DiLiGenT-layout folder "
                    "or, without --data, on a built-in synthetic scene. Writes a result folder atomically.",
    )
    p.add_argument("--data", default=None, help="DiLiGenT-layout object folder, or an RTI capture (a folder with one "
                                                "*.lp file and its photographs; default: synthetic scene)")
    p.add_argument("--linear", action="store_true",
                   help="RTI captures only: the photographs are already linear (default: remove the sRGB curve)")
    p.add_argument("--out", default="results/ps_demo", help="output folder (default results/ps_demo)")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or mps (default cpu)")
    p.add_argument("--holdout", type=_int_in(0), default=0,
                   help="0 (off) or 1..L-3: also fit on all but N lights and report the relighting error")
    p.add_argument("--drop-first", type=_int_in(0), default=0, help="skip the first N images (e.g. 20 for bearPNG)")
    p.add_argument("--max-images", type=_int_in(3), default=None, help="use at most N images (N >= 3)")
    p.add_argument("--scene", choices=("demo", "small"), default=None,
                   help="synthetic scene without --data: demo (default; a 128x128 bumpy sphere, GGX / Blinn-Phong "
                        "over a texture, cast shadows, 96 lights, noise, 16 bit: torch_hsh.scenes.demo_scene) or small "
                        "(a 48x48 sphere with three materials and 40 lights)")
    p.add_argument("--size", type=_int_in(8, 4096), default=None, help="synthetic image size (demo 128, small 48)")
    p.add_argument("--lights", type=_int_in(3, 10000), default=None, help="synthetic number of lights (demo 96, small 40)")
    p.add_argument("--seed", type=_int_in(0), default=0)
    p.add_argument("--threads", type=_int_in(1, 1024), default=2, help="CPU threads for torch (default 2)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out folder that is not a torch-hsh result (its files are deleted)")
    p.add_argument("--depth", action="store_true",
                   help="integrate the normals: write depth.npy and depth.exr (pixel units, orthographic) and surface.png")
    p.add_argument("--mesh", nargs="?", const="ply", choices=("ply", "obj"), default=None,
                   help="also write the surface as a mesh (mesh.ply, or mesh.obj with --mesh obj; needs torch-hsh[mesh])")
    p.add_argument("--integrator", choices=("poisson", "bilateral"), default="poisson",
                   help="normal integration for --depth / --mesh (default poisson)")
    p.add_argument("--figures", default=None, help="also copy the PNGs (prefixed ps_) into this folder")
    _add_solver_flags(p)
    _add_common(p)
    p.set_defaults(handler=_run_ps, parser=p)
    return p


def _solver_flags():
    """The fields of :class:`torch_hsh.ps.Settings` that name a ``torch-hsh ps`` flag, with that flag's spec."""
    import dataclasses

    from .ps.settings import Settings

    return [(f, f.metadata["cli"]) for f in dataclasses.fields(Settings) if f.metadata["cli"] is not None]


def _add_solver_flags(p: argparse.ArgumentParser) -> None:
    """The solver's flags, generated from the fields of :class:`torch_hsh.ps.Settings` (flag, type, help)."""
    types: Dict[str, Any] = {"int": _int_in, "float": lambda lo, hi, lo_open: _float_in(lo, hi, lo_open=lo_open),
             "materials": lambda: _materials_arg}
    g = p.add_argument_group("HSH solver options (fields of torch_hsh.ps.Settings)")
    for f, cli in _solver_flags():
        if "const" in cli:  # a switch that sets the option to one value
            g.add_argument(cli["flag"], dest=f.name, action="store_const", const=cli["const"], help=cli["help"])
        else:
            kind, *bounds = cli["type"]
            g.add_argument(cli["flag"], dest=f.name, type=types[kind](*bounds), default=f.default, help=cli["help"])


def _solver_options(args) -> Dict[str, Any]:
    """The solver's options from the flags: a flag left out gives the option's default (the flag's argparse
    default, so the manifest records it); a switch left out gives nothing; ``--materials 0`` is the independent
    model (``materials=None``)."""
    opts = {}
    for f, cli in _solver_flags():
        value = getattr(args, f.name)
        if value is None and "const" in cli:
            continue
        opts[f.name] = f.default if value is None else value
    if opts.get("materials") == 0:
        opts["materials"] = None
    return opts


def _save_surface(stage, args, res, mask, metrics, say) -> None:
    """depth.npy + depth.exr (``--depth``), mesh.ply / mesh.obj (``--mesh``) and surface.png from the normals."""
    from .io.diligent import _write_png
    from .surface import integrate_normals, save_depth, save_mesh, shade_depth

    t = time.perf_counter()
    n = res.normals.detach().cpu().double()
    m = mask.cpu()
    if getattr(res, "depth", None) is not None:  # the whole-surface stage's own depth (--refine-surface)
        depth, how = res.depth.detach().cpu().double(), "whole-surface stage"
        metrics["surface"] = {"integrator": how, "components": None, "runtime_s": 0.0}
    else:
        depth, info = integrate_normals(n, m, method=args.integrator, return_info=True)
        how = f"{args.integrator} integration"
        metrics["surface"] = {"integrator": args.integrator, "components": info.get("components"),
                              "runtime_s": time.perf_counter() - t}
    if args.depth:
        save_depth(stage.file("depth.npy"), depth, m)
        save_depth(stage.file("depth.exr"), depth, m)
    if args.mesh:
        albedo = res.albedo.detach().cpu().double() if getattr(res, "albedo", None) is not None else None
        save_mesh(stage.file(f"mesh.{args.mesh}"), depth, m, normals=n, albedo=albedo)
    img = shade_depth(depth, m).cpu().numpy()
    _write_png(stage.file("surface.png"), _to_png8(img))
    say(f"surface: {how} in {metrics['surface']['runtime_s']:.2f} s")


def _errors(n, gt, mask):
    from . import ps

    if gt is None:
        return float("nan"), float("nan")
    e = ps.angular_error(n, gt.to(n))[mask]
    return float(e.mean()), float(e.median())


def _check_ps_paths(args, ap: argparse.ArgumentParser):
    """``--out`` (checked, not yet created) and ``--figures`` (or None): neither inside the other nor the data."""
    out = _check_out(ap, Path(args.out), args.overwrite)
    if args.data is not None:
        data_dir = Path(os.path.abspath(args.data))
        if data_dir == out or out in data_dir.parents or data_dir in out.parents:
            ap.error("argument --out: must not be the --data folder, inside it or around it")
    figures = None
    if args.figures is not None:
        figures = Path(os.path.abspath(args.figures))
        if figures.exists() and not figures.is_dir():
            ap.error(f"argument --figures: {figures} exists and is not a folder")
        if figures == out or out in figures.parents:
            ap.error("argument --figures: must not be inside --out (the result folder is replaced as a whole)")
    return out, figures


def _solve_methods(args, opts, imgs, lights, inten, mask, gt, say):
    """Lambertian LS, robust Lambertian and the HSH solver; returns the HSH result, its time and the table rows."""
    from . import ps

    rows = []
    t = time.perf_counter()
    lam = ps.lambertian_ls(imgs, lights, inten, mask)
    rows.append(("Lambertian LS", *_errors(lam.normals, gt, mask), time.perf_counter() - t))
    t = time.perf_counter()
    rob = ps.robust_lambertian(imgs, lights, inten, mask)
    rows.append(("robust Lambertian (trimmed)", *_errors(rob.normals, gt, mask), time.perf_counter() - t))
    t = time.perf_counter()
    res = ps.solve_hsh(imgs, lights, inten, mask, progress=not args.quiet, **opts)
    t_hsh = time.perf_counter() - t
    rows.append((f"HSH (order {opts['order']})", *_errors(res.normals, gt, mask), t_hsh))
    for line in _stage_report(res.info):
        say(line)
    say(f"\n{'method':32s} {'mean (deg)':>10s} {'median (deg)':>12s} {'time (s)':>9s}")
    for name, mean, med, tt in rows:
        if gt is None:  # no error to report: say why instead of nan
            say(f"{name:32s} {'n/a':>10s} {'n/a':>12s} {tt:9.2f}")
        else:
            say(f"{name:32s} {mean:10.2f} {med:12.2f} {tt:9.2f}")
    if gt is None:
        say("(n/a: the data have no ground-truth normals, e.g. no Normal_gt.mat)")
    return res, t_hsh, rows


def _stage_report(info: Dict[str, Any]) -> List[str]:
    """One line per stage that ran after the solve (interreflections, whole surface): its safeguard's decision
    and the numbers it was taken on (``info`` of the result)."""
    lines = []
    if "interreflection_accepted" in info:
        kept = "kept" if info["interreflection_accepted"] else "rejected, the first solve is returned"
        lines.append(f"interreflections: one bounce ({info['interreflection_fraction']:.2%} of the light) removed, "
                     f"round {kept} (mean confidence {info['interreflection_confidence_before']:.4f} -> "
                     f"{info['interreflection_confidence_after']:.4f}; {info['interreflection_time_s']:.1f} s of "
                     f"bounce)")
    if "surface_accepted" in info:
        kept = "kept" if info["surface_accepted"] else "rejected, its start is returned"
        lines.append(f"whole-surface stage: {kept} (held-out-light loss {info['surface_heldout_before']:.4g} -> "
                     f"{info['surface_heldout_after']:.4g}; {info['surface_time_s']:.1f} s)")
    return lines


def _holdout_metrics(args, opts, imgs, lights, inten, mask, say) -> Dict[str, Any]:
    """``--holdout N``: the relighting error on N held-out lights, with the same solver options."""
    from . import ps

    t = time.perf_counter()
    ho = ps.holdout_evaluation(imgs, lights, inten, mask, holdout=args.holdout, seed=args.seed, **opts)
    say(f"\nheld-out relighting ({args.holdout} lights): HSH relative RMSE {ho.relative_rmse:.4f}, "
        f"robust Lambertian {ho.lambertian_relative_rmse:.4f}")
    return {"held_out_lights": ho.test_indices.tolist(), "relative_rmse": ho.relative_rmse, "rmse": ho.rmse,
            "lambertian_relative_rmse": ho.lambertian_relative_rmse, "runtime_s": time.perf_counter() - t}


def _run_ps(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    from . import ps
    from .io.exr import write_coefficient_maps_exr

    say = (lambda *a, **k: None) if args.quiet else (lambda *a, **k: print(*a, **k, flush=True))
    # ---- arguments and inputs, nothing created yet
    dev = _parse_device(ap, args.device)
    out, figures = _check_ps_paths(args, ap)
    torch.set_num_threads(args.threads)
    opts = _solver_options(args)
    order, materials = opts["order"], opts["materials"]
    if args.mesh:
        try:
            import trimesh  # noqa: F401
        except ImportError:
            ap.error("argument --mesh: needs trimesh (pip install 'torch-hsh[mesh]')")
    data = _load_data(args, ap)
    L = int(data["images"].shape[0])
    if args.holdout and not 1 <= args.holdout <= L - 3:
        ap.error(f"argument --holdout: must be 0 (off) or between 1 and L-3 = {L - 3} "
                 f"so that at least 3 of the L = {L} lights remain, got {args.holdout}")
    data = {k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in data.items()}
    imgs, lights, inten, mask, gt = (data[k] for k in ("images", "lights", "intensities", "mask", "normals_gt"))
    P = int(mask.sum())
    if P == 0:
        raise InputError(f"{data['name']}: the mask selects no pixel")

    previous = _previous_result(out)
    if previous is not None:
        say(f"--out {out} holds a torch-hsh result ({previous}); it is replaced when this run ends")
    # ---- solve (the output folder is staged only now, so a failed solve creates nothing)
    with _Staging(out) as stage:
        say(f"data: {data['name']}  pixels={P} lights={L} order={order} "
            f"materials={materials if materials else 'independent'} device={dev}")
        res, t_hsh, rows = _solve_methods(args, opts, imgs, lights, inten, mask, gt, say)
        metrics: Dict[str, Any] = {
            "method": "hsh", "order": order, "materials": materials, "pixels": P, "lights": L,
            "runtime_s": t_hsh, "data": data["name"], "drop_first": args.drop_first,
            "methods": {name: {"mean_angular_error_deg": m, "median_angular_error_deg": md, "runtime_s": tt}
                        for name, m, md, tt in rows},
            "solver_info": res.info,
        }
        err_map: Optional[np.ndarray] = None
        if gt is not None:
            metrics["mean_angular_error_deg"] = rows[2][1]
            metrics["median_angular_error_deg"] = rows[2][2]
            metrics["lambertian_mean_angular_error_deg"] = rows[0][1]
            metrics["robust_lambertian_mean_angular_error_deg"] = rows[1][1]
            err_map = ps.angular_error(res.normals, gt.to(res.normals), mask).cpu().numpy()
        confidence = _confidence_map(res, mask)
        if confidence is not None:
            metrics["confidence"] = _confidence_summary(confidence, mask.cpu().numpy())
        if args.holdout > 0:
            metrics["holdout"] = _holdout_metrics(args, opts, imgs, lights, inten, mask, say)

        np.save(stage.file("normals.npy"), res.normals.detach().cpu().numpy().astype(np.float32))
        if hasattr(res, "save"):
            res.save(stage.file("result.npz"))
        if args.depth or args.mesh:
            _save_surface(stage, args, res, mask, metrics, say)
        write_coefficient_maps_exr(stage.file("coefficients.exr"), res.coefficients.detach().cpu().float())
        _dump_json(stage.file("metrics.json"), metrics)
        _save_pictures(stage, data, res, err_map, confidence, relit_idx=L // 2, say=say)
        from ._version import __version__

        stage.write_manifest({"tool": f"{PROG} ps", "torch_hsh_version": __version__,
                              "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                              "arguments": _jsonable({k: v for k, v in vars(args).items() if k not in ("handler", "parser")})})
        written = sorted(stage.files + [MANIFEST])
        stage.commit()
    if figures is not None:
        figures.mkdir(parents=True, exist_ok=True)
        for f in written:
            if f.endswith(".png"):
                shutil.copyfile(out / f, figures / f"ps_{f}")
    say(f"\nwrote {out}/ ({', '.join(written)})" + ("" if previous is None else f", replacing the result ({previous})"))
    return _jsonable(metrics)


def _previous_result(out: Path) -> Optional[str]:
    """``"of <created_utc>"`` (or ``"of an unknown date"``) if ``out`` holds a torch-hsh result (its manifest; the
    files were checked against it by ``_check_out``), else None."""
    from ._result_folder import _read_manifest

    meta = _read_manifest(out) if out.is_dir() else None
    if meta is None:
        return None
    created = meta.get("created_utc")
    return f"of {created}" if isinstance(created, str) else "of an unknown date"


# --------------------------------------------------------------------------- #
# fit
# --------------------------------------------------------------------------- #
def _float_in(lo: float, hi: float, lo_open: bool = False, hi_open: bool = False):
    """A finite number in the interval ``lo .. hi`` (each end open or closed)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and (
            value < hi if hi_open else value <= hi)
        if not ok:
            rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            raise argparse.ArgumentTypeError(f"must be a number in {rng}, got {text}")
        return value

    return parse


def _fit_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "fit", help="fit the isotropic Helmholtz basis to a MERL .binary BRDF",
        description="Fit the isotropic Helmholtz basis to a MERL .binary BRDF and write the (3, K) RGB "
                    "coefficients, the relative L2 error on the table's samples and Acc(P) to an .npz file. "
                    "Default (--method samples): weighted least squares on the table's own samples with the "
                    "solid-angle weights of the half/difference bins (torch_hsh.io.fit_merl), seconds at any "
                    "lobe width. --method quadrature: the convergence-controlled projection of the table "
                    "lookup (torch_hsh.project), which is slow for sharp lobes and needs --grazing-cutoff for "
                    "the energy of raw microfacet tables.",
    )
    p.add_argument("merl", help="MERL .binary file")
    p.add_argument("--order", type=_int_in(0, 12), default=6, help="basis order P (default 6)")
    p.add_argument("--out", required=True, help="output .npz file (refused if it exists unless --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--method", choices=("samples", "quadrature"), default="samples",
                   help="samples (default): weighted least squares on the table's samples; quadrature: "
                        "adaptive projection of the table lookup")
    p.add_argument("--ridge", type=_float_in(0.0, 1e6), default=None,
                   help="Tikhonov ridge of the least-squares fit (--method samples; default 0; the normal matrix is "
                        "close to the identity, so the ridge is relative to 1)")
    p.add_argument("--grazing-cutoff", type=_float_in(0.0, 1.0, hi_open=True), default=None, metavar="C",
                   help="fit the BRDF set to zero where cos(theta_i) or cos(theta_o) < C (both methods; needed for "
                        "the energy of raw microfacet tables with --method quadrature)")
    p.add_argument("--tol", type=_float_in(0.0, 1.0, lo_open=True, hi_open=True), default=None,
                   help="--method quadrature: target relative error of the refinement (default 1e-3)")
    p.add_argument("--max-evaluations", type=_int_in(1), default=None,
                   help="--method quadrature: budget of BRDF evaluations (default 2^27)")
    p.add_argument("--accept-unconverged", action="store_true",
                   help="--method quadrature: when the budget runs out, warn and write the best result with its "
                        "error estimate instead of failing")
    p.add_argument("--threads", type=_int_in(1, 1024), default=2)
    _add_common(p)
    p.set_defaults(handler=_run_fit, parser=p)
    return p


#: Python argument names in library messages -> the fit options that set them.
_FIT_OPTION_NAMES = (
    ("pass strict=False", "pass --accept-unconverged"),
    ("grazing_cutoff=c", "--grazing-cutoff C"),
    ("grazing_cutoff", "--grazing-cutoff"),
    ("max_evaluations", "--max-evaluations"),
    ("ridge > 0", "--ridge > 0"),
    ("tol=", "--tol="),
    ("loosen tol", "loosen --tol"),
    ("n_phi refinements", "azimuthal refinements"),
)


def _fit_message(text: str) -> str:
    """A library message with its Python argument names replaced by the ``fit`` options."""
    for py, opt in _FIT_OPTION_NAMES:
        text = text.replace(py, opt)
    return text


def _check_fit_out(ap: argparse.ArgumentParser, out: Path, overwrite: bool) -> Path:
    """All checks of ``fit --out`` before any work: name, existing file, a writable folder (probed)."""
    if out.suffix != ".npz":
        ap.error(f"argument --out: expected a .npz file name, got {out.name}")
    if out.is_dir():
        ap.error(f"argument --out: {out} is a folder")
    if out.exists() and not overwrite:
        ap.error(f"argument --out: {out} exists; pass --overwrite to replace it")
    anc = out.parent
    while not anc.exists() and anc.parent != anc:
        anc = anc.parent
    if not anc.is_dir():
        ap.error(f"argument --out: cannot create {out}: {anc} is not a folder")
    # os.access says yes to root everywhere (even /proc): create and remove a file to be sure
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".probe", dir=anc)
    except OSError as err:
        ap.error(f"argument --out: cannot write into {anc} ({err.strerror or err})")
    os.close(fd)
    os.unlink(probe)
    return out


def _run_fit(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    from .fitting import ConvergenceError

    say = (lambda *a, **k: None) if args.quiet else (lambda *a, **k: print(*a, **k, flush=True))
    # ---- arguments, --out and the input file, before any work
    if args.method == "samples":
        for name in ("tol", "max_evaluations"):
            if getattr(args, name) is not None:
                ap.error(f"argument --{name.replace('_', '-')}: applies to --method quadrature only")
        if args.accept_unconverged:
            ap.error("argument --accept-unconverged: applies to --method quadrature only")
    elif args.ridge is not None:
        ap.error("argument --ridge: applies to --method samples only")
    out = _check_fit_out(ap, Path(os.path.abspath(args.out)), args.overwrite)
    torch.set_num_threads(args.threads)
    from .io.merl import read_merl

    try:
        brdf = read_merl(args.merl)
    except (ValueError, OSError, TypeError) as err:
        raise InputError(str(err)) from err
    say(f"{args.merl}: table {brdf.shape}, {float(brdf.measured.double().mean()):.1%} of the bins measured; "
        f"order {args.order}, method {args.method}")
    t = time.perf_counter()
    try:
        if args.method == "samples":
            result = _fit_samples(brdf, args)
        else:
            say("projecting by adaptive quadrature (no progress bar: refinement sizes are not known in advance; "
                "sharp lobes take minutes, --method samples takes seconds)")
            result = _fit_quadrature(brdf, args)
    except ConvergenceError as err:
        raise RuntimeError(_fit_message(str(err)) + " Or use --method samples (the default), which fits the "
                           "table's samples without a quadrature.") from err
    except ValueError as err:
        raise RuntimeError(_fit_message(str(err))) from err
    coeffs, arrays, extra = result
    rel = arrays["relative_error"]
    summary = {"file": str(args.merl), "order": args.order, "method": args.method,
               "num_functions": int(coeffs.shape[-1]), "grazing_cutoff": args.grazing_cutoff,
               "relative_error": rel.tolist(), "energy_accuracy": arrays["energy_accuracy"].tolist(),
               "runtime_s": time.perf_counter() - t, **extra}
    _write_fit_npz(out, coeffs, arrays, summary)
    say(f"order {args.order}: {coeffs.shape[-1]} functions x 3 channels, {summary['runtime_s']:.1f} s")
    say(f"relative L2 error on the table's samples (R, G, B): {', '.join(f'{v:.4g}' for v in rel.tolist())}"
        + (" (solid-angle weighted)" if args.method == "samples" else " (sqrt(1 - Acc(P)))"))
    if "relative_error_unweighted" in extra:
        say("  every measured bin weighted alike: "
            f"{', '.join(f'{v:.4g}' for v in extra['relative_error_unweighted'])}")
    if float(rel.max()) > 0.5:
        say("  most of the table's L2 norm is in what order P cannot represent: a sharp specular peak, or the "
            "grazing growth of a raw microfacet table; a higher --order or --grazing-cutoff (e.g. 0.1) tells which")
    say(f"Acc(P') for P' = 0..{args.order} (mean over RGB): "
        f"{', '.join(f'{v:.4f}' for v in arrays['energy_accuracy'].mean(0).tolist())}")
    say(f"wrote {out}")
    return _jsonable(summary)


def _write_fit_npz(out: Path, coeffs, arrays, summary) -> None:
    """Write the fit's ``.npz`` atomically; missing parent folders are created now, and removed again if the write fails."""
    created = []
    anc = out.parent
    while not anc.exists():
        created.append(anc)
        anc = anc.parent
    tmp = None
    try:
        for d in reversed(created):
            d.mkdir()
        fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".npz", dir=out.parent)
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, coefficients=coeffs, metadata=np.array(json.dumps(_jsonable(summary), allow_nan=False)),
                     **arrays)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, out)
        tmp = None
    except BaseException:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        for d in created:  # innermost first; only folders this run created, and only if still empty
            try:
                d.rmdir()
            except OSError:
                break
        raise


def _fit_samples(brdf, args):
    from .io.merl import fit_merl

    coeffs, info = fit_merl(brdf, args.order, ridge=args.ridge or 0.0, grazing_cutoff=args.grazing_cutoff,
                            progress=not args.quiet, return_info=True)
    arrays = {"relative_error": info["relative_error"].numpy(), "energy": info["energy"].numpy(),
              "energy_accuracy": info["accuracy"].numpy(),
              "relative_error_per_order": info["relative_error_per_order"].numpy()}
    extra = {"relative_error_unweighted": info["relative_error_unweighted"].tolist(),
             "relative_error_per_order": info["relative_error_per_order"].tolist(),
             "weights": "solid angle of each half/difference bin (torch_hsh.io.merl.merl_solid_angle_weights)",
             "ridge": args.ridge or 0.0, "num_samples": info["num_samples"], "coverage": info["coverage"],
             "condition": info["condition"]}
    return coeffs.numpy(), arrays, extra


def _fit_quadrature(brdf, args):
    from .fitting import brdf_energy, energy_accuracy, project

    kw: Dict[str, Any] = {"grazing_cutoff": args.grazing_cutoff, "strict": not args.accept_unconverged}
    if args.tol is not None:
        kw["tol"] = args.tol
    if args.max_evaluations is not None:
        kw["max_evaluations"] = args.max_evaluations
    import warnings

    from .fitting import ConvergenceWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        coeffs, info = project(brdf, order=args.order, return_info=True, **kw)
        energy = brdf_energy(brdf, order=args.order, **kw)
    for w in caught:  # --accept-unconverged: said in the options' names, even with --quiet
        if issubclass(w.category, ConvergenceWarning):
            print(f"{PROG} fit: warning: {_fit_message(str(w.message))}", file=sys.stderr, flush=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    coeffs, energy = coeffs.detach().cpu(), energy.detach().cpu()
    acc = energy_accuracy(coeffs, energy)
    rel = torch.sqrt((1.0 - acc[:, -1]).clamp(min=0.0))
    arrays = {"relative_error": rel.numpy(), "energy": energy.numpy(), "energy_accuracy": acc.numpy()}
    extra = {"error_estimate": info["error_estimate"], "n_theta": info["n_theta"], "n_phi": info["n_phi"],
             "converged": info["converged"]}
    return coeffs.numpy(), arrays, extra


# --------------------------------------------------------------------------- #
# entry points
# --------------------------------------------------------------------------- #
def build_parser() -> argparse.ArgumentParser:
    """The ``torch-hsh`` argument parser (subcommands ``ps``, ``fit``, ``lights``, ``rti`` and ``view``)."""
    from ._version import __version__

    ap = argparse.ArgumentParser(prog=PROG, description="Helmholtz HSH BRDF tools (torch_hsh).")
    ap.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    _ps_parser(sub)
    _fit_parser(sub)
    from .cli_rti import add_rti_commands  # lights, rti (torch_hsh/cli_rti.py)

    add_rti_commands(sub)
    return ap


def _one_line_warning(prefix: str):
    """A ``warnings.showwarning`` that prints ``prefix message`` on one line of stderr, without the source line."""
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{prefix} {' '.join(str(message).split())}", file=sys.stderr if file is None else file, flush=True)

    return show


def _dispatch(argv: Optional[List[str]]):
    ap = build_parser()
    args = ap.parse_args(argv)
    sub_ap = args.parser  # errors carry the subcommand's usage
    prefix = f"{PROG} {args.command}: error:"
    try:
        with warnings.catch_warnings():
            if not args.debug:  # a library warning is one line, like the errors; --debug keeps Python's form
                warnings.showwarning = _one_line_warning(f"{PROG} {args.command}: warning:")
            return args.handler(args, sub_ap)
    except SystemExit:
        raise
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"{prefix} interrupted; the previous output (if any) is unchanged", file=sys.stderr)
        raise SystemExit(130) from None
    except Exception as err:  # one line, traceback only with --debug
        if args.debug:
            traceback.print_exc()
        else:
            msg = " ".join(str(err).split()) or type(err).__name__
            hint = "" if isinstance(err, InputError) else f" ({type(err).__name__}; --debug shows the traceback)"
            print(f"{prefix} {msg}{hint}", file=sys.stderr)
        raise SystemExit(1) from None


def ps_main(argv: Optional[List[str]] = None) -> Dict[str, Any]:
    """``torch-hsh ps`` in-process: returns the metrics dict; errors raise ``SystemExit(1 or 2)``."""
    return _dispatch(["ps"] + list(sys.argv[1:] if argv is None else argv))


def main(argv: Optional[List[str]] = None) -> int:
    """Console entry point of ``torch-hsh``; returns the exit status (errors raise ``SystemExit``)."""
    _dispatch(argv)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
