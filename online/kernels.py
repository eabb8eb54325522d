"""numba kernels of the online runtime: only ``@njit`` functions writing into caller-owned buffers.

Every kernel has an explicit signature, so it is compiled (or loaded from the
on-disk cache, ``cache=True``) when this module is imported: nothing compiles
inside the haptic loop. None allocates except ``prepare_grassmann`` (small
eigendecompositions, run by ``set_contact`` only). Units: mm, N, N/mm. Besides them,
numpy helpers run once at set-up pack what a call reads into few arrays
(:func:`contact_table`, :func:`scalpel_tables`): a kernel call costs per array passed.

Status codes returned by the steps (nothing is written unless 0): 0 ok, 1 an input is
NaN or infinite, 2 an input is absurdly large (beyond the simulator's limit), 3 an input
has not 3 elements (read no further than its end), 4 a force step's displacement would
pass the displacement limit (``buf[MAX_DEPTH]``).

The model's arrays are read only here: every parameter a kernel only reads accepts a
read-only array (``flags.writeable`` False), so a shared model may be frozen. A step input
may be any 1-D float64 array (any strides, read-only or not).
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
# Read only (a mutable array converts to these at the call).
ro_f8_1d = "Array(float64, 1, 'C', readonly=True)"
ro_f8_2d = "Array(float64, 2, 'C', readonly=True)"
ro_f8_3d = "Array(float64, 3, 'C', readonly=True)"
ro_f8_4d = "Array(float64, 4, 'C', readonly=True)"
ro_f4_3d = "Array(float32, 3, 'C', readonly=True)"
ro_i8_1d = "Array(int64, 1, 'C', readonly=True)"
ro_i8_2d = "Array(int64, 2, 'C', readonly=True)"
vec = "Array(float64, 1, 'A', readonly=True)"  # a caller's vector: any 1-D float64 array

OK, NOT_FINITE, BEYOND_LIMIT, WRONG_SHAPE, DISPLACEMENT_LIMIT = 0, 1, 2, 3, 4


@njit(f"int64({f8_1d}, {ro_f8_2d}, {ro_i8_2d}, {f8_1d}, {i8_1d})", cache=True, nogil=True)
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
    f"void({f8_1d}, {i8_1d}, {ro_f8_2d}, {ro_f8_2d}, {ro_f8_2d}, {f8_1d}, {f8_1d}, {f8_1d})",
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
MAX_DEPTH = 20  # the largest depth a force step may return (mm): see step_force
# The contact's chart coordinates (2) and barycentric weights (3); the scalpel's unit blade
# and unit normal of its plane (6), its surface vertex and region vertex (2, as floats).
CHART, WEIGHTS, FRAME, PLACED = 21, 23, 26, 32
CURVE = 34

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


@njit(f"int64({vec}, float64)", cache=True, nogil=True)
def check_input(v, limit):
    """0 if v (3,) is finite and |v| <= limit; else the step's status code (3, 1 or 2)."""
    if v.shape[0] != 3:
        return WRONG_SHAPE  # before reading: a shorter array is never read past its end
    if not (math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])):
        return 1
    if not (v[0] * v[0] + v[1] * v[1] + v[2] * v[2] <= limit * limit):  # a NaN limit refuses
        return 2
    return 0


@njit(f"float64({vec}, {f8_1d})", cache=True, nogil=True)
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


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
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


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
def step_force(f, buf):
    """Force the tool applies (N) in, tool displacement (mm) into buf (inverse of the curve).

    A force whose depth passes ``buf[MAX_DEPTH]`` is refused (status 4, nothing written),
    as a displacement step refuses a displacement beyond the limit.
    """
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
    if not (depth <= buf[MAX_DEPTH]):
        return DISPLACEMENT_LIMIT
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
    f"void(float64, float64, {f8_1d}, {i8_1d}, {ro_f4_3d}, {ro_f8_3d}, {f8_1d}, {f8_2d})",
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
    f"void(float64, float64, {f8_1d}, {i8_1d}, int64, {ro_f4_3d}, {ro_f4_3d}, {f8_3d}, "
    f"{ro_f8_3d}, {f8_1d}, {f8_2d})",
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


@njit(f"void({f8_1d}, {i8_1d}, {ro_f8_4d}, {ro_f8_4d}, {ro_f8_3d}, {f8_3d})", cache=True)
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


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
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


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
def step_force_anm(f, buf):
    """As :func:`step_force`: the depth whose blended series force equals the push.

    A refused force (status 4) leaves the sections of the previous depth in the buffer.
    """
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
        if not (depth <= buf[MAX_DEPTH]):
            anm_force(buf, buf[DEPTH])  # the sections of the state before: unchanged
            return DISPLACEMENT_LIMIT
        anm_force(buf, depth)  # leave the sections of the returned depth in the buffer
        if buf[ANM_BEYOND] != 0.0:
            flags |= FLAG_BEYOND_DEPTH
    write_displacement(buf, depth, flags)
    return 0


@njit(f"void({f8_1d}, {i8_1d}, {ro_i8_1d}, {ro_f8_2d}, {f8_1d})", cache=True, nogil=True)
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
    f"void({i8_1d}, {ro_i8_1d}, {f8_1d}, {ro_f8_3d}, {ro_f4_3d}, {f8_1d}, {f8_2d})",
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


# -- contact points and the scalpel's placement ------------------------------------------
@njit(f"int64({vec}, {ro_f8_1d}, {ro_f8_2d}, {f8_1d})", cache=True, nogil=True)
def chart_coordinates(point, origin, axes, out):
    """The contact point (3,) in the samples' 2-D chart, into out (2,); or a status (3, 1)."""
    if point.shape[0] != 3:
        return WRONG_SHAPE
    if not (math.isfinite(point[0]) and math.isfinite(point[1]) and math.isfinite(point[2])):
        return NOT_FINITE
    for r in range(2):
        out[r] = (
            axes[r, 0] * (point[0] - origin[0])
            + axes[r, 1] * (point[1] - origin[1])
            + axes[r, 2] * (point[2] - origin[2])
        )
    return OK


def contact_table(origin, axes, chart_points, normals, forces, slopes) -> np.ndarray:
    """The model's arrays ``set_contact`` reads, packed into one read-only float64 array for
    :func:`prepare_contact` (a kernel call costs per array passed): [chart origin (3),
    chart axes (2, 3), chart points (P, 2), sample normals (P, 3), forces (P, K), slopes
    (P, K)], row-major."""
    parts = (origin, axes, chart_points, normals, forces, slopes)
    table = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in parts])
    table.flags.writeable = False
    return table


@njit(f"int64({vec}, {ro_f8_1d}, {ro_i8_2d}, {i8_1d}, {f8_1d})", cache=True, nogil=True)
def prepare_contact(point, table, triangles, vertices, buf):
    """set_contact in one call: chart coordinates, :func:`locate`, :func:`prepare_curves`
    (chart, weights, normal and curves into buf, the samples into ``vertices``) and
    buf[FLAGS], from the :func:`contact_table`. Returns 0, or -(status) of a point that is
    not 3 finite numbers (then nothing is written)."""
    chart, weights = buf[CHART : CHART + 2], buf[WEIGHTS : WEIGHTS + 3]
    knots = int(buf[KNOTS])
    samples = (table.shape[0] - 9) // (5 + 2 * knots)
    a, b = 9 + 2 * samples, 9 + 5 * samples
    c, e = b + samples * knots, b + 2 * samples * knots
    status = chart_coordinates(point, table[0:3], table[3:9].reshape((2, 3)), chart)
    if status:
        return -status
    flag = locate(chart, table[9:a].reshape((samples, 2)), triangles, weights, vertices)
    prepare_curves(weights, vertices, table[a:b].reshape((samples, 3)),
                   table[b:c].reshape((samples, knots)), table[c:e].reshape((samples, knots)),
                   buf[NORMAL : NORMAL + 3], buf[CURVE : CURVE + knots],
                   buf[CURVE + knots : CURVE + 2 * knots])  # fmt: skip
    buf[FLAGS] = flag
    return OK


def point_grid(points: np.ndarray, spacing: float, max_cells: int = 2_000_000) -> tuple:
    """A uniform grid over ``points`` (N, 3) for :func:`nearest_point`, built once (numpy).

    Returns (grid_i, grid_f): grid_i = [nx, ny, nz, cell starts (nx ny nz + 1), point ids
    by cell], grid_f = [origin (3), cell size]. The cell size is ``spacing`` or larger if
    the box would need more than ``max_cells`` cells.
    """
    points = np.asarray(points, dtype=np.float64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = np.maximum(hi - lo, 1e-12)
    h = max(float(spacing), float(np.prod(extent) / max_cells) ** (1 / 3), 1e-9 * extent.max())
    dims = np.minimum(np.floor(extent / h).astype(np.int64) + 1, max_cells)
    index = np.minimum(((points - lo) / h).astype(np.int64), dims - 1)
    cell = (index[:, 0] * dims[1] + index[:, 1]) * dims[2] + index[:, 2]
    order = np.argsort(cell, kind="stable")
    starts = np.searchsorted(cell[order], np.arange(int(np.prod(dims)) + 1))
    grid_i = np.concatenate([dims, starts, order]).astype(np.int64)
    grid_f = np.concatenate([lo, [h]]).astype(np.float64)
    for a in (grid_i, grid_f):
        a.flags.writeable = False
    return grid_i, grid_f


@njit(
    f"int64({vec}, float64, {ro_i8_1d}, {ro_f8_1d}, {ro_f8_2d}, {ro_i8_1d}, boolean)",
    cache=True,
    nogil=True,
)
def nearest_point(p, limit, grid_i, grid_f, points, key, keyed):
    """Index of the point nearest ``p`` within ``limit`` (mm, inclusive), -1 if none (or
    if p is not 3 finite numbers).

    Only points with ``key[i] >= 0`` count if ``keyed``. Exact (the brute-force argmin's
    point, the lowest index on ties): rings of grid cells around p's cell, until the
    ring reaches past the best distance found or past ``limit``.
    """
    if p.shape[0] != 3 or not (math.isfinite(p[0]) and math.isfinite(p[1])
                               and math.isfinite(p[2])):  # fmt: skip
        return -1
    nx, ny, nz = grid_i[0], grid_i[1], grid_i[2]
    ids = 3 + nx * ny * nz + 1  # where the point ids start
    h = grid_f[3]
    cx = int(min(max((p[0] - grid_f[0]) / h, 0.0), nx - 1.0))
    cy = int(min(max((p[1] - grid_f[1]) / h, 0.0), ny - 1.0))
    cz = int(min(max((p[2] - grid_f[2]) / h, 0.0), nz - 1.0))
    best, found = limit * limit, -1
    rings = min(int(limit / h) + 1, max(nx, ny, nz))
    for k in range(rings + 1):
        for ix in range(max(cx - k, 0), min(cx + k, nx - 1) + 1):
            for iy in range(max(cy - k, 0), min(cy + k, ny - 1) + 1):
                for iz in range(max(cz - k, 0), min(cz + k, nz - 1) + 1):
                    if max(abs(ix - cx), abs(iy - cy), abs(iz - cz)) != k:
                        continue  # an inner ring's cell: seen already
                    cell = 3 + (ix * ny + iy) * nz + iz
                    for j in range(grid_i[cell], grid_i[cell + 1]):
                        i = grid_i[ids + j]
                        if keyed and key[i] < 0:
                            continue
                        dx, dy, dz = points[i, 0] - p[0], points[i, 1] - p[1], points[i, 2] - p[2]
                        d = dx * dx + dy * dy + dz * dz
                        if d < best or (d == best and (found < 0 or i < found)):
                            best, found = d, i
        # Points not seen yet are at least k h away.
        if found >= 0 and best < (k * h) * (k * h):
            break
    return found


# place_scalpel's status codes (besides OK and WRONG_SHAPE, which is the position's)
BLADE_SHAPE, POSITION_NOT_FINITE, BLADE_NOT_FINITE, OFF_ORGAN, BLADE_ALONG_NORMAL = 5, 6, 7, 8, 9


def scalpel_tables(vertices, normals, region_of, spacing: float, reach: float,
                   region_reach: float) -> tuple:  # fmt: skip
    """What :func:`place_scalpel` reads, packed (read only): (floats, ints) = ([reach,
    region_reach, grid_f (4), vertices (V, 3), normals (V, 3)], [grid_i, region_of (V)]),
    with the :func:`point_grid` of the vertices."""
    grid_i, grid_f = point_grid(vertices, spacing)
    floats = np.concatenate([[reach, region_reach], grid_f, np.ravel(vertices), np.ravel(normals)])
    floats = floats.astype(np.float64, copy=False)
    ints = np.concatenate([grid_i, np.asarray(region_of, dtype=np.int64)])
    for a in (floats, ints):
        a.flags.writeable = False
    return floats, ints


@njit(
    f"int64({vec}, {vec}, {ro_f8_1d}, {ro_i8_1d}, {ro_f8_1d}, {ro_i8_2d}, {i8_1d}, {f8_1d})",
    cache=True,
    nogil=True,
)
def place_scalpel(p, b, floats, ints, table, triangles, vertices, buf):
    """A scalpel at ``p`` (mm) with its blade along ``b``: its frame and the contact there
    (one call: ``scalpel()`` every servo tick), or a status.

    The surface vertex nearest p (within ``reach``, else OFF_ORGAN) gives the normal n;
    the blade is b's part in the tangent plane (BLADE_ALONG_NORMAL if it is within ~6
    degrees of n). Writes buf[FRAME:] = [unit blade (3), unit normal of the blade's plane
    (3)], buf[PLACED:] = [that vertex, the nearest vertex of the cut region within
    ``region_reach`` or -1] and then :func:`prepare_contact` at p; nothing if the status
    is not OK. ``floats``, ``ints``: the :func:`scalpel_tables`.
    """
    reach, region_reach = floats[0], floats[1]
    count = (floats.shape[0] - 6) // 6
    grid_f = floats[2:6]
    points = floats[6 : 6 + 3 * count].reshape((count, 3))
    normals = floats[6 + 3 * count : 6 + 6 * count].reshape((count, 3))
    grid_end = 3 + ints[0] * ints[1] * ints[2] + 1 + count
    grid_i, region_of = ints[:grid_end], ints[grid_end : grid_end + count]
    if p.shape[0] != 3:
        return WRONG_SHAPE
    if b.shape[0] != 3:
        return BLADE_SHAPE
    if not (math.isfinite(p[0]) and math.isfinite(p[1]) and math.isfinite(p[2])):
        return POSITION_NOT_FINITE
    if not (math.isfinite(b[0]) and math.isfinite(b[1]) and math.isfinite(b[2])):
        return BLADE_NOT_FINITE
    vertex = nearest_point(p, reach, grid_i, grid_f, points, region_of, False)
    if vertex < 0:
        return OFF_ORGAN
    n0, n1, n2 = normals[vertex, 0], normals[vertex, 1], normals[vertex, 2]
    size = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    bn = b[0] * n0 + b[1] * n1 + b[2] * n2
    t0, t1, t2 = b[0] - bn * n0, b[1] - bn * n1, b[2] - bn * n2  # in the tangent plane
    tangent = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if size == 0.0 or tangent <= 0.1 * size:
        return BLADE_ALONG_NORMAL
    t0, t1, t2 = t0 / tangent, t1 / tangent, t2 / tangent
    a0, a1, a2 = t1 * n2 - t2 * n1, t2 * n0 - t0 * n2, t0 * n1 - t1 * n0  # blade x normal
    across = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    region = nearest_point(p, region_reach, grid_i, grid_f, points, region_of, True)
    prepare_contact(p, table, triangles, vertices, buf)  # p is 3 finite numbers: it succeeds
    f = FRAME
    buf[f], buf[f + 1], buf[f + 2] = t0, t1, t2
    buf[f + 3], buf[f + 4], buf[f + 5] = a0 / across, a1 / across, a2 / across
    buf[PLACED], buf[PLACED + 1] = vertex, region
    return OK


@njit(f"int64({vec}, {ro_f8_1d}, {ro_i8_1d})", cache=True, nogil=True)
def region_vertex(p, floats, ints):
    """The surface vertex of the cut region nearest p within ``region_reach`` (mm), or -1
    (also if p is not 3 finite numbers). ``floats``, ``ints``: the :func:`scalpel_tables`."""
    count = (floats.shape[0] - 6) // 6
    vertices = floats[6 : 6 + 3 * count].reshape((count, 3))
    grid_end = 3 + ints[0] * ints[1] * ints[2] + 1 + count
    grid_i, region_of = ints[:grid_end], ints[grid_end : grid_end + count]
    return nearest_point(p, floats[1], grid_i, floats[2:6], vertices, region_of, True)
