"""Benchmark ``materials="auto"`` of the HSH solver: its choice, its criterion, its cost against ``materials=2``.

Usage:
    python research/materials_auto.py                      # small synthetic scenes, 1 seed
    python research/materials_auto.py --fixed --seeds 3    # also every fixed M in 1..4 (acceptance rule)
    python research/materials_auto.py --data ../shared/data/diligent_cat --max-pixels 4000 --fixed

Scenes (random normals in a cone, DiLiGenT-like cone of lights, read noise 1e-3 of the maximum):

* ``lambert``: one material, Lambertian, textured RGB albedo (exactly ``M = 1``);
* ``phong``: one material, Blinn-Phong (``ks = 0.4``, shininess 8) times a textured RGB albedo;
* ``2mat`` / ``3mat``: Lambertian / Blinn-Phong / GGX shapes with distinct tints over a textured albedo;
* ``dichromatic``: Blinn-Phong with a coloured textured diffuse and a white specular (``M = 2`` structure).

Cost: ``select`` is the wall time of the selection stage over the wall time of the ``materials=2`` solve;
``ratio`` is the CPU time of the process (``time.process_time``) on ``--threads`` threads (default 1), so that the
ratio auto / ``materials=2`` does not depend on the load of the machine; both solves run in the same
process, back to back. With ``--fixed`` it also prints the mean angular error of every fixed ``M`` and
whether auto is within 0.3 deg of the best of them (averaged over the seeds: the rule of issue 8).
Every scene and seed prints its line as soon as it is solved (``flush``). ``--quick`` (the CI smoke run):
``--scenes lambert,2mat --pixels 200 --lights 30 --fixed``.
"""
from __future__ import annotations

import argparse
import time

import torch

DT = torch.float64
SCENES = ("lambert", "phong", "2mat", "3mat", "dichromatic")


def synthetic(kind: str, p: int, l: int, seed: int, noise: float = 1e-3):
    from torch_hsh.brdf import BlinnPhong, CookTorranceGGX, Lambertian
    from torch_hsh.render import render

    g = torch.Generator().manual_seed(seed)
    n = torch.randn(p, 3, generator=g, dtype=DT) * torch.tensor([0.45, 0.45, 0.2], dtype=DT)
    n[:, 2] += 1.0
    n = torch.nn.functional.normalize(n, dim=-1)
    d = torch.randn(l, 3, generator=g, dtype=DT) * torch.tensor([0.45, 0.45, 0.1], dtype=DT)
    d[:, 2] += 1.0
    d = torch.nn.functional.normalize(d, dim=-1)
    one = torch.ones(p, 1, dtype=DT)
    albedo = 0.2 + 0.6 * torch.rand(p, 3, generator=g, dtype=DT)
    shapes = [
        Lambertian(one),
        BlinnPhong(albedo=one, specular=0.4 * one, shininess=8.0 * one),
        CookTorranceGGX(albedo=0.3 * one, specular=one, roughness=0.5 * one, f0=0.9),
    ]
    tint = torch.tensor([[1.0, 0.8, 0.6], [0.5, 0.7, 1.0], [0.9, 0.4, 0.9]], dtype=DT)
    if kind == "dichromatic":
        img = render(n, d, BlinnPhong(albedo=albedo, specular=0.4 * one, shininess=8.0 * one))
    else:
        used = {"lambert": [0], "phong": [1], "2mat": [0, 1], "3mat": [0, 1, 2]}[kind]
        label = torch.arange(p) % len(used)
        img = torch.zeros(l, p, 3, dtype=DT)
        for k, s in enumerate(used):
            r = render(n, d, shapes[s])[..., :1] * albedo * tint[s]
            img = torch.where((label == k)[None, :, None], r, img)
    img = img + noise * float(img.max()) * torch.randn(img.shape, generator=g, dtype=DT)
    return dict(images=img.clamp(min=0), lights=d, intensities=None, mask=None, normals=n)


def diligent(path: str, max_pixels: int):
    from torch_hsh.io.diligent import load_diligent

    d = load_diligent(path, dtype=torch.float32, normalize_intensities=True)
    mask = d.mask
    if max_pixels:
        idx = mask.reshape(-1).nonzero().squeeze(1)
        keep = idx[torch.randperm(idx.numel(), generator=torch.Generator().manual_seed(0))[:max_pixels]]
        mask = torch.zeros(mask.numel(), dtype=torch.bool)
        mask[keep] = True
        mask = mask.reshape(d.mask.shape)
    return dict(images=d.images, lights=d.lights, intensities=None, mask=mask, normals=d.normals_gt)


def solve(data, materials, seed):
    from torch_hsh import ps

    c0, w0 = time.process_time(), time.perf_counter()
    r = ps.solve_hsh(data["images"], data["lights"], data["intensities"], data["mask"], materials=materials, seed=seed)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    err = float("nan")
    if data["normals"] is not None:
        e = ps.angular_error(r.normals, data["normals"].to(r.normals))
        err = float(e[r.mask].mean()) if e.dim() > 1 else float(e.mean())
    return r, err, cpu, wall


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated subset of {SCENES}")
    ap.add_argument("--pixels", type=int, default=400)
    ap.add_argument("--lights", type=int, default=40)
    ap.add_argument("--seeds", type=int, default=1, help="seeds 0..N-1 (scene and calibration subset)")
    ap.add_argument("--fixed", action="store_true", help="also solve every fixed M in 1..4")
    ap.add_argument("--data", nargs="*", default=[], help="DiLiGenT-layout folders (replace the synthetic scenes)")
    ap.add_argument("--max-pixels", type=int, default=4000, help="random pixels of each --data object (0: all)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quick", action="store_true",
                    help="CI smoke run: --scenes lambert,2mat --pixels 200 --lights 30 --fixed")
    args = ap.parse_args(argv)
    if args.quick:
        args.scenes, args.pixels, args.lights, args.fixed = "lambert,2mat", 200, 30, True
    unknown = set(args.scenes.split(",")) - set(SCENES)
    if unknown and not args.data:
        ap.error(f"--scenes: unknown {', '.join(sorted(unknown))}; choose from {', '.join(SCENES)}")
    torch.set_num_threads(args.threads)

    cases = [(p, None) for p in args.data] or [(s, None) for s in args.scenes.split(",")]
    ratios = []
    print(f"{'scene':12s} {'seed':>4s} {'auto M':>6s}  criterion M=1..4 (held-out Cauchy loss / obs)  "
          f"{'cpu auto':>8s} {'cpu M=2':>7s} {'ratio':>5s} {'select':>6s}"
          + ("  err M=1..4 / auto (deg)" if args.fixed else ""))
    for name, _ in cases:
        errs_auto, errs_fixed = [], []
        for seed in range(args.seeds):
            data = diligent(name, args.max_pixels) if args.data else synthetic(name, args.pixels, args.lights, seed)
            r_a, e_a, c_a, _ = solve(data, "auto", seed)
            _, e_2, c_2, w_2 = solve(data, 2, seed)
            ratios.append(c_a / c_2)
            crit = " ".join(f"{v:6.3f}" for v in r_a.info["materials_criterion"])
            line = (f"{str(name)[-12:]:12s} {seed:4d} {int(r_a.info['materials_chosen']):6d}  {crit:46s}  "
                    f"{c_a:8.2f} {c_2:7.2f} {c_a / c_2:5.2f} {r_a.info['time_materials_s'] / w_2:6.2f}")
            if args.fixed:
                ef = [e_2 if M == 2 else solve(data, M, seed)[1] for M in (1, 2, 3, 4)]
                errs_fixed.append(ef)
                errs_auto.append(e_a)
                line += "  " + " ".join(f"{v:5.2f}" for v in ef) + f" / {e_a:5.2f}"
            print(line, flush=True)
        if args.fixed:
            mean_fixed = torch.tensor(errs_fixed).mean(0)
            mean_auto = sum(errs_auto) / len(errs_auto)
            best = float(mean_fixed.min())
            print(f"  {name}: mean over seeds: fixed M=1..4 " + " ".join(f"{v:.2f}" for v in mean_fixed.tolist())
                  + f", auto {mean_auto:.2f}; within 0.3 deg of the best fixed M: {mean_auto <= best + 0.3}", flush=True)
    rs = torch.tensor(ratios)
    print(f"cost ratio auto / materials=2 (CPU time): median {float(rs.median()):.2f}, max {float(rs.max()):.2f}")


if __name__ == "__main__":
    main()
