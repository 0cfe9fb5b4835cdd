"""What every ``torch-hsh`` subcommand shares: the program name, the error of a bad input, the ``--debug`` /
``--quiet`` options, and the argument types (bounded integers and numbers, a device).

The subcommands live with their applications: :mod:`torch_hsh.ps.cli` (``ps``, ``demo``),
:mod:`torch_hsh.rti.cli` (``lights``, ``rti``, ``view``) and :mod:`torch_hsh.cli.fit` (``fit``); each imports
from here, and :mod:`torch_hsh.cli` assembles them into one parser.
"""
from __future__ import annotations

import argparse
import math
from typing import Optional

import torch

__all__ = ["InputError", "PROG"]

PROG = "torch-hsh"


class InputError(Exception):
    """A bad input (file or data): reported as one line, exit status 1."""


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--debug", action="store_true", help="show the traceback of an error")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def _int_in(lo: Optional[int] = None, hi: Optional[int] = None, what: str = "integer"):
    """An argparse ``type``: an integer in ``[lo, hi]`` (either bound optional), else a message with the range."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an {what}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            rng = f">= {lo}" if hi is None else f"between {lo} and {hi}"
            raise argparse.ArgumentTypeError(f"must be {rng}, got {value}")
        return value

    return parse


def _float_in(lo: float, hi: float, lo_open: bool = False, hi_open: bool = False):
    """A finite number in the interval ``lo .. hi`` (each end open or closed)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and (
            value < hi if hi_open else value <= hi)
        if not ok:
            rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            raise argparse.ArgumentTypeError(f"must be a number in {rng}, got {text}")
        return value

    return parse


def _parse_device(ap: argparse.ArgumentParser, spec: str) -> torch.device:
    try:
        dev = torch.device(spec)
    except (RuntimeError, ValueError) as err:
        ap.error(f"argument --device: invalid device {spec!r} ({err})")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            ap.error(f"argument --device: {spec!r} requested but CUDA is not available (use --device cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            ap.error(f"argument --device: {spec!r} but only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps":
        if not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            ap.error(f"argument --device: {spec!r} requested but MPS is not available")
    elif dev.type != "cpu":
        ap.error(f"argument --device: unsupported device type {dev.type!r} (cpu, cuda, cuda:N or mps)")
    return dev
