r"""Hemispherical harmonics (HSH) and the Helmholtz HSH-based BRDF bases.

Conventions (see ``docs/conventions.md`` and the shared math notes):

* Local frame: ``z`` is the surface normal; the hemisphere is ``z >= 0``.
* Associated Legendre functions **without** the Condon–Shortley phase, shifted
  to ``[0, 1]``: :math:`\tilde P_n^m(z) = P_n^m(2z - 1)`.
* :math:`H_n^m = \tilde N_n^{|m|} \tilde P_n^{|m|}(\cos\theta)\,\Phi_m(\phi)` with
  :math:`\Phi_m = \sqrt2\cos(m\phi)` (m > 0), 1 (m = 0),
  :math:`(-1)^m\sqrt2\sin(|m|\phi)` (m < 0).
* Flat HSH index ``n*n + n + m``.
* Isotropic Helmholtz functions use the orthonormal normalisation
  :math:`1/\sqrt{2 + 2\delta_{pr}}` for every q (erratum 1 of the math notes:
  the printed Eq. 21 has an extra :math:`\sqrt2` for q > 0).

Implementation: everything is evaluated from Cartesian components, without
trigonometric functions and without dividing by :math:`\sin\theta`:

.. math::
    H_n^{\pm m} = \hat R_n^m(2z-1)\; s^m\, \{\mathrm{Re},\mathrm{Im}\}(x + i y)^m,
    \qquad s = \sqrt{z / (1 + z)},

where :math:`\hat R_n^m` is a normalised polynomial obtained from a stable
three-term recurrence. The isotropic basis uses
:math:`\mathrm{Re}(c^q)`, :math:`c = (x_i - i y_i)(x_o + i y_o)`, evaluated by a
Chebyshev-like recurrence in :math:`\mathrm{Re}\,c = x_i x_o + y_i y_o` and
:math:`|c|^2`; it is polynomial in the direction components, so it is smooth
at the poles. Odd-m functions contain :math:`\sqrt z`, whose derivative is
infinite at the horizon ``z = 0``: within ``eps`` of the horizon (1e-12 in
float64, 1e-6 in float32) the derivative through that factor is cut to zero,
so gradients stay finite everywhere; values stay exact.

Performance layout: kernels build feature-major ``(features, N)`` tables so each
recurrence step and each column gather (``index_select`` along dim 0) touches
contiguous rows; the isotropic normalisation is folded into the gathered
tables (no separate scaling pass), and ``helmholtz_isotropic(w, w)`` with the
same tensor object computes the polar table once. Large batches are evaluated
in row chunks of about ``2**20`` output elements written into one
preallocated ``(N, K)`` output (temporaries stay cache-sized; no full-size
intermediates are allocated); the backward pass recomputes each chunk with
autograd (chunk-wise checkpointing; double backward is supported by a full
recomputation). Small batches, ``torch.func`` transforms, forward-mode AD and
recorded graphs (``torch.compile``, ``torch.export``, ``torch.jit.trace``, where
the row count is symbolic) use the plain autograd path. Outputs are always
contiguous ``(..., K)``.

Kernels (:func:`set_backend`, :func:`backend_status`): by default :func:`hsh` runs on the CPU
on the fused C kernel of :mod:`torch_hsh._native` (normalisation, polar recurrence, azimuth and
scale in one pass, written straight into the output; faster than the sphericart path at every
order, see docs/benchmarks.md), and on other devices (or where the C kernels are off) on
sphericart-torch's real-SH kernel where it is installed, through the identity
:math:`H_k(d) = \sqrt2\,\sigma_k\,Y_k(d')` with :math:`d' = (s'x, s'y, 2z - 1)`,
:math:`s' = 2\sqrt{z/(1+z)}` and :math:`\sigma_k = -1` for odd negative m; the Helmholtz bases
run on the CPU on the fused C kernels of :mod:`torch_hsh._native` (the whole isotropic basis per
block of rows; the anisotropic pair products over the HSH). The pure-torch recurrences described
above are the fallback and run inside ``torch.func`` transforms, forward-mode AD and double
backward; both paths agree to rounding. Eagerly the C kernels are called through
``torch.autograd.Function`` s; a recorded graph (``torch.compile``, ``torch.export``,
``torch.jit.trace``) holds them as the ``torch.library`` operators ``torch_hsh::hsh``,
``::isotropic``, ``::isotropic_core`` and ``::pair_products`` (with fake versions for the
tracer and their backward operators), so that the graph is whole at any number of rows and a
saved trace or exported program runs the same kernels (``import torch_hsh`` registers them).

Precision: float32 and float64 are computed as given. Half-precision inputs (float16,
bfloat16) are computed in float32 and returned in their dtype; under ``torch.autocast`` the
functions return float32 (as autocast's float32 operations do): the recurrences lose about
three digits in half precision, and float16 overflows at high orders.

Inputs are normalised inside the functions. **Directions strictly below the
horizon (z < 0) and zero-length vectors evaluate to 0, with zero gradient**:
the bases are supported on the upper hemisphere only, as a BRDF is.
"""
from __future__ import annotations

import math
import os
from functools import lru_cache
from typing import Callable, Dict, Optional, Tuple

import torch

from . import _native
from ._checks import (
    MAX_ANISOTROPIC_ORDER,
    broadcast_shapes,
    check_order,
    check_same,
    check_tensor,
)

__all__ = [
    "hsh",
    "helmholtz_isotropic",
    "helmholtz_isotropic_cosines",
    "helmholtz_anisotropic",
    "helmholtz_isotropic_world",
    "isotropic_indices",
    "anisotropic_indices",
    "hsh_index",
    "num_hsh",
    "num_isotropic",
    "num_anisotropic",
    "set_backend",
    "get_backend",
    "backend_status",
]


# --------------------------------------------------------------------------
# Counting and index tables
# --------------------------------------------------------------------------
def num_hsh(order: int) -> int:
    """Number of HSH functions up to ``order``: ``(order + 1)**2``."""
    order = check_order(order)
    return (order + 1) ** 2


def num_isotropic(order: int) -> int:
    """Number of isotropic Helmholtz functions up to ``order``: ``(P+1)(P+2)(P+3)/6``."""
    order = check_order(order)
    return (order + 1) * (order + 2) * (order + 3) // 6


def num_anisotropic(order: int) -> int:
    """Number of anisotropic Helmholtz functions up to ``order``: ``K(K+1)/2``, ``K=(P+1)**2``."""
    order = check_order(order, max_order=MAX_ANISOTROPIC_ORDER)
    k = (order + 1) ** 2
    return k * (k + 1) // 2


def hsh_index(n: int, m: int) -> int:
    """Flat index ``n*n + n + m`` of :math:`H_n^m`.

    Example:
        >>> hsh_index(2, -1)
        5
    """
    if not (0 <= abs(m) <= n):
        raise ValueError(f"need -n <= m <= n, got n={n}, m={m}")
    return n * n + n + m


@lru_cache(maxsize=None)
def _iso_list(order: int) -> Tuple[Tuple[int, int, int], ...]:
    return tuple((p, r, q) for p in range(order + 1) for r in range(p + 1) for q in range(r + 1))


@lru_cache(maxsize=None)
def _aniso_list(order: int) -> Tuple[Tuple[int, int], ...]:
    k = (order + 1) ** 2
    return tuple((j, kk) for j in range(k) for kk in range(j, k))


def isotropic_indices(order: int) -> torch.Tensor:
    """Index table of the isotropic Helmholtz basis.

    Returns:
        LongTensor of shape ``(K, 3)`` with rows ``(p, r, q)``, ``p >= r >= q >= 0``,
        ordered p-major (p, then r, then q ascending); ``K = (P+1)(P+2)(P+3)/6``.

    Example:
        >>> isotropic_indices(1).tolist()
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]]
    """
    order = check_order(order)
    return torch.tensor(_iso_list(order), dtype=torch.long).reshape(-1, 3)


def anisotropic_indices(order: int) -> torch.Tensor:
    """Index table of the anisotropic Helmholtz basis.

    Returns:
        LongTensor of shape ``(K(K+1)/2, 4)`` with rows ``(p, q, r, s)``: the pair of
        HSH :math:`H_p^q` (flat index j) and :math:`H_r^s` (flat index k) with
        ``j <= k``, ordered j-major then k ascending.

    Example:
        >>> anisotropic_indices(1)[:3].tolist()
        [[0, 0, 0, 0], [0, 0, 1, -1], [0, 0, 1, 0]]
    """
    order = check_order(order, max_order=MAX_ANISOTROPIC_ORDER)
    out = []
    for j, k in _aniso_list(order):
        p = int(math.isqrt(j))
        r = int(math.isqrt(k))
        out.append((p, j - p * p - p, r, k - r * r - r))
    return torch.tensor(out, dtype=torch.long).reshape(-1, 4)


# --------------------------------------------------------------------------
# Constants (float64 on the host, cached per device/dtype)
# --------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _polar_consts(order: int):
    """Recurrence constants of the normalised shifted Legendre table.

    Column layout of the table: blocks j = n - m = 0..P, block j holding m = 0..P-j.
    """
    P = order
    diag = []  # \hat R_m^m (constant)
    for m in range(P + 1):
        # sqrt((2m+1)/(2 pi)) * sqrt((2m)!) / m!
        diag.append(math.sqrt((2 * m + 1) / (2 * math.pi)) * math.exp(0.5 * math.lgamma(2 * m + 1) - math.lgamma(m + 1)))
    alpha = []  # per block j >= 1: coefficient of t * R_{n-1}
    beta = []  # per block j >= 2: coefficient of R_{n-2}
    for j in range(1, P + 1):
        a_j, b_j = [], []
        for m in range(P + 1 - j):
            n = m + j - 1  # computing R_{n+1}^m from R_n^m, R_{n-1}^m
            a_j.append(math.sqrt((2 * n + 1) * (2 * n + 3) / ((n + 1 - m) * (n + 1 + m))))
            if j >= 2:
                b_j.append(math.sqrt((2 * n + 3) / (2 * n - 1) * (n - m) * (n + m) / ((n + 1 - m) * (n + 1 + m))))
        alpha.append(a_j)
        beta.append(b_j)
    offsets = []
    off = 0
    for j in range(P + 1):
        offsets.append(off)
        off += P + 1 - j
    col = {}
    for j in range(P + 1):
        for m in range(P + 1 - j):
            col[(m + j, m)] = offsets[j] + m
    return diag, alpha, beta, col


@lru_cache(maxsize=None)
def _hsh_gather(order: int):
    """Columns of the polar table and of the azimuth table for each flat HSH index."""
    P = order
    _, _, _, col = _polar_consts(P)
    ridx, aidx = [], []
    for n in range(P + 1):
        for m in range(-n, n + 1):
            ridx.append(col[(n, abs(m))])
            aidx.append(m if m >= 0 else P - m)  # A_0..A_P, then B_1..B_P at P+1..2P
    az_scale = [1.0] + [math.sqrt(2.0)] * P + [(-1.0) ** m * math.sqrt(2.0) for m in range(1, P + 1)]
    return ridx, aidx, az_scale


def iso_pair_gather(order: int, col: Dict[Tuple[int, int], int]):
    """Gather table of the isotropic basis over a table of polar functions ``Theta_n^m``.

    ``col`` maps ``(n, m)`` to a column of a table ``X`` (``L = len(col)`` columns, plus a
    zero column ``L``) and of ``Y = [Theta G / sqrt2, Theta G]`` (``2L`` columns). Column
    ``k = (p, r, q)`` of the basis is ``X[i1] * Y[j1] + X[i2] * Y[j2]``: the normalisation
    ``1/sqrt(2 + 2 delta_pr)`` is folded into ``Y`` (``p == r``: one product, the second term
    hits the zero column). Used by the kernels here and by :mod:`torch_hsh.render.envmap`.
    """
    L = len(col)
    i1, j1, i2, j2 = [], [], [], []
    for p, r, q in _iso_list(order):
        a, b = col[(p, q)], col[(r, q)]
        if p == r:
            i1.append(a)
            j1.append(L + a)
            i2.append(L)
            j2.append(0)
        else:
            i1.append(a)
            j1.append(b)
            i2.append(b)
            j2.append(a)
    return i1, j1, i2, j2


@lru_cache(maxsize=None)
def _iso_gather(order: int):
    P = order
    _, _, _, col = _polar_consts(P)
    L = len(col)
    i1, j1, i2, j2 = iso_pair_gather(P, col)
    # m of every polar-table column (to attach the azimuthal factor G_q)
    qcol = [0] * L
    for (n, m), cc in col.items():
        qcol[cc] = m
    g_scale = [1.0] + [math.sqrt(2.0)] * P
    return i1, j1, i2, j2, qcol, g_scale


@lru_cache(maxsize=None)
def _aniso_gather(order: int):
    pairs = _aniso_list(order)
    j = [a for a, _ in pairs]
    k = [b for _, b in pairs]
    c = [0.5 if a == b else 1.0 / math.sqrt(2.0) for a, b in pairs]
    return j, k, c


_DEVICE_CACHE: Dict[tuple, torch.Tensor] = {}


def _const(key: tuple, values, device: torch.device, dtype: Optional[torch.dtype]) -> torch.Tensor:
    """Cached constant tensor on ``device``/``dtype``."""
    full = key + (str(device), dtype)
    t = _DEVICE_CACHE.get(full)
    if t is None:
        t = torch.tensor(values, dtype=dtype if dtype is not None else torch.long, device=device)
        # A tensor made inside a torch.func transform or a torch.compile trace is a wrapper
        # without storage: it must not outlive that call, so only plain tensors are cached.
        if not (_functorch_active() or _compiling()):
            _DEVICE_CACHE[full] = t
    return t


def _horizon_eps(dtype: torch.dtype) -> float:
    return 1e-12 if dtype == torch.float64 else 1e-6


# --------------------------------------------------------------------------
# Kernels (flat (N,) inputs, no validation)
# --------------------------------------------------------------------------
def _unit(d: torch.Tensor):
    """Normalise (N, 3) directions; returns x, y, z and the validity mask.

    Zero vectors stay zero (and are flagged invalid) with finite gradients.
    """
    n2 = (d * d).sum(-1)
    tiny = torch.finfo(d.dtype).tiny * 1e6
    ok = n2 > tiny
    inv = torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
    u = d * inv.unsqueeze(-1)
    x, y, z = u.unbind(-1)
    valid = ok & (z >= 0)
    return x, y, z, valid


def _safe_s(z: torch.Tensor) -> torch.Tensor:
    """s = sqrt(z / (1 + z)) for z >= 0, exact value, derivative cut within eps of z = 0."""
    eps = _horizon_eps(z.dtype)
    zp = z.clamp(min=0.0)
    live = torch.sqrt(zp.clamp(min=eps) / (1.0 + zp))
    frozen = torch.sqrt(zp.detach() / (1.0 + zp.detach()))
    return torch.where(zp > eps, live, frozen)


def _col(key: tuple, values, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """Cached constant as a ``(len, 1)`` column (broadcasts against ``(len, N)`` tables)."""
    return _const(key, values, device, dtype).unsqueeze(-1)


def _polar_table_t(z: torch.Tensor, order: int) -> torch.Tensor:
    """Feature-major normalised shifted-Legendre table, ``(L, N)``, L = (P+1)(P+2)/2.

    Row layout: blocks j = n - m = 0..P, block j holding m = 0..P-j. Every
    recurrence step works on contiguous rows of length N.
    """
    diag, alpha, beta, _ = _polar_consts(order)
    dev, dt = z.device, z.dtype
    t = (2.0 * z - 1.0).unsqueeze(0)
    d0 = _col(("diag", order), diag, dev, dt)
    blocks = [d0.expand(order + 1, z.shape[0])]
    if order >= 1:
        a1 = _col(("alpha", order, 1), alpha[0], dev, dt)
        blocks.append(t * (a1 * d0[:order]))
    for j in range(2, order + 1):
        mj = order + 1 - j
        aj = _col(("alpha", order, j), alpha[j - 1], dev, dt)
        bj = _col(("beta", order, j), beta[j - 1], dev, dt)
        blocks.append((aj * t) * blocks[j - 1][:mj] - bj * blocks[j - 2][:mj])
    return torch.cat(blocks, dim=0)


def _polar_table(z: torch.Tensor, order: int) -> torch.Tensor:
    """Normalised shifted-Legendre table, (N, L) with L = (P+1)(P+2)/2 (block layout)."""
    return _polar_table_t(z, order).t().contiguous()


def _azimuth_table_t(x, y, z, valid, order: int) -> torch.Tensor:
    """(2P+1, N): [s^m Re(x+iy)^m for m=0..P, s^m Im(x+iy)^m for m=1..P], masked and scaled."""
    P = order
    _, _, az_scale = _hsh_gather(P)
    mask = valid.to(z.dtype)
    re = [mask]
    im = []
    if P >= 1:
        s = _safe_s(z)
        u = s * x
        w = s * y
        cr, ci = u * mask, w * mask
        re.append(cr)
        im.append(ci)
        for _ in range(2, P + 1):
            cr, ci = cr * u - ci * w, cr * w + ci * u
            re.append(cr)
            im.append(ci)
    tab = torch.stack(re + im, dim=0)
    return tab * _col(("azs", P), az_scale, z.device, z.dtype)


def _hsh_flat_t(d: torch.Tensor, order: int) -> torch.Tensor:
    """HSH of flat (N, 3) directions, feature-major ``(K, N)``."""
    x, y, z, valid = _unit(d)
    R = _polar_table_t(z, order)
    A = _azimuth_table_t(x, y, z, valid, order)
    ridx, aidx, _ = _hsh_gather(order)
    ri = _const(("hsh_r", order), ridx, d.device, None)
    ai = _const(("hsh_a", order), aidx, d.device, None)
    return R.index_select(0, ri) * A.index_select(0, ai)


def _hsh_flat(d: torch.Tensor, order: int) -> torch.Tensor:
    """HSH of flat (N, 3) directions, ``(N, K)`` contiguous."""
    return _hsh_flat_t(d, order).t().contiguous()


def azimuthal_factors(w: torch.Tensor, a1: torch.Tensor, r1: torch.Tensor, order: int):
    r"""The azimuthal factors of the isotropic basis, ``[G_0, ..., G_P]`` (without the sqrt 2 of q > 0).

    :math:`G_q = w\,(s_i s_o)^q\,\mathrm{Re}(c^q)` with :math:`c = (x_i - i y_i)(x_o + i y_o)`, by the
    Chebyshev-like recurrence :math:`G_{q+1} = 2 a_1 G_q - r_1 G_{q-1}`, where
    ``a1 = s_i s_o Re(c)`` and ``r1 = (s_i s_o)^2 |c|^2``; ``w`` is a weight (the validity mask, or
    the shading of photometric stereo). Polynomial in its inputs, so smooth at the poles. The one
    implementation of this recurrence: the kernels here and :mod:`torch_hsh.ps.design` use it.
    """
    G = [w]
    if order >= 1:
        G.append(a1 * w)
        for _ in range(2, order + 1):
            G.append(2.0 * a1 * G[-1] - r1 * G[-2])
    return G


def _iso_kernel(zi, zo, a, rho, sio, valid, order: int, same: bool = False) -> torch.Tensor:
    """Isotropic Helmholtz basis from cos(theta_i), cos(theta_o), Re c, |c|^2 and s_i s_o.

    ``a = sin_i sin_o cos(dphi)``, ``rho = sin_i^2 sin_o^2``, ``sio = s_i s_o``;
    all ``(N,)``. Returns ``(N, K)`` contiguous.
    """
    return _iso_kernel_t(zi, zo, a, rho, sio, valid, order, same).t().contiguous()


def _iso_kernel_t(zi, zo, a, rho, sio, valid, order: int, same: bool = False) -> torch.Tensor:
    """Feature-major ``(K, N)`` version of :func:`_iso_kernel` (``same``: zi is zo)."""
    P = order
    i1, j1, i2, j2, qcol, g_scale = _iso_gather(P)
    dev, dt = zi.device, zi.dtype
    mask = valid.to(dt)
    # G_q = (s_i s_o)^q Re(c^q) (times sqrt 2 for q > 0)
    G = azimuthal_factors(mask, sio * a, sio * sio * rho, P) if P >= 1 else [mask]
    Gt = torch.stack(G, dim=0) * _col(("gsc", P), g_scale, dev, dt)
    Ri = _polar_table_t(zi, P)
    Ro = (Ri if same else _polar_table_t(zo, P)) * Gt.index_select(0, _const(("qcol", P), qcol, dev, None))
    X = torch.cat([Ri, Ri.new_zeros(1, Ri.shape[1])], dim=0)
    Y = torch.cat([Ro * (1.0 / math.sqrt(2.0)), Ro], dim=0)
    out = X.index_select(0, _const(("iso_i1", P), i1, dev, None)) * Y.index_select(
        0, _const(("iso_j1", P), j1, dev, None)
    )
    return out.addcmul(
        X.index_select(0, _const(("iso_i2", P), i2, dev, None)),
        Y.index_select(0, _const(("iso_j2", P), j2, dev, None)),
    )


def _flat(x: torch.Tensor, lead, tail=(3,)) -> torch.Tensor:
    """``x`` broadcast to ``(*lead, *tail)`` and flattened to ``(N, *tail)``, without a view where ``x`` already
    has that shape: a view of a tensor that requires grad costs an autograd node forward and backward (several
    microseconds per call at small batches)."""
    tail, tracing = tuple(tail), torch.jit.is_tracing()  # a trace records the shape ops, for any rank
    if tracing or tuple(x.shape) != (*lead, *tail):
        x = x.expand(*lead, *tail)
    return x if len(lead) == 1 and not tracing else x.reshape(-1, *tail)


def _shaped(out: torch.Tensor, lead, K: int) -> torch.Tensor:
    """``out (N, K)`` as ``(*lead, K)``, without a view where it already is."""
    return out if out.shape[:-1] == lead and not torch.jit.is_tracing() else out.reshape(*lead, K)


def _broadcast_pair(wi: torch.Tensor, wo: torch.Tensor):
    # equal shapes are the common case, without torch.broadcast_shapes (tens of microseconds)
    lead = wi.shape[:-1] if wi.shape == wo.shape else broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1])])
    return lead, _flat(wi, lead), _flat(wo, lead)


def _iso_dirs(wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
    """Isotropic basis of flat local directions (N, 3); ``wo is wi`` shares the polar table."""
    same = wo is wi
    xi, yi, zi, vi = _unit(wi)
    if same:
        xo, yo, zo, vo = xi, yi, zi, vi
    else:
        xo, yo, zo, vo = _unit(wo)
    a = xi * xo + yi * yo
    rho = (xi * xi + yi * yi) * (xo * xo + yo * yo)
    if order >= 1:
        si = _safe_s(zi)
        sio = si * si if same else si * _safe_s(zo)
    else:
        sio = zi
    return _iso_kernel_t(zi, zo, a, rho, sio, vi & vo, order, same=same)


_Geom = Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _iso_cosines_geom(zi: torch.Tensor, zo: torch.Tensor, cd: torch.Tensor) -> _Geom:
    """(zi, zo, a, rho, sio, valid) of the isotropic triple (flat (N,) inputs)."""
    valid = (zi >= 0) & (zo >= 0) & (zi <= 1) & (zo <= 1)
    zi_c = zi.clamp(0.0, 1.0)
    zo_c = zo.clamp(0.0, 1.0)
    rho = (1.0 - zi_c * zi_c) * (1.0 - zo_c * zo_c)
    eps = _horizon_eps(zi.dtype)
    sin_prod = torch.where(rho > eps, torch.sqrt(rho.clamp(min=eps)), torch.sqrt(rho.detach()))
    a = sin_prod * cd.clamp(-1.0, 1.0)
    sio = _safe_s(zi_c) * _safe_s(zo_c)
    return zi_c, zo_c, a, rho, sio, valid


def _iso_world_geom(wi: torch.Tensor, wo: torch.Tensor, nrm: torch.Tensor) -> _Geom:
    """(zi, zo, a, rho, sio, valid) of world-space directions and normals (flat (N, 3) inputs)."""
    wi = _normalize3(wi)
    wo = _normalize3(wo)
    nrm = _normalize3(nrm)
    zi = (wi * nrm).sum(-1)
    zo = (wo * nrm).sum(-1)
    valid = (zi >= 0) & (zo >= 0) & ((nrm * nrm).sum(-1) > 0.5) & ((wi * wi).sum(-1) > 0.5) & ((wo * wo).sum(-1) > 0.5)
    zi_c = zi.clamp(0.0, 1.0)
    zo_c = zo.clamp(0.0, 1.0)
    a = (wi * wo).sum(-1) - zi * zo
    rho = (1.0 - zi_c * zi_c) * (1.0 - zo_c * zo_c)
    sio = _safe_s(zi_c) * _safe_s(zo_c)
    return zi_c, zo_c, a, rho, sio, valid


def _aniso_flat(wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
    Hi = _hsh_flat_t(wi, order)
    Ho = Hi if wo is wi else _hsh_flat_t(wo, order)
    j, k, c = _aniso_gather(order)
    dev, dt = Hi.device, Hi.dtype
    jt = _const(("an_j", order), j, dev, None)
    kt = _const(("an_k", order), k, dev, None)
    out = Hi.index_select(0, jt) * Ho.index_select(0, kt)
    out = out.addcmul(Hi.index_select(0, kt), Ho.index_select(0, jt))
    return out.mul_(_col(("an_c", order), c, dev, dt))


# --------------------------------------------------------------------------
# Row-chunked evaluation (cache-sized blocks, one (N, K) allocation)
# --------------------------------------------------------------------------
#: Target number of output elements per row chunk: keeps every temporary of a
#: kernel in cache and avoids allocating several full (N, K) intermediates.
_CHUNK_ELEMS = 1 << 20


def _functorch_active() -> bool:
    try:
        return bool(torch._C._are_functorch_transforms_active())
    except AttributeError:  # pragma: no cover - older torch
        return False


class _RowChunked(torch.autograd.Function):
    """Evaluate a row-wise kernel ``fn`` chunk by chunk into one preallocated output.

    Backward recomputes each chunk with autograd (chunk-wise checkpointing), so
    no graph over full-size intermediates is kept. Under ``create_graph`` the
    backward is itself differentiable (full recomputation from the saved inputs).
    """

    @staticmethod
    def forward(ctx, fn, K, rows, *inputs):
        n = inputs[0].shape[0]
        out = inputs[0].new_empty((n, K))
        for s in range(0, n, rows):
            out[s : s + rows] = fn(*[x[s : s + rows] for x in inputs])
        ctx.fn, ctx.rows = fn, rows
        ctx.save_for_backward(*inputs)
        return out

    @staticmethod
    def backward(ctx, gout):
        inputs = ctx.saved_tensors
        needs = ctx.needs_input_grad[3:]
        fn, rows = ctx.fn, ctx.rows
        want = [i for i, nd in enumerate(needs) if nd]
        grads = [None] * len(inputs)
        if not want:
            return (None, None, None, *grads)
        if torch.is_grad_enabled():  # create_graph=True: keep the backward differentiable
            # aliases: an input may be another input, or computed from one (the caller's own tensors reach here)
            xs = [x if needs[i] else x.detach() for i, x in enumerate(_aliases(inputs))]
            y = fn(*xs)
            if not y.requires_grad:  # a kernel constant in its inputs (order 0): zero gradients
                return (None, None, None, *[torch.zeros_like(x) if i in want else None for i, x in enumerate(inputs)])
            gs = torch.autograd.grad(y, [xs[i] for i in want], gout, create_graph=True, allow_unused=True)
            for i, g in zip(want, gs):
                grads[i] = torch.zeros_like(inputs[i]) if g is None else g
            return (None, None, None, *grads)
        for i in want:
            grads[i] = torch.zeros_like(inputs[i])
        for s in range(0, inputs[0].shape[0], rows):
            with torch.enable_grad():
                xs = [x[s : s + rows].detach().requires_grad_(needs[i]) for i, x in enumerate(inputs)]
                y = fn(*xs)
                if not y.requires_grad:  # a kernel constant in its inputs (order 0): the gradient stays zero
                    continue
                gs = torch.autograd.grad(y, [xs[i] for i in want], gout[s : s + rows], allow_unused=True)
            for i, g in zip(want, gs):
                if g is not None:
                    grads[i][s : s + rows] = g
        return (None, None, None, *grads)


def _run_rows(fn, K: int, *inputs: torch.Tensor) -> torch.Tensor:
    """``fn(*inputs)`` for row-aligned inputs ``(N, ...)``, chunked over rows when large.

    ``fn`` returns a feature-major ``(K, n)`` block; the result is ``(N, K)`` contiguous.
    """
    rows = max(1, _CHUNK_ELEMS // max(K, 1))
    # unchunked: where the rows are symbolic (a graph; a Python loop over them would be unrolled or break it), or
    # where ``_RowChunked`` (backward only) cannot run (torch.func transforms, forward-mode AD)
    if _graph() or _functorch_active() or _forward_ad() or inputs[0].shape[0] <= rows:
        return fn(*inputs).t().contiguous()
    return _RowChunked.apply(lambda *xs: fn(*xs).t(), K, rows, *inputs)


def _iso_from_geometry(geom: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], _Geom], inputs: Tuple[torch.Tensor, torch.Tensor, torch.Tensor], order: int, K: int) -> torch.Tensor:
    """The isotropic basis ``(N, K)`` of flat row-aligned ``inputs``, through ``geom(*inputs)`` (a :data:`_Geom`):
    the fused C kernel eagerly, its ``torch.library`` operator in a recorded graph, else the pure-torch kernel
    in row chunks."""
    if _native_ok(inputs[0]):
        return _IsoCore.apply(*geom(*inputs), order)
    if _graph_ok(inputs[0]):
        return _OPS["isotropic_core"](*geom(*inputs), order)
    return _run_rows(lambda a, b, c: _iso_kernel_t(*geom(a, b, c), order), K, *inputs)


def _check_group(named, dirs: bool = True, defer_values: bool = False) -> bool:
    """Type checks, then device/dtype agreement, then per-tensor shape/value checks.

    ``defer_values``: where the fused C kernels will run (:func:`_native_ok`), skip the scan for
    non-finite values; the kernel flags them, and :func:`_recheck` then runs the full check. Returns
    whether the scan was deferred. (The scan is a torch reduction over the inputs: a pass over them,
    after which torch's OpenMP workers spin beside the kernel's threads.)
    """
    for nm, t in named:
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"`{nm}` must be a torch.Tensor, got {type(t).__name__}")
    check_same(named)
    deferred = defer_values and _native_ok(named[0][1])
    for nm, t in named:
        check_tensor(t, nm, last_dim=3 if dirs else None, min_dims=1 if dirs else 0, allow_nonfinite=deferred)
    return deferred


#: Half-precision dtypes: computed in float32 (see :func:`_in_float32`).
HALF_DTYPES = (torch.float16, torch.bfloat16)


def autocast_enabled(device_type: str) -> bool:
    """Whether ``torch.autocast`` is on for ``device_type`` (``"cpu"``, ``"cuda"``, ...)."""
    try:
        return bool(torch.is_autocast_enabled(device_type))
    except TypeError:  # pragma: no cover - torch < 2.4: no device argument
        return bool(torch.is_autocast_cpu_enabled() if device_type == "cpu" else torch.is_autocast_enabled())


def _half(*xs) -> bool:
    for x in xs:
        if getattr(x, "dtype", None) in HALF_DTYPES:
            return True
    return False


def _in_float32(fn, xs, *args) -> torch.Tensor:
    """``fn(*xs, *args)`` with the half-precision tensors of ``xs`` in float32; the result in the dtype that torch's
    type promotion gives ``xs`` (float16 for float16 inputs), or, under ``torch.autocast``, in float32 at least
    (as autocast's float32 operations). The recurrences and products of the bases lose about three digits
    against float32 when evaluated in float16 or bfloat16, and float16 overflows at high orders."""
    out = xs[0].dtype
    for x in xs[1:]:
        out = torch.promote_types(out, x.dtype)
    if autocast_enabled(xs[0].device.type):
        out = torch.promote_types(out, torch.float32)
    ys = [x.float() if x.dtype in HALF_DTYPES else x for x in xs]
    if len(xs) == 2 and xs[0] is xs[1]:  # one direction set stays one tensor (``wi is wo``)
        ys[1] = ys[0]
    return fn(*ys, *args).to(out)


def _recheck(flagged: bool, named) -> None:
    """The deferred finiteness check, where a C kernel saw a non-finite input (raises ValueError)."""
    if flagged:
        for nm, t in named:
            check_tensor(t, nm)


# --------------------------------------------------------------------------
# Fast paths: sphericart for the HSH, fused C kernels for the isotropic basis
# --------------------------------------------------------------------------
#: ``"auto"``: the fused C kernels (:mod:`torch_hsh._native`) for :func:`hsh` and the isotropic
#: basis on the CPU where a C compiler is found, sphericart-torch for :func:`hsh` elsewhere where
#: it is installed; ``"torch"``: the pure-torch recurrences above everywhere.
_BACKEND = {"name": os.environ.get("TORCH_HSH_BACKEND", "auto").strip().lower() or "auto"}
_BACKENDS = ("auto", "torch")
_SPHERICART: Dict[str, object] = {}


def set_backend(name: str) -> None:
    """Choose the kernels behind :func:`hsh` and the Helmholtz bases.

    Args:
        name: ``"auto"`` (default; also the environment variable ``TORCH_HSH_BACKEND``):
            :func:`hsh` and the isotropic basis through fused C kernels on the CPU where a
            C compiler is found (compiled once, cached; ``TORCH_HSH_NATIVE=0`` switches them
            off), and :func:`hsh` on other devices (or without the C kernels) through
            sphericart-torch's spherical-harmonics kernel where that package is installed
            (``pip install torch-hsh[fast]``). Everything else, and every
            call inside ``torch.func`` transforms or forward-mode AD, runs the pure-torch
            kernels; ``torch.compile``, ``torch.export`` and ``torch.jit.trace`` record the C
            kernels as ``torch.library`` operators. ``"torch"``: the pure-torch kernels everywhere.

    The paths agree to rounding (float64 to 1e-12); :func:`backend_status` says which
    one runs.

    Example:
        >>> import torch_hsh
        >>> torch_hsh.set_backend("torch")
        >>> torch_hsh.get_backend()
        'torch'
        >>> torch_hsh.set_backend("auto")
    """
    if not isinstance(name, str) or name.strip().lower() not in _BACKENDS:
        raise ValueError(f"`name` must be one of {_BACKENDS}, got {name!r}")
    _BACKEND["name"] = name.strip().lower()


def get_backend() -> str:
    """The backend chosen with :func:`set_backend` (``"auto"`` or ``"torch"``)."""
    return _BACKEND["name"]


def _sphericart_module():
    """``sphericart.torch`` or None (the import is tried once)."""
    if "mod" not in _SPHERICART:
        try:
            import sphericart.torch as sct

            _SPHERICART["mod"], _SPHERICART["error"] = sct, None
        except Exception as exc:  # not installed, or built for another torch
            _SPHERICART["mod"], _SPHERICART["error"] = None, f"{type(exc).__name__}: {exc}"
    return _SPHERICART["mod"]


def backend_status() -> Dict[str, Optional[str]]:
    """Which kernels run under the current backend, and why a fast path is off.

    Returns:
        dict with ``backend``, ``hsh`` (``"sphericart"`` or ``"torch"``: the HSH kernel on other devices
        than the CPU), ``hsh_cpu`` (``"native"``, ``"sphericart"`` or ``"torch"``), ``isotropic_cpu``
        (``"native"`` or ``"torch"``), ``native_threads`` (``"openmp"``: the C kernels split their rows over
        torch's own OpenMP threads; ``"pool (why)"``: over a Python thread pool; None: no C kernels),
        ``sphericart_error`` and ``native_error``.

    Example:
        >>> import torch_hsh
        >>> sorted(torch_hsh.backend_status())
        ['backend', 'hsh', 'hsh_cpu', 'isotropic_cpu', 'native_error', 'native_threads', 'sphericart_error']
    """
    auto = _BACKEND["name"] == "auto"
    sct = _sphericart_module() if auto else None
    lib = _native.library() if auto else None
    hsh_other = "sphericart" if sct is not None else "torch"
    return {
        "backend": _BACKEND["name"],
        "hsh": hsh_other,
        "hsh_cpu": "native" if lib is not None else hsh_other,
        "isotropic_cpu": "native" if lib is not None else "torch",
        "sphericart_error": _SPHERICART.get("error") if auto else None,  # type: ignore[dict-item]
        "native_error": _native.native_status()["error"] if auto else None,
        "native_threads": _native.native_status()["threads"] if lib is not None else None,
    }


_is_compiling = getattr(getattr(torch, "compiler", None), "is_compiling", None) or (lambda: False)


def _compiling() -> bool:
    """Inside a torch.compile or torch.export trace (strict or not; the tensors have no data)."""
    return _is_compiling()


def _forward_ad() -> bool:
    """Inside a forward-mode AD level (``torch.autograd.forward_ad.dual_level``)."""
    return getattr(torch.autograd.forward_ad, "_current_level", -1) >= 0


def _graph() -> bool:
    """A graph is being recorded: torch.compile, torch.export or torch.jit.trace (the row count is symbolic, or
    the recorded call must be one that the graph can hold)."""
    return _is_compiling() or torch.jit.is_tracing()


def _native_ok(t: torch.Tensor) -> bool:
    """The fused C kernels apply through their eager ``autograd.Function`` s: CPU float tensors outside functorch,
    forward-mode AD and graph recording (see :func:`_graph_ok`)."""
    return (
        _BACKEND["name"] == "auto"
        and t.device.type == "cpu"
        and t.dtype in (torch.float32, torch.float64)
        and not _functorch_active()
        and not _graph()
        and not _forward_ad()
        and _native.library() is not None
    )


def _graph_ok(t: torch.Tensor) -> bool:
    """The fused C kernels apply as the ``torch.library`` operators :data:`_OPS`: as :func:`_native_ok`, while a
    graph is being recorded."""
    return (
        _BACKEND["name"] == "auto"
        and _OPS is not None
        and _graph()
        and t.device.type == "cpu"
        and t.dtype in (torch.float32, torch.float64)
        and not _functorch_active()
        and not _forward_ad()
        and _native.available()
    )


def _suffix(dt: torch.dtype) -> str:
    return "f32" if dt == torch.float32 else "f64"


@lru_cache(maxsize=None)
def _native_iso_spec(order: int):
    """Recurrence and output tables of ``kernels.c``'s iso_core (see its header comment)."""
    diag, alpha, beta, col = _polar_consts(order)
    L = len(col)
    A, B, c1, c2 = [0.0] * L, [0.0] * L, [-1] * L, [-1] * L
    for (n, m), c in col.items():
        j = n - m
        if j == 0:
            A[c] = diag[m]
            continue
        A[c], c1[c] = alpha[j - 1][m], col[(n - 1, m)]
        if j >= 2:
            B[c], c2[c] = beta[j - 1][m], col[(n - 2, m)]
    ka, kb, kq, kc = [], [], [], []
    for p, r, q in _iso_list(order):
        ka.append(col[(p, q)])
        kb.append(col[(r, q)])
        kq.append(q)
        kc.append((1.0 if q == 0 else math.sqrt(2.0)) * (0.5 if p == r else 1.0 / math.sqrt(2.0)))
    return L, A, B, c1, c2, ka, kb, kq, kc


def _native_iso_tables(order: int, dt: torch.dtype):
    L, A, B, c1, c2, ka, kb, kq, kc = _native_iso_spec(order)
    cpu = torch.device("cpu")
    i32 = torch.int32
    return (
        L,
        _const(("nat_A", order), A, cpu, dt),
        _const(("nat_B", order), B, cpu, dt),
        _const(("nat_c1", order), c1, cpu, i32),
        _const(("nat_c2", order), c2, cpu, i32),
        len(ka),
        _const(("nat_ka", order), ka, cpu, i32),
        _const(("nat_kb", order), kb, cpu, i32),
        _const(("nat_kq", order), kq, cpu, i32),
        _const(("nat_kc", order), kc, cpu, dt),
    )


#: The kernels' table arguments (raw pointers) per (kernel, order, dtype). The tables they point to are
#: cached constants that live as long as the process (``_DEVICE_CACHE``); only the native paths, which
#: run outside torch.func and torch.compile, fill this.
_NATIVE_ARGS: Dict[tuple, tuple] = {}


def _iso_core_args(order: int, dt: torch.dtype):
    key = ("iso", order, dt)
    args = _NATIVE_ARGS.get(key)
    if args is None:
        L, A, B, c1, c2, K, ka, kb, kq, kc = _native_iso_tables(order, dt)
        p = _native.ptr
        args = (K, (L, p(A), p(B), p(c1), p(c2), order, K, p(ka), p(kb), p(kq), p(kc)))
        _remember_args(key, args)
    return args


def _remember_args(key: tuple, args: tuple) -> None:
    if not (_functorch_active() or _compiling()):  # only then are the tables cached (see _const)
        _NATIVE_ARGS[key] = args


def _aliases(xs):
    """Views of the saved inputs for a create_graph backward: ``autograd.grad`` with respect to them follows only
    the paths through each view, not the paths between the inputs (``wi is wo``, or ``sio`` computed from
    ``cos_i``), which would count the first derivative twice; the views keep the graph to the inputs."""
    return tuple(x.view_as(x) for x in xs)


def _iso_core_fwd(zi, zo, a, rho, sio, valid, order: int) -> torch.Tensor:
    """``kernels.c`` iso_core: (zi, zo, a, rho, sio, valid) -> (N, K); see :func:`_iso_kernel_t`."""
    ins = [x.contiguous() for x in (zi, zo, a, rho, sio)]
    v = valid.to(torch.uint8).contiguous()
    K, tab = _iso_core_args(order, zi.dtype)
    out = zi.new_empty((zi.shape[0], K))
    fn = getattr(_native.library(), "iso_core_fwd_" + _suffix(zi.dtype))
    _native.parallel_rows(fn, zi.shape[0], *[_native.ptr(x) for x in ins], _native.ptr(v), *tab, _native.ptr(out))
    return out


def _iso_core_bwd(zi, zo, a, rho, sio, valid, gout, order: int):
    """The gradients of :func:`_iso_core_fwd` with respect to (zi, zo, a, rho, sio), from ``gout (N, K)``."""
    ins = [x.contiguous() for x in (zi, zo, a, rho, sio)]
    v = valid.to(torch.uint8).contiguous()
    g = gout if gout.stride(-1) in (0, 1) else gout.contiguous()  # expanded gradients stay unmaterialised
    outs = [torch.empty_like(x) for x in ins]
    _, tab = _iso_core_args(order, g.dtype)
    fn = getattr(_native.library(), "iso_core_bwd_" + _suffix(g.dtype))
    _native.parallel_rows(fn, g.shape[0], *[_native.ptr(x) for x in ins], _native.ptr(v), *tab,
                          _native.ptr(g), g.stride(0), g.stride(1), *[_native.ptr(o) for o in outs])
    return outs


class _IsoCore(torch.autograd.Function):
    """:func:`_iso_core_fwd` with its backward (eager calls; see :func:`_route`)."""

    @staticmethod
    def forward(ctx, zi, zo, a, rho, sio, valid, order):
        out = _iso_core_fwd(zi, zo, a, rho, sio, valid, order)
        ctx.order = order
        ctx.save_for_backward(zi, zo, a, rho, sio, valid)
        return out

    @staticmethod
    def backward(ctx, gout):
        saved = ctx.saved_tensors
        xs, valid = saved[:5], saved[5]
        need = [i for i in range(5) if ctx.needs_input_grad[i]]
        grads = [None] * 7
        if not need:
            return tuple(grads)
        if torch.is_grad_enabled():  # create_graph: a differentiable backward through the torch kernel
            xs = _aliases(xs)
            y = _iso_kernel_t(*xs, valid, ctx.order).t()
            if not y.requires_grad:  # order 0: a constant
                return tuple(torch.zeros_like(xs[i]) if i in need else None for i in range(7))
            gs = torch.autograd.grad(y, [xs[i] for i in need], gout, create_graph=True, allow_unused=True)
            for i, g in zip(need, gs):
                grads[i] = torch.zeros_like(xs[i]) if g is None else g
            return tuple(grads)
        outs = _iso_core_bwd(*xs, valid, gout, ctx.order)
        for i in need:
            grads[i] = outs[i]
        return tuple(grads)


#: Orders at which the fused isotropic kernel is generated straight-line code (tools/generate_iso_kernels.py).
_ISO_SMALL_ORDERS = frozenset(_native.ISO_SMALL_ORDERS)


def _iso_geom_torch(wi: torch.Tensor, wo: torch.Tensor):
    """(zi, zo, a, rho, sio, valid) of flat local direction pairs (pure torch, as :func:`_iso_dirs`)."""
    xi, yi, zi, vi = _unit(wi)
    xo, yo, zo, vo = _unit(wo)
    a = xi * xo + yi * yo
    rho = (xi * xi + yi * yi) * (xo * xo + yo * yo)
    return zi, zo, a, rho, _safe_s(zi) * _safe_s(zo), vi & vo


def _iso_dirs_kernel(direction: str, order: int, dt: torch.dtype):
    """``(fn, head, tables)`` of the fused isotropic kernel (``direction``: ``"fwd"`` / ``"bwd"``): the
    kernel is called as ``fn(r0, r1, *head, wi, wo, tiny, eps, *tables, ...)``. At the orders of
    ``_ISO_SMALL_ORDERS`` it is the straight-line code with the tables built in (kernels_iso_small.h)."""
    lib, sfx = _native.library(), _suffix(dt)
    if order in _ISO_SMALL_ORDERS:
        return getattr(lib, f"iso_small_{direction}_{sfx}"), (order,), ()
    return getattr(lib, f"iso_dirs_{direction}_{sfx}"), (), _iso_core_args(order, dt)[1]


def _iso_dirs_native(wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
    """The fused forward of :class:`_IsoDirs` (no autograd): flat ``(N, 3), (N, 3) -> (N, K)``."""
    wi_c, wo_c = wi.contiguous(), wo.contiguous()
    n, dt = wi.shape[0], wi.dtype
    out = wi.new_empty((n, num_isotropic(order)))
    fn, head, tab = _iso_dirs_kernel("fwd", order, dt)
    bad = _native.parallel_rows(fn, n, *head, _native.ptr(wi_c), _native.ptr(wo_c), torch.finfo(dt).tiny * 1e6,
                                _horizon_eps(dt), *tab, _native.ptr(out))
    _recheck(bad, [("wi", wi), ("wo", wo)])
    return out


def _needs_grad(*xs: torch.Tensor) -> bool:
    """Whether autograd would record an operation on ``xs`` (else a kernel skips ``Function.apply``). Forward-mode
    AD and torch.jit.trace do not reach the eager kernels (:func:`_native_ok`): a bare ctypes call would leave
    no tangent, or an empty tensor in a trace."""
    return torch.is_grad_enabled() and any(x.requires_grad for x in xs)


class _IsoDirs(torch.autograd.Function):
    """``kernels.c`` iso_dirs: the isotropic basis of two flat (N, 3) direction sets, geometry fused."""

    @staticmethod
    def forward(ctx, wi, wo, order):
        out = _iso_dirs_native(wi, wo, order)
        ctx.order = order
        ctx.save_for_backward(wi, wo)
        return out

    @staticmethod
    def backward(ctx, gout):
        wi, wo = ctx.saved_tensors
        if not (ctx.needs_input_grad[0] or ctx.needs_input_grad[1]):
            return None, None, None
        if torch.is_grad_enabled():  # create_graph: a differentiable backward through the torch kernel
            wi, wo = _aliases((wi, wo))
            y = _iso_kernel_t(*_iso_geom_torch(wi, wo), ctx.order).t()
            if not y.requires_grad:  # order 0: a constant
                return tuple(torch.zeros_like(w) if nd else None for w, nd in zip((wi, wo), ctx.needs_input_grad[:2])) + (
                    None,)
            need = [w for w, nd in zip((wi, wo), ctx.needs_input_grad[:2]) if nd]
            gs = iter(torch.autograd.grad(y, need, gout, create_graph=True, allow_unused=True))
            out = [None, None, None]
            for i, w in enumerate((wi, wo)):
                if ctx.needs_input_grad[i]:
                    g = next(gs)
                    out[i] = torch.zeros_like(w) if g is None else g
            return tuple(out)
        return (*_iso_dirs_native_bwd(wi, wo, gout, ctx.order), None)


def _iso_dirs_native_bwd(wi: torch.Tensor, wo: torch.Tensor, gout: torch.Tensor, order: int):
    """The fused backward of :class:`_IsoDirs`: the gradients ``(N, 3), (N, 3)`` from ``gout (N, K)``."""
    n, dt = wi.shape[0], wi.dtype
    gwi = torch.empty((n, 3), dtype=dt)
    gwo = torch.empty((n, 3), dtype=dt)
    wi_c, wo_c = wi.contiguous(), wo.contiguous()  # kept alive across the call
    g = gout if gout.stride(-1) in (0, 1) else gout.contiguous()  # expanded gradients stay unmaterialised
    fn, head, tab = _iso_dirs_kernel("bwd", order, dt)
    _native.parallel_rows(fn, n, *head, _native.ptr(wi_c), _native.ptr(wo_c), torch.finfo(dt).tiny * 1e6,
                          _horizon_eps(dt), *tab, _native.ptr(g), g.stride(0), g.stride(1),
                          _native.ptr(gwi), _native.ptr(gwo))
    return gwi, gwo


def _remap_torch(d: torch.Tensor):
    """d -> (2 s x, 2 s y, 2 z - 1) of the unit direction, and the validity flag (pure torch)."""
    x, y, z, valid = _unit(d)
    s = 2.0 * _safe_s(z)
    return torch.stack([s * x, s * y, 2.0 * z.clamp(min=0.0) - 1.0], dim=-1), valid


class _Remap(torch.autograd.Function):
    """``kernels.c`` hsh_remap: the map that turns real spherical harmonics into HSH."""

    @staticmethod
    def forward(ctx, d):
        dc = d.contiguous()
        n, dt = d.shape[0], d.dtype
        dp = torch.empty_like(dc)
        valid = torch.empty(n, dtype=torch.uint8)
        fn = getattr(_native.library(), "hsh_remap_fwd_" + _suffix(dt))
        _native.parallel_rows(fn, n, _native.ptr(dc), torch.finfo(dt).tiny * 1e6, _horizon_eps(dt),
                              _native.ptr(dp), _native.ptr(valid))
        vb = valid.bool()
        ctx.mark_non_differentiable(vb)
        ctx.save_for_backward(d)
        return dp, vb

    @staticmethod
    def backward(ctx, gdp, _gvalid):
        (d,) = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph
            (gd,) = torch.autograd.grad(_remap_torch(d)[0], [d], gdp, create_graph=True)
            return gd
        n, dt = d.shape[0], d.dtype
        gd = torch.empty_like(d, memory_format=torch.contiguous_format)
        dc, g = d.contiguous(), gdp.contiguous()  # kept alive across the call
        fn = getattr(_native.library(), "hsh_remap_bwd_" + _suffix(dt))
        _native.parallel_rows(fn, n, _native.ptr(dc), torch.finfo(dt).tiny * 1e6, _horizon_eps(dt),
                              _native.ptr(g), _native.ptr(gd))
        return gd


@lru_cache(maxsize=None)
def _native_hsh_spec(order: int):
    """Tables of ``kernels.c``'s hsh_fwd / hsh_bwd: the polar recurrence of one set, and per output column its
    polar row, its azimuth row (Re w^m at m, Im w^m at P + m) and its scale (1, sqrt 2 or (-1)^m sqrt 2)."""
    L, A, B, c1, c2 = _native_iso_spec(order)[:5]
    ridx, aidx, az_scale = _hsh_gather(order)
    return L, A, B, c1, c2, ridx, aidx, [az_scale[a] for a in aidx]


def _native_hsh_args(order: int, dt: torch.dtype):
    key = ("hsh", order, dt)
    args = _NATIVE_ARGS.get(key)
    if args is None:
        args = _native_hsh_ptrs(order, dt)
        _remember_args(key, args)
    return args


def _native_hsh_ptrs(order: int, dt: torch.dtype):
    L, A, B, c1, c2, kr, ka, ks = _native_hsh_spec(order)
    cpu, i32, p = torch.device("cpu"), torch.int32, _native.ptr
    tabs = (_const(("nat_A", order), A, cpu, dt), _const(("nat_B", order), B, cpu, dt),
            _const(("nat_c1", order), c1, cpu, i32), _const(("nat_c2", order), c2, cpu, i32))
    cols = (_const(("nat_hr", order), kr, cpu, i32), _const(("nat_ha", order), ka, cpu, i32),
            _const(("nat_hs", order), ks, cpu, dt))
    return (L, *[p(t) for t in tabs], len(kr), *[p(t) for t in cols])


class _HshNative(torch.autograd.Function):
    """``kernels.c`` hsh: the HSH of flat (N, 3) directions, ``(N, K)``, in one pass (see :func:`_hsh_flat_t`)."""

    @staticmethod
    def forward(ctx, d, order):
        out = _hsh_native_fwd(d, order)
        ctx.order = order
        ctx.save_for_backward(d)
        return out

    @staticmethod
    def backward(ctx, gout):
        (d,) = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: a differentiable backward through the torch kernel
            (d,) = _aliases((d,))
            y = _hsh_flat_t(d, ctx.order).t()
            if not y.requires_grad:  # order 0: a constant
                return torch.zeros_like(d), None
            (gd,) = torch.autograd.grad(y, [d], gout, create_graph=True, allow_unused=True)
            return (torch.zeros_like(d) if gd is None else gd), None
        return _hsh_native_bwd(d, gout, ctx.order), None


def _hsh_native_fwd(d: torch.Tensor, order: int) -> torch.Tensor:
    """``kernels.c`` hsh_fwd: the HSH of flat (N, 3) directions, ``(N, K)``."""
    dc = d.contiguous()
    n, dt = d.shape[0], d.dtype
    out = d.new_empty((n, (order + 1) ** 2))
    fn = getattr(_native.library(), "hsh_fwd_" + _suffix(dt))
    bad = _native.parallel_rows(fn, n, order, _native.ptr(dc), torch.finfo(dt).tiny * 1e6,
                                *_native_hsh_args(order, dt), _native.ptr(out))
    _recheck(bad, [("dirs", d)])
    return out


def _hsh_native_bwd(d: torch.Tensor, gout: torch.Tensor, order: int) -> torch.Tensor:
    """``kernels.c`` hsh_bwd: the gradient ``(N, 3)`` of :func:`_hsh_native_fwd` from ``gout (N, K)``."""
    n, dt = d.shape[0], d.dtype
    dc = d.contiguous()
    gd = torch.empty_like(dc)
    g = gout if gout.stride(-1) in (0, 1) else gout.contiguous()  # expanded gradients stay unmaterialised
    fn = getattr(_native.library(), "hsh_bwd_" + _suffix(dt))
    _native.parallel_rows(fn, n, order, _native.ptr(dc), torch.finfo(dt).tiny * 1e6, _horizon_eps(dt),
                          *_native_hsh_args(order, dt), _native.ptr(g), g.stride(0), g.stride(1), _native.ptr(gd))
    return gd


class _PairProducts(torch.autograd.Function):
    """``kernels.c`` pair: ``out[:, p] = c_p (A[:, j_p] B[:, k_p] + A[:, k_p] B[:, j_p])`` (anisotropic basis)."""

    @staticmethod
    def forward(ctx, A, B, order):
        out = _pair_native_fwd(A, B, order)
        ctx.order, ctx.tabs = order, _pair_tables(order, A.dtype)
        ctx.save_for_backward(A, B)
        return out

    @staticmethod
    def backward(ctx, gout):
        A, B = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: differentiable torch formula
            A, B = _aliases((A, B))
            j, k, c = (t.to(torch.long) if t.dtype == torch.int32 else t for t in ctx.tabs)
            y = (A.index_select(1, j) * B.index_select(1, k) + A.index_select(1, k) * B.index_select(1, j)) * c
            need = [t for t, nd in zip((A, B), ctx.needs_input_grad[:2]) if nd]
            gs = iter(torch.autograd.grad(y, need, gout, create_graph=True))
            return (next(gs) if ctx.needs_input_grad[0] else None, next(gs) if ctx.needs_input_grad[1] else None, None)
        return (*_pair_native_bwd(A, B, gout, ctx.order), None)


def _pair_tables(order: int, dt: torch.dtype):
    """The column pairs ``j, k`` (int32) and the scales ``c`` of the anisotropic basis, for ``kernels.c`` pair."""
    j, k, c = _aniso_gather(order)
    cpu = torch.device("cpu")
    return (_const(("nat_pj", order), j, cpu, torch.int32), _const(("nat_pk", order), k, cpu, torch.int32),
            _const(("an_c", order), c, cpu, dt))


def _pair_native_fwd(A: torch.Tensor, B: torch.Tensor, order: int) -> torch.Tensor:
    """``kernels.c`` pair_fwd: ``out[:, p] = c_p (A[:, j_p] B[:, k_p] + A[:, k_p] B[:, j_p])``, ``(N, Q)``."""
    Ac, Bc = A.contiguous(), B.contiguous()
    tabs = _pair_tables(order, A.dtype)
    n, H, Q = A.shape[0], A.shape[1], tabs[0].shape[0]
    out = A.new_empty((n, Q))
    fn = getattr(_native.library(), "pair_fwd_" + _suffix(A.dtype))
    _native.parallel_rows(fn, n, _native.ptr(Ac), _native.ptr(Bc), H, Q, *[_native.ptr(t) for t in tabs],
                          _native.ptr(out))
    return out


def _pair_native_bwd(A: torch.Tensor, B: torch.Tensor, gout: torch.Tensor, order: int):
    """``kernels.c`` pair_bwd: the gradients of :func:`_pair_native_fwd` with respect to ``A`` and ``B``."""
    Ac, Bc = A.contiguous(), B.contiguous()
    tabs = _pair_tables(order, A.dtype)
    g = gout if gout.stride(-1) in (0, 1) else gout.contiguous()
    gA, gB = torch.empty_like(Ac), torch.empty_like(Bc)
    fn = getattr(_native.library(), "pair_bwd_" + _suffix(A.dtype))
    _native.parallel_rows(fn, A.shape[0], _native.ptr(Ac), _native.ptr(Bc), A.shape[1], g.shape[1],
                          *[_native.ptr(t) for t in tabs], _native.ptr(g), g.stride(0), g.stride(1),
                          _native.ptr(gA), _native.ptr(gB))
    return gA, gB


# --------------------------------------------------------------------------
# The C kernels as torch.library operators (torch.compile, torch.export, torch.jit.trace)
# --------------------------------------------------------------------------
def _torch_vjp(fn, inputs, needs, gout):
    """A differentiable backward (``create_graph``) of a C kernel: the vector-Jacobian product of its torch kernel
    ``fn`` at ``inputs`` (through :func:`_aliases`); zeros for an input that ``fn`` does not use, None for one
    that needs no gradient."""
    xs = _aliases(inputs)
    y = fn(*xs)
    want = [x for x, nd in zip(xs, needs) if nd]
    gs = iter(torch.autograd.grad(y, want, gout, create_graph=True, allow_unused=True) if y.requires_grad
              else [None] * len(want))
    out = []
    for x, nd in zip(xs, needs):
        g = next(gs) if nd else None
        out.append(torch.zeros_like(x) if nd and g is None else g)
    return out


def _define_ops():
    """The operators ``torch_hsh::hsh``, ``::isotropic``, ``::isotropic_core`` and ``::pair_products`` (each with its
    ``*_backward``), or None on a torch without ``torch.library.custom_op`` (< 2.4)."""
    lib = torch.library
    if not (hasattr(lib, "custom_op") and hasattr(lib, "register_autograd")):
        return None

    def op(name, schema, fn, fake):
        o = lib.custom_op("torch_hsh::" + name, fn, mutates_args=(), device_types="cpu", schema=schema)
        o.register_fake(fake)
        return o

    empty = torch.empty_like
    ops = {
        "hsh": op("hsh", "(Tensor dirs, int order) -> Tensor", _hsh_native_fwd,
                  lambda d, order: d.new_empty((d.shape[0], (order + 1) ** 2))),
        "hsh_backward": op("hsh_backward", "(Tensor dirs, Tensor grad, int order) -> Tensor", _hsh_native_bwd,
                           lambda d, g, order: empty(d)),
        "isotropic": op("isotropic", "(Tensor wi, Tensor wo, int order) -> Tensor", _iso_dirs_native,
                        lambda wi, wo, order: wi.new_empty((wi.shape[0], num_isotropic(order)))),
        "isotropic_backward": op("isotropic_backward", "(Tensor wi, Tensor wo, Tensor grad, int order) -> (Tensor, Tensor)",
                                 _iso_dirs_native_bwd, lambda wi, wo, g, order: (empty(wi), empty(wo))),
        "isotropic_core": op("isotropic_core", "(Tensor zi, Tensor zo, Tensor a, Tensor rho, Tensor sio, Tensor valid, "
                             "int order) -> Tensor", _iso_core_fwd,
                             lambda zi, *rest: zi.new_empty((zi.shape[0], num_isotropic(rest[-1])))),
        "isotropic_core_backward": op("isotropic_core_backward", "(Tensor zi, Tensor zo, Tensor a, Tensor rho, "
                                      "Tensor sio, Tensor valid, Tensor grad, int order) -> "
                                      "(Tensor, Tensor, Tensor, Tensor, Tensor)",
                                      lambda *xs: tuple(_iso_core_bwd(*xs)), lambda *xs: tuple(empty(x) for x in xs[:5])),
        "pair_products": op("pair_products", "(Tensor A, Tensor B, int order) -> Tensor", _pair_native_fwd,
                            lambda A, B, order: A.new_empty((A.shape[0], num_anisotropic(order)))),
        "pair_products_backward": op("pair_products_backward", "(Tensor A, Tensor B, Tensor grad, int order) -> "
                                     "(Tensor, Tensor)", _pair_native_bwd, lambda A, B, g, order: (empty(A), empty(B))),
    }

    def save(ctx, inputs, output):  # every operator: tensors, then the order
        ctx.order = inputs[-1]
        ctx.save_for_backward(*inputs[:-1])

    def hsh_bwd(ctx, g):
        (d,) = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph
            return _torch_vjp(lambda x: _hsh_flat_t(x, ctx.order).t(), (d,), (True,), g)[0], None
        return ops["hsh_backward"](d, g, ctx.order), None

    def iso_bwd(ctx, g):
        wi, wo = ctx.saved_tensors
        if torch.is_grad_enabled():
            fn = lambda a, b: _iso_kernel_t(*_iso_geom_torch(a, b), ctx.order).t()  # noqa: E731
            return (*_torch_vjp(fn, (wi, wo), ctx.needs_input_grad[:2], g), None)
        return (*ops["isotropic_backward"](wi, wo, g, ctx.order), None)

    def core_bwd(ctx, g):
        saved = ctx.saved_tensors
        if torch.is_grad_enabled():
            fn = lambda *xs: _iso_kernel_t(*xs, saved[5], ctx.order).t()  # noqa: E731
            return (*_torch_vjp(fn, saved[:5], ctx.needs_input_grad[:5], g), None, None)
        return (*ops["isotropic_core_backward"](*saved, g, ctx.order), None, None)

    def pair_bwd(ctx, g):
        A, B = ctx.saved_tensors
        if torch.is_grad_enabled():
            j, k, c = (_const(key, v, A.device, dt) for key, v, dt in zip(
                (("an_j", ctx.order), ("an_k", ctx.order), ("an_c", ctx.order)), _aniso_gather(ctx.order),
                (None, None, A.dtype)))
            fn = lambda a, b: (a.index_select(1, j) * b.index_select(1, k)  # noqa: E731
                               + a.index_select(1, k) * b.index_select(1, j)) * c
            return (*_torch_vjp(fn, (A, B), ctx.needs_input_grad[:2], g), None)
        return (*ops["pair_products_backward"](A, B, g, ctx.order), None)

    for name, bwd in (("hsh", hsh_bwd), ("isotropic", iso_bwd), ("isotropic_core", core_bwd),
                      ("pair_products", pair_bwd)):
        ops[name].register_autograd(bwd, setup_context=save)
    return ops


#: The C kernels as ``torch.library`` operators: what a torch.compile / torch.export graph or a torch.jit.trace
#: records in place of the eager ``autograd.Function`` s above (which these graphs cannot hold). Opaque to the
#: tracer (their fake versions give the output shapes), so the rows stay unchunked and symbolic. None: torch < 2.4.
_OPS = _define_ops()


@lru_cache(maxsize=None)
def _sph_scale(order: int) -> Tuple[float, ...]:
    """sqrt(2) * sign_k: HSH_k(d) = sqrt(2) sign_k Y_k(d') for sphericart's real SH Y_k (same (l, m) order);
    sign_k = -1 for m < 0 with odd |m| (the Condon-Shortley convention differs there)."""
    r2 = math.sqrt(2.0)
    return tuple(-r2 if (m < 0 and (-m) % 2 == 1) else r2 for n in range(order + 1) for m in range(-n, n + 1))


_SPH_CALC: Dict[int, object] = {}


def _hsh_fast_ok(d: torch.Tensor) -> bool:
    return (_BACKEND["name"] == "auto" and not _functorch_active() and not _forward_ad()
            and _sphericart_module() is not None)


def _hsh_sphericart(d: torch.Tensor, order: int) -> torch.Tensor:
    """HSH of flat (N, 3) directions through sphericart: ``sqrt(2) sign_k Y_k(d')``, ``(N, K)``."""
    calc = _SPH_CALC.get(order)
    if calc is None:
        calc = _SPH_CALC[order] = _sphericart_module().SphericalHarmonics(order)
    if _native_ok(d):
        dp, valid = _Remap.apply(d)
    else:
        dp, valid = _remap_torch(d)
    Y = calc(dp)  # type: ignore[operator]
    scale = _const(("sph_scale", order), _sph_scale(order), d.device, d.dtype)
    grad = Y.requires_grad
    out = Y * scale if grad else Y.mul_(scale)
    if _compiling() or (d.device.type != "cpu" and not grad):  # no host sync: mask the invalid rows
        return out * valid.unsqueeze(-1).to(out.dtype)
    # Rows that the pure-torch kernel evaluates instead (a host sync; free on the CPU, usually none):
    # invalid rows (zero), and with autograd the rows within eps of the horizon. There d' sits at
    # the pole of the sphere, where the derivative of the even-m functions reaches z only through
    # s ds/dz, a finite product of which the safe form of s keeps no part.
    fix = ~valid
    if grad:
        fix |= dp[:, 2].detach() <= 2.0 * _horizon_eps(d.dtype) - 1.0
    rows = fix.nonzero().squeeze(-1)
    if rows.numel():
        out = out.index_copy(0, rows, _hsh_flat_t(d.index_select(0, rows), order).t())
    return out


# --------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------
def hsh(dirs: torch.Tensor, order: int) -> torch.Tensor:
    r"""Real hemispherical harmonics up to ``order``.

    Args:
        dirs: ``(..., 3)`` directions in the local frame (z = normal); they are
            normalised here. Directions with ``z < 0`` and zero vectors give 0.
        order: maximum order ``P >= 0`` (at most 40).

    Returns:
        ``(..., (P+1)**2)`` tensor; entry ``n*n + n + m`` is :math:`H_n^m`.
        Same dtype and device as ``dirs`` (float16 / bfloat16 are computed in float32;
        float32 under ``torch.autocast``); differentiable.

    Example:
        >>> import torch, torch_hsh
        >>> y = torch_hsh.hsh(torch.tensor([0.0, 0.0, 1.0]), order=2)
        >>> y.shape
        torch.Size([9])
        >>> abs(float(y[0]) - (1 / (2 * math.pi)) ** 0.5) < 1e-6  # H_0^0 = 1/sqrt(2 pi)
        True
    """
    if _half(dirs):
        return _in_float32(hsh, (dirs,), order)
    _check_group([("dirs", dirs)], defer_values=True)
    order = check_order(order)
    lead = dirs.shape[:-1]
    K = (order + 1) ** 2
    flat = _flat(dirs, lead)
    if _native_ok(flat):
        out = _HshNative.apply(flat, order)  # checks the values that the kernel flags
    elif _graph_ok(flat):
        out = _OPS["hsh"](flat, order)
    elif _hsh_fast_ok(flat):
        out = _hsh_sphericart(flat, order)
    else:
        out = _run_rows(lambda d: _hsh_flat_t(d, order), K, flat)
    return _shaped(out, lead, K)


def helmholtz_isotropic(wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
    r"""Isotropic Helmholtz HSH basis :math:`\mathcal H_{pr}^q(\omega_i, \omega_o)`.

    .. math::
        \mathcal H_{pr}^q = \frac{1}{\sqrt{2 + 2\delta_{pr}}}
        [\Theta_p^q(\theta_i)\Theta_r^q(\theta_o) + \Theta_r^q(\theta_i)\Theta_p^q(\theta_o)]
        \Phi_q(\phi_o - \phi_i)

    orthonormal over :math:`\Omega_i \times \Omega_o` (erratum 1 applied).

    Args:
        wi: ``(..., 3)`` incident directions, local frame.
        wo: ``(..., 3)`` outgoing directions, local frame; broadcast with ``wi``.
        order: maximum order ``P``.

    Returns:
        ``(..., K)``, ``K = (P+1)(P+2)(P+3)/6``, columns in the order of
        :func:`isotropic_indices` (p-major over ``p >= r >= q >= 0``).
        Zero where either direction is below the horizon or zero.

    Example:
        >>> import torch_hsh
        >>> wi = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1).abs()
        >>> wo = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1).abs()
        >>> torch_hsh.helmholtz_isotropic(wi, wo, 3).shape
        torch.Size([10, 20])
    """
    if _half(wi, wo):
        return _in_float32(helmholtz_isotropic, (wi, wo), order)
    _check_group([("wi", wi), ("wo", wo)], defer_values=True)
    order = check_order(order)
    K = (order + 1) * (order + 2) * (order + 3) // 6
    # fused C kernels (geometry, then the basis), else the torch kernel in row chunks
    return _pair_basis(wi, wo, K,
                       lambda a, b: _IsoDirs.apply(a, b, order) if _needs_grad(a, b) else _iso_dirs_native(a, b, order),
                       lambda a, b: _OPS["isotropic"](a, b, order),
                       lambda a, b: _iso_dirs(a, b, order))


def _pair_basis(wi, wo, K, native, graph, flat):
    """A basis of two direction sets ``(*S, 3), (*S', 3) -> (*broadcast, K)``: ``native(a, b)`` (C kernels) on the
    flat rows where :func:`_native_ok`, ``graph(a, b)`` (the same as operators) where :func:`_graph_ok`, else
    ``flat(a, b)`` in row chunks. One direction set (``wi is wo``) is passed as the same tensor twice, so that a
    kernel computes its tables once."""
    if wi is wo:
        lead = wi.shape[:-1]
        a = b = _flat(wi, lead)
    else:
        lead, a, b = _broadcast_pair(wi, wo)
    if _native_ok(wi):
        out = native(a, b)
    elif _graph_ok(wi):
        out = graph(a, b)
    elif a is b:
        out = _run_rows(lambda w: flat(w, w), K, a)
    else:
        out = _run_rows(flat, K, a, b)
    return _shaped(out, lead, K)


def helmholtz_isotropic_cosines(
    cos_i: torch.Tensor, cos_o: torch.Tensor, cos_dphi: torch.Tensor, order: int
) -> torch.Tensor:
    r"""Isotropic Helmholtz basis from the isotropic triple.

    Args:
        cos_i: ``(...)`` :math:`\cos\theta_i` in ``[0, 1]`` (values < 0 give 0).
        cos_o: ``(...)`` :math:`\cos\theta_o`.
        cos_dphi: ``(...)`` :math:`\cos(\phi_o - \phi_i)` in ``[-1, 1]``; any value is
            fine where a direction is parallel to the normal.
        order: maximum order ``P``.

    Returns:
        ``(..., K)`` exactly as :func:`helmholtz_isotropic` for the same geometry.

    Example:
        >>> import torch_hsh
        >>> c = torch.tensor([0.5])
        >>> torch_hsh.helmholtz_isotropic_cosines(c, c, torch.tensor([-1.0]), 2).shape
        torch.Size([1, 10])
    """
    if _half(cos_i, cos_o, cos_dphi):
        return _in_float32(helmholtz_isotropic_cosines, (cos_i, cos_o, cos_dphi), order)
    _check_group([("cos_i", cos_i), ("cos_o", cos_o), ("cos_dphi", cos_dphi)], dirs=False)
    order = check_order(order)
    lead = broadcast_shapes([("cos_i", cos_i.shape), ("cos_o", cos_o.shape), ("cos_dphi", cos_dphi.shape)])
    zi, zo, cd = (_flat(t, lead, ()) for t in (cos_i, cos_o, cos_dphi))
    K = (order + 1) * (order + 2) * (order + 3) // 6
    return _shaped(_iso_from_geometry(_iso_cosines_geom, (zi, zo, cd), order, K), lead, K)


def helmholtz_anisotropic(wi: torch.Tensor, wo: torch.Tensor, order: int) -> torch.Tensor:
    r"""Anisotropic (general) Helmholtz HSH basis.

    .. math::
        \mathcal H_{jk} = \frac{1}{\sqrt{2 + 2\delta_{jk}}}[H_j(\omega_i) H_k(\omega_o) + H_k(\omega_i) H_j(\omega_o)]

    for flat HSH indices ``j <= k``.

    Args:
        wi: ``(..., 3)`` incident directions, local frame.
        wo: ``(..., 3)`` outgoing directions; broadcast with ``wi``.
        order: maximum HSH order ``P`` (at most 16).

    Returns:
        ``(..., K(K+1)/2)`` with ``K = (P+1)**2``, columns ordered as
        :func:`anisotropic_indices` (pairs ``j <= k``, j-major).

    Example:
        >>> import torch_hsh
        >>> w = torch.tensor([[0.0, 0.6, 0.8]])
        >>> torch_hsh.helmholtz_anisotropic(w, w, 1).shape
        torch.Size([1, 10])
    """
    if _half(wi, wo):
        return _in_float32(helmholtz_anisotropic, (wi, wo), order)
    _check_group([("wi", wi), ("wo", wo)])
    order = check_order(order, max_order=MAX_ANISOTROPIC_ORDER)
    K = (order + 1) ** 2
    K = K * (K + 1) // 2
    return _pair_basis(wi, wo, K, lambda a, b: _aniso_native(a, b, order, _PairProducts.apply),
                       lambda a, b: _aniso_native(a, b, order, _OPS["pair_products"]),
                       lambda a, b: _aniso_flat(a, b, order))


def _aniso_native(a: torch.Tensor, b: torch.Tensor, order: int, pairs) -> torch.Tensor:
    """The HSH of both sets (fast path; once where ``a is b``), then the fused pair products ``pairs``."""
    Hi = hsh(a, order)
    Ho = Hi if a is b else hsh(b, order)
    return pairs(Hi, Ho, order)


def helmholtz_isotropic_world(
    wi: torch.Tensor, wo: torch.Tensor, normal: torch.Tensor, order: int
) -> torch.Tensor:
    r"""Isotropic Helmholtz basis from world-space directions and a normal.

    Needs no tangent frame: the isotropic basis depends only on
    :math:`n\cdot\omega_i`, :math:`n\cdot\omega_o` and the tangential dot product
    :math:`\omega_i\cdot\omega_o - (n\cdot\omega_i)(n\cdot\omega_o)`, and is a smooth
    function of all three (polynomial apart from the horizon factor), so the
    gradient with respect to ``normal`` is well defined even when a direction is
    parallel to the normal. This is the entry point for photometric stereo.

    Args:
        wi: ``(..., 3)`` incident (light) directions, world frame.
        wo: ``(..., 3)`` outgoing (view) directions, world frame.
        normal: ``(..., 3)`` surface normals; all three broadcast together.
        order: maximum order ``P``.

    Returns:
        ``(..., K)`` equal to ``helmholtz_isotropic(to_local(wi), to_local(wo), P)``.

    Example:
        >>> import torch_hsh
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> l = torch.tensor([[0.3, 0.0, 0.95]])
        >>> torch_hsh.helmholtz_isotropic_world(l, n, n, 2).shape
        torch.Size([1, 10])
    """
    if _half(wi, wo, normal):
        return _in_float32(helmholtz_isotropic_world, (wi, wo, normal), order)
    _check_group([("wi", wi), ("wo", wo), ("normal", normal)])
    order = check_order(order)
    lead = broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1]), ("normal", normal.shape[:-1])])
    wi, wo, nrm = (_flat(t, lead) for t in (wi, wo, normal))
    K = (order + 1) * (order + 2) * (order + 3) // 6
    return _shaped(_iso_from_geometry(_iso_world_geom, (wi, wo, nrm), order, K), lead, K)


def _normalize3(d: torch.Tensor) -> torch.Tensor:
    """Normalise (N, 3) vectors; zero vectors stay zero with finite gradients."""
    n2 = (d * d).sum(-1, keepdim=True)
    ok = n2 > torch.finfo(d.dtype).tiny * 1e6
    return d * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
