"""The simulator's arithmetic in plain numpy: the reference the numba kernels are tested
against, and the baseline the latency benchmark compares with. Not for production use:
it allocates on every call."""

from __future__ import annotations

import numpy as np

from hapticrom.online import kernels
from hapticrom.online.model import ReducedModel
from hapticrom.shared.errors import StepInputError
from hapticrom.shared.lattice import lattice_corners, lattice_subdivisions, lattice_weights


def barycentric(model: ReducedModel, point) -> tuple[np.ndarray, np.ndarray, bool]:
    """(sample indices, weights, outside) of a contact point, by brute force over the
    sample triangles, by another algorithm than the kernel's Newton: a fixed-point
    iteration (the blended normal at the last (u, v), then the point moved along it onto
    the triangle's plane, a linear solve) and, outside every triangle, bisection along
    each border edge. Beneath a triangle's floor (the model's ``sample_floors``, never
    deeper than its longest edge) a point is not in it."""
    p = np.asarray(point, dtype=float)
    x, n = model.sample_points, model.sample_normals
    best = (np.inf, None, None)
    for tri, floor in zip(model.sample_triangles, model.sample_floors, strict=True):
        uvh = _fixed_point(p, x[tri], n[tri])
        if uvh is None:
            continue
        u, v, h = uvh
        edges = x[tri] - x[np.roll(tri, 1)]
        floor = max(floor, -np.sqrt(np.max(np.sum(edges * edges, axis=1))))
        if min(u, v, 1 - u - v) >= -1e-9 and abs(h) < best[0] and h >= floor:
            best = (abs(h), tri.copy(), np.array([1 - u - v, u, v]))
    if best[1] is not None:
        return best[1], best[2], False
    for a, b, c in _border(model.sample_triangles):
        s = _edge_bisection(p, x[a], x[b], n[a], n[b])
        dist = np.linalg.norm(p - x[a] - s * (x[b] - x[a]))
        if dist < best[0]:
            best = (dist, np.array([a, b, c]), np.array([1 - s, s, 0.0]))
    return best[1], best[2], True


def curve_weights(model: ReducedModel, vertices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The force curves' weights w_k k(x) / k_k (artifact 2.1), by another route than the
    kernel's: the sample triangle found by its corners (any rotation), and k(x) from the
    lattice's sub-triangle found by brute force over all of them."""
    if model.tool_stiffness is None:
        return weights
    for t, corners in enumerate(model.sample_triangles):
        for r in range(3):
            if np.array_equal(np.roll(corners, -r), vertices):
                order = (np.arange(3) + r) % 3  # sample k sits at corner order[k]
                b = np.zeros(3)
                b[order] = weights
                values = model.tool_stiffness[t]
                m = lattice_subdivisions(len(values))
                corner_values = values[lattice_corners(m)]
                return weights * _lattice_interpolation(values, m, b) / corner_values[order]
    raise AssertionError(f"no sample triangle has the corners {vertices}")


def outside_ratio(model: ReducedModel, point, vertices, weights) -> float:
    """k(x) / D of a contact x clamped to the border at c (artifact 2.3; D as
    ``kernels.scale_outside``: k at b, the point of c's normal line level with x, blended
    into the lattice's k(c) over the tool's radius beside the border), bounded to [0.1, 10];
    k linear on the loadable triangle nearest each point, by brute force over all of them
    (:func:`nearest_on_triangles`, not the kernel's grid); 1 without the stiffness."""
    f = model.contact_fields
    if f is None or f["stiffness_nodes"] is None:
        return 1.0

    grid = f["grid"]  # the kernel moves a query into the grid's box widened by 2 cells
    lo, hi = grid[:3] - 2 * grid[3], grid[:3] + (grid[4:7] + 2) * grid[3]

    def stiffness(p):
        q = np.clip(np.asarray(p, float), lo, hi)
        t, beta = nearest_on_triangles(q, model.vertices, f["triangles"])
        nodes = f["stiffness_nodes"]
        return float(np.clip(quadratic(nodes[t], beta), nodes.min(), nodes.max()))

    clamp = np.asarray(weights) @ model.sample_points[vertices]
    n = np.asarray(weights) @ model.sample_normals[vertices]
    level = clamp + (np.asarray(point, float) - clamp) @ n / (n @ n) * n
    denominator = stiffness(level)
    scaled = curve_weights(model, vertices, weights)
    j = int(np.argmax(weights))
    if model.tool_stiffness is not None and weights[0] != 1.0:  # the kernel's lattice cases
        # the lattice's k(c): w_j k(c) / k_j times the corner value k_j, from another route
        at_clamp = scaled[j] / weights[j] * _corner_value(model, vertices[j])
        aside = np.linalg.norm(np.asarray(point, float) - level)
        denominator += (at_clamp - denominator) * min(1.0, aside / model.contact_radius)
    return float(np.clip(stiffness(point) / denominator, 0.1, 10.0))


def quadratic(nodes: np.ndarray, beta: np.ndarray) -> float:
    """The P2 interpolant through a triangle's six nodal values (corners, then the midpoints
    of the edges opposite them) at barycentric ``beta`` (the shape functions written out,
    not the kernel's arithmetic)."""
    shapes = np.concatenate([beta * (2 * beta - 1), 4 * beta[[1, 2, 0]] * beta[[2, 0, 1]]])
    return float(shapes @ nodes)


def _corner_value(model: ReducedModel, sample: int) -> float:
    """The lattice's value at a sample (the same in each of its triangles: artifact rule)."""
    for t, corners in enumerate(model.sample_triangles):
        where = np.flatnonzero(corners == sample)
        if len(where):
            values = model.tool_stiffness[t]
            return float(values[lattice_corners(lattice_subdivisions(len(values)))][where[0]])
    raise AssertionError(f"sample {sample} is in no triangle")


def _lattice_interpolation(values: np.ndarray, m: int, b: np.ndarray) -> float:
    """The piecewise-linear interpolant of the lattice at barycentric weights b."""
    points = lattice_weights(m)
    index = {(int(a[1]), int(a[2])): i for i, a in enumerate(points)}
    q = np.clip(b[1:], 0.0, 1.0) * m
    for i in range(m):
        for j in range(m - i):
            for tri in (((i, j), (i + 1, j), (i, j + 1)), ((i + 1, j + 1), (i + 1, j), (i, j + 1))):
                if tri[0] not in index:
                    continue
                corner = np.array(tri, dtype=float)
                lam = np.linalg.solve(np.vstack([corner.T, np.ones(3)]), np.r_[q, 1.0])
                if lam.min() >= -1e-9:
                    return float(lam @ values[[index[c] for c in tri]])
    raise AssertionError(f"weights {b} are in no sub-triangle")


def _fixed_point(p, x, n, iterations: int = 200):
    """(u, v, h) with p = X(u, v) + h N(u, v) over one triangle (corners x, normals n),
    or None if p is far outside it."""
    e = np.column_stack([x[1] - x[0], x[2] - x[0]])
    flat = np.linalg.lstsq(e, p - x[0], rcond=None)[0]
    if flat.min() < -0.5 or flat.sum() > 1.5:
        return None
    u, v = flat
    for _ in range(iterations):
        normal = n[0] + u * (n[1] - n[0]) + v * (n[2] - n[0])
        u_new, v_new, h = np.linalg.solve(np.column_stack([e, normal]), p - x[0])
        done = abs(u_new - u) + abs(v_new - v) < 1e-15
        u, v = u_new, v_new
        if done:
            break
    return u, v, h


def _border(triangles: np.ndarray) -> list[tuple[int, int, int]]:
    """The edges of one triangle only, with that triangle's third sample."""
    count: dict[tuple[int, int], int] = {}
    for t in triangles:
        for k in range(3):
            key = tuple(sorted((int(t[k]), int(t[(k + 1) % 3]))))
            count[key] = count.get(key, 0) + 1
    return [
        (int(t[k]), int(t[(k + 1) % 3]), int(t[(k + 2) % 3]))
        for t in triangles
        for k in range(3)
        if count[tuple(sorted((int(t[k]), int(t[(k + 1) % 3]))))] == 1
    ]


def _edge_bisection(p, xa, xb, na, nb) -> float:
    """The edge parameter s in [0, 1] where p - X(s) is normal to the edge within the plane of
    the edge and the blended normal N(s) (by bisection on a sign change, else an end)."""
    e = xb - xa

    def g(s):
        r, normal = p - xa - s * e, na + s * (nb - na)
        return (r @ e) * (normal @ normal) - (e @ normal) * (r @ normal)

    lo, hi = 0.0, 1.0
    if g(lo) <= 0.0:
        return 0.0
    if g(hi) >= 0.0:
        return 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > 0.0 else (lo, mid)
    return 0.5 * (lo + hi)


def hermite_basis(t: float) -> np.ndarray:
    """The cubic Hermite basis at t in [0, 1]: weights of (F_k, h F'_k, F_k+1, h F'_k+1)."""
    return np.array(
        [2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2]
    )


def hermite(force: np.ndarray, slope: np.ndarray, step: float, depth: float) -> float:
    """The piecewise-cubic Hermite curve F(depth) (uniform knots 0, step, ...), in numpy."""
    last = len(force) - 1
    if depth >= last * step:
        return force[last] + slope[last] * (depth - last * step)
    k = int(depth // step)
    basis = hermite_basis(depth / step - k)
    return float(basis @ np.array([force[k], step * slope[k], force[k + 1], step * slope[k + 1]]))


class NumpySimulator:
    """Same contract as :class:`~hapticrom.online.simulator.Simulator` (PODI only).

    ``response="anm"`` evaluates the artifact's POD-ANM series with numpy's
    polynomial roots (eigenvalues of the companion matrix), an algorithm
    independent of the kernels' bracketed Newton iteration.
    """

    def __init__(self, model: ReducedModel, response: str = "curves", root: str = "eigen"):
        """``root``: "eigen" (polynomial roots, for tests) or "table" (the kernels'
        algorithm, the sections' tables interpolated, in numpy: the fair baseline for the
        latency benchmark)."""
        self.model, self.response, self.root = model, response, root
        # The contact (set_contact): samples, weights, clamped?, normal, curve and slopes.
        self.vertices, self.weights, self.outside = np.zeros(3, dtype=np.int64), np.zeros(3), False
        self.curve_weights = np.zeros(3)  # the force curves' (w_k k(x) / k_k, artifact 2.1)
        self.normal, self.curve, self.slope = np.zeros(3), np.zeros(0), np.zeros(0)
        self.depth = 0.0
        if response == "anm":
            a = model.artifact["anm"]
            self.offsets, self.a_max = a["section_offsets"], a["a_max"]
            self.depth_series, self.force_series = a["depth"], a["force"]
            self.coefficient_series = a["coefficients"]
            self.records, self.knots = model.anm["records"], model.anm["section_knots"]

    def set_contact(self, point) -> None:
        """The contact at ``point`` (mm): its samples, weights, normal and curve."""
        m = self.model
        self.vertices, self.weights, self.outside = barycentric(m, point)
        normal = self.weights @ m.sample_normals[self.vertices]
        self.normal = normal / np.linalg.norm(normal)
        scaled = curve_weights(m, self.vertices, self.weights)
        if self.outside:
            scaled = scaled * outside_ratio(m, point, self.vertices, self.weights)
        self.curve = scaled @ m.force[self.vertices]
        self.slope = scaled @ m.stiffness[self.vertices]
        self.curve_weights = scaled
        self.depth = 0.0

    def step_displacement(self, d) -> np.ndarray:
        """Tool displacement ``d`` (mm) -> force on the tool (N), a new array."""
        d = np.asarray(d, dtype=float)
        if not np.all(np.isfinite(d)):
            raise StepInputError("displacement is not finite")
        depth = -float(np.dot(d, self.normal))
        self.depth = max(depth, 0.0)
        if self.response == "anm":
            magnitude = 0.0 if depth <= 0 else self._anm(depth)[0]
        else:
            magnitude = (
                0.0 if depth <= 0 else hermite(self.curve, self.slope, self.model.depth_step, depth)
            )
        return magnitude * self.normal

    def _section(self, i: int, depth: float) -> tuple[int, float, bool]:
        """(artifact row, a, beyond) for sample i at a depth: roots of depth(a) - depth."""
        P = np.polynomial.polynomial
        rows = range(self.offsets[i], self.offsets[i + 1])
        for z in rows:
            end = P.polyval(self.a_max[z], self.depth_series[z])
            if depth <= end:
                c = self.depth_series[z].copy()
                c[0] -= depth
                roots = P.polyroots(c)
                real = roots[np.abs(roots.imag) <= 1e-9 * self.a_max[z]].real
                inside = real[(real >= -1e-9) & (real <= self.a_max[z] * (1 + 1e-9))]
                return z, float(inside.min()), False
        return rows[-1], float(self.a_max[rows[-1]]), True

    def _tabulated_force(self, i: int, depth: float) -> float:
        """Sample i's force at a depth from its sections' tables, as the kernels do."""
        k, q = kernels, self.knots
        rows = self.records[self.offsets[i] : self.offsets[i + 1]]
        r = rows[min(int(np.searchsorted(rows[:, k.REC_DEPTH_END], depth)), len(rows) - 1)]
        if depth > r[k.REC_DEPTH_END]:
            return r[k.REC_FORCE_END] + r[k.REC_SLOPE_END] * (depth - r[k.REC_DEPTH_END])
        x = min(max((depth - r[k.REC_DEPTH0]) * r[k.REC_INVERSE_SPACING], 0.0), q - 1.0)
        j = min(int(x), q - 2)
        force, slope = r[k.REC_FORCE :][:q], r[k.REC_FORCE + q :][:q] * r[k.REC_SPACING]
        return float(hermite_basis(x - j) @ (force[j], slope[j], force[j + 1], slope[j + 1]))

    def _anm(self, depth: float) -> tuple[float, list]:
        P = np.polynomial.polynomial
        total, found = 0.0, []
        for w, i in zip(self.curve_weights, self.vertices, strict=True):
            if self.root == "table":
                total += w * self._tabulated_force(i, depth)
                continue
            z, a, beyond = self._section(i, depth)
            force = P.polyval(a, self.force_series[z])
            if beyond:
                end = P.polyval(a, self.depth_series[z])
                slope = P.polyval(a, P.polyder(self.force_series[z])) / P.polyval(
                    a, P.polyder(self.depth_series[z])
                )
                force += slope * (depth - end)
            total += w * force
            found.append((z, a, beyond))
        return total, found

    def _coordinates(self, z: int, a: float, beyond: bool) -> np.ndarray:
        """A section's reduced coordinates at a; beyond its end, continued along the series'
        tangent: c(a_max) + (depth - end) dc/da / (d depth/da)."""
        P = np.polynomial.polynomial
        c = P.polyval(a, self.coefficient_series[z])
        if beyond:
            rate = 1.0 / P.polyval(a, P.polyder(self.depth_series[z]))  # da / d depth
            end = P.polyval(a, self.depth_series[z])
            c = c + (self.depth - end) * rate * P.polyval(a, P.polyder(self.coefficient_series[z]))
        return c

    def surface_displacement(self) -> np.ndarray:
        """The surface vertices' displacement (V, 3), mm, at the last step's depth."""
        m = self.model
        if self.response == "anm":
            _, found = self._anm(self.depth)
            fields = [
                m.surface_basis[i].astype(float) @ self._coordinates(z, a, beyond)
                for i, (z, a, beyond) in zip(self.vertices, found, strict=True)
            ]
            return (self.weights @ np.array(fields)).reshape(-1, 3)
        x = max(self.depth / m.depth_step, 0.0)  # beyond the last knot: continued linearly
        k = min(int(x), m.coefficients.shape[1] - 2)
        t = x - k
        coefficients = (1 - t) * m.coefficients[self.vertices, k] + t * m.coefficients[
            self.vertices, k + 1
        ]
        fields = np.einsum("irm,im->ir", m.surface_basis[self.vertices].astype(float), coefficients)
        return (self.weights @ fields).reshape(-1, 3)


def _segment_nearest(p, a, b):
    """(parameter t (T,), squared distance (T,)) of p's nearest point on segments a + t (b - a)."""
    ab = b - a
    t = np.clip(np.einsum("tx,tx->t", p - a, ab) / np.einsum("tx,tx->t", ab, ab), 0.0, 1.0)
    gap = a + t[:, None] * ab - p
    return t, np.einsum("tx,tx->t", gap, gap)


def nearest_on_triangles(point, vertices, triangles) -> tuple[int, np.ndarray]:
    """(triangle, barycentric weights (3,)) of the point of ``triangles`` nearest ``point``:
    the plane's foot where it is inside, else the nearest point of the three edges (numpy,
    all triangles at once; the kernels use Ericson's region tests instead)."""
    p = np.asarray(point, dtype=float)
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    nn = np.einsum("tx,tx->t", n, n)
    height = np.einsum("tx,tx->t", p - a, n) / nn
    foot = p - height[:, None] * n
    wb = np.einsum("tx,tx->t", np.cross(a - foot, c - a), n) / -nn  # areas: (a, foot, c)
    wc = np.einsum("tx,tx->t", np.cross(b - a, foot - a), n) / nn
    wa = 1.0 - wb - wc
    inside = (wa >= 0) & (wb >= 0) & (wc >= 0)
    best = np.where(inside, height**2 * nn, np.inf)
    weights = np.stack([wa, wb, wc], axis=1)
    for (i, j), (x, y) in zip(((0, 1), (1, 2), (2, 0)), ((a, b), (b, c), (c, a)), strict=True):
        t, d2 = _segment_nearest(p, x, y)
        closer = d2 < best
        best = np.where(closer, d2, best)
        edge = np.zeros((len(t), 3))
        edge[:, i], edge[:, j] = 1.0 - t, t
        weights = np.where(closer[:, None], edge, weights)
    k = int(np.argmin(best))
    return k, weights[k]


def linear_dent(model: ReducedModel, point, samples, weights, depth: float) -> np.ndarray:
    """The compliance surface's correction d (phi(x) - sum_j w_j phi_j) (V, 3) mm at the
    contact ``point`` (on the loadable surface) with its samples and weights."""
    f = model.contact_fields
    t, beta = nearest_on_triangles(point, model.vertices, f["triangles"])
    phi = beta @ f["fields"][f["triangle_rows"][t]].astype(float)
    blend = np.asarray(weights) @ f["fields"][f["sample_rows"][samples]].astype(float)
    return (depth * (phi - blend)).reshape(-1, 3)
