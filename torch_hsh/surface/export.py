r"""Export of reconstructed surfaces: depth maps, meshes, shaded pictures.

Frame and units as in :mod:`torch_hsh.surface.integrate`: DiLiGenT frame
(x right, y up, z toward the camera), orthographic, pixel ``(row, col)`` at
``x = col``, ``y = -row``; depth = height ``z`` in pixel units.

* Depth maps: ``.npy`` (NumPy, dtype kept, NaN outside the mask) or
  ``.exr`` (float32 channel ``Z`` plus a ``mask`` channel, written with
  :func:`torch_hsh.io.write_exr`).
* Meshes: one vertex per mask pixel at ``(col, -row, z)``, two triangles per
  2x2 block of mask pixels (one where only three of the four are in the
  mask), wound counter-clockwise seen from the camera so face normals point
  toward ``+z``; per-vertex normals (the given normal map, e.g. the
  photometric-stereo normals, else those of the depth) and optional
  per-vertex colours (albedo, sRGB-encoded 8-bit). Built and written by
  `trimesh <https://trimesh.org>`_ (PLY, OBJ, and the other formats trimesh
  exports), an optional dependency: ``pip install torch-hsh[mesh]``.
* Pictures: :func:`shade_depth` renders the depth as a Lambertian-shaded
  image (optionally with cast shadows), independent of any normal map, so it
  shows what the integration produced.

Writers never overwrite an existing file unless ``overwrite=True``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from .._checks import check_shape, check_tensor
from .integrate import _check_depth, depth_to_normals

__all__ = ["write_depth", "depth_to_mesh", "write_mesh", "shade_depth", "MESH_EXTRA_HINT"]

#: How to get the optional mesh dependency.
MESH_EXTRA_HINT = "pip install torch-hsh[mesh]"


def _trimesh():
    try:
        import trimesh
    except ImportError as e:
        raise ImportError(
            f"mesh export in torch_hsh.surface needs the optional `trimesh` package: {MESH_EXTRA_HINT} "
            "(or pip install trimesh)"
        ) from e
    return trimesh


def _out_path(path, overwrite: bool, suffixes: Sequence[str]) -> Path:
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"`path` must end with one of {tuple(suffixes)}, got {path.name!r}")
    if path.exists() and path.is_dir():
        raise ValueError(f"`path` {path} is a folder")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_depth(path, depth: torch.Tensor, mask: Optional[torch.Tensor] = None, overwrite: bool = False) -> Path:
    r"""Write a depth map as ``.npy`` or ``.exr`` (chosen by the suffix).

    Pixels outside ``mask`` are written as NaN. ``.npy`` keeps the dtype;
    ``.exr`` stores float32 channels ``Z`` (depth) and ``mask`` (1 / 0),
    readable with :func:`torch_hsh.io.read_exr`.

    Args:
        path: output file, ``*.npy`` or ``*.exr``.
        depth: ``(H, W)`` depth (height) in pixel units.
        mask: optional ``(H, W)`` bool.
        overwrite: replace an existing file.

    Returns:
        The path written.

    Example:
        >>> write_depth(tmp_path / "depth.exr", torch.zeros(4, 5))  # doctest: +SKIP
        >>> read_exr(tmp_path / "depth.exr")["Z"].shape  # doctest: +SKIP
        (4, 5)
    """
    depth, m = _check_depth(depth, mask)
    path = _out_path(path, overwrite, (".npy", ".exr"))
    d = torch.where(m, depth.detach(), torch.full_like(depth.detach(), float("nan"))).cpu().numpy()
    if path.suffix.lower() == ".npy":
        np.save(path, d)
        return path
    from ..io.exr import write_exr

    return write_exr(path, {"Z": d.astype(np.float32), "mask": m.cpu().numpy().astype(np.float32)}, overwrite=overwrite)


def _srgb8(rgb: np.ndarray) -> np.ndarray:
    x = np.clip(rgb, 0.0, 1.0)
    enc = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(enc * 255.0).astype(np.uint8)


def _grid_faces(m: np.ndarray, idmap: np.ndarray) -> np.ndarray:
    """Triangles over 2x2 blocks of mask pixels, counter-clockwise seen from +z."""
    a, b = m[:-1, :-1], m[:-1, 1:]  # top-left, top-right
    c, d = m[1:, :-1], m[1:, 1:]  # bottom-left, bottom-right
    H, W = m.shape
    r, q = np.meshgrid(np.arange(H - 1, dtype=np.int64), np.arange(W - 1, dtype=np.int64), indexing="ij")
    ia, ib = idmap[r, q], idmap[r, q + 1]
    ic, id_ = idmap[r + 1, q], idmap[r + 1, q + 1]
    tris = []
    for sel, tri in (
        (c & d & b, (ic, id_, ib)),  # lower-right triangle of a full block, or block missing a
        (c & b & a & d, (ic, ib, ia)),  # upper-left triangle of a full block
        (c & d & a & ~b, (ic, id_, ia)),  # block missing b
        (a & d & b & ~c, (ia, id_, ib)),  # block missing c
        (c & b & a & ~d, (ic, ib, ia)),  # block missing d
    ):
        tris.append(np.stack([t[sel] for t in tri], axis=-1))
    return np.concatenate(tris, axis=0)


def depth_to_mesh(
    depth: torch.Tensor,
    mask: Optional[torch.Tensor] = None,
    normals: Optional[torch.Tensor] = None,
    albedo: Optional[torch.Tensor] = None,
    white: Optional[float] = None,
):
    r"""A triangle mesh (``trimesh.Trimesh``) of the masked depth map.

    Vertices ``(col, -row, z)`` for the mask pixels (raster order), faces
    over 2x2 blocks of mask pixels (see the module docstring), per-vertex
    normals and optional per-vertex colours.

    Args:
        depth: ``(H, W)`` depth (height) in pixel units.
        mask: optional ``(H, W)`` bool.
        normals: optional ``(H, W, 3)`` per-pixel normals for the vertices
            (e.g. the photometric-stereo normals; normalised here); default:
            :func:`torch_hsh.surface.depth_to_normals` of the depth.
        albedo: optional ``(H, W, 3)`` or ``(H, W)`` linear albedo; divided by
            ``white``, clipped to ``[0, 1]`` and sRGB-encoded to 8 bits.
        white: albedo value shown as white; default the 99th percentile of
            the masked albedo (all channels).

    Returns:
        ``trimesh.Trimesh`` (unprocessed: vertex ``k`` is the ``k``-th mask
        pixel in raster order).

    Raises:
        ImportError: trimesh is missing (``pip install torch-hsh[mesh]``).

    Example:
        >>> z = torch.zeros(3, 4); m = torch.ones(3, 4, dtype=torch.bool)
        >>> mesh = depth_to_mesh(z, m)  # doctest: +SKIP
        >>> len(mesh.vertices), len(mesh.faces)  # doctest: +SKIP
        (12, 12)
    """
    trimesh = _trimesh()
    depth, m = _check_depth(depth, mask)
    H, W = depth.shape
    mc = m.cpu().numpy()
    rows, cols = np.nonzero(mc)
    n_v = rows.size
    idmap = np.full((H, W), -1, dtype=np.int64)
    idmap[rows, cols] = np.arange(n_v, dtype=np.int64)
    z = depth.detach().cpu().numpy().astype(np.float64)
    verts = np.stack([cols.astype(np.float64), -rows.astype(np.float64), z[rows, cols]], axis=-1)
    faces = _grid_faces(mc, idmap)
    if normals is None:
        vn = depth_to_normals(depth.detach().to(torch.float64), m).cpu().numpy()[rows, cols]
    else:
        check_tensor(normals, "normals", last_dim=3, allow_nonfinite=True)
        check_shape(normals, "normals", ("H", "W", 3), sizes={"H": H, "W": W})
        vn = normals.detach().cpu().numpy().astype(np.float64)[rows, cols]
        norm = np.linalg.norm(vn, axis=-1, keepdims=True)
        if not np.all(np.isfinite(vn)) or np.any(norm == 0):
            raise ValueError("`normals` must be finite and non-zero inside `mask`")
        vn = vn / norm
    colors = None
    if albedo is not None:
        check_tensor(albedo, "albedo", allow_nonfinite=True)
        check_shape(albedo, "albedo", ("H", "W", 3), ("H", "W"), sizes={"H": H, "W": W})
        a = albedo.detach().cpu().numpy().astype(np.float64)
        if a.shape == (H, W):
            a = np.repeat(a[..., None], 3, axis=-1)
        a = a[rows, cols]
        if not np.all(np.isfinite(a)):
            raise ValueError("`albedo` contains NaN or Inf inside `mask`")
        if white is None:
            white = float(np.percentile(a, 99)) if a.size else 1.0
            white = white if white > 0 else 1.0
        elif isinstance(white, bool) or not isinstance(white, (int, float)) or not np.isfinite(white) or white <= 0:
            raise ValueError(f"`white` must be a positive number, got {white!r}")
        rgb = _srgb8(a / float(white))
        colors = np.concatenate([rgb, np.full((n_v, 1), 255, dtype=np.uint8)], axis=-1)
    return trimesh.Trimesh(
        vertices=verts, faces=faces, vertex_normals=vn, vertex_colors=colors, process=False, validate=False
    )


def write_mesh(
    path,
    depth: torch.Tensor,
    mask: Optional[torch.Tensor] = None,
    normals: Optional[torch.Tensor] = None,
    albedo: Optional[torch.Tensor] = None,
    white: Optional[float] = None,
    overwrite: bool = False,
) -> Path:
    r"""Write the mesh of :func:`depth_to_mesh` as PLY (binary) or OBJ, with normals and colours.

    Args:
        path: ``*.ply`` or ``*.obj``.
        depth, mask, normals, albedo, white: as in :func:`depth_to_mesh`.
        overwrite: replace an existing file.

    Returns:
        The path written.

    Raises:
        ImportError: trimesh is missing (``pip install torch-hsh[mesh]``).

    Example:
        >>> write_mesh(tmp_path / "cat.ply", depth, mask, normals, albedo)  # doctest: +SKIP
    """
    _trimesh()
    path = _out_path(path, overwrite, (".ply", ".obj"))
    mesh = depth_to_mesh(depth, mask, normals, albedo, white)
    if path.suffix.lower() == ".ply":
        data = mesh.export(file_type="ply", encoding="binary", include_attributes=False)
    else:
        data = mesh.export(file_type="obj", include_normals=True, include_color=True, include_texture=False)
    mode = "wb" if isinstance(data, bytes) else "w"
    with open(path, mode) as f:
        f.write(data)
    return path


def shade_depth(
    depth: torch.Tensor,
    mask: Optional[torch.Tensor] = None,
    light: Sequence[float] = (-0.4, 0.45, 0.8),
    albedo: Optional[torch.Tensor] = None,
    ambient: float = 0.15,
    shadows: bool = False,
    background: float = 1.0,
    linear: bool = False,
) -> torch.Tensor:
    r"""A shaded picture of a depth map (Lambertian, one directional light).

    ``value = albedo * (ambient + (1 - ambient) * max(0, n . l) * V)`` with
    ``n`` the normals of the depth (:func:`torch_hsh.surface.depth_to_normals`)
    and ``V`` the cast-shadow visibility (:func:`light_visibility`) if
    ``shadows``; ``background`` outside the mask; sRGB-encoded for display
    unless ``linear``. Shows the reconstructed surface itself, independent of the
    normal map it came from.

    Args:
        depth: ``(H, W)`` depth (height) in pixel units.
        mask: optional ``(H, W)`` bool.
        light: direction toward the light (DiLiGenT frame; default upper left).
        albedo: optional ``(H, W)`` or ``(H, W, 3)`` albedo in ``[0, 1]``.
        ambient: floor of the shading in ``[0, 1]``.
        shadows: also cast shadows.
        background: value outside the mask.
        linear: return linear values; ``False`` (default) encodes them with the sRGB
            curve (for PNG output).

    Returns:
        ``(H, W)`` (or ``(H, W, 3)`` with a colour albedo) float image in
        ``[0, 1]``, dtype and device of ``depth``.

    Example:
        >>> z = torch.zeros(8, 8)
        >>> img = shade_depth(z, light=(0.0, 0.0, 1.0), linear=True)
        >>> float(img[4, 4])  # flat surface facing the light
        1.0
    """
    from .visibility import light_visibility

    depth, m = _check_depth(depth, mask)
    if not 0 <= float(ambient) <= 1:
        raise ValueError(f"`ambient` must be in [0, 1], got {ambient!r}")
    lt = torch.as_tensor(light, dtype=torch.float64)
    if lt.shape != (3,) or not bool(torch.isfinite(lt).all()) or float(lt.norm()) == 0:
        raise ValueError(f"`light` must be a non-zero direction (x, y, z), got {light!r}")
    lt = lt / lt.norm()
    d = torch.where(m, depth.detach(), torch.zeros_like(depth.detach())).to(torch.float64)
    n = depth_to_normals(d, m)
    shade = (n * lt.to(n.device)).sum(-1).clamp(min=0)
    if shadows:
        shade = shade * light_visibility(d, m, lt[None].to(d.device))[0].to(shade.dtype)
    shade = ambient + (1 - ambient) * shade
    if albedo is not None:
        check_tensor(albedo, "albedo", allow_nonfinite=True)
        check_shape(albedo, "albedo", ("H", "W"), ("H", "W", 3), sizes=dict(zip("HW", m.shape)))
        a = albedo.detach().to(device=d.device, dtype=torch.float64)
        a = torch.nan_to_num(a).clamp(0, 1)
        shade = shade[..., None] * a if a.dim() == 3 else shade * a
    mm = m[..., None] if shade.dim() == 3 else m
    img = torch.where(mm, shade.clamp(0, 1), torch.full_like(shade, float(background)))
    if not linear:
        img = torch.where(img <= 0.0031308, 12.92 * img, 1.055 * img.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)
    return img.to(depth.dtype)
