r"""Convergence control: refine a product rule until successive results agree (:func:`adaptive`).

The error estimate and the refinement strategy are described in :mod:`torch_hsh.fitting.rules`.
"""
from __future__ import annotations

import math
import warnings
from typing import Callable, Dict, List, Optional, Tuple

import torch

from .rules import RuleResult

__all__ = ["ConvergenceError", "ConvergenceWarning", "RuleResult", "adaptive", "relative_change"]


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


def relative_change(x: torch.Tensor, y: torch.Tensor) -> float:
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
        msg = _unconverged_message(what, e_phi, e_theta, tol, max_evaluations, cur, need, used, est, divergence_hint)
        if strict:
            raise ConvergenceError(msg, estimate=est, result=cur, info=info)
        warnings.warn(msg, ConvergenceWarning, stacklevel=3)
    return cur, info


def _unconverged_message(what: str, e_phi: float, e_theta: float, tol: float, max_evaluations: int, cur: RuleResult,
                         need: int, used: int, est: float, divergence_hint: str) -> str:
    """Say what failed when the budget ran out before both directions converged."""
    # The test is per direction (each change <= tol / 2), so the sum of the two
    # changes (the estimate) can be below tol while one direction still fails it.
    failing = []
    for d, e in (("phi", e_phi), ("theta", e_theta)):
        if not math.isfinite(e):
            failing.append(f"n_{d} was not yet checked at the last rule")
        elif e > tol / 2:
            failing.append(f"the last refinement of n_{d} changed the result by {e:.3g}, above tol/2 = {tol / 2:g}")
    if not failing:  # cannot happen with the loop in adaptive; kept so the message is never empty
        failing.append("the next refinement could not be afforded")
    return (f"{what} did not converge within max_evaluations={max_evaluations}: "
            f"{'; '.join(failing)} (each direction must change by at most tol/2 for tol={tol:g}). "
            f"The next refinement of the rule n_theta={cur.n_theta}, n_phi={cur.n_phi} needs "
            f"{need} evaluations, {max_evaluations - used} are left (error estimate of the returned rule, "
            f"the sum of the last changes in both directions: {est:.3g}). Raise max_evaluations, loosen tol, "
            f"or pass strict=False to accept the result with that estimate. {divergence_hint}")


def _info(r: RuleResult, used: int, est: float, converged: bool, history) -> Dict[str, object]:
    return {"error_estimate": est, "n_theta": r.n_theta, "n_phi": r.n_phi, "evaluations": used,
            "converged": converged, "history": list(history)}
