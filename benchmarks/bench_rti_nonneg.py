"""Cost of the non-negative RTI export (docs/rti.md): held-out relighting error, negative sums, time.

For a capture (the library's demo scene, or a DiLiGenT folder given by path, e.g. ``../shared/data/diligent_cat``),
some lights are held out, photometric stereo runs on the others, and the result is exported as 9-term HSH RTI
coefficients the way ``torch-hsh rti`` does (sRGB values, exposure: the 99.5th percentile of the head-on rendering
at 0.8, fit over the cap of the training lights), once plain (``--allow-negative``) and once non-negative.
Printed: the RMS in 8-bit codes against the held-out photographs (sRGB-encoded at the same exposure), the fraction
of pixels whose relit sum is negative in some colour at 0, 36, 58 and 90 deg from the view (OpenLIME's clamp,
averaged over 24 azimuths; also after writing the relight folder as JPEG and reading it back), and the time of
the constraint.

Run: ``OMP_NUM_THREADS=2 python benchmarks/bench_rti_nonneg.py [--diligent ../shared/data/diligent_cat]``.
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torch_hsh import ps
from torch_hsh.render import scenes
from torch_hsh.rti import OPENLIME_THETA_CLAMP, evaluate_rti, nonnegative_rti, project_to_rti
from torch_hsh.rti.fitting import _hemisphere_rule, rti_hsh_basis
from torch_hsh.rti.io import save_relight

print = functools.partial(print, flush=True)


def srgb(x):
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def read_relight(folder):
    from PIL import Image

    info = json.loads((folder / "info.json").read_text())
    sc, bi = np.array(info["materials"][0]["scale"]), np.array(info["materials"][0]["bias"])
    planes = [(np.asarray(Image.open(folder / f"plane_{j}.jpg").convert("RGB")) / 255.0 - bi[3 * j: 3 * j + 3])
              * sc[3 * j: 3 * j + 3] for j in range(9)]
    return torch.tensor(np.stack(planes, -1))


def negative_fractions(c, mask, angles=(0, 36, 58, 90)):
    out = []
    for a in angles:
        t = math.radians(a)
        ph = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        li = torch.tensor(np.stack([np.full(24, math.sin(t)) * np.cos(ph), np.full(24, math.sin(t)) * np.sin(ph),
                                    np.full(24, max(math.cos(t), 1e-6))], -1))
        v = evaluate_rti(c, li, OPENLIME_THETA_CLAMP)[:, mask]  # (24, P, 3)
        out.append(100 * float((v < 0).any(-1).double().mean()))
    return out


def run(name, images, lights, mask, holdout):
    L = lights.shape[0]
    perm = torch.randperm(L, generator=torch.Generator().manual_seed(0))
    test, train = perm[:holdout].sort().values, perm[holdout:].sort().values
    t = time.perf_counter()
    res = ps.solve_hsh(images[train], lights[train], None, mask, progress=False)
    print(f"\n## {name}: {int(mask.sum())} pixels, {len(train)} training / {holdout} held-out lights; "
          f"photometric stereo {time.perf_counter() - t:.0f} s")
    n, a = res.normals.double(), res.coefficients.double()
    head = res.relight(torch.tensor([[0.0, 0.0, 1.0]], dtype=n.dtype))[0][mask]
    exposure = 0.8 / float(torch.quantile(head.reshape(-1).float(), 0.995))
    cap = min(90.0, float(torch.rad2deg(torch.arccos(lights[train, 2].clamp(-1, 1))).max()))
    t = time.perf_counter()
    c0 = project_to_rti(n, a, 9, mask=mask, exposure=exposure, max_angle_deg=cap)
    t_proj = time.perf_counter() - t
    dirs, w = _hemisphere_rule(24, 48, z0=math.cos(math.radians(cap)))
    H = rti_hsh_basis(dirs, 9)
    G = (H * w[:, None]).T @ H
    flat = c0[mask]
    truth = srgb(exposure * images[test].double())[:, mask]
    lt = lights[test].double()

    def rms(c):
        return 255 * float((evaluate_rti(c, lt, OPENLIME_THETA_CLAMP)[:, mask] - truth).pow(2).mean().sqrt())

    full = 255 * float((srgb(exposure * res.relight(lt).double())[:, mask] - truth).pow(2).mean().sqrt())
    print(f"fit cap {cap:.1f} deg, exposure {exposure:.4g}; projection {t_proj:.1f} s; held-out RMS (8-bit codes) "
          f"of the full model {full:.2f}")
    print("\n| export | held-out RMS (codes) | constraint time | negative at 0 / 36 / 58 / 90 deg (% of pixels) "
          "| same, JPEG folder read back |\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for k, margin in enumerate((None, 0.0, 1 / 255, 2 / 255)):
            if margin is None:
                c1, label, tt = c0, "plain (--allow-negative)", "-"
            else:
                t = time.perf_counter()
                c1m = nonnegative_rti(flat, G, margin=margin)
                t_nn = time.perf_counter() - t
                c1 = c0.clone()
                c1[mask] = c1m
                moved = int((c1m != flat).any(-1).sum())
                label = f"non-negative, margin {255 * margin:.0f}/255"
                tt = (f"{t_nn:.2f} s, {moved} of {3 * flat.shape[0]} pixel-colours moved; "
                      f"{flat.shape[0] / t_nn:.0f} pixels/s")
            f1 = read_relight(save_relight(Path(tmp) / f"r{k}", c1))
            neg = " / ".join(f"{v:.1f}" for v in negative_fractions(c1, mask))
            negf = " / ".join(f"{v:.1f}" for v in negative_fractions(f1, mask))
            print(f"| {label} | {rms(c1):.2f} | {tt} | {neg} | {negf} |")

def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--diligent", default=None, help="a DiLiGenT folder (e.g. ../shared/data/diligent_cat)")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--holdout", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.diligent is None:
        d = scenes.demo_scene(args.size, n_lights=64, seed=0, dtype=torch.float64)
        imgs = d["images"] / d["intensities"][:, None, None, :]
        run(f"demo scene {args.size}x{args.size}", imgs / float(imgs.max()), d["lights"], d["mask"], args.holdout)
    else:
        from torch_hsh.io.diligent import load_diligent

        data = load_diligent(args.diligent, dtype=torch.float32)
        run(Path(args.diligent).name, data.images, data.lights.double(), data.mask, args.holdout)


if __name__ == "__main__":
    main()
