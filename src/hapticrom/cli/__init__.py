"""The ``hapticrom`` command line.

Offline commands (mesh, solve, campaign, reduce, train, anm, accuracy) need the
``offline`` extra and say so when it is missing; they run under ``mpirun -n N``.
PETSc options go at the end, or after ``--``, and reach PETSc unchanged; the ones PETSc
never used are reported in one warning line at the end::

    mpirun -n 2 hapticrom solve examples/cornea-hgo-indent.toml --out out/cornea \\
        -hapticrom_snes_rtol 1e-10 -hapticrom_snes_monitor

The other commands (play, bench, report, export, check) need only the runtime (``report``
also matplotlib: the ``report`` extra) and refuse any option they do not know, a
single-dash ``-steps 5`` included. ``-v`` adds debug lines, ``-q`` keeps only results,
warnings and errors (:mod:`hapticrom.cli.console`).

A mistake in the input, in a number or in an output location ends with one
line ``hapticrom: error: ...`` and exit status 2 (argparse's own errors too: no
usage block). Output locations are checked before any expensive work.

Modules: :mod:`~hapticrom.cli.parser` (the parser), :mod:`~hapticrom.cli.args` (its
machinery), :mod:`~hapticrom.cli.offline_commands` and
:mod:`~hapticrom.cli.online_commands` (the commands), :mod:`~hapticrom.cli.petsc` (the
offline commands' frame), :mod:`~hapticrom.cli.outputs` (output checks),
:mod:`~hapticrom.cli.console` (logging).
"""

from __future__ import annotations

import contextlib
import sys
import time

from hapticrom import __version__
from hapticrom.cli.args import EXIT_USAGE
from hapticrom.cli.console import LogStream, configure, error, log
from hapticrom.cli.parser import build_parser, parse
from hapticrom.shared.errors import HapticromError

__all__ = ["EXIT_MISSING_EXTRA", "EXIT_USAGE", "build_parser", "main"]

EXIT_MISSING_EXTRA = 3
# A module missing at run time, and the extra that brings it.
EXTRA_OF = {
    "dolfinx": "offline",
    "petsc4py": "offline",
    "slepc4py": "offline",
    "mpi4py": "offline",
    "gmsh": "offline",
    "pydantic": "offline",
    "matplotlib": "report",
}


def main(argv: list[str] | None = None) -> int:
    """Run ``hapticrom ARGV``; the exit status (0, 1 when the work failed, 2, 3)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args, petsc_args = parse(build_parser(), argv)
    configure(args.log_level)
    log.debug(f"hapticrom {__version__}, command line: {' '.join(argv)}")
    started = time.perf_counter()
    try:
        with contextlib.redirect_stdout(LogStream(sys.stdout)):
            code = args.func(args, petsc_args)
    except ImportError as exc:
        return missing_extra(exc)
    except HapticromError as exc:
        error(str(exc))
        return EXIT_USAGE
    log.debug(f"{args.command}: exit status {code} after {time.perf_counter() - started:.2f} s")
    return code


def missing_extra(exc: ImportError) -> int:
    """One line for a missing extra (exit status 3); any other ImportError is a bug."""
    name = (getattr(exc, "name", None) or "").split(".")[0]
    if "pip install" in str(exc):  # hapticrom.offline.require_offline's own message
        error(str(exc))
    elif name in EXTRA_OF:
        error(f"{exc}: pip install 'hapticrom[{EXTRA_OF[name]}]'")
    else:
        raise exc
    return EXIT_MISSING_EXTRA
