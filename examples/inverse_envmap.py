"""Inverse rendering under environment light: recover a sphere's BRDF from a few environment-lit images.

The normals are known (a unit sphere, orthographic). The lighting is known: three Poly Haven
maps, each also turned by 120 and 240 degrees about the up axis, giving 9 lighting conditions.
The images are rendered from an analytic material by the brute-force reference
(:func:`torch_hsh.render.envmap.render_envmap_reference`); the fitted models render them with
:func:`torch_hsh.render.envmap.render_envmap` at SH order ``--light-order``. After fitting, the sphere is
relit under a held-out map (``pedestrian_overpass``) and compared with the reference render of
the true material.

1. **One shared RGB Helmholtz BRDF at P = 4** (3 x 35 coefficients), true material GGX:
   * linear least squares: the render is linear in the coefficients, so one call of
     ``render_envmap`` with identity coefficients gives the design matrix;
   * a training loop: ``torch_hsh.HelmholtzBRDF`` + Adam on the image MSE.
2. **Per-pixel RGB albedo x one shared grey Helmholtz BRDF** over a textured albedo. Free
   per-pixel coefficients would be underdetermined from 9 images. The model is bilinear:
   * alternating least squares (albedo per pixel in closed form, then the shared BRDF);
   * the same model trained with Adam.

Reported: the relative RMSE of the fitted images, and of the relit held-out image, against the
reference renders.

Run: ``python examples/inverse_envmap.py [--envmaps ../shared/data/envmaps]`` (about 7 minutes on one loaded CPU core;
most of it is the reference renders of the ground truth).

``--synthetic`` replaces the four Poly Haven maps by built-in procedural skies (a sky gradient, a
ground and a coloured sun, at four sun positions; 32 x 64 texels), so that the script runs without
the data folder. ``--quick`` (the CI smoke run, a few seconds) is ``--synthetic`` with a 12 x 12
sphere, lighting order 8 and 150 Adam steps. ``--json PATH`` also writes the reported errors to a
JSON file.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch_hsh  # noqa: E402
from torch_hsh.brdf import CookTorranceGGX  # noqa: E402
from torch_hsh.render.envmap import EnvironmentMap, render_envmap, render_envmap_reference  # noqa: E402

TRAIN = ["venice_sunset_1k.exr", "overcast_soil_puresky_1k.exr", "royal_esplanade_1k.exr"]
HELD_OUT = "pedestrian_overpass_1k.exr"
DT = torch.float64


#: ``--quick``: settings of the CI smoke run (with the built-in maps).
QUICK = dict(size=12, light_order=8, steps=150)
#: Built-in maps: (sun direction (world, y up), sun RGB, sky RGB, ground RGB); the last one is held out.
SYNTHETIC = [
    ((0.5, 0.6, 0.62), (30.0, 24.0, 16.0), (0.30, 0.45, 0.80), (0.25, 0.20, 0.15)),
    ((-0.7, 0.3, 0.65), (40.0, 20.0, 8.0), (0.50, 0.40, 0.45), (0.20, 0.18, 0.15)),
    ((0.0, 0.9, 0.44), (20.0, 20.0, 22.0), (0.40, 0.50, 0.70), (0.30, 0.30, 0.28)),
    ((-0.3, 0.5, -0.8), (25.0, 22.0, 18.0), (0.35, 0.45, 0.75), (0.22, 0.22, 0.20)),
]


def synthetic_map(sun, sun_rgb, sky_rgb, ground_rgb, height: int = 32) -> EnvironmentMap:
    """A procedural sky (:func:`torch_hsh.render.envmap.procedural_sky`) whose sun lobe peaks at ``0.05 * sun_rgb``."""
    from torch_hsh.render.envmap import procedural_sky

    return procedural_sky(sun, [0.05 * c for c in sun_rgb], sky_rgb, ground_rgb, height=height, dtype=DT)


def sphere(size: int):
    u = (torch.arange(size, dtype=DT) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-u, u, indexing="ij")
    r2 = x * x + y * y
    mask = r2 < 0.97  # leave out the grazing rim
    return torch.stack([x, y, torch.sqrt((1 - r2).clamp(min=0))], -1)[mask], mask


def rel_rmse(pred: torch.Tensor, true: torch.Tensor) -> float:
    return float(((pred - true) ** 2).mean().sqrt() / (true ** 2).mean().sqrt())


def design(n: torch.Tensor, lights, K: int) -> torch.Tensor:
    """X[j, p, c, k]: image j, pixel p, channel c for the unit coefficient k (the model is linear)."""
    eye = torch.eye(K, dtype=DT).reshape(K, 1, 1, K).expand(K, 1, 3, K)  # (K, 1, C, K), broadcast over pixels
    return torch.stack([render_envmap(n, eye, L).permute(1, 2, 0) for L in lights])  # (J, P, C, K)


def adam(params, loss_fn, steps: int, lr: float) -> float:
    opt = torch.optim.Adam(params, lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
    return float(loss.detach())


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--envmaps", type=Path, default=ROOT.parent / "shared" / "data" / "envmaps")
    ap.add_argument("--synthetic", action="store_true", help="built-in procedural maps instead of --envmaps")
    ap.add_argument("--quick", action="store_true",
                    help="CI smoke run: --synthetic " + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in QUICK.items()))
    ap.add_argument("--json", type=Path, default=None, help="also write the reported errors to this JSON file")
    ap.add_argument("--size", type=int, default=32, help="sphere image size in pixels")
    ap.add_argument("--order", type=int, default=4, help="BRDF order P")
    ap.add_argument("--light-order", type=int, default=12, help="SH order N of the lighting in the model")
    ap.add_argument("--ref-height", type=int, default=64, help="rows of the map used by the reference renders")
    ap.add_argument("--steps", type=int, default=300, help="Adam steps")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    if args.quick:
        args.synthetic = True
        for k, v in QUICK.items():
            setattr(args, k, v)
    if args.json is not None and not args.json.parent.is_dir():
        ap.error(f"--json {str(args.json)!r}: the folder does not exist")
    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.time()
    n, mask = sphere(args.size)
    P, N = args.order, args.light_order
    K = torch_hsh.num_isotropic(P)

    # known lighting: 3 maps x 3 turns; the held-out map
    if args.synthetic:
        maps = [synthetic_map(*m) for m in SYNTHETIC[:-1]]
        held = synthetic_map(*SYNTHETIC[-1])
    else:
        maps = [EnvironmentMap.from_exr(args.envmaps / f, dtype=DT) for f in TRAIN]
        held = EnvironmentMap.from_exr(args.envmaps / HELD_OUT, dtype=DT)
    train = [m.rotated(a) for m in maps for a in (0.0, 2 * math.pi / 3, 4 * math.pi / 3)]
    results = {"pixels": int(n.shape[0]), "lighting_conditions": len(train), "order": P, "light_order": N,
               "steps": args.steps, "maps": "synthetic" if args.synthetic else str(args.envmaps)}
    L_train = [e.sh_coefficients(N) for e in train]
    L_held = held.sh_coefficients(N)

    def reference(brdf, env):  # ground-truth renders: analytic BRDF, texel quadrature
        return render_envmap_reference(n, brdf, env.downsample(max(1, env.height // args.ref_height)))

    # ---------------------------------------------------------------- 1. shared RGB BRDF
    ggx = CookTorranceGGX(torch.tensor([0.55, 0.35, 0.2], dtype=DT), 1.0, 0.45)
    imgs = torch.stack([reference(ggx, e) for e in train])  # (J, P, C)
    truth_held = reference(ggx, held)
    print(f"[1] shared RGB BRDF, P = {P} ({K} coefficients per channel), {len(train)} lighting conditions, "
          f"{n.shape[0]} pixels; references in {time.time() - t0:.0f} s")

    X = design(n, L_train, K)  # (J, P, C, K)
    a_ls = torch.stack([torch.linalg.lstsq(X[:, :, c].reshape(-1, K), imgs[..., c].reshape(-1, 1)).solution[:, 0]
                        for c in range(3)])  # (C, K)
    fit = torch.einsum("jpck,ck->jpc", X, a_ls)
    relit = render_envmap(n, a_ls, L_held)
    results["shared_lstsq"] = {"fit": rel_rmse(fit, imgs), "relit": rel_rmse(relit, truth_held)}
    print(f"  least squares: fit {rel_rmse(fit, imgs):.4f}, relit held-out {rel_rmse(relit, truth_held):.4f} (relative RMSE)")

    brdf = torch_hsh.HelmholtzBRDF(order=P, channels=3, dtype=DT)
    scale = float(imgs.pow(2).mean())

    def loss1():
        pred = torch.stack([render_envmap(n, brdf.coefficients, L) for L in L_train])
        return ((pred - imgs) ** 2).mean() / scale

    t = time.time()
    adam(brdf.parameters(), loss1, args.steps, lr=0.05)
    with torch.no_grad():
        fit = torch.stack([render_envmap(n, brdf.coefficients, L) for L in L_train])
        relit = render_envmap(n, brdf.coefficients, L_held)
    results["shared_adam"] = {"fit": rel_rmse(fit, imgs), "relit": rel_rmse(relit, truth_held)}
    print(f"  Adam ({args.steps} steps, {time.time() - t:.0f} s): fit {rel_rmse(fit, imgs):.4f}, "
          f"relit held-out {rel_rmse(relit, truth_held):.4f}")

    # ---------------------------------------------------------------- 2. textured albedo x shared BRDF
    g = CookTorranceGGX(0.8, 1.0, 0.45)  # grey material, tinted per pixel by the albedo
    u = n[:, 0] * 6
    v = n[:, 1] * 6
    stripes = (torch.floor(u) + torch.floor(v)) % 2
    albedo = torch.stack([0.3 + 0.6 * stripes, 0.5 + 0.3 * torch.sin(3 * n[:, 1]), 0.8 - 0.5 * stripes], -1)  # (P, 3)

    def textured(wi, wo):
        return g(wi, wo) * albedo  # (T, P, 1) x (P, 3)

    imgs2 = torch.stack([reference(textured, e) for e in train])
    truth2 = reference(textured, held)
    print(f"\n[2] per-pixel RGB albedo x shared grey BRDF (P = {P}), textured albedo")

    Xg = design(n, L_train, K)  # grey BRDF: same design, the channels differ only by the lighting
    b = torch.zeros(K, dtype=DT)
    b[0] = 1.0
    for _ in range(30):  # alternating least squares
        S = torch.einsum("jpck,k->jpc", Xg, b)  # shading of the shared BRDF
        alb = (S * imgs2).sum(0) / (S * S).sum(0).clamp(min=1e-30)  # (P, C) closed form
        A = (Xg * alb[None, :, :, None]).reshape(-1, K)
        b = torch.linalg.lstsq(A, imgs2.reshape(-1, 1)).solution[:, 0]
    s0 = float(b[0])
    b, alb = b / s0, alb * s0  # fix the scale ambiguity (albedo x BRDF): b_000 = 1
    fit = torch.einsum("jpck,k,pc->jpc", Xg, b, alb)
    relit = render_envmap(n, (alb.unsqueeze(-1) * b), L_held)
    results["textured_als"] = {"fit": rel_rmse(fit, imgs2), "relit": rel_rmse(relit, truth2)}
    print(f"  alternating least squares: fit {rel_rmse(fit, imgs2):.4f}, relit held-out {rel_rmse(relit, truth2):.4f}")

    grey = torch_hsh.HelmholtzBRDF(order=P, channels=1, dtype=DT, albedo=1.0)
    log_alb = torch.zeros(n.shape[0], 3, dtype=DT, requires_grad=True)
    scale2 = float(imgs2.pow(2).mean())

    def coefficients():
        return log_alb.exp().unsqueeze(-1) * grey.coefficients  # (P, C, K): albedo x shared BRDF

    def loss2():
        a = coefficients()
        pred = torch.stack([render_envmap(n, a, L) for L in L_train])
        return ((pred - imgs2) ** 2).mean() / scale2

    t = time.time()
    adam([log_alb, *grey.parameters()], loss2, args.steps, lr=0.03)
    with torch.no_grad():
        a = coefficients()
        fit = torch.stack([render_envmap(n, a, L) for L in L_train])
        relit = render_envmap(n, a, L_held)
    results["textured_adam"] = {"fit": rel_rmse(fit, imgs2), "relit": rel_rmse(relit, truth2)}
    print(f"  Adam ({args.steps} steps, {time.time() - t:.0f} s): fit {rel_rmse(fit, imgs2):.4f}, "
          f"relit held-out {rel_rmse(relit, truth2):.4f}")
    results["total_s"] = time.time() - t0
    print(f"\ntotal {results['total_s']:.0f} s")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
