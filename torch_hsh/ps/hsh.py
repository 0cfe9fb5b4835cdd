r"""Non-Lambertian photometric stereo with the isotropic Helmholtz HSH basis.

Model, per pixel (one unit normal ``n`` shared by the channels, one set of
isotropic Helmholtz coefficients per channel):

.. math::
    y_{jc} = I_{jc} / e_{jc} = \sum_k a_{ck}\, \Phi_{jk}(n), \qquad
    \Phi_{jk}(n) = B_k(l_j, v, n)\, \max(0, n\cdot l_j),

with ``v = (0, 0, 1)`` and :math:`B_k` from
:func:`torch_hsh.helmholtz_isotropic_world` (zero below the horizon).

Two models (see ``docs/photometric_stereo.md``):

* **shared basis BRDFs** (default, ``materials=M``): :math:`a_{pc} = \sum_m
  W_{pcm} B_m` (+ a ridge-shrunk per-pixel residual fitted at the end), with
  ``M`` basis BRDFs shared by the object and free per-pixel RGB mixing
  weights. Sharing removes the single-view elevation ambiguity of a BRDF
  that is free at every pixel. The basis is calibrated on a pixel subset
  (Cauchy IRLS on the basis and mixing weights alternating with LM on the
  normals, from two starts), then every pixel runs IRLS + variable-projection
  LM on its normal with the basis fixed (mixing weights in closed form).
* **independent** (``materials=None``): ``K`` free coefficients per pixel and
  channel with a ridge that grows with order; VP-LM from the robust
  Lambertian start with a coarse cone search and Cauchy IRLS stages.

Common pieces: observation weights from adaptive dark / saturation thresholds
(:func:`observation_weights`), a tangent parametrisation
``n(u) = normalize(n0 + u1 t1 + u2 t2)`` re-centred after every accepted step,
Golub–Pereyra Jacobians of the projected residual, and final coefficients with
a non-negativity safeguard (the rendered BRDF is penalised where it is
negative at the lights and at a fixed hemisphere of virtual lights).

Everything is batched over pixels and processed in chunks of ``chunk_size``
pixels, so memory is bounded by ``O(chunk_size * L * K)``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence

import torch

from .._checks import check_order
from functools import lru_cache

from ..basis import _polar_consts, _polar_table, _polar_table_t, _safe_s, isotropic_indices, num_isotropic
from ..render import render_coefficients
from ._common import prepare_inputs, robust_sigma, scatter_pixels, tangent_frame
from ._mixture import (
    MixedDesign,
    _ridge_diag,
    _t_scatter,
    cauchy_weights,
    fd_step,
    irls_weights,
    lm_normals,
    observation_residual,
    reduced_cost,
    solve_weights,
)
from .lambertian import _solve_flat, trimmed_weights

__all__ = [
    "HSHResult",
    "HoldoutResult",
    "DEFAULT_ORDER",
    "DEFAULT_MATERIALS",
    "solve_hsh",
    "holdout_evaluation",
    "directional_albedo_view",
    "observation_weights",
]

#: Default basis order: 3 (K = 20 functions per channel). With the view fixed
#: (orthographic camera) only (P+1)(P+2)/2 = 10 combinations per channel are
#: identifiable from one pixel, comfortably fewer than the 50-100 lights of a
#: typical capture even after shadows and highlights are removed.
DEFAULT_ORDER = 3

#: Default number of shared basis BRDFs ("materials") of the shared model.
#: Two cover the common dichromatic case (a coloured body reflection and a
#: specular reflection with its own colour) with free RGB weights per pixel.
DEFAULT_MATERIALS = 2


@dataclass
class HSHResult:
    """Output of :func:`solve_hsh`.

    Attributes:
        normals: ``(*S, 3)`` unit normals (DiLiGenT frame), zero outside ``mask``.
        coefficients: ``(*S, C, K)`` isotropic Helmholtz coefficient maps.
        albedo: ``(*S, C)`` directional albedo toward the camera,
            :math:`\\int f(\\omega_i, v) \\cos\\theta_i d\\omega_i`.
        residual: ``(*S)`` weighted RMS residual of the coefficient fit.
        weights: ``(*S, L)`` final robust observation weights of the normal
            estimation (0 = not used; the shared model fits the coefficients
            to every valid observation).
        mask: ``(*S)`` bool.
        order: basis order.
        lights: ``(L, 3)`` lights used in the fit.
        runtime_s: wall time of the solve in seconds.
        info: diagnostics (noise estimate, saturation level, iteration counts, ...).
        basis_brdfs: shared model only: ``(M, K)`` unit-norm basis BRDFs
            (isotropic Helmholtz coefficients), else ``None``.
        mixing: shared model only: ``(*S, C, M)`` per-pixel mixing weights
            (``coefficients ~= mixing @ basis_brdfs``), else ``None``.
    """

    normals: torch.Tensor
    coefficients: torch.Tensor
    albedo: torch.Tensor
    residual: torch.Tensor
    weights: torch.Tensor
    mask: torch.Tensor
    order: int
    lights: torch.Tensor
    runtime_s: float
    info: Dict[str, float] = field(default_factory=dict)
    basis_brdfs: Optional[torch.Tensor] = None
    mixing: Optional[torch.Tensor] = None

    def relight(self, lights: torch.Tensor, intensities: Optional[torch.Tensor] = None, clamp: bool = True) -> torch.Tensor:
        """Render the fitted surface under new lights.

        Args:
            lights: ``(L', 3)`` directions toward the lights.
            intensities: ``None``, ``(L',)`` or ``(L', C)``.
            clamp: clamp negative radiance to zero (default).

        Returns:
            ``(L', *S, C)`` images, zero outside the mask.

        Example:
            >>> res.relight(torch.tensor([[0.0, 0.0, 1.0]])).shape  # doctest: +SKIP
            torch.Size([1, 64, 64, 3])
        """
        img = render_coefficients(self.normals, lights.to(self.normals), self.coefficients, intensities, None)
        img = img * self.mask.to(img.dtype).unsqueeze(-1)
        return img.clamp(min=0.0) if clamp else img


@dataclass
class HoldoutResult:
    """Output of :func:`holdout_evaluation`.

    Attributes:
        train_indices, test_indices: light indices used for fitting / held out.
        relative_rmse: ``sqrt(sum (pred - obs)^2 / sum obs^2)`` over the held-out
            observations (inside the mask, unsaturated, finite) for the HSH fit.
        rmse: root-mean-square error of the HSH relighting (image units).
        lambertian_relative_rmse: the same for the robust Lambertian fit.
        predictions: ``(L_test, *S, C)`` relit images.
        result: the :class:`HSHResult` fitted on the training lights.
    """

    train_indices: torch.Tensor
    test_indices: torch.Tensor
    relative_rmse: float
    rmse: float
    lambertian_relative_rmse: float
    predictions: torch.Tensor
    result: HSHResult


# ---------------------------------------------------------------------------
# Closed-form pieces
# ---------------------------------------------------------------------------
def _albedo_vector(order: int, cos_o: torch.Tensor) -> torch.Tensor:
    """``D_k(cos_o) = integral of B_k(wi, wo) cos(theta_i) dwi`` for every isotropic function, ``(P, K)``.

    Only q = 0 terms with p <= 1 or r <= 1 are non-zero: the integral over
    ``[0, 1]`` of ``P~_n(x) x dx`` is 1/2 (n = 0), 1/6 (n = 1), 0 otherwise.
    """
    idx = isotropic_indices(order).tolist()
    R = _polar_table(cos_o.clamp(0.0, 1.0), order)  # normalised Theta_n^m(cos_o) table
    # columns of the polar table for m = 0 are the first block: n = 0..P at columns 0..P
    integ = {0: 0.5, 1: 1.0 / 6.0}
    cols = []
    zero = torch.zeros_like(cos_o)
    for p, r, q in idx:
        if q != 0:
            cols.append(zero)
            continue
        npr = 0.5 if p == r else 1.0 / math.sqrt(2.0)
        val = zero
        for a, b in ((p, r), (r, p)):
            if a in integ:
                ca = 2.0 * math.pi * math.sqrt((2 * a + 1) / (2.0 * math.pi)) * integ[a]
                val = val + ca * R[:, _m0_col(order, b)]
        cols.append(npr * val)
    return torch.stack(cols, dim=-1)


def _m0_col(order: int, n: int) -> int:
    # block layout of _polar_table: block j = n - m holds m = 0..P-j; m = 0 of block j sits at offset(j)
    off = 0
    for j in range(n):
        off += order + 1 - j
    return off


def directional_albedo_view(coefficients: torch.Tensor, cos_o: torch.Tensor) -> torch.Tensor:
    r"""Directional albedo :math:`\rho(\omega_o) = \int f(\omega_i, \omega_o)\cos\theta_i\,d\omega_i` in closed form.

    Args:
        coefficients: ``(..., C, K)`` isotropic Helmholtz coefficients.
        cos_o: ``(...)`` cosine of the outgoing direction with the normal.

    Returns:
        ``(..., C)``.

    Example:
        >>> a = torch.zeros(1, 3, 20, dtype=torch.float64); a[..., 0] = 2 * 0.5  # Lambertian rho = 0.5
        >>> directional_albedo_view(a, torch.tensor([0.7], dtype=torch.float64))
        tensor([[0.5000, 0.5000, 0.5000]], dtype=torch.float64)
    """
    K = coefficients.shape[-1]
    from ..render import order_from_num_coefficients

    order = order_from_num_coefficients(K)
    lead = cos_o.shape
    D = _albedo_vector(order, cos_o.reshape(-1).to(coefficients.dtype))  # (N, K)
    a = coefficients.reshape(-1, coefficients.shape[-2], K)
    return torch.einsum("nck,nk->nc", a, D).reshape(*lead, coefficients.shape[-2])


def _ridge_profile(order: int, dtype, device, eps: float = 1e-6) -> torch.Tensor:
    idx = isotropic_indices(order).to(device=device, dtype=dtype)
    p, r = idx[:, 0], idx[:, 1]
    return eps + 0.5 * (p * (p + 1) + r * (r + 1))


def _hemisphere_dirs(n: int, dtype, device) -> torch.Tensor:
    """Fibonacci set of ``n`` unit directions with z in (0, 1)."""
    i = torch.arange(n, dtype=dtype, device=device) + 0.5
    z = 1.0 - i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    s = torch.sqrt((1 - z * z).clamp(min=0))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], dim=-1)


class _Chunk:
    """One batch of pixels: data, weights, and the reduced (variable-projection) residual."""

    def __init__(self, y, w, lights, view, order, ridge_profile, ridge):
        self.y = y  # (p, L, C)
        self.lights = lights  # (L, 3)
        self.view = view
        self.order = order
        self.profile = ridge_profile  # (K,)
        self.ridge = ridge
        self.set_weights(w)

    def set_weights(self, w):
        self.w = w
        self.sw = w.sqrt()

    def design(self, n, lights=None):
        """``Phi (p, L, K)``: basis times ``max(0, n.l)`` for unit-ish normals ``n (p, 3)``.

        Same values as :func:`torch_hsh.render.shading_basis` with the view
        ``(0, 0, 1)``. With the view fixed, every isotropic function factorises as
        ``Phi = X @ T``: ``X (p, L, U)`` holds the normalised polar table at
        ``n.l`` times the azimuthal factor ``(s_i s_o)^q Re(c^q)`` and the shading,
        ``T (p, U, K)`` the polar table at ``n.v``, with ``U = (P+1)(P+2)/2``.
        One batched matmul replaces a per-(pixel, light) basis evaluation, and the
        rank of ``Phi`` is at most ``U`` (the identifiable part of the BRDF for
        one viewpoint). Plain differentiable ops: forward-mode AD works.
        """
        lights = self.lights if lights is None else lights
        X, T = _design_factors(n, lights, self.order)
        return X @ T

    def set_ridge_scale(self, n, Phi=None):
        Phi = self.design(n) if Phi is None else Phi
        G = torch.einsum("plk,pl,plk->pk", Phi, self.w, Phi)
        s = G.mean(-1)
        s = torch.where(s > 0, s, torch.ones_like(s))
        self.ridge_diag = self.ridge * s.unsqueeze(-1) * self.profile  # (p, K)

    def solve(self, Phi, w, ridge_diag, y, extra=None, rhs_extra=None):
        Pw = Phi * w.unsqueeze(-1)
        G = Pw.transpose(1, 2) @ Phi
        if extra is not None:
            G = G + extra
        G = G + torch.diag_embed(ridge_diag)
        rhs = Pw.transpose(1, 2) @ y  # (p, K, C)
        if rhs_extra is not None:
            rhs = rhs + rhs_extra
        return torch.cholesky_solve(rhs, self._chol(G))  # (p, K, C)

    @staticmethod
    def _chol(G):
        Lc, info = torch.linalg.cholesky_ex(G)
        if bool((info > 0).any()):
            jitter = 1e-8 * G.diagonal(dim1=-2, dim2=-1).mean(-1).clamp(min=1e-30)
            eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
            Lc, _ = torch.linalg.cholesky_ex(G + jitter[:, None, None] * eye)
        return Lc

    def residual(self, n, idx=None):
        """Stacked residual ``[sqrt(w)(y - Phi a); sqrt(ridge) a]`` of shape (p, M), and ``a``."""
        y = self.y if idx is None else self.y[idx]
        w = self.w if idx is None else self.w[idx]
        sw = self.sw if idx is None else self.sw[idx]
        rd = self.ridge_diag if idx is None else self.ridge_diag[idx]
        Phi = self.design(n)
        a = self.solve(Phi, w, rd, y)
        r_data = sw.unsqueeze(-1) * (y - Phi @ a)
        r_reg = rd.sqrt().unsqueeze(-1) * a
        return torch.cat([r_data.flatten(1), r_reg.flatten(1)], dim=1), a

    def cost(self, n, idx=None):
        r, _ = self.residual(n, idx)
        return (r * r).sum(-1)

    def jacobian(self, n, idx):
        """Gauss–Newton normal equations ``J^T J (q, 2, 2)``, ``J^T r (q, 2)`` of the reduced residual at ``n``.

        ``J`` is the Jacobian of the stacked residual ``[sqrt(w)(y - Phi a); sqrt(ridge) a]``
        w.r.t. the tangent coordinates (never formed explicitly).

        ``dPhi`` along both tangents comes from forward differences of the
        design matrix; the derivative of the closed-form coefficient solve is
        then analytic (variable projection, Golub–Pereyra), reusing the Cholesky
        factor: ``da = G^-1 (dPhi^T W e - Phi^T W dPhi a)``.
        """
        t1, t2 = tangent_frame(n)
        q = n.shape[0]
        # dPhi along both tangents by forward differences of the (cheap, smooth)
        # factorised design: ~1e-6 relative error in float64 (h = 1e-6), plenty
        # for LM and several times faster than forward-mode AD through the kernel
        h = fd_step(n.dtype)
        stack = torch.cat([n, n + h * t1, n + h * t2])
        D = self.design(stack).reshape(3, q, *self.y.shape[1:2], -1)
        Phi = D[0]
        dPhi = torch.stack([(D[1] - D[0]) / h, (D[2] - D[0]) / h], dim=1)  # (q, 2, L, K)
        y, w, sw, rd = self.y[idx], self.w[idx], self.sw[idx], self.ridge_diag[idx]
        Pw = Phi * w.unsqueeze(-1)
        G = Pw.transpose(1, 2) @ Phi + torch.diag_embed(rd)
        Lc = self._chol(G)
        a = torch.cholesky_solve(Pw.transpose(1, 2) @ y, Lc)  # (q, K, C)
        e = y - Phi @ a  # (q, L, C)
        dPa = dPhi @ a.unsqueeze(1)  # (q, 2, L, C)
        rhs = dPhi.transpose(-1, -2) @ (w.unsqueeze(-1) * e).unsqueeze(1) - Pw.transpose(1, 2).unsqueeze(1) @ dPa
        C = y.shape[-1]
        rhs_cat = torch.cat([rhs[:, 0], rhs[:, 1]], dim=-1)  # (q, K, 2C)
        da = torch.cholesky_solve(rhs_cat, Lc)
        da = torch.stack([da[..., :C], da[..., C:]], dim=1)  # (q, 2, K, C)
        dr_data = (-sw[:, None, :, None] * (dPa + Phi.unsqueeze(1) @ da)).flatten(2)  # (q, 2, L C)
        srd = rd.sqrt()
        dr_reg = (srd[:, None, :, None] * da).flatten(2)  # (q, 2, K C)
        r_data = (sw.unsqueeze(-1) * e).flatten(1).unsqueeze(-1)
        r_reg = (srd.unsqueeze(-1) * a).flatten(1).unsqueeze(-1)
        # normal equations of the stacked residual [data; ridge] without forming it
        JtJ = dr_data @ dr_data.transpose(1, 2) + dr_reg @ dr_reg.transpose(1, 2)  # (q, 2, 2)
        g = (dr_data @ r_data + dr_reg @ r_reg).squeeze(-1)  # (q, 2)
        return JtJ, g, t1, t2



@lru_cache(maxsize=None)
def _factor_tables(order: int):
    """Index tables of the factorisation ``Phi = X @ T`` (see :meth:`_Chunk.design`)."""
    col = _polar_consts(order)[3]
    U = len(col)
    qcol = [0] * U
    for (nn, m), c in col.items():
        qcol[c] = m
    # T[u=(p,q), k] += c R(r,q)(zo);  T[u=(r,q), k] += c R(p,q)(zo)
    rows, cols_k, src, coef = _t_scatter(order)
    return U, qcol, rows, cols_k, src, coef


def _design_factors(n: torch.Tensor, lights: torch.Tensor, order: int):
    """``X (p, L, U)`` and ``T (p, U, K)`` with ``X @ T`` the shading-weighted design matrix."""
    U, qcol, rows, cols_k, src, coef = _factor_tables(order)
    dev, dt = n.device, n.dtype
    K = num_isotropic(order)
    nrm = torch.nn.functional.normalize(n, dim=-1)
    p, L = nrm.shape[0], lights.shape[0]
    zi = nrm @ lights.T  # (p, L) n.l
    zo = nrm[:, 2]  # (p,) n.v
    valid = (zi >= 0) & (zo >= 0).unsqueeze(-1)
    zi_c = zi.clamp(0.0, 1.0)
    zo_c = zo.clamp(0.0, 1.0)
    a = lights[:, 2].unsqueeze(0) - zi * zo.unsqueeze(-1)  # tangential dot l_t . v_t
    rho = (1.0 - zi_c * zi_c) * (1.0 - zo_c * zo_c).unsqueeze(-1)
    sio = _safe_s(zi_c) * _safe_s(zo_c).unsqueeze(-1)
    mask = valid.to(dt) * zi_c  # shading max(0, n.l), zero where invalid
    G = [mask]
    if order >= 1:
        a1 = sio * a
        r1 = sio * sio * rho
        G.append(a1 * mask)
        for _ in range(2, order + 1):
            G.append(2.0 * a1 * G[-1] - r1 * G[-2])
    sq2 = math.sqrt(2.0)
    G = torch.stack([G[0]] + [g * sq2 for g in G[1:]], dim=-1)  # (p, L, P+1)
    Ri = _polar_table_t(zi_c.reshape(-1), order).t().reshape(p, L, U)  # (p, L, U)
    qidx = torch.tensor(qcol, device=dev)
    X = Ri * G.index_select(-1, qidx)
    Ro = _polar_table_t(zo_c, order).t()  # (p, U)
    vals = Ro[:, src] * torch.tensor(coef, dtype=dt, device=dev)  # (p, 2K)
    T = torch.zeros(p, U, K, dtype=dt, device=dev)
    T = T.index_put((torch.arange(p, device=dev).unsqueeze(-1), torch.tensor(rows, device=dev).unsqueeze(0).expand(p, -1),
                     torch.tensor(cols_k, device=dev).unsqueeze(0).expand(p, -1)), vals, accumulate=True)
    return X, T

def _lm(ch: _Chunk, n: torch.Tensor, max_iter: int, tol: float = 1e-5, max_step: float = 0.35):
    """Per-pixel Levenberg–Marquardt on the reduced problem; returns normals, costs, iterations used."""
    p = n.shape[0]
    n = n.clone()
    all_idx = torch.arange(p, device=n.device)
    cost = ch.cost(n, all_idx)
    mu = torch.full((p,), 1e-3, dtype=n.dtype, device=n.device)
    active = torch.ones(p, dtype=torch.bool, device=n.device)
    iters = 0
    for _ in range(max_iter):
        idx = active.nonzero().squeeze(1)
        if idx.numel() == 0:
            break
        iters += 1
        ni = n[idx]
        JtJ, g, t1, t2 = ch.jacobian(ni, idx)
        D = JtJ.diagonal(dim1=-2, dim2=-1)
        D = D + 1e-12 * D.sum(-1, keepdim=True) + 1e-30
        A = JtJ + torch.diag_embed(mu[idx].unsqueeze(-1) * D)
        delta = -torch.linalg.solve(A, g.unsqueeze(-1)).squeeze(-1)
        dn = delta.norm(dim=-1, keepdim=True)
        delta = delta * (max_step / dn.clamp(min=max_step))
        nn = torch.nn.functional.normalize(ni + delta[:, :1] * t1 + delta[:, 1:] * t2, dim=-1)
        cn = ch.cost(nn, idx)
        c0 = cost[idx]
        acc = cn < c0
        rel = (c0 - cn) / c0.clamp(min=1e-300)
        n[idx[acc]] = nn[acc]
        cost[idx[acc]] = cn[acc]
        mu_i = torch.where(acc, mu[idx] / 3.0, mu[idx] * 4.0).clamp(1e-9, 1e9)
        mu[idx] = mu_i
        small = dn.squeeze(-1) < tol
        done = (acc & (small | (rel < 1e-10))) | (~acc & ((mu_i >= 1e8) | small))
        active[idx[done]] = False
    return n, cost, iters


def _cone_candidates(n0: torch.Tensor, angles_deg: Sequence[float], azimuths: int):
    t1, t2 = tangent_frame(n0)
    out = []
    for k, ang in enumerate(angles_deg):
        a = math.radians(ang)
        for j in range(azimuths):
            phi = 2 * math.pi * (j + 0.5 * (k % 2)) / azimuths
            d = math.cos(phi) * t1 + math.sin(phi) * t2
            out.append(math.cos(a) * n0 + math.sin(a) * d)
    return out


def _cone_search(n: torch.Tensor, cost, angles_deg: Sequence[float], azimuths: int, base_cost=None):
    """Per pixel, the lowest-``cost`` normal among ``n`` and a cone of candidates around it.

    ``cost`` maps normals ``(p, 3)`` to ``(p,)``; ``base_cost`` is ``cost(n)`` if already known.
    """
    if len(angles_deg) == 0 or azimuths <= 0:
        return n
    best = cost(n) if base_cost is None else base_cost
    for cand in _cone_candidates(n, angles_deg, azimuths):
        cc = cost(cand)
        better = cc < best
        n = torch.where(better.unsqueeze(-1), cand, n)
        best = torch.where(better, cc, best)
    return n


def observation_weights(
    y: torch.Tensor,
    raw: torch.Tensor,
    background: Optional[torch.Tensor] = None,
    dark_fraction: float = 0.05,
    noise_sigma: Optional[float] = None,
    saturation: Optional[float] = None,
):
    """Weights ``(P, L)`` in {0, 1} from adaptive dark / saturation thresholds.

    Args:
        y: ``(P, L, C)`` observations divided by the light intensities.
        raw: ``(P, L, C)`` raw observations (same values before the division).
        background: ``(Q, C)`` raw values outside the object mask, used for the
            robust noise estimate ``sigma = 1.4826 MAD`` (ignored if fewer than
            64 pixels or if ``noise_sigma`` is given).
        dark_fraction: an observation is dark if its channel mean is below
            ``dark_fraction`` times the pixel's 75th-percentile brightness
            (attached/cast shadows, grazing light), or below ``3 sigma`` in raw units.
        noise_sigma: raw noise level; ``None``: estimated.
        saturation: raw saturation level; ``None``: detected as a plateau at the
            largest raw value present (at least 3 and at least 0.01% of the
            observations within 0.1% of the maximum); observations with a channel
            at or above 99% of that level are dropped.

    Returns:
        ``(weights (P, L), info dict)``.

    Example:
        >>> y = torch.rand(4, 10, 3)
        >>> w, info = observation_weights(y, y)
        >>> w.shape
        torch.Size([4, 10])
    """
    finite = torch.isfinite(raw).all(-1)
    rawf = torch.where(torch.isfinite(raw), raw, torch.zeros_like(raw))
    info = {}
    if saturation is None:
        mx = float(rawf.max())
        plateau = int((rawf >= mx * (1 - 1e-3)).sum()) if mx > 0 else 0
        if mx > 0 and plateau >= max(3, int(1e-4 * rawf.numel())):
            saturation = mx
    sat = torch.zeros_like(finite)
    if saturation is not None:
        sat = (rawf >= 0.99 * float(saturation)).any(-1)
        info["saturation_level"] = float(saturation)
    if noise_sigma is None:
        noise_sigma = 0.0
        if background is not None and background.shape[0] >= 64:
            bg = background[torch.isfinite(background).all(-1)]
            noise_sigma = robust_sigma(bg)
    info["noise_sigma"] = float(noise_sigma)
    g = torch.where(finite, y.mean(-1), torch.zeros_like(y[..., 0]))
    q75 = torch.quantile(g, 0.75, dim=1, keepdim=True)
    dark = (g <= dark_fraction * q75) | (rawf.mean(-1) <= 3.0 * noise_sigma)
    w = (finite & ~sat & ~dark).to(y.dtype)
    info["saturated_fraction"] = float(sat.to(y.dtype).mean())
    info["dark_fraction"] = float(dark.to(y.dtype).mean())
    return w, info


def _robust_weights(ch: _Chunk, n, w0, sigma_floor, c: float = 2.385):
    Phi = ch.design(n)
    a = ch.solve(Phi, ch.w, ch.ridge_diag, ch.y)
    res = (ch.y - Phi @ a).pow(2).mean(-1).sqrt()  # (p, L)
    big = torch.full_like(res, float("inf"))
    rr = torch.where(w0 > 0, res, big)
    cnt = (w0 > 0).sum(-1)
    srt = rr.sort(dim=1).values
    mid = ((cnt - 1).clamp(min=0) // 2).unsqueeze(-1)
    med = srt.gather(1, mid).squeeze(-1)
    med = torch.where(torch.isfinite(med), med, torch.zeros_like(med))
    scale = (1.4826 * med).clamp(min=sigma_floor)
    return w0 / (1.0 + (res / (c * scale.unsqueeze(-1))) ** 2)


def _final_coefficients(ch: _Chunk, n, nonneg: bool, prior=None, gamma: float = 10.0, iters: int = 4, virtual: int = 48,
                        Phi=None):
    """Per-pixel ridge coefficients ``(p, K, C)``, shrunk toward ``prior`` (default 0), with the non-negativity safeguard."""
    Phi = ch.design(n) if Phi is None else Phi
    a0 = torch.zeros(Phi.shape[0], Phi.shape[-1], ch.y.shape[-1], dtype=Phi.dtype, device=Phi.device) if prior is None else prior
    a = a0 + ch.solve(Phi, ch.w, ch.ridge_diag, ch.y - Phi @ a0)
    if not nonneg:
        return a
    vdirs = _hemisphere_dirs(virtual, n.dtype, n.device)
    Pv = ch.design(n, vdirs)  # (p, V, K)
    Pall = torch.cat([Phi, Pv], dim=1)
    Wv = Pall.new_zeros(Pall.shape[:2])
    scale = ch.w.sum(-1, keepdim=True).clamp(min=1.0) / Pall.shape[1]
    for _ in range(iters):
        pred = Pall @ a  # (p, L+V, C)
        neg = (pred < 0).any(-1)
        new = neg & (Wv == 0)
        if not bool(new.any()):
            break
        Wv = torch.where(neg, gamma * scale.expand_as(Wv), Wv)
        extra = (Pall * Wv.unsqueeze(-1)).transpose(1, 2) @ Pall
        # minimise |sqrt(w)(y - Phi a)|^2 + |sqrt(ridge)(a - a0)|^2 + |sqrt(Wv) Pall a|^2
        a = a0 + ch.solve(Phi, ch.w, ch.ridge_diag, ch.y - Phi @ a0, extra=extra, rhs_extra=-(extra @ a0))
    return a


# ---------------------------------------------------------------------------
# Shared-material model (default): a_pc = sum_m W_pcm B_m
# ---------------------------------------------------------------------------
# Iteration budgets of the shared model (fixed, not set per dataset; see
# docs/photometric_stereo.md for how much the results depend on them).
_INDEPENDENT_START_ITERS = 8  # LM iterations of the independent-model start on the subset
_CAL_IRLS = 5  # IRLS passes (+1) per calibration round
_CAL_LM_ITERS = 4  # LM iterations of the subset normals per calibration round
_PIXEL_IRLS = 2  # reweighting passes per iteration of the per-pixel pass
_SCALE_ROUNDS = 3  # calibration rounds that re-estimate the robust scale; later rounds keep it (MM-style)
_BASIS_RIDGE = 1e-3  # relative ridge (times the order profile) on the basis BRDFs


def _initial_mixing(albedo: torch.Tensor, M: int, seed: int) -> torch.Tensor:
    """Start mixing weights ``(p, C, M)``: per-channel albedo, its grey level, then seeded positive perturbations."""
    cols = [albedo]
    if M >= 2:
        cols.append(albedo.mean(-1, keepdim=True).expand_as(albedo))
    g = torch.Generator().manual_seed(int(seed))
    for _ in range(2, M):
        f = 0.5 + torch.rand(albedo.shape[0], 1, generator=g, dtype=torch.float64).to(albedo)
        cols.append(albedo * f)
    return torch.stack(cols, dim=-1)


def _fit_basis_brdfs(Phi, w, y, W, order, ridge_rel):
    """Shared basis BRDFs ``B (M, K)`` (unit rows) by weighted ridge LS over all pixels and channels."""
    M, K = W.shape[-1], Phi.shape[-1]
    Pw = Phi * w.unsqueeze(-1)
    G = Pw.transpose(1, 2) @ Phi
    A = torch.einsum("pcm,pcn,pkl->mknl", W, W, G).reshape(M * K, M * K)
    r = torch.einsum("pcm,pkc->mk", W, Pw.transpose(1, 2) @ y).reshape(-1)
    # the (M K, M K) system is tiny: solve it in float64 whatever the work dtype
    A, r = A.double(), r.double()
    prof = _ridge_profile(order, torch.float64, y.device).repeat(M)
    tr = A.diagonal().mean().clamp(min=1e-300)
    A = A + torch.diag(ridge_rel * tr * prof) + 1e-12 * tr * torch.eye(M * K, dtype=A.dtype, device=A.device)
    B = torch.linalg.solve(A, r).reshape(M, K).to(y.dtype)
    nb = B.norm(dim=-1, keepdim=True)
    return B / torch.where(nb > 0, nb, torch.ones_like(nb))


def _calibrate(y, w0, n, lights, order, W, rounds, irls, lm_iter, c, basis_ridge=_BASIS_RIDGE, weight_ridge=1e-4):
    """Alternate (basis BRDFs, mixing weights, robust weights) and the normals on a pixel subset.

    Every round: ``irls + 1`` Cauchy-IRLS passes of (fit ``B`` over all
    pixels and channels, closed-form mixing weights, robust weights) at fixed
    normals, then ``lm_iter`` variable-projection LM iterations of the normals
    at fixed ``B`` and weights. Returns ``B (M, K)``, the robust residual scale
    and the subset normals.
    """
    w = w0.clone()
    scale = None
    B = None
    yT = y.transpose(1, 2).contiguous()  # (p, C, L): the layout of the mixed design
    for rnd in range(rounds):
        X, T = _design_factors(n, lights, order)
        Phi = X @ T
        for _ in range(irls + 1):
            B = _fit_basis_brdfs(Phi, w, y, W, order, basis_ridge)
            Psi = (Phi @ B.T).transpose(1, 2).contiguous()  # (p, M, L)
            rd = _ridge_diag(Psi, w0, weight_ridge)
            Wt, _, _ = solve_weights(Psi, w, yT, rd)  # (p, M, C)
            W = Wt.transpose(1, 2)
            res = observation_residual(Psi, Wt, yT)
            if rnd < _SCALE_ROUNDS:
                live = res[w0 > 0]
                scale = max(float(1.4826 * live.median()) if live.numel() else 1.0, 1e-12)
            w = cauchy_weights(res, w0, scale, c)
        n, _ = lm_normals(MixedDesign(B, lights, order), yT, w, rd, n, lm_iter, fd_step(y.dtype))
    return B, scale, n


def _independent_chunk(y, w0, n, lights, view, order, profile, ridge, robust, robust_iters, search_angles,
                       search_azimuths, max_iter, sigma_y):
    """Independent per-pixel model on one batch: returns normals, the :class:`_Chunk` and LM iterations."""
    ch = _Chunk(y, w0, lights, view, order, profile, ridge)
    n = n.clone()
    ch.set_ridge_scale(n)
    iters = 0
    floor = None
    if robust:
        yscale = ch.y.mean(-1).abs().amax(-1)
        floor = torch.maximum(torch.full_like(yscale, 3 * sigma_y), 1e-3 * yscale).clamp(min=1e-12)
        # IRLS on the coefficients at the start normal: observations the basis
        # cannot explain (sharp highlights, interreflections) lose their weight
        # before the normal moves
        for _ in range(robust_iters + 1):
            ch.set_weights(_robust_weights(ch, n, w0, floor))
    n = _cone_search(n, ch.cost, search_angles, search_azimuths)  # coarse search over a cone of candidates
    n, _, k = _lm(ch, n, max_iter)
    iters += k
    if robust:
        for _ in range(robust_iters):
            ch.set_weights(_robust_weights(ch, n, w0, floor))
            n, _, k = _lm(ch, n, max_iter)
            iters += k
    return n, ch, iters


def _refine_normals_mixed(B, y, w0, n, lights, order, scale, c, iters, irls, search_angles, search_azimuths, work_dtype,
                          step_tol: float = 2e-4):
    """Per-pixel IRLS + Levenberg–Marquardt on the normals with the basis BRDFs fixed.

    Every iteration: ``irls`` Cauchy reweighting steps (mixing weights in
    closed form at the current normal), then one LM step of the normal. A
    pixel stops once its normal moves less than ``step_tol`` radians (after at
    least three iterations), so results do not depend on the chunking.

    Returns normals, robust weights, mixing weights ``(p, M, C)`` (in ``y``'s dtype) and the iterations used.
    """
    out_dt = y.dtype
    des = MixedDesign(B.to(work_dtype), lights.to(work_dtype), order)
    yd, w0d, nd = y.to(work_dtype).transpose(1, 2).contiguous(), w0.to(work_dtype), n.to(work_dtype)  # yd (p, C, L)
    h = fd_step(work_dtype)
    Psi = des(nd)
    w = w0d.clone()

    active = torch.ones(nd.shape[0], dtype=torch.bool, device=nd.device)
    used = 0
    for it in range(iters):
        idx = active.nonzero().squeeze(1)
        if idx.numel() == 0:
            break
        used += 1
        yi, ni, Pi = yd[idx], nd[idx], Psi[idx]
        wi, _ = irls_weights(Pi, yi, w[idx], w0d[idx], scale, c, irls)
        rd = _ridge_diag(Pi, wi, 1e-4)
        if it == 0:
            ni = _cone_search(
                ni, lambda m: reduced_cost(des(m), wi, yi, rd)[0], search_angles, search_azimuths,
                base_cost=reduced_cost(Pi, wi, yi, rd)[0],
            )
        n_new, _ = lm_normals(des, yi, wi, rd, ni, 1, h)
        step = (n_new - nd[idx]).norm(dim=-1)
        nd[idx] = n_new
        Psi[idx] = des(n_new)
        w[idx] = wi
        if it >= 2:
            active[idx[step < step_tol]] = False
    w, _ = irls_weights(Psi, yd, w, w0d, scale, c, irls)
    rd = _ridge_diag(Psi, w, 1e-4)
    Wt, _, _ = solve_weights(Psi, w, yd, rd)
    return nd.to(out_dt), w.to(out_dt), Wt.to(out_dt), used


def _calibrate_shared(y, lights, w0, n_start, order, M, profile, ridge, sigma_y, n_pixels, rounds, starts, seed,
                      work_dtype, c, progress, info):
    """Calibrate the shared basis BRDFs on a seeded random subset of ``n_pixels`` pixels.

    The alternation (:func:`_calibrate`) keeps the basin it starts in, so it
    runs from the robust Lambertian normals and, if ``"independent"`` is in
    ``starts``, from the independent-model normals on the subset (exact
    azimuth, biased elevation). The winner has the smallest Cauchy loss of the
    subset residuals at a common scale (the smaller of the scales): the scale
    alone would reward a basis bent to biased normals. Writes
    ``calibration_start`` / ``calibration_losses`` into ``info``.

    Returns ``B (M, K)``, the robust scale, the subset indices and their normals.
    """
    dt, dev = y.dtype, y.device
    usable = (w0.sum(-1) >= 3).nonzero().squeeze(1)
    if usable.numel() == 0:
        usable = torch.arange(y.shape[0], device=dev)
    g = torch.Generator().manual_seed(int(seed))
    S = usable[torch.randperm(usable.numel(), generator=g)[:n_pixels].to(dev)]
    yS, w0S = y[S], w0[S]
    _, alb = _solve_flat(yS, lights, trimmed_weights(yS, 0.25, 0.10))
    W0 = _initial_mixing(alb, M, seed)
    starts_S = [n_start[S]]
    if "independent" in starts:
        view = torch.tensor([0.0, 0.0, 1.0], dtype=work_dtype, device=dev)
        n_ind, _, _ = _independent_chunk(
            yS.to(work_dtype), w0S.to(work_dtype), n_start[S].to(work_dtype), lights.to(work_dtype), view, order,
            profile.to(work_dtype), ridge, True, 1, (), 0, _INDEPENDENT_START_ITERS, sigma_y,
        )
        starts_S.append(torch.nn.functional.normalize(n_ind.to(dt), dim=-1))
    it_starts = list(enumerate(starts_S))
    if progress:
        from tqdm.auto import tqdm

        it_starts = tqdm(it_starts, desc="HSH calibration (basis BRDFs)", unit="start")
    cands = []
    for k_s, nS0 in it_starts:
        # in the work dtype (the (M K, M K) basis solve is always float64)
        B_k, scale_k, n_k = _calibrate(
            yS.to(work_dtype), w0S.to(work_dtype), nS0.to(work_dtype), lights.to(work_dtype), order,
            W0.to(work_dtype), rounds, _CAL_IRLS, _CAL_LM_ITERS, c,
        )
        cands.append((B_k.to(dt), scale_k, k_s, n_k.to(dt)))
    sig = min(t[1] for t in cands)
    yT = yS.transpose(1, 2)
    losses = []
    for B_k, _, _, n_k in cands:
        X, T = _design_factors(n_k, lights, order)
        Psi = (X @ (T @ B_k.T)).transpose(1, 2)
        _, res = irls_weights(Psi, yT, w0S.clone(), w0S, sig, c, 3)
        losses.append(float((w0S * torch.log1p((res / (c * sig)) ** 2)).sum()))
    i_best = min(range(len(cands)), key=lambda i: losses[i])
    B, scale, chosen, n_cal = cands[i_best]
    info["calibration_losses"] = losses
    info["calibration_start"] = float(chosen)
    return B, scale, S, torch.nn.functional.normalize(n_cal, dim=-1)


# ---------------------------------------------------------------------------
# Public solver
# ---------------------------------------------------------------------------
def solve_hsh(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    order: int = DEFAULT_ORDER,
    materials: Optional[int] = DEFAULT_MATERIALS,
    init: Optional[torch.Tensor] = None,
    ridge: float = 0.1,
    search_angles: Sequence[float] = (8.0, 16.0),
    search_azimuths: int = 6,
    max_iter: Optional[int] = None,
    robust: bool = True,
    robust_iters: int = 2,
    calibration_pixels: int = 2048,
    calibration_rounds: int = 8,
    calibration_starts: Sequence[str] = ("lambertian", "independent"),
    dark_fraction: float = 0.05,
    noise_sigma: Optional[float] = None,
    saturation: Optional[float] = None,
    nonneg: bool = True,
    chunk_size: int = 8192,
    dtype: Optional[torch.dtype] = torch.float64,
    work_dtype: Optional[torch.dtype] = torch.float32,
    seed: int = 0,
    progress: bool = False,
) -> HSHResult:
    r"""Photometric stereo with isotropic Helmholtz HSH BRDFs.

    Two models (see ``docs/photometric_stereo.md``):

    * ``materials=M`` (default ``M = 2``): **shared basis BRDFs**. The
      coefficients of pixel ``p``, channel ``c`` are
      :math:`a_{pc} = \sum_m W_{pcm} B_m + \delta_{pc}`: ``M`` basis BRDFs
      ``B (M, K)`` shared by the whole object (Goldman et al. 2005; Alldrin
      et al. 2008) with free per-pixel RGB mixing weights ``W``, plus a small
      per-pixel residual ``delta`` (ridge-shrunk toward 0, fitted once the
      normal is fixed). Sharing is what makes the normal's elevation
      identifiable: with one viewpoint a BRDF free at every pixel only fixes
      the normal's azimuth (Alldrin & Kriegman 2007). Steps: robust Lambertian
      start; on a random subset of ``calibration_pixels`` pixels, alternate
      Cauchy-IRLS fits of ``(B, W)`` with Levenberg–Marquardt on the normals
      (``calibration_rounds`` rounds); then, with ``B`` fixed, every pixel
      runs IRLS + variable-projection LM on its normal (the mixing weights
      are linear, solved in closed form), with a coarse cone search at the
      first iteration. The robust scale is estimated from the data.
    * ``materials=None``: an **independent** BRDF per pixel (``K``
      coefficients per channel, ridge growing with order), VP-LM from the
      robust Lambertian start. Fits the data as closely, but the elevation of
      the normal is then set by the ridge, not by the data.

    Args:
        images: ``(L, H, W, C)`` or ``(L, P, C)`` linear images (trailing channel axis).
        lights: ``(L, 3)`` directions toward the lights (DiLiGenT frame).
        intensities: ``None``, ``(L,)`` or ``(L, C)`` light intensities (images are divided by them).
        mask: ``(H, W)`` / ``(P,)`` bool object mask (default: every pixel).
        order: basis order ``P`` (default 3: ``K = 20`` coefficients per channel).
        materials: number ``M`` of shared basis BRDFs (1..8), or ``None`` for
            independent per-pixel BRDFs.
        init: optional ``(*S, 3)`` starting normals (default: robust Lambertian).
        ridge: relative ridge strength ``lambda`` on the per-pixel coefficients
            (independent model) or on the per-pixel residual ``delta``
            (shared model); see the module docstring.
        search_angles: cone angles in degrees of the coarse candidate search
            (empty: no search).
        search_azimuths: candidates per cone angle.
        max_iter: Levenberg–Marquardt iterations per stage (independent model,
            default 15) or IRLS-LM iterations of the per-pixel pass (shared
            model, default 8; a pixel stops earlier once its normal is still).
        robust: independent model only: run Cauchy IRLS stages (``robust_iters`` of them).
        robust_iters: independent model only: number of reweighting stages.
        calibration_pixels: shared model: size of the pixel subset used to fit ``B``.
        calibration_rounds: shared model: alternation rounds on that subset.
        calibration_starts: shared model: starts of the calibration, any of
            ``"lambertian"`` (robust Lambertian normals, always used) and
            ``"independent"`` (normals of the independent model on the subset);
            the calibration with the smallest Cauchy loss of the subset
            residuals at a common scale is kept.
        dark_fraction, noise_sigma, saturation: thresholds, see :func:`observation_weights`.
        nonneg: apply the non-negativity safeguard to the final coefficients.
        chunk_size: pixels per batch of the per-pixel passes (bounded memory).
        dtype: dtype of the outputs and of the coefficient fits (default
            float64; ``None``: the images' dtype).
        work_dtype: shared model: dtype of the per-pixel normal iterations
            (default float32, about 3x faster than float64 with the same
            accuracy; ``None``: ``dtype``).
        seed: seed of the calibration subset.
        progress: show tqdm progress bars (calibration starts, then chunks of pixels).

    Returns:
        :class:`HSHResult` (normals, coefficient maps, directional albedo,
        and for the shared model the basis BRDFs and mixing weights), in
        ``dtype`` on the images' device.

    Raises:
        ValueError: shape mismatches, fewer than 3 lights, empty mask, bad
            order or number of materials.

    Example:
        >>> res = solve_hsh(images, lights, mask=mask, order=3)  # doctest: +SKIP
        >>> res.normals.shape, res.coefficients.shape  # doctest: +SKIP
        (torch.Size([64, 64, 3]), torch.Size([64, 64, 3, 20]))
    """
    t_start = time.perf_counter()
    order = check_order(order)
    if materials is not None:
        if isinstance(materials, bool) or int(materials) != materials or not 1 <= int(materials) <= 8:
            raise ValueError(f"`materials` must be an integer in [1, 8] or None (independent BRDFs), got {materials!r}")
        materials = int(materials)
    if not ridge > 0:
        raise ValueError(f"`ridge` must be > 0 (it keeps the rank-deficient normal equations solvable), got {ridge}")
    if int(chunk_size) < 1:
        raise ValueError(f"`chunk_size` must be >= 1, got {chunk_size}")
    if max_iter is None:
        max_iter = 15 if materials is None else 8
    if isinstance(max_iter, bool) or int(max_iter) != max_iter or max_iter < 0:
        raise ValueError(f"`max_iter` must be an integer >= 0, got {max_iter!r}")
    max_iter = int(max_iter)
    bad = [s_ for s_ in calibration_starts if s_ not in ("lambertian", "independent")]
    if isinstance(calibration_starts, str) or bad:
        raise ValueError(
            f"`calibration_starts` must be a sequence of 'lambertian' / 'independent', got {calibration_starts!r}"
        )
    if work_dtype is not None and work_dtype not in (torch.float32, torch.float64):
        raise ValueError(f"`work_dtype` must be torch.float32, torch.float64 or None, got {work_dtype!r}")
    if int(calibration_pixels) < 1 or int(calibration_rounds) < 0:
        raise ValueError(
            f"`calibration_pixels` must be >= 1 and `calibration_rounds` >= 0, got {calibration_pixels}, {calibration_rounds}"
        )
    d = prepare_inputs(images, lights, intensities, mask, min_lights=3, dtype=dtype)
    P, L, C = d.y.shape
    K = num_isotropic(order)
    dev, dt = d.y.device, d.y.dtype
    wdt = dt if work_dtype is None else work_dtype
    w0, info = observation_weights(d.y, d.raw, d.background, dark_fraction, noise_sigma, saturation)
    info["underdetermined_pixels"] = int((w0.sum(-1) < 3).sum())
    # start
    if init is None:
        n_start, _ = _solve_flat(d.y, d.lights, trimmed_weights(d.y, 0.25, 0.10))
    else:
        if not isinstance(init, torch.Tensor) or tuple(init.shape) != (*d.pixel_shape, 3):
            raise ValueError(f"`init` must be a tensor of shape {(*d.pixel_shape, 3)}, got {getattr(init, 'shape', init)!r}")
        n_start = torch.nn.functional.normalize(init.to(device=dev, dtype=dt).reshape(-1, 3)[d.mask.reshape(-1)], dim=-1)
    # keep the start in front of the camera
    nz = n_start[:, 2].clamp(min=0.05)
    n_start = torch.nn.functional.normalize(torch.cat([n_start[:, :2], nz.unsqueeze(-1)], -1), dim=-1)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=dt, device=dev)
    profile = _ridge_profile(order, dt, dev)
    sigma_y = info["noise_sigma"] / d.intensities.mean().item()

    normals = torch.empty(P, 3, dtype=dt, device=dev)
    coefs = torch.empty(P, C, K, dtype=dt, device=dev)
    resid = torch.empty(P, dtype=dt, device=dev)
    wfin = torch.empty(P, L, dtype=dt, device=dev)
    B = None
    mixing = None
    c_cauchy = 2.385
    if materials is not None:
        # --- calibration of the shared basis BRDFs on a random pixel subset
        with torch.no_grad():
            B, scale, S, n_cal = _calibrate_shared(
                d.y, d.lights, w0, n_start, order, materials, profile, ridge, sigma_y, int(calibration_pixels),
                int(calibration_rounds), calibration_starts, seed, wdt, c_cauchy, progress, info,
            )
            # the calibrated subset normals are the best start the per-pixel pass has for them
            n_start = n_start.clone()
            n_start[S] = n_cal
            # floor: the noise level, and 1e-4 of the typical brightness (quantisation,
            # float32 rounding) so that noise-free data do not get a zero scale
            yv = d.y.mean(-1)[w0 > 0]
            typical = float(yv.abs().median()) if yv.numel() else 1.0
            scale = max(scale, 3.0 * sigma_y, 1e-4 * typical, 1e-12)
        info["materials"] = float(materials)
        info["robust_scale"] = scale
        info["calibration_pixels"] = float(S.numel())
        mixing = torch.empty(P, C, materials, dtype=dt, device=dev)
    starts = list(range(0, P, int(chunk_size)))
    it = starts
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(starts, desc="HSH photometric stereo", unit="chunk")
    total_iters = 0
    moved = 0
    with torch.no_grad():
        for s in it:
            sl = slice(s, min(P, s + int(chunk_size)))
            if materials is not None:
                n, w, Wt, k = _refine_normals_mixed(
                    B, d.y[sl], w0[sl], n_start[sl], d.lights, order, scale, c_cauchy, max_iter, _PIXEL_IRLS,
                    search_angles, search_azimuths, wdt,
                )
                total_iters += k
                n = torch.nn.functional.normalize(n, dim=-1)
                w_out = w
                # the robust weights served the normals; the coefficients fit every valid
                # observation (shrunk toward the shared mix), which relights best
                ch = _Chunk(d.y[sl], w0[sl], d.lights, view, order, profile, ridge)
                Phi = ch.design(n)
                ch.set_ridge_scale(n, Phi)
                a = _final_coefficients(ch, n, nonneg, prior=B.T.unsqueeze(0) @ Wt, Phi=Phi)
                mixing[sl] = Wt.transpose(1, 2)
            else:
                n, ch, k = _independent_chunk(
                    d.y[sl], w0[sl], n_start[sl], d.lights, view, order, profile, ridge, robust, robust_iters,
                    search_angles, search_azimuths, max_iter, sigma_y,
                )
                total_iters += k
                w_out = ch.w
                Phi = ch.design(n)
                a = _final_coefficients(ch, n, nonneg, Phi=Phi)
            moved += int(((n_start[sl] - n).norm(dim=-1) > 1e-6).sum())
            r = (ch.y - Phi @ a) * ch.sw.unsqueeze(-1)
            resid[sl] = ((r * r).sum((-1, -2)) / (ch.w.sum(-1).clamp(min=1e-12) * C)).sqrt()
            normals[sl] = n
            coefs[sl] = a.transpose(1, 2)
            wfin[sl] = w_out
    albedo = directional_albedo_view(coefs, normals[:, 2])
    info["lm_iterations"] = float(total_iters)
    info["chunks"] = float(len(starts))
    info["moved_pixels"] = float(moved)
    return HSHResult(
        normals=scatter_pixels(normals, d.mask),
        coefficients=scatter_pixels(coefs, d.mask),
        albedo=scatter_pixels(albedo, d.mask),
        residual=scatter_pixels(resid, d.mask),
        weights=scatter_pixels(wfin, d.mask),
        mask=d.mask,
        order=order,
        lights=d.lights,
        runtime_s=time.perf_counter() - t_start,
        info=info,
        basis_brdfs=B,
        mixing=None if mixing is None else scatter_pixels(mixing, d.mask),
    )


def holdout_evaluation(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    holdout: int = 10,
    seed: int = 0,
    test_indices: Optional[Sequence[int]] = None,
    **solver_kwargs,
) -> HoldoutResult:
    """Fit on a subset of the lights and report the relighting error on the rest.

    Args:
        images, lights, intensities, mask: as in :func:`solve_hsh`.
        holdout: number of lights held out (chosen by a seeded permutation).
        seed: permutation seed.
        test_indices: explicit held-out light indices (overrides ``holdout``).
        **solver_kwargs: passed to :func:`solve_hsh` (e.g. ``order``).

    Returns:
        :class:`HoldoutResult`. Errors are computed over held-out observations
        inside the mask that are finite and below the detected saturation level.

    Raises:
        ValueError: if fewer than 3 lights would remain for fitting.

    Example:
        >>> ho = holdout_evaluation(images, lights, mask=mask, holdout=5)  # doctest: +SKIP
        >>> ho.relative_rmse < ho.lambertian_relative_rmse  # doctest: +SKIP
        True
    """
    from ._common import prepare_inputs as _prep

    d = _prep(images, lights, intensities, mask, min_lights=4)
    L = d.y.shape[1]
    if test_indices is None:
        if isinstance(holdout, bool) or int(holdout) != holdout or holdout < 1:
            raise ValueError(f"`holdout` must be a positive integer, got {holdout!r}")
        if L - int(holdout) < 3:
            raise ValueError(f"`holdout`={holdout} leaves {L - int(holdout)} lights for fitting; at least 3 are needed")
        g = torch.Generator().manual_seed(int(seed))
        perm = torch.randperm(L, generator=g)
        test = perm[: int(holdout)].sort().values
    else:
        test = torch.as_tensor(list(test_indices), dtype=torch.long).unique()
        if test.numel() < 1 or int(test.min()) < 0 or int(test.max()) >= L:
            raise ValueError(f"`test_indices` must be distinct light indices in [0, {L}), got {list(test_indices)}")
        if L - test.numel() < 3:
            raise ValueError(f"holding out {test.numel()} lights leaves fewer than 3 for fitting")
    keep = torch.ones(L, dtype=torch.bool)
    keep[test] = False
    train = keep.nonzero().squeeze(1)
    dev = images.device
    e_all = None if intensities is None else intensities.to(dev)
    e_tr = None if e_all is None else e_all[train.to(dev)]
    e_te = None if e_all is None else e_all[test.to(dev)]
    res = solve_hsh(images[train.to(dev)], lights[train.to(dev)], e_tr, mask, **solver_kwargs)
    pred = res.relight(lights[test.to(dev)].to(res.normals.dtype), None if e_te is None else e_te.to(res.normals.dtype))
    obs = images[test.to(dev)].to(pred.dtype)
    m = d.mask.unsqueeze(0).expand(obs.shape[:-1]).unsqueeze(-1).expand_as(obs)
    valid = m & torch.isfinite(obs)
    if "saturation_level" in res.info:
        valid = valid & (obs < 0.99 * res.info["saturation_level"])
    diff = torch.where(valid, pred - obs, torch.zeros_like(obs))
    ref = torch.where(valid, obs, torch.zeros_like(obs))
    nval = valid.sum().clamp(min=1)
    rmse = float(((diff * diff).sum() / nval).sqrt())
    rel = float((diff * diff).sum().sqrt() / (ref * ref).sum().sqrt().clamp(min=1e-30))
    # robust Lambertian baseline on the same split
    from .lambertian import robust_lambertian

    lam = robust_lambertian(images[train.to(dev)], lights[train.to(dev)], e_tr, mask)
    lt = torch.nn.functional.normalize(lights[test.to(dev)].to(pred.dtype), dim=-1)
    shade = torch.einsum("...a,la->l...", lam.normals.to(pred.dtype), lt).clamp(min=0.0)
    lpred = lam.albedo.to(pred.dtype).unsqueeze(0) / math.pi * shade.unsqueeze(-1)
    if e_te is not None:
        ee = e_te.to(pred.dtype)
        ee = ee.unsqueeze(-1) if ee.dim() == 1 else ee
        lpred = lpred * ee.reshape(ee.shape[0], *([1] * (lpred.dim() - 2)), ee.shape[-1])
    ldiff = torch.where(valid, lpred - obs, torch.zeros_like(obs))
    lrel = float((ldiff * ldiff).sum().sqrt() / (ref * ref).sum().sqrt().clamp(min=1e-30))
    return HoldoutResult(train, test, rel, rmse, lrel, pred, res)
