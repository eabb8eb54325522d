"""numba kernels of the online runtime: only ``@njit`` functions writing into caller-owned buffers.

Every kernel has an explicit signature, so it is compiled (or loaded from the
on-disk cache, ``cache=True``) when this module is imported: nothing compiles
inside the haptic loop. None allocates except ``prepare_grassmann`` (small
eigendecompositions, run by ``set_contact`` only). Units: mm, N, N/mm.

Status codes returned by the steps: 0 ok, 1 an input is NaN or infinite,
2 an input is absurdly large (see the limits), in which case nothing is written.
Flags (``buf[FLAGS]``, a bit field): 1 depth beyond the trained range
(extrapolated linearly), 2 no contact (the tool pulls away: zero force),
4 contact point outside the trained region (clamped to its boundary).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

FLAG_BEYOND_DEPTH = 1
FLAG_NO_CONTACT = 2
FLAG_OUTSIDE_REGION = 4

f8_1d = "float64[::1]"
f8_2d = "float64[:, ::1]"
f8_3d = "float64[:, :, ::1]"
f8_4d = "float64[:, :, :, ::1]"
f4_3d = "float32[:, :, ::1]"
i8_1d = "int64[::1]"
i8_2d = "int64[:, ::1]"


@njit(f"int64({f8_1d}, {f8_2d}, {i8_2d}, {f8_1d}, {i8_1d})", cache=True, nogil=True)
def locate(chart_x, chart_points, triangles, out_weights, out_vertices):
    """Barycentric weights of the chart point in the sample triangulation.

    A point outside the triangulation is clamped to the nearest point of it
    (returns FLAG_OUTSIDE_REGION), so weights stay continuous as it moves.
    """
    px, py = chart_x[0], chart_x[1]
    best = np.inf
    best_t = 0
    best_l0 = best_l1 = 0.0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay = chart_points[a, 0], chart_points[a, 1]
        bx, by = chart_points[b, 0], chart_points[b, 1]
        cx, cy = chart_points[c, 0], chart_points[c, 1]
        det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
        l1 = ((px - ax) * (cy - ay) - (cx - ax) * (py - ay)) / det
        l2 = ((bx - ax) * (py - ay) - (px - ax) * (by - ay)) / det
        l0 = 1.0 - l1 - l2
        if l0 >= -1e-12 and l1 >= -1e-12 and l2 >= -1e-12:
            out_vertices[0], out_vertices[1], out_vertices[2] = a, b, c
            out_weights[0], out_weights[1], out_weights[2] = l0, l1, l2
            return 0
        # Outside this triangle: the nearest point on its edges.
        for e in range(3):
            if e == 0:
                x0, y0, x1, y1 = ax, ay, bx, by
            elif e == 1:
                x0, y0, x1, y1 = bx, by, cx, cy
            else:
                x0, y0, x1, y1 = cx, cy, ax, ay
            ex, ey = x1 - x0, y1 - y0
            s = ((px - x0) * ex + (py - y0) * ey) / (ex * ex + ey * ey)
            s = min(1.0, max(0.0, s))
            dx, dy = x0 + s * ex - px, y0 + s * ey - py
            dist = dx * dx + dy * dy
            if dist < best:
                best, best_t = dist, t
                if e == 0:
                    best_l0, best_l1 = 1.0 - s, s
                elif e == 1:
                    best_l0, best_l1 = 0.0, 1.0 - s
                else:
                    best_l0, best_l1 = s, 0.0
    out_vertices[0] = triangles[best_t, 0]
    out_vertices[1] = triangles[best_t, 1]
    out_vertices[2] = triangles[best_t, 2]
    out_weights[0], out_weights[1] = best_l0, best_l1
    out_weights[2] = 1.0 - best_l0 - best_l1
    return FLAG_OUTSIDE_REGION


@njit(
    f"void({f8_1d}, {i8_1d}, {f8_2d}, {f8_2d}, {f8_2d}, {f8_1d}, {f8_1d}, {f8_1d})",
    cache=True,
    nogil=True,
)
def prepare_curves(weights, vertices, normals, forces, slopes, out_normal, out_force, out_slope):
    """Interpolated outward normal and force-depth curve (values and slopes) at the contact."""
    out_normal[:] = 0.0
    out_force[:] = 0.0
    out_slope[:] = 0.0
    for j in range(3):
        w, i = weights[j], vertices[j]
        for c in range(3):
            out_normal[c] += w * normals[i, c]
        for k in range(forces.shape[1]):
            out_force[k] += w * forces[i, k]
            out_slope[k] += w * slopes[i, k]
    norm = math.sqrt(out_normal[0] ** 2 + out_normal[1] ** 2 + out_normal[2] ** 2)
    for c in range(3):
        out_normal[c] /= norm


@njit("float64(float64[::1], float64[::1], float64, float64)", cache=True, nogil=True)
def hermite(force, slope, step, depth):
    """The piecewise-cubic Hermite curve F(depth) (uniform knots 0, step, 2 step, ...)."""
    last = force.shape[0] - 1
    if depth >= last * step:
        return force[last] + slope[last] * (depth - last * step)
    k = int(depth / step)
    t = depth / step - k
    t2, t3 = t * t, t * t * t
    return (
        (2 * t3 - 3 * t2 + 1) * force[k]
        + (t3 - 2 * t2 + t) * step * slope[k]
        + (-2 * t3 + 3 * t2) * force[k + 1]
        + (t3 - t2) * step * slope[k + 1]
    )


# Layout of the simulator's packed contact buffer (one float64 array, so a step
# call unboxes two arrays instead of eight: the dispatch dominates a step).
NORMAL, FORCE, DISPLACEMENT, DEPTH, FLAGS = 0, 3, 6, 9, 10
STEP, MAX_DISPLACEMENT, MAX_FORCE, KNOTS, CURVE = 11, 12, 13, 14, 15


def buffer_size(knots: int) -> int:
    return CURVE + 2 * knots


@njit(f"int64({f8_1d}, float64)", cache=True, nogil=True)
def check_input(v, limit):
    """0 if v (3,) is finite and |v| <= limit; else the step's status code (1 or 2)."""
    if not (math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])):
        return 1
    if v[0] * v[0] + v[1] * v[1] + v[2] * v[2] > limit * limit:
        return 2
    return 0


@njit(f"float64({f8_1d}, {f8_1d})", cache=True, nogil=True)
def inward(v, buf):
    """-v . normal: the component of v into the tissue."""
    return -(v[0] * buf[NORMAL] + v[1] * buf[NORMAL + 1] + v[2] * buf[NORMAL + 2])


@njit(f"int64({f8_1d}, {f8_1d})", cache=True, nogil=True)
def step_displacement(d, buf):
    """Prescribed tool displacement d (mm) in, reaction force on the tool (N) into buf.

    Depth = -d . normal (into the tissue). The contact is frictionless: only the
    normal component of d loads the tissue, and the force is along the normal.
    """
    status = check_input(d, buf[MAX_DISPLACEMENT])
    if status:
        return status
    knots = int(buf[KNOTS])
    force = buf[CURVE : CURVE + knots]
    slope = buf[CURVE + knots : CURVE + 2 * knots]
    step = buf[STEP]
    depth = inward(d, buf)
    flags = int(buf[FLAGS]) & FLAG_OUTSIDE_REGION
    if depth <= 0.0:
        magnitude = 0.0
        depth = 0.0
        flags |= FLAG_NO_CONTACT
    else:
        if depth > (knots - 1) * step:
            flags |= FLAG_BEYOND_DEPTH
        magnitude = hermite(force, slope, step, depth)
    for c in range(3):
        buf[FORCE + c] = magnitude * buf[NORMAL + c]
    buf[DEPTH] = depth
    buf[FLAGS] = flags
    return 0


@njit(f"int64({f8_1d}, {f8_1d})", cache=True, nogil=True)
def step_force(f, buf):
    """Force the tool applies (N) in, tool displacement (mm) into buf (inverse of the curve)."""
    status = check_input(f, buf[MAX_FORCE])
    if status:
        return status
    knots = int(buf[KNOTS])
    force = buf[CURVE : CURVE + knots]
    slope = buf[CURVE + knots : CURVE + 2 * knots]
    step = buf[STEP]
    push = inward(f, buf)
    flags = int(buf[FLAGS]) & FLAG_OUTSIDE_REGION
    last = knots - 1
    if push <= 0.0:
        depth = 0.0
        flags |= FLAG_NO_CONTACT
    elif push >= force[last]:
        depth = last * step + (push - force[last]) / slope[last]
        if push > force[last]:
            flags |= FLAG_BEYOND_DEPTH
    else:
        lo, hi = 0, last  # force[lo] <= push < force[hi]: bisection on the knots
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if force[mid] <= push:
                lo = mid
            else:
                hi = mid
        a, b = lo * step, hi * step
        depth = a + (push - force[lo]) / (force[hi] - force[lo]) * step
        for _ in range(50):  # safeguarded Newton on a monotone cubic
            r = hermite(force, slope, step, depth) - push
            if abs(r) <= 1e-13 * push:
                break
            if r > 0:
                b = depth
            else:
                a = depth
            k = min(int(depth / step), last - 1)
            t = depth / step - k
            dF = (
                (6 * t * t - 6 * t) * force[k] / step
                + (3 * t * t - 4 * t + 1) * slope[k]
                + (-6 * t * t + 6 * t) * force[k + 1] / step
                + (3 * t * t - 2 * t) * slope[k + 1]
            )
            trial = depth - r / dF if dF > 0 else 0.5 * (a + b)
            depth = trial if a < trial < b else 0.5 * (a + b)
    for c in range(3):
        buf[DISPLACEMENT + c] = -depth * buf[NORMAL + c]
    buf[DEPTH] = depth
    buf[FLAGS] = flags
    return 0


@njit(f"void(float64, float64, int64, {f8_1d})", cache=True, nogil=True)
def depth_weights(depth, step, last, out):
    """Linear interpolation weights in depth: out = [k, 1 - t, t] as floats."""
    x = min(max(depth / step, 0.0), float(last))
    k = min(int(x), last - 1)
    out[0] = k
    out[1] = 1.0 - (x - k)
    out[2] = x - k


@njit(
    f"void(float64, float64, {f8_1d}, {i8_1d}, {f4_3d}, {f8_3d}, {f8_1d}, {f8_2d})",
    cache=True,
    nogil=True,
    fastmath=True,
)
def surface_podi(depth, step, weights, vertices, basis_t, coefficients, scratch, out):
    """PODI surface displacement: sum_i w_i A_i c_i(depth), into out (V, 3), mm.

    ``basis_t`` is the surface basis transposed, (P, n, 3V): the inner loops run
    over contiguous rows (vectorised axpys).
    """
    n = basis_t.shape[1]
    last = coefficients.shape[1] - 1
    depth_weights(depth, step, last, scratch)
    k, a, b = int(scratch[0]), scratch[1], scratch[2]
    flat = out.reshape(out.size)
    flat[:] = 0.0
    for j in range(3):
        i = vertices[j]
        if weights[j] == 0.0:
            continue
        for m in range(n):
            c = weights[j] * (a * coefficients[i, k, m] + b * coefficients[i, k + 1, m])
            row = basis_t[i, m]
            for r in range(flat.shape[0]):
                flat[r] += c * row[r]


@njit(
    f"void(float64, float64, {f8_1d}, {i8_1d}, int64, {f4_3d}, {f4_3d}, {f8_3d}, {f8_3d}, "
    f"{f8_1d}, {f8_2d})",
    cache=True,
    nogil=True,
    fastmath=True,
)
def surface_grassmann(depth, step, weights, vertices, reference, basis_t, tangents_t, frames,
                      coefficients, scratch, out):  # fmt: skip
    """Grassmann surface displacement A(x) c(x, depth) into out (V, 3), mm.

    ``frames`` (from :func:`prepare_grassmann`): [V cos S, V S^-1 sin S, R_0, R_1, R_2].
    c = sum_i w_i R_i c_i(depth); A(x) c = A0 (V cos S c) + Gamma(x) (V S^-1 sin S c),
    Gamma(x) = sum_i w_i Gamma_i: only n-vectors are formed before the row loops, which
    run over contiguous rows of the transposed (P, n, 3V) bases and tangents.
    """
    n = basis_t.shape[1]
    last = coefficients.shape[1] - 1
    depth_weights(depth, step, last, scratch)
    k, a, b = int(scratch[0]), scratch[1], scratch[2]
    c = scratch[3 : 3 + n]
    c[:] = 0.0
    for j in range(3):
        i = vertices[j]
        for p in range(n):
            for q in range(n):
                c[p] += (
                    weights[j]
                    * frames[2 + j, p, q]
                    * (a * coefficients[i, k, q] + b * coefficients[i, k + 1, q])
                )
    ca = scratch[3 + n : 3 + 2 * n]  # V cos S c
    cb = scratch[3 + 2 * n : 3 + 3 * n]  # V S^-1 sin S c
    for p in range(n):
        ca[p] = 0.0
        cb[p] = 0.0
        for q in range(n):
            ca[p] += frames[0, p, q] * c[q]
            cb[p] += frames[1, p, q] * c[q]
    flat = out.reshape(out.size)
    flat[:] = 0.0
    for m in range(n):
        row = basis_t[reference, m]
        for r in range(flat.shape[0]):
            flat[r] += ca[m] * row[r]
        for j in range(3):
            w = weights[j] * cb[m]
            if w == 0.0:
                continue
            row = tangents_t[vertices[j], m]
            for r in range(flat.shape[0]):
                flat[r] += w * row[r]


@njit(f"void({f8_1d}, {i8_1d}, {f8_4d}, {f8_4d}, {f8_3d}, {f8_3d})", cache=True)
def prepare_grassmann(weights, vertices, gtt, gtb, grb, frames):
    """Grassmann interpolation (Amsallem-Farhat; thesis §2.3.1) at the contact, in n x n.

    The tangent vectors Gamma_i = Log_{A0}(A_i) are interpolated linearly,
    Gamma = sum_i w_i Gamma_i = U S V^T, and mapped back, A(x) = A0 V cos S +
    U sin S = A0 V cos S + Gamma V S^-1 sin S. Only small matrices are formed
    here (through precomputed Gram matrices); the surface rows are formed by
    :func:`surface_grassmann`. R_i = A(x)^T A_i carries sample i's reduced
    coordinates into the interpolated basis. Writes frames = [V cos S,
    V S^-1 sin S, R_0, R_1, R_2].
    """
    n = gtt.shape[2]
    G = np.zeros((n, n))
    for a in range(3):
        for b in range(3):
            G += weights[a] * weights[b] * gtt[vertices[a], vertices[b]]
    lam, V = np.linalg.eigh(G)  # Gamma^T Gamma = V S^2 V^T
    for m in range(n):
        s = math.sqrt(max(lam[m], 0.0))
        sinc = math.sin(s) / s if s > 1e-12 else 1.0
        for q in range(n):
            frames[0, q, m] = V[q, m] * math.cos(s)
            frames[1, q, m] = V[q, m] * sinc
    # R_i = (V cos S)^T (A0^T A_i) + (V S^-1 sin S)^T (Gamma^T A_i)
    for j in range(3):
        i = vertices[j]
        for p in range(n):
            for q in range(n):
                acc = 0.0
                for m in range(n):
                    ga = 0.0
                    for a in range(3):
                        ga += weights[a] * gtb[vertices[a], i, m, q]
                    acc += frames[0, m, p] * grb[i, m, q] + frames[1, m, p] * ga
                frames[2 + j, p, q] = acc
