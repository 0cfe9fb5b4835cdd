"""The ``torch-hsh`` parser for the command-line reference (docs/cli_reference.md, sphinx-argparse).

sphinx-argparse reads every help text, description and epilog as reStructuredText, but the texts of
:func:`torch_hsh.cli.build_parser` are plain text for ``--help`` (``*.lp``, ``prefixed ps_``,
``plane_*.jpg``): this builds the same parser with the characters that reStructuredText gives a
meaning to escaped, so the page shows the texts exactly as ``--help`` prints them.
"""
import argparse
import re

from torch_hsh.cli import build_parser as _build_parser

_SPECIAL = re.compile(r"([\\*_`|])")


def _escape(text):
    return _SPECIAL.sub(r"\\\1", text) if isinstance(text, str) else text


def _escape_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = _escape(parser.description)
    parser.epilog = _escape(parser.epilog)
    for action in parser._actions:
        if action.help is not argparse.SUPPRESS:
            action.help = _escape(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:  # the one-line summaries in the list of subcommands
                choice.help = _escape(choice.help)
            for sub in action.choices.values():
                _escape_parser(sub)


def build_parser() -> argparse.ArgumentParser:
    """:func:`torch_hsh.cli.build_parser` with its texts escaped for reStructuredText."""
    parser = _build_parser()
    _escape_parser(parser)
    return parser
