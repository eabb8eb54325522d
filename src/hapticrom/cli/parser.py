"""The argument parser of ``hapticrom``: global options and one sub-parser per command."""

from __future__ import annotations

import argparse
import logging

from hapticrom import __version__
from hapticrom.cli.args import (
    Parser,
    add_verbosity,
    command_of,
    misplaced_options,
    refuse,
    split_petsc_args,
    unknown_option,
)
from hapticrom.cli.offline_commands import add_offline_commands
from hapticrom.cli.online_commands import add_online_commands

DESCRIPTION = (
    "Haptic-rate soft-tissue forces by model order reduction (units: mm, N, MPa). "
    "[offline] commands need the offline extra and run under mpirun -n N, with PETSc "
    "options at the end of the line; the others need only the runtime."
)


def build_parser() -> Parser:
    """The parser; ``parser.commands`` maps each command to its own sub-parser."""
    parser = Parser(prog="hapticrom", description=DESCRIPTION)
    parser.add_argument(
        "--version",
        action="version",
        version=f"hapticrom {__version__}",
        help="print the version and exit",
    )
    add_verbosity(parser, logging.INFO)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_offline_commands(sub)
    add_online_commands(sub)
    parser.commands = dict(sub.choices)
    return parser


def takes_petsc_options(parser: Parser, command: str | None) -> bool:
    """Whether ``command`` hands the options it does not know to PETSc."""
    sub = parser.commands.get(command) if command else None
    func = sub.get_default("func") if sub is not None else None
    return bool(getattr(func, "takes_petsc_options", False))


def parse(parser: Parser, argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """(arguments, PETSc options) of ``argv``; anything unknown ends with one line.

    An offline command's PETSc options are split off first (from the first ``-name``, or
    after ``--``); every other command reads the whole line, so ``bench MODEL -steps 5``
    is refused rather than ignored.
    """
    command = command_of(argv)
    sub = parser.commands.get(command) if command else None
    petsc = takes_petsc_options(parser, command)
    ours, petsc_args = split_petsc_args(argv) if petsc else (argv, [])
    if petsc:
        misplaced_options(petsc_args, sub)
    elif sub is not None:
        option = unknown_option(argv[argv.index(command) + 1 :], sub)
        if option is not None:
            refuse(sub, [option], petsc=False)
    args, extras = parser.parse_known_args(ours)
    if extras:
        refuse(parser.commands[args.command], extras, petsc)
    return args, petsc_args
