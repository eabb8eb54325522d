"""Physics solved online: a region of an artifact's ``hyperreduced`` group (format 2.5;
group 1.3 in 2.8) stepped by :class:`~hapticrom.online.haptic_newton.HapticNewton` under
any number of pressing tools and holders (issue 18).

    physics = model.physics(region=0, holders=[grip_point])   # a ReducedModel's
    physics.press(0, point, force)      # tool 0 pushes with force (N) at a surface point (mm)
    physics.press(1, point2, force2)    # and tool 1 beside it
    physics.step()                      # one physics step (a modified Newton iteration)
    physics.surface_displacement(out)   # (V, 3) mm, to draw
    physics.holder_force(0)             # (3,) N: what the holder holds the tissue with
    physics.move_holder(0, lift)        # the holder's grip moved by lift (3,) mm
    physics.error_estimate()            # the field's relative error the sampling leaves

A pressing tool's load is the campaign's force tool's (its dead load spread over a disk of
``contact_radius``), stored per unit force at the region's loadable vertices and blended
linearly over the surface triangle nearest the point; a holder keeps the rigid motion (the
mean displacement and the least-squares rotation) and the cupping of the loadable surface's
nodes within ``contact_radius`` of its point (each of them if fewer than three; the
region's grip nodes, P2's mid-side nodes too, or in a format 2.5 file the vertices and no
cupping: ``holder_rows``; the holder a held region was built for, the force patterns the
full order holds its patch in: ``pattern_rows``), by a penalty in the
constant tangent (fixed for the physics' life: a holder that grips elsewhere is a new
physics); a moved holder's penalty pulls those rows towards its moved grip (a load). A
region is built for its holders (``hapticrom physics --held``, ``--lift``): on a region of
presses alone a holder nearly locks the tissue. The state lags equilibrium by what one
iteration a step leaves and settles on it while the loads hold (``HapticNewton``). Pressing
again with 1-D float64 arrays allocates nothing (the blend is compiled); moving a holder
allocates no array buffer (a few views).
One physics is one thread's: its scratch buffers are shared between its calls.

What is checked where: the artifact's values by its reader (``ARTIFACT.md``); here, once, the
region's element geometry (every quadrature point's Jacobian of one sign an element, not
degenerate; else ArtifactError) and the caller's input (InputError naming it). A refused
``press``, ``move_holder`` or ``step`` changes nothing.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hapticrom.online import element_kernels as ek
from hapticrom.online.haptic_newton import HapticNewton
from hapticrom.online.kernels import closest_on_triangle
from hapticrom.online.sampling_check import MAX_PARTS, SamplingCheck
from hapticrom.shared.artifact_rules import MAX_FORCE, MAX_LENGTH
from hapticrom.shared.errors import ArtifactError, InputError

GROUP = "hyperreduced"
MIN_JACOBIAN = 1e-12  # |det J| below this fraction of an element's largest: degenerate
MAX_ITERATIONS = 100  # modified Newton iterations a step: a step's cost is bounded
# The divergence guard (``step``): under a load that holds (changed by at most STEADY of
# itself since the last step) a converging step's update shrinks; one JUMP times the last
# and above FLOOR (of the state) is the lagging tangent diverging (measured on the test
# cornea's 201-element sample: 0.016 -> 0.146 -> 0.51, then every step refused).
STEADY, JUMP, FLOOR = 1e-3, 4.0, 1e-6
# Under a changing load a step that moves the state by more than LEAP times the larger of
# the states before and after it is taken again towards a half, a quarter, ... of the
# change (at most HALVINGS times): the demo's two-tool region released at once leapt 1.85
# times its state, then 1.15, then every step was refused. (1.01: a step from rest, or to
# it, is 1 up to rounding.)
LEAP, HALVINGS = 1.01, 8
# Under a steady ramp of the pressing tools (the load changed by what it changed the step
# before, to RAMP of it) a converging step's update changes little from step to step;
# RAMP_JUMP times the last is the lagging tangent diverging (the demo's pinch in 30 parts:
# updates of 0.04-0.06 of the state, then 0.114, 0.281, 1.40, and every step refused at
# 43-58 % of the load). Its price: a step right after a new tangent takes over can move
# little and the next much more, and a ramp down to rest grows its updates relative to the
# shrinking state: a few fresh tangents where nothing diverged (README, stop 47).
RAMP, RAMP_JUMP = 0.1, 2.0


def element_geometry(X: np.ndarray, cell: str, first: int = 0,
                     dataset: str = "element_nodes") -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(dN, dV) of the elements X (E, nodes, 3) mm (rows ``first`` on of the group's
    ``dataset``):
    ``element_kernels.element_geometry``'s, after refusing an element whose Jacobian
    changes sign or nearly vanishes at a quadrature point (a tangled or degenerate element:
    its |det J| would pass as volume)."""
    ref = ek.reference_element(cell)
    J = np.einsum("eni,qnj->eqij", X, ref.gradients)
    det = np.linalg.det(J)
    scale = np.abs(det).max(axis=1, keepdims=True)
    bad = ~(np.abs(det) > MIN_JACOBIAN * scale).all(axis=1)
    bad |= ~((det > 0).all(axis=1) | (det < 0).all(axis=1))
    if bad.any():
        raise ArtifactError(f"{GROUP}/{dataset}: element {first + int(np.argmax(bad))} is "
                            "tangled or degenerate (its Jacobian vanishes or changes "
                            "sign)")  # fmt: skip
    dN = np.empty((len(X), len(ref.weights), X.shape[1], 3))
    dV = np.empty((len(X), len(ref.weights)))
    ek.element_geometry(np.ascontiguousarray(X), ref.gradients, ref.weights, dN, dV)
    return dN, dV


def region_sample(h, cell: str, region: int, prefix: str = "") -> tuple:
    """Region ``region``'s sample (dN, dV, basis rows, pressure rows, parameters, weights)
    from the group ``h``'s datasets ``prefix`` + element_offsets, element_nodes, ... (the
    model's, or with "check_" the error indicator's check sample), its geometry checked."""
    first, last = (int(v) for v in h[prefix + "element_offsets"][region : region + 2])
    dN, dV = element_geometry(np.asarray(h[prefix + "element_nodes"][first:last], np.float64),
                              cell, first, prefix + "element_nodes")  # fmt: skip
    e = slice(first, last)
    return (dN, dV, h[prefix + "basis_rows"][e], h[prefix + "pressure_rows"][e],
            h[prefix + "parameters"][e], h[prefix + "weights"][e])  # fmt: skip


def loadable_vertices(surface) -> np.ndarray:
    """The vertices of an artifact surface's loadable triangles (group 1): where tools
    press and holders grip."""
    return np.unique(surface["triangles"][surface["groups"] == 1])


def holder_patch(points, grippable, point, radius) -> np.ndarray:
    """The nodes a holder at ``point`` grips: those of ``grippable`` (indices into
    ``points`` (G, 3) mm: the loadable surface's) within ``radius`` (mm), as the full
    order's displacement-controlled tool holds its nodes (``ContactPatch.blocks``); none
    is refused (where the full order holds the nearest node instead)."""
    near = grippable[np.linalg.norm(points[grippable] - point, axis=1) <= radius]
    if not len(near):
        raise InputError(f"a holder at {np.round(point, 4).tolist()} mm has no loadable "
                         f"surface node within the tool's radius {radius} mm")  # fmt: skip
    return near


def holder_rows(basis, points, patch, flat: bool = False) -> np.ndarray:
    """The rows a holder keeps still, in the ``basis`` (3G, n) of ``points`` (G, 3) mm: on
    a ``patch`` of three nodes or more, its mean displacement and least-squares rotation
    (times the patch's RMS radius, mm; 6 rows) and, if ``flat``, its cupping
    (``flatness_weights``; 3 rows more), on one or two (a coarse mesh) each node's
    displacement (3 a node)."""
    n = basis.shape[1]
    rows = basis.reshape(-1, 3, n)[patch]  # (patch, 3, n)
    if len(patch) < 3:
        return rows.reshape(-1, n)
    r = points[patch] - points[patch].mean(axis=0)
    if np.linalg.cond((r**2).sum() * np.eye(3) - r.T @ r) > 1e8:
        raise InputError(f"a holder grips nodes {patch.tolist()} in a line: its rotation "
                         "is not defined")  # fmt: skip
    held = [rows.mean(axis=0), rotation_rows(points[patch], rows)]
    w = flatness_weights(points[patch]) if flat else None
    if w is not None:
        held.append(np.einsum("p,pcn->cn", w, rows))
    return np.vstack(held)


def holder_map(nodes: int, rows: int) -> np.ndarray:
    """(rows, 3): what ``holder_rows`` of a patch of ``nodes`` read when it moves by d
    (times d): each node's d on one or two, else the mean's d, no rotation, no cupping."""
    if nodes < 3:
        return np.tile(np.eye(3), (nodes, 1))
    out = np.zeros((rows, 3))
    out[:3] = np.eye(3)
    return out


def pattern_rows(basis, patch, patterns) -> tuple[np.ndarray, np.ndarray]:
    """(rows (m, n), map (m, 3)): a held region's holder (ARTIFACT.md, group 1.3): the
    patch's displacement (``basis`` (3G, n) rows of the grip nodes ``patch``) read in
    its force ``patterns`` (3P, m, orthonormal), s L^T A, s = P^-1/2 (a translation d
    then reads about |d|, as the mean's rows), and what they read when it moves by d
    (s L^T (d at each node)). With patterns that span the full order's reactions, its
    held state (every node moved by the same vector) solves the reduced equations: the
    hold is neither softer (the mean and rotation alone let the patch cup) nor locked
    (each node held: more rows than modes)."""
    n = basis.shape[1]
    scale = 1.0 / np.sqrt(len(patch))
    A = basis.reshape(-1, 3, n)[patch].reshape(-1, n)
    moved = patterns.reshape(len(patch), 3, -1).sum(axis=0).T  # L^T (d at each node) / d
    return scale * (patterns.T @ A), np.ascontiguousarray(scale * moved)


def stored_hold(h, region: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(its patch, rows of the region's grip nodes; its patterns (3P, m)) of region
    ``region``'s held holder (group 1.3, ``hold_*``), or None."""
    if "hold_offsets" not in h:
        return None
    first, last = (int(v) for v in h["hold_offsets"][region : region + 2])
    if first == last:
        return None
    rank = int(h["hold_ranks"][region])
    patterns = np.asarray(h["hold_reactions"][first:last], np.float64)
    patterns = patterns.reshape(3 * (last - first), -1)[:, :rank]
    return np.asarray(h["hold_nodes"][first:last], np.int64), np.ascontiguousarray(patterns)


def flatness_weights(points) -> np.ndarray | None:
    """(P,): the weights of a patch's cupping rows, sum_i w_i u_i with w_i = |r_i|^2 less
    its mean (r_i about the centroid), of unit norm: zero for any translation, the
    displacement of the rim against the middle's. The full order's holder moves every node
    it holds by the same vector: a patch held by its mean and rotation alone cups under a
    lift (measured on the liver: the middle node 0.55 mm above the grip, the rim 0.3 mm
    below, of 2 mm). None for nodes all as far from their centroid (nothing to hold)."""
    s = ((points - points.mean(axis=0)) ** 2).sum(axis=1)
    w = s - s.mean()
    norm = np.linalg.norm(w)
    return w / norm if norm > 1e-9 * s.mean() else None


def rotation_rows(points, rows) -> np.ndarray:
    """(3, n): the least-squares rotation theta of a patch (``points`` (P, 3) mm, their
    displacement ``rows`` (P, 3, n)), u_i = t + theta x r_i about the centroid, times the
    patch's RMS radius (mm, as the mean's rows): theta = J^-1 sum_i r_i x u_i, J = sum_i
    |r_i|^2 I - r_i r_i^T."""
    r = points - points.mean(axis=0)
    J = (r**2).sum() * np.eye(3) - r.T @ r
    moments = np.cross(r[:, :, None], rows, axis=1).sum(axis=0)  # (3, n)
    return np.sqrt((r**2).sum(axis=1).mean()) * np.linalg.solve(J, moments)


# The compiled calls' array types: read-only (a writeable array converts at the call); a
# caller's vector in any layout
VEC = "Array(float64, 1, 'A', readonly=True)"
RO_F8_1D = "Array(float64, 1, 'C', readonly=True)"
RO_F8_2D = "Array(float64, 2, 'C', readonly=True)"
RO_F8_3D = "Array(float64, 3, 'C', readonly=True)"
RO_I8_2D = "Array(int64, 2, 'C', readonly=True)"


@njit(f"Tuple((int64, float64))({VEC}, {RO_F8_2D}, {RO_I8_2D}, float64[::1])",
      cache=True, nogil=True)  # fmt: skip
def _nearest_triangle(p, vertices, triangles, w):
    """(the triangle nearest p, distance^2); its barycentric weights into w (3,)."""
    best, t_best = np.inf, -1
    for t in range(triangles.shape[0]):
        a, b, c = vertices[triangles[t, 0]], vertices[triangles[t, 1]], vertices[triangles[t, 2]]
        u, v, s, d2 = closest_on_triangle(p, a, b, c)
        if d2 < best:
            best, t_best = d2, t
            w[0], w[1], w[2] = u, v, s
    return t_best, best


# _tool_load's statuses: the load written, or what is wrong (press's error names it)
LOADED, POINT_REFUSED, FORCE_REFUSED, OUTSIDE_REGION, OFF_SURFACE = 0, 1, 2, 3, 4
_NDARRAY, _F8 = np.ndarray, np.dtype(np.float64)
_INTEGER = (int, np.integer)  # built once: ``int | np.integer`` makes a union a call


@njit(f"boolean({VEC}, float64)", cache=True, nogil=True)
def _bounded(v, bound):
    """3 finite numbers within +-bound (a NaN fails every comparison)."""
    if v.shape[0] != 3:
        return False
    for i in range(3):
        if not abs(v[i]) <= bound:
            return False
    return True


@njit(f"int64({VEC}, {VEC}, {RO_F8_1D}, float64, float64, {RO_F8_2D}, {RO_I8_2D}, {RO_F8_3D}, "
      "float64[::1], float64[::1])", cache=True, nogil=True)  # fmt: skip
def _tool_load(point, force, centre, radius, reach, load_points, triangles, tool_loads, w, out):
    """The reduced load of ``force`` (N) at ``point`` (mm) into ``out`` (n,): the unit loads
    ``tool_loads`` (L, 3, n) of the nearest triangle's corners blended by its barycentric
    weights (into ``w``); a status other than LOADED leaves ``out`` untouched."""
    if not _bounded(point, MAX_LENGTH):
        return POINT_REFUSED
    if not _bounded(force, MAX_FORCE):
        return FORCE_REFUSED
    d2 = 0.0
    for i in range(3):
        d2 += (point[i] - centre[i]) ** 2
    if d2 > radius * radius:
        return OUTSIDE_REGION
    t, d2 = _nearest_triangle(point, load_points, triangles, w)
    if d2 > reach * reach:
        return OFF_SURFACE
    out[:] = 0.0
    for c in range(3):
        corner = tool_loads[triangles[t, c]]
        for a in range(3):
            coefficient = w[c] * force[a]
            for k in range(out.shape[0]):
                out[k] += coefficient * corner[a, k]
    return LOADED


def _vector(
    name: str, value, bound: float = MAX_LENGTH, out: np.ndarray | None = None
) -> np.ndarray:
    """``value`` as 3 finite float64 numbers within +-``bound`` (into ``out`` if given)."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.full(0, np.nan)
    if a.shape != (3,) or not np.isfinite(a).all() or np.abs(a).max() > bound:
        raise InputError(f"{name} must be 3 finite numbers within +-{bound:g}, got {value!r}")
    if out is None:
        return a
    out[:] = a
    return out


def _index(name: str, value, count: int) -> int:
    integer = isinstance(value, _INTEGER) and not isinstance(value, bool)
    if not integer or not 0 <= value < count:
        raise InputError(f"{name} must be an integer from 0 to {count - 1}, got {value!r}")
    return int(value)


def _count(name: str, value, high: int | None, low: int = 1) -> None:
    integer = isinstance(value, _INTEGER) and not isinstance(value, bool)
    if not integer or value < low or (high is not None and value > high):
        upto = f" to {high}" if high is not None else ""
        raise InputError(f"{name} must be an integer from {low}{upto}, got {value!r}")


def _tool_id(tool) -> int:
    if not isinstance(tool, _INTEGER) or isinstance(tool, bool):
        raise InputError(f"a tool id must be an integer, got {tool!r}")
    return int(tool)


class HyperReducedPhysics:
    """Region ``region`` of ``model``'s hyper-reduced physics with ``holders`` (points, mm)
    gripping the surface; ``iterations`` and ``slices`` as ``HapticNewton``'s (slices 30
    here: on the demo's held and two-tool regions the same settled errors and no more lag
    at a ramp's end than 20, at a p99 0.1 ms lower: README, stop 45); an error estimate
    spread over ``estimate_steps`` steps (``error_estimate``; 0: none, the steps about 5 %
    cheaper at 100 on the demo's two-tool regions); ``precision`` the tangent parts'
    projection's, as ``HapticNewton``'s (the estimate's Newton step on that tangent)."""

    def __init__(self, model, region: int = 0, holders=(), iterations: int = 1,
                 slices: int = 30, estimate_steps: int = 100,
                 precision: str = "single"):  # fmt: skip
        if GROUP not in model.artifact.groups:
            raise InputError(f"{model.artifact.path} has no hyper-reduced physics (group "
                             f"{GROUP}, artifact format 2.5)")  # fmt: skip
        h, attrs = model.artifact[GROUP], model.artifact.group_attrs[GROUP]
        region = self.region = _index("region", region, len(h["centres"]))
        _count("iterations", iterations, MAX_ITERATIONS)
        _count("slices", slices, None)
        _count("estimate_steps", estimate_steps, MAX_PARTS, low=0)  # 0: no estimate
        self.centre = np.ascontiguousarray(h["centres"][region], np.float64)  # the kernel's
        self.radius = float(h["radii"][region])
        self.contact_radius = float(model.artifact.group_attrs["model"]["contact_radius"])
        self.vertices = np.ascontiguousarray(model.artifact["surface"]["vertices"], np.float64)
        sample = region_sample(h, attrs["cell"], region)
        self.surface_basis = np.ascontiguousarray(h["surface_basis"][region], np.float64)
        n = self.surface_basis.shape[1]
        linear = np.array(h["constant_tangent"][region], np.float64)
        self.hold_stiffness = float(attrs["hold_stiffness"])
        self.grip_points, self.grip_basis, self.grippable = self._grip_nodes(model, h, region)
        if isinstance(holders, str) or not hasattr(holders, "__iter__"):
            raise InputError(f"holders must be a list of points (mm), got {holders!r}")
        patches = [self._holder_patch(p) for p in holders]
        # the file's regions were built for a hold of the patch's cupping too (ARTIFACT.md)
        self.holds_flat = bool(attrs.get("holder_cupping", 0))
        self.stored_hold = stored_hold(h, region)  # a held region's holder (group 1.3)
        held = [self._hold_rows(q) for q in patches]
        self.holders = [rows for rows, _ in held]  # (rows, n) each: what a holder keeps
        self.holder_maps = [m for _, m in held]  # (rows, 3): their values, the grip moved
        self.holder_nodes = [len(q) for q in patches]  # under 3: each node held
        for A in self.holders:
            linear[:n, :n] += self.hold_stiffness * (A.T @ A)
        # slices: at least one element a part (a small region has fewer elements than 30)
        self.newton = self._newton(sample, linear, iterations, min(slices, len(sample[5])),
                                   precision)  # fmt: skip
        self.check = None  # the error indicator (a file with check samples: group 1.2)
        if "check_element_offsets" in h and estimate_steps:
            check = region_sample(h, attrs["cell"], region, "check_")
            self.check = SamplingCheck(self.newton.sample, h["constant_tangent"][region], check,
                                       h["check_constant_tangent"][region],
                                       estimate_steps)  # fmt: skip
        self._loads_of(model, h, region)
        self.q, self.pi = np.zeros(n), np.zeros(linear.shape[0] - n)
        self.load = np.zeros(n)  # the pressing tools' and moved holders' reduced loads, summed
        self.pressing: dict[int, np.ndarray] = {}  # tool id -> its reduced load (n,)
        # a moved holder: its target rows (the held rows' values) and its load k A^T t
        self.holder_targets = [np.zeros(len(A)) for A in self.holders]
        self.holder_loads = np.zeros((len(self.holders), n))
        self._weights = np.zeros(3)  # the blend of the last tool's triangle corners
        self._point, self._force = np.zeros(3), np.zeros(3)  # press's slower path: copies
        self.refreshes = 0  # steps the divergence guard took again on a fresh tangent
        self.shortened = 0  # steps that leapt under a changing load, taken shorter
        self._applied = np.zeros(n)  # the load the last step was taken under
        self._load_gap, self._trial_load = np.zeros(n), np.zeros(n)
        self._before = (np.zeros(n), np.zeros(linear.shape[0] - n))  # q, pi before a step
        # the guard's steady test reads the pressing tools' loads alone (a moved holder's
        # load k A^T t is some 1e4 times theirs: beside it any press would pass as steady)
        self._pressing_load = np.zeros(n)  # the pressing tools' loads, summed
        self._last_load = np.zeros(n)  # the pressing load of the last step
        self._load_change = np.zeros(n)
        self._last_change = np.zeros(n)  # the pressing load's change the step before
        self._holders_moved = False  # a holder moved since the last step: not steady

    def _newton(self, sample, linear, iterations, slices, precision) -> HapticNewton:
        """HapticNewton on the region; a rest tangent that does not factorise is the file's
        (ArtifactError) or, with holders, theirs (InputError naming them)."""
        try:
            return HapticNewton(sample, linear, iterations, slices, precision)
        except InputError as exc:
            if "singular" not in str(exc):
                raise
            if self.holders:
                raise InputError(
                    f"region {self.region}'s tangent with the holders is singular "
                    "(holders too close to each other or to a support?)"
                ) from None
            raise ArtifactError(
                f"{GROUP}/constant_tangent: region {self.region}'s tangent at rest is singular"
            ) from None

    def _grip_nodes(self, model, h, region) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (G, 3) mm, their basis rows (3G, n), the rows a holder may grip): the
        region's grip nodes (group 1.1: the loadable facets' nodes, P2's mid-side nodes
        too), else (a 1.0 file) the surface vertices and the loadable ones among them."""
        if "grip_rows" not in h:
            loadable = loadable_vertices(model.artifact["surface"])
            return self.vertices, self.surface_basis, loadable
        first, last = (int(v) for v in h["grip_offsets"][region : region + 2])
        points = np.ascontiguousarray(h["grip_nodes"][first:last], np.float64)
        rows = np.ascontiguousarray(h["grip_rows"][first:last], np.float64)
        return points, rows.reshape(-1, rows.shape[-1]), np.arange(last - first)

    def _hold_rows(self, patch) -> tuple[np.ndarray, np.ndarray]:
        """(rows, map) of a holder gripping ``patch``: the region's hold patterns if it is
        the patch the region was built to hold, else ``holder_rows``."""
        stored = self.stored_hold
        if stored is not None and np.array_equal(np.sort(patch), np.sort(stored[0])):
            return pattern_rows(self.grip_basis, *stored)
        rows = holder_rows(self.grip_basis, self.grip_points, patch, self.holds_flat)
        return rows, holder_map(len(patch), len(rows))

    def _holder_patch(self, point) -> np.ndarray:
        point = _vector("a holder's point", point)
        self._check_within("a holder", point)
        return holder_patch(self.grip_points, self.grippable, point, self.contact_radius)

    def _loads_of(self, model, h, region) -> None:
        """The region's load vertices, their unit loads, and its triangles: the loadable
        triangles whose three corners are load vertices (corners as load rows)."""
        rows = slice(*h["load_offsets"][region : region + 2])
        vertices = h["load_vertices"][rows]
        self.tool_loads = np.ascontiguousarray(h["tool_loads"][rows], np.float64)  # (L, 3, n)
        local = np.full(len(self.vertices), -1, np.int64)
        local[vertices] = np.arange(len(vertices))
        surface = model.artifact["surface"]
        triangles = local[surface["triangles"][surface["groups"] == 1]]
        self.triangles = np.ascontiguousarray(triangles[(triangles >= 0).all(axis=1)])
        if not len(self.triangles):
            raise ArtifactError(f"{GROUP}/load_vertices: region {region} holds no whole "
                                "loadable triangle")  # fmt: skip
        self.load_points = np.ascontiguousarray(self.vertices[vertices])

    def _check_within(self, what: str, point) -> None:
        d = point - self.centre  # squared, as the kernel's test: one boundary for both
        if d @ d > self.radius * self.radius:
            raise self._outside(what, point)

    def _outside(self, what: str, point) -> InputError:
        centre = np.round(self.centre, 4).tolist()
        return InputError(f"{what} at {np.round(point, 4).tolist()} mm is outside the region "
                          f"({self.radius} mm about {centre})")  # fmt: skip

    def tool_load(self, point, force) -> np.ndarray:
        """(n,) the reduced load of ``force`` (N) of a tool at the surface ``point`` (mm):
        the stored unit loads of the nearest region triangle's corners, blended (a new
        array; ``press`` writes into the tool's own)."""
        out = np.empty(len(self.load))
        self._load_into(point, force, out)
        return out

    def press(self, tool: int, point, force) -> None:
        """Tool ``tool`` (any int id) presses with ``force`` (N) at ``point`` (mm) from
        the next step on (replacing its last press). A tool's press after its first
        allocates nothing when point and force are 1-D float64 arrays (other sequences of
        3 numbers are copied into buffers first)."""
        tool = _tool_id(tool)
        load = self.pressing.get(tool)
        if load is None:  # a new tool: its own load buffer, once
            load = np.empty(len(self.load))
            self._load_into(point, force, load)
            self.pressing[tool] = load
        else:
            self._load_into(point, force, load)
        self._sum_loads()

    def _load_into(self, point, force, out: np.ndarray) -> None:
        """The reduced load of a tool into ``out`` (compiled: nothing allocated for 1-D
        float64 input); refused input raises InputError naming it, ``out`` untouched."""
        p, f = point, force
        if type(p) is not _NDARRAY or p.dtype is not _F8 or p.ndim != 1:
            p = _vector("a tool's point", p, MAX_LENGTH, self._point)
        if type(f) is not _NDARRAY or f.dtype is not _F8 or f.ndim != 1:
            f = _vector("a tool's force (N)", f, MAX_FORCE, self._force)
        status = _tool_load(p, f, self.centre, self.radius, self.contact_radius,
                            self.load_points, self.triangles, self.tool_loads, self._weights,
                            out)  # fmt: skip
        if status != LOADED:
            self._refuse_tool(status, p, f)

    def _refuse_tool(self, status: int, p: np.ndarray, f: np.ndarray) -> None:
        """Raise the error of a tool whose point ``p`` and force ``f`` (the float64 arrays
        the kernel read) ``_tool_load`` refused."""
        if status == POINT_REFUSED:
            _vector("a tool's point", p)
        if status == FORCE_REFUSED:
            _vector("a tool's force (N)", f, MAX_FORCE)
        if status in (POINT_REFUSED, FORCE_REFUSED):  # _vector passed what the kernel did not
            raise InputError(f"a tool's point {p!r} or force {f!r} is not 3 finite numbers "
                             "within bounds")  # fmt: skip
        if status == OUTSIDE_REGION:
            raise self._outside("a tool", p)
        gap = np.sqrt(_nearest_triangle(p, self.load_points, self.triangles, np.zeros(3))[1])
        raise InputError(f"a tool at {np.round(p, 4).tolist()} mm is {gap:.3g} mm off "
                         "the region's loadable surface")  # fmt: skip

    def release(self, tool: int) -> None:
        """Tool ``tool`` no longer presses (nothing if it did not)."""
        if self.pressing.pop(_tool_id(tool), None) is not None:
            self._sum_loads()

    def _sum_loads(self) -> None:
        """The load summed again over the pressing tools and the moved holders (a running
        sum would keep the rounding of a large force after its tool is released)."""
        self._pressing_load.fill(0.0)
        for load in self.pressing.values():
            self._pressing_load += load
        np.copyto(self.load, self._pressing_load)
        for load in self.holder_loads:
            self.load += load

    def move_holder(self, holder: int, displacement) -> None:
        """Holder ``holder`` moves its grip by ``displacement`` (3,) mm from where it
        gripped (grasp-and-lift; zero: held in place), without turning it, from the next
        step on: the penalty's rest point moves, a load k A^T t (t = M d the held rows'
        target, M its ``holder_maps``: the patch's mean at ``displacement``, no rotation
        and no cupping, or each node there, or the patterns' reading of every node
        there)."""
        holder = _index("holder", holder, len(self.holders))
        d = displacement  # a 1-D float64 array within bounds is read as is (no copy)
        if (
            type(d) is not _NDARRAY
            or d.dtype is not _F8
            or d.ndim != 1
            or not _bounded(d, MAX_LENGTH)
        ):
            d = _vector("a holder's displacement (mm)", d, MAX_LENGTH, self._point)
        t = self.holder_targets[holder]
        np.dot(self.holder_maps[holder], d, out=t)
        np.dot(self.holders[holder].T, t, out=self.holder_loads[holder])
        self.holder_loads[holder] *= self.hold_stiffness
        self._holders_moved = True
        self._sum_loads()

    def step(self) -> bool:
        """One physics step under the tools' loads; False if refused (nothing changed).
        A taken step also sums its share of the error estimate (``error_estimate``).

        Guarded: a step that is refused, or whose update jumps while the load holds
        (``JUMP``, ``STEADY``, ``FLOOR``) or under a steady ramp (``RAMP``,
        ``RAMP_JUMP``), is taken again from the state before it on the
        whole tangent at that state (``HapticNewton.refresh``: the cost of the tangent's
        parts at once, 30 steps' worth, about 4.6 ms on the demo, once), and counted in
        ``refreshes``. Under a load that changed, a step that leaps (moves the state by more
        than ``LEAP`` times the larger of the states before and after it) is taken again
        towards a half, a quarter, ... of the change (``shortened``): the physics reaches a
        large change (a release) over a few steps instead of diverging. Such a step costs
        up to ``HALVINGS`` + 2 steps and a whole tangent (12.3 ms once on the demo's
        two-tool release); a large load applied at once from rest is not shortened (a step
        from rest moves the state by exactly the state it reaches)."""
        taken = self._guarded_step()
        if taken and self.check is not None:
            self.check.advance(self.q, self.pi, self.newton.lu, self.newton.pivots)
        return taken

    def _guarded_step(self) -> bool:
        q0, pi0 = self._before
        np.copyto(q0, self.q)
        np.copyto(pi0, self.pi)
        pressing = self._pressing_load
        change = np.subtract(pressing, self._last_load, out=self._load_change)
        held = change.dot(change) <= STEADY**2 * pressing.dot(pressing)  # dot: no norm's cost
        steady = held and not self._holders_moved
        # a steady ramp of the pressing tools (a moved holder's load is not theirs): the load
        # changed by what it changed the step before
        drift = np.subtract(change, self._last_change, out=self._last_change)
        ramping = not held and not self._holders_moved
        ramping = ramping and drift.dot(drift) <= RAMP**2 * change.dot(change)
        np.copyto(self._last_change, change)
        np.copyto(self._last_load, pressing)
        self._holders_moved = False
        gap = np.subtract(self.load, self._applied, out=self._load_gap)
        # the load to reach moved since the last step beyond a held tool's wobble (STEADY)
        moving = gap.dot(gap) > STEADY**2 * self.load.dot(self.load)
        steady = steady and not moving
        previous = self.newton.last_update
        limit = JUMP if steady else RAMP_JUMP if ramping else np.inf  # an update's jump
        if moving:
            self.newton.keep()  # a leap's tangent part is taken back (undo)
        taken = self.newton.step(self.q, self.pi, self.load)
        update = self.newton.last_update
        if moving and (not taken or self._leapt(q0)):
            if taken:
                self.newton.undo()  # its tangent part at a state dropped
            if self._shorter_steps(q0, pi0, previous):
                return True  # else (the state restored) a fresh tangent, below
        elif taken and not (update > FLOOR and update > limit * previous):
            np.copyto(self._applied, self.load)
            return True
        elif taken and moving:
            self.newton.undo()  # the jumped step's tangent part, at a state dropped
        self.q[:], self.pi[:] = q0, pi0
        self.newton.last_update = previous
        if not self.newton.refresh(self.q, self.pi):
            return False
        self.refreshes += 1
        return self._fresh_step(q0, pi0, previous, moving)

    def _fresh_step(self, q0, pi0, previous, moving) -> bool:
        """The step on the fresh tangent; under a moving load one that leaps or is refused
        is taken shorter again (``_shorter_steps`` from the whole change); False if
        nothing was taken (q, pi restored)."""
        if moving:
            self.newton.keep()
        taken = self.newton.step(self.q, self.pi, self.load)
        if taken and not (moving and self._leapt(q0)):
            np.copyto(self._applied, self.load)
            return True
        if not moving:
            return False
        if taken:
            self.newton.undo()
        np.subtract(self.load, self._applied, out=self._load_gap)
        return self._shorter_steps(q0, pi0, previous)

    def _leapt(self, q0) -> bool:
        """Whether the step from q0 moved q by more than ``LEAP`` times the larger of the
        states before and after it (a step from rest, or to it, moves it by exactly one
        of them; measured on q - q0, whatever the iterations)."""
        qq, q0q0 = self.q.dot(self.q), q0.dot(q0)
        moved = qq - 2.0 * self.q.dot(q0) + q0q0
        return moved > LEAP * LEAP * max(qq, q0q0)

    def _shorter_steps(self, q0, pi0, previous) -> bool:
        """The step again from (q0, pi0) towards the last applied load plus a half, a
        quarter, ... of the change in ``_load_gap`` (``HALVINGS`` at most) until it
        neither leaps (``_leapt``) nor is refused: the later steps go on towards the load
        asked (a load released at once, two tools at full force, diverged in one Newton
        iteration: README, stop 46). Counted in ``shortened``; False (q, pi restored) if
        none."""
        for _ in range(HALVINGS):
            self.q[:], self.pi[:] = q0, pi0
            self.newton.last_update = previous
            self._load_gap *= 0.5
            trial = np.add(self._applied, self._load_gap, out=self._trial_load)
            self.newton.keep()
            if self.newton.step(self.q, self.pi, trial):
                if not self._leapt(q0):
                    np.copyto(self._applied, trial)
                    self.shortened += 1
                    return True
                self.newton.undo()
        self.q[:], self.pi[:] = q0, pi0
        self.newton.last_update = previous
        return False

    def error_estimate(self) -> float:
        """The relative error of the displacement field (1) that the element sampling
        leaves, estimated on the region's check sample (``online/sampling_check.py``):
        each estimate is summed over ``estimate_steps`` taken steps at the state of the
        first of them (so the value read is up to 2 x ``estimate_steps`` - 1 steps old);
        NaN before the first estimate, if the check's sums were not finite, with
        ``estimate_steps`` 0, or in a file without check samples (group version 1.2).
        It does not see a load the region's basis does not span."""
        return np.nan if self.check is None else float(self.check.eta)

    def surface_displacement(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` (V, 3) float64 C-contiguous with the surface's displacement (mm)."""
        shape = self.vertices.shape
        if not isinstance(out, np.ndarray) or out.shape != shape or out.dtype != np.float64 \
                or not out.flags.c_contiguous or not out.flags.writeable:  # fmt: skip
            raise InputError(f"out must be a writeable C-contiguous float64 array of shape "
                             f"{shape}")  # fmt: skip
        np.dot(self.surface_basis, self.q, out=out.reshape(-1))
        return out

    def holder_force(self, holder: int) -> np.ndarray:
        """(3,) N: the force holder ``holder`` exerts on the tissue, its penalty's summed
        over the patch's nodes: -k M^T (A q - t) with M its ``holder_maps`` (the mean's
        gap on three nodes or more, the rotation's and cupping's summing to 0; each
        node's on one or two; the patterns' nodal forces summed for a held region's)."""
        holder = _index("holder", holder, len(self.holders))
        gap = self.holders[holder] @ self.q - self.holder_targets[holder]
        return -self.hold_stiffness * (self.holder_maps[holder].T @ gap)
