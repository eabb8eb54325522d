"""From snapshots to the reduced model (thesis ch. 2-3).

- :mod:`.pod` -- proper orthogonal decomposition of a row-distributed snapshot matrix.
- :mod:`.anm` -- the Asymptotic Numerical Method in a reduced space.
- :mod:`.reduction` -- the reductor: a campaign's snapshots to the artifact, step by step:
- :mod:`.inputs` -- what it reads: the configuration, the samples, the operators' rows;
- :mod:`.operators` -- the projected operators, per sample and global;
- :mod:`.anm_reduction` -- POD-ANM series of every campaign sample;
- :mod:`.interpolation` -- the chart, Grassmann tangents, the common depth grid;
- :mod:`.assemble` -- the one place the artifact's groups are assembled.
"""
