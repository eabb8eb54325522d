"""What the runtime interpolates between samples with: the chart, Grassmann tangents, the
force curves on one depth grid (thesis §2.3).

A 2-D chart of the sample positions with its Delaunay triangulation gives the
neighbourhood structure; the tangent vectors at a reference basis give the
interpolation of the bases on the Grassmann manifold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial import Delaunay

from hapticrom.offline.mpi import allreduce_sum
from hapticrom.offline.reduce.inputs import Sample
from hapticrom.offline.reduce.operators import ReducedSample
from hapticrom.shared.errors import InputError


# -- the chart ------------------------------------------------------------------------
@dataclass
class Chart:
    """The samples on a plane: positions (P, 3) mm and outward normals (P, 3); the
    chart's origin (3,), axes (2, 3), the samples' chart coordinates (P, 2) and their
    Delaunay triangles (S, 3); the most central sample (the Grassmann reference)."""

    points: np.ndarray
    normals: np.ndarray
    origin: np.ndarray
    axes: np.ndarray
    chart_points: np.ndarray
    triangles: np.ndarray
    reference: int


def chart_and_triangulation(points: np.ndarray, normals: np.ndarray):
    """A plane through the samples (normal = their mean normal) and its Delaunay triangles."""
    origin = points.mean(axis=0)
    n = normals.mean(axis=0)
    n /= np.linalg.norm(n)
    t1 = np.eye(3)[np.argmin(np.abs(n))]
    t1 -= (t1 @ n) * n
    t1 /= np.linalg.norm(t1)
    axes = np.vstack([t1, np.cross(n, t1)])
    chart = (points - origin) @ axes.T
    if len(points) < 3:
        raise InputError("the artifact needs at least 3 tool positions (a triangle) to interpolate")
    triangles = Delaunay(chart).simplices.astype(np.int32)
    return origin, axes, chart, triangles


def sample_chart(samples: list[Sample]) -> Chart:
    """The chart of the samples' tool positions."""
    points = np.array([s.point for s in samples])
    normals = -np.array([s.direction for s in samples])  # outward: against the push
    origin, axes, chart, triangles = chart_and_triangulation(points, normals)
    reference = int(np.argmin(np.linalg.norm(chart, axis=1)))  # the most central sample
    return Chart(points, normals, origin, axes, chart, triangles, reference)


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


def common_depth_grid(samples: list[Sample], reduced: list[ReducedSample]) -> DepthGrid:
    """Force curves and reduced coordinates on one uniform depth grid.

    Under displacement control every sample's grid is already this one; under
    force control each sample reached its own depths and is resampled
    (monotone cubic for the force, linear for the coordinates).
    """
    K = len(samples[0].depth)
    top = min(s.depth[-1] for s in samples)
    grid = np.linspace(0.0, top, K)
    forces = np.array([PchipInterpolator(s.depth, s.force)(grid) for s in samples])
    slopes = np.array([monotone_slopes(grid, f) for f in forces])
    coefficients = np.array(
        [
            np.column_stack([np.interp(grid, s.depth, c) for c in r.coefficients.T])
            for s, r in zip(samples, reduced, strict=True)
        ]
    )
    return DepthGrid(grid, forces, slopes, coefficients)
