"""Input validation shared by every public entry point.

All checks raise ``TypeError`` or ``ValueError`` naming the offending argument
and what was expected. Data-dependent checks (NaN / Inf) need a device sync;
they are skipped while ``torch.compile`` traces, and can be switched off
globally with :func:`torch_hsh.set_validation` for hot loops on GPU.
"""
from __future__ import annotations

import operator
from typing import Dict, Optional, Sequence, Tuple, Union

import torch

#: Largest order accepted by :func:`torch_hsh.hsh` and the isotropic basis.
MAX_ORDER = 40
#: Largest order accepted by the anisotropic basis (K(K+1)/2 grows as order**4).
MAX_ANISOTROPIC_ORDER = 16

_FLOAT_DTYPES = (torch.float32, torch.float64)

_state = {"validate": True}


def set_validation(enabled: bool) -> None:
    """Globally enable or disable data-dependent input checks (NaN/Inf scans).

    Shape, dtype, device and order checks are always performed; only the checks
    that read tensor values (and therefore synchronise a CUDA stream) are
    affected. Enabled by default.

    Example:
        >>> import torch_hsh
        >>> torch_hsh.set_validation(False)  # inside a tight CUDA training loop
        >>> torch_hsh.set_validation(True)
    """
    _state["validate"] = bool(enabled)


def validation_enabled() -> bool:
    """Whether data-dependent checks run (see :func:`set_validation`)."""
    if not _state["validate"]:
        return False
    try:
        if torch.compiler.is_compiling():
            return False
    except AttributeError:  # pragma: no cover - very old torch
        pass
    if torch.jit.is_tracing() or torch.jit.is_scripting():
        return False
    try:  # inside torch.func transforms (vmap, jacrev, ...) values cannot be read
        if torch._C._are_functorch_transforms_active():
            return False
    except AttributeError:  # pragma: no cover
        pass
    return True


def check_order(order, name: str = "order", max_order: int = MAX_ORDER) -> int:
    """Return ``order`` as a Python int or raise a clear error."""
    if isinstance(order, torch.Tensor):
        if order.numel() != 1 or order.is_floating_point() or order.is_complex():
            raise TypeError(f"`{name}` must be a non-negative integer, got a tensor {order!r}")
        order = int(order.item())
    order = check_count(order, name)
    if order > max_order:
        raise ValueError(f"`{name}` must be <= {max_order} (the supported maximum), got {order}")
    return order


def check_count(value, name: str, minimum: int = 0) -> int:
    """Return ``value`` as a Python int ``>= minimum`` (a bool or a float is refused) or raise a clear error.

    Example:
        >>> from torch_hsh._checks import check_count
        >>> check_count(3, "n_lights", minimum=3)
        3
    """
    kind = "a non-negative integer" if minimum == 0 else "an integer"
    try:
        if isinstance(value, bool):
            raise TypeError
        value = operator.index(value)
    except TypeError:
        raise TypeError(f"`{name}` must be {kind}, got {value!r} ({type(value).__name__})") from None
    if value < minimum:
        raise ValueError(f"`{name}` must be >= {minimum}, got {value}")
    return value


def check_tensor(
    x,
    name: str,
    last_dim: Optional[int] = None,
    min_dims: int = 0,
    allow_nonfinite: bool = False,
    floating: bool = True,
) -> torch.Tensor:
    """Check type, dtype, trailing dimension and finiteness of one tensor."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor, got {type(x).__name__}")
    if floating and x.dtype not in _FLOAT_DTYPES:
        raise TypeError(f"`{name}` must be float32 or float64, got dtype {x.dtype}")
    if x.dim() < min_dims:
        raise ValueError(f"`{name}` must have at least {min_dims} dimension(s), got shape {tuple(x.shape)}")
    if last_dim is not None and (x.dim() == 0 or x.shape[-1] != last_dim):
        raise ValueError(f"`{name}` must have shape (..., {last_dim}), got {tuple(x.shape)}")
    if not allow_nonfinite and x.device.type != "meta" and validation_enabled() and x.numel() > 0:
        # One reduction first: a finite sum proves every entry finite (NaN and Inf propagate);
        # only a non-finite sum (or an overflowing one) pays for the elementwise scan.
        if not bool(torch.isfinite(x.detach().sum())) and not bool(torch.isfinite(x).all()):
            bad = "NaN" if bool(torch.isnan(x).any()) else "Inf"
            raise ValueError(f"`{name}` contains {bad} values; expected finite numbers")
    return x


def check_dirs(x, name: str) -> torch.Tensor:
    """A (..., 3) float tensor of directions."""
    return check_tensor(x, name, last_dim=3, min_dims=1)


def check_same(tensors: Sequence[Tuple[str, torch.Tensor]]) -> None:
    """All tensors on one device with one dtype."""
    (n0, t0) = tensors[0]
    for n, t in tensors[1:]:
        if t.device != t0.device:
            raise ValueError(f"`{n}` is on {t.device} but `{n0}` is on {t0.device}; move them to the same device")
        if t.dtype != t0.dtype:
            raise TypeError(f"`{n}` has dtype {t.dtype} but `{n0}` has dtype {t0.dtype}; use the same dtype")


Dim = Union[int, str, None]


def check_shape(x, name: str, *shapes: Sequence[Dim], sizes: Optional[Dict[str, int]] = None) -> Dict[str, int]:
    """Check that ``x`` has one of ``shapes``; the one shape check of the package (one message format).

    Each shape is a sequence of dimensions: an ``int`` (exactly that size), a ``str`` (a named size:
    equal wherever the name recurs, and to ``sizes[name]`` when ``sizes`` has it), ``None`` (any
    size), or ``"*"`` as the first entry (any number of leading dimensions). The first shape that fits
    wins; its named sizes are returned merged into ``sizes`` (a new dict), so that later checks of
    other arguments can be bound to them.

    Raises ``TypeError`` when ``x`` has no shape, and ``ValueError`` in the form
    ``` `lights` must have shape (L, 3), got (5, 2)``` (with ``where L = 5`` when a bound size
    decided it).

    Example:
        >>> import torch
        >>> from torch_hsh._checks import check_shape
        >>> check_shape(torch.zeros(4, 3), "lights", ("L", 3))
        {'L': 4}
        >>> check_shape(torch.zeros(4), "intensities", ("L",), ("L", "C"), sizes={"L": 4})
        {'L': 4}
    """
    shape = getattr(x, "shape", None)
    if shape is None:
        raise TypeError(f"`{name}` must be a tensor, got {type(x).__name__}")
    # sizes as ints; a symbolic size (torch.compile / torch.export) stays symbolic: int() would specialise it
    shape = tuple(s if isinstance(s, torch.SymInt) else int(s) for s in shape)
    known = dict(sizes or {})
    for want in shapes:
        bound = _match_shape(shape, tuple(want), known)
        if bound is not None:
            return bound
    used = sorted({d for want in shapes for d in want if isinstance(d, str) and d != "*" and d in known})
    where = f" where {', '.join(f'{d} = {known[d]}' for d in used)}" if used else ""
    alts = " or ".join(_shape_str(w) for w in shapes)
    raise ValueError(f"`{name}` must have shape {alts}{where}, got {shape}")


def _match_shape(shape: Tuple[int, ...], want: Tuple[Dim, ...], known: Dict[str, int]) -> Optional[Dict[str, int]]:
    """The named sizes of ``shape`` against one pattern (see :func:`check_shape`), or None if it does not fit."""
    if want[:1] == ("*",):
        want = want[1:]
        if len(shape) < len(want):
            return None
        shape = shape[len(shape) - len(want):]
    elif len(shape) != len(want):
        return None
    bound = dict(known)
    for s, d in zip(shape, want):
        if isinstance(d, str):
            if bound.setdefault(d, s) != s:
                return None
        elif d is not None and s != d:
            return None
    return bound


def _shape_str(want: Sequence[Dim]) -> str:
    parts = ["..." if d == "*" else ("_" if d is None else str(d)) for d in want]
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def broadcast_shapes(named: Sequence[Tuple[str, torch.Size]]) -> torch.Size:
    """Broadcast leading shapes with an error that names the arguments."""
    try:
        return torch.broadcast_shapes(*[s for _, s in named])
    except RuntimeError:
        desc = ", ".join(f"`{n}` {tuple(s)}" for n, s in named)
        raise ValueError(f"leading shapes do not broadcast: {desc}") from None


def warn_user(message: str, category: type = UserWarning) -> None:
    """``warnings.warn`` attributed to the first caller outside this package (the user's line), so that the
    warning names the user's call, and the default filter shows it once per call site however deep in the
    library it was raised and however many library functions raise it for one call."""
    import os
    import sys
    import warnings

    from types import FrameType

    pkg = os.path.dirname(os.path.abspath(__file__)) + os.sep
    level = 2
    frame: Optional[FrameType] = sys._getframe(1)
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(pkg):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)


#: Largest decoded size (bytes) a file reader allocates, whatever the file's header claims.
MAX_DECODED_BYTES = 1 << 34
#: Largest ratio of decoded bytes to file bytes accepted from a header (deflate reaches 1032; LZW and
#: run-length coding of constant images a few thousand).
MAX_EXPANSION = 4096


def check_decoded_size(path, nbytes: int, what: str) -> None:
    """Refuse, before any allocation, a header that claims ``nbytes`` decoded bytes of ``path``.

    ``ValueError`` naming the file if the claim is negative, above :data:`MAX_DECODED_BYTES`, or above
    1 MiB plus :data:`MAX_EXPANSION` times the file's size (a header no compression can back).

    Example:
        >>> check_decoded_size(__file__, 1000, "test")
    """
    import os

    size = os.path.getsize(path)
    if nbytes < 0 or nbytes > MAX_DECODED_BYTES or nbytes > (1 << 20) + MAX_EXPANSION * size:
        raise ValueError(f"{path}: the {what} header claims {nbytes} decoded bytes, more than a {size}-byte "
                         f"file can hold (limit {MAX_DECODED_BYTES} bytes, {MAX_EXPANSION}x the file size); "
                         "the file is corrupt")
