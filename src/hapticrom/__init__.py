"""hapticrom: haptic-rate reaction forces of hyperelastic soft tissue by model order reduction.

Subpackages:

- :mod:`hapticrom.offline` -- the MPI-parallel trainer (DOLFINx, PETSc, SLEPc); needs
  the ``offline`` extra.
- :mod:`hapticrom.online` -- the runtime a simulator embeds (numpy, numba, h5py).
- :mod:`hapticrom.shared` -- what both agree on (errors, units, artifact schema).
- :mod:`hapticrom.meshes` -- gmsh generators of the organ meshes (needs ``offline``).
- :mod:`hapticrom.cli` -- the ``hapticrom`` command (one module per concern).
- :mod:`hapticrom.report` -- the HTML report (needs the ``report`` extra, not ``offline``).
- :mod:`hapticrom.export` -- ParaView files of a reduced model; :mod:`hapticrom.vtk` writes
  them (numpy only).

Units everywhere: mm, N, MPa.
"""

__version__ = "0.1.0"
