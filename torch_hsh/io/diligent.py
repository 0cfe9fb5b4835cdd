r"""Photometric-stereo image stacks in the DiLiGenT folder layout.

A DiLiGenT object folder holds::

    001.png ... NNN.png      one 16-bit RGB (or grey) PNG per light (linear radiance)
    filenames.txt            image names, one a line, in light order (optional here)
    light_directions.txt     N x 3 unit light directions, whitespace separated
    light_intensities.txt    N x 3 RGB light intensities (optional here)
    mask.png                 foreground mask, > 0 inside (optional here)
    Normal_gt.mat            MATLAB file, key ``Normal_gt``, (H, W, 3) normals (optional)

Frame (the DiLiGenT frame, used everywhere in :mod:`torch_hsh` for images):
``x`` to the right, ``y`` up, ``z`` toward the camera; the camera looks along
``-z`` (orthographic). Image row 0 is the **top** of the picture, so the pixel
at ``(row, col)`` sits at ``x = col``, ``y = -row`` (times the pixel size).
Light directions point from the surface toward the light; normals point out
of the surface (``n_z > 0`` where visible).

Radiometry: the PNG values are read as linear numbers in ``[0, 1]``
(16-bit value / 65535); with ``normalize_intensities=True`` image ``i`` colour
channel ``c`` is divided by ``light_intensities[i, c]``, which gives images as
if every light had unit intensity (the usual DiLiGenT preprocessing).

Image decoding pitfalls (why this module does not use OpenCV, Pillow or plain
``imageio``/``skimage.io``):

* ``cv2.imread`` returns **BGR** channel order (and 8 bits unless
  ``IMREAD_UNCHANGED`` is passed); dividing BGR pixels by RGB intensities
  silently swaps the red and blue calibration.
* Pillow — and therefore ``skimage.io.imread`` and ``imageio.v3.imread``,
  which use it for PNG — **silently truncates 16-bit RGB PNGs to 8 bits**
  (checked with Pillow 13 / scikit-image 0.26 / imageio 2.38), and cannot write
  16-bit RGB PNGs at all.

PNGs are therefore read and written with ``kornia_rs`` (kornia's Rust
backend, a declared dependency), which keeps 16 bits exactly; every written
image is read back and compared with the codes. Palette and grey+alpha files
(8 bits or fewer, e.g. a mask saved by an image editor) are decoded by Pillow,
which is exact for them. A file that cannot be decoded raises ``ValueError``
naming it; nothing falls back silently to another decoder. Channel order is
always RGB.

8-bit photographs are accepted with a :class:`UserWarning` (they are divided
by 255 and **not** linearised: DiLiGenT-style data is linear, and an 8-bit
file is most likely a preview or a different benchmark).
"""
from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from .._checks import check_count, check_decoded_size, check_shape

__all__ = ["PhotometricDataset", "load_diligent", "save_diligent"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Tolerance on | |l| - 1 | for light directions read from a file.
UNIT_TOLERANCE = 1e-3
#: Smallest accepted ratio of the third to the first singular value of the light matrix.
LIGHT_RANK_TOLERANCE = 1e-3
_FLOAT_DTYPES = (torch.float32, torch.float64)


# --------------------------------------------------------------------------- #
# PNG helpers
# --------------------------------------------------------------------------- #
def _png_info(path: Path):
    """(width, height, bit_depth, color_type, interlace) from the IHDR chunk."""
    with open(path, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"{path} is not a PNG file (bad signature or header)")
    width, height, bit_depth, color_type, _comp, _filt, interlace = struct.unpack(">IIBBBBB", head[16:29])
    return width, height, bit_depth, color_type, interlace


#: PNG colour type -> (kornia-rs mode, samples per pixel) for the types kornia-rs decodes.
_KRS_MODES = {0: ("mono", 1), 2: ("rgb", 3), 6: ("rgba", 4)}
_KRS_MODE_BY_CHANNELS = {1: "mono", 3: "rgb", 4: "rgba"}


def _kornia_rs_png(kind: str, depth: int):
    """``kornia_rs`` PNG function ``{kind}_image_png_u{depth}`` (top level up to 0.1.11, ``kornia_rs.io`` later)."""
    try:
        import kornia_rs
    except ImportError as err:  # a declared dependency: say so instead of degrading
        raise ImportError(
            "torch_hsh.io.diligent needs kornia-rs >= 0.1.9 for PNG files (pip install 'kornia-rs>=0.1.9')"
        ) from err
    name = f"{kind}_image_png_u{depth}"
    for mod in (getattr(kornia_rs, "io", None), kornia_rs):
        fn = getattr(mod, name, None)
        if fn is not None:
            return fn
    raise ImportError(
        f"kornia_rs {getattr(kornia_rs, '__version__', '?')} has no {name}; torch_hsh needs kornia-rs >= 0.1.9"
    )


def _read_png(path: Path) -> np.ndarray:
    """Decode a PNG keeping its bit depth: (H, W) or (H, W, C) uint8/uint16, RGB order.

    Grey, RGB and RGBA files at 8 or 16 bits are decoded by ``kornia_rs``
    (bit-exact); palette, grey+alpha and sub-8-bit files (8 bits or fewer,
    where Pillow is exact) by Pillow. A file that cannot be decoded raises
    ``ValueError`` naming it; there is no fallback decoder.
    """
    path = Path(path)
    width, height, depth, ctype, _interlace = _png_info(path)
    check_decoded_size(path, width * height * {0: 1, 4: 2, 6: 4}.get(ctype, 3) * (2 if depth == 16 else 1), "PNG")
    if depth in (8, 16) and ctype in _KRS_MODES:
        mode, nch = _KRS_MODES[ctype]
        read = _kornia_rs_png("read", depth)
        try:
            img = np.asarray(read(str(path), mode))
        except BaseException as err:  # kornia_rs raises Exception / ValueError / OSError, pyo3 a PanicException
            if not isinstance(err, Exception) and type(err).__name__ != "PanicException":
                raise
            raise ValueError(f"{path}: cannot decode the {depth}-bit PNG ({type(err).__name__}: {err})") from err
        want = np.uint16 if depth == 16 else np.uint8
        if img.dtype != want or img.size != height * width * nch:
            raise ValueError(f"{path}: decoded {img.dtype} array of shape {img.shape}, expected "
                             f"{height}x{width}x{nch} {np.dtype(want).name} from the PNG header")
        img = img.reshape(height, width, nch)
        return img[..., 0] if nch == 1 else img
    if depth == 16:
        raise ValueError(f"{path}: unsupported 16-bit PNG colour type {ctype} (use grey, RGB or RGBA)")
    from PIL import Image

    try:
        with Image.open(path) as opened:
            conv = opened.convert("RGB") if ctype == 3 else (opened.convert("L") if ctype == 0 else opened)
            img = np.asarray(conv)
    except Exception as err:
        raise ValueError(f"{path}: cannot decode the PNG ({err})") from err
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.shape[:2] != (height, width):
        raise ValueError(f"{path}: decoded shape {img.shape} does not match the PNG header {height}x{width}")
    return img


def _write_png(path: Path, img: np.ndarray) -> None:
    """Write a (H, W) / (H, W, 1|3|4) uint8 or uint16 array as a PNG with ``kornia_rs``."""
    if img.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"PNG data must be uint8 or uint16, got {img.dtype}")
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in _KRS_MODE_BY_CHANNELS:
        raise ValueError(f"PNG data must have shape (H, W) or (H, W, 1|3|4), got {img.shape}")
    depth = 16 if img.dtype == np.uint16 else 8
    write = _kornia_rs_png("write", depth)
    try:
        write(str(path), np.ascontiguousarray(img), _KRS_MODE_BY_CHANNELS[img.shape[2]])
    except Exception as err:
        raise OSError(f"{path}: cannot write the {depth}-bit PNG ({err})") from err


# --------------------------------------------------------------------------- #
# text helpers
# --------------------------------------------------------------------------- #
def _read_text(path: Path, what: str) -> str:
    """Text of ``path``; a binary or non-UTF-8 file raises ``ValueError`` naming it."""
    data = path.read_bytes()
    if b"\x00" in data:
        raise ValueError(f"{path}: binary file (NUL bytes), expected a text file of {what}")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a UTF-8 text file of {what} ({err.reason} at byte {err.start})") from None


def _read_rows(path: Path, what: str) -> np.ndarray:
    """Parse an N x 3 whitespace (or comma) separated text file of floats."""
    rows = []
    for lineno, line in enumerate(_read_text(path, what + " rows").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 3:
            raise ValueError(f"{path} line {lineno}: expected 3 numbers for {what}, got {len(parts)}: {line!r}")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"{path} line {lineno}: malformed {what} row {line!r} (not numbers)") from None
        if not all(np.isfinite(vals)):
            raise ValueError(f"{path} line {lineno}: non-finite {what} row {line!r}")
        rows.append(vals)
    if not rows:
        raise ValueError(f"{path}: no {what} rows found")
    return np.asarray(rows, dtype=np.float64)


def _check_file_name(name: str, where: str) -> None:
    """``ValueError`` (``where``: the file and line) for a name no file system takes: a part over 255 bytes.

    (A NUL byte never gets here: the text reader refuses it as a binary file.)"""
    if any(len(part.encode("utf-8", "surrogateescape")) > 255 for part in name.replace("\\", "/").split("/")):
        raise ValueError(f"{where}: image name {name[:80]!r}... is not a file name (a part is longer than 255 bytes)")


def _read_names(path: Path) -> List[str]:
    """Image names of ``filenames.txt``: relative paths inside the folder, each listed once."""
    names: List[str] = []
    first_line: Dict[str, int] = {}
    for lineno, line in enumerate(_read_text(path, "image names").splitlines(), start=1):
        name = line.strip()
        if not name:
            continue
        parts = Path(name.replace("\\", "/")).parts
        if Path(name).is_absolute() or name.startswith(("/", "\\")) or ".." in parts:
            raise ValueError(f"{path} line {lineno}: image name {name!r} points outside the folder")
        _check_file_name(name, f"{path} line {lineno}")
        if name in first_line:
            raise ValueError(f"{path} line {lineno}: image name {name!r} repeats line {first_line[name]}")
        first_line[name] = lineno
        names.append(name)
    return names


def _check_images_left(source, left: int, n: int, drop_first: int, max_images: Optional[int], check: bool) -> None:
    """``left`` of ``n`` images kept by ``drop_first`` / ``max_images``: none is an error, and so are fewer than 3
    (with ``check``) when the options, not the source, removed them (the message says "images left after", which
    the CLI reports as an error of those options)."""
    if left == 0:
        raise ValueError(f"{source}: no images left after drop_first={drop_first}, max_images={max_images}")
    if check and left < 3 <= n and (drop_first or max_images is not None):
        raise ValueError(f"{source}: {left} of its {n} images left after drop_first={drop_first}, "
                         f"max_images={max_images}; photometric stereo needs at least 3")


def _check_light_geometry(lights: np.ndarray, source, first_row: int, check_rank: bool = True) -> None:
    """Reject lights below the horizon (z <= 0) and sets of rank < 3 (one direction, or coplanar)."""
    below = np.nonzero(lights[:, 2] <= 0)[0]
    if below.size:
        raise ValueError(
            f"{source}: light direction row {int(below[0]) + first_row} has z = {lights[below[0], 2]:.6g} <= 0 "
            f"(below the horizon; z points toward the camera); {below.size} such row(s)"
        )
    if not check_rank:
        return
    sv = np.linalg.svd(lights, compute_uv=False)
    if lights.shape[0] < 3 or sv[2] < LIGHT_RANK_TOLERANCE * sv[0]:
        raise ValueError(
            f"{source}: the {lights.shape[0]} light directions span fewer than 3 dimensions (singular values "
            f"{', '.join(f'{v:.3g}' for v in sv)}): all identical or coplanar (e.g. with the view), so normals "
            "cannot be recovered; photometric stereo needs at least 3 non-coplanar lights"
        )


def _is_aux_picture(name: str) -> bool:
    stem = Path(name).stem.lower()
    return stem.startswith("mask") or stem.startswith("normal")


# --------------------------------------------------------------------------- #
# public API
# --------------------------------------------------------------------------- #
@dataclass
class PhotometricDataset:
    """One photometric-stereo object (see :func:`load_diligent`).

    Attributes:
        images: ``(L, H, W, 3)`` linear RGB images (divided by the light
            intensities when loaded with ``normalize_intensities=True``); a
            grey PNG gives three equal channels.
        lights: ``(L, 3)`` unit light directions, DiLiGenT frame
            (x right, y up, z toward the camera).
        intensities: ``(L, 3)`` RGB light intensities as stored in the folder.
        mask: ``(H, W)`` bool foreground mask.
        normals_gt: ``(H, W, 3)`` ground-truth normals (same frame) or ``None``.
        names: the ``L`` image file names, in light order.
        path: the folder the data came from.
    """

    images: torch.Tensor
    lights: torch.Tensor
    intensities: torch.Tensor
    mask: torch.Tensor
    normals_gt: Optional[torch.Tensor]
    names: List[str]
    path: Path

    @property
    def num_images(self) -> int:
        """Number of images / lights ``L``."""
        return int(self.images.shape[0])

    @property
    def shape(self):
        """``(H, W)`` of the images."""
        return tuple(self.images.shape[1:3])

    def to(self, device=None, dtype=None) -> "PhotometricDataset":
        """Copy with floating tensors moved / cast (the mask stays bool)."""

        def mv(t):
            return None if t is None else t.to(device=device, dtype=dtype)

        return PhotometricDataset(
            images=mv(self.images),
            lights=mv(self.lights),
            intensities=mv(self.intensities),
            mask=self.mask.to(device=device),
            normals_gt=mv(self.normals_gt),
            names=list(self.names),
            path=self.path,
        )


def load_diligent(
    path,
    dtype: torch.dtype = torch.float32,
    device=None,
    drop_first: int = 0,
    normalize_intensities: bool = True,
    max_images: Optional[int] = None,
    check_lights: bool = True,
) -> PhotometricDataset:
    r"""Load a photometric-stereo folder in the DiLiGenT layout.

    Args:
        path: folder with the images, ``light_directions.txt`` and optionally
            ``filenames.txt``, ``light_intensities.txt``, ``mask.png``,
            ``Normal_gt.mat`` (see the module docstring).
        dtype: ``torch.float32`` or ``torch.float64`` for the float tensors.
        device: target device (default CPU).
        drop_first: skip the first ``drop_first`` images (e.g. 20 for the
            corrupted first images of DiLiGenT ``bearPNG``).
        normalize_intensities: divide image ``i`` channel ``c`` by
            ``intensities[i, c]``.
        max_images: keep at most this many images (after ``drop_first``).
        check_lights: reject kept light sets of rank < 3 (all directions
            identical, or coplanar, e.g. with the view), from which normals
            cannot be recovered. Pass ``False`` to load fewer than three
            images, e.g. held-out views. Lights below the horizon
            (``z <= 0``) are rejected either way.

    Returns:
        :class:`PhotometricDataset` with ``images`` ``(L, H, W, 3)``,
        ``lights`` ``(L, 3)`` (re-normalised to unit length), ``intensities``
        ``(L, 3)``, ``mask`` ``(H, W)`` bool, ``normals_gt`` ``(H, W, 3)`` or
        ``None``, ``names`` and ``path``.

    Image names come from ``filenames.txt`` if present, else all ``*.png``
    files sorted by name, excluding ``mask*`` and ``normal*`` pictures.
    Missing ``light_intensities.txt`` means unit intensities and missing
    ``mask.png`` means every pixel is valid (both with a warning). 8-bit
    images are accepted with a warning (divided by 255, not linearised).

    Raises:
        FileNotFoundError: missing folder, ``light_directions.txt`` or image.
        ValueError: malformed / non-unit direction rows, lights below the
            horizon (``z <= 0``) or of rank < 3 (identical or coplanar),
            binary text files, ``filenames.txt`` entries that leave the
            folder or repeat, undecodable PNG or ``Normal_gt.mat`` files
            (the message names the file), count mismatches
            between images, directions, intensities and names, images of
            different sizes or neither RGB nor grey, mask or normals of the
            wrong size, fewer than 3 images left by ``drop_first`` /
            ``max_images``.

    Example:
        >>> data = load_diligent("../shared/data/bunny_specular")  # doctest: +SKIP
        >>> data.images.shape, data.lights.shape, int(data.mask.sum())  # doctest: +SKIP
        (torch.Size([50, 256, 256, 3]), torch.Size([50, 3]), 20317)
    """
    if dtype not in _FLOAT_DTYPES:
        raise TypeError(f"`dtype` must be torch.float32 or torch.float64, got {dtype}")
    drop_first = check_count(drop_first, "drop_first")
    max_images = None if max_images is None else check_count(max_images, "max_images")
    folder = Path(path)
    if not folder.is_dir():
        raise FileNotFoundError(f"DiLiGenT folder not found: {folder}")
    ldir_file = folder / "light_directions.txt"
    lights = _read_light_directions(ldir_file)
    n = lights.shape[0]
    intens = _read_light_intensities(folder, n)
    names = _read_image_names(folder, n)

    sel = slice(drop_first, None if max_images is None else drop_first + max_images)
    names, lights, intens = names[sel], lights[sel], intens[sel]
    _check_images_left(folder, len(names), n, drop_first, max_images, check_lights)
    _check_light_geometry(lights, ldir_file, first_row=drop_first + 1, check_rank=check_lights)

    images = _read_images(folder, names, drop_first, np.float32 if dtype == torch.float32 else np.float64)
    if normalize_intensities:
        images /= intens[:, None, None, :].astype(images.dtype)
    mask = _read_foreground_mask(folder, images.shape[1:3])
    normals = _read_ground_truth(folder / "Normal_gt.mat", mask)

    def t(a):
        return torch.as_tensor(np.ascontiguousarray(a)).to(device=device, dtype=dtype)

    return PhotometricDataset(
        images=t(images),
        lights=t(lights),
        intensities=t(intens),
        mask=torch.as_tensor(mask).to(device=device),
        normals_gt=None if normals is None else t(normals),
        names=list(names),
        path=folder,
    )


# The steps of load_diligent, in its order. A warning names the caller of load_diligent (stacklevel 3).
def _read_light_directions(ldir_file: Path) -> np.ndarray:
    """``light_directions.txt``: (N, 3) rows of unit length (within UNIT_TOLERANCE), re-normalised."""
    if not ldir_file.is_file():
        raise FileNotFoundError(f"{ldir_file.parent}: missing light_directions.txt (N x 3 unit light directions)")
    lights = _read_rows(ldir_file, "light direction")
    norms = np.linalg.norm(lights, axis=1)
    bad = np.nonzero(np.abs(norms - 1.0) > UNIT_TOLERANCE)[0]
    if bad.size:
        raise ValueError(
            f"{ldir_file}: light direction row {int(bad[0]) + 1} has length {norms[bad[0]]:.6g}; "
            f"expected unit vectors (|len - 1| <= {UNIT_TOLERANCE}); {bad.size} bad row(s)"
        )
    return lights / norms[:, None]


def _read_light_intensities(folder: Path, n: int) -> np.ndarray:
    """``light_intensities.txt``: (n, 3) positive rows; ones (with a warning) when the file is missing."""
    int_file = folder / "light_intensities.txt"
    if not int_file.is_file():
        warnings.warn(f"{folder}: no light_intensities.txt; assuming unit intensities", UserWarning, stacklevel=3)
        return np.ones((n, 3))
    intens = _read_rows(int_file, "light intensity")
    if intens.shape[0] != n:
        raise ValueError(
            f"{folder}: light_intensities.txt has {intens.shape[0]} rows but light_directions.txt has {n}"
        )
    if (intens <= 0).any():
        row = int(np.nonzero((intens <= 0).any(axis=1))[0][0]) + 1
        raise ValueError(f"{int_file} row {row}: light intensities must be > 0")
    return intens


def _read_image_names(folder: Path, n: int) -> List[str]:
    """The ``n`` image names: ``filenames.txt``, else the folder's ``*.png`` pictures sorted by name."""
    names_file = folder / "filenames.txt"
    if names_file.is_file():
        names = _read_names(names_file)
        source = "filenames.txt"
    else:
        names = sorted(p.name for p in folder.glob("*.png") if not _is_aux_picture(p.name))
        source = "*.png files"
    if len(names) != n:
        raise ValueError(f"{folder}: {len(names)} image names ({source}) but {n} light directions")
    return names


def _read_images(folder: Path, names: Sequence[str], drop_first: int, dtype) -> np.ndarray:
    """The (L, H, W, 3) images of ``names`` as linear values in [0, 1] (all of one size and bit depth)."""
    images: Optional[np.ndarray] = None
    depth0 = None
    for i, name in enumerate(names):
        f = folder / name
        if not f.is_file():
            raise FileNotFoundError(f"{folder}: image {name!r} (number {i + 1 + drop_first}, listed in filenames.txt) not found")
        depth = _png_info(f)[2]
        img = _read_png(f)
        if img.ndim == 3 and img.shape[2] == 4:
            img = img[..., :3]
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[..., 0]
        if img.ndim == 2:  # a grey capture: the same value in the three channels, so the (L, H, W, 3) layout holds
            img = np.repeat(img[..., None], 3, axis=-1)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"{f}: expected an RGB or grey image, got array of shape {img.shape}")
        if images is None:
            depth0 = depth
            if depth == 8:
                warnings.warn(
                    f"{folder}: 8-bit images (expected 16-bit linear PNGs); values are divided by 255 "
                    "and not linearised",
                    UserWarning,
                    stacklevel=3,
                )
            images = np.empty((len(names),) + img.shape, dtype=dtype)
        elif img.shape != images.shape[1:]:
            raise ValueError(f"{f}: image size {img.shape[:2]} differs from the first image's {images.shape[1:3]} "
                             f"({names[0]})")
        elif depth != depth0:
            raise ValueError(f"{f}: bit depth {depth} differs from the first image's {depth0} ({names[0]})")
        images[i] = img
    assert images is not None  # at least one name (checked by the caller)
    images /= 65535.0 if depth0 == 16 else 255.0
    return images


def _read_foreground_mask(folder: Path, shape) -> np.ndarray:
    """``mask.png`` (> 0 inside) of the image ``shape`` (H, W); all True (with a warning) when missing."""
    height, width = shape
    mask_file = folder / "mask.png"
    if not mask_file.is_file():
        warnings.warn(f"{folder}: no mask.png; every pixel is treated as valid", UserWarning, stacklevel=3)
        return np.ones((height, width), dtype=bool)
    m = _read_png(mask_file)
    if m.ndim == 3:
        m = m[..., :3].max(axis=-1) if m.shape[2] in (3, 4) else m[..., 0]
    if m.shape != (height, width):
        raise ValueError(f"{mask_file}: mask size {m.shape} differs from the image size {(height, width)}")
    return m > 0


def _read_ground_truth(ngt_file: Path, mask: np.ndarray) -> Optional[np.ndarray]:
    """``Normal_gt.mat``: (H, W, 3) finite normals, of unit length inside ``mask``; None when missing."""
    if not ngt_file.is_file():
        return None
    height, width = mask.shape
    normals = _read_normal_gt(ngt_file)
    if normals.shape != (height, width, 3):
        raise ValueError(f"{ngt_file}: Normal_gt has shape {normals.shape}, expected {(height, width, 3)}")
    bad = ~np.isfinite(normals).all(axis=-1)
    if bad.any():  # outside the mask too: the error maps and metrics use the whole array
        raise ValueError(f"{ngt_file}: Normal_gt has NaN or Inf values at {int(bad.sum())} pixels "
                         f"({int((bad & mask).sum())} inside the mask)")
    inside = normals[mask]
    off = np.abs(np.linalg.norm(inside, axis=-1) - 1.0) > _UNIT_TOL
    if off.any():
        raise ValueError(f"{ngt_file}: Normal_gt is not a unit normal at {int(off.sum())} of the {len(off)} "
                         f"pixels inside the mask (|n| - 1 up to "
                         f"{float(np.abs(np.linalg.norm(inside, axis=-1) - 1.0).max()):.3g})")
    return normals


#: Largest | |n| - 1 | accepted in ``Normal_gt.mat`` inside the mask (DiLiGenT's files: 1.4e-7).
_UNIT_TOL = 1e-3

# Run in a child process: a corrupt MAT file can crash scipy's reader (a segfault, not an exception).
_MAT_READER = """
import sys
import numpy as np
import scipy.io
try:
    mat = scipy.io.loadmat(sys.argv[1])
except Exception as err:
    sys.stderr.write(f"cannot read the MATLAB file ({type(err).__name__}: {err})")
    sys.exit(3)
if "Normal_gt" not in mat:
    sys.stderr.write(f"no variable 'Normal_gt' (found {[k for k in mat if not k.startswith('__')]})")
    sys.exit(3)
try:
    a = np.asarray(mat["Normal_gt"], dtype=np.float64)
except (TypeError, ValueError) as err:
    sys.stderr.write(f"Normal_gt is not a numeric array ({err})")
    sys.exit(3)
import io
buf = io.BytesIO()  # np.save straight into a pipe can fail ("obtaining file position failed")
np.save(buf, a, allow_pickle=False)
sys.stdout.buffer.write(buf.getvalue())
"""


def _read_normal_gt(path: Path) -> np.ndarray:
    """``Normal_gt`` of a MATLAB file, read by scipy in a child process so that a corrupt file gives a
    ValueError naming it instead of killing this process."""
    import io
    import signal
    import subprocess
    import sys

    try:
        r = subprocess.run([sys.executable, "-c", _MAT_READER, str(path)], capture_output=True, timeout=600)
    except subprocess.TimeoutExpired:
        raise ValueError(f"{path}: reading the MATLAB file did not finish within 600 s") from None
    if r.returncode == 0:
        try:
            return np.load(io.BytesIO(r.stdout), allow_pickle=False)
        except ValueError as err:
            raise ValueError(f"{path}: cannot read the MATLAB file ({err})") from err
    msg = r.stderr.decode("utf-8", "replace").strip()
    if r.returncode == 3:
        raise ValueError(f"{path}: {msg}")
    if r.returncode < 0:
        try:
            how = signal.Signals(-r.returncode).name
        except ValueError:
            how = f"signal {-r.returncode}"
        raise ValueError(f"{path}: the MATLAB file is corrupt: scipy's reader crashed on it ({how})")
    last = msg.splitlines()[-1] if msg else f"exit status {r.returncode}"
    raise ValueError(f"{path}: cannot read the MATLAB file ({last})")


def _to_numpy(x, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    elif not isinstance(x, np.ndarray):
        raise TypeError(f"`{name}` must be a torch.Tensor or numpy array, got {type(x).__name__}")
    return x


def save_diligent(
    path,
    images,
    lights,
    intensities=None,
    mask=None,
    normals_gt=None,
    overwrite: bool = False,
    bit_depth: int = 16,
    scale: Optional[float] = None,
    names: Optional[Sequence[str]] = None,
) -> Path:
    r"""Write an image stack in the DiLiGenT layout (readable by :func:`load_diligent`).

    Args:
        path: output folder (created; must be empty or absent unless
            ``overwrite=True``, in which case the files this call writes are
            replaced and nothing else is touched; a ``Normal_gt.mat`` that
            this call would not replace, because ``normals_gt`` is ``None``,
            raises ``FileExistsError``).
        images: ``(L, H, W, 3)`` non-negative linear RGB images **as if lit by
            unit-intensity lights** (what :func:`load_diligent` returns with
            ``normalize_intensities=True``).
        lights: ``(L, 3)`` light directions (normalised before writing).
        intensities: optional ``(L, 3)`` positive RGB light intensities
            (default ones). The recorded pixel is ``images * intensities``.
        mask: optional ``(H, W)`` bool/0-1 mask (default: all valid).
        normals_gt: optional ``(H, W, 3)`` normals written to ``Normal_gt.mat``.
        overwrite: allow writing into a non-empty folder.
        bit_depth: 16 (default, DiLiGenT) or 8.
        scale: factor ``s`` with ``pixel / (2**bit_depth - 1) = s * images *
            intensities``; default ``1 / max(images * intensities)`` so the
            brightest value maps to the largest code. Values above 1 after
            scaling are clipped (with a warning), negatives are clipped to 0.
        names: optional image file names (default ``001.png``, ... zero padded
            to at least 3 digits).

    Scale bookkeeping: the file ``light_intensities.txt`` stores
    ``s * intensities``, so loading with ``normalize_intensities=True`` gives
    ``(pixel / max_code) / (s * intensities) = images`` back up to
    quantisation (relative error below ``0.5 / 65535`` of the maximum for
    16 bits).

    Every PNG is read back and compared with the written codes; a mismatch
    raises ``RuntimeError``.

    Returns:
        The folder path.

    Example:
        >>> L, H, W = 4, 8, 8
        >>> imgs = torch.rand(L, H, W, 3)
        >>> lights = torch.nn.functional.normalize(torch.rand(L, 3) + torch.tensor([0, 0, 1.0]), dim=-1)
        >>> out = save_diligent(tmp_path / "obj", imgs, lights)  # doctest: +SKIP
        >>> load_diligent(out).images.sub(imgs).abs().max() < 1e-4  # doctest: +SKIP
        tensor(True)
    """
    images, lights, intensities, mask, normals_gt = _check_stack(images, lights, intensities, mask, normals_gt)
    if bit_depth not in (8, 16):
        raise ValueError(f"`bit_depth` must be 8 or 16, got {bit_depth!r}")
    names = _file_names(names, images.shape[0])
    codes, scale = _to_codes(images * intensities[:, None, None, :], scale, bit_depth)

    folder = _output_folder(path, overwrite)
    if normals_gt is None and (folder / "Normal_gt.mat").exists():
        # it would be read back as the ground truth of these images, and it is not ours to delete
        raise FileExistsError(
            f"{folder / 'Normal_gt.mat'} exists and this call writes no normals_gt; remove it or pass normals_gt"
        )

    def write_checked(f: Path, data: np.ndarray) -> None:
        _write_png(f, data)
        back = _read_png(f)
        if back.dtype != data.dtype or not np.array_equal(back, data):
            raise RuntimeError(f"{f}: PNG read-back differs from the written {bit_depth}-bit data")

    for i, name in enumerate(names):
        write_checked(folder / name, codes[i])
    write_checked(folder / "mask.png", mask.astype(np.uint8) * 255)
    (folder / "filenames.txt").write_text("".join(s + "\n" for s in names))
    np.savetxt(folder / "light_directions.txt", lights, fmt="%.17g", delimiter=" ")
    np.savetxt(folder / "light_intensities.txt", intensities * scale, fmt="%.17g", delimiter=" ")
    if normals_gt is not None:
        import scipy.io

        scipy.io.savemat(str(folder / "Normal_gt.mat"), {"Normal_gt": normals_gt})
    return folder


# The steps of save_diligent, in its order. A warning names the caller of save_diligent (stacklevel 3).
def _check_stack(images, lights, intensities, mask, normals_gt):
    """The arrays of :func:`save_diligent` as float64 / bool numpy arrays of matching shapes, lights
    normalised; ``intensities`` and ``mask`` default to ones / all True."""
    images = _to_numpy(images, "images").astype(np.float64)
    lights = _to_numpy(lights, "lights").astype(np.float64)
    sizes = check_shape(images, "images", ("L", "H", "W", 3))
    n, height, width, _ = images.shape
    if n == 0:
        raise ValueError("`images` must contain at least one image")
    check_shape(lights, "lights", ("L", 3), sizes=sizes)
    if not np.isfinite(images).all():
        raise ValueError("`images` contains NaN or Inf values")
    if not np.isfinite(lights).all():
        raise ValueError("`lights` contains NaN or Inf values")
    norms = np.linalg.norm(lights, axis=1)
    if (norms < 1e-12).any():
        raise ValueError(f"`lights` row {int(np.argmin(norms))} is a zero vector")
    lights = lights / norms[:, None]
    _check_light_geometry(lights, "`lights`", first_row=1, check_rank=False)
    if intensities is None:
        intensities = np.ones((n, 3))
    else:
        intensities = _to_numpy(intensities, "intensities").astype(np.float64)
        check_shape(intensities, "intensities", ("L", 3), sizes=sizes)
        if not np.isfinite(intensities).all() or (intensities <= 0).any():
            raise ValueError("`intensities` must be finite and > 0")
    if mask is None:
        mask = np.ones((height, width), dtype=bool)
    else:
        mask = _to_numpy(mask, "mask")
        check_shape(mask, "mask", ("H", "W"), sizes=sizes)
        mask = mask.astype(bool)
    if normals_gt is not None:
        normals_gt = _to_numpy(normals_gt, "normals_gt").astype(np.float64)
        check_shape(normals_gt, "normals_gt", ("H", "W", 3), sizes=sizes)
    return images, lights, intensities, mask, normals_gt


def _file_names(names: Optional[Sequence[str]], n: int) -> List[str]:
    """``n`` distinct plain ``*.png`` names; default ``001.png``, ... (zero padded to at least 3 digits)."""
    if names is None:
        digits = max(3, len(str(n)))
        return [f"{i + 1:0{digits}d}.png" for i in range(n)]
    names = [str(s) for s in names]
    if len(names) != n or len(set(names)) != n:
        raise ValueError(f"`names` must hold {n} distinct file names, got {len(names)}")
    if any(not s.lower().endswith(".png") or "/" in s or _is_aux_picture(s) for s in names):
        raise ValueError("`names` must be plain '*.png' file names not starting with 'mask'/'normal'")
    return names


def _to_codes(raw: np.ndarray, scale: Optional[float], bit_depth: int):
    """``(codes, scale)``: ``raw * scale`` clipped to [0, 1] (with warnings) and rounded to ``bit_depth``-bit
    codes; ``scale`` defaults to ``1 / max(raw)``."""
    if scale is None:
        peak = float(raw.max())
        scale = 1.0 / peak if peak > 0 else 1.0
    else:
        scale = float(scale)
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"`scale` must be a positive finite number, got {scale}")
    max_code = (1 << bit_depth) - 1
    scaled = raw * scale
    if (scaled > 1.0 + 1e-9).any():
        warnings.warn(
            f"{int((scaled > 1.0 + 1e-9).sum())} values exceed the {bit_depth}-bit range after scaling; clipped",
            UserWarning,
            stacklevel=3,
        )
    if (scaled < 0).any():
        warnings.warn(f"{int((scaled < 0).sum())} negative image values clipped to 0", UserWarning, stacklevel=3)
    codes = np.rint(np.clip(scaled, 0.0, 1.0) * max_code).astype(np.uint16 if bit_depth == 16 else np.uint8)
    return codes, scale


def _output_folder(path, overwrite: bool) -> Path:
    """Create the output folder ``path``; an existing non-empty one only with ``overwrite``."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"`path` {folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise FileExistsError(f"{folder} is not empty; pass overwrite=True to write into it")
    folder.mkdir(parents=True, exist_ok=True)
    return folder
