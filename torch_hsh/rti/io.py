r"""Reflectance Transformation Imaging (RTI) captures: ``.lp`` light files and image folders.

An RTI capture folder holds one photograph per light (8-bit JPEG, TIFF or
PNG; 16-bit PNG/TIFF are accepted too) and a light-position file ``*.lp``::

    48                                   number of images N
    IMG_0001.jpg  0.4130 -0.2210 0.8835   file name, then lx ly lz
    IMG_0002.jpg  ...                    (N lines)

Conventions (where each one comes from):

* **``.lp`` layout** -- a count line, then ``N`` lines ``filename lx ly lz``,
  whitespace separated. This is the layout that RTIBuilder writes and that
  ISTI-CNR's ``relight`` reads (``parseLP`` in ``relight/src/lp.cpp``: the
  first line is the count, each following line must hold four tokens, a light
  closer than 1e-4 to the origin is rejected). This reader adds: blank lines and
  lines starting with ``#`` are skipped anywhere; a file name may contain
  spaces (the last three tokens are the numbers); Windows ``\`` separators are
  accepted; an absolute path that does not exist on this machine (an ``.lp``
  written on another computer) falls back to the file of the same base name in
  the ``.lp`` file's folder; relative paths are relative to the ``.lp`` file.
* **Light frame** -- ``x`` to the right of the image, ``y`` up, ``z`` toward the
  camera: the DiLiGenT frame used by the rest of :mod:`torch_hsh`. ``relight``
  computes ``.lp`` directions from a sphere highlight with the image ``y``
  inverted (``sphere.cpp``, ``computeDirections``: "inverted y coords"), i.e. in
  this frame. Directions are normalised on reading.
* **Pixel values** -- RTI photographs are display-encoded (sRGB) 8-bit images.
  Photometric stereo needs linear radiance, so the sRGB transfer curve
  (IEC 61966-2-1, :func:`torch_hsh.render.scenes.srgb_to_linear`) is **removed** on
  reading unless ``linear=True`` (``torch-hsh ps --linear-input``: the images are already linear,
  e.g. 16-bit exports from a raw converter with a linear curve). The choice is
  explicit: there is no guessing from the bit depth.

Errors: every problem with an input file raises ``ValueError`` (or
``FileNotFoundError``) whose message starts with the file name, and with the
line number for ``.lp`` files: a count that does not match the lines that
follow, a zero light vector, a line that is not ``name lx ly lz`` with finite
numbers, a light below the horizon, a missing image, images of different
sizes, an image that cannot be decoded.

HSH RTI output (:func:`write_rti_hsh`, :func:`save_relight`) -- the layouts the
viewers read, taken from their loaders (clean-room: read for the format, no
code copied; RTIViewer is GPL, this package MIT):

* **``.rti`` (RTIViewer)** -- RTIViewer's ``UniversalRti::load`` and
  ``Hsh::loadData`` (``rtiviewer/src/universalrti.cpp``, ``hsh.cpp``; also
  ``LRti::loadHSH`` in ``relight/src/legacy_rti.cpp``): text lines ``#HSH1.2``
  (comments start with ``#``), the RTI type ``3`` (HSH), ``width height 3``,
  ``terms basis_type element_size`` (we write ``terms 2 1``); then
  ``terms`` little-endian float32 **scales** and ``terms`` float32 **biases**;
  then one byte per coefficient, pixel by pixel, rows from the **top** of the
  image, and per pixel the red terms, then green, then blue. A coefficient is
  ``byte / 255 * scale[t] + bias[t]`` (one scale and bias per term, shared
  by the colours). Row order: RTIViewer renders row ``j`` of the file as image
  row ``j`` (``Hsh::createImage`` fills a top-down ``QImage``), and ``relight``
  flips rows on reading (``Y = height - 1 - y``) to its bottom-up storage.
* **relight / OpenLIME folder** -- ``RtiBuilder::saveJSON``
  (``relight/src/cli/rtibuilder.cpp``) and OpenLIME's ``LayerRTI``
  and ``ShaderRTI`` (``type: "hsh"``, ``colorspace: "rgb"``): ``info.json`` with
  ``width``, ``height``, ``format``, ``type``, ``colorspace``, ``nplanes`` (27),
  ``quality`` and ``materials: [{"scale": [27], "bias": [27]}]``; images
  ``plane_0.jpg`` ... ``plane_8.jpg``, plane ``j`` holding term ``j`` of red,
  green and blue in its three channels (standard top-down images). A
  coefficient is ``(value - bias[3 j + c]) * scale[3 j + c]`` with ``value`` the
  channel in ``[0, 1]`` (byte / 255). OpenLIME's HSH evaluates 9 terms
  (``HSH.lightWeights``), ``relight`` builds 4 or 9 (``pickBaseHSH``), so this
  layout is written for 9 terms only.

Example:
    >>> from torch_hsh.rti.io import load_rti, save_rti  # doctest: +SKIP
    >>> save_rti("capture", images, lights)              # doctest: +SKIP
    >>> data = load_rti("capture")                       # doctest: +SKIP
"""
from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from .._atomic import atomic_file, staged_folder, sweep
from .._checks import check_decoded_size, check_shape
from ..io.diligent import PhotometricDataset, _check_file_name, _output_folder, _read_png, _read_text, _to_numpy, _write_png

__all__ = [
    "read_lp",
    "write_lp",
    "find_lp",
    "is_rti_folder",
    "read_image",
    "srgb_decode",
    "srgb_encode",
    "load_rti",
    "save_rti",
    "write_rti_hsh",
    "save_relight",
    "write_deepzoom",
    "deepzoom_levels",
    "RELIGHT_LAYOUTS",
]

#: Light vectors shorter than this are rejected as zero vectors (``relight`` uses 1e-4).
MIN_LIGHT_NORM = 1e-4
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".png")


# --------------------------------------------------------------------------- #
# sRGB transfer (numpy; the torch version is torch_hsh.render.scenes.srgb_to_linear)
# --------------------------------------------------------------------------- #
def srgb_decode(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in ``[0, 1]`` to linear (IEC 61966-2-1), any shape.

    Example:
        >>> float(srgb_decode(np.array(0.5)))  # doctest: +ELLIPSIS
        0.2140...
    """
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear values in ``[0, 1]`` to sRGB encoding (inverse of :func:`srgb_decode`), any shape.

    Example:
        >>> round(float(srgb_encode(srgb_decode(np.array(0.5)))), 9)
        0.5
    """
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, None)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


# --------------------------------------------------------------------------- #
# .lp files
# --------------------------------------------------------------------------- #
def _resolve_image(name: str, lp_path: Path) -> Path:
    """Path of image ``name`` listed in ``lp_path`` (see the module docstring for the rules)."""
    clean = name.replace("\\", "/")
    is_abs = os.path.isabs(clean) or (len(clean) > 2 and clean[1] == ":" and clean[2] == "/")  # C:/...
    if is_abs:
        p = Path(clean)
        if p.is_file():
            return p
        return lp_path.parent / clean.rsplit("/", 1)[-1]  # written on another machine
    return lp_path.parent / clean


def read_lp(path, check_directions: bool = True) -> Tuple[List[str], List[Path], np.ndarray]:
    r"""Read an RTI light-position file.

    Args:
        path: the ``.lp`` file.
        check_directions: reject zero vectors and lights below the horizon
            (``z <= 0``). ``False`` still requires four tokens and finite
            numbers on each line, e.g. when only the file names are needed
            (``torch-hsh lights`` recomputes the directions).

    Returns:
        ``(names, paths, lights)``: the ``N`` names as written, the resolved
        image paths (not checked for existence), and ``(N, 3)`` float64 unit
        light directions (x right, y up, z toward the camera; rows with a zero
        vector are left at zero when ``check_directions=False``).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: naming the file and the line: missing or bad count, a count
            that does not match the lines that follow, a line that is not
            ``name lx ly lz``, non-finite numbers, a zero light vector, a light
            with ``z <= 0``.

    Example:
        >>> names, paths, lights = read_lp("capture/lights.lp")  # doctest: +SKIP
        >>> lights.shape  # doctest: +SKIP
        (48, 3)
    """
    lp = Path(path)
    if not lp.is_file():
        raise FileNotFoundError(f"{lp}: no such .lp file")
    lines = _read_text(lp, "RTI light positions").splitlines()
    entries = [(i + 1, s.strip()) for i, s in enumerate(lines) if s.strip() and not s.strip().startswith("#")]
    if not entries:
        raise ValueError(f"{lp}: empty .lp file (expected a count line, then 'filename lx ly lz' lines)")
    count_line, count_text = entries[0]
    try:
        count = int(count_text.split()[0])
        if len(count_text.split()) != 1:
            raise ValueError
    except ValueError:
        raise ValueError(f"{lp} line {count_line}: expected the number of images, got {count_text!r}") from None
    if count <= 0:
        raise ValueError(f"{lp} line {count_line}: the number of images must be > 0, got {count}")
    rows = entries[1:]
    if len(rows) != count:
        where = f"line {rows[count][0]} is one too many" if len(rows) > count else "the file ends early"
        raise ValueError(
            f"{lp} line {count_line}: the count says {count} images but {len(rows)} light line(s) follow ({where})"
        )
    names: List[str] = []
    paths: List[Path] = []
    lights = np.zeros((count, 3))
    for k, (lineno, text) in enumerate(rows):
        parts = text.rsplit(None, 3)
        if len(parts) != 4:
            raise ValueError(f"{lp} line {lineno}: expected 'filename lx ly lz', got {text!r}")
        try:
            v = np.array([float(t) for t in parts[1:]])
        except ValueError:
            raise ValueError(f"{lp} line {lineno}: the light direction is not three numbers: {text!r}") from None
        if not np.isfinite(v).all():
            raise ValueError(f"{lp} line {lineno}: non-finite light direction {text!r}")
        norm = float(np.linalg.norm(v))
        if norm < MIN_LIGHT_NORM:
            if check_directions:
                raise ValueError(f"{lp} line {lineno}: zero light vector {parts[1:]} (length {norm:.3g})")
        else:
            v = v / norm
            if check_directions and v[2] <= 0:
                raise ValueError(f"{lp} line {lineno}: light below the horizon (z = {v[2]:.4g} <= 0; "
                                 "z points toward the camera)")
            lights[k] = v
        _check_file_name(parts[0], f"{lp} line {lineno}")
        names.append(parts[0])
        paths.append(_resolve_image(parts[0], lp))
    return names, paths, lights


def write_lp(path, names: Sequence[str], lights, overwrite: bool = False) -> Path:
    """Write an ``.lp`` file: the count, then ``name lx ly lz`` lines (6 decimals).

    Args:
        path: target file (refused if it exists unless ``overwrite=True``).
        names: ``N`` image names (relative to the ``.lp`` folder, or absolute).
        lights: ``(N, 3)`` light directions (normalised before writing).

    Example:
        >>> write_lp(tmp / "lights.lp", ["a.jpg"], [[0.0, 0.0, 1.0]])  # doctest: +SKIP
    """
    p = Path(path)
    li = np.asarray(lights.detach().cpu().numpy() if isinstance(lights, torch.Tensor) else lights, dtype=np.float64)
    check_shape(li, "lights", ("N", 3), sizes={"N": len(names)})
    norms = np.linalg.norm(li, axis=1)
    if not np.isfinite(li).all() or (norms < MIN_LIGHT_NORM).any():
        raise ValueError("`lights` must be finite non-zero vectors")
    if any(len(str(n).split()) == 0 or "\n" in str(n) for n in names):
        raise ValueError("`names` must be non-empty single-line file names")
    if p.exists() and not overwrite:
        raise FileExistsError(f"{p} exists; pass overwrite=True to replace it")
    li = li / norms[:, None]
    text = f"{len(names)}\n" + "".join(f"{n} {x:.6f} {y:.6f} {z:.6f}\n" for n, (x, y, z) in zip(names, li))
    with atomic_file(p) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return p


def find_lp(folder) -> Optional[Path]:
    """The ``.lp`` file of an RTI folder, ``None`` if there is none.

    Raises:
        ValueError: several ``.lp`` files (name one with ``lp=``).

    Example:
        >>> find_lp("capture")  # doctest: +SKIP
        PosixPath('capture/lights.lp')
    """
    folder = Path(folder)
    found = sorted(p for p in folder.glob("*.lp") if p.is_file())
    if len(found) > 1:
        raise ValueError(f"{folder}: several .lp files ({', '.join(p.name for p in found)}); name the one to use")
    return found[0] if found else None


def is_rti_folder(path) -> bool:
    """True if ``path`` is an ``.lp`` file or a folder with ``*.lp`` and no DiLiGenT ``light_directions.txt``."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() == ".lp"
    return p.is_dir() and not (p / "light_directions.txt").is_file() and any(p.glob("*.lp"))


# --------------------------------------------------------------------------- #
# images
# --------------------------------------------------------------------------- #
def read_image(path) -> Tuple[np.ndarray, int]:
    """Decode one JPEG / TIFF / PNG photograph to ``(H, W, 3)`` float64 codes in ``[0, 1]``.

    8- and 16-bit RGB, RGBA (alpha dropped) and grey images (repeated to three
    channels) are accepted. No transfer curve is applied here.

    Returns:
        ``(image, bit_depth)``.

    Raises:
        FileNotFoundError: missing file. ValueError: undecodable or unsupported
        file (the message names it).

    Example:
        >>> img, bits = read_image("capture/IMG_0001.jpg")  # doctest: +SKIP
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: image not found")
    with open(p, "rb") as f:
        head = f.read(8)
    if head.startswith(b"\x89PNG"):
        a = _read_png(p)  # kornia-rs keeps 16 bits; Pillow would truncate them
    else:
        from PIL import Image

        try:
            with Image.open(p) as im:  # the header only: the size is checked before the pixels are decoded
                mode = im.mode
                depth = 2 if "16" in mode else (4 if mode in ("I", "F") else 1)
                check_decoded_size(p, im.size[0] * im.size[1] * max(3, len(im.getbands())) * depth, im.format or "image")
                if mode in ("I;16", "I;16B", "I;16L", "I"):
                    a = np.asarray(im).astype(np.uint16) if mode != "I" else np.asarray(im)
                elif mode in ("RGB", "L", "RGBA"):
                    a = np.asarray(im)
                elif mode in ("P", "LA", "CMYK", "YCbCr", "1"):
                    a = np.asarray(im.convert("RGB"))
                else:
                    raise ValueError(f"unsupported image mode {mode!r} (use 8/16-bit RGB or grey)")
        except ValueError as err:
            if str(err).startswith(str(p)):
                raise
            raise ValueError(f"{p}: cannot read the image ({err})") from None
        except Exception as err:  # Pillow raises UnidentifiedImageError / OSError / SyntaxError
            raise ValueError(f"{p}: cannot decode the image ({type(err).__name__}: {err})") from None
    if a.dtype == np.uint8:
        bits = 8
    elif a.dtype == np.uint16:
        bits = 16
    elif a.dtype in (np.int32, np.uint32) and a.size and a.max() <= 65535 and a.min() >= 0:
        a, bits = a.astype(np.uint16), 16
    else:
        raise ValueError(f"{p}: unsupported sample type {a.dtype} (use 8- or 16-bit images)")
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"{p}: expected an RGB or grey image, got an array of shape {a.shape}")
    return a[..., :3].astype(np.float64) / float((1 << bits) - 1), bits


def _read_photographs(paths: Sequence[Path], missing: Callable[[int, Path], str],
                      convert: Optional[Callable[[np.ndarray], np.ndarray]] = None, dtype=np.float64) -> np.ndarray:
    """The stack of the photographs ``paths`` (:func:`read_image`), each passed through ``convert``.

    Every photograph must have the first one's size and bit depth (``ValueError`` naming the odd one);
    a missing one raises ``FileNotFoundError`` with the message ``missing(index, path)``.

    Returns:
        ``(N, *convert(image).shape)`` array of ``dtype`` (``(N, H, W, 3)`` without ``convert``).
    """
    images: Optional[np.ndarray] = None
    bits0 = None
    shape0 = None
    for i, f in enumerate(paths):
        if not f.is_file():
            raise FileNotFoundError(missing(i, f))
        img, bits = read_image(f)
        if shape0 is None:
            shape0, bits0 = img.shape, bits
        elif img.shape != shape0:
            raise ValueError(f"{f}: image size {img.shape[1]}x{img.shape[0]} (WxH) differs from the first image's "
                             f"{shape0[1]}x{shape0[0]} ({paths[0].name})")
        elif bits != bits0:
            raise ValueError(f"{f}: bit depth {bits} differs from the first image's {bits0} ({paths[0].name})")
        img = img if convert is None else convert(img)
        if images is None:
            images = np.empty((len(paths),) + img.shape, dtype=dtype)
        images[i] = img
    if images is None:
        raise ValueError("no photographs to read")
    return images


def _read_mask(path: Path, shape) -> np.ndarray:
    if path.suffix.lower() == ".png":
        m = _read_png(path)
    else:
        m = (read_image(path)[0] * 255).astype(np.uint8)
    if m.ndim == 3:
        m = m[..., :3].max(axis=-1)
    if m.shape != tuple(shape):
        raise ValueError(f"{path}: mask size {m.shape} differs from the image size {tuple(shape)}")
    return m > 0


def load_rti(
    path,
    lp=None,
    mask=None,
    linear: bool = False,
    dtype: torch.dtype = torch.float32,
    device=None,
    drop_first: int = 0,
    max_images: Optional[int] = None,
    check_lights: bool = True,
) -> PhotometricDataset:
    r"""Load an RTI capture (``.lp`` + photographs) as a photometric-stereo dataset.

    Args:
        path: the capture folder, or the ``.lp`` file itself.
        lp: the ``.lp`` file (default: the only ``*.lp`` in the folder).
        mask: optional mask image (``> 0`` inside); default ``mask.png`` in the
            folder if present, else every pixel (with a warning).
        linear: the images are already linear; default ``False`` removes the
            sRGB transfer curve (see the module docstring).
        dtype, device: of the returned tensors.
        drop_first, max_images: keep images ``drop_first ..
            drop_first + max_images - 1``.
        check_lights: reject kept light sets of rank < 3 (as
            :func:`~torch_hsh.io.diligent.load_diligent`).

    Returns:
        :class:`~torch_hsh.io.diligent.PhotometricDataset` with ``images``
        ``(L, H, W, 3)`` linear RGB in ``[0, 1]``, ``lights`` ``(L, 3)``,
        ``intensities`` ones ``(L, 3)`` (RTI files carry none), ``mask``
        ``(H, W)``, ``normals_gt=None``, ``names`` (as written in the ``.lp``)
        and ``path`` (the folder).

    Raises:
        FileNotFoundError: missing folder, ``.lp`` or image (named).
        ValueError: bad ``.lp`` (file and line named), undecodable images,
            images of mixed sizes or bit depths (the odd one named), mask of
            the wrong size.

    Example:
        >>> data = load_rti("capture")  # doctest: +SKIP
        >>> data.images.shape, data.lights.shape  # doctest: +SKIP
        (torch.Size([48, 600, 800, 3]), torch.Size([48, 3]))
    """
    from ..io.diligent import _check_images_left, _check_light_geometry

    p = Path(path)
    if p.is_file():
        lp_path, folder = p, p.parent
    else:
        if not p.is_dir():
            raise FileNotFoundError(f"RTI folder not found: {p}")
        folder = p
        lp_path = Path(lp) if lp is not None else find_lp(p)  # type: ignore[assignment]
        if lp_path is None:
            raise FileNotFoundError(f"{p}: no .lp light-position file")
    names, paths, lights = read_lp(lp_path)
    if isinstance(drop_first, bool) or int(drop_first) != drop_first or drop_first < 0:
        raise ValueError(f"`drop_first` must be an integer >= 0, got {drop_first!r}")
    stop = None if max_images is None else int(drop_first) + int(max_images)
    sel = slice(int(drop_first), stop)
    n = len(names)
    names, paths, lights = names[sel], paths[sel], lights[sel]
    _check_images_left(lp_path, len(names), n, drop_first, max_images, check_lights)
    _check_light_geometry(lights, lp_path, first_row=int(drop_first) + 1, check_rank=check_lights)
    images = _read_photographs(
        paths, lambda i, f: f"{lp_path}: image {names[i]!r} (number {i + 1 + int(drop_first)}) not found: {f}",
        convert=None if linear else srgb_decode, dtype=np.float32 if dtype == torch.float32 else np.float64)
    shape = images.shape[1:3]
    if mask is not None:
        mpath = Path(mask)
        if not mpath.is_file():
            raise FileNotFoundError(f"{mpath}: mask not found")
        m = _read_mask(mpath, shape)
    elif (folder / "mask.png").is_file():
        m = _read_mask(folder / "mask.png", shape)
    else:
        warnings.warn(f"{folder}: no mask.png; every pixel is treated as valid", UserWarning, stacklevel=2)
        m = np.ones(shape, dtype=bool)

    def t(a):
        return torch.as_tensor(np.ascontiguousarray(a)).to(device=device, dtype=dtype)

    return PhotometricDataset(images=t(images), lights=t(lights), intensities=t(np.ones((len(names), 3))),
                              mask=torch.as_tensor(m).to(device=device), normals_gt=None, names=list(names),
                              path=folder)


def save_rti(
    path,
    images,
    lights,
    mask=None,
    fmt: str = "png",
    linear: bool = False,
    scale: Optional[float] = None,
    names: Optional[Sequence[str]] = None,
    lp_name: str = "lights.lp",
    quality: int = 95,
    overwrite: bool = False,
) -> Path:
    r"""Write linear images as an RTI capture folder (8-bit images + ``.lp``), readable by :func:`load_rti`.

    Args:
        path: output folder (created; must be empty unless ``overwrite``).
        images: ``(L, H, W, 3)`` non-negative linear RGB images (e.g. from
            :func:`torch_hsh.render.render`).
        lights: ``(L, 3)`` light directions.
        mask: optional ``(H, W)`` bool mask written as ``mask.png``.
        fmt: ``"png"`` (lossless, default), ``"jpg"`` or ``"tif"``.
        linear: ``False`` (default) applies the sRGB curve before quantising (what a
            camera's JPEG holds); ``True`` writes linear codes (read them back with
            ``load_rti(..., linear=True)``).
        scale: exposure: codes are ``round(255 * T(scale * images))``, default
            ``1 / max(images)``; values above 1 are clipped with a warning.
        names: image names (default ``img_001.<fmt>``...).
        lp_name: name of the ``.lp`` file.
        quality: JPEG quality.
        overwrite: allow writing into a non-empty folder.

    Returns:
        The folder.

    Example:
        >>> from torch_hsh.render import render, scenes
        >>> n, m = scenes.sphere_normals(32)
        >>> li = scenes.diligent_like_lights(8, seed=0)
        >>> imgs = render(n, li, lambda wi, wo: torch.full(wi.shape[:-1] + (3,), 0.3))
        >>> save_rti(tmp_path / "cap", imgs, li, mask=m)  # doctest: +SKIP
    """
    from PIL import Image

    imgs = _to_numpy(images, "images").astype(np.float64)
    li = _to_numpy(lights, "lights").astype(np.float64)
    sizes = check_shape(imgs, "images", ("L", "H", "W", 3))
    n = imgs.shape[0]
    if n == 0:
        raise ValueError("`images` must hold at least one image")
    check_shape(li, "lights", ("L", 3), sizes=sizes)
    if not np.isfinite(imgs).all():
        raise ValueError("`images` contains NaN or Inf values")
    fmt = fmt.lower().lstrip(".")
    if fmt not in ("png", "jpg", "tif"):
        raise ValueError(f"`fmt` must be 'png', 'jpg' or 'tif', got {fmt!r}")
    if names is None:
        names = [f"img_{i + 1:03d}.{fmt}" for i in range(n)]
    names = [str(s) for s in names]
    if len(names) != n or len(set(names)) != n:
        raise ValueError(f"`names` must hold {n} distinct file names")
    if scale is None:
        peak = float(imgs.max())
        scale = 1.0 / peak if peak > 0 else 1.0
    scaled = imgs * float(scale)
    if (scaled > 1 + 1e-9).any():
        warnings.warn(f"{int((scaled > 1 + 1e-9).sum())} values exceed the 8-bit range after scaling; clipped",
                      UserWarning, stacklevel=2)
    scaled = np.clip(scaled, 0.0, 1.0)
    codes = np.rint((scaled if linear else srgb_encode(scaled)) * 255).astype(np.uint8)
    folder = _output_folder(path, overwrite)
    for name, c in zip(names, codes):
        f = folder / name
        if fmt == "png":
            _write_png(f, c)
        elif fmt == "jpg":
            Image.fromarray(c).save(f, quality=int(quality), subsampling=0)
        else:
            Image.fromarray(c).save(f)
    if mask is not None:
        m = _to_numpy(mask, "mask").astype(bool)
        check_shape(m, "mask", ("H", "W"), sizes=sizes)
        _write_png(folder / "mask.png", m.astype(np.uint8) * 255)
    write_lp(folder / lp_name, names, li, overwrite=overwrite)
    return folder



# --------------------------------------------------------------------------- #
# HSH RTI output
# --------------------------------------------------------------------------- #
def _coeff_maps(coefficients) -> np.ndarray:
    c = _to_numpy(coefficients, "coefficients").astype(np.float64)
    check_shape(c, "coefficients", ("H", "W", 3, 9), ("H", "W", 3, 16))  # the 9 or 16 terms of the RTI HSH basis
    if not np.isfinite(c).all():
        raise ValueError("`coefficients` contains NaN or Inf values")
    return c


def _quantise(v: np.ndarray, lo: np.ndarray, span: np.ndarray) -> np.ndarray:
    return np.clip(np.rint((v - lo) / span * 255.0), 0, 255).astype(np.uint8)


def write_rti_hsh(path, coefficients, overwrite: bool = False) -> Path:
    r"""Write RTI HSH coefficient maps as an RTIViewer ``.rti`` file (layout in the module docstring).

    Args:
        path: target ``.rti`` file (refused if it exists unless ``overwrite``).
        coefficients: ``(H, W, 3, T)`` coefficients of the RTI HSH basis
            (:func:`torch_hsh.rti.rti_hsh_basis`, ``T`` = 9 or 16), in display
            units (1 = white), row 0 at the top of the image.

    Quantisation: per term ``t``, ``bias = min`` and ``scale = max - min`` over
    every pixel and colour, so the error of a coefficient is at most
    ``scale[t] / 510``.

    Returns:
        The path.

    Example:
        >>> write_rti_hsh("object.rti", project_to_rti(res.normals, res.coefficients, 9))  # doctest: +SKIP
    """
    c = _coeff_maps(coefficients)
    H, W, _, T = c.shape
    p = Path(path)
    if p.exists() and not overwrite:
        raise FileExistsError(f"{p} exists; pass overwrite=True to replace it")
    lo = c.min(axis=(0, 1, 2))
    span = c.max(axis=(0, 1, 2)) - lo
    span = np.where(span > 0, span, 1.0)
    codes = _quantise(c, lo, span)  # (H, W, 3, T): per pixel R terms, G terms, B terms
    head = f"#HSH1.2\n3\n{W} {H} 3\n{T} 2 1\n".encode("ascii")
    data = head + span.astype("<f4").tobytes() + lo.astype("<f4").tobytes() + np.ascontiguousarray(codes).tobytes()
    with atomic_file(p) as tmp:
        tmp.write_bytes(data)
    return p


#: Layouts of the relight / OpenLIME folder (:func:`save_relight`), named as OpenLIME's ``Layer({layout: ...})``.
RELIGHT_LAYOUTS = ("image", "deepzoom", "deepzoom1px")
#: Deep Zoom tiles: 254 pixels a side plus a 1-pixel overlap (what libvips and relight write; 256 with both overlaps).
DEEPZOOM_TILE = 254
DEEPZOOM_OVERLAP = 1


def _halve(img: np.ndarray) -> np.ndarray:
    """Next Deep Zoom level: ``(ceil(H/2), ceil(W/2))``, each pixel the rounded mean of its 2 x 2 block (an odd last
    row or column is repeated). The codes are an affine function of the coefficients (one scale and bias per plane),
    so this is the mean of the coefficients too."""
    h, w = img.shape[:2]
    a = np.pad(img.astype(np.uint16), ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    s = a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]
    return ((s + 2) // 4).astype(np.uint8)


def deepzoom_levels(width: int, height: int, tile: int = DEEPZOOM_TILE, layout: str = "deepzoom") -> List[Tuple[int, int]]:
    """``(width, height)`` of each folder ``0, 1, ...`` of a Deep Zoom pyramid, the last one full size.

    * ``"deepzoom1px"``: the Deep Zoom specification -- level ``k`` is ``ceil(W / 2^(M - k))`` wide with
      ``M = ceil(log2(max(W, H)))``, so level 0 is 1 x 1 (what libvips writes; OpenSeadragon reads it).
    * ``"deepzoom"``: the same sizes from the first level that fits one tile: folder 0 is one tile
      (what relight writes and OpenLIME's ``layout: "deepzoom"`` reads: it fetches folders
      ``0 .. ceil(log2(max(W, H) / tile))``).

    Example:
        >>> deepzoom_levels(600, 300)
        [(150, 75), (300, 150), (600, 300)]
        >>> len(deepzoom_levels(600, 300, layout="deepzoom1px"))
        11
    """
    if layout not in ("deepzoom", "deepzoom1px"):
        raise ValueError(f"`layout` must be 'deepzoom' or 'deepzoom1px', got {layout!r}")
    big = max(int(width), int(height))
    top = (big - 1).bit_length()  # ceil(log2(big)); 0 for a 1 x 1 image
    sizes = [(-(-int(width) // (1 << (top - k))), -(-int(height) // (1 << (top - k)))) for k in range(top + 1)]
    if layout == "deepzoom":
        sizes = [wh for wh in sizes if max(wh) <= tile][-1:] + [wh for wh in sizes if max(wh) > tile]
    return sizes


def _write_tile(f: Path, img: np.ndarray, fmt: str, quality: int) -> None:
    from PIL import Image

    img = np.ascontiguousarray(img)
    if fmt == "png":
        _write_png(f, img)
    else:
        Image.fromarray(img).save(f, quality=int(quality), subsampling=0)


def write_deepzoom(base, image: np.ndarray, fmt: str = "jpg", quality: int = 95, layout: str = "deepzoom",
                   tile: int = DEEPZOOM_TILE, overlap: int = DEEPZOOM_OVERLAP) -> Path:
    r"""Write an 8-bit RGB image as a Deep Zoom pyramid: ``BASE.dzi`` and ``BASE_files/LEVEL/COL_ROW.FMT``.

    Tile ``(col, row)`` of a level ``w x h`` holds the pixels ``[col tile - overlap, (col + 1) tile + overlap)``
    (clipped to ``[0, w)``; no overlap before the first column), the same for rows; levels halve the size
    rounding up (:func:`deepzoom_levels`; ``layout`` picks the first level), each pixel the mean of a 2 x 2 block.

    Args:
        base: the path without suffix (``folder/plane_0``).
        image: ``(H, W, 3)`` uint8.
        fmt: ``"jpg"`` or ``"png"`` (the ``Format`` of the ``.dzi``: OpenLIME takes the tiles' suffix from it).

    Returns:
        The ``.dzi`` path.
    """
    import shutil

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"`image` must be (H, W, 3) uint8, got {img.dtype} {img.shape}")
    base = Path(base)
    H, W = img.shape[:2]
    sizes = deepzoom_levels(W, H, tile, layout)
    files = base.with_name(base.name + "_files")
    if files.exists():
        shutil.rmtree(files)  # tiles of an earlier export (another size or layout) must not linger
    levels = [img]
    while len(levels) < len(sizes):
        levels.append(_halve(levels[-1]))
    for k, ((w, h), lev) in enumerate(zip(sizes, reversed(levels))):
        assert lev.shape[:2] == (h, w), (lev.shape, w, h)
        d = files / str(k)
        d.mkdir(parents=True)
        for row in range(-(-h // tile)):
            y0, y1 = max(0, row * tile - overlap), min(h, (row + 1) * tile + overlap)
            for col in range(-(-w // tile)):
                x0, x1 = max(0, col * tile - overlap), min(w, (col + 1) * tile + overlap)
                _write_tile(d / f"{col}_{row}.{fmt}", lev[y0:y1, x0:x1], fmt, quality)
    dzi = base.with_name(base.name + ".dzi")
    dzi.write_text('<?xml version="1.0" encoding="UTF-8"?>\n'
                   f'<Image xmlns="http://schemas.microsoft.com/deepzoom/2008" Format="{fmt}" Overlap="{overlap}" '
                   f'TileSize="{tile}">\n  <Size Width="{W}" Height="{H}"/>\n</Image>\n', encoding="utf-8")
    return dzi


def save_relight(path, coefficients, fmt: str = "jpg", quality: int = 95, overwrite: bool = False,
                 layout: str = "image") -> Path:
    r"""Write 9-term RTI HSH coefficient maps as a relight / OpenLIME folder (``info.json`` + planes).

    Args:
        path: output folder (created; must be empty unless ``overwrite``).
        coefficients: ``(H, W, 3, 9)`` coefficients (as :func:`write_rti_hsh`).
        fmt: ``"jpg"`` (default; what relight writes, lossy) or ``"png"``
            (lossless, ``"format": "png"`` in ``info.json``).
        quality: JPEG quality (written to ``info.json`` too).
        layout: how the planes are stored, named as OpenLIME's ``Layer({type: "rti", layout})`` that reads them:
            ``"image"`` (default): one ``plane_N.FMT`` per plane; ``"deepzoom"``: a Deep Zoom pyramid per plane,
            ``plane_N.dzi`` + ``plane_N_files/LEVEL/COL_ROW.FMT``, 254-pixel tiles with a 1-pixel overlap, folder 0
            the level that fits one tile (relight's layout, the one OpenLIME's ``"deepzoom"`` reads);
            ``"deepzoom1px"``: the same with every level of the Deep Zoom specification, down to 1 x 1
            (OpenSeadragon; OpenLIME 1.2 has no RTI loader for it). See :func:`write_deepzoom`.

    Quantisation: per plane (term and colour) ``scale = max - min`` and
    ``bias = -min / scale``; the error of a coefficient is at most
    ``scale / 510`` plus the JPEG error. The full-size level of a pyramid holds
    the same codes as the ``image`` layout.

    Returns:
        The folder.

    Example:
        >>> save_relight("object_relight", project_to_rti(res.normals, res.coefficients, 9))  # doctest: +SKIP
    """
    import json

    c = _coeff_maps(coefficients)
    if c.shape[3] != 9:
        raise ValueError(f"relight/OpenLIME evaluate 9 HSH terms; got {c.shape[3]}")
    fmt = fmt.lower().lstrip(".")
    if fmt not in ("jpg", "png"):
        raise ValueError(f"`fmt` must be 'jpg' or 'png', got {fmt!r}")
    if layout not in RELIGHT_LAYOUTS:
        raise ValueError(f"`layout` must be one of {', '.join(RELIGHT_LAYOUTS)}, got {layout!r}")
    H, W = c.shape[:2]
    folder = _relight_target(path, overwrite)
    planes = c.transpose(0, 1, 3, 2).reshape(H, W, 27)  # plane index 3 j + colour
    lo = planes.min(axis=(0, 1))
    span = planes.max(axis=(0, 1)) - lo
    span = np.where(span > 0, span, 1.0)
    codes = _quantise(planes, lo, span)
    with staged_folder(folder) as stage:  # the folder is replaced as a whole when every file is written
        for j in range(9):
            img = np.ascontiguousarray(codes[..., 3 * j: 3 * j + 3])
            if layout == "image":
                _write_tile(stage / f"plane_{j}.{fmt}", img, fmt, quality)
            else:
                write_deepzoom(stage / f"plane_{j}", img, fmt=fmt, quality=quality, layout=layout)
        info = {"width": W, "height": H, "format": fmt, "type": "hsh", "colorspace": "rgb", "nplanes": 27,
                "quality": int(quality), "materials": [{"scale": [float(v) for v in span],
                                                        "bias": [float(v) for v in -lo / span]}]}
        (stage / "info.json").write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    return folder


_RELIGHT_ENTRY = re.compile(r"info\.json|plane_\d+(\.(jpg|png|dzi)|_files)")


def _relight_foreign_entries(path) -> List[str]:
    """Entries of the folder ``path`` that :func:`save_relight` does not write (``[]`` if it is missing or empty)."""
    folder = Path(path)
    return sorted(n for n in os.listdir(folder) if not _RELIGHT_ENTRY.fullmatch(n)) if folder.is_dir() else []


def _relight_target(path, overwrite: bool) -> Path:
    """The relight folder to replace (its parents created): a non-empty one only with ``overwrite``, and only if
    it holds nothing but what :func:`save_relight` writes (a file of the user's there would be lost)."""
    folder = Path(os.path.abspath(path))
    sweep(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"`path` {folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise FileExistsError(f"{folder} is not empty; pass overwrite=True to replace it")
    foreign = _relight_foreign_entries(folder)
    if foreign:
        raise FileExistsError(f"{folder} holds files that are not a relight folder's ({', '.join(foreign[:5])}); "
                              "they would be lost when it is replaced: move them or choose another folder")
    folder.parent.mkdir(parents=True, exist_ok=True)
    return folder
