"""Progress of long offline work on rank 0: a bar with done / total and an ETA."""

from __future__ import annotations

import sys
import time


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class ProgressBar:
    """Prints ``[#####.....] 12/37 solves  32%  elapsed 0:41  ETA 1:25`` lines.

    ``already_done`` items (resumed from a previous run) count as done but not
    towards the rate, so the ETA reflects this run's speed.
    """

    def __init__(self, total: int, already_done: int = 0, unit: str = "solves", stream=None):
        self.total, self.done, self.unit = total, already_done, unit
        self._start_done = already_done
        self._t0 = time.perf_counter()
        self.stream = stream or sys.stdout

    def advance(self, n: int = 1) -> None:
        """Count ``n`` more units done and redraw."""
        self.done += n
        self.render()

    def line(self) -> str:
        """The bar as one line: done / total, percentage, elapsed time and ETA."""
        width = 30
        frac = self.done / self.total if self.total else 1.0
        bar = "#" * int(round(width * frac)) + "." * (width - int(round(width * frac)))
        elapsed = time.perf_counter() - self._t0
        new = self.done - self._start_done
        eta = "?" if new == 0 else _clock(elapsed / new * (self.total - self.done))
        return (
            f"[{bar}] {self.done}/{self.total} {self.unit} {100 * frac:3.0f}%  "
            f"elapsed {_clock(elapsed)}  ETA {eta}"
        )

    def render(self) -> None:
        """Print the bar (rank 0's stream)."""
        print(self.line(), file=self.stream, flush=True)
