r"""The forward model of the HSH solver: design matrices for a fixed orthographic view.

Per pixel with unit normal ``n`` and lights ``l_j`` (view ``v = (0, 0, 1)``),
the shading-weighted isotropic Helmholtz design matrix is
``Phi_jk(n) = B_k(l_j, v, n) max(0, n.l_j)`` (same values as
:func:`torch_hsh.render.shading_basis`). Two evaluations:

* :func:`_design_factors`: with the view fixed, every isotropic function
  factorises as ``Phi = X @ T`` (``X (p, L, U)``: the polar table at ``n.l``
  times the azimuthal factor and the shading; ``T (p, U, K)``: the polar table
  at ``n.v``; ``U = (P+1)(P+2)/2`` is the rank of ``Phi``, the identifiable part
  of a BRDF from one viewpoint). Used by the independent model and the
  calibration.
* :class:`MixedDesign`: the *mixed design* ``Psi = Phi @ B^T`` of ``M`` shared
  basis BRDFs ``B (M, K)``, stored ``(pixels, M, lights)``, without forming
  ``Phi``. For every azimuthal frequency ``q``

      Psi_pjm = sum_q G_q(p, j) * E_pqm(t_pj),   t = 2 (n.l) - 1,

  where ``E_pqm`` is a polynomial of degree ``P - q`` whose coefficients depend
  only on ``n.v`` and ``B`` (one small matmul per pixel), evaluated by Horner's
  rule on contiguous rows of ``L`` values: no ``(pixels, lights, K)``
  intermediate, no trigonometry, no division by ``sin``.

Both are plain differentiable torch operations on any device.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import List

import numpy as np
import torch

from ..kernel import _polar_consts, _polar_table_t, _safe_s, azimuthal_factors, isotropic_indices, num_isotropic

__all__ = ["MixedDesign", "mixed_design_matrix", "ridge_profile"]


def ridge_profile(order: int, dtype, device, eps: float = 1e-6) -> torch.Tensor:
    idx = isotropic_indices(order).to(device=device, dtype=dtype)
    p, r = idx[:, 0], idx[:, 1]
    return eps + 0.5 * (p * (p + 1) + r * (r + 1))


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
        gs = azimuthal_factors(mask, a1, r1, P) if P >= 1 else [mask]
        gs = [gs[0]] + [g * math.sqrt(2.0) for g in gs[1:]]
        # Horner's rule for all M materials at once: (p, M, L) rows, one kernel per step
        t = t.unsqueeze(1)  # (p, 1, L)
        acc = None
        off = 0
        for q in range(P + 1):
            dq = self.deg[q]
            Eq = E[:, :, off : off + dq]  # (p, M, dq)
            off += dq
            poly = Eq[:, :, dq - 1 : dq].expand(-1, -1, t.shape[-1])
            for dd in range(dq - 2, -1, -1):
                poly = torch.addcmul(Eq[:, :, dd : dd + 1], poly, t)
            g = gs[q].unsqueeze(1)
            acc = poly * g if acc is None else torch.addcmul(acc, poly, g)
        assert acc is not None  # the q loop runs at least once (q = 0)
        return acc


@lru_cache(maxsize=None)
def _factor_tables(order: int):
    """Index tables of the factorisation ``Phi = X @ T`` (see :meth:`PixelProblem.design`)."""
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
    U = _factor_tables(order)[0]
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
    G = azimuthal_factors(mask, sio * a, sio * sio * rho, order) if order >= 1 else [mask]
    sq2 = math.sqrt(2.0)
    Gq = torch.stack([G[0]] + [g * sq2 for g in G[1:]], dim=-1)  # (p, L, P+1)
    Ri = _polar_table_t(zi_c.reshape(-1), order).t().reshape(p, L, U)  # (p, L, U)
    qidx, src_t, coef_t, rows_t, cols_t = _factor_index_tensors(order, dt, dev)
    X = Ri * Gq.index_select(-1, qidx)
    Ro = _polar_table_t(zo_c, order).t()  # (p, U)
    vals = Ro.index_select(1, src_t) * coef_t  # (p, 2K)
    T = torch.zeros(p, U, K, dtype=dt, device=dev)
    T = T.index_put((torch.arange(p, device=dev).unsqueeze(-1), rows_t.unsqueeze(0).expand(p, -1),
                     cols_t.unsqueeze(0).expand(p, -1)), vals, accumulate=True)
    return X, T


@lru_cache(maxsize=64)
def _factor_index_tensors(order: int, dtype: torch.dtype, device: torch.device):
    """The tables of :func:`_factor_tables` as tensors on ``device``, made once (no host-to-device copy per call)."""
    U, qcol, rows, cols_k, src, coef = _factor_tables(order)
    return (torch.tensor(qcol, device=device), torch.tensor(src, device=device),
            torch.tensor(coef, dtype=dtype, device=device), torch.tensor(rows, device=device),
            torch.tensor(cols_k, device=device))
