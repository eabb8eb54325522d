"""Position in, force out: a spherical tool tip against the organ, with a proxy (mm, N).

A haptic device reports where the tool tip is, not where the tissue is. The sphere of
radius R centred at the tip touches the surface where the tip comes within R of it, so
the tip is tested against the *offset sheet*: the loadable surface triangles with each
vertex moved by R along its outward normal (:func:`contact_surface`, built once). The
*proxy* (god-object: Zilles and Salisbury 1995; Ruspini et al. 1997) is where the tip
would be if the tissue did not yield:

- free: the proxy is the tip. A move whose segment enters the sheet from outside (the
  first crossing along it, :func:`first_crossing`) puts the proxy there: first contact,
  however fast the move, however thin the organ.
- in contact: the proxy walks over the sheet's triangles, through shared edges and
  vertices, to the point of the sheet nearest the tip (:func:`walk`), never through the
  sheet: it cannot pop to the far side of a thin organ or past an edge.
- release: when the tip is outside the sheet (above it along the normal at the proxy).
  At the sheet's border (where the loadable surface ends, not the organ) the proxy stays
  on the border; a tip far beside it (beyond the displacement limit) fades out of
  contact over as long again, without a force jump.

The contact point is the proxy's foot on the surface (the same barycentric point of the
undeformed triangle), and the depth is the tip's distance behind the sheet along the
sheet's normal at the proxy (the normals of the triangles' corners, blended), so that it
is zero exactly where the tool leaves the sheet: no force jump at release. The reduced
model takes it from there as it does for ``set_contact`` and ``step_displacement``: the
force along the model's normal at the contact (plus, with Coulomb friction, a tangential
force from a proxy that sticks and slips: "Coulomb friction" below), where that normal is
within 60 degrees of the sheet's (fading out to 90 degrees: a surface facing away from the trained
normals, e.g. inverted triangles, would otherwise pull the tool in). A tip that started inside
the organ (or entered it from the side, below the sheet) feels nothing until it leaves
and enters again from outside: no force jumps from nowhere.

Why the undeformed surface: in the reduced model only the tool deforms the tissue, and it
deforms it exactly where the tool is: the deformed surface meets the tool at the proxy
(to the contact consistency of the surface field), so the tip is in contact with the
deformed tissue exactly when it is in the undeformed one. With a second tool that would
no longer hold (the hyper-reduced model's issue).

Everything is one read-only table (:func:`contact_surface`) and one state array per
simulator (:data:`STATE_*`); the kernels allocate nothing.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from hapticrom.online import kernels as k
from hapticrom.online.kernels import closest_on_triangle  # noqa: F401 - here before
from hapticrom.shared.artifact_rules import MAX_LENGTH
from hapticrom.shared.geometry import vertex_normals

# -- the sheet table: one read-only float64 array ------------------------------------------
# header: triangles T, vertices V, radius R, grid origin (3), cell size, dims (3), the
# vertex->triangle list's length L; then offset vertices (3 V), vertex normals (3 V),
# surface vertices (3 V), triangles (3 T), neighbours across each edge (3 T; edge k is
# opposite corner k; -1 on the border), face normals (3 T), vertex->triangles offsets
# (V + 1) and list (L), grid cell starts (cells + 1) and triangles by cell.
S_TRIANGLES, S_VERTICES, S_RADIUS, S_ORIGIN, S_CELL, S_DIMS, S_INCIDENT = 0, 1, 2, 3, 6, 7, 10
S_HEADER = 11

# -- the proxy's state: one float64 array per simulator -------------------------------------
STATE_MODE = 0  # NEVER (no position yet), FREE, TOUCHING
STATE_PROXY = 1  # (3) the proxy (mm): on the sheet when touching, the tip when free
STATE_TRIANGLE = 4  # the sheet triangle holding the proxy (when touching)
STATE_BARY = 5  # (3) the proxy's barycentric coordinates in it
STATE_QUERY = 8  # queries so far (the stamps below say which triangle a query has tested)
STATE_SATURATED = 9  # 1 if the last step's displacement was held at the simulator's limit
STATE_D = 10  # (3) scratch: the displacement handed to the response
STATE_WHERE = 13  # (4) scratch: the walk's triangle and barycentric coordinates
STATE_FOOT = 17  # (3) the contact point: the proxy's foot on the undeformed surface (mm)
STATE_SLIDE = 20  # (4) scratch: where a proxy slipping with friction goes (as STATE_WHERE)
STATE_CONTACT = 24  # (2) the last step's own normal force (N) and dF_n/ddepth (N/mm), before
# any softening by cuts: what friction's stick test needs of the last step (see friction_proxy)
STATE_STAMPS = 26  # (T) the last query that tested each triangle
NEVER, FREE, TOUCHING = 0.0, 1.0, 2.0
MAX_WALK = 512  # triangles a proxy crosses in one step (a faster move goes on at the next)
# The trained response pushes along the model's normal at the contact: where the sheet faces
# more than 60 degrees away from it (the artifact rules' tolerance between sample triangles
# and their normals) the contact fades out, and beyond 90 degrees, where that force would
# pull the tool into the sheet instead of out of it (energy into the device), it is free.
MIN_ALIGNMENT = 0.5  # cos 60 degrees
FOLDED = 1e-6  # |sum of a vertex's area vectors| / sum of their lengths: the sheet folds there


def state_size(table: np.ndarray) -> int:
    """Length of a proxy state array for the sheet ``table``."""
    return STATE_STAMPS + int(table[S_TRIANGLES])


def contact_surface(vertices, triangles, groups, radius: float, max_cells: int = 200_000):
    """The offset sheet of the loadable triangles (``groups`` == 1) for a tip of ``radius``
    (mm), packed into one read-only table (layout above). ValueError (naming the dataset)
    if there is no loadable triangle, a loadable vertex lies beyond ``MAX_LENGTH``, or the
    loadable surface folds onto itself (a vertex whose triangles' normals cancel: the sheet
    has no outward side there); ValueError too for a radius that is not in (0, MAX_LENGTH]."""
    if not 0.0 < radius <= MAX_LENGTH:  # (NaN fails too) the offset must stay finite
        raise ValueError(f"the tool radius must lie in (0, {MAX_LENGTH:g}] mm, got {radius!r}")
    vertices = np.asarray(vertices, dtype=np.float64)
    loadable = np.asarray(triangles, dtype=np.int64)[np.asarray(groups) == 1]
    if len(loadable) == 0:
        raise ValueError(
            "surface/groups: the surface has no loadable triangle: nothing for a tool to touch"
        )
    used, local = np.unique(loadable, return_inverse=True)
    tri = local.reshape(-1, 3)
    x = vertices[used]
    if not np.all(np.abs(x) <= MAX_LENGTH):  # the kernels square distances: no overflow
        raise ValueError(f"surface/vertices: a loadable vertex lies beyond {MAX_LENGTH:g} mm")
    _refuse_folds(x, tri, used)
    normals = vertex_normals(x, tri)
    offset = x + radius * normals
    face = np.cross(offset[tri[:, 1]] - offset[tri[:, 0]], offset[tri[:, 2]] - offset[tri[:, 0]])
    face /= np.maximum(np.linalg.norm(face, axis=1), 1e-300)[:, None]
    incident_starts, incident = _incident(tri, len(x))
    grid = triangle_grid(offset, tri, max_cells)
    header = np.zeros(S_HEADER)
    header[S_TRIANGLES], header[S_VERTICES], header[S_RADIUS] = len(tri), len(x), radius
    header[S_ORIGIN : S_ORIGIN + 3], header[S_CELL] = grid[0], grid[1]
    header[S_DIMS : S_DIMS + 3], header[S_INCIDENT] = grid[2], len(incident)
    parts = [header, offset, normals, x, tri, _neighbours(tri), face, incident_starts,
             incident, grid[3], grid[4]]  # fmt: skip
    table = np.concatenate([np.ravel(np.asarray(a, dtype=np.float64)) for a in parts])
    table.flags.writeable = False
    return table


def _refuse_folds(x: np.ndarray, tri: np.ndarray, used: np.ndarray) -> None:
    """ValueError naming the first vertex where the loadable triangles' area vectors cancel
    (a triangle and its reverse, a sheet folded flat): no outward normal, no offset."""
    area = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    sums, lengths = np.zeros_like(x), np.zeros(len(x))
    for corner in range(3):
        np.add.at(sums, tri[:, corner], area)
        np.add.at(lengths, tri[:, corner], np.linalg.norm(area, axis=1))
    folded = np.flatnonzero(np.linalg.norm(sums, axis=1) <= FOLDED * lengths)
    if len(folded):
        i = int(used[folded[0]])
        raise ValueError(
            f"surface/triangles: the loadable surface folds onto itself at vertex {i} "
            f"({np.round(x[folded[0]], 3).tolist()} mm): its triangles' normals cancel"
        )


def _neighbours(tri: np.ndarray) -> np.ndarray:
    """(T, 3): the triangle across the edge opposite each corner, -1 on the border (and on
    a non-manifold edge, which a walk must not cross)."""
    T = len(tri)
    edges = np.stack([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]], axis=1).reshape(-1, 2)
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    out = np.full(3 * T, -1, dtype=np.int64)
    shared = np.flatnonzero(counts[inverse] == 2)
    order = shared[np.argsort(inverse[shared], kind="stable")]
    a, b = order[0::2], order[1::2]  # the two sides of each interior edge
    out[a], out[b] = b // 3, a // 3
    return out.reshape(T, 3)


def _incident(tri: np.ndarray, V: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR of the triangles at each vertex: (starts (V + 1), triangle ids)."""
    corners = tri.ravel()
    order = np.argsort(corners, kind="stable")
    starts = np.searchsorted(corners[order], np.arange(V + 1))
    return starts, order // 3


def triangle_grid(points: np.ndarray, tri: np.ndarray, max_cells: int,
                   max_entries: int = 4_000_000):  # fmt: skip
    """A uniform grid over the triangles' boxes: (origin, cell, dims, starts, ids); each
    triangle listed in every cell its bounding box meets. The cell starts at twice the
    mean edge and doubles while the grid would need more than ``max_cells`` cells or list
    more than ``max_entries`` triangles (a few huge triangles among small ones), or than
    the triangles themselves where they are more (each is listed once at least: a bound
    below that would never be met)."""
    max_entries = max(max_entries, len(tri))
    corners = points[tri]
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    origin, extent = points.min(axis=0), np.maximum(np.ptp(points, axis=0), 1e-9)
    edge = float(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1).mean())
    cell = max(2.0 * edge, 1e-9 * float(extent.max()))
    while True:
        dims = np.floor(extent / cell).astype(np.int64) + 1
        a = np.minimum(((lo - origin) / cell).astype(np.int64), dims - 1)
        span = np.minimum(((hi - origin) / cell).astype(np.int64), dims - 1) - a + 1
        count = span.prod(axis=1)
        if np.prod(dims) <= max_cells and count.sum() <= max_entries:
            break
        cell *= 2.0
    ids = np.repeat(np.arange(len(tri)), count)
    r = np.arange(len(ids)) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[ids, 1], span[ids, 2]
    ix, iy, iz = a[ids, 0] + r // (sy * sz), a[ids, 1] + (r // sz) % sy, a[ids, 2] + r % sz
    cells = (ix * dims[1] + iy) * dims[2] + iz
    order = np.argsort(cells, kind="stable")
    starts = np.searchsorted(cells[order], np.arange(int(np.prod(dims)) + 1))
    return origin, cell, dims, starts, ids[order]


@njit(inline="always")
def sheet_views(s):
    """The sheet table's parts (flat): offset vertices, normals, surface vertices,
    triangles, neighbours, face normals, incident starts, incident ids, cell starts, ids."""
    T, V, L = int(s[S_TRIANGLES]), int(s[S_VERTICES]), int(s[S_INCIDENT])
    cells = int(s[S_DIMS]) * int(s[S_DIMS + 1]) * int(s[S_DIMS + 2])
    a = S_HEADER
    b, c, d = a + 3 * V, a + 6 * V, a + 9 * V
    e, f, g = d + 3 * T, d + 6 * T, d + 9 * T
    h, i, j = g + V + 1, g + V + 1 + L, g + V + 1 + L + cells + 1
    return s[a:b], s[b:c], s[c:d], s[d:e], s[e:f], s[f:g], s[g:h], s[h:i], s[i:j], s[j:]


# -- geometry on one triangle ------------------------------------------------------------------
@njit(inline="always")
def corners(offset, triangles, t):
    a, b, c = int(triangles[3 * t]), int(triangles[3 * t + 1]), int(triangles[3 * t + 2])
    return k.vertex(offset, a), k.vertex(offset, b), k.vertex(offset, c)


@njit(cache=True, nogil=True)
def walk(p, sheet, t, out):
    """From sheet triangle t, the proxy's walk to the point of the sheet nearest p: to a
    neighbour across an edge (or around a vertex) holding a strictly nearer point, until
    none does or MAX_WALK triangles. Writes (triangle, barycentric u, v, w) into out (4)
    and returns whether the nearest point is on the sheet's border (an edge without a
    neighbour)."""
    offset, _, _, triangles, neighbours, _, inc_starts, incident, _, _ = sheet_views(sheet)
    a, b, c = corners(offset, triangles, t)
    u, v, w, best = closest_on_triangle(p, a, b, c)
    for _ in range(MAX_WALK):
        bary = (u, v, w)
        nxt, nu, nv, nw, nbest = -1, 0.0, 0.0, 0.0, best * (1.0 - 1e-12)
        for corner in range(3):
            if bary[corner] > 0.0:
                continue  # the nearest point is not on the edge opposite this corner
            s = int(neighbours[3 * t + corner])
            if s >= 0:
                a, b, c = corners(offset, triangles, s)
                su, sv, sw, d = closest_on_triangle(p, a, b, c)
                if d < nbest:
                    nxt, nu, nv, nw, nbest = s, su, sv, sw, d
        for corner in range(3):
            if bary[corner] < 1.0:
                continue  # at a vertex: every triangle around it
            x = int(triangles[3 * t + corner])
            for i in range(int(inc_starts[x]), int(inc_starts[x + 1])):
                s = int(incident[i])
                a, b, c = corners(offset, triangles, s)
                su, sv, sw, d = closest_on_triangle(p, a, b, c)
                if d < nbest:
                    nxt, nu, nv, nw, nbest = s, su, sv, sw, d
        if nxt < 0:
            break
        t, u, v, w, best = nxt, nu, nv, nw, nbest
    out[0], out[1], out[2], out[3] = t, u, v, w
    bary = (u, v, w)
    for corner in range(3):
        if bary[corner] <= 0.0 and neighbours[3 * t + corner] < 0:
            return True
    return False


@njit(inline="always")
def segment_hits(p0, e, a, b, c, face):
    """Where the segment p0 + s e (0 <= s <= 1) enters triangle (a, b, c) from its outer
    side (face: the outward unit normal): s, or 2.0 if it does not (Moller-Trumbore, its
    edges included so that a segment through an edge finds one of its two triangles)."""
    if e[0] * face[0] + e[1] * face[1] + e[2] * face[2] >= 0.0:
        return 2.0  # leaving, or along the sheet
    e1, e2 = k.minus(b, a), k.minus(c, a)
    q = k.cross(e, e2)
    det = k.dot(e1, q)
    if det == 0.0:
        return 2.0
    f = 1.0 / det
    r = k.minus(p0, a)
    u = f * k.dot(r, q)
    tol = 1e-12
    if u < -tol or u > 1.0 + tol:
        return 2.0
    g = k.cross(r, e1)
    v = f * k.dot(e, g)
    if v < -tol or u + v > 1.0 + tol:
        return 2.0
    s = f * k.dot(e2, g)
    return s if -tol <= s <= 1.0 else 2.0


@njit(cache=True, nogil=True)
def first_crossing(p0, p1, sheet, state):
    """The first sheet triangle the segment p0 -> p1 enters from outside: (triangle, s
    along it), or (-1, 2.0). Tests the triangles listed in the grid cells of the
    segment's box, each once (the state's stamps); all of them if the box has more cells
    than there are triangles (a jump across the organ)."""
    offset, _, _, triangles, _, faces, _, _, starts, ids = sheet_views(sheet)
    T = int(sheet[S_TRIANGLES])
    state[STATE_QUERY] += 1.0
    query = state[STATE_QUERY]
    e = k.minus(p1, p0)
    x0, x1, ok0 = _cells_along(p0, p1, sheet, 0)
    y0, y1, ok1 = _cells_along(p0, p1, sheet, 1)
    z0, z1, ok2 = _cells_along(p0, p1, sheet, 2)
    if not (ok0 and ok1 and ok2):
        return -1, 2.0  # the segment's box misses the grid
    count = (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)
    best, found = 2.0, -1
    if count > T:
        for t in range(T):
            s = _crossing(p0, e, offset, triangles, faces, t)
            if s < best:
                best, found = s, t
        return found, best
    ny, nz = int(sheet[S_DIMS + 1]), int(sheet[S_DIMS + 2])
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            for iz in range(z0, z1 + 1):
                i = (ix * ny + iy) * nz + iz
                for m in range(int(starts[i]), int(starts[i + 1])):
                    t = int(ids[m])
                    if state[STATE_STAMPS + t] == query:
                        continue
                    state[STATE_STAMPS + t] = query
                    s = _crossing(p0, e, offset, triangles, faces, t)
                    if s < best:
                        best, found = s, t
    return found, best


@njit(inline="always")
def _cells_along(p0, p1, sheet, c):
    """The grid cells (first, last) the segment's box spans along axis c, and whether it
    meets the grid at all."""
    dims, cell, origin = int(sheet[S_DIMS + c]), sheet[S_CELL], sheet[S_ORIGIN + c]
    lo = (min(p0[c], p1[c]) - origin) / cell
    hi = (max(p0[c], p1[c]) - origin) / cell
    if not (hi >= 0.0 and lo < dims):
        return 0, -1, False
    return int(max(lo, 0.0)), int(min(hi, dims - 1.0)), True  # clipped before int: no overflow


@njit(inline="always")
def _crossing(p0, e, offset, triangles, faces, t):
    a, b, c = corners(offset, triangles, t)
    return segment_hits((p0[0], p0[1], p0[2]), e, a, b, c, k.vertex(faces, t))


# -- the step ----------------------------------------------------------------------------------
@njit(inline="always")
def proxy_frame(sheet, t, u, v, w):
    """(the proxy on the offset sheet, its foot on the surface, the blended unit normal)
    at barycentric (u, v, w) of sheet triangle t."""
    offset, normals, points, triangles, _, _, _, _, _, _ = sheet_views(sheet)
    a, b, c = int(triangles[3 * t]), int(triangles[3 * t + 1]), int(triangles[3 * t + 2])
    x = _blend(k.vertex(offset, a), k.vertex(offset, b), k.vertex(offset, c), u, v, w)
    q = _blend(k.vertex(points, a), k.vertex(points, b), k.vertex(points, c), u, v, w)
    n = _blend(k.vertex(normals, a), k.vertex(normals, b), k.vertex(normals, c), u, v, w)
    norm = math.sqrt(k.dot(n, n))
    scale = 1.0 / norm if norm > 0.0 else math.nan  # normals that cancel: NaN, the tool free
    return x, q, (n[0] * scale, n[1] * scale, n[2] * scale)


@njit(inline="always")
def _blend(a, b, c, u, v, w):
    return (u * a[0] + v * b[0] + w * c[0], u * a[1] + v * b[1] + w * c[1],
            u * a[2] + v * b[2] + w * c[2])  # fmt: skip


@njit(inline="always")
def release(p, state, buf):
    """The tool is free: the proxy follows the tip, no force (the field back to depth 0)."""
    state[STATE_MODE] = FREE
    state[STATE_PROXY], state[STATE_PROXY + 1], state[STATE_PROXY + 2] = p[0], p[1], p[2]
    state[STATE_SATURATED] = 0.0
    buf[k.SLIPPING] = 0.0
    if buf[k.CONTACTS] == 0.0:  # never touched: nothing to take back to depth 0
        for c in range(3):
            buf[k.FORCE + c] = 0.0
        buf[k.DEPTH] = 0.0
        buf[k.FLAGS] = k.FLAG_NO_CONTACT
        return
    d = state[STATE_D : STATE_D + 3]
    d[0], d[1], d[2] = 0.0, 0.0, 0.0
    respond(d, buf)


@njit(inline="always")
def aligned(n, buf):
    """1 where the sheet's normal n is within 60 degrees of the model's at the contact (the
    force's direction), fading to 0 at 90 degrees and beyond (see MIN_ALIGNMENT)."""
    c = n[0] * buf[k.NORMAL] + n[1] * buf[k.NORMAL + 1] + n[2] * buf[k.NORMAL + 2]
    return min(1.0, max(0.0, c / MIN_ALIGNMENT))


@njit(inline="always")
def respond(d, buf):
    """The response's displacement step (the POD-ANM series or the stored curves)."""
    if buf[k.ANM_N1] > 0:
        return k.step_displacement_anm(d, buf)
    return k.step_displacement_curves(d, buf)


# -- Coulomb friction ------------------------------------------------------------------------
# The proxy sticks where it is while the tangential force it implies is inside the static
# friction cone, and slips towards the frictionless goal g (the sheet's point nearest the tip)
# otherwise (Salcudean and Vlaar 1997; CHAI3D's finger proxy does it with angles). The
# tangential force is a spring between them, across the model's normal m at the contact:
# F_t = -k_t delta (delta: g - proxy across m; zero without friction, exactly), with k_t a
# multiple of the normal contact stiffness dF_n/ddepth (2 (1 - nu) / (2 - nu), Mindlin 1949,
# = 2/3 for incompressible tissue, by default). Stuck while k_t |delta| <= mu_s F_n; else
# F_t = -mu_d F_n delta / |delta| and the proxy goes to mu_d F_n / k_t behind the goal. A
# sliding proxy slides on while k_t |delta| > mu_d F_n (the dynamic cone: Harwin and Melder
# 2002), so a steady slide feels mu_d F_n, not a stick-slip buzz; it sticks again when the
# tip stops or turns back, and needs the static cone to slide again. The reduced model's
# field stays the normal indentation: the tissue's tangential drag is not in it (the
# hyper-reduced model's issue).
@njit(inline="always")
def friction_proxy(goal, sheet, state, buf, where):
    """Where the proxy goes with friction, from where it was (the frictionless goal, and in
    where its place as walk writes it): it stays (returns True, where := the proxy's place)
    while k_t |delta| <= mu F_n (mu: mu_s if it was stuck, mu_d if it was sliding), else it
    slides to mu_d F_n / k_t behind the goal (returns False, where := there). F_n and k_t
    are the last step's own, as the kernel computed them (STATE_CONTACT: not softened by a
    cut, not another call's; one step of lag: the force itself obeys the law exactly,
    add_friction). No normal force: the frictionless goal."""
    fn = state[STATE_CONTACT]
    kt = buf[k.FRICTION + 2] * state[STATE_CONTACT + 1]
    if not (fn > 0.0 and kt > 0.0):
        return False
    t0 = int(state[STATE_TRIANGLE])
    x0, _, _ = proxy_frame(sheet, t0, state[STATE_BARY], state[STATE_BARY + 1],
                           state[STATE_BARY + 2])  # fmt: skip
    _, dl = _lateral(goal, x0, buf)
    # (sliding: the dynamic cone, where the last slide left the proxy to round-off: a tip
    # that stopped finds it there, and it sticks)
    cone = buf[k.FRICTION + 1] * (1.0 + 1e-9) if buf[k.SLIPPING] > 0.0 else buf[k.FRICTION]
    if kt * dl <= cone * fn:
        where[0] = t0
        for c in range(3):
            where[1 + c] = state[STATE_BARY + c]
        return True
    # Along the chord from the goal to the proxy (both on the sheet), not across m alone: the
    # sheet may be tilted from m's tangent plane (outside the trained region m is the border
    # sample's), and a target moved across m only lands on the sheet short of the lag, by the
    # tilt's cosine squared (the proxy then sticks again below the dynamic cone).
    s = min(buf[k.FRICTION + 1] * fn / kt, dl) / dl
    target = (goal[0] + s * (x0[0] - goal[0]), goal[1] + s * (x0[1] - goal[1]),
              goal[2] + s * (x0[2] - goal[2]))  # fmt: skip
    slide = state[STATE_SLIDE : STATE_SLIDE + 4]
    walk(target, sheet, t0, slide)
    x1, _, n1 = proxy_frame(sheet, int(slide[0]), slide[1], slide[2], slide[3])
    if k.finite3(x1) and k.finite3(n1):  # (else a degenerate triangle: the goal)
        for c in range(4):
            where[c] = slide[c]
    return False


@njit(inline="always")
def normal_force(buf):
    """The last step's force along the model's normal (N; the friction is across it)."""
    return (buf[k.FORCE] * buf[k.NORMAL] + buf[k.FORCE + 1] * buf[k.NORMAL + 1]
            + buf[k.FORCE + 2] * buf[k.NORMAL + 2])  # fmt: skip


@njit(inline="always")
def _lateral(goal, x, buf):
    """The goal's offset from the proxy x across the model's normal, and its length."""
    m = (buf[k.NORMAL], buf[k.NORMAL + 1], buf[k.NORMAL + 2])
    r = k.minus(goal, x)
    h = k.dot(r, m)
    lateral = (r[0] - h * m[0], r[1] - h * m[1], r[2] - h * m[2])
    return lateral, math.sqrt(k.dot(lateral, lateral))


@njit(inline="always")
def add_friction(goal, x, stuck, fn, slope, buf):
    """The tangential force on the tool, added to the step's normal force fn m (slope: its
    dF_n/ddepth): -k_t delta while stuck and within the static cone, else mu_d F_n against
    the slip (delta: the frictionless goal's offset from the proxy x). SLIPPING says which."""
    lateral, dl = _lateral(goal, x, buf)
    if not (fn > 0.0 and dl > 0.0):
        return
    kt = buf[k.FRICTION + 2] * slope
    if stuck and kt * dl <= buf[k.FRICTION] * fn:
        scale = kt
    else:
        scale = buf[k.FRICTION + 1] * fn / dl
        buf[k.SLIPPING] = 1.0
    for c in range(3):
        buf[k.FORCE + c] -= scale * lateral[c]


@njit(f"int64({k.vec}, {k.ro_f8_1d}, {k.f8_1d}, {k.ro_f8_1d}, {k.f8_1d})", cache=True,
      nogil=True)  # fmt: skip
def step_position(tip, sheet, state, table, buf):
    """The tool tip's centre (mm) in, the force on the tool (N) into buf (FORCE): the
    proxy's step (module docstring), then the contact at the proxy's foot
    (``kernels.prepare_contact``) and the response to d = tip - proxy.

    Returns the cut region's surface vertex nearest the contact (as prepare_contact; -1
    also when free), or minus a status (WRONG_SHAPE, POSITION_NOT_FINITE: nothing written). A
    displacement beyond the simulator's limit is held at the limit (STATE_SATURATED 1).
    """
    if tip.shape[0] != 3:
        return -k.WRONG_SHAPE
    if not k.finite3(tip):
        return -k.POSITION_NOT_FINITE  # (-NOT_FINITE would read as NO_VERTEX)
    p = (tip[0], tip[1], tip[2])
    mode = state[STATE_MODE]
    if mode == NEVER:  # the first position: free, wherever it is (inside: see the docstring)
        release(p, state, buf)
        return k.NO_VERTEX
    if mode == FREE:
        t, _ = first_crossing(state[STATE_PROXY : STATE_PROXY + 3], p, sheet, state)
        if t < 0:
            release(p, state, buf)
            return k.NO_VERTEX
    else:
        t = int(state[STATE_TRIANGLE])
    where = state[STATE_WHERE : STATE_WHERE + 4]
    border = walk(p, sheet, t, where)
    t = int(where[0])
    x, q, n = proxy_frame(sheet, t, where[1], where[2], where[3])
    if not (k.finite3(x) and k.finite3(n)):  # a degenerate triangle (zero area or normal)
        release(p, state, buf)
        return k.NO_VERTEX
    r = k.minus(p, x)
    height = k.dot(r, n)
    lateral2 = k.dot(r, r) - height * height
    # Beyond the sheet's border the organ goes on (the loadable surface ends, the tissue
    # does not): the proxy stays on the border and the tip keeps its depth along the
    # normal there, until it is farther beside the border than the displacement limit L;
    # from L to 2 L the displacement fades to nothing (no force jump), then the tool is free.
    reach = buf[k.MAX_DISPLACEMENT]
    fade = min(1.0, max(0.0, 2.0 - math.sqrt(max(lateral2, 0.0)) / reach)) if border else 1.0
    if height >= 0.0 or fade <= 0.0:
        release(p, state, buf)
        return k.NO_VERTEX
    goal, stuck = x, False  # the frictionless proxy: the sheet's point nearest the tip
    if mode == TOUCHING and buf[k.FRICTION] > 0.0:
        stuck = friction_proxy(goal, sheet, state, buf, where)
        t = int(where[0])
        x, q, n = proxy_frame(sheet, t, where[1], where[2], where[3])
    state[STATE_MODE], state[STATE_TRIANGLE] = TOUCHING, t
    for c in range(3):
        state[STATE_PROXY + c] = x[c]
        state[STATE_BARY + c] = where[1 + c]
    foot = state[STATE_FOOT : STATE_FOOT + 3]
    foot[0], foot[1], foot[2] = q
    region = k.prepare_contact(foot, table, buf)
    fade *= aligned(n, buf)
    if fade <= 0.0:  # the trained force would pull the tool into the sheet: no contact here
        release(p, state, buf)
        return k.NO_VERTEX
    # The depth along the sheet's normal at the proxy (so that it reaches 0 exactly where
    # the tool leaves the sheet: no force jump), held at the limit; the force along the
    # model's normal at the contact, as a displacement step gives it.
    depth = -k.dot(k.minus(p, x), n) * fade  # (height, unless a stuck proxy moved the frame)
    limit = buf[k.MAX_DISPLACEMENT] * (1.0 - 1e-12)
    state[STATE_SATURATED] = 1.0 if depth > limit else 0.0
    depth = max(min(depth, limit), 0.0)
    d = state[STATE_D : STATE_D + 3]
    for c in range(3):
        d[c] = -depth * buf[k.NORMAL + c]
    respond(d, buf)
    buf[k.SLIPPING] = 0.0
    fn, slope = normal_force(buf), k.contact_stiffness(buf)
    state[STATE_CONTACT], state[STATE_CONTACT + 1] = fn, slope
    if buf[k.FRICTION] > 0.0:
        add_friction(goal, x, stuck, fn, slope, buf)
    return region


@njit(f"int64({k.f8_1d}, {k.f8_2d})", cache=True, nogil=True)
def stiffness(buf, out):
    """The 3x3 contact stiffness K (N/mm) at the last step into out: F(tip + dx) ~ F - K dx
    for the force F on the tool. Frictionless: K = k n n^T with k = dF/ddepth; zero out of
    contact. With friction (step_position's), stuck: + k_t (I - n n^T); slipping along s
    (the unit slip, against the tangential force): + k_t (I - n n^T - s s^T) - mu_d k s n^T
    (the force keeps mu_d F_n along the slip, turns with the tip across it, and grows with
    the depth: not symmetric). (The normal's turn as the proxy slides, of order F / the
    surface's radius of curvature, is left out.) WRONG_SHAPE if out is not (3, 3)."""
    if out.shape[0] != 3 or out.shape[1] != 3:
        return k.WRONG_SHAPE
    touching = not (int(buf[k.FLAGS]) & k.FLAG_NO_CONTACT) and buf[k.CONTACTS] > 0.0
    slope = k.contact_stiffness(buf) if touching else 0.0
    n = (buf[k.NORMAL], buf[k.NORMAL + 1], buf[k.NORMAL + 2])
    for i in range(3):
        for j in range(3):
            out[i, j] = slope * n[i] * n[j]
    fn = normal_force(buf)
    if not (touching and buf[k.FRICTION] > 0.0 and fn > 0.0):
        return k.OK
    kt = buf[k.FRICTION + 2] * slope
    s = (fn * n[0] - buf[k.FORCE], fn * n[1] - buf[k.FORCE + 1], fn * n[2] - buf[k.FORCE + 2])
    ts = math.sqrt(k.dot(s, s))  # |F_t|; s: against the tangential force
    slipping = buf[k.SLIPPING] > 0.0 and ts > 0.0
    scale = 1.0 / ts if slipping else 0.0
    s = (s[0] * scale, s[1] * scale, s[2] * scale)
    mu = buf[k.FRICTION + 1] if slipping else 0.0
    for i in range(3):
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            out[i, j] += kt * (eye - n[i] * n[j] - s[i] * s[j]) - mu * slope * s[i] * n[j]
    return k.OK
