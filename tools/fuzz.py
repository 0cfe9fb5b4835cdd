"""Fuzzing of every file reader of torch_hsh (``make fuzz``; a short run is ``tests/test_fuzz.py``).

Each *target* is one reader fed one kind of file. Its valid seed files are written by the library's own
writers (``save_rti``, ``save_diligent``, ``write_merl``, ``write_exr``, ``HSHResult.write``, ...) into a
temporary folder at start-up; nothing is committed. Each input is a seed's file with 1 to 4 mutations
(bit flips, truncation, insertion, deletion, chunk duplication, numeric fields overwritten with NaN / inf /
huge / negative values, header dimensions made huge with the checksums fixed, text tokens and lines
replaced, removed, repeated, JSON nested 100,000 deep; inside an ``.npz`` one member mutated or removed,
the metadata's JSON as text, with valid checksums), drawn from a seeded RNG: the same ``--seed`` gives the
same inputs. Text mutations go to text targets and to any ``.json`` / ``.txt`` / ``.lp`` seed file.

The reader runs in one worker process (a pool of one), in-process there, under a per-input alarm and an
address-space limit (``--mem-mb`` above what the worker holds after start-up, so an allocation sized by an
unchecked header fails instead of swapping). The parent restarts a worker that dies (a crash: the signal
is counted) or stops answering (a hang). Each input is classified as

* ``ok``: the reader returned;
* ``lib``: it raised ``ValueError`` / ``OSError`` (or a subclass) or an exception class of torch_hsh (the
  CLI's ``InputError``) from a frame inside the imported ``torch_hsh`` package folder, with a message naming
  the mutated file (its name or path);
* ``foreign``: any other exception (raised outside torch_hsh, of another type, or not naming the file);
* ``hang``: no answer within ``--timeout`` seconds;
* ``crash``: the worker died (segfault, abort).

``PLANTED`` holds readers that misbehave on purpose, one per kind (tests/test_fuzz.py checks the classifier
on them); they are not part of a campaign.

Failing inputs (foreign, hang, crash) are written to ``--save`` with the message beside them, and replayed
one at a time (in this process, with the traceback) by::

    python tools/fuzz.py --replay failures/merl-000123-foreign.bin --target merl

Usage::

    make fuzz                                     # every target, FUZZ_INPUTS (8500) each
    python tools/fuzz.py                          # every target, --inputs each (default 6000)
    python tools/fuzz.py --target lp merl -n 500  # some targets
    python tools/fuzz.py --list
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import random
import re
import shutil
import signal
import struct
import sys
import tempfile
import time
import traceback
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("ok", "lib", "foreign", "hang", "crash")


# --------------------------------------------------------------------------- #
# seeds: (folder, mutated file, reader) written by the library's writers
# --------------------------------------------------------------------------- #
@dataclass
class Seed:
    folder: Path
    victim: str  # file name inside folder that is mutated
    call: Callable[[Path, Path], object]  # reader(folder, victim path)


def _lights(n: int):
    import numpy as np

    rng = np.random.default_rng(n)
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.8
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _images(n: int, h: int = 6, w: int = 5):
    import numpy as np

    return np.random.default_rng(h * w + n).uniform(0.05, 0.9, size=(n, h, w, 3))


def _quiet(fn):
    def run(*a, **kw):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return fn(*a, **kw)
    return run


def seeds_rti(base: Path, fmt: str) -> List[Seed]:
    """RTI captures (save_rti); the mutated file is the .lp, one photograph or the mask."""
    import numpy as np
    from PIL import Image

    from torch_hsh.io.diligent import _write_png
    from torch_hsh.rti.io import load_rti, read_lp, save_rti

    def load(folder, victim):
        load_rti(folder)

    def lp_then_load(folder, victim):
        read_lp(victim, check_directions=False)
        load_rti(folder)

    out: List[Seed] = []
    imgs, li = _images(4), _lights(4)
    mask = np.ones((6, 5), dtype=bool)
    mask[0, 0] = False
    if fmt == "lp":
        f = _quiet(save_rti)(base / "lp", imgs, li, mask=mask)
        return [Seed(f, "lights.lp", lp_then_load)]
    if fmt == "mask":
        f = _quiet(save_rti)(base / "mask", imgs, li, mask=mask)
        return [Seed(f, "mask.png", load)]
    if fmt in ("png", "jpg", "tif"):
        f = _quiet(save_rti)(base / f"{fmt}8", imgs, li, fmt=fmt)
        out.append(Seed(f, f"img_001.{fmt}", load))
    # odd depths and channel counts: every image of the capture rewritten in that layout
    codes = (imgs * 65535).astype(np.uint16)
    variants = {
        "png": [("png16", lambda p, c: _write_png(p, c)), ("pnggrey16", lambda p, c: _write_png(p, c[..., 0])),
                ("pngrgba", lambda p, c: _write_png(p, np.concatenate([c >> 8, c[..., :1] >> 8], -1).astype(np.uint8))),
                ("pngpal", lambda p, c: Image.fromarray((c >> 8).astype(np.uint8)).convert("P").save(p))],
        "tif": [("tifgrey16", lambda p, c: Image.fromarray(c[..., 0]).save(p)),
                ("tifrgba", lambda p, c: Image.fromarray(np.concatenate([c >> 8, c[..., :1] >> 8], -1)
                                                         .astype(np.uint8)).save(p))],
        "jpg": [("jpggrey", lambda p, c: Image.fromarray((c[..., 0] >> 8).astype(np.uint8)).save(p, quality=90)),
                ("jpgprog", lambda p, c: Image.fromarray((c >> 8).astype(np.uint8)).save(p, progressive=True))],
    }[fmt]
    for name, write in variants:
        f = _quiet(save_rti)(base / name, imgs, li, fmt=fmt)
        for k in range(4):
            write(f / f"img_{k + 1:03d}.{fmt}", codes[k])
        out.append(Seed(f, f"img_001.{fmt}", load))
    return out


def seeds_diligent(base: Path, which: str) -> List[Seed]:
    """DiLiGenT folders (save_diligent); the mutated file is one text file, the mask, a PNG or Normal_gt.mat."""
    import numpy as np

    from torch_hsh.io.diligent import load_diligent, save_diligent
    from torch_hsh.render import scenes

    def load(folder, victim):
        load_diligent(folder)

    imgs, li = _images(4), _lights(4)
    inten = np.random.default_rng(1).uniform(0.5, 2.0, size=(4, 3))
    mask = np.ones((6, 5), dtype=bool)
    mask[-1, -1] = False
    out: List[Seed] = []
    if which == "normal_gt":
        n, m = scenes.sphere_normals(6)
        n = n.numpy()
        n[~m.numpy()] = (0.0, 0.0, 1.0)
        f = _quiet(save_diligent)(base / which, _images(4, 6, 6), li, intensities=inten, mask=m, normals_gt=n)
        return [Seed(f, "Normal_gt.mat", load)]
    victim = {"lights": "light_directions.txt", "intensities": "light_intensities.txt", "names": "filenames.txt",
              "mask": "mask.png", "png": "001.png"}[which]
    f = _quiet(save_diligent)(base / which, imgs, li, intensities=inten, mask=mask)
    out.append(Seed(f, victim, load))
    if which == "png":
        f = _quiet(save_diligent)(base / "png8", imgs, li, intensities=inten, mask=mask, bit_depth=8)
        out.append(Seed(f, victim, load))
    return out


def seeds_merl(base: Path) -> List[Seed]:
    import numpy as np

    from torch_hsh.io.merl import read_merl, write_merl

    base.mkdir(parents=True, exist_ok=True)
    t = np.random.default_rng(0).uniform(0.0, 1.0, size=(3, 2, 3, 4))
    write_merl(base / "m.binary", t)
    return [Seed(base, "m.binary", lambda folder, victim: read_merl(victim))]


def seeds_exr(base: Path) -> List[Seed]:
    import numpy as np

    from torch_hsh.io import exr

    base.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    exr.write_coefficient_maps_exr(base / "coeff.exr", rng.normal(size=(4, 5, 3, 4)).astype(np.float32))
    exr.write_image_stack_exr(base / "stack.exr", rng.uniform(size=(3, 4, 5, 3)), half=True)
    exr.write_exr(base / "env.exr", {"": rng.uniform(size=(4, 8, 3))})
    exr.write_normal_map_exr(base / "normal.exr", np.tile([0.0, 0.0, 1.0], (4, 5, 1)), np.ones((4, 5), bool))
    return [Seed(base, "coeff.exr", lambda folder, v: exr.read_coefficient_maps_exr(v)),
            Seed(base, "stack.exr", lambda folder, v: exr.read_image_stack_exr(v)),
            Seed(base, "env.exr", lambda folder, v: exr.read_envmap(v)),
            Seed(base, "normal.exr", lambda folder, v: exr.read_exr(v))]


def _small_result(weights: bool):
    import torch

    from torch_hsh.ps import HSHResult

    g = torch.Generator().manual_seed(0)
    S = (3, 4)
    n = torch.nn.functional.normalize(torch.randn(*S, 3, generator=g) + torch.tensor([0, 0, 2.0]), dim=-1)
    return HSHResult(normals=n, coefficients=torch.randn(*S, 3, 20, generator=g), albedo=torch.rand(*S, 3, generator=g),
                     residual=torch.rand(*S, generator=g), weights=torch.rand(*S, 5, generator=g),
                     mask=torch.ones(*S, dtype=torch.bool), order=3,
                     lights=torch.nn.functional.normalize(torch.rand(5, 3, generator=g) + 0.5, dim=-1),
                     runtime_s=0.5, info={"noise": 0.01, "iterations": 3}, confidence=torch.rand(*S, generator=g))


def seeds_result(base: Path, which: str) -> List[Seed]:
    """A saved HSHResult (.npz) read by HSHResult.read and by the CLI from its result folder (manifest.json)."""
    from torch_hsh.cli.result_folder import _read_manifest, _Staging, is_result_folder
    from torch_hsh.ps import HSHResult
    from torch_hsh.rti.cli import _load_result

    base.mkdir(parents=True, exist_ok=True)
    if which == "npz":
        _small_result(False).write(base / "a.npz")
        _small_result(True).write(base / "b.npz", weights=True)
        read = lambda folder, v: HSHResult.read(v)  # noqa: E731
        return [Seed(base, "a.npz", read), Seed(base, "b.npz", read)]
    target = base / "result"
    with _Staging(target) as st:
        _small_result(False).write(st.file("result.npz"))
        (st.file("metrics.json")).write_text('{"mean_angular_error_deg": 1.5}\n')
        st.write_manifest({"tool": "torch-hsh ps", "created_utc": "2000-01-01T00:00:00Z"})
        st.commit()

    def read_folder(folder, victim):
        import argparse

        _read_manifest(folder)
        is_result_folder(folder)
        args = argparse.Namespace(result=str(folder), exposure=None, threads=1)
        _load_result(args, argparse.ArgumentParser(prog="fuzz"))

    return [Seed(target, "manifest.json", read_folder), Seed(target, "result.npz", read_folder)]


#: target -> (seed builder, text format?, default share of the inputs)
TARGETS: Dict[str, Tuple[Callable[[Path], List[Seed]], bool, float]] = {
    "lp": (lambda b: seeds_rti(b, "lp"), True, 1.0),
    "rti_jpg": (lambda b: seeds_rti(b, "jpg"), False, 1.0),
    "rti_png": (lambda b: seeds_rti(b, "png"), False, 1.0),
    "rti_tif": (lambda b: seeds_rti(b, "tif"), False, 1.0),
    "rti_mask": (lambda b: seeds_rti(b, "mask"), False, 0.5),
    "diligent_lights": (lambda b: seeds_diligent(b, "lights"), True, 1.0),
    "diligent_intensities": (lambda b: seeds_diligent(b, "intensities"), True, 1.0),
    "diligent_names": (lambda b: seeds_diligent(b, "names"), True, 1.0),
    "diligent_mask": (lambda b: seeds_diligent(b, "mask"), False, 0.5),
    "diligent_png": (lambda b: seeds_diligent(b, "png"), False, 1.0),
    "normal_gt": (lambda b: seeds_diligent(b, "normal_gt"), False, 0.02),  # a child process per read
    "merl": (seeds_merl, False, 1.0),
    "exr": (seeds_exr, False, 1.0),
    "npz": (lambda b: seeds_result(b, "npz"), False, 1.0),
    "result_folder": (lambda b: seeds_result(b, "folder"), False, 0.5),
}


def _planted(call: Callable[[Path, Path], object]) -> Callable[[Path], List[Seed]]:
    """A target of the classifier's own test: ``call`` fed a one-line file."""
    def build(base: Path) -> List[Seed]:
        base.mkdir(parents=True, exist_ok=True)
        (base / "planted.bin").write_bytes(b"planted\n")
        return [Seed(base, "planted.bin", call)]
    return build


def _hang_unalarmed(folder: Path, victim: Path) -> None:
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})  # as a C loop would: only the parent sees it
    time.sleep(3600)


def _spin(folder: Path, victim: Path) -> None:
    while True:
        pass


def _lib_read(folder: Path, victim: Path) -> None:
    from torch_hsh.io.merl import read_merl

    read_merl(victim)


#: Targets that misbehave on purpose (tests/test_fuzz.py checks that each is classified as its name says);
#: not part of a campaign.
PLANTED: Dict[str, Callable[[Path], List[Seed]]] = {
    "planted_lib": _planted(_lib_read),
    "planted_foreign": _planted(lambda folder, v: __import__("numpy").empty(-1)),
    "planted_hang": _planted(_spin),
    "planted_hang_unalarmed": _planted(_hang_unalarmed),
    "planted_abort": _planted(lambda folder, v: os.abort()),
    "planted_segfault": _planted(lambda folder, v: __import__("ctypes").string_at(0)),
}


def _builder(target: str) -> Callable[[Path], List[Seed]]:
    return PLANTED[target] if target in PLANTED else TARGETS[target][0]


# --------------------------------------------------------------------------- #
# mutations
# --------------------------------------------------------------------------- #
_INTS = [0, 1, -1, 2, 255, 256, 0x7FFF, 0x8000, 0xFFFF, 0x10000, 0x7FFFFFFF, -0x80000000, 0xFFFFFFFF, 1 << 24,
         1000000]
_FLOATS = [float("nan"), float("inf"), float("-inf"), 1e308, -1e308, -1.0, 0.0, 1e-320, 3.4e38, 65504.0]
_TOKENS = ["nan", "NaN", "inf", "-inf", "1e309", "-1e309", "-1", "0", "-0", "1e-320", "99999999999999999999999",
           "0x10", "1_0", "", "x", "#", "\t", "\x00", "\u00e9", "\ufeff", "..", "/", "\\", "C:\\a.png", "/etc/passwd",
           "1,2", "1e400", "-0.0", "+5", "٣", "[" * 100000, '{"a":' * 50000, "[]", "null", '"x"']


def _crc_fix_png(d: bytearray) -> bytearray:
    """Recompute every PNG chunk CRC (so a mutated header reaches the decoder)."""
    i = 8
    while i + 12 <= len(d):
        n = struct.unpack(">I", d[i:i + 4])[0]
        if i + 12 + n > len(d):
            break
        d[i + 8 + n:i + 12 + n] = struct.pack(">I", zlib.crc32(bytes(d[i + 4:i + 8 + n])) & 0xFFFFFFFF)
        i += 12 + n
    return d


def _huge_dims(d: bytearray, rng: random.Random) -> bytearray:
    """Make the image / table dimensions of a known header huge (or zero / negative)."""
    big = rng.choice([0, 1, 0xFFFF, 0x10000, 0x7FFFFFFF, 0xFFFFFFFF, 100000, 46341])
    if d[:8] == b"\x89PNG\r\n\x1a\n" and len(d) >= 24:
        off = rng.choice([16, 20])
        d[off:off + 4] = struct.pack(">I", big)
        return _crc_fix_png(d)
    if d[:2] == b"\xff\xd8":
        k = max(d.find(b"\xff\xc0"), d.find(b"\xff\xc2"))
        if k > 0 and k + 9 <= len(d):
            off = rng.choice([k + 5, k + 7])
            d[off:off + 2] = struct.pack(">H", big & 0xFFFF)
        return d
    k = d.find(b"dataWindow\x00box2i\x00")
    if k >= 0:
        off = k + len(b"dataWindow\x00box2i\x00") + 4 + 4 * rng.randrange(4)
        d[off:off + 4] = struct.pack("<i", rng.choice([-0x80000000, 0x7FFFFFFF, 1 << 20, -1, 100000]))
        return d
    m = re.search(rb"'shape': \(([0-9, ]*)\)", bytes(d))
    if m:
        dims = [x for x in m.group(1).split(b",") if x.strip()]
        if dims:
            dims[rng.randrange(len(dims))] = str(rng.choice([10 ** 12, 2 ** 40, 10 ** 6, 0])).encode()
        new = b"'shape': (" + b", ".join(d_.strip() for d_ in dims) + (b",)" if len(dims) == 1 else b")")
        old = m.group(0)
        pad = len(old) - len(new)
        j = m.end()
        # keep the header length: take the extra characters from the space padding after the dict
        if pad >= 0:
            d[m.start():j] = new + b" " * pad
        else:
            tail = bytes(d[j:j + 200])
            spaces = len(tail) - len(tail.lstrip(b"}, ")) if tail else 0
            if spaces >= -pad:
                d[m.start():j - pad] = new
        return d
    if len(d) >= 12 and d[:2] in (b"II", b"MM"):  # TIFF: overwrite one IFD value
        off = rng.randrange(8, min(len(d), 400) - 4) if len(d) > 12 else 8
        d[off:off + 4] = struct.pack("<I", big)
        return d
    if len(d) >= 12:  # MERL: three int32 bin counts
        off = 4 * rng.randrange(3)
        d[off:off + 4] = struct.pack("<i", rng.choice([0, -1, 0x10000, 0x7FFFFFFF, 1 << 20, 2]))
    return d


def _mutate_bytes(d: bytearray, rng: random.Random) -> bytearray:
    n = len(d)
    op = rng.randrange(10)
    pos = rng.randrange(n) if n else 0
    if n == 0:
        return bytearray(rng.randbytes(rng.randrange(1, 64)))
    if op == 0:  # bit flips
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(n)
            d[i] ^= 1 << rng.randrange(8)
    elif op == 1:  # interesting byte
        d[pos] = rng.choice([0, 0xFF, 0x7F, 0x80, 0x01, 0x20, 0x0A])
    elif op == 2:  # truncate
        del d[rng.randrange(n):]
    elif op == 3:  # insert random bytes
        d[pos:pos] = rng.randbytes(rng.randint(1, 64))
    elif op == 4:  # delete a chunk
        del d[pos:pos + rng.randint(1, 64)]
    elif op == 5:  # duplicate a chunk
        ln = rng.randint(1, min(256, n))
        src = rng.randrange(max(1, n - ln + 1))
        d[pos:pos] = d[src:src + ln]
    elif op == 6:  # integer field
        pos = rng.randrange(min(n, 64)) if rng.random() < 0.4 else pos
        fmt = rng.choice(["<i", ">i", "<I", ">I", "<h", ">H", "<q"])
        v = rng.choice(_INTS)
        try:
            b = struct.pack(fmt, v)
        except struct.error:
            b = struct.pack(fmt[0] + fmt[1].lower(), -1) if fmt[1] in "iIhHq" else b"\xff"
        d[pos:pos + len(b)] = b
    elif op == 7:  # float field
        fmt = rng.choice(["<f", "<d", ">f", ">d", "<e"])
        try:
            b = struct.pack(fmt, rng.choice(_FLOATS))
        except (OverflowError, struct.error):
            b = struct.pack(fmt, float("inf"))
        if rng.random() < 0.5 and n > 32:  # aligned, e.g. a float64 table
            step = struct.calcsize(fmt)
            pos = rng.randrange(n // step) * step
        d[pos:pos + len(b)] = b
    elif op == 8:
        d = _huge_dims(d, rng)
    else:  # splice: a chunk overwritten by random bytes
        ln = rng.randint(1, 32)
        d[pos:pos + ln] = rng.randbytes(ln)
    return d


_NUM = re.compile(rb"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def _mutate_text(d: bytearray, rng: random.Random) -> bytearray:
    lines = bytes(d).split(b"\n")
    op = rng.randrange(9)
    if op == 0:  # a number replaced by a token
        nums = list(_NUM.finditer(bytes(d)))
        if nums:
            m = rng.choice(nums)
            d[m.start():m.end()] = rng.choice(_TOKENS).encode("utf-8")
            return d
    if op == 1 and len(lines) > 1:  # delete a line
        del lines[rng.randrange(len(lines))]
    elif op == 2:  # duplicate a line
        i = rng.randrange(len(lines))
        lines.insert(rng.randrange(len(lines) + 1), lines[i])
    elif op == 3 and len(lines) > 1:  # swap two lines
        i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif op == 4:  # a line of random tokens
        toks = [rng.choice(_TOKENS + ["0.5", "1", "a.png", "img_001.png"]) for _ in range(rng.randint(0, 6))]
        lines.insert(rng.randrange(len(lines) + 1), " ".join(toks).encode("utf-8"))
    elif op == 5:  # a token inserted in a line
        i = rng.randrange(len(lines))
        j = rng.randrange(len(lines[i]) + 1)
        lines[i] = lines[i][:j] + rng.choice(_TOKENS).encode("utf-8") + lines[i][j:]
    elif op == 6:  # line endings / BOM / a very long line
        choice = rng.randrange(4)
        if choice == 0:
            return bytearray(bytes(d).replace(b"\n", b"\r\n"))
        if choice == 1:
            return bytearray(b"\xef\xbb\xbf" + bytes(d))
        if choice == 2:
            lines.insert(rng.randrange(len(lines) + 1), b"1 " * rng.randint(100, 20000))
        else:
            return bytearray(bytes(d).replace(b"\n", b"\r"))
    elif op == 7:  # the count line / first number scaled
        nums = list(_NUM.finditer(bytes(d)))
        if nums:
            m = nums[0]
            d[m.start():m.end()] = str(rng.choice([0, -1, 1, 3, 10 ** 9, 10 ** 18, 2 ** 63])).encode()
            return d
    else:
        return _mutate_bytes(d, rng)
    return bytearray(b"\n".join(lines))


def _mutate_zip(d: bytearray, rng: random.Random) -> bytearray:
    """An ``.npz``: one member removed or mutated (the metadata's JSON as text, re-saved), valid CRCs kept."""
    import io
    import zipfile

    import numpy as np

    try:
        with zipfile.ZipFile(io.BytesIO(bytes(d))) as zf:
            members = [(i.filename, zf.read(i)) for i in zf.infolist()]
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return _mutate_bytes(d, rng)
    k = rng.randrange(len(members))
    name, data = members[k]
    if rng.random() < 0.1:
        del members[k]
    elif name == "metadata.npy" and rng.random() < 0.7:
        text = bytes(np.load(io.BytesIO(data)))
        buf = io.BytesIO()
        np.save(buf, np.frombuffer(mutate(text, True, rng), dtype=np.uint8))
        members[k] = (name, buf.getvalue())
    else:
        members[k] = (name, mutate(data, rng.random() < 0.3, rng))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zw:
        for name, data in members:
            zw.writestr(name, data)
    return bytearray(out.getvalue())


def mutate(data: bytes, text: bool, rng: random.Random) -> bytes:
    d = bytearray(data)
    if d[:4] == b"PK\x03\x04" and rng.random() < 0.7:
        return bytes(_mutate_zip(d, rng))
    for _ in range(rng.choice([1, 1, 1, 2, 2, 3, 4])):
        d = _mutate_text(d, rng) if text and rng.random() < 0.75 else _mutate_bytes(d, rng)
    return bytes(d[: 1 << 20])


# --------------------------------------------------------------------------- #
# classification (in the worker)
# --------------------------------------------------------------------------- #
class _Timeout(BaseException):
    """Raised by the alarm; a BaseException so that the reader's ``except Exception`` does not swallow it."""


def _package_dir() -> str:
    import torch_hsh

    return os.path.realpath(os.path.dirname(torch_hsh.__file__))


def classify(exc: Optional[BaseException], victim: Path, pkg: str) -> Tuple[str, str]:
    """``(kind, detail)`` of the outcome of one read of ``victim`` (``exc`` None: it returned)."""
    if exc is None:
        return "ok", ""
    if isinstance(exc, _Timeout):
        return "hang", "timed out"
    frames = traceback.extract_tb(exc.__traceback__)
    where = os.path.realpath(frames[-1].filename) if frames else "?"
    in_lib = where.startswith(pkg + os.sep)
    msg = str(exc)
    names_file = victim.name in msg or str(victim) in msg
    detail = f"{type(exc).__module__}.{type(exc).__qualname__}: {msg[:500]} [raised at {where}:{frames[-1].lineno if frames else 0}]"
    own = isinstance(exc, (ValueError, OSError)) or type(exc).__module__.split(".")[0] == "torch_hsh"
    if in_lib and names_file and own:
        return "lib", detail
    return "foreign", detail


def _run_one(seed: Seed, data: bytes, timeout: float, pkg: str) -> Tuple[str, str]:
    """Read ``data`` as the seed's victim file (restored afterwards: seeds may share a folder)."""
    victim = seed.folder / seed.victim
    original = victim.read_bytes()
    victim.write_bytes(data)

    def alarm(signum, frame):
        raise _Timeout()

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, timeout)
    exc: Optional[BaseException] = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            seed.call(seed.folder, victim)
    except BaseException as e:  # noqa: B036 - classified, including the alarm
        exc = e
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        victim.write_bytes(original)
    kind, detail = classify(exc, victim, pkg)
    if kind == "foreign":
        detail += "\n" + "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)[-6:])
    return kind, detail


def _set_memory_limit(mem_mb: int) -> None:
    try:
        import resource

        with open("/proc/self/status") as f:
            vm = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
        lim = vm + mem_mb * (1 << 20)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
    except (OSError, ValueError, ImportError, StopIteration):
        pass


def _worker(conn, targets: List[str], timeout: float, mem_mb: int) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    import torch

    torch.set_num_threads(1)
    pkg = _package_dir()
    base = Path(tempfile.mkdtemp(prefix="torch_hsh_fuzz_"))
    try:
        seeds = {t: _builder(t)(base / t) for t in targets}
        conn.send({t: [(s.victim, (s.folder / s.victim).read_bytes()) for s in v] for t, v in seeds.items()})
        _set_memory_limit(mem_mb)
        while True:
            msg = conn.recv()
            if msg is None:
                break
            t, k, data = msg
            conn.send(_run_one(seeds[t][k], data, timeout, pkg))
    finally:
        shutil.rmtree(base, ignore_errors=True)


# --------------------------------------------------------------------------- #
# the campaign (parent)
# --------------------------------------------------------------------------- #
class _Pool1:
    """One worker process holding the seeds of ``targets``, restarted (at the next input) after a crash or a hang."""

    def __init__(self, targets: List[str], timeout: float, mem_mb: int, grace: float = 30.0):
        self.targets, self.timeout, self.mem_mb, self.grace = list(targets), timeout, mem_mb, grace
        self.ctx = mp.get_context("spawn")
        self.proc = None
        self.seeds: Dict[str, List[Tuple[str, bytes]]] = {}
        self.start()

    def start(self) -> None:
        self.conn, child = self.ctx.Pipe()
        self.proc = self.ctx.Process(target=_worker, args=(child, self.targets, self.timeout, self.mem_mb), daemon=True)
        self.proc.start()
        child.close()
        if not self.conn.poll(300):
            raise RuntimeError(f"the worker of {self.targets} did not start")
        self.seeds = self.conn.recv()

    def kill(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.kill()
        if self.proc is not None:
            self.proc.join(10)

    def run(self, target: str, k: int, data: bytes) -> Tuple[str, str]:
        if self.proc is None:
            self.start()
        try:
            self.conn.send((target, k, data))
            if self.conn.poll(self.timeout + self.grace):
                return self.conn.recv()
            kind, detail = "hang", f"no answer within {self.timeout + self.grace:.0f} s"
        except (EOFError, OSError, BrokenPipeError):
            kind, detail = "crash", ""
        self.kill()
        if kind == "crash":
            detail = f"worker died (exit code {self.proc.exitcode})"
        self.proc = None
        return kind, detail

    def close(self) -> None:
        if self.proc is None:
            return
        try:
            self.conn.send(None)
            self.proc.join(30)
        except (OSError, BrokenPipeError):
            pass
        self.kill()


def run_target(target: str, n: int, seed: int = 0, timeout: float = 10.0, mem_mb: int = 1024,
               save: Optional[Path] = None, examples: int = 3, grace: float = 30.0,
               pool: Optional[_Pool1] = None) -> Dict[str, object]:
    """Fuzz ``target`` with ``n`` inputs; returns the counts per kind, the time and a few failure details.

    ``grace``: seconds past ``timeout`` before a worker that does not answer (the alarm blocked) is killed.
    ``pool``: a worker holding this target's seeds (shared by several targets); default: one of its own.
    """
    rng = random.Random(f"{target}-{seed}")
    own = pool is None
    pool = _Pool1([target], timeout, mem_mb, grace) if pool is None else pool
    text_target = TARGETS[target][1] if target in TARGETS else False
    counts = {k: 0 for k in KINDS}
    failures: List[str] = []
    t0 = time.perf_counter()
    try:
        for i in range(n):
            k = rng.randrange(len(pool.seeds[target]))
            name, seed_data = pool.seeds[target][k]
            data = mutate(seed_data, text_target or name.endswith((".json", ".txt", ".lp")), rng)
            kind, detail = pool.run(target, k, data)
            counts[kind] += 1
            if kind in ("foreign", "hang", "crash"):
                if len(failures) < examples:
                    failures.append(f"input {i} (seed file {k}): {kind}: {detail}")
                if save is not None:
                    save.mkdir(parents=True, exist_ok=True)
                    stem = save / f"{target}-{i:06d}-{kind}"
                    stem.with_suffix(".bin").write_bytes(data)
                    stem.with_suffix(".txt").write_text(f"target {target}, seed file {k}\n{detail}\n")
    finally:
        if own:
            pool.close()
    return {"target": target, "inputs": n, **counts, "seconds": time.perf_counter() - t0, "failures": failures}


def replay(path: Path, target: str, seed_index: Optional[int] = None, timeout: float = 60.0) -> Tuple[str, str]:
    """Rerun one saved input in this process: ``(kind, detail)``; the traceback is printed for foreign ones."""
    if seed_index is None:
        txt = path.with_suffix(".txt")
        m = re.search(r"seed file (\d+)", txt.read_text()) if txt.is_file() else None
        seed_index = int(m.group(1)) if m else 0
    pkg = _package_dir()
    base = Path(tempfile.mkdtemp(prefix=f"torch_hsh_fuzz_replay_{target}_"))
    try:
        seeds = _builder(target)(base)
        return _run_one(seeds[seed_index], path.read_bytes(), timeout, pkg)
    finally:
        shutil.rmtree(base, ignore_errors=True)


def table(rows: List[Dict[str, object]]) -> str:
    head = "| target | inputs | ok | library errors | foreign | hangs | crashes | seconds |"
    out = [head, "|" + "---|" * 8]
    for r in rows:
        out.append(f"| {r['target']} | {r['inputs']} | {r['ok']} | {r['lib']} | {r['foreign']} | {r['hang']} | "
                   f"{r['crash']} | {r['seconds']:.0f} |")
    tot = {k: sum(int(r[k]) for r in rows) for k in ("inputs",) + KINDS}
    out.append(f"| **total** | {tot['inputs']} | {tot['ok']} | {tot['lib']} | {tot['foreign']} | {tot['hang']} | "
               f"{tot['crash']} | {sum(float(r['seconds']) for r in rows):.0f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--target", nargs="*", default=None, help="targets (default: all)")
    ap.add_argument("-n", "--inputs", type=int, default=6000,
                    help="inputs per target of share 1 (scaled by each target's share; default 6000)")
    ap.add_argument("--seed", type=int, default=0, help="RNG seed (the same seed gives the same inputs)")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds per input before it counts as a hang")
    ap.add_argument("--mem-mb", type=int, default=1024, help="address space the worker may add per input")
    ap.add_argument("--save", type=Path, default=Path("build/fuzz/failures"), help="folder for failing inputs")
    ap.add_argument("--replay", type=Path, default=None, help="rerun one saved input (with --target T)")
    ap.add_argument("--seed-file", type=int, default=None, help="seed file index of the replayed input")
    ap.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    ap.add_argument("--list", action="store_true", help="list the targets")
    args = ap.parse_args(argv)
    if args.list:
        for name, (_, text, share) in TARGETS.items():
            print(f"{name:22s} {'text' if text else 'binary'}  share {share}")
        return 0
    targets = args.target or list(TARGETS)
    bad = [t for t in targets if t not in TARGETS]
    if bad:
        ap.error(f"unknown target(s) {bad}; --list shows them")
    if args.replay is not None:
        if len(targets) != 1:
            ap.error("--replay needs exactly one --target")
        sys.path.insert(0, str(ROOT))
        kind, detail = replay(args.replay, targets[0], args.seed_file)
        print(f"{kind}: {detail}")
        return 0 if kind in ("ok", "lib") else 1
    rows = []
    for t in targets:
        n = max(1, int(round(args.inputs * TARGETS[t][2])))
        r = run_target(t, n, seed=args.seed, timeout=args.timeout, mem_mb=args.mem_mb, save=args.save)
        rows.append(r)
        print(f"{t}: {n} inputs, ok {r['ok']}, library errors {r['lib']}, foreign {r['foreign']}, hangs {r['hang']}, "
              f"crashes {r['crash']} ({r['seconds']:.0f} s)", flush=True)
        for f in r["failures"]:
            print("   ", f.replace("\n", "\n    "), flush=True)
    print()
    print(table(rows))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0 if all(r["foreign"] == r["hang"] == r["crash"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
