"""Distributed solves equal serial ones to solver tolerance (run under mpirun -n 2).

Each rank also solves the whole problem alone on MPI.COMM_SELF; the
distributed answer (all ranks cooperating on one DOLFINx mesh) must match.
"""

from __future__ import annotations

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.fullorder import FullOrderModel

pytestmark = pytest.mark.mpi


def l2_norm(u: fem.Function) -> float:
    """sqrt(int |u|^2 dX) (mm^2.5), summed over the ranks of u's mesh."""
    local = fem.assemble_scalar(fem.form(ufl.inner(u, u) * ufl.dx))
    return float(np.sqrt(u.function_space.mesh.comm.allreduce(local, op=MPI.SUM)))


CASES = {
    "cornea-hgo-Q1P0": (
        "cornea-coarse",
        {"law": "hgo"},
        {"mode": "displacement", "displacement": [0.0, 0.0, -0.4], "contact_radius": 0.8},
    ),
    "liver-neo-hookean-P2P0": (
        "liver-coarse",
        {"law": "neo-hookean", "E": 0.16, "nu": 0.48},
        {"mode": "force", "force": [0.0, 1.2, 0.0], "contact_radius": 10.0},
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_distributed_solve_equals_serial_solve(mesh_dir, case):
    comm = MPI.COMM_WORLD
    if comm.size < 2:
        pytest.skip("run under mpirun -n 2")
    mesh, material, load = CASES[case]
    config = ProblemConfig.from_dict(
        {
            "mesh": {"file": str(mesh_dir / f"{mesh}.msh")},
            "material": material,
            "load": {**load, "steps": 3},
        }
    )
    assert_distributed_equals_serial(config)


# Further tools (issue 18's references): a second force tool beside the first, and a
# force tool pressing beside one that holds its patch in place (grasping forceps)
FURTHER = {
    "two-forces": ({"mode": "force", "force": [0.0, 0.0, -0.01]}, (0.0, 0.0, -0.006)),
    "held-and-pressed": (
        {"mode": "displacement", "displacement": [0.0, 0.0, 0.0]},
        (0.0, 0.0, -0.01),
    ),  # fmt: skip
}


@pytest.mark.parametrize("case", list(FURTHER))
def test_further_tools_distributed_equal_serial(mesh_dir, case):
    from dataclasses import replace

    if MPI.COMM_WORLD.size < 2:
        pytest.skip("run under mpirun -n 2")
    from hapticrom.offline.fe.dofs import CanonicalOrder

    first, force = FURTHER[case]
    config = ProblemConfig.from_dict({
        "mesh": {"file": str(mesh_dir / "cornea-coarse.msh")},
        "material": {"law": "hgo"},
        "load": {**first, "contact_point": [0.0, 0.0, 0.0], "contact_radius": 0.5, "steps": 3},
    })  # fmt: skip
    tools = (((1.0, 0.5, 0.0), force),)  # on the loadable cap, 1.12 mm away: disks apart
    models = assert_distributed_equals_serial(
        replace(config, load=replace(config.load, tools=tools))
    )
    # the whole field, gathered in canonical order, and the further tool's share of it
    fields = [CanonicalOrder(m.model.V).gather(m.model.u.x.array) for m in models]
    alone = FullOrderModel(config, comm=MPI.COMM_SELF, verbose=False)
    alone.solve()
    without = CanonicalOrder(alone.model.V).gather(alone.model.u.x.array)
    if MPI.COMM_WORLD.rank == 0:
        distributed, serial = fields
        assert np.linalg.norm(distributed - serial) <= 1e-9 * np.linalg.norm(serial)
        assert np.linalg.norm(serial - without) > 0.1 * np.linalg.norm(serial)


def assert_distributed_equals_serial(config) -> tuple:
    """``config`` solved on COMM_WORLD and on COMM_SELF: forces, contact displacements and
    the field's L2 norm equal to 1e-9, every rank agreeing; the two models."""
    comm = MPI.COMM_WORLD
    distributed_model = FullOrderModel(config, comm=comm, verbose=False)
    assert distributed_model.model.V.dofmap.index_map.size_local < (
        distributed_model.model.V.dofmap.index_map.size_global
    ), "the mesh should be split over the ranks"
    distributed = distributed_model.solve()
    serial_model = FullOrderModel(config, comm=MPI.COMM_SELF, verbose=False)
    serial = serial_model.solve()

    assert len(distributed.records) == len(serial.records) == 3
    scale = np.abs(serial.force).max()
    np.testing.assert_allclose(distributed.force, serial.force, rtol=0, atol=1e-9 * scale)
    dscale = np.abs(serial.displacement).max()
    np.testing.assert_allclose(distributed.displacement, serial.displacement, atol=1e-9 * dscale)
    assert l2_norm(distributed_model.model.u) == pytest.approx(
        l2_norm(serial_model.model.u), rel=1e-9
    )
    # Every rank agrees on the distributed answer.
    gathered = comm.allgather(distributed.force)
    assert all(np.array_equal(g, gathered[0]) for g in gathered)
    return distributed_model, serial_model
