"""Tool positions of a training campaign on a surface group (mm).

Pure numpy (no DOLFINx or PETSc), so a campaign file fails here, early and
cheaply. A position is a node of the surface group (read with
:func:`hapticrom.meshes.msh.read_surface`) with its outward unit normal, the
direction the tool pushes against. The campaign TOML table::

    [positions]
    points = [[0.0, 0.0, 0.0]]           # snapped to the nearest surface node
    snap_tolerance = 1.0                 # mm; a point farther from every node is an error
    [[positions.polar]]                  # rings in the tangent plane about a centre
    centre = [0.0, 0.0, 0.0]
    radius = 3.0                         # mm, of the outermost ring
    rings = 3
    per_ring = [6, 12, 18]               # or one integer for every ring
    [[positions.farthest]]               # greedy farthest-point sampling
    n = 10
    centre = [0.0, 0.0, 0.0]             # optional, with radius: only nodes in that ball
    radius = 3.0

Explicit points come first, then the samplers in the order their kind first
appears in the table (all ``polar`` tables, then all ``farthest`` ones in the
example); a node already taken is skipped. The plan depends on the inputs only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hapticrom.meshes.msh import Surface, face_area_vectors
from hapticrom.shared.errors import InputError

Vector = tuple[float, float, float]

POSITIONS_KEYS = ("points", "snap_tolerance", "polar", "farthest")
POLAR_KEYS = ("centre", "radius", "rings", "per_ring", "include_centre", "phase_deg")
POLAR_REQUIRED = ("centre", "radius", "rings", "per_ring")
FARTHEST_KEYS = ("n", "centre", "radius")
# Below this length of the global x axis projected on the tangent plane (x
# within about 14 degrees of the normal) the first tangent comes from y instead.
TANGENT_FALLBACK = 0.25


@dataclass(frozen=True)
class ToolPosition:
    """One tool position: surface node ``node_tag`` at ``point`` (mm), outward unit ``normal``.

    ``index`` is its place in the plan (0-based); ``source`` the rule that
    chose it: ``"point"``, ``"polar"`` or ``"farthest"``.
    """

    index: int
    point: Vector
    normal: Vector
    node_tag: int
    source: str


@dataclass(frozen=True)
class PolarSampler:
    """Rings about ``centre`` in the surface's tangent plane there, snapped to nodes.

    Ring k = 1..``rings`` has radius ``radius`` * k / ``rings`` (mm) and
    ``per_ring`` points (one int for all rings, or one per ring), the first at
    ``phase_deg`` from the first tangent vector. ``include_centre`` adds the
    centre node itself first.
    """

    centre: Vector
    radius: float
    rings: int
    per_ring: int | tuple[int, ...]
    include_centre: bool = True
    phase_deg: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vector(self.centre, "centre"))
        object.__setattr__(self, "radius", _number(self.radius, "radius", positive=True))
        object.__setattr__(self, "rings", _integer(self.rings, "rings"))
        object.__setattr__(self, "per_ring", _per_ring(self.per_ring, self.rings))
        if not isinstance(self.include_centre, bool):
            raise InputError(f"include_centre must be true or false, got {self.include_centre!r}")
        object.__setattr__(self, "phase_deg", _number(self.phase_deg, "phase_deg"))

    def ring_counts(self) -> tuple[int, ...]:
        """Points on each ring, innermost first."""
        if isinstance(self.per_ring, int):
            return (self.per_ring,) * self.rings
        return self.per_ring


@dataclass(frozen=True)
class FarthestSampler:
    """Greedy farthest-point sampling of ``n`` surface nodes (Euclidean distances, mm).

    Candidates are the nodes within ``radius`` of ``centre`` (all nodes when
    ``radius`` is None); the first is the candidate nearest ``centre``, or
    nearest the surface's area-weighted centroid when ``centre`` is None.
    Fewer than ``n`` candidates: all of them.
    """

    n: int
    centre: Vector | None = None
    radius: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "n", _integer(self.n, "n"))
        if self.centre is not None:
            object.__setattr__(self, "centre", _vector(self.centre, "centre"))
        if self.radius is not None:
            if self.centre is None:
                raise InputError("radius needs a centre = [x, y, z]")
            object.__setattr__(self, "radius", _number(self.radius, "radius", positive=True))


@dataclass(frozen=True)
class PositionsSpec:
    """Explicit ``points`` (mm; snapped to nodes within ``snap_tolerance`` mm), then ``samplers``.

    Lists are accepted and stored as tuples; InputError when there are no positions at all.
    """

    points: tuple[Vector, ...] = ()
    samplers: tuple[PolarSampler | FarthestSampler, ...] = ()
    snap_tolerance: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.points, list | tuple):
            raise InputError(f"points must be a list of [x, y, z], got {self.points!r}")
        points = tuple(_vector(p, f"points[{i}]") for i, p in enumerate(self.points))
        object.__setattr__(self, "points", points)
        samplers = tuple(self.samplers)
        for sampler in samplers:
            if not isinstance(sampler, PolarSampler | FarthestSampler):
                raise InputError(f"not a position sampler: {sampler!r}")
        object.__setattr__(self, "samplers", samplers)
        tolerance = _number(self.snap_tolerance, "snap_tolerance", positive=True)
        object.__setattr__(self, "snap_tolerance", tolerance)
        if not points and not samplers:
            raise InputError("no positions: give points, [[polar]] or [[farthest]] samplers")


# --- validation helpers: messages name the key; the TOML parser adds the table ---------------


def _number(value: Any, key: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise InputError(f"{key} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise InputError(f"{key} must be finite, got {value!r}")
    if positive and value <= 0:
        raise InputError(f"{key} must be positive, got {value!r}")
    return float(value)


def _integer(value: Any, key: str) -> int:
    """A positive integer (counts of rings, points, samples)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise InputError(f"{key} must be an integer, got {value!r}")
    if value <= 0:
        raise InputError(f"{key} must be positive, got {value!r}")
    return int(value)


def _vector(value: Any, key: str) -> Vector:
    if not isinstance(value, list | tuple | np.ndarray) or len(value) != 3:
        raise InputError(f"{key} must be three numbers [x, y, z], got {value!r}")
    x, y, z = (_number(c, key) for c in value)
    return (x, y, z)


def _per_ring(value: Any, rings: int) -> int | tuple[int, ...]:
    if isinstance(value, list | tuple):
        if len(value) != rings:
            raise InputError(f"per_ring has {len(value)} entries but rings = {rings}")
        return tuple(_integer(v, "per_ring") for v in value)
    return _integer(value, "per_ring")


# --- the TOML table ---------------------------------------------------------------------------


def positions_from_dict(data: dict, where: str = "positions") -> PositionsSpec:
    """Parse the ``[positions]`` table ``data`` (as from tomllib); ``where`` names it in errors.

    InputError naming the table and key for unknown keys, wrong types,
    non-positive radius / rings / n / snap_tolerance, a per_ring list whose
    length is not rings, or no positions at all.
    """
    _check_table(data, f"[{where}]", POSITIONS_KEYS)
    samplers: list[PolarSampler | FarthestSampler] = []
    # Kinds in the order they first appear (tomllib keeps the file's order).
    for key, value in data.items():
        if key in ("polar", "farthest"):
            samplers.extend(_sampler_tables(key, value, where))
    return _build(
        f"[{where}]",
        PositionsSpec,
        points=data.get("points", ()),
        samplers=samplers,
        snap_tolerance=data.get("snap_tolerance", 1.0),
    )


def _sampler_tables(kind: str, value: Any, where: str) -> list[PolarSampler | FarthestSampler]:
    # A single [positions.polar] table is accepted as well as an array [[positions.polar]].
    tables = [value] if isinstance(value, dict) else value
    if not isinstance(tables, list):
        raise InputError(f"[{where}] {kind} must be tables [[{where}.{kind}]], got {value!r}")
    samplers = []
    for number, table in enumerate(tables, start=1):
        label = f"[[{where}.{kind}]] #{number}"
        if kind == "polar":
            _check_table(table, label, POLAR_KEYS, POLAR_REQUIRED)
            samplers.append(_build(label, PolarSampler, **table))
        else:
            _check_table(table, label, FARTHEST_KEYS, ("n",))
            samplers.append(_build(label, FarthestSampler, **table))
    return samplers


def _check_table(table: Any, label: str, allowed: tuple, required: tuple = ()) -> None:
    if not isinstance(table, dict):
        raise InputError(f"{label} must be a table, got {table!r}")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise InputError(
            f"{label} unknown key(s) {', '.join(unknown)}; allowed: {', '.join(allowed)}"
        )
    missing = [key for key in required if key not in table]
    if missing:
        raise InputError(f"{label} missing key(s) {', '.join(missing)}")


def _build(label: str, cls, **kwargs):
    """``cls(**kwargs)`` with the table's label put in front of a validation error."""
    try:
        return cls(**kwargs)
    except InputError as error:
        raise InputError(f"{label} {error}") from None


# --- planning ---------------------------------------------------------------------------------


def plan_positions(surface: Surface, spec: PositionsSpec) -> list[ToolPosition]:
    """The tool positions of ``spec`` on ``surface``: points first, then each sampler in order.

    A node already taken keeps its first source and is skipped after; the
    indices run 0..P-1 in the final order. InputError if an explicit point or
    a polar centre is farther than ``spec.snap_tolerance`` (mm) from every
    surface node, or a sampler finds no candidate node.
    """
    if len(surface.nodes) == 0:
        raise InputError(f"surface group {surface.group!r} has no nodes")
    chosen: list[tuple[int, str]] = []
    taken: set[int] = set()

    def take(nodes: list[int], source: str) -> None:
        for node in nodes:
            if node not in taken:
                taken.add(node)
                chosen.append((node, source))

    for i, point in enumerate(spec.points):
        take([_snap(surface, point, spec.snap_tolerance, f"points[{i}]")], "point")
    for sampler in spec.samplers:
        if isinstance(sampler, PolarSampler):
            take(_polar_nodes(surface, sampler, spec.snap_tolerance), "polar")
        else:
            take(_farthest_nodes(surface, sampler), "farthest")
    return [_position(surface, index, node, source) for index, (node, source) in enumerate(chosen)]


def _position(surface: Surface, index: int, node: int, source: str) -> ToolPosition:
    x, y, z = (float(c) for c in surface.nodes[node])
    nx, ny, nz = (float(c) for c in surface.normals[node])
    return ToolPosition(index, (x, y, z), (nx, ny, nz), int(surface.node_tags[node]), source)


def _distances(surface: Surface, point) -> np.ndarray:
    """Euclidean distances (k,) in mm from ``point`` to every surface node."""
    return np.sqrt(np.sum((surface.nodes - np.asarray(point, dtype=np.float64)) ** 2, axis=1))


def _nearest(surface: Surface, point) -> tuple[int, float]:
    """The nearest node (the lowest index on a tie) and its distance in mm."""
    distances = _distances(surface, point)
    node = int(np.argmin(distances))
    return node, float(distances[node])


def _snap(surface: Surface, point: Vector, tolerance: float, label: str) -> int:
    node, distance = _nearest(surface, point)
    if distance > tolerance:
        raise InputError(
            f"{label} {list(point)} is {distance:.3g} mm from the nearest node of surface "
            f"group {surface.group!r} (snap_tolerance = {tolerance:g} mm)"
        )
    return node


def tangent_frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal tangent vectors (t1, t2) for a unit ``normal``, with t1 x t2 = normal.

    t1 is the global x axis projected on the tangent plane (y when x is
    nearly normal), so grids on different meshes line up with the axes.
    """
    normal = np.asarray(normal, dtype=np.float64)
    for axis in np.eye(3)[:2]:
        t1 = axis - np.dot(axis, normal) * normal
        length = float(np.linalg.norm(t1))
        if length > TANGENT_FALLBACK:
            t1 = t1 / length
            return t1, np.cross(normal, t1)
    raise AssertionError("x and y cannot both be nearly parallel to a unit normal")


def _polar_nodes(surface: Surface, sampler: PolarSampler, tolerance: float) -> list[int]:
    centre = _snap(surface, sampler.centre, tolerance, "polar centre")
    origin = surface.nodes[centre]
    t1, t2 = tangent_frame(surface.normals[centre])
    nodes = [centre] if sampler.include_centre else []
    phase = math.radians(sampler.phase_deg)
    for k, count in enumerate(sampler.ring_counts(), start=1):
        ring_radius = sampler.radius * k / sampler.rings
        angles = phase + 2.0 * math.pi * np.arange(count) / count
        for angle in angles:
            # Points in the tangent plane go to the nearest node: on a curved
            # surface the achieved distance is a little shorter than the ring's.
            target = origin + ring_radius * (math.cos(angle) * t1 + math.sin(angle) * t2)
            nodes.append(_nearest(surface, target)[0])
    return nodes


def _farthest_nodes(surface: Surface, sampler: FarthestSampler) -> list[int]:
    centre = surface_centroid(surface) if sampler.centre is None else sampler.centre
    distances = _distances(surface, centre)
    if sampler.radius is None:
        candidates = np.arange(len(surface.nodes))
    else:
        candidates = np.flatnonzero(distances <= sampler.radius)
    if len(candidates) == 0:
        raise InputError(
            f"farthest sampler: no node of surface group {surface.group!r} within "
            f"{sampler.radius:g} mm of {list(sampler.centre)}"
        )
    points = surface.nodes[candidates]
    # argmin/argmax return the first extremum: ties go to the lowest node index.
    picked = [int(np.argmin(distances[candidates]))]
    gap = np.sqrt(np.sum((points - points[picked[0]]) ** 2, axis=1))
    while len(picked) < min(sampler.n, len(candidates)):
        picked.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.sqrt(np.sum((points - points[picked[-1]]) ** 2, axis=1)))
    return [int(candidates[i]) for i in picked]


def surface_centroid(surface: Surface) -> np.ndarray:
    """The area-weighted centroid (3,) of the surface's faces, mm."""
    areas = np.linalg.norm(face_area_vectors(surface.nodes, surface.faces), axis=1)
    centres = surface.nodes[surface.faces].mean(axis=1)
    return areas @ centres / areas.sum()


# --- logging ----------------------------------------------------------------------------------


def positions_table(positions: list[ToolPosition]) -> str:
    """A short listing for logs: index, source, x y z and the distance from the first (mm)."""
    lines = [f"{'index':>5}  {'source':<8} {'x':>10} {'y':>10} {'z':>10} {'from #0':>10}"]
    if not positions:
        return lines[0] + "\n(no positions)"
    first = np.asarray(positions[0].point)
    for p in positions:
        distance = float(np.linalg.norm(np.asarray(p.point) - first))
        x, y, z = p.point
        lines.append(
            f"{p.index:>5}  {p.source:<8} {x:>10.3f} {y:>10.3f} {z:>10.3f} {distance:>10.3f}"
        )
    lines.append(f"({len(positions)} positions, mm)")
    return "\n".join(lines)
