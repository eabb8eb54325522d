"""hapticrom: haptic-rate reaction forces of hyperelastic soft tissue by model order reduction.

Subpackages:

- :mod:`hapticrom.offline` -- the MPI-parallel trainer (DOLFINx, PETSc, SLEPc); needs
  the ``offline`` extra.
- :mod:`hapticrom.online` -- the runtime a simulator embeds (numpy, numba, h5py).
- :mod:`hapticrom.shared` -- what both agree on (errors, units, artifact schema).
- :mod:`hapticrom.meshes` -- gmsh generators of the organ meshes (needs ``offline``).

Units everywhere: mm, N, MPa.
"""

__version__ = "0.1.0"
