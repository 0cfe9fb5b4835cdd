"""The messages of :class:`torch_hsh.ConvergenceError` say what actually failed (issue 23, section 5).

The refinement loop (:func:`torch_hsh.fitting.convergence.adaptive`) is driven by a fake rule whose changes are
chosen per direction, so each scenario is exact and fast.
"""
import re

import pytest
import torch

from torch_hsh.fitting.convergence import ConvergenceError, RuleResult, adaptive


def _rule(nt, nph):
    return RuleResult(a=torch.tensor([[float(nt), float(nph)]]), E=None, n_theta=nt, n_phi=nph,
                      evaluations=nt * nt * nph)


def _metric(phi_change, theta_change):
    """Change between a finer and a coarser rule: ``phi_change(n_phi)`` or ``theta_change(n_theta)``."""

    def metric(fine, cur):
        if fine.n_phi != cur.n_phi:
            return phi_change(fine.n_phi)
        return theta_change(fine.n_theta)

    return metric


def test_budget_message_names_the_direction_that_failed_even_when_the_sum_is_below_tol():
    # n_phi converges at once (change 1.7e-4 <= tol/2); n_theta keeps changing by 6e-4 > tol/2 = 5e-4.
    # The sum of the two, 7.7e-4, is below tol: the old message said "did not reach tol=0.001 ... (error
    # estimate 0.00077)", which reads as a contradiction.
    tol = 1e-3
    with pytest.raises(ConvergenceError) as ei:
        adaptive(_rule, _metric(lambda n: 1.7e-4, lambda n: 6e-4), 8, 16, tol, 60_000, True, "project", "HINT")
    msg = str(ei.value)
    assert ei.value.estimate < tol  # the situation of the issue
    assert "n_theta changed the result by 0.0006, above tol/2 = 0.0005" in msg
    assert "n_phi changed" not in msg  # n_phi did converge
    assert "did not reach tol" not in msg
    # the numbers needed to act on it: the next rule's cost and what is left of the budget
    need, left = (int(x) for x in re.search(r"needs (\d+) evaluations, (-?\d+) are left", msg).groups())
    assert need > left >= 0
    assert msg.rstrip().endswith("HINT")


def test_budget_message_when_phi_is_still_refining():
    with pytest.raises(ConvergenceError) as ei:
        adaptive(_rule, _metric(lambda n: 0.3, lambda n: 1e-9), 8, 16, 1e-3, 20_000, True, "brdf_energy", "")
    msg = str(ei.value)
    assert "n_phi changed the result by 0.3, above tol/2 = 0.0005" in msg
    assert "n_theta was not yet checked" in msg


def test_divergence_message_lists_only_the_theta_changes():
    # n_phi always converges with a small, recognisable change; n_theta changes do not shrink
    theta = {}

    def theta_change(nt):
        theta.setdefault(nt, 0.11 + 0.01 * len(theta))
        return theta[nt]

    with pytest.raises(ConvergenceError, match="appears divergent") as ei:
        adaptive(_rule, _metric(lambda n: 2.5e-5, theta_change), 8, 16, 1e-3, 10**12, True, "brdf_energy", "")
    msg = str(ei.value)
    assert "2.5e-05" not in msg  # the old message mixed the n_phi changes into the list
    assert "0.11, 0.12, 0.13, 0.14" in msg
    assert "n_theta" in msg
