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
    """Every sample's force curve and reduced coordinates on one uniform depth grid."""

    depth: np.ndarray  # (K,) mm, depth[0] = 0
    force: np.ndarray  # (P, K) N
    stiffness: np.ndarray  # (P, K) N/mm, slopes of the monotone cubic
    coefficients: np.ndarray  # (P, K, n) mm


def monotone_slopes(depth: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Slopes (N/mm) of the monotone piecewise-cubic Hermite interpolant (Fritsch-Carlson)."""
    return PchipInterpolator(depth, force).derivative()(depth)


def on_common_grid(depths: list[np.ndarray], forces: list[np.ndarray]):
    """(grid (K,), forces (P, K)): the force curves on ``linspace(0, shallowest end, K)`` by
    monotone cubic interpolation, K the points of the first curve. The one definition of the
    grid: the artifact's (below) and the greedy trainer's indicator use it."""
    top = min(float(d[-1]) for d in depths)
    grid = np.linspace(0.0, top, len(depths[0]))
    return grid, np.array(
        [PchipInterpolator(d, f)(grid) for d, f in zip(depths, forces, strict=True)]
    )


def common_depth_grid(samples: list[Sample], reduced: list[ReducedSample]) -> DepthGrid:
    """Force curves and reduced coordinates on one uniform depth grid.

    Under displacement control every sample's grid is already this one; under
    force control each sample reached its own depths and is resampled
    (monotone cubic for the force, linear for the coordinates).
    """
    grid, forces = on_common_grid([s.depth for s in samples], [s.force for s in samples])
    slopes = np.array([monotone_slopes(grid, f) for f in forces])
    coefficients = np.array(
        [
            np.column_stack([np.interp(grid, s.depth, c) for c in r.coefficients.T])
            for s, r in zip(samples, reduced, strict=True)
        ]
    )
    return DepthGrid(grid, forces, slopes, coefficients)
