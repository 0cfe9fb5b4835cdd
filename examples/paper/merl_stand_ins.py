"""Paper Fig. 6 end to end on MERL-format files written from analytic BRDFs (real MERL data is not shipped).

1. Tabulates analytic BRDFs on MERL's real grid (90 x 90 x 180 bins: non-linear
   ``theta_h`` bins, ``phi_d`` folded into ``[0, pi)``) with
   :func:`torch_hsh.io.merl.tabulate_merl` and writes them with
   :func:`torch_hsh.io.merl.write_merl` into ``--merl-dir`` (default ``build/merl_stand_ins``,
   git-ignored; about 35 MB per file; existing files are kept unless ``--overwrite``).
2. Runs the Fig. 6 experiment on that folder through ``compactness.py --merl DIR --merl-only``
   (nearest-bin lookups, converged reduced rule, every isotropic basis).
3. Compares Acc(P) measured through the lookup with the analytic projection of the same
   BRDF and checks it against a tolerance derived from the binning: on one rule whose
   weights make the basis orthonormal (Gauss-Legendre x trapezoid, exact for products of
   basis functions), with ``f`` the analytic BRDF, ``g`` the lookup and
   ``r = ||g - f|| / ||f||``, Bessel's inequality and the triangle inequality give
   ``(s - r)/(1 + r) <= sqrt(Acc_g) <= (s + r)/(1 - r)``, ``s = sqrt(Acc_f)``.
   ``r`` is the binning error, measured on that rule.

Only materials whose ``int f^2`` is finite are used (Lambertian, Blinn-Phong): for the
microfacet and Oren-Nayar models the analytic Acc needs a grazing cutoff, while the
tabulated version is finite only because the grazing bins are bounded.

Outputs: ``<tables>/compactness_merl.csv``, ``compactness_merl.md``,
``<images>/paper_compactness_merl.png`` (step 2) and ``<tables>/merl_stand_ins.md``
(step 3). Run: ``python examples/paper/merl_stand_ins.py`` (a few minutes). ``--materials NAME ...`` runs a
subset of the stand-ins (their rows are those of the full run); ``--quick`` (CI) is ``--materials
blinn_phong_n10`` (about 10 s); give it a ``--merl-dir`` of its own (the folder's ``.binary`` files all go into step 2).

On the real database: download the MERL ``.binary`` files into a folder and run
``python examples/paper/compactness.py --merl /path/to/brdfs --merl-only``.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
import compactness  # noqa: E402

from torch_hsh.fitting import brdf_accuracy  # noqa: E402
from torch_hsh.fitting.rules import rule_sums  # noqa: E402
from torch_hsh.bases import get_basis  # noqa: E402
from torch_hsh.io.merl import MERL_SHAPE, tabulate_merl, write_merl  # noqa: E402

STAND_INS = ("lambert_0.8", "lambert_0.3", "blinn_phong_n3", "blinn_phong_n10", "blinn_phong_n20", "blinn_phong_n50",
             "blinn_phong_n100")
QUICK_STAND_INS = ("blinn_phong_n10",)
PAPER_CLAIMS = "all MERL materials reach 95 % at P <= 7; fabrics reach 99 % at P <= 4"


def write_stand_ins(folder: Path, overwrite: bool, names=STAND_INS):
    lib = {n: m for n, m, _ in C.material_library()}
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        path = folder / f"{name}.binary"
        if path.exists() and not overwrite:
            continue
        write_merl(path, tabulate_merl(lib[name], MERL_SHAPE), overwrite=overwrite)
    return {n: C.as_scalar_brdf(lib[n]) for n in names}


def binning_check(f, g, P, n_theta, n_phi):
    """Acc of f and g on one rule, the binning error r and the interval that r implies for Acc_g.

    On the rule, ``a = B^T W f`` with ``B^T W B = I``, so with ``d = g - f``:
    ``| ||a_g(P')|| - ||a_f(P')|| | <= ||a_d(P')||`` (projection of the binning error up to
    ``P'``) and ``| ||g|| - ||f|| | <= ||d||``, hence
    ``(||a_f|| - ||a_d||) / (||f|| + ||d||) <= sqrt(Acc_g) <= (||a_f|| + ||a_d||) / (||f|| - ||d||)``.
    """
    b = get_basis("helmholtz_isotropic")
    from torch_hsh.fitting import energy_accuracy

    def sums(h):
        return rule_sums(h, b, P, n_theta, n_phi, True, 0.0, True, True, torch.float64, None)

    rf, rg, rd = sums(f), sums(g), sums(lambda wi, wo: g(wi, wo) - f(wi, wo))
    acc_f = energy_accuracy(rf.a, rf.E, basis=b)[0]
    acc_g = energy_accuracy(rg.a, rg.E, basis=b)[0]
    nf, nd = torch.sqrt(rf.E[0]), torch.sqrt(rd.E[0])
    af = torch.sqrt(acc_f) * nf  # ||a_f(P')||
    ad = torch.sqrt(energy_accuracy(rd.a, rd.E, basis=b)[0]) * nd  # ||a_d(P')||
    lo = ((af - ad).clamp(min=0) / (nf + nd)) ** 2
    hi = (((af + ad) / (nf - nd)) ** 2).clamp(max=1.0)
    return acc_f, acc_g, float(nd / nf), lo, hi


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    p.add_argument("--merl-dir", type=Path, default=C.ROOT / "build" / "merl_stand_ins")
    p.add_argument("--check-rule", type=int, nargs=2, default=(48, 1024), metavar=("N_THETA", "N_PHI"))
    p.add_argument("--materials", nargs="+", default=list(STAND_INS), choices=STAND_INS, metavar="NAME",
                   help=f"subset of the stand-ins {', '.join(STAND_INS)} (default: all)")
    p.add_argument("--quick", action="store_true", help="CI smoke run: --materials " + " ".join(QUICK_STAND_INS))
    args = p.parse_args(argv)
    if args.quick:
        args.materials = list(QUICK_STAND_INS)
    C.set_threads(args.threads)
    out = args.tables / "merl_stand_ins.md"
    C.prepare_outputs([out], args.overwrite)
    t0 = time.time()
    analytic = write_stand_ins(args.merl_dir, args.overwrite, args.materials)
    cargs = ["--merl", str(args.merl_dir), "--merl-only", "--images", str(args.images), "--tables", str(args.tables),
             "--no-progress"]
    compactness.main(cargs + (["--overwrite"] if args.overwrite else []))
    merl_rows = {}
    with open(args.tables / "compactness_merl.csv") as fh:
        fh.readline()  # header
        for line in fh:
            v = line.strip().split(",")
            if v[1] == "helmholtz_isotropic":
                merl_rows[v[0]] = [float(x) for x in v[2:2 + 11]]
    P = 10
    rows = []
    for name, f in analytic.items():
        g = compactness.merl_brdf(args.merl_dir / f"{name}.binary")
        acc_conv = brdf_accuracy(f, P, tol=2e-4)
        acc_f, acc_g, r, lo, hi = binning_check(f, g, P, *args.check_rule)
        inside = bool(((acc_g >= lo - 1e-12) & (acc_g <= hi + 1e-12)).all())
        m = np.array(merl_rows[name])
        rows.append([name, float(acc_conv[2]), float(acc_conv[8]), float(m[2]), float(m[8]), r,
                     float((acc_g - acc_f).abs().max()), float(torch.maximum(acc_f - lo, hi - acc_f).max()),
                     "yes" if inside else "NO",
                     compactness.min_order(acc_conv.numpy(), 0.95), compactness.min_order(m, 0.95),
                     compactness.min_order(acc_conv.numpy(), 0.99), compactness.min_order(m, 0.99)])
    with open(out, "w") as fh:
        fh.write("# MERL-format stand-ins: Fig. 6 through the lookup vs the analytic projection\n\n")
        fh.write(f"Produced by `python examples/paper/merl_stand_ins.py` ("
                 f"{time.time() - t0:.0f} s). Files on MERL's grid {MERL_SHAPE}, raw BRDF f, Helmholtz isotropic basis. "
                 "`analytic`: converged projection of the analytic BRDF (tol 2e-4); `MERL`: the same through "
                 "`compactness.py --merl` (nearest-bin lookup, tol 2e-3). Binning check on one fixed rule "
                 f"{args.check_rule[0]} x {args.check_rule[0]} x {args.check_rule[1]}: r = ||lookup - f|| / ||f||, "
                 "|dAcc| = largest |Acc_lookup - Acc_f| over P' <= 10 on that rule, bound = largest half-width of "
                 "the interval derived from r (see the script docstring); `inside` says whether every P' is inside.\n\n")
        compactness._table(fh, ["material", "Acc(2) analytic", "Acc(8) analytic", "Acc(2) MERL", "Acc(8) MERL", "r",
                                "|dAcc|", "bound", "inside", "min P 95% analytic", "min P 95% MERL",
                                "min P 99% analytic", "min P 99% MERL"], rows)
        fh.write(f"\nPaper's claims for the real MERL database: {PAPER_CLAIMS}.\n")
    print(f"wrote {out} in {time.time() - t0:.0f} s")
    for r_ in rows:
        print("  ", r_)


if __name__ == "__main__":
    main()
