"""Atomic outputs: every temporary beside a target is made, committed and swept here.

A writer of ``DIR/NAME`` (a file or a folder) writes into a temporary ``DIR/.NAME.PID.HEX.partial`` and moves it
into place at the end: :func:`atomic_file` (``os.replace``) or :func:`replace_folder` (the old folder renamed to
``DIR/.NAME.PID.HEX.old``, the new one renamed in, the old one removed). ``PID`` is the writer's process id, so the
temporaries of a process killed with SIGKILL are known as such: :func:`sweep`, run by the next writer of the same
target, removes a ``.partial`` whose process is gone and puts a dead process's ``.old`` folder back in place if the
target is missing (killed between the two renames), so the old result is never lost. Nothing else is touched: only
names of exactly this form, and only those of processes that no longer exist.

SIGINT / SIGTERM are held off while a temporary is created, renamed or removed, so that an interrupt raised as an
exception (the CLI turns SIGTERM into one) never falls between the creation of a temporary and its clean-up.
"""
from __future__ import annotations

import os
import re
import secrets
import shutil
import signal
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional, Union

__all__ = ["atomic_file", "replace_folder", "staged_folder", "sweep", "new_temp", "remove", "signals_held"]

PathLike = Union[str, "os.PathLike[str]"]


@contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT / SIGTERM (delivered when the block ends) where the platform allows.

    Example:
        >>> with signals_held():
        ...     pass  # a Ctrl-C here is raised after the block
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _pattern(name: str) -> "re.Pattern[str]":
    return re.compile(r"\." + re.escape(name) + r"\.(\d+)\.[0-9a-f]{8}\.(partial|old)")


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # another user's process (or no way to tell): keep its files
    return True


def remove(path: PathLike) -> None:
    """Remove a temporary file or folder (if it exists), with SIGINT / SIGTERM held off.

    Example:
        >>> remove("results/.cat.123.0123abcd.partial")  # doctest: +SKIP
    """
    p = Path(path)
    with signals_held():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        elif os.path.lexists(p):
            try:
                p.unlink()
            except OSError:
                pass


def sweep(target: PathLike) -> None:
    """Clear what killed writers of ``target`` left: their ``.partial`` removed, their ``.old`` folder put back if
    ``target`` is missing, else removed. Temporaries of live processes and every other file stay.

    Example:
        >>> sweep("results/cat")  # doctest: +SKIP
    """
    target = Path(os.path.abspath(target))
    try:
        names = sorted(os.listdir(target.parent))
    except OSError:
        return
    pattern = _pattern(target.name)
    stale = [(n, m.group(2)) for n in names for m in [pattern.fullmatch(n)] if m and not _alive(int(m.group(1)))]
    for name, kind in sorted(stale, key=lambda s: s[1] == "partial"):  # the .old ones first
        p = target.parent / name
        if kind == "old" and not os.path.lexists(target):
            with signals_held():
                os.rename(p, target)
        else:
            remove(p)


def new_temp(target: PathLike, folder: bool = False) -> Path:
    """Sweep ``target``'s stale temporaries, then create an empty temporary file (or folder) beside it, named
    ``.NAME.PID.HEX.partial``, with the mode ``open()`` / ``mkdir()`` give under the umask. Call it with
    :func:`signals_held` and assign the result inside that block, so that no interrupt falls in between.

    Example:
        >>> with signals_held():  # doctest: +SKIP
        ...     tmp = new_temp("results/cat", folder=True)
    """
    target = Path(os.path.abspath(target))
    sweep(target)
    path = target.parent / f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.partial"
    if folder:
        os.mkdir(path, 0o777)
    else:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    return path


@contextmanager
def atomic_file(target: PathLike, mode: Optional[int] = None) -> Iterator[Path]:
    """Yield a temporary path beside ``target`` to write; it replaces ``target`` (``os.replace``) when the block ends
    without an error, and is removed otherwise. ``mode``: permission bits to give it (default: the umask's).

    Example:
        >>> with atomic_file(tmp / "a.txt") as tmp_path:  # doctest: +SKIP
        ...     tmp_path.write_text("hello")
    """
    tmp: Optional[Path] = None
    try:
        with signals_held():
            tmp = new_temp(target)
        yield tmp
        if mode is not None:
            os.chmod(tmp, mode)
        with signals_held():
            os.replace(tmp, target)
            tmp = None
    finally:
        if tmp is not None:
            remove(tmp)


def replace_folder(staged: PathLike, target: PathLike) -> None:
    """Move the complete folder ``staged`` to ``target``: an existing ``target`` is renamed to ``.NAME.PID.HEX.old``
    first and removed after (a kill between the two renames is undone by the next :func:`sweep`).

    Example:
        >>> replace_folder("results/.cat.123.0123abcd.partial", "results/cat")  # doctest: +SKIP
    """
    target = Path(os.path.abspath(target))
    old = None
    with signals_held():
        if os.path.lexists(target):
            old = target.parent / f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.old"
            os.rename(target, old)
        try:
            os.rename(staged, target)
        except BaseException:
            if old is not None:
                os.rename(old, target)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


@contextmanager
def staged_folder(target: PathLike) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``target``; it replaces ``target`` (:func:`replace_folder`) when the
    block ends without an error, and is removed otherwise.

    Example:
        >>> with staged_folder(tmp / "out") as d:  # doctest: +SKIP
        ...     (d / "info.json").write_text("{}")
    """
    tmp: Optional[Path] = None
    try:
        with signals_held():
            tmp = new_temp(target, folder=True)
        yield tmp
        with signals_held():
            replace_folder(tmp, target)
            tmp = None
    finally:
        if tmp is not None:
            remove(tmp)
