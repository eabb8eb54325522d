"""The online haptic runtime: loads a reduced model artifact and steps it at haptic rate.

Imports only numpy, numba and h5py (never the offline finite-element stack), so a
simulator can ``pip install hapticrom`` alone. The artifact loader and the numba
kernels arrive with the artifact issue; this package is the runtime's home.
"""
