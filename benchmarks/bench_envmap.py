"""Benchmark of environment-map rendering: :func:`torch_hsh.render.envmap.render_envmap` vs the texel reference.

On ``--threads`` CPU threads (default 2), float32 unless stated:

1. **Speed.** A ``--size`` x ``--size`` normal map (default 512 x 512, a bumpy sphere
   filling the frame, every pixel shaded), an RGB Helmholtz BRDF at order P =
   ``--brdf-order`` (default 3; a GGX material projected onto the basis) and the map
   ``--envmap`` (default ``../shared/data/envmaps/venice_sunset_1k.exr``) at SH order
   N = ``--light-order`` (default 8). Times: the SH projection of the 1024 x 512 map,
   ``render_envmap`` with one shared BRDF and with per-pixel coefficient maps
   (median of ``--repeats``).
2. **Accuracy and the ratio at equal accuracy.** On ``--pixels`` normals (default 64)
   the ground truth is the reference on the full-resolution map (float64). We report the
   error of ``render_envmap`` for N = 4 .. 24 and of the reference on 2x-downsampled maps
   down to 64 x 128 texels (power-preserving downsampling), the reference's time per
   pixel on the 64 x 128 map (measured on ``--ref-pixels`` pixels, extrapolated linearly
   to the whole normal map: its cost is proportional to the number of pixels), and the
   speed ratio.

``--quick`` (CI, a few seconds): a built-in 64 x 128 map (sky, ground and a sun), a 64 x 64 normal
map, 8 accuracy pixels, 64 reference pixels, one repeat. Every measurement is printed as it is taken.

Usage::

    python benchmarks/bench_envmap.py [--threads 2] [--envmap PATH] [--size 512]
    python benchmarks/bench_envmap.py --quick
"""
from __future__ import annotations

import argparse
import functools
import math
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch_hsh  # noqa: E402
from torch_hsh.brdf import CookTorranceGGX  # noqa: E402
from torch_hsh.render.envmap import EnvironmentMap, equirect_directions, render_envmap, render_envmap_reference  # noqa: E402

print = functools.partial(print, flush=True)  # noqa: A001  (a line per measurement, as it is taken)


def builtin_map(height: int = 64) -> EnvironmentMap:
    """A synthetic map for ``--quick``: sky gradient, ground and a 6 degree sun (float32)."""
    d = equirect_directions(height, 2 * height, dtype=torch.float64)
    up = d[..., 1:2]
    sky = torch.tensor([0.4, 0.6, 1.0], dtype=torch.float64) * (0.5 + 0.5 * up.clamp(min=0))
    img = torch.where(up > 0, sky, torch.tensor([0.3, 0.25, 0.2], dtype=torch.float64).expand_as(sky))
    sun = torch.nn.functional.normalize(torch.tensor([0.3, 0.5, 0.8], dtype=torch.float64), dim=0)
    img = img + 30.0 * ((d @ sun) > math.cos(math.radians(6.0))).to(torch.float64).unsqueeze(-1)
    return EnvironmentMap(img.float())


def timeit(fn, repeats: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def bumpy_sphere_normals(size: int, dtype=torch.float32) -> torch.Tensor:
    """A sphere filling the frame plus a sinusoidal bump field; every pixel faces the camera."""
    u = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-u, u, indexing="ij")
    r2 = (x * x + y * y).clamp(max=0.95)
    n = torch.stack([x, y, torch.sqrt(1 - r2)], -1)
    n[..., 0] += 0.15 * torch.sin(23 * x) * torch.cos(17 * y)
    n[..., 1] += 0.15 * torch.cos(19 * x + 0.3) * torch.sin(29 * y)
    return torch.nn.functional.normalize(n, dim=-1).to(dtype)


def material_coefficients(order: int, quick: bool = False) -> torch.Tensor:
    """(3, K) coefficients of an RGB GGX material (albedo, roughness 0.35); ``quick``: a fixed 16 x 128 rule."""
    ggx = CookTorranceGGX(torch.tensor([0.6, 0.35, 0.2], dtype=torch.float64), 0.8, 0.35)
    rule = {"n_theta": 16, "n_phi": 128} if quick else {}
    return torch_hsh.project(lambda wi, wo: ggx(wi, wo), order, **rule)  # (C, K)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--envmap", type=Path, default=ROOT.parent / "shared" / "data" / "envmaps" / "venice_sunset_1k.exr")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--brdf-order", type=int, default=3)
    ap.add_argument("--light-order", type=int, default=8)
    ap.add_argument("--pixels", type=int, default=64, help="pixels for the accuracy study")
    ap.add_argument("--ref-pixels", type=int, default=2048, help="pixels for timing the 64x128 reference")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--speed-only", action="store_true", help="skip the accuracy study and the ratio")
    ap.add_argument("--quick", action="store_true", help="CI mode: built-in 64x128 map, small sizes, one repeat")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.quick:
        args.size, args.pixels, args.ref_pixels, args.repeats = 64, 8, 64, 1
    elif not args.envmap.exists():
        sys.exit(f"environment map not found: {args.envmap} (pass --envmap)")
    P, N = args.brdf_order, args.light_order
    name = "built-in 64x128 sky + sun" if args.quick else args.envmap.name
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; map {name}; P = {P}, N = {N}")

    # ------------------------------------------------------------------ speed
    env32 = builtin_map(64) if args.quick else EnvironmentMap.from_exr(args.envmap, dtype=torch.float32)
    n = bumpy_sphere_normals(args.size)
    a64 = material_coefficients(P, args.quick)
    a = a64.float()
    t_sh = timeit(lambda: env32.sh_coefficients(N), args.repeats)
    L = env32.sh_coefficients(N)
    t_shared = timeit(lambda: render_envmap(n, a, L), args.repeats)
    amap = a.expand(args.size, args.size, *a.shape).contiguous()
    t_map = timeit(lambda: render_envmap(n, amap, L), max(1, args.repeats // 2))
    npx = args.size * args.size
    print(f"\n[speed] {args.size}x{args.size} normals, RGB, float32")
    print(f"  SH projection of the {env32.height}x{env32.width} map (N={N}): {t_sh * 1e3:8.1f} ms")
    print(f"  render_envmap, shared BRDF:            {t_shared:8.3f} s  ({t_shared / npx * 1e9:.0f} ns/pixel)")
    print(f"  render_envmap, per-pixel coefficients: {t_map:8.3f} s")
    print(f"  total with the projection (shared):    {t_shared + t_sh:8.3f} s   (target < 2 s)")

    if args.speed_only:
        return
    # ------------------------------------------------------------------ accuracy
    env = env32.to(torch.float64)
    g = torch.Generator().manual_seed(0)
    idx = torch.randint(0, npx, (args.pixels,), generator=g)
    nt = n.reshape(-1, 3)[idx].double()
    t0 = time.perf_counter()
    truth = render_envmap_reference(nt, a64, env)
    t_truth = time.perf_counter() - t0
    scale = float(truth.abs().mean())
    print(f"\n[accuracy] {args.pixels} pixels, float64; truth = reference on the full {env.height}x{env.width} map "
          f"({t_truth:.1f} s); errors are mean |error| / mean |truth|")
    rows = {}
    for Nl in (4, 6, 8, 12, 16, 24):
        err = float((render_envmap(nt, a64, env, light_order=Nl) - truth).abs().mean()) / scale
        rows[Nl] = err
        print(f"  render_envmap N={Nl:2d}: {err:.2e}")
    ref_err = {}
    small = env
    while small.height > (16 if args.quick else 64):
        small = small.downsample(2)
        err = float((render_envmap_reference(nt, a64, small) - truth).abs().mean()) / scale
        ref_err[small.height] = err
        print(f"  reference {small.height:3d}x{small.width:4d}: {err:.2e}")

    # ------------------------------------------------------------------ ratio
    ref_h = 16 if args.quick else 64
    ref_map = env32.downsample(env32.height // ref_h)
    sub = n.reshape(-1, 3)[: args.ref_pixels]
    t_ref_sub = timeit(lambda: render_envmap_reference(sub, a.expand(sub.shape[0], *a.shape), ref_map), 1, 0)
    t_ref = t_ref_sub * npx / sub.shape[0]
    print(f"\n[ratio] reference on the {ref_map.height}x{ref_map.width} map: {t_ref_sub:.2f} s for {sub.shape[0]} pixels "
          f"-> {t_ref:.1f} s for {npx} pixels (linear extrapolation)")
    e64 = ref_err.get(ref_h, float("nan"))
    print(f"  accuracy: reference {ref_h}x{2 * ref_h} {e64:.2e}; render_envmap N={N} {rows.get(N, float('nan')):.2e}")
    print(f"  speed ratio reference({ref_h}x{2 * ref_h}) / render_envmap(N={N}, shared BRDF, incl. projection): "
          f"{t_ref / (t_shared + t_sh):.0f}x (target >= 20x)")
    match = [k for k in sorted(rows) if rows[k] <= e64]
    if match:
        Nm = match[0]
        Lm = env32.sh_coefficients(Nm)
        t_m = timeit(lambda: render_envmap(n, a, Lm), max(1, args.repeats // 2)) + timeit(
            lambda: env32.sh_coefficients(Nm), 1)
        print(f"  at equal accuracy: render_envmap N={Nm} ({rows[Nm]:.2e} <= {e64:.2e}) takes {t_m:.2f} s "
              f"-> ratio {t_ref / t_m:.0f}x")
    else:
        print(f"  no tested N reaches the accuracy of the {ref_h}x{2 * ref_h} reference")

if __name__ == "__main__":
    main()
