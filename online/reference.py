"""The simulator's arithmetic in plain numpy: the reference the numba kernels are tested
against, and the baseline the latency benchmark compares with. Not for production use:
it allocates on every call."""

from __future__ import annotations

import numpy as np

from hapticrom.online.model import ReducedModel


def barycentric(model: ReducedModel, point) -> tuple[np.ndarray, np.ndarray, bool]:
    """(sample indices, weights, outside) of a contact point, by brute force over triangles."""
    x = model.chart_axes @ (np.asarray(point, dtype=float) - model.chart_origin)
    best = (np.inf, None, None)
    for tri in model.sample_triangles:
        a, b, c = model.chart_points[tri]
        T = np.column_stack([b - a, c - a])
        l12 = np.linalg.solve(T, x - a)
        lam = np.array([1 - l12.sum(), l12[0], l12[1]])
        if np.all(lam >= -1e-12):
            return tri.copy(), lam, False
        for e0, e1, i0, i1 in ((a, b, 0, 1), (b, c, 1, 2), (c, a, 2, 0)):
            s = np.clip((x - e0) @ (e1 - e0) / ((e1 - e0) @ (e1 - e0)), 0.0, 1.0)
            dist = np.sum((e0 + s * (e1 - e0) - x) ** 2)
            if dist < best[0]:
                w = np.zeros(3)
                w[i0], w[i1] = 1 - s, s
                best = (dist, tri.copy(), w)
    return best[1], best[2], True


def hermite(force: np.ndarray, slope: np.ndarray, step: float, depth: float) -> float:
    last = len(force) - 1
    if depth >= last * step:
        return force[last] + slope[last] * (depth - last * step)
    k = int(depth // step)
    t = depth / step - k
    basis = np.array(
        [2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2]
    )
    return float(basis @ np.array([force[k], step * slope[k], force[k + 1], step * slope[k + 1]]))


class NumpySimulator:
    """Same contract as :class:`~hapticrom.online.simulator.Simulator` (PODI only)."""

    def __init__(self, model: ReducedModel):
        self.model = model

    def set_contact(self, point) -> None:
        m = self.model
        self.vertices, self.weights, self.outside = barycentric(m, point)
        normal = self.weights @ m.sample_normals[self.vertices]
        self.normal = normal / np.linalg.norm(normal)
        self.curve = self.weights @ m.force[self.vertices]
        self.slope = self.weights @ m.stiffness[self.vertices]
        self.depth = 0.0

    def step_displacement(self, d) -> np.ndarray:
        d = np.asarray(d, dtype=float)
        if not np.all(np.isfinite(d)):
            raise ValueError("displacement is not finite")
        depth = -float(np.dot(d, self.normal))
        magnitude = (
            0.0 if depth <= 0 else hermite(self.curve, self.slope, self.model.depth_step, depth)
        )
        self.depth = max(depth, 0.0)
        return magnitude * self.normal

    def surface_displacement(self) -> np.ndarray:
        m = self.model
        x = min(self.depth / m.depth_step, m.coefficients.shape[1] - 1)
        k = min(int(x), m.coefficients.shape[1] - 2)
        t = x - k
        coefficients = (1 - t) * m.coefficients[self.vertices, k] + t * m.coefficients[
            self.vertices, k + 1
        ]
        fields = np.einsum("irm,im->ir", m.surface_basis[self.vertices].astype(float), coefficients)
        return (self.weights @ fields).reshape(-1, 3)
