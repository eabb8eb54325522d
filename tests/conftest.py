"""Test set-up: caches inside the project, serial/mpi markers, coarse meshes.

`make test` runs ``pytest -m "not mpi"`` serially and ``mpirun -n 2 pytest -m mpi``.
Tests marked ``serial`` are skipped when more than one rank runs them.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# Before anything imports dolfinx/numba/gmsh: compiled kernels go to a
# persistent cache in the project, never under $HOME.
os.environ.setdefault("XDG_CACHE_HOME", str(ROOT / ".cache"))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))
os.environ.setdefault("MPLCONFIGDIR", str(ROOT / ".cache" / "matplotlib"))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import h5py  # noqa: E402, F401 - before dolfinx: see hapticrom/offline/__init__.py

try:  # libmpi must be loaded before test modules import dolfinx
    from mpi4py import MPI  # noqa: F401
except ImportError:
    pass

if os.environ.get("PYTEST_XDIST_WORKER"):  # `make test` runs two workers on one JIT cache
    try:
        import dolfinx.jit

        # A worker that finds a form being compiled by the other waits for it: up to 10 min
        # (DOLFINx's 10 s is shorter than compiling the larger forms on a busy machine).
        _, doc = dolfinx.jit.DOLFINX_DEFAULT_JIT_OPTIONS["timeout"]
        dolfinx.jit.DOLFINX_DEFAULT_JIT_OPTIONS["timeout"] = (600, doc)
    except ImportError:  # the runtime-only install: no JIT
        pass


def _comm_size() -> int:
    for var in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "PMIX_SIZE"):
        if var in os.environ:
            return int(os.environ[var])
    return 1


def pytest_collection_modifyitems(config, items):
    if _comm_size() > 1:
        skip = pytest.mark.skip(reason="serial test: skipped under mpirun")
        for item in items:
            if "serial" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="session")
def mesh_dir() -> Path:
    """Coarse test meshes, generated afresh by rank 0 in every session (a second or two);
    one directory per pytest-xdist worker (``make test`` runs two)."""
    d = ROOT / ".cache" / "test-meshes" / os.environ.get("PYTEST_XDIST_WORKER", "main")
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        from hapticrom.meshes import generate

        d.mkdir(parents=True, exist_ok=True)
        for name in ("cornea", "beam", "hemisphere", "liver"):
            generate(name, d / f"{name}-coarse.msh", refinement="coarse")
    comm.barrier()
    return d


def campaign_toml(mesh: Path, steps: int = 4, rings: int = 1, per_ring: int = 4) -> str:
    return f"""
[campaign]
name = "test"
[mesh]
file = "{mesh}"
[material]
law = "hgo"
[load]
mode = "displacement"
magnitude = 0.3
contact_radius = 0.6
steps = {steps}
[positions]
points = [[0.0, 0.0, 0.0]]
[[positions.polar]]
centre = [0.0, 0.0, 0.0]
radius = 2.0
rings = {rings}
per_ring = {per_ring}
include_centre = false
"""


@pytest.fixture(scope="session")
def small_campaign(mesh_dir, tmp_path_factory):
    """A 5-position, 4-step HGO indentation campaign on the coarse cornea (serial)."""
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.campaign.store import SnapshotStore

    root = tmp_path_factory.mktemp("campaign")
    path = root / "campaign.toml"
    path.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh"))
    config = CampaignConfig.from_toml(path)
    report = run_campaign(config, root / "store", verbose=False)
    return config, SnapshotStore(root / "store"), report


@pytest.fixture(scope="session")
def small_artifact(small_campaign, tmp_path_factory) -> Path:
    """The reduced-model artifact of ``small_campaign`` (serial)."""
    from mpi4py import MPI

    from hapticrom.offline.reduce.reduction import reduce_campaign

    _, store, _ = small_campaign
    out = tmp_path_factory.mktemp("artifact") / "small.h5"
    reduce_campaign(store.root, out, MPI.COMM_SELF, verbose=False)
    return out


FORCE_CAMPAIGN = """
[campaign]
name = "{name}"
[mesh]
file = "{mesh}"
[material]
law = "hgo"
[load]
mode = "force"
magnitude = 0.03
direction = "normal"
contact_radius = 0.6
steps = 4
[positions]
points = {points}
"""
FORCE_TRAINING = [[0.0, 0.0, 0.0]] + [[2.8 * np.cos(a), 2.8 * np.sin(a), 0.0] for a in
                                      np.arange(4) * np.pi / 2 + np.pi / 4]  # fmt: skip
FORCE_HELD_OUT = [[1.3, 0.4, 0.0], [-0.5, -1.3, 0.0]]  # inside two of its sample triangles


def _force_campaign(mesh_dir, root: Path, name: str, points) -> tuple:
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.campaign.store import SnapshotStore

    path = root / f"{name}.toml"
    points = np.round(np.asarray(points, dtype=float), 6).tolist()
    text = FORCE_CAMPAIGN.format(name=name, mesh=mesh_dir / "cornea-coarse.msh", points=points)
    path.write_text(text)
    config = CampaignConfig.from_toml(path)
    run_campaign(config, root / name, verbose=False)
    return config, SnapshotStore(root / name)


@pytest.fixture(scope="session")
def force_campaign(mesh_dir, tmp_path_factory):
    """A force-controlled HGO campaign on the coarse cornea (the centre and a ring of 4),
    and 2 held-out positions solved alike: (config, store, held-out store)."""
    root = tmp_path_factory.mktemp("force-campaign")
    config, store = _force_campaign(mesh_dir, root, "training", FORCE_TRAINING)
    _, held_out = _force_campaign(mesh_dir, root, "held-out", FORCE_HELD_OUT)
    return config, store, held_out


@pytest.fixture(scope="session")
def force_artifact(force_campaign, tmp_path_factory) -> Path:
    """The artifact of ``force_campaign`` (with the tool's stiffness lattice, format 2.1)."""
    from mpi4py import MPI

    from hapticrom.offline.reduce.reduction import reduce_campaign

    out = tmp_path_factory.mktemp("force-artifact") / "force.h5"
    reduce_campaign(force_campaign[1].root, out, MPI.COMM_SELF, verbose=False)
    return out


def reseed(generator: np.random.Generator, name: str) -> None:
    """Restart a generator from a seed of ``name``: a test (or a module fixture) draws the
    same numbers whatever ran before it (pytest-xdist changes the order)."""
    seeded = np.random.default_rng(zlib.crc32(name.encode()))
    generator.bit_generator.state = seeded.bit_generator.state


@pytest.fixture(autouse=True)
def _reseed_module_generator(request):
    """A test module's ``RNG`` restarted from the test's id before each test."""
    generator = getattr(request.module, "RNG", None)
    if isinstance(generator, np.random.Generator):
        reseed(generator, request.node.nodeid)
