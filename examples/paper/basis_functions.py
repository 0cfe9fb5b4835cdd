"""Helmholtz basis functions at a fixed incident direction, paper Fig. 1 (d) and (e).

Each small disk is a basis function as a function of the outgoing direction
``wo`` on the upper hemisphere, drawn in the orthographic projection
``(x, y) = (sin(theta_o) cos(phi_o), sin(theta_o) sin(phi_o))`` (the rim is the
horizon), for the incident direction ``wi = (theta, phi) = (pi/3, 0)`` (marked by a
cross at the mirror position ``-wi_xy``; the incident azimuth is along +x).
Colour: the function value, blue negative, red positive, one symmetric scale per disk.

* (e) ``paper_fig1_isotropic.png``: the isotropic Helmholtz functions
  :math:`\\mathcal H_{pr}^q` up to order 3, as in the paper's caption: ``p`` runs down,
  ``r`` runs across, and ``q`` runs across within each ``r`` (20 functions).
* (d) ``paper_fig1_anisotropic.png``: the general Helmholtz functions
  :math:`\\mathcal H_{jk}`, ``j <= k`` flat HSH indices up to order 3 (136 functions).
  Layout: row = first HSH factor ``j = (p, q)``, column = second factor ``k = (r, s)``,
  both in flat order ``(0,0), (1,-1), (1,0), (1,1), (2,-2), ...``; the lower triangle
  (``k < j``) is empty because :math:`\\mathcal H_{jk} = \\mathcal H_{kj}`.

Run: ``python examples/paper/basis_functions.py`` (a few seconds).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

import torch_hsh  # noqa: E402

THETA_I, PHI_I = math.pi / 3, 0.0


def disk_grid(n: int = 61):
    """Outgoing directions on an orthographic disk grid: ``wo (n*n, 3)`` and the inside mask ``(n, n)``."""
    x = np.linspace(-1, 1, n)
    X, Y = np.meshgrid(x, -x)  # image rows run from +y (top) to -y
    R2 = X**2 + Y**2
    inside = R2 < 1.0
    Z = np.sqrt(np.clip(1 - R2, 0, 1))
    wo = torch.tensor(np.stack([X, Y, Z], -1).reshape(-1, 3), dtype=torch.float64)
    return wo, inside


def incident():
    return torch.tensor([math.sin(THETA_I) * math.cos(PHI_I), math.sin(THETA_I) * math.sin(PHI_I), math.cos(THETA_I)],
                        dtype=torch.float64)


def _draw(ax, v, inside, title=None):
    img = np.where(inside, v, np.nan)
    m = np.nanmax(np.abs(img)) or 1.0
    ax.imshow(img, cmap="RdBu_r", vmin=-m, vmax=m, extent=(-1, 1, -1, 1))
    ax.add_patch(__import__("matplotlib").patches.Circle((0, 0), 1.0, fill=False, lw=0.5, color="k"))
    ax.plot([-math.sin(THETA_I)], [0.0], "k+", ms=4, mew=0.6)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_frame_on(False)
    if title:
        ax.set_title(title, fontsize=7, pad=2)


def figure_isotropic(plt, path, n=61):
    wo, inside = disk_grid(n)
    wi = incident().expand_as(wo)
    P = 3
    B = torch_hsh.helmholtz_isotropic(wi, wo, P).numpy()
    idx = torch_hsh.isotropic_indices(P).tolist()
    cols = [(r, q) for r in range(P + 1) for q in range(r + 1)]  # r across, q across within r
    fig, axes = plt.subplots(P + 1, len(cols), figsize=(1.25 * len(cols), 1.35 * (P + 1)))
    for ax in axes.ravel():
        ax.axis("off")
    for k, (p, r, q) in enumerate(idx):
        ax = axes[p, cols.index((r, q))]
        ax.axis("on")
        _draw(ax, B[:, k].reshape(n, n), inside, f"p={p} r={r} q={q}")
    fig.suptitle("Isotropic Helmholtz basis up to order 3 at wi = (pi/3, 0): p down, r across, q across within r",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def figure_anisotropic(plt, path, n=41):
    wo, inside = disk_grid(n)
    wi = incident().expand_as(wo)
    P = 3
    B = torch_hsh.helmholtz_anisotropic(wi, wo, P).numpy()
    idx = torch_hsh.anisotropic_indices(P).tolist()  # rows (p, q, r, s), j-major pairs j <= k
    L = (P + 1) ** 2
    names = [(p, q) for p in range(P + 1) for q in range(-p, p + 1)]
    fig, axes = plt.subplots(L, L, figsize=(0.72 * L, 0.72 * L))
    for ax in axes.ravel():
        ax.axis("off")
    for c, (p, q, r, s) in enumerate(idx):
        j, k = names.index((p, q)), names.index((r, s))
        ax = axes[j, k]
        ax.axis("on")
        _draw(ax, B[:, c].reshape(n, n), inside)
    for j, (p, q) in enumerate(names):
        axes[j, j].set_ylabel(f"({p},{q})", fontsize=6)
        axes[j, j].yaxis.set_label_position("left")
        axes[0, j].set_title(f"({p},{q})", fontsize=6, pad=2)
    fig.suptitle("General Helmholtz basis H_jk up to order 3 at wi = (pi/3, 0): row j = (p, q), column k = (r, s), "
                 "j <= k", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97), h_pad=0.1, w_pad=0.1)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    args = p.parse_args(argv)
    C.set_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = [args.images / "paper_fig1_isotropic.png", args.images / "paper_fig1_anisotropic.png"]
    C.prepare_outputs(files, args.overwrite)
    figure_isotropic(plt, files[0])
    figure_anisotropic(plt, files[1])
    print("wrote", ", ".join(str(f) for f in files))


if __name__ == "__main__":
    main()
