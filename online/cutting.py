"""Cuts at run time: the cuts made so far in the organ's cuttable region and their effect.

numpy only. A cut happens when the force in the blade's plane exceeds the
artifact's cut force (thesis eq. 4.10, after Bielser and Gross; the blade and
its trigger are :mod:`hapticrom.online.scalpel`'s): the region's interior
faces under the blade are cut whole (:class:`~hapticrom.shared.cut_topology.CutTopology`),
the patch is rebuilt around all cuts so far and the coupled system factorised
(:class:`~hapticrom.online.coupled_patch.CoupledPatch`). For each surface vertex
of the region the factorisation gives the tissue's compliance under a unit tool
load (:class:`~hapticrom.online.tool_load.ToolLoad`) with the cuts, and without
them (the same patch uncut); their ratio scales the reduced model's force at the
contact, and the cut's own displacement field is added to the rendered surface.
A cut event may run on a worker thread (:mod:`hapticrom.online.cut_worker`).

Units: mm, N, N/mm.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hapticrom.online.coupled_patch import CoupledPatch, CutRegion, compliance
from hapticrom.online.cut_worker import CutWorker
from hapticrom.online.tool_load import ToolLoad
from hapticrom.shared.cut_topology import CutTopology


@dataclass
class CutEvent:
    """One topology change: which faces were cut, the patch after it, and what it cost."""

    faces: int
    new_nodes: int
    patch_unknowns: int
    seconds: float


@dataclass
class PreparedCut:
    """A cut state prepared (possibly on a worker thread), installed between steps."""

    topology: CutTopology
    patch: CoupledPatch | None
    compliances: tuple | None  # (vertices, ratio, extra compliance, loads)
    event: CutEvent


@dataclass
class ToolLoads:
    """The unit tool loads of the current patch: the surface vertices they are centred on,
    their right-hand sides with the cuts (B) and on the same patch uncut (B_uncut, uncut)."""

    vertices: np.ndarray
    B: np.ndarray | None = None
    B_uncut: np.ndarray | None = None
    uncut: CoupledPatch | None = None


class Cuts:
    """The cuts of one simulator in the region: topology, patch, softening, cut field.

    ``region``: the artifact's :class:`CutRegion`; ``surface_region`` (V,): each
    surface vertex's region node or -1; ``tool``: the unit tool loads; ``layers``:
    rings of cells of the patch around the cut; ``cell_size`` (mm): how far along
    and across the blade faces are cut; ``cut_depth`` (mm): how deep.
    """

    def __init__(self, region: CutRegion, surface_region: np.ndarray, tool: ToolLoad,
                 layers: int, cell_size: float, cut_depth: float):  # fmt: skip
        self.region, self.surface_region, self.tool = region, surface_region, tool
        self.layers, self.cell_size, self.cut_depth = layers, cell_size, cut_depth
        self.topology = region.intact_topology()
        self.patch: CoupledPatch | None = None
        self.events: list[CutEvent] = []
        V = len(surface_region)
        self.ratio = np.ones(V)  # cut / intact stiffness per surface vertex
        self.extra_compliance = np.zeros(V)  # cut - intact compliance per surface vertex, mm/N
        self.loads = ToolLoads(np.zeros(0, dtype=np.int64))
        self.worker = CutWorker()
        self.next: CutTopology | None = None  # the worker's topology (all cuts asked so far)
        self._faces, _ = self.topology.interior_faces()
        x = region.coordinates[self._faces]
        self._face_centroid = x.mean(axis=1)
        normal = np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
        self._face_normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        self._field_key: tuple[int, int] | None = None  # cut_field's cache: (vertex, events)
        self._field: np.ndarray | None = None

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

        ``wait=False``: do it on the worker thread and return None at once; the
        current cut state stays in force until :meth:`poll` installs the new one
        (cuts are installed in the order they were asked for). numpy's LAPACK calls,
        most of the work, release the GIL, so the servo loop keeps its pace.
        """
        if len(faces) == 0:
            return None
        if wait:
            self.finish()
            state = self._prepare(self.topology.copy(), faces)
            if self.next is not None:
                self.next = self.topology.copy() if state is None else state.topology.copy()
            return self._install(state)
        if not self.worker.started:
            self.next = self.topology.copy()
        # The worker cuts its own topology in order; each result is a state of its own.
        self.worker.submit(self._prepare, self.next, faces)
        return None

    @property
    def pending(self) -> bool:
        """Whether a background cut is still being prepared."""
        return self.worker.pending

    def poll(self) -> CutEvent | None:
        """Install the background cuts that are ready; the last event installed or None."""
        event = None
        while self.worker.first_done():
            event = self._install(self.worker.take()) or event
        return event

    def finish(self) -> CutEvent | None:
        """Wait for the background cuts and install them; the last event or None."""
        event = None
        while self.worker.pending:
            event = self._install(self.worker.take()) or event
        return event

    def _prepare(self, topology: CutTopology, faces: np.ndarray) -> PreparedCut | None:
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
            patch = CoupledPatch(work, self.region, self.layers)
            compliances = self._compliances(patch)
        topology.cells, topology.origin = work.cells.copy(), work.origin.copy()
        topology.cut_faces = set(work.cut_faces)
        size = 0 if patch is None else patch.size
        event = CutEvent(len(faces), len(new), size, time.perf_counter() - t0)
        return PreparedCut(work, patch, compliances, event)

    def _install(self, state: PreparedCut | None) -> CutEvent | None:
        """Make a prepared cut state the current one (main thread, between steps)."""
        if state is None:
            return None
        # Freeing the old patch's factors takes milliseconds: on the worker, not here.
        self.worker.discard((self.topology, self.patch, self.loads))
        self.topology = state.topology
        if state.patch is not None:
            on_region, ratio, extra, loads = state.compliances
            # New arrays swapped in, never half-updated ones.
            new_ratio, new_extra = np.ones_like(self.ratio), np.zeros_like(self.extra_compliance)
            new_ratio[on_region], new_extra[on_region] = ratio, extra
            self.patch, self.loads = state.patch, loads
            self.ratio, self.extra_compliance = new_ratio, new_extra
        self.events.append(state.event)
        return state.event

    def _compliances(self, patch: CoupledPatch) -> tuple:
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
        topology = patch.topology
        patch_nodes = np.unique(topology.origin[topology.cells[patch.cells]])
        x = self.region.coordinates[patch_nodes]
        v = self.tool.model.vertices[on_region]
        gap2 = (np.sum(v * v, axis=1)[:, None] + np.sum(x * x, axis=1)[None, :]
                - 2.0 * v @ x.T).min(axis=1)  # fmt: skip
        on_region = on_region[gap2 <= self.tool.radius**2]
        uncut = CoupledPatch(self.region.intact_topology(), self.region, 1, patch.cells)
        B, B_uncut = (self.tool.loads(p, on_region) for p in (patch, uncut))
        cut = compliance(patch, B)
        reference = compliance(uncut, B_uncut)
        ratio = np.ones_like(cut)
        np.divide(reference, cut, out=ratio, where=cut > 0)
        return on_region, ratio, cut - reference, ToolLoads(on_region, B, B_uncut, uncut)

    def cut_field(self, vertex: int) -> np.ndarray | None:
        """Displacement per unit normal force at ``vertex`` of (cut - intact) models, (Rn', 3).

        Cached per contact vertex and cut state (a solve with the patch's factor).
        """
        if self.patch is None or not np.any(self.loads.vertices == vertex):
            return None  # no cut, or the tool does not reach the patch from there
        key = (vertex, len(self.events))
        if self._field_key != key:
            self._field_key, self._field = key, self._cut_field(vertex)
        return self._field

    def _cut_field(self, vertex: int) -> np.ndarray:
        loads = self.loads
        k = int(np.flatnonzero(loads.vertices == vertex)[0])
        G = self.patch.G
        u = self.patch.region_displacement(self.patch.solve(loads.B[:G, k], loads.B[G:, k]))
        u0 = loads.uncut.region_displacement(
            loads.uncut.solve(loads.B_uncut[:G, k], loads.B_uncut[G:, k])
        )
        field = u.copy()
        field[: len(u0)] -= u0  # copies have no uncut twin: they move with their original
        copies = np.arange(len(u0), len(u))
        field[copies] -= u0[self.topology.origin[copies]]
        return field
