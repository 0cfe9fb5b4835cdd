r"""``torch.nn.Module`` layers built on the Helmholtz HSH bases.

* :class:`HSH` — hemispherical harmonics of a batch of directions, a thin
  wrapper of :func:`torch_hsh.hsh` (useful as a fixed feature layer).
* :class:`HelmholtzBRDF` — a reciprocal BRDF :math:`f(\omega_i, \omega_o) =
  \sum_k a_k \mathcal H_k(\omega_i, \omega_o)` with learnable (or fixed)
  coefficients, one set per colour channel, optionally supplied per call
  (per-pixel BRDFs predicted by a network).

Both modules are device/dtype agnostic (``.to(...)`` moves everything), save
and load through ``state_dict``, and work with ``torch.jit.trace`` (and
``torch.jit.save``), ``torch.compile`` (``fullgraph=True``), ``torch.export``
(dynamic batch), forward-mode AD and ``DistributedDataParallel``. Under
``torch.autocast``, and for half-precision (float16 / bfloat16) inputs, coefficients
or modules (``module.half()``), :class:`HelmholtzBRDF` computes in float32 inside and
returns the dtype that type promotion gives its inputs (float16 for a float16
module and inputs), float32 under autocast. ``torch.jit.script`` is **not** supported: the functional
bases they call validate their inputs in plain Python (``isinstance`` checks,
``functools.lru_cache`` constant tables, a global validation switch), which
TorchScript cannot compile. Use ``torch.jit.trace`` (or ``torch.compile``)
instead.

Conventions are those of :mod:`torch_hsh.kernel`: directions in the local
frame with ``z`` along the normal; a direction below the horizon (``z < 0``) or
a zero vector makes the BRDF 0.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import torch
from torch import nn

from ._checks import MAX_ANISOTROPIC_ORDER, check_order, check_shape, check_tensor
from .bases.helmholtz import albedo_terms
from .kernel import (
    HALF_DTYPES,
    anisotropic_indices,
    autocast_enabled,
    helmholtz_anisotropic,
    helmholtz_isotropic,
    helmholtz_isotropic_world,
    hsh,
    isotropic_indices,
    num_anisotropic,
    num_hsh,
    num_isotropic,
)

__all__ = ["HSH", "HelmholtzBRDF"]


class HSH(nn.Module):
    r"""Real hemispherical harmonics up to ``order`` as a module.

    ``forward(dirs)`` is :func:`torch_hsh.hsh` with a fixed order: it maps
    ``(..., 3)`` local-frame directions (normalised internally; ``z < 0`` and
    zero vectors give 0) to ``(..., (order+1)**2)`` values, entry
    ``n*n + n + m`` being :math:`H_n^m`. The module has no parameters.

    Args:
        order: maximum order ``P >= 0`` (at most 40).

    Example:
        >>> import torch, torch_hsh
        >>> layer = torch_hsh.HSH(2)
        >>> layer(torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])).shape
        torch.Size([2, 9])
    """

    def __init__(self, order: int) -> None:
        super().__init__()
        self.order = check_order(order)

    @property
    def num_functions(self) -> int:
        """Number of output features, ``(order + 1)**2``."""
        return num_hsh(self.order)

    def forward(self, dirs: torch.Tensor) -> torch.Tensor:
        """``(..., 3)`` directions -> ``(..., (order+1)**2)`` HSH values."""
        return hsh(dirs, self.order)

    def extra_repr(self) -> str:
        return f"order={self.order}, num_functions={self.num_functions}"

    # The order is kept in the state_dict (``_extra_state``) so that a checkpoint of another order
    # does not load silently into this module.
    def get_extra_state(self) -> Dict[str, Any]:
        return {"order": self.order}

    def set_extra_state(self, state: Any) -> None:
        if not isinstance(state, dict) or "order" not in state:
            raise ValueError(f"checkpoint for HSH: expected {{'order': P}} as its extra state, got {state!r}")
        if state["order"] != self.order:
            raise ValueError(f"checkpoint does not match this HSH: order={state['order']!r} (module has "
                             f"order={self.order}); build it with HSH({state['order']!r})")

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints from before the order was kept (an empty state) load as before, strict mode included
        if prefix + "_extra_state" not in state_dict:
            state_dict[prefix + "_extra_state"] = self.get_extra_state()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


# --------------------------------------------------------------------------
# Closed-form directional albedo tables
# --------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _albedo_terms(order: int, isotropic: bool) -> Tuple[Tuple[int, ...], Tuple[int, ...], Tuple[float, ...]]:
    r"""Sparse map from (HSH column of wo, coefficient column) to a weight.

    ``albedo(wo) = sum_e w_e * H_{h_e}(wo) * a_{c_e}``, flattened from
    :func:`torch_hsh.bases.helmholtz.albedo_terms` (see :meth:`HelmholtzBRDF.albedo`).
    """
    h_idx, c_idx, w = [], [], []
    for col, norm, terms in albedo_terms(order, isotropic):
        for moment, n, m in terms:
            h_idx.append(n * n + n + m)
            c_idx.append(col)
            w.append(norm * moment)
    return tuple(h_idx), tuple(c_idx), tuple(w)


#: The bases a :class:`HelmholtzBRDF` can be built on.
_BASES = ("helmholtz_isotropic", "helmholtz_anisotropic")


def _current_config(state: Dict[str, Any]) -> Dict[str, Any]:
    """A checkpoint's configuration in the current form (version 1 kept ``isotropic: bool`` for ``basis``)."""
    state = dict(state)
    if "basis" not in state and "isotropic" in state:
        state["basis"] = _BASES[0] if state.pop("isotropic") else _BASES[1]
    return state


_InitType = Union[str, torch.Tensor]


class HelmholtzBRDF(nn.Module):
    r"""A reciprocal BRDF expanded in the Helmholtz HSH basis.

    .. math::
        f_c(\omega_i, \omega_o) = \sum_{k=0}^{K-1} a_{c,k}\, \mathcal H_k(\omega_i, \omega_o),
        \qquad c = 0, \dots, C-1.

    Every basis function is reciprocal, so the module output satisfies
    :math:`f(\omega_i, \omega_o) = f(\omega_o, \omega_i)` exactly, for any
    coefficients.

    Args:
        order: maximum order ``P`` of the basis (isotropic: at most 40,
            anisotropic: at most 16).
        basis: ``"helmholtz_isotropic"`` (default) for the isotropic basis
            (:func:`torch_hsh.helmholtz_isotropic`,
            ``K = (P+1)(P+2)(P+3)/6`` columns in the order of
            :func:`torch_hsh.isotropic_indices`); ``"helmholtz_anisotropic"`` for the
            general basis (:func:`torch_hsh.helmholtz_anisotropic`,
            ``K = Q(Q+1)/2``, ``Q = (P+1)**2``, order of
            :func:`torch_hsh.anisotropic_indices`).
        channels: number of output channels ``C`` (e.g. 3 for RGB).
        init: ``"lambertian"`` (default): only :math:`a_{00}^0 = 2\rho` (``albedo``) is
            non-zero, so the module starts as the Lambertian BRDF
            :math:`\rho/\pi` (because :math:`\mathcal H_{00}^0 = 1/(2\pi)`);
            ``"zeros"``; or a tensor of shape ``(C, K)`` or ``(K,)`` (copied,
            repeated over channels) with the initial coefficients.
        albedo: Lambertian albedo used by ``init="lambertian"``: a float or a
            sequence of ``C`` floats. Default 0.5.
        learnable: if ``True`` (default) the coefficients are an
            ``nn.Parameter``; otherwise a buffer (still saved in the
            ``state_dict`` and moved by ``.to``).
        nonnegative: if ``True``, the output of :meth:`forward` /
            :meth:`forward_world` is clamped at 0 in the forward pass with a
            **straight-through gradient**: the value is ``max(f, 0)`` but the
            gradient is that of ``f``, so a sample clamped to 0 can still be
            pulled back up by the loss (a plain ``clamp`` would give it zero
            gradient). Values where ``f >= 0`` are unchanged, so a band-limited
            non-negative fit and the Lambertian init are exact.
            :meth:`albedo` and :meth:`basis` ignore the clamp. Default False.
        dtype, device: of the coefficient tensor (default: torch defaults).

    Attributes:
        coefficients: ``(C, K)`` tensor (parameter or buffer).
        basis_name: the ``basis`` argument (:meth:`basis` evaluates the basis functions).

    Shapes:
        ``forward(wi, wo, coefficients=None)``: ``wi``, ``wo`` ``(..., 3)``
        (broadcast together) -> ``(..., C)``. ``coefficients`` optionally replaces
        the module's coefficients for this call: ``(C, K)``, or
        ``(..., C, K)`` whose leading dimensions broadcast with those of the
        directions (e.g. one BRDF per pixel predicted by a network).

    Example:
        >>> import torch, torch_hsh
        >>> brdf = torch_hsh.HelmholtzBRDF(order=3, channels=3)
        >>> wi = torch.tensor([[0.0, 0.6, 0.8]])
        >>> wo = torch.tensor([[0.0, 0.0, 1.0]])
        >>> brdf(wi, wo).detach()  # Lambertian rho / pi = 0.5 / pi
        tensor([[0.1592, 0.1592, 0.1592]])
    """

    def __init__(
        self,
        order: int,
        basis: str = "helmholtz_isotropic",
        channels: int = 1,
        init: _InitType = "lambertian",
        albedo: Union[float, Sequence[float]] = 0.5,
        learnable: bool = True,
        nonnegative: bool = False,
        dtype: Optional[torch.dtype] = None,
        device: Optional[Union[str, torch.device]] = None,
    ) -> None:
        super().__init__()
        if basis not in _BASES:
            raise ValueError(f"`basis` must be one of {', '.join(map(repr, _BASES))}, got {basis!r}")
        isotropic = basis == "helmholtz_isotropic"
        if not isinstance(learnable, bool):
            raise TypeError(f"`learnable` must be a bool, got {type(learnable).__name__}")
        if not isinstance(nonnegative, bool):
            raise TypeError(f"`nonnegative` must be a bool, got {type(nonnegative).__name__}")
        if isotropic:
            order = check_order(order)
            k = num_isotropic(order)
        else:
            order = check_order(order, max_order=MAX_ANISOTROPIC_ORDER)
            k = num_anisotropic(order)
        if isinstance(channels, bool) or not isinstance(channels, int) or channels < 1:
            raise ValueError(f"`channels` must be a positive integer, got {channels!r}")
        if dtype is None:
            dtype = torch.get_default_dtype()
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"`dtype` must be torch.float32 or torch.float64, got {dtype}")
        self.order = order
        self.basis_name = basis
        self._isotropic = isotropic
        self.channels = channels
        self.nonnegative = nonnegative
        self.learnable = learnable

        initial = self._initial_coefficients(init, albedo, channels, k, dtype, device)
        if learnable:
            self.coefficients = nn.Parameter(initial)
        else:
            self.register_buffer("coefficients", initial)

    # ------------------------------------------------------------------ init
    @staticmethod
    def _initial_coefficients(init, albedo, channels, k, dtype, device) -> torch.Tensor:
        if isinstance(init, torch.Tensor):
            check_tensor(init, "init")
            # C channels, K basis functions
            check_shape(init, "init", ("C", "K"), ("K",), sizes={"C": channels, "K": k})
            if init.shape == (k,):
                init = init.unsqueeze(0).expand(channels, k)
            return init.detach().to(dtype=dtype, device=device).clone()
        if not isinstance(init, str):
            raise TypeError(f"`init` must be 'lambertian', 'zeros' or a tensor, got {type(init).__name__}")
        out = torch.zeros(channels, k, dtype=dtype, device=device)
        if init == "zeros":
            return out
        if init != "lambertian":
            raise ValueError(f"`init` must be 'lambertian', 'zeros' or a tensor, got {init!r}")
        if isinstance(albedo, (int, float)) and not isinstance(albedo, bool):
            albedo_t = torch.full((channels,), float(albedo), dtype=dtype, device=device)
        else:
            try:
                albedo_t = torch.as_tensor(albedo, dtype=dtype, device=device).reshape(-1)
            except (TypeError, ValueError, RuntimeError):
                raise TypeError(f"`albedo` must be a float or a sequence of {channels} floats, got {albedo!r}") from None
            if albedo_t.numel() != channels:
                raise ValueError(f"`albedo` must be a float or a sequence of {channels} floats, got {albedo_t.numel()} values")
        # Column 0 is (p, r, q) = (0, 0, 0) in the isotropic basis and the pair
        # (H_0^0, H_0^0) in the anisotropic one; both equal 1 / (2 pi).
        out[:, 0] = 2.0 * albedo_t
        return out

    # ------------------------------------------------------------ properties
    @property
    def num_functions(self) -> int:
        """Number of basis functions ``K`` per channel."""
        return int(self.coefficients.shape[-1])

    # ------------------------------------------------------------ checkpoints
    def get_extra_state(self) -> Dict[str, Any]:
        """The configuration kept in the ``state_dict`` (key ``_extra_state``):
        ``order``, ``basis``, ``channels``, ``learnable``, ``nonnegative``."""
        return {"version": 2, "order": self.order, "basis": self.basis_name, "channels": self.channels,
                "learnable": self.learnable, "nonnegative": self.nonnegative}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        """Check that a checkpoint's configuration matches this module (clear error if not)."""
        if not isinstance(state, dict) or "order" not in state:
            raise ValueError(f"HelmholtzBRDF checkpoint extra state is not recognised: {state!r}")
        mine = self.get_extra_state()
        state = _current_config(state)
        diff = [f"{k}={state[k]!r} (module has {mine[k]!r})" for k in ("order", "basis", "channels")
                if k in state and state[k] != mine[k]]
        if diff:
            raise ValueError(
                "checkpoint does not match this HelmholtzBRDF: " + ", ".join(diff)
                + "; build it with HelmholtzBRDF.from_state_dict(state_dict)"
            )
        self.nonnegative = bool(state.get("nonnegative", self.nonnegative))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints from before the configuration was kept load as before (strict mode included)
        if prefix + "_extra_state" not in state_dict:
            state_dict[prefix + "_extra_state"] = self.get_extra_state()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @classmethod
    def from_state_dict(cls, state_dict: Dict[str, Any], prefix: str = "", **kwargs: Any) -> "HelmholtzBRDF":
        """Build a module from a checkpoint without repeating its configuration.

        Args:
            state_dict: the output of :meth:`state_dict` (of this module, or of a
                model that holds it, with ``prefix`` such as ``"brdf."``).
            prefix: key prefix of this module inside ``state_dict``.
            **kwargs: further constructor arguments (e.g. ``device``).

        Example:
            >>> m = HelmholtzBRDF(order=2, channels=3, nonnegative=True)
            >>> m2 = HelmholtzBRDF.from_state_dict(m.state_dict())
            >>> (m2.order, m2.channels, m2.nonnegative, torch.equal(m2.coefficients, m.coefficients))
            (2, 3, True, True)
        """
        key = prefix + "_extra_state"
        if key not in state_dict:
            raise KeyError(f"no {key!r} in the state_dict: it was saved before HelmholtzBRDF kept its "
                           "configuration; construct the module with its order/basis/channels and load it")
        cfg = _current_config(dict(state_dict[key]))
        kwargs.setdefault("dtype", state_dict[prefix + "coefficients"].dtype)
        m = cls(order=cfg["order"], basis=cfg["basis"], channels=cfg["channels"], init="zeros",
                learnable=cfg.get("learnable", True), nonnegative=cfg.get("nonnegative", False), **kwargs)
        m.load_state_dict({k[len(prefix):]: v for k, v in state_dict.items() if k.startswith(prefix)
                           and "." not in k[len(prefix):]})
        return m

    @property
    def indices(self) -> torch.Tensor:
        """Index table of the basis columns: ``(K, 3)`` rows ``(p, r, q)`` if isotropic,
        else ``(K, 4)`` rows ``(p, q, r, s)`` (see :func:`torch_hsh.isotropic_indices` /
        :func:`torch_hsh.anisotropic_indices`)."""
        return isotropic_indices(self.order) if self._isotropic else anisotropic_indices(self.order)

    def extra_repr(self) -> str:
        return (
            f"order={self.order}, basis={self.basis_name!r}, channels={self.channels}, "
            f"num_functions={self.num_functions}, learnable={self.learnable}, "
            f"nonnegative={self.nonnegative}"
        )

    # --------------------------------------------------------------- helpers
    def _mixed(self, *dirs: torch.Tensor, coefficients: Optional[torch.Tensor] = None) -> Optional[Tuple[torch.dtype, torch.dtype]]:
        """``(work, out)`` dtypes where a call runs in float32 inside: under ``torch.autocast``, or where the
        directions, the coefficients used or the module are half precision (float16/bfloat16); else None.
        ``out`` is the dtype that torch's type promotion gives the inputs and coefficients (float16 for float16
        inputs and module), under autocast float32 at least (as autocast's float32 operations)."""
        c = self.coefficients if coefficients is None else coefficients
        half = getattr(c, "dtype", None) in HALF_DTYPES
        for t in dirs:
            half = half or getattr(t, "dtype", None) in HALF_DTYPES
        if not isinstance(dirs[0], torch.Tensor):
            return None  # the usual checks name the argument
        dev = "cpu" if dirs[0].is_cpu else dirs[0].device.type  # (is_cpu: a fraction of device.type's cost)
        if not (half or autocast_enabled(dev)):
            return None
        ts = [t for t in dirs if isinstance(t, torch.Tensor)]
        if len(ts) != len(dirs) or not isinstance(c, torch.Tensor):
            return None
        ts.append(c)
        amp = autocast_enabled(dev)
        out = ts[0].dtype
        for t in ts[1:]:
            out = torch.promote_types(out, t.dtype)
        if amp:
            out = torch.promote_types(out, torch.float32)
        return (torch.float64 if out == torch.float64 else torch.float32), out

    def _own(self, coefficients: Optional[torch.Tensor]) -> torch.Tensor:
        return self.coefficients if coefficients is None else coefficients

    def _in_float32(self, mixed: Tuple[torch.dtype, torch.dtype], fn, named: Dict[str, torch.Tensor]) -> torch.Tensor:
        """``fn(*named.values())`` in the work dtype of :meth:`_mixed` with autocast off, the result in its output
        dtype (the directions' device is checked against the module's)."""
        work, out = mixed
        for name, t in named.items():
            if name != "coefficients":
                self._check_device(t, name)
        xs = [t.to(work) for t in named.values()]
        if named.get("wi") is not None and named.get("wi") is named.get("wo"):
            xs[1] = xs[0]  # one direction set stays one tensor (computed once)
        with torch.autocast(xs[0].device.type, enabled=False):
            return fn(*xs).to(out)

    def _check_like(self, t: torch.Tensor, name: str) -> None:
        if t.dtype != self.coefficients.dtype:
            raise TypeError(
                f"`{name}` has dtype {t.dtype} but the module's coefficients are {self.coefficients.dtype}; "
                f"convert the input or call module.to({t.dtype})"
            )
        self._check_device(t, name)

    def _check_device(self, t: torch.Tensor, name: str) -> None:
        c = self.coefficients
        if t.device != c.device:
            raise ValueError(
                f"`{name}` is on {t.device} but the module's coefficients are on {c.device}; "
                f"move the input or call module.to({str(t.device)!r})"
            )

    def _resolve_coeffs(self, coefficients: Optional[torch.Tensor], ref: torch.Tensor) -> torch.Tensor:
        if coefficients is None:
            return self.coefficients
        check_tensor(coefficients, "coefficients", min_dims=2)
        check_shape(coefficients, "coefficients", ("*", self.channels, self.num_functions))  # (..., channels, basis functions)
        if coefficients.dtype != ref.dtype:
            raise TypeError(f"`coefficients` has dtype {coefficients.dtype} but the directions are {ref.dtype}")
        if coefficients.device != ref.device:
            raise ValueError(f"`coefficients` is on {coefficients.device} but the directions are on {ref.device}")
        return coefficients

    def _combine(self, basis: torch.Tensor, coefficients: Optional[torch.Tensor]) -> torch.Tensor:
        """``(..., K)`` basis values and coefficients -> ``(..., C)``."""
        c = self._resolve_coeffs(coefficients, basis)
        if c.dim() == 2:
            out = torch.nn.functional.linear(basis, c)
        else:
            batch = basis.shape[:-1]
            cb = c.shape[:-2]
            try:
                torch.broadcast_shapes(batch, cb)
            except RuntimeError:
                raise ValueError(
                    f"leading shape of `coefficients` {tuple(cb)} does not broadcast with the directions' "
                    f"leading shape {tuple(batch)}"
                ) from None
            out = torch.matmul(c, basis.unsqueeze(-1)).squeeze(-1)
        if self.nonnegative:
            # straight-through clamp: value max(f, 0), gradient of f
            out = out + (out.clamp(min=0.0) - out).detach()
        return out

    # --------------------------------------------------------------- forward
    def basis(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        r"""Basis matrix :math:`\mathcal H_k(\omega_i, \omega_o)`, ``(..., K)``.

        The design matrix of a linear least-squares fit: ``forward(wi, wo)``
        equals ``basis(wi, wo) @ coefficients.T`` (before the optional
        non-negativity clamp).

        Example:
            >>> import torch, torch_hsh
            >>> m = torch_hsh.HelmholtzBRDF(2)
            >>> m.basis(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.6, 0.8])).shape
            torch.Size([10])
        """
        mixed = self._mixed(wi, wo)
        if mixed is not None:
            return self._in_float32(mixed, self._basis, {"wi": wi, "wo": wo})
        self._check_like(wi, "wi")
        self._check_like(wo, "wo")
        return self._basis(wi, wo)

    def _basis(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        if self._isotropic:
            return helmholtz_isotropic(wi, wo, self.order)
        return helmholtz_anisotropic(wi, wo, self.order)

    def forward(self, wi: torch.Tensor, wo: torch.Tensor, coefficients: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Evaluate the BRDF at local-frame direction pairs.

        Args:
            wi: ``(..., 3)`` incident directions, local frame (z = normal).
            wo: ``(..., 3)`` outgoing directions; broadcast with ``wi``.
            coefficients: optional per-call coefficients ``(C, K)`` or ``(..., C, K)``
                (leading dims broadcast with the directions'); default: the
                module's own.

        Returns:
            ``(..., C)`` BRDF values (0 where a direction is below the horizon).
        """
        mixed = self._mixed(wi, wo, coefficients=coefficients)
        if mixed is not None:
            return self._in_float32(mixed, lambda a, b, c: self._combine(self._basis(a, b), c),
                                    {"wi": wi, "wo": wo, "coefficients": self._own(coefficients)})
        self._check_like(wi, "wi")
        self._check_like(wo, "wo")
        return self._combine(self._basis(wi, wo), coefficients)

    def forward_world(
        self,
        wi: torch.Tensor,
        wo: torch.Tensor,
        normal: torch.Tensor,
        coefficients: Optional[torch.Tensor] = None,
    ) -> torch.Tensor:
        """Evaluate an isotropic BRDF from world-space directions and normals.

        Uses :func:`torch_hsh.helmholtz_isotropic_world`, which needs no
        tangent frame and is differentiable with respect to ``normal`` (e.g.
        for photometric stereo or inverse rendering).

        Args:
            wi: ``(..., 3)`` light directions (toward the light), world frame.
            wo: ``(..., 3)`` view directions (toward the camera), world frame.
            normal: ``(..., 3)`` surface normals; all three broadcast together.
            coefficients: optional per-call coefficients as in :meth:`forward`.

        Returns:
            ``(..., C)``; equals ``forward(to_local(wi, n), to_local(wo, n))``.

        Raises:
            ValueError: if the module is anisotropic (its value depends on the
                tangent: rotate the directions with
                :func:`torch_hsh.frames.to_local` and a tangent, then call
                :meth:`forward`).
        """
        if not self._isotropic:
            raise ValueError(
                "forward_world needs an isotropic HelmholtzBRDF (basis=\"helmholtz_isotropic\"); an anisotropic BRDF "
                "depends on the tangent: use torch_hsh.frames.to_local(v, normal, tangent) and forward()"
            )
        mixed = self._mixed(wi, wo, normal, coefficients=coefficients)
        if mixed is not None:
            return self._in_float32(mixed, lambda a, b, n, c: self._combine(helmholtz_isotropic_world(a, b, n, self.order), c),
                                    {"wi": wi, "wo": wo, "normal": normal, "coefficients": self._own(coefficients)})
        self._check_like(wi, "wi")
        self._check_like(wo, "wo")
        self._check_like(normal, "normal")
        return self._combine(helmholtz_isotropic_world(wi, wo, normal, self.order), coefficients)

    def albedo(self, wo: torch.Tensor, coefficients: Optional[torch.Tensor] = None) -> torch.Tensor:
        r"""Directional albedo :math:`\rho(\omega_o) = \int_{\Omega} f(\omega_i, \omega_o)\cos\theta_i\, d\omega_i`
        in closed form.

        Derivation (isotropic basis). Integrating over :math:`\phi_i` kills every
        ``q > 0`` function (:math:`\int_0^{2\pi}\cos(q\,\Delta\phi)\,d\phi_i = 0`);
        for ``q = 0``, with :math:`\Theta_n^0 = \sqrt{(2n+1)/(2\pi)}\,\tilde P_n(\cos\theta)`,

        .. math::
            I_n = \int_\Omega \Theta_n^0(\theta_i)\cos\theta_i\,d\omega_i
                = 2\pi\sqrt{\tfrac{2n+1}{2\pi}}\int_0^1 \tilde P_n(x)\,x\,dx,

        i.e. :math:`I_0 = \sqrt{2\pi}/2`, :math:`I_1 = \sqrt{6\pi}/6 = \sqrt{\pi/6}`,
        :math:`I_n = 0` for ``n >= 2``. Hence

        .. math::
            \rho(\omega_o) = \sum_{p \ge r,\ q = 0} a_{pr}^0\,\frac{1}{\sqrt{2+2\delta_{pr}}}
            \left[I_p\,\Theta_r^0(\theta_o) + I_r\,\Theta_p^0(\theta_o)\right],

        where only ``r <= 1`` terms survive. The anisotropic basis is the same
        with :math:`J_{n}^{m} = I_n\delta_{m0}` in place of :math:`I_n` and
        :math:`H_j(\omega_o)` in place of :math:`\Theta(\theta_o)`. A
        Lambertian :math:`\rho/\pi` gives back :math:`\rho` for every ``wo``.
        The non-negativity clamp (if enabled) is not taken into account.

        Args:
            wo: ``(..., 3)`` outgoing directions, local frame.
            coefficients: optional per-call coefficients as in :meth:`forward`.

        Returns:
            ``(..., C)`` albedo (0 for ``wo`` below the horizon).

        Example:
            >>> import torch, torch_hsh
            >>> m = torch_hsh.HelmholtzBRDF(3, albedo=0.7)
            >>> m.albedo(torch.tensor([0.6, 0.0, 0.8])).detach()
            tensor([0.7000])
        """
        mixed = self._mixed(wo, coefficients=coefficients)
        if mixed is not None:
            return self._in_float32(mixed, self._albedo, {"wo": wo, "coefficients": self._own(coefficients)})
        self._check_like(wo, "wo")
        return self._albedo(wo, coefficients)

    def _albedo(self, wo: torch.Tensor, coefficients: Optional[torch.Tensor]) -> torch.Tensor:
        c = self._resolve_coeffs(coefficients, wo)
        h_idx, c_idx, w = _albedo_terms(self.order, self._isotropic)
        # H_n(wo) for every n <= P can enter (the factor I_r needs r <= 1, not p)
        n_hsh = 1 + max(h_idx)
        h_order = int(math.isqrt(n_hsh - 1))
        H = hsh(wo, h_order)  # (..., (h_order+1)^2)
        dev = wo.device
        hi = torch.tensor(h_idx, dtype=torch.long, device=dev)
        ci = torch.tensor(c_idx, dtype=torch.long, device=dev)
        wt = torch.tensor(w, dtype=wo.dtype, device=dev)
        Hs = H.index_select(-1, hi) * wt  # (..., E)
        Cs = c.index_select(-1, ci)  # (C, E) or (..., C, E)
        if Cs.dim() == 2:
            return torch.nn.functional.linear(Hs, Cs)
        return torch.matmul(Cs, Hs.unsqueeze(-1)).squeeze(-1)
