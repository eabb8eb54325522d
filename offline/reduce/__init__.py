"""From snapshots to the reduced model (thesis ch. 2-3).

- :mod:`.pod` -- proper orthogonal decomposition of a row-distributed snapshot matrix.
- :mod:`.anm` -- the Asymptotic Numerical Method in a reduced space.
- :mod:`.anm_reduction` -- POD-ANM series of every campaign sample.
- :mod:`.reduction` -- the reductor: a campaign's snapshots to the artifact.
"""
