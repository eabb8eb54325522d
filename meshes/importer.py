"""``hapticrom mesh import``: a user's organ mesh as a hapticrom mesh (.msh + .json, mm).

:func:`import_mesh` reads INPUT with meshio, checks it, selects the surface groups with a
rules file (:mod:`hapticrom.meshes.import_rules`) and writes the result with the one
writer of generated meshes (:func:`hapticrom.meshes.msh.write_msh`), so campaigns,
``hapticrom solve`` and :func:`hapticrom.offline.fe.organ.load_organ` read it unchanged.

Read: VTK legacy ``.vtk``, ``.vtu``, gmsh ``.msh`` (MSH 2 and 4), MEDIT ``.mesh``, Abaqus
``.inp`` (meshio; the format from the extension). Cells: tetrahedra (``tetra``,
``tetra10``) or hexahedra (``hexahedron``, ``hexahedron20``, ``hexahedron27``), one kind
per mesh. Lower-dimensional cells (boundary triangles, lines, points) are ignored: the
groups come from the rules. Point and cell data (material ids, ...) are ignored.

What is done to the mesh, in order, and said in the summary:

* coordinates times ``scale`` (a mesh in cm: ``scale = 10``); the nodes the cells use must
  then lie within the artifact's :data:`~hapticrom.shared.artifact_rules.MAX_LENGTH` of the
  origin in every axis and span at least :data:`MIN_EXTENT`;
* quadratic cells keep their corner nodes (meshio puts them first in every format): the
  result is the linear mesh of the same corners, and hapticrom chooses its own element on
  it (P2P0 on tetrahedra, Q1P0 on hexahedra); curved quadratic edges become straight;
* a mesh whose cells are *all* inverted (left-handed node order, as some tools write) is
  reoriented as a whole; a mix of orientations is refused;
* nodes no cell uses are dropped, the rest renumbered in file order.

Refused, each with one :class:`InputError` naming the culprit (a cell as its 0-based
position among the file's volume cells, a node as its 0-based position in the file's node
list, a rule by its table) and nothing written: an unknown extension or unreadable file,
an empty mesh, non-finite coordinates, coordinates (after ``scale``) too far or too close
together, no volume cells (a surface mesh), unsupported or mixed cell types, repeated or
out-of-range node indices, duplicate cells, degenerate cells (a corner Jacobian below
:data:`DEGENERATE_SHAPE` x the cube of the cell's longest edge), mixed orientations or tangled
hexahedra, coincident nodes (unmerged duplicates: a slit inside the body), a face shared
by more than two cells, several disconnected bodies, a boundary edge not shared by exactly
two boundary faces, and the rules' own mistakes
(:func:`~hapticrom.meshes.import_rules.classify_faces`).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hapticrom.meshes.fibres import fibre_directions
from hapticrom.meshes.import_rules import BoundaryFaces, RulesFile, classify_faces, read_rules
from hapticrom.meshes.msh import CELL_FACES, BuiltMesh, require, sidecar_path, write_msh
from hapticrom.shared.artifact_rules import MAX_LENGTH
from hapticrom.shared.errors import InputError
from hapticrom.shared.geometry import corner_area_vectors

# File extension -> (meshio format, the name said in messages).
FORMATS = {
    ".vtk": ("vtk", "VTK legacy"),
    ".vtu": ("vtu", "VTU"),
    ".msh": ("gmsh", "gmsh MSH"),
    ".mesh": ("medit", "MEDIT"),
    ".inp": ("abaqus", "Abaqus"),
}
# meshio cell type -> hapticrom cell type (corner nodes first in meshio's order).
VOLUME_TYPES = {
    "tetra": "tetrahedron",
    "tetra10": "tetrahedron",
    "hexahedron": "hexahedron",
    "hexahedron20": "hexahedron",
    "hexahedron27": "hexahedron",
}
CORNERS = {"tetrahedron": 4, "hexahedron": 8}
# Each hexahedron corner and its three edge neighbours, right-handed for a positively
# oriented cell (gmsh/VTK order): the corner Jacobians are the triple products.
HEX_CORNER_EDGES = np.array(
    [[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]]
)
# The edges of a cell by its number of corners, each once (pairs of local nodes).
CELL_EDGES = {
    4: np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]),
    8: np.array(sorted({tuple(sorted((c, n))) for c in range(8) for n in HEX_CORNER_EDGES[c]})),
}
# Node orders that mirror a cell (turn an inverted cell into a positive one).
MIRROR = {"tetrahedron": [0, 2, 1, 3], "hexahedron": [0, 3, 2, 1, 4, 7, 6, 5]}
# A cell whose smallest corner Jacobian is below this fraction of the cube of its longest
# edge is degenerate: a scale-free shape measure (a cube: 1; a regular tetrahedron:
# 1/sqrt(2); a 1 x 1 x 1e-6 plate: 1e-6), so a graded mesh's small cells are judged as its
# large ones.
DEGENERATE_SHAPE = 1e-6
# The smallest span (mm, after --scale) of an imported mesh: smaller is a wrong --scale.
MIN_EXTENT = 1e-6
# Two nodes closer than this fraction of the mesh's diagonal coincide (far above rounding
# of coordinates within MAX_LENGTH, far below any real edge).
COINCIDENT_RELATIVE_DISTANCE = 1e-9
# A given default contact point may lie this far from the nearest loadable node: at least
# 1 mm, or the longest edge of the loadable faces.
CONTACT_SNAP_MIN = 1.0

NO_RULES = (
    "hapticrom mesh import needs --rules RULES.toml: an imported mesh carries no clamped or "
    "loadable surface, and an organ held nowhere is a free rigid body "
    "(start from examples/mesh-import-rules.toml)"
)


@dataclass(frozen=True)
class SourceMesh:
    """The volume cells of an input file, read and checked for readability (file units).

    ``points`` (n, 3) as in the file; ``cells`` (m, 4|8) the corner nodes of the volume
    cells in file order (indices into ``points``); ``cell_type`` meshio's type name;
    ``higher_order`` the nodes only quadratic cells use beyond their corners;
    ``ignored`` lower-dimensional cells by type; ``notes`` what meshio printed.
    """

    path: Path
    format_name: str
    points: np.ndarray
    cell_type: str
    cells: np.ndarray
    higher_order: np.ndarray
    ignored: dict[str, int]
    notes: tuple[str, ...] = ()

    @property
    def kind(self) -> str:
        """hapticrom's cell type: tetrahedron or hexahedron."""
        return VOLUME_TYPES[self.cell_type]


@dataclass
class ImportReport:
    """What an import did, for the summary (:meth:`lines`)."""

    source: SourceMesh
    out: Path | None
    scale: float
    nodes: int
    cells: int
    groups: dict[str, int]
    unused_nodes: int
    reoriented: bool
    contact_point: list[float]
    contact_snap: float | None
    components: str
    extent: list[float] = field(default_factory=list)

    def lines(self) -> list[str]:
        """The summary, one fact per line."""
        s = self.source
        where = f" -> {self.out} + {self.out.with_suffix('.json').name}" if self.out else ""
        out = [
            f"imported {s.path} ({s.format_name}, {len(s.cells):,} {s.cell_type}){where}",
            f"  cells  {self.cells:,} {s.kind}" + _quadratic_note(s),
            f"  nodes  {self.nodes:,}" + self._dropped_nodes(),
            f"  scale  {self.scale:g} (file units x {self.scale:g} = mm); extent "
            + " x ".join(f"{e:.4g}" for e in self.extent)
            + " mm",
            "  faces  "
            + ", ".join(f"{g} {n:,}" for g, n in self.groups.items())
            + f" (of {sum(self.groups.values()):,} boundary faces)",
            f"  supports clamped {self.components}; default contact point "
            f"({', '.join(f'{c:.4g}' for c in self.contact_point)}) mm" + self._snap(),
        ]
        if s.ignored:
            ignored = ", ".join(f"{n:,} {t}" for t, n in s.ignored.items())
            out.append(f"  ignored {ignored} cells (the groups come from the rules)")
        if self.reoriented:
            out.append("  reoriented: every cell was inverted (left-handed node order)")
        return out

    def _dropped_nodes(self) -> str:
        parts = []
        if len(self.source.higher_order):
            parts.append(f"{len(self.source.higher_order):,} higher-order")
        if self.unused_nodes:
            parts.append(f"{self.unused_nodes:,} unused")
        return f" (dropped {', '.join(parts)})" if parts else ""

    def _snap(self) -> str:
        if self.contact_snap is None:
            return " (loadable node nearest the loadable surface's centroid)"
        return f" (given point snapped {self.contact_snap:.3g} mm to a loadable node)"


def _quadratic_note(source: SourceMesh) -> str:
    if source.cell_type in ("tetra", "hexahedron"):
        return ""
    return (
        f" (quadratic {source.cell_type}: corner nodes kept, a linear mesh; hapticrom picks "
        "its element on it, P2P0 on tetrahedra, Q1P0 on hexahedra)"
    )


# --- reading ---------------------------------------------------------------------------------


def read_source(path: str | Path) -> SourceMesh:
    """Read a mesh file with meshio and keep its volume cells' corners; InputError if it is
    missing, of an unknown extension, unreadable, empty, non-finite or has no or unsupported
    or mixed volume cells."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise InputError(
            f"{path}: unknown mesh file extension {path.suffix!r}; hapticrom mesh import reads "
            + ", ".join(f"{ext} ({name})" for ext, (_, name) in FORMATS.items())
        )
    if path.is_dir():
        raise InputError(f"mesh file {path} is a directory; give the mesh file in it")
    if not path.is_file():
        missing = "is not a regular file" if path.exists() else "not found"
        raise InputError(f"mesh file {path} {missing}")
    if path.stat().st_size == 0:
        raise InputError(f"{path} is an empty mesh: the file is empty (0 bytes)")
    file_format, format_name = FORMATS[path.suffix.lower()]
    if file_format == "gmsh":
        format_name = _gmsh_version(path)
    mesh, notes = _meshio_read(path, file_format, format_name)
    points = _checked_points(mesh.points, path)
    cell_type, blocks, ignored = _volume_blocks(mesh.cells, path)
    cells = np.vstack([_index_array(block, path) for block in blocks])
    bad = np.flatnonzero(np.any((cells < 0) | (cells >= len(points)), axis=1))
    if len(bad):
        raise InputError(
            f"{path}: volume cell #{bad[0]} refers to a node that does not exist "
            f"(the file has {len(points):,} nodes)"
        )
    corners = cells[:, : CORNERS[VOLUME_TYPES[cell_type]]]
    higher_order = np.setdiff1d(np.unique(cells[:, corners.shape[1] :]), corners)
    return SourceMesh(path, format_name, points, cell_type, corners, higher_order, ignored, notes)


def _gmsh_version(path: Path) -> str:
    """``gmsh MSH 4.1`` (binary) from the file's header, or ``gmsh MSH`` if it has none."""
    with path.open("rb") as f:
        head = f.read(64).split()
    if len(head) >= 3 and head[0] == b"$MeshFormat":
        version = head[1].decode("ascii", "replace")
        return f"gmsh MSH {version}" + (" binary" if head[2] == b"1" else "")
    return "gmsh MSH"


def _meshio_read(path: Path, file_format: str, format_name: str):
    """meshio's mesh and the lines it printed (its warnings go to stderr through rich)."""
    try:
        import meshio
    except ImportError:
        from hapticrom.offline import OFFLINE_EXTRA_HINT

        raise ImportError(f"{OFFLINE_EXTRA_HINT} (missing: meshio)") from None
    printed = io.StringIO()
    try:
        with contextlib.redirect_stderr(printed), contextlib.redirect_stdout(printed):
            # The format's own reader: meshio.read() calls sys.exit on a ReadError.
            mesh = getattr(meshio, file_format).read(str(path))
    except Exception as exc:  # meshio raises anything from ReadError to IndexError
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"cannot read {path} as {format_name}: {message}") from None
    notes = tuple(line.strip() for line in printed.getvalue().splitlines() if line.strip())
    return mesh, notes


def _checked_points(points: Any, path: Path) -> np.ndarray:
    """The nodes as an (n, 3) float array; InputError if empty, not 3-D or not finite."""
    try:
        points = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{path}: node coordinates are not numbers") from None
    if points.size == 0:
        raise InputError(f"{path} is an empty mesh: it has no nodes")
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(
            f"{path}: nodes have {points.shape[-1]} coordinates; a volume mesh needs x, y, z"
        )
    bad = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if len(bad):
        raise InputError(
            f"{path}: node {bad[0]} (0-based) has a non-finite coordinate {points[bad[0]].tolist()}"
            f" ({len(bad):,} such node(s))"
        )
    return points


def _volume_blocks(blocks, path: Path) -> tuple[str, list[np.ndarray], dict[str, int]]:
    """The meshio type and the cell arrays of the volume cells; counts of the others."""
    volume: dict[str, list] = {}
    ignored: Counter[str] = Counter()
    for block in blocks:
        if len(block.data) == 0:
            continue
        if block.dim == 3:
            volume.setdefault(block.type, []).append(block.data)
        else:
            ignored[block.type] += len(block.data)
    counts = {t: sum(len(d) for d in data) for t, data in volume.items()}
    unsupported = [t for t in volume if t not in VOLUME_TYPES]
    accepted = "tetrahedra (tetra, tetra10) or hexahedra (hexahedron, hexahedron20, hexahedron27)"
    if unsupported:
        raise InputError(
            f"{path}: unsupported cell type(s) "
            + ", ".join(f"{t} ({counts[t]:,})" for t in unsupported)
            + f"; hapticrom imports {accepted}, one type per mesh"
        )
    if not volume:
        found = ", ".join(f"{t} {n:,}" for t, n in ignored.items())
        if not found:
            raise InputError(f"{path} is an empty mesh: it has no cells")
        raise InputError(
            f"{path} has no volume cells (only {found}): a surface mesh does not bound a "
            f"volume hapticrom can solve on; fill it with {accepted} first (e.g. gmsh, TetGen)"
        )
    if len(volume) > 1:
        raise InputError(
            f"{path}: mixed cell types "
            + " and ".join(f"{t} ({n:,})" for t, n in counts.items())
            + "; hapticrom imports one cell type per mesh"
        )
    ((cell_type, data),) = volume.items()
    return cell_type, data, dict(ignored)


def _index_array(block: Any, path: Path) -> np.ndarray:
    """A block's node indices as an int64 (m, k) array."""
    array = np.asarray(block)
    if array.ndim != 2 or not np.issubdtype(array.dtype, np.integer):
        raise InputError(f"{path}: a block of volume cells is not a table of node indices")
    return array.astype(np.int64)


# --- checking the cells ------------------------------------------------------------------------


def corner_jacobians(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(m, 1) 6 x signed volume of tetrahedra, or (m, 8) the corner Jacobians of hexahedra
    (triple products of the three edges at each corner); positive for the gmsh/VTK order."""
    x = nodes[cells]
    if cells.shape[1] == 4:
        e = x[:, 1:] - x[:, :1]
        return np.einsum("ij,ij->i", np.cross(e[:, 0], e[:, 1]), e[:, 2])[:, None]
    corner = x[:, :, None, :]
    edges = x[:, HEX_CORNER_EDGES] - corner  # (m, 8, 3, 3)
    return np.einsum("mcj,mcj->mc", np.cross(edges[:, :, 0], edges[:, :, 1]), edges[:, :, 2])


def orient_cells(nodes: np.ndarray, cells: np.ndarray, kind: str, path: Path):
    """The cells positively oriented, and whether all were mirrored; InputError for a
    cell that repeats a node, duplicate cells, degenerate, tangled or mixed-orientation cells."""
    ordered = np.sort(cells, axis=1)
    repeats = np.flatnonzero(np.any(ordered[:, 1:] == ordered[:, :-1], axis=1))
    if len(repeats):
        raise InputError(f"{path}: degenerate {_cell(nodes, cells, repeats[0])}: a node repeats")
    inverse, counts = unique_rows(ordered)
    repeated = np.flatnonzero(counts[inverse] > 1)
    if len(repeated):
        twice = np.flatnonzero(inverse == inverse[repeated[0]])
        raise InputError(f"{path}: volume cells #{twice[0]} and #{twice[1]} are the same cell")
    jac = corner_jacobians(nodes, cells)
    shape = cell_shapes(nodes, cells, jac)
    small = np.flatnonzero(~(shape > DEGENERATE_SHAPE))  # NaN (an underflow) included
    if len(small):
        raise InputError(
            f"{path}: degenerate {_cell(nodes, cells, small[0])}: volume ~ 0 (smallest corner "
            f"Jacobian {shape[small[0]]:.2g} x its longest edge cubed, below "
            f"{DEGENERATE_SHAPE:g}; {len(small):,} such cell(s))"
        )
    positive, negative = np.all(jac > 0, axis=1), np.all(jac < 0, axis=1)
    tangled = np.flatnonzero(~positive & ~negative)
    if len(tangled):
        raise InputError(
            f"{path}: tangled {_cell(nodes, cells, tangled[0])}: its corner Jacobians have both "
            f"signs ({len(tangled):,} such cell(s))"
        )
    if negative.all():
        return cells[:, MIRROR[kind]], True
    if negative.any():
        inverted, upright = np.flatnonzero(negative), np.flatnonzero(positive)
        # Name a cell of the minority: that is where the file is most likely wrong.
        if len(inverted) <= len(upright):
            culprit = f"inverted {_cell(nodes, cells, inverted[0])}"
        else:
            culprit = f"mixed orientation: {_cell(nodes, cells, upright[0])} is positive"
        raise InputError(
            f"{path}: {culprit}: {len(inverted):,} of {len(cells):,} cells are inverted "
            f"(negative volume) and the others not; a mesh's cells share one orientation"
        )
    return cells, False


def cell_shapes(nodes: np.ndarray, cells: np.ndarray, jacobians: np.ndarray) -> np.ndarray:
    """(m,) each cell's smallest |corner Jacobian| over the cube of its longest edge: scale-free,
    0 for a flat cell, NaN where the edge's cube underflows (a cell far below the mesh's size)."""
    x = nodes[cells]
    pairs = CELL_EDGES[cells.shape[1]]
    edges = x[:, pairs[:, 1]] - x[:, pairs[:, 0]]
    longest = np.sqrt(np.einsum("mek,mek->me", edges, edges).max(axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.min(np.abs(jacobians), axis=1) / longest**3


def _cell(nodes: np.ndarray, cells: np.ndarray, i: int) -> str:
    """``volume cell #i (0-based, file order) at (x, y, z) mm``."""
    centre = nodes[cells[i]].mean(axis=0)
    return f"volume cell #{i} (0-based, file order) at ({', '.join(f'{c:.4g}' for c in centre)})"


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inverse (k,), counts (u,)) of the distinct rows of an integer array (k, w): row i is
    distinct row inverse[i], which occurs counts[inverse[i]] times. A lexicographic sort of
    the columns (np.unique(axis=0) sorts rows as opaque bytes, several times slower)."""
    order = np.lexsort(rows.T[::-1])
    ranked = rows[order]
    starts = np.ones(len(rows), dtype=bool)
    starts[1:] = np.any(ranked[1:] != ranked[:-1], axis=1)
    inverse = np.empty(len(rows), dtype=np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return inverse, np.bincount(inverse)


def compact_nodes(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cells renumbered 0..k-1, the file index of each kept node), nodes in file order."""
    used = np.unique(cells)
    return np.searchsorted(used, cells).astype(np.int64), used


def check_topology(nodes: np.ndarray, cells: np.ndarray, source_ids: np.ndarray, path: Path):
    """InputError for a face shared by more than two cells, several bodies, or a boundary edge
    not shared by exactly two boundary faces; otherwise the boundary faces (outward)."""
    local = CELL_FACES[{4: "tetrahedron", 8: "hexahedron"}[cells.shape[1]]]
    faces = cells[:, local].reshape(-1, local.shape[1])
    inverse, counts = unique_rows(np.sort(faces, axis=1))
    crowded = np.flatnonzero(counts[inverse] > 2)
    if len(crowded):
        owners = np.flatnonzero(inverse == inverse[crowded[0]]) // len(local)
        raise InputError(
            f"{path}: non-manifold mesh: the face of file nodes "
            f"{sorted(source_ids[faces[crowded[0]]].tolist())} is shared by {len(owners)} cells "
            f"(#{', #'.join(str(c) for c in owners)}); a face bounds at most two cells"
        )
    _check_one_body(nodes, cells, inverse, counts, len(local), path)
    # As msh.boundary_faces (faces of one cell, in cell then local face order), from the
    # counts at hand.
    boundary = faces[counts[inverse] == 1]
    _check_boundary_edges(nodes, boundary, source_ids, path)
    return boundary


def _check_one_body(nodes, cells, inverse, counts, faces_per_cell: int, path: Path) -> None:
    """InputError if the cells fall apart into bodies that share no face."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    order = np.argsort(inverse, kind="stable")
    shared = np.flatnonzero(np.diff(inverse[order]) == 0)  # interior faces: consecutive pairs
    a, b = order[shared] // faces_per_cell, order[shared + 1] // faces_per_cell
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(cells), len(cells)))
    n_bodies, body = connected_components(graph, directed=False)
    if n_bodies == 1:
        return
    sizes = np.bincount(body)
    other = int(np.flatnonzero(body != body[0])[0])
    # Coincident nodes (unmerged duplicates) were refused before: these bodies are apart.
    raise InputError(
        f"{path}: {n_bodies} disconnected bodies (cells per body: "
        f"{', '.join(f'{s:,}' for s in sizes[:8])}{', ...' if n_bodies > 8 else ''}): "
        f"{_cell(nodes, cells, other)} shares no face with cell #0's body; import one body "
        "per file"
    )


def _check_boundary_edges(nodes, boundary, source_ids, path: Path) -> None:
    """InputError unless every boundary edge lies on exactly two boundary faces."""
    v = boundary.shape[1]
    edges = np.stack([boundary, np.roll(boundary, -1, axis=1)], axis=2).reshape(-1, 2)
    edges = np.sort(edges, axis=1)
    inverse, counts = unique_rows(edges)
    bad = np.flatnonzero(counts[inverse] != 2)
    if len(bad):
        edge = edges[bad[0]]
        middle = nodes[edge].mean(axis=0)
        ids = sorted(source_ids[edge].tolist())
        raise InputError(
            f"{path}: non-manifold boundary: the edge of file nodes {ids} "
            f"at ({', '.join(f'{c:.4g}' for c in middle)}) lies on {counts[inverse[bad[0]]]} "
            f"boundary faces, not 2 ({len(np.unique(inverse[bad])):,} such edge(s); {v}-node "
            "faces)"
        )


# --- building and writing -----------------------------------------------------------------------


def build_imported(
    source: SourceMesh,
    rules: RulesFile,
    rules_path: str | Path,
    scale: float = 1.0,
    name: str = "imported",
) -> tuple[BuiltMesh, ImportReport]:
    """The checked, grouped mesh in memory and the report; nothing written.

    ``rules_path`` names the rules in messages and the sidecar; ``name`` is the mesh's
    name unless the rules give one.
    """
    rules_path = Path(rules_path)
    nodes, cells, source_ids, reoriented = prepare_cells(source, scale)
    faces = check_topology(nodes, cells, source_ids, source.path)
    boundary = boundary_geometry(nodes, faces, source_ids, len(source.points))
    masks = classify_faces(rules, boundary, str(rules_path))
    groups = {g: faces[m] for g, m in masks.items()}
    contact, snap = _checked_contact(nodes, groups["loadable"], rules, rules_path)
    mesh = BuiltMesh(
        name=rules.name or name,
        params=_provenance(source, rules_path, scale, reoriented),
        nodes=nodes,
        cells=cells,
        facet_groups=groups,
        supports=[{"group": "clamped", "components": rules.clamped.components}],
        default_contact_point=[float(c) for c in contact],
        description=rules.description or _description(source, rules, rules_path, scale),
        fibres=_fibres(rules, nodes, cells, rules_path),
    )
    report = ImportReport(
        source=source,
        out=None,
        scale=scale,
        nodes=len(nodes),
        cells=len(cells),
        groups={g: len(f) for g, f in groups.items()},
        unused_nodes=len(source.points) - len(source_ids) - len(source.higher_order),
        reoriented=reoriented,
        contact_point=mesh.default_contact_point,
        contact_snap=snap,
        components=rules.clamped.components,
        extent=(nodes.max(axis=0) - nodes.min(axis=0)).tolist(),
    )
    return mesh, report


def prepare_cells(source: SourceMesh, scale: float):
    """(nodes in mm, positively oriented cells on them, each node's index in the file,
    whether every cell was mirrored): scaled, checked, unused nodes dropped."""
    require(math.isfinite(scale) and scale > 0, f"--scale must be a positive number, got {scale}")
    points = scaled_points(source, scale)
    cells, reoriented = orient_cells(points, source.cells, source.kind, source.path)
    cells, source_ids = compact_nodes(cells)
    nodes = points[source_ids]
    check_coincident_nodes(nodes, source_ids, source.path)
    return nodes, cells, source_ids, reoriented


def scaled_points(source: SourceMesh, scale: float) -> np.ndarray:
    """The file's nodes times ``scale`` (mm); InputError if a node a cell uses lies beyond
    the artifact's MAX_LENGTH in some axis (a trained model would be refused), or if the
    cells span less than MIN_EXTENT (a wrong --scale)."""
    with np.errstate(over="ignore"):
        points = source.points * scale
    used = np.unique(source.cells)
    far = used[~(np.max(np.abs(points[used]), axis=1) <= MAX_LENGTH)]
    if len(far):
        raise InputError(
            f"{source.path}: node {far[0]} (0-based) lies at {_xyz(points[far[0]])} mm (file "
            f"coordinates x --scale {scale:g}), beyond the {MAX_LENGTH:g} mm from the origin a "
            f"hapticrom model allows in each axis ({len(far):,} such node(s)): move the mesh "
            "near the origin, or check --scale"
        )
    extent = float(np.max(np.ptp(points[used], axis=0)))
    if extent < MIN_EXTENT:
        raise InputError(
            f"{source.path}: the mesh spans {extent:.3g} mm (file coordinates x --scale "
            f"{scale:g}), less than {MIN_EXTENT:g} mm: check --scale (file units x scale = mm)"
        )
    return points


def check_coincident_nodes(nodes: np.ndarray, source_ids: np.ndarray, path: Path) -> None:
    """InputError if two nodes (of those the cells use) coincide: closer than
    COINCIDENT_RELATIVE_DISTANCE x the mesh's diagonal. Two nodes of one cell cannot (the
    cell would be degenerate), so cells that should share a node each use their own copy:
    the body is slit there (its lips would become boundary) or falls apart."""
    from scipy.spatial import cKDTree

    tolerance = COINCIDENT_RELATIVE_DISTANCE * float(np.linalg.norm(np.ptp(nodes, axis=0)))
    pairs = cKDTree(nodes).query_pairs(tolerance, output_type="ndarray")
    if len(pairs) == 0:
        return
    pairs = np.sort(pairs, axis=1)
    first = pairs[np.lexsort(pairs.T[::-1])[0]]  # the pair of lowest file positions
    a, b = source_ids[first]
    raise InputError(
        f"{path}: nodes {a} and {b} (0-based) coincide at {_xyz(nodes[first[0]])} mm (within "
        f"{tolerance:.2g} mm; {len(np.unique(pairs)):,} such node(s)): the cells meeting there "
        "each use their own copy, which slits the body (or splits it) there; merge duplicate "
        "nodes first (e.g. ParaView's Clean filter); a mesh with a crack or cut cannot be "
        "imported"
    )


def _xyz(point: np.ndarray) -> str:
    """``(x, y, z)`` with 4 significant digits."""
    return f"({', '.join(f'{c:.4g}' for c in point)})"


def boundary_geometry(
    nodes: np.ndarray, faces: np.ndarray, source_ids: np.ndarray, source_node_count: int
) -> BoundaryFaces:
    """Centroids, outward unit normals and file node ids of the boundary faces."""
    face_xyz = nodes[faces]
    area = corner_area_vectors(face_xyz)
    return BoundaryFaces(
        centroids=face_xyz.mean(axis=1),
        normals=area / np.linalg.norm(area, axis=1)[:, None],
        source_ids=source_ids[faces],
        source_node_count=source_node_count,
    )


def _checked_contact(nodes, loadable, rules: RulesFile, rules_path: Path):
    """The default contact point and its snap distance; InputError if the given point is
    not on the loadable surface."""
    contact, snap = contact_point(nodes, loadable, rules.default_contact_point)
    if snap is not None and snap > max(CONTACT_SNAP_MIN, _longest_edge(nodes, loadable)):
        raise InputError(
            f"{rules_path}: default_contact_point {list(rules.default_contact_point)} is "
            f"{snap:.4g} mm from the nearest loadable node: not on the loadable surface (mm, "
            "after --scale)"
        )
    return contact, snap


def contact_point(
    nodes: np.ndarray, loadable: np.ndarray, asked
) -> tuple[np.ndarray, float | None]:
    """The default contact point: a loadable node, and how far ``asked`` was from it.

    Without ``asked``: the loadable face whose centroid is nearest the area-weighted
    centroid of the loadable surface, and of its nodes the one nearest that centroid
    (the distance is then None).
    """
    candidates = np.unique(loadable)
    if asked is not None:
        offset = nodes[candidates] - np.asarray(asked)
        distance = np.sqrt(np.einsum("ij,ij->i", offset, offset))
        best = int(np.argmin(distance))
        return nodes[candidates[best]], float(distance[best])
    x = nodes[loadable]
    area = np.linalg.norm(corner_area_vectors(x), axis=1)
    centroids = x.mean(axis=1)
    centre = (area[:, None] * centroids).sum(axis=0) / area.sum()
    face = loadable[np.argmin(np.linalg.norm(centroids - centre, axis=1))]
    return nodes[face[np.argmin(np.linalg.norm(nodes[face] - centre, axis=1))]], None


def _longest_edge(nodes: np.ndarray, faces: np.ndarray) -> float:
    x = nodes[faces]
    return float(np.max(np.linalg.norm(x - np.roll(x, -1, axis=1), axis=2)))


def _fibres(rules: RulesFile, nodes, cells, rules_path: Path) -> dict[str, Any] | None:
    """The sidecar's fibre spec, checked to be defined at every cell centre."""
    if rules.fibres is None:
        return None
    spec = rules.fibres.spec()
    try:
        fibre_directions(spec, nodes[cells].mean(axis=1))
    except InputError as exc:
        raise InputError(f"{rules_path}: [fibres] {exc}") from None
    return spec


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _provenance(source: SourceMesh, rules_path: Path, scale: float, reoriented: bool) -> dict:
    """The sidecar's ``params``: where the mesh came from (no built-in preset matches it)."""
    return {
        "imported_from": source.path.name,
        "source_format": source.format_name,
        "source_cell_type": source.cell_type,
        "source_sha256": _sha256(source.path),
        "scale": float(scale),
        "rules": rules_path.name,
        "rules_sha256": _sha256(rules_path),
        "reoriented": reoriented,
    }


def _description(source: SourceMesh, rules: RulesFile, rules_path: Path, scale: float) -> str:
    def selectors(group: str) -> str:
        table = getattr(rules, group)
        return ", ".join(label for label, _ in table.selectors(group))

    return (
        f"Imported from {source.path.name} ({source.format_name}, {len(source.cells):,} "
        f"{source.cell_type} cells, coordinates x {scale:g} = mm) with the rules of "
        f"{rules_path.name}: clamped ({rules.clamped.components}) by {selectors('clamped')}; "
        f"loadable by {selectors('loadable')}; the rest of the boundary free."
    )


def import_mesh(
    input_path: str | Path,
    out: str | Path,
    rules_path: str | Path | None,
    scale: float = 1.0,
) -> ImportReport:
    """Import ``input_path`` into ``out`` (.msh) and its .json sidecar; return the report.

    Everything is read and checked before anything is written (the writer then writes
    next to the target and renames), so a refusal leaves no file behind. The mesh's name
    is the rules' ``name`` or the output's stem.
    """
    out = Path(out)
    require(out.suffix == ".msh", f"mesh output must be a .msh file, got {str(out)!r}")
    require(not out.is_dir(), f"mesh output {out} is a directory; give a file name in it")
    require(
        not sidecar_path(out).is_dir(),
        f"mesh output {out}: its sidecar {sidecar_path(out)} is an existing directory; remove it "
        "or choose another name",
    )
    if rules_path is None:
        raise InputError(NO_RULES)
    require(
        isinstance(scale, int | float) and math.isfinite(scale) and scale > 0,
        f"--scale must be a positive number, got {scale}",
    )
    rules = read_rules(rules_path)
    source = read_source(input_path)
    mesh, report = build_imported(source, rules, rules_path, float(scale), name=out.stem)
    write_msh(out, mesh.nodes, mesh.cells, mesh.facet_groups, mesh.sidecar())
    report.out = out
    return report
