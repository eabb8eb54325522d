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
    selected: list[int] = []
    residual = b.copy()
    iterations = 0
    while np.linalg.norm(residual) > tolerance * norm_b and len(selected) < limit:
        if iterations >= 3 * limit + 10:  # round-off cycling an element in and out
            break
        iterations += 1
        gradient = G.T @ residual
        gradient[selected] = -np.inf
        e = int(np.argmax(gradient))
        if not gradient[e] > 1e-14 * norm_b * max(np.abs(G[:, e]).max(), 1e-300):
            break  # no element can reduce the residual any more: the NNLS optimum
        selected.append(e)
        selected = _positive_least_squares(G, b, w, selected)
        residual = b - G[:, selected] @ w[selected]
    order = np.sort(np.asarray(selected, dtype=np.int64))
    return Sampling(
        elements=order,
        weights=w[order].copy(),
        residual=float(np.linalg.norm(residual) / norm_b) if norm_b > 0 else 0.0,
        iterations=iterations,
    )


def _positive_least_squares(G, b, w, selected: list[int]) -> list[int]:
    """Lawson and Hanson's inner loop: the least-squares weights of the selected columns,
    stepping back towards the previous w (and dropping the columns that reach zero) while
    any comes out non-positive. Updates w in place; returns the columns kept."""
    while True:
        z, *_ = np.linalg.lstsq(G[:, selected], b, rcond=None)
        if np.all(z > 0):
            w[selected] = z
            return selected
        current = w[selected]
        negative = z <= 0
        step = np.min(current[negative] / (current[negative] - z[negative]))
        w[selected] = current + step * (z - current)
        kept = [e for e in selected if w[e] > 1e-14 * max(w[selected].max(), 1e-300)]
        for e in set(selected) - set(kept):
            w[e] = 0.0
        selected = kept
        if not selected:
            return selected


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
