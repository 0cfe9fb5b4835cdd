r"""Environment lighting: equirectangular maps, their spherical harmonics, and shading under them.

Conventions (derivation and pictures in ``docs/environment_lighting.md``):

* **World frame** = the DiLiGenT frame: x right, y up, z toward the (orthographic)
  camera; the view direction toward the camera is ``v = (0, 0, 1)``.
* **Equirectangular maps** ``(H, W, C)``: row 0 is the zenith (+y), row ``H-1`` the
  nadir; the polar angle from +y is :math:`\vartheta = \pi (i + 1/2) / H` at texel
  centres. Columns sweep the azimuth :math:`\varphi = 2\pi (j + 1/2)/W - \pi`, with
  direction :math:`(\sin\vartheta\sin\varphi, \cos\vartheta, -\sin\vartheta\cos\varphi)`:
  the centre column looks along -z (the scene behind the object, as the camera sees
  it), a quarter of the width to the right is +x, the left and right edges are +z
  (behind the camera). This is the usual panorama layout (seen from inside, not
  mirrored); the maps of ``../shared/data/envmaps`` are read in this layout as they are.
* **Rotation about the up axis** by ``angle`` turns the environment by ``angle``
  radians counter-clockwise about +y (right-hand rule): the radiance that came from
  ``d`` comes from ``R_y(angle) d`` afterwards.
* **Spherical harmonics**: the real, orthonormal SH of
  :func:`torch_hsh.bases.westin.real_sh` (no Condon–Shortley phase,
  :math:`Y_l^m = N_l^{|m|} P_l^{|m|}(\cos\theta)\Phi_m(\phi)` with
  :math:`\Phi_m = \sqrt2\cos m\phi` (m > 0), 1, :math:`(-1)^m\sqrt2\sin|m|\phi` (m < 0)),
  flat index ``l*l + l + m``, **polar axis = world z** (the camera axis) and azimuth
  measured from +x toward +y. Coefficients have shape ``(C, (N+1)**2)``.
* **Radiance units**: map values are radiance; :meth:`EnvironmentMap.power` is
  :math:`\int L\,d\omega` per channel.

Method. Each texel is a constant-radiance patch bounded by two parallels and two
meridians of the map's own (up = y) spherical coordinates. In those coordinates
every SH factorises into a polar and an azimuthal part, so the texel integral of
each SH is a product of a Gauss–Legendre integral over the texel's rows (exact to
float64 rounding) and a closed-form azimuthal integral; a fixed rotation then turns
the map-frame coefficients into world-frame ones. A constant map therefore has no
higher-order coefficients (up to rounding).

:func:`render_envmap` uses the fixed view. In the local frame of a pixel (z = normal,
x toward the tangential part of v, so the view azimuth is 0) the isotropic Helmholtz
function :math:`B_{pr}^q` times :math:`\cos\theta_i` only needs the lighting integrals

.. math::
    E_{pq} = \int_{\Omega^+} \lambda(\omega)\, H_p^q(\omega) \cos\theta\, d\omega
           = \sum_{l} \lambda_{lq}\, T^q_{lp},\qquad
    T^q_{lp} = \int_{\Omega^+} Y_l^q H_p^q \cos\theta\,d\omega,

where :math:`\lambda_{lm}` are the SH coefficients of the lighting rotated into the
local frame (the azimuthal integral keeps m = q only) and ``T`` is a constant table.
The outgoing radiance is
:math:`\sum_{prq} a_{prq} N_{pr} [\Theta_r^q(\theta_o) E_{pq} + \Theta_p^q(\theta_o) E_{rq}]`.
The rotation into the local frame is the only per-pixel work: with Euler angles
:math:`R = R_z(\alpha) R_y(\beta) R_z(\pi)` of the normal (``alpha``, ``beta`` its
azimuth and polar angle about z), :math:`\lambda = S_\pi J_+ Z_\beta J_- Z_\alpha L`
with constant matrices :math:`J_\pm` (rotations by :math:`\pm\pi/2` about x) and
cheap z rotations :math:`Z`. Performance layout: with
:math:`t(\theta) = [1, \cos m\theta, \sin m\theta]_{m \le N}` the integrals are
:math:`E = \sum_{a,b} t_a(\alpha) t_b(\beta) Q_{ab}`, where ``Q`` (``(2N+1)^2 C (P+1)(P+2)/2``
numbers) is built once per call from the lighting and the constant matrices. Per pixel
there is one GEMM of :math:`t(\alpha)` against ``Q``, a batched contraction with
:math:`t(\beta)` and the final gather over the K coefficients (one small GEMM for a shared
BRDF). Pixels are processed in chunks of ``chunk_size`` (cache-sized temporaries); nothing
per pixel is Monte Carlo.

Singular points: at normals parallel to the view (``|n_xy| < eps``, eps = 1e-12 in
float64, 1e-6 in float32) the azimuth alpha is undefined; it is frozen to 0 there
(values stay exact). Because the Euler-angle path loses the tangential derivative at
the axis and suffers cancellation just off it, the gradient with respect to the
normal of pixels with ``|n_xy| < delta`` (1e-6 in float64, 3e-4 in float32) is taken
at the same normal moved to ``|n_xy| = delta`` (a smooth function: error O(delta));
values are unaffected. Gradients are therefore finite and correct to O(delta)
everywhere, including ``n = v`` (tested against finite differences). Normals facing away from the camera
(``n_z < 0``) give zero radiance, as the Helmholtz basis is zero for a view below
the horizon.

:func:`render_envmap_reference` is a brute-force texel quadrature of the same
integral (midpoint rule over texels with their exact solid angles, optional
supersampling), for coefficient maps or analytic BRDF callables; it reuses the BRDF
evaluation of :mod:`torch_hsh.render`.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Callable, Optional, Tuple, Union

import numpy as np
import torch

from .._checks import broadcast_shapes, check_dirs, check_order, check_same, check_shape, check_tensor
from ..kernel import hsh, iso_pair_gather
from ..bases.westin import _sh_gather, _sh_polar, complex_powers, real_sh
from .images import brdf_cosine, order_from_num_functions

__all__ = [
    "EnvironmentMap",
    "equirect_directions",
    "equirect_solid_angles",
    "sh_coefficients",
    "sh_evaluate",
    "render_envmap",
    "render_envmap_reference",
    "envmap_shading_table",
    "EnvironmentLighting",
    "procedural_sky",
]

#: Map frame (x_m, y_m, z_m = up) to world: world = A @ map.
_MAP_TO_WORLD = ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0))


def _eps(dtype: torch.dtype) -> float:
    return 1e-12 if dtype == torch.float64 else 1e-6


# --------------------------------------------------------------------------
# Constant SH tables (float64 on the host, cached)
# --------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _leggauss(n: int) -> Tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(n)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _sphere_rule(order: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Product rule on the sphere exact for polynomials of degree ``<= 2 order``."""
    nz, nphi = order + 2, 2 * order + 3
    x, w = _leggauss(nz)
    phi = 2.0 * math.pi * (np.arange(nphi) + 0.5) / nphi
    Z, PH = np.meshgrid(x, phi, indexing="ij")
    S = np.sqrt(np.clip(1.0 - Z * Z, 0.0, None))
    d = np.stack([S * np.cos(PH), S * np.sin(PH), Z], -1).reshape(-1, 3)
    wt = np.outer(w, np.full(nphi, 2.0 * math.pi / nphi)).reshape(-1)
    return torch.from_numpy(d), torch.from_numpy(wt)


def _sh_rotation_matrix(R: np.ndarray, order: int) -> torch.Tensor:
    r"""``D`` with ``D @ c`` = SH coefficients of :math:`\omega \mapsto f(R\omega)` (``c``: those of f).

    ``D[k, j] = \int Y_j(R w) Y_k(w) dw`` by an exact product rule (float64).
    Composition: ``D(R1 @ R2) = D(R2) @ D(R1)``.
    """
    d, wt = _sphere_rule(order)
    Rt = torch.as_tensor(np.asarray(R, dtype=np.float64))
    Y = real_sh(d, order)
    YR = real_sh(d @ Rt.T, order)
    return (Y * wt.unsqueeze(-1)).T @ YR


@lru_cache(maxsize=None)
def _z_rotation_gather(order: int):
    """Per flat index k: trig column of cos(|m| t), partner index k', signed sin column for ``Z(t)``.

    ``(Z(t) c)_k = cos(|m| t) c_k + sign_k sin(|m| t) c_{k'}`` (sign 0 for m = 0).
    """
    N = order
    cos_col, sin_col, partner, sign = [], [], [], []
    for l in range(N + 1):
        for m in range(-l, l + 1):
            a = abs(m)
            cos_col.append(a)
            sin_col.append(N + a if a > 0 else 0)
            partner.append(l * l + l - m)
            sign.append(0.0 if m == 0 else ((-1.0) ** a if m > 0 else -((-1.0) ** a)))
    return cos_col, sin_col, partner, sign


def _pq_list(order: int):
    return [(p, q) for p in range(order + 1) for q in range(p + 1)]


@lru_cache(maxsize=None)
def _shading_table(light_order: int, brdf_order: int) -> torch.Tensor:
    r"""``T[k, j] = \int_{z>0} Y_k(w) H_p^q(w) cos(theta) dw`` for ``j = (p, q)``, q >= 0 (float64).

    Product rule in ``u = sqrt(z)`` (Gauss–Legendre, so the half-integer powers of
    ``z`` in odd-q functions become polynomial) times the uniform rule in phi
    (exact for the trigonometric degree ``N + P``).
    """
    N, P = light_order, brdf_order
    nu = 64 + N + P
    x, w = _leggauss(nu)
    u = 0.5 * (x + 1.0)
    wu = 0.5 * w
    z = u * u
    wz = wu * 2.0 * u
    nphi = N + P + 2
    phi = 2.0 * math.pi * (np.arange(nphi) + 0.5) / nphi
    Z, PH = np.meshgrid(z, phi, indexing="ij")
    S = np.sqrt(np.clip(1.0 - Z * Z, 0.0, None))
    d = torch.from_numpy(np.stack([S * np.cos(PH), S * np.sin(PH), Z], -1).reshape(-1, 3))
    wt = torch.from_numpy((np.outer(wz, np.full(nphi, 2.0 * math.pi / nphi)) * Z).reshape(-1))
    Y = real_sh(d, N)
    H = hsh(d, P)
    cols = [p * p + p + q for p, q in _pq_list(P)]
    return (Y * wt.unsqueeze(-1)).T @ H[:, cols]


def envmap_shading_table(light_order: int, brdf_order: int, dtype=torch.float64, device=None) -> torch.Tensor:
    r"""The constant table :math:`T[k, j] = \int_{\Omega^+} Y_k\, H_p^q \cos\theta\, d\omega`.

    Rows: SH flat index ``k = l*l + l + m`` up to ``light_order``; columns: pairs
    ``(p, q)``, ``p = 0..brdf_order``, ``q = 0..p`` (p-major). Only rows with
    ``m = q`` are non-zero (the azimuthal integral selects them).

    Example:
        >>> T = envmap_shading_table(2, 1)
        >>> T.shape
        torch.Size([9, 3])
        >>> round(float(T[0, 0]), 6)  # Y_0^0 H_0^0 cos: (1/sqrt(4 pi)) (1/sqrt(2 pi)) pi
        0.353553
    """
    N = check_order(light_order, "light_order")
    P = check_order(brdf_order, "brdf_order")
    return _shading_table(N, P).to(dtype=dtype, device=device)


@lru_cache(maxsize=None)
def _render_consts_host(N: int, P: int):
    Jm = _sh_rotation_matrix(_rot_x(-math.pi / 2), N)
    Jp = _sh_rotation_matrix(_rot_x(math.pi / 2), N)
    Spi = _sh_rotation_matrix(_rot_z(math.pi), N)
    cos_col, sin_col, partner, sign = _z_rotation_gather(N)
    Kn = len(cos_col)
    # Z_a L = Ocos[a] * L + Osin[a] * L[partner] (one-hot rows, signs folded in)
    Ocos = torch.zeros(2 * N + 1, Kn, dtype=torch.float64)
    Osin = torch.zeros(2 * N + 1, Kn, dtype=torch.float64)
    Ocos[cos_col, range(Kn)] = 1.0
    Osin[sin_col, range(Kn)] = torch.tensor(sign, dtype=torch.float64)
    T = _shading_table(N, P)  # (K, Lp)
    W = (Spi @ Jp).T @ T  # (K, Lp): E = W^T Y with Y = Z_beta X
    # (Z_b X)^T W = sum_k X_k [cos_k W_k + sum_{k': partner(k') = k} sign_k' sin_k' W_k']
    inv = [0] * len(partner)
    for k, kk in enumerate(partner):
        inv[kk] = k
    W2 = W[inv] * torch.tensor([sign[i] for i in inv], dtype=W.dtype).unsqueeze(-1)
    sin2 = [sin_col[i] for i in inv]
    # final gather of the isotropic basis: B_k uses E[i1] Th[j1] + E[i2] Th[j2]
    pq = {v: i for i, v in enumerate(_pq_list(P))}
    Lp = len(pq)
    i1, j1, i2, j2 = iso_pair_gather(P, pq)
    K = len(i1)
    S1 = torch.zeros(K, Lp + 1, dtype=torch.float64)
    S2 = torch.zeros(K, Lp + 1, dtype=torch.float64)
    S1[range(K), i1] = 1.0
    S2[range(K), i2] = 1.0
    S1, S2 = S1[:, :Lp], S2[:, :Lp]
    j2z = [2 * Lp if i == Lp else j for i, j in zip(i2, j2)]  # the zero column of Ty where there is no 2nd term
    # shared coefficients: w[b, j, c] = sum_t Ty[b, t] A1[t, j, k] a[c, k]
    A1 = torch.zeros(2 * Lp + 1, Lp, K, dtype=torch.float64)
    for k in range(K):
        A1[j1[k], i1[k], k] += 1.0
        if i2[k] < Lp:
            A1[j2[k], i2[k], k] += 1.0
    A1 = A1.reshape(2 * Lp + 1, Lp * K)
    th_cols = [p * p + p + q for p, q in _pq_list(P)]
    th_scale = [1.0 if q == 0 else 1.0 / math.sqrt(2.0) for _, q in _pq_list(P)]
    # Q-form: E[c, j] = sum_{a, b} trig_alpha[a] trig_beta[b] Q[a, b, c, j] with
    # Q[a, b] = sum_k (J_- Z_a L)_k (W_kj [cos_col[k] = b] + W2_kj [sin2[k] = b])
    Kl = W.shape[0]
    Bsel = torch.zeros(2 * N + 1, Kl, Lp, dtype=torch.float64)
    for k in range(Kl):
        Bsel[cos_col[k], k] += W[k]
        if sign[inv[k]] != 0.0:
            Bsel[sin2[k], k] += W2[k]
    return dict(Jm=Jm, Ocos=Ocos, Osin=Osin, partner=partner, W=W, Bsel=Bsel, j1=j1, j2=j2z, S1=S1, S2=S2, A1=A1,
                th_cols=th_cols, th_scale=th_scale)


_CONST_CACHE: dict = {}


def _render_consts(N: int, P: int, dtype: torch.dtype, device: torch.device) -> dict:
    key = (N, P, dtype, str(device))
    c = _CONST_CACHE.get(key)
    if c is None:
        h = _render_consts_host(N, P)
        c = {}
        for k, v in h.items():
            if isinstance(v, torch.Tensor):
                c[k] = v.to(dtype=dtype, device=device)
            elif k == "th_scale":
                c[k] = torch.tensor(v, dtype=dtype, device=device)
            else:
                c[k] = torch.tensor(v, dtype=torch.long, device=device)
        _CONST_CACHE[key] = c
    return c


# --------------------------------------------------------------------------
# Equirectangular geometry
# --------------------------------------------------------------------------
def _check_hw(height, width) -> Tuple[int, int]:
    for nm, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"`{nm}` must be a positive integer, got {v!r}")
    return int(height), int(width)


def _map_azimuth_edges(width: int, rotation: float) -> np.ndarray:
    """Map-frame azimuth (about up, from x_m toward y_m) of the column edges, ``(W+1,)`` decreasing."""
    return math.pi - 2.0 * math.pi * np.arange(width + 1) / width + rotation


def equirect_directions(height: int, width: int, rotation: float = 0.0, dtype=torch.float32, device=None) -> torch.Tensor:
    """World directions of the texel centres of an equirectangular map, ``(H, W, 3)``.

    See the module docstring for the layout; ``rotation`` turns the map about +y.

    Example:
        >>> d = equirect_directions(2, 4, dtype=torch.float64)
        >>> d.shape
        torch.Size([2, 4, 3])
        >>> [round(float(v), 4) for v in d[0, 1]]  # upper row, column left of the centre: -z side
        [-0.5, 0.7071, -0.5]
    """
    H, W = _check_hw(height, width)
    th = math.pi * (np.arange(H) + 0.5) / H
    e = _map_azimuth_edges(W, float(rotation))
    ph = 0.5 * (e[:-1] + e[1:])
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    m = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1)
    d = m @ np.array(_MAP_TO_WORLD).T
    return torch.from_numpy(d).to(dtype=dtype, device=device)


def equirect_solid_angles(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    r"""Exact solid angle of every texel, ``(H, W)``: :math:`(2\pi/W)(\cos\vartheta_i - \cos\vartheta_{i+1})`.

    Example:
        >>> float(equirect_solid_angles(3, 5, dtype=torch.float64).sum()) - 4 * math.pi < 1e-12
        True
    """
    H, W = _check_hw(height, width)
    c = np.cos(math.pi * np.arange(H + 1) / H)
    row = (c[:-1] - c[1:]) * (2.0 * math.pi / W)
    return torch.from_numpy(np.repeat(row[:, None], W, axis=1)).to(dtype=dtype, device=device)


@lru_cache(maxsize=8)
def _texel_tables(H: int, W: int, order: int, rotation: float):
    """Exact texel integrals of the map-frame SH: polar ``(H, K)`` and azimuthal ``(W, K)`` factors."""
    N = order
    # polar factor g_k(theta) = Q_l^{|m|}(cos) sin^{|m|} * scale_m; integrated with sin(theta) over each row
    n = N + 8
    x, w = _leggauss(n)
    edges = math.pi * np.arange(H + 1) / H
    a, b = edges[:-1, None], edges[1:, None]
    th = 0.5 * (a + b) + 0.5 * (b - a) * x[None, :]  # (H, n)
    wt = 0.5 * (b - a) * w[None, :] * np.sin(th)
    z = torch.from_numpy(np.cos(th).reshape(-1))
    s = torch.from_numpy(np.sin(th).reshape(-1))
    Q = _sh_polar(z, N)  # (H n, L)
    pidx, aidx, scale, _ = _sh_gather(N)
    mabs = [abs(m) for l in range(N + 1) for m in range(-l, l + 1)]
    spow = torch.stack([s ** m for m in range(N + 1)], -1)  # (H n, N+1)
    g = Q[:, pidx] * spow[:, mabs] * torch.tensor(scale, dtype=torch.float64)[aidx]
    G = (g.reshape(H, n, -1) * torch.from_numpy(wt).unsqueeze(-1)).sum(1)  # (H, K)
    # azimuthal factor: 1, cos(m phi) (m > 0), sin(|m| phi) (m < 0) integrated over each column
    e = _map_azimuth_edges(W, rotation)
    lo, hi = e[1:], e[:-1]  # lo < hi
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    F = np.zeros((W, (N + 1) ** 2))
    for l in range(N + 1):
        for m in range(-l, l + 1):
            k = l * l + l + m
            am = abs(m)
            if m == 0:
                F[:, k] = hi - lo
            elif m > 0:  # int cos(m p) = 2 cos(m mid) sin(m half) / m
                F[:, k] = 2.0 * np.cos(am * mid) * np.sin(am * half) / am
            else:  # int sin(m p) = 2 sin(m mid) sin(m half) / m
                F[:, k] = 2.0 * np.sin(am * mid) * np.sin(am * half) / am
    return G, torch.from_numpy(F)


@lru_cache(maxsize=None)
def _map_to_world(order: int) -> torch.Tensor:
    # f_world(d) = f_map(A^T d): coefficients D(A^T) c_map
    A = np.array(_MAP_TO_WORLD)
    return _sh_rotation_matrix(A.T, order)


# --------------------------------------------------------------------------
# EnvironmentMap
# --------------------------------------------------------------------------
class EnvironmentMap:
    r"""An equirectangular (latitude-longitude) radiance map in the DiLiGenT world frame.

    Args:
        data: ``(H, W, C)`` float tensor of radiance (row 0 = zenith, +y; see the
            module docstring for the column layout). It may require grad: every
            derived quantity (SH coefficients, renders) is differentiable in it.
        rotation: turn about +y in radians (counter-clockwise seen from above).

    Example:
        >>> env = EnvironmentMap(torch.ones(8, 16, 3, dtype=torch.float64))
        >>> env.shape
        (8, 16, 3)
        >>> c = env.sh_coefficients(2)
        >>> round(float(c[0, 0]), 6), float(c[:, 1:].abs().max()) < 1e-12  # sqrt(4 pi); no higher orders
        (3.544908, True)
    """

    def __init__(self, data: torch.Tensor, rotation: float = 0.0) -> None:
        check_tensor(data, "data")
        check_shape(data, "data", ("H", "W", "C"))
        if data.numel() == 0:
            raise ValueError(f"`data` must have H, W, C >= 1, got shape {tuple(data.shape)}")
        if isinstance(rotation, torch.Tensor):
            rotation = float(rotation)
        if not isinstance(rotation, (int, float)) or not math.isfinite(rotation):
            raise TypeError(f"`rotation` must be a finite float (radians), got {rotation!r}")
        self.data = data
        self.rotation = float(rotation)

    # ----------------------------------------------------------- constructors
    @classmethod
    def from_exr(cls, path, dtype: torch.dtype = torch.float32, device=None, rotation: float = 0.0) -> "EnvironmentMap":
        """Read an RGB EXR with :func:`torch_hsh.io.read_envmap` (``(H, W, 3)``, row 0 = zenith).

        Example:
            >>> env = EnvironmentMap.from_exr("../shared/data/envmaps/venice_sunset_1k.exr")  # doctest: +SKIP
            >>> env.shape  # doctest: +SKIP
            (512, 1024, 3)
        """
        from ..io.exr import read_envmap

        arr = np.ascontiguousarray(read_envmap(path), dtype=np.float64)
        if not np.isfinite(arr).all():
            raise ValueError(f"{path}: the environment map contains NaN or Inf values")
        return cls(torch.from_numpy(arr).to(dtype=dtype, device=device), rotation)

    @classmethod
    def from_sh(cls, coefficients: torch.Tensor, height: int, width: int) -> "EnvironmentMap":
        """Map of height x width texels holding the SH expansion ``(C, (N+1)**2)`` at texel centres.

        A band-limited version of a map ``env`` (with rotation 0) is
        ``EnvironmentMap.from_sh(env.sh_coefficients(N), env.height, env.width)``.

        Example:
            >>> c = torch.zeros(1, 4, dtype=torch.float64); c[0, 0] = math.sqrt(4 * math.pi)
            >>> round(EnvironmentMap.from_sh(c, 4, 8).data.max().item(), 12)
            1.0
        """
        H, W = _check_hw(height, width)
        check_tensor(coefficients, "coefficients")
        check_shape(coefficients, "coefficients", ("C", "(N+1)**2"))
        N = _sh_order(coefficients.shape[-1], "coefficients")
        d = equirect_directions(H, W, 0.0, coefficients.dtype, coefficients.device)
        return cls(real_sh(d, N) @ coefficients.T)

    # ----------------------------------------------------------- geometry
    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def channels(self) -> int:
        return int(self.data.shape[2])

    @property
    def shape(self) -> Tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape)  # type: ignore[return-value]

    def directions(self) -> torch.Tensor:
        """World directions of the texel centres (after the rotation), ``(H, W, 3)``."""
        return equirect_directions(self.height, self.width, self.rotation, self.data.dtype, self.data.device)

    def solid_angles(self) -> torch.Tensor:
        """Exact solid angles of the texels, ``(H, W)`` (they sum to 4 pi)."""
        return equirect_solid_angles(self.height, self.width, self.data.dtype, self.data.device)

    def power(self) -> torch.Tensor:
        r"""Total power :math:`\int L\, d\omega` per channel, ``(C,)``."""
        return torch.einsum("hwc,hw->c", self.data, self.solid_angles())

    def rotated(self, angle: float) -> "EnvironmentMap":
        """The same map turned by ``angle`` radians about +y (shares ``data``).

        Example:
            >>> env = EnvironmentMap(torch.rand(4, 8, 3))
            >>> env.rotated(0.5).rotated(-0.5).rotation
            0.0
        """
        if isinstance(angle, torch.Tensor):
            angle = float(angle)
        if not isinstance(angle, (int, float)) or not math.isfinite(angle):
            raise TypeError(f"`angle` must be a finite float (radians), got {angle!r}")
        return EnvironmentMap(self.data, self.rotation + float(angle))

    def to(self, *args, **kwargs) -> "EnvironmentMap":
        """Move/cast the data (``torch.Tensor.to`` arguments)."""
        return EnvironmentMap(self.data.to(*args, **kwargs), self.rotation)

    def downsample(self, factor: Union[int, Tuple[int, int]]) -> "EnvironmentMap":
        r"""Average blocks of ``factor`` (or ``(fh, fw)``) texels, weighted by solid angle.

        Each new texel holds :math:`\sum L_t \Omega_t / \sum \Omega_t` over its block, so
        the total power :meth:`power` (and the order-0 SH coefficient) is preserved
        exactly. ``H`` and ``W`` must be divisible by the factors.

        Example:
            >>> env = EnvironmentMap(torch.rand(8, 16, 3, dtype=torch.float64))
            >>> small = env.downsample(4)
            >>> small.shape, torch.allclose(small.power(), env.power())
            ((2, 4, 3), True)
        """
        if isinstance(factor, (tuple, list)):
            if len(factor) != 2:
                raise ValueError(f"`factor` must be an int or a pair (fh, fw), got {factor!r}")
            fh, fw = factor
        else:
            fh = fw = factor
        for v in (fh, fw):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"`factor` entries must be positive integers, got {factor!r}")
        H, W, C = self.shape
        if H % fh or W % fw:
            raise ValueError(f"map of {H}x{W} texels is not divisible by the factor ({fh}, {fw})")
        om = self.solid_angles()
        num = (self.data * om.unsqueeze(-1)).reshape(H // fh, fh, W // fw, fw, C).sum((1, 3))
        den = om.reshape(H // fh, fh, W // fw, fw).sum((1, 3)).unsqueeze(-1)
        return EnvironmentMap(num / den, self.rotation)

    def sh_coefficients(self, order: int) -> torch.Tensor:
        """Real SH coefficients ``(C, (order+1)**2)`` in the world frame; see :func:`sh_coefficients`."""
        return sh_coefficients(self, order)

    def __repr__(self) -> str:
        H, W, C = self.shape
        return f"EnvironmentMap({H}x{W}, C={C}, rotation={self.rotation:g}, dtype={self.data.dtype})"


def procedural_sky(sun, sun_rgb, sky_rgb, ground_rgb, height: int = 32, dtype=torch.float64,
                   device=None) -> "EnvironmentMap":
    r"""A small procedural sky for examples and tests, no file needed.

    In the map frame (``y`` up, :func:`equirect_directions`): the sky ``sky_rgb * (1 + y) / 2`` above the
    horizon, the ground ``ground_rgb * (0.6 + 0.4 |y|)`` below it, plus a sun lobe
    ``sun_rgb * exp(40 (d . s - 1))`` around the direction ``s``.

    Args:
        sun: ``(3,)`` direction of the sun in the map frame (normalised here).
        sun_rgb, sky_rgb, ground_rgb: ``(3,)`` RGB radiances (the sun's at the lobe's peak).
        height: texel rows; the map is ``height x 2 height``.

    Returns:
        An :class:`EnvironmentMap` of ``(height, 2 height, 3)`` texels.

    Example:
        >>> env = procedural_sky((0.0, 0.9, 0.44), (2.0, 2.0, 2.2), (0.4, 0.5, 0.7), (0.3, 0.3, 0.28), height=16)
        >>> tuple(env.data.shape)
        (16, 32, 3)
    """
    d = equirect_directions(height, 2 * height, dtype=dtype, device=device)
    s = torch.nn.functional.normalize(torch.as_tensor(sun, dtype=dtype, device=device), dim=0)
    y = d[..., 1:2]
    upper = torch.as_tensor(sky_rgb, dtype=dtype, device=device) * (0.5 + 0.5 * y.clamp(min=0))
    lower = torch.as_tensor(ground_rgb, dtype=dtype, device=device) * (0.6 + 0.4 * (-y).clamp(min=0))
    lobe = torch.exp(40.0 * ((d * s).sum(-1, keepdim=True) - 1.0)) * torch.as_tensor(sun_rgb, dtype=dtype, device=device)
    return EnvironmentMap(torch.where(y >= 0, upper, lower) + lobe)


def _sh_order(k: int, name: str) -> int:
    n = int(math.isqrt(int(k)))
    if n * n != k or n < 1:
        raise ValueError(f"`{name}` must have (N+1)**2 entries on its last axis (1, 4, 9, 16, ...), got {k}")
    return n - 1


def sh_coefficients(env: EnvironmentMap, order: int) -> torch.Tensor:
    r"""World-frame real SH coefficients of a piecewise-constant map, ``(C, (order+1)**2)``.

    :math:`c_{c,k} = \sum_t L_{t,c} \int_{\text{texel } t} Y_k\, d\omega`, each texel integral
    exact to float64 rounding (closed form in azimuth, Gauss–Legendre over the rows,
    in the map's own up = y frame, then a fixed rotation to world z). Linear and
    differentiable in ``env.data``.

    Example:
        >>> env = EnvironmentMap(torch.rand(16, 32, 3, dtype=torch.float64))
        >>> c = sh_coefficients(env, 4)
        >>> torch.allclose(c[:, 0] * math.sqrt(4 * math.pi), env.power())
        True
    """
    if not isinstance(env, EnvironmentMap):
        raise TypeError(f"`env` must be an EnvironmentMap, got {type(env).__name__}")
    N = check_order(order)
    G, F = _texel_tables(env.height, env.width, N, env.rotation)
    dt, dev = env.data.dtype, env.data.device
    G, F = G.to(dt).to(dev), F.to(dt).to(dev)
    S = torch.einsum("hwc,wk->hck", env.data, F)  # (H, C, K)
    cmap = torch.einsum("hck,hk->ck", S, G)
    return cmap @ _map_to_world(N).to(dtype=dt, device=dev).T


def sh_evaluate(coefficients: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate an SH expansion ``(C, (N+1)**2)`` at world directions ``(..., 3)``; returns ``(..., C)``.

    Example:
        >>> c = torch.zeros(2, 4, dtype=torch.float64); c[:, 0] = math.sqrt(4 * math.pi)
        >>> sh_evaluate(c, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)).round(decimals=12)
        tensor([[1., 1.]], dtype=torch.float64)
    """
    check_tensor(coefficients, "coefficients")
    check_dirs(dirs, "dirs")
    check_same([("coefficients", coefficients), ("dirs", dirs)])
    check_shape(coefficients, "coefficients", ("C", "(N+1)**2"))
    N = _sh_order(coefficients.shape[-1], "coefficients")
    return real_sh(dirs, N) @ coefficients.T


# --------------------------------------------------------------------------
# Frequency-space rendering
# --------------------------------------------------------------------------
def _safe_azimuth(n: torch.Tensor):
    """cos/sin of the normal's azimuth alpha and sin(beta) = |n_xy|; frozen (alpha = 0) at the pole."""
    nx, ny = n[..., 0], n[..., 1]
    r2 = nx * nx + ny * ny
    eps = _eps(n.dtype)
    ok = r2 > eps * eps
    r = torch.sqrt(torch.where(ok, r2, torch.ones_like(r2)))
    ca = torch.where(ok, nx / r, torch.ones_like(nx))
    sa = torch.where(ok, ny / r, torch.zeros_like(ny))
    rho = torch.where(ok, r, r2.detach().sqrt())
    return ca, sa, rho


def _render_chunk(n: torch.Tensor, a: torch.Tensor, Q: torch.Tensor, c: dict, N: int, P: int) -> torch.Tensor:
    """n (B, 3) unit, a (B or 1, C, K), Q (2N+1, (2N+1) C Lp) -> (B, C)."""
    B = n.shape[0]
    Lp = c["W"].shape[1]
    C = Q.shape[1] // ((2 * N + 1) * Lp)
    ca, sa, rho = _safe_azimuth(n)
    nz = n[..., 2]
    REa, IMa = complex_powers(ca, sa, N)
    REb, IMb = complex_powers(nz, rho, N)
    trig_a = torch.cat([REa, IMa], -1)  # (B, 2N+1): 1, cos m alpha, sin m alpha
    trig_b = torch.cat([REb, IMb], -1)  # (B, 2N+1): 1, cos m beta, sin m beta
    U = (trig_a @ Q).reshape(B, 2 * N + 1, C * Lp)
    E = torch.bmm(trig_b.unsqueeze(1), U).reshape(B, C, Lp)  # lighting integrals E_pq
    # Theta_p^q(theta_o): HSH of the local view (sin, 0, cos) over Phi_q(0)
    vloc = torch.stack([rho, torch.zeros_like(rho), nz], -1)
    Th = hsh(vloc, P).index_select(1, c["th_cols"]) * c["th_scale"]  # (B, Lp)
    Ty = torch.cat([Th * (1.0 / math.sqrt(2.0)), Th, Th.new_zeros(B, 1)], -1)  # (B, 2Lp+1)
    if a.shape[0] == 1:  # shared BRDF: weights of E_pq by one small GEMM
        A = (c["A1"].reshape(-1, Lp, a.shape[-1]) @ a[0].t()).reshape(Ty.shape[1], -1)  # (2Lp+1, Lp C')
        w = (Ty @ A).reshape(B, Lp, -1)  # (B, Lp, C')
        out = (E * w.transpose(1, 2)).sum(-1)
    else:
        w = (a * Ty.index_select(1, c["j1"]).unsqueeze(1)) @ c["S1"] + (
            a * Ty.index_select(1, c["j2"]).unsqueeze(1)
        ) @ c["S2"]  # (B, C', Lp)
        out = (E * w).sum(-1)
    return torch.where((nz >= 0).unsqueeze(-1), out, torch.zeros_like(out))


def _lighting_coefficients(env, light_order, like: torch.Tensor) -> Tuple[torch.Tensor, int]:
    if isinstance(env, EnvironmentMap):
        if light_order is None:
            raise ValueError("`light_order` is required when `env` is an EnvironmentMap")
        N = check_order(light_order, "light_order")
        if env.data.dtype != like.dtype or env.data.device != like.device:
            raise TypeError(
                f"`env` data is {env.data.dtype} on {env.data.device} but `normals` is {like.dtype} on {like.device}; "
                "use env.to(...)"
            )
        return env.sh_coefficients(N), N
    if isinstance(env, torch.Tensor):
        check_tensor(env, "env")
        check_same([("normals", like), ("env", env)])
        if env.dim() != 2:
            raise ValueError(f"`env` as SH coefficients must have shape (C, (N+1)**2), got {tuple(env.shape)}")
        N = _sh_order(env.shape[-1], "env")
        if light_order is not None:
            Nl = check_order(light_order, "light_order")
            if Nl > N:
                raise ValueError(f"`light_order`={Nl} exceeds the order {N} of the given SH coefficients")
            env, N = env[:, : (Nl + 1) ** 2], Nl
        return env, N
    raise TypeError(f"`env` must be an EnvironmentMap or SH coefficients (C, (N+1)**2), got {type(env).__name__}")


def render_envmap(
    normals: torch.Tensor,
    coefficients: torch.Tensor,
    env: Union[EnvironmentMap, torch.Tensor],
    light_order: Optional[int] = None,
    chunk_size: int = 4096,
) -> torch.Tensor:
    r"""Outgoing radiance toward the camera (+z, orthographic) under environment lighting.

    Computes :math:`L_o(n) = \int_{n\cdot\omega > 0} L_N(\omega) f(\omega', v') (n\cdot\omega)\, d\omega`
    exactly for the lighting :math:`L_N` truncated to SH order ``light_order`` and the
    isotropic Helmholtz BRDF ``f`` (no Monte Carlo; see the module docstring).

    Args:
        normals: ``(*S, 3)`` world normals (normalised here).
        coefficients: ``(*S', C, K)`` isotropic Helmholtz coefficients, ``*S'``
            broadcastable with ``*S`` (e.g. ``(C, K)`` for one shared BRDF); the
            order P is inferred from K.
        env: an :class:`EnvironmentMap` (``C`` or 1 channels) or precomputed SH
            coefficients ``(C, (N+1)**2)`` (pass these in loops to avoid recomputing).
        light_order: SH order N of the lighting (required for a map; for
            coefficients it may truncate them).
        chunk_size: pixels per chunk (memory knob only).

    Returns:
        ``(*S, C)`` radiance (not clamped: a truncated expansion may ring below 0).
        Zero where ``n_z < 0``. Differentiable w.r.t. normals, coefficients and env.

    Example:
        >>> env = EnvironmentMap(torch.full((8, 16, 3), 2.0, dtype=torch.float64))
        >>> a = torch.zeros(3, 4, dtype=torch.float64); a[:, 0] = 2 * 0.5  # Lambertian, albedo 0.5
        >>> n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
        >>> render_envmap(n, a, env, light_order=2)  # rho * L
        tensor([[1.0000, 1.0000, 1.0000],
                [1.0000, 1.0000, 1.0000]], dtype=torch.float64)
    """
    check_dirs(normals, "normals")
    check_tensor(coefficients, "coefficients", min_dims=2)
    check_same([("normals", normals), ("coefficients", coefficients)])
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}")
    L, N = _lighting_coefficients(env, light_order, normals)
    P = order_from_num_functions(coefficients.shape[-1])
    Ca, Cl = coefficients.shape[-2], L.shape[0]
    if Ca != Cl and Ca != 1 and Cl != 1:
        raise ValueError(f"channel mismatch: `coefficients` has C={Ca} but the lighting has C={Cl} (need equal or 1)")
    C = max(Ca, Cl)
    S = broadcast_shapes([("normals", normals.shape[:-1]), ("coefficients", coefficients.shape[:-2])])
    dt, dev = normals.dtype, normals.device
    c = _render_consts(N, P, dt, dev)
    Lc = L.expand(C, -1)
    ZL = c["Ocos"].unsqueeze(1) * Lc + c["Osin"].unsqueeze(1) * Lc.index_select(1, c["partner"])  # Z_a L
    M = ZL @ c["Jm"].t()  # (2N+1, C, Kl): J_- Z_a L
    Q = torch.einsum("ack,bkj->abcj", M, c["Bsel"]).reshape(2 * N + 1, -1)  # (2N+1, (2N+1) C Lp)
    n = torch.nn.functional.normalize(normals.expand(*S, 3).reshape(-1, 3), dim=-1)
    if coefficients.shape[:-2] == S:
        a = coefficients.reshape(-1, Ca, coefficients.shape[-1])
    elif all(s == 1 for s in coefficients.shape[:-2]):
        a = coefficients.reshape(1, Ca, coefficients.shape[-1])
    else:
        a = coefficients.expand(*S, Ca, coefficients.shape[-1]).reshape(-1, Ca, coefficients.shape[-1])
    nn_ = n.shape[0]
    outs = []
    for s in range(0, nn_, chunk_size):
        e = min(s + chunk_size, nn_)
        ac = a if a.shape[0] == 1 else a[s:e]
        outs.append(_render_chunk(n[s:e], ac, Q, c, N, P))
    out = torch.cat(outs, 0) if len(outs) != 1 else outs[0]
    if torch.is_grad_enabled() and n.requires_grad:
        out = _pole_gradients(out, n, a, Q, c, N, P)
    if out.shape[-1] != C:
        out = out.expand(-1, C)
    return out.reshape(*S, C)


def _pole_gradients(out: torch.Tensor, n: torch.Tensor, a: torch.Tensor, Q: torch.Tensor, c: dict, N: int, P: int):
    """Exact values, but gradients w.r.t. the normal taken at ``|n_xy| = delta`` for pixels closer to the view axis.

    The Euler angles are singular at ``n = v``: there the angle path loses the tangential gradient,
    and just off it the gradient suffers cancellation (relative error ~ machine eps / |n_xy|). The
    function is smooth, so its gradient at distance ``delta`` (1e-6 in float64, 3e-4 in float32) from
    the axis differs from the true one by O(delta) (measured: ~1e-5 relative in float64, ~5e-3 in float32).
    """
    delta = 1e-6 if n.dtype == torch.float64 else 3e-4
    r2 = (n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1]).detach()
    idx = torch.nonzero((r2 < delta * delta) & (n[:, 2].detach() > 0)).flatten()
    if idx.numel() == 0:
        return out
    npole = n.index_select(0, idx)
    shift = torch.zeros_like(npole)
    shift[:, 0] = delta - npole[:, 0].detach()  # move to n_x = delta (the tangential offset), keep n_z
    shift[:, 1] = -npole[:, 1].detach()
    moved = torch.nn.functional.normalize(npole + shift, dim=-1)
    ap = a if a.shape[0] == 1 else a.index_select(0, idx)
    g = _render_chunk(moved, ap, Q, c, N, P)
    return out.index_copy(0, idx, out.index_select(0, idx).detach() + (g - g.detach()))


def render_envmap_reference(
    normals: torch.Tensor,
    brdf: Union[torch.Tensor, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]],
    env: EnvironmentMap,
    supersample: int = 1,
    chunk_size: int = 2 ** 22,
) -> torch.Tensor:
    r"""Brute-force texel quadrature of the environment-lit radiance (ground truth).

    :math:`L_o(n) = \sum_t L_t\, \Omega_t\, f(\omega_t', v')\, \max(0, n\cdot\omega_t)` over the
    texels ``t`` of ``env`` (directions at texel centres, exact solid angles); with
    ``supersample = s`` every texel is split into ``s x s`` sub-texels of the same
    radiance, so the result converges to the exact integral of the piecewise-constant
    map as ``s`` grows. Texels with zero radiance are skipped. The BRDF is evaluated by
    :func:`torch_hsh.render.brdf_cosine` (the point-light renderer's code).

    Args:
        normals: ``(*S, 3)``.
        brdf: coefficient maps ``(*S, C, K)`` or ``(C, K)`` (isotropic Helmholtz,
            not clamped), or a callable ``f(wi, wo) -> (T, *S, C)`` on local directions
            (an analytic model of :mod:`torch_hsh.brdf`).
        env: the map (``C`` or 1 channels).
        supersample: sub-texels per texel side.
        chunk_size: values per chunk, a memory knob: a chunk holds about ``chunk_size`` values
            (texels x pixels x K), i.e. ``chunk_size // (pixels x K)`` texels.

    Returns:
        ``(*S, C)`` radiance toward the camera.

    Example:
        >>> env = EnvironmentMap(torch.ones(16, 32, 1, dtype=torch.float64))
        >>> lam = lambda wi, wo: torch.full(wi.shape[:-1] + (1,), 0.5 / math.pi, dtype=wi.dtype)
        >>> n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> abs(float(render_envmap_reference(n, lam, env, supersample=4)) - 0.5) < 2e-3
        True
    """
    if not isinstance(env, EnvironmentMap):
        raise TypeError(f"`env` must be an EnvironmentMap, got {type(env).__name__}")
    check_dirs(normals, "normals")
    check_same([("normals", normals), ("env.data", env.data)])
    if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
        raise ValueError(f"`supersample` must be a positive integer, got {supersample!r}")
    S = normals.shape[:-1]
    if isinstance(brdf, torch.Tensor):
        check_tensor(brdf, "brdf", min_dims=2)
        if brdf.shape[:-2] != S:
            brdf = brdf.expand(*S, *brdf.shape[-2:])
        width = brdf.shape[-1]
    elif callable(brdf):
        width = 64  # unknown memory per evaluation (a basis expansion holds K values): be conservative
    else:
        raise TypeError(f"`brdf` must be coefficient maps or a callable f(wi, wo), got {type(brdf).__name__}")
    data = env.data
    if supersample > 1:
        data = data.repeat_interleave(supersample, 0).repeat_interleave(supersample, 1)
    H, W, C = data.shape
    dirs = equirect_directions(H, W, env.rotation, data.dtype, data.device).reshape(-1, 3)
    w = (data * equirect_solid_angles(H, W, data.dtype, data.device).unsqueeze(-1)).reshape(-1, C)
    keep = (data.detach().reshape(-1, C) != 0).any(-1)
    dirs, w = dirs[keep], w[keep]
    npix = max(1, int(np.prod(S)) if len(S) else 1)
    step = max(1, int(chunk_size // (npix * width)))
    out = None
    for s in range(0, dirs.shape[0], step):
        f = brdf_cosine(normals, dirs[s : s + step], brdf)  # (T, *S, C')
        if f.shape[-1] != C and C != 1 and f.shape[-1] != 1:
            raise ValueError(f"channel mismatch: the BRDF gives C={f.shape[-1]} but `env` has C={C}")
        ws = w[s : s + step]
        part = (f * ws.reshape(ws.shape[0], *([1] * len(S)), C)).sum(0)
        out = part if out is None else out + part
    if out is None:  # an all-black map
        Cb = brdf.shape[-2] if isinstance(brdf, torch.Tensor) else C
        out = normals.new_zeros(*S, max(C, Cb))
    return out


class EnvironmentLighting(torch.nn.Module):
    """SH lighting as a module: learnable (inverse rendering of the light) or fixed.

    Args:
        lighting: an :class:`EnvironmentMap` (projected to ``light_order``) or SH
            coefficients ``(C, (N+1)**2)`` (copied).
        light_order: SH order N (required for a map; optional truncation otherwise).
        learnable: coefficients as an ``nn.Parameter`` (default) or a buffer.

    Shapes:
        ``forward(normals (*S, 3), brdf (*S', C, K))`` -> ``(*S, C)``, i.e.
        :func:`render_envmap` with this lighting.

    Example:
        >>> env = EnvironmentMap(torch.ones(8, 16, 3, dtype=torch.float64))
        >>> light = EnvironmentLighting(env, light_order=2)
        >>> a = torch.zeros(3, 4, dtype=torch.float64); a[:, 0] = 2.0  # Lambertian, albedo 1
        >>> light(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), a).detach()
        tensor([[1.0000, 1.0000, 1.0000]], dtype=torch.float64)
    """

    def __init__(self, lighting: Union[EnvironmentMap, torch.Tensor], light_order: Optional[int] = None,
                 learnable: bool = True) -> None:
        super().__init__()
        if not isinstance(learnable, bool):
            raise TypeError(f"`learnable` must be a bool, got {type(learnable).__name__}")
        if isinstance(lighting, EnvironmentMap):
            if light_order is None:
                raise ValueError("`light_order` is required when `lighting` is an EnvironmentMap")
            coefficients = lighting.sh_coefficients(light_order)
        else:
            tensor = lighting if isinstance(lighting, torch.Tensor) else None
            coefficients, _ = _lighting_coefficients(lighting, light_order, tensor)
        coefficients = coefficients.detach().clone()
        if learnable:
            self.coefficients = torch.nn.Parameter(coefficients)
        else:
            self.register_buffer("coefficients", coefficients)
        self.light_order = _sh_order(coefficients.shape[-1], "lighting")

    def forward(self, normals: torch.Tensor, brdf: torch.Tensor) -> torch.Tensor:
        return render_envmap(normals, brdf, self.coefficients)

    def to_map(self, height: int, width: int) -> EnvironmentMap:
        """The lighting sampled on an equirectangular map (e.g. to look at a recovered light)."""
        return EnvironmentMap.from_sh(self.coefficients.detach(), height, width)

    def extra_repr(self) -> str:
        return f"channels={self.coefficients.shape[0]}, light_order={self.light_order}"
