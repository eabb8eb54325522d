"""The offline trainer: full-order hyperelastic solves with DOLFINx and PETSc.

Needs the ``offline`` extra (``pip install 'hapticrom[offline]'``). The folders follow the
pipeline (README, "Architecture"):

- :mod:`~hapticrom.offline.config` -- TOML configuration of a solve (pure Python).
- :mod:`~hapticrom.offline.tables` -- the one validator of every TOML table (pydantic models).
- :mod:`~hapticrom.offline.check` -- ``hapticrom check CONFIG``; the JSON Schemas (``schemas/``).
- :mod:`~hapticrom.offline.fe` -- the full-order model: laws, organ, formulation, contact, solver.
- :mod:`~hapticrom.offline.campaign` -- tool positions, the snapshot store, the campaign loop.
- :mod:`~hapticrom.offline.reduce` -- POD, POD-ANM and the reductor that writes the artifact.
- :mod:`~hapticrom.offline.cutting` -- the cut patch and the artifact's cuttable region.
- :mod:`~hapticrom.offline.accuracy` -- the held-out check (``hapticrom accuracy``).
- :mod:`~hapticrom.offline.studies` -- studies of the thesis' figures (``hapticrom anm``).
- :mod:`~hapticrom.offline.mpi`, :mod:`~hapticrom.offline.progress` -- rank-0 helpers.
"""

# Import order matters with the PyPI wheels:
# - h5py before dolfinx/petsc4py: h5py's own HDF5 library fails to initialise
#   ("Not a datatype") once PETSc's HDF5 is loaded, while the other way round
#   both work (XDMF output checked, serial and parallel);
# - mpi4py before dolfinx/petsc4py: it loads libmpi, which PETSc needs.
import h5py  # noqa: F401, E402

try:
    from mpi4py import MPI as _MPI  # noqa: F401
except ImportError:  # the offline extra is missing: require_offline() says so
    pass

OFFLINE_EXTRA_HINT = (
    "this command needs the offline trainer stack (DOLFINx, PETSc, gmsh): "
    "pip install 'hapticrom[offline]' (Python >= 3.12)"
)


def require_offline() -> None:
    """Raise a clear ImportError when the offline extra is not installed."""
    import importlib.util

    def absent(module: str) -> bool:
        try:
            return importlib.util.find_spec(module) is None
        except ImportError:
            return True

    missing = [m for m in ("dolfinx", "petsc4py", "mpi4py", "gmsh") if absent(m)]
    if missing:
        raise ImportError(f"{OFFLINE_EXTRA_HINT} (missing: {', '.join(missing)})")
