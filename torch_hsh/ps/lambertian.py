r"""Lambertian photometric-stereo baselines.

Model: ``I_jc / e_jc = (rho_c / pi) max(0, n . l_j)`` (the renderer's convention
``f = rho / pi``). Channels are averaged (after dividing by the light
intensities) to estimate the scaled normal ``b = (rho / pi) n`` by least
squares (Woodham 1980); the per-channel albedo is then fitted with the normal
fixed. Both solvers are batched over pixels (``(N, 3, 3)`` normal equations).

* :func:`lambertian_ls` uses every observation.
* :func:`robust_lambertian` trims, per pixel, the darkest ``drop_dark``
  fraction (shadows) and the brightest ``drop_bright`` fraction (highlights)
  of the observations, ranked by their channel-averaged value.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from ._chunks import scatter_pixels
from .observations import prepare_inputs

__all__ = ["LambertianResult", "lambertian_ls", "robust_lambertian", "trimmed_weights"]


@dataclass
class LambertianResult:
    """Result of a Lambertian solver.

    Attributes:
        normals: ``(*S, 3)`` unit normals, zero outside ``mask``.
        albedo: ``(*S, C)`` diffuse albedo ``rho`` (with ``f = rho / pi``), zero outside ``mask``.
        mask: ``(*S)`` bool.
    """

    normals: torch.Tensor
    albedo: torch.Tensor
    mask: torch.Tensor


def _solve_flat(y: torch.Tensor, lights: torch.Tensor, w: Optional[torch.Tensor]):
    """Weighted Lambertian LS. ``y (N, L, C)``, ``lights (L, 3)``, ``w (N, L)`` -> normals (N, 3), albedo (N, C)."""
    g = y.mean(-1)  # (N, L)
    g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
    if w is None:
        w = torch.ones_like(g)
    A = torch.einsum("pl,la,lb->pab", w, lights, lights)
    rhs = torch.einsum("pl,pl,la->pa", w, g, lights)
    tr = A.diagonal(dim1=-2, dim2=-1).sum(-1).clamp(min=1e-30)
    A = A + (1e-9 * tr)[:, None, None] * torch.eye(3, dtype=A.dtype, device=A.device)
    b = torch.linalg.solve_ex(A, rhs.unsqueeze(-1))[0].squeeze(-1)  # SPD (diagonal load): no host-side check
    nb = b.norm(dim=-1, keepdim=True)
    default = torch.zeros_like(b)
    default[:, 2] = 1.0
    n = torch.where(nb > 0, b / nb.clamp(min=1e-30), default)
    shade = (lights @ n.T).T.clamp(min=0.0)  # (N, L)
    ws = w * shade
    yy = torch.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
    num = torch.einsum("pl,plc->pc", ws, yy)
    den = (ws * shade).sum(-1, keepdim=True).clamp(min=1e-30)
    return n, math.pi * num / den


def trimmed_weights(y: torch.Tensor, drop_dark: float = 0.25, drop_bright: float = 0.10) -> torch.Tensor:
    """Per-pixel 0/1 weights keeping the observations between two rank quantiles.

    Args:
        y: ``(N, L, C)`` observations.
        drop_dark: fraction of darkest observations dropped per pixel, in ``[0, 1)``.
        drop_bright: fraction of brightest observations dropped, ``drop_dark + drop_bright < 1``.

    Returns:
        ``(N, L)`` weights (at least 3 observations kept per pixel).

    Example:
        >>> trimmed_weights(torch.arange(8.0).reshape(1, 8, 1), 0.25, 0.25)
        tensor([[0., 0., 1., 1., 1., 1., 0., 0.]])
    """
    if not (0.0 <= drop_dark < 1.0 and 0.0 <= drop_bright < 1.0 and drop_dark + drop_bright < 1.0):
        raise ValueError(
            f"need 0 <= drop_dark, drop_bright and drop_dark + drop_bright < 1, got {drop_dark}, {drop_bright}"
        )
    N, L, _ = y.shape
    g = torch.nan_to_num(y.mean(-1), nan=-float("inf"))
    lo = int(math.floor(drop_dark * L))
    hi = L - int(math.floor(drop_bright * L))
    if hi - lo < 3:
        lo, hi = max(0, min(lo, L - 3)), max(3, min(L, lo + 3))
    rank = torch.argsort(torch.argsort(g, dim=1), dim=1)
    return ((rank >= lo) & (rank < hi)).to(y.dtype)


def lambertian_ls(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
) -> LambertianResult:
    """Woodham's least-squares Lambertian photometric stereo, batched over pixels.

    Args:
        images: ``(L, H, W, C)`` or ``(L, N, C)`` images (trailing channel axis).
        lights: ``(L, 3)`` directions toward the lights.
        intensities: ``None``, ``(L,)`` or ``(L, C)``; images are divided by them.
        mask: optional ``(H, W)`` / ``(N,)`` bool mask of the pixels to solve.

    Returns:
        :class:`LambertianResult` with ``normals (*S, 3)`` and ``albedo (*S, C)``.

    Example:
        >>> l = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
        >>> imgs = (l @ torch.tensor([0.0, 0.0, 1.0])).reshape(3, 1, 1) / torch.pi
        >>> lambertian_ls(imgs, l).normals.round(decimals=4).abs()
        tensor([[0., 0., 1.]])
    """
    d = prepare_inputs(images, lights, intensities, mask)
    n, rho = _solve_flat(d.y, d.lights, None)
    return LambertianResult(scatter_pixels(n, d.mask), scatter_pixels(rho, d.mask), d.mask)


def robust_lambertian(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    drop_dark: float = 0.25,
    drop_bright: float = 0.10,
) -> LambertianResult:
    """Trimmed least-squares Lambertian photometric stereo.

    Per pixel, the darkest ``drop_dark`` and brightest ``drop_bright`` fractions
    of the observations (ranked by channel mean after dividing by the light
    intensities) are discarded before Woodham's least squares.

    Args:
        images, lights, intensities, mask: as in :func:`lambertian_ls`.
        drop_dark: fraction of darkest observations to drop (default 0.25).
        drop_bright: fraction of brightest observations to drop (default 0.10).

    Returns:
        :class:`LambertianResult`.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> l = torch.nn.functional.normalize(torch.rand(20, 3, generator=g) + torch.tensor([0, 0, 1.0]), dim=-1)
        >>> imgs = (l @ torch.tensor([0.0, 0.0, 1.0])).reshape(20, 1, 1)
        >>> robust_lambertian(imgs, l).normals.round(decimals=4).abs()
        tensor([[0., 0., 1.]])
    """
    d = prepare_inputs(images, lights, intensities, mask)
    w = trimmed_weights(d.y, drop_dark, drop_bright)
    n, rho = _solve_flat(d.y, d.lights, w)
    return LambertianResult(scatter_pixels(n, d.mask), scatter_pixels(rho, d.mask), d.mask)
