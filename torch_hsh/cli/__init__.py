r"""The ``torch-hsh`` command (also ``python -m torch_hsh``): one parser over the applications' subcommands.

Subcommands, each in the package of its application:

* ``torch-hsh ps CAPTURE`` / ``torch-hsh demo`` — photometric stereo on a capture (a DiLiGenT-layout
  folder or an RTI capture) or on a built-in synthetic scene (:mod:`torch_hsh.ps.cli`);
* ``torch-hsh lights CAPTURE`` / ``rti RESULT`` / ``view RESULT`` — light directions from a glossy sphere,
  the HSH RTI export and a WebGL2 relighting page of a result (:mod:`torch_hsh.rti.cli`);
* ``torch-hsh fit MERL`` — the Helmholtz basis fitted to a MERL ``.binary`` BRDF (:mod:`torch_hsh.cli.fit`).

Conventions shared by every subcommand: the input is the positional argument; options are spelled out in
full (no abbreviations); every argument and input
file is checked before anything is written; a bad argument exits with status 2 (an argparse message), a
bad input file or any other failure with status 1 (one line ``torch-hsh CMD: error: ...`` that names the
file; the traceback with ``--debug``); Ctrl-C exits with 130 and SIGTERM with 143, and neither leaves a
partial output behind. Library warnings are printed as one line ``torch-hsh CMD: warning: ...``.

Example::

    torch-hsh demo --out results/demo
    torch-hsh ps ../shared/data/diligent_cat --out results/cat
    torch-hsh view results/cat --out results/cat.html
"""
from __future__ import annotations

import argparse
import re
import signal
import sys
import threading
import traceback
import warnings
from contextlib import contextmanager
from typing import Any, List, NoReturn, Optional

from .common import PROG, InputError

__all__ = ["build_parser", "main", "run", "PROG", "InputError"]


# --------------------------------------------------------------------------- #
# entry points
# --------------------------------------------------------------------------- #
def build_parser() -> argparse.ArgumentParser:
    """The ``torch-hsh`` argument parser (subcommands ``ps``, ``demo``, ``lights``, ``rti``, ``view`` and ``fit``)."""
    from .._version import __version__
    from ..ps.cli import add_ps_commands
    from ..rti.cli import add_rti_commands
    from .fit import add_fit_command

    ap = _TopParser(prog=PROG, description="Helmholtz HSH BRDF tools (torch_hsh).", allow_abbrev=False)
    ap.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    # no abbreviations: `--linear` would otherwise mean --linear-input in ps and --linear-output in rti
    sub = ap.add_subparsers(dest="command", metavar="COMMAND", parser_class=_ExactParser)
    sub.required = True
    add_ps_commands(sub)
    add_rti_commands(sub)
    add_fit_command(sub)
    return ap


class _ExactParser(argparse.ArgumentParser):
    """A subcommand's parser: options must be spelled out (no prefix abbreviations)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)


class _TopParser(argparse.ArgumentParser):
    """The top parser: its message for an unknown option names the option's new name where it was renamed."""

    def error(self, message: str) -> NoReturn:
        if re.search(r"unrecognized arguments:.*--linear(\s|$)", message):
            message += " (renamed: `torch-hsh ps --linear-input`, `torch-hsh rti --linear-output`)"
        super().error(message)


def _one_line_warning(prefix: str):
    """A ``warnings.showwarning`` that prints ``prefix message`` on one line of stderr, without the source line."""
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{prefix} {' '.join(str(message).split())}", file=sys.stderr if file is None else file, flush=True)

    return show


class Terminated(BaseException):
    """Raised in the main thread on SIGTERM, so that a run unwinds (its staging folder removed) as on Ctrl-C."""


@contextmanager
def _sigterm_unwinds():
    """SIGTERM raises :class:`Terminated` in the main thread while the command runs (the previous handler after)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def run(argv: Optional[List[str]] = None) -> Any:
    """Run one ``torch-hsh`` command in-process and return what it reports (a dict); errors raise
    ``SystemExit`` with the exit status (2: a bad argument, 1: a bad input or a failure, 130 / 143: interrupted).

    Example:
        >>> metrics = run(["demo", "--scene", "small", "--size", "16", "--lights", "8", "--quiet",
        ...                "--out", str(tmp_path / "demo")])  # doctest: +SKIP
    """
    return _dispatch(argv)


def _dispatch(argv: Optional[List[str]]):
    ap = build_parser()
    args = ap.parse_args(argv)
    sub_ap = args.parser  # errors carry the subcommand's usage
    prefix = f"{PROG} {args.command}: error:"
    try:
        with warnings.catch_warnings():
            if not args.debug:  # a library warning is one line, like the errors; --debug keeps Python's form
                warnings.showwarning = _one_line_warning(f"{PROG} {args.command}: warning:")
            with _sigterm_unwinds():
                return args.handler(args, sub_ap)
    except SystemExit:
        raise
    except (KeyboardInterrupt, Terminated) as err:
        if args.debug:
            raise
        print(f"{prefix} {'terminated' if isinstance(err, Terminated) else 'interrupted'}; the previous output "
              "(if any) is unchanged", file=sys.stderr)
        raise SystemExit(143 if isinstance(err, Terminated) else 130) from None
    except Exception as err:  # one line, traceback only with --debug
        if args.debug:
            traceback.print_exc()
        else:
            msg = " ".join(str(err).split()) or type(err).__name__
            hint = "" if isinstance(err, InputError) else f" ({type(err).__name__}; --debug shows the traceback)"
            print(f"{prefix} {msg}{hint}", file=sys.stderr)
        raise SystemExit(1) from None


def main(argv: Optional[List[str]] = None) -> int:
    """Console entry point of ``torch-hsh``; returns the exit status (errors raise ``SystemExit``)."""
    _dispatch(argv)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
