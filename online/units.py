"""The simulator in SI units, for hosts that work in metres (CHAI3D, most game engines).

The runtime works in mm and N throughout (the artifact, the kernels, the errors).
:class:`SIUnits` wraps a simulator so that a host speaks metres, newtons and N/m::

    sim = SIUnits(model.simulator())
    force = sim.step_position(tip_m)          # m in, N out
    sim.stiffness(K)                          # N/m
    sim.surface_displacement(u)               # m

Conversions go through buffers of the wrapper: nothing is allocated per call, and the
arrays returned (read only) are reused by the next call, as the simulator's are. Forces
are N either way. Everything else (errors, threads, limits, which stay in mm and N) is the
simulator's.
"""

from __future__ import annotations

import numpy as np

from hapticrom.online.scalpel import readonly

MM_PER_M = 1e3


class SIUnits:
    """``simulator`` with positions and displacements in m and stiffness in N/m."""

    def __init__(self, simulator):
        self.simulator = simulator
        self._input = np.zeros(3)  # a position or displacement, in mm
        self._displacement = np.zeros(3)  # step_force's output, in m
        self._displacement_out = readonly(self._displacement)
        self._stiffness = np.zeros((3, 3))  # N/mm

    def _mm(self, value) -> np.ndarray:
        """``value`` (m) in mm, in the wrapper's buffer (refused as the simulator would)."""
        if type(value) is not np.ndarray:  # the slower path (a list, a tuple)
            try:
                value = np.asarray(value)
            except (TypeError, ValueError):
                return value  # the simulator refuses it with its own error, naming it
        if value.shape != (3,) or value.dtype.kind not in "iuf":
            return value  # (no broadcasting of a scalar or a (1,) array): refused there
        np.multiply(value, MM_PER_M, out=self._input)
        return self._input

    def step_position(self, tip) -> np.ndarray:
        """Tool tip centre (m) -> reaction force on the tool (N)."""
        return self.simulator.step_position(self._mm(tip))

    def set_contact(self, point) -> None:
        """The contact point (m)."""
        self.simulator.set_contact(self._mm(point))

    def step_displacement(self, d) -> np.ndarray:
        """Tool displacement from the contact (m) -> reaction force on the tool (N)."""
        return self.simulator.step_displacement(self._mm(d))

    def step_force(self, f) -> np.ndarray:
        """Force on the tissue (N) -> tool displacement (m)."""
        np.divide(self.simulator.step_force(f), MM_PER_M, out=self._displacement)
        return self._displacement_out

    def stiffness(self, out: np.ndarray) -> np.ndarray:
        """The 3x3 contact stiffness (N/m) into ``out`` (C-contiguous float64 (3, 3))."""
        self.simulator.stiffness(self._stiffness)
        np.multiply(self._stiffness, MM_PER_M, out=out)
        return out

    def surface_displacement(self, out: np.ndarray) -> np.ndarray:
        """The surface vertices' displacement (m) into ``out`` (V, 3) float64."""
        self.simulator.surface_displacement(out)
        out /= MM_PER_M
        return out

    @property
    def depth(self) -> float:
        """Current indentation depth (m)."""
        return self.simulator.depth / MM_PER_M

    @property
    def proxy(self) -> np.ndarray:
        """The proxy (m; a new array)."""
        return self.simulator.proxy / MM_PER_M

    @property
    def contact_point(self) -> np.ndarray:
        """Where the tool touches the undeformed surface (m; a new array)."""
        return self.simulator.contact_point / MM_PER_M

    @property
    def tool_radius(self) -> float:
        """The tool tip's radius (m)."""
        return self.simulator.tool_radius / MM_PER_M

    @property
    def contact_normal(self) -> np.ndarray:
        """Outward unit normal at the contact (no unit)."""
        return self.simulator.contact_normal

    @property
    def in_contact(self) -> bool:
        """Whether the tool pressed the tissue at the last step."""
        return self.simulator.in_contact
