"""The result folder of ``torch-hsh ps``: ownership, staging and the swap commit, ``manifest.json``.

A folder is *ours* only if it holds our ``manifest.json`` and nothing else than the files the
manifest lists, unchanged since the run (same size and SHA-256). A new result is written into a
temporary folder beside the target (:class:`_Staging`), the manifest last, and swapped into place
with Ctrl-C and SIGTERM held off for the two renames (:mod:`torch_hsh._atomic`), so that the target holds either the previous complete
result or the new one, never a mix. See the module docstring of :mod:`torch_hsh.cli` for the
contract as the user sees it.

Also here: the strict-JSON writer of the result files (``null`` for NaN / Inf).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from .._atomic import new_temp, remove, replace_folder, signals_held, sweep

__all__ = ["MANIFEST", "MANIFEST_FORMAT", "MANIFEST_VERSION", "is_result_folder"]

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "torch-hsh-ps-result"
MANIFEST_VERSION = 1


# --------------------------------------------------------------------------- #
# output folder: ownership, staging, swap commit
# --------------------------------------------------------------------------- #
def _read_manifest(folder: Path) -> Optional[dict]:
    try:
        meta = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # RecursionError: JSON nested too deeply
        return None
    if not isinstance(meta, dict) or meta.get("format") != MANIFEST_FORMAT or not isinstance(meta.get("files"), dict):
        return None
    return meta


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _foreign_entries(folder: Path, meta: dict) -> List[str]:
    """Entries of ``folder`` that are not ours as written: not listed in the manifest, not a plain file,
    or changed since (size or SHA-256 differs from the manifest). A listed file that is gone is no loss."""
    foreign = []
    for p in sorted(folder.iterdir(), key=lambda q: q.name):
        if p.name == MANIFEST:
            continue
        entry = meta["files"].get(p.name)
        if not isinstance(entry, dict) or p.is_symlink() or not p.is_file():
            foreign.append(p.name)
            continue
        try:
            same = p.stat().st_size == entry.get("bytes") and _sha256(p) == entry.get("sha256")
        except OSError:
            same = False
        if not same:
            foreign.append(f"{p.name} (changed since the run)")
    return foreign


def is_result_folder(folder) -> bool:
    """True if ``folder`` holds our ``manifest.json`` and nothing else than the files it lists, unchanged
    (same size and SHA-256 as recorded): a file edited after the run makes the folder the user's."""
    folder = Path(folder)
    meta = _read_manifest(folder) if folder.is_dir() else None
    if meta is None:
        return False
    return not _foreign_entries(folder, meta)


def _check_out(ap: argparse.ArgumentParser, out: Path, overwrite: bool, option: str = "--out") -> Path:
    """Static checks of the output folder (nothing is created): exit 2 on a bad ``--out``."""
    out = Path(os.path.abspath(out))
    sweep(out)  # what a killed run left (its old result put back if it was killed in the swap)
    cwd = Path(os.getcwd())
    if out == cwd or out in cwd.parents or out == Path.home() or out.parent == out:
        # never replaced as a whole, not even with --overwrite
        ap.error(f"argument {option}: {out} is the current folder, one of its parents, the home folder or the "
                 "root; give a folder of its own for the result")
    if out.exists() and not out.is_dir():
        ap.error(f"argument {option}: {out} exists and is not a folder")
    if out.is_dir():
        entries = sorted(p.name for p in out.iterdir())
        meta = _read_manifest(out) if entries else None
        foreign = entries if meta is None else _foreign_entries(out, meta)
        if foreign and not overwrite:
            shown = ", ".join(foreign[:5]) + (" ..." if len(foreign) > 5 else "")
            ap.error(
                f"argument {option}: {out} holds files that are not a torch-hsh result ({shown}); "
                "choose another folder or pass --overwrite to replace the whole folder"
            )
    anc = out.parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        ap.error(f"argument {option}: cannot create {out}: {anc} is not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        ap.error(f"argument {option}: cannot create {out}: {anc} is not writable")
    # os.access says yes to root everywhere (e.g. /proc): try it, with an empty folder removed at once
    try:
        with signals_held():
            os.rmdir(tempfile.mkdtemp(prefix=".torch-hsh-probe.", dir=anc))
    except OSError as err:
        ap.error(f"argument {option}: cannot create {out}: {anc} does not accept new folders ({err.strerror})")
    return out


class _Staging:
    """A temporary folder beside ``target``; :meth:`commit` swaps it into place.

    Leaving the ``with`` block without a commit (error, Ctrl-C) removes the
    temporary folder and leaves ``target`` as it was.
    """

    def __init__(self, target: Path):
        self.target = target
        self.path: Optional[Path] = None
        self.files: List[str] = []
        self.created: List[Path] = []

    def __enter__(self) -> "_Staging":
        # the parent folders this run creates: removed again (if still empty) when it does not commit
        self.created = []
        anc = self.target.parent
        while not anc.exists():
            self.created.append(anc)
            anc = anc.parent
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
            with signals_held():
                self.path = new_temp(self.target, folder=True)
        except BaseException:
            self._remove_created()
            raise
        return self

    def _remove_created(self) -> None:
        for d in self.created:  # deepest first; a folder something else has written into stays
            try:
                d.rmdir()
            except OSError:
                break

    def __exit__(self, *exc) -> None:
        if self.path is not None and self.path.exists():
            with signals_held():
                remove(self.path)
                self._remove_created()

    @property
    def folder(self) -> Path:
        """The staging folder (only inside the ``with`` block, before the commit)."""
        if self.path is None:
            raise RuntimeError("the staging folder is not open")
        return self.path

    def file(self, name: str) -> Path:
        self.files.append(name)
        return self.folder / name

    def write_manifest(self, meta: Dict[str, Any]) -> None:
        files = {}
        for name in self.files:
            p = self.folder / name
            files[name] = {"bytes": p.stat().st_size, "sha256": _sha256(p)}
        manifest = dict(meta, format=MANIFEST_FORMAT, format_version=MANIFEST_VERSION, files=files)
        tmp = self.folder / (MANIFEST + ".tmp")
        tmp.write_text(json.dumps(manifest, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, self.folder / MANIFEST)

    def commit(self) -> None:
        """Old result aside, new one in place, the old one removed (:func:`torch_hsh._atomic.replace_folder`)."""
        with signals_held():
            replace_folder(self.folder, self.target)
            self.path = None


def _jsonable(x):
    """Plain JSON values: NaN/Inf -> None, tensors/arrays -> lists, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, torch.Tensor):
        return _jsonable(x.detach().cpu().tolist())
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, (bool, int, str)):
        return x
    return str(x)


def _dump_json(path: Path, obj) -> None:
    path.write_text(json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n", encoding="utf-8")
