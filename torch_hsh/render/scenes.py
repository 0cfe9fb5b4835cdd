r"""Synthetic photometric-stereo scenes: geometry, materials, textures, lights, cast shadows.

Frame (the DiLiGenT frame, as in :mod:`torch_hsh.io.diligent`): ``x`` to the
right, ``y`` up, ``z`` toward the camera, orthographic view along ``-z``.
Image row 0 is the **top**: pixel ``(row, col)`` is at
``x = col * pixel_size``, ``y = -row * pixel_size``. Height fields ``h(row,
col)`` are ``z`` values in the same length unit as ``pixel_size``; their
normals are ``normalize(-dh/dx, -dh/dy, 1)``.

Randomness: every random function takes ``seed`` — an ``int``, a CPU
``torch.Generator`` or ``None`` (fresh nondeterministic seed). Random numbers
are drawn on the CPU and then moved to ``device``, so a given seed gives the
same scene on every device.
"""
from __future__ import annotations

import math
import operator
from typing import Tuple, Union

import torch
import torch.nn.functional as F

from .._checks import check_count, check_tensor
from .visibility import _positive, cast_shadow_mask

__all__ = [
    "sphere_normals",
    "bumpy_heightfield",
    "heightfield_normals",
    "material_regions",
    "albedo_texture",
    "srgb_to_linear",
    "TEXTURE_SOURCES",
    "diligent_like_lights",
    "cone_lights",
    "light_intensities",
    "demo_scene",
    "synthetic_scene",
]

#: ``skimage.data`` images shipped inside scikit-image (no download needed).
TEXTURE_SOURCES = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "immunohistochemistry",
    "hubble_deep_field",
    "colorwheel",
    "brick",
    "grass",
    "gravel",
    "camera",
    "moon",
)

Seed = Union[int, torch.Generator, None]
_FLOAT_DTYPES = (torch.float32, torch.float64)


def _gen(seed: Seed) -> torch.Generator:
    if isinstance(seed, torch.Generator):
        if seed.device.type != "cpu":
            raise ValueError(f"`seed` generator must be a CPU torch.Generator, got one on {seed.device}")
        return seed
    g = torch.Generator()
    if seed is None:
        g.seed()
        return g
    if isinstance(seed, bool):
        raise TypeError(f"`seed` must be an int, a torch.Generator or None, got {seed!r}")
    try:
        g.manual_seed(operator.index(seed))
    except TypeError:
        raise TypeError(f"`seed` must be an int, a torch.Generator or None, got {type(seed).__name__}") from None
    return g


def _size(size, name: str = "size") -> Tuple[int, int]:
    if isinstance(size, (tuple, list, torch.Size)):
        if len(size) != 2:
            raise ValueError(f"`{name}` must be an int or a pair (H, W), got {size!r}")
        h, w = size
    else:
        h = w = size
    try:
        if isinstance(h, bool) or isinstance(w, bool):
            raise TypeError
        h, w = operator.index(h), operator.index(w)
    except TypeError:
        raise TypeError(f"`{name}` must be an int or a pair of ints (H, W), got {size!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"`{name}` must be positive, got {(h, w)}")
    return h, w


def _dtype(dtype) -> torch.dtype:
    if dtype not in _FLOAT_DTYPES:
        raise TypeError(f"`dtype` must be torch.float32 or torch.float64, got {dtype}")
    return dtype


def _pixel_grid(h: int, w: int, dtype, device):
    rows = torch.arange(h, dtype=dtype, device=device)[:, None].expand(h, w)
    cols = torch.arange(w, dtype=dtype, device=device)[None, :].expand(h, w)
    return rows, cols


# --------------------------------------------------------------------------- #
# geometry
# --------------------------------------------------------------------------- #
def sphere_normals(size, radius: float = 0.9, dtype=torch.float32, device=None):
    r"""Normals of an orthographically viewed sphere centred in the image.

    Args:
        size: ``H`` (square) or ``(H, W)``.
        radius: sphere radius as a fraction of ``min(H, W) / 2``, in ``(0, 1]``.

    Returns:
        ``(normals, mask)``: ``(H, W, 3)`` unit normals in the DiLiGenT frame
        (x right, y up, z toward the camera; zero outside the mask) and the
        ``(H, W)`` bool mask of pixel centres strictly inside the disc.

    Example:
        >>> n, m = sphere_normals(64)
        >>> n.shape, bool(m[32, 32]), bool(m[0, 0])
        (torch.Size([64, 64, 3]), True, False)
        >>> n[8:31, 32, 1].min() > 0  # upper rows have normals pointing up (+y)
        tensor(True)
    """
    h, w = _size(size)
    radius = _positive(radius, "radius")
    if radius > 1:
        raise ValueError(f"`radius` must be in (0, 1], got {radius}")
    dtype = _dtype(dtype)
    rpx = radius * min(h, w) / 2.0
    rows, cols = _pixel_grid(h, w, dtype, device)
    x = (cols + 0.5 - w / 2.0) / rpx
    y = -(rows + 0.5 - h / 2.0) / rpx
    r2 = x * x + y * y
    mask = r2 < 1.0
    z = torch.sqrt(torch.clamp(1.0 - r2, min=0.0))
    n = torch.stack([x, y, z], dim=-1)
    n = F.normalize(n, dim=-1) * mask[..., None]
    return n, mask


def bumpy_heightfield(
    size, n_bumps: int = 16, seed: Seed = None, smoothness: float = 0.1, dtype=torch.float32, device=None
) -> torch.Tensor:
    r"""A smooth random height field: a sum of isotropic Gaussian bumps and dents.

    Bump ``k`` has a centre uniform over the image, width
    ``sigma_k = smoothness * min(H, W) * U(0.6, 1.4)`` pixels and amplitude
    ``+-sigma_k * U(0.3, 1.0)`` (random sign), so the steepest slope of a lone
    bump is below ``exp(-1/2) ~ 0.61`` (about 31 degrees).

    Args:
        size: ``H`` or ``(H, W)``.
        n_bumps: number of Gaussians (>= 0; 0 gives a flat field).
        seed: int, CPU ``torch.Generator`` or None.
        smoothness: relative bump width (> 0); larger is smoother.

    Returns:
        ``(H, W)`` heights in pixel units (use ``pixel_size=1`` with
        :func:`heightfield_normals` and :func:`cast_shadow_mask`).

    Example:
        >>> hgt = bumpy_heightfield(64, n_bumps=8, seed=0)
        >>> normals = heightfield_normals(hgt)
        >>> hgt.shape, normals.shape
        (torch.Size([64, 64]), torch.Size([64, 64, 3]))
    """
    h, w = _size(size)
    n_bumps = check_count(n_bumps, "n_bumps", minimum=0)
    smoothness = _positive(smoothness, "smoothness")
    dtype = _dtype(dtype)
    g = _gen(seed)
    u = torch.rand(n_bumps, 5, generator=g, dtype=torch.float64)
    cr, cc = u[:, 0] * h, u[:, 1] * w
    sigma = smoothness * min(h, w) * (0.6 + 0.8 * u[:, 2])
    amp = sigma * (0.3 + 0.7 * u[:, 3]) * torch.where(u[:, 4] < 0.5, -1.0, 1.0).to(torch.float64)
    rows, cols = _pixel_grid(h, w, torch.float64, "cpu")
    out = torch.zeros(h, w, dtype=torch.float64)
    for k in range(n_bumps):
        d2 = (rows - cr[k]) ** 2 + (cols - cc[k]) ** 2
        out += amp[k] * torch.exp(-0.5 * d2 / sigma[k] ** 2)
    return out.to(device=device, dtype=dtype)


def _extrapolate_pad(x: torch.Tensor) -> torch.Tensor:
    """Pad the last two dims by one sample with linear extrapolation."""
    top = 2 * x[..., :1, :] - x[..., 1:2, :]
    bottom = 2 * x[..., -1:, :] - x[..., -2:-1, :]
    x = torch.cat([top, x, bottom], dim=-2)
    left = 2 * x[..., :, :1] - x[..., :, 1:2]
    right = 2 * x[..., :, -1:] - x[..., :, -2:-1]
    return torch.cat([left, x, right], dim=-1)


def heightfield_normals(height: torch.Tensor, pixel_size: float = 1.0) -> torch.Tensor:
    r"""Unit normals of a height field ``z = h(x, y)`` in the DiLiGenT frame.

    ``n = normalize(-dh/dx, -dh/dy, 1)`` with ``x = col * pixel_size`` and
    ``y = -row * pixel_size`` (row 0 at the top, y up), so
    ``dh/dy = -(dh/drow) / pixel_size``. Derivatives are kornia's normalised
    Sobel filter (``kornia.filters.spatial_gradient``, which returns
    ``(d/dcol, d/drow)`` per pixel) after padding the field by one pixel with
    linear extrapolation: exact for planes everywhere (kornia's own replicate
    border would halve the slope on the border) and for quadratics away from
    the border. Differentiable.

    Args:
        height: ``(..., H, W)`` float tensor with ``H, W >= 2``.
        pixel_size: spacing between pixel centres, in the units of ``height``.

    Returns:
        ``(..., H, W, 3)`` unit normals (``n_z > 0``).

    Example:
        >>> rows, cols = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
        >>> n = heightfield_normals(0.5 * cols)  # rises to the right: normal tilts left
        >>> torch.allclose(n[3, 3], torch.tensor([-0.5, 0.0, 1.0]) / 1.25 ** 0.5)
        True
    """
    import kornia

    check_tensor(height, "height", min_dims=2)
    ps = _positive(pixel_size, "pixel_size")
    hgt, wid = height.shape[-2:]
    if hgt < 2 or wid < 2:
        raise ValueError(f"`height` must be at least 2x2 in its last two dims, got {tuple(height.shape)}")
    lead = height.shape[:-2]
    x = _extrapolate_pad(height.reshape(-1, 1, hgt, wid))
    grad = kornia.filters.spatial_gradient(x, mode="sobel", order=1, normalized=True)[..., 1:-1, 1:-1]
    dh_dcol, dh_drow = grad[:, 0, 0], grad[:, 0, 1]
    dh_dx = dh_dcol / ps
    dh_dy = -dh_drow / ps
    n = torch.stack([-dh_dx, -dh_dy, torch.ones_like(dh_dx)], dim=-1)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    return n.reshape(*lead, hgt, wid, 3)


# --------------------------------------------------------------------------- #
# materials and textures
# --------------------------------------------------------------------------- #
def material_regions(
    size, n_regions: int = 6, seed: Seed = None, warp: float = 0.08, device=None
) -> torch.Tensor:
    r"""A label map of smooth Voronoi-like regions.

    ``n_regions`` distinct seed pixels are drawn; every pixel gets the label
    of the nearest seed after a smooth warp of the plane (a sum of four random
    sinusoids of amplitude ``warp * min(H, W)`` pixels), so boundaries are
    smooth curves rather than straight lines. Distances are measured between
    warped positions, so each seed pixel keeps its own label and every label
    ``0 .. n_regions-1`` occurs (ties go to the lower label).

    Args:
        size: ``H`` or ``(H, W)``.
        n_regions: number of regions, ``1 <= n_regions <= H * W``.
        seed: int, CPU ``torch.Generator`` or None.
        warp: boundary waviness (>= 0; 0 gives a plain Voronoi diagram).

    Returns:
        ``(H, W)`` int64 labels.

    Example:
        >>> lab = material_regions(32, n_regions=4, seed=0)
        >>> lab.shape, sorted(lab.unique().tolist())
        (torch.Size([32, 32]), [0, 1, 2, 3])
    """
    h, w = _size(size)
    n_regions = check_count(n_regions, "n_regions", minimum=1)
    if n_regions > h * w:
        raise ValueError(f"`n_regions` must be <= H * W = {h * w}, got {n_regions}")
    if isinstance(warp, bool) or not isinstance(warp, (int, float)) or not math.isfinite(warp) or warp < 0:
        raise ValueError(f"`warp` must be a finite number >= 0, got {warp!r}")
    g = _gen(seed)
    idx = torch.randperm(h * w, generator=g)[:n_regions]
    rows, cols = _pixel_grid(h, w, torch.float64, "cpu")
    p = torch.stack([rows, cols], dim=-1).reshape(-1, 2)
    if warp > 0:
        k = 4
        ang = torch.rand(k, generator=g, dtype=torch.float64) * 2 * math.pi
        freq = (1.0 + 2.0 * torch.rand(k, generator=g, dtype=torch.float64)) * 2 * math.pi / min(h, w)
        phase = torch.rand(k, 2, generator=g, dtype=torch.float64) * 2 * math.pi
        dirs = torch.stack([torch.cos(ang), torch.sin(ang)], dim=-1) * freq[:, None]  # (k, 2)
        arg = p @ dirs.T  # (HW, k)
        amp = warp * min(h, w) / k
        disp = torch.stack(
            [torch.sin(arg + phase[:, 0]).sum(-1), torch.sin(1.3 * arg + phase[:, 1]).sum(-1)], dim=-1
        )
        p = p + amp * disp
    centres = p[idx]
    labels = torch.empty(h * w, dtype=torch.int64)
    chunk = max(1, (1 << 22) // n_regions)
    for s in range(0, h * w, chunk):
        labels[s : s + chunk] = torch.cdist(p[s : s + chunk], centres).argmin(dim=-1)
    labels[idx] = torch.arange(n_regions)  # seed pixels own their label even if warped points coincide
    return labels.reshape(h, w).to(device)


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    r"""sRGB-encoded values in ``[0, 1]`` to linear (IEC 61966-2-1 piecewise curve).

    ``x / 12.92`` for ``x <= 0.04045``, else ``((x + 0.055) / 1.055) ** 2.4``.

    Example:
        >>> srgb_to_linear(torch.tensor([0.0, 0.5, 1.0]))
        tensor([0.0000, 0.2140, 1.0000])
    """
    check_tensor(x, "x")
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


def albedo_texture(
    size, seed: Seed = None, source: str = "astronaut", dtype=torch.float32, device=None
) -> torch.Tensor:
    r"""A linear-RGB albedo texture from a scikit-image sample picture.

    The picture (one of :data:`TEXTURE_SOURCES`, all shipped inside
    scikit-image, no download) is cropped to the target aspect ratio —
    centred if ``seed`` is None, else a random crop covering 50-100 % of the
    largest such crop, randomly mirrored — resized with anti-aliasing
    (``skimage.transform.resize``), and converted from sRGB to linear.
    Grey pictures are repeated over the 3 channels; alpha is dropped.

    Args:
        size: ``H`` or ``(H, W)``.
        seed: None (deterministic centred crop), int or CPU ``torch.Generator``.
        source: name of the ``skimage.data`` picture.

    Returns:
        ``(H, W, 3)`` linear albedo in ``[0, 1]``.

    Example:
        >>> tex = albedo_texture(32, source="coffee")
        >>> tex.shape, bool(tex.min() >= 0), bool(tex.max() <= 1)
        (torch.Size([32, 32, 3]), True, True)
    """
    import numpy as np
    import skimage.data
    import skimage.transform

    h, w = _size(size)
    dtype = _dtype(dtype)
    if source not in TEXTURE_SOURCES:
        raise ValueError(f"`source` must be one of {TEXTURE_SOURCES}, got {source!r}")
    img = np.asarray(getattr(skimage.data, source)())
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    img = img[..., :3].astype(np.float64) / 255.0
    ih, iw = img.shape[:2]
    # largest crop with the target aspect ratio
    ch, cw = (ih, min(iw, round(ih * w / h))) if iw * h >= ih * w else (min(ih, round(iw * h / w)), iw)
    if seed is None:
        r0, c0, flip = (ih - ch) // 2, (iw - cw) // 2, False
    else:
        u = torch.rand(4, generator=_gen(seed), dtype=torch.float64).tolist()
        frac = 0.5 + 0.5 * u[0]
        ch, cw = max(1, round(ch * frac)), max(1, round(cw * frac))
        r0, c0 = int(u[1] * (ih - ch + 1)), int(u[2] * (iw - cw + 1))
        r0, c0 = min(r0, ih - ch), min(c0, iw - cw)
        flip = u[3] < 0.5
    crop = img[r0 : r0 + ch, c0 : c0 + cw]
    if flip:
        crop = crop[:, ::-1]
    out = skimage.transform.resize(crop, (h, w, 3), order=1, anti_aliasing=True, mode="reflect")
    out = torch.as_tensor(np.clip(out, 0.0, 1.0), dtype=torch.float64)
    return srgb_to_linear(out).to(device=device, dtype=dtype)


# --------------------------------------------------------------------------- #
# lights
# --------------------------------------------------------------------------- #
def diligent_like_lights(
    n: int = 96, seed: Seed = None, max_polar_deg: float = 55.0, dtype=torch.float32, device=None
) -> torch.Tensor:
    r"""Light directions on a DiLiGenT-like planar grid in front of the object.

    DiLiGenT uses 96 LEDs on a flat 8 x 12 grid facing the object. Here the
    ``n`` lights sit on a ``rows x cols`` grid in the plane ``z = 1`` with
    ``rows = round(sqrt(2 n / 3))`` (8 for ``n = 96``), ``cols = ceil(n /
    rows)`` (12), equal spacing in x and y, scaled so that the corner light is
    ``max_polar_deg`` from the view axis ``+z``; the first ``n`` grid points
    are used in row-major order starting top-left (``+y``, ``-x``). With a
    seed, each point is jittered by up to 15 % of the spacing (and pulled back
    inside the ``max_polar_deg`` cone).

    Returns:
        ``(n, 3)`` unit directions (toward the lights), all with ``z > 0``.

    Example:
        >>> L = diligent_like_lights()
        >>> L.shape, bool((L[:, 2] > 0).all())
        (torch.Size([96, 3]), True)
    """
    n = check_count(n, "n", minimum=1)
    max_polar = _positive(max_polar_deg, "max_polar_deg")
    if max_polar >= 90:
        raise ValueError(f"`max_polar_deg` must be < 90, got {max_polar}")
    dtype = _dtype(dtype)
    rows = max(1, round(math.sqrt(2 * n / 3)))
    cols = math.ceil(n / rows)
    tmax = math.tan(math.radians(max_polar))
    half_diag = 0.5 * math.hypot(cols - 1, rows - 1)
    s = tmax / half_diag if half_diag > 0 else 0.0
    i = torch.arange(n, dtype=torch.float64)
    r, c = torch.div(i, cols, rounding_mode="floor"), torch.remainder(i, cols)
    u = (c - (cols - 1) / 2) * s
    v = ((rows - 1) / 2 - r) * s
    if seed is not None and s > 0:
        jit = (torch.rand(n, 2, generator=_gen(seed), dtype=torch.float64) * 2 - 1) * 0.15 * s
        u, v = u + jit[:, 0], v + jit[:, 1]
        rad = torch.sqrt(u * u + v * v)
        shrink = torch.where(rad > tmax, tmax / rad.clamp(min=1e-300), torch.ones_like(rad))
        u, v = u * shrink, v * shrink
    d = torch.stack([u, v, torch.ones_like(u)], dim=-1)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return d.to(device=device, dtype=dtype)


def cone_lights(
    n: int, max_angle_deg: float = 60.0, seed: Seed = None, dtype=torch.float32, device=None
) -> torch.Tensor:
    r"""Directions uniformly distributed (by solid angle) on the cap around ``+z``.

    ``cos(theta) ~ U(cos(max_angle), 1)``, ``phi ~ U(0, 2 pi)``.

    Args:
        n: number of directions.
        max_angle_deg: half-angle of the cap in degrees, in ``(0, 180]``.
        seed: int, CPU ``torch.Generator`` or None.

    Returns:
        ``(n, 3)`` unit vectors.

    Example:
        >>> L = cone_lights(100, 30.0, seed=0)
        >>> bool((L[:, 2] >= math.cos(math.radians(30.0)) - 1e-6).all())
        True
    """
    n = check_count(n, "n", minimum=1)
    ang = _positive(max_angle_deg, "max_angle_deg")
    if ang > 180:
        raise ValueError(f"`max_angle_deg` must be in (0, 180], got {ang}")
    dtype = _dtype(dtype)
    u = torch.rand(n, 2, generator=_gen(seed), dtype=torch.float64)
    cmin = math.cos(math.radians(ang))
    ct = 1.0 - u[:, 0] * (1.0 - cmin)
    st = torch.sqrt(torch.clamp(1.0 - ct * ct, min=0.0))
    phi = 2 * math.pi * u[:, 1]
    d = torch.stack([st * torch.cos(phi), st * torch.sin(phi), ct], dim=-1)
    return d.to(device=device, dtype=dtype)


def light_intensities(
    n: int, seed: Seed = None, variation: float = 0.2, dtype=torch.float32, device=None
) -> torch.Tensor:
    r"""Random RGB light intensities around 1, like DiLiGenT's calibrated LEDs.

    Every entry is independently ``U(1 - variation, 1 + variation)``.

    Args:
        n: number of lights.
        seed: int, CPU ``torch.Generator`` or None.
        variation: half-width of the range, in ``[0, 1)``.

    Returns:
        ``(n, 3)`` positive intensities.

    Example:
        >>> I = light_intensities(96, seed=0)
        >>> I.shape, bool(((I >= 0.8) & (I <= 1.2)).all())
        (torch.Size([96, 3]), True)
    """
    n = check_count(n, "n", minimum=1)
    if isinstance(variation, bool) or not isinstance(variation, (int, float)) or not 0 <= variation < 1:
        raise ValueError(f"`variation` must be a number in [0, 1), got {variation!r}")
    dtype = _dtype(dtype)
    u = torch.rand(n, 3, generator=_gen(seed), dtype=torch.float64)
    return (1.0 + variation * (2 * u - 1)).to(device=device, dtype=dtype)


# --------------------------------------------------------------------------- #
# cast shadows
# --------------------------------------------------------------------------- #
def _bumpy_sphere(h: int, w: int, radius: float, n_bumps: int, g: torch.Generator):
    r"""Height (pixel units), analytic normals and the disc mask of a bumpy hemisphere (float64, CPU).

    ``z = sqrt(R^2 - r^2) + (1 - r^2 / R^2) * b(x, y)`` inside the disc ``r < R``
    and ``z = 0`` outside, with ``b`` a sum of Gaussian bumps and dents. The
    taper ``1 - r^2 / R^2`` keeps ``z >= 0`` and continuous at the rim.
    Normals come from the exact gradient (autograd of the closed form).
    """
    R = radius * min(h, w) / 2.0
    u = torch.rand(n_bumps, 5, generator=g, dtype=torch.float64)
    rad = 0.8 * R * torch.sqrt(u[:, 0])  # centres uniform over the disc of radius 0.8 R
    ang = 2 * math.pi * u[:, 1]
    cx, cy = rad * torch.cos(ang), rad * torch.sin(ang)
    sigma = R * (0.10 + 0.10 * u[:, 2])
    amp = sigma * (0.6 + 0.6 * u[:, 3]) * torch.where(u[:, 4] < 0.5, -1.0, 1.0).to(torch.float64)
    rows, cols = _pixel_grid(h, w, torch.float64, "cpu")
    x = (cols + 0.5 - w / 2.0).clone().requires_grad_(True)
    y = (-(rows + 0.5 - h / 2.0)).clone().requires_grad_(True)
    with torch.enable_grad():
        r2 = x * x + y * y
        mask = (r2 < R * R).detach()
        inside = torch.where(mask, R * R - r2, torch.ones_like(r2))  # keeps sqrt's gradient finite outside
        b = torch.zeros_like(x)
        for k in range(n_bumps):
            b = b + amp[k] * torch.exp(-0.5 * ((x - cx[k]) ** 2 + (y - cy[k]) ** 2) / sigma[k] ** 2)
        z = torch.sqrt(inside) + (1.0 - r2 / (R * R)) * b
        z = torch.where(mask, z, torch.zeros_like(z))
        gx, gy = torch.autograd.grad(z.sum(), (x, y))
    n = torch.stack([-gx, -gy, torch.ones_like(gx)], dim=-1)
    n = F.normalize(n, dim=-1) * mask[..., None]
    return z.detach(), n, mask


def demo_scene(
    size=128,
    n_lights: int = 96,
    seed: int = 0,
    dtype=torch.float32,
    device=None,
    min_nz: float = 0.0,
    relative_read_std: float = 1e-3,
    relative_shot_gain: float = 1e-4,
    bits: int = 16,
) -> dict:
    r"""The photometric-stereo demo scene: a bumpy sphere, two analytic materials, cast shadows, sensor noise.

    * **Geometry**: a hemisphere of radius ``0.9 min(H, W) / 2`` pixels
      carrying 12 smooth Gaussian bumps and dents (widths ``sigma`` 10-20 %
      of the radius, heights 0.6-1.2 ``sigma``, so a lone bump is at most
      about 36 degrees steep), tapered to zero at the rim:
      ``z = sqrt(R^2 - r^2) + (1 - r^2/R^2) b(x, y)``, ``z = 0`` outside
      (heights in pixel units, DiLiGenT frame, see the module docstring).
      ``normals_gt`` are the exact normals of this height field (closed-form
      gradient), the normals used for shading; ``height`` is the same field
      sampled at the pixel centres, used for the cast shadows.
    * **Materials**: six smooth regions (:func:`material_regions`)
      alternating between GGX (:class:`~torch_hsh.brdf.CookTorranceGGX`,
      ``k_s = 0.4``, roughness 0.4, ``f0 = 0.3``) and Blinn–Phong
      (:class:`~torch_hsh.brdf.BlinnPhong`, ``k_s = 0.3``, shininess 30),
      both with white specular reflection over the diffuse albedo
      ``0.15 + 0.7 * texture`` (:func:`albedo_texture`, linear RGB).
    * **Lights**: ``n_lights`` jittered DiLiGenT-like directions
      (:func:`diligent_like_lights`, up to 55 degrees from the view) with RGB
      intensities in ``[0.8, 1.2]`` (:func:`light_intensities`).
    * **Image formation** (:func:`torch_hsh.render.render_model`): attached
      shadows, cast shadows (:func:`cast_shadow_mask` on ``height``); then,
      with full scale ``F = 1.05 x`` the brightest noise-free value in the
      mask: Gaussian read noise of std ``relative_read_std * F``, shot noise of
      variance ``relative_shot_gain * F * I`` (:func:`torch_hsh.render.add_sensor_noise`
      with ``read_std = relative_read_std * F`` and ``shot_gain = relative_shot_gain * F``;
      ``1 / relative_shot_gain`` photo-electrons at full scale), clipping to
      ``[0, F]`` and quantisation to ``bits`` bits
      (:func:`torch_hsh.render.quantize`). Images are zero outside the mask.

    All randomness comes from ``seed``: the same seed gives the same scene.
    Computed in float64 on the CPU, returned in ``dtype`` on ``device``.

    Args:
        size: ``H`` or ``(H, W)`` (at least 8 x 8).
        n_lights: number of lights (>= 3).
        seed: int.
        dtype: ``torch.float32`` or ``torch.float64``.
        device: output device.
        min_nz: the mask keeps the pixels inside the sphere's disc whose
            true normal has ``n_z > min_nz`` (in ``[0, 1)``; 0 keeps the whole
            disc, grazing rim included).
        relative_read_std: read-noise std relative to the full scale ``F`` (>= 0).
        relative_shot_gain: shot-noise variance per unit signal, relative to the full scale ``F`` (>= 0).
        bits: quantisation depth, 1..32.

    Returns:
        dict with ``images (L, H, W, 3)``, ``lights (L, 3)``,
        ``intensities (L, 3)``, ``mask (H, W)`` bool, ``normals_gt (H, W, 3)``
        (unit inside the mask, zero outside), ``labels (H, W)`` int64 (0 GGX,
        1 Blinn–Phong), ``name`` (str), and for inspection ``height (H, W)``,
        ``albedo (H, W, 3)``, ``visibility (L, H, W)`` bool (cast shadows;
        True = lit) and ``full_scale`` (float, the value of the top code).

    Example:
        >>> s = demo_scene(32, n_lights=12, seed=0)
        >>> s["images"].shape, s["lights"].shape, s["normals_gt"].shape
        (torch.Size([12, 32, 32, 3]), torch.Size([12, 3]), torch.Size([32, 32, 3]))
        >>> bool((~s["visibility"][:, s["mask"]]).any())  # some observations are cast-shadowed
        True
    """
    from ..brdf import BlinnPhong, CookTorranceGGX
    from .images import add_sensor_noise, quantize, render_model

    h, w = _size(size)
    if min(h, w) < 8:
        raise ValueError(f"`size` must be at least 8 x 8, got {(h, w)}")
    n_lights = check_count(n_lights, "n_lights", minimum=3)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"`seed` must be an int, got {seed!r}")
    dtype = _dtype(dtype)
    if isinstance(min_nz, bool) or not isinstance(min_nz, (int, float)) or not 0 <= min_nz < 1:
        raise ValueError(f"`min_nz` must be a number in [0, 1), got {min_nz!r}")
    for name, val in (("relative_read_std", relative_read_std), ("relative_shot_gain", relative_shot_gain)):
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val) or val < 0:
            raise ValueError(f"`{name}` must be a finite number >= 0, got {val!r}")
    bits = check_count(bits, "bits", minimum=1)
    if bits > 32:
        raise ValueError(f"`bits` must be in [1, 32], got {bits}")

    f64 = torch.float64
    g = _gen(seed)
    height, normals, disc = _bumpy_sphere(h, w, 0.9, 12, g)
    mask = disc & (normals[..., 2] > min_nz)
    labels = material_regions((h, w), n_regions=6, seed=g) % 2
    albedo = 0.15 + 0.7 * albedo_texture((h, w), seed=g, dtype=f64)
    lights = diligent_like_lights(n_lights, seed=g, dtype=f64)
    inten = light_intensities(n_lights, seed=g, dtype=f64)
    noise_seed = int(torch.randint(0, 2 ** 31 - 1, (1,), generator=g))

    ones = torch.ones(h, w, 1, dtype=f64)
    safe_n = torch.where(disc[..., None], normals, torch.tensor([0.0, 0.0, 1.0], dtype=f64))
    ggx = CookTorranceGGX(albedo=albedo, specular=0.4 * ones, roughness=0.4 * ones, f0=0.3)
    phong = BlinnPhong(albedo=albedo, specular=0.3 * ones, shininess=30.0 * ones)
    img = torch.where(
        (labels == 0)[None, ..., None],
        render_model(safe_n, lights, ggx, intensities=inten),
        render_model(safe_n, lights, phong, intensities=inten),
    )
    vis = cast_shadow_mask(height, lights)
    img = img * vis[..., None].to(f64) * mask[None, ..., None].to(f64)
    full = 1.05 * float(img.max()) if bool(mask.any()) else 1.0
    img = add_sensor_noise(img, read_std=relative_read_std * full, shot_gain=relative_shot_gain * full,
                           seed=noise_seed)
    img = quantize(img, bits, full) * mask[None, ..., None].to(f64)

    out = dict(
        images=img, lights=lights, intensities=inten, mask=mask, normals_gt=normals * mask[..., None],
        labels=labels, height=height, albedo=albedo, visibility=vis,
    )
    out = {k: (v.to(device=device, dtype=dtype) if v.is_floating_point() else v.to(device)) for k, v in out.items()}
    out["full_scale"] = full
    out["name"] = f"demo: bumpy sphere {h}x{w}, GGX / Blinn-Phong, {n_lights} lights, cast shadows, noise, {bits} bit"
    return out


def synthetic_scene(size: int = 48, n_lights: int = 40, seed: int = 0, dtype=torch.float64) -> dict:
    """The small scene of ``torch-hsh demo --scene small``: a sphere with three analytic-BRDF regions
    (GGX, Blinn-Phong, Torrance-Sparrow), a textured albedo, DiLiGenT-like lights, sensor noise.

    Returns a dict with ``images (L, H, W, 3)``, ``lights (L, 3)``,
    ``intensities (L, 3)``, ``mask (H, W)``, ``normals_gt (H, W, 3)``,
    ``labels`` and ``name``.

    Example:
        >>> d = synthetic_scene(16, 8)
        >>> tuple(d["images"].shape), tuple(d["lights"].shape)
        ((8, 16, 16, 3), (8, 3))
    """
    from ..brdf import BlinnPhong, CookTorranceGGX, TorranceSparrow
    from .images import add_sensor_noise, quantize, render

    normals, mask = sphere_normals(size, radius=0.95, dtype=dtype)
    mask = mask & (normals[..., 2] > 0.3)  # leave out grazing rim pixels (mostly attached shadow)
    labels = material_regions(size, n_regions=3, seed=seed)
    albedo = 0.15 + 0.7 * albedo_texture(size, seed=seed, dtype=dtype)  # (H, W, 3)
    lights = diligent_like_lights(n_lights, seed=seed, dtype=dtype)
    inten = light_intensities(n_lights, seed=seed, dtype=dtype)
    ones = torch.ones(size, size, 1, dtype=dtype)
    models = [
        CookTorranceGGX(albedo=albedo, specular=0.3 * ones, roughness=0.5 * ones, f0=0.3),
        BlinnPhong(albedo=albedo, specular=0.3 * ones, shininess=20.0 * ones),
        TorranceSparrow(albedo, 0.15 * ones, 0.35 * ones, 1.5 * ones),
    ]
    img = torch.zeros(n_lights, size, size, 3, dtype=dtype)
    for k, m in enumerate(models):
        sel = (labels % len(models)) == k
        img = torch.where(sel[None, ..., None], render(normals, lights, m, intensities=inten), img)
    full = float(img[:, mask].max()) * 1.05
    img = quantize(add_sensor_noise(img, read_std=2e-3 * full, shot_gain=1e-4 * full, seed=seed), 16, full)
    img = img * mask[None, ..., None].to(dtype)
    return dict(images=img, lights=lights, intensities=inten, mask=mask, normals_gt=normals,
                labels=labels, name="synthetic sphere (GGX / Blinn-Phong / Torrance-Sparrow)")
