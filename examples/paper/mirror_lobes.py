"""Reconstruction of the ideal specular (mirror) kernel, paper Figs. 2 and 3.

The mirror kernel (paper Eq. 28) is a distribution; its spectrum in an isotropic
basis is ``a_k = int_Omega B_k(w, R w) dw`` with ``R w`` the mirror direction.

* Helmholtz HSH (ours): closed form with **erratum 2** (:func:`torch_hsh.spectra.mirror_spectrum`):
  ``a = 1`` for ``p = r, q = 0``, ``sqrt2 (-1)^q`` for ``p = r, q > 0``, 0 otherwise.
* Koenderink-van Doorn Zernike: closed form ``1`` / ``sqrt2 (-1)^l`` for ``n = m``
  (:func:`torch_hsh.bases.zernike.zernike_mirror_coefficients`, from
  ``int R_n^l R_m^l 2 rho d rho = delta_nm / (n+1)``).

Both closed forms are re-derived here by numerical projection (1-D Gauss-Legendre in
``cos(theta)``, exact for these polynomial integrands) and the script stops if they differ.

The truncated series ``f_P(wi, wo) = sum_{label <= P} a_k B_k(wi, wo)`` is drawn in the
plane of incidence (``wi`` at polar angle ``theta_i``, azimuth 0; ``wo`` sweeps from
-90 to +90 degrees, positive on the mirror side), normalised by its maximum; negative
values (ringing) are drawn dotted as ``|f_P|``.

Outputs (refuses to overwrite without ``--overwrite``): ``<images>/paper_mirror_orders.png``
(Fig. 2: theta_i = 45 deg, P = 0, 1, 2, 4, 6, 8), ``<images>/paper_mirror_angles.png``
(Fig. 3: several incidence angles at P = 8), ``<tables>/mirror_lobes.csv`` (peak
direction, half-maximum width and largest negative lobe per basis/order/angle).

Run: ``python examples/paper/mirror_lobes.py`` (a few seconds).
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

from torch_hsh.bases import get_basis  # noqa: E402
from torch_hsh.bases.zernike import zernike_mirror_coefficients  # noqa: E402
from torch_hsh.spectra import mirror_spectrum  # noqa: E402

BASES = {"helmholtz_isotropic": "Helmholtz HSH (ours)", "koenderink_zernike": "Zernike (Koenderink-van Doorn)"}


def numeric_mirror_spectrum(basis_name: str, order: int, n: int = 64) -> torch.Tensor:
    """``a_k = 2 pi int_0^1 B_k(w(z), R w(z)) dz`` (isotropic basis: the azimuth integral is 2 pi)."""
    x, wz = np.polynomial.legendre.leggauss(n)
    z, wz = 0.5 * (x + 1), 0.5 * wz
    s = np.sqrt(1 - z * z)
    w = torch.tensor(np.stack([s, 0 * s, z], -1))
    Rw = torch.tensor(np.stack([-s, 0 * s, z], -1))
    B = get_basis(basis_name).evaluate(w, Rw, order)
    return 2 * math.pi * (B * torch.tensor(wz)[:, None]).sum(0)


def closed_form(basis_name: str, order: int) -> torch.Tensor:
    if basis_name == "helmholtz_isotropic":
        return mirror_spectrum(order, basis="helmholtz_isotropic")
    return zernike_mirror_coefficients(order)


def lobe(basis_name: str, coefficients: torch.Tensor, order: int, theta_i: float, t: torch.Tensor) -> torch.Tensor:
    b = get_basis(basis_name)
    keep = b.function_orders(order) <= order
    wi = torch.tensor([[math.sin(theta_i), 0.0, math.cos(theta_i)]], dtype=torch.float64)
    # positive t on the mirror side (azimuth pi)
    wo = torch.stack([-torch.sin(t), torch.zeros_like(t), torch.cos(t)], -1)
    B = b.evaluate(wi.expand_as(wo), wo, order)[:, keep]
    return B @ coefficients[: int(keep.sum())]


def stats(t, f):
    fmax = float(f.max())
    k = int(torch.argmax(f))
    above = (f >= 0.5 * fmax).numpy()
    # contiguous half-max region around the peak
    lo = k
    while lo > 0 and above[lo - 1]:
        lo -= 1
    hi = k
    while hi < len(above) - 1 and above[hi + 1]:
        hi += 1
    return math.degrees(float(t[k])), math.degrees(float(t[hi] - t[lo])), float(f.min()) / fmax


def polar(ax, t, f, color, label, ls="-"):
    fn = f / f.max()
    pos = torch.clamp(fn, min=0)
    neg = torch.clamp(-fn, min=0)
    ax.plot(t.numpy(), pos.numpy(), ls, color=color, label=label)
    if float(neg.max()) > 1e-3:
        ax.plot(t.numpy(), neg.numpy(), ":", color=color, lw=0.8)


def setup(ax, theta_i):
    ax.set_theta_zero_location("N")
    ax.set_thetamin(-90)
    ax.set_thetamax(90)
    ax.set_ylim(0, 1.05)
    ax.set_yticklabels([])
    ax.plot([-theta_i, -theta_i], [0, 1.05], color="orange", lw=2)  # incident ray (drawn on the light side)
    ax.plot([theta_i, theta_i], [0, 1.05], "--", color="orange", lw=1.5)  # mirror direction


def main(argv=None):
    p = C.base_parser(__doc__.split("\n")[0])
    p.add_argument("--orders", type=int, nargs="+", default=[0, 1, 2, 4, 6, 8])
    p.add_argument("--angles", type=float, nargs="+", default=[15, 30, 45, 60, 75], help="incidence angles (deg)")
    p.add_argument("--order-angles", type=int, default=8)
    args = p.parse_args(argv)
    C.set_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = [args.images / "paper_mirror_orders.png", args.images / "paper_mirror_angles.png",
             args.tables / "mirror_lobes.csv"]
    C.prepare_outputs(files, args.overwrite)
    Pmax = max(max(args.orders), args.order_angles)
    coefficients = {}
    for bn in BASES:
        num = numeric_mirror_spectrum(bn, Pmax)
        cf = closed_form(bn, Pmax)
        err = float((num - cf).abs().max())
        print(f"{bn}: numerical vs closed-form mirror spectrum, max |diff| = {err:.2e}")
        if err > 1e-10:
            raise SystemExit(f"mirror spectrum mismatch for {bn}: {err}")
        coefficients[bn] = cf
    t = torch.linspace(-math.pi / 2, math.pi / 2, 721, dtype=torch.float64)
    rows = []
    th = math.radians(45.0)
    fig, axes = plt.subplots(2, len(args.orders), subplot_kw={"projection": "polar"}, figsize=(3 * len(args.orders), 4.6))
    for r, bn in enumerate(BASES):
        for c, P in enumerate(tqdm(args.orders, desc=bn)):
            f = lobe(bn, coefficients[bn], P, th, t)
            ax = axes[r, c]
            setup(ax, th)
            polar(ax, t, f, "C0" if r == 0 else "C3", BASES[bn])
            ax.set_title(f"P = {P}", fontsize=9)
            rows.append([bn, P, 45.0, *stats(t, f)])
        axes[r, 0].text(-0.35, 0.5, BASES[bn], transform=axes[r, 0].transAxes, rotation=90, va="center", fontsize=9)
    fig.suptitle("Mirror kernel, theta_i = 45 deg (solid: f_P/max, dotted: |negative part|)", fontsize=10)
    fig.tight_layout()
    fig.savefig(files[0], dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, subplot_kw={"projection": "polar"}, figsize=(10, 4.2))
    for ax, bn in zip(axes, BASES):
        ax.set_theta_zero_location("N")
        ax.set_thetamin(-90)
        ax.set_thetamax(90)
        ax.set_ylim(0, 1.05)
        ax.set_yticklabels([])
        for k, a in enumerate(args.angles):
            tha = math.radians(a)
            f = lobe(bn, coefficients[bn], args.order_angles, tha, t)
            polar(ax, t, f, f"C{k}", f"{a:g} deg")
            ax.plot([tha, tha], [0, 1.05], "--", color=f"C{k}", lw=0.8)
            rows.append([bn, args.order_angles, a, *stats(t, f)])
        ax.set_title(f"{BASES[bn]}, P = {args.order_angles}", fontsize=10)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(files[1], dpi=120)
    plt.close(fig)
    C.write_csv(files[2], ["basis", "order", "theta_i_deg", "peak_deg", "half_max_width_deg", "min_over_max"], rows)
    for r in rows:
        if r[2] == 45.0 and r[1] in (4, 8):
            print(f"  {r[0]:20s} P={r[1]} peak {r[3]:.1f} deg, FWHM {r[4]:.1f} deg, min/max {r[5]:.3f}")


if __name__ == "__main__":
    main()
