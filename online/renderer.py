"""The rendered surface, and a render thread's consistent view of a stepping simulator.

:func:`surface_of` computes the surface of a state buffer in a thread's own scratch
(:class:`SurfaceWork`): the simulator's ``surface_displacement`` calls it on its own state.
A render thread (60 Hz) that draws while the servo thread steps (1 kHz) uses a
:class:`SurfaceRenderer` (``sim.renderer()``): it copies the simulator's state under a
sequence lock and renders the copy, so a surface is always one step's state, never half of
one step and half of the next, and the servo thread never waits.

The lock: every call of the simulator that writes its state adds 1 to ``sim._sequence``
before and after (a Python int, under the GIL; the kernels between let the GIL go). The
renderer reads the sequence, copies the buffer, reads it again: equal and even, the copy is
whole (the GIL's hand-overs order the memory); otherwise it copies again.
"""

from __future__ import annotations

import time

import numpy as np

from hapticrom.online import kernels, packed_surface, surface_kernels
from hapticrom.shared.errors import InputError, OutputArrayError, SimulatorBusyError

MAX_ATTEMPTS = 10_000  # copies a renderer tries before it gives up (the servo never paused)


class SurfaceWork:
    """The scratch one thread's surfaces are computed in (none of it is shared), and the
    packed arrays a surface reads (:mod:`~hapticrom.online.packed_surface`)."""

    def __init__(self, model, interpolation: str, response: str):
        self.model, self.interpolation, self.response = model, interpolation, response
        n = model.num_modes
        self.coefficients = np.zeros((3, n))  # the neighbours' reduced coordinates
        # The transported field: the neighbours' sum on the chart's grid, (x, y, z, 0) a
        # node; each neighbour's sample and shift, its weighed rotation and coefficients; each
        # charted vertex's cell and bilinear weights (surface_kernels.transported_surface).
        transport = interpolation == "transport"
        nodes = int(np.prod(model.chart.shape)) if transport else 1
        charted = len(model.chart.charted) if transport else 1
        self.chart_grid = np.zeros((nodes, 4), dtype=np.float32)
        self.chart_neighbours = np.zeros((3, 2), dtype=np.int64)
        self.chart_terms = np.zeros((3, surface_kernels.terms_width(n)), dtype=np.float32)
        self.chart_weights = np.zeros((4, charted), dtype=np.float32)
        self.chart_cells = np.zeros(charted, dtype=np.int64)
        uncharted = len(model.chart.uncharted) if transport else 0
        self.uncharted_sum = np.zeros(3 * uncharted)  # their blended field, x, y, z a vertex
        self.frames = np.zeros((5, n, n))  # Grassmann: V cos S, V S^-1 sin S, R_0..R_2
        self.frames_of = -1.0  # the contact (buf[CONTACTS]) the frames are of
        self.scratch = np.zeros(3 + 3 * n)  # (unused) + three n-vectors
        # compliance: the loadable triangle under the contact and the weights there
        self.surface_weights = np.zeros(3)
        self.surface_triangle = 0
        self.located_of = -1.0  # the contact (buf[CONTACTS]) they are of
        self.chart_halo = np.array([model.chart.halo if transport else 0], dtype=np.int64)
        # Every array a surface reads, packed once (kept alive here: the addresses point
        # into them), and the one call that renders from them (None: Grassmann, and the
        # compliance surface, whose location is kept per contact: surface_of's own path).
        packed = interpolation in ("transport", "podi", "compliance")
        self.arrays = (
            packed_surface.surface_arrays(model, interpolation, response, self) if packed else {}
        )
        self.addresses, self.dims = packed_surface.pack(self.arrays, response)
        self.entry = packed_surface.ENTRIES.get((interpolation, response))

    def __reduce__(self):
        """A copy (copy, deepcopy, pickle) is made afresh: copied, the packed addresses would
        still point into this object's arrays, and render into them after it is gone."""
        return SurfaceWork, (self.model, self.interpolation, self.response)


def surface_of(buf, work: SurfaceWork, out) -> None:
    """The surface displacement (V, 3) mm of the state ``buf`` into ``out`` (no cuts) for
    ``work``'s model, interpolation and response: transported and PODI surfaces in one call
    on its packed arrays, the others here."""
    entry = work.entry
    if entry is not None:
        entry(work.addresses, work.dims, buf, out)
        return
    m, c = work.model, work.coefficients
    interpolation, response = work.interpolation, work.response
    if response == "anm":
        a = m.anm
        surface_kernels.anm_coefficients(buf, a["offsets"], a["coefficients"], c)
    elif interpolation != "grassmann":
        surface_kernels.curves_coefficients(buf, m.coefficients, c)
    if interpolation == "grassmann":
        g = m.grassmann
        contacts = float(buf[kernels.CONTACTS])
        if work.frames_of != contacts:  # prepared once per contact
            kernels.prepare_grassmann(buf, g["gtt"], g["gtb"], g["grb"], work.frames)
            work.frames_of = contacts
        kernels.surface_grassmann(
            buf, g["reference"], m.surface_basis_t, g["tangents_t"], work.frames,
            m.coefficients, work.scratch, out,
        )  # fmt: skip
    else:
        surface_kernels.blended_surface(buf, c, m.surface_basis_t, out)
    if interpolation == "compliance":
        f = m.contact_fields
        contacts = float(buf[kernels.CONTACTS])
        if work.located_of != contacts:  # located once per contact
            work.surface_triangle = surface_kernels.locate_on_surface(
                buf, m.sample_points, m.sample_normals, m.vertices, f["triangles"], f["grid"],
                f["grid_starts"], f["grid_ids"], work.surface_weights,
            )  # fmt: skip
            work.located_of = contacts
        surface_kernels.add_linear_dent(
            buf, work.surface_triangle, work.surface_weights, f["fields"], f["triangle_rows"],
            f["sample_rows"], out,
        )  # fmt: skip


def check_surface_out(model, out) -> None:
    """OutputArrayError unless ``out`` is a C-contiguous float64 (V, 3) array."""
    shape = model.vertices.shape
    if (
        not isinstance(out, np.ndarray)
        or out.shape != shape
        or out.dtype != np.float64
        or not out.flags.c_contiguous
        or not out.flags.writeable
    ):
        raise OutputArrayError(
            f"out must be a writeable, C-contiguous float64 array of shape {shape}, got "
            f"{getattr(out, 'dtype', type(out).__name__)} {np.shape(out)}"
        )


class SurfaceRenderer:
    """A render thread's view of ``simulator``: :meth:`surface` renders the state of one
    whole step while the servo thread goes on stepping. One renderer per render thread;
    its calls on two threads at once raise SimulatorBusyError. Cuts are not drawn here yet
    (InputError once the simulator has a scalpel: render on the servo thread then)."""

    def __init__(self, simulator):
        self.simulator = simulator
        self._buf = np.zeros_like(simulator._buf)  # the copy a surface is rendered from
        self._work = SurfaceWork(simulator.model, simulator.interpolation, simulator.response)
        self.sequence = 0  # the simulator's writing calls before the last rendered state
        self._inside = False  # a flag, not a lock (see Simulator)

    def surface(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` (V, 3) float64 with the surface displacement (mm) of the simulator's
        last whole step; ``sequence`` says which (its writing calls before it)."""
        sim = self.simulator
        check_surface_out(sim.model, out)
        if sim.cutting is not None:
            raise InputError(
                "SurfaceRenderer does not draw cuts yet: render with sim.surface_displacement "
                "on the servo thread"
            )
        if self._inside:
            raise SimulatorBusyError("SurfaceRenderer.surface: another thread is inside it")
        self._inside = True
        try:
            self._copy_state()
            surface_of(self._buf, self._work, out)
        finally:
            self._inside = False
        return out

    def _copy_state(self) -> None:
        """The simulator's state buffer into ours, whole (module docstring)."""
        sim = self.simulator
        for _ in range(MAX_ATTEMPTS):
            before = sim._sequence
            if before % 2 == 0:
                np.copyto(self._buf, sim._buf)
                if sim._sequence == before:
                    self.sequence = before // 2
                    return
            # The servo thread is inside a kernel: let the GIL go, or it would wait for the
            # interpreter's switch interval (5 ms) to come back from it.
            time.sleep(0)
        raise SimulatorBusyError(
            f"SurfaceRenderer.surface: the servo thread kept writing during {MAX_ATTEMPTS} "
            "copies of its state; try again"
        )
