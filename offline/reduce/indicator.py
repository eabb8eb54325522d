"""An error indicator of the interpolation over tool positions: leave one sample out.

For each sample i the samples' triangulation on the surface is built again
without it, the runtime locates i's position in it (as ``set_contact`` would)
and blends the neighbours' force curves there. The indicator of sample i is
the largest difference from i's own (full-order) curve over the trained depth
range, relative to i's largest force:

    e_i = max_k |sum_j w_j F_j(d_k) - F_i(d_k)| / max_k F_i(d_k)

(where the others make no triangle, e.g. three samples, the nearest other
sample's curve is the prediction).

It needs only the samples' force curves, so the greedy trainer evaluates it
between solves, and the artifact stores it (``samples/indicator``) for the
runtime, which blends it with the contact's weights (``sim.error_estimate``).
Leaving a sample out doubles the local spacing, so e_i overestimates the error
at the full spacing (about 4x for a smooth response whose interpolation error
scales with the spacing squared); the effectivity is measured, not assumed
(``bench/greedy_history.py``).
"""

from __future__ import annotations

import numpy as np

from hapticrom.offline.reduce.sample_triangulation import triangulate_samples
from hapticrom.online.model import locate_points
from hapticrom.shared.errors import InputError


def leave_one_out(points, normals, surface, force, stiffness=None) -> np.ndarray:
    """The indicator e_i (P,) of every sample (``force``: (P, K) N on one depth grid;
    ``surface``: vertices, triangles and groups of the organ's surface; ``stiffness``: (P,)
    the tool's linear stiffness at the samples (N/mm), or None). With ``stiffness`` the
    curves are blended as the runtime blends them when the artifact has ``tool_stiffness``,
    with the weights w_j k_i / k_j (k_i sample i's own); without, with w_j."""
    points, normals = np.asarray(points, float), np.asarray(normals, float)
    force = np.asarray(force, float)
    if stiffness is not None:
        # The relative error of sample i is the same for F / k_i: blend the F_j / k_j.
        force = force / np.asarray(stiffness, float)[:, None]
    P = len(points)
    indicator = np.zeros(P)
    for i in range(P):
        rest = np.delete(np.arange(P), i)
        try:
            others = triangulate_samples(
                points[rest], normals[rest], surface.vertices, surface.triangles, surface.groups
            )
        except InputError:  # no triangle left: predict with the nearest other sample
            nearest = rest[np.argmin(np.linalg.norm(points[rest] - points[i], axis=1))]
            predicted = force[nearest]
        else:
            samples, weights, _ = locate_points(
                others.points, others.normals, others.triangles, points[i : i + 1]
            )
            predicted = weights[0] @ force[rest][samples[0]]
        indicator[i] = np.max(np.abs(predicted - force[i])) / max(np.max(force[i]), 1e-300)
    return indicator
