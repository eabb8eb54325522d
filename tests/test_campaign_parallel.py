"""The stored campaign does not depend on the number of ranks N or ranks per solve K.

Run under ``mpirun -n 2``: the same campaign with (N=2, K=1) and (N=2, K=2), and
serially on MPI.COMM_SELF by rank 0, must store the same data.
"""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
from hapticrom.offline.campaign.store import SnapshotStore

pytestmark = pytest.mark.mpi


def test_stored_data_independent_of_ranks(mesh_dir, tmp_path_factory):
    comm = MPI.COMM_WORLD
    if comm.size < 2:
        pytest.skip("run under mpirun -n 2")
    root = comm.bcast(str(tmp_path_factory.mktemp("campaign")) if comm.rank == 0 else None)
    from pathlib import Path

    root = Path(root)
    if comm.rank == 0:
        (root / "c.toml").write_text(
            f"""
[mesh]
file = "{mesh_dir / "cornea-coarse.msh"}"
[material]
law = "hgo"
[load]
mode = "force"
magnitude = 0.004
contact_radius = 1.0
steps = 3
[positions]
[[positions.farthest]]
n = 4
centre = [0.0, 0.0, 0.0]
radius = 3.0
"""
        )
    comm.barrier()
    config = CampaignConfig.from_toml(root / "c.toml")
    run_campaign(config, root / "k1", comm, ranks_per_solve=1, verbose=False)
    run_campaign(config, root / "k2", comm, ranks_per_solve=2, verbose=False)
    if comm.rank == 0:
        run_campaign(config, root / "serial", MPI.COMM_SELF, verbose=False)
    comm.barrier()
    if comm.rank != 0:
        return
    serial = SnapshotStore(root / "serial")
    indices = serial.completed()
    assert len(indices) == 4
    for name in ("k1", "k2"):
        other = SnapshotStore(root / name)
        assert other.completed() == indices
        ops, _ = other.read_operators()
        ref_ops, _ = serial.read_operators()
        for key in ref_ops:
            scale = np.abs(ref_ops[key]).max()
            np.testing.assert_allclose(
                ops[key], ref_ops[key], rtol=0, atol=1e-13 * scale, err_msg=key
            )
        for i in indices:
            mine, _ = other.read_position(i)
            ref, _ = serial.read_position(i)
            assert mine.keys() == ref.keys()
            for key in ref:
                scale = np.abs(ref[key]).max() or 1.0
                np.testing.assert_allclose(
                    mine[key], ref[key], rtol=0, atol=1e-10 * scale, err_msg=f"{name} {i} {key}"
                )
