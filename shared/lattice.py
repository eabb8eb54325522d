"""The lattice of points on each sample triangle where the artifact stores the tool's
linear stiffness (``samples/tool_stiffness``): its layout, which the trainer writes and the
runtime reads.

A triangle (corners c0, c1, c2) divided into m x m sub-triangles has the points
b = (m - i - j, i, j) / m for i = 0..m and j = 0..m - i, stored row by row (i outer,
j inner): point (i, j) is entry ``i (m + 1) - i (i - 1) / 2 + j`` of
``(m + 1) (m + 2) / 2``. The weights (b0, b1, b2) are the runtime's barycentric weights
of the contact in that triangle (``online.kernels.locate``), so i / m is c1's weight and
j / m c2's. Values between the points are linear on each sub-triangle: continuous across
the sub-triangles and, since a shared edge's points carry the same values in both
triangles, across the sample triangles.
"""

from __future__ import annotations

import math

import numpy as np

MAX_SUBDIVISIONS = 64


def lattice_size(subdivisions: int) -> int:
    """Points of the lattice with ``subdivisions`` (m >= 1) sub-triangles along an edge."""
    return (subdivisions + 1) * (subdivisions + 2) // 2


def lattice_subdivisions(size: int) -> int | None:
    """m of a lattice of ``size`` points, or None if no m in 1..MAX_SUBDIVISIONS has it."""
    m = (math.isqrt(8 * size + 1) - 3) // 2 if size > 0 else 0
    return m if 1 <= m <= MAX_SUBDIVISIONS and lattice_size(m) == size else None


def lattice_weights(subdivisions: int) -> np.ndarray:
    """(L, 3) integers: each point's (m - i - j, i, j), in storage order (sum m)."""
    m = subdivisions
    return np.array([(m - i - j, i, j) for i in range(m + 1) for j in range(m + 1 - i)])


def lattice_corners(subdivisions: int) -> list[int]:
    """The storage indices of the triangle's corners c0, c1, c2: points (0, 0), (m, 0), (0, m)."""
    return [0, lattice_size(subdivisions) - 1, subdivisions]
