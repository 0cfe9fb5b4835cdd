r"""The photometric-stereo commands of ``torch-hsh``: ``ps`` on a capture, ``demo`` on a synthetic scene.

* ``torch-hsh ps CAPTURE`` — photometric stereo with the isotropic Helmholtz HSH basis on a
  DiLiGenT-layout folder or an RTI capture (a folder with one ``.lp`` file and its photographs).
  Compares Lambertian least squares, robust (trimmed) Lambertian and the HSH solver and writes a
  result folder (default ``<CAPTURE name>_ps`` in the current folder).
* ``torch-hsh demo`` — the same on a built-in synthetic scene with ground truth
  (:func:`torch_hsh.render.scenes.demo_scene`: a 128x128 bumpy sphere under 96 lights; ``--scene small``:
  :func:`torch_hsh.render.scenes.synthetic_scene`, a 48x48 sphere with three materials under 40 lights).

Every argument and input file is checked before any folder is created and before the solve. A bad
argument gets an argparse message and exit status 2; a bad input file (or any other failure) one line
``torch-hsh ps: error: ...`` naming the file and exit status 1, with the traceback only under ``--debug``;
Ctrl-C gives exit status 130 and SIGTERM 143, both leaving the previous result untouched and no
temporary folder behind.

The result folder (``--out``) is written into a temporary folder beside the target, ``manifest.json``
last, and swapped into place (:mod:`torch_hsh.cli.result_folder`): the target holds either the previous
complete result or the new one, never a mix. A folder is *ours* only if it holds our ``manifest.json``
and nothing that the manifest does not list; anything else is refused unless ``--overwrite`` is given,
in which case it is replaced as a whole. ``metrics.json`` is strict JSON (``null`` for NaN / Inf).

Written files: ``normals.npy`` (H, W, 3) float32 in the DiLiGenT frame (zero outside the mask),
``coefficients.exr`` (coefficient maps), ``metrics.json``, ``normal_map.png``, ``confidence.png``
(8-bit, when the solver reports a confidence map), ``error_map.png`` (with ground truth) and
``relighting.png`` (input / relit / error; these two need matplotlib), ``result.npz`` (the whole
:class:`~torch_hsh.ps.HSHResult`, see ``HSHResult.read``), ``manifest.json``; with ``--depth``:
``depth.npy``, ``depth.exr`` and ``surface.png`` (a shaded rendering of the integrated depth); with
``--mesh``: ``mesh.ply`` (or ``mesh.obj``) and ``surface.png``.

Example::

    torch-hsh demo --out results/demo
    torch-hsh ps ../shared/data/diligent_cat --depth --mesh --out results/cat
    torch-hsh ps capture/ --linear-input --holdout 5
"""
from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import numpy as np
import torch

from ..cli.common import PROG, InputError, _add_common, _float_in, _int_in, _parse_device
from ..cli.result_folder import MANIFEST, _check_out, _dump_json, _jsonable, _Staging

__all__ = ["add_ps_commands", "MIN_IMAGES"]

#: The fewest images a run may keep (``--max-images``): the HSH model needs 4 observations per pixel.
MIN_IMAGES = 4


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



# --------------------------------------------------------------------------- #
# data
# --------------------------------------------------------------------------- #
def _default_out(name: str) -> str:
    """``--out`` when it is not given: ``<name>_ps`` in the current folder."""
    return f"{name}_ps"


def _load_demo(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    """The synthetic scene of ``torch-hsh demo`` (``--scene``, ``--size``, ``--lights``, ``--seed``)."""
    from ..render.scenes import demo_scene, synthetic_scene

    demo = args.scene == "demo"
    if args.size is None:
        args.size = 128 if demo else 48
    if args.lights is None:
        args.lights = 96 if demo else 40
    if args.drop_first >= args.lights:
        ap.error(f"argument --drop-first: {args.drop_first} leaves no image of the {args.lights} synthetic lights")
    left = args.lights - args.drop_first if args.max_images is None else min(
        args.max_images, args.lights - args.drop_first)
    if left < MIN_IMAGES:
        ap.error(f"argument --drop-first/--max-images: {left} synthetic image(s) left; at least {MIN_IMAGES} are "
                 "needed")
    if demo:
        d = demo_scene(args.size, n_lights=args.lights, seed=args.seed, dtype=torch.float32)
    else:
        d = synthetic_scene(args.size, args.lights, args.seed)
    stop = None if args.max_images is None else args.drop_first + args.max_images
    sel = slice(args.drop_first, stop)
    d.update(images=d["images"][sel], lights=d["lights"][sel], intensities=d["intensities"][sel])
    return d


def _load_capture(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    """The capture of ``torch-hsh ps CAPTURE``: a DiLiGenT-layout folder or an RTI capture."""
    from ..io.diligent import load_diligent
    from ..rti.io import is_rti_folder, load_rti

    folder = Path(args.capture)
    rti = is_rti_folder(folder)  # an RTI capture: *.lp + photographs (torch_hsh.rti.io)
    if not folder.is_dir() and not rti:
        what = "does not exist" if not folder.exists() else "is neither a folder nor an .lp file"
        ap.error(f"argument CAPTURE: {folder} {what}")
    if args.linear_input and not rti:
        ap.error(f"argument --linear-input: applies to RTI captures only; {folder} is a DiLiGenT folder "
                 "(linear 16-bit PNGs)")
    try:
        if rti:
            ds = load_rti(folder, linear=args.linear_input, dtype=torch.float32, drop_first=args.drop_first,
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
    if int(ds.images.shape[0]) < MIN_IMAGES:
        raise InputError(f"{folder}: {int(ds.images.shape[0])} image(s); photometric stereo with the HSH model "
                         f"needs at least {MIN_IMAGES}")
    return dict(images=ds.images, lights=ds.lights, intensities=None, mask=ds.mask, normals_gt=ds.normals_gt,
                name=str(folder))


def _to_png8(x: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(x, 0.0, 1.0) * 255).astype(np.uint8)


def _save_pictures(stage: _Staging, data, res, err_map, confidence, relit_idx: int, say) -> List[str]:
    """normal_map.png / confidence.png (kornia-rs) and error_map.png / relighting.png (matplotlib)."""
    from ..io.diligent import _write_png

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
# ps and demo
# --------------------------------------------------------------------------- #
def add_ps_commands(sub) -> None:
    """Add the ``ps`` and ``demo`` subparsers to the ``torch-hsh`` subparsers ``sub``."""
    p = sub.add_parser(
        "ps", help="photometric stereo on a capture (DiLiGenT folder or RTI capture)",
        description="Photometric stereo with the isotropic Helmholtz HSH basis on a capture: a DiLiGenT-layout "
                    "folder or an RTI capture (a folder with one *.lp file and its photographs). Compares the "
                    "HSH solver with Lambertian baselines and writes a result folder atomically.",
    )
    p.add_argument("capture", metavar="CAPTURE", help="DiLiGenT-layout folder, or an RTI capture (a folder with one *.lp file and its "
                                   "photographs, or the .lp file itself)")
    p.add_argument("--linear-input", action="store_true",
                   help="RTI captures: the photographs hold linear values (default: remove the sRGB curve); "
                        "DiLiGenT folders are always linear")
    _add_run_arguments(p, out_help="output folder (default: CAPTURE's name + '_ps', in the current folder)")
    p.set_defaults(handler=_run_ps, parser=p)

    d = sub.add_parser(
        "demo", help="photometric stereo on a built-in synthetic scene (no data needed)",
        description="Render a built-in synthetic scene with ground truth, solve it with the HSH solver and the "
                    "Lambertian baselines, print the angular errors and write a result folder.",
    )
    d.add_argument("--scene", choices=("demo", "small"), default="demo",
                   help="demo (default): a 128x128 bumpy sphere, GGX / Blinn-Phong over a texture, cast shadows, "
                        "96 lights, sensor noise, 16 bit; small: a 48x48 sphere with three materials and 40 lights")
    d.add_argument("--size", type=_int_in(8, 4096), default=None, help="image size (demo 128, small 48)")
    d.add_argument("--lights", type=_int_in(MIN_IMAGES, 10000), default=None,
                   help="number of lights (demo 96, small 40)")
    _add_run_arguments(d, out_help="output folder (default: the scene's name + '_ps', e.g. demo_ps, in the current "
                                   "folder)")
    d.set_defaults(handler=_run_demo, parser=d)


def _add_run_arguments(p: argparse.ArgumentParser, out_help: str) -> None:
    """The options that ``ps`` and ``demo`` share: output, device, image selection, surface, solver."""
    p.add_argument("--out", default=None, help=out_help)
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out folder that is not a torch-hsh result (its files are deleted)")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or mps (default cpu)")
    p.add_argument("--threads", type=_int_in(1, 1024), default=2, help="CPU threads for torch (default 2)")
    p.add_argument("--seed", type=_int_in(0), default=0,
                   help="seed of the synthetic scene (demo) and of the --holdout light choice (default 0)")
    p.add_argument("--holdout", type=_int_in(0), default=0,
                   help="0 (off) or 1..L-3: also fit on all but N lights and report the relighting error")
    p.add_argument("--drop-first", type=_int_in(0), default=0, help="skip the first N images (e.g. 20 for bearPNG)")
    p.add_argument("--max-images", type=_int_in(MIN_IMAGES), default=None,
                   help=f"use at most N images, the first N in the capture's order (N >= {MIN_IMAGES}: the HSH model "
                        f"needs {MIN_IMAGES} observations per pixel)")
    p.add_argument("--depth", action="store_true",
                   help="integrate the normals: write depth.npy and depth.exr (pixel units, orthographic) and surface.png")
    p.add_argument("--mesh", nargs="?", const="ply", choices=("ply", "obj"), default=None,
                   help="also write the surface as a mesh (mesh.ply, or mesh.obj with --mesh obj; needs torch-hsh[mesh])")
    p.add_argument("--integrator", choices=("poisson", "bilateral"), default="poisson",
                   help="normal integration for --depth / --mesh (default poisson)")
    p.add_argument("--figures", default=None, help="also copy the PNGs (prefixed ps_) into this folder")
    _add_solver_flags(p)
    _add_common(p)


def _solver_flags():
    """The fields of :class:`torch_hsh.ps.Settings` that name a ``torch-hsh ps`` flag, with that flag's spec."""
    import dataclasses

    from ..ps.settings import Settings

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
    from ..io.diligent import _write_png
    from ..surface import integrate_normals, write_depth, write_mesh, shade_depth

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
        write_depth(stage.file("depth.npy"), depth, m)
        write_depth(stage.file("depth.exr"), depth, m)
    if args.mesh:
        albedo = res.albedo.detach().cpu().double() if getattr(res, "albedo", None) is not None else None
        write_mesh(stage.file(f"mesh.{args.mesh}"), depth, m, normals=n, albedo=albedo)
    img = shade_depth(depth, m).cpu().numpy()
    _write_png(stage.file("surface.png"), _to_png8(img))
    say(f"surface: {how} in {metrics['surface']['runtime_s']:.2f} s")


def _errors(n, gt, mask):
    from .. import ps

    if gt is None:
        return float("nan"), float("nan")
    e = ps.angular_error(n, gt.to(n))[mask]
    return float(e.mean()), float(e.median())


def _check_ps_paths(args, ap: argparse.ArgumentParser):
    """``--out`` (checked, not yet created) and ``--figures`` (or None): neither inside the other nor the capture."""
    out = _check_out(ap, Path(args.out), args.overwrite)
    capture = getattr(args, "capture", None)
    if capture is not None:
        data_dir = Path(os.path.abspath(capture))
        if data_dir.suffix.lower() == ".lp":
            data_dir = data_dir.parent
        if data_dir == out or out in data_dir.parents or data_dir in out.parents:
            ap.error("argument --out: must not be the CAPTURE folder, inside it or around it")
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
    from .. import ps

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
    from .. import ps

    t = time.perf_counter()
    ho = ps.holdout_evaluation(imgs, lights, inten, mask, holdout=args.holdout, seed=args.seed, **opts)
    say(f"\nheld-out relighting ({args.holdout} lights): HSH relative RMSE {ho.relative_rmse:.4f}, "
        f"robust Lambertian {ho.lambertian_relative_rmse:.4f}")
    return {"held_out_lights": ho.test_indices.tolist(), "relative_rmse": ho.relative_rmse, "rmse": ho.rmse,
            "lambertian_relative_rmse": ho.lambertian_relative_rmse, "runtime_s": time.perf_counter() - t}


def _run_ps(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    """``torch-hsh ps CAPTURE``."""
    if args.out is None:
        args.out = _default_out(Path(os.path.abspath(args.capture)).with_suffix("").name
                                if Path(args.capture).suffix.lower() == ".lp"
                                else Path(os.path.abspath(args.capture)).name)
    return _run(args, ap, _load_capture)


def _run_demo(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    """``torch-hsh demo``."""
    if args.out is None:
        args.out = _default_out(args.scene)
    return _run(args, ap, _load_demo)


def _run(args, ap: argparse.ArgumentParser, load: Callable[..., Dict[str, Any]]) -> Dict[str, Any]:
    """Load, solve, write the result folder: what ``ps`` and ``demo`` share."""
    from .. import ps
    from ..io.exr import write_coefficient_maps_exr

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
    data = load(args, ap)
    L = int(data["images"].shape[0])
    if args.holdout and not 1 <= args.holdout <= L - 3:
        ap.error(f"argument --holdout: must be 0 (off) or between 1 and L-3 = {L - 3} "
                 f"so that at least 3 of the L = {L} lights remain, got {args.holdout}")
    data = {k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in data.items()}
    imgs, lights, inten, mask, gt = (data[k] for k in ("images", "lights", "intensities", "mask", "normals_gt"))
    N = int(mask.sum())
    if N == 0:
        raise InputError(f"{data['name']}: the mask selects no pixel")

    previous = _previous_result(out)
    if previous is not None:
        say(f"--out {out} holds a torch-hsh result ({previous}); it is replaced when this run ends")
    # ---- solve (the output folder is staged only now, so a failed solve creates nothing)
    with _Staging(out) as stage:
        say(f"data: {data['name']}  pixels={N} lights={L} order={order} "
            f"materials={materials if materials else 'independent'} device={dev}")
        res, t_hsh, rows = _solve_methods(args, opts, imgs, lights, inten, mask, gt, say)
        metrics: Dict[str, Any] = {
            "method": "hsh", "order": order, "materials": materials, "pixels": N, "lights": L,
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
        if hasattr(res, "write"):
            res.write(stage.file("result.npz"))
        if args.depth or args.mesh:
            _save_surface(stage, args, res, mask, metrics, say)
        write_coefficient_maps_exr(stage.file("coefficients.exr"), res.coefficients.detach().cpu().float())
        _dump_json(stage.file("metrics.json"), metrics)
        _save_pictures(stage, data, res, err_map, confidence, relit_idx=L // 2, say=say)
        from .._version import __version__

        stage.write_manifest({"tool": f"{PROG} {args.command}", "torch_hsh_version": __version__,
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
    from ..cli.result_folder import _read_manifest

    meta = _read_manifest(out) if out.is_dir() else None
    if meta is None:
        return None
    created = meta.get("created_utc")
    return f"of {created}" if isinstance(created, str) else "of an unknown date"
