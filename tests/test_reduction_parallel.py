"""The POD of a campaign on 1 and on 2 ranks gives the same eigenvalues and bases.

Run under ``mpirun -n 2``. The campaign is solved once (serially, by rank 0);
its reduction is done on both ranks together and on rank 0 alone.

Accuracy note: the method of snapshots squares the singular values, so an
eigenvalue lambda_i is reproducible only to about eps * lambda_1 in absolute
terms; 1e-10 relative holds for lambda_i >= 1e-5 lambda_1 (the rest of the
kept ones, down to the 1e-8 cut, to about 1e-8). The SVD method is accurate to
rounding for every kept eigenvalue.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import campaign_toml
from mpi4py import MPI

from hapticrom.offline.campaign import CampaignConfig, run_campaign
from hapticrom.offline.pod import principal_angles
from hapticrom.offline.reduction import reduce_campaign

pytestmark = pytest.mark.mpi


@pytest.mark.parametrize("method", ["snapshots", "svd"])
def test_reduction_on_two_ranks_equals_one(mesh_dir, tmp_path_factory, method):
    comm = MPI.COMM_WORLD
    if comm.size < 2:
        pytest.skip("run under mpirun -n 2")
    root = Path(comm.bcast(str(tmp_path_factory.mktemp("red")) if comm.rank == 0 else None))
    if comm.rank == 0:
        text = campaign_toml(mesh_dir / "cornea-coarse.msh", rings=2, per_ring=4)
        (root / "c.toml").write_text(text + f'\n[pod]\nmethod = "{method}"\n')
        config = CampaignConfig.from_toml(root / "c.toml")
        run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
        reduce_campaign(root / "store", root / "serial.h5", MPI.COMM_SELF, verbose=False)
    comm.barrier()
    reduce_campaign(root / "store", root / "parallel.h5", comm, verbose=False)
    if comm.rank != 0:
        return
    with h5py.File(root / "serial.h5") as s, h5py.File(root / "parallel.h5") as p:
        groups = ["global"] + [f"positions/{i}" for i in s["positions/index"][()]]
        for g in groups:
            lam_s, lam_p = s[f"{g}/eigenvalues"][()], p[f"{g}/eigenvalues"][()]
            A_s, A_p = s[f"{g}/basis"][()], p[f"{g}/basis"][()]
            n = A_s.shape[1]
            assert A_p.shape[1] == n, g
            exact = lam_s[:n] >= (1e-5 * lam_s[0] if method == "snapshots" else 0)
            rel = np.abs(lam_p[:n] - lam_s[:n]) / lam_s[:n]
            assert rel[exact].max() <= 1e-10, (g, rel)
            assert rel.max() <= 1e-7, (g, rel)
            # Symmetric tool positions give repeated eigenvalues, whose eigenvectors are
            # any basis of their eigenspace: compare subspaces that end at a gap.
            lead = exact.sum()
            gaps = np.flatnonzero(lam_s[: lead - 1] > (1 + 1e-3) * lam_s[1:lead]) + 1
            k = gaps.max() if gaps.size else lead
            assert principal_angles(A_p[:, :k], A_s[:, :k]).max() < 1e-6, g
            K_s, K_p = s[f"{g}/K_r"][:k, :k], p[f"{g}/K_r"][:k, :k]
            np.testing.assert_allclose(np.linalg.eigvalsh(K_p), np.linalg.eigvalsh(K_s), rtol=1e-6)
            if np.all(lam_s[: lead - 1] > (1 + 1e-3) * lam_s[1:lead]):
                # No repeated eigenvalue: deterministic signs make the columns match.
                np.testing.assert_allclose(A_p[:, :lead], A_s[:, :lead], atol=1e-8, err_msg=g)
