"""``torch-hsh fit``: the isotropic Helmholtz basis fitted to a MERL ``.binary`` BRDF.

Weighted least squares on the table's samples by default (:func:`torch_hsh.io.fit_merl`), or the
convergence-controlled projection of the table lookup (:func:`torch_hsh.project`); writes the (3, K) RGB
coefficients, the relative L2 error on the samples, Acc(P) and a JSON summary into one ``.npz`` file.

Example::

    torch-hsh fit my_material.binary --order 6 --out my_material.npz
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict

import numpy as np
import torch

from .common import PROG, InputError, _add_common, _float_in, _int_in
from .._atomic import atomic_file, signals_held
from .result_folder import _jsonable

__all__ = ["add_fit_command"]


def add_fit_command(sub) -> None:
    """Add the ``fit`` subparser to the ``torch-hsh`` subparsers ``sub``."""
    _fit_parser(sub)


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
    p.add_argument("merl", metavar="MERL", help="MERL .binary file")
    p.add_argument("--order", type=_int_in(0, 12), default=6, help="basis order P (default 6)")
    p.add_argument("--out", default=None, help="output .npz file (default: MERL's name with .npz, beside it; refused "
                                               "if it exists unless --overwrite)")
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
    p.add_argument("--threads", type=_int_in(1, 1024), default=2, help="CPU threads for torch (default 2)")
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
        with signals_held():  # no interrupt between the creation and the removal
            fd, probe = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".probe", dir=anc)
            os.close(fd)
            os.unlink(probe)
    except OSError as err:
        ap.error(f"argument --out: cannot write into {anc} ({err.strerror or err})")
    return out


def _run_fit(args, ap: argparse.ArgumentParser) -> Dict[str, Any]:
    from ..fitting import ConvergenceError

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
    src = Path(args.merl)  # default --out: NAME.npz beside NAME.binary (never the input itself)
    out_name = args.out if args.out is not None else str(
        src.with_name(src.stem + ("_fit" if src.suffix == ".npz" else "") + ".npz"))
    out = _check_fit_out(ap, Path(os.path.abspath(out_name)), args.overwrite)
    torch.set_num_threads(args.threads)
    from ..io.merl import read_merl

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
    coefficients, arrays, extra = result
    rel = arrays["relative_error"]
    summary = {"file": str(args.merl), "order": args.order, "method": args.method,
               "num_functions": int(coefficients.shape[-1]), "grazing_cutoff": args.grazing_cutoff,
               "relative_error": rel.tolist(), "energy_accuracy": arrays["energy_accuracy"].tolist(),
               "runtime_s": time.perf_counter() - t, **extra}
    _write_fit_npz(out, coefficients, arrays, summary)
    say(f"order {args.order}: {coefficients.shape[-1]} functions x 3 channels, {summary['runtime_s']:.1f} s")
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


def _write_fit_npz(out: Path, coefficients, arrays, summary) -> None:
    """Write the fit's ``.npz`` atomically; missing parent folders are created now, and removed again if the write fails."""
    created = []
    anc = out.parent
    while not anc.exists():
        created.append(anc)
        anc = anc.parent
    try:
        for d in reversed(created):
            d.mkdir()
        with atomic_file(out) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, coefficients=coefficients, metadata=np.array(json.dumps(_jsonable(summary), allow_nan=False)),
                     **arrays)
    except BaseException:
        for d in created:  # innermost first; only folders this run created, and only if still empty
            try:
                d.rmdir()
            except OSError:
                break
        raise


def _fit_samples(brdf, args):
    from ..io.merl import fit_merl

    coefficients, info = fit_merl(brdf, args.order, ridge=args.ridge or 0.0, grazing_cutoff=args.grazing_cutoff,
                            progress=not args.quiet, return_info=True)
    arrays = {"relative_error": info["relative_error"].numpy(), "energy": info["energy"].numpy(),
              "energy_accuracy": info["accuracy"].numpy(),
              "relative_error_per_order": info["relative_error_per_order"].numpy()}
    extra = {"relative_error_unweighted": info["relative_error_unweighted"].tolist(),
             "relative_error_per_order": info["relative_error_per_order"].tolist(),
             "weights": "solid angle of each half/difference bin (torch_hsh.io.merl.merl_solid_angle_weights)",
             "ridge": args.ridge or 0.0, "num_samples": info["num_samples"], "coverage": info["coverage"],
             "condition": info["condition"]}
    return coefficients.numpy(), arrays, extra


def _fit_quadrature(brdf, args):
    from ..fitting import brdf_energy, energy_accuracy, project

    kw: Dict[str, Any] = {"grazing_cutoff": args.grazing_cutoff, "strict": not args.accept_unconverged}
    if args.tol is not None:
        kw["tol"] = args.tol
    if args.max_evaluations is not None:
        kw["max_evaluations"] = args.max_evaluations
    import warnings

    from ..fitting import ConvergenceWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        coefficients, info = project(brdf, order=args.order, return_info=True, **kw)
        energy = brdf_energy(brdf, order=args.order, **kw)
    for w in caught:  # --accept-unconverged: said in the options' names, even with --quiet
        if issubclass(w.category, ConvergenceWarning):
            print(f"{PROG} fit: warning: {_fit_message(str(w.message))}", file=sys.stderr, flush=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    coefficients, energy = coefficients.detach().cpu(), energy.detach().cpu()
    acc = energy_accuracy(coefficients, energy)
    rel = torch.sqrt((1.0 - acc[:, -1]).clamp(min=0.0))
    arrays = {"relative_error": rel.numpy(), "energy": energy.numpy(), "energy_accuracy": acc.numpy()}
    extra = {"error_estimate": info["error_estimate"], "n_theta": info["n_theta"], "n_phi": info["n_phi"],
             "converged": info["converged"]}
    return coefficients.numpy(), arrays, extra
