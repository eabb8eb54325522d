"""Surgical cuts meshed explicitly: duplicate the nodes of a set of interior faces (mm).

The full-order reference of a cut (issue "surgical cutting"): the faces of the
cut surface become two boundary faces, one per lip, and the nodes inside the
cut get one copy per side. Nodes on the cut's front (its edges inside the
tissue, where the material still holds together) are not duplicated, which is
what stops the cut there. Nodes on the outer surface are duplicated, so the
cut opens to the surface. The new lip faces join the ``free`` surface group.

:func:`cut_faces` selects interior faces; :func:`limbal_arc` is the selection
of a limbal relaxing incision (thesis §4.5.1) on the cornea: the radial-facing
faces nearest a given distance from the optical axis, over an angular range,
from the anterior surface down to a fraction of the thickness.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hapticrom.meshes.msh import CELL_FACES, CELL_TYPE_OF_NODES, BuiltMesh, boundary_faces
from hapticrom.shared.cut_topology import CutTopology  # the runtime cuts the same way
from hapticrom.shared.errors import InputError


def _topology(cells: np.ndarray, num_nodes: int | None = None):
    local = CELL_FACES[CELL_TYPE_OF_NODES[cells.shape[1]]]
    return CutTopology(cells, int(cells.max()) + 1 if num_nodes is None else num_nodes, local)


def interior_faces(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each interior face once (as seen from its first cell) and its two cells (k, 2)."""
    return _topology(np.asarray(cells)).interior_faces()


@dataclass(frozen=True)
class LimbalArc:
    """A limbal relaxing incision on the cornea (mm, degrees).

    ``radius``: distance of the incision from the optical (z) axis; the faces
    between the cells inside and outside that cylinder are cut (near the limbus
    the O-grid's rings are circles, so this is one ring of faces). ``start`` /
    ``end``: its angular extent about z (degrees, counter-clockwise from +x).
    ``depth``: the fraction of the local thickness it reaches from the anterior
    surface (0 < depth <= 1).
    """

    radius: float
    start: float
    end: float
    depth: float = 0.7

    def __post_init__(self):
        if not self.radius > 0:
            raise InputError(f"incision radius must be positive, got {self.radius} mm")
        if not 0 < self.end - self.start < 360:
            raise InputError(f"incision angles must satisfy 0 < end - start < 360, got "
                             f"{self.start}..{self.end}")  # fmt: skip
        if not 0 < self.depth <= 1:
            raise InputError(f"incision depth must be a fraction in (0, 1], got {self.depth}")


def limbal_arc(mesh: BuiltMesh, arc: LimbalArc) -> np.ndarray:
    """Indices (into :func:`interior_faces`) of the faces of a limbal arc incision."""
    if mesh.name != "cornea":
        raise InputError(f"a limbal incision needs the cornea mesh, got {mesh.name!r}")
    faces, pair = interior_faces(mesh.cells)
    x = mesh.nodes[faces]  # (k, 4, 3)
    centroid = x.mean(axis=1)
    normal = np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    rho = np.hypot(centroid[:, 0], centroid[:, 1])
    radial = np.column_stack([centroid[:, 0], centroid[:, 1], np.zeros(len(faces))])
    radial /= np.maximum(rho, 1e-12)[:, None]
    facing = np.abs(np.sum(normal * radial, axis=1)) > 0.7  # a surface of about constant radius
    # The face separates a cell inside the cylinder rho = radius from one outside it.
    cell_rho = np.hypot(*mesh.nodes[mesh.cells].mean(axis=1)[:, :2].T)
    inside = cell_rho[pair]
    straddles = (np.minimum(inside[:, 0], inside[:, 1]) < arc.radius) & (
        np.maximum(inside[:, 0], inside[:, 1]) >= arc.radius
    )
    angle = np.degrees(np.arctan2(centroid[:, 1], centroid[:, 0]))
    within = (angle - arc.start) % 360.0 <= (arc.end - arc.start)
    # Depth below the anterior sphere (centre (0, 0, -R)) relative to the local thickness.
    R = mesh.params["radius"]
    below = R - np.linalg.norm(centroid - np.array([0.0, 0.0, -R]), axis=1)
    t0, t1 = mesh.params["central_thickness"], mesh.params["limbus_thickness"]
    rim = np.arcsin(min(1.0, mesh.params["limbus_diameter"] / (2 * R)))
    polar = np.arcsin(np.clip(rho / R, 0, 1))
    thickness = t0 + (t1 - t0) * (polar / rim) ** 2
    shallow = below <= arc.depth * thickness
    chosen = np.flatnonzero(facing & straddles & within & shallow)
    if chosen.size == 0:
        raise InputError(f"no faces of the cornea mesh lie on the incision {arc}")
    return chosen


def cut_mesh(mesh: BuiltMesh, face_indices: np.ndarray) -> tuple[BuiltMesh, np.ndarray]:
    """The mesh with the given interior faces (indices into :func:`interior_faces`) cut.

    Returns the new mesh and ``origin`` (new node -> original node). Cells keep
    their order; new nodes are appended after the original ones. The runtime's
    :class:`~hapticrom.shared.cut_topology.CutTopology` does the cutting, so the
    explicit reference and the runtime's cuts are the same by construction.
    """
    faces, _ = interior_faces(mesh.cells)
    face_indices = np.unique(np.asarray(face_indices, dtype=np.int64))
    if face_indices.size == 0:
        raise InputError("nothing to cut: no face selected")
    topology = _topology(mesh.cells, len(mesh.nodes))
    topology.cut(faces[face_indices])
    cells, origin = topology.cells, topology.origin
    groups = _regroup_boundary(mesh, cells, origin)
    return replace(mesh, nodes=mesh.nodes[origin], cells=cells, facet_groups=groups), origin


def _regroup_boundary(mesh: BuiltMesh, cells: np.ndarray, origin: np.ndarray) -> dict:
    """Boundary faces of the cut mesh in their old groups; the new lip faces in ``free``."""
    old = {}
    for name, faces in mesh.facet_groups.items():
        for f in faces:
            old[tuple(sorted(f))] = name
    groups: dict[str, list] = {name: [] for name in mesh.facet_groups}
    groups.setdefault("free", [])
    for f in boundary_faces(cells):
        groups[old.get(tuple(sorted(origin[f])), "free")].append(f)
    k = cells.shape[1] // 2 if cells.shape[1] == 8 else 3
    return {name: np.array(f, dtype=np.int64).reshape(-1, k) for name, f in groups.items()}
