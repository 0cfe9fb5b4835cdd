"""Compactness of the BRDF bases on a library of analytic materials (paper Figs. 6-7 analogue).

For every material and basis: the spectrum up to order ``--max-order`` (default 10)
by deterministic quadrature, Acc(P) (paper Eq. 17) for P = 0..10, and the minimum
order reaching 95 % and 99 %, for two quantities: the cosine-weighted BRDF
``f cos(theta_i) cos(theta_o)`` (main result: bounded and reciprocal for every model)
and the raw BRDF ``f`` (whose squared integral diverges at grazing angles for the
GGX, Ward and Oren-Nayar models, so its raw-BRDF averages use Lambertian and
Blinn-Phong materials only; see ``docs/conventions_and_errata.md``).

* Isotropic materials (25): the isotropic bases (ours, both Koenderink--van Doorn
  bases, Gautron, Westin, H-basis) on the reduced 3-D rule, **converged**: the rule
  of every material and quantity is refined by :func:`torch_hsh.fitting.brdf_accuracy`
  until Acc(P') of the Helmholtz basis changes by less than ``--tol`` (default 5e-4)
  for every P' <= 10, and that rule is then used for every basis (all of them see the
  BRDF through the same azimuthal Fourier modes |q| <= 10). The error estimate is
  written to the tables. The raw BRDF of the GGX, Ward and Oren-Nayar models needs a
  grazing cutoff (``--cutoff``, default cos(theta) >= 0.01); a cutoff study is written too.
* Anisotropic Ward materials (6): the product bases, projected separably,
  ``C = H^T diag(w) F diag(w) H`` on a direction product rule (checked against
  :func:`torch_hsh.fitting.project` at start-up), refined in ``n_phi`` (doubling) and
  ``n_theta`` until Acc(P') of the Helmholtz basis changes by less than ``--tol-aniso``
  or the rule would exceed ``--max-dirs`` directions; the estimate is printed.
* ``--merl DIR``: paper Fig. 6, the isotropic comparison on MERL ``.binary`` files
  (raw BRDF, mean of the colour channels, nearest-bin lookup through
  :func:`torch_hsh.io.merl.read_merl`, converged reduced rule), with the minimum
  orders for 95 % and 99 %.

Outputs (refuses to overwrite them without ``--overwrite``):
``<tables>/compactness_isotropic.csv``, ``compactness_anisotropic.csv``,
``compactness_cutoff.csv``, ``compactness_summary.md``, ``<images>/paper_compactness.png``;
with ``--merl`` also ``compactness_merl.csv``, ``compactness_merl.md`` and
``paper_compactness_merl.png`` (``--merl-only``: just those).

``--materials NAME ...`` restricts the analytic library to those materials (their rows are the same
as in a full run: every material's rule is converged on its own); ``--quick`` is
``--materials lambert_0.8 blinn_phong_n10 ggx_r0.8_f0.04 ward_aniso_0.3x0.6`` (about 10 s on one core; the
cutoff study is empty then, its materials are the slow ones; the CI test compares the rows with the committed
tables).

Run: ``python examples/paper/compactness.py`` (6-10 minutes on one CPU core, depending on load).
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torch_hsh.bases import get_basis  # noqa: E402
from torch_hsh.bases.westin import pair_table  # noqa: E402
from torch_hsh.quadrature import direction_quadrature  # noqa: E402

THRESH = (0.95, 0.99)
#: ``--quick``: one cheap material per kind (Lambertian, Blinn-Phong, GGX with its grazing cutoff, anisotropic Ward).
QUICK_MATERIALS = ("lambert_0.8", "blinn_phong_n10", "ggx_r0.8_f0.04", "ward_aniso_0.3x0.6")
CUTOFF_MATERIALS = ("ggx_r0.5_f0.04", "ward_iso_a0.25", "oren_nayar_s0.5")


def min_order(acc_row: np.ndarray, thr: float) -> float:
    idx = np.nonzero(acc_row >= thr - 1e-12)[0]
    return float(idx[0]) if len(idx) else float("nan")


def acc_padded(acc: torch.Tensor, P: int) -> np.ndarray:
    """(n, P_b+1) -> (n, P+1), NaN where the basis stops (H-basis beyond order 2)."""
    out = np.full((acc.shape[0], P + 1), np.nan)
    out[:, : acc.shape[1]] = acc.numpy()
    return out


def converged_iso(f, P, tol, cutoff):
    """Acc ``{basis: (P+1,)}`` of one isotropic BRDF on the rule converged for the Helmholtz basis, and the info."""
    from torch_hsh.fitting import brdf_accuracy, energy_accuracy
    from torch_hsh.fitting.rules import rule_sums

    _, info = brdf_accuracy(f, P, "helmholtz_isotropic", tol=tol, grazing_cutoff=cutoff, strict=False,
                            return_info=True)
    out = {}
    for bn in C.ISO_BASES:
        b = get_basis(bn)
        Pb = min(P, b.max_order)
        r = rule_sums(f, b, Pb, info["n_theta"], info["n_phi"], True, cutoff or 0.0, True, True, torch.float64, None)
        out[bn] = acc_padded(energy_accuracy(r.a, r.E, basis=b), P)[0]
    return out, info


def run_isotropic(materials, P, tol, cutoff, progress):
    """``{"brdf": {basis: (n, P+1)}, "cosine": {...}}``, the error estimates and rule sizes per material."""
    res = {"brdf": {bn: [] for bn in C.ISO_BASES}, "cosine": {bn: [] for bn in C.ISO_BASES}}
    meta = {"brdf": [], "cosine": []}
    for name, f in progress(materials, desc="isotropic materials"):
        for q in ("cosine", "brdf"):
            g = C.cosine_weighted(f) if q == "cosine" else f
            c = None if (q == "cosine" or C.finite_energy(name)) else cutoff
            acc, info = converged_iso(g, P, tol, c)
            for bn in C.ISO_BASES:
                res[q][bn].append(acc[bn])
            meta[q].append((info["error_estimate"], info["n_theta"], info["n_phi"], c))
    return {q: {k: np.stack(v) for k, v in r.items()} for q, r in res.items()}, meta


def cutoff_study(materials, P, tol, cutoffs, progress):
    """Raw-BRDF Acc(2, 4, 8) of the Helmholtz basis against the grazing cutoff (rows for the CSV)."""
    from torch_hsh.fitting import brdf_accuracy

    rows = []
    for name, f in progress(materials, desc="cutoff study"):
        for c in cutoffs:
            acc, info = brdf_accuracy(f, P, "helmholtz_isotropic", tol=tol, grazing_cutoff=c, strict=False,
                                      return_info=True)
            rows.append([name, c] + [float(acc[k]) for k in (0, 2, 4, 8)] + [info["error_estimate"]])
    return rows


def _separable_acc(f, P, nt, nphi, cosine, block=512):
    """Acc ``{basis: (P+1,)}`` of the product bases on the (nt x nphi)^2 rule, without storing F."""
    d, wd = direction_quadrature(nt, nphi, dtype=torch.float64)
    N = d.shape[0]
    tabs = {}
    for bn in C.ANISO_BASES:
        kind, _ = C.ANISO_KIND[bn]
        Pb = min(P, get_basis(bn).max_order)
        H, labels = C.per_direction_table(kind, d, Pb)
        tabs[bn] = (H * wd[:, None], labels, Pb, torch.zeros(H.shape[1], H.shape[1], dtype=torch.float64))
    E = 0.0
    for s in range(0, N, block):
        di = d[s : s + block]
        wi = di[:, None, :].expand(-1, N, 3).reshape(-1, 3)
        wo = d[None].expand(di.shape[0], N, 3).reshape(-1, 3)
        Fm = f(wi, wo)
        if cosine:
            Fm = Fm * wi[:, 2] * wo[:, 2]
        Fm = Fm.reshape(di.shape[0], N)
        E += float((Fm * Fm * wd[s : s + block, None] * wd[None, :]).sum())
        for bn, (Hw, _, _, Cm) in tabs.items():
            Cm += Hw[s : s + block].T @ (Fm @ Hw)
    out = {}
    for bn, (Hw, labels, Pb, Cm) in tabs.items():
        _, sym = C.ANISO_KIND[bn]
        j, k, c, lab = pair_table(labels, Pb, sym)
        j, k = torch.tensor(j), torch.tensor(k)
        a = torch.tensor(c, dtype=Cm.dtype) * (Cm[j, k] + Cm[k, j]) if sym else Cm[j, k]
        lab = torch.tensor(lab)
        cum = torch.cumsum(torch.stack([(a[lab == p] ** 2).sum() for p in range(Pb + 1)]), 0) / E
        out[bn] = acc_padded(cum[None], P)[0]
    return out


def run_anisotropic(materials, P, tol, max_dirs, progress):
    """Refine (n_theta, n_phi) per material until Acc of the Helmholtz basis changes by < tol (or max_dirs)."""
    res = {bn: [] for bn in C.ANISO_BASES}
    meta = []
    for name, f in progress(materials, desc="anisotropic materials"):
        nt, nphi = 16, 32
        cur = _separable_acc(f, P, nt, nphi, True)
        est = float("inf")
        while True:
            if nt * 2 * nphi > max_dirs:
                break
            fine = _separable_acc(f, P, nt, 2 * nphi, True)
            e_phi = float(np.abs(fine["helmholtz_anisotropic"] - cur["helmholtz_anisotropic"]).max())
            cur, nphi = fine, 2 * nphi
            if e_phi > tol / 2:
                est = e_phi
                continue
            nt2 = int(math.ceil(1.5 * nt))
            if nt2 * nphi > max_dirs:
                est = e_phi
                break
            fine = _separable_acc(f, P, nt2, nphi, True)
            e_t = float(np.abs(fine["helmholtz_anisotropic"] - cur["helmholtz_anisotropic"]).max())
            cur, nt = fine, nt2
            est = e_phi + e_t
            if e_t <= tol / 2:
                break
        for bn in C.ANISO_BASES:
            res[bn].append(cur[bn])
        meta.append((est, nt, nphi))
        print(f"  {name}: Acc(2,4,8) = {cur['helmholtz_anisotropic'][[2, 4, 8]].round(4).tolist()} "
              f"(n_theta={nt}, n_phi={nphi}, change of the last refinement {est:.2g})", flush=True)
    return {"cosine": {k: np.stack(v) for k, v in res.items()}}, meta


def merl_brdf(path: Path):
    """A MERL file as a scalar BRDF callable (nearest-bin lookup, mean of the colour channels, 0 if unmeasured)."""
    try:
        from torch_hsh.io.merl import read_merl
    except ImportError as e:  # pragma: no cover - depends on the checkout
        raise SystemExit(f"--merl needs torch_hsh.io.merl.read_merl ({e})") from e
    table = read_merl(path)

    def f(wi, wo):
        return table(wi, wo).to(wi.dtype).mean(-1).clamp(min=0.0)

    return f


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    p.add_argument("--max-order", type=int, default=10)
    p.add_argument("--tol", type=float, default=5e-4, help="target change of Acc(P'), isotropic materials")
    p.add_argument("--cutoff", type=float, default=0.01,
                   help="grazing cutoff cos(theta) >= c for the raw BRDF of GGX, Ward and Oren-Nayar")
    p.add_argument("--tol-aniso", type=float, default=2e-3, help="target change of Acc(P'), anisotropic materials")
    p.add_argument("--max-dirs", type=int, default=6144, help="largest n_theta * n_phi of the anisotropic rule")
    p.add_argument("--merl", type=Path, default=None, help="folder of MERL .binary files (paper Fig. 6)")
    p.add_argument("--merl-only", action="store_true", help="with --merl: skip the analytic library")
    p.add_argument("--merl-tol", type=float, default=2e-3, help="target change of Acc(P'), MERL lookups")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--materials", nargs="+", default=None, metavar="NAME",
                   help="only these materials of the analytic library (default: all 31)")
    p.add_argument("--quick", action="store_true",
                   help="CI smoke run: --materials " + " ".join(QUICK_MATERIALS) + " (about 10 s)")
    args = p.parse_args(argv)
    if args.quick and args.materials is None:
        args.materials = list(QUICK_MATERIALS)
    if args.materials is not None:
        known = [n for n, _, _ in C.material_library()]
        unknown = [n for n in args.materials if n not in known]
        if unknown:
            p.error(f"--materials: unknown {', '.join(unknown)}; the library has {', '.join(known)}")
        kinds = {iso for n, _, iso in C.material_library() if n in args.materials}
        if kinds != {True, False}:
            p.error("--materials needs at least one isotropic and one anisotropic (ward_aniso_*) material")
    C.set_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = [args.tables / "compactness_isotropic.csv", args.tables / "compactness_anisotropic.csv",
             args.tables / "compactness_summary.md", args.images / "paper_compactness.png",
             args.tables / "compactness_cutoff.csv"]
    if args.merl_only and not args.merl:
        p.error("--merl-only needs --merl DIR")
    if args.merl_only:
        files = [None] * 5
    if args.merl:
        files += [args.tables / "compactness_merl.csv", args.images / "paper_compactness_merl.png",
                  args.tables / "compactness_merl.md"]
    C.prepare_outputs([f for f in files if f is not None], args.overwrite)
    progress = (lambda it, **k: it) if args.no_progress else (lambda it, **k: tqdm(it, **k))
    t0 = time.time()
    P = args.max_order
    if args.merl_only:
        run_merl(args, files, P, progress)
        return

    for bn in C.ANISO_BASES:  # the separable projection is the same sum as torch_hsh.fitting.project
        err = C.check_against_fitting(bn, C.material_library()[-1][1])
        assert err < 1e-10, (bn, err)

    lib = C.material_library()
    if args.materials is not None:
        lib = [m for m in lib if m[0] in args.materials]
    iso_names = [n for n, _, iso_ in lib if iso_]
    an_names = [n for n, _, iso_ in lib if not iso_]
    iso_mats = [(n, C.as_scalar_brdf(m)) for n, m, i in lib if i]
    iso, iso_meta = run_isotropic(iso_mats, P, args.tol, args.cutoff, progress)
    t_iso = time.time() - t0
    cut_rows = cutoff_study([m for m in iso_mats if m[0] in CUTOFF_MATERIALS],
                            8, args.tol, (0.1, 0.03, 0.01, 0.003), progress)
    an, an_meta = run_anisotropic([(n, C.as_scalar_brdf(m)) for n, m, i in lib if not i], P, args.tol_aniso,
                                  args.max_dirs, progress)

    hdr = ["quantity", "material", "grazing_cutoff", "basis"] + [f"acc_P{k}" for k in range(P + 1)] + [
        "min_order_95", "min_order_99", "error_estimate", "n_theta", "n_phi"]

    def rows_of(names, res, meta, bases, quantities):
        rows = []
        for q in quantities:
            for i, name in enumerate(names):
                est, nt, nph = meta[q][i][:3]
                c = meta[q][i][3] if len(meta[q][i]) > 3 else None
                for bn in bases:
                    r = res[q][bn][i]
                    rows.append([q, name, "none" if c is None else c, bn] + [float(x) for x in r]
                                + [min_order(r, THRESH[0]), min_order(r, THRESH[1]), est, nt, nph])
        return rows

    C.write_csv(files[0], hdr, rows_of(iso_names, iso, iso_meta, C.ISO_BASES, ("cosine", "brdf")))
    C.write_csv(files[1], hdr, rows_of(an_names, an, {"cosine": an_meta}, C.ANISO_BASES, ("cosine",)))
    C.write_csv(files[4], ["material", "grazing_cutoff", "acc_P0", "acc_P2", "acc_P4", "acc_P8", "error_estimate"],
                cut_rows)

    def summary(res, bases, sel):
        rows = []
        n = int(np.sum(sel))
        for bn in bases:
            A = res[bn][sel]
            mean = [float(np.mean(A[:, k])) for k in range(P + 1)]
            mo95 = [min_order(r, 0.95) for r in A]
            mo99 = [min_order(r, 0.99) for r in A]
            rows.append([bn] + [mean[k] for k in (1, 2, 4, 6, 8, 10) if k <= P]
                        + [f"{sum(not math.isnan(x) for x in mo95)}/{n}", f"{sum(not math.isnan(x) for x in mo99)}/{n}",
                           _med(mo95), _med(mo99)])
        return rows

    sh = ["basis"] + [f"mean Acc({k})" for k in (1, 2, 4, 6, 8, 10) if k <= P] + [
        "reach 95% by P<=10", "reach 99% by P<=10", "median min P (95%)", "median min P (99%)"]
    all_iso = np.ones(len(iso_names), bool)
    fin_iso = np.array([C.finite_energy(n) for n in iso_names])
    all_an = np.ones(len(an_names), bool)
    cmp_bases = [b for b in C.ISO_BASES if b != "hbasis_isotropic"]
    best = {k: _best_counts(iso["cosine"], cmp_bases, k, tol=2 * args.tol) for k in (2, 4, 8) if k <= P}
    est_iso = max(m[0] for q in ("cosine", "brdf") for m in iso_meta[q])
    est_an = max(m[0] for m in an_meta)
    with open(files[2], "w") as fh:
        fh.write("# Compactness of the BRDF bases on analytic materials\n\n")
        fh.write("Produced by `python examples/paper/compactness.py`. "
                 "Acc(P) = captured energy fraction (paper Eq. 17); `n/a` where the H-basis stops (order 2) "
                 "or a threshold is not reached by P = 10. Medians ignore materials that never reach the threshold.\n\n"
                 f"**Isotropic materials** use the reduced rule refined per material and quantity until Acc(P') of the "
                 f"Helmholtz basis changes by less than {args.tol:g} for every P' <= {P} (largest error estimate "
                 f"{est_iso:.2g}; per-material estimates and rule sizes in compactness_isotropic.csv). "
                 f"**Anisotropic materials** use the 4-D rule refined up to {args.max_dirs} directions per hemisphere "
                 f"(target {args.tol_aniso:g}; largest change of the last refinement {est_an:.2g}, see "
                 "compactness_anisotropic.csv).\n\n"
                 "Two quantities: **cosine** = f cos(theta_i) cos(theta_o) (bounded for every model) and **brdf** = f "
                 "itself, the quantity of the paper's Eq. 17. For the GGX, Ward and Oren-Nayar models the integral of "
                 f"f^2 diverges at grazing angles; their raw-BRDF Acc is that of f cut at cos(theta) >= {args.cutoff:g} "
                 "for both directions (see compactness_cutoff.csv for the dependence on the cutoff). Lambertian and "
                 "Blinn-Phong need no cutoff.\n\n")
        fh.write(f"## Cosine-weighted, {len(iso_names)} isotropic materials, isotropic bases\n\n")
        _table(fh, sh, summary(iso["cosine"], C.ISO_BASES, all_iso))
        fh.write(f"\nNumber of isotropic materials (cosine-weighted) for which each basis has the highest Acc(P) "
                 f"(H-basis excluded, it stops at order 2; ties within {2 * args.tol:g} count for every tied basis):\n\n")
        _table(fh, ["P"] + cmp_bases, [[k] + [best[k][bn] for bn in cmp_bases] for k in best])
        fh.write(f"\n## Raw BRDF f (paper Eq. 17), {len(iso_names)} isotropic materials "
                 f"(cutoff {args.cutoff:g} where f^2 is not integrable)\n\n")
        _table(fh, sh, summary(iso["brdf"], C.ISO_BASES, all_iso))
        fh.write(f"\n## Raw BRDF f, the {int(fin_iso.sum())} finite-energy materials only (no cutoff)\n\n")
        _table(fh, sh, summary(iso["brdf"], C.ISO_BASES, fin_iso))
        fh.write(f"\n## Cosine-weighted, {len(an_names)} anisotropic Ward materials, product bases (4-D)\n\n")
        _table(fh, sh, summary(an["cosine"], C.ANISO_BASES, all_an))
        fh.write("\n## Raw-BRDF Acc of the Helmholtz basis against the grazing cutoff\n\n")
        _table(fh, ["material", "cutoff", "Acc(0)", "Acc(2)", "Acc(4)", "Acc(8)", "error estimate"], cut_rows)
        fh.write(f"\nRuntime: {time.time() - t0:.0f} s (isotropic part {t_iso:.0f} s).\n")

    _figure(plt, files[3], iso, an, iso_names, an_names, fin_iso, P, args.cutoff)

    if args.merl:
        run_merl(args, files, P, progress)
    print(f"wrote {len(files)} files in {time.time() - t0:.0f} s")
    for q in ("cosine", "brdf"):
        for bn in C.ISO_BASES:
            print(f"  {q:6s} {bn:28s} mean Acc(2,4,8) = "
                  + ", ".join(f"{np.nanmean(iso[q][bn][:, k]):.4f}" for k in (2, 4, 8) if k <= P))
    for bn in C.ANISO_BASES:
        print(f"  aniso  {bn:28s} mean Acc(2,4,8) = "
              + ", ".join(f"{np.mean(an['cosine'][bn][:, k]):.4f}" for k in (2, 4, 8) if k <= P))


def _plot_mean(ax, res, bases, P, title, aniso=False):
    Ps = np.arange(P + 1)
    for bn in bases:
        lab = C.LABEL[bn] + (" (4-D)" if aniso else "")
        ax.plot(Ps, np.mean(res[bn], 0), label=lab, **C.STYLE[bn])
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("truncation order P")
    ax.set_ylabel("mean Acc(P)")
    ax.set_ylim(0, 1.01)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="lower right")


def _figure(plt, path, iso, an, iso_names, an_names, fin_iso, P, cutoff):
    fig, axes = plt.subplots(2, 2, figsize=(14, 10.5))
    _plot_mean(axes[0, 0], iso["cosine"], C.ISO_BASES, P,
               f"(a) {len(iso_names)} isotropic materials, f cos(theta_i) cos(theta_o)")
    _plot_mean(axes[0, 1], iso["brdf"], C.ISO_BASES, P,
               f"(b) same materials, raw BRDF f (cutoff cos >= {cutoff:g} where f^2 diverges)")
    _plot_mean(axes[1, 0], an["cosine"], C.ANISO_BASES, P,
               f"(c) {len(an_names)} anisotropic Ward, f cos cos, product bases", aniso=True)
    ax = axes[1, 1]
    y = np.arange(len(iso_names))
    for off, q, col in ((-0.2, "cosine", "tab:gray"), (0.2, "brdf", "tab:purple")):
        A = iso[q]["helmholtz_isotropic"]
        mo = [min_order(r, 0.95) for r in A]
        ax.barh(y + off, [P + 1 if math.isnan(v) else v for v in mo], 0.4, color=col,
                label=f"95 %, {'f cos cos' if q == 'cosine' else 'raw f'}")
    ax.set_yticks(y)
    ax.set_yticklabels(iso_names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel(f"minimum order P for Acc >= 95 % ({P + 1} = not reached by {P})")
    ax.set_title("(d) Helmholtz isotropic: minimum order per material", fontsize=10)
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=8, loc="upper right")  # the top rows (diffuse materials) have short bars
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_merl(args, files, P, progress):
    """Paper Fig. 6 on a folder of MERL files: Acc(P) per isotropic basis, minimum orders, figure."""
    import warnings

    import matplotlib.pyplot as plt

    warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)  # H-basis columns beyond order 2

    paths = sorted(args.merl.glob("*.binary"))
    if not paths:
        raise SystemExit(f"--merl: no .binary files in {args.merl}")
    res = {bn: [] for bn in C.ISO_BASES}
    meta = []
    for path in progress(paths, desc="MERL files"):
        acc, info = converged_iso(merl_brdf(path), P, args.merl_tol, None)
        for bn in C.ISO_BASES:
            res[bn].append(acc[bn])
        meta.append((info["error_estimate"], info["n_theta"], info["n_phi"]))
    names = [p.stem for p in paths]
    res = {k: np.stack(v) for k, v in res.items()}
    hdr = ["material", "basis"] + [f"acc_P{k}" for k in range(P + 1)] + [
        "min_order_95", "min_order_99", "error_estimate", "n_theta", "n_phi"]
    rows = []
    for i, nm in enumerate(names):
        for bn in C.ISO_BASES:
            r = res[bn][i]
            rows.append([nm, bn] + [float(v) for v in r] + [min_order(r, 0.95), min_order(r, 0.99)] + list(meta[i]))
    C.write_csv(files[5], hdr, rows)
    with open(files[7], "w") as fh:
        where = args.merl.resolve()
        where = where.relative_to(C.ROOT) if C.ROOT in where.parents else where
        fh.write(f"# Paper Fig. 6 on {len(names)} MERL files in `{where}`\n\n"
                 "Raw BRDF f (mean of the colour channels, nearest-bin lookup), reduced rule refined until Acc(P') of "
                 f"the Helmholtz basis changes by less than {args.merl_tol:g}. Minimum order of the Helmholtz basis:\n\n")
        _table(fh, ["material", "Acc(2)", "Acc(4)", "Acc(8)", "min P (95%)", "min P (99%)", "error estimate"],
               [[nm, res["helmholtz_isotropic"][i][2], res["helmholtz_isotropic"][i][4], res["helmholtz_isotropic"][i][8],
                 min_order(res["helmholtz_isotropic"][i], 0.95), min_order(res["helmholtz_isotropic"][i], 0.99),
                 meta[i][0]] for i, nm in enumerate(names)])
        fh.write("\nMean Acc(P) per basis:\n\n")
        _table(fh, ["basis", "Acc(2)", "Acc(4)", "Acc(8)"],
               [[bn] + [float(np.nanmean(res[bn][:, k])) for k in (2, 4, 8)] for bn in C.ISO_BASES])
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    Ps = np.arange(P + 1)
    for bn in C.ISO_BASES:
        axes[0].plot(Ps, np.nanmean(res[bn], 0), label=C.LABEL[bn], **C.STYLE[bn])
    axes[0].set_xlabel("truncation order P")
    axes[0].set_ylabel("mean Acc(P) (raw BRDF)")
    axes[0].set_title(f"MERL files in {args.merl.resolve().name}/ ({len(names)} materials)", fontsize=10)
    axes[0].legend(fontsize=8, loc="lower right")
    axes[0].set_ylim(0, 1.01)
    axes[0].grid(alpha=0.3)
    y = np.arange(len(names))
    for off, thr, col in ((-0.2, 0.95, "tab:gray"), (0.2, 0.99, "tab:purple")):
        mo = [min_order(r, thr) for r in res["helmholtz_isotropic"]]
        axes[1].barh(y + off, [P + 1 if math.isnan(v) else v for v in mo], 0.4, color=col, label=f"{thr:.0%}")
    axes[1].set_yticks(y)
    axes[1].set_yticklabels(names, fontsize=8)
    axes[1].invert_yaxis()
    axes[1].set_xlabel(f"minimum order P, Helmholtz isotropic ({P + 1} = not reached)")
    axes[1].legend(fontsize=8)
    axes[1].grid(alpha=0.3, axis="x")
    fig.tight_layout()
    fig.savefig(files[6], dpi=110)
    plt.close(fig)
    print(f"MERL: wrote {files[5]}, {files[6]}, {files[7]}")


def _med(v):
    v = [x for x in v if not math.isnan(x)]
    return float(np.median(v)) if v else float("nan")


def _best_counts(res, bases, k, tol=1e-9):
    """Materials on which each basis attains the highest Acc(k) (ties within ``tol`` count for every tied basis)."""
    out = {bn: 0 for bn in bases}
    n = res[bases[0]].shape[0]
    for i in range(n):
        vals = np.array([res[bn][i, k] for bn in bases])
        for bn, v in zip(bases, vals):
            if v >= vals.max() - tol:
                out[bn] += 1
    return out


def _table(fh, header, rows):
    fh.write("| " + " | ".join(header) + " |\n")
    fh.write("|" + "|".join("---" for _ in header) + "|\n")
    for r in rows:
        fh.write("| " + " | ".join(C._fmt(v) for v in r) + " |\n")


if __name__ == "__main__":
    main()
