"""Numerical kernels shared by the stages of the HSH solver.

* Mixing weights of the shared model: :func:`solve_weights` (weighted ridge
  least squares, closed form for ``M <= 2``), :func:`combine`,
  :func:`reduced_cost` (variable projection: the weights are eliminated).
* Robust reweighting: :func:`cauchy_weights`, :func:`irls_weights`,
  :func:`observation_residual`.
* Normals: :func:`lm_normals` (shared model) and :func:`lm_independent`
  (independent model, on a :class:`PixelProblem`): Levenberg–Marquardt on
  the reduced cost in the tangent parametrisation ``n(u) = normalize(n0 + u1
  t1 + u2 t2)``, re-centred after every accepted step, Golub–Pereyra
  Jacobians from forward differences of the design. Plus the coarse
  :func:`cone_search`.

Everything is batched over pixels; one host synchronisation per LM iteration
(the active set, compacted with ``nonzero``). Accepted steps and finished
pixels are written by selection (``torch.where``), never by boolean indexing,
and no small solve checks its status on the host (``cholesky_ex`` /
``solve_ex``), so on CUDA the iterations queue without further stalls.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch

from ._geometry import tangent_frame
from .design import MixedDesign, _design_factors

__all__ = [
    "small_solve", "safe_cholesky", "combine", "solve_weights", "fd_step", "cauchy_weights", "cauchy_rho",
    "observation_residual", "irls_weights", "reduced_cost", "lm_normals", "active_rows", "lm_accept",
    "PixelProblem", "lm_independent", "cone_search", "robust_coefficient_weights",
]


def small_solve(G: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Batched SPD solve ``G x = rhs`` for tiny ``G (p, M, M)`` (closed form for M <= 2)."""
    M = G.shape[-1]
    if M == 1:
        return rhs / G[:, :1, :1]
    if M == 2:  # adjugate over determinant, both rows at once (few kernels: GPUs are launch-bound here)
        a, b, d = G[:, 0, 0], G[:, 0, 1], G[:, 1, 1]
        det = a * d - b * b
        det = torch.where(det.abs() > 0, det, torch.finfo(G.dtype).tiny)
        nb = -b
        adj = torch.stack([d, nb, nb, a], dim=-1).reshape(-1, 2, 2, 1)  # adj[:, i, j] = adj(G)_ij
        return (adj[:, :, 0] * rhs[:, :1, :] + adj[:, :, 1] * rhs[:, 1:, :]) / det[:, None, None]
    return torch.cholesky_solve(rhs, safe_cholesky(G))


def safe_cholesky(G: torch.Tensor) -> torch.Tensor:
    """Batched Cholesky factor of ``G (p, K, K)``; a matrix that is not numerically SPD gets a tiny diagonal jitter.

    Only the failing matrices are jittered, so a pixel's factor does not depend
    on the other pixels of its batch. The jittered factor is computed only when
    some matrix fails, which costs one host synchronisation per call: on CUDA
    that is cheaper than always computing it (measured on an H200: the solver's
    small kernels are bound by launches, and the check adds one sync, the
    fallback eight launches).
    """
    Lc, info = torch.linalg.cholesky_ex(G)
    bad = info > 0
    if not bool(bad.any()):
        return Lc
    jitter = 1e-8 * G.diagonal(dim1=-2, dim2=-1).mean(-1).clamp(min=1e-30)
    eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
    Lj, _ = torch.linalg.cholesky_ex(G + jitter[:, None, None] * eye)
    return torch.where(bad[:, None, None], Lj, Lc)


def combine(W: torch.Tensor, Psi: torch.Tensor) -> torch.Tensor:
    """``sum_m W[..., m, c] Psi[..., m, l]``: ``W (..., M, C)``, ``Psi (..., M, L)`` -> ``(..., C, L)``."""
    M = W.shape[-2]
    if M <= 3:
        out = W[..., 0, :, None] * Psi[..., 0, None, :]
        for m in range(1, M):
            out = out + W[..., m, :, None] * Psi[..., m, None, :]
        return out
    return W.transpose(-1, -2) @ Psi


def _ridge_diag(Psi: torch.Tensor, w: torch.Tensor, rel: float) -> torch.Tensor:
    """Tiny per-pixel ridge ``rel * mean diag(Psi W Psi^T)`` on the mixing weights, ``(p, M)``."""
    d = (Psi * Psi * w.unsqueeze(1)).sum(-1).mean(-1, keepdim=True)
    d = torch.where(d > 0, d, torch.ones_like(d))
    return (rel * d).expand(-1, Psi.shape[1])


def solve_weights(Psi: torch.Tensor, w: torch.Tensor, y: torch.Tensor, rd: torch.Tensor):
    """Mixing weights ``W (p, M, C)`` of the weighted ridge LS problem, and ``Pw``, ``G``.

    ``Psi (p, M, L)``, ``w (p, L)``, ``y (p, C, L)``, ``rd (p, M)``.
    """
    Pw = Psi * w.unsqueeze(1)
    G = Pw @ Psi.transpose(1, 2) + torch.diag_embed(rd)
    return small_solve(G, Pw @ y.transpose(1, 2)), Pw, G


def fd_step(dtype: torch.dtype) -> float:
    """Forward-difference step of the design derivatives (relative error ~h in float64, rounding-limited in float32)."""
    return 1e-6 if dtype == torch.float64 else 3e-3


def cauchy_weights(res: torch.Tensor, w0: torch.Tensor, scale: float, c: float) -> torch.Tensor:
    """Cauchy IRLS weights ``w0 / (1 + (res / (c scale))^2)``."""
    return w0 / (1.0 + (res / (c * scale)) ** 2)


def cauchy_rho(res: torch.Tensor, scale: float, c: float) -> torch.Tensor:
    """Cauchy loss ``log(1 + (res / (c scale))^2)`` of every residual: the robust loss whose IRLS weights
    :func:`cauchy_weights` gives, by which the solver compares fits (calibration starts, materials, held-out lights)."""
    return torch.log1p((res / (c * scale)) ** 2)


def observation_residual(Psi: torch.Tensor, W: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """RMS over the channels of ``y - W^T Psi``, ``(p, L)``."""
    return (y - combine(W, Psi)).pow(2).mean(1).sqrt()


def irls_weights(Psi, y, w, w0, scale: float, c: float, passes: int, ridge_rel: float = 1e-4):
    """``passes`` Cauchy reweighting steps at a fixed design: closed-form mixing weights, residuals, new weights.

    Returns the weights and the residuals of the last pass (``None`` for ``passes = 0``).
    """
    res = None
    for _ in range(passes):
        W, _, _ = solve_weights(Psi, w, y, _ridge_diag(Psi, w, ridge_rel))
        res = observation_residual(Psi, W, y)
        w = cauchy_weights(res, w0, scale, c)
    return w, res


def reduced_cost(Psi, w, y, rd):
    W, _, _ = solve_weights(Psi, w, y, rd)
    e = y - combine(W, Psi)
    return (w.unsqueeze(1) * e * e).sum((-1, -2)) + (rd.unsqueeze(-1) * W * W).sum((-1, -2)), W


def lm_normals(design: MixedDesign, y, w, rd, n, iters: int, h: float, max_step: float = 0.35, tol: float = 1e-6,
               Psi=None):
    """Levenberg–Marquardt on the variable-projection cost of the normals (tangent parametrisation).

    ``y (p, C, L)``, ``w (p, L)`` fixed weights, ``rd (p, M)`` ridge on the
    mixing weights, ``n (p, 3)`` start. The Jacobian of the reduced residual
    (Golub–Pereyra, exact given ``dPsi``) uses forward differences of the
    design along two tangents; the design at the current normals is cached, so
    one iteration costs three design evaluations. ``Psi`` is the design at ``n``
    if the caller has it. Returns the normals, the iterations used and the
    design at the returned normals.
    """
    p = n.shape[0]
    n = n.clone()
    if iters <= 0 or p == 0:
        return n, 0, (design(n) if Psi is None else Psi)
    Psi = design(n) if Psi is None else Psi.clone()
    cost, _ = reduced_cost(Psi, w, y, rd)
    mu = torch.full((p,), 1e-3, dtype=n.dtype, device=n.device)
    active = torch.ones(p, dtype=torch.bool, device=n.device)
    sw = w.sqrt()
    srd = rd.sqrt()
    used = 0
    for idx in active_rows(active, iters):
        q = idx.numel()
        used += 1
        ni, Pi, yi, wi, rdi = n[idx], Psi[idx], y[idx], w[idx], rd[idx]
        t1, t2 = tangent_frame(ni)
        D = design(torch.cat([ni + h * t1, ni + h * t2]))
        dPsi = torch.stack([(D[:q] - Pi) / h, (D[q:] - Pi) / h], dim=1)  # (q, 2, M, L)
        W, Pw, G = solve_weights(Pi, wi, yi, rdi)
        e = yi - combine(W, Pi)  # (q, C, L)
        dPa = combine(W.unsqueeze(1), dPsi)  # (q, 2, C, L)
        we = wi.unsqueeze(1) * e
        rhs = dPsi @ we.transpose(1, 2).unsqueeze(1) - Pw.unsqueeze(1) @ dPa.transpose(-1, -2)  # (q, 2, M, C)
        C = yi.shape[1]
        dW = small_solve(G, torch.cat([rhs[:, 0], rhs[:, 1]], dim=-1))
        dW = torch.stack([dW[..., :C], dW[..., C:]], dim=1)  # (q, 2, M, C)
        swi = sw[idx][:, None, None, :]
        Jd = -swi * (dPa + combine(dW, Pi.unsqueeze(1)))  # (q, 2, C, L)
        Jr = srd[idx][:, None, :, None] * dW  # (q, 2, M, C)
        r_d = swi[:, 0] * e  # (q, C, L)
        r_r = srd[idx].unsqueeze(-1) * W
        Jf = Jd.flatten(2)
        JtJ = Jf @ Jf.transpose(1, 2) + torch.einsum("qamc,qbmc->qab", Jr, Jr)
        g = (Jf @ r_d.flatten(1).unsqueeze(-1)).squeeze(-1) + torch.einsum("qamc,qmc->qa", Jr, r_r)
        dg = JtJ.diagonal(dim1=-2, dim2=-1)
        dg = dg + 1e-12 * dg.sum(-1, keepdim=True) + 1e-30
        A = JtJ + torch.diag_embed(mu[idx].unsqueeze(-1) * dg)
        delta = -small_solve(A, g.unsqueeze(-1)).squeeze(-1)
        dn = delta.norm(dim=-1, keepdim=True)
        delta = delta * (max_step / dn.clamp(min=max_step))
        nn_ = torch.nn.functional.normalize(ni + delta[:, :1] * t1 + delta[:, 1:] * t2, dim=-1)
        Pn = design(nn_)
        cn, _ = reduced_cost(Pn, wi, yi, rdi)
        acc = lm_accept(idx, n, cost, mu, active, ni, nn_, cn, dn, tol)
        Psi[idx] = torch.where(acc[:, None, None], Pn, Pi)
    return n, used, Psi


def active_rows(active: torch.Tensor, iters: int):
    """The indices of the rows (pixels) still ``active``, once per iteration, for at most ``iters`` iterations
    (the iterations stop early once no row is active; the caller updates ``active`` in place)."""
    for _ in range(iters):
        idx = active.nonzero().squeeze(1)
        if idx.numel() == 0:
            return
        yield idx


def lm_accept(idx, n, cost, mu, active, ni, n_new, c_new, dn, tol) -> torch.Tensor:
    """The Levenberg–Marquardt accept/reject step of the pixels ``idx``, in place; returns the accepted mask.

    A step that lowers the cost is kept and the damping ``mu`` divided by 3, else rejected and ``mu``
    multiplied by 4; a pixel stops (``active`` False) once an accepted step is small (below ``tol``) or
    barely lowers the cost, or a rejected one is small or ``mu`` has grown past 1e8. Masked updates by
    selection (no boolean indexing: no host synchronisation).
    """
    c0 = cost[idx]
    acc = c_new < c0
    rel = (c0 - c_new) / c0.clamp(min=1e-300)
    n[idx] = torch.where(acc.unsqueeze(-1), n_new, ni)
    cost[idx] = torch.where(acc, c_new, c0)
    mu_i = torch.where(acc, mu[idx] / 3.0, mu[idx] * 4.0).clamp(1e-9, 1e9)
    mu[idx] = mu_i
    small = dn.squeeze(-1) < tol
    done = (acc & (small | (rel < 1e-10))) | (~acc & ((mu_i >= 1e8) | small))
    active[idx] = ~done
    return acc


class PixelProblem:
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
        return torch.cholesky_solve(rhs, safe_cholesky(G))  # (p, K, C)

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
        Lc = safe_cholesky(G)
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


def lm_independent(ch: PixelProblem, n: torch.Tensor, max_iter: int, tol: float = 1e-5, max_step: float = 0.35):
    """Per-pixel Levenberg–Marquardt on the reduced problem; returns normals, costs, iterations used."""
    p = n.shape[0]
    n = n.clone()
    all_idx = torch.arange(p, device=n.device)
    cost = ch.cost(n, all_idx)
    mu = torch.full((p,), 1e-3, dtype=n.dtype, device=n.device)
    active = torch.ones(p, dtype=torch.bool, device=n.device)
    iters = 0
    for idx in active_rows(active, max_iter):
        iters += 1
        ni = n[idx]
        JtJ, g, t1, t2 = ch.jacobian(ni, idx)
        D = JtJ.diagonal(dim1=-2, dim2=-1)
        D = D + 1e-12 * D.sum(-1, keepdim=True) + 1e-30
        A = JtJ + torch.diag_embed(mu[idx].unsqueeze(-1) * D)
        delta = -torch.linalg.solve_ex(A, g.unsqueeze(-1))[0].squeeze(-1)  # A is SPD (mu > 0): no error check
        dn = delta.norm(dim=-1, keepdim=True)
        delta = delta * (max_step / dn.clamp(min=max_step))
        nn = torch.nn.functional.normalize(ni + delta[:, :1] * t1 + delta[:, 1:] * t2, dim=-1)
        cn = ch.cost(nn, idx)
        lm_accept(idx, n, cost, mu, active, ni, nn, cn, dn, tol)
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


def cone_search(n: torch.Tensor, cost, angles_deg: Sequence[float], azimuths: int, base_cost=None):
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


def robust_coefficient_weights(ch: PixelProblem, n, w0, sigma_floor, c: float = 2.385):
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
