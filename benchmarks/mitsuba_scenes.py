"""Photometric-stereo scenes rendered by Mitsuba 3 (an independent path tracer), in the DiLiGenT layout.

No formula of torch_hsh renders these images: Mitsuba's ``path`` integrator (``max_depth`` 6 by
default, at least 4) traces cast shadows and interreflections between the folds, the grooves and
the walls of a bowl, with Mitsuba's own BSDFs (rough plastic, rough conductor, principled). The
ground-truth normals are Mitsuba's ``aov`` integrator's ``sh_normal`` (the shading normal that the
renderer used), averaged over each pixel and normalised; the mask is the set of pixels that the
object covers completely.

Frames. The camera is ``orthographic`` with ``look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0,
1, 0])``: image x to the right, y up, z toward the camera, which is the DiLiGenT frame of
``torch_hsh.io`` (row 0 is the top of the picture). World coordinates are therefore written
unchanged: the light directions (toward the light, ``l``) and the normals. A Mitsuba ``directional``
emitter's ``direction`` is where the light travels, so it is ``-l``. ``tests/test_mitsuba_scenes.py``
checks the frame once on a dome: its right-most pixel has ``n_x > 0``, its top one ``n_y > 0``.

Radiometry. Images are linear HDR radiance (no tone mapping), written by
``torch_hsh.io.save_diligent`` as 16-bit PNGs with one scale for the whole stack (stored in
``light_intensities.txt``, so ``load_diligent(normalize_intensities=True)`` gives the images back
as if every light had unit intensity). Each light's irradiance is an RGB value in [0.8, 1.2]
(``torch_hsh.render.scenes.light_intensities``), like DiLiGenT's LEDs. Light directions are
``torch_hsh.render.scenes.diligent_like_lights`` (a jittered 8 x 12-like grid up to 55 degrees from the
view).

Caching. Scenes are rendered on demand into a cache folder (``$TORCH_HSH_CACHE/mitsuba`` or
``~/.cache/torch_hsh/mitsuba``, or ``--out``), one sub-folder per scene and parameter set, e.g.
``folds_plastic-128px-48L-64spp-seed0``. The parameters are recorded in ``params.json``, written
last; a run with the same parameters reuses the folder. A non-empty folder without a matching
``params.json`` is never written into unless ``--overwrite`` is given. Rendered scenes are never
committed.

Usage:
    python benchmarks/mitsuba_scenes.py --list
    python benchmarks/mitsuba_scenes.py folds_plastic bowl_principled --size 128 --lights 48 --spp 64
    python benchmarks/mitsuba_scenes.py dome_plastic --size 24 --lights 4 --spp 4 --out /tmp/mts --threads 1

Needs the ``bench`` extra (``pip install -e ".[bench]"``: ``mitsuba>=3.5``). Only the ``scalar_rgb``
variant is used (the llvm variants crash with some system libLLVM builds).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Optional, Tuple

import numpy as np

#: Bump when the scenes or the image formation change: cached folders of another version are not reused.
GENERATOR_VERSION = 1
#: Half-width of the orthographic view in world units (the objects lie within [-1, 1]^2).
VIEW_HALF_WIDTH = 1.1
DEFAULT_MAX_DEPTH = 6


def default_cache() -> Path:
    """``$TORCH_HSH_CACHE/mitsuba`` if set, else ``~/.cache/torch_hsh/mitsuba``."""
    base = os.environ.get("TORCH_HSH_CACHE")
    return (Path(base) if base else Path.home() / ".cache" / "torch_hsh") / "mitsuba"


def import_mitsuba(threads: Optional[int] = None):
    """Mitsuba with the ``scalar_rgb`` variant set (and drjit's thread count, if given)."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    if threads:
        dr.set_thread_count(int(threads))
    return mi


# --------------------------------------------------------------------------- #
# Geometry: height fields z = h(x, y) over [-1, 1]^2 with analytic gradients (the vertex normals).
def _folds(x, y):
    """Accordion folds (a smoothed triangle wave) across a diagonal, slopes up to about 40 degrees."""
    phi, period, delta = math.radians(30.0), 0.5, 0.05
    amp = math.tan(math.radians(40.0)) * period / (4 * (1 - delta))
    w = 2 * math.pi / period
    u = x * math.cos(phi) + y * math.sin(phi)
    s = (1 - delta) * np.sin(w * u)
    h = amp * (2 / math.pi) * np.arcsin(s)
    dhdu = amp * (2 / math.pi) * (1 - delta) * w * np.cos(w * u) / np.sqrt(1 - s * s)
    # a gentle cross slope so that the faces of the folds are not all alike
    h = h + 0.12 * np.sin(0.5 * math.pi * (y * math.cos(phi) - x * math.sin(phi)))
    dv = 0.12 * 0.5 * math.pi * np.cos(0.5 * math.pi * (y * math.cos(phi) - x * math.sin(phi)))
    return h, dhdu * math.cos(phi) - dv * math.sin(phi), dhdu * math.sin(phi) + dv * math.cos(phi)


def _grooves(x, y):
    """A low dome crossed by narrow Gaussian V-grooves (three along y, two along x), walls up to ~50 degrees."""
    k = math.pi / 2.2
    h = 0.25 * np.cos(k * x) * np.cos(k * y)
    gx = -0.25 * k * np.sin(k * x) * np.cos(k * y)
    gy = -0.25 * k * np.cos(k * x) * np.sin(k * y)
    depth, width = 0.1, 0.08
    for c in (-0.5, 0.0, 0.5):  # grooves along y (functions of x)
        e = depth * np.exp(-((x - c) / width) ** 2)
        h, gx = h - e, gx + e * 2 * (x - c) / width ** 2
    for c in (-0.45, 0.45):  # grooves along x (functions of y)
        e = depth * np.exp(-((y - c) / width) ** 2)
        h, gy = h - e, gy + e * 2 * (y - c) / width ** 2
    return h, gx, gy


_BOWL_R, _BOWL_RIM, _BOWL_EDGE = 1.0, 0.8, 0.95


def _bowl(x, y):
    """A concave spherical bowl (radius 1, opening radius 0.8, depth 0.4, walls up to 53 degrees) in a flat rim."""
    r2 = x * x + y * y
    inside = r2 < _BOWL_RIM ** 2
    root = np.sqrt(np.clip(_BOWL_R ** 2 - r2, 1e-12, None))
    zc = math.sqrt(_BOWL_R ** 2 - _BOWL_RIM ** 2)
    h = np.where(inside, zc - root, 0.0)
    return h, np.where(inside, x / root, 0.0), np.where(inside, y / root, 0.0)


def _bowl_keep(x, y):
    return x * x + y * y <= _BOWL_EDGE ** 2


GEOMETRIES: Dict[str, Tuple[Callable, Optional[Callable]]] = {
    "folds": (_folds, None),
    "grooves": (_grooves, None),
    "bowl": (_bowl, _bowl_keep),
}


def heightfield_ply(path: Path, geometry: str, n: int) -> Path:
    """Write the height field ``geometry`` as an ``n x n``-vertex binary PLY with analytic vertex normals.

    Vertex ``(i, j)`` is at ``x = -1 + 2 j / (n - 1)``, ``y = 1 - 2 i / (n - 1)`` (row 0 at the top).
    Texture coordinates ``u = (x + 1) / 2``, ``v = (1 - y) / 2`` map a texture over the whole square.
    """
    fn, keep = GEOMETRIES[geometry]
    t = np.linspace(-1.0, 1.0, n)
    x, y = np.meshgrid(t, -t)  # (n, n): x along columns, y down the rows
    h, gx, gy = fn(x, y)
    nrm = np.stack([-gx, -gy, np.ones_like(h)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # counter-clockwise seen from +z (the camera): a (top-left), c (bottom-left), d; a, d, b
    faces = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    if keep is not None:
        cen = np.stack([x.ravel(), y.ravel()], -1)[faces].mean(1)
        faces = faces[keep(cen[:, 0], cen[:, 1])]
    fields = [(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "u", "v")]
    v = np.empty(n * n, dtype=fields)
    cols = [x, y, h, nrm[..., 0], nrm[..., 1], nrm[..., 2], (x + 1) / 2, (1 - y) / 2]
    for (name, _), arr in zip(fields, cols):
        v[name] = arr.ravel()
    f = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    f["n"], f["i"] = 3, faces
    props = "".join(f"property float {name}\n" for name, _ in fields)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n * n}\n{props}"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
        fh.write(f.tobytes())
    return path


# --------------------------------------------------------------------------- #
# Materials (Mitsuba BSDF dicts); "texture" means a linear albedo picture mapped over the square.
def _rgb(v):
    return {"type": "rgb", "value": list(v)}


_TEX = "texture"  # replaced by a bitmap texture in render_arrays
MATERIALS: Dict[str, Tuple[dict, bool]] = {
    # (BSDF, textured?)
    "plastic": ({"type": "roughplastic", "distribution": "ggx", "alpha": 0.25, "int_ior": 1.5,
                 "diffuse_reflectance": _TEX}, True),
    "matte_plastic": ({"type": "roughplastic", "distribution": "ggx", "alpha": 0.6, "int_ior": 1.5,
                       "diffuse_reflectance": _rgb([0.7, 0.55, 0.4])}, False),
    "conductor": ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "Cu"}, False),
    "principled": ({"type": "principled", "base_color": _TEX, "metallic": 0.3, "roughness": 0.4,
                    "specular": 0.6}, True),
}


@dataclass(frozen=True)
class SceneDef:
    """A named scene: a geometry (a height field of :data:`GEOMETRIES`, or ``"dome"``: a sphere of radius 0.8)
    and a material of :data:`MATERIALS`."""

    geometry: str
    material: str
    note: str = ""


SCENES: Dict[str, SceneDef] = {
    "folds_plastic": SceneDef("folds", "plastic", "accordion folds, textured rough plastic (GGX 0.25)"),
    "grooves_conductor": SceneDef("grooves", "conductor", "grooved dome, rough copper (GGX 0.3)"),
    "bowl_principled": SceneDef("bowl", "principled", "concave bowl, textured principled (metallic 0.3, rough 0.4)"),
    "dome_plastic": SceneDef("dome", "matte_plastic", "sphere, matte rough plastic (GGX 0.6): the sanity scene"),
}


def _sensor(mi, size: int, spp: int, seed: int, pixel_format: str = "rgb") -> dict:
    T = mi.ScalarTransform4f
    return {
        "type": "orthographic",
        "to_world": T.look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])
        @ T().scale([VIEW_HALF_WIDTH, VIEW_HALF_WIDTH, 1.0]),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
                 "pixel_format": pixel_format},
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
    }


def _shape(scene: SceneDef, ply: Optional[Path], bsdf: dict) -> dict:
    if scene.geometry == "dome":
        return {"type": "sphere", "radius": 0.8, "bsdf": bsdf}
    return {"type": "ply", "filename": str(ply), "face_normals": False, "bsdf": bsdf}


def _emitter_to_world(mi, l):
    """A ``directional`` emitter's frame whose direction (its local +z, where the light travels) is ``-l``."""
    d = -np.asarray(l, dtype=np.float64)
    up = [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0]
    return mi.ScalarTransform4f.look_at(origin=[0, 0, 0], target=d.tolist(), up=up)


def render_arrays(name: str, size: int = 64, lights: int = 16, spp: int = 32, seed: int = 0,
                  max_depth: int = DEFAULT_MAX_DEPTH, threads: Optional[int] = None, aov_spp: int = 64,
                  progress: Optional[Callable[[str], None]] = None) -> dict:
    """Render scene ``name`` of :data:`SCENES`; returns numpy arrays (nothing written).

    Returns a dict: ``images (L, H, W, 3)`` float32 linear radiance as if every light had unit
    irradiance, ``lights (L, 3)`` (toward the lights, DiLiGenT frame), ``intensities (L, 3)`` (the
    irradiance each light had), ``mask (H, W)`` bool, ``normals (H, W, 3)`` (unit inside the mask,
    zero outside), ``coverage (H, W)``, ``render_s``.
    """
    import torch

    from torch_hsh.render.scenes import albedo_texture, diligent_like_lights, light_intensities

    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    if max_depth < 4:
        raise ValueError(f"max_depth must be >= 4 (interreflections), got {max_depth}")
    for key, val in (("size", size), ("lights", lights), ("spp", spp)):
        if int(val) < 1:
            raise ValueError(f"{key} must be >= 1, got {val}")
    mi = import_mitsuba(threads)
    sd = SCENES[name]
    bsdf, textured = MATERIALS[sd.material]
    g = torch.Generator().manual_seed(int(seed))
    ldirs = diligent_like_lights(lights, seed=g, dtype=torch.float64).numpy()
    inten = light_intensities(lights, seed=g, dtype=torch.float64).numpy()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="torch_hsh_mts_") as tmp:
        ply = None
        if sd.geometry != "dome":
            nv = int(min(513, max(129, 3 * size)))
            ply = heightfield_ply(Path(tmp) / "object.ply", sd.geometry, nv)
        if textured:
            alb = (0.15 + 0.7 * albedo_texture(max(64, 2 * size), seed=g, dtype=torch.float64)).numpy()
            tex = {"type": "bitmap", "bitmap": mi.Bitmap(alb.astype(np.float32)), "raw": True,
                   "filter_type": "bilinear", "wrap_mode": "clamp"}
            bsdf = {k: (tex if v == _TEX else v) for k, v in bsdf.items()}
        # ground truth: the shading normal averaged over each pixel, and the coverage (an emissive twin)
        aov = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "nn:sh_normal"},
                            "sensor": _sensor(mi, size, aov_spp, seed),
                            "object": _shape(sd, ply, {"type": "diffuse"})})
        mi.render(aov, seed=int(seed))
        bm = np.array(aov.sensors()[0].film().bitmap(), dtype=np.float64)
        nsum = bm[..., -3:]
        cov = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                            "sensor": _sensor(mi, size, aov_spp, seed),
                            "object": dict(_shape(sd, ply, {"type": "diffuse"}),
                                           emitter={"type": "area", "radiance": _rgb([1.0, 1.0, 1.0])})})
        coverage = np.array(mi.render(cov, seed=int(seed)), dtype=np.float64).mean(-1)
        nlen = np.linalg.norm(nsum, axis=-1)
        mask = (coverage > 0.999) & (nlen > 1e-3)
        normals = np.where(mask[..., None], nsum / np.maximum(nlen, 1e-12)[..., None], 0.0)
        mask &= normals[..., 2] > 0
        # the images
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)},
                              "sensor": _sensor(mi, size, spp, seed),
                              "object": _shape(sd, ply, bsdf),
                              "light": {"type": "directional", "direction": [0.0, 0.0, -1.0],
                                        "irradiance": _rgb([1.0, 1.0, 1.0])}})
        params = mi.traverse(scene)
        images = np.empty((lights, size, size, 3), dtype=np.float32)
        for i in range(lights):
            params["light.to_world"] = _emitter_to_world(mi, ldirs[i])
            params.update()
            images[i] = np.array(mi.render(scene, seed=int(seed) * 100003 + i), dtype=np.float32)
            if progress is not None:
                progress(f"{name}: light {i + 1}/{lights} ({time.perf_counter() - t0:.1f} s)")
    # irradiance was 1 while rendering: the recorded images are images * intensities (linear), and
    # save_diligent takes the unit-intensity images with the intensities separately
    return {"images": images, "lights": ldirs, "intensities": inten, "mask": mask, "normals": normals,
            "coverage": coverage, "render_s": time.perf_counter() - t0}


# --------------------------------------------------------------------------- #
# Folders and the cache
def scene_params(name: str, size: int, lights: int, spp: int, seed: int, max_depth: int = DEFAULT_MAX_DEPTH) -> dict:
    """The parameters that define a rendered folder (compared with ``params.json`` to reuse the cache)."""
    return {"scene": name, "size": int(size), "lights": int(lights), "spp": int(spp), "seed": int(seed),
            "max_depth": int(max_depth), "generator_version": GENERATOR_VERSION, "variant": "scalar_rgb"}


def folder_name(name: str, size: int, lights: int, spp: int, seed: int, max_depth: int = DEFAULT_MAX_DEPTH) -> str:
    depth = "" if max_depth == DEFAULT_MAX_DEPTH else f"-depth{max_depth}"
    return f"{name}-{size}px-{lights}L-{spp}spp-seed{seed}{depth}"


def cached_params(folder: Path) -> Optional[dict]:
    """``params.json`` of a folder written by :func:`write_scene`, or None."""
    try:
        return json.loads((Path(folder) / "params.json").read_text())
    except (OSError, ValueError):
        return None


def write_scene(folder, name: str, size: int = 64, lights: int = 16, spp: int = 32, seed: int = 0,
                max_depth: int = DEFAULT_MAX_DEPTH, overwrite: bool = False, threads: Optional[int] = None,
                progress: Optional[Callable[[str], None]] = None) -> Tuple[Path, bool]:
    """Render scene ``name`` into ``folder`` (DiLiGenT layout + ``params.json``), or reuse it.

    Returns ``(folder, rendered)``: ``rendered`` is False when the folder already held these
    parameters. A non-empty folder with other (or no) parameters raises ``FileExistsError`` unless
    ``overwrite`` (then the files of the layout are replaced; nothing else is deleted).
    """
    from torch_hsh.io import save_diligent

    folder = Path(folder)
    want = scene_params(name, size, lights, spp, seed, max_depth)
    have = cached_params(folder)
    if have is not None and {k: have.get(k) for k in want} == want:
        return folder, False
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())) and not overwrite:
        why = "other parameters in its params.json" if have is not None else "no params.json of this generator"
        raise FileExistsError(f"{folder} is not empty ({why}); pass --overwrite (overwrite=True) to render into it")
    r = render_arrays(name, size, lights, spp, seed, max_depth, threads=threads, progress=progress)
    if folder.is_dir() and (folder / "params.json").exists():
        (folder / "params.json").unlink()  # a half-written folder must not look complete
    save_diligent(folder, r["images"], r["lights"], intensities=r["intensities"], mask=r["mask"],
                  normals_gt=r["normals"], overwrite=overwrite)
    import mitsuba as mi

    rec = dict(want, mitsuba_version=mi.__version__, render_s=round(r["render_s"], 2),
               mask_pixels=int(r["mask"].sum()), note=SCENES[name].note,
               frame="DiLiGenT: x right, y up, z toward the camera; row 0 at the top")
    (folder / "params.json").write_text(json.dumps(rec, indent=1) + "\n")
    return folder, True


def ensure_scene(name: str, size: int = 64, lights: int = 16, spp: int = 32, seed: int = 0,
                 max_depth: int = DEFAULT_MAX_DEPTH, root=None, overwrite: bool = False,
                 threads: Optional[int] = None, progress=None) -> Tuple[Path, bool]:
    """The folder of scene ``name`` with these parameters under ``root`` (default :func:`default_cache`),
    rendered if not cached. Returns ``(folder, rendered)``."""
    root = default_cache() if root is None else Path(root)
    folder = root / folder_name(name, size, lights, spp, seed, max_depth)
    return write_scene(folder, name, size, lights, spp, seed, max_depth, overwrite, threads, progress)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="*", help=f"scene names ({', '.join(SCENES)}); default all")
    ap.add_argument("--list", action="store_true", help="list the scenes and exit")
    ap.add_argument("--size", type=int, default=64, help="image height and width (default 64)")
    ap.add_argument("--lights", type=int, default=16, help="number of lights (default 16)")
    ap.add_argument("--spp", type=int, default=32, help="samples per pixel of each image (default 32)")
    ap.add_argument("--seed", type=int, default=0, help="light jitter, intensities, texture crop, sampler")
    ap.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH, help="path length (>= 4; default 6)")
    ap.add_argument("--out", default=None, help=f"root folder of the scene folders (default {default_cache()})")
    ap.add_argument("--overwrite", action="store_true", help="render into a non-empty folder of other parameters")
    ap.add_argument("--threads", type=int, default=None, help="Mitsuba's render threads (default: all cores)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.list:
        for k, s in SCENES.items():
            print(f"{k:20s} {s.note}")
        return 0
    names = args.scenes or list(SCENES)
    bad = [n for n in names if n not in SCENES]
    if bad:
        ap.error(f"unknown scene(s) {bad}; known: {', '.join(SCENES)}")
    if args.max_depth < 4:
        ap.error("--max-depth must be >= 4")
    say = None if args.quiet else (lambda s: print("  " + s, file=sys.stderr, flush=True))
    for n in names:
        try:
            folder, rendered = ensure_scene(n, args.size, args.lights, args.spp, args.seed, args.max_depth,
                                            root=args.out, overwrite=args.overwrite, threads=args.threads,
                                            progress=say)
        except FileExistsError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        p = cached_params(folder) or {}
        state = "rendered" if rendered else "cached"
        print(f"{n}: {state} {folder} ({p.get('mask_pixels')} mask px, render {p.get('render_s')} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
