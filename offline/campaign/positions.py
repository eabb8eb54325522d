"""Tool positions of a training campaign on a surface group (mm).

Pure numpy and pydantic (no DOLFINx or PETSc), so a campaign file fails here,
early and cheaply. A position is a node of the surface group (read with
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
    [positions.greedy]                   # optional: greedy training (offline/campaign/greedy.py)
    target = 0.02                        # stop when every sample's error indicator is at most this
    max_solves = 60                      # or when this many positions are solved (initial included)
    per_round = 4                        # positions added per round

Explicit points come first, then the samplers in the order their kind first
appears in the table (all ``polar`` tables, then all ``farthest`` ones in the
example); a node already taken is skipped. The plan depends on the inputs only.
With ``[positions.greedy]`` these are the initial positions; the greedy trainer
appends the nodes it picks (:attr:`PositionsSpec.added`, source ``"greedy"``)
after them, so the first positions keep their indices as the campaign grows.

The tables are typed models (:class:`PositionsTable`, :class:`PolarTable`,
:class:`FarthestTable`, :mod:`hapticrom.offline.tables`); the samplers and
:class:`PositionsSpec` built in code are checked by the same models.

Snapping is reported, not silent: every position keeps the point it was asked
at and its distance to the node it got (an explicit point or a polar centre:
the distance in space; a ring point: in the tangent plane of the ring, since
the plane's sag off a curved surface is by design). :func:`snapping_report`
lists the positions moved by more than ``max(SNAP_REPORT_MIN_MM,
SNAP_REPORT_EDGE_FRACTION x the mean surface edge)`` (0.12 mm on the default
cornea, 2.1 mm on the default hemisphere), and the points dropped
because their node was already taken; the campaign prints it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Annotated, Any

import numpy as np
from pydantic import (
    BeforeValidator,
    Field,
    PlainValidator,
    PrivateAttr,
    WithJsonSchema,
    model_validator,
)

from hapticrom.meshes.msh import Surface, face_area_vectors
from hapticrom.offline.tables import (
    Table,
    boolean,
    check_integer,
    check_value,
    integer,
    invalid,
    number,
    rule,
    validate,
    vector,
)
from hapticrom.shared.errors import InputError

Vector = tuple[float, float, float]

# Below this length of the global x axis projected on the tangent plane (x
# within about 14 degrees of the normal) the first tangent comes from y instead.
TANGENT_FALLBACK = 0.25
# Snapped positions are listed when they moved by more than the larger of these: 0.1 mm,
# or half the mean edge of the surface (a node grid puts an arbitrary point up to about
# 0.7 edge from its nearest node, 0.4 on average: beyond half an edge the plan visibly
# differs from what was asked). At most SNAP_REPORT_ROWS rows, the largest moves first;
# the manifest keeps every position's asked point and move.
SNAP_REPORT_MIN_MM = 0.1
SNAP_REPORT_EDGE_FRACTION = 0.5
SNAP_REPORT_ROWS = 12


@dataclass(frozen=True)
class ToolPosition:
    """One tool position: surface node ``node_tag`` at ``point`` (mm), outward unit ``normal``.

    ``index`` is its place in the plan (0-based); ``source`` the rule that
    chose it: ``"point"``, ``"polar"``, ``"farthest"`` or ``"greedy"``; ``asked``
    the point asked for (None for farthest-point and greedy samples, which pick
    nodes) and
    ``snap_distance`` how far the node is from it (mm; see the module doc).
    """

    index: int
    point: Vector
    normal: Vector
    node_tag: int
    source: str
    asked: Vector | None = None
    snap_distance: float = 0.0


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
        _checked(self, PolarTable)

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
        _checked(self, FarthestTable)


@dataclass(frozen=True)
class GreedyMode:
    """Greedy training: add ``per_round`` positions where the error indicator is worst,
    solve them, repeat until every sample's indicator is at most ``target`` (a relative
    force error) or ``max_solves`` positions (the initial ones included) are solved.
    ``cover``: the whole surface group is the region to train, so up to half of each
    round goes where the samples' triangulation does not reach yet (holes, the rim)."""

    target: float
    max_solves: int
    per_round: int = 4
    cover: bool = False

    def __post_init__(self) -> None:
        _checked(self, GreedyTable)


@dataclass(frozen=True)
class PositionsSpec:
    """Explicit ``points`` (mm; snapped to nodes within ``snap_tolerance`` mm), then ``samplers``,
    then the ``added`` surface nodes (mm; the greedy trainer's, in the order it added them).

    ``greedy``: the greedy mode, or None. Lists are accepted and stored as tuples;
    InputError when there are no positions at all.
    """

    points: tuple[Vector, ...] = ()
    samplers: tuple[PolarSampler | FarthestSampler, ...] = ()
    snap_tolerance: float = 1.0
    greedy: GreedyMode | None = None
    added: tuple[Vector, ...] = ()

    def __post_init__(self) -> None:
        points = tuple(check_value(Points, self.points, "points"))
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "added", tuple(check_value(Points, self.added, "added")))
        if self.greedy is not None and not isinstance(self.greedy, GreedyMode):
            raise InputError(f"not a greedy mode: {self.greedy!r}")
        samplers = tuple(self.samplers)
        for sampler in samplers:
            if not isinstance(sampler, PolarSampler | FarthestSampler):
                raise InputError(f"not a position sampler: {sampler!r}")
        object.__setattr__(self, "samplers", samplers)
        tolerance = check_value(PositiveNumber, self.snap_tolerance, "snap_tolerance")
        object.__setattr__(self, "snap_tolerance", tolerance)
        if not points and not samplers:
            raise InputError("no positions: give points, [[polar]] or [[farthest]] samplers")


def _checked(sampler, table: type[Table]) -> None:
    """Check a sampler's fields with its table's model and keep the values it read."""
    given = {f.name: getattr(sampler, f.name) for f in fields(sampler)}
    checked = validate(table, {k: v for k, v in given.items() if v is not None})
    for name in given:
        object.__setattr__(sampler, name, getattr(checked, name))


# --- the TOML tables --------------------------------------------------------------------------

Number = number(as_float=True)
PositiveNumber = number(gt=0, as_float=True)
Count = integer(ge=1)
Point = vector()
Boolean = boolean()


def _list_of_points(value: Any) -> list:
    if isinstance(value, tuple | np.ndarray):
        return list(value)
    if not isinstance(value, list):
        raise invalid(f"must be a list of points [x, y, z], got {value!r}")
    return value


Points = Annotated[list[Point], BeforeValidator(_list_of_points)]


def _per_ring(value: Any) -> int | tuple[int, ...]:
    if not isinstance(value, list | tuple):
        return check_integer(value, ge=1)
    if not value or any(
        isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1 for v in value
    ):
        raise invalid(f"must be positive integers, one per ring, got {value!r}")
    return tuple(int(v) for v in value)


PerRing = Annotated[
    int | tuple[int, ...],
    PlainValidator(_per_ring),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "integer", "minimum": 1},
                {"type": "array", "items": {"type": "integer", "minimum": 1}, "minItems": 1},
            ]
        }
    ),
]


def _one_or_many(value: Any) -> list:
    """A single ``[positions.polar]`` table is accepted as well as an array ``[[...]]``."""
    if isinstance(value, dict):
        return [value]
    if not isinstance(value, list | tuple):
        raise invalid(f"must be a table or an array of tables, got {value!r}")
    return list(value)


class PolarTable(Table):
    """``[[positions.polar]]``: rings about a centre (see :class:`PolarSampler`)."""

    missing = {"centre": "centre = [x, y, z]"}
    centre: Point = Field(description="mm, snapped to the nearest surface node")
    radius: PositiveNumber = Field(description="mm, of the outermost ring")
    rings: Count = Field(description="number of rings")
    per_ring: PerRing = Field(description="points on every ring, or a list of one per ring")
    include_centre: Boolean = Field(True, description="the centre node itself first")
    phase_deg: Number = Field(0.0, description="angle of each ring's first point (degrees)")

    @model_validator(mode="after")
    def _one_count_per_ring(self) -> PolarTable:
        """A list ``per_ring`` has one entry per ring."""
        if isinstance(self.per_ring, tuple) and len(self.per_ring) != self.rings:
            raise invalid(f"per_ring has {len(self.per_ring)} entries but rings = {self.rings}")
        return self


class FarthestTable(Table):
    """``[[positions.farthest]]``: farthest-point sampling (see :class:`FarthestSampler`)."""

    n: Count = Field(description="number of surface nodes to pick")
    centre: Point | None = Field(None, description="mm; with radius: only nodes in that ball")
    radius: PositiveNumber | None = Field(None, description="mm, needs centre")

    @model_validator(mode="after")
    def _radius_needs_centre(self) -> FarthestTable:
        """A radius is about a centre."""
        if self.radius is not None and self.centre is None:
            raise invalid("radius needs a centre = [x, y, z]")
        return self


Target = number(gt=0, lt=1, as_float=True)


class GreedyTable(Table):
    """``[positions.greedy]``: greedy training (see :class:`GreedyMode`)."""

    missing = {
        "target": "target = 0.02 (the indicator's relative force error to reach)",
        "max_solves": "max_solves (the most positions to solve, the initial ones included)",
    }
    target: Target = Field(description="stop when every sample's indicator is at most this (1)")
    max_solves: Count = Field(description="the most positions solved, the initial ones included")
    per_round: Count = Field(4, description="positions added per round")
    cover: Boolean = Field(
        False,
        description="the whole surface group is the region: add positions where the samples' "
        "triangulation does not reach yet (up to half of a round)",
    )


def asked_count(spec: PositionsSpec) -> tuple[int, bool]:
    """How many initial positions ``spec`` asks for, and whether exactly.

    Points and ring points count one each; a farthest-point sampler up to ``n`` (it
    stops at the candidate nodes). Points that snap to a node already taken are
    dropped when the positions are planned on the mesh.
    """
    count, exact = len(spec.points), True
    for sampler in spec.samplers:
        if isinstance(sampler, PolarSampler):
            count += int(sampler.include_centre) + sum(sampler.ring_counts())
        else:
            count, exact = count + sampler.n, False
    return count, exact


def _one_or_many_schema(schema: dict[str, Any]) -> None:
    """The JSON Schema of ``polar`` and ``farthest``: an array of tables, or one table."""
    for key in ("polar", "farthest"):
        many = schema["properties"][key]
        one = many["items"]
        schema["properties"][key] = {
            "anyOf": [{"type": "array", "items": one}, one],
            "description": many.get("description", ""),
        }


class PositionsTable(Table, json_schema_extra=_one_or_many_schema):
    """``[positions]``: explicit points, then samplers, as the module doc says.

    ``spec`` is the :class:`PositionsSpec`, built as the table is checked.
    """

    points: Points = Field(default_factory=list, description="mm, snapped to surface nodes")
    snap_tolerance: PositiveNumber = Field(
        1.0, description="mm; a point farther from every node is an error"
    )
    polar: Annotated[list[PolarTable], BeforeValidator(_one_or_many)] = Field(
        default_factory=list, description="rings in the tangent plane about a centre"
    )
    farthest: Annotated[list[FarthestTable], BeforeValidator(_one_or_many)] = Field(
        default_factory=list, description="greedy farthest-point sampling"
    )
    greedy: GreedyTable | None = Field(
        None, description="greedy training: the positions above are the initial ones"
    )
    _spec: PositionsSpec | None = PrivateAttr(None)

    @model_validator(mode="wrap")
    @classmethod
    def _build_spec(cls, data: Any, handler) -> PositionsTable:
        """The samplers in the order their kind first appears (tomllib keeps the file's)."""
        table = handler(data)
        samplers: list[PolarSampler | FarthestSampler] = []
        for kind in (key for key in data if key in ("polar", "farthest")):
            for t in getattr(table, kind):
                sampler = PolarSampler if kind == "polar" else FarthestSampler
                samplers.append(
                    sampler(**{name: getattr(t, name) for name in type(t).model_fields})
                )
        greedy = None
        if (g := table.greedy) is not None:
            greedy = GreedyMode(g.target, g.max_solves, g.per_round, g.cover)
        table._spec = rule(
            lambda: PositionsSpec(
                tuple(table.points), tuple(samplers), table.snap_tolerance, greedy
            )
        )
        if greedy is not None:
            _check_greedy_budget(table._spec)
        return table

    @property
    def spec(self) -> PositionsSpec:
        """The positions to plan."""
        return self._spec


def _check_greedy_budget(spec: PositionsSpec) -> None:
    """The greedy ``max_solves`` leaves room for the initial positions the table asks for."""
    asked, exact = asked_count(spec)
    if spec.greedy.max_solves < asked:
        how = "" if exact else "up to "
        raise invalid(
            f"greedy max_solves = {spec.greedy.max_solves} is fewer than the initial positions "
            f"(points, polar, farthest) the table asks for ({how}{asked}): raise max_solves "
            "or ask for fewer initial positions"
        )


def positions_from_dict(data: dict, where: str = "positions") -> PositionsSpec:
    """Parse the ``[positions]`` table ``data`` (as from tomllib); ``where`` names it in errors.

    InputError naming the table and key for unknown keys, wrong types,
    non-positive radius / rings / n / snap_tolerance, a per_ring list whose
    length is not rings, or no positions at all.
    """
    return validate(PositionsTable, data, where=tuple(where.split("."))).spec


# --- planning ---------------------------------------------------------------------------------


def plan_positions(surface: Surface, spec: PositionsSpec) -> list[ToolPosition]:
    """The tool positions of ``spec`` on ``surface``: points first, then each sampler in order.

    A node already taken keeps its first source and is skipped after; the
    indices run 0..P-1 in the final order. InputError if an explicit point or
    a polar centre is farther than ``spec.snap_tolerance`` (mm) from every
    surface node, or a sampler finds no candidate node.
    """
    return _plan(surface, spec)[0]


# One choice of a sampler: (node, the point asked for or None, distance in mm).
Choice = tuple[int, Vector | None, float]


def _plan(surface: Surface, spec: PositionsSpec) -> tuple[list[ToolPosition], list[tuple]]:
    """The positions, and the (source, asked, node) of each choice dropped as a duplicate."""
    if len(surface.nodes) == 0:
        raise InputError(f"surface group {surface.group!r} has no nodes")
    chosen: list[tuple[Choice, str]] = []
    dropped: list[tuple] = []
    taken: set[int] = set()

    def take(choices: list[Choice], source: str) -> None:
        for choice in choices:
            if choice[0] in taken:
                if choice[1] is not None:
                    dropped.append((source, choice[1], choice[0]))
                continue
            taken.add(choice[0])
            chosen.append((choice, source))

    for i, point in enumerate(spec.points):
        node = _snap(surface, point, spec.snap_tolerance, f"points[{i}]")
        take([(node, point, float(_distances(surface, point)[node]))], "point")
    for sampler in spec.samplers:
        if isinstance(sampler, PolarSampler):
            take(_polar_nodes(surface, sampler, spec.snap_tolerance), "polar")
        else:
            take([(n, None, 0.0) for n in _farthest_nodes(surface, sampler)], "farthest")
    for i, point in enumerate(spec.added):
        node = _snap(surface, point, spec.snap_tolerance, f"added[{i}]")
        if node in taken:  # dropping it would renumber the positions after it
            raise InputError(
                f"greedy position added[{i}] {list(point)} is a node already taken by an "
                "earlier position: the campaign's added positions do not fit its table"
            )
        take([(node, None, 0.0)], "greedy")
    positions = [
        _position(surface, index, choice, source) for index, (choice, source) in enumerate(chosen)
    ]
    return positions, dropped


def _position(surface: Surface, index: int, choice: Choice, source: str) -> ToolPosition:
    node, asked, distance = choice
    x, y, z = (float(c) for c in surface.nodes[node])
    nx, ny, nz = (float(c) for c in surface.normals[node])
    asked = None if asked is None else tuple(float(c) for c in asked)
    return ToolPosition(
        index, (x, y, z), (nx, ny, nz), int(surface.node_tags[node]), source, asked, distance
    )


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


def _polar_nodes(surface: Surface, sampler: PolarSampler, tolerance: float) -> list[Choice]:
    centre = _snap(surface, sampler.centre, tolerance, "polar centre")
    origin = surface.nodes[centre]
    normal = surface.normals[centre]
    t1, t2 = tangent_frame(normal)
    nodes = []
    if sampler.include_centre:
        nodes.append((centre, sampler.centre, float(np.linalg.norm(origin - sampler.centre))))
    phase = math.radians(sampler.phase_deg)
    for k, count in enumerate(sampler.ring_counts(), start=1):
        ring_radius = sampler.radius * k / sampler.rings
        angles = phase + 2.0 * math.pi * np.arange(count) / count
        for angle in angles:
            # Points in the tangent plane go to the nearest node: on a curved
            # surface the achieved distance is a little shorter than the ring's.
            target = origin + ring_radius * (math.cos(angle) * t1 + math.sin(angle) * t2)
            node = _nearest(surface, target)[0]
            offset = surface.nodes[node] - target
            in_plane = offset - np.dot(offset, normal) * normal
            nodes.append((node, tuple(target), float(np.linalg.norm(in_plane))))
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


def mean_edge(surface: Surface) -> float:
    """The mean edge length of the surface's faces (mm)."""
    a = surface.nodes[surface.faces]
    b = surface.nodes[np.roll(surface.faces, -1, axis=1)]
    return float(np.linalg.norm(a - b, axis=2).mean())


def snap_report_tolerance(surface: Surface) -> float:
    """Moves (mm) beyond which :func:`snapping_report` lists a position."""
    return max(SNAP_REPORT_MIN_MM, SNAP_REPORT_EDGE_FRACTION * mean_edge(surface))


def plan_with_report(surface: Surface, spec: PositionsSpec) -> tuple[list[ToolPosition], str]:
    """:func:`plan_positions` and its :func:`snapping_report` ('' when nothing was asked)."""
    positions, dropped = _plan(surface, spec)
    return positions, snapping_report(positions, surface, dropped)


def snapping_report(positions: list[ToolPosition], surface: Surface, dropped=()) -> str:
    """The positions moved by more than :func:`snap_report_tolerance` by snapping (mm).

    One summary line, then asked and snapped coordinates and the distance of each
    position moved further, then the asked points dropped because their nearest
    node was already taken.
    """
    asked = [p for p in positions if p.asked is not None]
    if not asked and not dropped:
        return ""
    edge = mean_edge(surface)
    tolerance = snap_report_tolerance(surface)
    moved = [p for p in asked if p.snap_distance > tolerance]
    lines = []
    if asked and not moved:
        far = max(p.snap_distance for p in asked)
        lines.append(
            f"snapping: {len(asked)} asked point(s) moved at most {far:.3g} mm to their surface "
            f"nodes (none by more than {tolerance:.3g} mm)"
        )
    elif asked:
        far = max(asked, key=lambda p: p.snap_distance)
        lines.append(
            f"snapping: {len(asked)} asked point(s) moved to the nearest surface node, the "
            f"farthest by {far.snap_distance:.3g} mm (position {far.index}); {len(moved)} by "
            f"more than {tolerance:.3g} mm (the larger of {SNAP_REPORT_MIN_MM:g} mm and "
            f"{SNAP_REPORT_EDGE_FRACTION:g} x the mean surface edge {edge:.3g} mm)"
        )
    if moved:
        lines += _moved_rows(sorted(moved, key=lambda p: -p.snap_distance))
    if dropped:
        shown = "; ".join(
            f"{src} ({at[0]:.3g}, {at[1]:.3g}, {at[2]:.3g})" for src, at, _ in dropped
        )
        lines.append(
            f"snapping: {len(dropped)} asked point(s) dropped, their nearest node already "
            f"taken: {shown}"
        )
    return "\n".join(lines)


def _moved_rows(moved: list[ToolPosition]) -> list[str]:
    """Table rows of the largest moves (at most SNAP_REPORT_ROWS), with a header and a note."""
    lines = [
        f"{'index':>5}  {'source':<6} {'asked x':>8} {'y':>8} {'z':>8}   "
        f"{'snapped x':>9} {'y':>8} {'z':>8} {'moved':>7}"
    ]
    for p in moved[:SNAP_REPORT_ROWS]:
        lines.append(
            f"{p.index:>5}  {p.source:<6} {_xyz(p.asked)}   {_xyz(p.point, 9)} "
            f"{p.snap_distance:>7.3f}"
        )
    more = len(moved) - SNAP_REPORT_ROWS
    lines.append(
        (f"({more} more, all in the campaign's manifest.json; " if more > 0 else "(")
        + "mm; ring points are asked in the tangent plane at the ring's centre and their "
        "move measured in that plane)"
    )
    return lines


def _xyz(point, first: int = 8) -> str:
    x, y, z = point
    return f"{x:>{first}.3f} {y:>8.3f} {z:>8.3f}"
