"""numba kernels of the rendered surface: the neighbours' coefficients, then one field.

A surface is two steps. First the three neighbours' reduced coordinates at the last depth,
unweighted, into a (3, n) array: from the stored curves' coefficients
(:func:`curves_coefficients`) or from the POD-ANM series (:func:`anm_coefficients`).
Then the field from them: blended where each neighbour was trained
(:func:`blended_surface`, PODI), carried to the contact first
(:func:`transported_surface`, the chart of :mod:`hapticrom.online.surface_chart`), or
blended with the tool's linear dent at the contact added and its blend at the neighbours
taken off (:func:`add_linear_dent`, the "compliance" surface of
:mod:`hapticrom.offline.reduce.contact_fields`).
The Grassmann field (``kernels.surface_grassmann``) interpolates the bases themselves.

Every kernel has an explicit signature (compiled or loaded from the cache at import) and
allocates nothing. Units: mm.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hapticrom.online.kernels import (
    CONTACT_POINT,
    DEPTH,
    HEIGHT,
    NORMAL,
    SAMPLES,
    STEP,
    TRIANGLE,
    WEIGHTS,
    anm_layout,
    anm_section,
    axpy,
    box_gap2,
    closest_on_triangle,
    f8_1d,
    f8_2d,
    field_depth_weights,
    grid_cell,
    grid_reach,
    ring_row,
    ring_span,
    ro_f4_3d,
    ro_f8_3d,
    ro_i8_1d,
)


# -- the neighbours' reduced coordinates -------------------------------------------------------
@njit(f"void({f8_1d}, {ro_f8_3d}, {f8_2d})", cache=True, nogil=True)
def curves_coefficients(buf, coefficients, out):
    """out[j] = c_i(depth) of neighbour j (i = buf[SAMPLES + j]), linear between the stored
    depth knots of ``coefficients`` (P, K, n), and beyond the last (:func:`field_depth_weights`)."""
    k, a, b = field_depth_weights(buf[DEPTH], buf[STEP], coefficients.shape[1] - 1)
    for j in range(3):
        i = int(buf[SAMPLES + j])
        for m in range(out.shape[1]):
            out[j, m] = a * coefficients[i, k, m] + b * coefficients[i, k + 1, m]


@njit(f"void({f8_1d}, {ro_i8_1d}, {ro_f8_3d}, {f8_2d})", cache=True, nogil=True)
def anm_coefficients(buf, offsets, series, out):
    """out[j] = the POD-ANM series of neighbour j at the last step's depth: at its section
    and path parameter there (``series`` (Z, N1, n), Horner in a); beyond its last section,
    continued along the series' tangent at a_max (the series is not evaluated past the
    range where it holds)."""
    base, n1, _, block = anm_layout(buf)
    for j in range(3):
        b = base + j * block
        i = int(buf[SAMPLES + j])
        section, a, beyond = anm_section(buf, b, buf[DEPTH])
        row = offsets[i] + section
        for m in range(out.shape[1]):
            acc = slope = 0.0
            for k in range(n1 - 1, -1, -1):
                acc = acc * a + series[row, k, m]
                if k > 0:
                    slope = slope * a + k * series[row, k, m]
            out[j, m] = acc + beyond * slope


# -- PODI: the fields blended where they were trained ---------------------------------------
@njit(f"void({f8_1d}, {f8_2d}, {ro_f4_3d}, {f8_2d})", cache=True, nogil=True, fastmath=True)
def blended_surface(buf, coefficients, basis_t, out):
    """out (V, 3) = sum_j w_j A_j c_j: the neighbours' fields where each was trained (mm).
    ``basis_t`` (P, n, 3V): the transposed surface bases (contiguous rows)."""
    flat = out.reshape(out.size)
    flat[:] = 0.0
    for j in range(3):
        w = buf[WEIGHTS + j]
        if w == 0.0:
            continue
        i = int(buf[SAMPLES + j])
        for m in range(coefficients.shape[1]):
            axpy(w * coefficients[j, m], basis_t[i, m], flat)


# -- the transported field ----------------------------------------------------------------
@njit(inline="always")
def rotation(a, b):
    """The smallest rotation taking unit a to unit b (Rodrigues), row-major as a 9-tuple;
    the identity for opposite vectors, which neighbouring samples never are."""
    vx, vy, vz = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
    c = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    if c <= -0.99:
        return 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    f = 1.0 / (1.0 + c)
    return (c + f * vx * vx, f * vx * vy - vz, f * vx * vz + vy,
            f * vy * vx + vz, c + f * vy * vy, f * vy * vz - vx,
            f * vz * vx - vy, f * vz * vy + vx, c + f * vz * vz)  # fmt: skip


@njit(inline="always")
def layer_run(shape, layer, rows, columns):
    """[first, last): the flat nodes of one layer from the rectangle's first node (row
    rows[0], column columns[0]) to its last (rows[1] - 1, columns[1] - 1), the columns
    outside it on the rows between included: one contiguous loop a layer does the rectangle
    faster than a loop a row (measured: 30 against 38 us for the cornea's three contractions;
    the loops' set-up, not the 30 % more nodes, was the cost)."""
    n_rows, n_cols = shape[1], shape[2]
    first = (layer * n_rows + rows[0]) * n_cols + columns[0]
    return first, (layer * n_rows + rows[1] - 1) * n_cols + columns[1]


MODES_A_PASS = 4  # modes summed in one pass over the nodes (the last pass padded with zeros)


@njit(inline="always")
def four_modes(a, c, b):
    """sum_k c_k a_k[b] in single precision (16-bit modes); ``a`` four planes, ``c`` four
    coefficients."""
    return (c[0] * np.float32(a[0][b]) + c[1] * np.float32(a[1][b])
            + c[2] * np.float32(a[2][b]) + c[3] * np.float32(a[3][b]))  # fmt: skip


@njit(inline="always")
def pass_coefficients(mode_scale, i, c, k):
    """The pass from mode k on: its four modes (past the last, the last again) and their
    coefficients times their scales (float32; zero for a repeated mode). Once a pass."""
    n = c.shape[0]
    k1, k2, k3 = min(k + 1, n - 1), min(k + 2, n - 1), min(k + 3, n - 1)
    zero = np.float32(0.0)
    cs = (np.float32(c[k] * mode_scale[i, k]),
          np.float32(c[k1] * mode_scale[i, k1]) if k + 1 < n else zero,
          np.float32(c[k2] * mode_scale[i, k2]) if k + 2 < n else zero,
          np.float32(c[k3] * mode_scale[i, k3]) if k + 3 < n else zero)  # fmt: skip
    return (k, k1, k2, k3), cs


@njit(inline="always")
def pass_planes(node_basis, i, modes, s, e):
    """The four ``modes``' x, y, z planes over the nodes [s, e) of sample i."""
    k0, k1, k2, k3 = modes
    x = (node_basis[i, k0, 0, s:e], node_basis[i, k1, 0, s:e],
         node_basis[i, k2, 0, s:e], node_basis[i, k3, 0, s:e])  # fmt: skip
    y = (node_basis[i, k0, 1, s:e], node_basis[i, k1, 1, s:e],
         node_basis[i, k2, 1, s:e], node_basis[i, k3, 1, s:e])  # fmt: skip
    z = (node_basis[i, k0, 2, s:e], node_basis[i, k1, 2, s:e],
         node_basis[i, k2, 2, s:e], node_basis[i, k3, 2, s:e])  # fmt: skip
    return x, y, z


@njit(inline="always")
def keep_partial_sums(x, y, z, cs, qx, qy, qz, opens):
    """q (=, or += after the first pass) the pass's sums at each node: a pass before the
    last (more than four modes)."""
    if opens:
        for b in range(qx.shape[0]):
            qx[b] = four_modes(x, cs, b)
            qy[b] = four_modes(y, cs, b)
            qz[b] = four_modes(z, cs, b)
    else:
        for b in range(qx.shape[0]):
            qx[b] += four_modes(x, cs, b)
            qy[b] += four_modes(y, cs, b)
            qz[b] += four_modes(z, cs, b)


@njit(inline="always")
def add_rotated_sums(x, y, z, cs, qx, qy, qz, opens, M, gx, gy, gz, first):
    """g (=, or += after the first neighbour) M (the pass's sums, plus the partial sums q
    unless it ``opens``): the last pass. Four loops, so that no branch is inside one."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = M
    if opens and first:
        for b in range(gx.shape[0]):
            px, py, pz = four_modes(x, cs, b), four_modes(y, cs, b), four_modes(z, cs, b)
            gx[b] = m00 * px + m01 * py + m02 * pz
            gy[b] = m10 * px + m11 * py + m12 * pz
            gz[b] = m20 * px + m21 * py + m22 * pz
    elif opens:
        for b in range(gx.shape[0]):
            px, py, pz = four_modes(x, cs, b), four_modes(y, cs, b), four_modes(z, cs, b)
            gx[b] += m00 * px + m01 * py + m02 * pz
            gy[b] += m10 * px + m11 * py + m12 * pz
            gz[b] += m20 * px + m21 * py + m22 * pz
    elif first:
        for b in range(gx.shape[0]):
            px, py, pz = four_modes(x, cs, b), four_modes(y, cs, b), four_modes(z, cs, b)
            px, py, pz = px + qx[b], py + qy[b], pz + qz[b]
            gx[b] = m00 * px + m01 * py + m02 * pz
            gy[b] = m10 * px + m11 * py + m12 * pz
            gz[b] = m20 * px + m21 * py + m22 * pz
    else:
        for b in range(gx.shape[0]):
            px, py, pz = four_modes(x, cs, b), four_modes(y, cs, b), four_modes(z, cs, b)
            px, py, pz = px + qx[b], py + qy[b], pz + qz[b]
            gx[b] += m00 * px + m01 * py + m02 * pz
            gy[b] += m10 * px + m11 * py + m12 * pz
            gz[b] += m20 * px + m21 * py + m22 * pz


@njit(inline="always")
def add_neighbour(node_basis, mode_scale, i, c, M, shape, rows, columns, offset, partial, grid,
                  first):  # fmt: skip
    """grid (3, N) (+)= M u_i(node + offset) over the rectangle of rows [rows[0], rows[1]) and
    columns [columns[0], columns[1]) (its :func:`layer_run`s), u_i = sum_m c_m s_im phi_im
    the field of sample i (modes ``node_basis`` (P, n, 3, N) int16 on its own lattice, times
    their scales ``mode_scale`` (P, n)): a neighbour's field shifted by whole nodes, rotated
    and weighed (M = w R, 9 values), written (``first``) or added.

    Each neighbour's field lies on its own lattice (surface_chart), so the shifts differ by
    whole nodes and the neighbours add on one grid, which a vertex then reads once
    (:func:`read_grid`). One pass over the nodes sums MODES_A_PASS modes and adds their
    rotated sum to the grid, with no field in between; the passes before the last (more
    than four modes) keep partial sums in ``partial`` (3, N) float32 scratch. Measured on
    the cornea demo, three neighbours: 30 us as a contraction and then a rotated sum, 19 us
    in one pass, 15 us with 16-bit modes (README, "The rendered surface"). The branches stay
    outside the node loops: inside, the loops did not vectorise (164 against 55 us a
    surface)."""
    R = (np.float32(M[0]), np.float32(M[1]), np.float32(M[2]), np.float32(M[3]),
         np.float32(M[4]), np.float32(M[5]), np.float32(M[6]), np.float32(M[7]),
         np.float32(M[8]))  # fmt: skip
    n = c.shape[0]
    for k in range(0, n, MODES_A_PASS):
        opens, closes = k == 0, k + MODES_A_PASS >= n
        modes, cs = pass_coefficients(mode_scale, i, c, k)
        for layer in range(shape[0]):
            g0, g1 = layer_run(shape, layer, rows, columns)
            x, y, z = pass_planes(node_basis, i, modes, g0 + offset, g1 + offset)
            qx, qy, qz = partial[0, g0:g1], partial[1, g0:g1], partial[2, g0:g1]
            if not closes:
                keep_partial_sums(x, y, z, cs, qx, qy, qz, opens)
            else:
                add_rotated_sums(x, y, z, cs, qx, qy, qz, opens, R, grid[0, g0:g1],
                                 grid[1, g0:g1], grid[2, g0:g1], first)  # fmt: skip


@njit(inline="always")
def bilinear_at(f, s, columns, w00, w10, w01, w11):
    """f at a point of the cell whose lower-left node is s (unsigned: the index needs no
    negative-index check; weights of its four nodes)."""
    t = s + columns
    one = np.uint64(1)
    return w00 * f[s] + w10 * f[t] + w01 * f[s + one] + w11 * f[t + one]


@njit(inline="always")
def read_grid(grid, charted, charted_node, charted_frac, pa, pb, n_cols, fracs, cells, out):
    """out[v] = grid (3, N) at every charted vertex, bilinear, on the lattice moved by the
    contact's fraction of a cell (pa rows, pb columns): the vertex's place in its cell less
    that fraction, a cell back where it turns negative. Single precision, as the grid: 1e-7
    of the dent.

    Two loops: the first finds each vertex's shifted place and cell (``fracs`` (2, C)
    float32 and ``cells`` (C,) scratch) over contiguous planes without a branch, so it
    vectorises; the second reads. One loop doing both ran 18.7 against 13.3 us for the
    cornea demo's 4,352 charted vertices (its reads are scalar: a gather a value)."""
    one, zero = np.float32(1.0), np.float32(0.0)
    fa0, fb0 = np.float32(pa), np.float32(pb)
    fa_in, fb_in, fa_out, fb_out = charted_frac[0], charted_frac[1], fracs[0], fracs[1]
    n = min(charted.shape[0], fracs.shape[1], cells.shape[0])  # scratch too short: fewer
    for k in range(n):
        fa, fb = fa_in[k] - fa0, fb_in[k] - fb0
        da, db = fa < zero, fb < zero
        fa_out[k] = fa + one if da else fa
        fb_out[k] = fb + one if db else fb
        cells[k] = charted_node[k] - (n_cols if da else 0) - (1 if db else 0)
    columns = np.uint64(n_cols)
    for k in range(n):  # in the order of the cells: the reads stay local
        fa, fb = fa_out[k], fb_out[k]
        s = np.uint64(cells[k])
        ga, gb = one - fa, one - fb
        w00, w10, w01, w11 = ga * gb, fa * gb, ga * fb, fa * fb
        v = charted[k]
        out[v, 0] = bilinear_at(grid[0], s, columns, w00, w10, w01, w11)
        out[v, 1] = bilinear_at(grid[1], s, columns, w00, w10, w01, w11)
        out[v, 2] = bilinear_at(grid[2], s, columns, w00, w10, w01, w11)


@njit(inline="always")
def blended_vertices(buf, coefficients, basis_t, vertices, out):
    """out[v] = sum_j w_j A_j c_j at the listed vertices only (the uncharted ones): a
    neighbour's mode at a time over the vertices, whose sums are independent (a chain of
    sums a vertex waits on each addition: 6.7 against 4 us on the cornea demo)."""
    for v in vertices:
        out[v, 0] = out[v, 1] = out[v, 2] = 0.0
    for j in range(3):
        w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
        if w == 0.0:
            continue
        for m in range(coefficients.shape[1]):
            wc = w * coefficients[j, m]
            a = basis_t[i, m]
            for v in vertices:
                out[v, 0] += wc * a[3 * v]
                out[v, 1] += wc * a[3 * v + 1]
                out[v, 2] += wc * a[3 * v + 2]


@njit(
    "void(float64[::1], float64[:, ::1], Array(int16, 4, 'C', readonly=True), "
    "Array(float64, 2, 'C', readonly=True), "
    "Array(float64, 2, 'C', readonly=True), Array(float64, 2, 'C', readonly=True), "
    "Array(int64, 1, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), "
    "Array(int64, 1, 'C', readonly=True), int64, "
    "Array(int64, 1, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), "
    "Array(float32, 2, 'C', readonly=True), "
    "Array(int64, 1, 'C', readonly=True), Array(float32, 3, 'C', readonly=True), "
    "float32[:, :, ::1], int64[:, ::1], float64[:, ::1], float32[:, ::1], int64[::1], "
    "float64[:, ::1])",
    cache=True,
    nogil=True,
    fastmath=True,
)
def transported_surface(buf, coefficients, node_basis, mode_scale, sample_grid, sample_normals,
                        shape, rows, columns, halo, charted, charted_node, charted_frac, uncharted,
                        basis_t, fields, rectangles, shifts, fracs, cells, out):  # fmt: skip
    """out (V, 3) = sum_j w_j R_j u_j(X + x_j - x) (mm): each neighbour's field carried to
    the contact (shifted in plan view by x_j - x, rotated from its normal to the contact's)
    on the chart's grid, read at the charted vertices; the uncharted keep the blended field.
    x = sum_j w_j x_j in plan view, so the field is as continuous as the weights.

    In nodes (``sample_grid``, the chart's), x = I + p with I whole and p the contact's
    fraction of a cell; neighbour j's field lies on its own lattice, the grid moved by the
    fraction of x_j, so it is read at X - p + (floor(x_j) - I): a whole-node shift of its
    lattice. The neighbours add on one grid (:func:`add_neighbour`) read once at X - p
    (:func:`read_grid`), the same bilinear reads as three reads a vertex.

    ``node_basis`` (P, n, 3, N) int16 and ``mode_scale`` (P, n): the samples' modes on
    their lattices, in units of their scales (surface_chart). ``fields`` (2, 3, N) float32
    scratch: the partial sums of a neighbour's modes beyond MODES_A_PASS, then the
    neighbours' sum (single precision: it is rendered, 1e-7 of a millimetre is far below a
    pixel, and twice the lanes vectorise); ``rectangles`` (3, 5) int64: the node rows and
    columns each neighbour's field is read on, and its shift in flat nodes; ``shifts``
    (3, 12): its weight, the contact's fraction of a cell and w R (filled here: scratch);
    ``fracs`` (2, C) float32 and ``cells`` (C,) int64: each charted vertex's place and
    cell on the moved lattice (scratch, :func:`read_grid`). ``charted_frac`` (2, C)
    float32: the charted vertices' places in their cells, a plane each.
    """
    xa = xb = 0.0
    for j in range(3):
        w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
        xa += w * sample_grid[i, 0]
        xb += w * sample_grid[i, 1]
    ia, ib = np.floor(xa), np.floor(xb)
    pa, pb = xa - ia, xb - ib
    limit = halo - 1  # a corrupt state cannot read past the halo
    normal = buf[NORMAL : NORMAL + 3]
    n_cols = shape[2]
    grid_rows = (rows[0] - 1, rows[1])  # a vertex's read moves a cell back at most
    grid_columns = (columns[0] - 1, columns[1])
    count = 0  # the neighbours with a weight
    for j in range(3):
        w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
        if w == 0.0:
            continue
        # Clamped as integers: with fastmath a NaN compares as anything, but int(NaN) is the
        # least int64 here, which the clamp takes to -limit (a corrupt state).
        oa = min(max(int(np.floor(sample_grid[i, 0]) - ia), -limit), limit)
        ob = min(max(int(np.floor(sample_grid[i, 1]) - ib), -limit), limit)
        r = rectangles[count]
        r[0], r[1] = grid_rows[0] + oa, grid_rows[1] + oa
        r[2], r[3] = grid_columns[0] + ob, grid_columns[1] + ob
        r[4] = oa * n_cols + ob
        c = shifts[count]
        c[0], c[1], c[2] = w, pa, pb
        c[3:12] = rotation(sample_normals[i], normal)
        for q in range(3, 12):
            c[q] *= w
        add_neighbour(node_basis, mode_scale, i, coefficients[j], c[3:12], shape, grid_rows,
                      grid_columns, r[4], fields[0], fields[1], count == 0)  # fmt: skip
        count += 1
    if count == 0:  # no weight (a corrupt state): nothing to read
        fields[1, :, :] = 0.0
    read_grid(fields[1], charted, charted_node, charted_frac, pa, pb, n_cols, fracs, cells, out)
    blended_vertices(buf, coefficients, basis_t, uncharted, out)


# -- the compliance field: PODI plus the linear dent at the contact -------------------------
@njit(inline="always")
def _nearest_in_cell(p, cell, vertices, triangles, starts, ids, best, found, out_weights):
    """(best squared distance, triangle) after the triangles listed in grid ``cell``."""
    for i in range(starts[cell], starts[cell + 1]):
        t = ids[i]
        a, b, c = vertices[triangles[t, 0]], vertices[triangles[t, 1]], vertices[triangles[t, 2]]
        u, v, w, d2 = closest_on_triangle(p, (a[0], a[1], a[2]), (b[0], b[1], b[2]),
                                          (c[0], c[1], c[2]))  # fmt: skip
        if d2 < best:
            best, found = d2, t
            out_weights[0], out_weights[1], out_weights[2] = u, v, w
    return best, found


@njit(
    "int64(float64[::1], Array(float64, 2, 'C', readonly=True), "
    "Array(float64, 2, 'C', readonly=True), Array(float64, 2, 'C', readonly=True), "
    "Array(int64, 2, 'C', readonly=True), Array(float64, 1, 'C', readonly=True), "
    "Array(int64, 1, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), float64[::1])",
    cache=True,
    nogil=True,
)
def locate_on_surface(buf, sample_points, sample_normals, vertices, triangles, grid, starts, ids,
                      out_weights):  # fmt: skip
    """The loadable triangle nearest the contact (its index; its barycentric weights into
    ``out_weights`` (3)). The contact p = sum_j w_j (x_j + h n_j) is rebuilt from the state
    (``kernels.locate``'s map); outside the trained region it is the point as set
    (``buf[CONTACT_POINT]``), where the tool is.

    The triangles are listed by the cells of a uniform grid their boxes meet (``grid``:
    origin (3), cell size, dims (3); ``starts``/``ids``: ``proxy.triangle_grid``'s lists):
    the cells are searched in rings around p's, until the nearest point found is nearer
    than the searched block's nearest face (any nearer point lies in the block). The
    liver's 1,079 triangles searched one by one took 37 us a contact."""
    p0 = p1 = p2 = 0.0
    if buf[TRIANGLE] >= 0.0:  # inside: the located point, x(u, v) + h n(u, v)
        h = buf[HEIGHT]
        for j in range(3):
            w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
            p0 += w * (sample_points[i, 0] + h * sample_normals[i, 0])
            p1 += w * (sample_points[i, 1] + h * sample_normals[i, 1])
            p2 += w * (sample_points[i, 2] + h * sample_normals[i, 2])
    else:  # clamped: the contact point as set, not the border's clamp point (HEIGHT is then
        # the distance to the border): the dent goes under the tool, as the full order's
        # (measured on the liver outside its region: 9-222 % off at the clamp point)
        p0, p1, p2 = buf[CONTACT_POINT], buf[CONTACT_POINT + 1], buf[CONTACT_POINT + 2]
    p = (p0, p1, p2)
    (c0, c1, c2), (n0, n1, n2) = grid_cell(p, grid)
    best, found = np.inf, 0
    for r in range(max(n0, n1, n2)):
        for i0 in range(*ring_span(c0, r, n0)):
            for i1 in range(*ring_span(c1, r, n1)):
                shell = abs(i0 - c0) == r or abs(i1 - c1) == r
                for i2 in range(*ring_row(c2, r, n2, shell)):
                    if box_gap2(p, grid, i0, i1, i2) >= best:
                        continue
                    best, found = _nearest_in_cell(p, (i0 * n1 + i1) * n2 + i2, vertices,
                                                   triangles, starts, ids, best, found,
                                                   out_weights)  # fmt: skip
        if best <= grid_reach(p, grid, (c0, c1, c2), r) ** 2:
            break
    return found


@njit(
    "void(float64[::1], int64, float64[::1], Array(float32, 2, 'C', readonly=True), "
    "Array(int64, 2, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), float64[:, ::1])",
    cache=True,
    nogil=True,
    fastmath=True,
)
def add_linear_dent(buf, triangle, weights, fields, triangle_rows, sample_rows, out):
    """out (V, 3) += d (phi(x) - sum_j w_j phi_j): the tool's linear field at the contact
    (``weights`` on the loadable ``triangle``'s vertices' rows) minus its blend at the three
    neighbours, times the last depth d (mm). Zero at a sample."""
    flat = out.reshape(out.size)
    d = buf[DEPTH]
    for k in range(3):
        if weights[k] != 0.0:
            axpy(d * weights[k], fields[triangle_rows[triangle, k]], flat)
    for j in range(3):
        w = buf[WEIGHTS + j]
        if w != 0.0:
            axpy(-d * w, fields[sample_rows[int(buf[SAMPLES + j])]], flat)
