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
STEP, MAX_DISPLACEMENT, MAX_FORCE, KNOTS = 11, 12, 13, 14
ANM_BASE, ANM_N1, ANM_SMAX, ANM_SLOPE, ANM_BEYOND = 15, 16, 17, 18, 19  # POD-ANM (below)
CURVE = 20

# POD-ANM region, at buf[ANM_BASE]: three neighbour blocks of 4 + SMAX * stride floats,
# [weight, section count, section found (artifact row), a found, records...], one record
# per section: [a_max, depth at 0, depth at a_max, force at a_max, dF/ddepth at a_max,
# depth coefficients (N1), force coefficients (N1)]: stride = 5 + 2 N1.
REC_AMAX, REC_DEPTH0, REC_DEPTH_END, REC_FORCE_END, REC_SLOPE_END, REC_COEFFS = 0, 1, 2, 3, 4, 5


def record_stride(n1: int) -> int:
    return REC_COEFFS + 2 * n1


def anm_block_size(n1: int, smax: int) -> int:
    return 4 + smax * record_stride(n1)


def buffer_size(knots: int, n1: int = 0, smax: int = 0) -> int:
    return CURVE + 2 * knots + (3 * anm_block_size(n1, smax) if n1 else 0)


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


@njit(f"void({f8_1d}, float64, float64, int64)", cache=True, nogil=True)
def write_force(buf, magnitude, depth, flags):
    """A displacement step's outputs: the force along the normal (N), depth, flags."""
    for c in range(3):
        buf[FORCE + c] = magnitude * buf[NORMAL + c]
    buf[DEPTH] = depth
    buf[FLAGS] = flags


@njit(f"void({f8_1d}, float64, int64)", cache=True, nogil=True)
def write_displacement(buf, depth, flags):
    """A force step's outputs: the tool displacement against the normal (mm), depth, flags."""
    for c in range(3):
        buf[DISPLACEMENT + c] = -depth * buf[NORMAL + c]
    buf[DEPTH] = depth
    buf[FLAGS] = flags


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
    write_force(buf, magnitude, depth, flags)
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
    write_displacement(buf, depth, flags)
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


@njit(f"Tuple((float64[::1], float64[:, ::1]))({f8_2d})", cache=True)
def symmetric_eigen(G):
    """Eigenvalues and orthonormal eigenvectors (columns) of a small symmetric matrix.

    Cyclic Jacobi rotations: a few sweeps for the n <= 20 matrices here, exact
    to rounding, and no LAPACK: numba's np.linalg.eigh needs scipy, which the
    runtime does not depend on.
    """
    n = G.shape[0]
    A = G.copy()
    V = np.eye(n)
    for _ in range(100):
        off = 0.0
        scale = 0.0
        for p in range(n):
            scale += A[p, p] * A[p, p]
            for q in range(p + 1, n):
                off += A[p, q] * A[p, q]
        if off <= 1e-32 * scale or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # A <- A J (columns p, q)
                    akp, akq = A[k, p], A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(n):  # A <- J^T A (rows p, q)
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(n):  # V <- V J
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    values = np.empty(n)
    for p in range(n):
        values[p] = A[p, p]
    return values, V


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
    lam, V = symmetric_eigen(G)  # Gamma^T Gamma = V S^2 V^T
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


# -- POD-ANM series ---------------------------------------------------------------------
@njit(f"float64({f8_1d}, int64, int64, float64)", cache=True, nogil=True)
def horner(c, start, n, a):
    """sum_k c[start + k] a^k, k < n."""
    acc = 0.0
    for k in range(n - 1, -1, -1):
        acc = acc * a + c[start + k]
    return acc


@njit(f"float64({f8_1d}, int64, int64, float64)", cache=True, nogil=True)
def horner_derivative(c, start, n, a):
    """d/da sum_k c[start + k] a^k."""
    acc = 0.0
    for k in range(n - 1, 0, -1):
        acc = acc * a + k * c[start + k]
    return acc


@njit(f"float64({f8_1d}, int64, int64, float64)", cache=True, nogil=True)
def section_root(buf, rec, n1, depth):
    """a in [0, a_max] with depth(a) = depth on the section at buf[rec]: bracketed Newton."""
    c = rec + REC_COEFFS
    lo, hi = 0.0, buf[rec + REC_AMAX]
    d0, d1 = buf[rec + REC_DEPTH0], buf[rec + REC_DEPTH_END]
    a = lo + (hi - lo) * (depth - d0) / (d1 - d0) if d1 > d0 else 0.5 * (lo + hi)
    tol = 1e-14 * (1.0 + abs(depth))
    for _ in range(60):
        r = horner(buf, c, n1, a) - depth
        if abs(r) <= tol:
            break
        if r > 0.0:
            hi = a
        else:
            lo = a
        slope = horner_derivative(buf, c, n1, a)
        trial = a - r / slope if slope > 0.0 else 0.5 * (lo + hi)
        a = trial if lo < trial < hi else 0.5 * (lo + hi)
        if hi - lo <= 1e-15 * buf[rec + REC_AMAX]:
            break
    return a


@njit(f"float64({f8_1d}, float64)", cache=True, nogil=True)
def anm_force(buf, depth):
    """Blended normal force (N) of the three neighbours' series at ``depth`` (mm).

    Writes each neighbour's section and path parameter (for the surface), the
    blended dF/ddepth into buf[ANM_SLOPE] and 1 into buf[ANM_BEYOND] if a
    neighbour's last section ends before ``depth`` (its force then continues
    linearly with the end slope).
    """
    base = int(buf[ANM_BASE])
    n1 = int(buf[ANM_N1])
    stride = REC_COEFFS + 2 * n1
    block = 4 + int(buf[ANM_SMAX]) * stride
    total = 0.0
    slope_total = 0.0
    beyond = 0
    for j in range(3):
        b = base + j * block
        w = buf[b]
        count = int(buf[b + 1])
        s = 0
        while s < count - 1 and buf[b + 4 + s * stride + REC_DEPTH_END] < depth:
            s += 1
        rec = b + 4 + s * stride
        if depth > buf[rec + REC_DEPTH_END]:
            beyond = 1
            a = buf[rec + REC_AMAX]
            force = buf[rec + REC_FORCE_END] + buf[rec + REC_SLOPE_END] * (
                depth - buf[rec + REC_DEPTH_END]
            )
            slope = buf[rec + REC_SLOPE_END]
        else:
            a = section_root(buf, rec, n1, depth)
            c = rec + REC_COEFFS
            force = horner(buf, c + n1, n1, a)
            dd = horner_derivative(buf, c, n1, a)
            slope = horner_derivative(buf, c + n1, n1, a) / dd if dd > 0.0 else 0.0
        buf[b + 2] = s  # section index within the sample
        buf[b + 3] = a
        total += w * force
        slope_total += w * slope
    buf[ANM_SLOPE] = slope_total
    buf[ANM_BEYOND] = beyond
    return total


@njit(f"int64({f8_1d}, {f8_1d})", cache=True, nogil=True)
def step_displacement_anm(d, buf):
    """As :func:`step_displacement`, the force from the POD-ANM series of the neighbours."""
    status = check_input(d, buf[MAX_DISPLACEMENT])
    if status:
        return status
    depth = inward(d, buf)
    flags = int(buf[FLAGS]) & FLAG_OUTSIDE_REGION
    if depth <= 0.0:
        magnitude = 0.0
        depth = 0.0
        flags |= FLAG_NO_CONTACT
        anm_force(buf, 0.0)
    else:
        magnitude = anm_force(buf, depth)
        if buf[ANM_BEYOND] != 0.0:
            flags |= FLAG_BEYOND_DEPTH
    write_force(buf, magnitude, depth, flags)
    return 0


@njit(f"int64({f8_1d}, {f8_1d})", cache=True, nogil=True)
def step_force_anm(f, buf):
    """As :func:`step_force`: the depth whose blended series force equals the push."""
    status = check_input(f, buf[MAX_FORCE])
    if status:
        return status
    push = inward(f, buf)
    flags = int(buf[FLAGS]) & FLAG_OUTSIDE_REGION
    if push <= 0.0:
        depth = 0.0
        flags |= FLAG_NO_CONTACT
        anm_force(buf, 0.0)
    else:
        # Bracket [0, hi]: hi the smallest trained depth of the three neighbours.
        base = int(buf[ANM_BASE])
        n1 = int(buf[ANM_N1])
        stride = REC_COEFFS + 2 * n1
        block = 4 + int(buf[ANM_SMAX]) * stride
        hi = np.inf
        for j in range(3):
            b = base + j * block
            last = b + 4 + (int(buf[b + 1]) - 1) * stride
            hi = min(hi, buf[last + REC_DEPTH_END])
        f_hi = anm_force(buf, hi)
        lo = 0.0
        if push > f_hi:
            # Beyond the first end: bracket by steps along the end slope, doubling.
            width = (push - f_hi) / buf[ANM_SLOPE] if buf[ANM_SLOPE] > 0.0 else hi
            for _ in range(60):
                lo = hi
                hi = lo + 1.5 * width
                if anm_force(buf, hi) >= push:
                    break
                width *= 2.0
        depth = 0.5 * (lo + hi)
        for _ in range(100):
            r = anm_force(buf, depth) - push
            if abs(r) <= 1e-13 * push:
                break
            if r > 0.0:
                hi = depth
            else:
                lo = depth
            slope = buf[ANM_SLOPE]
            trial = depth - r / slope if slope > 0.0 else 0.5 * (lo + hi)
            depth = trial if lo < trial < hi else 0.5 * (lo + hi)
            if hi - lo <= 1e-15 * hi:
                break
        anm_force(buf, depth)  # leave the sections of the returned depth in the buffer
        if buf[ANM_BEYOND] != 0.0:
            flags |= FLAG_BEYOND_DEPTH
    write_displacement(buf, depth, flags)
    return 0


@njit(f"void({f8_1d}, {i8_1d}, {i8_1d}, {f8_2d}, {f8_1d})", cache=True, nogil=True)
def prepare_anm(weights, vertices, offsets, records, buf):
    """Copy the three neighbours' section records and weights into the buffer (set_contact)."""
    base = int(buf[ANM_BASE])
    stride = records.shape[1]
    block = 4 + int(buf[ANM_SMAX]) * stride
    for j in range(3):
        b = base + j * block
        i = vertices[j]
        first, count = offsets[i], offsets[i + 1] - offsets[i]
        buf[b] = weights[j]
        buf[b + 1] = count
        buf[b + 2] = 0.0
        buf[b + 3] = 0.0
        for s in range(count):
            r = b + 4 + s * stride
            for k in range(stride):
                buf[r + k] = records[first + s, k]


@njit(
    f"void({i8_1d}, {i8_1d}, {f8_1d}, {f8_3d}, {f4_3d}, {f8_1d}, {f8_2d})",
    cache=True,
    nogil=True,
    fastmath=True,
)
def surface_anm(vertices, offsets, buf, coefficients, basis_t, scratch, out):
    """Surface displacement sum_j w_j A_j c_j(a_j) (mm) from the series' coordinates.

    ``coefficients`` (Z, N1, n): the artifact's series of the reduced coordinates;
    the section and a of each neighbour are those of the last step.
    """
    base = int(buf[ANM_BASE])
    n1 = int(buf[ANM_N1])
    block = 4 + int(buf[ANM_SMAX]) * (REC_COEFFS + 2 * n1)
    n = basis_t.shape[1]
    flat = out.reshape(out.size)
    flat[:] = 0.0
    for j in range(3):
        b = base + j * block
        w = buf[b]
        if w == 0.0:
            continue
        i = vertices[j]
        row_index = offsets[i] + int(buf[b + 2])
        a = buf[b + 3]
        for m in range(n):
            acc = 0.0
            for k in range(n1 - 1, -1, -1):
                acc = acc * a + coefficients[row_index, k, m]
            scratch[m] = w * acc
        for m in range(n):
            row = basis_t[i, m]
            c = scratch[m]
            for r in range(flat.shape[0]):
                flat[r] += c * row[r]
