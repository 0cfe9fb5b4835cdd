"""What every ``torch-hsh`` subcommand shares: the error of a bad input, the ``--debug`` / ``--quiet`` options and
the bounded-integer argument type.

:mod:`torch_hsh.cli` (``ps``, ``fit``, the entry points) and :mod:`torch_hsh.cli_rti` (``lights``,
``rti``, ``view``) both import from here, and neither imports the other's handlers back.
"""
from __future__ import annotations

import argparse
from typing import Optional

__all__ = ["InputError"]


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
