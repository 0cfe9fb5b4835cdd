"""Is the remaining error the optimiser's basin or the model's objective? Solves started from the TRUE normals.

The per-pixel solver keeps the basin it starts in (docs/photometric_stereo.md, "Limits"). This script
asks, per scene of the issue-21 suite, whether a better start could help at all:

1. ``default``: :func:`torch_hsh.ps.solve_hsh` at its defaults (solver seed 0).
2. ``truth start``: the same solve with ``init`` = the ground-truth normals and ``calibration_starts =
   ("lambertian",)``, so both the calibration of the basis BRDFs and the per-pixel pass start from the
   truth (an oracle: it uses the ground truth). Its error is what the model's objective holds when the
   optimiser is given the truth's basin.
3. ``default basis, truth pixels``: the basis BRDFs and robust scale of (1), the per-pixel pass started
   from the truth. It separates the basis from the per-pixel basins.

(1) and (3) share their basis BRDFs, so their losses also compare pixel by pixel. ``per-pixel choice`` is the
error of the normals that take, at every pixel, whichever of (1) and (3) has the lower loss, and ``truth pixels
chosen`` the share of pixels where that is (3). It is what a per-pixel search led by the loss could at best
reach among these two basins: near (3)'s error if the per-pixel objective is right, near (1)'s if it is not.

For each solve it evaluates the solver's own objective on every pixel: the Cauchy loss
``sum_l w0 log(1 + (r / (c s))^2)`` of the residuals after three IRLS passes of the closed-form mixing
weights. That is the criterion by which the calibration chooses between its starts (``calibration_losses``),
here over all pixels, at one scale ``s``: the smaller of the robust scales of (1) and (2), as the solver
uses them (floored at the noise level; the calibration's choice uses the unfloored ones). The mean over
the pixels is printed.

Reading: if the truth-start solve has the *lower* loss, the objective is right and the error of the
default is a search problem: a better start or search could gain up to the truth-start error. If it has
the *higher* loss, the objective itself prefers the default's worse normals, so a search led by this loss
does not lead to the truth's basin. Only a better model (interreflections, cast shadows, the surface)
can. The comparison is between two local minima, each with its own basis, at one solver seed.

Usage:
    python research/objective_floor.py --shared ../shared/data       # the suite (bench_suite.py)
    python research/objective_floor.py --only diligent_harvest --shared ../shared/data --materials 3
    python research/objective_floor.py --quick --only bumpy_shadows  # CI: a 32² synthetic scene
    python research/objective_floor.py --only diligent_harvest --shared ../shared/data --surface --interreflections

``--surface`` adds the whole-surface stage's own loss (:func:`surface_loss`) at three surfaces, and
``--interreflections`` runs everything on the images after the solver's one-bounce round.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the suite's scenes
import suite as suite_mod  # noqa: E402


def solution_loss(obs, basis: torch.Tensor, normals: torch.Tensor, scale: float, order: int, c: float,
                  chunk_size: int = 4096) -> torch.Tensor:
    """Per-pixel Cauchy loss ``(P,)`` of the shared model at ``basis (M, K)`` and ``normals (P, 3)``.

    ``obs`` is the solver's :class:`~torch_hsh.ps.observations.Observations` (unit brightness); ``scale``
    is in the same units. Three IRLS passes of the mixing weights from the observation weights, as the
    calibration's choice between starts does.
    """
    from torch_hsh.ps.design import MixedDesign
    from torch_hsh.ps.optim import cauchy_rho, irls_weights

    y, w0 = obs.data.y.double(), obs.weights.double()
    des = MixedDesign(basis.double(), obs.data.lights.double(), order)
    out = []
    for s in range(0, normals.shape[0], chunk_size):
        sl = slice(s, s + chunk_size)
        _, res = irls_weights(des(normals[sl].double()), y[sl].transpose(1, 2), w0[sl].clone(), w0[sl], scale, c, 3)
        out.append((w0[sl] * cauchy_rho(res, scale, c)).sum(-1))
    return torch.cat(out)


def pixel_choice(normals_a: torch.Tensor, normals_b: torch.Tensor, loss_a: torch.Tensor, loss_b: torch.Tensor):
    """At every pixel the normal of ``(P, 3)`` ``normals_a`` or ``normals_b`` whose per-pixel loss ``(P,)`` is lower
    (``a`` on ties). Returns the chosen normals ``(P, 3)`` (float64) and ``(P,)`` True where ``b`` was chosen."""
    b = loss_b < loss_a
    return torch.where(b[:, None], normals_b, normals_a).double(), b


def surface_loss(obs, basis: torch.Tensor, normals: torch.Tensor, mask: torch.Tensor, scale: float, order: int,
                 c: float, bias: float) -> float:
    """Mean per-pixel loss of the whole-surface stage's objective at the surface of ``normals (H, W, 3)``.

    As in :func:`torch_hsh.ps.refine_surface`: the bilateral depth of the normals (the stage's start,
    :func:`torch_hsh.ps._geometry.start_depth`), the normals of that depth (discontinuity-weighted differences),
    and the observation weights times that depth's cast shadows (:func:`torch_hsh.surface.light_visibility`,
    ``bias`` pixels); then :func:`solution_loss` with ``basis``.
    """
    from types import SimpleNamespace

    from torch_hsh.ps import whole_surface as ws
    from torch_hsh.ps._geometry import start_depth
    from torch_hsh.surface import light_visibility

    box, z = start_depth(normals.to(torch.float64), mask)
    mb = mask[box].cpu()
    n = ws.depth_normals(z, mb, ws.discontinuity_weights(z, mb))[mb]
    vis = light_visibility(z, mb, obs.data.lights.detach().to(torch.float64).cpu(), bias=bias).permute(1, 2, 0)[mb]
    shadowed = SimpleNamespace(data=obs.data, weights=obs.weights.double() * vis.to(obs.weights.device).double())
    return float(solution_loss(shadowed, basis, n.to(obs.data.y.device), scale, order, c).mean())


def scene_row(d, seed: int = 0, surface: bool = False, **solve_kw) -> dict:
    """The three solves of the module docstring on one loaded scene ``d``, their errors (deg) and losses.

    ``surface``: also the whole-surface stage's loss (:func:`surface_loss`, the default basis, which the stage
    keeps) at the surfaces of the default solve, of the truth-start solve and of the true normals.
    ``solve_kw``: further options of every solve (for example ``order=4`` or ``materials=3``)."""
    from torch_hsh import ps
    from torch_hsh.ps.calibration import reuse_calibration
    from torch_hsh.ps.observations import observe
    from torch_hsh.ps.settings import Settings

    gt, mask = d.normals_gt.to(torch.float64), d.mask
    images, lights, inten = d.images, d.lights, None  # as the suite loads them (bench_suite.py)

    def err(r) -> float:
        return float(ps.angular_error(r.normals.double(), gt, mask)[mask].mean())

    t = time.perf_counter()
    r_def = ps.solve_hsh(images, lights, inten, mask, seed=seed, **solve_kw)  # 1, 2 and 3 of the docstring
    r_gt = ps.solve_hsh(images, lights, inten, mask, seed=seed, init=gt, calibration_starts=("lambertian",), **solve_kw)
    r_px = ps.solve_hsh(images, lights, inten, mask, seed=seed, init=gt, **{**solve_kw, **reuse_calibration(r_def)})
    cfg = Settings(**solve_kw)
    obs = observe(images, lights, inten, mask, cfg)
    # the results' robust scales are in the images' units (x image_scale); the observations are at unit brightness
    scale = min(r_def.info["robust_scale"], r_gt.info["robust_scale"]) / obs.scale
    per_px = {k: solution_loss(obs, r.basis_brdfs, r.normals[mask], scale, cfg.order, cfg.cauchy_c)
              for k, r in (("default", r_def), ("truth start", r_gt), ("default basis, truth pixels", r_px))}
    # (1) and (3) share the basis, so their losses compare pixel by pixel: each pixel takes the lower one
    chosen, truth_px = pixel_choice(r_def.normals[mask], r_px.normals[mask], per_px["default"],
                                    per_px["default basis, truth pixels"])
    out = {
        "default": err(r_def), "truth start": err(r_gt), "default basis, truth pixels": err(r_px),
        **{f"loss {k}": float(v.mean()) for k, v in per_px.items()},
        "per-pixel choice": float(ps.angular_error(chosen, gt[mask]).mean()),
        "truth pixels chosen (%)": 100 * float(truth_px.double().mean()),
        "scale": scale,
    }
    if surface:
        for k, n in (("default", r_def.normals), ("truth start", r_gt.normals), ("truth", gt)):
            out[f"surface loss {k}"] = surface_loss(obs, r_def.basis_brdfs, n, mask, scale, cfg.order, cfg.cauchy_c,
                                                    cfg.shadow_bias)
    out["time_s"] = time.perf_counter() - t
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("Reading: ")[1].split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the suite's quick scenes (bench_suite.py --quick)")
    ap.add_argument("--shared", default=None, help="folder of the shared captures (default ../shared/data)")
    ap.add_argument("--only", nargs="+", default=None, help="these scenes only (names of suite.py)")
    ap.add_argument("--seed", type=int, default=0, help="solver seed (the calibration subset)")
    ap.add_argument("--order", type=int, default=None, choices=range(1, 9), metavar="P",
                    help="solve_hsh(order=P), 1-8, of every solve (default: the library's)")
    ap.add_argument("--materials", type=int, default=None, choices=range(1, 9), metavar="M",
                    help="solve_hsh(materials=M), 1-8, of every solve (default: the library's)")
    ap.add_argument("--interreflections", action="store_true",
                    help="first remove one bounce of interreflection (the solver's round, solve_hsh(interreflections=1)) "
                         "and run everything on the corrected images")
    ap.add_argument("--surface", action="store_true",
                    help="three more columns: the whole-surface stage's loss (default basis, each depth's cast shadows) "
                         "at the surfaces of the default solve, the truth-start solve and the true normals")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the solves and of Mitsuba renders")
    args = ap.parse_args(argv)
    solve_kw = {k: v for k, v in (("order", args.order), ("materials", args.materials)) if v is not None}
    torch.set_num_threads(args.threads)
    from torch_hsh.io.diligent import load_diligent

    scenes = suite_mod.QUICK if args.quick else suite_mod.SUITE
    if args.only:
        unknown = sorted(set(args.only) - {s.name for s in scenes})
        if unknown:
            ap.error(f"--only: unknown scene(s) {unknown}; known: {[s.name for s in scenes]}")
        scenes = [s for s in scenes if s.name in args.only]
    shared = Path(args.shared) if args.shared else (None if args.quick else suite_mod.default_shared())
    cols = ["default", "truth start", "default basis, truth pixels", "loss default", "loss truth start",
            "loss default basis, truth pixels", "objective prefers", "per-pixel choice", "truth pixels chosen (%)"]
    if args.surface:
        cols += ["surface loss default", "surface loss truth start", "surface loss truth"]
    if args.interreflections:
        cols += ["bounce (% of the light)"]
    cols += ["time"]
    print("| scene | " + " | ".join(cols) + " |\n|" + "---|" * (len(cols) + 1), flush=True)
    for sc in scenes:
        folder, why = suite_mod.available_folder(sc, shared=shared, threads=args.threads,
                                                 progress=suite_mod.render_progress)
        d = None if folder is None else load_diligent(folder, dtype=torch.float32)
        if d is None or d.normals_gt is None:
            print(f"| {sc.name} | skipped ({why or 'no ground-truth normals'}) |", flush=True)
            continue
        extra = []
        if args.interreflections:  # the solver's round: solve, one bounce from its surface, subtract it
            from torch_hsh.ps.interreflections import interreflection_loop
            from torch_hsh.ps.pipeline import run_stages
            from torch_hsh.ps.settings import Settings

            res, images, _ = interreflection_loop(run_stages, d.images, d.lights, None, d.mask,
                                                  Settings(interreflections=1, seed=args.seed, **solve_kw))
            d.images = images
            kept = "kept" if res.info.get("interreflection_rounds", 0) else "rejected: images unchanged"
            extra = [f"{100 * res.info.get('interreflection_fraction', float('nan')):.2f} ({kept})"]
        r = scene_row(d, args.seed, surface=args.surface, **solve_kw)
        verdict = "truth start" if r["loss truth start"] < r["loss default"] else "default"
        cells = [f"{r[k]:.2f}" for k in cols[:3]] + [f"{r[k]:.4f}" for k in cols[3:6]] + [verdict]
        cells += [f"{r['per-pixel choice']:.2f}", f"{r['truth pixels chosen (%)']:.0f}"]
        if args.surface:
            cells += [f"{r[k]:.4f}" for k in ("surface loss default", "surface loss truth start", "surface loss truth")]
        cells += extra + [f"{r['time_s']:.0f} s"]
        print(f"| {sc.name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
