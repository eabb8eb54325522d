"""The on-disk mesh format: a gmsh MSH 4.1 file plus a JSON sidecar.

A mesh is ``NAME.msh`` (written through the gmsh Python API as discrete
entities, so the node and element numbers are exactly ours; binary by
default, so coordinates round-trip bit for bit) and ``NAME.json`` next to it.
The .msh carries the physical groups

* ``"tissue"`` (dim 3): every cell;
* ``"clamped"``, ``"loadable"``, ``"free"`` (dim 2): a partition of the whole
  outer boundary into faces (``"free"`` is left out when it is empty).

The physical tags are fixed (:data:`GROUP_TAGS`) and distinct across
dimensions so a tag alone names its group. Coordinates are in mm.

Besides the writer this module holds the pure-numpy pieces every generator
shares: :class:`BuiltMesh`, :func:`boundary_faces` and :func:`resolve_params`;
and :func:`read_surface`, which reads one surface group back (nodes, faces,
outward vertex normals) on one process, for planning tool positions.
gmsh is imported lazily so the numpy builders work without it.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hapticrom.shared.errors import InputError
from hapticrom.shared.files import read_versioned_json
from hapticrom.shared.geometry import (  # noqa: F401 (face_area_vectors: for the planners)
    corner_area_vectors,
    face_area_vectors,
    vertex_normals,
)

SIDECAR_FORMAT = "hapticrom-mesh"
SIDECAR_VERSION = 1
REFINEMENTS = ("coarse", "default", "fine")
SURFACE_GROUPS = ("clamped", "loadable", "free")
# Physical tags written to the .msh; unique over all dimensions.
GROUP_TAGS = {"tissue": 1, "clamped": 2, "loadable": 3, "free": 4}

# gmsh element types and the outward-oriented local faces of each cell type
# (right-hand rule gives the outward normal for a positively oriented cell).
GMSH_TYPES = {"hexahedron": 5, "tetrahedron": 4, "quadrangle": 3, "triangle": 2}
CELL_FACES = {
    "hexahedron": np.array(
        [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [0, 4, 7, 3], [1, 2, 6, 5]]
    ),
    "tetrahedron": np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
}
CELL_TYPE_OF_NODES = {8: "hexahedron", 4: "tetrahedron"}
FACE_TYPE_OF_NODES = {4: "quadrangle", 3: "triangle"}


@dataclass
class BuiltMesh:
    """A generated mesh in memory: arrays plus the sidecar metadata.

    ``nodes`` (n, 3) in mm; ``cells`` (m, 8) hexahedra or (m, 4) tetrahedra
    as 0-based node indices in gmsh order; ``facet_groups`` maps a surface
    group name to its boundary faces (k, 4) quads or (k, 3) triangles,
    oriented with outward normals.
    """

    name: str
    params: dict[str, Any]
    nodes: np.ndarray
    cells: np.ndarray
    facet_groups: dict[str, np.ndarray]
    supports: list[dict[str, Any]]
    default_contact_point: list[float]
    description: str
    fibres: dict[str, Any] | None = None

    @property
    def cell_type(self) -> str:
        """The cell type: hexahedron or tetrahedron."""
        return CELL_TYPE_OF_NODES[self.cells.shape[1]]

    def sidecar(self) -> dict[str, Any]:
        """The JSON sidecar contents (plain Python types only)."""
        return {
            "format": SIDECAR_FORMAT,
            "version": SIDECAR_VERSION,
            "name": self.name,
            "units": "mm",
            "cell_type": self.cell_type,
            "params": dict(self.params),
            "counts": {"nodes": int(len(self.nodes)), "cells": int(len(self.cells))},
            "supports": [dict(s) for s in self.supports],
            "fibres": None if self.fibres is None else dict(self.fibres),
            "default_contact_point": [float(c) for c in self.default_contact_point],
            "surface_groups": [g for g in SURFACE_GROUPS if len(self.facet_groups.get(g, ())) > 0],
            "description": self.description,
        }


def boundary_faces(cells: np.ndarray) -> np.ndarray:
    """Faces that belong to exactly one cell, outward oriented, in a fixed order.

    The order is that of (cell index, local face index), so it is
    reproducible. Returns (k, 4) for hexahedra, (k, 3) for tetrahedra.
    """
    cells = np.asarray(cells)
    local = CELL_FACES[CELL_TYPE_OF_NODES[cells.shape[1]]]
    faces = cells[:, local].reshape(-1, local.shape[1])
    keys = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def resolve_params(
    mesh_name: str,
    defaults: Mapping[str, Any],
    presets: Mapping[str, Mapping[str, Any]],
    refinement: str,
    overrides: Mapping[str, Any],
) -> dict[str, Any]:
    """Merge defaults, the refinement preset and user overrides; check names and types.

    Integer defaults require integer overrides (counts of divisions), float
    defaults require finite real numbers (lengths in mm). Value ranges are
    the generator's business.
    """
    if refinement not in REFINEMENTS:
        raise InputError(
            f"unknown refinement {refinement!r} for mesh {mesh_name!r}; "
            f"choose one of {', '.join(REFINEMENTS)}"
        )
    unknown = sorted(set(overrides) - set(defaults))
    if unknown:
        raise InputError(
            f"unknown parameter(s) {', '.join(unknown)} for mesh {mesh_name!r}; "
            f"valid: {', '.join(sorted(defaults))}"
        )
    params = {**defaults, **presets[refinement]}
    for key, value in overrides.items():
        if isinstance(defaults[key], int):
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise InputError(f"parameter {key} of mesh {mesh_name!r} must be an integer")
            params[key] = int(value)
        else:
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise InputError(f"parameter {key} of mesh {mesh_name!r} must be a number")
            if not math.isfinite(float(value)):
                raise InputError(f"parameter {key} of mesh {mesh_name!r} must be finite")
            params[key] = float(value)
    return params


def require(condition: bool, message: str) -> None:
    """Raise :class:`InputError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise InputError(message)


def sidecar_path(msh_path: str | Path) -> Path:
    """The JSON sidecar that belongs to a .msh file (same stem, .json)."""
    return Path(msh_path).with_suffix(".json")


@contextlib.contextmanager
def gmsh_home_guard() -> Iterator[None]:
    """Point $HOME elsewhere while gmsh starts: its FLTK layer writes $HOME/.fltk/ on start.

    ``gmsh.initialize()`` (also the one inside
    ``dolfinx.io.gmsh.read_from_msh``) creates ``$HOME/.fltk/fltk.org/fltk.prefs``
    even without a GUI. Wrap such calls in this guard to send that file to
    ``$XDG_CACHE_HOME/hapticrom-gmsh-home`` (or the temporary directory)
    instead. It changes the process environment, so it is not thread-safe.
    """
    base = os.environ.get("XDG_CACHE_HOME") or tempfile.gettempdir()
    scratch_home = Path(base) / "hapticrom-gmsh-home"
    scratch_home.mkdir(parents=True, exist_ok=True)
    previous = os.environ.get("HOME")
    os.environ["HOME"] = str(scratch_home)
    try:
        yield
    finally:
        if previous is None:
            del os.environ["HOME"]
        else:
            os.environ["HOME"] = previous


@contextlib.contextmanager
def gmsh_model(name: str, options: Mapping[str, float]) -> Iterator[None]:
    """A scratch gmsh model with ``options`` set, leaving any caller's gmsh state as it was.

    Starts gmsh (no config files, $HOME guarded) only if it is not running
    and then finalises it on exit; otherwise removes the scratch model and
    restores the caller's current model and the options changed here (gmsh
    options are global).
    """
    import gmsh

    started_here = not gmsh.isInitialized()
    if started_here:
        with gmsh_home_guard():
            gmsh.initialize(readConfigFiles=False)
    previous_model = gmsh.model.getCurrent() if gmsh.model.list() else None
    saved = {key: gmsh.option.getNumber(key) for key in options}
    try:
        for key, value in options.items():
            gmsh.option.setNumber(key, value)
        gmsh.model.add(name)
        yield
    finally:
        if name in gmsh.model.list():
            gmsh.model.setCurrent(name)
            gmsh.model.remove()
        for key, value in saved.items():
            gmsh.option.setNumber(key, value)
        if previous_model is not None:
            gmsh.model.setCurrent(previous_model)
        if started_here:
            gmsh.finalize()


def write_msh(
    path: str | Path,
    nodes: np.ndarray,
    cells: np.ndarray,
    facet_groups: Mapping[str, np.ndarray],
    sidecar: Mapping[str, Any],
    binary: bool = True,
) -> Path:
    """Write ``path`` (gmsh MSH 4.1) and its JSON sidecar; return the .msh path.

    ``nodes`` (n, 3) in mm, ``cells`` (m, 8|4) and ``facet_groups`` as in
    :class:`BuiltMesh`, 0-based. Node i gets gmsh tag i+1, cell j tag j+1,
    faces follow in the order clamped, loadable, free. All nodes are
    classified on the volume entity. An already running gmsh session (and its
    current model and options) is left as it was; otherwise gmsh is started
    and finalised here. ``binary=False`` writes ASCII, whose 16 significant
    digits can lose the last bit of a coordinate.
    """
    import gmsh

    path = Path(path)
    require(path.suffix == ".msh", f"mesh file name must end in .msh, got {path.name!r}")
    nodes = np.ascontiguousarray(nodes, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    require(nodes.ndim == 2 and nodes.shape[1] == 3, "nodes must be an (n, 3) array")
    require(cells.ndim == 2 and cells.shape[1] in CELL_TYPE_OF_NODES, "cells must be (m, 8|4)")
    unknown = sorted(set(facet_groups) - set(SURFACE_GROUPS))
    require(not unknown, f"unknown surface group(s) {unknown}; valid: {list(SURFACE_GROUPS)}")
    for target in (path, sidecar_path(path)):
        require(not target.is_dir(), f"cannot write mesh file {target}: it is a directory")
    options = {
        "General.Terminal": 0,
        "Mesh.MshFileVersion": 4.1,
        "Mesh.Binary": int(binary),
        "Mesh.SaveAll": 0,
    }
    # Write next to the target, then rename: a crash never leaves a half mesh, and a
    # failure (e.g. the sidecar's name taken by a directory) removes the partial files.
    # ... named by process: two processes writing the same mesh do not share partial files
    partial = path.with_name(f".{path.stem}.partial-{os.getpid()}.msh")
    partial_sidecar = partial.with_suffix(".json")
    try:
        with gmsh_model(f"hapticrom-write-{path.stem}", options):
            _add_volume(nodes, cells)
            _add_surface_groups(facet_groups, first_element=len(cells) + 1)
            path.parent.mkdir(parents=True, exist_ok=True)
            gmsh.write(str(partial))
        partial_sidecar.write_text(json.dumps(dict(sidecar), indent=2) + "\n")
        os.replace(partial_sidecar, sidecar_path(path))
        os.replace(partial, path)
    except BaseException:
        for leftover in (partial, partial_sidecar):
            with contextlib.suppress(OSError):  # a directory of that name is left alone
                leftover.unlink(missing_ok=True)
        raise
    return path


def _add_volume(nodes: np.ndarray, cells: np.ndarray) -> None:
    """Into the current gmsh model: the nodes (tags 1..n), the cells (tags 1..m) and the
    physical group "tissue", on one discrete volume entity."""
    import gmsh

    volume = 1
    gmsh.model.addDiscreteEntity(3, volume)
    gmsh.model.mesh.addNodes(
        3, volume, np.arange(1, len(nodes) + 1, dtype=np.uint64), nodes.ravel()
    )
    gmsh.model.mesh.addElementsByType(
        volume,
        GMSH_TYPES[CELL_TYPE_OF_NODES[cells.shape[1]]],
        np.arange(1, len(cells) + 1, dtype=np.uint64),
        (cells + 1).astype(np.uint64).ravel(),
    )
    gmsh.model.addPhysicalGroup(3, [volume], tag=GROUP_TAGS["tissue"], name="tissue")


def _add_surface_groups(facet_groups: Mapping[str, np.ndarray], first_element: int) -> None:
    """Into the current gmsh model: each non-empty surface group as a discrete surface
    entity and physical group, its faces numbered from ``first_element`` on."""
    import gmsh

    next_element = first_element
    for surface_tag, group in enumerate(SURFACE_GROUPS, start=1):
        faces = np.asarray(facet_groups.get(group, np.empty((0, 0))), dtype=np.int64)
        if faces.size == 0:
            continue
        gmsh.model.addDiscreteEntity(2, surface_tag)
        gmsh.model.mesh.addElementsByType(
            surface_tag,
            GMSH_TYPES[FACE_TYPE_OF_NODES[faces.shape[1]]],
            np.arange(next_element, next_element + len(faces), dtype=np.uint64),
            (faces + 1).astype(np.uint64).ravel(),
        )
        next_element += len(faces)
        gmsh.model.addPhysicalGroup(2, [surface_tag], tag=GROUP_TAGS[group], name=group)


def read_sidecar(msh_path: str | Path) -> dict[str, Any]:
    """Read the JSON sidecar of a .msh file; InputError if missing or not ours."""
    json_path = sidecar_path(msh_path)
    if not json_path.is_file():
        raise InputError(f"mesh sidecar {json_path} not found (generate the mesh first)")
    return read_versioned_json(json_path, SIDECAR_FORMAT, SIDECAR_VERSION, "sidecar")


# --- reading a surface group back -----------------------------------------------------------

GMSH_TYPE_NAMES = {tag: name for name, tag in GMSH_TYPES.items()}
NODES_OF_TYPE = {"hexahedron": 8, "tetrahedron": 4, "quadrangle": 4, "triangle": 3}


@dataclass(frozen=True, eq=False)
class Surface:
    """One surface group of a mesh file, as plain arrays (mm).

    ``nodes`` (k, 3): the distinct nodes of the group's faces, sorted by gmsh
    node tag; ``node_tags`` (k,) their 1-based gmsh tags; ``faces`` (f, 3|4)
    indices into ``nodes``, oriented outwards; ``normals`` (k, 3) outward unit
    vertex normals (area-weighted mean of the adjacent faces' normals);
    ``group`` the physical group's name.
    """

    nodes: np.ndarray
    node_tags: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    group: str


def read_surface(msh_path: str | Path, group: str = "loadable") -> Surface:
    """Read surface group ``group`` of a hapticrom .msh file as a :class:`Surface` (mm).

    gmsh reads the file on the calling process only (no MPI); the rest is
    numpy. The faces are checked to point out of the tissue cell they bound,
    so the normals are outward. InputError if the file, the group or the
    tissue is missing, or the group is not a set of outward boundary faces.
    """
    path = Path(msh_path)
    require(path.is_file(), f"mesh file {path} not found (generate it with `hapticrom mesh`)")
    all_tags, coords, face_tags, cell_tags = read_msh_group(path, group)
    node_tags = np.unique(face_tags)
    # gmsh tags are arbitrary positive integers: map them through a sorted index.
    order = np.argsort(all_tags)
    rows = order[np.searchsorted(all_tags, node_tags, sorter=order)]
    require(bool(np.all(all_tags[rows] == node_tags)), f"{path}: a face refers to a missing node")
    nodes = coords[rows]
    faces = np.searchsorted(node_tags, face_tags)
    _check_outward(path, group, coords, all_tags, order, face_tags, cell_tags)
    return Surface(
        nodes=nodes,
        node_tags=node_tags.astype(np.int64),
        faces=faces.astype(np.int64),
        normals=_outward_normals(nodes, faces),
        group=group,
    )


def _outward_normals(nodes: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals of a surface group; InputError if one is not defined."""
    normals = vertex_normals(nodes, faces)
    require(
        bool(np.all(np.any(normals != 0.0, axis=1))), "a surface node has no well-defined normal"
    )
    return normals


def read_msh_group(path: Path, group: str):
    """Node tags (n,), coordinates (n, 3), the group's faces and the tissue cells as node tags."""
    import gmsh

    with gmsh_model(f"hapticrom-read-{path.stem}", {"General.Terminal": 0}):
        try:
            gmsh.merge(str(path))
        except Exception as error:  # gmsh raises a bare Exception with its log line
            raise InputError(f"cannot read mesh file {path}: {error}") from None
        tags, coords, _ = gmsh.model.mesh.getNodes(returnParametricCoord=False)
        face_tags = _group_elements(path, group, 2)
        cell_tags = _group_elements(path, "tissue", 3)
    return np.asarray(tags, dtype=np.int64), np.reshape(coords, (-1, 3)), face_tags, cell_tags


def _group_elements(path: Path, name: str, dim: int) -> np.ndarray:
    """The elements of physical group ``name`` (of dimension ``dim``) as node tags (e, v)."""
    import gmsh

    groups = {gmsh.model.getPhysicalName(d, t): (d, t) for d, t in gmsh.model.getPhysicalGroups()}
    require(
        name in groups,
        f"mesh {path} has no physical group {name!r}; it has {', '.join(sorted(groups))}",
    )
    group_dim, tag = groups[name]
    require(group_dim == dim, f"physical group {name!r} of {path} is not {dim}-dimensional")
    blocks = []
    for entity in gmsh.model.getEntitiesForPhysicalGroup(group_dim, tag):
        types, _, node_tags = gmsh.model.mesh.getElements(group_dim, entity)
        for gmsh_type, tags in zip(types, node_tags, strict=True):
            kind = GMSH_TYPE_NAMES.get(int(gmsh_type))
            require(kind is not None, f"{path}: unsupported gmsh element type {gmsh_type}")
            blocks.append(np.asarray(tags, dtype=np.int64).reshape(-1, NODES_OF_TYPE[kind]))
    widths = {block.shape[1] for block in blocks if len(block)}
    require(len(widths) == 1, f"group {name!r} of {path} is empty or mixes element types")
    return np.vstack([block for block in blocks if len(block)])


def _check_outward(path, group, coords, all_tags, order, face_tags, cell_tags) -> None:
    """InputError unless every face is a face of one tissue cell and points away from it.

    Tested rather than trusted: a flipped face would turn the tool's push
    direction around without any other sign.
    """
    local = CELL_FACES[CELL_TYPE_OF_NODES[cell_tags.shape[1]]]
    require(local.shape[1] == face_tags.shape[1], f"group {group!r} of {path}: wrong face type")
    # Only cells with enough nodes on the group can own one of its faces.
    near = np.count_nonzero(np.isin(cell_tags, face_tags), axis=1) >= face_tags.shape[1]
    cells = cell_tags[near]
    cell_faces = np.sort(cells[:, local].reshape(-1, local.shape[1]), axis=1)
    keys = np.sort(face_tags, axis=1)
    _, inverse = np.unique(np.vstack([keys, cell_faces]), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    owner = np.full(inverse.max() + 1, -1, dtype=np.int64)
    owner[inverse[len(keys) :]] = np.arange(len(cell_faces)) // len(local)
    face_owner = owner[inverse[: len(keys)]]
    require(bool(np.all(face_owner >= 0)), f"group {group!r} of {path} has faces of no cell")

    def xyz(tags: np.ndarray) -> np.ndarray:
        return coords[order[np.searchsorted(all_tags, tags, sorter=order)]]

    face_xyz = xyz(face_tags)
    cell_centre = xyz(cells[face_owner]).mean(axis=1)
    # Outward: the face's normal points from its cell's centroid to the face's.
    area = corner_area_vectors(face_xyz)
    outward = np.einsum("ij,ij->i", area, face_xyz.mean(axis=1) - cell_centre)
    require(
        bool(np.all(outward > 0.0)),
        f"group {group!r} of {path}: {np.count_nonzero(outward <= 0.0)} face(s) point inwards",
    )
