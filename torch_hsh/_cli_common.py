"""What every ``torch-hsh`` subcommand shares: the error of a bad input and the ``--debug`` / ``--quiet`` options.

:mod:`torch_hsh.cli` (``ps``, ``fit``, the entry points) and :mod:`torch_hsh.cli_rti` (``lights``,
``rti``, ``view``) both import from here, and neither imports the other's handlers back.
"""
from __future__ import annotations

import argparse

__all__ = ["InputError"]


class InputError(Exception):
    """A bad input (file or data): reported as one line, exit status 1."""


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--debug", action="store_true", help="show the traceback of an error")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
