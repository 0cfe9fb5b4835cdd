"""Compactness of the BRDF bases on a library of analytic materials (paper Figs. 6-7 analogue).

For every material and basis: the spectrum up to order ``--max-order`` (default 10)
by deterministic quadrature, Acc(P) (paper Eq. 17) for P = 0..10, and the minimum
order reaching 95 % and 99 %, for two quantities: the cosine-weighted BRDF
``f cos(theta_i) cos(theta_o)`` (main result: bounded and reciprocal for every model)
and the raw BRDF ``f`` (whose squared integral diverges at grazing angles for the
GGX, Ward and Oren-Nayar models, so its raw-BRDF averages use Lambertian and
Blinn-Phong materials only; see ``docs/conventions_and_errata.md``).

* Isotropic materials (25): the isotropic bases (ours, Zernike, Gautron, Westin,
  H-basis), projected with the reduced 3-D isotropic rule
  (:func:`torch_hsh.quadrature.isotropic_quadrature`).
* Anisotropic Ward materials (6): the anisotropic/product bases, projected
  separably, ``C = H^T diag(w) F diag(w) H`` on a direction product rule
  (checked against :func:`torch_hsh.fitting.project` at start-up); and the isotropic
  bases, which can only capture the **azimuthal average** of the BRDF (an isotropic
  basis function is invariant under a common rotation of wi and wo, so its
  coefficient equals that of the rotation-averaged BRDF), projected from that
  average; their Acc is bounded by the energy fraction of the average.
* ``--merl DIR``: the isotropic comparison on MERL ``.binary`` files (reduced rule,
  nearest-bin lookup through :func:`torch_hsh.io.merl.read_merl` when available).

Outputs (refuses to overwrite them without ``--overwrite``):
``docs/tables/compactness_isotropic.csv``, ``compactness_anisotropic.csv``,
``compactness_summary.md``, ``docs/images/paper_compactness.png``; with ``--merl``
also ``compactness_merl.csv`` and ``paper_compactness_merl.png``.

Run: ``python examples/paper/compactness.py`` (about 2-4 minutes on 2 CPU cores).
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
from torch_hsh.quadrature import direction_quadrature  # noqa: E402

THRESH = (0.95, 0.99)


def min_order(acc_row: np.ndarray, thr: float) -> float:
    idx = np.nonzero(acc_row >= thr - 1e-12)[0]
    return float(idx[0]) if len(idx) else float("nan")


def acc_padded(acc: torch.Tensor, P: int) -> np.ndarray:
    """(n, P_b+1) -> (n, P+1), NaN where the basis stops (H-basis beyond order 2)."""
    out = np.full((acc.shape[0], P + 1), np.nan)
    out[:, : acc.shape[1]] = acc.numpy()
    return out


def run_isotropic(materials, P, n_theta, n_phi, progress):
    """Acc for both quantities: ``{"brdf": {basis: (n, P+1)}, "cosine": {...}}`` (one basis evaluation)."""
    wi, wo, w = C.reduced_rule(n_theta, n_phi)
    F = torch.stack([f(wi, wo) for _, f in materials], -1)
    F = torch.cat([F, F * (wi[:, 2] * wo[:, 2])[:, None]], -1)  # raw | cosine-weighted
    energy = (F * F * w[:, None]).sum(0)
    n = len(materials)
    res = {"brdf": {}, "cosine": {}}
    for bn in progress(C.ISO_BASES, desc="isotropic bases"):
        Pb = min(P, get_basis(bn).max_order)
        a = C.project_values(bn, Pb, wi, wo, w, F)
        acc = acc_padded(C.accuracy_from_coeffs(bn, a, energy), P)
        res["brdf"][bn], res["cosine"][bn] = acc[:n], acc[n:]
    return res


def run_anisotropic(materials, P, n_theta, n_phi, n_theta_iso, n_phi_iso, progress):
    d, wd = direction_quadrature(n_theta, n_phi, dtype=torch.float64)
    N = d.shape[0]
    wi4 = d[:, None, :].expand(N, N, 3).reshape(-1, 3)
    wo4 = d[None, :, :].expand(N, N, 3).reshape(-1, 3)
    W4 = (wd[:, None] * wd[None, :]).reshape(-1)
    cos4 = wi4[:, 2] * wo4[:, 2]
    wi, wo, w = C.reduced_rule(n_theta_iso, n_phi_iso)
    res = {q: {bn: [] for bn in C.ANISO_BASES + C.ISO_BASES} for q in ("brdf", "cosine")}
    for name, f in progress(materials, desc="anisotropic materials"):
        Fraw = f(wi4, wo4)
        Fbar_raw = C.azimuthal_average(f, wi, wo)  # rotations about z keep cos(theta)
        for q in ("brdf", "cosine"):
            Fm = Fraw * cos4 if q == "cosine" else Fraw
            E = float((Fm * Fm * W4).sum())
            Fm = Fm.reshape(N, N)
            for bn in C.ANISO_BASES:
                Pb = min(P, get_basis(bn).max_order)
                a, lab = C.separable_coefficients(bn, Pb, d, wd, Fm)
                cum = torch.cumsum(torch.stack([(a[lab == p] ** 2).sum() for p in range(Pb + 1)]), 0) / E
                res[q][bn].append(acc_padded(cum[None], P)[0])
            Fbar = (Fbar_raw * (wi[:, 2] * wo[:, 2]) if q == "cosine" else Fbar_raw)[:, None]
            for bn in C.ISO_BASES:
                Pb = min(P, get_basis(bn).max_order)
                a = C.project_values(bn, Pb, wi, wo, w, Fbar)
                acc = C.accuracy_from_coeffs(bn, a, torch.tensor([E], dtype=a.dtype))
                res[q][bn].append(acc_padded(acc, P)[0])
    return {q: {k: np.stack(v) for k, v in r.items()} for q, r in res.items()}


def load_merl(folder: Path, n_theta, n_phi, progress):
    """Tabulate MERL materials on the reduced rule: ``names, F (M, n)``, plus the rule."""
    try:
        from torch_hsh.io.merl import read_merl
    except ImportError as e:  # pragma: no cover - depends on the checkout
        raise SystemExit(f"--merl needs torch_hsh.io.merl.read_merl ({e})") from e
    files = sorted(folder.glob("*.binary"))
    if not files:
        raise SystemExit(f"--merl: no .binary files in {folder}")
    wi, wo, w = C.reduced_rule(n_theta, n_phi)
    cols, names = [], []
    for fpath in progress(files, desc="MERL files"):
        brdf = read_merl(fpath)
        v = brdf(wi, wo) if callable(brdf) else None
        if v is None:
            raise SystemExit("read_merl returned an object that is not callable as brdf(wi, wo)")
        v = v.to(torch.float64)
        if v.dim() == 2:
            v = v.mean(-1)  # average of the colour channels
        cols.append(torch.nan_to_num(v.clamp(min=0.0)))
        names.append(fpath.stem)
    return names, torch.stack(cols, -1), (wi, wo, w)


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    p.add_argument("--max-order", type=int, default=10)
    p.add_argument("--n-theta", type=int, default=32, help="GL nodes per cos(theta), reduced isotropic rule")
    p.add_argument("--n-phi", type=int, default=64, help="dphi nodes, reduced isotropic rule")
    p.add_argument("--n-theta-4d", type=int, default=20, help="GL nodes per direction, anisotropic rule")
    p.add_argument("--n-phi-4d", type=int, default=40, help="azimuths per direction, anisotropic rule")
    p.add_argument("--merl", type=Path, default=None, help="folder of MERL .binary files")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    C.set_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = [args.tables / "compactness_isotropic.csv", args.tables / "compactness_anisotropic.csv",
             args.tables / "compactness_summary.md", args.images / "paper_compactness.png"]
    if args.merl:
        files += [args.tables / "compactness_merl.csv", args.images / "paper_compactness_merl.png"]
    C.prepare_outputs(files, args.overwrite)
    progress = (lambda it, **k: it) if args.no_progress else (lambda it, **k: tqdm(it, **k))
    t0 = time.time()
    P = args.max_order

    for bn in C.ANISO_BASES:  # the separable projection is the same sum as torch_hsh.fitting.project
        err = C.check_against_fitting(bn, C.material_library()[-1][1])
        assert err < 1e-10, (bn, err)

    lib = C.material_library()
    iso_names = [n for n, _, iso_ in lib if iso_]
    an_names = [n for n, _, iso_ in lib if not iso_]
    iso = run_isotropic([(n, C.as_scalar_brdf(m)) for n, m, i in lib if i], P, args.n_theta, args.n_phi, progress)
    an = run_anisotropic([(n, C.as_scalar_brdf(m)) for n, m, i in lib if not i], P, args.n_theta_4d, args.n_phi_4d,
                         args.n_theta, args.n_phi, progress)

    hdr = ["quantity", "material", "finite_brdf_energy", "basis"] + [f"acc_P{k}" for k in range(P + 1)] + [
        "min_order_95", "min_order_99"]

    def rows_of(names, res, bases):
        rows = []
        for q in ("cosine", "brdf"):
            for i, name in enumerate(names):
                for bn in bases:
                    r = res[q][bn][i]
                    rows.append([q, name, C.finite_energy(name), bn] + [float(x) for x in r]
                                + [min_order(r, THRESH[0]), min_order(r, THRESH[1])])
        return rows

    C.write_csv(files[0], hdr, rows_of(iso_names, iso, C.ISO_BASES))
    C.write_csv(files[1], hdr, rows_of(an_names, an, C.ANISO_BASES + C.ISO_BASES))

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
    best = {k: _best_counts(iso["cosine"], C.ISO_BASES[:4], k) for k in (2, 4, 8) if k <= P}
    with open(files[2], "w") as fh:
        fh.write("# Compactness of the BRDF bases on analytic materials\n\n")
        fh.write(f"Produced by `python examples/paper/compactness.py` ({time.strftime('%Y-%m-%d')}), "
                 f"reduced isotropic rule {args.n_theta}x{args.n_theta}x{args.n_phi}, "
                 f"anisotropic rule ({args.n_theta_4d}x{args.n_phi_4d})^2 per direction pair. "
                 "Acc(P) = captured energy fraction (paper Eq. 17); `n/a` where the H-basis stops (order 2) "
                 "or a threshold is not reached by P = 10. Medians ignore materials that never reach the threshold.\n\n"
                 "Two quantities are expanded: **cosine** = f cos(theta_i) cos(theta_o) (bounded and reciprocal for every "
                 "model; main result) and **brdf** = f itself. The squared BRDF of the microfacet (GGX, Ward) and "
                 "Oren-Nayar models is not integrable (grazing 1/cos growth), so their raw-BRDF Acc depends on the "
                 "quadrature; raw-BRDF averages below use only the finite-energy materials (Lambertian, Blinn-Phong).\n\n")
        fh.write(f"## Cosine-weighted, {len(iso_names)} isotropic materials, isotropic bases\n\n")
        _table(fh, sh, summary(iso["cosine"], C.ISO_BASES, all_iso))
        fh.write("\nNumber of isotropic materials (cosine-weighted) for which each basis has the highest Acc(P) "
                 "(H-basis excluded, it stops at order 2; ties within 1e-9 count for every tied basis):\n\n")
        _table(fh, ["P"] + C.ISO_BASES[:4], [[k] + [best[k][bn] for bn in C.ISO_BASES[:4]] for k in best])
        fh.write(f"\n## Raw BRDF, {int(fin_iso.sum())} finite-energy isotropic materials\n\n")
        _table(fh, sh, summary(iso["brdf"], C.ISO_BASES, fin_iso))
        fh.write(f"\n## Cosine-weighted, {len(an_names)} anisotropic Ward materials\n\n")
        fh.write("Product bases (full 4-D projection) and isotropic bases (which capture the azimuthal "
                 "average only; their Acc is bounded by its energy fraction):\n\n")
        _table(fh, sh, summary(an["cosine"], C.ANISO_BASES + C.ISO_BASES, all_an))
        fh.write(f"\nRuntime: {time.time() - t0:.0f} s.\n")
    iso_mats, an_mats = iso_names, an_names
    iso_c, an_c = iso["cosine"], an["cosine"]

    # figure
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    Ps = np.arange(P + 1)
    for bn in C.ISO_BASES:
        axes[0].plot(Ps, np.mean(iso_c[bn], 0), "o-", label=C.LABEL[bn])
    axes[0].set_title(f"{len(iso_mats)} isotropic materials (f cos cos): mean Acc(P)")
    for bn in C.ANISO_BASES:
        axes[1].plot(Ps, np.mean(an_c[bn], 0), "o-", label=C.LABEL[bn] + " (4-D)")
    axes[1].plot(Ps, np.mean(an_c["helmholtz_isotropic"], 0), "k--", label="Helmholtz isotropic (azimuthal avg.)")
    axes[1].set_title(f"{len(an_mats)} anisotropic Ward (f cos cos): mean Acc(P)")
    for ax in axes[:2]:
        ax.set_xlabel("truncation order P")
        ax.set_ylabel("Acc(P)")
        ax.set_ylim(0, 1.01)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    mo = [min_order(r, 0.95) for r in iso_c["helmholtz_isotropic"]]
    mo99 = [min_order(r, 0.99) for r in iso_c["helmholtz_isotropic"]]
    x = np.arange(len(iso_mats))
    axes[2].bar(x - 0.2, [11 if math.isnan(v) else v for v in mo], 0.4, label="95 %")
    axes[2].bar(x + 0.2, [11 if math.isnan(v) else v for v in mo99], 0.4, label="99 %")
    axes[2].set_xticks(x)
    axes[2].set_xticklabels(iso_mats, rotation=90, fontsize=6)
    axes[2].set_ylabel("min order P (11 = not reached by 10)")
    axes[2].set_title("Helmholtz isotropic (f cos cos): minimum order per material")
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(files[3], dpi=120)
    plt.close(fig)

    if args.merl:
        names, F, (wi, wo, w) = load_merl(args.merl, args.n_theta, args.n_phi, progress)
        energy = (F * F * w[:, None]).sum(0)
        res = {}
        for bn in progress(C.ISO_BASES, desc="bases (MERL)"):
            Pb = min(P, get_basis(bn).max_order)
            a = C.project_values(bn, Pb, wi, wo, w, F)
            res[bn] = acc_padded(C.accuracy_from_coeffs(bn, a, energy), P)
        rows = []
        for i, nm in enumerate(names):
            for bn in C.ISO_BASES:
                r = res[bn][i]
                rows.append([nm, bn] + [float(v) for v in r] + [min_order(r, 0.95), min_order(r, 0.99)])
        C.write_csv(files[4], hdr, rows)
        fig, ax = plt.subplots(figsize=(6, 4.5))
        for bn in C.ISO_BASES:
            ax.plot(Ps, np.mean(res[bn], 0), "o-", label=C.LABEL[bn])
        ax.set_xlabel("P")
        ax.set_ylabel("mean Acc(P)")
        ax.set_title(f"MERL ({len(names)} materials)")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(files[5], dpi=120)
        plt.close(fig)
    print(f"wrote {len(files)} files in {time.time() - t0:.0f} s")
    for bn in C.ISO_BASES:
        print(f"  {bn:24s} mean Acc(2,4,8) = " + ", ".join(f"{np.mean(iso_c[bn][:, k]):.4f}" for k in (2, 4, 8) if k <= P))
    for bn in C.ISO_BASES:
        print(f"  {bn:24s} raw BRDF (finite-energy) mean Acc(2,4,8) = "
              + ", ".join(f"{np.mean(iso['brdf'][bn][fin_iso, k]):.4f}" for k in (2, 4, 8) if k <= P))
    for bn in C.ANISO_BASES:
        print(f"  {bn:24s} (aniso) mean Acc(2,4,8) = " + ", ".join(f"{np.mean(an_c[bn][:, k]):.4f}" for k in (2, 4, 8) if k <= P))


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
