"""Cutting (thesis ch. 4): the reduced model coupled with a finite-element patch.

- :mod:`.patch` -- reduced model + superimposed patch around a cut (offline reference).
- :mod:`.element_matrices` -- element stiffness matrices for the runtime's cut patch.
- :mod:`.export` -- the artifact's cuttable region.
"""
