"""Stage 6 of the HSH solver: the result.

:class:`HSHResult` (maps of normals, coefficients, albedo, residuals, weights;
relighting), the closed-form directional albedo toward the camera
(:func:`directional_albedo_view`), and :class:`HoldoutResult` (the output of
:func:`~torch_hsh.ps.holdout_evaluation`, in :mod:`torch_hsh.ps.evaluation`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence

import torch

from ..bases.helmholtz import albedo_terms
from ..kernel import _polar_table, num_isotropic
from ..render.images import order_from_num_functions, render_coefficients
from ._chunks import row_sum

__all__ = ["HSHResult", "HoldoutResult", "confidence", "directional_albedo_view"]


_SAVE_FORMAT = "torch_hsh.HSHResult"
_SAVE_VERSION = 1


def _check_npy_member(p, zf, info) -> None:
    """Refuse an ``.npy`` member of ``p`` whose header claims more bytes than the member (or the archive) holds."""
    import numpy as np

    from .._checks import check_decoded_size

    check_decoded_size(p, info.file_size, "zip")
    with zf.open(info) as f:
        major, _ = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(f)
    claimed = math.prod(int(n) for n in shape) * dtype.itemsize
    if claimed > info.file_size:
        raise ValueError(f"{p}: member {info.filename} claims {claimed} bytes of {dtype} {shape}, it holds "
                         f"{info.file_size}")


#: The arrays of a saved HSHResult: name -> (trailing dimensions after the pixel shape S, None: not per pixel).
_SAVED = {"normals": (3,), "coefficients": (-1, -1), "albedo": (-1,), "residual": (), "mask": (), "lights": None,
          "weights": (-1,), "confidence": (), "mixing": (-1, -1), "depth": (), "basis_brdfs": None}


def _check_saved_arrays(p, arrays) -> None:
    """``ValueError`` naming ``p`` unless the arrays have the shapes and kinds of a saved HSHResult."""
    missing = [k for k in ("normals", "coefficients", "albedo", "residual", "mask", "lights") if k not in arrays]
    if missing:
        raise ValueError(f"{p}: not a saved HSHResult (no {', '.join(missing)})")
    n = arrays["normals"]
    S = n.shape[:-1] if n.ndim >= 2 else ()
    for name, v in arrays.items():
        if name not in _SAVED:
            continue
        tail = _SAVED[name]
        want = (-1, 3) if name == "lights" else ((-1, -1) if tail is None else S + tail)
        kind = "b" if name == "mask" else "f"
        if v.dtype.kind != kind or v.ndim != len(want) or any(w not in (-1, g) for w, g in zip(want, v.shape)):
            raise ValueError(f"{p}: corrupt HSHResult: {name} is {v.dtype} {v.shape}, expected "
                             f"{'bool' if kind == 'b' else 'float'} ({', '.join('*' if w < 0 else str(w) for w in want)})")


@dataclass
class HSHResult:
    """Output of :func:`solve_hsh`.

    Attributes:
        normals: ``(*S, 3)`` unit normals (DiLiGenT frame), zero outside ``mask``.
        coefficients: ``(*S, C, K)`` isotropic Helmholtz coefficient maps.
        albedo: ``(*S, C)`` directional albedo toward the camera,
            :math:`\\int f(\\omega_i, v) \\cos\\theta_i d\\omega_i`.
        residual: ``(*S)`` weighted RMS residual of the coefficient fit.
        weights: ``(*S, L)`` final robust observation weights of the normal
            estimation (0 = not used; the shared model fits the coefficients
            to every valid observation).
        mask: ``(*S)`` bool.
        order: basis order.
        lights: ``(L, 3)`` lights used in the fit.
        runtime_s: wall time of the solve in seconds.
        info: diagnostics (noise estimate, saturation level, iteration counts, ...).
        basis_brdfs: shared model only: ``(M, K)`` unit-norm basis BRDFs
            (isotropic Helmholtz coefficients), else ``None``.
        mixing: shared model only: ``(*S, C, M)`` per-pixel mixing weights
            (``coefficients ~= mixing @ basis_brdfs``), else ``None``.
        confidence: ``(*S)`` per-pixel confidence in ``[0, 1]`` (0 outside the
            mask and where fewer than 4 observations are valid): the coverage
            by inlier observations times the Cauchy weight of the pixel's
            residual (see :func:`torch_hsh.ps.result.confidence`). Threshold it
            to keep reliable pixels.
        depth: ``(*S)`` height map in pixel units (z toward the camera, NaN
            outside the mask) of the whole-surface stage
            (:func:`torch_hsh.ps.refine_surface`), else ``None``.
    """

    normals: torch.Tensor
    coefficients: torch.Tensor
    albedo: torch.Tensor
    residual: torch.Tensor
    weights: torch.Tensor
    mask: torch.Tensor
    order: int
    lights: torch.Tensor
    runtime_s: float
    info: Dict[str, float] = field(default_factory=dict)
    basis_brdfs: Optional[torch.Tensor] = None
    mixing: Optional[torch.Tensor] = None
    confidence: Optional[torch.Tensor] = None
    depth: Optional[torch.Tensor] = None

    def write(self, path, channels: Optional[Sequence[str]] = None, weights: bool = False,
             overwrite: bool = False) -> None:
        """Write the result to one ``.npz`` file with a versioned JSON metadata entry.

        Stored: ``normals``, ``coefficients`` (with named channels), ``albedo``,
        ``residual``, ``mask``, ``lights``, ``confidence``, ``basis_brdfs``,
        ``mixing`` and ``depth`` where they exist, and ``weights`` only if ``weights=True``
        (``(*S, L)``, the largest array); ``order``, ``info`` and ``runtime_s`` go
        into the metadata.

        Args:
            path: target file (``.npz`` is appended if missing).
            channels: names of the coefficient channels (default ``R, G, B`` for 3
                channels, ``Y`` for 1, else ``c0, c1, ...``).
            weights: also store the robust weight maps.
            overwrite: replace an existing file (default: refuse).

        Example:
            >>> res.write("bunny_result.npz")  # doctest: +SKIP
            >>> HSHResult.read("bunny_result.npz").normals.shape  # doctest: +SKIP
            torch.Size([256, 256, 3])
        """
        import json
        from pathlib import Path

        import numpy as np

        p = Path(path)
        if p.suffix != ".npz":
            p = p.with_name(p.name + ".npz")
        if p.exists() and not overwrite:
            raise FileExistsError(f"{p} exists; pass overwrite=True to replace it")
        C = self.coefficients.shape[-2]
        if channels is None:
            channels = ["R", "G", "B"] if C == 3 else (["Y"] if C == 1 else [f"c{i}" for i in range(C)])
        channels = [str(c) for c in channels]
        if len(channels) != C:
            raise ValueError(f"`channels` must name the {C} coefficient channels, got {channels}")
        arrays = {}
        for name in ("normals", "coefficients", "albedo", "residual", "mask", "lights", "confidence", "basis_brdfs",
                     "mixing", "depth") + (("weights",) if weights else ()):
            v = getattr(self, name)
            if v is not None:
                arrays[name] = v.detach().cpu().numpy()

        def _plain(v):
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, (list, tuple)):
                return [_plain(x) for x in v]
            return v if isinstance(v, (int, float, str, bool)) or v is None else str(v)

        meta = {"format": _SAVE_FORMAT, "version": _SAVE_VERSION, "order": int(self.order), "channels": channels,
                "runtime_s": float(self.runtime_s), "info": {k: _plain(v) for k, v in self.info.items()}}
        arrays["metadata"] = np.frombuffer(json.dumps(meta, allow_nan=False).encode("utf-8"), dtype=np.uint8)
        from .._atomic import atomic_file

        with atomic_file(p) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)

    @classmethod
    def read(cls, path, device=None) -> "HSHResult":
        """Read a result written by :meth:`write` (``weights`` is ``(*S, 0)`` if it was not stored).

        Raises:
            FileNotFoundError: missing file.
            ValueError: not a saved :class:`HSHResult`, or a newer format version.
        """
        import json
        import zipfile
        from pathlib import Path

        import numpy as np

        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
        with open(p, "rb") as f:
            magic = f.read(4)
        if magic != b"PK\x03\x04":  # every .npz is a zip archive; a .npy, a .json or a text file is not
            raise ValueError(f"{p}: not a saved HSHResult (not an .npz archive; give a result folder or its result.npz)")
        try:
            with zipfile.ZipFile(p) as zf:  # every header checked before numpy allocates what it claims
                for member in zf.infolist():
                    _check_npy_member(p, zf, member)
            with np.load(p, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            meta = json.loads(bytes(arrays.pop("metadata")).decode("utf-8"))
        except Exception as e:  # zipfile and numpy raise many kinds (BadZipFile, TokenError, NotImplementedError, ...)
            raise ValueError(f"{p}: not a saved HSHResult ({type(e).__name__}: {e})") from e
        if not isinstance(meta, dict) or meta.get("format") != _SAVE_FORMAT:
            got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
            raise ValueError(f"{p}: not a saved HSHResult (format {got!r})")
        version, order = meta.get("version", 0), meta.get("order")
        if not isinstance(version, int) or not isinstance(order, int) or isinstance(order, bool) or order < 0:
            raise ValueError(f"{p}: corrupt HSHResult metadata (version {version!r}, order {order!r})")
        if version > _SAVE_VERSION:
            raise ValueError(f"{p}: format version {meta['version']} is newer than this library's {_SAVE_VERSION}")
        _check_saved_arrays(p, arrays)
        try:
            t = {k: torch.from_numpy(v).to(device) for k, v in arrays.items()}
            runtime, info = float(meta.get("runtime_s", 0.0)), dict(meta.get("info", {}))
        except (TypeError, ValueError) as e:
            raise ValueError(f"{p}: corrupt HSHResult ({type(e).__name__}: {e})") from e
        S = tuple(t["normals"].shape[:-1])
        w = t.get("weights", torch.zeros(*S, 0, dtype=t["normals"].dtype, device=device))
        return cls(normals=t["normals"], coefficients=t["coefficients"], albedo=t["albedo"], residual=t["residual"],
                   weights=w, mask=t["mask"], order=order, lights=t["lights"], runtime_s=runtime, info=info,
                   basis_brdfs=t.get("basis_brdfs"), mixing=t.get("mixing"), confidence=t.get("confidence"),
                   depth=t.get("depth"))

    def relight(self, lights: torch.Tensor, intensities: Optional[torch.Tensor] = None, clamp: bool = True) -> torch.Tensor:
        """Render the fitted surface under new lights.

        Args:
            lights: ``(L', 3)`` directions toward the lights.
            intensities: ``None``, ``(L',)`` or ``(L', C)``.
            clamp: clamp negative radiance to zero (default).

        Returns:
            ``(L', *S, C)`` images, zero outside the mask.

        Example:
            >>> res.relight(torch.tensor([[0.0, 0.0, 1.0]])).shape  # doctest: +SKIP
            torch.Size([1, 64, 64, 3])
        """
        img = render_coefficients(self.normals, lights.to(self.normals), self.coefficients, intensities, None)
        img = img * self.mask.to(img.dtype).unsqueeze(-1)
        return img.clamp(min=0.0) if clamp else img


@dataclass
class HoldoutResult:
    """Output of :func:`~torch_hsh.ps.holdout_evaluation`.

    Attributes:
        train_indices, test_indices: light indices used for fitting / held out.
        relative_rmse: ``sqrt(sum (pred - obs)^2 / sum obs^2)`` over the held-out
            observations (inside the mask, unsaturated, finite) for the HSH fit.
        rmse: root-mean-square error of the HSH relighting (image units).
        lambertian_relative_rmse: the same for the robust Lambertian fit.
        predictions: ``(L_test, *S, C)`` relit images.
        result: the :class:`HSHResult` fitted on the training lights.
    """

    train_indices: torch.Tensor
    test_indices: torch.Tensor
    relative_rmse: float
    rmse: float
    lambertian_relative_rmse: float
    predictions: torch.Tensor
    result: HSHResult


def _albedo_vector(order: int, cos_o: torch.Tensor) -> torch.Tensor:
    """``D_k(cos_o) = integral of B_k(wi, wo) cos(theta_i) dwi`` for every isotropic function, ``(N, K)``.

    The terms are :func:`torch_hsh.bases.helmholtz.albedo_terms`; they are evaluated here on the solver's
    polar table (not the HSH of ``fitting.directional_albedo``) and summed per column, which keeps this
    function's rounding, and with it ``HSHResult.albedo``, as it was.
    """
    R = _polar_table(cos_o.clamp(0.0, 1.0), order)  # normalised Theta_n^m(cos_o) table
    # columns of the polar table for m = 0 are the first block: n = 0..P at columns 0..P
    terms = {k: (norm, zonal) for k, norm, zonal in albedo_terms(order, True)}
    cols = []
    zero = torch.zeros_like(cos_o)
    for k in range(num_isotropic(order)):
        if k not in terms:
            cols.append(zero)
            continue
        norm, zonal = terms[k]
        val = zero
        for moment, n, _ in zonal:
            val = val + moment * R[:, _m0_col(order, n)]
        cols.append(norm * val)
    return torch.stack(cols, dim=-1)


def _m0_col(order: int, n: int) -> int:
    # block layout of _polar_table: block j = n - m holds m = 0..P-j; m = 0 of block j sits at offset(j)
    off = 0
    for j in range(n):
        off += order + 1 - j
    return off


def directional_albedo_view(coefficients: torch.Tensor, cos_o: torch.Tensor) -> torch.Tensor:
    r"""Directional albedo :math:`\rho(\omega_o) = \int f(\omega_i, \omega_o)\cos\theta_i\,d\omega_i` in closed form.

    Args:
        coefficients: ``(..., C, K)`` isotropic Helmholtz coefficients.
        cos_o: ``(...)`` cosine of the outgoing direction with the normal.

    Returns:
        ``(..., C)``.

    Example:
        >>> a = torch.zeros(1, 3, 20, dtype=torch.float64); a[..., 0] = 2 * 0.5  # Lambertian rho = 0.5
        >>> directional_albedo_view(a, torch.tensor([0.7], dtype=torch.float64))
        tensor([[0.5000, 0.5000, 0.5000]], dtype=torch.float64)
    """
    K = coefficients.shape[-1]

    order = order_from_num_functions(K)
    lead = cos_o.shape
    D = _albedo_vector(order, cos_o.reshape(-1).to(coefficients.dtype))  # (N, K)
    a = coefficients.reshape(-1, coefficients.shape[-2], K)
    return torch.einsum("nck,nk->nc", a, D).reshape(*lead, coefficients.shape[-2])


def confidence(weights: torch.Tensor, residual: torch.Tensor, scale: float, order: int, c: float) -> torch.Tensor:
    """Per-pixel confidence in ``[0, 1]``: enough inliers, times a fit at the noise level.

    ``weights (N, L)`` robust weights, ``residual (N,)`` weighted RMS residual,
    ``scale`` the robust residual scale of the solve. Two factors:

    * coverage ``clamp((n_eff - 3) / (U - 3), 0, 1)`` with ``n_eff`` the sum of
      the robust weights and ``U = (P+1)(P+2)/2`` the number of BRDF
      combinations one viewpoint can identify: 0 with 3 inliers (a normal and
      nothing else), 1 once there are as many inliers as identifiable terms;
    * fit ``1 / (1 + (residual / (c scale))^2)``: the Cauchy weight of the
      pixel's residual, the same weight the solver gives an observation.
    """
    U = (order + 1) * (order + 2) // 2
    n_eff = row_sum(weights, residual.dtype)
    cover = ((n_eff - 3.0) / max(U - 3, 1)).clamp(0.0, 1.0)
    sc = max(float(scale), 1e-30)
    fit = 1.0 / (1.0 + (residual / (c * sc)) ** 2)
    out = cover * fit
    return torch.where(torch.isfinite(out), out, torch.zeros_like(out))
