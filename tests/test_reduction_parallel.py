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

import numpy as np
import pytest
from conftest import campaign_toml
from mpi4py import MPI

from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
from hapticrom.offline.reduce.pod import principal_angles
from hapticrom.offline.reduce.reduction import reduce_campaign
from hapticrom.shared.artifact import read_artifact

pytestmark = pytest.mark.mpi


def solved_on_rank_zero(tmp_path_factory, name: str, text: str, serial_reduction=False) -> Path:
    """A campaign (TOML ``text``) solved by rank 0 alone, and reduced there too if asked;
    its directory, on every rank (skips unless run on 2 ranks or more)."""
    comm = MPI.COMM_WORLD
    if comm.size < 2:
        pytest.skip("run under mpirun -n 2")
    root = Path(comm.bcast(str(tmp_path_factory.mktemp(name)) if comm.rank == 0 else None))
    if comm.rank == 0:
        (root / "c.toml").write_text(text)
        config = CampaignConfig.from_toml(root / "c.toml")
        run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
        if serial_reduction:
            reduce_campaign(root / "store", root / "serial.h5", MPI.COMM_SELF, verbose=False)
    comm.barrier()
    return root


@pytest.mark.parametrize("method", ["snapshots", "svd"])
def test_reduction_on_two_ranks_equals_one(mesh_dir, tmp_path_factory, method):
    comm = MPI.COMM_WORLD
    text = campaign_toml(mesh_dir / "cornea-coarse.msh", rings=2, per_ring=4)
    text += f'\n[pod]\nmethod = "{method}"\n'
    root = solved_on_rank_zero(tmp_path_factory, "red", text, serial_reduction=True)
    reduce_campaign(root / "store", root / "parallel.h5", comm, verbose=False)
    if comm.rank != 0:
        return
    s, p = read_artifact(root / "serial.h5"), read_artifact(root / "parallel.h5")
    np.testing.assert_allclose(p["samples"]["force"], s["samples"]["force"], rtol=1e-12)
    spectra = [("global", s["global"]["eigenvalues"], p["global"]["eigenvalues"])]
    spectra += [
        (f"sample {i}", s["samples"]["eigenvalues"][i], p["samples"]["eigenvalues"][i])
        for i in range(len(s["samples"]["points"]))
    ]
    for name, lam_s, lam_p in spectra:
        kept = lam_s >= 1e-8 * lam_s[0]
        exact = lam_s >= (1e-5 * lam_s[0] if method == "snapshots" else 1e-8 * lam_s[0])
        rel = np.abs(lam_p - lam_s) / np.where(kept, lam_s, 1.0)
        assert rel[exact].max() <= 1e-10, (name, rel)
        assert rel[kept].max() <= 1e-7, (name, rel)
    S, P = s["samples"], p["samples"]
    for i in range(len(S["points"])):
        assert (
            principal_angles(
                P["surface_basis"][i].astype(float), S["surface_basis"][i].astype(float)
            ).max()
            < 1e-3
        )  # float32
        np.testing.assert_allclose(
            np.linalg.eigvalsh(P["reduced_stiffness"][i]),
            np.linalg.eigvalsh(S["reduced_stiffness"][i]),
            rtol=1e-6,
        )


def test_cutting_region_on_two_ranks(mesh_dir, tmp_path_factory):
    """The element-condensed reduced stiffness, reduced over 2 ranks, matches its elements."""
    comm = MPI.COMM_WORLD
    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=2, per_ring=3)
    text += "\n[anm]\nenabled = false\n[cutting]\ncentre = [0.0, 0.0, -3.0]\nradius = 20.0\n"
    root = solved_on_rank_zero(tmp_path_factory, "cutred", text)
    reduce_campaign(root / "store", root / "parallel.h5", comm, verbose=False)
    if comm.rank != 0:
        return
    cutting = read_artifact(root / "parallel.h5")["cutting"]
    K = np.zeros_like(cutting["reduced_stiffness"])
    for c, cell in enumerate(cutting["cells"]):
        A_c = cutting["basis"][(3 * cell[:, None] + np.arange(3)).ravel()]
        K += A_c.T @ cutting["element_stiffness"][c] @ A_c
    scale = np.abs(K).max()
    np.testing.assert_allclose(cutting["reduced_stiffness"], K, atol=1e-10 * scale)
    # The pressure coupling's blocks, reduced over 2 ranks, make up its cells' blocks.
    A = cutting["reduced_displacement_stiffness"].copy()
    B = cutting["reduced_pressure_coupling"].copy()
    C = cutting["reduced_pressure_stiffness"].copy()
    for c, cell in enumerate(cutting["cells"]):
        A_c = cutting["basis"][(3 * cell[:, None] + np.arange(3)).ravel()]
        psi = cutting["pressure_basis"][c]
        A -= A_c.T @ cutting["element_displacement_stiffness"][c] @ A_c
        B -= np.outer(A_c.T @ cutting["element_pressure_coupling"][c], psi)
        C -= cutting["element_pressure_stiffness"][c] * np.outer(psi, psi)
    assert np.abs(A).max() <= 1e-10 * np.abs(cutting["reduced_displacement_stiffness"]).max()
    assert np.abs(B).max() <= 1e-10 * np.abs(cutting["reduced_pressure_coupling"]).max()
    assert np.abs(C).max() <= 1e-10 * np.abs(cutting["reduced_pressure_stiffness"]).max()
