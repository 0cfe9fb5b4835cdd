r"""MERL BRDF ``.binary`` files: reader, writer, table lookup and tabulation.

Format (Matusik et al. 2003, "A data-driven reflectance model"), little-endian:

* header: three int32 ``(N_th, N_td, N_pd)`` = numbers of bins in ``theta_h``,
  ``theta_d`` and ``phi_d`` (``(90, 90, 180)`` for the published materials);
* then ``3 * N`` float64 values (``N = N_th * N_td * N_pd``) in three blocks
  R, G, B; inside a block the flat index is
  ``phi_d + N_pd * (theta_d + N_td * theta_h)``;
* stored values are multiplied by the per-channel scale :data:`MERL_SCALE`
  ``(1/1500, 1.15/1500, 1.66/1500)`` to give the BRDF; negative values mean
  "not measured".

Bins (Rusinkiewicz half/difference coordinates, see :func:`half_diff_coords`):
``theta_h`` bin ``floor(sqrt(theta_h / (pi/2)) * N_th)`` (non-linear: dense
near the specular peak), ``theta_d`` bin ``floor(theta_d / (pi/2) * N_td)``,
``phi_d`` bin ``floor(phi_d / pi * N_pd)`` after folding ``phi_d`` into
``[0, pi)`` (an isotropic reciprocal BRDF is unchanged by ``phi_d -> phi_d + pi``).
Bin indices are clamped to the valid range. Tables of another size are read
when the header says so, and the same formulas are used with its bin counts.

Example:
    >>> import tempfile, os, torch
    >>> from torch_hsh.brdf import Lambertian
    >>> from torch_hsh.io.merl import tabulate_merl, write_merl, read_merl
    >>> brdf = tabulate_merl(Lambertian([0.5, 0.5, 0.5]), shape=(8, 8, 16))
    >>> path = os.path.join(tempfile.mkdtemp(), "lambert.binary")
    >>> _ = write_merl(path, brdf)
    >>> again = read_merl(path)
    >>> torch.equal(again.raw, brdf.raw)
    True
"""
from __future__ import annotations

import math
import os
import pathlib
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import nn

from .._atomic import atomic_file
from .._checks import broadcast_shapes, check_dirs, check_same, check_shape

__all__ = [
    "MERL_SHAPE",
    "MERL_SCALE",
    "MERLBRDF",
    "read_merl",
    "write_merl",
    "tabulate_merl",
    "half_diff_coords",
    "half_diff_to_dirs",
    "merl_bin_centers",
    "merl_solid_angle_weights",
    "fit_merl",
]

#: Bin counts ``(theta_h, theta_d, phi_d)`` of the published MERL tables.
MERL_SHAPE: Tuple[int, int, int] = (90, 90, 180)
#: Per-channel factors from stored values to BRDF values (R, G, B).
MERL_SCALE: Tuple[float, float, float] = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)
#: Stored value written for entries that are not measured.
UNMEASURED_RAW = -1.0

_HEADER_BYTES = 12
_MAX_BINS = 1 << 16  # per axis; larger headers are rejected as corrupt
_INTERPOLATIONS = ("nearest", "trilinear")
_UNMEASURED = ("zero", "nan")

PathLike = Union[str, os.PathLike]


# ----------------------------------------------------------------------------- coordinates

def _unit(v: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    n2 = (v * v).sum(-1, keepdim=True)
    ok = n2 > torch.finfo(v.dtype).tiny * 1e6
    return v * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2))), ok[..., 0]


def _safe_norm2(x: torch.Tensor, y: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(sqrt(x^2 + y^2), ok)`` with zero (finite) gradient where the norm vanishes."""
    r2 = x * x + y * y
    ok = r2 > torch.finfo(x.dtype).tiny * 1e6
    return torch.where(ok, r2, torch.ones_like(r2)).sqrt() * ok, ok


def half_diff_coords(wi: torch.Tensor, wo: torch.Tensor) -> Tuple[torch.Tensor, ...]:
    r"""Rusinkiewicz half/difference angles of local direction pairs.

    ``h = normalize(wi + wo)``, ``theta_h = acos(h_z)``, ``phi_h = atan2(h_y, h_x)``;
    ``d = R_y(-theta_h) R_z(-phi_h) wi``, ``theta_d = acos(d_z)``,
    ``phi_d = atan2(d_y, d_x)`` in ``(-pi, pi]`` (not folded). Angles are computed
    with ``atan2`` (accurate near 0); where ``h`` is parallel to the normal,
    ``phi_h = 0``; where ``wi + wo = 0`` the half vector is taken as the normal.
    Swapping ``wi`` and ``wo`` keeps ``theta_h, phi_h, theta_d`` and shifts
    ``phi_d`` by ``pi``.

    Args:
        wi, wo: ``(..., 3)`` local directions (normalised here), broadcast together.

    Returns:
        ``(theta_h, phi_h, theta_d, phi_d)``, each of the broadcast leading shape.

    Example:
        >>> z = torch.tensor([0.0, 0.0, 1.0])
        >>> [float(a) for a in half_diff_coords(z, z)]
        [0.0, 0.0, 0.0, 0.0]
    """
    check_dirs(wi, "wi")
    check_dirs(wo, "wo")
    check_same([("wi", wi), ("wo", wo)])
    lead = broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1])])
    ui, _ = _unit(wi.expand(*lead, 3))
    uo, _ = _unit(wo.expand(*lead, 3))
    h, okh = _unit(ui + uo)
    h = torch.where(okh[..., None], h, torch.zeros_like(h) + torch.tensor([0.0, 0.0, 1.0], dtype=h.dtype, device=h.device))
    hx, hy, hz = h.unbind(-1)
    rho, okr = _safe_norm2(hx, hy)
    inv = 1.0 / torch.where(okr, rho, torch.ones_like(rho))
    cphi = torch.where(okr, hx * inv, torch.ones_like(hx))
    sphi = torch.where(okr, hy * inv, torch.zeros_like(hy))
    theta_h = torch.atan2(rho, hz)
    phi_h = torch.atan2(sphi, cphi)
    vx, vy, vz = ui.unbind(-1)
    x1 = vx * cphi + vy * sphi
    y1 = vy * cphi - vx * sphi
    dx = x1 * hz - vz * rho
    dz = x1 * rho + vz * hz
    dy = y1
    rd, okd = _safe_norm2(dx, dy)
    theta_d = torch.atan2(rd, dz)
    phi_d = torch.atan2(torch.where(okd, dy, torch.zeros_like(dy)), torch.where(okd, dx, torch.ones_like(dx)))
    return theta_h, phi_h, theta_d, phi_d


def half_diff_to_dirs(theta_h, phi_h, theta_d, phi_d) -> Tuple[torch.Tensor, torch.Tensor]:
    r"""Inverse of :func:`half_diff_coords`: ``(wi, wo)`` unit local directions ``(..., 3)``.

    ``wi = R_z(phi_h) R_y(theta_h) d`` and ``wo = R_z(phi_h) R_y(theta_h) d'`` with
    ``d = (sin theta_d cos phi_d, sin theta_d sin phi_d, cos theta_d)`` and
    ``d' = (-d_x, -d_y, d_z)`` (the mirror of ``d`` about the half vector).
    Directions may fall below the horizon (large ``theta_h`` and ``theta_d``).

    Args:
        theta_h, phi_h, theta_d, phi_d: float tensors (or numbers), broadcast together.

    Example:
        >>> wi, wo = half_diff_to_dirs(torch.tensor(0.0), 0.0, torch.tensor(math.pi / 4), 0.0)
        >>> [round(float(v), 4) + 0.0 for v in wi], [round(float(v), 4) + 0.0 for v in wo]
        ([0.7071, 0.0, 0.7071], [-0.7071, 0.0, 0.7071])
    """
    ref = next((t for t in (theta_h, phi_h, theta_d, phi_d) if isinstance(t, torch.Tensor)), None)
    if ref is None:
        raise TypeError("half_diff_to_dirs needs at least one tensor argument")
    if ref.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"angles must be float32 or float64, got {ref.dtype}")
    th, ph, td, pd = (torch.as_tensor(t, dtype=ref.dtype, device=ref.device) for t in (theta_h, phi_h, theta_d, phi_d))
    th, ph, td, pd = torch.broadcast_tensors(th, ph, td, pd)
    st, ct = td.sin(), td.cos()
    dx, dy, dz = st * pd.cos(), st * pd.sin(), ct
    ch, sh, cp, sp = th.cos(), th.sin(), ph.cos(), ph.sin()

    def rot(x, y, z):
        x1, z1 = ch * x + sh * z, -sh * x + ch * z  # R_y(theta_h)
        return torch.stack([cp * x1 - sp * y, sp * x1 + cp * y, z1], -1)  # R_z(phi_h)

    return rot(dx, dy, dz), rot(-dx, -dy, dz)


def merl_bin_centers(shape: Sequence[int] = MERL_SHAPE, dtype=torch.float64, device=None):
    """Angles ``(theta_h (N_th,), theta_d (N_td,), phi_d (N_pd,))`` at the bin centres.

    Centres are taken in index space: ``theta_h = ((i + 1/2) / N_th)^2 pi/2``,
    ``theta_d = (j + 1/2) / N_td * pi/2``, ``phi_d = (k + 1/2) / N_pd * pi``,
    so each maps back to its own bin.

    Example:
        >>> th, td, pd = merl_bin_centers((2, 2, 4))
        >>> [round(float(v), 4) for v in pd]
        [0.3927, 1.1781, 1.9635, 2.7489]
    """
    nh, nd, npd = _check_shape(shape, "shape")
    kw = dict(dtype=dtype, device=device)
    th = ((torch.arange(nh, **kw) + 0.5) / nh) ** 2 * (math.pi / 2)
    td = (torch.arange(nd, **kw) + 0.5) / nd * (math.pi / 2)
    pd = (torch.arange(npd, **kw) + 0.5) / npd * math.pi
    return th, td, pd


# ----------------------------------------------------------------------------- table object

def _check_shape(shape, name) -> Tuple[int, int, int]:
    try:
        dims = tuple(int(s) for s in shape)
    except (TypeError, ValueError):
        raise TypeError(f"`{name}` must be three positive integers, got {shape!r}") from None
    if len(dims) != 3 or any(d <= 0 for d in dims):
        raise ValueError(f"`{name}` must be three positive integers (theta_h, theta_d, phi_d), got {shape!r}")
    return dims


def _check_scale(scale) -> torch.Tensor:
    s = torch.as_tensor(scale, dtype=torch.float64).flatten()
    if s.numel() != 3 or not bool(torch.isfinite(s).all()) or not bool((s > 0).all()):
        raise ValueError(f"`scale` must be three positive finite numbers (R, G, B), got {scale!r}")
    return s


def _check_option(value, name, allowed):
    if value not in allowed:
        raise ValueError(f"`{name}` must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
    return value


def _as_table(x, name) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"`{name}` must be a MERLBRDF, a torch.Tensor or a numpy array, got {type(x).__name__}")
    if x.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"`{name}` must be float32 or float64, got dtype {x.dtype}")
    check_shape(x, name, (3, "N_theta_h", "N_theta_d", "N_phi_d"))
    if any(s == 0 for s in x.shape):
        raise ValueError(f"`{name}` must have at least one bin in each dimension, got shape {tuple(x.shape)}")
    return x


def _table_to_raw(table: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    t = table.detach().to(torch.float64)
    if bool(torch.isinf(t).any()):
        raise ValueError("`table` contains Inf values; use NaN or a negative value for unmeasured entries")
    raw = t / scale.to(t.device).view(3, 1, 1, 1)
    return torch.where(torch.isnan(raw) | (raw < 0), torch.full_like(raw, UNMEASURED_RAW), raw)


class MERLBRDF(nn.Module):
    r"""A tabulated isotropic BRDF on the MERL half/difference grid.

    Attributes:
        raw: buffer ``(3, N_th, N_td, N_pd)``, float64 values as stored in the
            file (negative = not measured). Writing keeps them bit-exact.
        scale: buffer ``(3,)``, per-channel factors (:data:`MERL_SCALE` by default).

    Calling ``brdf(wi, wo)`` with local directions ``(..., 3)`` returns
    ``(..., 3)`` RGB BRDF values in the dtype of the directions:

    * ``interpolation="nearest"`` (default): the value of the bin that contains
      the direction pair (exactly the MERL reference lookup);
      ``"trilinear"``: linear interpolation between bin centres in the index
      coordinates ``(sqrt(theta_h/(pi/2)) N_th, theta_d/(pi/2) N_td, phi_d/pi N_pd)``,
      periodic in ``phi_d`` (period ``pi``) and constant beyond the first/last
      centre in ``theta_h`` and ``theta_d``. Unmeasured corners are left out and
      the remaining weights renormalised. Trilinear lookup is differentiable
      with respect to the directions (finite gradients) and the table.
    * ``unmeasured="zero"`` (default) returns 0 for unmeasured entries,
      ``"nan"`` returns NaN (to mask them downstream).
    * Directions below the horizon (``z < 0``) or zero vectors give 0.

    The lookup is reciprocal: swapping ``wi`` and ``wo`` shifts ``phi_d`` by
    ``pi``, which the fold removes.

    Args:
        raw: stored values ``(3, N_th, N_td, N_pd)`` (tensor or numpy array).
        scale: per-channel factors from stored to BRDF values.
        interpolation, unmeasured: default lookup options (see above).

    Example:
        >>> raw = torch.full((3, 4, 4, 8), 1500.0, dtype=torch.float64)
        >>> brdf = MERLBRDF(raw)
        >>> z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        >>> [round(float(v), 4) for v in brdf(z, z)]
        [1.0, 1.15, 1.66]
    """

    raw: torch.Tensor
    scale: torch.Tensor

    def __init__(self, raw, scale=MERL_SCALE, interpolation: str = "nearest", unmeasured: str = "zero") -> None:
        super().__init__()
        raw = _as_table(raw, "raw").to(torch.float64)
        if bool(torch.isnan(raw).any()) or bool(torch.isinf(raw).any()):
            raise ValueError("`raw` must be finite (negative values mark unmeasured entries), got NaN/Inf")
        self.register_buffer("raw", raw)
        self.register_buffer("scale", _check_scale(scale).to(raw.device))
        self.interpolation = _check_option(interpolation, "interpolation", _INTERPOLATIONS)
        self.unmeasured = _check_option(unmeasured, "unmeasured", _UNMEASURED)

    @classmethod
    def from_table(cls, table, scale=MERL_SCALE, **kwargs) -> "MERLBRDF":
        """Build from BRDF values ``(3, N_th, N_td, N_pd)``; NaN or negative entries become unmeasured.

        The stored values are ``table / scale`` (so ``brdf.table`` equals ``table``
        up to one rounding).

        Example:
            >>> b = MERLBRDF.from_table(torch.full((3, 2, 2, 4), 0.25, dtype=torch.float64))
            >>> float(b.raw[0, 0, 0, 0])
            375.0
        """
        s = _check_scale(scale)
        return cls(_table_to_raw(_as_table(table, "table"), s), scale=s, **kwargs)

    @property
    def shape(self) -> Tuple[int, int, int]:
        """Bin counts ``(N_th, N_td, N_pd)``."""
        n_th, n_td, n_pd = self.raw.shape[1:]
        return int(n_th), int(n_td), int(n_pd)

    @property
    def table(self) -> torch.Tensor:
        """BRDF values ``raw * scale`` ``(3, N_th, N_td, N_pd)`` (unmeasured entries stay negative)."""
        return self.raw * self.scale.view(3, 1, 1, 1)

    @property
    def measured(self) -> torch.Tensor:
        """Boolean mask ``(3, N_th, N_td, N_pd)`` of measured entries (``raw >= 0``)."""
        return self.raw >= 0

    def extra_repr(self) -> str:
        frac = float(self.measured.double().mean())
        return (f"shape={self.shape}, measured={frac:.3f}, interpolation={self.interpolation!r}, "
                f"unmeasured={self.unmeasured!r}")

    def bin_indices(self, wi: torch.Tensor, wo: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Nearest-bin indices ``(i_theta_h, i_theta_d, i_phi_d)`` (LongTensors) of direction pairs.

        Example:
            >>> b = MERLBRDF(torch.zeros(3, 90, 90, 180, dtype=torch.float64))
            >>> z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
            >>> [int(i) for i in b.bin_indices(z, z)]
            [0, 0, 0]
        """
        nh, nd, npd = self.shape
        th, _, td, pd = half_diff_coords(wi, wo)
        ih = (torch.sqrt(th.clamp(min=0.0) / (math.pi / 2)) * nh).floor().long().clamp(0, nh - 1)
        idd = (td.clamp(min=0.0) / (math.pi / 2) * nd).floor().long().clamp(0, nd - 1)
        ip = (torch.remainder(pd, math.pi) / math.pi * npd).floor().long().clamp(0, npd - 1)
        return ih, idd, ip

    def _gather(self, ih, idd, ip, dtype):
        nh, nd, npd = self.shape
        flat = ip + npd * (idd + nd * ih)
        raw = self.raw.reshape(3, -1)
        vals = raw[:, flat.reshape(-1)].reshape(3, *flat.shape)
        vals = vals.movedim(0, -1)  # (..., 3)
        return (vals * self.scale).to(dtype), (vals >= 0)

    def lookup(self, wi: torch.Tensor, wo: torch.Tensor, interpolation: Optional[str] = None,
               unmeasured: Optional[str] = None) -> torch.Tensor:
        """BRDF values ``(..., 3)`` at local direction pairs; options override the defaults.

        Example:
            >>> b = MERLBRDF(torch.full((3, 4, 4, 8), 1500.0, dtype=torch.float64))
            >>> z = torch.tensor([0.0, 0.0, 1.0])
            >>> b.lookup(z, z, interpolation="trilinear").shape
            torch.Size([3])
        """
        interpolation = _check_option(interpolation or self.interpolation, "interpolation", _INTERPOLATIONS)
        unmeasured = _check_option(unmeasured or self.unmeasured, "unmeasured", _UNMEASURED)
        check_dirs(wi, "wi")
        check_dirs(wo, "wo")
        check_same([("wi", wi), ("wo", wo)])
        lead = broadcast_shapes([("wi", wi.shape[:-1]), ("wo", wo.shape[:-1])])
        dev, dtype = wi.device, wi.dtype
        if self.raw.device != dev:
            raise ValueError(f"the table is on {self.raw.device} but `wi` is on {dev}; use brdf.to(device)")
        _, oki = _unit(wi.expand(*lead, 3))
        _, oko = _unit(wo.expand(*lead, 3))
        above = oki & oko & (wi.expand(*lead, 3)[..., 2] >= 0) & (wo.expand(*lead, 3)[..., 2] >= 0)
        if interpolation == "nearest":
            vals, ok = self._gather(*self.bin_indices(wi, wo), dtype)
        else:
            vals, ok = self._trilinear(wi, wo, dtype)
        fill = 0.0 if unmeasured == "zero" else float("nan")
        vals = torch.where(ok, vals, torch.full_like(vals, fill))
        return torch.where(above[..., None], vals, torch.zeros_like(vals))

    def _trilinear(self, wi, wo, dtype):
        nh, nd, npd = self.shape
        th, _, td, pd = half_diff_coords(wi, wo)
        tiny = torch.finfo(th.dtype).tiny
        # sqrt with a finite gradient at theta_h = 0
        sq = torch.where(th > tiny, th, torch.full_like(th, tiny)).sqrt() * (th > tiny)
        xs = (
            (sq / math.sqrt(math.pi / 2) * nh - 0.5, nh, False),
            (td / (math.pi / 2) * nd - 0.5, nd, False),
            (torch.remainder(pd, math.pi) / math.pi * npd - 0.5, npd, True),
        )
        idx, wts = [], []
        for x, n, periodic in xs:
            if periodic:
                i0 = x.detach().floor()
                t = x - i0
                i0 = i0.long()
                idx.append((torch.remainder(i0, n), torch.remainder(i0 + 1, n)))
            else:
                x = x.clamp(0.0, n - 1.0)
                i0 = x.detach().floor().clamp(max=max(n - 2, 0))
                t = x - i0
                i0 = i0.long()
                idx.append((i0, (i0 + 1).clamp(max=n - 1)))
            wts.append((1.0 - t, t))
        num = 0.0
        den = 0.0
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    v, ok = self._gather(idx[0][a], idx[1][b], idx[2][c], dtype)
                    w = (wts[0][a] * wts[1][b] * wts[2][c]).to(dtype)[..., None] * ok
                    num = num + w * torch.where(ok, v, torch.zeros_like(v))
                    den = den + w
        good = den > 0
        return num / torch.where(good, den, torch.ones_like(den)), good

    def forward(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """``brdf(wi, wo) -> (..., 3)`` with the default options (see :meth:`lookup`)."""
        return self.lookup(wi, wo)


# ----------------------------------------------------------------------------- files

def _check_path(path, name="path") -> pathlib.Path:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"`{name}` must be a str or os.PathLike, got {type(path).__name__}")
    return pathlib.Path(path)


def read_merl(path: PathLike, interpolation: str = "nearest", unmeasured: str = "zero") -> MERLBRDF:
    """Read a MERL ``.binary`` BRDF file.

    Args:
        path: file path.
        interpolation, unmeasured: default lookup options of the returned
            :class:`MERLBRDF`.

    Returns:
        :class:`MERLBRDF` with ``raw`` of shape ``(3, N_th, N_td, N_pd)`` as given
        by the header (``(90, 90, 180)`` for the published files).

    Raises:
        FileNotFoundError: no such file. IsADirectoryError: a directory.
        ValueError: truncated file, invalid header (non-positive or absurd bin
        counts) or a size that does not match the header.

    Example:
        >>> import tempfile, os
        >>> p = os.path.join(tempfile.mkdtemp(), "x.binary")
        >>> _ = write_merl(p, torch.full((3, 2, 3, 4), 0.1, dtype=torch.float64))
        >>> read_merl(p).shape
        (2, 3, 4)
    """
    p = _check_path(path)
    if not p.exists():
        raise FileNotFoundError(f"MERL BRDF file not found: {str(p)!r}")
    if p.is_dir():
        raise IsADirectoryError(f"MERL BRDF path is a directory, expected a .binary file: {str(p)!r}")
    size = p.stat().st_size
    with open(p, "rb") as fh:
        if size < _HEADER_BYTES:
            raise ValueError(f"{str(p)!r} is truncated: {size} bytes, but a MERL file starts with a "
                             f"{_HEADER_BYTES}-byte header of three int32 bin counts")
        dims = np.frombuffer(fh.read(_HEADER_BYTES), dtype="<i4")
        if any(int(d) <= 0 or int(d) > _MAX_BINS for d in dims):
            raise ValueError(f"{str(p)!r} has an invalid MERL header {tuple(int(d) for d in dims)}: expected three "
                             f"bin counts in [1, {_MAX_BINS}] such as {MERL_SHAPE}")
        nh, nd, npd = (int(d) for d in dims)
        n = nh * nd * npd
        expected = _HEADER_BYTES + 3 * n * 8
        if size != expected:
            what = "truncated" if size < expected else "longer than its header says"
            raise ValueError(f"{str(p)!r} is {what}: the header {(nh, nd, npd)} needs {expected} bytes "
                             f"(12 + 3 x {n} float64), the file has {size}")
        data = np.frombuffer(fh.read(3 * n * 8), dtype="<f8").astype(np.float64)
    raw = torch.from_numpy(data.reshape(3, nh, nd, npd).copy())
    if not bool(torch.isfinite(raw).all()):
        raise ValueError(f"{str(p)!r} contains NaN/Inf values; MERL files mark unmeasured entries with negatives")
    return MERLBRDF(raw, interpolation=interpolation, unmeasured=unmeasured)


def _current_umask() -> int:
    """The process umask (read from /proc where possible, else set and restored)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_merl(path: PathLike, table_or_brdf, overwrite: bool = False, scale=MERL_SCALE) -> pathlib.Path:
    """Write a MERL ``.binary`` file.

    Args:
        path: destination path.
        table_or_brdf: a :class:`MERLBRDF` (its ``raw`` values are written
            bit-exact), or BRDF values ``(3, N_th, N_td, N_pd)`` as a float tensor
            or numpy array (stored as ``table / scale``; NaN or negative entries
            are written as :data:`UNMEASURED_RAW`).
        overwrite: replace an existing file (default: refuse).
        scale: per-channel factors used for a plain table (ignored for a MERLBRDF,
            whose own ``scale`` must equal the MERL convention to be read back
            correctly by other readers).

    Returns:
        The path written. The file is written to a temporary name in the same
        folder and moved into place, so a failure never leaves a partial file.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.

    Example:
        >>> import tempfile, os
        >>> p = os.path.join(tempfile.mkdtemp(), "y.binary")
        >>> os.path.getsize(write_merl(p, torch.zeros(3, 2, 2, 4, dtype=torch.float64)))
        396
    """
    p = _check_path(path)
    if not isinstance(overwrite, bool):
        raise TypeError(f"`overwrite` must be a bool, got {type(overwrite).__name__}")
    if isinstance(table_or_brdf, MERLBRDF):
        raw = table_or_brdf.raw.detach()
    else:
        raw = _table_to_raw(_as_table(table_or_brdf, "table_or_brdf"), _check_scale(scale))
    if p.exists() and not overwrite:
        raise FileExistsError(f"{str(p)!r} exists; pass overwrite=True to replace it")
    if p.is_dir():
        raise IsADirectoryError(f"{str(p)!r} is a directory")
    header = np.asarray(raw.shape[1:], dtype="<i4")
    data = raw.cpu().numpy().astype("<f8", copy=False)
    folder = p.parent if str(p.parent) else pathlib.Path(".")
    # mkstemp creates 0600; give the file the mode open() would (umask, or the replaced file's mode)
    mode = (p.stat().st_mode & 0o7777) if p.exists() else (0o666 & ~_current_umask())
    with atomic_file(folder / p.name, mode=mode) as tmp, open(tmp, "wb") as fh:
        fh.write(header.tobytes())
        fh.write(np.ascontiguousarray(data).tobytes())
    return p


def tabulate_merl(model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], shape: Sequence[int] = MERL_SHAPE,
                  scale=MERL_SCALE, below_horizon: str = "unmeasured", chunk_size: int = 8) -> MERLBRDF:
    """Sample a BRDF callable at the bin centres of the MERL grid.

    Every bin ``(i, j, k)`` gets ``model(wi, wo)`` at the direction pair of its
    centre (:func:`merl_bin_centers`, ``phi_h = 0``: the grid assumes an
    isotropic BRDF, so an anisotropic model is sampled along ``phi_h = 0`` only).
    Evaluation is in float64 without gradients.

    Args:
        model: callable ``(wi (..., 3), wo (..., 3)) -> (..., C)`` with ``C`` 1 or 3
            (for example a :mod:`torch_hsh.brdf` model or another :class:`MERLBRDF`).
        shape: bin counts ``(N_th, N_td, N_pd)``.
        scale: per-channel stored-value factors.
        below_horizon: bins whose centre puts ``wi`` or ``wo`` below the horizon
            are stored as unmeasured (``"unmeasured"``, default, like missing MERL
            samples) or as 0 (``"zero"``).
        chunk_size: ``theta_h`` rows of bins evaluated per call of ``model`` (bounds peak memory).

    Returns:
        :class:`MERLBRDF`.

    Example:
        >>> from torch_hsh.brdf import Lambertian
        >>> b = tabulate_merl(Lambertian(0.5), shape=(4, 4, 8))
        >>> z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        >>> round(float(b(z, z)[0]) * math.pi, 12)
        0.5
    """
    if not callable(model):
        raise TypeError(f"`model` must be callable (wi, wo) -> (..., C), got {type(model).__name__}")
    nh, nd, npd = _check_shape(shape, "shape")
    s = _check_scale(scale)
    _check_option(below_horizon, "below_horizon", ("unmeasured", "zero"))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}")
    dev = None
    if isinstance(model, nn.Module):
        bufs = list(model.buffers()) + list(model.parameters())
        dev = bufs[0].device if bufs else None
    th, td, pd = merl_bin_centers((nh, nd, npd), dtype=torch.float64, device=dev)
    raw = torch.empty(3, nh, nd, npd, dtype=torch.float64, device=dev)
    with torch.no_grad():
        for start in range(0, nh, chunk_size):
            rows = th[start:start + chunk_size]
            TH, TD, PD = torch.meshgrid(rows, td, pd, indexing="ij")
            wi, wo = half_diff_to_dirs(TH, torch.zeros_like(TH), TD, PD)
            f = model(wi, wo)
            if not isinstance(f, torch.Tensor) or f.shape[:-1] != TH.shape or f.shape[-1] not in (1, 3):
                got = tuple(f.shape) if isinstance(f, torch.Tensor) else type(f).__name__
                raise ValueError(f"`model` must return (..., 1) or (..., 3) values for (..., 3) directions, got {got}")
            f = f.to(torch.float64).expand(*TH.shape, 3).movedim(-1, 0)
            block = _table_to_raw(f, s)
            if below_horizon == "unmeasured":
                below = (wi[..., 2] < 0) | (wo[..., 2] < 0)
                block = torch.where(below, torch.full_like(block, UNMEASURED_RAW), block)
            raw[:, start:start + chunk_size] = block
    return MERLBRDF(raw, scale=s)


# ----------------------------------------------------------------------------- fitting the table's samples

#: Jacobian of the half/difference parameterisation times the phi_h integral (2 pi) and the phi_d fold (2):
#: d(omega_i) d(omega_o) = 4 cos(theta_d) d(omega_h) d(omega_d).
_HD_MEASURE = 4.0 * 2.0 * math.pi * 2.0


def merl_solid_angle_weights(shape: Sequence[int] = MERL_SHAPE, n_sub: int = 4, dtype=torch.float64,
                             device=None) -> torch.Tensor:
    r"""Measure of :math:`\Omega_i\times\Omega_o` that each bin of a MERL table stands for.

    In Rusinkiewicz coordinates
    :math:`d\omega_i\,d\omega_o = 4\cos\theta_d\,d\omega_h\,d\omega_d`
    (:math:`d\omega_h = \sin\theta_h\,d\theta_h\,d\phi_h`, the same for ``d``). An isotropic table
    does not depend on :math:`\phi_h` (a factor :math:`2\pi`) and folds :math:`\phi_d` into
    :math:`[0, \pi)` (the other half is the same pairs with ``wi`` and ``wo`` swapped: a factor 2).
    So bin ``(i, j, k)`` has the weight

    .. math::
        w_{ijk} = 16\pi \int_{\theta_h \in \text{bin } i}\int_{\theta_d \in \text{bin } j}
        \sin\theta_h\,\cos\theta_d\sin\theta_d\;
        \bigl|\{\phi_d \in \text{bin } k : z_i \ge 0,\ z_o \ge 0\}\bigr|\,d\theta_d\,d\theta_h,

    where both directions are above the horizon iff
    :math:`|\cos\phi_d| \le \cot\theta_h\cot\theta_d` (the :math:`\phi_d` part is exact; the two
    polar integrals use ``n_sub`` Gauss--Legendre nodes per bin). The ``theta_h`` bins are the
    non-linear MERL bins (see :func:`merl_bin_centers`). The weights of all bins add up to
    :math:`(2\pi)^2 = 4\pi^2`, the measure of :math:`\Omega_i\times\Omega_o`: they are the
    quadrature weights that turn sums over the table into integrals over direction pairs.

    Args:
        shape: bin counts ``(N_th, N_td, N_pd)``.
        n_sub: Gauss--Legendre nodes per bin and polar axis (>= 1).
        dtype, device: of the result.

    Returns:
        ``(N_th, N_td, N_pd)`` non-negative weights (zero for bins entirely below the horizon).

    Example:
        >>> w = merl_solid_angle_weights((8, 8, 16))
        >>> round(float(w.sum() / (4 * math.pi ** 2)), 4)   # the polar sub-rule resolves the horizon to ~4e-5
        1.0
    """
    nh, nd, npd = _check_shape(shape, "shape")
    if isinstance(n_sub, bool) or not isinstance(n_sub, int) or n_sub < 1:
        raise ValueError(f"`n_sub` must be a positive integer, got {n_sub!r}")
    from ..quadrature import gauss_legendre

    f64 = torch.float64
    x, wx = gauss_legendre(n_sub, 0.0, 1.0, dtype=f64)  # nodes on [0, 1]
    half = math.pi / 2
    eh = (torch.arange(nh + 1, dtype=f64) / nh) ** 2 * half  # theta_h bin edges (non-linear)
    ed = torch.arange(nd + 1, dtype=f64) / nd * half
    th = (eh[:-1, None] + (eh[1:] - eh[:-1])[:, None] * x).reshape(-1)  # (nh * n_sub,)
    wth = ((eh[1:] - eh[:-1])[:, None] * wx).reshape(-1) * th.sin()
    td = (ed[:-1, None] + (ed[1:] - ed[:-1])[:, None] * x).reshape(-1)
    wtd = ((ed[1:] - ed[:-1])[:, None] * wx).reshape(-1) * td.sin() * td.cos()
    ep = torch.arange(npd + 1, dtype=f64) / npd * math.pi
    out = torch.empty(nh, nd, npd, dtype=f64)
    step = max(1, (1 << 21) // (n_sub * n_sub * nd * npd))  # theta_h bins per block: bounded memory
    for s in range(0, nh, step):
        e = min(s + step, nh)
        ths, wths = th[s * n_sub:e * n_sub], wth[s * n_sub:e * n_sub]
        # allowed phi_d in [0, pi): [alpha, pi - alpha] with cos(alpha) = min(1, cot th cot td)
        c = (ths.cos()[:, None] * td.cos()[None, :]) / (ths.sin()[:, None] * td.sin()[None, :]).clamp(min=1e-300)
        alpha = torch.acos(c.clamp(max=1.0))[..., None]  # (r n_sub, nd n_sub, 1)
        length = (torch.minimum(ep[1:], math.pi - alpha) - torch.maximum(ep[:-1], alpha)).clamp(min=0.0)
        w = length * (wths[:, None] * wtd[None, :])[..., None]
        out[s:e] = w.reshape(e - s, n_sub, nd, n_sub, npd).sum((1, 3)) * _HD_MEASURE
    w = out
    return w.to(dtype=dtype, device=device)


def fit_merl(brdf, order: int, basis="helmholtz_isotropic", weights: Optional[torch.Tensor] = None,
             ridge: float = 0.0, grazing_cutoff: Optional[float] = None, chunk_size: int = 1 << 16,
             progress: bool = False, return_info: bool = False):
    r"""Fit an isotropic basis to a MERL table's own samples by weighted least squares.

    A MERL file is a set of samples, one per bin, at the bin centres (:func:`merl_bin_centers`,
    ``phi_h = 0``). This fits :math:`f \approx \sum_k a_k B_k` to them, minimising

    .. math:: \sum_n w_n \bigl(y_n - \textstyle\sum_k a_k B_k(\omega_{i,n}, \omega_{o,n})\bigr)^2
              + \text{ridge}\,\|a\|^2

    per RGB channel, with the solid-angle weights :math:`w_n` of
    :func:`merl_solid_angle_weights`. The weighted sum is a quadrature of the :math:`L^2` norm
    over :math:`\Omega_i\times\Omega_o`, so the result approximates the projection (paper
    Eq. 14) of the tabulated function and needs no quadrature of the function itself: sharp
    and rough lobes cost the same. The basis is orthonormal and the weights add up to the
    measure, so the normal matrix is close to the identity and ``ridge`` is relative to 1.

    Only bins that are measured (``raw >= 0``, per channel), have a positive weight and whose
    centre has both directions above the horizon take part. With ``grazing_cutoff = c`` the
    fitted function is :math:`f\,1[\cos\theta_i \ge c, \cos\theta_o \ge c]` (samples beyond the
    cutoff count as zero), the same convention as :func:`torch_hsh.fitting.project`; it removes
    the grazing growth of raw microfacet models, which otherwise dominates the L2 error. The basis is evaluated once per sample, in chunks of ``chunk_size``
    samples (memory ``O(chunk_size * K)``); the normal equations are accumulated in float64
    and solved by Cholesky.

    Args:
        brdf: a :class:`MERLBRDF` or the path of a ``.binary`` file.
        order: basis order ``P``.
        basis: an **isotropic** basis name or object (the table is sampled at ``phi_h = 0``).
        weights: ``(N_th, N_td, N_pd)`` sample weights >= 0 (default: the solid-angle weights).
        ridge: Tikhonov strength >= 0.
        grazing_cutoff: fit the table set to zero where ``cos theta_i`` or ``cos theta_o`` is below it.
        chunk_size: samples per basis evaluation.
        progress: show a tqdm bar (on stderr) over the samples.
        return_info: also return the diagnostics dict.

    Returns:
        ``(3, K)`` float64 coefficients; with ``return_info``, ``(coefficients, info)`` where ``info``
        holds, per channel ``(3,)`` unless noted:

        * ``relative_error``: :math:`\|y - Aa\|_W / \|y\|_W`, the weighted relative L2 error on
          the samples (a quadrature of the relative L2 error of the fit over direction pairs);
        * ``relative_error_unweighted``: the same with every used sample weighted alike;
        * ``relative_error_per_order`` ``(3, P + 1)``: ``relative_error`` of the least-squares fit
          truncated to each order ``P' <= P`` (refitted from the same normal equations);
        * ``energy``: :math:`\|y\|_W^2`; ``accuracy`` ``(3, P + 1)``: ``1 - relative_error_per_order**2``
          (the sample analogue of Acc(P), Eq. 17);
        * ``num_samples`` (used samples of the first channel), ``coverage`` (their weight over
          :math:`4\pi^2`), ``condition`` (of the normal matrix), ``runtime_s``.

    Raises:
        TypeError / ValueError: bad arguments (each names the argument); ValueError when no
        sample is usable or the normal equations are singular (pass ``ridge > 0``).

    Example:
        >>> from torch_hsh.brdf import Lambertian
        >>> t = tabulate_merl(Lambertian(0.5), shape=(8, 8, 16))
        >>> a, info = fit_merl(t, 2, return_info=True)
        >>> round(float(a[0, 0]), 9), float(info["relative_error"].max()) < 1e-6   # a_0 = 2 rho
        (1.0, True)
    """
    import time

    t0 = time.perf_counter()
    brdf, b, P = _check_fit_arguments(brdf, order, basis, ridge, grazing_cutoff, chunk_size)
    wgt = _fit_weights(brdf, weights)
    sums = _normal_equations(brdf, b, P, wgt, grazing_cutoff, chunk_size, progress)
    if bool((sums.nused == 0).any()):
        raise ValueError("no usable sample in the table (every bin is unmeasured, has zero weight or lies below "
                         "the horizon)")
    K = b.num_functions(P)
    dev = sums.rhs.device
    orders = b.function_orders(P).to(dev)
    per_order = torch.zeros(3, P + 1, dtype=torch.float64, device=dev)
    coefficients, cond = _solve_orders(sums, ridge, orders, torch.ones(K, dtype=torch.bool, device=dev))
    full = torch.ones(K, dtype=torch.bool, device=dev)
    for p in range(P + 1):
        sel = orders <= p
        a_p = coefficients if p == P else _solve_orders(sums, ridge, orders, sel)[0]
        per_order[:, p] = _relative_error(a_p, sel, sums.G, sums.rhs, sums.yy)
    if not return_info:
        return coefficients
    info = {
        "relative_error": per_order[:, P].clone(),
        "relative_error_unweighted": _relative_error(coefficients, full, sums.Gu, sums.rhsu, sums.yyu),
        "relative_error_per_order": per_order,
        "energy": sums.yy,
        "accuracy": 1.0 - per_order ** 2,
        "num_samples": int(sums.nused[0]),
        "coverage": float(sums.wsum[0] / (4 * math.pi ** 2)),
        "condition": cond,
        "runtime_s": time.perf_counter() - t0,
    }
    return coefficients, info


def _check_fit_arguments(brdf, order, basis, ridge, grazing_cutoff, chunk_size):
    """``(MERLBRDF, basis, P)`` after the argument checks of :func:`fit_merl` (a path is read here)."""
    from ..bases import get_basis

    if isinstance(brdf, (str, os.PathLike)):
        brdf = read_merl(brdf)
    if not isinstance(brdf, MERLBRDF):
        raise TypeError(f"`brdf` must be a MERLBRDF or the path of a .binary file, got {type(brdf).__name__}")
    b = get_basis(basis)
    if not b.isotropic:
        raise ValueError(f"`basis` must be isotropic (a MERL table is sampled at phi_h = 0), got '{b.name}'")
    P = b.check_order(order)
    if isinstance(ridge, bool) or not isinstance(ridge, (int, float)) or not math.isfinite(ridge) or ridge < 0:
        raise ValueError(f"`ridge` must be a finite number >= 0, got {ridge!r}")
    if grazing_cutoff is not None and (isinstance(grazing_cutoff, bool) or not isinstance(grazing_cutoff, (int, float))
                                       or not 0.0 <= grazing_cutoff < 1.0):
        raise ValueError(f"`grazing_cutoff` must be a number in [0, 1) (a cosine) or None, got {grazing_cutoff!r}")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}")
    return brdf, b, P


def _fit_weights(brdf: "MERLBRDF", weights: Optional[torch.Tensor]) -> torch.Tensor:
    """The sample weights of :func:`fit_merl`: the solid-angle weights, or ``weights`` checked, as float64."""
    from .._checks import check_tensor

    shape = brdf.shape
    dev = brdf.raw.device
    if weights is None:
        return merl_solid_angle_weights(shape, device=dev)
    check_tensor(weights, "weights")
    check_shape(weights, "weights", ("N_theta_h", "N_theta_d", "N_phi_d"),  # the table's bins
                sizes=dict(zip(("N_theta_h", "N_theta_d", "N_phi_d"), shape)))
    wgt = weights.to(device=dev, dtype=torch.float64)
    if not bool(torch.isfinite(wgt).all()) or bool((wgt < 0).any()):
        raise ValueError("`weights` must be finite and >= 0")
    return wgt


@dataclass
class _NormalSums:
    """Weighted (and unweighted, suffix ``u``) normal equations of :func:`fit_merl` and the sample sums."""

    G: torch.Tensor  # (1 | 3, K, K): one matrix when every channel measures the same bins
    Gu: torch.Tensor
    rhs: torch.Tensor  # (3, K)
    rhsu: torch.Tensor
    yy: torch.Tensor  # (3,) weighted energy of the samples
    yyu: torch.Tensor
    wsum: torch.Tensor  # (3,) weight of the used samples
    nused: torch.Tensor  # (3,) number of used samples


def _normal_equations(brdf: "MERLBRDF", b, P: int, wgt: torch.Tensor, grazing_cutoff, chunk_size: int,
                      progress: bool) -> _NormalSums:
    """Accumulate the normal equations over the table's bins, in chunks of ``theta_h`` rows."""
    shape = brdf.shape
    dev = brdf.raw.device
    f64 = torch.float64
    table = brdf.table.to(f64)  # (3, nh, nd, npd)
    measured = brdf.measured
    shared = bool((measured == measured[:1]).all())  # one normal matrix for all channels
    nh, nd, npd = shape
    K = b.num_functions(P)
    G = torch.zeros(1 if shared else 3, K, K, dtype=f64, device=dev)
    z3 = torch.zeros(3, dtype=f64, device=dev)
    S = _NormalSums(G, torch.zeros_like(G), torch.zeros(3, K, dtype=f64, device=dev),
                    torch.zeros(3, K, dtype=f64, device=dev), z3.clone(), z3.clone(), z3.clone(),
                    torch.zeros(3, dtype=torch.long, device=dev))
    # Every isotropic reciprocal basis function takes the same value at phi_d and pi - phi_d (a mirror
    # of both directions, then wi <-> wo), and the bins k and N_pd - 1 - k are mirror images: the basis
    # is evaluated on half of the phi_d bins and each pair of bins is summed with its own weights.
    half = (npd + 1) // 2
    lo = torch.arange(half, device=dev)
    hi = npd - 1 - lo
    pair = (hi != lo).to(f64)  # 0 for the middle bin of an odd N_pd (its own mirror)
    th_c, td_c, pd_c = merl_bin_centers(shape, dtype=f64, device=dev)
    rows = max(1, chunk_size // (nd * half))
    bar = None
    if progress:
        import sys

        from tqdm.auto import tqdm

        bar = tqdm(total=nh * nd * npd, desc=f"fit_merl P={P}", unit="sample", unit_scale=True, file=sys.stderr)

    def fold(t):  # (..., npd) -> (..., half): bin k plus its mirror N_pd - 1 - k
        return t.index_select(-1, lo) + t.index_select(-1, hi) * pair

    try:
        for s in range(0, nh, rows):
            sl = slice(s, min(s + rows, nh))
            TH, TD, PD = torch.meshgrid(th_c[sl], td_c, pd_c, indexing="ij")
            # min(cos theta_i, cos theta_o) = cos th cos td - sin th sin td |cos pd| (see half_diff_to_dirs)
            zmin = TH.cos() * TD.cos() - TH.sin() * TD.sin() * PD.cos().abs()
            w = wgt[sl]  # (r, nd, npd)
            y = table[:, sl]  # (3, r, nd, npd)
            m = measured[:, sl] & (w > 0)[None] & (zmin >= 0.0)[None]
            if grazing_cutoff is not None:  # f set to zero beyond the cutoff, as in fitting.project
                y = torch.where((zmin >= float(grazing_cutoff))[None], y, torch.zeros_like(y))
            y = torch.where(m, y, torch.zeros_like(y))
            mf = m.to(f64)
            S.yy += (y * y * w).sum((1, 2, 3))
            S.yyu += (y * y).sum((1, 2, 3))
            S.wsum += (mf * w).sum((1, 2, 3))
            S.nused += m.sum((1, 2, 3))
            wm = fold(mf * w).reshape(3, -1)  # (3, n) weights of the half-grid samples
            um = fold(mf).reshape(3, -1)
            yw = fold(y * w).reshape(3, -1)
            yu = fold(y).reshape(3, -1)
            use = (um > 0).any(0)
            if bool(use.any()):
                idx = use.nonzero().squeeze(-1)
                wi, wo = half_diff_to_dirs(TH[..., :half], torch.zeros_like(TH[..., :half]), TD[..., :half],
                                           PD[..., :half])
                A = b.evaluate(wi.reshape(-1, 3)[idx], wo.reshape(-1, 3)[idx], P).to(f64)  # (n, K)
                for c in range(S.G.shape[0]):
                    S.G[c] += A.T @ (A * wm[c, idx, None])
                    S.Gu[c] += A.T @ (A * um[c, idx, None])
                S.rhs += yw[:, idx] @ A
                S.rhsu += yu[:, idx] @ A
            if bar is not None:
                bar.update((sl.stop - sl.start) * nd * npd)
    finally:
        if bar is not None:
            bar.close()
    return S


def _solve_orders(S: _NormalSums, ridge: float, orders: torch.Tensor, sel: torch.Tensor):
    """Coefficients ``(3, k)`` of the functions ``sel`` by Cholesky, and the condition of their normal matrix."""
    K = S.rhs.shape[-1]
    Gs = S.G.expand(3, K, K)
    eye = torch.eye(K, dtype=torch.float64, device=S.rhs.device)
    Gk = Gs[:, sel][:, :, sel] + ridge * eye[: int(sel.sum()), : int(sel.sum())]
    L, bad = torch.linalg.cholesky_ex(Gk)
    d = torch.diagonal(L, dim1=-2, dim2=-1).abs() if not bool(bad.any()) else None
    cond = float(((d.max(-1).values / d.min(-1).values.clamp(min=1e-300)) ** 2).max()) if d is not None else math.inf
    if d is None or cond > 1e12:
        raise ValueError(
            f"the normal equations of the order-{int(orders[sel].max())} fit are singular or ill-conditioned "
            f"(condition {cond:.3g}): the {int(S.nused.min())} usable samples do not determine the {int(sel.sum())} "
            f"functions; pass ridge > 0 (on the command line: --ridge, e.g. 1e-6) or lower the order")
    a = torch.cholesky_solve(S.rhs[:, sel, None], L)[..., 0]  # (3, k)
    return a, cond


def _relative_error(a: torch.Tensor, sel: torch.Tensor, Gm: torch.Tensor, r: torch.Tensor, n2: torch.Tensor):
    """``||y - A a|| / ||y||`` per channel from the normal equations ``Gm``, ``r`` and ``n2 = ||y||^2``."""
    K = r.shape[-1]
    Gk = Gm.expand(3, K, K)[:, sel][:, :, sel]
    res = n2 - 2 * (a * r[:, sel]).sum(-1) + torch.einsum("ck,ckl,cl->c", a, Gk, a)
    return torch.sqrt(res.clamp(min=0.0) / n2.clamp(min=1e-300))
