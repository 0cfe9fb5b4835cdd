"""Projection accuracy versus the number of BRDF evaluations: deterministic quadrature vs Monte Carlo.

The paper projects BRDFs by Monte Carlo integration; :func:`torch_hsh.fitting.project`
also offers deterministic product quadrature. For the isotropic Helmholtz basis at
order ``--order`` (default 6) and three isotropic materials, this script compares

* ``reduced``: the 3-D isotropic rule (Gauss-Legendre in both cosines, uniform in dphi,
  ``n_phi = 2 n_theta``), ``n_theta^2 n_phi`` evaluations;
* ``product``: the full 4-D product rule over both hemispheres (``n_phi = 2 n_theta`` per
  direction), ``(n_theta n_phi)^2`` evaluations;
* ``monte_carlo``: uniform sampling of both hemispheres (as in the paper), mean over
  ``--seeds`` seeds;

against a reference from the reduced rule with 64 x 64 x 128 nodes. Metric: relative
L2 error of the coefficient vector, ``|a - a_ref| / |a_ref|``.

Outputs (refuses to overwrite without ``--overwrite``): ``<images>/paper_quadrature_vs_mc.png``,
``<tables>/quadrature_vs_mc.csv``.

``--quick`` (CI): one material (``blinn_phong_n10``) and a few sizes of each method; its rows are
rows of the full table (same rules, same seeds), which the CI test checks against the committed CSV.

Run: ``python examples/paper/quadrature_vs_mc.py`` (10-60 s depending on load; ``--quick``: a few seconds).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torch_hsh.fitting import project  # noqa: E402

MATERIALS = ["blinn_phong_n10", "blinn_phong_n40", "oren_nayar_s0.35"]
#: ``--quick``: materials and sizes (a subset of the full run's rows).
QUICK = dict(materials=["blinn_phong_n10"], reduced_sizes=[4, 8, 16], product_sizes=[3, 6], mc_samples=[1000, 10000])


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    p.add_argument("--order", type=int, default=6)
    p.add_argument("--basis", default="helmholtz_isotropic")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--mc-samples", type=int, nargs="+", default=[1000, 3000, 10000, 30000, 100000, 300000])
    p.add_argument("--reduced-sizes", type=int, nargs="+", default=[4, 6, 8, 12, 16, 24, 32])
    p.add_argument("--product-sizes", type=int, nargs="+", default=[3, 4, 6, 8, 12])
    p.add_argument("--materials", nargs="+", default=MATERIALS, choices=MATERIALS, metavar="NAME",
                   help=f"subset of {', '.join(MATERIALS)} (default: all)")
    p.add_argument("--quick", action="store_true",
                   help="CI smoke run: one material, a few sizes (a subset of the full table's rows)")
    args = p.parse_args(argv)
    if args.quick:
        for k, v in QUICK.items():
            setattr(args, k, v)
    C.set_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = [args.images / "paper_quadrature_vs_mc.png", args.tables / "quadrature_vs_mc.csv"]
    C.prepare_outputs(files, args.overwrite)
    lib = {n: m for n, m, _ in C.material_library()}
    P, bn = args.order, args.basis
    rows = []
    for name in tqdm(args.materials, desc="materials"):
        f = C.as_scalar_brdf(lib[name])
        ref = project(f, P, basis=bn, n_theta=64, n_phi=128)
        nref = float(ref.norm())

        def err(a, ref=ref, nref=nref):
            return float((a - ref).norm()) / nref

        for nt in args.reduced_sizes:
            a = project(f, P, basis=bn, n_theta=nt, n_phi=2 * nt)
            rows.append([name, "reduced", nt * nt * 2 * nt, err(a)])
        for nt in args.product_sizes:
            a = project(f, P, basis=bn, n_theta=nt, n_phi=2 * nt, reduced=False)
            rows.append([name, "product", (nt * 2 * nt) ** 2, err(a)])
        for n in args.mc_samples:
            e = [err(project(f, P, basis=bn, method="monte_carlo", n_samples=n, seed=s)) for s in range(args.seeds)]
            rows.append([name, "monte_carlo", n, float(np.mean(e))])
    C.write_csv(files[1], ["material", "method", "brdf_evaluations", "relative_coefficient_error"], rows)

    fig, axes = plt.subplots(1, len(args.materials), figsize=(5 * len(args.materials), 4), sharey=True,
                             squeeze=False)
    axes = axes[0]
    for ax, name in zip(axes, args.materials):
        for meth, st in (("reduced", "o-"), ("product", "s-"), ("monte_carlo", "^-")):
            r = [x for x in rows if x[0] == name and x[1] == meth]
            ax.loglog([x[2] for x in r], [max(x[3], 1e-16) for x in r], st, label=meth)
        n = np.array(args.mc_samples, dtype=float)
        r0 = [x for x in rows if x[0] == name and x[1] == "monte_carlo"][0]
        ax.loglog(n, r0[3] * np.sqrt(n[0] / n), "k:", lw=0.8, label="N^-1/2")
        ax.set_title(f"{name}, {bn}, P = {P}")
        ax.set_xlabel("BRDF evaluations")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("relative coefficient error")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(files[0], dpi=120)
    plt.close(fig)
    for r in rows:
        print(f"  {r[0]:18s} {r[1]:12s} N={r[2]:>9d} err={r[3]:.2e}")


if __name__ == "__main__":
    main()
