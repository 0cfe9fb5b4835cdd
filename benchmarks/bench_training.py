"""Benchmark: an SVBRDF network trained on images rendered by the library, eager against torch.compile and
bfloat16 autocast.

The scene: ``--size`` x ``--size`` pixels of a bumped surface (per-pixel normals) made of two materials (least-
squares Helmholtz fits of two Blinn-Phong BRDFs, order ``--order``) blended by a smooth pattern, rendered under
``--lights`` distant lights with :func:`torch_hsh.render.render_coefficients`. The network: an MLP from Fourier
features of the pixel position to the per-pixel Helmholtz coefficients (``channels x K``), evaluated through
:class:`torch_hsh.HelmholtzBRDF` (``learnable=False``, ``forward_world`` with per-pixel coefficients), loss the
mean squared error against the images. One step evaluates the basis at ``lights x size**2`` rows (65,536 by
default) forward and backward, then takes an Adam step.

Modes (each from the same initial weights, ``--steps`` steps):

* ``eager``: float32;
* ``compiled``: the loss (network, basis, image formation) through ``torch.compile(fullgraph=True)``, backend
  ``--compile-backend`` (default ``inductor``); the first ``--warmup`` steps, which compile, are not timed;
* ``bf16``: eager under ``torch.autocast("cpu", dtype=torch.bfloat16)`` (the basis runs in float32 inside).

Printed per mode: steps/s (after ``--warmup`` steps), the first and final loss, and the ratio of steps/s
against eager measured in the same run. A second table times forward+backward of the basis alone
(``HelmholtzBRDF(P)(wi, wo).sum()`` at ``--rows`` rows, orders 3 and 8), eager against compiled.

Usage::

    python benchmarks/bench_training.py                 # 64 x 64 pixels, 16 lights, inductor
    python benchmarks/bench_training.py --quick         # seconds: 16 x 16 pixels, aot_eager
    python benchmarks/bench_training.py --backend torch # the pure-torch kernels
"""
from __future__ import annotations

import argparse
import math
import statistics
import time
from typing import Dict, List

import torch

import torch_hsh


def hemisphere(n: int, g: torch.Generator, min_z: float = 0.0) -> torch.Tensor:
    v = torch.randn(n, 3, generator=g)
    v[:, 2] = v[:, 2].abs() + min_z
    return torch.nn.functional.normalize(v, dim=-1)


def materials(order: int, g: torch.Generator) -> torch.Tensor:
    """Two Blinn-Phong BRDFs fitted in the Helmholtz basis (least squares in float64): ``(2, 3, K)``."""
    wi, wo = hemisphere(20000, g), hemisphere(20000, g)
    B = torch_hsh.helmholtz_isotropic(wi.double(), wo.double(), order)
    out = []
    for kd, ks, shin in (([0.6, 0.35, 0.2], 0.3, 6.0), ([0.15, 0.3, 0.55], 0.6, 12.0)):
        f = torch_hsh.brdf.BlinnPhong(albedo=kd, specular=ks, shininess=shin)(wi, wo).double()
        out.append(torch.linalg.lstsq(B, f).solution.T)
    return torch.stack(out).float()


def scene(size: int, n_lights: int, order: int, seed: int = 0) -> Dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    u, v = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    h_u = 0.6 * torch.cos(2.5 * u) * torch.sin(2.0 * v)  # slopes of a smooth bump
    h_v = 0.6 * torch.sin(1.5 * u) * torch.cos(2.5 * v)
    normals = torch.nn.functional.normalize(torch.stack([-h_u, -h_v, torch.ones_like(u)], -1), dim=-1).reshape(-1, 3)
    mix = torch.sigmoid(6.0 * torch.sin(3.0 * u) * torch.sin(2.0 * v)).reshape(-1, 1, 1)
    mats = materials(order, g)
    coeffs = mix * mats[0] + (1 - mix) * mats[1]  # (P, 3, K)
    lights = hemisphere(n_lights, g, min_z=0.8)
    render = getattr(torch_hsh, "render_coefficients", None) or torch_hsh.render.render_coefficients
    images = render(normals, lights, coeffs)  # (L, P, 3)
    freqs = 2.0 ** torch.arange(4) * math.pi
    ang = torch.stack([u, v], -1).reshape(-1, 2, 1) * freqs
    feats = torch.cat([ang.sin().flatten(1), ang.cos().flatten(1), normals], -1)  # (P, 19)
    return {"normals": normals, "lights": lights, "images": images, "features": feats}


class Svbrdf(torch.nn.Module):
    """MLP: pixel features -> per-pixel Helmholtz coefficients; image = f(l, v; n) max(0, n . l)."""

    def __init__(self, n_in: int, order: int, hidden: int = 64) -> None:
        super().__init__()
        self.brdf = torch_hsh.HelmholtzBRDF(order, channels=3, learnable=False)
        K = self.brdf.num_functions
        self.K = K
        self.mlp = torch.nn.Sequential(torch.nn.Linear(n_in, hidden), torch.nn.SiLU(), torch.nn.Linear(hidden, hidden),
                                       torch.nn.SiLU(), torch.nn.Linear(hidden, 3 * K))

    def forward(self, feats: torch.Tensor, normals: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
        coeffs = self.mlp(feats).reshape(-1, 3, self.K)  # (P, 3, K)
        view = torch.tensor([0.0, 0.0, 1.0], dtype=normals.dtype)
        li = lights[:, None, :]  # (L, 1, 3)
        f = self.brdf.forward_world(li, view, normals, coeffs)  # (L, P, 3)
        cos = (normals * li).sum(-1, keepdim=True).clamp(min=0.0)
        return f * cos


def train(mode: str, data: Dict[str, torch.Tensor], order: int, steps: int, warmup: int, lr: float,
          compile_backend: str) -> Dict[str, float]:
    torch.manual_seed(0)
    model = Svbrdf(data["features"].shape[1], order)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    feats, normals, lights, images = data["features"], data["normals"], data["lights"], data["images"]

    def loss_fn(feats, normals, lights, images):
        return (model(feats, normals, lights) - images).square().mean()

    fn = loss_fn
    if mode == "compiled":
        torch._dynamo.reset()
        fn = torch.compile(loss_fn, fullgraph=True, backend=compile_backend)
    losses: List[float] = []
    t0 = time.perf_counter()
    t_warm = t0
    for step in range(steps):
        if step == warmup:
            t_warm = time.perf_counter()
        if mode == "bf16":
            with torch.autocast("cpu", dtype=torch.bfloat16):
                loss = fn(feats, normals, lights, images)
        else:
            loss = fn(feats, normals, lights, images)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss))
    t1 = time.perf_counter()
    return {"steps_per_s": (steps - warmup) / (t1 - t_warm), "warmup_s": t_warm - t0, "first": losses[0],
            "final": losses[-1]}


def time_basis(order: int, rows: int, compile_backend: str, repeats: int) -> Dict[str, float]:
    """Median seconds of forward+backward of the basis alone, eager and compiled."""
    g = torch.Generator().manual_seed(1)
    wi, wo = hemisphere(rows, g).requires_grad_(), hemisphere(rows, g).requires_grad_()
    brdf = torch_hsh.HelmholtzBRDF(order, channels=3)

    def fb(fn):
        loss = fn(wi, wo)
        loss.backward()

    def run(fn) -> float:
        for _ in range(2):
            fb(fn)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fb(fn)
            ts.append(time.perf_counter() - t)
        return statistics.median(ts)

    eager = lambda a, b: brdf(a, b).sum()  # noqa: E731
    torch._dynamo.reset()
    compiled = torch.compile(eager, fullgraph=True, backend=compile_backend)
    te = run(eager)
    tc = run(compiled)
    te2 = run(eager)  # eager again: the spread of the machine shows in the two eager numbers
    return {"eager": min(te, te2), "eager_spread": abs(te - te2) / min(te, te2), "compiled": tc}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=64, help="image side in pixels")
    ap.add_argument("--lights", type=int, default=16)
    ap.add_argument("--order", type=int, default=3)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--backend", default="auto", choices=["auto", "torch"], help="torch_hsh.set_backend")
    ap.add_argument("--compile-backend", default=None, help="torch.compile backend (default inductor; quick: aot_eager)")
    ap.add_argument("--rows", type=int, default=65536, help="rows of the basis-only timing")
    ap.add_argument("--basis-orders", type=int, nargs="*", default=[3, 8])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--modes", nargs="+", default=["eager", "compiled", "bf16"], choices=["eager", "compiled", "bf16"])
    ap.add_argument("--quick", action="store_true", help="seconds: 16 x 16 pixels, 8 lights, 40 steps, aot_eager")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.lights, args.steps, args.rows, args.repeats = 16, 8, 40, 8192, 3
        args.basis_orders = [3]
        args.lr = 1e-2
    backend = args.compile_backend or ("aot_eager" if args.quick else "inductor")
    torch.set_num_threads(args.threads)
    torch_hsh.set_backend(args.backend)
    status = torch_hsh.backend_status()
    rows = args.lights * args.size ** 2
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, torch_hsh backend {args.backend} "
          f"(isotropic_cpu: {status['isotropic_cpu']}), torch.compile backend {backend}")
    print(f"SVBRDF: {args.size}x{args.size} pixels, {args.lights} lights ({rows} basis rows per step), "
          f"order {args.order}, {args.steps} steps ({args.warmup} untimed)")
    data = scene(args.size, args.lights, args.order)
    res = {m: train(m, data, args.order, args.steps, args.warmup, args.lr, backend) for m in args.modes}
    base = res.get("eager", {}).get("steps_per_s")
    print(f"{'mode':>9} {'steps/s':>9} {'warmup s':>9} {'first loss':>11} {'final loss':>11} {'vs eager':>9}")
    for m, r in res.items():
        ratio = f"{r['steps_per_s'] / base:9.2f}" if base else f"{'-':>9}"
        print(f"{m:>9} {r['steps_per_s']:9.2f} {r['warmup_s']:9.2f} {r['first']:11.3e} {r['final']:11.3e} {ratio}")
    for m, r in res.items():
        print(f"loss {m}: {r['first']:.3e} -> {r['final']:.3e} ({'falls' if r['final'] < r['first'] else 'DOES NOT FALL'})")
    if base:
        for m, r in res.items():
            if m != "eager":
                print(f"final loss {m} / eager: {r['final'] / res['eager']['final']:.3f}")
    if args.basis_orders:
        print(f"\nbasis alone, forward+backward of HelmholtzBRDF(P)(wi, wo).sum() at {args.rows} rows, "
              f"median of {args.repeats} (ms)")
        print(f"{'P':>3} {'eager':>9} {'compiled':>9} {'eager/compiled':>15} {'eager spread':>13}")
        for order in args.basis_orders:
            t = time_basis(order, args.rows, backend, args.repeats)
            print(f"{order:>3} {t['eager'] * 1e3:9.2f} {t['compiled'] * 1e3:9.2f} {t['eager'] / t['compiled']:15.2f} "
                  f"{t['eager_spread']:12.0%}")


if __name__ == "__main__":
    main()
