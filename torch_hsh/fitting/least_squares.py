r"""Least-squares coefficients from scattered BRDF samples (paper Section 6)."""
from __future__ import annotations

import math
from typing import Dict, Optional

import torch

from .._checks import broadcast_shapes, check_dirs, check_same, check_shape, check_tensor, validation_enabled
from .arguments import _DEFAULT, BasisLike, _basis

__all__ = ["fit"]


def fit(
    wi: torch.Tensor,
    wo: torch.Tensor,
    values: torch.Tensor,
    order: int,
    basis: BasisLike = _DEFAULT,
    weights: Optional[torch.Tensor] = None,
    ridge: float = 0.0,
    ridge_growth: float = 0.0,
    rcond: Optional[float] = None,
    method: str = "auto",
    return_info: bool = False,
):
    r"""Least-squares coefficients from scattered BRDF samples (paper Section 6).

    Minimises :math:`\sum_n w_n (y_n - \sum_k a_k B_k(\omega_{i,n}, \omega_{o,n}))^2
    + \sum_k \lambda_k a_k^2` with
    :math:`\lambda_k = \text{ridge}\cdot(1 + L_k)^{\text{ridge\_growth}}`, where
    :math:`L_k` is ``basis.function_orders`` (``max(p, r)`` for the Helmholtz
    bases): ``ridge_growth=0`` is plain Tikhonov, ``ridge_growth=2`` penalises
    high orders quadratically (a smoothness prior).

    Shapes (``N`` samples, ``K`` functions). Directions are either **shared**,
    ``(N, 3)``, or **per BRDF**, ``(B, N, 3)`` (``wi`` and ``wo`` broadcast
    together). ``values``:

    ====================  ====================  ===============
    ``values``            directions            result
    ====================  ====================  ===============
    ``(N,)``              shared                ``(K,)``
    ``(N, C)``            shared                ``(C, K)``
    ``(B, N)``            per BRDF              ``(B, K)``
    ``(B, N, C)``         shared or per BRDF    ``(B, C, K)``
    ====================  ====================  ===============

    i.e. a 2-D ``values`` means ``(N, C)`` channels when the directions are shared
    and ``(B, N)`` when they are per BRDF. (To fit ``B`` scalar BRDFs sampled at
    shared directions pass ``values.T`` as ``(N, B)`` channels, or ``(B, N, 1)``.)
    ``weights`` (non-negative, per sample): ``(N,)`` or ``(B, N)``.

    Solver: everything is done in float64 internally (float32 inputs are
    promoted; the result is cast back to the input dtype). ``method="auto"``
    solves the normal equations :math:`(A^T W A + \Lambda)a = A^T W y` by
    Cholesky and falls back to a rank-revealing least-squares solve of the
    augmented system :math:`[\sqrt W A; \sqrt\Lambda]` (``torch.linalg.lstsq``
    with the SVD driver ``gelsd`` on CPU, ``pinv`` elsewhere; relative cut-off
    ``rcond``) when the Cholesky factorisation fails or its estimated condition
    number exceeds ``1e12`` (e.g. fewer samples than functions and no ridge:
    the minimum-norm solution is returned). ``method="cholesky"`` or
    ``"lstsq"`` forces one solver (``"cholesky"`` raises if the system is
    singular).

    Args:
        wi, wo: local directions, ``(N, 3)`` or ``(B, N, 3)``.
        values: BRDF samples (see table), finite.
        order: basis order ``P``.
        basis: basis name or object.
        weights: optional per-sample weights >= 0.
        ridge: Tikhonov strength >= 0.
        ridge_growth: exponent of the order dependence of the ridge (>= 0).
        rcond: relative singular-value cut-off of the fallback (default: machine
            epsilon times ``max(N, K)``).
        method: ``"auto"``, ``"cholesky"`` or ``"lstsq"``.
        return_info: also return a dict of diagnostics.

    Returns:
        ``coefficients`` (see table), or ``(coefficients, info)`` with ``info`` holding
        ``residuals`` (same shape as ``values``: ``y - A a``),
        ``rms`` (weighted RMS residual per fitted function, shape of ``coefficients``
        without ``K``), ``relative_residual`` (``||r||_W / ||y||_W``),
        ``condition`` (condition-number estimate of the normal matrix, per batch),
        ``solver`` (``"cholesky"`` or ``"lstsq"``), ``num_samples`` and
        ``num_functions``.

    Example:
        >>> wi = torch.nn.functional.normalize(torch.rand(500, 3, dtype=torch.float64), dim=-1)
        >>> wo = torch.nn.functional.normalize(torch.rand(500, 3, dtype=torch.float64), dim=-1)
        >>> a = fit(wi, wo, torch.full((500,), 0.5 / math.pi, dtype=torch.float64), 2)
        >>> round(float(a[0]), 10)
        1.0
    """
    b = _basis(basis)
    P = b.check_order(order)
    y, layout, N = _check_samples(wi, wo, values)
    Bn = y.shape[0]
    _check_solver_options(ridge, ridge_growth, method, rcond)
    out_dtype = values.dtype
    f64 = torch.float64
    dev = values.device
    A = b.evaluate(wi.to(f64), wo.to(f64), P)  # (N, K) or (Bd, N, K)
    K = A.shape[-1]
    if A.dim() == 2:
        A = A[None]
    y64 = y.to(f64)
    wt = _sample_weights(weights, values, N, Bn)
    lam_diag = None
    if ridge > 0:
        L = b.function_orders(P).to(device=dev, dtype=f64)
        lam_diag = ridge * (1.0 + L) ** ridge_growth
    coefficients, solver, cond = _solve(A, y64, wt, lam_diag, method, rcond)  # coefficients: (Bn, K, C)
    res = _LAYOUT[layout](coefficients.transpose(-1, -2)).to(out_dtype)  # from (Bn, C, K)
    if not return_info:
        return res
    info = _diagnostics(A, coefficients, y64, wt, values, layout, out_dtype)
    info.update(condition=cond, solver=solver, num_samples=N, num_functions=K)
    return res, info


#: The result layout from its ``(B, C, ...)`` batch form, by the shape of ``values`` (see :func:`fit`).
_LAYOUT = {
    "K": lambda t: t[0, 0],
    "CK": lambda t: t[0],
    "BK": lambda t: t[:, 0],
    "BCK": lambda t: t,
}


def _check_samples(wi: torch.Tensor, wo: torch.Tensor, values: torch.Tensor):
    """Check the directions and values; returns ``values`` as ``(Bv, N, C)``, the output layout and ``N``."""
    check_dirs(wi, "wi")
    check_dirs(wo, "wo")
    check_same([("wi", wi), ("wo", wo)])
    check_tensor(values, "values", min_dims=1)
    check_same([("wi", wi), ("values", values)])
    for name, d in (("wi", wi), ("wo", wo)):
        check_shape(d, name, ("N", 3), ("B", "N", 3))
    lead = broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1])])
    per_brdf = len(lead) == 2
    N = lead[-1]
    check_shape(values, "values", ("N",), ("N", "C"), ("B", "N"), ("B", "N", "C"))
    # normalise values to (Bv, N, C) and remember the output layout
    if values.dim() == 1:
        if per_brdf:
            raise ValueError(f"`values` (N,) needs shared directions (N, 3); got per-BRDF directions {tuple(lead)} + (3,)")
        y = values[None, :, None]
        layout = "K"
    elif values.dim() == 2 and not per_brdf:
        y = values[None]
        layout = "CK"
    elif values.dim() == 2:
        y = values[:, :, None]
        layout = "BK"
    else:
        y = values
        layout = "BCK"
    if y.shape[1] != N:
        raise ValueError(
            f"`values` {tuple(values.shape)} does not match the {N} samples of `wi`/`wo` "
            f"(rule: (N,) or (N, C) with shared (N, 3) directions, (B, N) with (B, N, 3), (B, N, C) with either)"
        )
    if per_brdf and y.shape[0] != lead[0] and lead[0] != 1:
        raise ValueError(f"`values` has batch {y.shape[0]} but the directions have batch {lead[0]}")
    return y, layout, N


def _check_solver_options(ridge, ridge_growth, method, rcond) -> None:
    if isinstance(ridge, bool) or not isinstance(ridge, (int, float)) or not math.isfinite(ridge) or ridge < 0:
        raise ValueError(f"`ridge` must be a finite number >= 0, got {ridge!r}")
    if isinstance(ridge_growth, bool) or not isinstance(ridge_growth, (int, float)) or not math.isfinite(ridge_growth) or ridge_growth < 0:
        raise ValueError(f"`ridge_growth` must be a finite number >= 0, got {ridge_growth!r}")
    if method not in ("auto", "cholesky", "lstsq"):
        raise ValueError(f"`method` must be 'auto', 'cholesky' or 'lstsq', got {method!r}")
    if rcond is not None and (not isinstance(rcond, (int, float)) or isinstance(rcond, bool) or rcond < 0):
        raise ValueError(f"`rcond` must be a number >= 0 or None, got {rcond!r}")


def _sample_weights(weights: Optional[torch.Tensor], values: torch.Tensor, N: int, Bn: int) -> Optional[torch.Tensor]:
    """The per-sample weights as float64 ``(1 | Bn, N)``, checked; ``None`` without weights."""
    if weights is None:
        return None
    f64 = torch.float64
    check_tensor(weights, "weights", min_dims=1)
    if weights.device != values.device:
        raise ValueError(f"`weights` is on {weights.device} but `values` is on {values.device}")
    check_shape(weights, "weights", ("N",), (1, "N"), ("B", "N"), sizes={"N": N, "B": Bn})
    wt = weights.to(f64)[None] if weights.dim() == 1 else weights.to(f64)
    if validation_enabled():
        if bool((wt < 0).any()):
            raise ValueError("`weights` must be non-negative")
        empty = (wt == 0).all(dim=-1)
        if bool(empty.any()):
            where = "" if wt.shape[0] == 1 else f" for batch entry {int(empty.nonzero()[0, 0])}"
            raise ValueError(f"`weights` are all zero{where}: no sample takes part in the fit")
    return wt


def _solve(A, y64, wt, lam_diag, method, rcond):
    """``(coefficients (Bn, K, C), solver, condition)``: the normal equations by Cholesky, else the augmented lstsq."""
    Bn = y64.shape[0]
    Aw = A if wt is None else A * wt[..., None]  # W A
    G = A.transpose(-1, -2) @ Aw  # (Bg, K, K), Bg in {1, Bd, Bw}
    rhs = Aw.transpose(-1, -2) @ y64 if Aw.shape[0] == Bn or Aw.shape[0] == 1 else None  # (Bn, K, C)
    if rhs is None:
        raise ValueError(f"direction/weight batch {Aw.shape[0]} does not match values batch {Bn}")
    if lam_diag is not None:
        G = G + torch.diag_embed(lam_diag).expand_as(G)
    if method in ("auto", "cholesky"):
        Lc, chol_info = torch.linalg.cholesky_ex(G)
        d = torch.diagonal(Lc, dim1=-2, dim2=-1).abs()
        ok = bool((chol_info == 0).all())
        if ok:
            cond = (d.max(-1).values / d.min(-1).values.clamp(min=1e-300)) ** 2
            ok = bool((cond < 1e12).all()) or method == "cholesky"
        if ok:
            return torch.cholesky_solve(rhs, Lc), "cholesky", cond
        if method == "cholesky":
            raise ValueError("the normal equations are singular (Cholesky failed); use ridge > 0 or method='lstsq'")
    coefficients, cond = _solve_lstsq(A, y64, wt, lam_diag, rcond)
    return coefficients, "lstsq", cond


def _solve_lstsq(A, y64, wt, lam_diag, rcond):
    """Rank-revealing least squares of the augmented system ``[sqrt(W) A; sqrt(Lambda)]``.

    Returns ``(coefficients, condition)``.
    """
    f64 = torch.float64
    Bn, N, K = y64.shape[0], A.shape[1], A.shape[-1]
    sw = None if wt is None else torch.sqrt(wt)
    Aa = A if sw is None else A * sw[..., None]
    ya = y64 if sw is None else y64 * sw[..., None]
    Aa = Aa.expand(Bn, N, K) if Aa.shape[0] == 1 else Aa
    ya = ya.expand(Aa.shape[0], N, ya.shape[-1]) if ya.shape[0] == 1 else ya
    if lam_diag is not None:
        Aa = torch.cat([Aa, torch.diag_embed(torch.sqrt(lam_diag)).expand(Aa.shape[0], K, K)], dim=1)
        ya = torch.cat([ya, ya.new_zeros(ya.shape[0], K, ya.shape[-1])], dim=1)
    rc = rcond if rcond is not None else torch.finfo(f64).eps * max(Aa.shape[1], K)
    if Aa.device.type == "cpu":
        coefficients = torch.linalg.lstsq(Aa, ya, rcond=rc, driver="gelsd").solution
    else:
        coefficients = torch.linalg.pinv(Aa, rtol=rc) @ ya
    sv = torch.linalg.svdvals(Aa)
    cond = (sv[..., 0] / sv[..., -1].clamp(min=1e-300)) ** 2 if Aa.shape[1] >= K else torch.full(
        sv.shape[:-1], float("inf"), dtype=f64, device=y64.device)
    return coefficients, cond


def _diagnostics(A, coefficients, y64, wt, values, layout: str, out_dtype) -> Dict[str, object]:
    """Residuals, weighted RMS and relative residual of the fit, in the layout of ``values``/the result."""
    N = y64.shape[1]
    pred = A @ coefficients  # (Bn, N, C)
    r = y64 - pred
    wr = torch.ones_like(r[..., :1]) if wt is None else wt[..., None].expand(r.shape[0], N, 1)
    rss = (wr * r * r).sum(1)  # (Bn, C)
    yss = (wr * y64 * y64).sum(1)
    wsum = wr.sum(1).clamp(min=1e-300)
    rms = torch.sqrt(rss / wsum)
    rel = torch.sqrt(rss / yss.clamp(min=1e-300))
    shape_fix = _LAYOUT[layout]
    resid = r.reshape(values.shape) if layout != "CK" else r[0]
    return {
        "residuals": resid.to(out_dtype),
        "rms": shape_fix(rms).to(out_dtype),
        "relative_residual": shape_fix(rel).to(out_dtype),
    }
