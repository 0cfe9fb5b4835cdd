"""Fused CPU kernels, compiled from plain C at first use and called through ctypes.

The kernels in ``kernels.c`` (bodies in ``kernels_impl.h``) evaluate the HSH and the isotropic
Helmholtz basis (forward and backward) row by row, in blocks of 64 rows that stay in the L1 cache,
the pair products of the anisotropic basis, and the direction map of the sphericart HSH path; at
P = 1-3 (:data:`ISO_SMALL_ORDERS`) the isotropic basis runs on straight-line kernels that
``tools/generate_iso_kernels.py`` writes into ``kernels_iso_small.h`` from the same tables (committed;
a test checks it is current). They
need no Python or torch headers: the first call compiles them with the system C compiler (``$CC``,
else ``cc``; a few seconds) into ``$TORCH_HSH_CACHE`` (default ``~/.cache/torch_hsh``), keyed by a
hash of the source, the compiler and the machine, and later calls load the cached library.

Threads: the rows are split into block-aligned ranges that ``torch.get_num_threads()`` threads take
in turn; calls of fewer than 4,096 rows run on the caller's thread. The library is compiled with
OpenMP (``-fopenmp``), and the loader binds it to the OpenMP runtime that torch has already loaded, so
the ranges run on torch's own intra-op threads. A separate thread pool would compete with those
threads, which keep spinning for a while after each torch operator: on 2 cores that made the fused
forward+backward 1.4-1.9x slower. Where that is not possible (a compiler without OpenMP, a torch
without the OpenMP backend, two OpenMP runtimes in the process, or a child made by ``fork()``,
where GNU libgomp's team is gone), or where ``TORCH_HSH_THREADS=pool`` is set, a Python thread pool
runs the ranges instead (ctypes releases the GIL). The values do not depend on the split.

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
_SOURCES = (_SRC, Path(__file__).with_name("kernels_impl.h"), Path(__file__).with_name("kernels_iso_small.h"))
_BLOCK = 64  # rows per block in kernels.c (BS)
#: Orders of the isotropic basis with a generated straight-line kernel (kernels_iso_small.h).
ISO_SMALL_ORDERS = (1, 2, 3)
_MIN_ROWS_PER_THREAD = 2048
_CHUNKS_PER_THREAD = 4  # row ranges per thread (taken dynamically, see _run_chunks)

_state: Dict[str, object] = {"lib": None, "tried": False, "error": None, "path": None}
_lock = threading.Lock()
_pool: Optional[ThreadPoolExecutor] = None
_PAR: Dict[str, Callable[..., int]] = {}  # row kernel's name -> its OpenMP driver (PAR in kernels.c)


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
    """The cached library, compiled first where needed: with OpenMP, else (no OpenMP in this compiler)
    without it."""
    src = b"".join(p.read_bytes() for p in _SOURCES)
    try:
        version = subprocess.run(cc + ["--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise RuntimeError(f"no C compiler ({' '.join(cc)}): {exc}") from None
    flags = ["-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-std=gnu99", "-shared", "-fPIC"]
    omp = _library_path(flags + ["-fopenmp"], src, version)
    no_omp = omp.with_suffix(".no-openmp")  # marker: this compiler failed with -fopenmp (do not retry)
    if not no_omp.exists():
        try:
            return _compile(cc, flags + ["-fopenmp"], omp)
        except RuntimeError as exc:
            try:
                path = _compile(cc, flags, _library_path(flags, src, version))
            except RuntimeError:
                raise exc from None
            no_omp.write_text(str(exc))
            return path
    return _compile(cc, flags, _library_path(flags, src, version))


def _library_path(flags: List[str], src: bytes, version: str) -> Path:
    """Cache path of the library built from ``src`` with ``flags`` by this compiler, on this machine."""
    key = hashlib.sha256(src + version.encode() + " ".join(flags).encode() + platform.machine().encode()
                         + _cpu_tag().encode()).hexdigest()[:16]
    return _cache_dir() / f"torch_hsh_kernels_{key}.so"


def _compile(cc: List[str], flags: List[str], path: Path) -> Path:
    """``path``, compiled first where it is not in the cache."""
    if path.exists():
        return path
    out_dir = path.parent
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
            "iso_small_fwd": [_I64, _I64, _INT, _P, _P, real, real, _P],
            "iso_small_bwd": [_I64, _I64, _INT, _P, _P, real, real, _P, _I64, _I64, _P, _P],
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
            par = getattr(lib, f"{name}_par_{suf}")  # (n, step, nt) + the row kernel's arguments after r0, r1
            par.argtypes = [_I64, _I64, _INT] + argtypes[2:]  # type: ignore[index]
            par.restype = ctypes.c_int
            _PAR[fn.__name__] = par
    lib.torch_hsh_openmp.restype = ctypes.c_int


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
                _state["threads"] = _threading(lib)
            except Exception as exc:  # no compiler, failed build, unloadable library
                _state["error"] = f"{type(exc).__name__}: {exc}"
        _state["tried"] = True
    return _state["lib"]  # type: ignore[return-value]


def _constant(fn):
    """``fn`` called, not traced, by torch.compile (its result taken as a constant of the graph)."""
    mark = getattr(getattr(torch, "compiler", None), "assume_constant_result", None)
    return mark(fn) if mark is not None else fn


@_constant
def available() -> bool:
    """Whether the kernel library is in use (built and loaded on the first call, see :func:`library`); the
    call that torch.compile can take, where :func:`library` takes a lock."""
    return library() is not None


def _omp_symbol(lib: ctypes.CDLL) -> Optional[int]:
    """Address of ``omp_get_max_threads`` as ``lib`` and its dependencies resolve it (None: none)."""
    try:
        return ctypes.cast(lib.omp_get_max_threads, ctypes.c_void_p).value
    except AttributeError:
        return None


def _torch_openmp() -> Optional[int]:
    """Address of the ``omp_get_max_threads`` that torch's CPU library is bound to (None: unknown)."""
    if "parallel backend: OpenMP" not in torch.__config__.parallel_info():
        return None
    lib_dir = Path(torch.__file__).parent / "lib"
    for name in ("libtorch_cpu.so", "libtorch_cpu.dylib"):
        if (lib_dir / name).exists():
            try:  # already loaded by torch: this returns its handle, the search starts at its dependencies
                return _omp_symbol(ctypes.CDLL(str(lib_dir / name), mode=getattr(os, "RTLD_NOLOAD", 0)))
            except OSError:
                return None
    return None


def _threading(lib: ctypes.CDLL) -> str:
    """``"openmp"`` where the kernels run on torch's own OpenMP threads, else ``"pool (why)"``."""
    if os.environ.get("TORCH_HSH_THREADS", "").strip().lower() == "pool":
        return "pool (TORCH_HSH_THREADS=pool)"
    if not lib.torch_hsh_openmp():
        return "pool (compiled without OpenMP)"
    ours, torchs = _omp_symbol(lib), _torch_openmp()
    if torchs is None:
        return "pool (torch does not run on an OpenMP runtime that can be found)"
    if ours != torchs:
        return "pool (the kernels were bound to another OpenMP runtime than torch's)"
    return "openmp"


def _forked_child() -> None:
    """After fork(): the OpenMP runtime of the parent has no threads here, and GNU libgomp does not
    recover from that (a parallel region waits for them for ever, as torch's own operators do); the
    kernels of the child run on the thread pool instead."""
    _state["forked"] = True


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forked_child)


def native_status() -> Dict[str, Optional[str]]:
    """``{"available": "yes"/"no", "path": library path, "error": why not, "threads": how the rows are
    split over threads}`` (builds on first call). ``threads`` is ``"openmp"`` where the kernels run on
    the OpenMP threads that torch's operators use, else ``"pool (why)"``: a Python thread pool whose
    threads each run a range of rows."""
    lib = library()
    threads = _state.get("threads") if lib is not None else None
    if threads == "openmp" and _state.get("forked"):
        threads = "pool (a forked child)"
    return {"available": "yes" if lib is not None else "no", "path": _state["path"],  # type: ignore[dict-item]
            "error": _state["error"], "threads": threads}  # type: ignore[dict-item]


def ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


def parallel_rows(fn: Callable[..., int], n: int, *args) -> bool:
    """Call ``fn(r0, r1, *args)`` over row ranges that split ``[0, n)`` across torch's threads.

    A kernel of the library runs on the OpenMP team that torch's operators use (its ``_par`` driver,
    see :func:`native_status`); any other ``fn``, or any kernel where that is not possible (no OpenMP,
    a forked child), runs on a Python thread pool, one range per call.

    Returns:
        True where a kernel saw a non-finite input (return code 2 of the forward kernels that
        normalise directions: the caller then runs the full input check, which names the argument).

    Raises:
        MemoryError: where a kernel could not allocate its scratch tables (return code 1).
    """
    nt = min(torch.get_num_threads(), max(1, n // _MIN_ROWS_PER_THREAD))
    par = _PAR.get(getattr(fn, "__name__", "")) if _state.get("threads") == "openmp" else None
    if nt <= 1:
        codes = [fn(0, n, *args)]
    elif par is not None and not _state.get("forked"):
        codes = [par(n, _step(n, nt), nt, *args)]
    else:
        codes = _run_chunks(fn, n, nt, args)
    code = 0
    for c in codes:
        code |= c
    if code & 1:
        raise MemoryError(f"{fn.__name__}: could not allocate the kernel's scratch tables")
    return bool(code & 2)


def _step(n: int, nt: int) -> int:
    """Rows per range: about ``_CHUNKS_PER_THREAD`` ranges per thread, a multiple of the block size (so that
    the blocks, and the values, do not depend on the split), taken in turn: a thread slowed down by another
    process takes fewer ranges instead of holding the others up."""
    step = max(_MIN_ROWS_PER_THREAD, -(-n // (nt * _CHUNKS_PER_THREAD)))
    return -(-step // _BLOCK) * _BLOCK


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
    step = _step(n, nt)
    ranges = iter([(r0, min(n, r0 + step)) for r0 in range(0, n, step)])

    def take() -> List[int]:  # next() of a list iterator is atomic under the GIL
        return [fn(r0, r1, *args) for r0, r1 in ranges]

    futs = [_pool.submit(take) for _ in range(nt - 1)]
    codes = take()
    for f in futs:
        codes += f.result()
    return codes
