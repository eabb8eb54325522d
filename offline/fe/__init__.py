"""The full-order finite-element model (DOLFINx, PETSc; mm, N, MPa).

- :mod:`.materials` -- material laws as UFL strain energies (SVK, neo-Hookean, HGO).
- :mod:`.organ` -- an organ mesh with its surface groups, supports, fibres.
- :mod:`.formulation` -- finite-element spaces, the (mixed) energy, residuals.
- :mod:`.contact` -- the tool's contact patch, reaction force, patch displacement.
- :mod:`.solver` -- PETSc SNES plumbing and incremental loading with step cutting.
- :mod:`.fullorder` -- the full-order model: all of the above for one problem.
- :mod:`.sanity` -- physics sanity of a load path (inversion, softening, jumps).
- :mod:`.dofs` -- a DOF numbering that does not depend on the partition.
- :mod:`.operators` -- the reference tangent, mass and load operators in that numbering.
- :mod:`.output` -- curve.csv and XDMF fields for ParaView.
"""
