r"""Projection, least-squares fitting, reconstruction and energy analysis.

Every function takes a ``basis`` argument: a registered name (see
:func:`torch_hsh.bases.available_bases`) or a :class:`torch_hsh.bases.Basis`;
the default is ``"helmholtz_isotropic"``. Nothing here is specific to the
Helmholtz bases except :func:`directional_albedo`'s closed form (which falls
back to quadrature for other bases).

Conventions
-----------
* Directions are in the local frame (z = normal). A BRDF is a callable
  ``brdf(wi, wo)`` taking two ``(M, 3)`` tensors and returning ``(M,)`` (one
  channel) or ``(M, C)`` (e.g. RGB).
* Coefficients: ``(K,)`` for one scalar BRDF, ``(C, K)`` for C channels, with
  leading batch dimensions in front where documented.
* Projection (paper Eq. 14): :math:`a_k = \int_{\Omega_i}\int_{\Omega_o} f\,B_k\,
  d\omega_i\,d\omega_o`. The integral is always taken over the **upper**
  hemispheres: for ``domain == "sphere"`` bases (orthonormal over full spheres)
  this is exactly the projection of the BRDF extended by zero below the
  horizon, without integrating across the discontinuity at ``z = 0``.
* Default quadrature sizes: ``n_theta = 2 (P + 1)`` Gauss--Legendre nodes in
  ``cos(theta)`` and ``n_phi = 2 (2P + 1)`` azimuths per direction. The
  product of a basis function of order ``<= P`` with a function band-limited
  to order ``L`` is integrated exactly when ``n_theta >= (L + P)/2 + 1`` and
  ``n_phi >= L + P + 1`` (see :mod:`torch_hsh.quadrature`), so the defaults
  project any function band-limited to order ``L <= 3P + 1`` **exactly** (the
  minimal exact rule for ``L = P`` would be ``P + 1`` and ``2P + 1``; the factor
  two buys accuracy on BRDFs that are not band-limited). Pass larger values for
  sharp specular lobes.
* **Convergence control** (default): when neither ``n_theta`` nor ``n_phi`` is
  given, :func:`project`, :func:`brdf_energy` and :func:`brdf_accuracy` estimate
  their own error by comparing successive rules and refine until the estimate is
  below ``tol`` (see :mod:`torch_hsh._integrate`); when ``max_evaluations`` runs
  out they raise :class:`ConvergenceError` carrying the estimate (``strict=False``:
  a :class:`ConvergenceWarning` and the best result). Passing ``n_theta``/``n_phi``
  (or ``tol=None``) selects one fixed rule without an estimate, as before.
  ``grazing_cutoff=c`` integrates over :math:`\cos\theta_i, \cos\theta_o \ge c`
  only; it is **required** where the integral diverges, e.g. :math:`\iint f^2` of
  the GGX, Ward, Oren--Nayar and Torrance--Sparrow models (they grow like
  :math:`1/\cos` at grazing angles), which the refinement detects and reports.
  Cost: sharp lobes need many azimuths (the azimuthal width of a specular lobe
  shrinks towards the grazing mirror configuration; ``n_phi`` of 1000-4000 for GGX
  roughness 0.3), which the azimuthal low-pass keeps cheap (seconds). A BRDF with
  an integrable grazing singularity (raw GGX: :math:`\int f B` is finite) converges
  only algebraically in ``n_theta`` (about 30 s at P = 8 for raw GGX roughness 0.7);
  a ``grazing_cutoff`` makes it fast again (about 1 s).
* Singularities at grazing angles: Gauss--Legendre nodes are strictly inside
  ``(0, 1)``, so ``z = 0`` is never evaluated and integrable singularities
  (e.g. :math:`z^{-1/2}`) give finite sums that converge as ``n_theta``
  grows. Note that the Torrance--Sparrow :math:`1/\cos\theta_i` term of paper
  Eq. (38) is *not* integrable at the horizon unless its Gaussian factor
  vanishes there (:math:`\int_0 dz/z` diverges logarithmically); the sums stay
  finite but then grow like :math:`e^{-\pi^2/(16\sigma^2)}\log n_\theta`, which is
  negligible for small roughness :math:`\sigma` and a caveat for large ones (measured
  with :func:`project_normal_exitance`, ``a_0`` of the specular term for
  ``n_theta`` = 64/256/1024/4096: 4.24819/4.24822/4.24825/4.24828 at
  ``sigma = 0.2`` but 10.67/12.54/14.42/16.30 at ``sigma = 0.5``).
"""
from __future__ import annotations

import math
from typing import Callable, Dict, Iterator, Optional, Tuple, Union

import torch

from . import kernel as _hb
from ._checks import broadcast_shapes, check_dirs, check_same, check_tensor, validation_enabled
from .bases import Basis, get_basis
from .bases.helmholtz import HelmholtzAnisotropic, HelmholtzIsotropic
from ._integrate import ConvergenceError, ConvergenceWarning, adaptive as _adaptive, rule_sums as _rule_sums
from .quadrature import (
    direction_quadrature,
    gauss_legendre,
    isotropic_directions,
    isotropic_quadrature,
    monte_carlo_directions,
)

__all__ = [
    "project",
    "project_normal_exitance",
    "normal_exitance_to_isotropic",
    "normal_exitance_energy",
    "fit",
    "reconstruct",
    "evaluate",
    "truncate",
    "energy_accuracy",
    "brdf_energy",
    "brdf_accuracy",
    "ConvergenceError",
    "ConvergenceWarning",
    "directional_albedo",
    "default_quadrature_sizes",
    "infer_order",
]

BasisLike = Union[str, Basis]
_DEFAULT = "helmholtz_isotropic"
_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------
def _basis(basis) -> Basis:
    return get_basis(basis)


def infer_order(basis: BasisLike, num_functions: int) -> int:
    """The order ``P`` with ``basis.num_functions(P) == num_functions``.

    Raises ``ValueError`` listing the nearest valid counts when none matches.

    Example:
        >>> infer_order("helmholtz_isotropic", 20)
        3
    """
    b = _basis(basis)
    k = int(num_functions)
    mx = b.max_order if b.max_order is not None else 40
    counts = []
    for p in range(mx + 1):
        c = b.num_functions(p)
        counts.append(c)
        if c == k:
            return p
        if c > k:
            break
    raise ValueError(
        f"the last dimension of `coeffs` ({k}) matches no order of basis '{b.name}'; "
        f"valid sizes start {counts[:8]}{' ...' if len(counts) > 8 else ''}"
    )


def _order_of(b: Basis, K: int, order) -> int:
    if order is None:
        return infer_order(b, K)
    P = b.check_order(order)
    if b.num_functions(P) != K:
        raise ValueError(
            f"`coeffs` has {K} functions in its last dimension but basis '{b.name}' has "
            f"{b.num_functions(P)} functions up to order {P}"
        )
    return P


def default_quadrature_sizes(order: int) -> Tuple[int, int]:
    """Default ``(n_theta, n_phi) = (2 (P + 1), 2 (2P + 1))`` for order ``P``.

    Exact for projecting any function band-limited to order ``<= 3P + 1`` onto the
    basis up to order ``P`` (see the module docstring).

    Example:
        >>> default_quadrature_sizes(3)
        (8, 14)
    """
    P = int(order)
    return 2 * (P + 1), 2 * (2 * P + 1)


def _check_callable(brdf, name="brdf"):
    if not callable(brdf):
        raise TypeError(f"`{name}` must be callable as {name}(wi, wo) -> (M,) or (M, C), got {type(brdf).__name__}")


def _check_dtype(dtype):
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"`dtype` must be torch.float32 or torch.float64, got {dtype!r}")


def _call_brdf(brdf, wi, wo, name="brdf"):
    v = brdf(wi, wo)
    if not isinstance(v, torch.Tensor):
        raise TypeError(f"`{name}` must return a torch.Tensor, got {type(v).__name__}")
    M = wi.shape[0]
    if v.dim() == 0 or v.shape[0] != M or v.dim() > 2:
        raise ValueError(f"`{name}` called with ({M}, 3) directions must return ({M},) or ({M}, C), got {tuple(v.shape)}")
    if not v.is_floating_point():
        v = v.to(wi.dtype)
    if validation_enabled() and not bool(torch.isfinite(v).all()):
        raise ValueError(
            f"`{name}` returned NaN/Inf values (it is evaluated at interior quadrature nodes, z > 0); "
            "make it finite there"
        )
    return v.to(wi.dtype)


def _chunk(chunk_size, K) -> int:
    if chunk_size is None:
        return max(256, (1 << 22) // max(K, 1))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}")
    return chunk_size


def _sizes(P, n_theta, n_phi):
    dt, dp = default_quadrature_sizes(P)
    nt = dt if n_theta is None else n_theta
    npf = dp if n_phi is None else n_phi
    for nm, v in (("n_theta", nt), ("n_phi", npf)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"`{nm}` must be a positive integer, got {v!r}")
    return nt, npf


def _nodes(
    b: Basis,
    P: int,
    method: str,
    n_theta,
    n_phi,
    n_samples,
    reduced,
    seed,
    generator,
    dtype,
    device,
    chunk: int,
) -> Iterator[Tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Yield ``(wi, wo, w)`` chunks of a rule over Omega_i x Omega_o (upper hemispheres)."""
    if method == "quadrature":
        if reduced is None:
            reduced = bool(b.isotropic)
        reduced = bool(reduced)
        if reduced and not b.isotropic:
            raise ValueError(
                f"`reduced=True` needs an isotropic basis; '{b.name}' is not isotropic (use reduced=False)"
            )
        nt, npf = _sizes(P, n_theta, n_phi)
        if reduced:
            ci, co, dp, w = isotropic_quadrature(nt, npf, dtype=dtype, device=device)
            for s in range(0, ci.shape[0], chunk):
                wi, wo = isotropic_directions(ci[s : s + chunk], co[s : s + chunk], dp[s : s + chunk])
                yield wi, wo, w[s : s + chunk]
        else:
            d, wd = direction_quadrature(nt, npf, "hemisphere", dtype=dtype, device=device)
            nd = d.shape[0]
            total = nd * nd
            for s in range(0, total, chunk):
                idx = torch.arange(s, min(s + chunk, total), device=d.device)
                i, o = idx // nd, idx % nd
                yield d[i], d[o], wd[i] * wd[o]
    elif method == "monte_carlo":
        if reduced:
            raise ValueError("`reduced=True` applies to method='quadrature' only")
        if isinstance(n_samples, bool) or not isinstance(n_samples, int) or n_samples < 1:
            raise ValueError(f"`n_samples` must be a positive integer, got {n_samples!r}")
        if generator is None and seed is not None:
            generator = torch.Generator().manual_seed(int(seed))
        di, _ = monte_carlo_directions(n_samples, generator=generator, seed=None, dtype=dtype, device=device)
        do, _ = monte_carlo_directions(n_samples, generator=generator, seed=None, dtype=dtype, device=device)
        w = torch.full((n_samples,), _TWO_PI**2 / n_samples, dtype=dtype, device=di.device)
        for s in range(0, n_samples, chunk):
            yield di[s : s + chunk], do[s : s + chunk], w[s : s + chunk]
    else:
        raise ValueError(f"`method` must be 'quadrature' or 'monte_carlo', got {method!r}")


# --------------------------------------------------------------------------
# projection
# --------------------------------------------------------------------------
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
        return r, {"error_estimate": None, "n_theta": nt, "n_phi": npf, "evaluations": r.evaluations,
                   "converged": None, "history": []}
    nt, npf = _start_sizes(P, red)
    return _adaptive(ev, metric, nt, npf, float(tol), max_evaluations, strict, what, hint)


def _squeeze(t: torch.Tensor, r) -> torch.Tensor:
    return t[0] if r.scalar else t


def _rel_change(x: torch.Tensor, y: torch.Tensor) -> float:
    d = (x - y).detach().reshape(x.shape[0], -1).norm(dim=-1)
    n = y.detach().reshape(y.shape[0], -1).norm(dim=-1).clamp(min=torch.finfo(y.dtype).tiny)
    return float((d / n).max())


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
        the column order of ``basis.evaluate``; with ``return_info``, ``(coeffs, info)``.

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
    _check_callable(brdf)
    _check_dtype(dtype)
    b = _basis(basis)
    P = b.check_order(order)
    K = b.num_functions(P)
    cutoff = _check_control(tol, max_evaluations, grazing_cutoff, method)
    fixed = n_theta is not None or n_phi is not None or tol is None
    if method != "quadrature" or (fixed and grazing_cutoff is None and not _lowpass_pays(b, P, n_theta, n_phi)):
        acc = _project_fixed(brdf, b, P, K, method, n_theta, n_phi, n_samples, reduced, chunk_size, seed,
                             generator, dtype, device)
        if not return_info:
            return acc
        nt, npf = _sizes(P, n_theta, n_phi) if method == "quadrature" else (None, None)
        return acc, {"error_estimate": None, "n_theta": nt, "n_phi": npf, "evaluations": None,
                     "converged": None, "history": []}
    r, info = _controlled(brdf, b, P, n_theta, n_phi, reduced, cutoff, tol, max_evaluations, strict, True, False,
                          lambda f, c: _rel_change(f.a, c.a), "project", _PROJECT_HINT, dtype, device)
    out = _squeeze(r.a, r)
    return (out, info) if return_info else out


def _lowpass_pays(b: Basis, P: int, n_theta, n_phi) -> bool:
    """Whether a fixed rule is cheaper through the azimuthal low-pass of :mod:`torch_hsh._integrate`."""
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
        >>> e = brdf_energy(lambda wi, wo: torch.ones(wi.shape[0], dtype=wi.dtype), 1)
        >>> abs(float(e) - 4 * math.pi**2) < 1e-9
        True
    """
    _check_callable(brdf)
    _check_dtype(dtype)
    b = _basis(basis)
    P = b.check_order(order)
    cutoff = _check_control(tol, max_evaluations, grazing_cutoff, method)
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
        nt, npf = _sizes(P, n_theta, n_phi) if method == "quadrature" else (None, None)
        return acc, {"error_estimate": None, "n_theta": nt, "n_phi": npf, "evaluations": None,
                     "converged": None, "history": []}
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
        ``info["coeffs"]`` and ``info["energy"]`` are the converged sums).

    Example:
        >>> acc = brdf_accuracy(lambda wi, wo: torch.full(wi.shape[:1], 0.2, dtype=wi.dtype), 2)
        >>> [round(float(x), 9) for x in acc]   # a constant is captured at order 0
        [1.0, 1.0, 1.0]
    """
    _check_callable(brdf)
    _check_dtype(dtype)
    b = _basis(basis)
    P = b.check_order(order)
    cutoff = _check_control(tol, max_evaluations, grazing_cutoff, "quadrature")

    def acc_of(r):
        return energy_accuracy(r.a, r.E, basis=b, order=P)

    def metric(f, c):
        return float((acc_of(f) - acc_of(c)).detach().abs().max())

    r, info = _controlled(brdf, b, P, n_theta, n_phi, reduced, cutoff, tol, max_evaluations, strict, True, True,
                          metric, "brdf_accuracy", _ENERGY_HINT, dtype, device)
    out = _squeeze(acc_of(r), r)
    if not return_info:
        return out
    info = dict(info, coeffs=_squeeze(r.a, r), energy=_squeeze(r.E, r))
    return out, info


def _theta_table(z: torch.Tensor, P: int) -> torch.Tensor:
    """Zonal HSH Theta_p(z) = sqrt((2p+1)/(2 pi)) P~_p(z), ``(..., P+1)``."""
    s = torch.sqrt((1.0 - z * z).clamp(min=0.0))
    d = torch.stack([s, torch.zeros_like(s), z], dim=-1)
    H = _hb.hsh(d, P)
    idx = torch.tensor([n * n + n for n in range(P + 1)], device=z.device)
    return H.index_select(-1, idx)


def project_normal_exitance(
    brdf_1d: Callable[[torch.Tensor], torch.Tensor],
    order: int,
    n_theta: Optional[int] = None,
    normalization: str = "helmholtz",
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r"""Single-index spectrum of a BRDF at normal exitance (paper Eqs. 41--45).

    The paper expands a BRDF known only as a function ``g(cos theta_i)`` of the
    incident direction at fixed exitance :math:`\theta_o = 0` (e.g. its
    Torrance--Sparrow model, Eq. 38) in the zonal (``q = 0``) isotropic basis,
    treating ``g`` as a function on :math:`\Omega_i\times\Omega_o` that does not
    depend on :math:`\omega_o`, :math:`F(\omega_i, \omega_o) = g(\cos\theta_i)`.

    With the 1-D zonal HSH :math:`\Theta_p(z) = \sqrt{(2p+1)/(2\pi)}\,\tilde P_p(z)`
    (orthonormal on the hemisphere) and
    :math:`b_p = \int_{\Omega_i} g\,\Theta_p\,d\omega_i = 2\pi\int_0^1 g\,\Theta_p\,dz`,
    and using :math:`\int_{\Omega}\Theta_r\,d\omega = \sqrt{2\pi}\,\delta_{r0}`, the
    isotropic coefficients of ``F`` are exactly

    .. math::
        a_{p0}^0 = a_{0p}^0 = \begin{cases}\sqrt{2\pi}\,b_0 & p = 0\\
        \sqrt{\pi}\,b_p & p > 0\end{cases}, \qquad a_{pr}^q = 0 \text{ otherwise},

    which reproduces Eqs. (41), (42), (44) term by term (e.g. ``a_0 = 2 rho_d`` for
    a Lambertian part). Because every basis function is reciprocal, the
    expansion :math:`\sum_p a_p\,\mathcal H_{p0}^0` represents the *symmetrised*
    function :math:`(g(\cos\theta_i) + g(\cos\theta_o))/2`, not ``F``.

    Discrepancy with the paper: Eq. (45),
    :math:`f = a_0 + 2\sum_{p\ge1} a_p\mathcal H_{p0}^0`, is inconsistent with
    Eqs. (39)--(44): its first term lacks the factor
    :math:`\mathcal H_{00}^0 = 1/(2\pi)` and the factor 2 double counts the
    orthonormal functions :math:`\mathcal H_{p0}^0 = \mathcal H_{0p}^0`. The
    consistent reconstruction of ``g`` itself is
    :math:`g(z) = \sum_p b_p\,\Theta_p(z)` with ``b`` from
    ``normalization="hsh"``, and the energy fraction (Fig. 5) is
    ``cumsum(b**2) / normal_exitance_energy(g)`` (Parseval holds for ``b``, not
    for ``a``).

    Args:
        brdf_1d: callable ``g(cos_theta_i)``: ``(M,)`` -> ``(M,)`` or ``(M, C)``;
            evaluated at interior Gauss--Legendre nodes only (never at ``z = 0``).
        order: largest ``p``.
        n_theta: Gauss--Legendre nodes on ``[0, 1]``; default
            ``max(2 (P + 1), 256)`` (exact for polynomial ``g`` of degree
            ``<= 511 - P``).
        normalization: ``"helmholtz"`` -> the paper's :math:`a_p = a_{p0}^0`;
            ``"hsh"`` -> the orthonormal 1-D coefficients :math:`b_p`.
        dtype, device: working precision / device.

    Returns:
        ``(P + 1,)`` or ``(C, P + 1)``; see :func:`normal_exitance_to_isotropic`
        to place ``a_p`` into an isotropic coefficient vector.

    Example:
        >>> a = project_normal_exitance(lambda z: torch.full_like(z, 0.3 / math.pi), 3)
        >>> [round(float(x), 12) + 0.0 for x in a]  # Lambertian: a_0 = 2 rho_d
        [0.6, 0.0, 0.0, 0.0]
    """
    if not callable(brdf_1d):
        raise TypeError(f"`brdf_1d` must be callable as g(cos_theta_i), got {type(brdf_1d).__name__}")
    _check_dtype(dtype)
    P = _hb.check_order(order)
    if normalization not in ("helmholtz", "hsh"):
        raise ValueError(f"`normalization` must be 'helmholtz' or 'hsh', got {normalization!r}")
    nt = max(2 * (P + 1), 256) if n_theta is None else n_theta
    if isinstance(nt, bool) or not isinstance(nt, int) or nt < 1:
        raise ValueError(f"`n_theta` must be a positive integer, got {nt!r}")
    z, w = gauss_legendre(nt, 0.0, 1.0, dtype=dtype, device=device)
    g = _call_1d(brdf_1d, z)
    T = _theta_table(z, P) * (w * _TWO_PI)[:, None]  # (nt, P+1)
    bcoef = g.transpose(0, -1) @ T if g.dim() == 2 else g @ T
    if normalization == "hsh":
        return bcoef
    scale = torch.full((P + 1,), math.sqrt(math.pi), dtype=dtype, device=z.device)
    scale[0] = math.sqrt(_TWO_PI)
    return bcoef * scale


def _call_1d(brdf_1d, z):
    g = brdf_1d(z)
    if not isinstance(g, torch.Tensor):
        raise TypeError(f"`brdf_1d` must return a torch.Tensor, got {type(g).__name__}")
    if g.dim() == 0 or g.dim() > 2 or g.shape[0] != z.shape[0]:
        raise ValueError(f"`brdf_1d` called with ({z.shape[0]},) must return ({z.shape[0]},) or ({z.shape[0]}, C), got {tuple(g.shape)}")
    g = g.to(z.dtype)
    if validation_enabled() and not bool(torch.isfinite(g).all()):
        raise ValueError("`brdf_1d` returned NaN/Inf values at interior Gauss-Legendre nodes")
    return g


def normal_exitance_energy(
    brdf_1d: Callable[[torch.Tensor], torch.Tensor],
    n_theta: int = 256,
    dtype: torch.dtype = torch.float64,
    device: Optional[torch.device] = None,
) -> torch.Tensor:
    r""":math:`\int_{\Omega_i} g(\cos\theta_i)^2 d\omega_i = 2\pi\int_0^1 g^2 dz` (Gauss--Legendre).

    Denominator of the 1-D accuracy ``cumsum(b**2) / E`` with ``b`` from
    ``project_normal_exitance(..., normalization="hsh")``.

    Returns:
        ``()`` or ``(C,)``.

    Example:
        >>> round(float(normal_exitance_energy(lambda z: torch.ones_like(z))), 12) == round(2 * math.pi, 12)
        True
    """
    if not callable(brdf_1d):
        raise TypeError(f"`brdf_1d` must be callable as g(cos_theta_i), got {type(brdf_1d).__name__}")
    _check_dtype(dtype)
    z, w = gauss_legendre(n_theta, 0.0, 1.0, dtype=dtype, device=device)
    g = _call_1d(brdf_1d, z)
    ww = w * _TWO_PI
    return ((g * g) * (ww if g.dim() == 1 else ww[:, None])).sum(0)


def normal_exitance_to_isotropic(a: torch.Tensor, order: Optional[int] = None) -> torch.Tensor:
    r"""Place the single-index spectrum ``a_p`` at the isotropic columns ``(p, 0, 0)``.

    Args:
        a: ``(..., P' + 1)`` from ``project_normal_exitance(normalization="helmholtz")``.
        order: isotropic order ``P`` of the result (default ``P'``); entries with
            ``p > P`` are dropped, missing ones are zero.

    Returns:
        ``(..., K)`` coefficients of ``helmholtz_isotropic`` (``K = num_isotropic(P)``),
        zero except ``[..., index of (p, 0, 0)] = a_p``.

    Example:
        >>> normal_exitance_to_isotropic(torch.tensor([1.0, 2.0])).tolist()
        [1.0, 2.0, 0.0, 0.0]
    """
    check_tensor(a, "a", min_dims=1)
    P = a.shape[-1] - 1 if order is None else _hb.check_order(order)
    idx = _hb.isotropic_indices(P)
    sel = ((idx[:, 1] == 0) & (idx[:, 2] == 0)).nonzero().squeeze(-1)  # p-major: p = 0..P
    n = min(P + 1, a.shape[-1])
    out = a.new_zeros(*a.shape[:-1], idx.shape[0])
    out[..., sel[:n].to(a.device)] = a[..., :n]
    return out


# --------------------------------------------------------------------------
# least squares
# --------------------------------------------------------------------------
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
        ``coeffs`` (see table), or ``(coeffs, info)`` with ``info`` holding
        ``residuals`` (same shape as ``values``: ``y - A a``),
        ``rms`` (weighted RMS residual per fitted function, shape of ``coeffs``
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
    check_dirs(wi, "wi")
    check_dirs(wo, "wo")
    check_same([("wi", wi), ("wo", wo)])
    check_tensor(values, "values", min_dims=1)
    check_same([("wi", wi), ("values", values)])
    if wi.dim() not in (2, 3) or wo.dim() not in (2, 3):
        raise ValueError(f"`wi`/`wo` must be (N, 3) or (B, N, 3), got {tuple(wi.shape)} and {tuple(wo.shape)}")
    lead = broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1])])
    per_brdf = len(lead) == 2
    N = lead[-1]
    if values.dim() > 3:
        raise ValueError(f"`values` must be (N,), (N, C), (B, N) or (B, N, C), got {tuple(values.shape)}")
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
    Bn = y.shape[0]
    if isinstance(ridge, bool) or not isinstance(ridge, (int, float)) or not math.isfinite(ridge) or ridge < 0:
        raise ValueError(f"`ridge` must be a finite number >= 0, got {ridge!r}")
    if isinstance(ridge_growth, bool) or not isinstance(ridge_growth, (int, float)) or not math.isfinite(ridge_growth) or ridge_growth < 0:
        raise ValueError(f"`ridge_growth` must be a finite number >= 0, got {ridge_growth!r}")
    if method not in ("auto", "cholesky", "lstsq"):
        raise ValueError(f"`method` must be 'auto', 'cholesky' or 'lstsq', got {method!r}")
    if rcond is not None and (not isinstance(rcond, (int, float)) or isinstance(rcond, bool) or rcond < 0):
        raise ValueError(f"`rcond` must be a number >= 0 or None, got {rcond!r}")

    out_dtype = values.dtype
    f64 = torch.float64
    dev = values.device
    A = b.evaluate(wi.to(f64), wo.to(f64), P)  # (N, K) or (Bd, N, K)
    K = A.shape[-1]
    if A.dim() == 2:
        A = A[None]
    y64 = y.to(f64)
    if weights is not None:
        check_tensor(weights, "weights", min_dims=1)
        if weights.device != values.device:
            raise ValueError(f"`weights` is on {weights.device} but `values` is on {values.device}")
        if weights.dim() == 1 and weights.shape[0] == N:
            wt = weights.to(f64)[None]
        elif weights.dim() == 2 and weights.shape[1] == N and weights.shape[0] in (1, Bn):
            wt = weights.to(f64)
        else:
            raise ValueError(f"`weights` must be (N,) or (B, N) with N={N}, B={Bn}; got {tuple(weights.shape)}")
        if validation_enabled():
            if bool((wt < 0).any()):
                raise ValueError("`weights` must be non-negative")
            empty = (wt == 0).all(dim=-1)
            if bool(empty.any()):
                where = "" if wt.shape[0] == 1 else f" for batch entry {int(empty.nonzero()[0, 0])}"
                raise ValueError(f"`weights` are all zero{where}: no sample takes part in the fit")
    else:
        wt = None

    lam_diag = None
    if ridge > 0:
        L = b.function_orders(P).to(device=dev, dtype=f64)
        lam_diag = ridge * (1.0 + L) ** ridge_growth

    Aw = A if wt is None else A * wt[..., None]  # W A
    G = A.transpose(-1, -2) @ Aw  # (Bg, K, K), Bg in {1, Bd, Bw}
    rhs = Aw.transpose(-1, -2) @ y64 if Aw.shape[0] == Bn or Aw.shape[0] == 1 else None  # (Bn, K, C)
    if rhs is None:
        raise ValueError(f"direction/weight batch {Aw.shape[0]} does not match values batch {Bn}")
    if lam_diag is not None:
        G = G + torch.diag_embed(lam_diag).expand_as(G)

    coeffs = None
    solver = None
    cond = None
    if method in ("auto", "cholesky"):
        Lc, chol_info = torch.linalg.cholesky_ex(G)
        d = torch.diagonal(Lc, dim1=-2, dim2=-1).abs()
        ok = bool((chol_info == 0).all())
        if ok:
            cond = (d.max(-1).values / d.min(-1).values.clamp(min=1e-300)) ** 2
            ok = bool((cond < 1e12).all()) or method == "cholesky"
        if ok:
            coeffs = torch.cholesky_solve(rhs, Lc)  # (Bn, K, C)
            solver = "cholesky"
        elif method == "cholesky":
            raise ValueError("the normal equations are singular (Cholesky failed); use ridge > 0 or method='lstsq'")
    if coeffs is None:
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
            coeffs = torch.linalg.lstsq(Aa, ya, rcond=rc, driver="gelsd").solution
        else:
            coeffs = torch.linalg.pinv(Aa, rtol=rc) @ ya
        solver = "lstsq"
        sv = torch.linalg.svdvals(Aa)
        cond = (sv[..., 0] / sv[..., -1].clamp(min=1e-300)) ** 2 if Aa.shape[1] >= K else torch.full(
            sv.shape[:-1], float("inf"), dtype=f64, device=dev)
    # coeffs: (Bn, K, C)
    coeffs_out = coeffs.transpose(-1, -2)  # (Bn, C, K)
    if layout == "K":
        res = coeffs_out[0, 0]
    elif layout == "CK":
        res = coeffs_out[0]
    elif layout == "BK":
        res = coeffs_out[:, 0]
    else:
        res = coeffs_out
    res = res.to(out_dtype)
    if not return_info:
        return res
    pred = A @ coeffs  # (Bn, N, C)
    r = y64 - pred
    wr = torch.ones_like(r[..., :1]) if wt is None else wt[..., None].expand(r.shape[0], N, 1)
    rss = (wr * r * r).sum(1)  # (Bn, C)
    yss = (wr * y64 * y64).sum(1)
    wsum = wr.sum(1).clamp(min=1e-300)
    rms = torch.sqrt(rss / wsum)
    rel = torch.sqrt(rss / yss.clamp(min=1e-300))
    shape_fix = {
        "K": lambda t: t[0, 0],
        "CK": lambda t: t[0],
        "BK": lambda t: t[:, 0],
        "BCK": lambda t: t,
    }[layout]
    resid = r.reshape(values.shape) if layout != "CK" else r[0]
    info: Dict[str, object] = {
        "residuals": resid.to(out_dtype),
        "rms": shape_fix(rms).to(out_dtype),
        "relative_residual": shape_fix(rel).to(out_dtype),
        "condition": cond,
        "solver": solver,
        "num_samples": N,
        "num_functions": K,
    }
    return res, info


# --------------------------------------------------------------------------
# reconstruction / truncation / energy
# --------------------------------------------------------------------------
def reconstruct(
    coeffs: torch.Tensor,
    wi: torch.Tensor,
    wo: torch.Tensor,
    order: Optional[int] = None,
    basis: BasisLike = _DEFAULT,
    channels: bool = False,
) -> torch.Tensor:
    r"""Evaluate :math:`f(\omega_i, \omega_o) = \sum_k a_k B_k(\omega_i, \omega_o)`.

    Broadcasting is element-wise over leading dimensions:

    * ``channels=False``: ``coeffs`` ``(..., K)`` -> result ``(...)``, where the
      leading shapes of ``coeffs``, ``wi`` ``(..., 3)`` and ``wo`` ``(..., 3)``
      broadcast together. One BRDF at ``N`` points: ``(K,)`` with ``(N, 3)`` ->
      ``(N,)``; ``B`` BRDFs from a batched fit, ``(B, K)``, at per-BRDF points
      ``(B, N, 3)``: pass ``coeffs[:, None]``.
    * ``channels=True``: ``coeffs`` ``(..., C, K)`` -> ``(..., C)``; e.g. ``(C, K)``
      from :func:`project`/:func:`fit` with ``(N, 3)`` directions -> ``(N, C)``.

    Args:
        coeffs: coefficients in the column order of ``basis.evaluate``.
        wi, wo: local directions ``(..., 3)``.
        order: basis order; inferred from ``K`` when omitted (``ValueError`` when
            ``K`` matches no order).
        basis: basis name or object.
        channels: whether the second-to-last dimension of ``coeffs`` is a channel axis.

    Returns:
        Values in the dtype of ``coeffs``; differentiable with respect to
        ``coeffs`` and the directions.

    Example:
        >>> a = torch.zeros(20, dtype=torch.float64); a[0] = 2 * 0.5  # Lambertian rho = 0.5
        >>> w = torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64)
        >>> round(float(reconstruct(a, w, w)[0] * math.pi), 12)
        0.5
    """
    check_tensor(coeffs, "coeffs", min_dims=2 if channels else 1)
    check_dirs(wi, "wi")
    check_dirs(wo, "wo")
    check_same([("coeffs", coeffs), ("wi", wi), ("wo", wo)])
    b = _basis(basis)
    P = _order_of(b, coeffs.shape[-1], order)
    B = b.evaluate(wi, wo, P)  # (..., K)
    if channels:
        broadcast_shapes([("coeffs[..., C, K]", coeffs.shape[:-2]), ("wi/wo", B.shape[:-1])])
        return (B.unsqueeze(-2) * coeffs).sum(-1)
    broadcast_shapes([("coeffs[..., K]", coeffs.shape[:-1]), ("wi/wo", B.shape[:-1])])
    return (B * coeffs).sum(-1)


#: Alias of :func:`reconstruct`.
evaluate = reconstruct


def truncate(
    coeffs: torch.Tensor,
    order: int,
    basis: BasisLike = _DEFAULT,
    source_order: Optional[int] = None,
    zero_fill: bool = False,
) -> torch.Tensor:
    """Keep the functions up to ``order`` (those with ``basis.function_orders <= order``).

    Args:
        coeffs: ``(..., K)`` coefficients of order ``source_order`` (inferred from ``K``).
        order: target order ``P <= source_order``.
        basis: basis name or object.
        zero_fill: keep the shape ``(..., K)`` and zero the dropped functions
            instead of removing them.

    Returns:
        ``(..., K_P)`` in the column order of ``basis.evaluate(..., P)`` (the
        selected columns keep their relative order, which is how every
        registered basis lays out its lower orders), or ``(..., K)`` with
        ``zero_fill``.

    Example:
        >>> truncate(torch.arange(20.0), 1).tolist()
        [0.0, 1.0, 2.0, 3.0]
    """
    check_tensor(coeffs, "coeffs", min_dims=1)
    b = _basis(basis)
    Ps = _order_of(b, coeffs.shape[-1], source_order)
    P = b.check_order(order)
    if P > Ps:
        raise ValueError(f"`order` ({P}) must be <= the order of `coeffs` ({Ps})")
    keep = b.function_orders(Ps).to(coeffs.device) <= P
    if zero_fill:
        return coeffs * keep.to(coeffs.dtype)
    return coeffs[..., keep]


#: Relative excess of sum(a_k^2) over ``total_energy`` that :func:`energy_accuracy` tolerates
#: (quadrature / rounding error of the two estimates); beyond it the energy is wrong.
ENERGY_EXCESS_TOLERANCE = 1e-2


def energy_accuracy(
    coeffs: torch.Tensor,
    total_energy: Union[torch.Tensor, float],
    basis: BasisLike = _DEFAULT,
    order: Optional[int] = None,
) -> torch.Tensor:
    r"""Acc(P') for every truncation order ``P' = 0..P`` (paper Eq. 17).

    .. math:: \mathrm{Acc}(P') = \frac{\sum_{k:\,L_k \le P'} a_k^2}{\iint f^2}

    with :math:`L_k` = ``basis.function_orders``.

    Args:
        coeffs: ``(..., K)`` coefficients of order ``P`` (inferred from ``K``).
        total_energy: :math:`\iint f^2` (e.g. :func:`brdf_energy`), a positive
            number or a tensor broadcasting with ``coeffs.shape[:-1]``.
        basis: basis name or object.
        order: order of ``coeffs`` (checked against ``K``).

    Returns:
        ``(..., P + 1)``, non-decreasing in the last dimension; equals 1 at
        ``P`` for a function band-limited to ``P`` (Parseval).

    Raises:
        ValueError: ``total_energy <= 0``, or smaller than the energy the
            coefficients hold (``Acc(P) > 1 + ENERGY_EXCESS_TOLERANCE``):
            by Bessel's inequality that energy is not the function's.

    Example:
        >>> a = torch.zeros(4, dtype=torch.float64); a[0], a[2] = 3.0, 4.0
        >>> energy_accuracy(a, 25.0).tolist()
        [0.36, 1.0]
    """
    check_tensor(coeffs, "coeffs", min_dims=1)
    b = _basis(basis)
    P = _order_of(b, coeffs.shape[-1], order)
    if not isinstance(total_energy, torch.Tensor):
        if isinstance(total_energy, bool) or not isinstance(total_energy, (int, float)):
            raise TypeError(f"`total_energy` must be a number or a tensor, got {type(total_energy).__name__}")
        total_energy = torch.tensor(float(total_energy), dtype=coeffs.dtype, device=coeffs.device)
    check_tensor(total_energy, "total_energy")
    if validation_enabled() and bool((total_energy <= 0).any()):
        raise ValueError("`total_energy` must be > 0")
    broadcast_shapes([("coeffs[..., K]", coeffs.shape[:-1]), ("total_energy", total_energy.shape)])
    labels = b.function_orders(P).to(coeffs.device)
    onehot = (labels[:, None] == torch.arange(P + 1, device=coeffs.device)[None, :]).to(coeffs.dtype)  # (K, P+1)
    per_order = (coeffs * coeffs) @ onehot
    acc = torch.cumsum(per_order, dim=-1) / total_energy.to(coeffs.dtype).unsqueeze(-1)
    if validation_enabled() and bool((acc[..., -1] > 1.0 + ENERGY_EXCESS_TOLERANCE).any()):
        worst = float(acc[..., -1].max())
        raise ValueError(
            f"`total_energy` is below the energy the coefficients hold (Acc(P) = {worst:.6g} > 1): pass the "
            "full energy of the function (e.g. brdf_energy), not a truncated or mismatched one"
        )
    return acc


# --------------------------------------------------------------------------
# directional albedo
# --------------------------------------------------------------------------
_I0 = math.sqrt(_TWO_PI) * 0.5  # int over the hemisphere of Theta_0(z) z
_I1 = math.sqrt(_TWO_PI * 3.0) / 6.0  # int of Theta_1(z) z = sqrt(pi/6)


def _albedo_matrix(b: Basis, P: int, dtype, device):
    """(K, M) matrix S and a function wo -> (..., M) table T with albedo = (a @ S) . T(wo)."""
    if isinstance(b, HelmholtzIsotropic):
        idx = _hb.isotropic_indices(P).tolist()
        S = torch.zeros(len(idx), P + 1, dtype=torch.float64)
        I = [_I0, _I1] + [0.0] * max(0, P - 1)
        for k, (p, r, q) in enumerate(idx):
            if q != 0:
                continue
            n = 1.0 / math.sqrt(2.0 + 2.0 * (p == r))
            S[k, r] += n * I[p]
            S[k, p] += n * I[r]
        return S.to(dtype=dtype, device=device), lambda wo: _theta_table_dirs(wo, P)
    if isinstance(b, HelmholtzAnisotropic):
        idx = _hb.anisotropic_indices(P).tolist()
        S = torch.zeros(len(idx), (P + 1) ** 2, dtype=torch.float64)
        Iflat = {0: _I0, 2: _I1}  # flat indices of H_0^0, H_1^0
        for k, (p, q, r, s) in enumerate(idx):
            j, kk = p * p + p + q, r * r + r + s
            n = 1.0 / math.sqrt(2.0 + 2.0 * (j == kk))
            S[k, kk] += n * Iflat.get(j, 0.0)
            S[k, j] += n * Iflat.get(kk, 0.0)
        return S.to(dtype=dtype, device=device), lambda wo: _hb.hsh(wo, P)
    return None, None


def _theta_table_dirs(wo: torch.Tensor, P: int) -> torch.Tensor:
    H = _hb.hsh(wo, P)
    idx = torch.tensor([n * n + n for n in range(P + 1)], device=wo.device)
    return H.index_select(-1, idx)


def directional_albedo(
    coeffs: torch.Tensor,
    wo: torch.Tensor,
    order: Optional[int] = None,
    basis: BasisLike = _DEFAULT,
    channels: bool = False,
    n_theta: Optional[int] = None,
    n_phi: Optional[int] = None,
) -> torch.Tensor:
    r"""Directional albedo :math:`\rho(\omega_o) = \int_{\Omega_i} f(\omega_i, \omega_o)\cos\theta_i\,d\omega_i`.

    Closed form for the Helmholtz bases. Only ``q = 0`` functions survive the
    azimuthal integral, and with :math:`\Theta_n = \sqrt{(2n+1)/(2\pi)}\tilde P_n`,
    :math:`I_n = \int_\Omega \Theta_n(\cos\theta)\cos\theta\,d\omega
    = \sqrt{2\pi(2n+1)}\int_0^1 \tilde P_n(x)\,x\,dx` is
    :math:`\sqrt{2\pi}/2` (n = 0), :math:`\sqrt{\pi/6}` (n = 1), 0 (n >= 2). Hence

    .. math::
        \rho(\omega_o) = \sum_{p \ge r} a_{pr}^0 \frac{I_p\,\Theta_r(\cos\theta_o)
        + I_r\,\Theta_p(\cos\theta_o)}{\sqrt{2 + 2\delta_{pr}}}

    (isotropic basis; only ``p <= 1`` or ``r <= 1`` contribute), and the same
    with flat HSH indices ``j <= k`` and :math:`H_k(\omega_o)` for the anisotropic
    basis. Other bases: Gauss--Legendre x trapezoid quadrature over
    :math:`\omega_i` with ``n_theta = P + 2``, ``n_phi = 2P + 2`` by default
    (exact for polynomial-type bases of order ``P``).

    Args:
        coeffs: ``(..., K)`` or with ``channels=True`` ``(..., C, K)``.
        wo: ``(..., 3)`` outgoing local directions, broadcast element-wise with the
            leading dimensions of ``coeffs`` (as in :func:`reconstruct`).
        order: inferred from ``K`` when omitted.
        basis: basis name or object.
        channels: whether ``coeffs`` has a channel axis before ``K``.
        n_theta, n_phi: quadrature sizes for non-Helmholtz bases.

    Returns:
        ``(...)`` or ``(..., C)``; zero for ``wo`` below the horizon.

    Example:
        >>> a = torch.zeros(20, dtype=torch.float64); a[0] = 2 * 0.7  # Lambertian rho = 0.7
        >>> round(float(directional_albedo(a, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))), 12)
        0.7
    """
    check_tensor(coeffs, "coeffs", min_dims=2 if channels else 1)
    check_dirs(wo, "wo")
    check_same([("coeffs", coeffs), ("wo", wo)])
    b = _basis(basis)
    P = _order_of(b, coeffs.shape[-1], order)
    S, table = _albedo_matrix(b, P, coeffs.dtype, coeffs.device)
    if S is not None:
        T = table(wo)  # (..., M)
        cs = coeffs @ S  # (..., M) or (..., C, M)
        if channels:
            broadcast_shapes([("coeffs[..., C, K]", coeffs.shape[:-2]), ("wo", wo.shape[:-1])])
            return (cs * T.unsqueeze(-2)).sum(-1)
        broadcast_shapes([("coeffs[..., K]", coeffs.shape[:-1]), ("wo", wo.shape[:-1])])
        return (cs * T).sum(-1)
    nt = P + 2 if n_theta is None else n_theta
    npf = 2 * P + 2 if n_phi is None else n_phi
    d, w = direction_quadrature(nt, npf, "hemisphere", dtype=coeffs.dtype, device=coeffs.device)
    wo_e = wo.unsqueeze(-2)  # (..., 1, 3)
    Bv = b.evaluate(d, wo_e, P)  # (..., Q, K)
    kern = (Bv * (w * d[:, 2]).unsqueeze(-1)).sum(-2)  # (..., K)
    if channels:
        return (kern.unsqueeze(-2) * coeffs).sum(-1)
    return (kern * coeffs).sum(-1)
