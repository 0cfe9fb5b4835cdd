"""Shared helpers of the paper-reproduction scripts (output handling, material library, projections).

Not part of the library API. Every script writes a fixed list of files into
``--images`` (figures, default ``results/paper/images``) and ``--tables`` (tables,
default ``results/paper/tables``), both under the repository root, and refuses to
overwrite any of *its own* files unless ``--overwrite`` is given; it never touches
other files. No script writes into ``docs/`` unless asked: the committed figures and
tables are regenerated on purpose with ``--images docs/images --tables docs/tables
--overwrite``.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import List, Sequence, Tuple

import torch

ROOT = Path(__file__).resolve().parents[2]
#: Default output folder of the paper scripts (ignored by git); never ``docs/`` unless asked.
OUT = ROOT / "results" / "paper"
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

import torch_hsh  # noqa: E402
from torch_hsh.bases import get_basis  # noqa: E402
from torch_hsh.bases.hbasis import h_basis  # noqa: E402
from torch_hsh.bases.westin import pair_table, real_sh  # noqa: E402
from torch_hsh.quadrature import direction_quadrature, isotropic_directions, isotropic_quadrature  # noqa: E402

#: Isotropic bases compared in paper Figs. 5-6 (ours first).
ISO_BASES = ["helmholtz_isotropic", "koenderink_helmholtz", "koenderink_zernike_product", "gautron_hsh_isotropic",
             "westin_sh_isotropic", "hbasis_isotropic"]
#: Anisotropic bases compared in paper Fig. 7.
ANISO_BASES = ["helmholtz_anisotropic", "gautron_hsh", "westin_sh", "hbasis"]
LABEL = {
    "helmholtz_isotropic": "Helmholtz HSH (ours)",
    "helmholtz_anisotropic": "Helmholtz HSH (ours)",
    "koenderink_zernike": "Koenderink-van Doorn Zernike",
    "koenderink_helmholtz": "KvD Helmholtz (Zernike, reciprocal)",
    "koenderink_zernike_product": "KvD Zernike product (non-reciprocal)",
    "gautron_hsh_isotropic": "Gautron HSH product",
    "gautron_hsh": "Gautron HSH product",
    "westin_sh_isotropic": "Westin SH (sphere)",
    "westin_sh": "Westin SH (sphere)",
    "hbasis_isotropic": "Habel-Wimmer H-basis",
    "hbasis": "Habel-Wimmer H-basis",
}


def base_parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--images", type=Path, default=OUT / "images",
                   help="output folder for figures (default: results/paper/images; docs/images to regenerate "
                        "the committed figures)")
    p.add_argument("--tables", type=Path, default=OUT / "tables",
                   help="output folder for tables (default: results/paper/tables; docs/tables to regenerate "
                        "the committed tables)")
    p.add_argument("--overwrite", action="store_true", help="replace this script's existing output files")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    return p


def prepare_outputs(files: Sequence[Path], overwrite: bool) -> None:
    """Create parent folders; refuse (exit 2) if any of this script's files exists without ``--overwrite``."""
    existing = [str(f) for f in files if f.exists()]
    if existing and not overwrite:
        sys.stderr.write("refusing to overwrite existing output (pass --overwrite):\n  " + "\n  ".join(existing) + "\n")
        raise SystemExit(2)
    for f in files:
        f.parent.mkdir(parents=True, exist_ok=True)


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    with open(path, "w") as fh:
        fh.write(",".join(header) + "\n")
        for r in rows:
            fh.write(",".join(_fmt(v) for v in r) + "\n")


def write_md(path: Path, title: str, header: Sequence[str], rows: Sequence[Sequence], notes: str = "") -> None:
    with open(path, "w") as fh:
        fh.write(f"# {title}\n\n")
        if notes:
            fh.write(notes.strip() + "\n\n")
        fh.write("| " + " | ".join(header) + " |\n")
        fh.write("|" + "|".join("---" for _ in header) + "|\n")
        for r in rows:
            fh.write("| " + " | ".join(_fmt(v) for v in r) + " |\n")


def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "n/a"
        return f"{v:.6g}"
    return str(v)


# --------------------------------------------------------------------------- materials
def material_library() -> List[Tuple[str, object, bool]]:
    """``(name, model, isotropic)`` for 31 analytic materials from diffuse to sharp specular.

    Parameters are illustrative (chosen to span the range), not fitted to data.
    """
    from torch_hsh.brdf import BlinnPhong, CookTorranceGGX, Lambertian, OrenNayar, WardAnisotropic

    L: List[Tuple[str, object, bool]] = []
    L.append(("lambert_0.8", Lambertian(0.8), True))
    L.append(("lambert_0.3", Lambertian(0.3), True))
    for a, s in ((0.7, 0.2), (0.5, 0.35), (0.7, 0.5)):
        L.append((f"oren_nayar_s{s}", OrenNayar(a, s), True))
    for kd, ks, n in ((0.7, 0.2, 3), (0.5, 0.5, 5), (0.5, 0.3, 10), (0.3, 0.5, 20), (0.4, 0.4, 40),
                      (0.2, 0.6, 50), (0.1, 0.6, 70), (0.05, 0.8, 100)):
        L.append((f"blinn_phong_n{n}", BlinnPhong(kd, ks, float(n)), True))
    for alb, spec, r, f0 in ((0.7, 1.0, 0.6, 0.04), (0.5, 1.0, 0.8, 0.04), (0.5, 1.0, 0.5, 0.04), (0.5, 1.0, 0.45, 0.04),
                             (0.4, 1.0, 0.4, 0.04), (0.3, 1.0, 0.35, 0.04), (0.3, 1.0, 0.3, 0.04),
                             (0.0, 1.0, 0.5, 0.9), (0.0, 1.0, 0.4, 0.9), (0.2, 1.0, 0.3, 0.9)):
        L.append((f"ggx_r{r}_f{f0}", CookTorranceGGX(alb, spec, r, f0), True))
    for rd, rs, a in ((0.3, 0.3, 0.25), (0.2, 0.4, 0.15)):
        L.append((f"ward_iso_a{a}", WardAnisotropic(rd, rs, a, a), True))
    for rd, rs, ax, ay in ((0.3, 0.3, 0.15, 0.3), (0.2, 0.4, 0.15, 0.4), (0.3, 0.3, 0.2, 0.5), (0.4, 0.2, 0.2, 0.6),
                           (0.2, 0.5, 0.12, 0.25), (0.3, 0.3, 0.3, 0.6)):
        L.append((f"ward_aniso_{ax}x{ay}", WardAnisotropic(rd, rs, ax, ay), False))
    return L


#: Materials whose squared BRDF is integrable over the hemisphere pair. Microfacet models
#: (GGX with height-correlated Smith G, normalised Ward) and Oren-Nayar grow like 1/cos near
#: grazing, so the integral of f^2 diverges (logarithmically or worse) and Acc(P) of the raw
#: BRDF depends on the quadrature; their raw-BRDF numbers are reported but flagged.
FINITE_ENERGY_PREFIXES = ("lambert", "blinn_phong")


def finite_energy(name: str) -> bool:
    return name.startswith(FINITE_ENERGY_PREFIXES)


def cosine_weighted(f):
    """``f(wi, wo) cos(theta_i) cos(theta_o)``: reciprocal and bounded for every model here."""

    def g(wi, wo):
        return f(wi, wo) * wi[..., 2].clamp(min=0) * wo[..., 2].clamp(min=0)

    return g


def as_scalar_brdf(model):
    """``model(wi, wo) -> (M, 1)`` to ``(M,)``."""

    def f(wi, wo):
        v = model(wi, wo)
        return v[..., 0] if v.dim() == wi.dim() else v

    return f


# --------------------------------------------------------------------------- projections
def reduced_rule(n_theta: int, n_phi: int, dtype=torch.float64):
    """Reduced 3-D isotropic rule as directions: ``wi, wo (M, 3), w (M,)``."""
    ci, co, dp, w = isotropic_quadrature(n_theta, n_phi, dtype=dtype)
    wi, wo = isotropic_directions(ci, co, dp)
    return wi, wo, w


def rotate_z(d: torch.Tensor, a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)


def azimuthal_average(f, wi, wo, n_rot: int = 24) -> torch.Tensor:
    """``(1/2pi) int f(R_a wi, R_a wo) da`` by the uniform rule (what an isotropic basis sees)."""
    acc = torch.zeros(wi.shape[0], dtype=wi.dtype)
    for k in range(n_rot):
        a = 2 * math.pi * k / n_rot
        acc += f(rotate_z(wi, a), rotate_z(wo, a))
    return acc / n_rot


def project_values(basis_name: str, order: int, wi, wo, w, F: torch.Tensor, chunk: int = 20000) -> torch.Tensor:
    """Coefficients ``(n_materials, K)`` of many BRDFs tabulated on one rule: ``F`` is ``(M, n_materials)``.

    The same sum as :func:`torch_hsh.fitting.project` (``sum_k w_k f B``), but each
    basis is evaluated once for all materials.
    """
    b = get_basis(basis_name)
    P = b.check_order(order)
    acc = torch.zeros(F.shape[1], b.num_functions(P), dtype=F.dtype)
    for s in range(0, wi.shape[0], chunk):
        B = b.evaluate(wi[s : s + chunk], wo[s : s + chunk], P)
        acc += (F[s : s + chunk] * w[s : s + chunk, None]).T @ B
    return acc


def accuracy_from_coefficients(basis_name: str, coefficients: torch.Tensor, energy: torch.Tensor) -> torch.Tensor:
    """Acc(P') for P' = 0..P, ``(n_materials, P+1)`` via :func:`torch_hsh.fitting.energy_accuracy`."""
    from torch_hsh.fitting import energy_accuracy

    return energy_accuracy(coefficients, energy, basis=basis_name)


def per_direction_table(kind: str, d: torch.Tensor, order: int) -> Tuple[torch.Tensor, Tuple[int, ...]]:
    """Per-direction functions and their order labels: ``hsh`` | ``sh`` | ``h``."""
    if kind == "hsh":
        H = torch_hsh.hsh(d, order)
        return H, tuple(int(math.isqrt(k)) for k in range(H.shape[-1]))
    if kind == "sh":
        H = real_sh(d, order)
        return H, tuple(int(math.isqrt(k)) for k in range(H.shape[-1]))
    if kind == "h":
        H = h_basis(d, order)
        return H, (0, 1, 1, 1, 2, 2)[: H.shape[-1]]
    raise ValueError(kind)


ANISO_KIND = {"helmholtz_anisotropic": ("hsh", True), "gautron_hsh": ("hsh", False), "westin_sh": ("sh", True),
              "hbasis": ("h", True)}


def separable_coefficients(basis_name: str, order: int, d: torch.Tensor, wd: torch.Tensor, Fmat: torch.Tensor):
    """Coefficients of product bases from ``C = H^T diag(w) F diag(w) H`` (``Fmat`` is ``(N, N)`` on a direction rule).

    Returns the coefficients in the **label order of** :func:`pair_table` (``(K,)``)
    and the matching labels. For symmetrised bases ``a_jk = N (C_jk + C_kj)``.
    """
    kind, sym = ANISO_KIND[basis_name]
    H, labels = per_direction_table(kind, d, order)
    Hw = H * wd[:, None]
    C = Hw.T @ Fmat @ Hw
    j, k, c, lab = pair_table(labels, order, sym)
    j, k = torch.tensor(j), torch.tensor(k)
    if sym:
        a = torch.tensor(c, dtype=C.dtype) * (C[j, k] + C[k, j])
    else:
        a = C[j, k]
    return a, torch.tensor(lab)


def check_against_fitting(basis_name: str, model, order: int = 2, n_theta: int = 8, n_phi: int = 12) -> float:
    """Max abs difference between :func:`separable_coefficients` and :func:`torch_hsh.fitting.project` (same rule)."""
    from torch_hsh.fitting import project

    f = as_scalar_brdf(model)
    ref = project(f, order, basis=basis_name, n_theta=n_theta, n_phi=n_phi, reduced=False)
    d, wd = direction_quadrature(n_theta, n_phi, dtype=torch.float64)
    Fm = f(d[:, None, :].expand(-1, d.shape[0], 3).reshape(-1, 3), d[None].expand(d.shape[0], -1, 3).reshape(-1, 3))
    a, _ = separable_coefficients(basis_name, order, d, wd, Fm.reshape(d.shape[0], d.shape[0]))
    kind, sym = ANISO_KIND[basis_name]
    _, labels = per_direction_table(kind, d[:1], order)
    j, k, _, _ = pair_table(labels, order, sym)
    mine = dict(zip(zip(j, k), a.tolist()))
    if basis_name == "helmholtz_anisotropic":  # registered columns are j-major pairs j <= k
        K = len(labels)
        cols = [(jj, kk) for jj in range(K) for kk in range(jj, K)]
    else:  # the other product bases use pair_table's order
        cols = list(zip(j, k))
    return max(abs(mine[c] - float(v)) for c, v in zip(cols, ref.tolist()))


def set_threads(n):
    if n:
        torch.set_num_threads(int(n))
    os.environ.setdefault("MPLBACKEND", "Agg")


#: Distinct marker / line style per basis (readable in print and where curves coincide).
STYLE = {
    "helmholtz_isotropic": dict(color="k", marker="o", ls="-", lw=2.2, ms=7, mfc="none"),
    "helmholtz_anisotropic": dict(color="k", marker="o", ls="-", lw=2.2, ms=7, mfc="none"),
    "gautron_hsh_isotropic": dict(color="tab:orange", marker="x", ls="--", lw=1.4, ms=7),
    "gautron_hsh": dict(color="tab:orange", marker="x", ls="--", lw=1.4, ms=7),
    "koenderink_helmholtz": dict(color="tab:blue", marker="s", ls="-.", lw=1.4, ms=5),
    "koenderink_zernike_product": dict(color="tab:cyan", marker="+", ls=":", lw=1.8, ms=9),
    "westin_sh_isotropic": dict(color="tab:green", marker="^", ls="-", lw=1.2, ms=5),
    "westin_sh": dict(color="tab:green", marker="^", ls="-", lw=1.2, ms=5),
    "hbasis_isotropic": dict(color="tab:red", marker="D", ls="-", lw=1.2, ms=5),
    "hbasis": dict(color="tab:red", marker="D", ls="-", lw=1.2, ms=5),
}
