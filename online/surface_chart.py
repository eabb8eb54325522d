"""The chart that carries each neighbour's surface field to the contact (built at load).

Why: PODI blends the three neighbours' fields where each was trained, so at an untrained
contact it draws three shallow dents around the tool instead of one under it. The
transported field (``interpolation="transport"``) moves each neighbour's field to the
contact before blending:

    u(X) = sum_j w_j R_j u_j(X + x_j - x)

with the shift x_j - x taken in plan coordinates and R_j the rotation from the neighbour's
normal to the contact's. Measured on the cornea demo (README, "The rendered surface"): the
surface error drops from 8-13 % to 2-3 %, and the dent's deepest point is the vertex under
the tool.

The chart: the surface seen along the samples' mean normal (their plan view) splits into
sheets, the part facing the viewer (layer 0) and the part facing away (layer 1); each is a
height field over the plan, rasterised on one uniform grid of spacing ``spacing`` (mm). A
node takes the values of the sheet triangle over it (the one nearest the viewer for layer 0,
the farthest for layer 1, where a fold covers it twice); a node no triangle covers takes the
values of the nearest covered node of its layer, so that a shifted read near a sheet's border
stays on the organ. A vertex is *charted* when the four nodes of its cell are covered and its
height is the sheet's there; the others (side walls, hidden folds) keep the blended field in
place. The grid has a halo as wide as the largest shift (the longest sample-triangle edge),
so a shifted read never leaves it.

Layouts (N = layers x rows x columns nodes, row-major; flat node index
``(layer * rows + a) * columns + b``): ``node_basis`` (P, n, 3, N) int16 (in units of
``mode_scale`` (P, n) mm), each sample's surface modes at the nodes of its own lattice
(the grid moved by less than a cell, so that the sample sits on a node: see
:func:`_node_basis`), component planes apart so the rows are contiguous; ``sample_grid``
(P, 2) the samples' places in nodes of the grid; ``vertex_node`` (V,) the flat index of
the lower-left node of each charted vertex's cell (-1: not charted) and ``vertex_frac``
(V, 2) its place in that cell; ``blocks`` (B,) the first flat nodes of the runs of LANES
nodes the kernel sums the neighbours on (:func:`node_blocks`: every node a charted vertex
reads, at any contact, and few others); ``uncharted_basis`` (P, n, 3U) the modes at the
uncharted vertices, contiguous.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from hapticrom.online.node_blocks import LANES
from hapticrom.shared.errors import ArtifactError
from hapticrom.shared.geometry import plan_view

FACING = math.cos(math.radians(75.0))  # a triangle whose normal is steeper belongs to no sheet
SPACING_PER_EDGE = 0.8  # grid spacing / the median edge of the charted triangles
MIN_MEAN_NORMAL = 0.5  # samples' mean unit normal shorter than this: no plan view
MAX_VALUES = 30_000_000  # P n 3 N, the modes on the grid (60 MB int16): coarser beyond
MAX_NODES = 1_000_000  # N: the build's own arrays and each simulator's (36 bytes a node)
MAX_RASTER = 50_000_000  # node visits of the rasterisation (the triangles' bounding boxes)
HEIGHT_TOLERANCE = 0.5  # in grid spacings: a vertex this far off its sheet is hidden
BACK_PROJECTIONS = 64  # at most, rounds of fitting the nodes to the vertices read from them
READ_BACK_TOLERANCE = 1e-3  # ... until the read-back's RMS error is this fraction of the RMS
QUANTUM = 32767  # a mode's largest value in 16 bits (node_basis)


@dataclass(frozen=True)
class SurfaceChart:
    """The plan-view grid of a model's surface and its samples' modes on it (see module)."""

    origin: np.ndarray  # (3,) mm
    axes: np.ndarray  # (2, 3) unit, the plan's axes
    spacing: float  # mm
    shape: np.ndarray  # (3,) int64: layers, rows, columns
    halo: int  # nodes of margin around the charted vertices' cells
    sample_grid: np.ndarray  # (P, 2): the samples' places in plan view, in nodes from the
    # grid's first node
    node_basis: np.ndarray  # (P, n, 3, N) int16, each on its sample's own lattice, in
    # units of mode_scale
    mode_scale: np.ndarray  # (P, n) mm: a mode's value at the nodes is node_basis times this
    vertex_node: np.ndarray  # (V,) int64, -1 where not charted
    vertex_frac: np.ndarray  # (V, 2)
    uncharted: np.ndarray  # (U,) int64: the vertices that keep the blended field
    charted: np.ndarray  # (C,) int64: the others, in the order of their cells (locality)
    charted_node: np.ndarray  # (C,) int64: vertex_node of those, in that order
    charted_frac: np.ndarray  # (2, C) float32: vertex_frac of those, in that order, a plane
    # each (the reads' first loop vectorises over the planes: surface_kernels.read_weights)
    uncharted_basis: np.ndarray  # (P, n, 3U) float32: the samples' modes at the uncharted
    # vertices, contiguous (x, y, z a vertex), for their blended field
    blocks: np.ndarray  # (B,) int64, ascending: the first flat nodes of the runs of LANES
    # nodes the kernel sums the neighbours on, covering every node a charted vertex reads
    # at any contact (node_blocks; :func:`node_blocks`)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) of a triangulated surface."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    length = np.linalg.norm(normals, axis=1)
    return normals / np.where(length > 0, length, 1.0)[:, None]


def _layers(vertices, triangles, normal):
    """Each triangle's layer (0 facing the viewer, 1 away, -1 neither) and each vertex's."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    facing = face @ normal / np.maximum(np.linalg.norm(face, axis=1), 1e-300)
    tri_layer = np.where(facing > FACING, 0, np.where(facing < -FACING, 1, -1))
    vn = vertex_normals(vertices, triangles) @ normal
    vertex_layer = np.where(vn > FACING, 0, np.where(vn < -FACING, 1, -1))
    return tri_layer, vertex_layer


def _spacing(vertices, triangles, tri_layer, extent, longest_shift, values_per_node):
    """The grid spacing: SPACING_PER_EDGE of the charted triangles' median edge, coarser
    until the grid (the halo included) has at most MAX_NODES nodes and the modes on it at
    most MAX_VALUES values: an artifact cannot make the load allocate without bound. None
    when no triangle faces the samples or no spacing fits (a halo of many times the grid:
    samples far apart over a small surface; more modes than the budget holds)."""
    t = triangles[tri_layer >= 0]
    if len(t) == 0:
        return None
    edges = np.linalg.norm(vertices[t] - vertices[np.roll(t, 1, axis=1)], axis=2)
    h = max(SPACING_PER_EDGE * float(np.median(edges)), 1e-9 * max(float(extent.max()), 1.0))
    for _ in range(200):  # x 1.25 each: 200 rounds span 19 decades
        halo = math.ceil(longest_shift / h) + 2
        nodes = 2 * math.prod(math.ceil(e / h) + 2 * halo + 2 for e in extent)
        if nodes <= MAX_NODES and nodes * values_per_node <= MAX_VALUES:
            return h
        if 2 * (2 * halo + 2) ** 2 > MAX_NODES and longest_shift / h < 1:
            break  # the halo's own nodes no longer shrink with the spacing
        h *= 1.25
    return None


def longest_sample_edge(plan: np.ndarray, sample_triangles: np.ndarray) -> float:
    """The longest edge (mm) of the sample triangles in plan view: the largest shift a
    contact inside them asks for (barycentric weights: x_j - x is within the triangle)."""
    if len(sample_triangles) == 0:
        return 0.0
    t = plan[sample_triangles]
    return float(np.max(np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2)))


def surface_chart(vertices, triangles, sample_points, sample_normals, sample_triangles,
                  surface_basis) -> SurfaceChart | None:  # fmt: skip
    """The chart of a model (see module; ``surface_basis`` (P, 3V, n)), or None where one plan
    view cannot hold it: samples facing all around (their mean unit normal shorter than
    MIN_MEAN_NORMAL, a closed organ trained all over) or no vertex facing along it."""
    if np.linalg.norm(np.mean(sample_normals, axis=0)) < MIN_MEAN_NORMAL:
        return None
    origin, axes, _ = plan_view(sample_points, sample_normals)
    normal = np.cross(axes[0], axes[1])
    plan = (vertices - origin) @ axes.T
    height = (vertices - origin) @ normal
    sample_plan = (sample_points - origin) @ axes.T
    tri_layer, vertex_layer = _layers(vertices, triangles, normal)
    charted = vertex_layer >= 0
    if not charted.any():
        return None
    lo, hi = plan[charted].min(axis=0), plan[charted].max(axis=0)
    longest = longest_sample_edge(sample_plan, sample_triangles)
    P, _, n = surface_basis.shape
    h = _spacing(vertices, triangles, tri_layer, hi - lo, longest, 3 * P * n)
    if h is None:
        return None
    halo = int(math.ceil(longest / h)) + 2
    start = lo - halo * h
    rows, columns = (int(math.ceil((hi[k] - lo[k]) / h)) + 2 * halo + 2 for k in range(2))
    shape = (2, rows, columns)
    if _raster_visits(plan, triangles[tri_layer >= 0], h) > MAX_RASTER:
        return None  # overlapping or huge triangles: PODI's blend instead (a lattice a
        # sample rasterises P times, but the fit's rounds over the vertices cost more)
    _, _, node_height, covered = _rasterise(
        plan, height, triangles, tri_layer.astype(np.int64), start, h, shape
    )
    vertex_node, vertex_frac = _vertex_cells(
        plan, height, vertex_layer, start, h, shape, covered, node_height, halo
    )
    used = vertex_node[vertex_node >= 0]
    if len(used) == 0:
        return None
    charted = np.flatnonzero(vertex_node >= 0)
    charted = charted[np.argsort(vertex_node[charted], kind="stable")].astype(np.int64)
    sample_grid = (sample_plan - start) / h
    sheet = (plan, height, triangles, tri_layer.astype(np.int64))
    node_basis, mode_scale = _node_basis(surface_basis, sheet, start, h, shape, vertex_node,
                                         sample_grid)  # fmt: skip
    uncharted = np.flatnonzero(vertex_node < 0).astype(np.int64)
    return SurfaceChart(
        origin=origin,
        axes=axes,
        spacing=h,
        shape=np.array(shape, dtype=np.int64),
        halo=halo,
        sample_grid=sample_grid,
        node_basis=node_basis,
        mode_scale=mode_scale,
        vertex_node=vertex_node,
        vertex_frac=vertex_frac,
        uncharted=uncharted,
        uncharted_basis=uncharted_basis(surface_basis, uncharted),
        charted=charted,
        charted_node=np.ascontiguousarray(vertex_node[charted]),
        charted_frac=np.ascontiguousarray(vertex_frac[charted].T, dtype=np.float32),
        blocks=node_blocks(vertex_node[charted], shape, halo),
    )


def uncharted_basis(surface_basis: np.ndarray, uncharted: np.ndarray) -> np.ndarray:
    """(P, n, 3U) float32: the rows of ``surface_basis`` (P, 3V, n) of the ``uncharted``
    vertices, transposed: a mode's values there are contiguous (the blend sums them as
    vectors; read from the whole basis, 3 -> 1 us on the cornea demo)."""
    rows = (3 * uncharted[:, None] + np.arange(3)).ravel()
    return np.ascontiguousarray(surface_basis[:, rows, :].transpose(0, 2, 1), dtype=np.float32)


def nodes_read(charted_node: np.ndarray, columns: int) -> np.ndarray:
    """The flat nodes the charted vertices' bilinear reads can touch (ascending): a cell's
    four nodes, and those of the cells a row, a column or both back (where the contact's
    fraction of a cell passes the vertex's own)."""
    steps = [da * columns + db for da in (-1, 0, 1) for db in (-1, 0, 1)]
    return np.unique(np.add.outer(np.asarray(charted_node, dtype=np.int64), steps))


def node_blocks(charted_node: np.ndarray, shape, halo: int) -> np.ndarray:
    """The first nodes of runs of LANES nodes covering :func:`nodes_read`: each starts at
    the first node the runs before it leave out, moved back where its nodes, shifted by a
    neighbour's offset (at most ``halo - 1`` rows and columns), would leave the grid. The
    cells lie ``halo`` nodes from the grid's edges (:func:`_vertex_cells`), so the runs fit;
    ArtifactError (a chart the kernel could not sum) if they do not."""
    _, _, columns = (int(v) for v in shape)
    nodes = int(np.prod(shape))
    reach = (halo - 1) * (columns + 1)
    needed = nodes_read(charted_node, columns)
    blocks = _greedy_runs(needed, nodes - LANES - reach)
    runs = blocks[:, None] + np.arange(LANES)
    if len(needed) and (blocks.min() < reach or not np.isin(needed, runs).all()):
        raise ArtifactError(
            f"the surface chart's {len(needed)} read nodes do not fit runs of {LANES} nodes "
            f"inside its {nodes}-node grid (halo {halo})"
        )
    return blocks


@njit(cache=True)
def _rasterise(plan, height, triangles, tri_layer, start, h, shape):
    """Per node: the covering triangle of its layer (nearest the viewer for layer 0,
    farthest for layer 1), its barycentric weights there, the height, and whether any
    triangle covers the node."""
    layers, rows, columns = shape
    N = layers * rows * columns
    node_tri = np.full(N, -1, dtype=np.int64)
    node_bary = np.zeros((N, 3))
    node_height = np.zeros(N)
    for t in range(triangles.shape[0]):
        layer = tri_layer[t]
        if layer < 0:
            continue
        i, j, k = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = plan[i, 0], plan[i, 1]
        e1x, e1y = plan[j, 0] - x0, plan[j, 1] - y0
        e2x, e2y = plan[k, 0] - x0, plan[k, 1] - y0
        det = e1x * e2y - e1y * e2x
        if abs(det) < 1e-300:
            continue
        a_lo = max(int(math.floor((min(x0, x0 + e1x, x0 + e2x) - start[0]) / h)), 0)
        a_hi = min(int(math.ceil((max(x0, x0 + e1x, x0 + e2x) - start[0]) / h)), rows - 1)
        b_lo = max(int(math.floor((min(y0, y0 + e1y, y0 + e2y) - start[1]) / h)), 0)
        b_hi = min(int(math.ceil((max(y0, y0 + e1y, y0 + e2y) - start[1]) / h)), columns - 1)
        for a in range(a_lo, a_hi + 1):
            px = start[0] + a * h - x0
            for b in range(b_lo, b_hi + 1):
                py = start[1] + b * h - y0
                s = (px * e2y - py * e2x) / det
                r = (e1x * py - e1y * px) / det
                if s < -1e-12 or r < -1e-12 or s + r > 1.0 + 1e-12:
                    continue
                z = (1.0 - s - r) * height[i] + s * height[j] + r * height[k]
                node = (layer * rows + a) * columns + b
                if node_tri[node] >= 0 and (z <= node_height[node]) == (layer == 0):
                    continue
                node_tri[node] = t
                node_bary[node, 0], node_bary[node, 1], node_bary[node, 2] = 1.0 - s - r, s, r
                node_height[node] = z
    return node_tri, node_bary, node_height, node_tri >= 0


@njit(cache=True)
def _greedy_runs(needed, last):
    """The first nodes of runs of LANES nodes: each at the first of the ascending ``needed``
    nodes the runs before it leave out, at most ``last``."""
    starts = np.empty(len(needed), dtype=np.int64)
    count, covered_to = 0, -1
    for node in needed:
        if node >= covered_to:
            starts[count] = min(node, last)
            covered_to = starts[count] + LANES
            count += 1
    return starts[:count].copy()


@njit(cache=True)
def _nearest_covered(covered, shape):
    """(N,) for every node the flat index of a nearest covered node of its layer (itself if
    covered): breadth-first over the 4-neighbours from all covered nodes at once, O(N). A
    layer with no covered node points at node 0 (never read: no vertex is charted there)."""
    rows, columns = shape[1], shape[2]
    N = covered.shape[0]
    source = np.full(N, -1, dtype=np.int64)
    queue = np.empty(N, dtype=np.int64)
    head = tail = 0
    for node in range(N):
        if covered[node]:
            source[node] = node
            queue[tail] = node
            tail += 1
    while head < tail:
        node = queue[head]
        head += 1
        b = node % columns
        a = (node // columns) % rows
        for da, db in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if 0 <= a + da < rows and 0 <= b + db < columns:
                other = node + da * columns + db
                if source[other] < 0:
                    source[other] = source[node]
                    queue[tail] = other
                    tail += 1
    for node in range(N):
        if source[node] < 0:
            source[node] = 0
    return source


def _raster_visits(plan, triangles, h) -> float:
    """How many nodes the rasterisation visits: the triangles' bounding boxes in nodes."""
    corners = plan[triangles]  # (T, 3, 2)
    span = np.floor((corners.max(axis=1) - corners.min(axis=1)) / h) + 2
    return float(np.sum(span[:, 0] * span[:, 1]))


def _vertex_cells(plan, height, vertex_layer, start, h, shape, covered, node_height, halo):
    """Each vertex's cell (flat lower-left node, -1 if not charted) and place in it. A cell
    lies at least ``halo`` nodes from the grid's edges (then every shifted read of the
    kernel stays inside the grid, whatever the rounding)."""
    layers, rows, columns = shape
    cell = np.floor((plan - start) / h).astype(np.int64)
    frac = np.clip((plan - start) / h - cell, 0.0, 1.0)
    a, b = cell[:, 0], cell[:, 1]
    inside = (a >= halo) & (a <= rows - 2 - halo) & (b >= halo) & (b <= columns - 2 - halo)
    ok = (vertex_layer >= 0) & inside
    layer = np.maximum(vertex_layer, 0)
    node = np.where(
        ok, (layer * rows + np.clip(a, 0, rows - 2)) * columns + np.clip(b, 0, columns - 2), 0
    )
    corners = np.stack([node, node + columns, node + 1, node + columns + 1])
    ok &= covered[corners].all(axis=0)
    fa, fb = frac[:, 0], frac[:, 1]
    weights = np.stack([(1 - fa) * (1 - fb), fa * (1 - fb), (1 - fa) * fb, fa * fb])
    sheet_height = (weights * node_height[corners]).sum(axis=0)
    ok &= np.abs(sheet_height - height) <= HEIGHT_TOLERANCE * h
    return np.where(ok, node, -1).astype(np.int64), np.ascontiguousarray(frac)


def _node_basis(surface_basis, sheet, start, h, shape, vertex_node, sample_grid):
    """(node_basis (P, n, 3, N) int16, mode_scale (P, n)): each sample's modes at the nodes
    of its own lattice (the grid moved by the fraction of a cell that puts the sample on a
    node), fitted so that the charted vertices read back their own values, then stored in
    16 bits, each mode in units of its largest value / 32767.

    Why a lattice a sample: the neighbours' shifts x_j - x then differ by whole nodes, so
    their shifted fields add on one grid without interpolating them (a second bilinear
    step smooths the dent: measured on the cornea demo, the node under the tool 3.8 % shallow
    against 0.25 %), and a vertex reads the sum once (surface_kernels.transported_surface).

    Why 16 bits: a surface streams three samples' modes (1.3 MB on the cornea demo in single
    precision), and half the bytes is a fifth less time (the neighbours' sums at stop 35: 19
    against 15 us); the rounding is 1.5e-5 of a mode's largest value, far below the fit's tolerance.

    The nodes first take the surface's values (barycentric in the covering triangle of each
    node's source); a bilinear read at a vertex then smooths a sharp dent (measured on the
    cornea demo: the node under the tool 1-5 % shallow). Rounds of residual correction
    (each vertex's read-back error spread to the nodes the same way) bring the read-back
    to the vertex values, until its RMS error is READ_BACK_TOLERANCE of the values' RMS, or
    BACK_PROJECTIONS rounds (a Richardson iteration: 4-6 rounds on the cornea demo, where
    the grid is finer than the mesh; more on a coarse mesh).
    """
    plan, height, triangles, tri_layer = sheet
    P, rows3, n = surface_basis.shape
    modes = surface_basis.reshape(P, rows3 // 3, 3 * n)
    layer = np.where(vertex_node >= 0, vertex_node // (shape[1] * shape[2]), -1)
    out = np.empty((P, n, 3, int(np.prod(shape))), dtype=np.int16)
    scale = np.zeros((P, n))
    fitted = np.empty((1, *out.shape[1:]), dtype=np.float32)
    for i in range(P):
        origin = start + (sample_grid[i] - np.floor(sample_grid[i])) * h
        node_tri, node_bary, _, covered = _rasterise(plan, height, triangles, tri_layer, origin,
                                                     h, shape)  # fmt: skip
        source = _nearest_covered(covered, np.array(shape, dtype=np.int64))
        corners = np.ascontiguousarray(triangles[np.maximum(node_tri[source], 0)])
        cells, frac = _lattice_cells(plan, layer, origin, h, shape, covered)
        _fit_nodes(modes[i : i + 1], corners, node_bary[source], cells, frac, shape[2],
                   BACK_PROJECTIONS, READ_BACK_TOLERANCE, fitted)  # fmt: skip
        if not np.all(np.isfinite(fitted)):  # float32 overflow of a finite basis near its max
            raise ArtifactError(
                "samples/surface_basis: its modes overflow single precision on the surface chart"
            )
        # in double precision: a float32 scale of a tiny mode (1e-40) is subnormal, and the
        # ratio then passes 32767 and wraps in int16 (found by review: signs flipped)
        largest = np.abs(fitted[0]).astype(np.float64).max(axis=(1, 2))
        scale[i] = largest / QUANTUM
        safe = np.where(scale[i] > 0.0, scale[i], 1.0)[:, None, None]
        out[i] = np.clip(np.rint(fitted[0] / safe), -QUANTUM, QUANTUM)
    return out, scale


def _lattice_cells(plan, layer, origin, h, shape, covered):
    """Each charted vertex's cell (flat lower-left node; -1 for the others and where a
    corner is not covered) and place in it, on the lattice whose first node is ``origin``:
    the chart's grid moved by less than a cell, so the cell stays inside the grid."""
    _, rows, columns = shape
    q = (plan - origin) / h
    cell = np.clip(np.floor(q).astype(np.int64), 0, [rows - 2, columns - 2])
    frac = np.ascontiguousarray(np.clip(q - cell, 0.0, 1.0))
    node = (np.maximum(layer, 0) * rows + cell[:, 0]) * columns + cell[:, 1]
    ok = layer >= 0
    for corner in (node, node + columns, node + 1, node + columns + 1):
        ok &= covered[corner]
    return np.where(ok, node, -1).astype(np.int64), frac


@njit(cache=True)
def _fit_nodes(modes, corners, bary, vertex_node, vertex_frac, columns, rounds, tolerance,
               out):  # fmt: skip
    """out[i, m, c, node] for every sample i (see :func:`_node_basis`); ``modes`` (P, V, 3n)."""
    P, V, width = modes.shape
    N = corners.shape[0]
    nodes = np.zeros((N, width))
    residual = np.zeros((V, width))
    for i in range(P):
        exact = modes[i].astype(np.float64)
        _spread(exact, corners, bary, nodes, False)
        scale = tolerance**2 * np.sum(exact**2)
        previous = np.inf
        for _ in range(rounds):
            residual[:, :] = 0.0
            for v in range(V):
                s = vertex_node[v]
                if s < 0:
                    continue
                fa, fb = vertex_frac[v, 0], vertex_frac[v, 1]
                for k in range(width):
                    read = (
                        (1 - fa) * (1 - fb) * nodes[s, k]
                        + fa * (1 - fb) * nodes[s + columns, k]
                        + (1 - fa) * fb * nodes[s + 1, k]
                        + fa * fb * nodes[s + columns + 1, k]
                    )
                    residual[v, k] = exact[v, k] - read
            squared = np.sum(residual**2)
            if squared <= scale or squared >= previous:  # converged, or no longer converging
                break
            previous = squared
            _spread(residual, corners, bary, nodes, True)
        for node in range(N):
            for k in range(width):
                out[i, k % (width // 3), k // (width // 3), node] = nodes[node, k]


@njit(cache=True)
def _spread(values, corners, bary, nodes, add):
    """nodes (N, w) (+)= the surface values (V, w) at each node (barycentric)."""
    for node in range(corners.shape[0]):
        a, b, c = corners[node, 0], corners[node, 1], corners[node, 2]
        wa, wb, wc = bary[node, 0], bary[node, 1], bary[node, 2]
        for k in range(values.shape[1]):
            value = wa * values[a, k] + wb * values[b, k] + wc * values[c, k]
            nodes[node, k] = nodes[node, k] + value if add else value
