r"""The RTI subcommands of ``torch-hsh`` (registered by :func:`torch_hsh.cli.build_parser`).

* ``torch-hsh lights CAPTURE (--sphere-mask MASK.png | --sphere-circle CX CY R) --out LIGHTS.lp`` --
  light directions from the highlight on a glossy sphere
  (:func:`torch_hsh.rti.sphere_light_directions`). ``CAPTURE`` is an RTI capture
  (photographs plus an ``.lp`` file, whose directions are ignored) or a
  DiLiGenT folder (``filenames.txt`` or its ``*.png`` images).
* ``torch-hsh view RESULT --out RESULT.html`` -- a self-contained WebGL2 relighting viewer of
  the full model (:func:`torch_hsh.rti.viewer.write_viewer`).
* ``torch-hsh rti RESULT --terms 9 [--rti OUT.rti] [--relight OUT_DIR [--layout image|deepzoom|deepzoom1px]]
  [--allow-negative]`` -- the HSH RTI export of a ``torch-hsh ps`` result (:func:`torch_hsh.rti.project_to_rti`,
  non-negative by default: :func:`torch_hsh.rti.nonnegative_rti`; :func:`torch_hsh.rti.io.write_rti_hsh`,
  :func:`torch_hsh.rti.io.save_relight`).

Exit status as for the other subcommands: 2 for a bad argument value (e.g. a
circle outside the image), 1 for a bad input file (named), 0 on success.

Example::

    torch-hsh lights capture --sphere-circle 60 60 40 --out capture/lights.lp
    torch-hsh rti results/capture --terms 9 --rti capture.rti --relight capture_relight
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Any, Callable, Dict, List, Tuple

import numpy as np

from ..cli.common import InputError, _add_common, _int_in

__all__ = ["add_rti_commands"]  # lights, rti, view


def add_rti_commands(sub) -> None:
    """Add the ``lights``, ``rti`` and ``view`` subparsers to the ``torch-hsh`` subparsers ``sub``."""
    _subcommand(
        sub, "lights", _run_lights, _lights_arguments, "replace an existing --out file",
        help="light directions from a glossy sphere (highlight RTI), written as an .lp file",
        description="Estimate each image's light direction from the highlight on a glossy sphere in the frame "
                    "(orthographic view along +z; x right, y up, z toward the camera) and write an .lp file.",
    )
    _subcommand(
        sub, "rti", _run_rti, _rti_arguments, "replace existing output files",
        help="export a torch-hsh ps result as HSH RTI files (.rti for RTIViewer, relight/OpenLIME folder)",
        description="Project the per-pixel image model of a torch-hsh ps result onto the RTI HSH basis "
                    "(9 or 16 terms) and write RTIViewer's .rti and/or a relight/OpenLIME folder.",
    )
    _subcommand(
        sub, "view", _run_view, _view_arguments, "replace an existing --out file",
        help="write a self-contained HTML relighting viewer (WebGL2) of a torch-hsh ps result",
        description="Write one HTML file (no network access; the maps are embedded) that relights the result "
                    "with its per-pixel isotropic Helmholtz BRDF under a light that follows the mouse, and shows "
                    "the normal map, the albedo, the confidence and the residual map.",
    )


# --------------------------------------------------------------------------- #
# what the three subcommands share
# --------------------------------------------------------------------------- #
def _subcommand(sub, name: str, handler, add_arguments: Callable[[argparse.ArgumentParser], None],
                overwrite_help: str, **texts) -> None:
    """One subparser: its own arguments, then ``--overwrite``, ``--debug`` and ``--quiet``; it runs ``handler``."""
    p = sub.add_parser(name, **texts)
    add_arguments(p)
    p.add_argument("--overwrite", action="store_true", help=overwrite_help)
    _add_common(p)
    p.set_defaults(handler=handler, parser=p)


def _float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _add_result(p) -> None:
    p.add_argument("result", metavar="RESULT", help="result folder of torch-hsh ps (with result.npz), or a result .npz file")
    p.add_argument("--threads", type=_int_in(1, 1024), default=2, help="CPU threads for torch (default 2)")


def _add_exposure(p) -> None:
    p.add_argument("--exposure", type=_float, default=None,
                   help="factor on the radiance before the sRGB curve (default: 99.5th percentile of the head-on "
                        "rendering maps to 0.8)")


def _say(args) -> Callable[..., None]:
    return (lambda *a, **k: None) if args.quiet else (lambda *a, **k: print(*a, **k, flush=True))


def _out_file(ap: argparse.ArgumentParser, path: str, suffixes: Tuple[str, ...], overwrite: bool) -> Path:
    """Static checks of the ``--out`` file (nothing is written): exit 2 on a bad one."""
    out = Path(os.path.abspath(path))
    if out.suffix.lower() not in suffixes:
        ap.error(f"argument --out: expected an {suffixes[0]} file name, got {out.name}")
    if out.is_dir():
        ap.error(f"argument --out: {out} is a folder")
    if out.exists() and not overwrite:
        ap.error(f"argument --out: {out} exists; pass --overwrite to replace it")
    if not out.parent.is_dir():
        ap.error(f"argument --out: the folder {out.parent} does not exist")
    _not_into_a_result(ap, "--out", out)
    return out


def _not_into_a_result(ap: argparse.ArgumentParser, option: str, path: Path) -> None:
    """Exit 2 if ``path`` would be written inside a ``torch-hsh ps`` result folder: a foreign file there makes the
    next ``ps --out`` run refuse the folder (it only replaces folders that hold nothing but its own files)."""
    from ..cli.result_folder import is_result_folder

    path = Path(os.path.abspath(path))
    for folder in (path, path.parent):  # the path itself (a folder output, replaced with --overwrite) or its parent
        if is_result_folder(folder):
            ap.error(f"argument {option}: {folder} is a torch-hsh ps result folder; write beside it, not into it "
                     "(a file of yours there makes the next `torch-hsh ps --out` refuse the folder)")


def _load_result(args, ap: argparse.ArgumentParser):
    """The :class:`~torch_hsh.ps.HSHResult` of ``args.result`` (a result folder or its ``.npz``), after the
    check of ``--exposure``."""
    from ..ps import HSHResult

    if args.exposure is not None and not args.exposure > 0:
        ap.error(f"argument --exposure: must be > 0, got {args.exposure:g}")
    import torch

    torch.set_num_threads(args.threads)
    src = Path(args.result)
    try:
        return HSHResult.read(src / "result.npz" if src.is_dir() else src)
    except (OSError, ValueError) as err:
        raise InputError(str(err)) from err


# --------------------------------------------------------------------------- #
# lights
# --------------------------------------------------------------------------- #
def _lights_arguments(p) -> None:
    p.add_argument("folder", metavar="CAPTURE", help="RTI capture folder (photographs + .lp; its directions are ignored) or DiLiGenT folder")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--sphere-mask", metavar="MASK", help="image marking the sphere (> 0 on the sphere)")
    g.add_argument("--sphere-circle", nargs=3, type=_float, metavar=("CX", "CY", "R"),
                   help="sphere circle in pixels: centre column, centre row (pixel centres at integers), radius")
    p.add_argument("--out", default=None, help="output .lp file (default: CAPTURE's name + '.lp', beside it; then "
                                               "torch-hsh ps CAPTURE.lp; refused if it exists unless --overwrite)")


def _capture_paths(folder: Path) -> Tuple[List[Path], str]:
    """Image paths of an RTI or DiLiGenT folder and a description of where they came from."""
    from ..io.diligent import _is_aux_picture, _read_names
    from .io import find_lp, read_lp

    lp = find_lp(folder)
    if lp is not None:
        _, paths, _ = read_lp(lp, check_directions=False)
        return paths, str(lp)
    names_file = folder / "filenames.txt"
    if names_file.is_file():
        return [folder / n for n in _read_names(names_file)], str(names_file)
    names = sorted(p.name for p in folder.glob("*.png") if not _is_aux_picture(p.name))
    if not names:
        raise ValueError(f"{folder}: neither an RTI folder (*.lp) nor a DiLiGenT folder (filenames.txt or *.png)")
    return [folder / n for n in names], f"{folder} (*.png)"


def _sphere_circle(args, ap: argparse.ArgumentParser, shape: Tuple[int, int]) -> Tuple[float, float, float]:
    """The sphere's circle ``(cx, cy, r)``: from ``--sphere-mask`` or ``--sphere-circle`` (inside the images)."""
    from .io import _read_mask
    from .fitting import sphere_circle_from_mask

    H, W = shape
    if args.sphere_mask is not None:
        mpath = Path(args.sphere_mask)
        if not mpath.is_file():
            raise FileNotFoundError(f"{mpath}: sphere mask not found")
        try:
            return sphere_circle_from_mask(_read_mask(mpath, (H, W)))
        except ValueError as err:
            raise ValueError(f"{mpath}: {err}") from None
    cx, cy, r = args.sphere_circle
    if cx - r < -0.5 or cy - r < -0.5 or cx + r > W - 0.5 or cy + r > H - 0.5:
        ap.error(f"argument --sphere-circle: the circle (cx={cx:g}, cy={cy:g}, r={r:g}) is not inside the "
                 f"{W}x{H} images")
    return cx, cy, r


def _run_lights(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    import torch

    from .io import _read_photographs, write_lp
    from .fitting import sphere_light_directions

    say = _say(args)
    folder = Path(args.folder)
    if not folder.is_dir():
        ap.error(f"argument folder: {folder} is not a folder")
    out = _out_file(ap, args.out if args.out is not None else _beside(args.folder, ".lp"), (".lp",), args.overwrite)
    if args.sphere_circle is not None and args.sphere_circle[2] < 3:
        ap.error(f"argument --sphere-circle: the radius must be >= 3 pixels, got {args.sphere_circle[2]:g}")
    try:
        paths, source = _capture_paths(folder)
        images = _read_photographs(paths, lambda i, f: f"{source}: image {i + 1} not found: {f}",
                                   convert=lambda img: img.mean(axis=-1))
        circle = tuple(_sphere_circle(args, ap, images.shape[1:]))
        est = sphere_light_directions(torch.as_tensor(images), circle=circle, on_missing="keep")
    except (OSError, ValueError) as err:
        raise InputError(str(err)) from err
    missing = np.nonzero(~est.found)[0]
    if missing.size:
        names = ", ".join(str(paths[i]) for i in missing[:3]) + (" ..." if missing.size > 3 else "")
        raise InputError(f"no highlight found on the sphere in {missing.size} image(s): {names}")
    below = np.nonzero(est.lights[:, 2] <= 0)[0]
    if below.size:  # a highlight beyond r / sqrt(2) of the centre: the light is at or below the horizon
        names = ", ".join(str(paths[i]) for i in below[:3]) + (" ..." if below.size > 3 else "")
        raise InputError(f"{below.size} image(s) put the light at or below the horizon (their highlight is more than "
                         f"0.71 r from the sphere's centre), which `torch-hsh ps` refuses: {names}; check the sphere "
                         "(--sphere-mask / --sphere-circle)")
    rel = [os.path.relpath(p.resolve(), out.parent) for p in paths]
    rel = [r if not r.startswith("..") else str(p.resolve()) for r, p in zip(rel, paths)]
    write_lp(out, rel, est.lights, overwrite=args.overwrite)
    elev = np.degrees(np.arccos(np.clip(est.lights[:, 2], -1, 1)))
    say(f"sphere circle cx={circle[0]:.2f} cy={circle[1]:.2f} r={circle[2]:.2f}; {len(paths)} lights, "
        f"angle from the view {elev.min():.1f} to {elev.max():.1f} deg; "
        f"{int((est.saturated > 1).sum())} image(s) with a clipped highlight")
    say(f"wrote {out}")
    return {"lights": est.lights.tolist(), "circle": list(circle), "highlights": est.highlights.tolist()}


# --------------------------------------------------------------------------- #
# rti export
# --------------------------------------------------------------------------- #
def _rti_arguments(q) -> None:
    _add_result(q)
    q.add_argument("--terms", type=int, choices=(9, 16), default=9, help="number of HSH terms (default 9)")
    q.add_argument("--rti", default=None, help="write this .rti file (RTIViewer HSH; default without --relight: "
                                               "RESULT's name + '.rti', beside it)")
    q.add_argument("--relight", default=None, help="write this relight/OpenLIME folder (info.json + plane_*.jpg; 9 terms)")
    q.add_argument("--layout", choices=("image", "deepzoom", "deepzoom1px"), default="image",
                   help="planes of the --relight folder: image (default): one plane_N.jpg each; deepzoom: a Deep Zoom "
                        "pyramid each (plane_N.dzi + plane_N_files/LEVEL/COL_ROW.jpg, 254-pixel tiles, 1-pixel overlap, "
                        "folder 0 the one-tile level), for OpenLIME's layout 'deepzoom' and relight; deepzoom1px: every "
                        "level of the Deep Zoom specification, down to 1x1 (OpenSeadragon)")
    q.add_argument("--allow-negative", action="store_true",
                   help="keep the plain least-squares coefficients even where their sum is negative at some light "
                        "(default: the nearest coefficients whose sum is >= 0 at every light within OpenLIME's clamp, "
                        "81.4 deg from the view; OpenLIME shows a negative sum as a bright artefact)")
    _add_exposure(q)
    q.add_argument("--linear-output", action="store_true",
                   help="write linear values (default: sRGB-encoded, as RTI viewers expect)")
    q.add_argument("--max-angle", default="auto",
                   help="fit the lights within this many degrees of the view (default auto: the largest angle of the "
                        "result's lights; 90: the whole hemisphere, an orthonormal projection)")


def _run_rti(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    import torch

    from .._atomic import sweep
    from .io import _relight_foreign_entries, save_relight, write_rti_hsh
    from .fitting import project_to_rti

    say = _say(args)
    if args.rti is None and args.relight is None:
        args.rti = _beside(args.result, ".rti")
    if args.layout != "image" and args.relight is None:
        ap.error("argument --layout: applies to the --relight folder; give --relight OUT_DIR")
    if args.relight is not None and args.terms != 9:
        ap.error("argument --relight: relight/OpenLIME evaluate 9 HSH terms only; use --terms 9")
    for opt, val in (("--rti", args.rti), ("--relight", args.relight)):
        if val is not None:
            sweep(val)  # what a killed run left (a relight folder put back if it was killed in the swap)
        if val is not None and Path(val).exists() and not args.overwrite:
            ap.error(f"argument {opt}: {val} exists; pass --overwrite to replace it")
        if val is None:
            continue
        parent = Path(os.path.abspath(val)).parent
        if opt == "--rti" and not parent.is_dir():  # before the projection (--relight creates its parents)
            ap.error(f"argument {opt}: the folder {parent} does not exist")
        _not_into_a_result(ap, opt, Path(val))
        foreign = _relight_foreign_entries(val) if opt == "--relight" else []
        if foreign:
            ap.error(f"argument --relight: {val} holds files that are not a relight folder's "
                     f"({', '.join(foreign[:5])}); the folder is replaced as a whole: move them or choose another")
    if args.max_angle != "auto":
        try:
            max_angle = float(args.max_angle)
        except ValueError:
            ap.error(f"argument --max-angle: expected 'auto' or a number of degrees, got {args.max_angle!r}")
        if not 0 < max_angle <= 90:
            ap.error(f"argument --max-angle: must be in (0, 90], got {args.max_angle}")
    res = _load_result(args, ap)
    mask = res.mask.bool()
    n = res.normals.double()
    a = res.coefficients.double()
    if args.exposure is None:
        head = res.relight(torch.tensor([[0.0, 0.0, 1.0]], dtype=n.dtype))[0][mask]
        ref = float(torch.quantile(head.reshape(-1).float(), 0.995)) if head.numel() else 1.0
        exposure = 0.8 / ref if ref > 0 else 1.0
    else:
        exposure = args.exposure
    if args.max_angle == "auto":
        lz = torch.nn.functional.normalize(res.lights.double(), dim=-1)[:, 2].clamp(-1, 1)
        max_angle = min(90.0, float(torch.rad2deg(torch.arccos(lz)).max()))
    coefficients = project_to_rti(n, a, args.terms, mask=mask, exposure=exposure, max_angle_deg=max_angle,
                                  linear=args.linear_output, nonnegative=not args.allow_negative,
                                  progress=not args.quiet)
    written = []
    if args.rti is not None:
        write_rti_hsh(args.rti, coefficients, overwrite=args.overwrite)
        written.append(args.rti)
    if args.relight is not None:
        save_relight(args.relight, coefficients, overwrite=args.overwrite, layout=args.layout)
        written.append(args.relight)
    say(f"{args.terms}-term HSH RTI of {int(mask.sum())} pixels, lights within {max_angle:.1f} deg, "
        f"exposure {exposure:.4g}, "
        f"{'linear' if args.linear_output else 'sRGB'} values"
        f"{'' if args.allow_negative else ', non-negative within 81.4 deg'}; wrote {', '.join(written)}")
    return {"exposure": exposure, "terms": args.terms, "max_angle_deg": max_angle, "written": written,
            "nonnegative": not args.allow_negative, "layout": args.layout}


# --------------------------------------------------------------------------- #
# view
# --------------------------------------------------------------------------- #
def _view_arguments(v) -> None:
    _add_result(v)
    v.add_argument("--out", default=None,
                   help="output .html file (default: RESULT's name + '.html', beside it; refused if it exists "
                        "unless --overwrite)")
    _add_exposure(v)


def _beside(path: str, suffix: str) -> str:
    """The default output of an input: ``FOLDER.suffix`` beside a folder (beside the folder of a ``result.npz``),
    ``NAME.suffix`` beside any other file."""
    p = Path(os.path.abspath(path))
    if p.is_dir() or p.name == "result.npz":
        folder = p if p.is_dir() else p.parent
        return str(folder.parent / f"{folder.name}{suffix}")
    return str(p.with_suffix(suffix))


def _run_view(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    from .viewer import write_viewer

    say = _say(args)
    out = _out_file(ap, args.out if args.out is not None else _beside(args.result, ".html"), (".html", ".htm"),
                    args.overwrite)
    res = _load_result(args, ap)
    exposure = write_viewer(out, res, exposure=args.exposure, title=f"torch_hsh: {Path(args.result).name}",
                            overwrite=args.overwrite)
    size = out.stat().st_size
    say(f"wrote {out} ({size / 2 ** 20:.1f} MiB, exposure {exposure:.4g})")
    return {"exposure": exposure, "bytes": size}
