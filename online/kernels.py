"""numba kernels of the online runtime: ``@njit`` functions writing into caller-owned buffers.

Start here: the default response of an artifact with POD-ANM series steps with
:func:`step_displacement_anm` (tool displacement in, force out) and
:func:`step_force_anm` (force in, displacement out), on the series tabulated per section
at load (:func:`tabulate_series`); the stored full-order curves
(``response="curves"``) with :func:`step_displacement_curves` and
:func:`step_force_curves`. :func:`prepare_contact` is ``set_contact`` in one call,
:func:`place_scalpel` the scalpel's placement, :func:`surface_grassmann` the Grassmann
surface (the others: :mod:`hapticrom.online.surface_kernels`).

Everything a step reads and writes is one float64 array per simulator, the
*state buffer* (its layout: the constants below, ``NORMAL`` ... ``CURVE``); what the
contact and the scalpel's placement read of the model is one read-only array, the
*table* (:func:`contact_table`, :func:`scalpel_table`). A kernel call costs per array
passed: packing is what keeps a step near a microsecond.

Every kernel called from Python has an explicit signature, so it is compiled (or
loaded from the on-disk cache, ``cache=True``) when this module is imported:
nothing compiles inside the haptic loop. None allocates except
:func:`prepare_grassmann` (small eigendecompositions, run before a Grassmann
surface only). Units: mm, N, N/mm.

Status codes returned by the steps (nothing is written unless OK): OK 0,
NOT_FINITE 1 an input is NaN or infinite, BEYOND_LIMIT 2 an input is absurdly large
(beyond the simulator's limit), WRONG_SHAPE 3 an input has not 3 elements (read no
further than its end), DISPLACEMENT_LIMIT 4 a force step's displacement would pass
the displacement limit (``buf[MAX_DEPTH]``), NO_CONTACT_POINT 10 no contact point was
set yet (``buf[CONTACTS]`` 0). The contact and placement kernels return
a region vertex (>= 0), NO_VERTEX (-1), or minus a status (< -1, nothing written).

The model's arrays are read only here: every parameter a kernel only reads accepts a
read-only array (``flags.writeable`` False), so a shared model may be frozen. A step input
may be any 1-D float64 array (any strides, read-only or not).
Flags (``buf[FLAGS]``, a bit field): 1 depth beyond the trained range
(extrapolated linearly; for the curves, beyond ``buf[SOLVED_DEPTH]``), 2 no contact
(the tool pulls away: zero force), 4 contact point outside the trained region (clamped
to its boundary).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from hapticrom.shared.lattice import lattice_subdivisions

FLAG_BEYOND_DEPTH = 1
FLAG_NO_CONTACT = 2
FLAG_OUTSIDE_REGION = 4

f8_1d = "float64[::1]"
f8_2d = "float64[:, ::1]"
f8_3d = "float64[:, :, ::1]"
# Read only (a mutable array converts to these at the call).
ro_f8_1d = "Array(float64, 1, 'C', readonly=True)"
ro_f8_3d = "Array(float64, 3, 'C', readonly=True)"
ro_f8_4d = "Array(float64, 4, 'C', readonly=True)"
ro_f4_3d = "Array(float32, 3, 'C', readonly=True)"
ro_i8_1d = "Array(int64, 1, 'C', readonly=True)"
vec = "Array(float64, 1, 'A', readonly=True)"  # a caller's vector: any 1-D float64 array

OK, NOT_FINITE, BEYOND_LIMIT, WRONG_SHAPE, DISPLACEMENT_LIMIT = 0, 1, 2, 3, 4
NO_CONTACT_POINT = 10  # a step before any contact point was set
# The scalpel's placement (besides WRONG_SHAPE, the position's), and a contact point's.
BLADE_SHAPE, POSITION_NOT_FINITE, BLADE_NOT_FINITE, OFF_ORGAN, BLADE_ALONG_NORMAL = 5, 6, 7, 8, 9
NO_VERTEX = -1

# -- the state buffer: one float64 array per simulator ------------------------------------
NORMAL = 0  # (3) outward unit surface normal at the contact
FORCE = 3  # (3) force on the tool (N): a displacement step's output
DISPLACEMENT = 6  # (3) tool displacement (mm): a force step's output
DEPTH = 9  # indentation depth (mm) of the last step
FLAGS = 10  # the last step's FLAG_* bits
STEP = 11  # spacing of the force curves' depth knots (mm)
MAX_DISPLACEMENT = 12  # a displacement step's input limit (mm)
MAX_FORCE = 13  # a force step's input limit (N)
KNOTS = 14  # K, knots of the force curves
ANM_BASE = 15  # where the POD-ANM blocks start (below)
ANM_N1 = 16  # N1, coefficients per series; 0: the curves response (no blocks)
ANM_SMAX = 17  # the most sections of a sample
ANM_SLOPE = 18  # the blended dF/ddepth at the last depth (N/mm)
ANM_BEYOND = 19  # 1 if a neighbour's last section ends before the last depth
MAX_DEPTH = 20  # the largest depth a force step may return (mm): see step_force_*
TRIANGLE = 21  # the sample triangle holding the contact (its index, as a float)
HEIGHT = 22  # the contact's height (mm) above that triangle, along the blended normal
WEIGHTS = 23  # (3) the contact's barycentric weights in the sample triangle
FRAME = 26  # (6) the scalpel's unit blade, the unit normal of the blade's plane
PLACED = 32  # (2) the scalpel's surface vertex and region vertex (or -1), as floats
PLACEMENT = 34  # (6) the last placement's position and blade (NaN: none since)
CONTACTS = 40  # contacts prepared so far (a count: what depends on the contact is stale)
SAMPLES = 41  # (3) the contact's three samples (indices, as floats) of those weights
LOCATE_SCRATCH = 44  # (3) locate's (u, v, h) of the triangle being tried
FRICTION = 47  # (3) step_position's Coulomb friction: static and dynamic coefficients (0 0:
# frictionless), the tangential stiffness as a multiple of the normal one (see proxy)
SLIPPING = 50  # 1 if the last step_position slid with friction (0: stuck, or frictionless)
SECTION_KNOTS = 51  # POD-ANM: the knots of each section's table (below)
FORCE_WEIGHTS = 52  # (3) the weights the force curves are blended with: w_i k(x) / k_i
SOLVED_DEPTH = 55  # the contact's solved depth: its neighbours' (weight > 0) smallest (mm)
CONTACT_POINT = 56  # (3) the contact point as set (mm; clamped or not)
CURVE = 59  # (K) the contact's force curve (N), then (K) its slopes (N/mm)
# POD-ANM (response "anm"), at buf[ANM_BASE] = CURVE + 2 K: three neighbour blocks, each a
# header then SMAX section records (the neighbour's sections, artifact order).
BLOCK_WEIGHT, BLOCK_COUNT, BLOCK_SAMPLE, BLOCK_RECORDS = 0, 1, 2, 3
# header: barycentric weight, section count, the sample whose records the block holds (-1:
# none yet; set_contact copies a sample's records only when they are not there already).
# A section record is the section's series tabulated at buf[SECTION_KNOTS] = Q depths,
# uniform from its start to its end: cubic Hermite interpolation of force and path parameter
# a in depth then costs a few multiplications a step, where solving depth(a) = depth by
# Newton on the series costs three iterations per neighbour (0.78 us a step; tabulated: see
# README). The model chooses Q at load (`tabulate_sections`, `TABULATION_TOLERANCE`).
# Record: [depth at a = 0, depth at a_max, force at a_max, dF/ddepth at a_max, a_max,
# knot spacing, its inverse, then at the knots: force (N), dF/ddepth, a, da/ddepth (Q each)].
REC_DEPTH0, REC_DEPTH_END, REC_FORCE_END, REC_SLOPE_END, REC_AMAX = 0, 1, 2, 3, 4
REC_SPACING, REC_INVERSE_SPACING, REC_FORCE = 5, 6, 7
TABULATION_TOLERANCE = 1e-11  # of the largest force, and of the largest a_max: see model.py
MAX_TABLE_FLOATS = 1 << 23  # 64 MB of section records at most, beyond 17 knots a section


def record_stride(knots: int) -> int:
    """Floats per section record of ``knots`` knots."""
    return REC_FORCE + 4 * knots


def anm_block_size(knots: int, smax: int) -> int:
    """Floats per neighbour block."""
    return BLOCK_RECORDS + smax * record_stride(knots)


def buffer_size(knots: int, n1: int = 0, smax: int = 0, section_knots: int = 0) -> int:
    """Length of the state buffer of a model with ``knots`` depths (and POD-ANM series of
    N1 coefficients, at most ``smax`` sections a sample, tabulated at ``section_knots``)."""
    return CURVE + 2 * knots + (3 * anm_block_size(section_knots, smax) if n1 else 0)


def tabulate_series(depth, force, a_max, budget: int = MAX_TABLE_FLOATS
                    ) -> tuple[np.ndarray, int, tuple[float, float]]:  # fmt: skip
    """(section records (Z, record_stride(Q)), Q, (force error N, a error)) of POD-ANM
    series ``depth``, ``force`` (Z, N1) on [0, ``a_max``]: the fewest knots Q (17, 33, ...,
    1025) whose interpolant is within TABULATION_TOLERANCE of the largest force and a_max
    (the cubic Hermite error falls as Q^-4). No more knots than ``budget`` floats of
    records allow (a crafted file's rough series cannot make the tables huge): the knots
    reached are kept, and their error returned, if the tolerance is not met."""
    depth, force, a_max = (np.array(x, dtype=np.float64) for x in (depth, force, a_max))
    ends = np.array([horner(c, 0, len(c), a) for c, a in zip(depth, a_max, strict=True)])
    flat = np.flatnonzero(~(ends > depth[:, 0]))
    if flat.size:
        raise ValueError(f"POD-ANM section {flat[0]} has no depth range: it starts at "
                         f"{depth[flat[0], 0]!r} mm and ends at {ends[flat[0]]!r} mm")  # fmt: skip
    for q in (17, 33, 65, 129, 257, 513, 1025):
        if q > 17 and len(a_max) * record_stride(q) > budget:
            break
        records = np.zeros((len(a_max), record_stride(q)))
        tabulate_sections(depth, force, a_max, records)
        errors = tabulation_error(depth, force, a_max, records)
        scale = np.abs(records[:, REC_FORCE : REC_FORCE + q]).max(initial=0.0)
        if errors[0] <= TABULATION_TOLERANCE * scale and (
            errors[1] <= TABULATION_TOLERANCE * a_max.max(initial=0.0)
        ):
            break
    return records, (records.shape[1] - REC_FORCE) // 4, errors


# -- the table: what set_contact and the scalpel read of the model ---------------------------
# One read-only float64 array per simulator (indices stored as floats: exact), a header
T_SAMPLES, T_KNOTS, T_TRIANGLES, T_STRIDE, T_SECTIONS, T_SCALPEL, T_VERTICES, T_EDGES = range(8)
T_LATTICE = 8
T_OUTSIDE = 9  # where the outside part starts (0: none): see outside_part
T_HEADER = 10
GRID_ORIGIN, GRID_CELL, GRID_DIMS, GRID_STARTS = 0, 3, 4, 7  # a point_grid's parts
# (P samples, K knots, S sample triangles, the section records' stride or 0, Z sections,
# where the scalpel's part starts, V surface vertices or 0 without it, E border edges,
# m the tool stiffness lattice's subdivisions or 0 without it, where the outside part starts
# or 0 without it),
# then the contact's part: sample points (P, 3), sample normals (P, 3), forces (P, K),
# slopes (P, K), solved depths (P), sample triangles (S, 3), their planes (S, PLANE), the
# triangulation's border edges (E, 3), the tool's stiffness on each triangle's lattice (S, L;
# L = 0 if m = 0), POD-ANM section records (Z, stride) and section offsets (P + 1, with the
# records); then the scalpel's part: reach, region reach, the surface vertices' point_grid,
# the vertices (V, 3), their normals (V, 3), their region nodes (V; -1 outside the region).
# Row-major.


def border_edges(triangles) -> np.ndarray:
    """The edges of exactly one triangle (the triangulation's border), (E, 3): the edge's
    two samples as ordered in its triangle, then the triangle's third sample."""
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    edges = np.vstack([t[:, [0, 1, 2]], t[:, [1, 2, 0]], t[:, [2, 0, 1]]])
    _, inverse, counts = np.unique(
        np.sort(edges[:, :2], axis=1), axis=0, return_inverse=True, return_counts=True
    )
    return edges[counts[inverse.ravel()] == 1]


PLANE = 14  # floats per sample triangle's plane: corner a, unit normal, g1, g2, longest edge^2,
PLANE_FLOOR = 13  # ... and its floor: the lowest height (mm, along the normals) a contact has in it
FACING = math.cos(math.radians(75.0))  # a surface vertex faces a triangle's way (or away) beyond
FLOOR_MARGIN = 0.25  # a floor's place from the opposite face to the triangle's own (face_floors)
FLOOR_RAYS = 4  # face_floors' rays per sample triangle: (4 + 1)(4 + 2) / 2 = 15
FLOOR_WORK = 10_000_000  # face_floors' projections and ray-face tests at most (2-3 s at worst)
FLOOR_SCAN = 50_000_000  # ... and the box tests that find them (numpy, about as long)


def triangle_planes(points, triangles, floors=None) -> np.ndarray:
    """Per sample triangle (S, PLANE): its first corner x_a (3), unit normal (3), the dual
    vectors g1, g2 (3 each; the flat coordinates of p are u = g1 (p - x_a), v = g2 (p -
    x_a)), its longest edge squared, so that :func:`locate`'s first pass costs a few
    dot products per triangle, and its floor: ``floors`` (S,) mm (:func:`face_floors`),
    never below minus the longest edge (the bound without them)."""
    x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    xa, e1, e2 = x[t[:, 0]], x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]
    n = np.cross(e1, e2)
    area2 = np.einsum("sx,sx->s", n, n)[:, None]
    reach2 = np.max([np.sum(e1 * e1, 1), np.sum(e2 * e2, 1), np.sum((e2 - e1) ** 2, 1)], axis=0)
    floor = -np.sqrt(reach2)
    if floors is not None:
        floor = np.maximum(np.reshape(np.asarray(floors, dtype=np.float64), len(t)), floor)
    return np.column_stack(
        [xa, n / np.sqrt(area2), np.cross(e2, n) / area2, np.cross(n, e1) / area2, reach2, floor]
    )


def face_floors(points, normals, triangles, vertices, vertex_normals, faces) -> np.ndarray:
    """(S,) mm: each sample triangle's floor, the lowest height along its blended normals
    at which :func:`locate` puts a contact in it.

    Why: a triangle of samples on one face of an organ also holds, far beneath it, points
    of the opposite face (a liver's lower face under its upper one, a cornea's posterior
    under its anterior): without a floor a tool on that face got the other face's
    response. The floor lies a quarter of the way from the opposite face's highest point
    under the triangle to its own face's lowest point above that: the opposite face and
    the tissue just above it are not in the triangle, the rest of the tissue is. Not
    halfway: a contact point given a little inside a thin organ (a tool's tip pressed into
    a 0.55 mm cornea, a chord across its samples) must stay in.

    The faces under the triangle: its surface vertices there (normal within 75 degrees of
    the blended normal: its own face; over 105: the opposite one) and, along rays from 15
    points of the triangle down its blended normals, the first face turned away (where the
    ray leaves the organ) and a face turned its way crossed before it (a concave stretch
    below the chord), since on a mesh coarser than the samples no vertex may lie under a
    small triangle. Only what lies above the opposite face counts as its own face (a
    deeper layer of the organ does not). No opposite face: minus infinity (the longest edge
    bounds it, :func:`triangle_planes`). ``vertices``, ``vertex_normals`` (V, 3): the
    organ's surface vertices and their outward unit normals; ``faces`` (F, 3 or 4): its
    outward faces, vertex indices. Refused (ValueError) if the triangles' boxes hold more
    than FLOOR_WORK projections and ray tests."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if faces.shape[1] == 4:  # quadrilaterals: two triangles each
        faces = np.vstack([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
    faces = np.ascontiguousarray(faces)
    flat = [np.ravel(np.asarray(a, dtype=np.float64)) for a in (points, normals, triangles)]
    planes = triangle_planes(points, triangles)
    # Each triangle looks only at what lies in its box: its corners +- its longest edge (no
    # point farther from it is in it, :func:`project_on_triangle`), within a budget.
    corners = np.asarray(points, dtype=np.float64)[np.asarray(triangles, dtype=np.int64)]
    reach = np.sqrt(planes[:, 12])[:, None]
    lo, hi = corners.min(axis=1) - reach, corners.max(axis=1) + reach
    near = in_boxes(v, v, lo, hi, "surface vertices")
    corners = v[faces] if len(faces) else np.zeros((0, 3, 3))
    crossed = in_boxes(corners.min(axis=1), corners.max(axis=1), lo, hi, "surface faces")
    work = len(near[1]) + _rays(FLOOR_RAYS) * len(crossed[1])
    if work > FLOOR_WORK:
        raise ValueError(
            f"the sample triangles' floors would take {work:,} projections and ray tests, more "
            f"than {FLOOR_WORK:,} ({len(near[1]):,} surface vertices and {len(crossed[1]):,} "
            "faces in the triangles' boxes: overlapping or oversized triangles)"
        )
    heights = np.zeros((len(triangles), 2))  # the own face's lowest, the opposite's highest
    heights[:, 0], heights[:, 1] = 0.0, -np.inf  # the corners are on the own face
    _ray_heights(*flat, v, faces, *crossed, FLOOR_RAYS, heights)
    scratch = np.zeros((len(near[1]), 2))
    unit = np.ascontiguousarray(vertex_normals, dtype=np.float64)
    _vertex_heights(*flat, np.ravel(planes), v, unit, *near, scratch, heights)
    facing, away = heights[:, 0], heights[:, 1]
    floors = np.full(len(facing), -np.inf)
    below = np.isfinite(away) & (away < facing)
    floors[below] = away[below] + FLOOR_MARGIN * (facing[below] - away[below])
    folded = np.isfinite(away) & (away >= facing)  # a face turned away above it: a fold
    floors[folded] = facing[folded]
    return floors


def _rays(m: int) -> int:
    """The rays :func:`_ray_heights` casts per triangle: its points (i/m, j/m)."""
    return (m + 1) * (m + 2) // 2


def in_boxes(item_lo, item_hi, lo, hi, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(starts (S + 1,), ids): for each box [lo[t], hi[t]] (S, 3), the items whose own box
    [item_lo, item_hi] (N, 3) meets it (CSR). The items sorted by their lower x bound, each
    box scans those whose bound falls within its x range widened by the widest item, with
    numpy; if that scan (counted first, with a thousand a box for its own overhead) would
    pass FLOOR_SCAN, ValueError (naming ``what``, plural) before any is done."""
    item_lo, item_hi = np.asarray(item_lo, dtype=np.float64), np.asarray(item_hi, dtype=np.float64)
    order = np.argsort(item_lo[:, 0], kind="stable")
    keys = item_lo[order, 0]
    width = float(np.max(item_hi[:, 0] - item_lo[:, 0])) if len(keys) else 0.0
    first = np.searchsorted(keys, lo[:, 0] - width, side="left")
    last = np.searchsorted(keys, hi[:, 0], side="right")
    scanned = int(np.sum(last - first)) + 1000 * len(lo)
    if scanned > FLOOR_SCAN:
        raise ValueError(
            f"the sample triangles' boxes would scan {scanned:,} {what}, more than the "
            f"{FLOOR_SCAN:,} the triangles' floors may (overlapping or oversized triangles)"
        )
    ids, starts = [], [0]
    for t in range(len(lo)):
        cand = order[first[t] : last[t]]
        meets = np.all((item_lo[cand] <= hi[t]) & (item_hi[cand] >= lo[t]), axis=1)
        ids.append(cand[meets])
        starts.append(starts[-1] + int(meets.sum()))
    ids = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
    return np.asarray(starts, dtype=np.int64), ids.astype(np.int64)


@njit(inline="always")
def blended_normal(normals, triangles, t, u, v):
    """N(u, v) over sample triangle t: the blend of its samples' normals (not unit)."""
    a, b, c = int(triangles[3 * t]), int(triangles[3 * t + 1]), int(triangles[3 * t + 2])
    na = vertex(normals, a)
    return combine(na, u, minus(vertex(normals, b), na), v, minus(vertex(normals, c), na))


@njit(cache=True, nogil=True)
def _vertex_heights(points, normals, triangles, planes, vertices, vertex_normals, starts, ids,
                    scratch, heights):  # fmt: skip
    """heights (S, 2), lowered (own face) and raised (opposite face) by the surface vertices
    each sample triangle holds (:func:`project_on_triangle`, as :func:`locate`; triangle t
    looks at ids[starts[t]:starts[t + 1]], :func:`in_boxes`): first the opposite face's
    highest, then the own face's lowest above it. ``scratch`` (len(ids), 2): each
    candidate's height and side (1 own, -1 opposite, 0 neither or not in the triangle)."""
    uvh = np.zeros(3)
    for t in range(triangles.shape[0] // 3):
        for k in range(starts[t], starts[t + 1]):
            scratch[k, 1] = 0.0
            i = ids[k]
            if not project_on_triangle(vertices[i], points, normals, triangles, planes, t,
                                       np.inf, uvh):  # fmt: skip
                continue
            u, v, h = uvh[0], uvh[1], uvh[2]
            if u < -1e-12 or v < -1e-12 or u + v > 1.0 + 1e-12:
                continue
            n = blended_normal(normals, triangles, t, u, v)
            turn = dot(n, vertex_normals[i]) / math.sqrt(dot(n, n))
            scratch[k, 0] = h
            if turn >= FACING:
                scratch[k, 1] = 1.0
            elif turn <= -FACING:
                scratch[k, 1] = -1.0
                heights[t, 1] = max(heights[t, 1], h)
        for k in range(starts[t], starts[t + 1]):
            if scratch[k, 1] > 0.0 and scratch[k, 0] > heights[t, 1]:
                heights[t, 0] = min(heights[t, 0], scratch[k, 0])


@njit(cache=True, nogil=True)
def _ray_heights(points, normals, triangles, vertices, faces, starts, ids, m, heights):
    """heights (S, 2), lowered (own face) and raised (opposite face) along rays from the
    points (i/m, j/m) of each sample triangle down its blended normal: the first face
    turned away (where the ray leaves the organ) and a face turned its way crossed before
    it (Moller-Trumbore; heights in :func:`project_on_triangle`'s units), of the faces
    ids[starts[t]:starts[t + 1]] (:func:`in_boxes`)."""
    for t in range(triangles.shape[0] // 3):
        a, b, c = int(triangles[3 * t]), int(triangles[3 * t + 1]), int(triangles[3 * t + 2])
        xa, xb, xc = vertex(points, a), vertex(points, b), vertex(points, c)
        for i in range(m + 1):
            for j in range(m + 1 - i):
                u, v = i / m, j / m
                x = combine(xa, u, minus(xb, xa), v, minus(xc, xa))
                n = blended_normal(normals, triangles, t, u, v)
                leave, enter = _first_crossings(x, n, vertices, faces,
                                                ids[starts[t] : starts[t + 1]])  # fmt: skip
                if leave < np.inf:
                    heights[t, 1] = max(heights[t, 1], -leave)
                if enter < leave:
                    heights[t, 0] = min(heights[t, 0], -enter)


@njit(inline="always")
def _first_crossings(x, n, vertices, faces, candidates):
    """(leave, enter): the smallest s > 0 at which x - s n crosses one of the ``candidates``
    faces turned away from n, and one turned its way (inf: none)."""
    leave = enter = np.inf
    nn = math.sqrt(dot(n, n))
    d = (-n[0], -n[1], -n[2])
    for f in candidates:
        p0, p1, p2 = vertices[faces[f, 0]], vertices[faces[f, 1]], vertices[faces[f, 2]]
        e1 = (p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2])
        e2 = (p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2])
        face_normal = cross(e1, e2)
        turn = dot(face_normal, n) / (math.sqrt(dot(face_normal, face_normal)) * nn + 1e-300)
        if -FACING < turn < FACING:
            continue  # a wall along the ray: neither face
        q = cross(d, e2)
        det = dot(e1, q)
        if det == 0.0:
            continue
        r = (x[0] - p0[0], x[1] - p0[1], x[2] - p0[2])
        beta = dot(r, q) / det
        if beta < 0.0 or beta > 1.0:
            continue
        w = cross(r, e1)
        gamma = dot(d, w) / det
        if gamma < 0.0 or beta + gamma > 1.0:
            continue
        s = dot(e2, w) / det
        if s > 0.0 and turn <= -FACING:
            leave = min(leave, s)
        elif s > 0.0:
            enter = min(enter, s)
    return leave, enter


def contact_table(points, normals, forces, slopes, solved_depth, triangles, records=None,
                  offsets=None, tool_stiffness=None, floors=None,
                  outside=None) -> np.ndarray:  # fmt: skip
    """The model's arrays :func:`prepare_contact` reads, packed into one read-only array
    (``solved_depth`` (P,): the depth each sample was solved to, mm; ``tool_stiffness``
    (S, L): the lattice values, or None; ``floors`` (S,): the triangles' floors,
    :func:`face_floors`, or None; ``outside``: :func:`outside_part`'s arguments, or None)."""
    P, K = np.shape(forces)
    stride, Z = (0, 0) if records is None else np.shape(records)[::-1]
    edges = border_edges(triangles)
    lattice = np.zeros((len(triangles), 0)) if tool_stiffness is None else tool_stiffness
    m = lattice_subdivisions(np.shape(lattice)[1]) or 0
    if np.shape(lattice) != (len(triangles), (m + 1) * (m + 2) // 2 if m else 0):
        raise ValueError(f"tool stiffness of shape {np.shape(lattice)} is no lattice per triangle")
    if not np.all((np.asarray(lattice) > 0) & np.isfinite(lattice)):  # divided by at set_contact
        raise ValueError("tool stiffness must be finite and positive")
    parts = [points, normals, forces, slopes, solved_depth, triangles,
             triangle_planes(points, triangles, floors), edges,
             lattice]  # fmt: skip
    if records is not None:
        parts += [records, offsets]
    body = np.concatenate([np.ravel(np.asarray(a, dtype=np.float64)) for a in parts])
    start = T_HEADER + len(body) if outside is not None else 0
    if outside is not None:
        body = np.concatenate([body, outside_part(*outside)])
    header = [P, K, len(triangles), stride, Z, T_HEADER + len(body), 0, len(edges), m, start]
    return _frozen(np.concatenate([header, body]))


def outside_part(corners, stiffness, grid, starts, ids, blend: float) -> np.ndarray:
    """The table's outside part (:func:`scale_outside`): [TL, cells, ids, the blend length
    (mm), grid (origin (3), cell size, dims (3)), cell starts (cells + 1), triangle ids by
    cell, the loadable triangles' corners (TL, 3, 3), the tool's linear stiffness at the
    corners and at the edges' midpoints opposite them (TL, 6), its least and largest value],
    from the contact fields' triangle grid (``model._contact_fields``)."""
    corners, stiffness = np.asarray(corners, np.float64), np.asarray(stiffness, np.float64)
    if corners.shape != (len(stiffness), 3, 3) or np.shape(stiffness)[1:] != (6,):
        raise ValueError(f"corners {corners.shape} and stiffness {np.shape(stiffness)} differ")
    if not blend > 0.0:
        raise ValueError(f"the blend length must be positive, got {blend!r}")
    head = [len(stiffness), len(starts) - 1, len(ids), blend]
    bounds = [stiffness.min(initial=np.inf), stiffness.max(initial=-np.inf)]
    parts = [head, grid, starts, ids, corners.ravel(), stiffness.ravel(), bounds]
    return np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in parts])


def scalpel_table(table: np.ndarray, vertices, normals, region_of, spacing: float, reach: float,
                  region_reach: float) -> np.ndarray:  # fmt: skip
    """The contact ``table`` with the scalpel's part appended (read only): the surface
    vertices' :func:`point_grid`, their normals and region nodes (-1: not in the region),
    the reach (mm) of a placement and of the region search."""
    parts = ([reach, region_reach], point_grid(vertices, spacing), np.ravel(vertices),
             np.ravel(normals), region_of)  # fmt: skip
    table = np.concatenate([table[: int(table[T_SCALPEL])], *parts]).astype(np.float64)
    table[T_VERTICES] = len(vertices)
    return _frozen(table)


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@njit(inline="always")
def contact_views(table):
    """The contact's parts of the table as flat views (row-major; a reshape costs more
    than the index arithmetic): sample points, normals, forces, slopes, solved depths,
    sample triangles, their planes, border edges, the stiffness lattices, section records,
    section offsets."""
    P, K, S = int(table[T_SAMPLES]), int(table[T_KNOTS]), int(table[T_TRIANGLES])
    Z, stride, E = int(table[T_SECTIONS]), int(table[T_STRIDE]), int(table[T_EDGES])
    m = int(table[T_LATTICE])
    o = T_HEADER
    a = o + 3 * P
    b = a + 3 * P
    c = b + P * K
    d = c + P * K
    e = d + P
    r = e + 3 * S
    q = r + PLANE * S
    t = q + 3 * E
    w = t + (S * (m + 1) * (m + 2) // 2 if m > 0 else 0)
    u = w + Z * stride
    v = u + (P + 1 if stride > 0 else 0)
    return (table[o:a], table[a:b], table[b:c], table[c:d], table[d:e], table[e:r],
            table[r:q], table[q:t], table[t:w], table[w:u], table[u:v])  # fmt: skip


@njit(inline="always")
def scalpel_views(table):
    """The scalpel's part of the table: reach, region reach, the grid, the surface
    vertices (3 V, row-major), their normals (3 V), their region nodes (V,)."""
    f, V = int(table[T_SCALPEL]), int(table[T_VERTICES])
    g = f + 2
    d = g + GRID_DIMS
    x = g + GRID_STARTS + int(table[d]) * int(table[d + 1]) * int(table[d + 2]) + 1 + V  # its end
    return (table[f], table[f + 1], table[g:x], table[x : x + 3 * V],
            table[x + 3 * V : x + 6 * V], table[x + 6 * V : x + 7 * V])  # fmt: skip


# -- inputs, outputs, the layout's pieces ----------------------------------------------------
@njit(inline="always")
def finite3(v):
    """Whether v[0], v[1], v[2] are all finite."""
    return math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])


@njit(f"int64({vec}, float64)", cache=True, nogil=True)
def check_input(v, limit):
    """0 if v (3,) is finite and |v| <= limit; else the step's status code (3, 1 or 2)."""
    if v.shape[0] != 3:
        return WRONG_SHAPE  # before reading: a shorter array is never read past its end
    if not finite3(v):
        return NOT_FINITE
    if not (v[0] * v[0] + v[1] * v[1] + v[2] * v[2] <= limit * limit):  # a NaN limit refuses
        return BEYOND_LIMIT
    return OK


@njit(inline="always")
def step_input(x, buf, limit):
    """A step's start: (status, x's component into the tissue, the flags the step keeps)."""
    if buf[CONTACTS] == 0.0:
        return NO_CONTACT_POINT, 0.0, 0
    status = check_input(x, limit)
    if status:
        return status, 0.0, 0
    inward = -(x[0] * buf[NORMAL] + x[1] * buf[NORMAL + 1] + x[2] * buf[NORMAL + 2])
    return OK, inward, int(buf[FLAGS]) & FLAG_OUTSIDE_REGION


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


@njit(inline="always")
def anm_layout(buf):
    """(where the blocks start, N1, a record's stride, a block's size) of the POD-ANM part."""
    stride = REC_FORCE + 4 * int(buf[SECTION_KNOTS])
    return int(buf[ANM_BASE]), int(buf[ANM_N1]), stride, BLOCK_RECORDS + int(buf[ANM_SMAX]) * stride


@njit(inline="always")
def curve_views(buf):
    """(K, the contact's force curve (N), its slopes (N/mm)) in the buffer."""
    knots = int(buf[KNOTS])
    return knots, buf[CURVE : CURVE + knots], buf[CURVE + knots : CURVE + 2 * knots]


@njit(inline="always")
def newton_step(x, r, slope, lo, hi):
    """One safeguarded Newton step for an increasing function with residual r at x in the
    bracket [lo, hi]: (the next x, lo, hi), the bracket shrunk to x's side; bisection
    when the step leaves the bracket or the slope is not positive."""
    if r > 0.0:
        hi = x
    else:
        lo = x
    trial = x - r / slope if slope > 0.0 else 0.5 * (lo + hi)
    return (trial if lo < trial < hi else 0.5 * (lo + hi)), lo, hi


@njit(cache=True, nogil=True)
def depth_weights(depth, step, last):
    """Linear interpolation in depth over knots 0 .. last: (k, 1 - t, t)."""
    x = min(max(depth / step, 0.0), float(last))
    k = min(int(x), last - 1)
    return k, 1.0 - (x - k), x - k


@njit(inline="always")
def field_depth_weights(depth, step, last):
    """:func:`depth_weights` for the surface field's coordinates, continued linearly beyond
    the last knot (t > 1). Why: a soft place reaches the trained force at several times
    the trained depth (the liver: 2.2 mm against 0.46 mm); a field held at the last knot
    stopped following the tool there (its surface 45-68 % off; the force, continued with
    the end slope, 0.4-2.3 %)."""
    x = max(depth / step, 0.0)
    k = min(int(min(x, float(last))), last - 1)  # int() of a huge x would wrap around
    return k, 1.0 - (x - k), x - k


# -- POD-ANM series (the default response) ---------------------------------------------------
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


@njit(f"float64({f8_1d}, float64, float64)", cache=True, nogil=True)
def series_root(c, a_max, depth):
    """a in [0, a_max] with sum_k c[k] a^k = depth (c: a section's depth series, increasing
    on [0, a_max]): bracketed Newton."""
    n = c.shape[0]
    lo, hi = 0.0, a_max
    d0, d1 = c[0], horner(c, 0, n, a_max)
    a = lo + (hi - lo) * (depth - d0) / (d1 - d0) if d1 > d0 else 0.5 * (lo + hi)
    tol = 1e-14 * (1.0 + abs(depth))
    for _ in range(60):
        r = horner(c, 0, n, a) - depth
        if abs(r) <= tol:
            break
        a, lo, hi = newton_step(a, r, horner_derivative(c, 0, n, a), lo, hi)
        if hi - lo <= 1e-15 * a_max:
            break
    return a


@njit(inline="always")
def section_of(buf, b, stride, depth):
    """Where the record of neighbour block b's section holding ``depth`` starts (the last
    section if depth is beyond them all)."""
    first, count = b + BLOCK_RECORDS, int(buf[b + BLOCK_COUNT])
    s = 0
    while s < count - 1 and buf[first + s * stride + REC_DEPTH_END] < depth:
        s += 1
    return s, first + s * stride


@njit(inline="always")
def knot_of(buf, rec, q, depth):
    """(knot k, t in [0, 1] between knots k and k + 1, spacing, its inverse) of ``depth``
    in a section of q knots. A depth in the 1e-6 mm gap before a section's start reads its
    start: never an extrapolation, however short a crafted section is."""
    x = min(max((depth - buf[rec + REC_DEPTH0]) * buf[rec + REC_INVERSE_SPACING], 0.0), q - 1.0)
    k = min(int(x), q - 2)
    return k, x - k, buf[rec + REC_SPACING], buf[rec + REC_INVERSE_SPACING]


@njit(inline="always")
def cubic_hermite(buf, values, slopes, k, t, h, inverse_h):
    """(value, d/ddepth) of the cubic Hermite interpolant between knots k and k + 1."""
    v0, v1 = buf[values + k], buf[values + k + 1]
    s0, s1 = h * buf[slopes + k], h * buf[slopes + k + 1]
    c2, c3 = 3.0 * (v1 - v0) - 2.0 * s0 - s1, 2.0 * (v0 - v1) + s0 + s1
    return v0 + t * (s0 + t * (c2 + t * c3)), (s0 + t * (2.0 * c2 + t * 3.0 * c3)) * inverse_h


@njit(f"void({f8_2d}, {f8_2d}, {f8_1d}, {f8_2d})", cache=True, nogil=True)
def tabulate_sections(depth, force, a_max, out):
    """The section records ``out`` (Z, record_stride(Q)) of the series depth(a), force(a)
    (Z, N1) on [0, a_max] (Z): each section solved for a at Q uniform depths (at load)."""
    n1, q = depth.shape[1], (out.shape[1] - REC_FORCE) // 4
    for z in range(depth.shape[0]):
        c, f, r = depth[z], force[z], out[z]
        d0, d1 = c[0], horner(c, 0, n1, a_max[z])
        h = (d1 - d0) / (q - 1)
        r[REC_DEPTH0], r[REC_DEPTH_END], r[REC_AMAX] = d0, d1, a_max[z]
        r[REC_SPACING], r[REC_INVERSE_SPACING] = h, 1.0 / h
        for k in range(q):
            a = a_max[z] if k == q - 1 else series_root(c, a_max[z], d0 + k * h)
            dd = horner_derivative(c, 0, n1, a)  # > 0: monotone sections (artifact_rules)
            r[REC_FORCE + k] = horner(f, 0, n1, a)
            r[REC_FORCE + q + k] = horner_derivative(f, 0, n1, a) / dd
            r[REC_FORCE + 2 * q + k] = a
            r[REC_FORCE + 3 * q + k] = 1.0 / dd
        r[REC_FORCE_END] = r[REC_FORCE + q - 1]
        r[REC_SLOPE_END] = r[REC_FORCE + 2 * q - 1]


@njit(f"UniTuple(float64, 2)({f8_2d}, {f8_2d}, {f8_1d}, {f8_2d})", cache=True, nogil=True)
def tabulation_error(depth, force, a_max, records):
    """(largest |force error| (N), largest |a error|) of the tabulated sections between
    their knots: at every interval's midpoint, where a cubic Hermite interpolant's error
    peaks, against the series solved there."""
    n1, q = depth.shape[1], (records.shape[1] - REC_FORCE) // 4
    worst_force = worst_a = 0.0
    for z in range(depth.shape[0]):
        r = records[z]
        for k in range(q - 1):
            d = r[REC_DEPTH0] + (k + 0.5) * r[REC_SPACING]
            a = series_root(depth[z], a_max[z], d)
            f, _ = cubic_hermite(r, REC_FORCE, REC_FORCE + q, k, 0.5, r[REC_SPACING],
                                 r[REC_INVERSE_SPACING])  # fmt: skip
            t, _ = cubic_hermite(r, REC_FORCE + 2 * q, REC_FORCE + 3 * q, k, 0.5,
                                 r[REC_SPACING], r[REC_INVERSE_SPACING])  # fmt: skip
            worst_force = max(worst_force, abs(f - horner(force[z], 0, n1, a)))
            worst_a = max(worst_a, abs(t - a))
    return worst_force, worst_a


@njit(inline="always")
def anm_section(buf, b, depth):
    """(section index, path parameter a, da beyond) of neighbour block b at ``depth`` (mm):
    what the surface field evaluates its series at. Beyond the last section: a_max, and
    how far a would go on linearly with its end slope (the field continues along the
    series' tangent there, :func:`~hapticrom.online.surface_kernels.anm_coefficients`);
    0 elsewhere."""
    _, _, stride, _ = anm_layout(buf)
    q = int(buf[SECTION_KNOTS])
    s, rec = section_of(buf, b, stride, depth)
    k, t, h, inverse_h = knot_of(buf, rec, q, depth)
    a, slope = cubic_hermite(buf, rec + REC_FORCE + 2 * q, rec + REC_FORCE + 3 * q, k, t, h,
                             inverse_h)  # fmt: skip
    end = buf[rec + REC_DEPTH_END]
    if depth > end:
        return s, buf[rec + REC_AMAX], (depth - end) * slope
    return s, a, 0.0


@njit(f"float64({f8_1d}, float64)", cache=True, nogil=True)
def anm_force(buf, depth):
    """Blended normal force (N) of the three neighbours' series at ``depth`` (mm), from the
    sections' tables.

    Writes the blended dF/ddepth into buf[ANM_SLOPE] and 1 into buf[ANM_BEYOND] if a
    neighbour's last section ends before ``depth`` (its force then continues linearly
    with the end slope).
    """
    base, _, stride, block = anm_layout(buf)
    q = int(buf[SECTION_KNOTS])
    total = 0.0
    slope_total = 0.0
    beyond = 0
    for j in range(3):
        b = base + j * block
        _, rec = section_of(buf, b, stride, depth)
        if depth > buf[rec + REC_DEPTH_END]:
            beyond = 1
            slope = buf[rec + REC_SLOPE_END]
            force = buf[rec + REC_FORCE_END] + slope * (depth - buf[rec + REC_DEPTH_END])
        else:
            k, t, h, inverse_h = knot_of(buf, rec, q, depth)
            force, slope = cubic_hermite(buf, rec + REC_FORCE, rec + REC_FORCE + q, k, t, h,
                                         inverse_h)  # fmt: skip
        total += buf[b + BLOCK_WEIGHT] * force
        slope_total += buf[b + BLOCK_WEIGHT] * slope
    buf[ANM_SLOPE] = slope_total
    buf[ANM_BEYOND] = beyond
    return total


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
def step_displacement_anm(d, buf):
    """Prescribed tool displacement d (mm) in, reaction force on the tool (N) into buf:
    the default step (the POD-ANM series of the contact's three neighbour samples).

    Depth = -d . normal (into the tissue). The contact is frictionless: only the
    normal component of d loads the tissue, and the force is along the normal.
    """
    status, depth, flags = step_input(d, buf, buf[MAX_DISPLACEMENT])
    if status:
        return status
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
    return OK


@njit(inline="always")
def anm_bracket(buf):
    """The smallest trained depth (mm) of the three neighbours: their last sections' end."""
    base, _, stride, block = anm_layout(buf)
    hi = np.inf
    for j in range(3):
        b = base + j * block
        last = b + BLOCK_RECORDS + (int(buf[b + BLOCK_COUNT]) - 1) * stride
        hi = min(hi, buf[last + REC_DEPTH_END])
    return hi


@njit(f"float64({f8_1d}, float64)", cache=True, nogil=True)
def anm_depth(buf, push):
    """The depth (mm) whose blended series force is ``push`` (N, > 0): safeguarded Newton
    on the bracket [0, the neighbours' first trained end], widened along the end slope."""
    hi = anm_bracket(buf)
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
        depth, lo, hi = newton_step(depth, r, buf[ANM_SLOPE], lo, hi)
        if hi - lo <= 1e-15 * hi:
            break
    return depth


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
def step_force_anm(f, buf):
    """Force the tool applies (N) in, tool displacement (mm) into buf: the depth whose
    blended series force equals the push (the default response).

    A force whose depth passes ``buf[MAX_DEPTH]`` is refused (status 4, nothing written;
    the sections of the previous depth stay in the buffer), as a displacement step
    refuses a displacement beyond the limit.
    """
    status, push, flags = step_input(f, buf, buf[MAX_FORCE])
    if status:
        return status
    if push <= 0.0:
        depth = 0.0
        flags |= FLAG_NO_CONTACT
        anm_force(buf, 0.0)
    else:
        depth = anm_depth(buf, push)
        if not (depth <= buf[MAX_DEPTH]):
            anm_force(buf, buf[DEPTH])  # the sections of the state before: unchanged
            return DISPLACEMENT_LIMIT
        anm_force(buf, depth)  # leave the sections of the returned depth in the buffer
        if buf[ANM_BEYOND] != 0.0:
            flags |= FLAG_BEYOND_DEPTH
    write_displacement(buf, depth, flags)
    return OK


# -- the stored full-order curves (response "curves") ---------------------------------------
@njit(inline="always")
def beyond_solved(depth, buf):
    """Whether a depth passes the contact's solved depth by more than rounding (a force step
    at exactly a sample's trained force lands within 1e-9 of it, either side: review)."""
    return depth > buf[SOLVED_DEPTH] * (1.0 + 1e-9)


@njit("float64(float64[::1], float64[::1], float64, float64)", cache=True, nogil=True)
def hermite(force, slope, step, depth):
    """The piecewise-cubic Hermite curve F(depth) (uniform knots 0, step, 2 step, ...)."""
    last = force.shape[0] - 1
    if depth >= last * step:
        return force[last] + slope[last] * (depth - last * step)
    k = min(int(depth / step), last - 1)  # depth / step may round up to last just below it
    t = depth / step - k
    t2, t3 = t * t, t * t * t
    return (
        (2 * t3 - 3 * t2 + 1) * force[k]
        + (t3 - 2 * t2 + t) * step * slope[k]
        + (-2 * t3 + 3 * t2) * force[k + 1]
        + (t3 - t2) * step * slope[k + 1]
    )


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
def step_displacement_curves(d, buf):
    """As :func:`step_displacement_anm`, the force from the contact's interpolated curve."""
    status, depth, flags = step_input(d, buf, buf[MAX_DISPLACEMENT])
    if status:
        return status
    knots, force, slope = curve_views(buf)
    step = buf[STEP]
    if depth <= 0.0:
        magnitude = 0.0
        depth = 0.0
        flags |= FLAG_NO_CONTACT
    else:
        if beyond_solved(depth, buf):
            flags |= FLAG_BEYOND_DEPTH
        magnitude = hermite(force, slope, step, depth)
    write_force(buf, magnitude, depth, flags)
    return OK


@njit("float64(float64[::1], float64[::1], float64, float64)", cache=True, nogil=True)
def curve_depth(force, slope, step, push):
    """The depth (mm) where the Hermite curve reaches ``push`` (N, 0 < push < the last
    knot's force): bisection on the knots, then safeguarded Newton on the monotone cubic."""
    last = force.shape[0] - 1
    lo, hi = 0, last  # force[lo] <= push < force[hi]
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if force[mid] <= push:
            lo = mid
        else:
            hi = mid
    a, b = lo * step, hi * step
    depth = a + (push - force[lo]) / (force[hi] - force[lo]) * step
    for _ in range(50):
        r = hermite(force, slope, step, depth) - push
        if abs(r) <= 1e-13 * push:
            break
        k = min(int(depth / step), last - 1)
        t = depth / step - k
        dF = (
            (6 * t * t - 6 * t) * force[k] / step
            + (3 * t * t - 4 * t + 1) * slope[k]
            + (-6 * t * t + 6 * t) * force[k + 1] / step
            + (3 * t * t - 2 * t) * slope[k + 1]
        )
        depth, a, b = newton_step(depth, r, dF, a, b)
    return depth


@njit(f"int64({vec}, {f8_1d})", cache=True, nogil=True)
def step_force_curves(f, buf):
    """As :func:`step_force_anm`, by inverting the contact's interpolated curve.

    A force whose depth passes ``buf[MAX_DEPTH]`` is refused (status 4, nothing written).
    """
    status, push, flags = step_input(f, buf, buf[MAX_FORCE])
    if status:
        return status
    knots, force, slope = curve_views(buf)
    step = buf[STEP]
    last = knots - 1
    if push <= 0.0:
        depth = 0.0
        flags |= FLAG_NO_CONTACT
    elif push >= force[last]:
        depth = last * step + (push - force[last]) / slope[last]
    else:
        depth = curve_depth(force, slope, step, push)
    if beyond_solved(depth, buf):
        flags |= FLAG_BEYOND_DEPTH
    if not (depth <= buf[MAX_DEPTH]):
        return DISPLACEMENT_LIMIT
    write_displacement(buf, depth, flags)
    return OK


@njit(f"float64({f8_1d})", cache=True, nogil=True)
def contact_stiffness(buf):
    """d force / d depth (N/mm) at the last step's depth: the series' blended slope, or the
    curve's slopes interpolated linearly in depth."""
    if buf[ANM_N1] > 0:
        return buf[ANM_SLOPE]
    knots, _, slope = curve_views(buf)
    k, a, b = depth_weights(buf[DEPTH], buf[STEP], knots - 1)
    return a * slope[k] + b * slope[k + 1]


# -- the contact -----------------------------------------------------------------------------
@njit(inline="always")
def vertex(points, i):
    """Row i of a flat (N, 3) row-major array, as a tuple."""
    return points[3 * i], points[3 * i + 1], points[3 * i + 2]


@njit(inline="always")
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(inline="always")
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(inline="always")
def combine(a, s, b, t, c):
    """a + s b + t c (tuples)."""
    return (a[0] + s * b[0] + t * c[0], a[1] + s * b[1] + t * c[1], a[2] + s * b[2] + t * c[2])


@njit(inline="always")
def minus(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


# -- the point of a triangle nearest a point (the proxy's, the surface's, a clamped contact's) --
@njit(cache=True, nogil=True)
def closest_on_triangle(p, a, b, c):
    """The point of triangle (a, b, c) nearest p: (its barycentric coordinates, distance^2).
    The region tests of Ericson (Real-Time Collision Detection, 5.1.5)."""
    ab, ac, ap = minus(b, a), minus(c, a), minus(p, a)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return _result(p, a, b, c, 1.0, 0.0, 0.0)
    bp = minus(p, b)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return _result(p, a, b, c, 0.0, 1.0, 0.0)
    # The divisions below are by sums of terms of one sign: zero only on a degenerate
    # triangle (corners that coincide, or in a line: an offset sheet can fold them so),
    # where numba would raise ZeroDivisionError into the servo loop. Such a triangle is
    # the union of its edges: the nearest point of those instead.
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        if not d1 > d3:
            return _nearest_on_edges(p, a, b, c)
        v = d1 / (d1 - d3)
        return _result(p, a, b, c, 1.0 - v, v, 0.0)
    cp = minus(p, c)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return _result(p, a, b, c, 0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        if not d2 > d6:
            return _nearest_on_edges(p, a, b, c)
        w = d2 / (d2 - d6)
        return _result(p, a, b, c, 1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        span = (d4 - d3) + (d5 - d6)
        if not span > 0.0:
            return _nearest_on_edges(p, a, b, c)
        w = (d4 - d3) / span
        return _result(p, a, b, c, 0.0, 1.0 - w, w)
    total = va + vb + vc  # |ab x ac|^2 up to rounding
    if not total > 0.0:  # a degenerate triangle (or NaN from an overflow)
        return _nearest_on_edges(p, a, b, c)
    v, w = vb / total, vc / total
    return _result(p, a, b, c, 1.0 - v - w, v, w)


@njit(cache=True, nogil=True)
def _nearest_on_edges(p, a, b, c):
    """The point of the edges ab, bc, ca nearest p: (barycentric u, v, w, distance^2), for
    a degenerate triangle (which is the union of its edges)."""
    best, u, v, w = math.inf, 1.0, 0.0, 0.0
    for edge in range(3):
        s, e = (a, b) if edge == 0 else ((b, c) if edge == 1 else (c, a))
        d = minus(e, s)
        length2 = dot(d, d)
        t = min(1.0, max(0.0, dot(minus(p, s), d) / length2)) if length2 > 0.0 else 0.0
        r = minus(p, (s[0] + t * d[0], s[1] + t * d[1], s[2] + t * d[2]))
        distance2 = dot(r, r)
        if distance2 < best:
            best = distance2
            if edge == 0:
                u, v, w = 1.0 - t, t, 0.0
            elif edge == 1:
                u, v, w = 0.0, 1.0 - t, t
            else:
                u, v, w = t, 0.0, 1.0 - t
    return u, v, w, best


@njit(inline="always")
def _result(p, a, b, c, u, v, w):
    x = (u * a[0] + v * b[0] + w * c[0], u * a[1] + v * b[1] + w * c[1],
         u * a[2] + v * b[2] + w * c[2])  # fmt: skip
    r = minus(p, x)
    return u, v, w, dot(r, r)


@njit(inline="always")  # called per triangle: a call passing arrays costs more
def project_on_triangle(p, points, normals, triangles, planes, t, best, out):
    """The point p's coordinates over sample triangle t = (a, b, c) along its blended
    normals: (u, v, h) into out[0:3] with

        p = X(u, v) + h N(u, v),  X = x_a + u (x_b - x_a) + v (x_c - x_a),

    N the same blend of the samples' normals. On an edge the answer depends on the edge's
    two samples only, so the weights (1 - u - v, u, v) are continuous from one triangle
    into the next on a curved or closed surface (a plane projection is not). Newton from
    the flat projection. False if Newton failed or p cannot lie in the triangle with
    |h| < ``best``: |h| is at least p's distance from the plane (|N| <= 1), and the flat
    coordinates differ from (u, v) by at most |h| / the smallest altitude (the shift
    h N in the plane), so a triangle farther from p, or with a flat coordinate below
    minus that margin (at most 1/2; the plane farther than the longest edge), is skipped
    without Newton."""
    u, v, height = flat_coordinates(p, planes, t)
    reach2 = planes[PLANE * t + 12]
    if height * height >= best * best or height * height > reach2:
        return False
    a, b, c = int(triangles[3 * t]), int(triangles[3 * t + 1]), int(triangles[3 * t + 2])
    xa, xb, xc = vertex(points, a), vertex(points, b), vertex(points, c)
    e1, e2, d = minus(xb, xa), minus(xc, xa), minus((p[0], p[1], p[2]), xa)
    n = cross(e1, e2)
    margin = min(0.5, best * math.sqrt(reach2 / dot(n, n)))  # best / the smallest altitude
    if u < -margin or v < -margin or u + v > 1.0 + margin:
        return False
    na = vertex(normals, a)
    dn1, dn2 = minus(vertex(normals, b), na), minus(vertex(normals, c), na)
    h = 0.0
    for _ in range(12):
        normal = combine(na, u, dn1, v, dn2)
        x = combine(d, -u, e1, -v, e2)  # p - X(u, v)
        g = combine(x, -h, normal, 0.0, normal)  # the residual p - X - h N
        c1, c2 = combine(e1, h, dn1, 0.0, dn1), combine(e2, h, dn2, 0.0, dn2)
        det = dot(c1, cross(c2, normal))
        if abs(det) <= 1e-300:
            return False
        du = dot(g, cross(c2, normal)) / det
        dv = dot(g, cross(normal, c1)) / det
        dh = dot(g, cross(c1, c2)) / det
        u, v, h = u + du, v + dv, h + dh
        # Quadratic convergence: a step this small leaves an error near round-off.
        if abs(du) + abs(dv) <= 1e-9 and dh * dh <= 1e-18 * reach2:
            out[0], out[1], out[2] = u, v, h
            return True
    return False


@njit(inline="always")
def sum_of_products(p, planes, origin, axis):
    """(p - planes[origin:origin + 3]) . planes[axis:axis + 3]."""
    return ((p[0] - planes[origin]) * planes[axis] + (p[1] - planes[origin + 1]) * planes[axis + 1]
            + (p[2] - planes[origin + 2]) * planes[axis + 2])  # fmt: skip


@njit(inline="always")
def flat_coordinates(p, planes, t):
    """(u, v, height) of p's projection on sample triangle t's plane (:func:`triangle_planes`)."""
    o = PLANE * t
    d0, d1, d2 = p[0] - planes[o], p[1] - planes[o + 1], p[2] - planes[o + 2]
    height = d0 * planes[o + 3] + d1 * planes[o + 4] + d2 * planes[o + 5]
    u = d0 * planes[o + 6] + d1 * planes[o + 7] + d2 * planes[o + 8]
    v = d0 * planes[o + 9] + d1 * planes[o + 10] + d2 * planes[o + 11]
    return u, v, height


@njit(cache=True, nogil=True)
def locate(p, points, normals, triangles, planes, edges, out_weights, out_samples, out_where,
           uvh):  # fmt: skip
    """Barycentric weights of the point p (mm, on or near the surface) in the samples'
    triangulation (flat row-major points and normals (3 P), triangles (3 S), their planes
    (PLANE S, :func:`triangle_planes`), border edges (3 E): two samples and the
    triangle's third): of the triangle that holds p along its
    blended normals (:func:`project_on_triangle`) with the smallest height (the near side
    of a closed organ) and not beneath its floor (nearer its face than the opposite face,
    :func:`face_floors`). The samples go into ``out_samples`` (as floats), the triangle and
    the height into ``out_where`` (2); ``uvh`` (3) is scratch.

    The triangle whose plane projection holds p deepest is solved first: it is usually
    the one, and its |h| then rules most others out before their Newton (the bounds of
    :func:`project_on_triangle`). A point beyond the triangulation's border is clamped to
    the nearest point of the border (returns FLAG_OUTSIDE_REGION), so weights stay
    continuous as it moves.
    """
    count = triangles.shape[0] // 3
    first, deepest = 0, -np.inf
    for t in range(count):
        u, v, height = flat_coordinates(p, planes, t)
        inside = min(u, v, 1.0 - u - v)
        if inside > deepest and height * height <= planes[PLANE * t + 12]:
            first, deepest = t, inside
    best, found, bu, bv = np.inf, -1, 0.0, 0.0
    for k in range(count):
        t = (first + k) % count
        o = PLANE * t
        height = sum_of_products(p, planes, o, o + 3)  # p's height over the plane
        if height * height >= best * best:
            continue  # |h| >= that height: this triangle cannot hold p nearer
        if not project_on_triangle(p, points, normals, triangles, planes, t, best, uvh):
            continue
        u, v, h = uvh[0], uvh[1], uvh[2]
        inside = u >= -1e-12 and v >= -1e-12 and u + v <= 1.0 + 1e-12
        if inside and abs(h) < best and h >= planes[o + PLANE_FLOOR]:
            best, found, bu, bv = abs(h), t, u, v
            out_where[1] = h
    if found < 0:
        out_where[0] = -1.0
        if edges.shape[0] == 0:  # a closed triangulation: p is off the surface
            return nearest_corner(p, points, triangles, out_weights, out_samples, out_where)
        return clamp_to_border(p, points, normals, edges, out_weights, out_samples, out_where)
    for k in range(3):
        out_samples[k] = triangles[3 * found + k]
    out_weights[0], out_weights[1], out_weights[2] = 1.0 - bu - bv, bu, bv
    out_where[0] = found
    return 0


@njit(inline="always")
def edge_equation(d, e, na, dn, s):
    """g(s) = (r.e)(N.N) - (e.N)(r.N) with r = d - s e, N = na + s dn, and dg/ds: zero where
    r is normal to the edge within the plane of e and N (the blended normal's projection
    of p on the edge)."""
    r = combine(d, -s, e, 0.0, e)
    normal = combine(na, s, dn, 0.0, dn)
    re, nn, en, rn = dot(r, e), dot(normal, normal), dot(e, normal), dot(r, normal)
    g = re * nn - en * rn
    dg = -dot(e, e) * nn + 2.0 * re * dot(normal, dn) - dot(e, dn) * rn
    dg -= en * (-en + dot(r, dn))
    return g, dg


@njit(cache=True, nogil=True)
def nearest_corner(p, points, triangles, out_weights, out_samples, out_where):
    """The sample nearest p, as weight 1 in a triangle that has it: where a closed
    triangulation (no border) holds no point, i.e. p is far off the surface.
    FLAG_OUTSIDE_REGION."""
    best, best_t, best_k = np.inf, 0, 0
    for t in range(triangles.shape[0] // 3):
        for k in range(3):
            d = distance2(points, int(triangles[3 * t + k]), p)
            if d < best:
                best, best_t, best_k = d, t, k
    for k in range(3):
        out_samples[k] = triangles[3 * best_t + (best_k + k) % 3]
    out_weights[0], out_weights[1], out_weights[2] = 1.0, 0.0, 0.0
    out_where[1] = math.sqrt(best)
    return FLAG_OUTSIDE_REGION


@njit(cache=True, nogil=True)
def clamp_to_border(p, points, normals, edges, out_weights, out_samples, out_where):
    """The nearest point of the border edges to p (each edge's point where p projects
    along the blended normal, as in :func:`project_on_triangle`), as weights of the edge's
    two samples (the third sample of its triangle with weight 0): FLAG_OUTSIDE_REGION."""
    best, best_e, best_s = np.inf, 0, 0.0
    q = (p[0], p[1], p[2])
    for k in range(edges.shape[0] // 3):
        a, b = int(edges[3 * k]), int(edges[3 * k + 1])
        xa, xb = vertex(points, a), vertex(points, b)
        na = vertex(normals, a)
        e, d, dn = minus(xb, xa), minus(q, xa), minus(vertex(normals, b), na)
        s = min(1.0, max(0.0, dot(d, e) / dot(e, e)))
        for _ in range(8):
            g, dg = edge_equation(d, e, na, dn, s)
            if dg == 0.0:
                break
            s_new = min(1.0, max(0.0, s - g / dg))
            if abs(s_new - s) <= 1e-14:
                s = s_new
                break
            s = s_new
        r = combine(d, -s, e, 0.0, e)
        dist = dot(r, r)
        if dist < best:
            best, best_e, best_s = dist, k, s
    out_samples[0] = edges[3 * best_e]
    out_samples[1] = edges[3 * best_e + 1]
    out_samples[2] = edges[3 * best_e + 2]
    out_weights[0], out_weights[1], out_weights[2] = 1.0 - best_s, best_s, 0.0
    out_where[1] = math.sqrt(best)
    return FLAG_OUTSIDE_REGION


@njit(inline="always")
def lattice_at(values, start, m, i, j):
    """Point (i, j) of the lattice stored from ``start`` (``shared/lattice.py``)."""
    return values[start + i * (m + 1) - i * (i - 1) // 2 + j]


@njit(inline="always")
def lattice_value(values, start, m, bu, bv):
    """The lattice's value (m subdivisions, stored from ``start``) at the weights
    (1 - bu - bv, bu, bv): linear on the sub-triangle that holds them."""
    x, y = min(max(bu, 0.0), 1.0) * m, min(max(bv, 0.0), 1.0) * m
    i, j = min(int(x), m - 1), min(int(y), m - 1)
    if i + j > m - 1:  # on the far edge (i + j = m): the last sub-triangle of row i
        j = m - 1 - i
    fx, fy = x - i, y - j
    if fx + fy <= 1.0 or i + j == m - 1:  # the sub-triangle (i, j), (i + 1, j), (i, j + 1)
        return ((1.0 - fx - fy) * lattice_at(values, start, m, i, j)
                + fx * lattice_at(values, start, m, i + 1, j)
                + fy * lattice_at(values, start, m, i, j + 1))  # fmt: skip
    return ((fx + fy - 1.0) * lattice_at(values, start, m, i + 1, j + 1)
            + (1.0 - fy) * lattice_at(values, start, m, i + 1, j)
            + (1.0 - fx) * lattice_at(values, start, m, i, j + 1))  # fmt: skip


@njit(inline="always")
def triangle_rotation(triangles, samples):
    """(t, r): the sample triangle whose corner (r + k) % 3 is samples[k] (a border
    clamp names an edge's samples in their triangle's cyclic order), or (-1, 0)."""
    for t in range(triangles.shape[0] // 3):
        for r in range(3):
            if (triangles[3 * t + r] == samples[0] and triangles[3 * t + (r + 1) % 3] == samples[1]
                    and triangles[3 * t + (r + 2) % 3] == samples[2]):  # fmt: skip
                return t, r
    return -1, 0


@njit(inline="always")
def force_weights(weights, samples, triangle, triangles, lattice, m, out):
    """The force curves' weights w_k k(x) / k_k into ``out`` (``FORCE_WEIGHTS``): k(x) from
    the lattice of the contact's triangle at its weights, k_k at the corner of sample k.
    Without a lattice, or at a sample (a closed triangulation's nearest corner), w_k.
    Returns k(x) (N/mm), or 0 where it took w_k."""
    for k in range(3):
        out[k] = weights[k]
    if m == 0 or weights[0] == 1.0:
        return 0.0
    t, r = triangle, 0
    if t < 0:  # clamped to the border: the edge's triangle
        t, r = triangle_rotation(triangles, samples)
        if t < 0:
            return 0.0
    size = (m + 1) * (m + 2) // 2
    start = t * size
    # corner c holds sample (c - r) % 3: the lattice's weights are the triangle's corners'
    stiffness = lattice_value(lattice, start, m, weights[(4 - r) % 3], weights[(5 - r) % 3])
    for k in range(3):
        corner = (r + k) % 3
        at_corner = lattice[start + (0 if corner == 0 else (size - 1 if corner == 1 else m))]
        out[k] = weights[k] * stiffness / at_corner
    return stiffness


@njit(cache=True, nogil=True)
def prepare_curves(weights, curve_weights, samples, normals, forces, slopes, out_normal,
                   out_force, out_slope):  # fmt: skip
    """Interpolated outward normal (``weights``) and force-depth curve (values and slopes,
    ``curve_weights``) at the contact (normals (3 P), forces and slopes (K P), row-major;
    K = len(out_force))."""
    knots = out_force.shape[0]
    out_normal[:] = 0.0
    out_force[:] = 0.0
    out_slope[:] = 0.0
    for j in range(3):
        w, c_w, i = weights[j], curve_weights[j], int(samples[j])
        for c in range(3):
            out_normal[c] += w * normals[3 * i + c]
        for k in range(knots):
            out_force[k] += c_w * forces[knots * i + k]
            out_slope[k] += c_w * slopes[knots * i + k]
    norm = math.sqrt(out_normal[0] ** 2 + out_normal[1] ** 2 + out_normal[2] ** 2)
    for c in range(3):
        out_normal[c] /= norm


@njit(inline="always")
def solved_at(weights, samples, solved):
    """The contact's solved depth (mm): the smallest of its neighbours' with a weight above
    1e-9 (beyond it one of the blended curves is a continuation; a smaller weight's share of
    the force is below rounding)."""
    depth = np.inf
    for j in range(3):
        if abs(weights[j]) > 1e-9:  # not locate's rounding at a sample (up to 6e-18: review)
            depth = min(depth, solved[int(samples[j])])
    return depth


@njit(cache=True, nogil=True)
def load_sections(weights, samples, offsets, records, buf):
    """The three neighbours' force weights into the POD-ANM blocks, and their section
    records (``records``: Z stride, row-major) unless a block holds that sample's already."""
    base, _, stride, block = anm_layout(buf)
    for j in range(3):
        b = base + j * block
        i = int(samples[j])
        buf[b + BLOCK_WEIGHT] = weights[j]
        if buf[b + BLOCK_SAMPLE] == i:
            continue
        first, count = int(offsets[i]), int(offsets[i + 1] - offsets[i])
        buf[b + BLOCK_COUNT] = count
        buf[b + BLOCK_SAMPLE] = i
        start = b + BLOCK_RECORDS
        for k in range(count * stride):
            buf[start + k] = records[first * stride + k]


# -- a contact outside the trained region: the force scaled by the tool's linear stiffness --
# The ratio's bounds: as the tool stiffness lattice's within a triangle (artifact_rules), the
# force stays within 10x the border's.
MIN_OUTSIDE_RATIO, MAX_OUTSIDE_RATIO = 0.1, 10.0


@njit(inline="always")
def outside_views(table):
    """The outside part (:func:`outside_part`): blend length, grid, cell starts, ids, corners
    (TL 9), stiffness (TL 6), flat, and its bounds (2)."""
    o = int(table[T_OUTSIDE])
    count, cells, listed = int(table[o]), int(table[o + 1]), int(table[o + 2])
    g = o + 4
    a = g + 7
    b = a + cells + 1
    c = b + listed
    d = c + 9 * count
    return (table[o + 3], table[g:a], table[a:b], table[b:c], table[c:d],
            table[d : d + 6 * count], table[d + 6 * count : d + 6 * count + 2])  # fmt: skip


@njit(inline="always")
def grid_reach(p, grid, cell, r):
    """How far around p the cells within r of p's ``cell`` reach (mm): the distance from p
    to the block's nearest face inside the grid (beyond the grid there are no triangles)."""
    size, reach = grid[3], np.inf
    for a in range(3):
        lo = grid[a] + (cell[a] - r) * size
        hi = grid[a] + (cell[a] + r + 1) * size
        if cell[a] - r > 0:
            reach = min(reach, p[a] - lo)
        if cell[a] + r < int(grid[4 + a]) - 1:
            reach = min(reach, hi - p[a])
    return max(reach, 0.0)


@njit(inline="always")
def grid_cell(p, grid):
    """(the cell of p, clamped into the grid (3), the grid's dims (3)) of a uniform grid
    (origin (3), cell size, dims (3)): where a ring search starts."""
    size = grid[3]
    n0, n1, n2 = int(grid[4]), int(grid[5]), int(grid[6])
    c0 = min(max(int(math.floor((p[0] - grid[0]) / size)), 0), n0 - 1)
    c1 = min(max(int(math.floor((p[1] - grid[1]) / size)), 0), n1 - 1)
    c2 = min(max(int(math.floor((p[2] - grid[2]) / size)), 0), n2 - 1)
    return (c0, c1, c2), (n0, n1, n2)


@njit(inline="always")
def ring_span(c, r, n):
    """[first, last + 1) of the cells within r of cell c along one axis of n cells."""
    return max(c - r, 0), min(c + r, n - 1) + 1


@njit(inline="always")
def ring_row(c, r, n, shell):
    """(start, stop, step) of the cells of ring r along the last axis of n cells, in a row
    whose first two indices are ``shell`` (on the ring's outer layer: every cell within r
    of c) or not (only the row's two ends, c - r and c + r, those inside the grid): a ring
    visits its own cells only, O(r^2), not the whole cube around c."""
    if shell:
        first, stop = ring_span(c, r, n)
        return first, stop, 1
    first = c - r if c - r >= 0 else c + r
    last = c + r if c + r <= n - 1 else c - r
    if first > last:
        return 0, 0, 1
    return first, last + 1, max(last - first, 1)


@njit(inline="always")
def box_gap2(p, grid, i0, i1, i2):
    """A lower bound of the squared distance from p to grid cell (i0, i1, i2): a cell no
    nearer than the best triangle found holds no nearer point of any triangle listed in
    it (each is listed in every cell its box meets, the nearer part in nearer cells)."""
    size = grid[3]
    g0 = cell_gap(p[0], grid[0], size, i0)
    g1 = cell_gap(p[1], grid[1], size, i1)
    g2 = cell_gap(p[2], grid[2], size, i2)
    return max(g0, 0.0) ** 2 + max(g1, 0.0) ** 2 + max(g2, 0.0) ** 2


@njit(inline="always")
def quadratic_on_triangle(values, o, u, v, w):
    """The quadratic through a triangle's corners' values (values[o:o + 3]) and its edges'
    midpoints' (values[o + 3:o + 6], the edge opposite each corner) at barycentric (u, v,
    w). On an edge it depends on that edge's three values only: continuous across it."""
    return (
        u * (2.0 * u - 1.0) * values[o]
        + v * (2.0 * v - 1.0) * values[o + 1]
        + w * (2.0 * w - 1.0) * values[o + 2]
        + 4.0 * (v * w * values[o + 3] + w * u * values[o + 4] + u * v * values[o + 5])
    )


@njit(inline="always")
def stiffness_nearest(p, grid, starts, ids, corners, stiffness, bounds):
    """The tool's linear stiffness (N/mm) at the loadable surface's point nearest p:
    quadratic on the triangle holding it (:func:`quadratic_on_triangle`), found ring by ring
    through the grid (as ``surface_kernels.locate_on_surface``); clamped to ``bounds``, the
    least and largest stored value (a quadratic overshoots its values between them). The
    bounds are the same everywhere: a triangle's own range would differ from its
    neighbour's, and the clamped values along their edge with it (1.45 % force steps at 22
    of the liver's 1,571 shared edges: review)."""
    (c0, c1, c2), (n0, n1, n2) = grid_cell(p, grid)
    best, k = np.inf, 0.0
    for r in range(max(n0, n1, n2)):
        for i0 in range(*ring_span(c0, r, n0)):
            for i1 in range(*ring_span(c1, r, n1)):
                shell = abs(i0 - c0) == r or abs(i1 - c1) == r
                for i2 in range(*ring_row(c2, r, n2, shell)):
                    if box_gap2(p, grid, i0, i1, i2) >= best:
                        continue
                    cell = (i0 * n1 + i1) * n2 + i2
                    for q in range(int(starts[cell]), int(starts[cell + 1])):
                        t = int(ids[q])
                        u, v, w, d2 = closest_on_triangle(
                            p, vertex(corners, 3 * t), vertex(corners, 3 * t + 1),
                            vertex(corners, 3 * t + 2),
                        )  # fmt: skip
                        if d2 < best:
                            best, k = d2, quadratic_on_triangle(stiffness, 6 * t, u, v, w)
        if best <= grid_reach(p, grid, (c0, c1, c2), r) ** 2:
            break
    return min(max(k, bounds[0]), bounds[1])


@njit(inline="always")
def into_box(p, grid, margin):
    """p moved into the grid's box widened by ``margin`` cells (a point far off the organ
    would otherwise search every cell: 49 / 91 us p50 / p99 at 1e4 mm on the liver, review)."""
    size = grid[3]
    out = [0.0, 0.0, 0.0]
    for a in range(3):
        lo = grid[a] - margin * size
        hi = grid[a] + (grid[4 + a] + margin) * size
        out[a] = min(max(p[a], lo), hi)
    return out[0], out[1], out[2]


@njit(inline="always")
def scale_outside(point, table, weights, samples, points, normals, at_clamp, curve_weights):
    """A contact x clamped to the trained region's border at c takes the border's curves
    (scaled by the lattice's k(c) = ``at_clamp``, 0 without it), scaled by k(x) / D:

        D = k(b) + (k(c) - k(b)) min(1, |x - b| / L),

    k the tool's linear stiffness on the loadable surface point nearest a point, b the point
    of c's normal line level with x (c + ((x - c) . n) n), L the blend length (the tool's
    radius). Where the contact leaves the region it lies on that line (locate's map): b = x
    and the ratio is 1, so the force is continuous (k at c itself, on the chord between
    border samples 2-8 mm beneath the liver's surface, jumped 5-10 %: review). A tool radius
    beyond, the force is k(x) times the neighbours' curves per unit linear stiffness (k(b)
    there was 33 % off at the liver's worst held-out place, the lattice's k(c) 0.9 %).
    Bounded to [MIN_OUTSIDE_RATIO, MAX_OUTSIDE_RATIO]. Nothing without the outside part."""
    if table[T_OUTSIDE] == 0.0:
        return
    blend, grid, starts, ids, corners, stiffness, bounds = outside_views(table)
    c, n = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    for j in range(3):
        w, i = weights[j], int(samples[j])
        for a in range(3):
            c[a] += w * points[3 * i + a]
            n[a] += w * normals[3 * i + a]
    norm2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
    h = ((point[0] - c[0]) * n[0] + (point[1] - c[1]) * n[1] + (point[2] - c[2]) * n[2]) / norm2
    level = (c[0] + h * n[0], c[1] + h * n[1], c[2] + h * n[2])
    aside = math.sqrt((point[0] - level[0]) ** 2 + (point[1] - level[1]) ** 2
                      + (point[2] - level[2]) ** 2)  # fmt: skip
    x = into_box((point[0], point[1], point[2]), grid, 2.0)
    at_contact = stiffness_nearest(x, grid, starts, ids, corners, stiffness, bounds)
    at_level = stiffness_nearest(into_box(level, grid, 2.0), grid, starts, ids, corners,
                                 stiffness, bounds)  # fmt: skip
    denominator = at_level
    if at_clamp > 0.0:
        denominator += (at_clamp - at_level) * min(1.0, aside / blend)
    ratio = at_contact / denominator if denominator > 0.0 else 1.0
    ratio = min(max(ratio, MIN_OUTSIDE_RATIO), MAX_OUTSIDE_RATIO)
    for j in range(3):
        curve_weights[j] *= ratio


@njit(cache=True, nogil=True)
def contact_at(point, table, buf):
    """Everything that depends on the contact point only (3 finite numbers, mm): the
    sample triangle, its weights (buf[SAMPLES], buf[WEIGHTS]) and the height above it,
    the normal, the curves, buf[FLAGS] and, for the POD-ANM response, the neighbours'
    sections at the current depth."""
    (points, normals, forces, slopes, solved, triangles, planes, edges, lattice, records,
     offsets) = contact_views(table)  # fmt: skip
    weights, samples = buf[WEIGHTS : WEIGHTS + 3], buf[SAMPLES : SAMPLES + 3]
    where, scratch = buf[TRIANGLE : TRIANGLE + 2], buf[LOCATE_SCRATCH : LOCATE_SCRATCH + 3]
    flag = locate(point, points, normals, triangles, planes, edges, weights, samples, where,
                  scratch)  # fmt: skip
    curve_weights = buf[FORCE_WEIGHTS : FORCE_WEIGHTS + 3]
    at_clamp = force_weights(weights, samples, int(buf[TRIANGLE]), triangles, lattice,
                             int(table[T_LATTICE]), curve_weights)  # fmt: skip
    if flag & FLAG_OUTSIDE_REGION:
        scale_outside(point, table, weights, samples, points, normals, at_clamp, curve_weights)
    knots = int(buf[KNOTS])
    prepare_curves(weights, curve_weights, samples, normals, forces, slopes,
                   buf[NORMAL : NORMAL + 3], buf[CURVE : CURVE + knots],
                   buf[CURVE + knots : CURVE + 2 * knots])  # fmt: skip
    buf[SOLVED_DEPTH] = solved_at(weights, samples, solved)
    for c in range(3):
        buf[CONTACT_POINT + c] = point[c]
    buf[FLAGS] = flag
    if buf[ANM_N1] > 0:
        load_sections(curve_weights, samples, offsets, records, buf)
        anm_force(buf, buf[DEPTH])  # the slope and beyond flag of the new contact
    buf[CONTACTS] += 1.0


# -- nearest surface vertices; the contact and the scalpel's placement in one call each --
def point_grid(points: np.ndarray, spacing: float, max_cells: int = 2_000_000) -> np.ndarray:
    """A uniform grid over ``points`` (N, 3) for :func:`nearest_point`, built once (numpy).

    Returns [origin (3), cell size, nx, ny, nz, cell starts (nx ny nz + 1), point ids by
    cell] (float64; the GRID_* offsets). The cell size is ``spacing`` or larger if the box
    would need more than ``max_cells`` cells.
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
    return _frozen(np.concatenate([lo, [h], dims, starts, order]).astype(np.float64))


@njit(inline="always")
def cell_gap(x, origin, h, i):
    """A lower bound of the distance from coordinate x to grid cell i along one axis
    (a relative 1e-9 cell below the exact gap: never more than a point's distance)."""
    lo = origin + i * h
    return max(lo - x, x - (lo + h), 0.0) - 1e-9 * h


@njit(inline="always")
def distance2(points, i, p):
    """|point i - p|^2 (``points``: 3 N, row-major)."""
    dx, dy, dz = points[3 * i] - p[0], points[3 * i + 1] - p[1], points[3 * i + 2] - p[2]
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True)
def nearest_point(p, limit, grid, points, key, keyed, seed):
    """Index of the point nearest ``p`` within ``limit`` (mm, inclusive), -1 if none (or
    if p is not 3 finite numbers). ``points``: (3 N) row-major, ``key`` (N,).

    Only points with ``key[i] >= 0`` count if ``keyed``. Exact (the brute-force argmin's
    point, the lowest index on ties): rings of grid cells around p's cell, until the
    ring reaches past the best distance found or past ``limit``; a cell that cannot hold
    a point as near as the best so far is skipped. ``seed`` (a point index, or -1), e.g.
    the last answer, is tried first: near it, few cells are opened.
    """
    if p.shape[0] != 3 or not finite3(p):
        return -1
    ox, oy, oz, h = grid[GRID_ORIGIN], grid[GRID_ORIGIN + 1], grid[GRID_ORIGIN + 2], grid[GRID_CELL]
    nx, ny, nz = int(grid[GRID_DIMS]), int(grid[GRID_DIMS + 1]), int(grid[GRID_DIMS + 2])
    ids = GRID_STARTS + nx * ny * nz + 1  # where the point ids start
    cx = int(min(max((p[0] - ox) / h, 0.0), nx - 1.0))
    cy = int(min(max((p[1] - oy) / h, 0.0), ny - 1.0))
    cz = int(min(max((p[2] - oz) / h, 0.0), nz - 1.0))
    best, found = limit * limit, -1
    if 0 <= seed < key.shape[0] and (not keyed or key[seed] >= 0):
        d = distance2(points, seed, p)
        if d <= best:
            best, found = d, seed
    rings = min(int(limit / h) + 1, max(nx, ny, nz))
    for k in range(rings + 1):
        for ix in range(max(cx - k, 0), min(cx + k, nx - 1) + 1):
            gx = cell_gap(p[0], ox, h, ix)
            gx2 = gx * gx if gx > 0.0 else 0.0
            if gx2 > best:
                continue
            for iy in range(max(cy - k, 0), min(cy + k, ny - 1) + 1):
                gy = cell_gap(p[1], oy, h, iy)
                gxy2 = gx2 + (gy * gy if gy > 0.0 else 0.0)
                if gxy2 > best:
                    continue
                # On the ring's x or y faces every z; inside them, only its two z faces.
                if abs(ix - cx) != k and abs(iy - cy) != k:
                    iz, dz = (cz - k if cz - k >= 0 else cz + k), 2 * k
                else:
                    iz, dz = max(cz - k, 0), 1
                while iz <= min(cz + k, nz - 1):
                    gz = cell_gap(p[2], oz, h, iz)
                    if gxy2 + (gz * gz if gz > 0.0 else 0.0) <= best:
                        cell = GRID_STARTS + (ix * ny + iy) * nz + iz
                        for j in range(int(grid[cell]), int(grid[cell + 1])):
                            i = int(grid[ids + j])
                            if keyed and key[i] < 0:
                                continue
                            d = distance2(points, i, p)
                            if d < best or (d == best and (found < 0 or i < found)):
                                best, found = d, i
                    iz += dz
        # Points not seen yet are at least k h away.
        if found >= 0 and best < (k * h) * (k * h):
            break
    return found


@njit(f"int64({vec}, {ro_f8_1d}, {f8_1d})", cache=True, nogil=True)
def prepare_contact(point, table, buf):
    """``set_contact`` in one call: :func:`contact_at` ``point`` (mm) from the table
    (:func:`contact_table`), and the placement given up (buf[PLACEMENT] NaN).

    Returns the cut region's surface vertex nearest the point (within the region
    reach) if the table has a scalpel's part, else NO_VERTEX; or -WRONG_SHAPE,
    -POSITION_NOT_FINITE for a point that is not 3 finite numbers (nothing written).
    """
    if point.shape[0] != 3:
        return -WRONG_SHAPE
    if not finite3(point):
        return -POSITION_NOT_FINITE
    contact_at(point, table, buf)
    buf[PLACEMENT] = np.nan
    if table[T_VERTICES] == 0:
        return NO_VERTEX
    _, region_reach, grid, points, _, region_of = scalpel_views(table)
    return nearest_point(point, region_reach, grid, points, region_of, True, int(buf[PLACED + 1]))


@njit(f"int64({vec}, {ro_f8_1d})", cache=True, nogil=True)
def region_vertex(p, table):
    """The cut region's surface vertex nearest p within the region reach (mm), or
    NO_VERTEX (also if p is not 3 finite numbers). ``table``: :func:`scalpel_table`."""
    _, region_reach, grid, points, _, region_of = scalpel_views(table)
    return nearest_point(p, region_reach, grid, points, region_of, True, NO_VERTEX)


@njit(inline="always")
def placement_status(p, b):
    """OK if the position p and blade b are 3 finite numbers each, else a placement status."""
    if p.shape[0] != 3:
        return WRONG_SHAPE
    if b.shape[0] != 3:
        return BLADE_SHAPE
    if not finite3(p):
        return POSITION_NOT_FINITE
    if not finite3(b):
        return BLADE_NOT_FINITE
    return OK


@njit(inline="always")
def same_placement(p, b, buf):
    """Whether (p, b) is the placement in force (its contact not given up since)."""
    q = PLACEMENT
    return (p[0] == buf[q] and p[1] == buf[q + 1] and p[2] == buf[q + 2]
            and b[0] == buf[q + 3] and b[1] == buf[q + 4] and b[2] == buf[q + 5])  # fmt: skip


@njit(inline="always")
def blade_frame(b, normals, vertex, buf):
    """The blade b's unit part in the tangent plane of ``vertex`` and the unit normal of the
    blade's plane, into buf[FRAME:] ; False (nothing written) if b is zero or within ~6
    degrees of the normal."""
    n0, n1, n2 = normals[3 * vertex], normals[3 * vertex + 1], normals[3 * vertex + 2]
    size = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    bn = b[0] * n0 + b[1] * n1 + b[2] * n2
    t0, t1, t2 = b[0] - bn * n0, b[1] - bn * n1, b[2] - bn * n2  # in the tangent plane
    tangent = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if size == 0.0 or tangent <= 0.1 * size:
        return False
    t0, t1, t2 = t0 / tangent, t1 / tangent, t2 / tangent
    a0, a1, a2 = t1 * n2 - t2 * n1, t2 * n0 - t0 * n2, t0 * n1 - t1 * n0  # blade x normal
    across = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    f = FRAME
    buf[f], buf[f + 1], buf[f + 2] = t0, t1, t2
    buf[f + 3], buf[f + 4], buf[f + 5] = a0 / across, a1 / across, a2 / across
    return True


@njit(f"int64({vec}, {vec}, {ro_f8_1d}, {f8_1d})", cache=True, nogil=True)
def place_scalpel(p, b, table, buf):
    """A scalpel at ``p`` (mm) with its blade along ``b``: its frame and the contact there in
    one call (``scalpel()`` every servo tick). ``table``: the :func:`scalpel_table`.

    The surface vertex nearest p (within ``reach``, else OFF_ORGAN) gives the normal n;
    the blade is b's part in the tangent plane (BLADE_ALONG_NORMAL if it is within ~6
    degrees of n). Writes buf[FRAME:] = [unit blade (3), unit normal of the blade's plane
    (3)], buf[PLACED:] = [that vertex, the nearest vertex of the cut region within
    ``region_reach`` or -1], :func:`contact_at` p and buf[PLACEMENT:] = (p, b). The same
    placement as the one in force writes nothing. Returns the region vertex or
    NO_VERTEX; minus the status if refused (nothing written then).
    """
    status = placement_status(p, b)
    if status:
        return -status
    if same_placement(p, b, buf):
        return int(buf[PLACED + 1])
    reach, region_reach, grid, points, normals, region_of = scalpel_views(table)
    vertex = nearest_point(p, reach, grid, points, region_of, False, int(buf[PLACED]))
    if vertex < 0:
        return -OFF_ORGAN
    if not blade_frame(b, normals, vertex, buf):
        return -BLADE_ALONG_NORMAL
    if region_of[vertex] >= 0:  # the nearest vertex is the region's nearest too
        region = vertex if distance2(points, vertex, p) <= region_reach * region_reach else -1
    else:
        region = nearest_point(p, region_reach, grid, points, region_of, True,
                               int(buf[PLACED + 1]))  # fmt: skip
    contact_at(p, table, buf)
    buf[PLACED], buf[PLACED + 1] = vertex, region
    for c in range(3):
        buf[PLACEMENT + c], buf[PLACEMENT + 3 + c] = p[c], b[c]
    return region


# -- the rendered surface ------------------------------------------------------------------
@njit(inline="always")
def axpy(c, row, flat):
    """flat += c row: a contiguous row of a transposed basis (a vectorised loop)."""
    for r in range(flat.shape[0]):
        flat[r] += c * row[r]


@njit(
    f"void({f8_1d}, int64, {ro_f4_3d}, {ro_f4_3d}, {f8_3d}, {ro_f8_3d}, {f8_1d}, {f8_2d})",
    cache=True,
    nogil=True,
    fastmath=True,
)
def surface_grassmann(buf, reference, basis_t, tangents_t, frames, coefficients, scratch, out):
    """Grassmann surface displacement A(x) c(x, depth) at the last depth into out (V, 3), mm.

    ``frames`` (from :func:`prepare_grassmann`): [V cos S, V S^-1 sin S, R_0, R_1, R_2].
    c = sum_i w_i R_i c_i(depth); A(x) c = A0 (V cos S c) + Gamma(x) (V S^-1 sin S c),
    Gamma(x) = sum_i w_i Gamma_i: only n-vectors are formed before the row loops, which
    run over contiguous rows of the transposed (P, n, 3V) bases and tangents.
    """
    n = basis_t.shape[1]
    k, a, b = field_depth_weights(buf[DEPTH], buf[STEP], coefficients.shape[1] - 1)
    weights = buf[WEIGHTS : WEIGHTS + 3]
    c = scratch[3 : 3 + n]
    c[:] = 0.0
    for j in range(3):
        i = int(buf[SAMPLES + j])
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
        axpy(ca[m], basis_t[reference, m], flat)
        for j in range(3):
            w = weights[j] * cb[m]
            if w == 0.0:
                continue
            axpy(w, tangents_t[int(buf[SAMPLES + j]), m], flat)


# -- Grassmann interpolation of the bases ------------------------------------------------------
@njit(inline="always")
def jacobi_rotation(A, V, p, q):
    """Zero A[p, q] by a Jacobi rotation J: A <- J^T A J, V <- V J."""
    n = A.shape[0]
    apq = A[p, q]
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
                if A[p, q] != 0.0:
                    jacobi_rotation(A, V, p, q)
    values = np.empty(n)
    for p in range(n):
        values[p] = A[p, p]
    return values, V


@njit(f"void({f8_1d}, {ro_f8_4d}, {ro_f8_4d}, {ro_f8_3d}, {f8_3d})", cache=True)
def prepare_grassmann(buf, gtt, gtb, grb, frames):
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
    weights = buf[WEIGHTS : WEIGHTS + 3]
    vertices = np.empty(3, dtype=np.int64)  # the contact's samples
    for j in range(3):
        vertices[j] = int(buf[SAMPLES + j])
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
