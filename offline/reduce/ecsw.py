"""Energy-conserving sampling and weighting (ECSW): the elements a hyper-reduced model
integrates its internal forces on, and their weights (issue 18, the online physics).

A Galerkin-reduced model's internal force is a sum over the mesh's E elements,
``f(q) = sum_e V_e^T f_e(V_e q)`` (V_e: the basis' rows at element e's dofs). ECSW
(Farhat, Avery, Chapman and Cortial 2014; Farhat, Chapman and Avery 2015) keeps a few
elements with positive weights, ``f(q) ~ sum_{e in S} w_e V_e^T f_e(V_e q)``, chosen so that
the sum reproduces the full one on training snapshots: with ``G`` the matrix whose column e
stacks element e's reduced contributions at every snapshot, and ``b = G 1`` the full sums,

    min ||w||_0  subject to  ||G w - b|| <= tolerance ||b||,  w >= 0,

solved approximately by the active-set non-negative least squares of Lawson and Hanson
stopped as soon as the tolerance holds (each outer iteration adds the element whose column
best reduces the residual, so the selection is sparse). Positive weights keep the reduced
internal force the gradient of a positive sum of element energies: the hyper-reduced model
stays conservative (energy-conserving, hence the name), unlike point-wise sampling.

This module is the selection alone (numpy, any G); assembling G from element kernels and
snapshots is the trainer's step that calls it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from hapticrom.shared.errors import InputError


@dataclass(frozen=True)
class Sampling:
    """ECSW's result: the sampled elements (column indices of G, increasing), their positive
    weights, the relative residual ||G w - b|| / ||b|| reached and the outer iterations."""

    elements: np.ndarray  # (s,) int64
    weights: np.ndarray  # (s,) float64, > 0
    residual: float
    iterations: int


def ecsw(G: np.ndarray, b: np.ndarray | None = None, tolerance: float = 1e-2,
         max_elements: int | None = None) -> Sampling:  # fmt: skip
    """Sparse non-negative weights w with ||G w - b|| <= tolerance ||b|| (module docstring).

    ``G`` (m, E): column e, element e's contributions at the training snapshots; ``b``
    (m,): the full sums, G @ 1 by default (every element with weight 1, the mesh's own
    quadrature). ``max_elements`` stops the selection there even if the tolerance is not
    met (the residual says how far it got). Raises InputError on non-finite input, a
    tolerance outside [0, 1) or shapes that do not agree.
    """
    G, b = _checked(G, b, tolerance)
    m, E = G.shape
    limit = min(E, m) if max_elements is None else min(int(max_elements), E)
    norm_b = float(np.linalg.norm(b))
    w = np.zeros(E)
    qr = _ColumnQR(G, b, limit)
    residual = b.copy()
    iterations = 0
    excluded = np.zeros(E, dtype=bool)  # selected, or dependent on the selected columns
    while np.linalg.norm(residual) > tolerance * norm_b and len(qr.columns) < limit:
        if iterations >= 3 * limit + 10:  # round-off cycling an element in and out
            break
        iterations += 1
        gradient = G.T @ residual
        gradient[excluded] = -np.inf
        e = int(np.argmax(gradient))
        if not gradient[e] > 1e-14 * norm_b * max(np.abs(G[:, e]).max(), 1e-300):
            break  # no element can reduce the residual any more: the NNLS optimum
        excluded[e] = True
        if not qr.append(e):
            continue  # in the span of the selected columns: it cannot help
        _positive_least_squares(qr, w)
        excluded[:] = False
        excluded[qr.columns] = True
        residual = b - qr.selected() @ w[qr.columns]
    order = np.sort(np.asarray(qr.columns, dtype=np.int64))
    return Sampling(
        elements=order,
        weights=w[order].copy(),
        residual=float(np.linalg.norm(residual) / norm_b) if norm_b > 0 else 0.0,
        iterations=iterations,
    )


class _ColumnQR:
    """A thin QR factorisation of the selected columns of G, grown a column at a time
    (classical Gram-Schmidt, twice: orthogonal to round-off), so that a least-squares
    solve costs O(m k) per added column instead of a fresh O(m k^2) factorisation."""

    def __init__(self, G: np.ndarray, b: np.ndarray, capacity: int):
        self.G, self.b = G, b
        self.Q = np.zeros((G.shape[0], capacity))
        # the selected columns of G, in order, side by side: gathering them from G (C order,
        # each a strided column) at every iteration cost more than the rest of ECSW
        self.A = np.zeros((G.shape[0], capacity))
        self.R = np.zeros((capacity, capacity))
        self.qtb = np.zeros(capacity)  # Q^T b
        self.columns: list[int] = []

    def append(self, e: int) -> bool:
        """Add column e; False (nothing added) if it lies in the others' span."""
        k = len(self.columns)
        v = self.G[:, e].copy()
        norm = np.linalg.norm(v)
        r = np.zeros(k)
        for _ in range(2):
            c = self.Q[:, :k].T @ v
            v -= self.Q[:, :k] @ c
            r += c
        rest = np.linalg.norm(v)
        if not rest > 1e-10 * norm:
            return False
        self.Q[:, k] = v / rest
        self.A[:, k] = self.G[:, e]
        self.R[:k, k], self.R[k, k] = r, rest
        self.qtb[k] = self.Q[:, k] @ self.b
        self.columns.append(e)
        return True

    def selected(self) -> np.ndarray:
        """The selected columns of G, (m, k), in the order of ``columns`` (a view)."""
        return self.A[:, : len(self.columns)]

    def solve(self) -> np.ndarray:
        """The least-squares weights of the columns: R z = Q^T b."""
        k = len(self.columns)
        return solve_triangular(self.R[:k, :k], self.qtb[:k]) if k else np.zeros(0)

    def keep(self, columns: list[int]) -> None:
        """Factorise these columns afresh (some were dropped: rare)."""
        self.columns = []
        for e in columns:
            self.append(e)


def _positive_least_squares(qr: _ColumnQR, w: np.ndarray) -> None:
    """Lawson and Hanson's inner loop: the least-squares weights of the selected columns,
    stepping back towards the previous w (and dropping the columns that reach zero) while
    any comes out non-positive. Updates w and the selection in place."""
    while qr.columns:
        selected = qr.columns
        z = qr.solve()
        if np.all(z > 0):
            w[selected] = z
            return
        current = w[selected]
        negative = z <= 0
        step = np.min(current[negative] / (current[negative] - z[negative]))
        w[selected] = current + step * (z - current)
        largest = max(w[selected].max(), 1e-300)
        kept = [e for e in selected if w[e] > 1e-14 * largest]
        w[[e for e in selected if w[e] <= 1e-14 * largest]] = 0.0
        qr.keep(kept)


def _checked(G, b, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    G = np.asarray(G, dtype=np.float64)
    if G.ndim != 2 or G.shape[1] == 0:
        raise InputError(f"ecsw: G must be a 2-D array with one column per element, got {G.shape}")
    b = G.sum(axis=1) if b is None else np.asarray(b, dtype=np.float64)
    if b.shape != (G.shape[0],):
        raise InputError(f"ecsw: b must have {G.shape[0]} entries (G's rows), got {b.shape}")
    if not (np.all(np.isfinite(G)) and np.all(np.isfinite(b))):
        raise InputError("ecsw: G and b must be finite")
    if not 0.0 <= tolerance < 1.0:
        raise InputError(f"ecsw: tolerance must be in [0, 1), got {tolerance!r}")
    return G, b
