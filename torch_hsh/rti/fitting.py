r"""Reflectance Transformation Imaging (RTI): light directions from a sphere, and the RTI HSH basis.

Two tools for users of RTI captures (see :mod:`torch_hsh.rti.io` for the files):

* :func:`sphere_light_directions` -- highlight RTI: each photograph's light
  direction from the specular highlight on a glossy sphere in the frame.
* :func:`rti_hsh_basis`, :func:`project_to_rti`, :func:`fit_rti` -- the
  hemispherical-harmonics basis that RTI viewers evaluate (RTIViewer's ``.rti``
  HSH files, ISTI-CNR ``relight`` / OpenLIME ``type: "hsh"``), the projection of a
  photometric-stereo result onto it, and the plain per-pixel RTI fit from the
  photographs (the baseline RTI users know).

Frames and pixel coordinates:

* Directions use the DiLiGenT frame of the rest of the library: ``x`` to the
  right, ``y`` up, ``z`` toward the (orthographic) camera, which looks along
  ``-z``; the view direction is ``v = (0, 0, 1)``.
* Image positions (sphere centre, highlight) are ``(x, y) = (column, row)`` in
  pixels with the centre of pixel ``(row 0, column 0)`` at ``(0, 0)``; rows go
  **down**. The scene sphere of :func:`torch_hsh.render.scenes.sphere_normals` of size
  ``H x W`` and radius fraction ``f`` is the circle ``cx = W/2 - 1/2``,
  ``cy = H/2 - 1/2``, ``r = f min(H, W) / 2``.

Highlight model: at the highlight the sphere normal ``n`` is the half vector of
the view and the light, so ``l = 2 (n . v) n - v`` (mirror reflection of the
view). The normal at image point ``(x, y)`` is
``n = ((x - cx)/r, -(y - cy)/r, sqrt(1 - ...))`` (the minus: rows go down, ``y``
goes up). ``relight`` (ISTI-CNR) computes its ``.lp`` directions the same way
(``Sphere::computeDirections``: ``2 asin(d)`` from the view, "inverted y
coords"); the highlight detector here is this library's own (threshold between
the background level and the peak, connected component of the peak,
weighted centroid).

RTI HSH basis (terms in the order the viewers store them; ``theta`` the angle
from ``+z``, ``phi = atan2(ly, lx)`` in ``[0, 2 pi)``, ``c = cos(theta)``,
``s = sqrt(c - c^2)``)::

    k  0: 1/sqrt(2 pi)                      k  9: 2 sqrt(35/pi) cos(3 phi) s^3
    k  1: sqrt(6/pi) cos(phi) s             k 10: sqrt(210/pi) cos(2 phi) (2c-1)(c^2-c)
    k  2: sqrt(3/(2 pi)) (2c - 1)           k 11: 2 sqrt(21/pi) cos(phi) s (1 - 5c + 5c^2)
    k  3: sqrt(6/pi) sin(phi) s             k 12: sqrt(7/(2 pi)) (20c^3 - 30c^2 + 12c - 1)
    k  4: sqrt(30/pi) cos(2 phi) (c^2 - c)  k 13: 2 sqrt(21/pi) sin(phi) s (1 - 5c + 5c^2)
    k  5: sqrt(30/pi) cos(phi) (2c - 1) s   k 14: sqrt(210/pi) sin(2 phi) (2c-1)(c^2-c)
    k  6: sqrt(5/(2 pi)) (6c^2 - 6c + 1)    k 15: 2 sqrt(35/pi) sin(3 phi) s^3
    k  7: sqrt(30/pi) sin(phi) (2c - 1) s
    k  8: sqrt(30/pi) sin(2 phi) (c^2 - c)

These are the orthonormal hemispherical harmonics of Gautron et al. (2004) up to
order 2 (9 terms) or 3 (16 terms), with the term order and signs of RTIViewer's
``getHSH`` (``rtiviewer/src/util.h``) and OpenLIME's ``HSH.lightWeights``
(``src/ShaderRTI.js``, 9 terms); each term equals ``+-`` one of this library's
:func:`torch_hsh.hsh` functions (checked in the tests). The viewers clamp
``theta`` to ``pi/2 - 0.04`` (RTIViewer) or ``pi/2 - 0.15`` (OpenLIME) before
evaluating; :func:`rti_hsh_basis` takes the clamp as an argument (default none).
A relit value is ``sum_k coeff_k basis_k(l)``, displayed as is (``1`` = white):
the viewers apply no transfer curve, so coefficients fitted to sRGB photographs
are sRGB values.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from .._checks import check_shape

__all__ = [
    "SphereLights",
    "sphere_circle_from_mask",
    "sphere_light_directions",
    "rti_hsh_basis",
    "evaluate_rti",
    "project_to_rti",
    "fit_rti",
    "nonnegative_rti",
    "NONNEGATIVE_MAX_ANGLE_DEG",
    "RTI_TERMS",
    "RTIVIEWER_THETA_CLAMP",
    "OPENLIME_THETA_CLAMP",
]

#: Numbers of HSH terms an RTI file may hold (RTI tools call them "order 3" and "order 4").
RTI_TERMS = (9, 16)
#: RTIViewer evaluates HSH at ``min(theta, pi/2 - 0.04)``.
RTIVIEWER_THETA_CLAMP = math.pi / 2 - 0.04
#: OpenLIME evaluates HSH at ``min(theta, pi/2 - 0.15)``.
OPENLIME_THETA_CLAMP = math.pi / 2 - 0.15


# --------------------------------------------------------------------------- #
# light directions from a sphere
# --------------------------------------------------------------------------- #
@dataclass
class SphereLights:
    """Output of :func:`sphere_light_directions`.

    Attributes:
        lights: ``(L, 3)`` float64 unit light directions (x right, y up, z to
            the camera); rows of images without a highlight are zero.
        highlights: ``(L, 2)`` highlight centroids ``(x, y)`` in pixels
            (NaN where none was found).
        found: ``(L,)`` bool, a highlight was found.
        saturated: ``(L,)`` number of pixels of the highlight at the image's
            maximum value (a plateau: clipped highlight).
        circle: ``(cx, cy, r)`` used, in pixels.
    """

    lights: np.ndarray
    highlights: np.ndarray
    found: np.ndarray
    saturated: np.ndarray
    circle: Tuple[float, float, float]


def sphere_circle_from_mask(mask) -> Tuple[float, float, float]:
    """Circle ``(cx, cy, r)`` (pixels, see the module docstring) of a sphere mask: centroid and ``sqrt(area / pi)``.

    Args:
        mask: ``(H, W)`` bool / 0-1 array or tensor, true on the sphere.

    Raises:
        ValueError: the mask selects fewer than 12 pixels ("no sphere").

    Example:
        >>> from torch_hsh.render import scenes
        >>> _, m = scenes.sphere_normals(64, radius=0.5)
        >>> [round(v, 1) for v in sphere_circle_from_mask(m)]
        [31.5, 31.5, 16.1]
    """
    m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    check_shape(m, "mask", ("H", "W"))
    m = m.astype(bool)
    count = int(m.sum())
    if count < 12:
        raise ValueError(f"no sphere found: the sphere mask selects {count} pixel(s)")
    rows, cols = np.nonzero(m)
    return float(cols.mean()), float(rows.mean()), math.sqrt(count / math.pi)


def sphere_light_directions(
    images,
    circle: Optional[Sequence[float]] = None,
    mask=None,
    inner: float = 0.8,
    threshold: float = 0.7,
    min_contrast: float = 0.05,
    on_missing: str = "raise",
) -> SphereLights:
    r"""Light direction of each image from the highlight on a glossy sphere (highlight RTI).

    Args:
        images: ``(L, H, W, C)`` or ``(L, H, W)`` images (tensor or array; any
            encoding, only the ordering of brightness matters much).
        circle: ``(cx, cy, r)`` of the sphere in pixels (module docstring), or
        mask: ``(H, W)`` sphere mask (its circle is :func:`sphere_circle_from_mask`).
        inner: search the highlight within ``inner * r`` of the centre (a
            light at 90 deg from the view puts it at ``0.71 r``).
        threshold: highlight pixels are those above ``bg + threshold (peak - bg)``
            (``bg``: median inside the search disc), in the connected
            component of the brightest pixel; their centroid is weighted by
            the excess over the threshold (plain centroid on a clipped plateau).
        min_contrast: an image whose ``peak - bg`` is below ``min_contrast *
            peak`` (or whose peak is 0) has no highlight.
        on_missing: ``"raise"`` (default) or ``"keep"`` (zero row, ``found`` false).

    Returns:
        :class:`SphereLights`.

    Raises:
        ValueError: bad circle (outside the image, radius < 3 px), no sphere in
            the mask, or (``on_missing="raise"``) an image without a highlight
            (its index is named).

    Example:
        >>> from torch_hsh.render import render, scenes
        >>> from torch_hsh.brdf import BlinnPhong
        >>> n, m = scenes.sphere_normals(96, radius=0.8, dtype=torch.float64)
        >>> li = torch.tensor([[0.3, 0.2, 0.933]], dtype=torch.float64)
        >>> one = torch.ones(96, 96, 1, dtype=torch.float64)
        >>> img = render(n, li, BlinnPhong(0.05 * one, one, 400 * one))
        >>> est = sphere_light_directions(img, mask=m)
        >>> float(torch.rad2deg(torch.arccos((torch.as_tensor(est.lights) * li / li.norm()).sum()))) < 1
        True
    """
    a = images.detach().cpu().double().numpy() if isinstance(images, torch.Tensor) else np.asarray(images, float)
    sizes = check_shape(a, "images", ("L", "H", "W"), ("L", "H", "W", None))
    if a.ndim == 4:
        a = a.mean(axis=-1)
    if a.shape[0] == 0:
        raise ValueError("`images` must hold at least one image")
    L, H, W = a.shape
    if circle is None:
        if mask is None:
            raise ValueError("give the sphere as `circle=(cx, cy, r)` or `mask`")
        mm = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
        check_shape(mm, "mask", ("H", "W"), sizes=sizes)
        circle = sphere_circle_from_mask(mm)
    cx, cy, r = (float(v) for v in circle)
    if not all(math.isfinite(v) for v in (cx, cy, r)) or r < 3:
        raise ValueError(f"the sphere circle needs finite values and a radius >= 3 px, got {(cx, cy, r)}")
    if cx - r < -0.5 or cy - r < -0.5 or cx + r > W - 0.5 or cy + r > H - 0.5:
        raise ValueError(f"the sphere circle (cx={cx:g}, cy={cy:g}, r={r:g}) is not inside the {W}x{H} image")
    if on_missing not in ("raise", "keep"):
        raise ValueError(f"`on_missing` must be 'raise' or 'keep', got {on_missing!r}")
    from scipy import ndimage

    rows, cols = np.mgrid[0:H, 0:W]
    search = (cols - cx) ** 2 + (rows - cy) ** 2 <= (inner * r) ** 2
    lights = np.zeros((L, 3))
    hl = np.full((L, 2), np.nan)
    found = np.zeros(L, dtype=bool)
    sat = np.zeros(L, dtype=np.int64)
    for i in range(L):
        g = a[i]
        vals = g[search]
        peak = float(vals.max())
        bg = float(np.median(vals))
        if not peak > 0 or peak - bg < min_contrast * peak:
            if on_missing == "raise":
                raise ValueError(f"image {i}: no highlight found on the sphere (peak {peak:.4g}, background {bg:.4g})")
            continue
        t = bg + threshold * (peak - bg)
        above = search & (g >= t)
        lab, _ = ndimage.label(above)
        rr, cc = np.nonzero(search & (g == peak))
        comp = lab == lab[rr[0], cc[0]]
        w = np.where(comp, g - t, 0.0)
        if not w.sum() > 0:  # flat plateau exactly at the threshold
            w = comp.astype(float)
        x = float((w * cols).sum() / w.sum())
        y = float((w * rows).sum() / w.sum())
        nx, ny = (x - cx) / r, -(y - cy) / r
        nz = math.sqrt(max(0.0, 1.0 - nx * nx - ny * ny))
        n = np.array([nx, ny, nz]) / max(1e-12, math.sqrt(nx * nx + ny * ny + nz * nz))
        li = 2.0 * n[2] * n - np.array([0.0, 0.0, 1.0])
        lights[i] = li / np.linalg.norm(li)
        hl[i] = (x, y)
        found[i] = True
        sat[i] = int((comp & (g >= peak)).sum())
    return SphereLights(lights=lights, highlights=hl, found=found, saturated=sat, circle=(cx, cy, r))


# --------------------------------------------------------------------------- #
# the RTI HSH basis
# --------------------------------------------------------------------------- #
def _check_terms(terms: int) -> int:
    if isinstance(terms, bool) or terms not in RTI_TERMS:
        raise ValueError(f"`terms` must be 9 or 16 (RTI 'order 3' / 'order 4'), got {terms!r}")
    return int(terms)


def rti_hsh_basis(lights: torch.Tensor, terms: int = 9, theta_clamp: Optional[float] = None) -> torch.Tensor:
    r"""The RTI HSH basis functions at light directions, in the viewers' term order.

    Args:
        lights: ``(..., 3)`` light directions (normalised here; x right, y up,
            z toward the camera).
        terms: 9 or 16.
        theta_clamp: evaluate at ``min(theta, theta_clamp)`` as a viewer does
            (:data:`RTIVIEWER_THETA_CLAMP`, :data:`OPENLIME_THETA_CLAMP`);
            default ``None``: no clamp, ``theta`` itself (below the horizon
            ``cos(theta)`` is clamped to 0).

    Returns:
        ``(..., terms)``, same dtype as ``lights``.

    Example:
        >>> b = rti_hsh_basis(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        >>> round(float(b[0]) * math.sqrt(2 * math.pi), 6), round(float(b[2]), 4)  # k=2: sqrt(3/(2 pi))
        (1.0, 0.691)
    """
    terms = _check_terms(terms)
    d = torch.nn.functional.normalize(lights, dim=-1)
    x, y, z = d.unbind(-1)
    c = z.clamp(0.0, 1.0)
    if theta_clamp is not None:
        c = torch.maximum(c, torch.full_like(c, math.cos(theta_clamp)))
    phi = torch.atan2(y, x)
    cp, sp = torch.cos(phi), torch.sin(phi)
    c2p, s2p = torch.cos(2 * phi), torch.sin(2 * phi)
    s = torch.sqrt((c - c * c).clamp(min=0.0))
    q = c * c - c  # = -s^2
    u = 2 * c - 1
    pi = math.pi
    out = [
        torch.full_like(c, 1 / math.sqrt(2 * pi)),
        math.sqrt(6 / pi) * cp * s,
        math.sqrt(3 / (2 * pi)) * u,
        math.sqrt(6 / pi) * sp * s,
        math.sqrt(30 / pi) * c2p * q,
        math.sqrt(30 / pi) * cp * u * s,
        math.sqrt(5 / (2 * pi)) * (6 * c * c - 6 * c + 1),
        math.sqrt(30 / pi) * sp * u * s,
        math.sqrt(30 / pi) * s2p * q,
    ]
    if terms == 16:
        s3 = s * s * s
        w = 1 - 5 * c + 5 * c * c
        out += [
            2 * math.sqrt(35 / pi) * torch.cos(3 * phi) * s3,
            math.sqrt(210 / pi) * c2p * u * q,
            2 * math.sqrt(21 / pi) * cp * s * w,
            math.sqrt(7 / (2 * pi)) * (20 * c ** 3 - 30 * c * c + 12 * c - 1),
            2 * math.sqrt(21 / pi) * sp * s * w,
            math.sqrt(210 / pi) * s2p * u * q,
            2 * math.sqrt(35 / pi) * torch.sin(3 * phi) * s3,
        ]
    return torch.stack(out, dim=-1)


def evaluate_rti(coefficients: torch.Tensor, lights: torch.Tensor, theta_clamp: Optional[float] = None) -> torch.Tensor:
    """Relight RTI HSH coefficient maps: ``sum_k coeff_k basis_k(l)``.

    Args:
        coefficients: ``(*S, C, T)`` with ``T`` 9 or 16.
        lights: ``(L, 3)``.
        theta_clamp: as in :func:`rti_hsh_basis`.

    Returns:
        ``(L, *S, C)``.

    Example:
        >>> a = torch.zeros(2, 2, 3, 9, dtype=torch.float64); a[..., 0] = math.sqrt(2 * math.pi)
        >>> evaluate_rti(a, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0, 0, 0]
        tensor([1., 1., 1.], dtype=torch.float64)
    """
    B = rti_hsh_basis(lights.to(coefficients), coefficients.shape[-1], theta_clamp)  # (L, T)
    return torch.einsum("...ct,lt->l...c", coefficients, B)


def _hemisphere_rule(nz: int, nphi: int, dtype=torch.float64, z0: float = 0.0):
    """Gauss-Legendre in ``cos(theta)`` on ``[z0, 1]`` x uniform ``phi``: ``(dirs (M, 3), weights (M,))``.

    The weights sum to the solid angle of the cap, ``2 pi (1 - z0)``.
    """
    x, w = np.polynomial.legendre.leggauss(nz)
    z = z0 + 0.5 * (1.0 - z0) * (x + 1.0)
    w = (1.0 - z0) * w
    phi = 2.0 * math.pi * (np.arange(nphi) + 0.5) / nphi
    Z, PH = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1.0 - Z * Z)
    dirs = np.stack([s * np.cos(PH), s * np.sin(PH), Z], axis=-1).reshape(-1, 3)
    wts = np.outer(0.5 * w, np.full(nphi, 2.0 * math.pi / nphi)).reshape(-1)
    return torch.tensor(dirs, dtype=dtype), torch.tensor(wts, dtype=dtype)


def project_to_rti(
    normals: torch.Tensor,
    coefficients: torch.Tensor,
    terms: int = 9,
    mask: Optional[torch.Tensor] = None,
    exposure: float = 1.0,
    linear: bool = False,
    max_angle_deg: Optional[float] = None,
    nz: int = 24,
    nphi: int = 48,
    chunk_size: int = 256,
    nonnegative: bool = False,
    progress: bool = False,
) -> torch.Tensor:
    r"""Project a photometric-stereo result onto the RTI HSH basis, pixel by pixel.

    With the view fixed at ``v = (0, 0, 1)``, each pixel's image as a function
    of the light is ``I(l) = sum_k a_k B_k(l, v, n) max(0, n . l)`` (this
    library's isotropic Helmholtz basis, :func:`torch_hsh.render.render_coefficients`).
    The viewers display ``sum_t c_t H_t(l)`` as is, so the function projected is
    ``g(l) = T(clip(exposure * I(l), 0, 1))`` with ``T`` the sRGB encoding
    (``linear=False``, default: what an RTI made from the photographs holds)
    or the identity (``linear=True``: the RTI holds linear values).

    * ``max_angle_deg=None`` (default): the projection on the whole upper
      hemisphere. The RTI basis is orthonormal there, so
      ``c_t = integral g H_t d omega``: the least-squares fit over every light
      direction a viewer can ask for, grazing ones included.
    * ``max_angle_deg=A``: the least-squares fit over the cap of lights within
      ``A`` degrees of the view (uniform in solid angle), ``c = G^-1 integral_cap
      g H d omega`` with ``G`` the Gram matrix of the basis on the cap. Use the
      largest angle of the captured lights: the model was observed there, and 9
      or 16 terms cannot follow it everywhere (see docs/rti.md for the numbers).

    The integrals use a Gauss-Legendre (in ``cos theta``) x uniform-``phi`` rule
    of ``nz x nphi`` directions; the model is a low-order polynomial in the
    directions times ``max(0, n . l)``: against 48 x 96, the default 24 x 48
    changes relit values by less than 2e-3 of white (half an 8-bit code) on the
    test scene (a textured sphere, Lambertian + Blinn-Phong, 16 terms).

    Args:
        normals: ``(*S, 3)`` unit normals.
        coefficients: ``(*S, C, K)`` isotropic Helmholtz coefficient maps.
        terms: 9 or 16.
        mask: optional ``(*S)`` bool; coefficients are zero outside.
        exposure: factor applied to the radiance before ``T`` (1 = the
            result's own units; choose it so that the brightest value is near 1).
        linear: ``True`` to project linear values (no sRGB transfer); ``False`` (default) to
            project sRGB-encoded values.
        max_angle_deg: ``None`` (whole hemisphere) or the half-angle of the
            cap of lights to fit, in ``(0, 90]``.
        nz, nphi: quadrature size.
        nonnegative: make the relit value non-negative at every light the viewers show
            (:func:`nonnegative_rti` with the fit's own metric: the constrained least-squares fit). ``torch-hsh rti``
            does this unless ``--allow-negative``.
        chunk_size: pixels per chunk. The rendering of a chunk holds about ``chunk_size x nz x nphi x K x 3``
            float64 values (at order 3 and the default rule, 256 pixels: about 250 MB); larger chunks are not faster
            (the bunny, 20,317 pixels, 1 thread: 14 s at 256, 24 s and 2 GB at 4,096).
        progress: show a progress bar per stage (tqdm, on stderr), as ``torch-hsh rti`` does.

    Returns:
        ``(*S, C, terms)`` RTI coefficients (float64).

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> a = torch.zeros(1, 3, 4, dtype=torch.float64); a[..., 0] = 2.0  # Lambertian, albedo 1
        >>> c = project_to_rti(n, a, 9, linear=True, exposure=math.pi)  # I = cos(theta)
        >>> l = torch.tensor([[0.6, 0.0, 0.8]], dtype=torch.float64)
        >>> abs(float(evaluate_rti(c, l)[0, 0, 0]) - 0.8) < 0.01
        True
    """
    from ..render.images import render_coefficients

    terms = _check_terms(terms)
    if not isinstance(linear, bool):
        raise TypeError(f"`linear` must be a bool, got {type(linear).__name__}")
    if normals.shape[-1] != 3 or coefficients.shape[:-2] != normals.shape[:-1]:
        raise ValueError(f"`normals` (*S, 3) and `coefficients` (*S, C, K) disagree: {tuple(normals.shape)}, "
                         f"{tuple(coefficients.shape)}")
    S = normals.shape[:-1]
    C = coefficients.shape[-2]
    n = normals.reshape(-1, 3).double()
    a = coefficients.reshape(n.shape[0], C, -1).double()
    keep = torch.ones(n.shape[0], dtype=torch.bool) if mask is None else mask.reshape(-1).bool().cpu()
    if max_angle_deg is None:
        dirs, w = _hemisphere_rule(nz, nphi)
        Hw = rti_hsh_basis(dirs, terms) * w[:, None]  # (M, T): orthonormal basis, projection = integral
    else:
        if not 0 < float(max_angle_deg) <= 90:
            raise ValueError(f"`max_angle_deg` must be in (0, 90], got {max_angle_deg}")
        dirs, w = _hemisphere_rule(nz, nphi, z0=math.cos(math.radians(float(max_angle_deg))))
        H = rti_hsh_basis(dirs, terms)
        G = (H * w[:, None]).T @ H  # Gram matrix on the cap
        Hw = torch.linalg.solve(G, (H * w[:, None]).T).T  # (M, T): least squares on the cap
    metric = torch.eye(terms, dtype=torch.float64) if max_angle_deg is None else G
    dirs, Hw = dirs.to(n.device), Hw.to(n.device)
    out = torch.zeros(n.shape[0], C, terms, dtype=torch.float64, device=n.device)
    idx = keep.nonzero().squeeze(1).to(n.device)
    bar = _bar(progress, idx.numel(), "RTI projection")
    for s0 in range(0, idx.numel(), chunk_size):
        sel = idx[s0 : s0 + chunk_size]
        img = render_coefficients(n[sel], dirs, a[sel]).clamp(min=0.0)  # (M, P, C)
        img = (img * float(exposure)).clamp(max=1.0)
        if not linear:
            img = torch.where(img <= 0.0031308, 12.92 * img, 1.055 * img.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)
        out[sel] = torch.einsum("mpc,mt->pct", img, Hw)
        bar.update(sel.numel())
    bar.close()
    if nonnegative:
        out[idx] = nonnegative_rti(out[idx], metric, progress=progress)
    return out.reshape(*S, C, terms)


def _bar(show: bool, total: int, desc: str, unit: str = "px"):
    """A tqdm bar over ``total`` items, or a stand-in that does nothing when ``show`` is false."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=not show)


def _cap_grid(max_angle_deg: float, nz: int, nphi: int, dtype=torch.float64) -> torch.Tensor:
    """Directions on the cap ``theta <= max_angle_deg``: ``nz`` rings uniform in ``theta`` from the rim to the
    pole (the rim included: a viewer evaluates every light beyond its clamp there), ``nphi`` azimuths a ring
    (fewer near the pole), and the pole."""
    tmax = math.radians(float(max_angle_deg))
    dirs = [np.array([[0.0, 0.0, 1.0]])]
    for i in range(nz):
        t = tmax * (nz - i) / nz
        m = max(6, int(round(nphi * math.sin(t) / math.sin(tmax)))) if tmax > 0 else 1
        ph = 2.0 * math.pi * (np.arange(m) + 0.5 * (i % 2)) / m
        dirs.append(np.stack([math.sin(t) * np.cos(ph), math.sin(t) * np.sin(ph), np.full(m, math.cos(t))], -1))
    return torch.tensor(np.concatenate(dirs), dtype=dtype)


#: Light directions where :func:`nonnegative_rti` requires a non-negative sum: OpenLIME's clamp, beyond which
#: it evaluates every light at the clamp.
NONNEGATIVE_MAX_ANGLE_DEG = math.degrees(OPENLIME_THETA_CLAMP)


def nonnegative_rti(
    coefficients: torch.Tensor,
    metric: Optional[torch.Tensor] = None,
    max_angle_deg: float = NONNEGATIVE_MAX_ANGLE_DEG,
    margin: float = 0.0,
    iterations: int = 40,
    rounds: int = 3,
    working: int = 16,
    nz: int = 24,
    nphi: int = 96,
    chunk_size: int = 16384,
    progress: bool = False,
) -> torch.Tensor:
    r"""The nearest RTI coefficients whose relit value is non-negative at every light a viewer can show.

    OpenLIME raises the HSH sum to the power 2.2 with no clamp, so a pixel whose sum is negative at some light
    shows a bright artefact there. For each pixel and colour whose sum ``sum_t c_t H_t(l)`` drops below
    ``margin`` somewhere on the cap ``theta <= max_angle_deg`` (default OpenLIME's clamp, 81.4 deg: it evaluates
    every light beyond it at the clamp), this solves the quadratic program

    ``min_c (c - c0)^T M (c - c0)  subject to  sum_t c_t H_t(l_k) >= margin``

    at the directions ``l_k`` of a grid of the cap (``2 nz`` rings uniform in ``theta``, the rim included,
    about ``2 nphi`` azimuths a ring; 5,700 directions by default), with ``M`` the ``metric`` (the Gram matrix of
    the least-squares fit that gave ``c0``: then the result is the constrained least-squares fit; default the
    identity, the L2 distance of the functions on the hemisphere).

    Solver, vectorised over pixels: each round keeps, per pixel and colour, the ``working`` directions of a
    coarser grid (``nz`` x ``nphi``) where the current sum is lowest (half of them the tightest of the last
    round's) and runs ``iterations`` ADMM steps on them (one small ``T x T`` system per pixel);
    ``rounds`` rounds (a round picks up directions that the last solution pushed below the bound). Last, where
    the sum is still below ``margin`` at a direction of the fine grid (the solver is approximate, and the coarse
    grid misses the lowest point by a little), the constant term is raised
    by the shortfall, so the result meets the constraint at every direction of the fine grid to rounding. Pixels
    and colours that already meet it there are returned unchanged. On the demo scene the objective is within
    0.1 % of the exact quadratic program's (SLSQP on the same constraints).

    Args:
        coefficients: ``(*S, C, T)`` RTI coefficients (T = 9 or 16).
        metric: ``(T, T)`` symmetric positive definite; default identity.
        max_angle_deg: half-angle of the cap of constrained lights.
        margin: lower bound of the sum (display units, 1 = white).
        iterations, rounds, working: ADMM steps per round, rounds, constraints kept per pixel and colour.
        nz, nphi: the solver's grid; the constraint holds on the grid twice as fine in each direction.
        chunk_size: pixel-colours per chunk.
        progress: show a progress bar over the pixel-colours that need the constraint (tqdm, on stderr).

    Returns:
        ``(*S, C, T)``, same dtype.

    Example:
        >>> c = torch.zeros(1, 1, 9, dtype=torch.float64); c[..., 0] = 0.5; c[..., 1] = 1.0  # negative toward -x
        >>> l = torch.tensor([[-0.98, 0.0, 0.2]], dtype=torch.float64)
        >>> before = float(evaluate_rti(c, l, OPENLIME_THETA_CLAMP))
        >>> after = float(evaluate_rti(nonnegative_rti(c), l, OPENLIME_THETA_CLAMP))
        >>> round(before, 2), after > -1e-3
        (-0.35, True)
    """
    T = coefficients.shape[-1]
    _check_terms(T)
    if not 0 < float(max_angle_deg) <= 90:
        raise ValueError(f"`max_angle_deg` must be in (0, 90], got {max_angle_deg}")
    dev = coefficients.device
    c = coefficients.reshape(-1, T).double()
    A = rti_hsh_basis(_cap_grid(max_angle_deg, nz, nphi), T).to(dev)  # (K, T): where the solver looks
    check = rti_hsh_basis(_cap_grid(max_angle_deg, 2 * nz, 2 * nphi), T).to(dev)  # (4 K, T): what is guaranteed
    M = torch.eye(T, dtype=torch.float64, device=dev) if metric is None else metric.to(dev, torch.float64)
    if M.shape != (T, T):
        raise ValueError(f"`metric` must be ({T}, {T}), got {tuple(M.shape)}")
    L = torch.linalg.cholesky(0.5 * (M + M.T))  # M = L L^T: y = L^T c whitens the objective to |y - y0|^2
    Linv_T = torch.linalg.inv(L).T  # c = Linv_T y
    B = A @ Linv_T  # (K, T): the constraints on y, A c = B y
    nb = B.norm(dim=1)
    B = B / nb[:, None]  # unit rows: B y >= lo
    lo = float(margin) / nb  # (K,)
    k = min(int(working), B.shape[0])
    rho = T / k  # ~ 1 / mean eigenvalue of B_W^T B_W (k unit rows in T dimensions)
    eye = torch.eye(T, dtype=torch.float64, device=dev)
    h0 = 1.0 / math.sqrt(2 * math.pi)  # H_0, the constant term
    out = c.clone()
    bad = ((c @ check.T).amin(dim=1) < float(margin)).nonzero().squeeze(1)
    bar = _bar(progress, bad.numel(), "RTI non-negative sums", "pixel-colour")
    for s0 in range(0, bad.numel(), chunk_size):
        sel = bad[s0: s0 + chunk_size]
        y0 = c[sel] @ L  # (P, T): rows (L^T c)^T
        y = y0
        W: Optional[torch.Tensor] = None
        BW: Optional[torch.Tensor] = None
        loW: Optional[torch.Tensor] = None
        for _ in range(int(rounds)):
            low = (y @ B.T - lo).topk(k, dim=1, largest=False).indices  # (P, k) the lowest directions now
            if W is not None and BW is not None and loW is not None:  # keep the half of the last working set that is tightest at the last solution
                keep = torch.gather(W, 1, (torch.einsum("pt,pkt->pk", y, BW) - loW).topk(
                    k // 2, dim=1, largest=False).indices)
                low = torch.cat([keep, low[:, : k - k // 2]], dim=1)
            W = low
            BW, loW = B[W], lo[W]  # (P, k, T), (P, k)
            step = torch.linalg.inv(eye + rho * BW.transpose(1, 2) @ BW)  # (P, T, T)
            z = torch.einsum("pt,pkt->pk", y0, BW).clamp(min=loW)
            u = torch.zeros_like(z)
            for _ in range(int(iterations)):
                y = torch.einsum("ps,pts->pt", y0 + rho * torch.einsum("pk,pkt->pt", z - u, BW), step)
                By = torch.einsum("pt,pkt->pk", y, BW)
                z = (By + u).clamp(min=loW)
                u = u + By - z
        cs = y @ Linv_T.T
        short = (float(margin) - (cs @ check.T).amin(dim=1)).clamp(min=0.0)
        cs[:, 0] = cs[:, 0] + short / h0
        out[sel] = cs
        bar.update(sel.numel())
    bar.close()
    return out.reshape(coefficients.shape).to(coefficients.dtype)


def fit_rti(
    images: torch.Tensor,
    lights: torch.Tensor,
    terms: int = 9,
    mask: Optional[torch.Tensor] = None,
    ridge: float = 1e-6,
) -> torch.Tensor:
    r"""Plain RTI fit: per-pixel least squares of the images in the RTI HSH basis (no normal, no BRDF).

    ``min_c sum_j (sum_t c_t H_t(l_j) - I_j)^2 + ridge ||c||^2`` for every pixel
    and channel: what RTIBuilder and ``relight`` compute from the photographs
    (one shared pseudo-inverse for all pixels). Fit the values in the encoding
    that the viewer will display (sRGB for photographs).

    Args:
        images: ``(L, *S, C)``.
        lights: ``(L, 3)``.
        terms: 9 or 16 (needs at least that many lights).
        mask: optional ``(*S)``; coefficients are zero outside.
        ridge: Tikhonov weight relative to ``trace(A^T A) / terms``.

    Returns:
        ``(*S, C, terms)`` float64.

    Example:
        >>> from torch_hsh.render import scenes
        >>> li = scenes.cone_lights(30, 80.0, seed=0, dtype=torch.float64)
        >>> c0 = torch.randn(4, 3, 9, dtype=torch.float64)
        >>> c = fit_rti(evaluate_rti(c0, li), li, ridge=0.0)
        >>> bool(torch.allclose(c, c0, atol=1e-8))
        True
    """
    terms = _check_terms(terms)
    L = images.shape[0]
    check_shape(lights, "lights", ("L", 3), sizes={"L": L})
    if L < terms:
        raise ValueError(f"a {terms}-term RTI fit needs at least {terms} lights, got {L}")
    A = rti_hsh_basis(lights.double(), terms)  # (L, T)
    G = A.T @ A
    G = G + ridge * float(torch.trace(G)) / terms * torch.eye(terms, dtype=G.dtype)
    pinv = torch.linalg.solve(G, A.T)  # (T, L)
    c = torch.einsum("tl,l...c->...ct", pinv.to(images.device), images.double())
    if mask is not None:
        c = c * mask.to(c.device, c.dtype)[..., None, None]
    return c
