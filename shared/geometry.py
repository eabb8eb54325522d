"""Surface geometry shared by the trainer and the runtime: face area vectors, vertex normals.

numpy only (the runtime imports it).
"""

from __future__ import annotations

import numpy as np


def corner_area_vectors(p: np.ndarray) -> np.ndarray:
    """Area vectors (f, 3) of faces given by their corner coordinates ``p`` (f, 3|4, 3), mm^2.

    For a quadrangle, half the cross product of its diagonals: exact for a
    planar one and the mean area vector of a warped one. The right-hand rule
    of the corner order gives the direction.
    """
    if p.shape[1] == 3:
        return 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return 0.5 * np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])


def face_area_vectors(nodes: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area vectors (f, 3) of triangles or quadrangles ``faces`` (indices into ``nodes``), mm^2."""
    return corner_area_vectors(nodes[faces])


def vertex_normals(nodes: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (k, 3): the area-weighted mean of the adjacent faces' normals.

    Summing area vectors is that weighted mean up to length. A node on no
    face, or whose adjacent normals cancel, gets the zero vector (callers that
    need every normal check for it).
    """
    sums = np.zeros_like(nodes, dtype=np.float64)
    area = face_area_vectors(nodes, faces)
    for corner in range(faces.shape[1]):
        np.add.at(sums, faces[:, corner], area)
    lengths = np.sqrt(np.einsum("ij,ij->i", sums, sums))
    return sums / np.maximum(lengths, np.finfo(np.float64).tiny)[:, None]


def triangle_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edges (E, 2) sorted vertex pairs, index (T, 3)): the distinct edges of the triangles
    and, per triangle, the edge opposite each corner (corners 1-2, 2-0, 0-1); a shared edge
    is one entry (the layout of ``contact_fields/edge_stiffness``)."""
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    pairs = np.stack([t[:, [1, 2]], t[:, [2, 0]], t[:, [0, 1]]], axis=1)  # (T, 3, 2)
    edges, index = np.unique(np.sort(pairs, axis=2).reshape(-1, 2), axis=0, return_inverse=True)
    return edges, index.reshape(-1, 3)


def plan_view(points: np.ndarray, normals: np.ndarray):
    """A plane through points (P, 3) seen along their mean outward normal: its origin (3,)
    (their mean), orthonormal axes (2, 3) and the points' coordinates in it (P, 2), mm.

    For ordering and drawing only (plan-view plots, spreading held-out positions, a
    straight tool path): the runtime interpolates on the surface, not in this plane.
    """
    points = np.asarray(points, dtype=np.float64)
    origin = points.mean(axis=0)
    n = np.asarray(normals, dtype=np.float64).mean(axis=0)
    n /= np.linalg.norm(n)
    t1 = np.eye(3)[np.argmin(np.abs(n))]
    t1 -= (t1 @ n) * n
    t1 /= np.linalg.norm(t1)
    axes = np.vstack([t1, np.cross(n, t1)])
    return origin, axes, (points - origin) @ axes.T
