"""The online haptic runtime: load a reduced-model artifact and step it at haptic rate.

Imports only numpy, numba and h5py (never the offline finite-element stack), so a
simulator can ``pip install hapticrom`` alone::

    import numpy as np
    import hapticrom.online

    model = hapticrom.online.load("cornea.h5")     # verifies the artifact, warms the kernels
    sim = model.simulator()                       # or simulator("grassmann")
    sim.set_contact(np.array([0.0, 0.0, 0.0]))    # mm, on the surface
    d = np.array([0.0, 0.0, -0.3])                # tool displacement, mm
    force = sim.step_displacement(d)              # reaction force on the tool, N

Units: mm, N. See :mod:`hapticrom.online.simulator` for the contact model.
"""

from hapticrom.online.model import ReducedModel, load
from hapticrom.shared.artifact import ArtifactError

__all__ = ["ArtifactError", "ReducedModel", "load"]
