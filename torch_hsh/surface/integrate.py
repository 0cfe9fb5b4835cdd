r"""Normal integration: from a normal map over a mask to a depth map.

Conventions (the DiLiGenT frame of :mod:`torch_hsh.render.scenes`): ``x`` to the
right, ``y`` up, ``z`` toward the camera; orthographic view. Pixel ``(row,
col)`` is at ``x = col``, ``y = -row`` (pixel units), and the returned
"depth" is the **height** ``z(row, col)`` of the surface in pixel units
(larger = closer to the camera), exactly the height fields of
:func:`torch_hsh.render.scenes.heightfield_normals` and
:func:`torch_hsh.render.visibility.cast_shadow_mask` with ``pixel_size=1``. A unit
normal ``n`` gives the slopes ``dz/dcol = -n_x / n_z`` and ``dz/drow =
+n_y / n_z`` (rows grow downward, ``y`` upward).

Method. Both integrators are weighted least squares over the **edges**
between 4-connected mask pixels ``i -> j`` (one step right or down):

.. math::
    \min_z \sum_{(i,j)} w_{ij}\,(z_j - z_i - t_{ij})^2 ,

a weighted graph-Laplacian system ``L z = A^T W t``:

* ``"poisson"``: ``w = 1`` and ``t`` the trapezoidal slope
  ``(g_i + g_j) / 2`` (the classic Poisson / least-squares integrator on an
  arbitrary mask, natural boundary conditions at the mask border);
* ``"bilateral"``: bilateral normal integration (Cao et al., "Bilateral
  Normal Integration", ECCV 2022), orthographic case. Each pixel has a
  forward and a backward one-sided equation per axis, ``n_z (z_j - z_i) =
  -n_x`` weighted by ``w^+ = sigmoid(k (d_-^2 - d_+^2))`` and ``w^- = 1 -
  w^+`` from the current depth differences ``d_\pm`` (``n_z``-scaled, as in
  the authors' code); the two equations of an edge combine into one edge
  term with ``w_{ij} = w_i^+ n_{z,i}^2 + w_j^- n_{z,j}^2`` and the weighted
  mean slope. Re-weighting is iterated (IRLS) until the energy changes by
  less than ``energy_tol`` (relative). Depth jumps at which the normals are
  inconsistent (e.g. a spiral staircase) stay sharp instead of spreading
  over the whole surface.

Slopes are computed with ``n_z`` clamped to ``min_nz`` (default 0.05,
slopes up to 20 px/px), so grazing or back-facing normals at silhouettes
cannot blow up the solution.

Disconnected mask parts (4-connectivity, :func:`connected_components`) have
unknown relative offsets: nothing in the normals relates them. Every part is
integrated on its own and **shifted to zero mean depth**; callers that know
the offsets (e.g. from a depth sensor) add them afterwards.

Solvers (``solver=``):

* ``"scipy"`` (CPU): the sparse Laplacian (int64 indices) solved by conjugate
  gradients preconditioned with classical algebraic multigrid
  (``pyamg.ruge_stuben_solver``); BLAS is limited to one thread during the
  solve (``threadpoolctl``: vector-sized BLAS calls only lose from threading);
* ``"torch"`` (any device, e.g. CUDA): matrix-free conjugate gradients on the
  ``(H, W)`` grid (the Laplacian is four shifted differences, no index
  arrays), preconditioned by the exact inverse of the Neumann Laplacian of
  the mask's bounding box, applied with DCTs (``torch.fft``; about 10-15
  iterations for 1e-6 on discs and masks with holes), scaled by the
  diagonal for weighted systems;
* ``"auto"``: ``"torch"`` for CUDA tensors, else ``"scipy"``.

Each part is made non-singular by one soft anchor (``+ z_a^2``, which moves
the least-squares minimiser by a constant only, removed by the zero-mean
shift). ``tol`` is the relative residual ``|b - L z| / |b|`` of the linear
solves (1e-6 by default). Internally everything runs in float64; the result
has the dtype and device of ``normals``. Memory is ``O(H W)`` (a few dozen
float64 maps).

Performance (2 CPU threads, disc mask, ``tol=1e-6``): see
``benchmarks/bench_surface.py`` and ``docs/surfaces.md`` (Poisson at 1024^2
in a few seconds with scipy + pyamg).
"""
from __future__ import annotations

import inspect

import math
import time
from typing import Dict, Optional, Tuple

import numpy as np
import torch

from .._checks import check_shape, check_tensor

__all__ = [
    "integrate_normals",
    "connected_components",
    "normals_to_slopes",
    "depth_to_normals",
    "INTEGRATION_METHODS",
]

#: Methods of :func:`integrate_normals`.
INTEGRATION_METHODS = ("poisson", "bilateral")
_SOLVERS = ("auto", "scipy", "torch")


# --------------------------------------------------------------------------- #
# input checks
# --------------------------------------------------------------------------- #
def _check_mask(mask, hw: Tuple[int, ...], device, name: str = "mask") -> torch.Tensor:
    if mask is None:
        return torch.ones(hw, dtype=torch.bool, device=device)
    if not isinstance(mask, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor of shape (H, W), got {type(mask).__name__}")
    check_shape(mask, name, ("H", "W"), sizes={"H": hw[0], "W": hw[1]})
    if mask.dtype != torch.bool:
        if mask.is_floating_point() or mask.is_complex():
            raise TypeError(f"`{name}` must be a bool (or integer 0/1) tensor, got dtype {mask.dtype}")
        mask = mask != 0
    return mask.to(device)


def _check_normals(normals, mask) -> Tuple[torch.Tensor, torch.Tensor]:
    check_tensor(normals, "normals", last_dim=3, min_dims=3, allow_nonfinite=True)
    H, W = normals.shape[-3:-1]
    if H < 1 or W < 1:
        raise ValueError(f"`normals` must have shape (..., H, W, 3) with H, W >= 1, got {tuple(normals.shape)}")
    mask = _check_mask(mask, (H, W), normals.device)
    if not bool(torch.isfinite(normals[..., mask, :]).all()):
        raise ValueError("`normals` contains NaN or Inf inside `mask`; expected finite normals on the mask")
    return normals, mask


def _check_depth(depth, mask) -> Tuple[torch.Tensor, torch.Tensor]:
    """An (H, W) depth map, finite inside ``mask``, and the (H, W) bool mask (default: every pixel)."""
    check_tensor(depth, "depth", allow_nonfinite=True)
    check_shape(depth, "depth", ("H", "W"))
    m = _check_mask(mask, tuple(depth.shape), depth.device)
    if not bool(torch.isfinite(depth[m]).all()):
        raise ValueError("`depth` contains NaN or Inf inside `mask`")
    return depth, m


def _positive_float(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0:
        raise ValueError(f"`{name}` must be a positive finite number, got {x!r}")
    return float(x)


def _positive_int(x, name: str) -> int:
    if isinstance(x, bool) or not isinstance(x, int) or x < 1:
        raise ValueError(f"`{name}` must be a positive integer, got {x!r}")
    return int(x)


# --------------------------------------------------------------------------- #
# small public helpers
# --------------------------------------------------------------------------- #
def connected_components(mask: torch.Tensor) -> Tuple[torch.Tensor, int]:
    r"""Label the 4-connected parts of a mask (the parts integrated separately).

    Two pixels are connected when they share an edge (the integrators only
    use horizontal and vertical differences, so diagonal contact does not
    tie two parts together).

    Args:
        mask: ``(H, W)`` bool tensor.

    Returns:
        ``(labels, n)``: ``(H, W)`` int64 labels on ``mask``'s device, ``0``
        outside the mask and ``1 .. n`` on the parts (raster order of their
        first pixel), and the number of parts ``n``.

    Example:
        >>> m = torch.zeros(4, 6, dtype=torch.bool); m[:, :2] = True; m[1:3, 4:] = True
        >>> lab, n = connected_components(m)
        >>> n, lab[0].tolist()
        (2, [1, 1, 0, 0, 0, 0])
    """
    import scipy.ndimage

    if not isinstance(mask, torch.Tensor) or mask.dim() != 2:
        raise ValueError(f"`mask` must be an (H, W) tensor, got {getattr(mask, 'shape', type(mask).__name__)}")
    m = _check_mask(mask, tuple(mask.shape), mask.device)
    lab, n = scipy.ndimage.label(m.cpu().numpy(), structure=[[0, 1, 0], [1, 1, 1], [0, 1, 0]])
    return torch.from_numpy(lab.astype(np.int64)).to(mask.device), int(n)


def normals_to_slopes(normals: torch.Tensor, min_nz: float = 0.05) -> Tuple[torch.Tensor, torch.Tensor]:
    r"""Depth slopes ``(dz/dcol, dz/drow)`` of unit normals (DiLiGenT frame, orthographic).

    ``dz/dcol = -n_x / n_z`` and ``dz/drow = n_y / n_z`` (rows grow
    downward while ``y`` grows upward), with ``n_z`` clamped to ``>= min_nz``.

    Args:
        normals: ``(..., 3)`` normals (need not be unit: only ratios matter).
        min_nz: lower clamp of ``n_z`` (bounds the slopes by ``1 / min_nz``).

    Returns:
        Two ``(...)`` tensors.

    Example:
        >>> n = torch.tensor([-0.6, 0.0, 0.8])  # tilted left: depth rises to the right
        >>> normals_to_slopes(n)
        (tensor(0.7500), tensor(0.))
    """
    check_tensor(normals, "normals", last_dim=3, allow_nonfinite=True)
    min_nz = _positive_float(min_nz, "min_nz")
    nz = normals[..., 2].clamp(min=min_nz)
    return -normals[..., 0] / nz, normals[..., 1] / nz


def depth_to_normals(depth: torch.Tensor, mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    r"""Unit normals of a depth (height) map, using only differences inside the mask.

    Per axis: the central difference where both neighbours are in the mask,
    the one-sided difference where only one is, 0 where none is; then
    ``n = normalize(-dz/dcol, dz/drow, 1)`` (the inverse of
    :func:`normals_to_slopes`). Values outside ``mask`` (NaN allowed) are
    never read; the result is 0 there.

    Args:
        depth: ``(H, W)`` heights in pixel units (z toward the camera).
        mask: optional ``(H, W)`` bool (default: every pixel).

    Returns:
        ``(H, W, 3)`` unit normals (zero outside the mask).

    Example:
        >>> z = torch.arange(5.0)[None, :].expand(4, 5) * 0.75  # rises to the right
        >>> depth_to_normals(z)[1, 2]
        tensor([-0.6000,  0.0000,  0.8000])
    """
    depth, m = _check_depth(depth, mask)
    z = torch.where(m, depth, torch.zeros_like(depth))

    def axis_diff(z, m, dim):
        zf = torch.zeros_like(z)
        zb = torch.zeros_like(z)
        mf = torch.zeros_like(m)
        mb = torch.zeros_like(m)
        n = z.shape[dim]
        if n > 1:
            zf.narrow(dim, 0, n - 1).copy_(z.narrow(dim, 1, n - 1))
            mf.narrow(dim, 0, n - 1).copy_(m.narrow(dim, 1, n - 1))
            zb.narrow(dim, 1, n - 1).copy_(z.narrow(dim, 0, n - 1))
            mb.narrow(dim, 1, n - 1).copy_(m.narrow(dim, 0, n - 1))
        both = mf & mb
        d = torch.where(both, (zf - zb) / 2, torch.where(mf, zf - z, torch.where(mb, z - zb, torch.zeros_like(z))))
        return d

    dcol = axis_diff(z, m, 1)
    drow = axis_diff(z, m, 0)
    n = torch.stack([-dcol, drow, torch.ones_like(z)], dim=-1)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    return n * m[..., None].to(n.dtype)


# --------------------------------------------------------------------------- #
# the edge least-squares system on the (H, W) grid
# --------------------------------------------------------------------------- #
class _Edges:
    """Weights and targets of the horizontal ``(H, W-1)`` and vertical ``(H-1, W)`` edges."""

    def __init__(self, wh, th, wv, tv):
        self.wh, self.th, self.wv, self.tv = wh, th, wv, tv

    def rhs(self) -> torch.Tensor:
        """``A^T W t`` on the grid."""
        H, W = self.wv.shape[0] + 1, self.wh.shape[1] + 1
        b = torch.zeros(H, W, dtype=self.wh.dtype, device=self.wh.device)
        fh, fv = self.wh * self.th, self.wv * self.tv
        b[:, 1:] += fh
        b[:, :-1] -= fh
        b[1:] += fv
        b[:-1] -= fv
        return b

    def diag(self) -> torch.Tensor:
        H, W = self.wv.shape[0] + 1, self.wh.shape[1] + 1
        d = torch.zeros(H, W, dtype=self.wh.dtype, device=self.wh.device)
        d[:, 1:] += self.wh
        d[:, :-1] += self.wh
        d[1:] += self.wv
        d[:-1] += self.wv
        return d

    def lap(self, z: torch.Tensor) -> torch.Tensor:
        """``A^T W A z`` on the grid (matrix free)."""
        out = torch.zeros_like(z)
        dh = self.wh * (z[:, 1:] - z[:, :-1])
        dv = self.wv * (z[1:] - z[:-1])
        out[:, 1:] += dh
        out[:, :-1] -= dh
        out[1:] += dv
        out[:-1] -= dv
        return out

    def energy(self, z: torch.Tensor) -> float:
        rh = z[:, 1:] - z[:, :-1] - self.th
        rv = z[1:] - z[:-1] - self.tv
        return float((self.wh * rh * rh).sum() + (self.wv * rv * rv).sum())


def _edge_masks(m: torch.Tensor, dtype) -> Tuple[torch.Tensor, torch.Tensor]:
    mf = m.to(dtype)
    return mf[:, 1:] * mf[:, :-1], mf[1:] * mf[:-1]


def _poisson_edges(gc, gr, m) -> _Edges:
    eh, ev = _edge_masks(m, gc.dtype)
    return _Edges(eh, 0.5 * (gc[:, 1:] + gc[:, :-1]) * eh, ev, 0.5 * (gr[1:] + gr[:-1]) * ev)


def _anchors(labels: torch.Tensor, n: int) -> torch.Tensor:
    """One pixel per part (its first in raster order) as a flat index tensor."""
    flat = labels.flatten()
    pos = torch.arange(flat.numel(), device=flat.device)
    first = torch.full((n + 1,), flat.numel(), dtype=torch.int64, device=flat.device)
    first.scatter_reduce_(0, flat, pos, reduce="amin")
    return first[1:]


def _zero_mean(z: torch.Tensor, labels: torch.Tensor, n: int) -> torch.Tensor:
    flat = labels.flatten()
    s = torch.zeros(n + 1, dtype=z.dtype, device=z.device).index_add_(0, flat, z.flatten())
    c = torch.bincount(flat, minlength=n + 1).to(z.dtype).clamp(min=1)
    mean = s / c
    mean[0] = 0
    return z - mean[flat].reshape(z.shape)


# ---- scipy + pyamg --------------------------------------------------------- #
def _pyamg():
    try:
        import pyamg
    except ImportError as e:  # pragma: no cover - declared in setup.py
        raise ImportError(
            "solver='scipy' of torch_hsh.surface needs pyamg (pip install pyamg); or use solver='torch'"
        ) from e
    return pyamg


def _solve_scipy(edges: _Edges, m: torch.Tensor, anchors: torch.Tensor, z0, tol: float, max_iter: int, cache=None):
    # The Krylov loops call BLAS on single vectors; multithreaded OpenBLAS turns each such call into
    # a thread synchronisation (20x slower on a busy machine), so BLAS runs on one thread here.
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _solve_scipy_impl(edges, m, anchors, z0, tol, max_iter, cache)


def _solve_scipy_impl(edges, m, anchors, z0, tol, max_iter, cache):
    import scipy.sparse as sp

    pyamg = _pyamg()
    H, W = m.shape
    mc = m.cpu().numpy()
    flat_pix = np.flatnonzero(mc).astype(np.int64)
    N = flat_pix.size
    idmap = np.full(H * W, -1, dtype=np.int64)
    idmap[flat_pix] = np.arange(N, dtype=np.int64)
    wh = edges.wh.cpu().numpy()
    wv = edges.wv.cpu().numpy()
    rh, ch = np.nonzero(wh)
    rv, cv = np.nonzero(wv)
    rh, ch, rv, cv = (a.astype(np.int64) for a in (rh, ch, rv, cv))
    i = np.concatenate([idmap[rh * W + ch], idmap[rv * W + cv]])
    j = np.concatenate([idmap[rh * W + ch + 1], idmap[(rv + 1) * W + cv]])
    w = np.concatenate([wh[rh, ch], wv[rv, cv]])
    anc = idmap[anchors.cpu().numpy()]
    rows = np.concatenate([i, j, i, j, anc])
    cols = np.concatenate([i, j, j, i, anc])
    vals = np.concatenate([w, w, -w, -w, np.ones(anc.size)])
    Lmat = sp.csr_matrix((vals, (rows, cols)), shape=(N, N))
    Lmat.sum_duplicates()
    b = edges.rhs().cpu().numpy().reshape(-1)[flat_pix]
    x0 = None if z0 is None else z0.cpu().numpy().reshape(-1)[flat_pix]
    bn = float(np.linalg.norm(b))
    if bn == 0:
        return torch.zeros(H, W, dtype=torch.float64, device=m.device), {"iterations": 0, "residual": 0.0}
    if cache is not None and cache.get("ml") is not None:
        # re-weighted system (bilateral): reuse the last AMG hierarchy as a preconditioner
        import scipy.sparse.linalg as spla

        count = [0]

        def _cb(_):
            count[0] += 1

        # scipy >= 1.12 names the relative tolerance `rtol`; older releases call it `tol`
        tol_kw = {"rtol": tol} if "rtol" in inspect.signature(spla.cg).parameters else {"tol": tol}
        x, _ = spla.cg(Lmat, b, x0=x0, maxiter=max_iter, M=cache["ml"].aspreconditioner(), callback=_cb, **tol_kw)
        its = count[0]
        if its > max(2 * cache["iterations"], 15):
            cache["ml"] = None  # the weights drifted: rebuild next time
    else:
        ml = pyamg.ruge_stuben_solver(Lmat)
        res = []
        x = ml.solve(b, x0=x0, tol=tol, maxiter=max_iter, accel="cg", residuals=res)
        its = max(len(res) - 1, 0)
        if cache is not None:
            cache.update(ml=ml, iterations=its)
    rel = float(np.linalg.norm(b - Lmat @ x) / bn)
    out = np.zeros(H * W)
    out[flat_pix] = x
    z = torch.from_numpy(out.reshape(H, W)).to(m.device)
    return z, {"iterations": its, "residual": rel}


# ---- torch: matrix-free PCG with a DCT preconditioner ---------------------- #
def _dct2_raw(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``X_k = sum_n x_n cos(pi k (2n+1) / (2N))`` along ``dim`` (via a 2N-point FFT)."""
    N = x.shape[dim]
    X = torch.fft.fft(x, n=2 * N, dim=dim).narrow(dim, 0, N)
    k = torch.arange(N, dtype=x.dtype, device=x.device)
    shape = [1] * x.dim()
    shape[dim] = N
    return (X * torch.polar(torch.ones_like(k), -math.pi * k / (2 * N)).reshape(shape)).real


def _dct3_raw(X: torch.Tensor, dim: int) -> torch.Tensor:
    """``x_n = sum_k X_k cos(pi k (2n+1) / (2N))`` along ``dim`` (transpose of :func:`_dct2_raw`)."""
    N = X.shape[dim]
    k = torch.arange(N, dtype=X.dtype, device=X.device)
    shape = [1] * X.dim()
    shape[dim] = N
    w = X * torch.polar(torch.ones_like(k), math.pi * k / (2 * N)).reshape(shape)
    return (torch.fft.ifft(w, n=2 * N, dim=dim).narrow(dim, 0, N) * (2 * N)).real


class _DCTPreconditioner:
    """Exact inverse of the Neumann Laplacian of a ``(h, w)`` box, applied with orthonormal DCTs."""

    def __init__(self, h: int, w: int, n_pix: int, dtype, device):
        kh = torch.arange(h, dtype=dtype, device=device)
        kw = torch.arange(w, dtype=dtype, device=device)
        lam = (2 - 2 * torch.cos(math.pi * kh / h))[:, None] + (2 - 2 * torch.cos(math.pi * kw / w))[None, :]
        inv = 1.0 / lam.clamp(min=1e-300)
        inv[0, 0] = float(n_pix)  # the anchored constant mode has eigenvalue ~ 1 / n_pix
        sh = torch.full((h,), math.sqrt(2.0 / h), dtype=dtype, device=device)
        sh[0] = math.sqrt(1.0 / h)
        sw = torch.full((w,), math.sqrt(2.0 / w), dtype=dtype, device=device)
        sw[0] = math.sqrt(1.0 / w)
        self.inv, self.sh, self.sw = inv, sh[:, None], sw[None, :]

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        c = _dct2_raw(_dct2_raw(r, 0) * self.sh, 1) * self.sw
        c = c * self.inv
        return _dct3_raw(_dct3_raw(c * self.sw, 1) * self.sh, 0)


def _solve_torch(edges: _Edges, m: torch.Tensor, anchors: torch.Tensor, z0, tol: float, max_iter: int):
    H, W = m.shape
    rows = torch.nonzero(m.any(dim=1)).flatten()
    cols = torch.nonzero(m.any(dim=0)).flatten()
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    # crop everything to the bounding box of the mask
    hs, vs = (slice(r0, r1), slice(c0, c1 - 1)), (slice(r0, r1 - 1), slice(c0, c1))
    e = _Edges(edges.wh[hs], edges.th[hs], edges.wv[vs], edges.tv[vs])
    mb = m[r0:r1, c0:c1]
    mf = mb.to(torch.float64)
    anc = torch.zeros(H * W, dtype=torch.float64, device=m.device)
    anc[anchors] = 1.0
    anc = anc.reshape(H, W)[r0:r1, c0:c1]
    h, w = r1 - r0, c1 - c0
    n_pix = int(mb.sum())
    prec = _DCTPreconditioner(h, w, n_pix, torch.float64, m.device)
    eh, ev = _edge_masks(mb, torch.float64)
    deg = _Edges(eh, None, ev, None).diag() + anc
    diag = e.diag() + anc
    scale = torch.where(mb, torch.sqrt(deg / diag.clamp(min=1e-300)), torch.zeros_like(mf))

    def A(z):
        return e.lap(z) + anc * z

    def M(r):
        return scale * prec(scale * r)

    b = e.rhs() * mf
    bn = float(torch.linalg.vector_norm(b))
    out = torch.zeros(H, W, dtype=torch.float64, device=m.device)
    if bn == 0:
        return out, {"iterations": 0, "residual": 0.0}
    x = torch.zeros_like(b) if z0 is None else z0[r0:r1, c0:c1] * mf
    r = b - A(x)
    z = M(r)
    p = z.clone()
    rz = (r * z).sum()
    it = 0
    rel = float(torch.linalg.vector_norm(r)) / bn
    while rel > tol and it < max_iter:
        Ap = A(p)
        alpha = rz / (p * Ap).sum()
        x = x + alpha * p
        r = r - alpha * Ap
        it += 1
        rel = float(torch.linalg.vector_norm(r)) / bn
        if rel <= tol:
            break
        z = M(r)
        rz_new = (r * z).sum()
        p = z + (rz_new / rz) * p
        rz = rz_new
    rel = float(torch.linalg.vector_norm(b - A(x))) / bn
    out[r0:r1, c0:c1] = x
    return out, {"iterations": it, "residual": rel}


def _solve(edges, m, labels, n, anchors, z0, solver, tol, max_iter, cache=None):
    if solver == "scipy":
        z, info = _solve_scipy(edges, m, anchors, z0, tol, max_iter, cache)
    else:
        z, info = _solve_torch(edges, m, anchors, z0, tol, max_iter)
    return _zero_mean(z, labels, n) * m, info


# --------------------------------------------------------------------------- #
# bilateral normal integration (Cao et al. 2022), orthographic
# --------------------------------------------------------------------------- #
def _shift(x: torch.Tensor, dim: int, forward: bool) -> torch.Tensor:
    """Neighbour values: ``out[i] = x[i + 1]`` (forward) or ``x[i - 1]`` along ``dim``; 0 past the border."""
    out = torch.zeros_like(x)
    n = x.shape[dim]
    if n > 1:
        if forward:
            out.narrow(dim, 0, n - 1).copy_(x.narrow(dim, 1, n - 1))
        else:
            out.narrow(dim, 1, n - 1).copy_(x.narrow(dim, 0, n - 1))
    return out


def _bilateral_weights(z, nz, m, k):
    """Per-pixel forward weights ``w^+`` along columns and rows (``w^- = 1 - w^+``)."""
    mf = m.to(z.dtype)
    out = []
    for dim in (1, 0):
        zf, zb = _shift(z, dim, True), _shift(z, dim, False)
        vf, vb = _shift(mf, dim, True) * mf, _shift(mf, dim, False) * mf
        dp = nz * (zf - z) * vf
        dm = nz * (z - zb) * vb
        out.append(torch.sigmoid(k * (dm * dm - dp * dp)))
    return out  # [wu_plus (cols), wv_plus (rows)]


def _bilateral_edges(gc, gr, nz, m, wu, wv) -> _Edges:
    eh, ev = _edge_masks(m, gc.dtype)
    nz2 = nz * nz
    # horizontal edge (r, c) -> (r, c+1): forward eq. of the left pixel, backward eq. of the right one
    a, b = wu[:, :-1] * nz2[:, :-1], (1 - wu[:, 1:]) * nz2[:, 1:]
    wh = (a + b) * eh
    th = torch.where(wh > 0, (a * gc[:, :-1] + b * gc[:, 1:]) / (a + b).clamp(min=1e-300), torch.zeros_like(wh))
    a, b = wv[:-1] * nz2[:-1], (1 - wv[1:]) * nz2[1:]
    wvv = (a + b) * ev
    tv = torch.where(wvv > 0, (a * gr[:-1] + b * gr[1:]) / (a + b).clamp(min=1e-300), torch.zeros_like(wvv))
    return _Edges(wh, th * eh, wvv, tv * ev)


# --------------------------------------------------------------------------- #
# public entry point
# --------------------------------------------------------------------------- #
def integrate_normals(
    normals: torch.Tensor,
    mask: Optional[torch.Tensor] = None,
    method: str = "poisson",
    *,
    solver: str = "auto",
    tol: float = 1e-6,
    max_iter: int = 1000,
    min_nz: float = 0.05,
    fill: float = float("nan"),
    k: float = 2.0,
    iterations: int = 100,
    energy_tol: float = 1e-4,
    return_info: bool = False,
):
    r"""Integrate a normal map into a depth (height) map, orthographic DiLiGenT frame.

    See the module docstring for the conventions, the two methods and the
    solvers. Each 4-connected part of ``mask`` is integrated separately and
    shifted to **zero mean depth** (relative offsets of disconnected parts are
    unknowable from normals).

    Args:
        normals: ``(H, W, 3)`` (or ``(*B, H, W, 3)``, integrated one by one)
            normals in the DiLiGenT frame (x right, y up, z toward the
            camera); need not be unit; values outside ``mask`` are ignored
            (NaN allowed there).
        mask: ``(H, W)`` bool (default: every pixel).
        method: ``"poisson"`` (least squares, fast) or ``"bilateral"``
            (discontinuity preserving, Cao et al. 2022; slower, iterative).
        solver: ``"auto"``, ``"scipy"`` (CPU, pyamg-preconditioned CG) or
            ``"torch"`` (matrix-free DCT-preconditioned CG on any device).
        tol: relative residual of each linear solve.
        max_iter: cap on the CG iterations of each linear solve.
        min_nz: ``n_z`` is clamped to this before computing slopes.
        fill: value written outside the mask (NaN by default).
        k: bilateral sharpness (Cao et al.'s ``k``; larger = sharper jumps).
        iterations: cap on the bilateral re-weighting iterations.
        energy_tol: bilateral stopping rule: relative energy change below this.
        return_info: also return a dict (``iterations`` per solve,
            ``residual``, ``outer_iterations``, ``components``, ``solver``,
            ``seconds``; lists for batched input).

    Returns:
        ``(H, W)`` (or ``(*B, H, W)``) depth in pixel units, dtype and device
        of ``normals``; ``fill`` outside the mask. With ``return_info``,
        ``(depth, info)``. Not differentiable (the normals are detached).

    Example:
        >>> from torch_hsh.render.scenes import sphere_normals
        >>> n, m = sphere_normals(64, dtype=torch.float64)
        >>> z = integrate_normals(n, m)
        >>> bool(z[32, 32] > z[32, 10] > z[32, 4])  # a dome: highest in the middle
        True
        >>> bool(z[0, 0].isnan())  # outside the mask
        True
    """
    normals, m = _check_normals(normals, mask)
    if method not in INTEGRATION_METHODS:
        raise ValueError(f"`method` must be one of {INTEGRATION_METHODS}, got {method!r}")
    if solver not in _SOLVERS:
        raise ValueError(f"`solver` must be one of {_SOLVERS}, got {solver!r}")
    if solver == "auto":
        solver = "torch" if normals.device.type != "cpu" else "scipy"
    tol = _positive_float(tol, "tol")
    max_iter = _positive_int(max_iter, "max_iter")
    min_nz = _positive_float(min_nz, "min_nz")
    k = _positive_float(k, "k")
    iterations = _positive_int(iterations, "iterations")
    energy_tol = _positive_float(energy_tol, "energy_tol")
    if isinstance(fill, bool) or not isinstance(fill, (int, float)):
        raise TypeError(f"`fill` must be a number (NaN allowed), got {fill!r}")
    if normals.dim() > 3:
        lead = normals.shape[:-3]
        flat = normals.reshape(-1, *normals.shape[-3:])
        outs, infos = [], []
        for nb in flat:
            z, info = _integrate_one(nb, m, method, solver, tol, max_iter, min_nz, float(fill), k, iterations, energy_tol)
            outs.append(z)
            infos.append(info)
        depth = torch.stack(outs).reshape(*lead, *normals.shape[-3:-1])
        if return_info:
            return depth, {key: [i[key] for i in infos] for key in infos[0]}
        return depth
    depth, info = _integrate_one(normals, m, method, solver, tol, max_iter, min_nz, float(fill), k, iterations, energy_tol)
    return (depth, info) if return_info else depth


def _integrate_one(normals, m, method, solver, tol, max_iter, min_nz, fill, k, iterations, energy_tol):
    t0 = time.perf_counter()
    H, W = m.shape
    n64 = torch.where(m[..., None], normals.detach().to(torch.float64), torch.zeros((), dtype=torch.float64, device=m.device))
    n64[..., 2] = torch.where(m, n64[..., 2], torch.ones_like(n64[..., 2]))
    labels, n_parts = connected_components(m)
    info: Dict[str, object] = {"solver": solver, "components": n_parts, "iterations": [], "outer_iterations": 0}
    z = torch.zeros(H, W, dtype=torch.float64, device=m.device)
    if n_parts == 0:
        out = torch.full((H, W), fill, dtype=normals.dtype, device=normals.device)
        info.update(residual=0.0, seconds=time.perf_counter() - t0)
        return out, info
    anchors = _anchors(labels, n_parts)
    gc, gr = normals_to_slopes(n64, min_nz)
    gc, gr = gc * m, gr * m
    if method == "poisson":
        z, si = _solve(_poisson_edges(gc, gr, m), m, labels, n_parts, anchors, None, solver, tol, max_iter)
        info["iterations"].append(si["iterations"])
        info["residual"] = si["residual"]
    else:
        nz = n64[..., 2].clamp(min=min_nz) * m
        half = torch.full((H, W), 0.5, dtype=torch.float64, device=m.device)
        wu, wv = half, half
        edges = _bilateral_edges(gc, gr, nz, m, wu, wv)
        energy = None
        cache: Dict[str, object] = {}
        for outer in range(iterations):
            z, si = _solve(edges, m, labels, n_parts, anchors, z if outer else None, solver, tol, max_iter, cache)
            info["iterations"].append(si["iterations"])
            info["residual"] = si["residual"]
            info["outer_iterations"] = outer + 1
            wu, wv = _bilateral_weights(z, nz, m, k)
            edges = _bilateral_edges(gc, gr, nz, m, wu, wv)
            e_new = edges.energy(z)
            if energy is not None and abs(e_new - energy) <= energy_tol * max(abs(energy), 1e-300):
                break
            energy = e_new
    out = torch.where(m, z, torch.full_like(z, fill)).to(dtype=normals.dtype)
    info["seconds"] = time.perf_counter() - t0
    return out, info
