"""The parser's machinery: one-line errors, bounded numbers, PETSc options, unknown options.

argparse cannot be trusted with PETSc's single-dash long options (``-hapticrom_snes_rtol``
would be read as ``-h``), so for the commands that take them they are split off first
(:func:`split_petsc_args`); every other command reads its whole command line and refuses
what it does not know, single-dash typos such as ``-steps 5`` included
(:func:`unknown_option`).
"""

from __future__ import annotations

import argparse
import difflib
import logging
import math
import sys

from hapticrom.cli.console import error

EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    """argparse that keeps the promise: a mistake is one line ``hapticrom: error: ...``.

    No abbreviations (``--step`` is not ``--steps``): an option is spelled out or refused.
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        """Print ``hapticrom: error: COMMAND: MESSAGE (see ... --help)`` and exit 2."""
        command = self.prog.removeprefix("hapticrom").strip()
        where = f"{command}: " if command else ""
        error(f"{where}{message} (see {self.prog} --help)")
        sys.exit(EXIT_USAGE)


# -- argument types (argparse turns ArgumentTypeError into one line) -----------------------
def int_in(low: int, high: int):
    """An argparse type: an integer in [low, high]."""

    def parse(text: str) -> int:
        """The integer, or ArgumentTypeError."""
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must lie in [{low:,}, {high:,}], got {value:,}")
        return value

    return parse


def float_in(low: float, high: float, unit: str = "", low_inclusive: bool = False):
    """An argparse type: a finite float in (low, high] ([low, high] with ``low_inclusive``)."""

    def parse(text: str) -> float:
        """The number, or ArgumentTypeError."""
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        above = low <= value if low_inclusive else low < value
        if not (math.isfinite(value) and above and value <= high):
            least = "at least" if low_inclusive else "above"
            raise argparse.ArgumentTypeError(
                f"must be {least} {low:g} and at most {high:g} {unit}".rstrip() + f", got {text}"
            )
        return value

    return parse


# -- the command line before argparse -------------------------------------------------------
def is_number(token: str) -> bool:
    """Whether ``token`` reads as a number (a negative value, not an option)."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def command_of(argv: list[str]) -> str | None:
    """The command word: the first token that is not an option (global options come first)."""
    return next((token for token in argv if not token.startswith("-")), None)


def split_petsc_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """Split off PETSc options: everything after ``--``, or from the first ``-name`` on."""
    if "--" in argv:
        i = argv.index("--")
        return argv[:i], argv[i + 1 :]
    for i, token in enumerate(argv):
        if is_single_dash_long(token):
            return argv[:i], argv[i:]
    return argv, []


def is_single_dash_long(token: str) -> bool:
    """``-name`` (PETSc's spelling), not ``-v``, ``--name`` or ``-5``."""
    return (
        token.startswith("-")
        and not token.startswith("--")
        and len(token) > 2
        and not is_number(token)
    )


def _long_options(parser: argparse.ArgumentParser) -> list[str]:
    return [s for action in parser._actions for s in action.option_strings if s.startswith("--")]


def _short_flags(parser: argparse.ArgumentParser) -> set[str]:
    return {
        s[1]
        for action in parser._actions
        for s in action.option_strings
        if len(s) == 2 and s[0] == "-" and action.nargs == 0
    }


def suggestion(token: str, parser: argparse.ArgumentParser) -> str:
    """``; did you mean --steps?`` for ``-steps`` or ``--stepz``; empty if nothing is close."""
    options = _long_options(parser)
    name = token.split("=", 1)[0]
    spelled = "--" + name.lstrip("-")
    if spelled in options:
        return f"; did you mean {spelled}?"
    close = difflib.get_close_matches(spelled, options, n=1, cutoff=0.75)
    return f"; did you mean {close[0]}?" if close else ""


def unknown_option(tokens: list[str], parser: argparse.ArgumentParser) -> str | None:
    """The first single-dash token of ``tokens`` that is none of the parser's options.

    Short flags may be grouped (``-vq``); values are not options (``-5``, ``-0.3``); what
    follows ``--`` is positional.
    """
    flags = _short_flags(parser)
    for token in tokens:
        if token == "--":
            return None
        if is_single_dash_long(token) and not set(token[1:]) <= flags:
            return token
    return None


def refuse(parser: argparse.ArgumentParser, extras: list[str], petsc: bool) -> None:
    """Exit with one line naming the first of ``extras`` (what the parser did not take)."""
    option = next((t for t in extras if t.startswith("-") and not is_number(t)), None)
    if option is None:
        parser.error(f"unexpected argument(s): {' '.join(extras)}")
    hint = suggestion(option, parser)
    if not hint and not option.startswith("--"):
        hint = (
            "; PETSc options go last, after the command's own"
            if petsc
            else f"; {parser.prog} takes no PETSc options"
        )
    parser.error(f"unknown option {option}{hint}")


def misplaced_options(petsc_args: list[str], parser: argparse.ArgumentParser) -> None:
    """Refuse, among the PETSc options, a ``-out`` that is the command's own ``--out`` (a
    typo PETSc would never use) and any ``--name`` (PETSc's options have one dash)."""
    ours = _long_options(parser)
    for token in petsc_args:
        name = token.split("=", 1)[0]
        if is_single_dash_long(token) and "-" + name in ours:
            parser.error(f"unknown option {token}; did you mean -{name}?")
        if name in ours:
            parser.error(f"{name} comes after a PETSc option: the command's own options go first")
        if name.startswith("--"):
            refuse(parser, [token], petsc=True)


# -- building the parser ----------------------------------------------------------------------
def add_verbosity(parser: argparse.ArgumentParser, default) -> None:
    """``-v/--verbose`` and ``-q/--quiet``: the logging level, in ``args.log_level``.

    On the main parser (``default`` INFO) and on each command's (``default`` SUPPRESS, so
    that ``hapticrom -q bench ...`` and ``hapticrom bench ... -q`` both work).
    """
    group = parser.add_mutually_exclusive_group()
    for flags, level, text in (
        (("-v", "--verbose"), logging.DEBUG, "also print debug lines (on stderr)"),
        (("-q", "--quiet"), logging.WARNING, "no progress, no information: results and problems"),
    ):
        group.add_argument(
            *flags, dest="log_level", action="store_const", const=level, default=default, help=text
        )


def new_command(sub, name: str, func, help: str, **kwargs) -> argparse.ArgumentParser:
    """A command's parser: its help, ``-v``/``-q``, and ``func(args, petsc_tokens) -> int``."""
    parser = sub.add_parser(name, help=help, description=kwargs.pop("description", help))
    add_verbosity(parser, argparse.SUPPRESS)
    parser.set_defaults(func=func)
    return parser


def number_option(parser, flag: str, parse, default, metavar: str, help: str) -> None:
    """An option taking a bounded number (``parse``: :func:`int_in` or :func:`float_in`)."""
    parser.add_argument(flag, type=parse, default=default, metavar=metavar, help=help)


def model_argument(parser: argparse.ArgumentParser) -> None:
    """The positional reduced-model artifact of the online commands."""
    parser.add_argument("model", help="reduced-model artifact (.h5)")
