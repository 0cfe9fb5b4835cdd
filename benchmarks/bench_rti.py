"""RTI numbers for docs/rti.md: sphere light estimation, HSH RTI projection error, held-out relighting.

Part 1 renders a glossy black sphere (Blinn-Phong, shininess 400, k_d 0.05) under lights up to
75 deg from the view and measures the angular error of :func:`torch_hsh.rti.sphere_light_directions`
clean, as 8-bit sRGB photographs, with Gaussian noise and with clipped highlights.

Part 2 takes the demo scene (bumpy sphere, GGX / Blinn-Phong, cast shadows), writes its training
images as an 8-bit sRGB RTI capture (as a camera would), reads it back (sRGB removed), solves
photometric stereo, and compares on held-out lights, against the sRGB images a camera would record:
the full model, its 9/16-term HSH RTI projection (:func:`torch_hsh.rti.project_to_rti`), and the
plain RTI fit of the photographs (:func:`torch_hsh.rti.fit_rti`). Errors are RMS in 8-bit codes.

Run: ``OMP_NUM_THREADS=2 python benchmarks/bench_rti.py [--size 96] [--lights 64] [--holdout 16]``
(about a minute at the defaults on 2 cores). ``--quick`` (the CI run, ``tests/test_bench_rti_quick.py``):
a 64 x 64 sphere under 16 lights, and the demo scene at 32 x 32 with 24 lights (16 training, 8
held out), on one thread, a few seconds. Every measurement prints its line as soon as it is made.
"""
from __future__ import annotations

import argparse
import functools
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torch_hsh import ps

from torch_hsh.render import scenes
from torch_hsh.brdf import BlinnPhong
from torch_hsh.rti.io import load_rti, save_rti, srgb_encode
from torch_hsh.render import render
from torch_hsh.rti import evaluate_rti, fit_rti, project_to_rti, sphere_light_directions

print = functools.partial(print, flush=True)  # a line per measurement as it is made, also into a pipe


def srgb(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def part_lights(size: int = 128, n: int = 48) -> None:
    nrm, m = scenes.sphere_normals(size, radius=0.8, dtype=torch.float64)
    li = scenes.cone_lights(n, max_angle_deg=75.0, seed=1, dtype=torch.float64)
    one = torch.ones(size, size, 1, dtype=torch.float64)
    img = render(nrm, li, BlinnPhong(0.05 * one.expand(-1, -1, 3), one, 400 * one)) * m[None, ..., None]
    img = img / img.max()
    g = torch.Generator().manual_seed(0)

    def err(x, **kw):
        e = sphere_light_directions(x, **kw)
        c = (torch.as_tensor(e.lights) * li).sum(-1).clamp(-1, 1)
        d = torch.rad2deg(torch.arccos(c))
        return float(d.mean()), float(d.max())

    rows = [("clean (float)", img)]
    rows.append(("8-bit sRGB", torch.as_tensor(np.rint(srgb_encode(img.numpy()) * 255) / 255)))
    for s in (0.01, 0.03, 0.05):
        rows.append((f"noise {s:.0%} of peak", img + s * torch.randn(img.shape, generator=g, dtype=img.dtype)))
    for c in (0.2, 0.05, 0.01):
        rows.append((f"clipped at {c:.0%} of peak", img.clamp(max=c)))
    circle = (size / 2 - 0.5, size / 2 - 0.5, 0.8 * size / 2)
    print(f"\n### Light directions from a {size}x{size} sphere (r = {circle[2]:.1f} px), {n} lights up to 75 deg\n")
    print("| images | mean / max error, mask (deg) | mean / max error, exact circle (deg) |")
    print("|---|---|---|")
    for name, x in rows:
        a = err(x, mask=m)
        b = err(x, circle=circle)
        print(f"| {name} | {a[0]:.2f} / {a[1]:.2f} | {b[0]:.2f} / {b[1]:.2f} |")


def _strip(panels, gap: int = 3) -> np.ndarray:
    """Panels (H, W, 3) in [0, 1] side by side with white gaps, as 8-bit codes."""
    h = max(p.shape[0] for p in panels)
    out = []
    for i, p in enumerate(panels):
        if i:
            out.append(np.ones((h, gap, 3)))
        out.append(np.pad(p, ((0, h - p.shape[0]), (0, 0), (0, 0)), constant_values=1.0))
    return np.rint(np.clip(np.concatenate(out, axis=1), 0, 1) * 255).astype(np.uint8)


def part_export(size: int, n_lights: int, holdout: int, figures=None) -> None:
    print(f"\n### Held-out relighting, demo scene {size}x{size}, {n_lights - holdout} training / {holdout} held-out "
          f"lights (RMS in 8-bit sRGB codes)\n")
    d = scenes.demo_scene(size, n_lights=n_lights, seed=0, dtype=torch.float64)
    imgs = d["images"] / d["intensities"][:, None, None, :]  # unit-intensity lights (RTI files carry none)
    mask = d["mask"]
    perm = torch.randperm(n_lights, generator=torch.Generator().manual_seed(0))
    test, train = perm[:holdout].sort().values, perm[holdout:].sort().values
    s = 1.0 / float(imgs[train].max())
    with tempfile.TemporaryDirectory() as tmp:
        cap = save_rti(Path(tmp) / "cap", imgs[train], d["lights"][train], mask=mask, scale=s)
        data = load_rti(cap, dtype=torch.float64)  # linear, = s * images up to 8-bit quantisation
        photos = torch.as_tensor(np.stack([np.asarray(__import__("PIL.Image", fromlist=["x"]).open(
            cap / nm).convert("RGB")) for nm in data.names]), dtype=torch.float64) / 255.0
    t = time.perf_counter()
    res = ps.solve_hsh(data.images, data.lights, None, data.mask, progress=False)
    t_ps = time.perf_counter() - t
    lt = d["lights"][test]
    truth = srgb(s * imgs[test])[:, mask]  # what the camera records at the held-out lights
    full = srgb(res.relight(lt))[:, mask]

    def rms(x):
        return 255 * float((x - truth).pow(2).mean().sqrt())

    print(f"photometric stereo: {t_ps:.1f} s, mean normal error "
          f"{float(ps.angular_error(res.normals, d['normals_gt'])[mask].mean()):.2f} deg")
    print(f"\nfull HSH model (the viewer's shader): {rms(full):.2f}\n")
    cap = float(torch.rad2deg(torch.arccos(data.lights[:, 2].clamp(-1, 1))).max())
    print("| terms | fit region of the export | physical export | plain RTI fit of the photographs "
          "| export vs full model | export time (s) |")
    print("|---|---|---|---|---|---|")
    maps = {}
    for terms in (9, 16):
        plain_img = evaluate_rti(fit_rti(photos, data.lights, terms, mask=mask), lt)
        plain = plain_img[:, mask]
        for region, angle in ((f"cap of the lights ({cap:.0f} deg)", cap), ("whole hemisphere", None)):
            t = time.perf_counter()
            c = project_to_rti(res.normals, res.coefficients, terms, mask=mask, exposure=1.0, max_angle_deg=angle)
            t_proj = time.perf_counter() - t
            proj_img = evaluate_rti(c, lt)
            proj = proj_img[:, mask]
            if terms == 9 and angle is not None:
                maps["export"], maps["plain"] = proj_img, plain_img
            pf = 255 * float((proj - full).pow(2).mean().sqrt())
            print(f"| {terms} | {region} | {rms(proj):.2f} | {rms(plain):.2f} | {pf:.2f} | {t_proj:.1f} |")


    if figures is not None:
        from torch_hsh.io.diligent import _write_png

        figures = Path(figures)
        figures.mkdir(parents=True, exist_ok=True)
        m3 = mask[..., None].numpy()
        j = int(torch.argmax(torch.arccos(lt[:, 2])))  # the most oblique held-out light
        cam = srgb(s * imgs[test[j]]).numpy()
        nrm = np.where(m3, (res.normals.numpy() + 1) / 2, 1.0)
        _write_png(figures / "rti_input_normals.png", _strip([np.where(m3, cam, 1.0), nrm]))
        err = [srgb(res.relight(lt[j: j + 1]))[0], maps["export"][j], maps["plain"][j]]
        panels = [np.where(m3, e.numpy(), 1.0) for e in err]
        panels += [np.where(m3, np.repeat((8 * (e.numpy() - cam).__abs__().mean(-1, keepdims=True)), 3, -1), 1.0)
                   for e in err]
        _write_png(figures / "rti_relighting.png", _strip(panels))
        print(f"\nfigures in {figures}: held-out light {j} at "
              f"{float(torch.rad2deg(torch.arccos(lt[j, 2]))):.0f} deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=None, help="demo scene side (default 96; 32 with --quick)")
    ap.add_argument("--lights", type=int, default=None, help="demo scene lights (default 64; 24 with --quick)")
    ap.add_argument("--holdout", type=int, default=None, help="held-out lights (default 16; 8 with --quick)")
    ap.add_argument("--skip-lights", action="store_true")
    ap.add_argument("--figures", default=None, help="write rti_input_normals.png and rti_relighting.png here")
    ap.add_argument("--quick", action="store_true",
                    help="the CI run: a 64x64 sphere under 16 lights; the demo scene at 32x32 with 24 lights, "
                         "8 held out (unless given); one thread")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default 2; 1 with --quick)")
    a = ap.parse_args()
    for k, full, quick in (("size", 96, 32), ("lights", 64, 24), ("holdout", 16, 8)):
        if getattr(a, k) is None:
            setattr(a, k, quick if a.quick else full)
    # one thread in CI: two OpenMP threads on two cores shared with other jobs made the quick
    # solve 30x slower (26 s instead of 1 s)
    torch.set_num_threads(a.threads or (1 if a.quick else 2))
    if not a.skip_lights:
        part_lights(*((64, 16) if a.quick else (128, 48)))
    part_export(a.size, a.lights, a.holdout, a.figures)


if __name__ == "__main__":
    main()
