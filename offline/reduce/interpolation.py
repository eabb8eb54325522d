"""What the runtime interpolates between samples with: Grassmann tangents and the force
curves on one depth grid (thesis §2.3).

The neighbourhoods (the samples' triangulation on the surface) are
:mod:`.sample_triangulation`'s; the tangent vectors at a reference basis give
the interpolation of the bases on the Grassmann manifold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from hapticrom.offline.mpi import allreduce_sum
from hapticrom.offline.reduce.inputs import Sample
from hapticrom.offline.reduce.operators import ReducedSample


# -- Grassmann tangents -----------------------------------------------------------------
@dataclass
class GrassmannTangents:
    """Log-map tangents Gamma_i at the reference basis (this rank's rows) and the small
    Gram matrices the runtime needs: Gamma_i^T Gamma_j, Gamma_i^T A_j, A_ref^T A_j."""

    tangents_local: list[np.ndarray]
    tangent_tangent: np.ndarray  # (P, P, n, n)
    tangent_basis: np.ndarray  # (P, P, n, n)
    reference_basis: np.ndarray  # (P, n, n)


def log_map(comm, A0: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Gamma = U atan(S) V^T with U S V^T the SVD of (I - A0 A0^T) A (A0^T A)^-1 (thesis
    §2.3.1), from distributed rows through n x n Gram matrices (this rank's rows)."""
    M = allreduce_sum(comm, A0.T @ A)  # A0^T A
    # inv(M) of the n x n Gram matrix as the thesis writes it: a solve would move the
    # Grassmann datasets by ~1e-15 relative (measured), and they stay bit for bit.
    X = (A - A0 @ M) @ np.linalg.inv(M)
    lam, V = np.linalg.eigh(allreduce_sum(comm, X.T @ X))  # X^T X = V S^2 V^T
    s = np.sqrt(np.clip(lam, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(s > 1e-14, np.arctan(s) / s, 1.0)  # atan(S) S^-1 -> 1 as S -> 0
    return X @ (V * scale) @ V.T  # U atan(S) V^T = X V S^-1 atan(S) V^T


def grassmann_tangents(comm, reduced: list[ReducedSample], reference: int) -> GrassmannTangents:
    """Every sample's tangent at the reference sample's basis, and the Gram matrices."""
    A0 = reduced[reference].basis_local
    tangents = [log_map(comm, A0, r.basis_local) for r in reduced]
    P = len(reduced)
    n = A0.shape[1]
    gtt = np.zeros((P, P, n, n))
    gtb = np.zeros((P, P, n, n))
    grb = np.zeros((P, n, n))
    for i in range(P):
        grb[i] = allreduce_sum(comm, A0.T @ reduced[i].basis_local)
        for j in range(P):
            gtt[i, j] = allreduce_sum(comm, tangents[i].T @ tangents[j])
            gtb[i, j] = allreduce_sum(comm, tangents[i].T @ reduced[j].basis_local)
    return GrassmannTangents(tangents, gtt, gtb, grb)


# -- force curves -------------------------------------------------------------------------
@dataclass
class DepthGrid:
    """Every sample's force curve and reduced coordinates on one uniform depth grid, to the
    deepest sample's depth: beyond its own ``solved_depth`` a sample's curve goes on linearly
    (the force with its end slope, the coordinates along their last segment), as the runtime
    continues any curve beyond the grid."""

    depth: np.ndarray  # (K,) mm, depth[0] = 0
    force: np.ndarray  # (P, K) N
    stiffness: np.ndarray  # (P, K) N/mm, slopes of the monotone cubic
    coefficients: np.ndarray  # (P, K, n) mm
    solved_depth: np.ndarray  # (P,) mm: the depth each sample was solved to


# The artifact's grid is at most this many times finer than the common one (the deepest
# sample's depth against the shallowest's: 6.3 on the liver, 7.4 on the 4k organ). Beyond
# it the stiffest samples get fewer knots than they were solved at.
MAX_GRID_REFINEMENT = 16


def monotone_slopes(depth: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Slopes (N/mm) of the monotone piecewise-cubic Hermite interpolant (Fritsch-Carlson)."""
    return PchipInterpolator(depth, force).derivative()(depth)


def on_common_grid(depths: list[np.ndarray], forces: list[np.ndarray]):
    """(grid (K,), forces (P, K)): the force curves on ``linspace(0, shallowest end, K)`` by
    monotone cubic interpolation, K the points of the first curve: the depths every sample
    reached. The error indicator (the greedy trainer's and the artifact's) is taken on it."""
    top = min(float(d[-1]) for d in depths)
    grid = np.linspace(0.0, top, len(depths[0]))
    return grid, np.array(
        [PchipInterpolator(d, f)(grid) for d, f in zip(depths, forces, strict=True)]
    )


def extended_grid(depths: list[np.ndarray]) -> np.ndarray:
    """The artifact's grid: uniform from 0 to the deepest sample's end, its spacing that of
    :func:`on_common_grid` or finer (up to MAX_GRID_REFINEMENT), so the stiffest sample
    keeps its knots.

    Why: under force control a soft place reaches the trained force several times deeper
    than the stiffest (the liver 6.3x, the 4k organ 7.4x). A grid that stopped at the
    shallowest end left the runtime to extrapolate every neighbour's curve there with its
    end slope, though the campaign had solved the soft ones: the force was 2.3 % (liver)
    and 3.35 % (4k organ) off next to the softest samples."""
    top = max(float(d[-1]) for d in depths)
    common = min(float(d[-1]) for d in depths)
    refinement = min(max(int(np.ceil(top / common - 1e-9)), 1), MAX_GRID_REFINEMENT)
    return np.linspace(0.0, top, (len(depths[0]) - 1) * refinement + 1)


def sample_on_grid(depth: np.ndarray, force: np.ndarray, coefficients: np.ndarray,
                   grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(force (K,), coefficients (K, n)) of one sample on ``grid``: within its solved range
    the monotone cubic of the force and the coordinates linear between its steps; beyond
    its end, linear (the force with the cubic's end slope, the coordinates along their last
    segment: what the runtime does beyond the grid's end)."""
    cubic = PchipInterpolator(depth, force)
    end = float(depth[-1])
    beyond = grid > end
    f = cubic(np.minimum(grid, end))
    f[beyond] = force[-1] + float(cubic.derivative()(end)) * (grid[beyond] - end)
    c = np.column_stack([np.interp(grid, depth, column) for column in coefficients.T])
    rate = (coefficients[-1] - coefficients[-2]) / (depth[-1] - depth[-2])
    c[beyond] = coefficients[-1] + np.outer(grid[beyond] - end, rate)
    return f, c


def artifact_depth_grid(samples: list[Sample], reduced: list[ReducedSample]) -> DepthGrid:
    """Force curves and reduced coordinates on the artifact's uniform depth grid
    (:func:`extended_grid`).

    Under displacement control every sample's grid is already this one; under force
    control each sample reached its own depths and is resampled.
    """
    grid = extended_grid([s.depth for s in samples])
    on_grid = [
        sample_on_grid(s.depth, s.force, r.coefficients, grid)
        for s, r in zip(samples, reduced, strict=True)
    ]
    forces = np.array([f for f, _ in on_grid])
    slopes = np.array([monotone_slopes(grid, f) for f in forces])
    ends = np.array([float(s.depth[-1]) for s in samples])
    # a depth within rounding of the grid's end is the end (displacement control: all are)
    solved = np.where(ends >= grid[-1] * (1 - 1e-9), grid[-1], ends)
    return DepthGrid(grid, forces, slopes, np.array([c for _, c in on_grid]), solved)
