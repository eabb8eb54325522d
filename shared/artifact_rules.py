"""What the values of an artifact must satisfy before the runtime may use them.

A valid checksum says a file is what its writer wrote, not that the writer was
honest or correct: anyone can recompute it. The runtime's numba kernels do no
bounds checks and a haptic motor renders whatever force comes out, so every
value the runtime uses is checked here, once, at load:

- field rules, named in :data:`~hapticrom.shared.artifact.SCHEMA` (``checks``):
  every float dataset is finite; ``index:S`` values lie in [0, S); ``unit`` rows
  have norm 1; ``orthonormal`` rows; ``symmetric`` matrices; signs;
- attribute kinds and rules (a number is a finite number, a JSON attribute
  parses, not too deep);
- rules across fields (:data:`CROSS_RULES`): the depth grid is uniform from 0,
  force curves start at 0 and increase, the sample triangles face outward with the sample
  points, no degenerate triangle, every POD-ANM section increases in depth and
  force and follows its predecessor, and the series agree with the stored
  full-order curves (two independent records of the same response).

Each failure raises :class:`ArtifactError` naming the dataset or attribute.
"""

from __future__ import annotations

import json
from collections.abc import Callable

import numpy as np
from numpy.polynomial import polynomial as poly

from hapticrom.shared.errors import ArtifactError
from hapticrom.shared.geometry import triangle_edges
from hapticrom.shared.lattice import lattice_corners, lattice_subdivisions
from hapticrom.shared.material_layout import packed_problem

# Bounds on attributes (the writer's are a few hundred bytes; a JSON campaign a few kB).
MAX_ATTRIBUTE_ITEMS = 1 << 14
MAX_TEXT = 1 << 22
MAX_JSON_DEPTH = 32
# Tolerances (relative): rounding of values the trainer computed in float64.
UNIT_TOL = 1e-6
SYMMETRY_TOL = 1e-6
# POD-ANM series against the full-order curves, relative to the sample's largest force: the
# two agree to 0.1 % on the trained models (docs: ARTIFACT.md); a tampered or broken series is
# off by far more.
ANM_CURVE_TOL = 0.05
# Physical bounds no surgical model comes near (a tool force of 10 tonnes, a 10 m dent): past
# them a file is absurd, and squares of forces would overflow float64 in a consumer.
MAX_FORCE = 1e5  # N
MAX_STIFFNESS = 1e9  # N/mm
MAX_LENGTH = 1e4  # mm
MAX_SECTIONS = 256  # POD-ANM sections per sample (4 to 6 in practice): buffer and scan sizes
# A sample triangle faces within 60 degrees of its samples' normals: every blend N of them then
# has N . n_triangle >= 0.5, so |N| >= 0.5 and the runtime's projection along N is well posed.
MIN_NORMAL_DOT = 0.5
# Neighbouring samples' normals pairwise within 80 degrees (cos 80 = 0.17): across a rim
# (the liver's) 60 left most of it uncovered; the facing rule above is what the runtime needs.
MIN_NEIGHBOUR_NORMAL_DOT = 0.17
# A section starts where its predecessor ends up to the reduced Newton correction at its start
# (measured up to 1.4e-6 of the force scale on the test model).
ANM_JUMP_TOL = 1e-3


# -- attributes ----------------------------------------------------------------------
def attribute_value(attrs, spec, fail: Callable[[str], ArtifactError], where: str):
    """The attribute ``spec.name`` of ``attrs`` (an h5py AttributeManager), typed and checked."""
    shape = attrs.get_id(spec.name).shape
    if shape and int(np.prod(shape, dtype=np.int64)) > MAX_ATTRIBUTE_ITEMS:
        raise fail(f"{where} has {shape} items, too many")
    raw = attrs[spec.name]
    value = _KINDS[spec.kind](raw)
    if value is None:
        raise fail(f"{where} must be {_KIND_NAMES[spec.kind]}, got {_show(raw)}")
    for check in spec.checks:
        name, _, arg = check.partition(":")
        problem = _ATTRIBUTE_CHECKS[name](value, arg)
        if problem:
            raise fail(f"{where} {problem}, got {_show(value)}")
    return value


def _show(value) -> str:
    text = repr(value)
    return text if len(text) < 80 else text[:77] + "..."


def _as_text(raw):
    if isinstance(raw, bytes | np.bytes_):
        try:
            raw = bytes(raw).decode("utf-8")
        except UnicodeDecodeError:
            return None
    if not isinstance(raw, str) or len(raw) > MAX_TEXT:
        return None
    try:
        raw.encode("utf-8")  # h5py hands undecodable bytes over as surrogates
    except UnicodeEncodeError:
        return None
    return str(raw)


def _as_json(raw):
    text = _as_text(raw)
    if text is None:
        return None
    try:
        value = json.loads(text)
    except (ValueError, RecursionError):
        return None
    if not isinstance(value, dict | list) or _depth(value) > MAX_JSON_DEPTH:
        return None
    return value


def _depth(value, level: int = 0) -> int:
    if level > MAX_JSON_DEPTH:
        return level
    children = value.values() if isinstance(value, dict) else value
    if isinstance(value, dict | list):
        return max((_depth(c, level + 1) for c in children), default=level + 1)
    return level


def _as_number(raw, integer: bool):
    a = np.asarray(raw)
    if a.shape != () or a.dtype.kind not in ("iu" if integer else "iuf"):
        return None
    value = int(a) if integer else float(a)
    return value if integer or np.isfinite(value) else None


def _as_numbers(raw, integer: bool):
    a = np.asarray(raw)
    if a.ndim > 1 or a.dtype.kind not in ("iu" if integer else "iuf"):
        return None
    a = a.reshape(-1)
    if not integer and not np.all(np.isfinite(a)):
        return None
    return tuple(int(v) for v in a) if integer else tuple(float(v) for v in a)


_KINDS = {
    "str": _as_text,
    "json": _as_json,
    "float": lambda raw: _as_number(raw, integer=False),
    "int": lambda raw: _as_number(raw, integer=True),
    "floats": lambda raw: _as_numbers(raw, integer=False),
    "ints": lambda raw: _as_numbers(raw, integer=True),
}
_KIND_NAMES = {
    "str": "a UTF-8 string",
    "json": f"a JSON object or list (at most {MAX_JSON_DEPTH} levels deep)",
    "float": "a finite number",
    "int": "an integer",
    "floats": "a list of finite numbers",
    "ints": "a list of integers",
}


def _choice(value, arg: str) -> str | None:
    options = arg.split(",")
    return None if value in options else f"must be one of {', '.join(options)}"


def _range(value, arg: str) -> str | None:
    lo, hi = (int(v) for v in arg.split(","))
    return None if lo <= value <= hi else f"must lie in [{lo}, {hi}]"


_ATTRIBUTE_CHECKS = {
    "positive": lambda v, _: None if v > 0 else "must be positive",
    "nonnegative": lambda v, _: None if v >= 0 else "must not be negative",
    "pair": lambda v, _: None if len(v) == 2 and min(v) >= 0 else "must be [major, minor]",
    "length": lambda v, n: None if len(v) == int(n) else f"must have {n} values",
    "choice": _choice,
    "range": _range,
}


# -- datasets, one at a time ------------------------------------------------------------
def _index(a, arg, symbols):
    size = symbols[arg]
    bad = (a < 0) | (a >= size)
    return f"has indices outside [0, {size})" if np.any(bad) else None


def _unit(a, arg, symbols):
    norms = np.linalg.norm(a, axis=-1)
    return "has rows that are not unit vectors" if np.any(abs(norms - 1) > UNIT_TOL) else None


def _orthonormal(a, arg, symbols):
    gram = a @ a.T
    return "is not orthonormal" if np.max(abs(gram - np.eye(len(a)))) > UNIT_TOL else None


def _symmetric(a, arg, symbols):
    scale = np.max(abs(a), initial=0.0)
    asym = np.max(abs(a - np.swapaxes(a, -1, -2)), initial=0.0)
    return "is not symmetric" if asym > SYMMETRY_TOL * scale else None


def _choice_values(a, arg, symbols):
    allowed = np.array([int(v) for v in arg.split(",")])
    return f"has values other than {arg}" if not np.all(np.isin(a, allowed)) else None


FIELD_RULES = {
    "index": _index,
    "distinct": lambda a, arg, s: None if len(np.unique(a)) == len(a) else "has repeated values",
    "unit": _unit,
    "orthonormal": _orthonormal,
    "symmetric": _symmetric,
    "choice": _choice_values,
    "positive": lambda a, arg, s: None if np.all(a > 0) else "has values that are not positive",
    "negative": lambda a, arg, s: None if np.all(a < 0) else "has values that are not negative",
    "nonnegative": lambda a, arg, s: None if np.all(a >= 0) else "has negative values",
}


def _check_fields(artifact) -> None:
    from hapticrom.shared.artifact import SCHEMA

    for group in SCHEMA:
        arrays = artifact.groups.get(group.name, {})
        for spec in group.fields:
            if spec.name not in arrays:
                continue
            a = arrays[spec.name]
            if spec.dtype == "f" and not np.all(np.isfinite(a)):
                raise _fail(artifact, f"{group.name}/{spec.name} has NaN or infinite values")
            for check in spec.checks:
                name, _, arg = check.partition(":")
                problem = FIELD_RULES[name](a, arg, artifact.symbols)
                if problem:
                    raise _fail(artifact, f"{group.name}/{spec.name} {problem}")


def _fail(artifact, message: str) -> ArtifactError:
    return ArtifactError(f"{artifact.path}: {message}")


# -- rules across fields ----------------------------------------------------------------
def _depth_grid(artifact) -> None:
    depth = artifact["samples"]["depth"]
    steps = np.diff(depth)
    if len(depth) < 2 or depth[0] != 0.0 or steps[0] <= 0:
        raise _fail(artifact, "samples/depth must start at 0 and increase")
    if not np.allclose(steps, steps[0], rtol=1e-9, atol=0):
        raise _fail(artifact, "samples/depth must be uniform")
    if depth[-1] > MAX_LENGTH:
        raise _fail(artifact, f"samples/depth reaches {depth[-1]:.3g} mm (over {MAX_LENGTH:g})")


def solved_depths(samples) -> np.ndarray:
    """(P,) the depth each sample was solved to (mm): ``samples/solved_depth`` (format 2.3),
    else the grid's end for every sample (older files: their grid stops where every sample
    was solved)."""
    if "solved_depth" in samples:
        return np.asarray(samples["solved_depth"], dtype=np.float64)
    return np.full(len(samples["points"]), float(samples["depth"][-1]))


def _solved_depth(artifact) -> None:
    """Each sample's solved depth lies on the grid's range, at least its first knot from 0
    (the runtime flags a depth beyond its contact's shallowest neighbour's as extrapolated,
    and the simulator's displacement limit is 10x the shallowest), and the deepest one is
    the grid's end (the grid goes no further than a solve)."""
    s = artifact["samples"]
    if "solved_depth" not in s:
        return
    solved, depth = s["solved_depth"], s["depth"]
    if np.any(solved < depth[1] * (1 - 1e-9)) or np.any(solved > depth[-1] * (1 + 1e-9)):
        raise _fail(
            artifact,
            f"samples/solved_depth has values outside [{depth[1]:.6g}, "
            f"{depth[-1]:.6g}] mm (the grid's first knot to its end)",
        )
    if abs(solved.max() - depth[-1]) > 1e-9 * depth[-1]:
        raise _fail(artifact, "samples/solved_depth: no sample reaches the depth grid's end")


def _continued_beyond_solved(artifact) -> None:
    """Beyond its solved depth a sample's curve and coordinates are continuations: linear
    (second differences within rounding) and the force's slope there at most 3x the largest
    secant within its solves (a crafted curve could otherwise jump where no sweep looks:
    review). Linear, as the writer continues them (``sample_on_grid``)."""
    s = artifact["samples"]
    if "solved_depth" not in s:
        return
    depth, force, coefficients = s["depth"], s["force"], s["coefficients"]
    step = depth[1]
    for p, solved in enumerate(s["solved_depth"]):
        beyond = np.flatnonzero(depth > solved * (1 + 1e-9))
        f, c = force[p], coefficients[p]
        if len(beyond) >= 3:
            scale_f = np.max(np.abs(f))
            scale_c = np.max(np.abs(c), axis=0) + 1e-300
            if np.any(np.abs(np.diff(f[beyond], 2)) > 1e-9 * scale_f) or np.any(
                np.abs(np.diff(c[beyond], 2, axis=0)) > 1e-9 * scale_c
            ):
                raise _fail(artifact, f"samples: sample {p}'s curve is not linear beyond its "
                                      "solved depth")  # fmt: skip
        inside = depth <= solved * (1 + 1e-9)
        if len(beyond) >= 2 and np.count_nonzero(inside) >= 2:
            slope = (f[beyond[1]] - f[beyond[0]]) / step
            largest = np.max(np.diff(f[inside])) / step
            if slope > 3 * largest + 1e-9 * np.max(np.abs(f)) / step:
                raise _fail(artifact, f"samples: sample {p}'s force beyond its solved depth "
                                      f"rises {slope / largest:.3g}x its steepest solved "
                                      "secant (at most 3)")  # fmt: skip


def _force_curves(artifact) -> None:
    s = artifact["samples"]
    force, slope = s["force"], s["stiffness"]
    scale = np.max(force, axis=1)
    if np.any(scale <= 0) or np.any(scale > MAX_FORCE):
        raise _fail(
            artifact, f"samples/force: a sample's largest force not in (0, {MAX_FORCE:g}] N"
        )
    if np.any(abs(force[:, 0]) > 1e-6 * scale):
        raise _fail(artifact, "samples/force must be 0 at depth 0")
    if np.any(np.diff(force, axis=1) < 0):
        raise _fail(artifact, "samples/force is not increasing with depth")
    _monotone_slopes(artifact, force, slope, s["depth"][1])


def _monotone_slopes(artifact, force, slope, step) -> None:
    """The knot slopes of a monotone cubic Hermite (Fritsch-Carlson): 0 <= s_k <= 3 times each
    adjacent secant, and a positive last slope (the runtime extrapolates and inverts with it).
    Within these bounds the curve neither overshoots nor turns back between knots."""
    secant = np.diff(force, axis=1) / step
    bound = np.minimum(np.c_[secant[:, :1], secant], np.c_[secant, secant[:, -1:]])
    tol = 1e-9 * np.max(slope, axis=1, keepdims=True)
    if np.any(slope > 3 * bound + tol):
        raise _fail(artifact, "samples/stiffness exceeds 3x an adjacent secant of samples/force")
    if np.any(slope[:, -1] <= 0) or np.any(slope > MAX_STIFFNESS):
        raise _fail(artifact, "samples/stiffness must end positive and stay below 1e9 N/mm")


def _sample_triangulation(artifact) -> None:
    """The samples' triangles: not degenerate, facing the way their samples' normals do
    (within 60 degrees: the runtime's projection along blended normals needs it),
    neighbours' normals within 80 degrees, no sample edge in more than two triangles."""
    s = artifact["samples"]
    p, t = s["points"], s["triangles"]
    if np.max(abs(p)) > MAX_LENGTH:
        raise _fail(artifact, f"samples/points lie beyond {MAX_LENGTH:g} mm")
    extent = max(np.ptp(p, axis=0).max(initial=0.0), 1e-300)
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    area2 = np.linalg.norm(n, axis=1)
    if len(t) == 0 or np.any(area2 <= 1e-9 * extent**2):
        raise _fail(artifact, "samples/triangles has a degenerate (zero-area) triangle")
    normals = s["normals"][t]  # (S, 3 corners, 3)
    if np.any(np.einsum("sij,skj->sik", normals, normals) < MIN_NEIGHBOUR_NORMAL_DOT):
        raise _fail(
            artifact, "samples/normals of neighbouring samples differ by more than 80 degrees"
        )
    if len(np.unique(np.sort(t, axis=1), axis=0)) < len(t):
        raise _fail(artifact, "samples/triangles lists a triangle twice")
    edges = np.sort(np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    if np.unique(edges, axis=0, return_counts=True)[1].max() > 2:
        raise _fail(artifact, "samples/triangles has a sample edge in more than two triangles")
    facing = np.einsum("sx,skx->sk", n / area2[:, None], s["normals"][t])
    if np.any(facing < MIN_NORMAL_DOT):
        raise _fail(
            artifact,
            "samples/triangles has a triangle not facing along its samples' normals "
            "(within 60 degrees, counter-clockwise seen from outside)",
        )


MAX_STIFFNESS_RATIO = 10.0  # within one sample triangle's lattice (see below)
TOOL_STIFFNESS_RANGE = (1e-9, 1e9)  # N/mm: no product of two overflows, no weight underflows


def _tool_stiffness(artifact) -> None:
    """The tool's stiffness lattice (optional): a lattice of m = 1..64 subdivisions
    (``shared/lattice.py``); at a sample, the same value in every triangle of that sample
    (the runtime then reproduces the sample's own curve, and the force is continuous);
    values in 1e-9..1e9 N/mm (a red team's 1.8e308 overflowed the interpolant to inf, its
    5e-324 underflowed every weight to 0); within a triangle, values within a factor of 10
    (the runtime scales the neighbours' curves by their ratios, so the force stays within
    the simulator's limit, 10x the largest trained force; the demo liver's triangles vary
    by less than 2x)."""
    s = artifact["samples"]
    if "tool_stiffness" not in s:
        return
    k, t = s["tool_stiffness"], s["triangles"]
    m = lattice_subdivisions(k.shape[1])
    if m is None:
        raise _fail(artifact, f"samples/tool_stiffness has {k.shape[1]} points per triangle, "
                              "not those of a lattice (m + 1)(m + 2)/2, m = 1..64")  # fmt: skip
    corners = k[:, lattice_corners(m)]  # (S, 3), as the triangles' corners
    ends = np.zeros(len(s["points"]))
    np.maximum.at(ends, t.ravel(), corners.ravel())
    starts = np.full(len(s["points"]), np.inf)
    np.minimum.at(starts, t.ravel(), corners.ravel())
    used = np.isfinite(starts)
    if np.any(ends[used] - starts[used] > 1e-12 * ends[used]):
        raise _fail(artifact, "samples/tool_stiffness differs at a sample between its triangles")
    low, high = TOOL_STIFFNESS_RANGE
    if np.any(k < low) or np.any(k > high):
        raise _fail(artifact, f"samples/tool_stiffness has values outside {low:g} to {high:g} N/mm")
    if np.any(k.max(axis=1) > MAX_STIFFNESS_RATIO * k.min(axis=1)):
        raise _fail(artifact, "samples/tool_stiffness varies more than 10-fold in a triangle")


MAX_FIELD_PER_DEPTH = 1e3  # mm/mm: see _contact_fields
# The simulator's displacement limit is 10x the trained depth, and the load's sweep goes to
# 1.5x it: the correction d (phi(x) - sum_j w_j phi_j) stays within that limit where any
# row's largest value plus the largest of a sample's row is at most 10 / 1.5 per unit depth
# (honest: 3.3 on the liver, 5.4 on the coarse test cornea's rim).
MAX_FIELD_SUM = 10.0 / 1.5


def contact_field_reach(fields: np.ndarray, sample_rows: np.ndarray) -> float:
    """The largest |value| of any row plus that of any sample's row (per unit depth): what
    bounds the rendered correction (MAX_FIELD_SUM)."""
    largest = np.abs(fields).max(axis=1)
    return float(largest.max(initial=0.0) + largest[sample_rows].max(initial=0.0))


def _edge_stiffness(artifact, c, s) -> None:
    """``contact_fields/edge_stiffness`` (optional, format 2.4): with the vertices'
    ``stiffness`` only; one row per loadable triangle, in the surface's order; within the
    stiffness range; and equal in the two triangles that share an edge (the trainer solves
    each edge once), so that the quadratic interpolant is continuous across it."""
    if "edge_stiffness" not in c:
        return
    if "stiffness" not in c:
        raise _fail(artifact, "contact_fields/edge_stiffness needs contact_fields/stiffness")
    triangles = np.asarray(s["triangles"])[np.asarray(s["groups"]) == 1]
    k = np.asarray(c["edge_stiffness"])
    if k.shape != (len(triangles), 3):
        raise _fail(artifact, f"contact_fields/edge_stiffness has {k.shape[0]} rows, expected "
                              f"one per loadable triangle ({len(triangles)})")  # fmt: skip
    low, high = TOOL_STIFFNESS_RANGE
    if np.any(k < low) or np.any(k > high):
        raise _fail(artifact, f"contact_fields/edge_stiffness has values outside {low:g} to "
                              f"{high:g} N/mm")  # fmt: skip
    edges, index = triangle_edges(triangles)
    first = np.empty(len(edges))
    first[index.ravel()[::-1]] = k.ravel()[::-1]  # each edge's value in its first triangle
    if np.any(k.ravel() != first[index.ravel()]):
        raise _fail(artifact, "contact_fields/edge_stiffness differs between the two triangles "
                              "of an edge")  # fmt: skip


def _contact_fields(artifact) -> None:
    """The tool's linear fields (optional): one row for exactly each vertex of a loadable
    triangle (the runtime reads the rows of the loadable triangle under the contact); each
    sample's row at the sample's point, the only loadable vertex there (the correction then
    vanishes at a sample; a second vertex there was the red team's 1.1 mm off); values
    within +-MAX_FIELD_PER_DEPTH (a vertex moving 1,000 times the depth is no tissue's
    linear response, and 1e300 would overflow the rendered field); and any row's largest
    value plus a sample row's at most MAX_FIELD_SUM (a row the load's sweep never reads at
    999 loaded, and drew 362 mm against the simulator's 3.9 mm limit: red team)."""
    if "contact_fields" not in artifact.groups:
        return
    c, s = artifact["contact_fields"], artifact["surface"]
    loadable = np.unique(s["triangles"][np.asarray(s["groups"]) == 1])
    if not np.array_equal(np.sort(c["vertices"]), loadable):
        raise _fail(artifact, "contact_fields/vertices are not the loadable triangles' vertices")
    x = s["vertices"][c["vertices"]]
    extent = max(np.ptp(s["vertices"], axis=0).max(initial=0.0), 1e-300)
    points = artifact["samples"]["points"]
    if np.any(np.linalg.norm(x[c["sample_rows"]] - points, axis=1) > 1e-9 * extent):
        raise _fail(artifact, "contact_fields/sample_rows name a vertex that is not at its sample")
    for p in points:  # another vertex there: the contact's triangle may not be the row's
        if np.count_nonzero(np.linalg.norm(x - p, axis=1) <= 1e-9 * extent) != 1:
            raise _fail(artifact, "contact_fields: a sample's point is at more than one "
                                  "loadable vertex")  # fmt: skip
    if np.any(np.abs(c["fields"]) > MAX_FIELD_PER_DEPTH):
        raise _fail(artifact, f"contact_fields/fields has values beyond +-{MAX_FIELD_PER_DEPTH:g}")
    if "stiffness" in c:
        low, high = TOOL_STIFFNESS_RANGE
        if np.any(c["stiffness"] < low) or np.any(c["stiffness"] > high):
            raise _fail(artifact, f"contact_fields/stiffness has values outside {low:g} to "
                                  f"{high:g} N/mm")  # fmt: skip
    _edge_stiffness(artifact, c, s)
    reach = contact_field_reach(c["fields"], c["sample_rows"])
    if not reach <= MAX_FIELD_SUM:
        raise _fail(artifact, f"contact_fields/fields: a row's largest value plus a sample's "
                              f"reach {reach:.4g} per unit depth (at most {MAX_FIELD_SUM:.4g}: "
                              "the rendered dent could pass the simulator's limit, 10x the "
                              "trained depth)")  # fmt: skip


def _surface(artifact) -> None:
    s = artifact["surface"]
    v, t = s["vertices"], s["triangles"]
    extent = max(np.ptp(v, axis=0).max(initial=0.0), 1e-300)
    area = np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    if len(t) == 0 or np.any(area <= 1e-12 * extent**2):
        raise _fail(artifact, "surface/triangles has a degenerate (zero-area) triangle")
    if len(np.unique(t)) != len(v):
        raise _fail(artifact, "surface/vertices has vertices that no triangle uses")


def _anm_sections(artifact) -> None:
    if "anm" not in artifact.groups:
        return
    a, samples = artifact["anm"], artifact["samples"]
    offsets, a_max = a["section_offsets"], a["a_max"]
    Z, P = len(a_max), len(samples["points"])
    if len(offsets) != P + 1 or a["depth"].shape[1] != artifact.group_attrs["anm"]["order"] + 1:
        raise _fail(artifact, "anm: section_offsets or the series' order do not fit the samples")
    if offsets[0] != 0 or offsets[-1] != Z or np.any(np.diff(offsets) < 1):
        raise _fail(artifact, f"anm/section_offsets must rise from 0 to {Z}, one or more each")
    if np.any(np.diff(offsets) > MAX_SECTIONS):
        raise _fail(artifact, f"anm: a sample has more than {MAX_SECTIONS} sections")
    sample = np.repeat(np.arange(P), np.diff(offsets))
    depth_scale = samples["depth"][-1]
    force_scale = samples["force"].max(axis=1)[sample]
    for name, scale in (("depth", depth_scale), ("force", force_scale)):
        series = a[name]
        end = _horner(series, a_max[:, None])[:, 0]
        previous = np.r_[0.0, end[:-1]]
        previous[offsets[:-1]] = 0.0  # each sample's first section starts at 0
        jump = np.flatnonzero(abs(series[:, 0] - previous) > ANM_JUMP_TOL * scale)
        if len(jump):
            raise _fail(
                artifact, f"anm section {jump[0]} does not start where its predecessor ends"
            )
        slope = min_slope(series, a_max) * a_max
        # depth strictly increasing; force non-decreasing up to rounding
        bad = np.flatnonzero(slope <= 0 if name == "depth" else slope < -1e-6 * scale)
        if len(bad):
            raise _fail(artifact, f"anm/{name} decreases along section {bad[0]}")
        solved = solved_depths(samples)
        if name == "depth" and np.any(end[offsets[1:] - 1] < solved * (1 - 1e-6)):
            raise _fail(artifact, "anm: the sections of a sample end before its solved depth")
    _anm_end_slopes(artifact, offsets[1:] - 1)


def _anm_end_slopes(artifact, last: np.ndarray) -> None:
    """Beyond its last section the runtime extrapolates each sample's series with the slope
    dF/d depth there: within [1/3, 3] times the stored curve's last secant (0.92-0.97 on the
    trained models)."""
    a, s = artifact["anm"], artifact["samples"]
    n1 = a["depth"].shape[1]
    at = a["a_max"][last][:, None]
    dd = _horner(a["depth"][last, 1:] * np.arange(1, n1), at)[:, 0]
    df = _horner(a["force"][last, 1:] * np.arange(1, n1), at)[:, 0]
    secant = (s["force"][:, -1] - s["force"][:, -2]) / s["depth"][1]
    ratio = df / (dd * secant)
    if not np.all((ratio >= 1 / 3) & (ratio <= 3)):
        p = int(np.flatnonzero(~((ratio >= 1 / 3) & (ratio <= 3)))[0])
        raise _fail(artifact, f"anm: sample {p}'s end slope is {ratio[p]:.3g}x its curve's")


def _horner(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Row-wise polynomials c (Z, N1), coefficients in increasing order, at x (Z, m)."""
    out = np.broadcast_to(c[:, -1:], x.shape).copy()
    for k in range(c.shape[1] - 2, -1, -1):
        out = out * x + c[:, k : k + 1]
    return out


def min_slope(c: np.ndarray, a_max: np.ndarray) -> np.ndarray:
    """Each row's smallest derivative on [0, a_max]: at the ends or a real critical point."""
    n1 = c.shape[1]
    d1 = c[:, 1:] * np.arange(1, n1)
    points = [np.zeros((len(c), 1)), a_max[:, None]]
    if n1 > 3:
        roots = _roots(d1[:, 1:] * np.arange(1, n1 - 1))  # of the second derivative
        inside = (abs(roots.imag) <= 1e-9 * (1 + abs(roots))) & (roots.real > 0)
        inside &= roots.real < a_max[:, None]
        points.append(np.where(inside, roots.real, 0.0))
    return _horner(d1, np.hstack(points)).min(axis=1)


def _roots(c: np.ndarray) -> np.ndarray:
    """Roots of each row's polynomial (companion matrices, batched); a row whose leading
    coefficient is zero gets its roots one by one."""
    m = c.shape[1] - 1
    roots = np.zeros((len(c), m), dtype=complex)
    lead = c[:, -1]
    full = lead != 0
    companion = np.zeros((int(full.sum()), m, m))
    companion[:, np.arange(1, m), np.arange(m - 1)] = 1.0
    companion[:, :, -1] = -c[full, :-1] / lead[full, None]
    roots[full] = np.linalg.eigvals(companion)
    for z in np.flatnonzero(~full):
        r = poly.polyroots(np.trim_zeros(c[z], "b")) if np.any(c[z]) else np.zeros(0)
        roots[z] = np.r_[r, np.zeros(m - len(r))]  # padding: 0, an end point anyway
    return roots


def _anm_against_curves(artifact) -> None:
    """The series' force at the depths each sample was solved to against the stored
    full-order curves."""
    if "anm" not in artifact.groups:
        return
    a, s = artifact["anm"], artifact["samples"]
    offsets = a["section_offsets"]
    x = np.linspace(0.0, 1.0, 33) * a["a_max"][:, None]
    depth, force = _horner(a["depth"], x), _horner(a["force"], x)
    solved = solved_depths(s)
    for p in range(len(s["points"])):
        rows = slice(offsets[p], offsets[p + 1])
        solves = s["depth"] <= solved[p] * (1 + 1e-9)  # beyond, both are continuations
        series = np.interp(s["depth"][solves], depth[rows].ravel(), force[rows].ravel())
        if np.max(abs(series - s["force"][p][solves])) > ANM_CURVE_TOL * s["force"][p].max():
            raise _fail(
                artifact, f"anm/force of sample {p} disagrees with samples/force (over 5 %)"
            )


# The hyper-reduced physics (format 2.5). Its bases have orthonormal columns over the organ's
# DOFs, so no entry exceeds 1; a unit force's reduced load is a sum of its nodal loads (P2
# facets give corners negative shares) times such entries: a few units at most.
ELEMENT_NODES = {"hexahedron": 8, "tetrahedron": 10}  # the runtime's elements (Q1, P2)
BASIS_BOUND = 1.0 + 1e-6
MAX_TOOL_LOAD = 10.0  # per N
MAX_WEIGHT = 1e6  # an ECSW weight: elements one sampled element stands for
MAX_TANGENT = 1e15  # N/mm: the constant tangent with a holder's penalty (1e4 x its stiffest)


# the error indicator's check sample (hyperreduced 1.2), with check_element_offsets: a second
# sample's datasets, each as the model's sample's of the name less the prefix
CHECK_DATASETS = ("check_element_nodes", "check_weights", "check_basis_rows",
                  "check_pressure_rows", "check_parameters", "check_constant_tangent")  # fmt: skip


# a held region's holder (hyperreduced 1.3): its patch and the force patterns it holds it in
HOLD_DATASETS = ("hold_offsets", "hold_nodes", "hold_reactions", "hold_ranks")
ORTHONORMAL = 1e-6  # the hold patterns' Gram matrix off the identity, at most


def _hyperreduced(artifact) -> None:
    """``hyperreduced``: offsets that split the elements, load vertices and (with the other two
    grip datasets) grip nodes into the regions (each at least one of each), n + n_p the
    tangent's size, the cell's node count, each element's packed law, each region's load
    vertices distinct and loadable, and bounds on every value (above)."""
    if "hyperreduced" not in artifact.groups:
        return
    h, sym = artifact["hyperreduced"], artifact.symbols
    regions = sym["Hr"]
    if regions < 1:
        raise _fail(artifact, "hyperreduced/centres: the group holds no region")
    offsets = [("element_offsets", sym["He"]), ("load_offsets", sym["Hl"])]
    grip = _together(artifact, h, ("grip_offsets", "grip_nodes", "grip_rows"))
    if grip:
        offsets.append(("grip_offsets", sym["Hg"]))
    check = _together(artifact, h, ("check_element_offsets",) + CHECK_DATASETS)
    if check:
        offsets.append(("check_element_offsets", sym["Hc"]))
    for name, total in offsets:
        o = h[name].astype(np.int64)  # unsigned offsets would wrap in np.diff
        if len(o) != regions + 1 or o[0] != 0 or o[-1] != total or np.any(np.diff(o) < 1):
            raise _fail(artifact, f"hyperreduced/{name} must rise from 0 to {total} in "
                                  f"{regions} steps of at least 1")  # fmt: skip
    if sym["Hs"] != sym["Hq"] + sym["Hp"]:
        raise _fail(artifact, "hyperreduced/constant_tangent is not of n + n_p (basis_rows' "
                              "and pressure_rows' modes)")  # fmt: skip
    cell = artifact.group_attrs["hyperreduced"]["cell"]
    if sym["Hk"] != ELEMENT_NODES[cell]:
        raise _fail(artifact, f"hyperreduced/element_nodes has {sym['Hk']} nodes an element, "
                              f"a {cell} {ELEMENT_NODES[cell]}")  # fmt: skip
    for name in ("parameters", "check_parameters") if check else ("parameters",):
        problem = packed_problem(h[name])
        if problem:
            raise _fail(artifact, f"hyperreduced/{name} {problem}")
    _hyperreduced_loads(artifact, h)
    if grip:
        _hyperreduced_grip(artifact, h)
    if _together(artifact, h, HOLD_DATASETS):
        if not grip:
            raise _fail(artifact, "hyperreduced/hold_nodes: a holder's patch is of grip nodes, "
                                  "and the file has none")  # fmt: skip
        _hyperreduced_hold(artifact, h)
    bounds = (("centres", MAX_LENGTH), ("radii", MAX_LENGTH), ("element_nodes", MAX_LENGTH),
              ("weights", MAX_WEIGHT), ("basis_rows", BASIS_BOUND),
              ("pressure_rows", BASIS_BOUND), ("surface_basis", BASIS_BOUND),
              ("tool_loads", MAX_TOOL_LOAD), ("constant_tangent", MAX_TANGENT))  # fmt: skip
    bounds += (("grip_nodes", MAX_LENGTH), ("grip_rows", BASIS_BOUND)) if grip else ()
    bounds += (("check_element_nodes", MAX_LENGTH), ("check_weights", MAX_WEIGHT),
               ("check_basis_rows", BASIS_BOUND), ("check_pressure_rows", BASIS_BOUND),
               ("check_constant_tangent", MAX_TANGENT)) if check else ()  # fmt: skip
    for name, bound in bounds:
        if np.max(np.abs(h[name]), initial=0.0) > bound:
            raise _fail(artifact, f"hyperreduced/{name} has values beyond +-{bound:g}")
    if artifact.group_attrs["hyperreduced"]["hold_stiffness"] > MAX_TANGENT:
        raise _fail(artifact, f"attribute hold_stiffness of hyperreduced is over {MAX_TANGENT:g}")


def _together(artifact, h, names) -> bool:
    """Whether the optional datasets ``names`` are in the group: all of them or none."""
    present = [name for name in names if name in h]
    if present and len(present) < len(names):
        raise _fail(artifact, f"hyperreduced: {', '.join(names)} go together (the file has "
                              f"only {', '.join(present)})")  # fmt: skip
    return bool(present)


def _hyperreduced_loads(artifact, h) -> None:
    s = artifact["surface"]
    loadable = np.zeros(len(s["vertices"]), dtype=bool)
    loadable[s["triangles"][s["groups"] == 1].ravel()] = True
    o, vertices = h["load_offsets"], h["load_vertices"]
    if not loadable[vertices].all():
        raise _fail(artifact, "hyperreduced/load_vertices has a vertex of no loadable triangle")
    for r in range(len(o) - 1):
        rows = vertices[o[r] : o[r + 1]]
        if len(np.unique(rows)) != len(rows):
            raise _fail(artifact, f"hyperreduced/load_vertices repeats a vertex in region {r}")


def _hyperreduced_grip(artifact, h) -> None:
    """Each region's grip nodes distinct and within its radius plus the tool's of its
    centre (where its holders may grip: the trainer keeps those)."""
    reach = float(artifact.group_attrs["model"]["contact_radius"])
    o = h["grip_offsets"]
    for r in range(len(o) - 1):
        nodes = h["grip_nodes"][o[r] : o[r + 1]]
        far = np.linalg.norm(nodes - h["centres"][r], axis=1).max()
        if not far <= (h["radii"][r] + reach) * (1 + 1e-6):
            raise _fail(artifact, f"hyperreduced/grip_nodes: region {r} has a node {far:.6g} mm "
                                  "from its centre, beyond its radius plus the tool's")  # fmt: skip
        if len(np.unique(nodes, axis=0)) != len(nodes):
            raise _fail(artifact, f"hyperreduced/grip_nodes repeats a node in region {r}")


def _hyperreduced_hold(artifact, h) -> None:
    """Each region's hold nodes (possibly none) distinct rows of its grip nodes, its rank
    within 1..min(3P, Hm) (0 without nodes) and the hold patterns' columns up to it orthonormal over
    the patch's DOFs, the rest zero."""
    regions, rows, width = (artifact.symbols[k] for k in ("Hr", "Hh", "Hm"))
    o, grips = h["hold_offsets"].astype(np.int64), h["grip_offsets"].astype(np.int64)
    if len(o) != regions + 1 or o[0] != 0 or o[-1] != rows or np.any(np.diff(o) < 0):
        raise _fail(artifact, f"hyperreduced/hold_offsets must rise from 0 to {rows} in "
                              f"{regions} steps")  # fmt: skip
    nodes, ranks = h["hold_nodes"].astype(np.int64), h["hold_ranks"].astype(np.int64)
    for r in range(regions):
        patch, rank = nodes[o[r] : o[r + 1]], int(ranks[r])
        if np.any(patch >= grips[r + 1] - grips[r]) or len(np.unique(patch)) != len(patch):
            raise _fail(artifact, f"hyperreduced/hold_nodes: region {r}'s are not distinct "
                                  "rows of its grip nodes")  # fmt: skip
        if not (rank == 0 if not len(patch) else 1 <= rank <= min(3 * len(patch), width)):
            raise _fail(artifact, f"hyperreduced/hold_ranks: region {r}'s {rank} does not fit "
                                  f"its {len(patch)} hold nodes")  # fmt: skip
        if not len(patch):
            continue  # a region without a held holder
        patterns = np.asarray(h["hold_reactions"][o[r] : o[r + 1]], np.float64)
        patterns = patterns.reshape(3 * len(patch), -1)
        if np.any(patterns[:, rank:]):
            raise _fail(artifact, f"hyperreduced/hold_reactions: region {r}'s columns beyond "
                                  f"its rank {rank} are not zero")  # fmt: skip
        gram = patterns[:, :rank].T @ patterns[:, :rank]
        if not np.all(np.abs(gram - np.eye(rank)) <= ORTHONORMAL):
            raise _fail(artifact, f"hyperreduced/hold_reactions: region {r}'s patterns are "
                                  "not orthonormal")  # fmt: skip


CROSS_RULES = (
    _depth_grid,
    _solved_depth,
    _continued_beyond_solved,
    _force_curves,
    _sample_triangulation,
    _tool_stiffness,
    _surface,
    _contact_fields,
    _hyperreduced,
    _anm_sections,
    _anm_against_curves,
)


def check_values(artifact) -> None:
    """Every rule of this module on a read artifact; the first failure is raised."""
    _check_fields(artifact)
    for rule in CROSS_RULES:
        rule(artifact)
