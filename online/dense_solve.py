"""Dense LU factorisation with partial pivoting and its solve, in place and allocation-free,
for the reduced tangents of a hyper-reduced model (n + n_p of a few tens to a hundred):
what a compiled haptic step (:mod:`.haptic_newton`) calls instead of LAPACK through
Python. The layout is LAPACK getrf's: after the factorisation, A holds U on and above the
diagonal and L (unit diagonal, not stored) below it; ``pivots[k]`` is the row swapped with
row k at step k. The loops over a row run over contiguous entries counted from 0 (see
:mod:`.hyperreduced`: they then vectorise).

``_lu_factor`` and ``_lu_solve`` are inlined into their callers (with their fastmath
flags); :func:`lu_factor` and :func:`lu_solve` are the same, compiled with explicit
signatures and shape checks, for Python.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(inline="always")
def _lu_factor(A, pivots) -> bool:
    """A = P L U in place; False (A then partly overwritten) if an entry is not finite or
    a pivot is at most ``size`` machine epsilons of A's largest entry: singular to working
    precision (such a pivot is rounding, its factors garbage). The blocks of a mixed
    tangent differ in scale, but its pivots stay far above that: the smallest is 1e-5 of
    the largest entry on test_ecsw_model's cornea (8 + 8 modes), at rest and loaded."""
    size = A.shape[0]
    scale = 0.0
    for i in range(size):
        for j in range(size):
            if not np.isfinite(A[i, j]):
                return False
            scale = max(scale, abs(A[i, j]))
    smallest = size * np.finfo(np.float64).eps * scale
    for k in range(size):
        pivot, largest = k, abs(A[k, k])
        for i in range(k + 1, size):
            if abs(A[i, k]) > largest:
                pivot, largest = i, abs(A[i, k])
        if not (largest > smallest and largest < np.inf):
            return False
        pivots[k] = pivot
        if pivot != k:
            for j in range(size):
                A[k, j], A[pivot, j] = A[pivot, j], A[k, j]
        inverse = 1.0 / A[k, k]
        rest = size - k - 1
        for i in range(k + 1, size):
            factor = A[i, k] * inverse
            A[i, k] = factor
            if factor != 0.0:
                for j in range(rest):
                    A[i, k + 1 + j] -= factor * A[k, k + 1 + j]
    return True


@njit(inline="always")
def _lu_solve(A, pivots, b):
    """b = A^-1 b in place, A and pivots from :func:`_lu_factor`."""
    size = b.shape[0]
    for k in range(size):
        pivot = pivots[k]
        if pivot != k:
            b[k], b[pivot] = b[pivot], b[k]
    for i in range(size):  # L y = P b, L unit lower triangular
        v = b[i]
        for j in range(i):
            v -= A[i, j] * b[j]
        b[i] = v
    for i in range(size - 1, -1, -1):  # U x = y
        v = b[i]
        for j in range(size - 1 - i):
            v -= A[i, i + 1 + j] * b[i + 1 + j]
        b[i] = v / A[i, i]


@njit(inline="always")
def _check(A, pivots, size):
    if A.shape[0] != A.shape[1] or pivots.shape[0] != A.shape[0] or size != A.shape[0]:
        raise ValueError("A must be square, pivots and b of its size")


@njit(inline="always")
def _check_factors(A, pivots):
    """Every pivot a row (a solve swaps the rows they name) and U's diagonal nonzero and
    finite (a solve divides by it): factors as :func:`_lu_factor` leaves them."""
    for k in range(pivots.shape[0]):
        if not 0 <= pivots[k] < pivots.shape[0]:
            raise ValueError("a pivot is not a row of A")
        if not (abs(A[k, k]) > 0.0 and np.isfinite(A[k, k])):
            raise ValueError("the factors' diagonal must be nonzero and finite (lu_factor's)")


@njit("boolean(float64[:, ::1], int64[::1])", cache=True, nogil=True)
def lu_factor(A, pivots) -> bool:
    """:func:`_lu_factor`, shapes checked (ValueError)."""
    _check(A, pivots, A.shape[0])
    return _lu_factor(A, pivots)


@njit("void(Array(float64, 2, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), "
      "float64[::1])", cache=True, nogil=True)  # fmt: skip
def lu_solve(A, pivots, b):
    """:func:`_lu_solve`, shapes checked (ValueError)."""
    _check(A, pivots, b.shape[0])
    _check_factors(A, pivots)
    _lu_solve(A, pivots, b)
