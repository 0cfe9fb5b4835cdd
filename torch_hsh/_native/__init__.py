"""Fused CPU kernels, compiled from plain C at first use and called through ctypes.

The kernels in ``kernels.c`` (bodies in ``kernels_impl.h``) evaluate the HSH and the isotropic
Helmholtz basis (forward and backward) row by row, in blocks of 64 rows that stay in the L1 cache,
the pair products of the anisotropic basis, and the direction map of the sphericart HSH path. They
need no Python or torch headers: the first call compiles them with the system C compiler (``$CC``,
else ``cc``; a few seconds) into ``$TORCH_HSH_CACHE`` (default ``~/.cache/torch_hsh``), keyed by a
hash of the source, the compiler and the machine, and later calls load the cached library. The rows
are split into block-aligned ranges that ``torch.get_num_threads()`` threads take in turn (ctypes
releases the GIL); calls of fewer than 4,096 rows run on the caller's thread.

Where no compiler is found, the compilation fails, or ``TORCH_HSH_NATIVE=0`` is set, the
pure-torch kernels of :mod:`torch_hsh.kernel` run instead (same values to rounding).
:func:`native_status` says which is in use and why.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shlex
import subprocess
import sysconfig
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Dict, List, Optional

import torch

_SRC = Path(__file__).with_name("kernels.c")
_SOURCES = (_SRC, Path(__file__).with_name("kernels_impl.h"))
_BLOCK = 64  # rows per block in kernels.c (BS)
_MIN_ROWS_PER_THREAD = 2048
_CHUNKS_PER_THREAD = 4  # row ranges per thread (taken dynamically, see _run_chunks)

_state: Dict[str, object] = {"lib": None, "tried": False, "error": None, "path": None}
_lock = threading.Lock()
_pool: Optional[ThreadPoolExecutor] = None


def _compiler() -> List[str]:
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    return shlex.split(cc)[:1] or ["cc"]


def _cache_dir() -> Path:
    root = os.environ.get("TORCH_HSH_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "torch_hsh"


def _cpu_tag() -> str:
    """CPU model and flags (a library built with -march=native is only valid there)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor()
    keep = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags", "Features"))]
    return "\n".join(sorted(set(keep)))


def _build(cc: List[str]) -> Path:
    src = b"".join(p.read_bytes() for p in _SOURCES)
    try:
        version = subprocess.run(cc + ["--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise RuntimeError(f"no C compiler ({' '.join(cc)}): {exc}") from None
    flags = ["-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-std=gnu99", "-shared", "-fPIC"]
    key = hashlib.sha256(src + version.encode() + " ".join(flags).encode() + platform.machine().encode()
                         + _cpu_tag().encode()).hexdigest()[:16]
    out_dir = _cache_dir()
    path = out_dir / f"torch_hsh_kernels_{key}.so"
    if path.exists():
        return path
    out_dir.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.stem, suffix=".so.tmp", dir=out_dir)
    os.close(fd)
    try:
        res = subprocess.run(cc + flags + ["-o", tmp, str(_SRC), "-lm"], capture_output=True, text=True, timeout=300)
        if res.returncode != 0:
            raise RuntimeError(f"compiling {_SRC.name} failed:\n{res.stderr.strip()[-2000:]}")
        os.replace(tmp, path)  # atomic: concurrent processes see a whole file or none
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_INT = ctypes.c_int


def _declare(lib: ctypes.CDLL) -> None:
    core = [_INT, _P, _P, _P, _P, _INT, _INT, _P, _P, _P, _P]  # CORE_ARGS of kernels_impl.h
    hsh = [_INT, _P, _P, _P, _P, _INT, _P, _P, _P]  # HSH_ARGS
    for suf, real in (("f32", ctypes.c_float), ("f64", ctypes.c_double)):
        sigs = {
            "iso_core_fwd": [_I64, _I64] + [_P] * 6 + core + [_P],
            "iso_core_bwd": [_I64, _I64] + [_P] * 6 + core + [_P, _I64, _I64] + [_P] * 5,
            "iso_dirs_fwd": [_I64, _I64, _P, _P, real, real] + core + [_P],
            "iso_dirs_bwd": [_I64, _I64, _P, _P, real, real] + core + [_P, _I64, _I64, _P, _P],
            "hsh_fwd": [_I64, _I64, _INT, _P, real] + hsh + [_P],
            "hsh_bwd": [_I64, _I64, _INT, _P, real, real] + hsh + [_P, _I64, _I64, _P],
            "hsh_remap_fwd": [_I64, _I64, _P, real, real, _P, _P],
            "hsh_remap_bwd": [_I64, _I64, _P, real, real, _P, _P],
            "pair_fwd": [_I64, _I64, _P, _P, _INT, _INT, _P, _P, _P, _P],
            "pair_bwd": [_I64, _I64, _P, _P, _INT, _INT, _P, _P, _P, _P, _I64, _I64, _P, _P],
        }
        for name, argtypes in sigs.items():
            fn = getattr(lib, f"{name}_{suf}")
            fn.argtypes = argtypes
            fn.restype = ctypes.c_int  # 0, or 1 where a scratch buffer could not be allocated


def library() -> Optional[ctypes.CDLL]:
    """The compiled kernel library, or None where it is switched off or cannot be built."""
    if _state["tried"]:
        return _state["lib"]  # type: ignore[return-value]
    with _lock:
        if _state["tried"]:
            return _state["lib"]  # type: ignore[return-value]
        if os.environ.get("TORCH_HSH_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
            _state["error"] = "switched off by TORCH_HSH_NATIVE=0"
        else:
            try:
                path = _build(_compiler())
                lib = ctypes.CDLL(str(path))
                _declare(lib)
                _state["lib"], _state["path"] = lib, str(path)
            except Exception as exc:  # no compiler, failed build, unloadable library
                _state["error"] = f"{type(exc).__name__}: {exc}"
        _state["tried"] = True
    return _state["lib"]  # type: ignore[return-value]


def native_status() -> Dict[str, Optional[str]]:
    """``{"available": "yes"/"no", "path": library path, "error": why not}`` (builds on first call)."""
    lib = library()
    return {"available": "yes" if lib is not None else "no", "path": _state["path"],  # type: ignore[dict-item]
            "error": _state["error"]}  # type: ignore[dict-item]


def ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


def parallel_rows(fn: Callable[..., int], n: int, *args) -> bool:
    """Call ``fn(r0, r1, *args)`` over row ranges that split ``[0, n)`` across torch's threads.

    Returns:
        True where a kernel saw a non-finite input (return code 2 of the forward kernels that
        normalise directions: the caller then runs the full input check, which names the argument).

    Raises:
        MemoryError: where a kernel could not allocate its scratch tables (return code 1).
    """
    nt = min(torch.get_num_threads(), max(1, n // _MIN_ROWS_PER_THREAD))
    if nt <= 1:
        codes = [fn(0, n, *args)]
    else:
        codes = _run_chunks(fn, n, nt, args)
    if 1 in codes:
        raise MemoryError(f"{fn.__name__}: could not allocate the kernel's scratch tables")
    return 2 in codes


def _run_chunks(fn: Callable[..., int], n: int, nt: int, args: tuple) -> List[int]:
    """``fn`` over about ``_CHUNKS_PER_THREAD * nt`` row ranges (multiples of the block size, so that
    the blocks, and the values, do not depend on the split), taken in turn by the caller and ``nt - 1``
    pool threads: a thread slowed down by another process (or by torch's OpenMP workers, which spin for
    a while after a torch operation) takes fewer ranges instead of holding the others up."""
    global _pool
    # a pool inherited through fork() has no threads in the child: make a new one there
    if _pool is None or _pool._max_workers < nt or _state.get("pool_pid") != os.getpid():
        _pool = ThreadPoolExecutor(max_workers=max(nt, os.cpu_count() or 1), thread_name_prefix="torch_hsh")
        _state["pool_pid"] = os.getpid()
    step = max(_MIN_ROWS_PER_THREAD, -(-n // (nt * _CHUNKS_PER_THREAD)))
    step = -(-step // _BLOCK) * _BLOCK
    ranges = iter([(r0, min(n, r0 + step)) for r0 in range(0, n, step)])

    def take() -> List[int]:  # next() of a list iterator is atomic under the GIL
        return [fn(r0, r1, *args) for r0, r1 in ranges]

    futs = [_pool.submit(take) for _ in range(nt - 1)]
    codes = take()
    for f in futs:
        codes += f.result()
    return codes
