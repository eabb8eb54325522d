"""The offline commands' common frame: the extra, PETSc's options, and the ones never used.

Every offline command (:func:`offline_command`) first checks that the ``offline`` extra is
installed, then checks its own input and output locations, then starts PETSc with the
options of the command line (:meth:`PetscOptions.start`), does the work, and at the end
warns about the options PETSc never looked at (a misspelt ``-hapticrom_snes_rtoll`` or a
missing prefix), in one line, as PETSc's ``-options_left`` would in many::

    hapticrom: warning: PETSc option(s) never used: -snes_rtol (misspelt? not under the
    solver's prefix, hapticrom_ by default? for a solver this command does not create?)

PETSc's own multi-line listing at exit is off unless ``-options_left`` is given.
"""

from __future__ import annotations

import functools
import sys

from hapticrom.cli.args import is_number
from hapticrom.cli.console import log

# Options PETSc reads only at PetscFinalize, after the check: never reported.
READ_AT_EXIT = frozenset(
    {"options_left", "options_view", "mpidump", "log_view_gpu_time", "log_view_gpu_energy"}
)


def parse_options(tokens: list[str]) -> list[tuple[str, str | None]]:
    """``-name [value]`` tokens as (name without the dash, value or None) pairs."""
    pairs: list[tuple[str, str | None]] = []
    for token in tokens:
        if token.startswith("-") and not is_number(token):
            pairs.append((token.lstrip("-"), None))
        elif pairs and pairs[-1][1] is None:
            pairs[-1] = (pairs[-1][0], token)
        # else: a word before any option (``-- word``), which PETSc skips too
    return pairs


class PetscOptions:
    """The PETSc options of one offline command: handed to PETSc once, checked after the run."""

    def __init__(self, tokens: list[str]):
        self.tokens = list(tokens)
        self.pairs = parse_options(self.tokens)
        self.started = False
        self._inserted: list[str] = []

    def start(self) -> None:
        """Hand PETSc the options, before anything imports ``petsc4py.PETSc``.

        When PETSc already runs in this process (``main`` called twice), the options are
        put in its database for this command and taken out again by :meth:`take_back`.
        """
        from mpi4py import MPI  # noqa: F401 - loads libmpi, which PETSc's library needs

        if "petsc4py.PETSc" in sys.modules:
            from petsc4py import PETSc

            database = PETSc.Options()
            for name, value in self.pairs:
                database.setValue(name, value)
                self._inserted.append(name)
        else:
            import petsc4py

            wants_listing = any(name == "options_left" for name, _ in self.pairs)
            quiet_exit = [] if wants_listing else ["-options_left", "no"]
            petsc4py.init(["hapticrom", *quiet_exit, *self.tokens])
        self.started = True
        log.debug("PETSc options: %s", " ".join(self.tokens) or "none")

    def unused(self) -> list[str]:
        """The options of the command line PETSc has not looked at (``-name``)."""
        if not self.started or not self.pairs:
            return []
        from petsc4py import PETSc

        database = PETSc.Options()
        return [
            f"-{name}"
            for name, _ in self.pairs
            if name not in READ_AT_EXIT and not database.used(name)
        ]

    def report_unused(self) -> None:
        """Warn, in one line, about the options PETSc never used."""
        unused = self.unused()
        if unused:
            log.warning(unused_message(unused))

    def take_back(self) -> None:
        """Take out of PETSc's database what :meth:`start` put in (PETSc already running)."""
        if self._inserted:
            from petsc4py import PETSc

            for name in self._inserted:
                PETSc.Options().delValue(name)
            self._inserted.clear()


def unused_message(unused: list[str]) -> str:
    """The warning for options PETSc never used, with the likely causes."""
    return (
        f"PETSc option(s) never used: {' '.join(unused)} (misspelt? not under the solver's "
        "prefix, hapticrom_ by default? for a solver this command does not create?)"
    )


def offline_command(petsc: bool = True):
    """Decorate ``cmd(args, petsc_options) -> int`` as an offline command.

    The command runs only with the offline extra installed; it calls
    ``petsc_options.start()`` once its input is checked; the unused options are reported
    when it returns. ``petsc=False``: the command takes no PETSc options (``mesh``).
    """

    def decorate(command):
        """Wrap ``command`` in the offline frame."""

        @functools.wraps(command)
        def run(args, tokens: list[str]) -> int:
            """Check the extra, run the command, report the unused PETSc options."""
            from hapticrom.offline import require_offline

            require_offline()
            options = PetscOptions(tokens)
            try:
                code = command(args, options)
                options.report_unused()
            finally:
                options.take_back()
            return code

        run.takes_petsc_options = petsc
        return run

    return decorate
