"""The rules file of ``hapticrom mesh import``: which boundary faces are clamped, loadable, free.

An imported mesh carries none of hapticrom's surface groups, so a small TOML file says
which of its boundary faces the organ is held by (``clamped``) and which a tool may touch
(``loadable``); every other boundary face is ``free``. ``examples/mesh-import-rules.toml``
is a commented example of every key. In short::

    name = "kidney"                          # optional: the sidecar's name (default: file stem)
    description = "..."                      # optional
    default_contact_point = [0, -40, 0]      # optional, mm: snapped to the nearest loadable node

    [clamped]
    components = "xyz"                       # displacement components held (default xyz)
    [[clamped.box]]                          # faces whose centroid is inside the box
    min = [-10, 20, -10]
    max = [10, 60, 10]

    [loadable]
    [[loadable.normal_cone]]                 # faces whose outward normal is within the cone
    axis = [0, -1, 0]
    max_angle = 60.0

Selectors (each group takes any number of each, as ``[[GROUP.KIND]]`` arrays or one
``[GROUP.KIND]`` table; all have an optional ``name`` used in messages):

* ``box``: ``min``, ``max`` corners (mm): the face's centroid lies inside, bounds included
  (as SOFA's BoxROI; the centroid, not all nodes, so a face straddling the box's side is
  decided by where most of it lies);
* ``half_space``: ``point``, ``normal`` (mm): the face's centroid c satisfies
  (c - point) . normal >= 0 (the normal points into the selected side, i.e. it is the
  organ's outward direction there);
* ``normal_cone``: ``axis``, ``max_angle`` (degrees, (0, 180]): the angle between the
  face's outward unit normal and the axis is at most max_angle;
* ``nodes``: ``ids`` and ``base`` (0 or 1): the face is selected when all its corner nodes
  are listed. An id is a node's position in the input file's node list, counted from
  ``base``: ``base = 0`` for VTK/VTU point ids (ParaView's), ``base = 1`` for the n-th node
  of a .msh, .mesh or .inp file (its node tag when the file numbers its nodes 1..n in order).

Coordinates are in mm, after ``--scale``: the same rules serve a mesh in cm imported with
``--scale 10`` and the same mesh in mm. A group is the union of its selectors. Precedence:
``clamped`` wins over ``loadable`` (a face both select is clamped); ``free`` is the rest.
Every selector must select at least one face (a loadable one at least one face that is not
clamped), and both groups must end up non-empty; otherwise one :class:`InputError` names
the selector.

Validated with the project's table models (:mod:`hapticrom.offline.tables`): unknown keys,
wrong types, NaN, a zero axis (or one whose length is outside :data:`DIRECTION_LENGTH`), a
node id beyond :data:`MAX_NODE_ID` are refused with one line naming the file, table and key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BeforeValidator, Field, PlainValidator, WithJsonSchema, model_validator

from hapticrom.meshes.fibres import RULES as FIBRE_RULES
from hapticrom.offline.config import read_toml
from hapticrom.offline.tables import (
    VECTOR_SCHEMA,
    Table,
    check_integer,
    check_vector,
    choice,
    integer,
    invalid,
    number,
    text,
    validate,
    vector,
)
from hapticrom.shared.errors import InputError

GROUPS = ("clamped", "loadable")  # the groups a rules file selects; the rest is "free"
SELECTOR_KINDS = ("box", "half_space", "normal_cone", "nodes")

# The largest node id: every integer up to it is exact in a JSON number and a float64, and
# far beyond any mesh's node count (a larger id would only overflow numpy's int64).
MAX_NODE_ID = 2**53 - 1
# A direction's length (axis, normal): the selectors normalise it, and beyond these bounds
# the squares of its components underflow or overflow. Only its direction counts.
DIRECTION_LENGTH = (1e-100, 1e100)

Point = vector()
Angle = number(gt=0, le=180, as_float=True)
Base = integer(ge=0, le=1)
FibreRule = choice(FIBRE_RULES)
Label = text("a non-empty name")
Components = text(
    'one to three of x, y, z without repeats, e.g. "xyz"',
    accept=lambda v: 0 < len(v) <= 3 and set(v) <= set("xyz") and len(set(v)) == len(v),
    pattern="^(?!.*(.).*\\1)[xyz]{1,3}$",
)


def _direction(value: Any) -> tuple[float, float, float]:
    """Three finite numbers whose length lies in :data:`DIRECTION_LENGTH`."""
    direction = check_vector(value, nonzero=True)
    length = math.hypot(*direction)  # hypot neither underflows nor overflows here
    low, high = DIRECTION_LENGTH
    if not low <= length <= high:
        raise invalid(
            f"must have a length in [{low:g}, {high:g}], got {length:.3g} (only its direction "
            "counts: scale it, e.g. to a unit vector)"
        )
    return direction


Direction = Annotated[
    tuple[float, float, float], PlainValidator(_direction), WithJsonSchema(VECTOR_SCHEMA)
]


def _node_ids(value: Any) -> tuple[int, ...]:
    """A non-empty list of integers in [0, MAX_NODE_ID] (the base is checked against them
    later)."""
    if not isinstance(value, list | tuple) or not value:
        raise invalid(f"must be a non-empty list of node ids, got {value!r}")
    return tuple(check_integer(v, ge=0, le=MAX_NODE_ID) for v in value)


NodeIds = Annotated[
    tuple[int, ...],
    PlainValidator(_node_ids),
    WithJsonSchema(
        {
            "type": "array",
            "items": {"type": "integer", "minimum": 0, "maximum": MAX_NODE_ID},
            "minItems": 1,
        }
    ),
]


def _one_or_many(value: Any) -> list:
    """One ``[GROUP.KIND]`` table is accepted as well as an array ``[[GROUP.KIND]]``."""
    if isinstance(value, dict):
        return [value]
    if not isinstance(value, list | tuple):
        raise invalid(f"must be a table or an array of tables, got {value!r}")
    return list(value)


@dataclass(frozen=True)
class BoundaryFaces:
    """What the selectors look at, one row per boundary face (mm, outward normals).

    ``source_ids`` (k, 3|4): the corner nodes as positions in the input file's node list
    (0-based); ``source_node_count``: how many nodes the file has.
    """

    centroids: np.ndarray
    normals: np.ndarray
    source_ids: np.ndarray
    source_node_count: int


class Selector(Table):
    """What every selector has: an optional name for messages."""

    name: Label | None = Field(None, description="names the selector in messages")

    def select(self, faces: BoundaryFaces, label: str) -> np.ndarray:
        """Boolean mask (k,) of the faces this selector selects."""
        raise NotImplementedError


class BoxSelector(Selector):
    """``[[GROUP.box]]``: faces whose centroid lies in the box [min, max] (bounds included)."""

    missing = {"min": "min = [x, y, z]", "max": "max = [x, y, z]"}
    min: Point = Field(description="mm, the box's lowest corner")
    max: Point = Field(description="mm, the box's highest corner")

    @model_validator(mode="after")
    def _ordered(self) -> BoxSelector:
        """min <= max in every axis."""
        if any(lo > hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise invalid(f"min {list(self.min)} must not exceed max {list(self.max)} in any axis")
        return self

    def select(self, faces: BoundaryFaces, label: str) -> np.ndarray:
        """Centroids inside the box."""
        c = faces.centroids
        return np.all((c >= np.asarray(self.min)) & (c <= np.asarray(self.max)), axis=1)


class HalfSpaceSelector(Selector):
    """``[[GROUP.half_space]]``: faces whose centroid c has (c - point) . normal >= 0."""

    missing = {"point": "point = [x, y, z]", "normal": "normal = [x, y, z]"}
    point: Point = Field(description="mm, a point of the bounding plane")
    normal: Direction = Field(description="points into the selected side (need not be unit)")

    def select(self, faces: BoundaryFaces, label: str) -> np.ndarray:
        """Centroids on the side the normal points to (the plane included)."""
        offset = faces.centroids - np.asarray(self.point)
        return offset @ np.asarray(self.normal) >= 0.0


class NormalConeSelector(Selector):
    """``[[GROUP.normal_cone]]``: faces whose outward normal is within max_angle of axis."""

    missing = {"axis": "axis = [x, y, z]", "max_angle": "max_angle = 45.0"}
    axis: Direction = Field(description="the cone's axis (need not be unit)")
    max_angle: Angle = Field(description="degrees in (0, 180]: the cone's half-angle")

    def select(self, faces: BoundaryFaces, label: str) -> np.ndarray:
        """Unit outward normals n with n . axis / |axis| >= cos(max_angle)."""
        axis = np.asarray(self.axis) / np.linalg.norm(self.axis)
        return faces.normals @ axis >= math.cos(math.radians(self.max_angle))


class NodesSelector(Selector):
    """``[[GROUP.nodes]]``: faces all of whose corner nodes are listed (ids from ``base``)."""

    missing = {"ids": "ids = [1, 2, 3]", "base": "base = 0 (VTK, VTU) or 1 (.msh, .mesh, .inp)"}
    ids: NodeIds = Field(description="node ids: positions in the input file's node list")
    base: Base = Field(description="0: ids count from 0 (VTK point ids); 1: from 1 (gmsh, ...)")

    def select(self, faces: BoundaryFaces, label: str) -> np.ndarray:
        """Faces whose corners are all among the listed nodes."""
        ids = np.asarray(self.ids, dtype=np.int64) - self.base
        last = faces.source_node_count - 1 + self.base
        bad = ids[(ids < 0) | (ids >= faces.source_node_count)]
        if len(bad):
            raise InputError(
                f"{label}: node id {int(bad[0]) + self.base} is not a node of the input "
                f"(with base = {self.base} the ids run from {self.base} to {last})"
            )
        return np.all(np.isin(faces.source_ids, ids), axis=1)


def _many(model: type[Selector]) -> Any:
    return Annotated[list[model], BeforeValidator(_one_or_many)]


class GroupTable(Table):
    """``[loadable]`` (and the selectors of ``[clamped]``): the union of its selectors."""

    box: _many(BoxSelector) = Field(default_factory=list, description="boxes (centroid inside)")
    half_space: _many(HalfSpaceSelector) = Field(
        default_factory=list, description="half-spaces (centroid on the normal's side)"
    )
    normal_cone: _many(NormalConeSelector) = Field(
        default_factory=list, description="cones of outward normals"
    )
    nodes: _many(NodesSelector) = Field(
        default_factory=list, description="node lists (all corners listed)"
    )

    def selectors(self, group: str) -> list[tuple[str, Selector]]:
        """(label for messages, selector) of every selector, kind by kind in file order."""
        labelled = []
        for kind in SELECTOR_KINDS:
            for i, selector in enumerate(getattr(self, kind), start=1):
                name = f" '{selector.name}'" if selector.name else ""
                labelled.append((f"[[{group}.{kind}]] #{i}{name}", selector))
        return labelled


class ClampedTable(GroupTable):
    """``[clamped]``: its selectors and the displacement components held there."""

    components: Components = Field("xyz", description="components held at zero: x, y, z")


class FibresTable(Table):
    """``[fibres]`` (optional): a fibre rule of :mod:`hapticrom.meshes.fibres` (for HGO)."""

    missing = {"rule": 'rule = "spherical_cap"'}
    rule: FibreRule = Field(description="the fibre rule")
    centre: Point = Field(description="mm, the spherical cap's centre of curvature")
    m_axis: Direction = Field(description="first family's direction before projection")
    n_axis: Direction = Field(description="second family's direction before projection")

    def spec(self) -> dict[str, Any]:
        """The sidecar's ``fibres`` entry."""
        return {
            "rule": self.rule,
            "centre": list(self.centre),
            "m_axis": list(self.m_axis),
            "n_axis": list(self.n_axis),
        }


class RulesFile(Table):
    """A rules file: the sidecar's name and description, the groups, the contact point."""

    name: Label | None = Field(None, description="the mesh's name (default: the output's stem)")
    description: Label | None = Field(None, description="one paragraph about the organ")
    default_contact_point: Point | None = Field(
        None, description="mm; snapped to the nearest loadable node (default: see the docs)"
    )
    clamped: ClampedTable = Field(description="where the organ is held")
    loadable: GroupTable = Field(description="where a tool may touch it")
    fibres: FibresTable | None = Field(None, description="fibre directions (HGO law)")


def read_rules(path: str | Path) -> RulesFile:
    """Read and check a rules file; one InputError naming the file, table and key otherwise."""
    path = Path(path)
    return validate(RulesFile, read_toml(path, "rules file"), str(path))


def classify_faces(rules: RulesFile, faces: BoundaryFaces, source: str) -> dict[str, np.ndarray]:
    """Boolean masks ``clamped``, ``loadable``, ``free`` partitioning the boundary faces.

    ``clamped`` wins over ``loadable``. InputError (prefixed with ``source``, the rules
    file) for a selector that selects nothing, or an empty clamped or loadable group.
    """
    clamped = _union(rules.clamped, "clamped", faces, source, taken=None)
    if not clamped.any():
        raise InputError(
            f"{source}: no clamped face: [clamped] has no selector ({', '.join(SELECTOR_KINDS)}); "
            "an organ held nowhere is a free rigid body"
        )
    loadable = _union(rules.loadable, "loadable", faces, source, taken=clamped)
    if not loadable.any():
        raise InputError(
            f"{source}: no loadable face: [loadable] has no selector "
            f"({', '.join(SELECTOR_KINDS)}); a tool needs a surface to touch"
        )
    return {"clamped": clamped, "loadable": loadable, "free": ~(clamped | loadable)}


def _union(
    table: GroupTable, group: str, faces: BoundaryFaces, source: str, taken: np.ndarray | None
) -> np.ndarray:
    """The faces any selector of ``table`` selects, less ``taken`` (faces of a stronger group)."""
    mask = np.zeros(len(faces.centroids), dtype=bool)
    for label, selector in table.selectors(group):
        try:
            picked = selector.select(faces, label)
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        if not picked.any():
            raise InputError(f"{source}: {label} selects no boundary face")
        if taken is not None and not (picked & ~taken).any():
            raise InputError(
                f"{source}: {label} selects {np.count_nonzero(picked)} face(s), all of them "
                "clamped (clamped wins over loadable)"
            )
        mask |= picked
    return mask if taken is None else mask & ~taken


def summary(rules: RulesFile) -> str:
    """One line about a checked rules file (``hapticrom check``): its name and selectors."""

    def count(group: str) -> str:
        selectors = getattr(rules, group).selectors(group)
        return f"{len(selectors)} {group} selector{'s' if len(selectors) != 1 else ''}"

    name = f"'{rules.name}', " if rules.name else ""
    return f"{name}{count('clamped')} ({rules.clamped.components}), {count('loadable')}"
