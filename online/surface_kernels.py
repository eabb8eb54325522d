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
from hapticrom.online.node_blocks import (
    LANES,
    MODES_A_BLOCK,
    ROTATION,
    block_modes,
    block_rotate,
    block_store,
    node_read,
)
from hapticrom.online.vector_tiles import tile, tile_zero


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


@njit(cache=True)
def terms_width(modes):
    """The columns of a neighbour's terms (``transported_surface``): its rotation, then its
    modes' coefficients padded to whole blocks of MODES_A_BLOCK."""
    return ROTATION + -(-modes // MODES_A_BLOCK) * MODES_A_BLOCK


@njit(inline="always")
def neighbour_terms(buf, coefficients, mode_scale, sample_grid, sample_normals, ia, ib, n_cols,
                    limit, neighbours, terms):  # fmt: skip
    """The neighbours with a weight, one slot each (their number is returned):
    ``neighbours[slot]`` = (sample i, its shift in flat nodes), the whole-node offset of its
    lattice clamped to ``limit`` nodes a way (with fastmath a NaN compares as anything, but
    int(NaN) is the least int64, which the clamp takes to -limit: a corrupt state reads
    inside the halo); ``terms[slot]`` = w R (row-major: the rotation from the sample's normal
    to the contact's, weighed), then c_m s_im, the coefficients times the modes' scales,
    zero past the last mode (float32: see :mod:`hapticrom.online.node_blocks`)."""
    normal = buf[NORMAL : NORMAL + 3]
    count = 0
    for j in range(3):
        w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
        if w == 0.0:
            continue
        oa = min(max(int(np.floor(sample_grid[i, 0]) - ia), -limit), limit)
        ob = min(max(int(np.floor(sample_grid[i, 1]) - ib), -limit), limit)
        neighbours[count, 0], neighbours[count, 1] = i, oa * n_cols + ob
        t = terms[count]
        R = rotation(sample_normals[i], normal)
        for q in range(ROTATION):
            t[q] = w * R[q]
        t[ROTATION:] = 0.0
        for m in range(min(coefficients.shape[1], mode_scale.shape[1], terms.shape[1] - ROTATION)):
            t[ROTATION + m] = coefficients[j, m] * mode_scale[i, m]
        count += 1
    return count


@njit(inline="always")
def add_slot(P, acc, node_basis, i, shift, terms, j, g):
    """acc (=, for slot 0; else +=) the rotated sums of slot j's modes (sample i, moved by
    ``shift`` flat nodes) at the block's nodes from g, in the tiles (``P``: scratch)."""
    for k in range(0, node_basis.shape[1], MODES_A_BLOCK):
        block_modes(P, node_basis, i, terms, j, k, g + shift, k == 0)
    block_rotate(acc, P, terms, j, j == 0)


@njit(inline="always")
def sum_blocks(node_basis, blocks, neighbours, terms, count, reach, grid):
    """grid[g : g + LANES] = sum over the ``count`` slots of R_j sum_m c_jm phi_jm at the
    block's nodes moved by the slot's shift, interleaved (x, y, z, 0) a node, for every
    block g of the chart (``blocks``): the modes' sums and the rotated sum in registers,
    each block written once (:mod:`hapticrom.online.node_blocks`). A block whose nodes, moved
    by up to ``reach`` flat nodes, would leave the modes or the grid is skipped (a chart's
    blocks never are: ``surface_chart.node_blocks``).

    The slots' samples and shifts are read into locals before the loop, one call a slot:
    read from ``neighbours`` in the loop, LLVM reloads them and recomputes the modes'
    addresses every block (it cannot tell the grid's stores from them): 8.45 against 7.05
    us on the cornea demo."""
    P, acc = tile(grid), tile(grid)
    last = min(node_basis.shape[3], grid.shape[0]) - LANES - reach
    i0 = s0 = i1 = s1 = i2 = s2 = 0  # count is 0 where the scratch is too small
    if count > 0:
        i0, s0 = neighbours[0, 0], neighbours[0, 1]
    if count > 1:
        i1, s1 = neighbours[1, 0], neighbours[1, 1]
    if count > 2:
        i2, s2 = neighbours[2, 0], neighbours[2, 1]
    for b in range(blocks.shape[0]):
        g = blocks[b]
        if g < reach or g > last:
            continue
        if count > 0:
            add_slot(P, acc, node_basis, i0, s0, terms, 0, g)
        if count > 1:
            add_slot(P, acc, node_basis, i1, s1, terms, 1, g)
        if count > 2:
            add_slot(P, acc, node_basis, i2, s2, terms, 2, g)
        if count == 0:  # no weight (a corrupt state): a zero field
            tile_zero(acc)
        block_store(grid, g, acc)


@njit(inline="always")
def read_weights(charted_node, charted_frac, pa, pb, n_cols, weights, cells):
    """Each charted vertex's cell on the lattice moved by the contact's fraction of a cell
    (pa rows, pb columns) and its four bilinear weights there (``weights`` (4, C) float32
    scratch: w00, w10, w01, w11; ``cells`` (C,)): its place in its cell less that fraction,
    a cell back where that turns negative. Branch-free over contiguous planes, so it
    vectorises (one loop that also read: 18.7 against 13.3 us, stop 40). Returns the number
    of vertices (fewer where the scratch is short)."""
    one, zero = np.float32(1.0), np.float32(0.0)
    fa0, fb0 = np.float32(pa), np.float32(pb)
    fa_in, fb_in = charted_frac[0], charted_frac[1]
    w00, w10, w01, w11 = weights[0], weights[1], weights[2], weights[3]
    n = min(charted_node.shape[0], charted_frac.shape[1], weights.shape[1], cells.shape[0])
    for k in range(n):
        fa, fb = fa_in[k] - fa0, fb_in[k] - fb0
        da, db = fa < zero, fb < zero
        fa = fa + one if da else fa
        fb = fb + one if db else fb
        ga, gb = one - fa, one - fb
        w00[k], w10[k], w01[k], w11[k] = ga * gb, fa * gb, ga * fb, fa * fb
        cells[k] = charted_node[k] - (n_cols if da else 0) - (1 if db else 0)
    return n


@njit(inline="always")
def read_nodes(grid, charted, n, n_cols, weights, cells, out):
    """out[v] = the grid at the first n charted vertices, bilinear in their cells
    (:func:`read_weights`), in the order of the cells (the reads stay local). Single
    precision, as the grid: 1e-7 of the dent. One intrinsic a vertex reads and writes it
    (node_blocks.node_read: 10.7 us for the cornea demo's 4,352 as twelve scalar loads, 5.6
    us as four vector loads and one widening, min in one harness)."""
    w00, w10, w01, w11 = weights[0], weights[1], weights[2], weights[3]
    for k in range(n):
        node_read(out, charted[k], grid, cells[k], n_cols, w00[k], w10[k], w01[k], w11[k])


@njit(inline="always")
def blended_uncharted(buf, coefficients, basis, vertices, total, out):
    """out[v] = sum_j w_j A_j c_j at the uncharted ``vertices`` (U,): the neighbours' modes
    there (``basis`` (P, n, 3U), contiguous) summed as vectors into ``total`` (3U,) float64
    scratch, then written to the vertices (from the whole basis, a mode's values scattered
    over 3V: 3 against 1 us on the cornea demo). Scratch too short: the vertices it holds."""
    u = min(vertices.shape[0], total.shape[0] // 3, basis.shape[2] // 3)
    values = total[: 3 * u]
    values[:] = 0.0
    for j in range(3):
        w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
        if w == 0.0:
            continue
        for m in range(coefficients.shape[1]):
            wc = w * coefficients[j, m]
            a = basis[i, m]
            for q in range(3 * u):
                values[q] += wc * a[q]
    for k in range(u):
        v = vertices[k]
        out[v, 0], out[v, 1], out[v, 2] = values[3 * k], values[3 * k + 1], values[3 * k + 2]


@njit(
    "void(float64[::1], float64[:, ::1], Array(int16, 4, 'C', readonly=True), "
    "Array(float64, 2, 'C', readonly=True), "
    "Array(float64, 2, 'C', readonly=True), Array(float64, 2, 'C', readonly=True), "
    "Array(int64, 1, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), int64, "
    "Array(int64, 1, 'C', readonly=True), Array(int64, 1, 'C', readonly=True), "
    "Array(float32, 2, 'C', readonly=True), "
    "Array(int64, 1, 'C', readonly=True), Array(float32, 3, 'C', readonly=True), "
    "float32[:, ::1], int64[:, ::1], float32[:, ::1], float32[:, ::1], int64[::1], "
    "float64[::1], float64[:, ::1])",
    cache=True,
    nogil=True,
    fastmath=True,
)
def transported_surface(buf, coefficients, node_basis, mode_scale, sample_grid, sample_normals,
                        shape, blocks, halo, charted, charted_node, charted_frac, uncharted,
                        uncharted_basis, grid, neighbours, terms, weights, cells, total,
                        out):  # fmt: skip
    """out (V, 3) = sum_j w_j R_j u_j(X + x_j - x) (mm): each neighbour's field carried to
    the contact (shifted in plan view by x_j - x, rotated from its normal to the contact's)
    on the chart's grid, read at the charted vertices; the uncharted keep the blended field
    (:func:`blended_uncharted`: ``uncharted_basis`` (P, n, 3U), ``total`` (3U,) scratch).
    x = sum_j w_j x_j in plan view, so the field is as continuous as the weights.

    In nodes (``sample_grid``, the chart's), x = I + p with I whole and p the contact's
    fraction of a cell; neighbour j's field lies on its own lattice, the grid moved by the
    fraction of x_j, so it is read at X - p + (floor(x_j) - I): a whole-node shift of its
    lattice. The neighbours add on one grid (:func:`sum_blocks`, over the chart's
    ``blocks`` of the nodes the vertices read) read once at X - p (:func:`read_nodes`), the
    same bilinear reads as three reads a vertex.

    ``node_basis`` (P, n, 3, N) int16 and ``mode_scale`` (P, n): the samples' modes on
    their lattices, in units of their scales (surface_chart). Scratch: ``grid`` (N, 4)
    float32, the neighbours' sum interleaved a node (single precision: it is rendered, 1e-7
    of a millimetre is far below a pixel, and twice the lanes vectorise); ``neighbours``
    (3, 2) int64 and ``terms`` (3, terms_width(n)) float32, the neighbours' slots
    (:func:`neighbour_terms`); ``weights`` (4, C) float32 and ``cells`` (C,) int64, each
    charted vertex's read (:func:`read_weights`). ``charted_frac`` (2, C) float32: the
    charted vertices' places in their cells, a plane each. Scratch of the wrong size renders
    the charted vertices as zero (the terms, the grid) or fewer of them (the reads, the
    uncharted sum), and reads and writes nothing outside it.
    """
    xa = xb = 0.0
    for j in range(3):
        w, i = buf[WEIGHTS + j], int(buf[SAMPLES + j])
        xa += w * sample_grid[i, 0]
        xb += w * sample_grid[i, 1]
    ia, ib = np.floor(xa), np.floor(xb)
    pa, pb = xa - ia, xb - ib
    limit = halo - 1  # a corrupt state cannot read past the halo
    n_cols = shape[2]
    count = 0
    modes = node_basis.shape[1]
    narrow = modes == 0 or terms.shape[1] < terms_width(modes) or terms.shape[0] < 3
    if not (narrow or neighbours.shape[0] < 3 or neighbours.shape[1] < 2):
        count = neighbour_terms(buf, coefficients, mode_scale, sample_grid, sample_normals, ia,
                                ib, n_cols, limit, neighbours, terms)  # fmt: skip
    rows = grid.shape[1] == 4 and weights.shape[0] == 4 and out.shape[1] == 3
    if grid.shape[0] >= node_basis.shape[3] and rows:
        sum_blocks(node_basis, blocks, neighbours, terms, count, limit * (n_cols + 1), grid)
        n = read_weights(charted_node, charted_frac, pa, pb, n_cols, weights, cells)
        read_nodes(grid, charted, min(n, charted.shape[0]), n_cols, weights, cells, out)
    else:  # the grid does not hold the nodes (x, y, z, 0) a row, or the reads their weights
        for v in charted:
            out[v, 0] = out[v, 1] = out[v, 2] = 0.0
    blended_uncharted(buf, coefficients, uncharted_basis, uncharted, total, out)


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
