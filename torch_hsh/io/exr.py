r"""OpenEXR reading and writing (via the ``OpenEXR`` >= 3.2 Python package).

All readers return ``float32`` NumPy arrays (half-float files are widened
exactly); writers accept NumPy arrays or torch tensors (float, int or bool
dtypes, cast to float32, or to float16 with ``half=True``) and always write ZIP-compressed
scanline single-part files.

Channel naming: EXR stores channels sorted by name. A multi-channel array
``(H, W, C)`` given under the name ``"normal"`` is written as ``normal.X``,
``normal.Y``, ``normal.Z`` for ``C = 3`` with ``"X","Y","Z"`` suffixes when the
name says so, otherwise ``name.R/G/B(/A)`` for 3 or 4 channels and
``name.0``, ``name.1``, ... beyond; an empty name writes bare ``R``, ``G``,
``B``. The coefficient-map helpers record the coefficient order in a header
attribute so that it survives the alphabetical sorting.

Pitfalls of the ``OpenEXR`` bindings handled here: ``OpenEXR.File(header,
channels)`` replaces the arrays in the ``channels`` dict it is given by
``Channel`` objects (we always pass a fresh dict), it writes non-contiguous
arrays incorrectly (we make them contiguous), and it rejects float64.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch

from .._checks import check_decoded_size, check_shape

__all__ = [
    "read_exr",
    "write_exr",
    "write_image_stack_exr",
    "read_image_stack_exr",
    "write_normal_map_exr",
    "write_coefficient_maps_exr",
    "read_coefficient_maps_exr",
    "read_envmap",
]

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
_COEFF_ATTR = "torch_hsh_coefficients"
_COLOR_ATTR = "torch_hsh_colors"


def _openexr():
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover - dependency declared in setup.py
        raise ImportError("torch_hsh.io.exr needs the `OpenEXR` package (pip install OpenEXR)") from e
    return OpenEXR


def _as_array(x, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        if x.dtype == torch.bfloat16:
            x = x.float()
        x = x.numpy()
    elif not isinstance(x, np.ndarray):
        raise TypeError(f"`{name}` must be a numpy array or torch.Tensor, got {type(x).__name__}")
    if x.dtype.kind not in "fiub":
        raise TypeError(f"`{name}` must hold real numbers or bools, got dtype {x.dtype}")
    return x


def _check_existing(path: Path, what: str) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != _EXR_MAGIC:
        raise ValueError(f"{path} is not an OpenEXR file (bad magic number)")


def _suffixes(name: str, c: int) -> List[str]:
    if c == 3 and name.lower().startswith("normal"):
        return ["X", "Y", "Z"]
    if c == 3:
        return ["R", "G", "B"]
    if c == 4:
        return ["R", "G", "B", "A"]
    width = len(str(c - 1))
    return [f"{k:0{width}d}" for k in range(c)]


def write_exr(path, channels: Mapping[str, Any], half: bool = False, overwrite: bool = False, header=None) -> Path:
    r"""Write named channels to a single-part OpenEXR file.

    Args:
        path: output ``.exr`` file.
        channels: ``name -> array``; each array is ``(H, W)`` (one channel) or
            ``(H, W, C)`` (expanded to ``name.R/G/B[/A]``, ``normal*.X/Y/Z``
            or ``name.0 ... name.{C-1}``; an empty name gives bare ``R``,
            ``G``, ``B``). All channels must share ``(H, W)``. Names use
            letters, digits, ``_``, ``.`` and ``-``.
        half: store float16 (values beyond +-65504 become inf) instead of float32.
        overwrite: replace an existing file.
        header: optional extra header attributes (``str``/``int``/``float``).

    Returns:
        The path written.

    Example:
        >>> write_exr(tmp_path / "a.exr", {"Z": np.zeros((4, 5))})  # doctest: +SKIP
        >>> read_exr(tmp_path / "a.exr")["Z"].shape  # doctest: +SKIP
        (4, 5)
    """
    OpenEXR = _openexr()
    path = Path(path)
    if not isinstance(channels, dict) or not channels:
        raise TypeError("`channels` must be a non-empty dict name -> (H, W) or (H, W, C) array")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    if path.exists() and path.is_dir():
        raise ValueError(f"`path` {path} is a folder")
    dt = np.float16 if half else np.float32
    flat: Dict[str, np.ndarray] = {}
    hw: Optional[Tuple[int, int]] = None
    for name, arr in channels.items():
        if not isinstance(name, str):
            raise TypeError(f"channel names must be str, got {name!r}")
        arr = _as_array(arr, f"channels[{name!r}]")
        if arr.ndim == 2:
            parts = {name: arr}
        elif arr.ndim == 3:
            sfx = _suffixes(name, arr.shape[2])
            parts = {(f"{name}.{s}" if name else s): arr[:, :, k] for k, s in enumerate(sfx)}
        else:
            raise ValueError(f"`channels[{name!r}]` must be (H, W) or (H, W, C), got shape {arr.shape}")
        if hw is None:
            hw = arr.shape[:2]
        elif arr.shape[:2] != hw:
            raise ValueError(f"`channels[{name!r}]` has size {arr.shape[:2]}, other channels have {hw}")
        if hw[0] == 0 or hw[1] == 0:
            raise ValueError("channels must have a non-zero height and width")
        for cname, a in parts.items():
            if not cname or not _NAME_RE.match(cname):
                raise ValueError(f"invalid EXR channel name {cname!r} (letters, digits, '_', '.', '-')")
            if cname in flat:
                raise ValueError(f"duplicate EXR channel name {cname!r}")
            flat[cname] = np.ascontiguousarray(a, dtype=dt)
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if header:
        for k, v in header.items():
            if not isinstance(v, (str, int, float)):
                raise TypeError(f"header attribute {k!r} must be str, int or float, got {type(v).__name__}")
            hdr[str(k)] = v
    path.parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File(hdr, dict(flat)) as f:
        f.write(str(path))
    return path


def _open(path, what: str, **kwargs):
    """``OpenEXR.File`` with every failure (corrupt, truncated) as a ``ValueError`` naming the file."""
    OpenEXR = _openexr()
    path = Path(path)
    _check_existing(path, what)
    if not kwargs.get("header_only"):
        _check_exr_size(path, what)
    try:
        f = OpenEXR.File(str(path), **kwargs)
        n_parts = len(f.parts)
    except Exception as e:
        raise ValueError(f"could not read OpenEXR file {path}: {e}") from e
    if n_parts == 0:  # the bindings swallow pixel-read errors and return a file without parts
        raise ValueError(f"could not read OpenEXR file {path}: corrupt or truncated pixel data")
    return f


def _check_exr_size(path: Path, what: str) -> None:
    """Refuse a data window whose pixels could not fit in the file, before the bindings allocate them."""
    with _open(path, what, header_only=True) as f:
        total = 0
        for part in f.parts:
            lo, hi = part.header.get("dataWindow", ((0, 0), (-1, -1)))
            w, h = int(hi[0]) - int(lo[0]) + 1, int(hi[1]) - int(lo[1]) + 1
            total += max(w, 0) * max(h, 0) * 4 * len(part.header.get("channels", ()))
    check_decoded_size(path, total, "OpenEXR")


def _read_file(path, what="EXR file"):
    return _open(path, what, separate_channels=True)


def read_exr(path) -> Dict[str, np.ndarray]:
    r"""Read every channel of the first part of an OpenEXR file.

    Args:
        path: an ``.exr`` file.

    Returns:
        ``dict`` channel name -> ``(H, W)`` float32 array (half and float
        channels are widened; uint channels converted), in the file's
        (alphabetical) channel order.

    Raises:
        FileNotFoundError: missing file. ValueError: not an OpenEXR file.

    Example:
        >>> ch = read_exr("../shared/data/envmaps/venice_sunset_1k.exr")  # doctest: +SKIP
        >>> sorted(ch), ch["R"].shape  # doctest: +SKIP
        (['B', 'G', 'R'], (512, 1024))
    """
    f = _read_file(path)
    with f:
        return {name: np.asarray(c.pixels, dtype=np.float32) for name, c in f.channels().items()}


def _read_header(path) -> dict:
    with _open(path, "EXR file", header_only=True) as f:
        return dict(f.header())


def write_image_stack_exr(path, images, overwrite: bool = False, half: bool = False) -> Path:
    r"""Write an ``(L, H, W, 3)`` (or ``(L, H, W)``) image stack as one EXR.

    Image ``i`` becomes the layer ``img{i:0Nd}`` with channels
    ``img000.R/G/B`` (zero padded so the alphabetical order is the stack
    order). Read back with :func:`read_image_stack_exr`.

    Example:
        >>> write_image_stack_exr(tmp_path / "s.exr", torch.rand(5, 8, 8, 3))  # doctest: +SKIP
    """
    arr = _as_array(images, "images")
    check_shape(arr, "images", ("L", "H", "W"), *[("L", "H", "W", c) for c in (1, 3, 4)])
    if arr.shape[0] == 0:
        raise ValueError("`images` must hold at least one image")
    if arr.ndim == 4 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    width = max(3, len(str(arr.shape[0] - 1)))
    chans = {f"img{i:0{width}d}": arr[i] for i in range(arr.shape[0])}
    return write_exr(path, chans, half=half, overwrite=overwrite, header={"torch_hsh_stack": int(arr.shape[0])})


def read_image_stack_exr(path) -> np.ndarray:
    r"""Read a stack written by :func:`write_image_stack_exr`: ``(L, H, W, C)`` float32 (or ``(L, H, W)``)."""
    ch = read_exr(path)
    layers: Dict[str, Dict[str, np.ndarray]] = {}
    for name, a in ch.items():
        m = re.match(r"^img(\d+)(?:\.([RGBA]))?$", name)
        if not m:
            raise ValueError(f"{path}: channel {name!r} is not part of an image stack written by torch_hsh")
        layers.setdefault(m.group(1), {})[m.group(2) or ""] = a
    out = []
    for key in sorted(layers, key=int):
        d = layers[key]
        if "" in d:
            out.append(d[""])
        elif len({a.shape for a in d.values()}) == 1:
            out.append(np.stack([d[c] for c in "RGBA" if c in d], axis=-1))
        else:
            raise ValueError(f"{path}: the channels of image {key} differ in size (subsampled channels)")
    if len({a.shape for a in out}) > 1:
        raise ValueError(f"{path}: the images of the stack differ in size or channels "
                         f"({sorted({a.shape for a in out})})")
    return np.stack(out, axis=0)


def write_normal_map_exr(path, normals, mask=None, overwrite: bool = False) -> Path:
    r"""Write an ``(H, W, 3)`` normal map as ``normal.X/Y/Z`` float32 (plus ``mask`` if given).

    The values are written unchanged (no remapping to ``[0, 1]``); pixels
    outside ``mask`` are set to 0.

    Example:
        >>> n, m = sphere_normals(32)  # doctest: +SKIP
        >>> write_normal_map_exr(tmp_path / "n.exr", n, m)  # doctest: +SKIP
        >>> read_exr(tmp_path / "n.exr")["normal.Z"].shape  # doctest: +SKIP
        (32, 32)
    """
    n = _as_array(normals, "normals").astype(np.float32)
    sizes = check_shape(n, "normals", ("H", "W", 3))
    chans = {"normal": n}
    if mask is not None:
        m = _as_array(mask, "mask").astype(bool)
        check_shape(m, "mask", ("H", "W"), sizes=sizes)
        n = np.where(m[..., None], n, 0.0).astype(np.float32)
        chans = {"normal": n, "mask": m.astype(np.float32)}
    return write_exr(path, chans, overwrite=overwrite)


def write_coefficient_maps_exr(
    path,
    coefficients,
    names: Optional[Sequence[str]] = None,
    colors: Optional[Sequence[str]] = None,
    overwrite: bool = False,
) -> Path:
    r"""Write per-pixel basis coefficients ``(H, W, C, K)`` as float32 channels ``color.name``.

    Args:
        path: output ``.exr`` file.
        coefficients: ``(H, W, C, K)`` array/tensor (``C`` colour channels, ``K``
            basis coefficients); a ``(H, W, K)`` array is treated as ``C = 1``.
        names: ``K`` coefficient names, e.g. ``"a_2_1_0"`` for the isotropic
            triple ``(p, r, q) = (2, 1, 0)``; default ``c0000, c0001, ...``.
        colors: ``C`` colour names; default ``R, G, B`` for ``C = 3``,
            ``Y`` for ``C = 1``, else ``C0, C1, ...``.
        overwrite: replace an existing file.

    Channels are named ``f"{color}.{name}"`` (e.g. ``"R.a_2_1_0"``); the
    orders of ``names`` and ``colors`` are stored in header attributes, so
    :func:`read_coefficient_maps_exr` restores the exact array (bit exact in
    float32).

    Example:
        >>> c = torch.randn(16, 16, 3, 10)
        >>> write_coefficient_maps_exr(tmp_path / "c.exr", c)  # doctest: +SKIP
        >>> np.array_equal(read_coefficient_maps_exr(tmp_path / "c.exr")[0], c.numpy())  # doctest: +SKIP
        True
    """
    a = _as_array(coefficients, "coefficients").astype(np.float32)
    check_shape(a, "coefficients", ("H", "W", "C", "K"), ("H", "W", "K"))
    if a.ndim == 3:
        a = a[:, :, None, :]
    if 0 in a.shape:
        raise ValueError(f"`coefficients` must be non-empty, got shape {a.shape}")
    _, _, c, k = a.shape
    if names is None:
        names = [f"c{i:04d}" for i in range(k)]
    names = [str(s) for s in names]
    if colors is None:
        colors = ["R", "G", "B"] if c == 3 else (["Y"] if c == 1 else [f"C{i}" for i in range(c)])
    colors = [str(s) for s in colors]
    if len(names) != k or len(set(names)) != k:
        raise ValueError(f"`names` must hold {k} distinct coefficient names, got {len(names)}")
    if len(colors) != c or len(set(colors)) != c:
        raise ValueError(f"`colors` must hold {c} distinct colour names, got {len(colors)}")
    for s in names + colors:
        if "," in s or "." in s or not _NAME_RE.match(s):
            raise ValueError(f"invalid coefficient/colour name {s!r} (letters, digits, '_', '-')")
    chans = {f"{col}.{nm}": a[:, :, ci, ki] for ci, col in enumerate(colors) for ki, nm in enumerate(names)}
    hdr = {_COEFF_ATTR: ",".join(names), _COLOR_ATTR: ",".join(colors)}
    return write_exr(path, chans, overwrite=overwrite, header=hdr)


def read_coefficient_maps_exr(path) -> Tuple[np.ndarray, List[str], List[str]]:
    r"""Read a file from :func:`write_coefficient_maps_exr`.

    Returns:
        ``(coefficients, names, colors)``: ``(H, W, C, K)`` float32 array and the
        coefficient and colour names in the written order.

    Raises:
        ValueError: the file lacks the torch_hsh header attributes or channels.

    Example:
        >>> coefficients, names, colors = read_coefficient_maps_exr(tmp_path / "c.exr")  # doctest: +SKIP
    """
    hdr = _read_header(path)
    if _COEFF_ATTR not in hdr or _COLOR_ATTR not in hdr:
        raise ValueError(f"{path}: not a coefficient-map EXR (missing header attribute {_COEFF_ATTR!r})")
    try:
        names = str(hdr[_COEFF_ATTR]).split(",")
        colors = str(hdr[_COLOR_ATTR]).split(",")
    except UnicodeDecodeError as e:  # the bindings decode string attributes on access
        raise ValueError(f"{path}: corrupt header: an attribute is not UTF-8 text ({e})") from None
    ch = read_exr(path)
    try:
        planes = [[ch[f"{col}.{nm}"] for nm in names] for col in colors]
    except KeyError as e:
        raise ValueError(f"{path}: channel {e.args[0]!r} listed in the header is missing") from None
    out = np.stack([np.stack(p, axis=-1) for p in planes], axis=2)
    return out, names, colors


def read_envmap(path) -> np.ndarray:
    r"""Read an RGB (latitude-longitude) environment map as ``(H, W, 3)`` float32.

    Accepts bare ``R, G, B`` channels (the usual layout, also of
    ``../shared/data/envmaps``) or a single layer ``layer.R/G/B``; an
    alpha channel is ignored. Row 0 is the top (zenith) in the usual
    convention; no remapping is done here.

    Example:
        >>> env = read_envmap("../shared/data/envmaps/venice_sunset_1k.exr")  # doctest: +SKIP
        >>> env.shape, env.dtype  # doctest: +SKIP
        ((512, 1024, 3), dtype('float32'))
    """
    ch = read_exr(path)
    if all(c in ch for c in "RGB"):
        return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
    layers = {n.rsplit(".", 1)[0] for n in ch if "." in n and n.rsplit(".", 1)[1] in ("R", "G", "B")}
    full = [lay for lay in sorted(layers) if all(f"{lay}.{c}" in ch for c in "RGB")]
    if len(full) == 1:
        return np.stack([ch[f"{full[0]}.{c}"] for c in "RGB"], axis=-1)
    if len(ch) == 1:
        (only,) = ch.values()
        return np.repeat(only[..., None], 3, axis=-1)
    raise ValueError(f"{path}: no unique R, G, B channels (found {sorted(ch)})")
