"""The online haptic runtime: load a reduced-model artifact and step it at haptic rate.

Imports only numpy, numba and h5py (never the offline finite-element stack), so a
simulator can ``pip install hapticrom`` alone::

    import numpy as np
    import hapticrom.online

    model = hapticrom.online.load("cornea.h5")     # verifies the artifact, warms the kernels
    sim = model.simulator()                       # or simulator("grassmann")
    force = sim.step_position(np.array([0.0, 0.0, 0.3]))  # tool tip centre (mm) -> N
    sim.set_contact(np.array([0.0, 0.0, 0.0]))    # or: a contact point (mm, on the surface)
    d = np.array([0.0, 0.0, -0.3])                # and the tool displacement from it, mm
    force = sim.step_displacement(d)              # reaction force on the tool, N

Units: mm, N. See :mod:`hapticrom.online.simulator` for the contact model. Every error
the runtime raises while it runs is a :class:`SimulatorError` (a ``HapticromError``);
a damaged artifact is an :class:`ArtifactError`.

Modules: :mod:`~hapticrom.online.model` (the loaded artifact), :mod:`~hapticrom.online.simulator`
(the servo loop's object), :mod:`~hapticrom.online.kernels` (the numba kernels and the state
buffer's layout), :mod:`~hapticrom.online.proxy` (``step_position``: the tool tip against
the surface), the rendered surface (:mod:`~hapticrom.online.renderer`,
:mod:`~hapticrom.online.packed_surface`: one call on packed arrays, the bodies the C ABI's
:mod:`~hapticrom.online.cabi` runs too; :mod:`~hapticrom.online.surface_kernels`,
:mod:`~hapticrom.online.surface_chart`, :mod:`~hapticrom.online.node_blocks`),
:mod:`~hapticrom.online.scalpel` (the simulator's cutting controller),
:mod:`~hapticrom.online.cutting`, :mod:`~hapticrom.online.coupled_patch`,
:mod:`~hapticrom.online.tool_load`, :mod:`~hapticrom.online.cut_render`,
:mod:`~hapticrom.online.cut_worker` (the cuts), :mod:`~hapticrom.online.latency`,
:mod:`~hapticrom.online.play`, :mod:`~hapticrom.online.reference` (benchmarks, a scripted
tool path, the plain-numpy reference), :mod:`~hapticrom.online.jit_cache` (numba's cache
kept in step with the sources). Hyper-reduced physics solved online (issue 18; the
artifact's ``hyperreduced`` group, ``model.physics()``): :mod:`~hapticrom.online.physics`
(a region under pressing tools and holders), :mod:`~hapticrom.online.material_kernels`,
:mod:`~hapticrom.online.element_kernels`, :mod:`~hapticrom.online.hyperreduced` (the
sampled sums), :mod:`~hapticrom.online.haptic_newton` (a step of fixed cost) and
:mod:`~hapticrom.online.dense_solve` (its LU), over :mod:`~hapticrom.online.vector_math`
(exp, expm1, log in vector lanes) and :mod:`~hapticrom.online.vector_tiles` (register tiles
for the tangent's projection).
"""

from hapticrom.online.jit_cache import drop_if_stale

drop_if_stale()  # before any kernel is compiled or loaded from the cache: see jit_cache

from hapticrom.online.model import ReducedModel, load  # noqa: E402
from hapticrom.shared.artifact import ArtifactError  # noqa: E402
from hapticrom.shared.errors import (  # noqa: E402
    NoContactError,
    OutputArrayError,
    ScalpelInputError,
    SimulatorBusyError,
    SimulatorError,
    StepInputError,
)

__all__ = [
    "ArtifactError",
    "NoContactError",
    "OutputArrayError",
    "ReducedModel",
    "ScalpelInputError",
    "SimulatorBusyError",
    "SimulatorError",
    "StepInputError",
    "load",
]
