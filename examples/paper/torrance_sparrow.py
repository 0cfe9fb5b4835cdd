"""Torrance-Sparrow spectrum at normal exitance, paper Figs. 4 and 5 (Eqs. 38, 41-45).

At normal exitance (theta_o = 0) the paper's TS model (Eq. 38, F(1)/F(1) = 1, so
``eta`` plays no role) is a function of the incident polar angle only,

    g(z) = rho_d / pi + rho_s / (pi sigma^2 z) exp(-(acos z / (2 sigma))^2),   z = cos(theta_i).

**Singularity.** ``int g^2 dw`` diverges (the ``1/z`` term squared is not integrable at
the horizon unless the Gaussian vanishes there), so Acc(P) of ``g`` itself is not
defined: with a cosine clamp ``z >= eps`` it tends to 0 as ``eps -> 0``. This script
therefore reports

* the **cosine-weighted kernel** ``g(z) z`` (smooth, finite energy; the quantity that
  multiplies the incident radiance): main result, Figs. 4-5;
* ``g`` with ``z`` clamped at ``eps`` in {0.1, 0.03, 0.01, 0.001} (table only) to show the
  dependence on the regularisation.

Spectra (1-D, zonal): Helmholtz HSH / Gautron (the same zonal HSH ``Theta_p``; the
normal-exitance slice cannot tell them apart), Westin (zonal SH ``Y_l^0`` on the full
sphere, ``g`` extended by zero), Koenderink-van Doorn (zonal Zernike ``R_n^0`` with
``rho = sqrt(1 - z)``, even ``n`` only) and the H-basis (H1, H3; stops at order 2).
Acc(P) = sum of b^2 over functions of order <= P / (2 pi int g^2 dz), Gauss-Legendre
with ``--n-theta`` nodes. Fig. 4 plots the paper's ``a_p`` (Eqs. 41-44), from
:func:`torch_hsh.fitting.project_normal_exitance` with ``normalization="helmholtz"``.

**Parameters are illustrative**, not the Weyrich et al. (2006) table (not available
here): six skin types with rho_d 0.60 ... 0.15 (very light ... very dark), rho_s
0.16 ... 0.11, sigma 0.30 ... 0.40, eta = 1.38; ``--samples`` (default 100) samples per
type jitter rho_s and sigma by a factor U(0.8, 1.2) (seeded), standing in for facial
regions.

Outputs (refuses to overwrite without ``--overwrite``): ``<images>/paper_ts_spectrum.png``
(Fig. 4), ``<images>/paper_ts_accuracy.png`` (Fig. 5), ``<tables>/ts_spectrum.csv``,
``<tables>/ts_accuracy.csv``, ``<tables>/ts_regularisation.csv``.

Run: ``python examples/paper/torrance_sparrow.py`` (seconds).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torch_hsh.fitting import normal_exitance_energy, project_normal_exitance  # noqa: E402
from torch_hsh.quadrature import gauss_legendre  # noqa: E402

SKIN = [  # (name, rho_d, rho_s, sigma): illustrative values
    ("type I", 0.60, 0.16, 0.30),
    ("type II", 0.52, 0.15, 0.32),
    ("type III", 0.44, 0.14, 0.34),
    ("type IV", 0.35, 0.13, 0.36),
    ("type V", 0.25, 0.12, 0.38),
    ("type VI", 0.15, 0.11, 0.40),
]
FAMILIES = ["helmholtz/gautron (zonal HSH)", "koenderink_zernike (zonal Zernike)", "westin (zonal SH)", "hbasis (H1, H3)"]


def ts_normal_exitance(rho_d, rho_s, sigma, eps=None, cosine_weighted=True):
    def g(z):
        zc = z if eps is None else z.clamp(min=eps)
        th = torch.acos(z.clamp(-1.0, 1.0))
        v = rho_d / math.pi + rho_s / (math.pi * sigma**2 * zc) * torch.exp(-((th / (2 * sigma)) ** 2))
        return v * z if cosine_weighted else v

    return g


def zonal_tables(z: torch.Tensor, P: int):
    """Per family: (values (n, K), labels (K,)) of orthonormal zonal functions on the hemisphere/sphere."""
    from numpy.polynomial import legendre as L

    zn = z.numpy()
    out = {}
    hsh = np.stack([math.sqrt((2 * p + 1) / (2 * math.pi)) * L.legval(2 * zn - 1, np.eye(P + 1)[p]) for p in range(P + 1)], -1)
    out[FAMILIES[0]] = (hsh, np.arange(P + 1))
    from torch_hsh.bases.zernike import zernike_radial

    rho = torch.sqrt((1 - z).clamp(min=0))
    ns = list(range(0, P + 1, 2))
    zer = np.stack([math.sqrt((n + 1) / (2 * math.pi)) * zernike_radial(rho, n, 0).numpy() for n in ns], -1)
    out[FAMILIES[1]] = (zer, np.array(ns))
    sh = np.stack([math.sqrt((2 * l + 1) / (4 * math.pi)) * L.legval(zn, np.eye(P + 1)[l]) for l in range(P + 1)], -1)
    out[FAMILIES[2]] = (sh, np.arange(P + 1))
    c1 = math.sqrt(3 / (2 * math.pi))
    hb = np.stack([np.full_like(zn, 1 / math.sqrt(2 * math.pi)), c1 * (2 * zn - 1)], -1)
    out[FAMILIES[3]] = (hb, np.array([0, 1]))
    return out


def accuracy_1d(gz, z, wz, tables, P):
    E = 2 * math.pi * float((gz**2 * wz).sum())
    acc = {}
    for fam, (T, lab) in tables.items():
        b = 2 * math.pi * (T * (gz * wz)[:, None]).sum(0)
        row = []
        for p in range(P + 1):
            row.append(float((b[lab <= p] ** 2).sum()) / E if (fam != FAMILIES[3] or p <= 2) else float("nan"))
        acc[fam] = row
    return acc


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    p.add_argument("--max-order", type=int, default=12)
    p.add_argument("--samples", type=int, default=100, help="samples per skin type")
    p.add_argument("--n-theta", type=int, default=512, help="Gauss-Legendre nodes on [0, 1]")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    C.set_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = [args.images / "paper_ts_spectrum.png", args.images / "paper_ts_accuracy.png",
             args.tables / "ts_spectrum.csv", args.tables / "ts_accuracy.csv", args.tables / "ts_regularisation.csv"]
    C.prepare_outputs(files, args.overwrite)
    P = args.max_order
    z, wz = gauss_legendre(args.n_theta, 0.0, 1.0, dtype=torch.float64)
    zn, wn = z.numpy(), wz.numpy()
    tables = zonal_tables(z, P)
    rng = np.random.default_rng(args.seed)
    spec = {s[0]: [] for s in SKIN}
    accs = {fam: [] for fam in FAMILIES}
    acc_hsh_by_type = {s[0]: [] for s in SKIN}
    T_hsh = torch.tensor(tables[FAMILIES[0]][0]) * (2 * math.pi * wz)[:, None]  # b_p = 2 pi sum w g Theta_p
    scale = np.full(P + 1, math.sqrt(math.pi))
    scale[0] = math.sqrt(2 * math.pi)  # a_p (Eqs. 41-44) from b_p, see torch_hsh.fitting.project_normal_exitance
    for name, rd, rs, sg in tqdm(SKIN, desc="skin types"):
        for _ in range(args.samples):
            rs_k, sg_k = rs * rng.uniform(0.8, 1.2), sg * rng.uniform(0.8, 1.2)
            g = ts_normal_exitance(rd, rs_k, sg_k)
            gz_t = g(z)
            b = (gz_t @ T_hsh).numpy()
            spec[name].append(b * scale)
            E = 2 * math.pi * float((gz_t**2 * wz).sum())
            acc_hsh_by_type[name].append(np.cumsum(b**2) / E)
            acc = accuracy_1d(gz_t.numpy(), zn, wn, tables, P)
            for fam in FAMILIES:
                accs[fam].append(acc[fam])
    # the local sums are the library's: compare with torch_hsh.fitting once (same Gauss-Legendre rule)
    g0 = ts_normal_exitance(*SKIN[0][1:])
    a_lib = project_normal_exitance(g0, P, n_theta=args.n_theta, normalization="helmholtz").numpy()
    a_loc = (g0(z) @ T_hsh).numpy() * scale
    assert np.allclose(a_lib, a_loc, rtol=1e-10, atol=1e-12), (a_lib, a_loc)
    E_lib = float(normal_exitance_energy(g0, n_theta=args.n_theta))
    assert abs(E_lib - 2 * math.pi * float((g0(z) ** 2 * wz).sum())) < 1e-10 * E_lib
    hsh_local = np.mean(accs[FAMILIES[0]], 0)
    hsh_lib = np.mean([np.mean(v, 0) for v in acc_hsh_by_type.values()], 0)
    assert np.allclose(hsh_local, hsh_lib, atol=1e-10)

    mean_spec = {k: np.mean(v, 0) for k, v in spec.items()}
    C.write_csv(files[2], ["skin_type"] + [f"a_{k}" for k in range(P + 1)],
                [[k] + [float(x) for x in v] for k, v in mean_spec.items()])
    mean_acc = {fam: np.nanmean(np.array(v, dtype=float), 0) if fam != FAMILIES[3] else np.array(v, dtype=float).mean(0)
                for fam, v in accs.items()}
    C.write_csv(files[3], ["basis_family"] + [f"acc_P{k}" for k in range(P + 1)],
                [[fam] + [float(x) for x in mean_acc[fam]] for fam in FAMILIES]
                + [[f"hsh {k}"] + [float(x) for x in np.mean(v, 0)] for k, v in acc_hsh_by_type.items()])
    # regularisation dependence of the raw (non cosine-weighted) kernel
    reg_rows = []
    rules = {nt: gauss_legendre(nt, 0.0, 1.0, dtype=torch.float64) for nt in (128, args.n_theta)}
    for eps in (0.1, 0.03, 0.01, 0.001):
        for nt, (zz, ww) in rules.items():
            Th = torch.tensor(zonal_tables(zz, P)[FAMILIES[0]][0]) * (2 * math.pi * ww)[:, None]
            accs5 = []
            for name, rd, rs, sg in SKIN:
                gz_t = ts_normal_exitance(rd, rs, sg, eps=eps, cosine_weighted=False)(zz)
                b = (gz_t @ Th).numpy()
                E = 2 * math.pi * float((gz_t**2 * ww).sum())
                accs5.append(np.cumsum(b**2) / E)
            m = np.mean(accs5, 0)
            reg_rows.append([eps, nt, float(m[2]), float(m[5]), float(m[8]), float(m[12]) if P >= 12 else float("nan")])
    C.write_csv(files[4], ["cos_clamp_eps", "n_theta", "acc_P2", "acc_P5", "acc_P8", "acc_P12"], reg_rows)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ks = np.arange(P + 1)
    wbar = 0.8 / len(SKIN)
    for i, (k, v) in enumerate(mean_spec.items()):
        axes[0].bar(ks + (i - len(SKIN) / 2) * wbar, v, wbar, label=k)
    axes[0].set_xlabel("p")
    axes[0].set_ylabel("a_p (Eqs. 41-44), cosine-weighted TS")
    axes[0].set_title("TS spectrum at normal exitance (mean over samples)")
    axes[0].legend(fontsize=7)
    for k, v in acc_hsh_by_type.items():
        axes[1].plot(ks, np.mean(v, 0), "o-", ms=3, label=k)
    axes[1].axhline(0.99, color="k", lw=0.6, ls="--")
    axes[1].set_ylim(min(0.9, float(min(np.mean(v, 0)[0] for v in acc_hsh_by_type.values()))) - 0.02, 1.002)
    axes[1].set_xlabel("P")
    axes[1].set_ylabel("Acc(P), zonal HSH")
    axes[1].set_title("cumulative energy")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(files[0], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4.3))
    for fam in FAMILIES:
        ax.plot(ks, mean_acc[fam], "o-", ms=3, label=fam)
    ax.set_xlabel("truncation order P")
    ax.set_ylabel("mean Acc(P)")
    ax.set_title(f"TS at normal exitance, {len(SKIN)} skin types x {args.samples} samples")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(files[1], dpi=120)
    plt.close(fig)

    first99 = {k: int(np.argmax(np.mean(v, 0) >= 0.99)) if np.any(np.mean(v, 0) >= 0.99) else None
               for k, v in acc_hsh_by_type.items()}
    print("zonal-HSH Acc(5) per skin type:", {k: round(float(np.mean(v, 0)[5]), 4) for k, v in acc_hsh_by_type.items()})
    print("first order with Acc >= 99%:", first99)
    for fam in FAMILIES:
        print(f"  {fam:36s} Acc(2,5,8) = " + ", ".join(f"{mean_acc[fam][k]:.4f}" for k in (2, 5, 8)))
    print("raw-kernel regularisation (eps, n_theta, Acc2, Acc5, Acc8, Acc12):")
    for r in reg_rows:
        print("  ", r)


if __name__ == "__main__":
    main()
