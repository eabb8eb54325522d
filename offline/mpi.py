"""MPI helpers: rank-0 work that never deadlocks the other ranks, rank-0 printing, and the
sums and gathers of row-distributed arrays."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import numpy as np
from mpi4py import MPI


def on_rank_zero[T](comm, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """Run ``fn`` on rank 0 and broadcast its result to every rank.

    If ``fn`` raises on rank 0, the exception is broadcast and raised on every
    rank, so a failure (a missing file, a bad mesh) never leaves the other
    ranks waiting in a collective call.
    """
    result, error = None, None
    if comm.rank == 0:
        try:
            result = fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - re-raised on every rank below
            error = exc
    result, error = comm.bcast((result, error), root=0)
    if error is not None:
        raise error
    return result


def print0(comm, *args: Any, **kwargs: Any) -> None:
    """print() on rank 0 only, flushed (progress lines must appear as they happen)."""
    if comm.rank == 0:
        kwargs.setdefault("flush", True)
        kwargs.setdefault("file", sys.stdout)
        print(*args, **kwargs)


def allreduce_sum(comm, array) -> np.ndarray:
    """The element-wise sum of ``array`` over the ranks of ``comm``, on every rank."""
    return comm.allreduce(np.asarray(array), op=MPI.SUM)


def allgather_rows(comm, local: np.ndarray) -> np.ndarray:
    """Every rank's block of rows stacked in rank order (the whole row-distributed array)."""
    return np.concatenate(comm.allgather(local), axis=0)
