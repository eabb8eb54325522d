"""A worker thread for cut events that must not stall the servo loop (``background=True``).

While a worker runs Python code it holds the GIL for up to the interpreter's switch
interval (5 ms by default): a servo tick would wait that long. While any background
cut is on its way the interval is 0.1 ms; the interpreter's own value is restored
after. The setting is process-wide, so it is counted over all workers
(:class:`SwitchInterval`).
"""

from __future__ import annotations

import sys
import threading
import weakref
from concurrent.futures import Future, ThreadPoolExecutor


class SwitchInterval:
    """The process-wide short GIL switch interval, held by any number of users at once."""

    def __init__(self, short: float = 1e-4):
        self.short = short
        self._lock = threading.Lock()
        self._users = 0
        self._saved: float | None = None

    def hold(self) -> None:
        """One more user: the interval is short from the first one on."""
        with self._lock:
            if self._users == 0:
                self._saved = sys.getswitchinterval()
                sys.setswitchinterval(min(self._saved, self.short))
            self._users += 1

    def release(self) -> None:
        """One user fewer: the interpreter's own interval is back after the last one."""
        with self._lock:
            self._users -= 1
            if self._users == 0:
                sys.setswitchinterval(self._saved)


SWITCH_INTERVAL = SwitchInterval()


class CutWorker:
    """One worker thread running jobs in order; ``pending`` futures are taken in order.

    The thread is started by the first :meth:`submit` and stopped when the worker is
    garbage collected. The short switch interval is held while any job is pending.
    """

    def __init__(self, switch: SwitchInterval = SWITCH_INTERVAL):
        self._switch = switch
        self._executor: ThreadPoolExecutor | None = None
        self.jobs: list[Future] = []  # the jobs not taken yet, in order
        self._holding = [False]  # a list: shared with the finaliser

    @property
    def started(self) -> bool:
        """Whether the thread runs (a job was submitted once)."""
        return self._executor is not None

    @property
    def pending(self) -> bool:
        """Whether a job is still to be taken."""
        return bool(self.jobs)

    def submit(self, job, *args) -> None:
        """Run ``job(*args)`` on the worker after the jobs before it; taken by :meth:`take`."""
        self.jobs.append(self._start().submit(job, *args))
        if not self._holding[0]:
            self._switch.hold()
            self._holding[0] = True

    def discard(self, objects) -> None:
        """Let the worker drop the last references to ``objects`` (freeing large arrays
        takes milliseconds: not on the servo thread). Nothing if the worker never ran."""
        if self._executor is not None:
            self._executor.submit(_drop, objects)

    def first_done(self) -> bool:
        """Whether the oldest pending job has finished."""
        return bool(self.jobs) and self.jobs[0].done()

    def take(self):
        """The oldest pending job's result (waiting for it); its exception is raised here."""
        future = self.jobs.pop(0)
        if not self.jobs and self._holding[0]:
            self._holding[0] = False
            self._switch.release()
        return future.result()

    def _start(self) -> ThreadPoolExecutor:
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hapticrom-cut")
            weakref.finalize(self, _close, self._executor, self._holding, self._switch)
        return self._executor


def _close(executor: ThreadPoolExecutor, holding: list, switch: SwitchInterval) -> None:
    """A worker is gone: stop its thread, give back the switch interval if it held it."""
    executor.shutdown(wait=False, cancel_futures=True)
    if holding[0]:
        holding[0] = False
        switch.release()


def _drop(_objects) -> None:
    """Nothing: the worker thread drops the last references to what it was given."""
