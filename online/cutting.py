"""Cuts at run time: a cut region's topology and its patch coupled with the reduced model.

numpy only at import (the scalpel's placement uses numba kernels of
:mod:`hapticrom.online.kernels`, imported by :class:`Scalpel`). The offline side
exports, for a cuttable region of the organ, its cells, their element stiffness matrices at
the reference tangent, the reduced basis rows at its nodes and which nodes
must stay continuous (the region's boundary and the supports). Here:

- :class:`CutTopology` cuts faces of the region one event at a time: the
  nodes inside the cut get one copy per side, the cut's front stays joined
  (the same rule as the explicit cut meshes of :mod:`hapticrom.meshes.cut`);
- :class:`CutPatch` builds the superimposed patch around the cut and the
  coupled system of thesis eq. 4.8 (reduced coordinates + the patch's local
  DOFs, with one DOF set per lip: Heaviside enrichment of a face-aligned cut),
  factorises it once per topology change, and solves it for a load. With an
  element-wise pressure (:class:`PressureCoupling`) the reduced part keeps the
  reduced pressure basis outside the patch, so nearly incompressible tissue
  does not lock; the patch's cells keep their own pressures.

Units: mm, N, N/mm.
"""

from __future__ import annotations

import sys
import threading
import time
import weakref
from dataclasses import dataclass

import numpy as np

from hapticrom.shared.errors import HapticromError, InputError

_F8 = np.dtype(np.float64)
HEX_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [0, 4, 7, 3], [1, 2, 6, 5]]
)


# Degree-4 symmetric quadrature on a triangle (Dunavant): barycentric points, weights (sum 1).
_A, _B = 0.445948490915965, 0.091576213509771
TRIANGLE_RULE = (
    np.array([[_A, _A, 1 - 2 * _A], [_A, 1 - 2 * _A, _A], [1 - 2 * _A, _A, _A],
              [_B, _B, 1 - 2 * _B], [_B, 1 - 2 * _B, _B], [1 - 2 * _B, _B, _B]]),
    np.array([0.223381589678011] * 3 + [0.109951743655322] * 3),
)  # fmt: skip


@dataclass
class PressureCoupling:
    """What a consistent coupling needs when the element has an element-wise pressure.

    The reduced model keeps its pressure in a reduced basis (locking-free, as the
    reduced model everywhere else); the patch's cells keep their own pressure,
    condensed cell by cell. So the patch's cells are taken out of the reduced
    blocks and put back with their own pressures. Per region cell: ``displacement``
    K_uu,c (C, 24, 24) N/mm, ``coupling`` k_up,c (C, 24) mm^2, ``pressure`` k_pp,c
    (C,) mm^3/MPa (< 0), ``pressure_basis`` (C, P) the reduced pressure modes' cell
    values. Reduced, over the whole organ: ``reduced_displacement`` A^T K_uu A
    (G, G), ``reduced_coupling`` A^T K_up P (G, P), ``reduced_pressure`` P^T K_pp P (P, P).
    """

    displacement: np.ndarray
    coupling: np.ndarray
    pressure: np.ndarray
    pressure_basis: np.ndarray
    reduced_displacement: np.ndarray
    reduced_coupling: np.ndarray
    reduced_pressure: np.ndarray

    def outside(self, cells: np.ndarray, cell_basis: np.ndarray) -> tuple:
        """(A^T K_uu A, A^T K_up P, P^T K_pp P) of the cells not in ``cells``.

        ``cell_basis`` (len(cells), 24, G): the reduced basis rows at those cells' nodes.
        """
        psi = self.pressure_basis[cells]  # (c, P)
        G = cell_basis.shape[2]
        KA = self.displacement[cells] @ cell_basis  # (c, 24, G)
        A = self.reduced_displacement - cell_basis.reshape(-1, G).T @ KA.reshape(-1, G)
        coupling = np.einsum("cig,ci->cg", cell_basis, self.coupling[cells])
        B = self.reduced_coupling - coupling.T @ psi
        C = self.reduced_pressure - (self.pressure[cells][:, None] * psi).T @ psi
        return A, B, C


@dataclass
class CutRegion:
    """What the runtime knows of the cuttable region (region-local node numbering).

    ``coordinates`` (R, 3) mm; ``cells`` (C, 8) hexahedra; ``element_stiffness``
    (C, 24, 24) N/mm, DOFs 3 i + c of the cell's nodes in order; ``basis`` (3 R, G)
    rows of the reduced basis; ``fixed`` (R,) bool: nodes whose local field is
    zero (on the region's boundary or supported); ``reduced_stiffness`` (G, G).
    """

    coordinates: np.ndarray
    cells: np.ndarray
    element_stiffness: np.ndarray
    basis: np.ndarray
    fixed: np.ndarray
    reduced_stiffness: np.ndarray
    pressure: PressureCoupling | None = None

    def __post_init__(self):
        R, C = len(self.coordinates), len(self.cells)
        G = self.reduced_stiffness.shape[0]
        checks = {
            "cells": self.cells.shape == (C, 8) and self.cells.min() >= 0
            and self.cells.max() < R,
            "element_stiffness": self.element_stiffness.shape == (C, 24, 24),
            "basis": self.basis.shape == (3 * R, G),
            "fixed": self.fixed.shape == (R,),
            "reduced_stiffness": self.reduced_stiffness.shape == (G, G),
        }  # fmt: skip
        if self.pressure is not None:
            q = self.pressure
            P = q.reduced_pressure.shape[0]
            checks |= {
                "displacement stiffness": q.displacement.shape == (C, 24, 24),
                "pressure coupling": q.coupling.shape == (C, 24),
                "pressure stiffness": q.pressure.shape == (C,),
                "pressure basis": q.pressure_basis.shape == (C, P),
                "reduced displacement": q.reduced_displacement.shape == (G, G),
                "reduced coupling": q.reduced_coupling.shape == (G, P),
                "reduced pressure": q.reduced_pressure.shape == (P, P),
                "pressure stiffness sign (k_pp < 0)": bool(np.all(q.pressure < 0)),
            }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"cut region: inconsistent {', '.join(bad)}")


class CutTopology:
    """Cells with cut faces opened (lip-aware connectivity), one cut event at a time.

    ``cells`` (m, k): node indices of the intact cells; ``num_nodes``: how many
    nodes there are; ``local_faces``: each cell's faces as local node indices
    (hexahedra by default, gmsh order). New nodes are numbered from ``num_nodes``
    on; ``origin`` maps every node to the intact node it copies.
    """

    def __init__(self, cells: np.ndarray, num_nodes: int, local_faces: np.ndarray = HEX_FACES):
        self.intact = np.asarray(cells)
        self.local_faces = np.asarray(local_faces)
        self.cells = self.intact.copy()
        self.origin = np.arange(num_nodes)  # node -> intact node it copies
        self.cut_faces: set[tuple[int, ...]] = set()  # in intact node ids

    @classmethod
    def of_region(cls, region: CutRegion) -> CutTopology:
        return cls(region.cells, len(region.coordinates))

    def copy(self) -> CutTopology:
        other = CutTopology.__new__(CutTopology)
        other.intact, other.local_faces = self.intact, self.local_faces
        other.cells, other.origin = self.cells.copy(), self.origin.copy()
        other.cut_faces = set(self.cut_faces)
        return other

    def interior_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """The interior faces (intact node ids, (f, k)) and their two cells."""
        nf, k = self.local_faces.shape
        faces = self.intact[:, self.local_faces].reshape(-1, k)
        owner = np.repeat(np.arange(len(self.intact)), nf)
        keys = np.sort(faces, axis=1)
        order = np.lexsort(keys.T[::-1])
        same = np.all(keys[order][1:] == keys[order][:-1], axis=1)
        first, second = order[:-1][same], order[1:][same]
        return faces[first], np.column_stack([owner[first], owner[second]])

    def cut(self, faces: np.ndarray) -> np.ndarray:
        """Open interior ``faces`` ((f, k), intact node ids); return the new nodes."""
        faces = np.atleast_2d(np.asarray(faces, dtype=np.int64))
        self.cut_faces |= {tuple(sorted(f)) for f in faces}
        before = len(self.origin)
        for node in np.unique(faces):
            self._split(int(node))
        return np.arange(before, len(self.origin))

    def _split(self, original: int) -> None:
        """Regroup the cells around an original node by sides; one node copy per side."""
        cells_at = np.flatnonzero(np.any(self.origin[self.cells] == original, axis=1))
        parent = {int(c): int(c) for c in cells_at}

        def find(c):
            while parent[c] != c:
                parent[c] = parent[parent[c]]
                c = parent[c]
            return c

        seen: dict[tuple, int] = {}
        for c in cells_at:
            for f in self.intact[c][self.local_faces]:
                if original not in f:
                    continue
                key = tuple(sorted(f))
                if key in self.cut_faces:
                    continue
                if key in seen:
                    parent[find(int(c))] = find(seen[key])
                else:
                    seen[key] = int(c)
        sides: dict[int, list[int]] = {}
        for c in cells_at:
            sides.setdefault(find(int(c)), []).append(int(c))
        groups = sorted(sides.values(), key=min)
        # The first side keeps the original node; each other side gets a node of its own,
        # reusing a copy it holds from an earlier cut if no other side took it already.
        used = {original}
        for c in groups[0]:
            self.cells[c][self.origin[self.cells[c]] == original] = original
        for component in groups[1:]:
            held = {int(n) for c in component for n in self.cells[c]
                    if self.origin[n] == original} - used  # fmt: skip
            if held:
                node = min(held)
            else:
                node = len(self.origin)
                self.origin = np.append(self.origin, original)
            used.add(node)
            for c in component:
                self.cells[c][self.origin[self.cells[c]] == original] = node

    @property
    def lip_nodes(self) -> np.ndarray:
        """Nodes (originals and copies) that exist more than once."""
        return np.flatnonzero(np.bincount(self.origin)[self.origin] > 1)


class CutPatch:
    """The factorised coupled system (thesis eq. 4.8) of one cut topology of a region."""

    def __init__(
        self,
        topology: CutTopology,
        region: CutRegion,
        layers: int = 2,
        patch_cells: np.ndarray | None = None,
    ):
        """``patch_cells``: use these cells instead of ``layers`` rings around the cut."""
        if layers < 1:
            raise ValueError(f"the patch needs at least one layer of cells, got {layers}")
        self.region = region
        cells = topology.cells
        if patch_cells is None:
            in_patch = np.any(np.isin(cells, topology.lip_nodes), axis=1)
            for _ in range(layers - 1):
                in_patch |= np.any(np.isin(cells, np.unique(cells[in_patch])), axis=1)
        else:
            in_patch = np.zeros(len(cells), dtype=bool)
            in_patch[patch_cells] = True
        outside = np.unique(cells[~in_patch])
        fixed = region.fixed[topology.origin]
        candidates = np.unique(cells[in_patch])
        nodes = candidates[~np.isin(candidates, outside) & ~fixed[candidates]]
        self.topology, self.cells, self.nodes = topology, np.flatnonzero(in_patch), nodes
        G = region.reduced_stiffness.shape[0]
        m = 3 * len(nodes)
        index = np.full(len(topology.origin), -1)
        index[nodes] = np.arange(len(nodes))
        conn = cells[self.cells]  # (c, 8) nodes of the patch cells, lips apart
        # The reduced field does not see the cut: each copy takes its original's rows.
        basis = region.basis[(3 * topology.origin[conn][:, :, None] + np.arange(3)).reshape(
            len(conn), 24)]  # (c, 24, G)  # fmt: skip
        Ke = region.element_stiffness[self.cells]  # (c, 24, 24)
        KA = Ke @ basis  # (c, 24, G); Ke is symmetric: (A_c^T Ke)^T
        if region.pressure is None:
            K_zz = region.reduced_stiffness.copy()
        else:
            # Reduced pressure outside the patch, the cells' own pressures inside it.
            A, B, C = region.pressure.outside(self.cells, basis)
            K_zz = A - B @ np.linalg.solve(C, B.T) + basis.reshape(-1, G).T @ KA.reshape(-1, G)
        dofs = (3 * index[conn][:, :, None] + np.arange(3)).reshape(len(conn), 24)
        keep = dofs >= 0
        K_dz = np.zeros((m, G))
        np.add.at(K_dz, dofs[keep], KA[keep])
        both = keep[:, :, None] & keep[:, None, :]
        rows = np.broadcast_to(dofs[:, :, None], both.shape)[both]
        columns = np.broadcast_to(dofs[:, None, :], both.shape)[both]
        K_dd = np.bincount(rows * m + columns, Ke[both], m * m).reshape(m, m)
        K = np.block([[K_zz, K_dz.T], [K_dz, K_dd]])
        self.size, self.G = K.shape[0], G
        self.factor = np.linalg.cholesky((K + K.T) / 2)  # raises LinAlgError if not SPD

    @property
    def dofs(self) -> np.ndarray:
        return (3 * self.nodes[:, None] + np.arange(3)).ravel()

    def solve(self, load_reduced: np.ndarray, load_patch: np.ndarray) -> np.ndarray:
        """[zeta, d] for the reduced load A^T f (G,) and the load on the patch DOFs."""
        L = self.factor
        y = solve_lower(L, np.r_[load_reduced, load_patch])
        return solve_lower(L, y, transposed=True)

    def region_displacement(self, x: np.ndarray) -> np.ndarray:
        """Displacement (mm) of every node of the cut region (copies included), (R', 3)."""
        topology, region = self.topology, self.region
        rows = (3 * topology.origin[:, None] + np.arange(3)).ravel()
        u = region.basis[rows] @ x[: self.G]
        u[self.dofs] += x[self.G :]
        return u.reshape(-1, 3)


# -- the scalpel ------------------------------------------------------------------------
class ScalpelInputError(HapticromError, ValueError):
    """A scalpel position off the organ or a degenerate blade; the cut state is unchanged."""


@dataclass
class CutEvent:
    """One topology change: which faces were cut, the patch after it, and what it cost."""

    faces: int
    new_nodes: int
    patch_unknowns: int
    seconds: float


@dataclass
class _CutState:
    """A cut state prepared (possibly on a worker thread), installed between steps."""

    topology: CutTopology
    patch: CutPatch | None
    compliances: tuple | None  # (vertices, ratio, extra compliance, loads)
    event: CutEvent


class Scalpel:
    """Cuts of one simulator: blade position and direction, cut faces, the coupled patch.

    A cut happens when the force in the blade's plane exceeds ``cut_force`` (thesis
    eq. 4.10, after Bielser and Gross): the region's interior faces under the
    blade (facing across the blade's plane, down to ``cut_depth`` below the
    surface) are cut whole, the patch is rebuilt around all cuts so far and the
    coupled system factorised. For each surface vertex of the region the
    factorisation gives the tissue's compliance under a unit tool load with the
    cuts, and without them (the same patch uncut); their ratio scales the
    reduced model's force at the contact (a cut softens the tissue near it), and
    the cut's own displacement field is added to the rendered surface, lips
    included.
    """

    def __init__(self, model, cut_depth: float | None = None, layers: int | None = None):
        region = model.cut_region
        if region is None:
            raise InputError("this artifact has no cuttable region (format 1.2 'cutting' group)")
        attrs = model.artifact.group_attrs["cutting"]
        self.model, self.region = model, region
        self.cut_force = float(attrs["cut_force"])
        # The training's soft tip: the tool load of the stiffness ratios (mm).
        self.tool_radius = float(
            model.artifact.attrs["campaign"]["load"].get("contact_radius", 0.5)
        )
        self.layers = int(layers or attrs["patch_layers"])
        edges = np.linalg.norm(
            region.coordinates[region.cells[:, 1]] - region.coordinates[region.cells[:, 0]], axis=1
        )
        self.cell_size = float(np.median(edges))
        self.cut_depth = float(cut_depth) if cut_depth is not None else 0.7 * self._thickness()
        self.topology = CutTopology.of_region(region)
        self.patch: CutPatch | None = None
        self.events: list[CutEvent] = []
        self._faces, _ = self.topology.interior_faces()
        self._face_centroid = region.coordinates[self._faces].mean(axis=1)
        x = region.coordinates[self._faces]
        normal = np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
        self._face_normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        # Surface vertices of the model that are region nodes (canonical node ids).
        canonical = np.asarray(model.artifact["cutting"]["nodes"])
        surface_nodes = np.asarray(model.artifact["surface"]["nodes"])
        local = {int(n): i for i, n in enumerate(canonical)}
        self.surface_region = np.array([local.get(int(n), -1) for n in surface_nodes],
                                       dtype=np.int64)  # fmt: skip
        self.surface_region.flags.writeable = False
        self.ratio = np.ones(len(surface_nodes))  # cut / intact stiffness per surface vertex
        self.extra_compliance = np.zeros(len(surface_nodes))  # cut - intact compliance, mm/N
        self._loads = (np.zeros(0, dtype=np.int64), None, None, None)
        self._executor = None  # a worker thread, once a cut is asked not to wait
        self._next: CutTopology | None = None  # the worker's topology (all cuts asked so far)
        self._pending: list = []  # futures of background cuts, in order
        self._fast_switch = [False]  # whether this scalpel holds the short GIL switch interval
        self.normals = _vertex_normals(model.vertices, model.triangles)  # outward, per vertex
        self.normals.flags.writeable = False
        # Where the scalpel is placed: the surface vertex nearest a point, by a grid (exact).
        from hapticrom.online import kernels  # numba: only once a scalpel is made

        self._kernels = kernels
        # What placing the scalpel reads (kernels.place_scalpel), packed once.
        self.tables = kernels.scalpel_tables(model.vertices, self.normals, self.surface_region,
                                              self.cell_size, 2.0 * self.cell_size,
                                              self.cell_size)  # fmt: skip
        self._region_triangles(self.topology)  # cached now: workers only read it

    def region_vertex(self, point) -> int:
        """The surface vertex of the region nearest ``point`` (3,), or -1 if none is within
        a cell, or not 3 finite numbers (no allocation for a 1-D float64 array)."""
        if type(point) is not np.ndarray or point.dtype is not _F8 or point.ndim != 1:
            point = np.asarray(point, dtype=np.float64).reshape(-1)
        floats, ints = self.tables
        return self._kernels.region_vertex(point, floats, ints)

    def placement_error(self, status: int, position, blade_direction) -> ScalpelInputError:
        """The error of a refused placement (a status of ``kernels.place_scalpel``),
        naming what is wrong."""
        k = self._kernels
        p, b = np.asarray(position), np.asarray(blade_direction)
        if status in (k.WRONG_SHAPE, k.BLADE_SHAPE):
            what, value = ("scalpel position", p) if status == k.WRONG_SHAPE else ("blade", b)
            return ScalpelInputError(f"{what} must be 3 numbers, shape (3,); got shape "
                                     f"{value.shape}")  # fmt: skip
        if status == k.POSITION_NOT_FINITE:
            return ScalpelInputError(
                f"scalpel position must be 3 finite numbers (mm), got {p.tolist()}"
            )
        if status == k.BLADE_NOT_FINITE:
            return ScalpelInputError(f"blade direction must be 3 finite numbers, got {b.tolist()}")
        if status == k.OFF_ORGAN:
            gap = np.min(np.linalg.norm(self.model.vertices - p, axis=1))
            return ScalpelInputError(
                f"scalpel position {p.tolist()} mm is off the organ ({gap:.3g} mm from its "
                f"surface; at most {2 * self.cell_size:.3g} mm)"
            )
        return ScalpelInputError(
            f"blade direction {b.tolist()} is zero or along the surface normal: it must have "
            "a component along the surface"
        )

    def surface_layout(self):
        """(surface vertices in the region, their region nodes, lip copies, the vertices the
        copies duplicate) for the current cut state; cached per cut event."""
        key = len(self.events)
        if getattr(self, "_layout_key", None) != key:
            on = np.flatnonzero(self.surface_region >= 0)
            vertex_of = np.full(len(self.region.coordinates), -1)
            vertex_of[self.surface_region[on]] = on
            copies = np.arange(len(self.region.coordinates), len(self.topology.origin))
            duplicates = vertex_of[self.topology.origin[copies]]
            keep = duplicates >= 0
            self._layout = (on, self.surface_region[on], copies[keep], duplicates[keep])
            self._layout_key = key
        return self._layout

    def surface_triangles(self) -> np.ndarray:
        """The surface triangles with the lips split: a triangle on a copy's side of the cut
        uses that copy's lip vertex (numbered V + k, k as in ``surface_layout``'s copies)."""
        key = len(self.events)
        if getattr(self, "_triangles_key", None) == key:
            return self._triangles
        triangles = np.asarray(self.model.triangles).copy()
        _, _, copies, _ = self.surface_layout()
        vertex_of = np.full(len(self.topology.origin), -1)
        vertex_of[copies] = len(self.model.vertices) + np.arange(len(copies))
        which, current = self._region_triangles(self.topology)
        lip = vertex_of[current]
        triangles[which] = np.where(lip >= 0, lip, triangles[which])
        self._triangles_key, self._triangles = key, triangles
        return triangles

    def _region_triangles(self, topology: CutTopology) -> tuple[np.ndarray, np.ndarray]:
        """(indices of the surface triangles wholly in the region, their nodes in
        ``topology``'s numbering: a triangle on a copy's side of a cut uses the copy)."""
        if not hasattr(self, "_triangle_cell"):
            nodes = self.surface_region[np.asarray(self.model.triangles)]
            which = np.flatnonzero(np.all(nodes >= 0, axis=1))
            cells = self.region.cells
            cells_at: dict[int, set] = {}
            for c, cell_nodes in enumerate(cells.tolist()):
                for n in cell_nodes:
                    cells_at.setdefault(n, set()).add(c)
            cell = np.full(len(which), -1)
            for i, (a, b, c) in enumerate(nodes[which].tolist()):
                # The one region cell holding the three nodes of a surface triangle.
                holding = cells_at.get(a, set()) & cells_at.get(b, set()) & cells_at.get(c, set())
                cell[i] = min(holding, default=-1)
            keep = cell >= 0
            which, cell = which[keep], cell[keep]
            position = np.argmax(cells[cell][:, None, :] == nodes[which][:, :, None], axis=2)
            self._triangle_cell = (which, cell, position)
        which, cell, position = self._triangle_cell
        return which, topology.cells[cell[:, None], position]

    def _surface_quadrature(self, topology: CutTopology):
        """(loadable region triangles in ``topology``'s numbering (T, 3), their quadrature
        points (T, 6, 3) mm, and weights (T, 6) mm^2), for tool tractions.

        Only the loadable surface counts (a tool touches the anterior surface, not the
        posterior one, however thin the tissue). A lip copy's triangles are those of
        its own side of the cut.
        """
        which, triangles = self._region_triangles(topology)
        triangles = triangles[np.asarray(self.model.artifact["surface"]["groups"])[which] == 1]
        x = self.region.coordinates[topology.origin[triangles]]  # (T, 3, 3)
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        points = np.einsum("qi,tij->tqj", TRIANGLE_RULE[0], x)
        return triangles, points, area[:, None] * TRIANGLE_RULE[1]

    def _thickness(self) -> float:
        """A rough local thickness: the region's extent along its mean surface normal."""
        x = self.region.coordinates
        centred = x - x.mean(axis=0)
        n = np.linalg.svd(centred, full_matrices=False)[2][-1]
        return float(np.ptp(centred @ n))

    def faces_under(self, position: np.ndarray, blade: np.ndarray, normal: np.ndarray):
        """Region interior faces under the blade: facing across its plane, within its depth."""
        across = np.cross(blade, normal)  # normal of the blade's plane
        facing = np.abs(self._face_normal @ across) > 0.7
        rel = self._face_centroid - position
        depth = -(rel @ normal)  # below the surface, along the inward normal
        along = rel @ blade
        off_plane = np.abs(rel @ across)
        # A blade is a few cells long: the faces within one cell size along it are cut.
        near = (np.abs(along) <= self.cell_size) & (off_plane <= 0.75 * self.cell_size)
        within = (depth >= -0.5 * self.cell_size) & (depth <= self.cut_depth)
        keys = self.topology.cut_faces
        chosen = [i for i in np.flatnonzero(facing & near & within)
                  if tuple(sorted(self._faces[i])) not in keys]  # fmt: skip
        return self._faces[chosen]

    def cut(self, faces: np.ndarray, wait: bool = True) -> CutEvent | None:
        """Cut ``faces`` (region node ids), rebuild and factorise the patch.

        ``wait=False``: do it on a worker thread and return None at once; the
        current cut state stays in force until :meth:`poll` installs the new one
        (cuts are installed in the order they were asked for). numpy's LAPACK calls,
        most of the work, release the GIL, so the servo loop keeps its pace.
        """
        if len(faces) == 0:
            return None
        if wait:
            self.finish()
            state = self._prepare(self.topology.copy(), faces)
            if self._next is not None:
                self._next = self.topology.copy() if state is None else state.topology.copy()
            return self._install(state)
        if self._executor is None:
            from concurrent.futures import ThreadPoolExecutor

            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hapticrom-cut")
            self._next = self.topology.copy()
            weakref.finalize(self, _close, self._executor, self._fast_switch)
        # The worker cuts its own topology in order; each result is a state of its own.
        self._pending.append(self._executor.submit(self._prepare, self._next, faces))
        if not self._fast_switch[0]:
            _fast_switch(True)
            self._fast_switch[0] = True
        return None

    @property
    def pending(self) -> bool:
        """Whether a background cut is still being prepared."""
        return bool(self._pending)

    def poll(self) -> CutEvent | None:
        """Install the background cuts that are ready; the last event installed or None."""
        event = None
        while self._pending and self._pending[0].done():
            event = self._install(self._take()) or event
        return event

    def finish(self) -> CutEvent | None:
        """Wait for the background cuts and install them; the last event or None."""
        event = None
        while self._pending:
            event = self._install(self._take()) or event
        return event

    def _take(self) -> _CutState | None:
        future = self._pending.pop(0)
        if not self._pending and self._fast_switch[0]:
            self._fast_switch[0] = False
            _fast_switch(False)
        # A worker's exception is raised here; the cut it failed changed nothing.
        return future.result()

    def _prepare(self, topology: CutTopology, faces: np.ndarray) -> _CutState | None:
        """Cut ``topology`` (modified) and build everything a cut state needs."""
        t0 = time.perf_counter()
        faces = np.atleast_2d(np.asarray(faces, dtype=np.int64))
        faces = faces[[tuple(sorted(f)) not in topology.cut_faces for f in faces.tolist()]]
        if len(faces) == 0:
            return None
        work = topology.copy()  # ``topology`` changes only if everything below succeeds
        new = work.cut(faces)
        patch = compliances = None
        if len(work.lip_nodes) > 0:  # else only front nodes so far: nothing opens yet
            patch = CutPatch(work, self.region, self.layers)
            compliances = self._compliances(patch)
        topology.cells, topology.origin = work.cells.copy(), work.origin.copy()
        topology.cut_faces = set(work.cut_faces)
        size = 0 if patch is None else patch.size
        return _CutState(work, patch, compliances, CutEvent(len(faces), len(new), size,
                                                           time.perf_counter() - t0))  # fmt: skip

    def _install(self, state: _CutState | None) -> CutEvent | None:
        """Make a prepared cut state the current one (main thread, between steps)."""
        if state is None:
            return None
        if self._executor is not None:
            # Freeing the old patch's factors takes milliseconds: on the worker, not here.
            self._executor.submit(_drop, (self.topology, self.patch, self._loads))
        self.topology = state.topology
        if state.patch is not None:
            on_region, ratio, extra, loads = state.compliances
            # New arrays swapped in, never half-updated ones.
            new_ratio, new_extra = np.ones_like(self.ratio), np.zeros_like(self.extra_compliance)
            new_ratio[on_region], new_extra[on_region] = ratio, extra
            self.patch, self._loads = state.patch, loads
            self.ratio, self.extra_compliance = new_ratio, new_extra
        self.events.append(state.event)
        return state.event

    def _compliances(self, patch: CutPatch) -> tuple:
        """Stiffness ratio (cut / uncut) for a unit tool load at the region's surface
        vertices whose tool disk reaches the patch (1 elsewhere: the patch is the cut's
        zone of influence, u^L = 0 beyond it).

        The uncut reference is the same patch without the cut, not the reduced model
        alone: the patch's local DOFs relax the reduced basis a little too (a lot if
        the reduced part has its pressure condensed per element, which locks nearly
        incompressible tissue), and only the cut's share of the softening belongs
        in the force.
        """
        on_region = np.flatnonzero(self.surface_region >= 0)
        radius = self.tool_radius
        topology = patch.topology
        patch_nodes = np.unique(topology.origin[topology.cells[patch.cells]])
        x = self.region.coordinates[patch_nodes]
        v = self.model.vertices[on_region]
        gap2 = (np.sum(v * v, axis=1)[:, None] + np.sum(x * x, axis=1)[None, :]
                - 2.0 * v @ x.T).min(axis=1)  # fmt: skip
        on_region = on_region[gap2 <= radius**2]
        uncut = CutPatch(CutTopology.of_region(self.region), self.region, 1, patch.cells)
        B, B_uncut = (self._tool_loads(p, on_region) for p in (patch, uncut))
        cut = _compliance(patch, B)
        reference = _compliance(uncut, B_uncut)
        ratio = np.ones_like(cut)
        np.divide(reference, cut, out=ratio, where=cut > 0)
        return on_region, ratio, cut - reference, (on_region, B, B_uncut, uncut)

    def _tool_loads(self, patch: CutPatch, vertices: np.ndarray) -> np.ndarray:
        """Right-hand sides (patch.size, len(vertices)) of a unit tool force centred on
        each of ``vertices``.

        The tool presses as the training's soft tip does: a traction of profile
        (1 - r^2 / a^2)^2 within its radius a, along the inward normal at its centre,
        1 N in all, integrated over the surface triangles (6-point rule, linear
        shapes). A point load would not do (at a lip its compliance is the local,
        singular response), nor would a load on one lip only: each lip takes the
        traction of its own side of the surface; nor a nodal lumping, on a mesh as
        coarse as the tool.
        """
        model = self.model
        radius = self.tool_radius
        topology, region, G = patch.topology, patch.region, patch.G
        triangles, points, weights = self._surface_quadrature(topology)
        nodes, triangles = np.unique(triangles, return_inverse=True)
        triangles = triangles.reshape(-1, 3)
        centres = model.vertices[vertices]
        # Traction at every quadrature point for every tool centre: (T * 6, k).
        x = points.reshape(-1, 3)
        s = (np.sum(x * x, axis=1)[:, None] + np.sum(centres * centres, axis=1)[None, :]
             - 2.0 * x @ centres.T) / radius**2  # fmt: skip
        traction = weights.reshape(-1, 1) * np.where(s < 1.0, (1.0 - s) ** 2, 0.0)
        # Spread to the triangles' nodes by the linear shapes: W (nodes, k), columns sum to 1.
        corner = np.einsum("qc,tqk->tck", TRIANGLE_RULE[0], traction.reshape(len(triangles), 6, -1))
        W = np.zeros((len(nodes), len(vertices)))
        np.add.at(W, triangles.ravel(), corner.reshape(-1, len(vertices)))
        W /= np.maximum(W.sum(axis=0), 1e-300)
        direction = -self.normals[vertices]  # (k, 3)
        rows = (3 * topology.origin[nodes][:, None] + np.arange(3)).ravel()
        basis = region.basis[rows].reshape(len(nodes), 3, G)
        B = np.zeros((patch.size, len(vertices)))
        for j in range(3):
            B[:G] += (basis[:, j, :].T @ W) * direction[:, j]
        index = np.full(len(topology.origin), -1)
        index[patch.nodes] = np.arange(len(patch.nodes))
        local = index[nodes]
        on_patch = np.flatnonzero(local >= 0)
        for j in range(3):
            B[G + 3 * local[on_patch] + j] = W[on_patch] * direction[:, j]
        return B

    def cut_field(self, vertex: int) -> np.ndarray | None:
        """Displacement per unit normal force at ``vertex`` of (cut - intact) models, (Rn', 3).

        Cached per contact vertex and cut state (a solve with the patch's factor).
        """
        if self.patch is None or not np.any(self._loads[0] == vertex):
            return None  # no cut, or the tool does not reach the patch from there
        key = (vertex, len(self.events))
        if getattr(self, "_field_key", None) == key:
            return self._field
        self._field_key, self._field = key, self._cut_field(vertex)
        return self._field

    def _cut_field(self, vertex: int) -> np.ndarray:
        on_region, B, B_uncut, uncut = self._loads
        k = int(np.flatnonzero(on_region == vertex)[0])
        G = self.patch.G
        u = self.patch.region_displacement(self.patch.solve(B[:G, k], B[G:, k]))
        u0 = uncut.region_displacement(uncut.solve(B_uncut[:G, k], B_uncut[G:, k]))
        field = u.copy()
        field[: len(u0)] -= u0  # copies have no uncut twin: they move with their original
        copies = np.arange(len(u0), len(u))
        field[copies] -= u0[self.topology.origin[copies]]
        return field


# While a worker runs Python code it holds the GIL for up to the interpreter's switch
# interval (5 ms by default): a servo tick would wait that long. While any background cut
# is on its way the interval is 0.1 ms; the interpreter's own value is restored after.
# Process-wide like the setting itself: counted over all scalpels.
_switch = {"lock": threading.Lock(), "users": 0, "saved": None}


def _fast_switch(on: bool) -> None:
    with _switch["lock"]:
        if on:
            if _switch["users"] == 0:
                _switch["saved"] = sys.getswitchinterval()
                sys.setswitchinterval(min(_switch["saved"], 1e-4))
            _switch["users"] += 1
        else:
            _switch["users"] -= 1
            if _switch["users"] == 0:
                sys.setswitchinterval(_switch["saved"])


def _close(executor, held: list) -> None:
    """A scalpel is gone: stop its worker, give back the switch interval if it held it."""
    executor.shutdown(wait=False, cancel_futures=True)
    if held[0]:
        held[0] = False
        _fast_switch(False)


def _drop(_objects) -> None:
    """Nothing: the worker thread drops the last references to what it was given."""


def _compliance(patch: CutPatch, B: np.ndarray) -> np.ndarray:
    """b^T K^-1 b for every column b of B, from the Cholesky factor: |L^-1 b|^2."""
    Y = solve_lower(patch.factor, B)
    return np.sum(Y * Y, axis=0)


def solve_lower(L: np.ndarray, B: np.ndarray, transposed: bool = False, block: int = 128):
    """L^-1 B (or L^-T B) for a lower-triangular L, by blocks.

    numpy has no triangular solve, and np.linalg.solve factorises L again (2/3 n^3):
    here only the diagonal blocks are solved, the rest is matrix products.
    """
    n = L.shape[0]
    Y = np.empty(B.shape)
    starts = list(range(0, n, block))
    if not transposed:
        for i0 in starts:
            i1 = min(i0 + block, n)
            rhs = B[i0:i1] - L[i0:i1, :i0] @ Y[:i0]
            Y[i0:i1] = np.linalg.solve(L[i0:i1, i0:i1], rhs)
    else:  # L^T is upper triangular: from the last block up
        for i0 in reversed(starts):
            i1 = min(i0 + block, n)
            rhs = B[i0:i1] - L[i1:, i0:i1].T @ Y[i1:]
            Y[i0:i1] = np.linalg.solve(L[i0:i1, i0:i1].T, rhs)
    return Y


def _vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Outward unit vertex normals (area-weighted) of a triangulated surface."""
    x = vertices[triangles]
    area = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, triangles[:, k], area)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
