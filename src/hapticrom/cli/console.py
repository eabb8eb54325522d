"""What the command line prints, through :mod:`logging`: levels, streams, ranks.

- ``hapticrom.progress`` (INFO): whatever the work prints (progress bars, Newton steps,
  tables); during a command ``sys.stdout`` is a :class:`LogStream` that turns each printed
  line into a record of this logger;
- ``hapticrom`` (DEBUG, INFO, WARNING): the command line's own messages;
- :func:`result`: a command's product (``hapticrom bench``'s table), printed whatever the
  level; :func:`error`: the one line ``hapticrom: error: ...``.

INFO goes to stdout as it always did (``-q`` silences it, ``-v`` adds DEBUG); warnings and
debug lines go to stderr as ``hapticrom: warning: ...``. Under ``mpirun`` only rank 0 says
what the command line says; the work's own printing stays as it was.
"""

from __future__ import annotations

import io
import logging
import os
import sys

LOGGER = "hapticrom"
PROGRESS = "hapticrom.progress"
log = logging.getLogger(LOGGER)

_streams = {"stdout": sys.stdout}


def rank() -> int:
    """MPI rank from the launcher's environment, without importing mpi4py."""
    for var in ("PMI_RANK", "PMIX_RANK", "OMPI_COMM_WORLD_RANK"):
        if var in os.environ:
            return int(os.environ[var])
    return 0


def error(message: str) -> None:
    """Print ``hapticrom: error: MESSAGE`` on stderr (rank 0 only)."""
    if rank() == 0:
        print(f"hapticrom: error: {message}", file=sys.stderr, flush=True)


def result(text: str) -> None:
    """Print a command's product on the real stdout, whatever the level (rank 0 only)."""
    if rank() == 0:
        print(text, file=_streams["stdout"], flush=True)


class _Prefixed(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        """``hapticrom: warning: MESSAGE``."""
        return f"hapticrom: {record.levelname.lower()}: {record.getMessage()}"


class _OnlyInfo(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        """INFO records only."""
        return record.levelno == logging.INFO


class _RankZeroSpeaks(logging.Filter):
    """Off rank 0, only the work's own lines (as before: it chooses where it prints)."""

    def filter(self, record: logging.LogRecord) -> bool:
        """The work's own lines only."""
        return record.name == PROGRESS


def configure(level: int) -> None:
    """Send the ``hapticrom`` loggers to today's stdout (INFO) and stderr (the rest).

    Called once per :func:`hapticrom.cli.main`; a second call replaces the handlers (the
    streams may have changed, as under pytest's capture).
    """
    stdout, stderr = sys.stdout, sys.stderr
    _streams["stdout"] = stdout
    info = logging.StreamHandler(stdout)
    info.setFormatter(logging.Formatter("%(message)s"))
    info.addFilter(_OnlyInfo())
    other = logging.StreamHandler(stderr)
    other.setFormatter(_Prefixed())
    other.addFilter(lambda record: record.levelno != logging.INFO)
    log.handlers.clear()
    for handler in (info, other):
        if rank() != 0:
            handler.addFilter(_RankZeroSpeaks())
        log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False


class LogStream(io.TextIOBase):
    """A text stream whose every line becomes an INFO record of ``hapticrom.progress``.

    Stands in for ``sys.stdout`` while a command runs, so that ``-q`` silences what the
    work prints without the work knowing about logging. A line is sent when its newline
    arrives (or on :meth:`flush`); ``fileno`` is the real stdout's (C-level writers, such as
    PETSc's monitors, keep writing there directly).
    """

    def __init__(self, real):
        super().__init__()
        self._real = real
        self._pending = ""
        self._log = logging.getLogger(PROGRESS)

    @property
    def encoding(self) -> str:
        """The real stream's encoding."""
        return getattr(self._real, "encoding", "utf-8")

    def writable(self) -> bool:
        """Always: it is an output stream."""
        return True

    def write(self, text: str) -> int:
        """Buffer ``text``; log every complete line."""
        *lines, self._pending = (self._pending + text).split("\n")
        for line in lines:
            self._log.info(line)
        return len(text)

    def flush(self) -> None:
        """Log a partial line, if any, then flush the real stream."""
        if self._pending:
            self._log.info(self._pending)
            self._pending = ""
        self._real.flush()

    def fileno(self) -> int:
        """The real stream's descriptor."""
        return self._real.fileno()
