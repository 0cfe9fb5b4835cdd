"""The photometric-stereo benchmark suite of issue 21, fixed before any tuning.

Three kinds of scenes (run by ``benchmarks/bench_suite.py``):

* ``mitsuba``: scenes that no formula of torch_hsh renders, path traced by Mitsuba 3
  (``benchmarks/mitsuba_scenes.py``: cast shadows and interreflections, rough plastic, rough
  conductor, principled), rendered on demand into the cache. Size 128 x 128, 48 DiLiGenT-like
  lights, 64 samples per pixel, scene seed 0: what scalar path tracing on a 2-core machine
  affords (about 3 to 6 minutes a scene on one thread). Full DiLiGenT size (612 x 512, 96 lights)
  would take hours.
* ``synthetic``: the library's own cast-shadow scenes, rendered by torch_hsh formulas and written
  to the cache with ``torch_hsh.io.save_diligent``: the demo scene (``make demo``: bumpy sphere, GGX
  and Blinn-Phong regions, cast shadows, sensor noise) and a bumpy height field with cast
  shadows and an ambient term (:func:`bumpy_shadows`).
* ``capture``: the shared real captures (bunny_specular, diligent_cat, diligent_harvest), read
  in place from a folder given by path (``--shared``), never copied.

The ``quick`` variants (``--quick``, CI) are tiny versions of the same scenes (24 x 24, 8 lights,
4 spp for Mitsuba; 32 x 32 for the synthetic ones); captures are skipped in quick mode unless a
``--shared`` folder is passed.

Solver seeds: every scene runs with solver seeds 0-4 (the seed draws the calibration subset of
``solve_hsh``); the scene itself is fixed (scene seed 0).

Do not change these definitions to suit a method: the point of the suite is that it was fixed
before the tuning of issue 21 started. Add scenes, do not edit them; a changed scene is a new name.
"""
from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

ROOT = Path(__file__).resolve().parents[1]

#: Solver seeds of the full suite.
SEEDS: Tuple[int, ...] = (0, 1, 2, 3, 4)


@dataclass(frozen=True)
class Scene:
    """One suite entry. ``kind``: ``mitsuba`` / ``synthetic`` / ``capture``; ``params``: what builds it."""

    name: str
    kind: str
    params: Dict = field(default_factory=dict)
    note: str = ""


MITSUBA_FULL = dict(size=128, lights=48, spp=64, seed=0, max_depth=6)
MITSUBA_QUICK = dict(size=24, lights=8, spp=4, seed=0, max_depth=6)

_MITSUBA_NAMES = ("folds_plastic", "grooves_conductor", "bowl_principled", "dome_plastic")

SUITE: List[Scene] = [
    *[Scene(n, "mitsuba", dict(MITSUBA_FULL)) for n in _MITSUBA_NAMES],
    Scene("demo", "synthetic", dict(size=128, lights=96, seed=0),
          "torch_hsh.render.scenes.demo_scene(128, n_lights=96, seed=0): the `make demo` scene"),
    Scene("bumpy_shadows", "synthetic", dict(size=64, lights=40, seed=1),
          "bumpy height field x 1.6, 40 lights in a 65 deg cone, Blinn-Phong, cast shadows + ambient 0.3"),
    Scene("bunny_specular", "capture", dict(folder="bunny_specular")),
    Scene("diligent_cat", "capture", dict(folder="diligent_cat")),
    Scene("diligent_harvest", "capture", dict(folder="diligent_harvest")),
]

QUICK: List[Scene] = [
    *[Scene(n, "mitsuba", dict(MITSUBA_QUICK)) for n in _MITSUBA_NAMES],
    Scene("demo", "synthetic", dict(size=32, lights=20, seed=0)),
    Scene("bumpy_shadows", "synthetic", dict(size=32, lights=20, seed=1)),
    *[s for s in SUITE if s.kind == "capture"],
]


def default_shared() -> Optional[Path]:
    """``$TORCH_HSH_SHARED_DATA``, else ``<repo>/../shared/data`` if it exists, else None."""
    env = os.environ.get("TORCH_HSH_SHARED_DATA")
    if env:
        return Path(env)
    p = ROOT.parent / "shared" / "data"
    return p if p.is_dir() else None


def suite_cache() -> Path:
    """Where the synthetic scenes are written (``$TORCH_HSH_CACHE/suite`` or ``~/.cache/torch_hsh/suite``)."""
    base = os.environ.get("TORCH_HSH_CACHE")
    return (Path(base) if base else Path.home() / ".cache" / "torch_hsh") / "suite"


def bumpy_shadows(size: int = 64, lights: int = 40, seed: int = 1) -> dict:
    """A bumpy height field with cast shadows and a constant ambient term (torch_hsh formulas only).

    ``bumpy_heightfield(size, n_bumps=10, seed=seed, smoothness=0.12) x 1.6`` (pixel units), its
    exact normals, ``cone_lights(lights, 65 deg, seed=seed + 1)``, Blinn-Phong with albedo 0.6 (grey),
    ``specular = 0.3``, shininess 20; each image is ``visibility x direct + 0.3 x albedo / pi`` (the
    ambient is 0.3 of the Lambertian radiance under a unit light at the view), visibility from
    ``cast_shadow_mask``. Follows the description of the bumpy field in docs/photometric_stereo.md
    (whose script was not committed), so its numbers need not match that page's.
    """
    import torch

    from torch_hsh.brdf import BlinnPhong
    from torch_hsh.render import render_model
    from torch_hsh.render.scenes import bumpy_heightfield, cone_lights, heightfield_normals
    from torch_hsh.render.visibility import cast_shadow_mask

    f64 = torch.float64
    h = bumpy_heightfield(size, n_bumps=10, seed=seed, smoothness=0.12, dtype=f64) * 1.6
    n = heightfield_normals(h)
    L = cone_lights(lights, 65.0, seed=seed + 1, dtype=f64)
    vis = cast_shadow_mask(h, L)
    ones = torch.ones(size, size, 1, dtype=f64)
    albedo = 0.6 * torch.ones(size, size, 3, dtype=f64)
    img = render_model(n, L, BlinnPhong(albedo=albedo, specular=0.3 * ones, shininess=20.0 * ones))
    img = img * vis[..., None] + 0.3 * albedo / math.pi
    mask = torch.ones(size, size, dtype=torch.bool)
    return {"images": img, "lights": L, "intensities": None, "mask": mask, "normals_gt": n,
            "shadowed": float((~vis).double().mean())}


def synthetic_folder(scene: Scene, root: Optional[Path] = None) -> Path:
    """The DiLiGenT-layout folder of a synthetic scene, written once into the cache (by save_diligent)."""
    import json

    from torch_hsh.io import save_diligent

    p = scene.params
    root = suite_cache() if root is None else Path(root)
    folder = root / f"{scene.name}-{p['size']}px-{p['lights']}L-seed{p['seed']}"
    rec = dict(p, scene=scene.name, version=1)
    try:
        if json.loads((folder / "params.json").read_text()) == rec:
            return folder
    except (OSError, ValueError):
        pass
    if scene.name == "demo":
        from torch_hsh.render.scenes import demo_scene

        s = demo_scene(p["size"], n_lights=p["lights"], seed=p["seed"])
        inten = s["intensities"]
        images = s["images"] / inten[:, None, None, :]  # save_diligent takes unit-intensity images
        normals, mask, lights = s["normals_gt"], s["mask"], s["lights"]
    elif scene.name == "bumpy_shadows":
        s = bumpy_shadows(p["size"], p["lights"], p["seed"])
        images, inten, normals, mask, lights = s["images"], None, s["normals_gt"], s["mask"], s["lights"]
    else:
        raise ValueError(f"unknown synthetic scene {scene.name!r}")
    if (folder / "params.json").exists():
        (folder / "params.json").unlink()
    save_diligent(folder, images, lights, intensities=inten, mask=mask, normals_gt=normals,
                  overwrite=folder.is_dir())  # our own cache folder (named by its parameters)
    (folder / "params.json").write_text(json.dumps(rec) + "\n")
    return folder


def scene_folder(scene: Scene, shared: Optional[Path] = None, mitsuba_root: Optional[Path] = None,
                 threads: Optional[int] = None, progress=None) -> Optional[Path]:
    """The DiLiGenT-layout folder of a suite scene (rendered / written on demand), or None for a capture
    that is not found under ``shared``."""
    if scene.kind == "mitsuba":
        import mitsuba_scenes as ms

        p = scene.params
        folder, _ = ms.ensure_scene(scene.name, p["size"], p["lights"], p["spp"], p["seed"], p["max_depth"],
                                    root=mitsuba_root, threads=threads, progress=progress)
        return folder
    if scene.kind == "synthetic":
        return synthetic_folder(scene)
    if scene.kind == "capture":
        if shared is None:
            return None
        f = Path(shared) / scene.params["folder"]
        return f if (f / "light_directions.txt").is_file() else None
    raise ValueError(f"unknown scene kind {scene.kind!r}")


def available_folder(scene: Scene, shared: Optional[Path] = None, **kw) -> Tuple[Optional[Path], str]:
    """:func:`scene_folder` for the scripts that loop over the suite: ``(folder, "")``, or ``(None, why)``
    when the scene cannot be had here (Mitsuba not installed, capture not found under ``shared``)."""
    try:
        folder = scene_folder(scene, shared=shared, **kw)
    except ImportError as err:
        return None, f"{scene.kind}: {err}; install the bench extra"
    if folder is None:
        return None, f"capture not found under {shared}; pass --shared DIR"
    return folder, ""


def render_progress(msg: str) -> None:
    """Progress of a Mitsuba render (only when a scene is not cached), on stderr: the ``progress`` of
    :func:`scene_folder` for the scripts that loop over the suite."""
    print(f"    rendering {msg}", file=sys.stderr, flush=True)
