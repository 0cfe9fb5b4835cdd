"""Shared-material machinery of the HSH photometric-stereo solver.

Per pixel ``p`` and channel ``c`` the isotropic Helmholtz coefficients are a
mix of ``M`` shared basis BRDFs ("materials", Goldman et al. 2005, Alldrin
et al. 2008): ``a_pc = sum_m W_pcm B_m``. The image of pixel ``p`` under
light ``j`` is then ``y_pjc = sum_m Psi_pjm(n_p) W_pcm`` with the *mixed
design* ``Psi = Phi @ B^T`` (``Phi`` the shading-weighted basis of
:func:`torch_hsh.ps.hsh._design_factors`).

This module evaluates ``Psi`` (stored as ``(pixels, M, lights)``) without forming ``Phi``. With the view fixed
(``v = (0, 0, 1)``) every basis function factorises into a polar polynomial in
``t = 2 (n.l) - 1`` times an azimuthal factor ``G_q`` (see ``_design_factors``),
so for every azimuthal frequency ``q``

    Psi_pjm = sum_q G_q(p, j) * E_pqm(t_pj),

where ``E_pqm`` is a polynomial of degree ``P - q`` whose coefficients depend
only on ``n.v`` and ``B`` (one small matmul per pixel). The polynomials are
evaluated by Horner's rule on ``(pixels, lights, M)`` arrays: no ``(pixels,
lights, K)`` intermediate, no trigonometry, no division by ``sin``.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import List

import numpy as np
import torch

from ..basis import _polar_consts, _polar_table_t, _safe_s, isotropic_indices, num_isotropic
from ._common import tangent_frame


@lru_cache(maxsize=None)
def _monomial_tables(order: int):
    """Monomial coefficients (in ``t = 2z - 1``) of every polar-table column, grouped by ``q``.

    Returns ``(blocks, coef)``: ``blocks[q]`` lists the polar-table columns with
    ``m = q`` ordered by degree ``n - q``; ``coef[u]`` is the coefficient
    vector (lowest degree first) of column ``u``.
    """
    diag, alpha, beta, col = _polar_consts(order)
    U = len(col)
    coef: List[np.ndarray] = [np.zeros(1)] * U
    for m in range(order + 1):
        prev2 = None
        prev = np.array([diag[m]])
        coef[col[(m, m)]] = prev
        for n in range(m, order):
            j = n + 1 - m  # block of R_{n+1}^m
            nxt = alpha[j - 1][m] * np.concatenate([[0.0], prev])
            if prev2 is not None:
                nxt = nxt - beta[j - 1][m] * np.concatenate([prev2, [0.0, 0.0]])
            coef[col[(n + 1, m)]] = nxt
            prev2, prev = prev, nxt
    blocks = [[col[(n, q)] for n in range(q, order + 1)] for q in range(order + 1)]
    return blocks, coef


@lru_cache(maxsize=None)
def _t_scatter(order: int):
    """Entries of ``T`` (``Phi = X @ T``): rows (polar column of X), cols (basis index), src (polar column of ``R(n.v)``), coef."""
    col = _polar_consts(order)[3]
    rows, cols_k, src, coef = [], [], [], []
    for k, (p, r, q) in enumerate(isotropic_indices(order).tolist()):
        c = 0.5 if p == r else 1.0 / math.sqrt(2.0)
        rows += [col[(p, q)], col[(r, q)]]
        cols_k += [k, k]
        src += [col[(r, q)], col[(p, q)]]
        coef += [c, c]
    return rows, cols_k, src, coef


def mixed_design_matrix(B: torch.Tensor, order: int) -> torch.Tensor:
    """``Q (U, D)`` with ``E = R(n.v)^T @ Q`` the Horner coefficients of the mixed design.

    ``B (M, K)`` basis BRDFs. Column layout of ``D``: for q = 0..P, degrees
    0..P-q, then the M materials (``D = U * M``).
    """
    M, K = B.shape
    if K != num_isotropic(order):
        raise ValueError(f"B has {K} columns, order {order} needs {num_isotropic(order)}")
    blocks, coef = _monomial_tables(order)
    rows, cols_k, src, cf = _t_scatter(order)
    U = len(coef)
    Bd = B.detach().to(torch.float64).cpu().numpy()
    # TB[s_src, u, m] = sum_e [src_e = s][rows_e = u] cf_e B[m, cols_e]
    TB = np.zeros((U, U, M))
    for r_, k_, s_, c_ in zip(rows, cols_k, src, cf):
        TB[s_, r_, :] += c_ * Bd[:, k_]
    # monomial conversion per q block: E[s, (q, d), m] = sum_{u in block q} coef[u][d] TB[s, u, m]
    out = []
    for q, blk in enumerate(blocks):
        deg = len(blk)
        Cq = np.zeros((len(blk), deg))
        for i, u in enumerate(blk):
            Cq[i, : len(coef[u])] = coef[u]
        out.append(np.einsum("sum,ud->sdm", TB[:, blk, :], Cq))  # (U, deg, M)
    Q = np.concatenate(out, axis=1).reshape(U, U * M)
    return torch.as_tensor(Q, dtype=B.dtype, device=B.device)


class MixedDesign:
    """Evaluate ``Psi (p, M, L)`` for normals ``(p, 3)`` (fixed lights, view ``+z``, basis ``B``).

    Layout: materials before lights, so every elementwise step runs over
    contiguous rows of ``L`` values (several times faster on CPU than a
    trailing axis of size ``M``).
    """

    def __init__(self, B: torch.Tensor, lights: torch.Tensor, order: int):
        self.order = order
        self.M = B.shape[0]
        self.lights_t = lights.T.contiguous()
        self.lz = lights[:, 2]
        self.Q = mixed_design_matrix(B, order)
        self.deg = [order + 1 - q for q in range(order + 1)]

    def __call__(self, n: torch.Tensor) -> torch.Tensor:
        P = self.order
        M = self.M
        nrm = torch.nn.functional.normalize(n, dim=-1)
        lz = self.lz
        zi = nrm @ self.lights_t  # (p, L)
        zo = nrm[:, 2]
        zi_c = zi.clamp(0.0, 1.0)
        zo_c = zo.clamp(0.0, 1.0)
        mask = torch.where((zi >= 0) & (zo >= 0).unsqueeze(-1), zi_c, torch.zeros_like(zi_c))
        E = (_polar_table_t(zo_c, P).t() @ self.Q).reshape(-1, sum(self.deg), M)  # (p, D, M)
        E = E.transpose(1, 2).contiguous()  # (p, M, D)
        t = 2.0 * zi_c - 1.0  # (p, L)
        if P >= 1:
            if torch.is_grad_enabled():
                sio = _safe_s(zi_c) * _safe_s(zo_c).unsqueeze(-1)
            else:  # same values; the derivative guard of _safe_s is not needed without autograd
                sio = torch.sqrt(zi_c / (1.0 + zi_c) * (zo_c / (1.0 + zo_c)).unsqueeze(-1))
            a1 = sio * (lz.unsqueeze(0) - zi * zo.unsqueeze(-1))
            r1 = sio * sio * (1.0 - zi_c * zi_c) * (1.0 - zo_c * zo_c).unsqueeze(-1)
        # azimuthal factors G_q (with the shading), sqrt(2) for q >= 1
        gs = [mask]
        if P >= 1:
            gs.append(a1 * mask)
            for _ in range(2, P + 1):
                gs.append(2.0 * a1 * gs[-1] - r1 * gs[-2])
        gs = [gs[0]] + [g * math.sqrt(2.0) for g in gs[1:]]
        outs = []
        for m in range(M):
            acc = None
            off = 0
            for q in range(P + 1):
                dq = self.deg[q]
                Eq = E[:, m, off : off + dq]  # (p, dq)
                off += dq
                poly = Eq[:, dq - 1 : dq].expand(-1, t.shape[1])
                for dd in range(dq - 2, -1, -1):
                    poly = torch.addcmul(Eq[:, dd : dd + 1], poly, t)
                acc = poly * gs[q] if acc is None else torch.addcmul(acc, poly, gs[q])
            outs.append(acc)
        return torch.stack(outs, dim=1)


def small_solve(G: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Batched SPD solve ``G x = rhs`` for tiny ``G (p, M, M)`` (closed form for M <= 2)."""
    M = G.shape[-1]
    if M == 1:
        return rhs / G[:, :1, :1]
    if M == 2:
        a, b, d = G[:, 0, 0], G[:, 0, 1], G[:, 1, 1]
        det = a * d - b * b
        det = torch.where(det.abs() > 0, det, torch.full_like(det, torch.finfo(G.dtype).tiny))
        r0, r1 = rhs[:, 0, :], rhs[:, 1, :]
        x0 = (d.unsqueeze(-1) * r0 - b.unsqueeze(-1) * r1) / det.unsqueeze(-1)
        x1 = (a.unsqueeze(-1) * r1 - b.unsqueeze(-1) * r0) / det.unsqueeze(-1)
        return torch.stack([x0, x1], dim=1)
    Lc, info = torch.linalg.cholesky_ex(G)
    if bool((info > 0).any()):
        jitter = 1e-8 * G.diagonal(dim1=-2, dim2=-1).mean(-1).clamp(min=1e-30)
        Lc, _ = torch.linalg.cholesky_ex(G + jitter[:, None, None] * torch.eye(M, dtype=G.dtype, device=G.device))
    return torch.cholesky_solve(rhs, Lc)


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


def lm_normals(design: MixedDesign, y, w, rd, n, iters: int, h: float, max_step: float = 0.35, tol: float = 1e-6):
    """Levenberg–Marquardt on the variable-projection cost of the normals (tangent parametrisation).

    ``y (p, C, L)``, ``w (p, L)`` fixed weights, ``rd (p, M)`` ridge on the
    mixing weights, ``n (p, 3)`` start. The Jacobian of the reduced residual
    (Golub–Pereyra, exact given ``dPsi``) uses forward differences of the
    design along two tangents; the design at the current normals is cached, so
    one iteration costs three design evaluations.
    """
    p = n.shape[0]
    n = n.clone()
    if iters <= 0 or p == 0:
        return n, 0
    Psi = design(n)
    cost, _ = reduced_cost(Psi, w, y, rd)
    mu = torch.full((p,), 1e-3, dtype=n.dtype, device=n.device)
    active = torch.ones(p, dtype=torch.bool, device=n.device)
    sw = w.sqrt()
    srd = rd.sqrt()
    used = 0
    for _ in range(iters):
        idx = active.nonzero().squeeze(1)
        q = idx.numel()
        if q == 0:
            break
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
        c0 = cost[idx]
        acc = cn < c0
        rel = (c0 - cn) / c0.clamp(min=1e-300)
        ia = idx[acc]
        n[ia] = nn_[acc]
        Psi[ia] = Pn[acc]
        cost[ia] = cn[acc]
        mu_i = torch.where(acc, mu[idx] / 3.0, mu[idx] * 4.0).clamp(1e-9, 1e9)
        mu[idx] = mu_i
        small = dn.squeeze(-1) < tol
        done = (acc & (small | (rel < 1e-10))) | (~acc & ((mu_i >= 1e8) | small))
        active[idx[done]] = False
    return n, used
