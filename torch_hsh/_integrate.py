r"""Convergence-controlled product rules for :func:`torch_hsh.fitting.project` and friends.

Conventions
-----------
* The integrals are over the upper hemispheres, optionally cut at grazing angles:
  :math:`\cos\theta \ge c` for **both** directions (``grazing_cutoff = c``). With a
  cutoff the integrand is the BRDF times the indicator of that region, so Parseval
  still holds for the truncated function (Acc of ``f 1[z_i >= c, z_o >= c]``).
* Rules: Gauss--Legendre in :math:`\cos\theta` on ``[c, 1]`` (``n_theta`` nodes) times
  the trapezoid rule in the azimuth (``n_phi`` equispaced nodes). The reduced 3-D
  rule (isotropic integrands) puts :math:`\omega_i` at :math:`\phi = 0` and uses
  ``n_phi`` nodes in :math:`\Delta\phi`; the full 4-D rule uses ``n_phi`` nodes in each
  of :math:`\phi_i, \phi_o`.

Method
------
* **Azimuthal low-pass.** When ``basis.azimuthal_degree(P) = D`` is known, every
  basis function up to order ``P`` is, at fixed polar angles, a trigonometric
  polynomial of degree ``<= D`` in each azimuth. Then
  :math:`\int F B\,d\phi = \int F_D B\,d\phi` where :math:`F_D` keeps the Fourier
  modes ``|q| <= D`` of ``F``. The BRDF is sampled on the fine azimuthal grid,
  its low modes are taken by FFT, resampled on ``M = 2D + 2`` nodes (exact for the
  product, degree ``<= 2D``), and the basis is evaluated on the coarse grid only.
  The basis cost no longer grows with ``n_phi``, which is what sharp lobes need
  (their azimuthal width shrinks towards the grazing mirror configuration).
* **Error estimate and refinement.** :func:`adaptive` doubles ``n_phi`` while the
  result changes by more than ``tol / 2`` between ``n_phi`` and ``2 n_phi``, then
  checks ``n_theta`` against ``ceil(1.5 n_theta)`` the same way, and repeats. The
  estimate is the sum of the last two changes (the error of the returned coarser
  rule, a conservative estimate for exponentially or algebraically converging
  rules). A refinement of ``n_theta`` that does not shrink the change (ratio > 0.7
  three times in a row) is taken as a divergent integral (e.g. :math:`\iint f^2`
  of a microfacet BRDF without a grazing cutoff) and raised as such.

Performance: ``O(n_theta^2 n_phi)`` (reduced) or ``O(n_theta^2 n_phi^2)`` (4-D) BRDF
evaluations, in chunks of about ``2**21`` samples; basis evaluations
``O(n_theta^2 M K)`` / ``O(n_theta^2 M^2 K)``.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import torch

from .quadrature import gauss_legendre

__all__ = ["ConvergenceError", "ConvergenceWarning", "RuleResult", "rule_sums", "adaptive"]

_TWO_PI = 2.0 * math.pi


class ConvergenceError(RuntimeError):
    """A convergence-controlled integral did not reach its tolerance.

    Attributes:
        estimate: the error estimate reached (same units as ``tol``).
        result: the best value computed (what ``strict=False`` returns).
        info: dict with the rule sizes, evaluation count and refinement history.
    """

    def __init__(self, message: str, estimate: float, result=None, info: Optional[dict] = None):
        super().__init__(message)
        self.estimate = estimate
        self.result = result
        self.info = info or {}


class ConvergenceWarning(UserWarning):
    """Issued instead of :class:`ConvergenceError` when ``strict=False``."""


@dataclass
class RuleResult:
    """Sums of one rule: coefficients ``a`` (``(K,)`` or ``(C, K)``), energy ``E`` (``()`` or ``(C,)``)."""

    a: Optional[torch.Tensor]
    E: Optional[torch.Tensor]
    n_theta: int
    n_phi: int
    evaluations: int
    scalar: bool = False


def _call(brdf, wi, wo):
    from .fitting import _call_brdf

    return _call_brdf(brdf, wi, wo)


def _lowpass(F: torch.Tensor, D: int, M: int, dim: int) -> torch.Tensor:
    """Resample the modes ``|q| <= D`` of ``F`` along ``dim`` (``n`` equispaced nodes) onto ``M`` nodes."""
    n = F.shape[dim]
    Fh = torch.fft.rfft(F, dim=dim)
    Fh = Fh.narrow(dim, 0, min(D + 1, Fh.shape[dim]))
    return torch.fft.irfft(Fh * (M / n), n=M, dim=dim)


def _grid_dirs(zi, zo, phi_i, phi_o):
    """Direction pairs on a tensor grid; every argument broadcasts to a common shape."""
    shape = torch.broadcast_shapes(zi.shape, zo.shape, phi_i.shape, phi_o.shape)
    zi, zo, phi_i, phi_o = (t.expand(shape) for t in (zi, zo, phi_i, phi_o))
    si = torch.sqrt((1.0 - zi * zi).clamp(min=0.0))
    so = torch.sqrt((1.0 - zo * zo).clamp(min=0.0))
    wi = torch.stack([si * torch.cos(phi_i), si * torch.sin(phi_i), zi], -1)
    wo = torch.stack([so * torch.cos(phi_o), so * torch.sin(phi_o), zo], -1)
    return wi.reshape(-1, 3), wo.reshape(-1, 3), shape


def _channels_last(v: torch.Tensor, shape) -> torch.Tensor:
    """``(N,)`` or ``(N, C)`` BRDF values to ``(C, *shape)``."""
    if v.dim() == 1:
        return v.reshape(1, *shape)
    return v.T.reshape(v.shape[1], *shape)


def rule_sums(brdf, basis, order: int, n_theta: int, n_phi: int, reduced: bool, cutoff: float,
              want_a: bool, want_E: bool, dtype, device, budget_chunk: int = 1 << 21) -> RuleResult:
    """Coefficients and/or energy of ``brdf`` by one product rule (see the module docstring).

    Returns:
        :class:`RuleResult`; ``a`` is ``(C, K)`` and ``E`` is ``(C,)`` (channel axis always present).
    """
    z, wz = gauss_legendre(n_theta, float(cutoff), 1.0, dtype=dtype, device=device)
    P = order
    D = basis.azimuthal_degree(P) if want_a else None
    phi = torch.arange(n_phi, dtype=dtype, device=device) * (_TWO_PI / n_phi)
    use_lp = D is not None and n_phi > 2 * D + 2
    M = 2 * D + 2 if D is not None and use_lp else n_phi
    if reduced:
        return _reduced(brdf, basis, P, z, wz, phi, M, D, use_lp, want_a, want_E, budget_chunk)
    return _full(brdf, basis, P, z, wz, phi, M, D, use_lp, want_a, want_E, budget_chunk)


def _reduced(brdf, b, P, z, wz, phi, M, D, use_lp, want_a, want_E, chunk):
    nt, n_phi = z.shape[0], phi.shape[0]
    rows = max(1, chunk // (nt * n_phi))
    E = None
    Fc_parts: List[torch.Tensor] = []
    zo = z[None, :, None]
    scalar = False
    for s in range(0, nt, rows):
        zi = z[s : s + rows, None, None]
        wi, wo, shape = _grid_dirs(zi, zo, torch.zeros((), dtype=z.dtype, device=z.device), phi[None, None, :])
        v = _call(brdf, wi, wo)
        scalar = v.dim() == 1
        F = _channels_last(v, shape)  # (C, r, nt, n_phi)
        W = (_TWO_PI * wz[s : s + rows, None] * wz[None, :]) * (_TWO_PI / n_phi)  # (r, nt)
        if want_E:
            e = (F * F * W[..., None]).sum((1, 2, 3))
            E = e if E is None else E + e
        if want_a:
            Fc_parts.append(_lowpass(F, D, M, -1) if use_lp else F)
    a = None
    if want_a:
        Fc = torch.cat(Fc_parts, 1)  # (C, nt, nt, M)
        phi_c = torch.arange(M, dtype=z.dtype, device=z.device) * (_TWO_PI / M)
        Wc = (_TWO_PI * wz[:, None] * wz[None, :])[..., None] * (_TWO_PI / M)  # (nt, nt, 1)
        G = (Fc * Wc).reshape(Fc.shape[0], -1)  # (C, nt*nt*M)
        wi, wo, _ = _grid_dirs(z[:, None, None], z[None, :, None], torch.zeros((), dtype=z.dtype, device=z.device),
                               phi_c[None, None, :])
        a = _basis_dot(b, P, wi, wo, G, chunk)
    return RuleResult(a, E, nt, n_phi, nt * nt * n_phi, scalar)


def _full(brdf, b, P, z, wz, phi, M, D, use_lp, want_a, want_E, chunk):
    nt, n_phi = z.shape[0], phi.shape[0]
    per_i = nt * n_phi * n_phi
    rows = max(1, chunk // per_i)
    E = None
    parts: List[torch.Tensor] = []
    scalar = False
    for s in range(0, nt, rows):
        zi = z[s : s + rows, None, None, None]
        wi, wo, shape = _grid_dirs(zi, z[None, None, :, None], phi[None, :, None, None], phi[None, None, None, :])
        v = _call(brdf, wi, wo)
        scalar = v.dim() == 1
        F = _channels_last(v, shape)  # (C, r, n_phi_i, nt_o, n_phi_o)
        W = (wz[s : s + rows, None] * wz[None, :]) * (_TWO_PI / n_phi) ** 2  # (r, nt_o)
        if want_E:
            e = (F * F * W[:, None, :, None]).sum((1, 2, 3, 4))
            E = e if E is None else E + e
        if want_a:
            parts.append(_lowpass(_lowpass(F, D, M, 2), D, M, 4) if use_lp else F)
    a = None
    if want_a:
        Fc = torch.cat(parts, 1)  # (C, nt, M, nt, M)
        phi_c = torch.arange(M, dtype=z.dtype, device=z.device) * (_TWO_PI / M)
        Wc = (wz[:, None] * wz[None, :]) * (_TWO_PI / M) ** 2
        G = (Fc * Wc[:, None, :, None]).reshape(Fc.shape[0], -1)
        wi, wo, _ = _grid_dirs(z[:, None, None, None], z[None, None, :, None], phi_c[None, :, None, None],
                               phi_c[None, None, None, :])
        a = _basis_dot(b, P, wi, wo, G, chunk)
    return RuleResult(a, E, nt, n_phi, nt * nt * n_phi * n_phi, scalar)


def _basis_dot(b, P, wi, wo, G, chunk):
    """``G @ B`` with ``B = b.evaluate(wi, wo, P)`` in row chunks: ``(C, N) -> (C, K)``."""
    K = b.num_functions(P)
    step = max(256, (1 << 22) // max(K, 1))
    acc = None
    for s in range(0, wi.shape[0], step):
        with torch.no_grad():
            B = b.evaluate(wi[s : s + step], wo[s : s + step], P)
        part = G[:, s : s + step] @ B.to(G.dtype)
        acc = part if acc is None else acc + part
    return acc


def _rel(x: torch.Tensor, y: torch.Tensor) -> float:
    """Largest per-channel relative L2 change ``||x - y|| / ||y||`` (last dim = values)."""
    d = (x - y).detach().reshape(x.shape[0], -1).norm(dim=-1)
    n = y.detach().reshape(y.shape[0], -1).norm(dim=-1).clamp(min=torch.finfo(y.dtype).tiny)
    return float((d / n).max())


def adaptive(evaluate: Callable[[int, int], RuleResult], metric: Callable[[RuleResult, RuleResult], float],
             n_theta: int, n_phi: int, tol: float, max_evaluations: int, strict: bool, what: str,
             divergence_hint: str) -> Tuple[RuleResult, Dict[str, object]]:
    """Refine ``(n_theta, n_phi)`` until ``metric`` between successive rules is ``<= tol / 2`` in each direction.

    Args:
        evaluate: ``(n_theta, n_phi) -> RuleResult``.
        metric: change between a finer and a coarser result (a float, same units as ``tol``).
        n_theta, n_phi: starting sizes.
        tol: target of the error estimate.
        max_evaluations: budget of BRDF evaluations over all rules.
        strict: raise :class:`ConvergenceError` (True) or warn (False) when the budget runs out.
        what: name of the quantity in messages.
        divergence_hint: appended to the divergence message.

    Returns:
        ``(result, info)``; ``info`` has ``error_estimate``, ``n_theta``, ``n_phi``,
        ``evaluations``, ``converged`` and ``history`` (list of ``(n_theta, n_phi, change)``).
    """
    used = 0
    history: List[Tuple[str, int, int, float]] = []

    def run(nt, nph):
        nonlocal used
        r = evaluate(nt, nph)
        used += r.evaluations
        return r

    cur = run(n_theta, n_phi)
    per = cur.evaluations / float(n_theta * n_theta * n_phi)  # 1 (reduced) or n_phi (4-D)
    full4d = per > 1.5

    def size(nt, nph):
        return nt * nt * nph * (nph if full4d else 1)

    e_phi = e_theta = float("inf")
    streak = {"theta": 0}
    last = {"theta": None}

    def note(direction, e):
        prev = last[direction]
        streak[direction] = streak[direction] + 1 if (prev is not None and prev > 0 and e > 0.7 * prev
                                                       and e > tol / 2) else 0
        last[direction] = e
        if streak[direction] >= 3:
            info = _info(cur, used, e_phi + e_theta, False, history)
            # only the changes of this direction: the n_phi refinements in between are a different sequence
            mine = [h[3] for h in history if h[0] == direction][-(streak[direction] + 1):]
            raise ConvergenceError(
                f"{what}: the integral appears divergent: refining n_{direction} does not shrink the change "
                f"(successive n_{direction} refinements changed the result by "
                f"{', '.join(f'{x:.3g}' for x in mine)}). {divergence_hint}",
                estimate=e, result=cur, info=info)

    need = 0
    while True:
        converged = False
        need = size(cur.n_theta, 2 * cur.n_phi)
        if used + need > max_evaluations:
            break
        fine = run(cur.n_theta, 2 * cur.n_phi)
        e_phi = metric(fine, cur)
        history.append(("phi", fine.n_theta, fine.n_phi, e_phi))
        if e_phi > tol / 2:  # at fixed n_theta the azimuthal trapezoid always converges: no divergence test
            cur = fine
            continue
        nt2 = int(math.ceil(1.5 * cur.n_theta))
        need = size(nt2, cur.n_phi)
        if used + need > max_evaluations:
            break
        fine_t = run(nt2, cur.n_phi)
        e_theta = metric(fine_t, cur)
        history.append(("theta", fine_t.n_theta, fine_t.n_phi, e_theta))
        if e_theta > tol / 2:
            note("theta", e_theta)
            cur = fine_t
            continue
        converged = True
        break
    finite = [e for e in (e_phi, e_theta) if math.isfinite(e)]
    est = sum(finite) if finite else float("inf")  # an unchecked direction adds nothing it could quantify
    info = _info(cur, used, est, converged, history)
    if not converged:
        # Say what failed: the test is per direction (each change <= tol / 2), so the sum of the two
        # changes (the estimate) can be below tol while one direction still fails it.
        failing = []
        for d, e in (("phi", e_phi), ("theta", e_theta)):
            if not math.isfinite(e):
                failing.append(f"n_{d} was not yet checked at the last rule")
            elif e > tol / 2:
                failing.append(f"the last refinement of n_{d} changed the result by {e:.3g}, above tol/2 = {tol / 2:g}")
        if not failing:  # cannot happen with the loop above; kept so the message is never empty
            failing.append("the next refinement could not be afforded")
        msg = (f"{what} did not converge within max_evaluations={max_evaluations}: "
               f"{'; '.join(failing)} (each direction must change by at most tol/2 for tol={tol:g}). "
               f"The next refinement of the rule n_theta={cur.n_theta}, n_phi={cur.n_phi} needs "
               f"{need} evaluations, {max_evaluations - used} are left (error estimate of the returned rule, "
               f"the sum of the last changes in both directions: {est:.3g}). Raise max_evaluations, loosen tol, "
               f"or pass strict=False to accept the result with that estimate. {divergence_hint}")
        if strict:
            raise ConvergenceError(msg, estimate=est, result=cur, info=info)
        warnings.warn(msg, ConvergenceWarning, stacklevel=3)
    return cur, info


def _info(r: RuleResult, used: int, est: float, converged: bool, history) -> Dict[str, object]:
    return {"error_estimate": est, "n_theta": r.n_theta, "n_phi": r.n_phi, "evaluations": used,
            "converged": converged, "history": list(history)}
