r"""Projection of a BRDF onto a basis (paper Eq. 14), its energy and Acc(P): fixed or convergence-controlled rules."""
from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch

from ..bases import Basis
from .arguments import (
    _DEFAULT,
    BasisLike,
    _basis,
    _call_brdf,
    _check_callable,
    _check_dtype,
    _chunk,
    _sizes,
    default_quadrature_sizes,
)
from .coefficients import energy_accuracy
from .convergence import adaptive as _adaptive, relative_change as _rel_change
from .rules import _nodes, rule_sums as _rule_sums

__all__ = ["project", "brdf_energy", "brdf_accuracy"]


_ENERGY_HINT = (
    "If the BRDF grows like 1/cos(theta) at grazing angles (microfacet GGX or Ward, Oren-Nayar, Torrance-Sparrow), "
    "the integral of f^2 diverges: pass grazing_cutoff=c (e.g. 0.01) to integrate over cos(theta) >= c, or expand "
    "f cos(theta_i) cos(theta_o) instead."
)
_PROJECT_HINT = (
    "Sharp lobes need large n_phi; a BRDF with a non-integrable grazing singularity (e.g. the 1/cos(theta_i) of "
    "Torrance-Sparrow) needs grazing_cutoff=c."
)


def _check_control(tol, max_evaluations, grazing_cutoff, method):
    if tol is not None and (isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (0 < tol < 1)):
        raise ValueError(f"`tol` must be a number in (0, 1) or None, got {tol!r}")
    if isinstance(max_evaluations, bool) or not isinstance(max_evaluations, int) or max_evaluations < 1:
        raise ValueError(f"`max_evaluations` must be a positive integer, got {max_evaluations!r}")
    c = 0.0
    if grazing_cutoff is not None:
        if isinstance(grazing_cutoff, bool) or not isinstance(grazing_cutoff, (int, float)) or not (
                0.0 <= grazing_cutoff < 1.0):
            raise ValueError(f"`grazing_cutoff` must be a number in [0, 1) (a cosine), got {grazing_cutoff!r}")
        if method != "quadrature":
            raise ValueError("`grazing_cutoff` applies to method='quadrature' only")
        c = float(grazing_cutoff)
    return c


def _prepare(brdf, basis, order, dtype, tol, max_evaluations, grazing_cutoff, method) -> Tuple[Basis, int, float]:
    """The argument checks of :func:`project`, :func:`brdf_energy` and :func:`brdf_accuracy`: ``(basis, P, cutoff)``."""
    _check_callable(brdf)
    _check_dtype(dtype)
    b = _basis(basis)
    P = b.check_order(order)
    return b, P, _check_control(tol, max_evaluations, grazing_cutoff, method)


def _fixed_info(n_theta, n_phi, evaluations=None) -> Dict[str, object]:
    """The ``info`` of a fixed rule (no error estimate)."""
    return {"error_estimate": None, "n_theta": n_theta, "n_phi": n_phi, "evaluations": evaluations,
            "converged": None, "history": []}


def _use_reduced(b: Basis, reduced) -> bool:
    if reduced is None:
        return bool(b.isotropic)
    if bool(reduced) and not b.isotropic:
        raise ValueError(f"`reduced=True` needs an isotropic basis; '{b.name}' is not isotropic (use reduced=False)")
    return bool(reduced)


def _start_sizes(P: int, reduced: bool) -> Tuple[int, int]:
    nt, npf = default_quadrature_sizes(P)
    return (max(nt, 16), max(npf, 64)) if reduced else (max(nt, 12), max(npf, 32))


def _controlled(brdf, b: Basis, P: int, n_theta, n_phi, reduced, cutoff, tol, max_evaluations, strict,
                want_a, want_E, metric, what, hint, dtype, device):
    """Run the fixed rule (sizes given or ``tol is None``) or the adaptive loop; returns ``(RuleResult, info)``."""
    red = _use_reduced(b, reduced)

    def ev(nt, npf):
        return _rule_sums(brdf, b, P, nt, npf, red, cutoff, want_a, want_E, dtype, device)

    if n_theta is not None or n_phi is not None or tol is None:
        nt, npf = _sizes(P, n_theta, n_phi)
        r = ev(nt, npf)
        return r, _fixed_info(nt, npf, r.evaluations)
    nt, npf = _start_sizes(P, red)
    return _adaptive(ev, metric, nt, npf, float(tol), max_evaluations, strict, what, hint)


def _squeeze(t: torch.Tensor, r) -> torch.Tensor:
    return t[0] if r.scalar else t


def project(
    brdf: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    order: int,
    basis: BasisLike = _DEFAULT,
    n_theta: Optional[int] = None,
    n_phi: Optional[int] = None,
    method: str = "quadrature",
    n_samples: int = 100_000,
    reduced: Optional[bool] = None,
    chunk_size: Optional[int] = None,
    seed: Optional[int] = 0,
    generator: Optional[torch.Generator] = None,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
    tol: Optional[float] = 1e-3,
    max_evaluations: int = 1 << 27,
    strict: bool = True,
    grazing_cutoff: Optional[float] = None,
    return_info: bool = False,
):
    r"""Project a BRDF onto a basis: :math:`a_k = \iint f\,B_k\,d\omega_i\,d\omega_o` (Eq. 14).

    Args:
        brdf: callable ``brdf(wi, wo)``; receives ``(M, 3)`` unit local directions
            (``z > 0``) in ``dtype``/``device`` and returns ``(M,)`` or ``(M, C)``.
            It may carry autograd parameters: the result is differentiable
            with respect to them.
        order: truncation order ``P``.
        basis: basis name or :class:`~torch_hsh.bases.Basis`.
        n_theta, n_phi: fixed quadrature sizes per direction. When both are omitted
            (default) the rule is **refined until the relative L2 change of the
            coefficients** (= of the projected function, by Parseval) between
            successive rules is below ``tol`` (see the module docstring).
            Giving either selects one fixed rule (the other defaults to
            :func:`default_quadrature_sizes`) without an error estimate.
        method: ``"quadrature"`` (deterministic product rule) or
            ``"monte_carlo"`` (uniform sampling of both hemispheres, as in the paper;
            no error control).
        n_samples: number of ``(wi, wo)`` pairs for Monte Carlo.
        reduced: use the reduced 3-D isotropic rule (``wi`` at ``phi = 0``).
            Default: ``True`` iff the basis is isotropic, which **assumes an
            isotropic BRDF**. ``reduced=False`` forces the full 4-D product rule,
            which also projects an anisotropic BRDF onto an isotropic basis
            correctly (the result is the projection of its azimuthal average).
        chunk_size: pairs per chunk of the fixed rule without a cutoff
            (memory ``O(chunk_size * K)``); default ``max(256, 2**22 // K)``.
        seed, generator: Monte Carlo randomness (a fresh CPU generator seeded
            with ``seed`` unless ``generator`` is given).
        dtype, device: working precision and device.
        tol: target relative error of the coefficients (``None``: fixed default rule).
        max_evaluations: budget of BRDF evaluations over all refinements.
        strict: raise :class:`ConvergenceError` when the budget runs out (``False``:
            warn with :class:`ConvergenceWarning` and return the best result).
        grazing_cutoff: integrate over :math:`\cos\theta_i, \cos\theta_o \ge c` only
            (the projection of ``f`` set to zero below the cutoff).
        return_info: also return a dict (``error_estimate``, ``n_theta``, ``n_phi``,
            ``evaluations``, ``converged``, ``history``).

    Returns:
        ``(K,)`` coefficients for a scalar BRDF, ``(C, K)`` for ``C`` channels, in
        the column order of ``basis.evaluate``; with ``return_info``, ``(coefficients, info)``.

    Raises:
        ConvergenceError: the budget ran out before every direction's last change was
            ``<= tol / 2`` (the message says which direction failed), or the integral
            appears divergent (carries ``.estimate`` and ``.result``).

    Example:
        >>> import math, torch, torch_hsh
        >>> a = torch_hsh.project(lambda wi, wo: torch.full(wi.shape[:1], 0.5 / math.pi, dtype=wi.dtype), 2)
        >>> round(float(a[0]), 12), float(a[1:].abs().max()) < 1e-12   # Lambertian: 2 rho
        (1.0, True)
    """
    b, P, cutoff = _prepare(brdf, basis, order, dtype, tol, max_evaluations, grazing_cutoff, method)
    K = b.num_functions(P)
    fixed = n_theta is not None or n_phi is not None or tol is None
    if method != "quadrature" or (fixed and grazing_cutoff is None and not _lowpass_pays(b, P, n_theta, n_phi)):
        acc = _project_fixed(brdf, b, P, K, method, n_theta, n_phi, n_samples, reduced, chunk_size, seed,
                             generator, dtype, device)
        if not return_info:
            return acc
        return acc, _fixed_info(*(_sizes(P, n_theta, n_phi) if method == "quadrature" else (None, None)))
    r, info = _controlled(brdf, b, P, n_theta, n_phi, reduced, cutoff, tol, max_evaluations, strict, True, False,
                          lambda f, c: _rel_change(f.a, c.a), "project", _PROJECT_HINT, dtype, device)
    out = _squeeze(r.a, r)
    return (out, info) if return_info else out


def _lowpass_pays(b: Basis, P: int, n_theta, n_phi) -> bool:
    """Whether a fixed rule is cheaper through the azimuthal low-pass of :mod:`torch_hsh.fitting.rules`."""
    D = b.azimuthal_degree(P)
    return D is not None and _sizes(P, n_theta, n_phi)[1] > 4 * (D + 1)


def _project_fixed(brdf, b, P, K, method, n_theta, n_phi, n_samples, reduced, chunk_size, seed, generator,
                   dtype, device):
    acc = None
    for wi, wo, w in _nodes(b, P, method, n_theta, n_phi, n_samples, reduced, seed, generator, dtype, device,
                            _chunk(chunk_size, K)):
        with torch.no_grad():
            B = b.evaluate(wi, wo, P)
        v = _call_brdf(brdf, wi, wo)
        vw = v * (w if v.dim() == 1 else w[:, None])
        part = vw.transpose(0, -1) @ B if v.dim() == 2 else vw @ B
        if acc is None:
            acc = part
        else:
            if part.shape != acc.shape:
                raise ValueError(f"`brdf` returned inconsistent channel counts across chunks: {tuple(part.shape)} vs {tuple(acc.shape)}")
            acc = acc + part
    assert acc is not None  # the quadrature has at least one chunk
    return acc


def brdf_energy(
    brdf: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    order: int,
    basis: BasisLike = _DEFAULT,
    n_theta: Optional[int] = None,
    n_phi: Optional[int] = None,
    method: str = "quadrature",
    n_samples: int = 100_000,
    reduced: Optional[bool] = None,
    chunk_size: Optional[int] = None,
    seed: Optional[int] = 0,
    generator: Optional[torch.Generator] = None,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
    tol: Optional[float] = 1e-3,
    max_evaluations: int = 1 << 27,
    strict: bool = True,
    grazing_cutoff: Optional[float] = None,
    return_info: bool = False,
):
    r""":math:`\iint f^2\,d\omega_i\,d\omega_o` over the upper hemispheres (the denominator of Acc(P), Eq. 17).

    Same arguments as :func:`project`; ``order`` and ``basis`` only select the rule
    (the reduced isotropic rule when ``basis`` is isotropic, which assumes an
    isotropic BRDF). By default the rule is refined until the **relative change of
    the energy** between successive rules is below ``tol``. The integral diverges
    for BRDFs that grow like :math:`1/\cos\theta` at grazing angles (GGX, Ward,
    Oren--Nayar, Torrance--Sparrow): the refinement detects that and raises
    :class:`ConvergenceError`; pass ``grazing_cutoff`` to define a finite quantity.
    With identical fixed rules, Parseval holds to rounding for band-limited BRDFs:
    ``(project(...)**2).sum(-1) == brdf_energy(...)``.

    Returns:
        ``()`` for a scalar BRDF, ``(C,)`` for ``C`` channels; with ``return_info``,
        ``(energy, info)`` as in :func:`project`.

    Example:
        >>> import math
        >>> e = brdf_energy(lambda wi, wo: torch.ones(wi.shape[0], dtype=wi.dtype), 1)
        >>> abs(float(e) - 4 * math.pi**2) < 1e-9
        True
    """
    b, P, cutoff = _prepare(brdf, basis, order, dtype, tol, max_evaluations, grazing_cutoff, method)
    fixed = n_theta is not None or n_phi is not None or tol is None
    if method != "quadrature" or (fixed and grazing_cutoff is None):
        acc = None
        for wi, wo, w in _nodes(b, P, method, n_theta, n_phi, n_samples, reduced, seed, generator, dtype, device,
                                _chunk(chunk_size, 64)):
            v = _call_brdf(brdf, wi, wo)
            part = ((v * v) * (w if v.dim() == 1 else w[:, None])).sum(0)
            acc = part if acc is None else acc + part
        if not return_info:
            return acc
        return acc, _fixed_info(*(_sizes(P, n_theta, n_phi) if method == "quadrature" else (None, None)))
    r, info = _controlled(brdf, b, P, n_theta, n_phi, reduced, cutoff, tol, max_evaluations, strict, False, True,
                          lambda f, c: _rel_change(f.E[:, None], c.E[:, None]), "brdf_energy", _ENERGY_HINT,
                          dtype, device)
    out = _squeeze(r.E, r)
    return (out, info) if return_info else out


def brdf_accuracy(
    brdf: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    order: int,
    basis: BasisLike = _DEFAULT,
    tol: Optional[float] = 1e-3,
    max_evaluations: int = 1 << 27,
    strict: bool = True,
    grazing_cutoff: Optional[float] = None,
    reduced: Optional[bool] = None,
    n_theta: Optional[int] = None,
    n_phi: Optional[int] = None,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
    return_info: bool = False,
):
    r"""Acc(P') for ``P' = 0..P`` (paper Eq. 17) with coefficients and energy from one converged rule.

    The rule is refined until the largest change of Acc(P') over all ``P' <= P`` (and
    channels) between successive rules is below ``tol`` (**absolute**, in units of
    Acc). Numerator and denominator come from the same BRDF samples. See
    :func:`project` for the arguments; ``grazing_cutoff`` is required for BRDFs whose
    :math:`\iint f^2` diverges (Acc is then that of the BRDF cut at the cutoff).

    Returns:
        ``(P + 1,)`` for a scalar BRDF, ``(C, P + 1)`` for ``C`` channels; with
        ``return_info``, ``(acc, info)`` (``info["error_estimate"]`` is in units of Acc,
        ``info["coefficients"]`` and ``info["energy"]`` are the converged sums).

    Example:
        >>> acc = brdf_accuracy(lambda wi, wo: torch.full(wi.shape[:1], 0.2, dtype=wi.dtype), 2)
        >>> [round(float(x), 9) for x in acc]   # a constant is captured at order 0
        [1.0, 1.0, 1.0]
    """
    b, P, cutoff = _prepare(brdf, basis, order, dtype, tol, max_evaluations, grazing_cutoff, "quadrature")

    def acc_of(r):
        return energy_accuracy(r.a, r.E, basis=b, order=P)

    def metric(f, c):
        return float((acc_of(f) - acc_of(c)).detach().abs().max())

    r, info = _controlled(brdf, b, P, n_theta, n_phi, reduced, cutoff, tol, max_evaluations, strict, True, True,
                          metric, "brdf_accuracy", _ENERGY_HINT, dtype, device)
    out = _squeeze(acc_of(r), r)
    if not return_info:
        return out
    info = dict(info, coefficients=_squeeze(r.a, r), energy=_squeeze(r.E, r))
    return out, info
