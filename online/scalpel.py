"""The scalpel of a simulator: its placement, the blade's trigger, the cuts' effect on steps.

A :class:`~hapticrom.online.simulator.Simulator` holds one :class:`CuttingController`
once ``scalpel()`` is first called (an artifact with a cuttable region). The
simulator places the blade with one kernel call
(:func:`~hapticrom.online.kernels.place_scalpel`) and tells the controller what
happened; the controller answers through a small interface:

- :meth:`~CuttingController.placed`, :meth:`~CuttingController.moved`: the scalpel
  was placed (the blade armed), or the contact moved by ``set_contact`` (disarmed);
- :meth:`~CuttingController.displacement_stepped`, :meth:`~CuttingController.limit_depth`
  and :meth:`~CuttingController.force_stepped`: after a displacement step (cut if the
  blade's force passes the cut force, soften the force), around a force step;
- :meth:`~CuttingController.add_field`, :meth:`~CuttingController.surface`: rendering.

The cuts themselves (topology, patch, softening) are :class:`~hapticrom.online.cutting.Cuts`.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from hapticrom.online import kernels
from hapticrom.online.cut_render import LipLayout
from hapticrom.online.cutting import CutEvent, Cuts
from hapticrom.online.tool_load import ToolLoad
from hapticrom.shared.errors import InputError, ScalpelInputError
from hapticrom.shared.geometry import vertex_normals


def readonly(a: np.ndarray) -> np.ndarray:
    """A view of ``a`` that cannot be written through."""
    view = a.view()
    view.flags.writeable = False
    return view


class CuttingController:
    """The cutting state of one simulator, composed into it (see the module's docstring).

    ``model``: the reduced model (its artifact has a cuttable region, else
    :class:`~hapticrom.shared.errors.InputError`); ``buf``: the simulator's state buffer
    (the kernels write the blade's frame there); ``table``: the simulator's contact
    table, extended here with the scalpel's part. ``cut_depth`` (mm; default 0.7 times
    the region's thickness) and ``layers`` (the artifact's ``patch_layers``) tune the cuts.
    """

    def __init__(self, model, buf: np.ndarray, table: np.ndarray, cut_depth: float | None = None,
                 layers: int | None = None):  # fmt: skip
        region = model.cut_region
        if region is None:
            raise InputError("this artifact has no cuttable region (format 1.2 'cutting' group)")
        attrs = model.artifact.group_attrs["cutting"]
        self.model = model
        self.cut_force = float(attrs["cut_force"])  # N, in the blade's plane
        # The training's soft tip: the tool load of the stiffness ratios (mm).
        self.tool_radius = float(model.artifact.group_attrs["model"]["contact_radius"])
        coordinates, cells = region.coordinates, region.cells
        edges = np.linalg.norm(coordinates[cells[:, 1]] - coordinates[cells[:, 0]], axis=1)
        self.cell_size = float(np.median(edges))
        self.surface_region = _surface_region(model)  # each surface vertex's region node, or -1
        self.normals = readonly(vertex_normals(model.vertices, model.triangles))  # outward
        tool = ToolLoad(model, region, self.surface_region, self.normals, self.tool_radius)
        depth = float(cut_depth) if cut_depth is not None else 0.7 * _thickness(coordinates)
        self.cuts = Cuts(region, self.surface_region, tool, int(layers or attrs["patch_layers"]),
                         self.cell_size, depth)  # fmt: skip
        self.lips = LipLayout(self.cuts, model.triangles)
        # What placing the scalpel reads (kernels.place_scalpel), packed once: a placement
        # reaches 2 cells from the surface, the region's vertices 1 cell.
        self.table = kernels.scalpel_table(
            table, model.vertices, self.normals, self.surface_region, self.cell_size,
            2.0 * self.cell_size, self.cell_size,
        )  # fmt: skip
        self._buf = buf
        f = kernels.FRAME
        self.blade = readonly(buf[f : f + 3])  # unit blade direction
        self.across = readonly(buf[f + 3 : f + 6])  # unit normal of the blade's plane
        self.vertex = kernels.NO_VERTEX  # the region's surface vertex at the contact, or -1
        self.armed = False  # the blade may still cut at this placement
        self.background = False  # cut events on the worker thread (scalpel(background=True))
        self.last_cut: CutEvent | None = None
        self.cut_error: Exception | None = None  # the last cut that failed, if any
        self.rendered_lips = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64))  # (displacement,
        # surface vertices) of the second lip at the last surface_displacement

    @property
    def scalpel_vertex(self) -> int:
        """The surface vertex under the scalpel (its last placement)."""
        return int(self._buf[kernels.PLACED])

    @property
    def ratio(self) -> float:
        """The cuts' softening at the contact: cut / intact stiffness (1 away from them)."""
        return 1.0 if self.vertex < 0 else float(self.cuts.ratio[self.vertex])

    # -- what the simulator tells the controller -------------------------------------------
    def placed(self, region: int, background) -> None:
        """The scalpel was placed (its contact at the region vertex ``region`` or -1): the
        blade is armed; its cut events run on the worker thread if ``background``."""
        self.vertex, self.armed, self.background = region, True, background

    def moved(self, region: int) -> None:
        """A plain contact (``set_contact``) at the region vertex ``region`` or -1: the
        blade is disarmed until the scalpel is placed again."""
        self.vertex, self.armed = region, False

    def displacement_stepped(self, force: np.ndarray) -> None:
        """After a displacement step: cut if the blade's force passes the cut force, then
        soften ``force`` (N, on the tool; changed in place) by the cuts at the contact."""
        self._cut_step(force)
        if self.vertex >= 0:
            force *= self.cuts.ratio[self.vertex]

    def limit_depth(self) -> None:
        """Before a force step: cut tissue yields 1 / ratio times more, so the depth a force
        step may reach is the displacement limit times the ratio."""
        buf = self._buf
        buf[kernels.MAX_DEPTH] = buf[kernels.MAX_DISPLACEMENT] * self.ratio

    def force_stepped(self, force: np.ndarray, displacement: np.ndarray) -> None:
        """After a force step (``force`` N on the tissue): cut if the blade's force passes
        the cut force, then scale ``displacement`` (mm; in place) by the cuts' softening:
        linear, held at the displacement limit (a cut of this step may soften it past)."""
        self._cut_step(force)
        if self.vertex < 0:
            return
        d = displacement
        d /= self.cuts.ratio[self.vertex]
        size = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        limit = self._buf[kernels.MAX_DISPLACEMENT]
        if size > limit:
            d *= limit / size

    def _cut_step(self, force) -> None:
        """Install a ready background cut; cut if the force (N, on the tool or on the
        tissue) in the blade's plane passes the cut force.

        A cut that fails (e.g. a patch that is no longer positive definite) changes
        nothing: the error is kept in ``cut_error`` and the servo loop goes on.
        """
        cuts = self.cuts
        try:
            if cuts.worker.jobs:  # a background cut: install it once ready (between steps)
                event = cuts.poll()
                if event is not None:
                    self.last_cut = event
            if self.armed:
                f0, f1, f2 = force
                a0, a1, a2 = self.across
                across = f0 * a0 + f1 * a1 + f2 * a2
                if f0 * f0 + f1 * f1 + f2 * f2 - across * across > self.cut_force**2:
                    # Once per placement: an unmoved scalpel has nothing new under it, and
                    # the steps stay cheap until scalpel() places it again.
                    self.armed = False
                    self._cut()
        except Exception as exc:  # noqa: BLE001 - the servo loop must not stop here
            self.cut_error = exc
            warnings.warn(f"a cut failed and was not made: {exc!r}", RuntimeWarning, stacklevel=4)

    def _cut(self) -> None:
        """Cut the faces under the blade (now, or on the worker thread)."""
        vertex = self.scalpel_vertex
        faces = self.cuts.faces_under(self.model.vertices[vertex], self.blade, self.normals[vertex])
        event = self.cuts.cut(faces, wait=not self.background)
        if event is not None:
            self.last_cut = event

    def finish(self) -> None:
        """Wait for the background cuts and put them in force."""
        event = self.cuts.finish()
        if event is not None:
            self.last_cut = event

    # -- where the scalpel can go ----------------------------------------------------------
    def region_vertex(self, point) -> int:
        """The surface vertex of the region nearest ``point`` (3,), or -1 if none is within
        a cell, or not 3 finite numbers (no allocation for a 1-D float64 array)."""
        if type(point) is not np.ndarray or point.dtype != np.float64 or point.ndim != 1:
            point = np.asarray(point, dtype=np.float64).reshape(-1)
        return kernels.region_vertex(point, self.table)

    def placement_error(self, status: int, position, blade_direction) -> ScalpelInputError:
        """The error of a refused placement (a status of ``kernels.place_scalpel``),
        naming what is wrong."""
        k = kernels
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

    # -- rendering -------------------------------------------------------------------------
    def add_field(self, out: np.ndarray, force: np.ndarray, depth: float,
                  controlled: str) -> None:  # fmt: skip
        """Add the cuts' displacement (per unit force, times the current ``force``) to the
        surface displacement ``out`` (V, 3) and keep the second lip's (``rendered_lips``).

        Under displacement control (``controlled``) the reduced model's field is that of
        the intact tissue at the tool's ``depth``, while the cut tissue reaches that
        depth at a lower force: the cut's field already holds the extra depth (its
        compliance increase times the force), so the intact part is scaled down to the
        depth the intact tissue would have under that force (linear, as the cut's field).
        """
        if self.cuts.patch is None:
            return
        cuts = self.cuts
        field = cuts.cut_field(self.vertex) if self.vertex >= 0 else None
        on, region_of_on, copies, lip_vertices = self.lips.surface_layout()
        size = float(np.linalg.norm(force))
        if field is not None and controlled == "displacement" and depth > 0:
            extra = size * cuts.extra_compliance[self.vertex]
            out *= max(0.0, 1.0 - extra / depth)
        base = out[lip_vertices]
        if field is not None:
            out[on] += size * field[region_of_on]
            base = base + size * field[copies]
        self.rendered_lips = (base, lip_vertices)

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, triangles) to render with the cuts open (read only): the model's
        surface vertices, then the lip copies, the triangles re-indexed so each lip uses
        its own vertices; the model's surface while nothing is open."""
        m = self.model
        if self.cuts.patch is None:
            return readonly(m.vertices), readonly(m.triangles)
        _, _, _, duplicated = self.lips.surface_layout()
        vertices = np.vstack([m.vertices, m.vertices[duplicated]])
        return readonly(vertices), readonly(self.lips.surface_triangles())


def _surface_region(model) -> np.ndarray:
    """Each surface vertex's node in the cut region (region-local), or -1 (read only)."""
    canonical = np.asarray(model.artifact["cutting"]["nodes"])
    surface_nodes = np.asarray(model.artifact["surface"]["nodes"])
    local = {int(n): i for i, n in enumerate(canonical)}
    region = np.array([local.get(int(n), -1) for n in surface_nodes], dtype=np.int64)
    return readonly(region)


def _thickness(coordinates: np.ndarray) -> float:
    """A rough local thickness: the region's extent along its mean surface normal."""
    centred = coordinates - coordinates.mean(axis=0)
    n = np.linalg.svd(centred, full_matrices=False)[2][-1]
    return float(np.ptp(centred @ n))
