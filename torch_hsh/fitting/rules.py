r"""Product rules over :math:`\Omega_i\times\Omega_o`: the fixed node sets and the sums of one rule.

Conventions of the rules
------------------------
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
* **Error estimate and refinement** (:func:`torch_hsh.fitting.convergence.adaptive`). It doubles ``n_phi`` while the
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
from dataclasses import dataclass
from typing import Iterator, List, Optional, Tuple

import torch

from ..bases import Basis
from ..quadrature import (
    direction_quadrature,
    gauss_legendre,
    isotropic_directions,
    isotropic_quadrature,
    monte_carlo_directions,
)
from .arguments import _call_brdf, _sizes

__all__ = ["RuleResult", "rule_sums"]

_TWO_PI = 2.0 * math.pi


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


@dataclass
class RuleResult:
    """Sums of one rule: coefficients ``a`` (``(K,)`` or ``(C, K)``), energy ``E`` (``()`` or ``(C,)``)."""

    a: Optional[torch.Tensor]
    E: Optional[torch.Tensor]
    n_theta: int
    n_phi: int
    evaluations: int
    scalar: bool = False


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
              want_a: bool, want_E: bool, dtype, device, chunk_size: int = 1 << 21) -> RuleResult:
    """Coefficients and/or energy of ``brdf`` by one product rule (see the module docstring).

    ``chunk_size`` bounds the memory: about that many direction pairs (samples) are evaluated per chunk.

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
        return _reduced(brdf, basis, P, z, wz, phi, M, D, use_lp, want_a, want_E, chunk_size)
    return _full(brdf, basis, P, z, wz, phi, M, D, use_lp, want_a, want_E, chunk_size)


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
        v = _call_brdf(brdf, wi, wo)
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
        v = _call_brdf(brdf, wi, wo)
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
