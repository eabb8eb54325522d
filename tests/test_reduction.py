"""POD of a real campaign (SLEPc vs numpy) and the reduced operators of the export."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.offline.campaign.store import csr_from
from hapticrom.offline.reduce.pod import Truncation, pod, pod_numpy, principal_angles
from hapticrom.offline.reduce.reduction import reduce_campaign
from hapticrom.shared.artifact import read_artifact

pytestmark = pytest.mark.serial


@pytest.fixture(scope="module")
def reduced(small_artifact):
    return small_artifact


def snapshot_matrix(store) -> np.ndarray:
    return np.hstack([store.read_position(i)[0]["displacement"].T for i in store.completed()])


@pytest.mark.parametrize("method", ["snapshots", "svd"])
def test_slepc_pod_matches_numpy_svd_on_a_real_campaign(small_campaign, method):
    """Eigenvalues to 1e-8 relative, subspaces to a principal angle below 1e-6."""
    _, store, _ = small_campaign
    Q = snapshot_matrix(store)  # 1305 DOFs x 20 snapshots of the HGO cornea
    truncation = Truncation(eigenvalue_ratio=1e-8)
    slepc = pod(Q, MPI.COMM_SELF, truncation=truncation, method=method)
    reference = pod_numpy(Q, truncation=truncation)
    n = reference.n_modes
    assert slepc.n_modes == n >= 5
    rel = np.abs(slepc.eigenvalues[:n] - reference.eigenvalues[:n]) / reference.eigenvalues[:n]
    assert rel.max() <= 1e-8, rel
    assert principal_angles(slepc.basis_local, reference.basis_local).max() < 1e-6
    # The spectrum decays over many orders, as in the thesis (Figs. 2.4, 3.13).
    assert reference.eigenvalues[n - 1] / reference.eigenvalues[0] < 1e-6


def test_reduced_stiffness_does_not_lock(small_campaign, reduced):
    """K_r with a reduced pressure gives the contact stiffness of the full model; the
    element-wise condensed K0 projected on the same basis is far too stiff (locking)."""
    _, store, _ = small_campaign
    artifact = read_artifact(reduced)
    samples = artifact["samples"]
    ops, _ = store.read_operators()
    K0 = csr_from(ops, "K0")
    for i in range(len(samples["points"])):
        data, attrs = store.read_position(i)
        n = -np.asarray(attrs["direction"])  # outward
        C, K_r = samples["contact_rows"][i], samples["reduced_stiffness"][i]
        stiffness = 1.0 / (n @ C @ np.linalg.solve(K_r, C.T) @ n)
        # Secant stiffness of the full nonlinear model at its first (small) step.
        depth = data["contact_displacement"][0] @ -n
        secant = (data["force"][0] @ -n) / depth
        assert stiffness == pytest.approx(secant, rel=0.05), (i, stiffness, secant)
        # The same basis with the element-wise condensed K0 is stiffer (never softer): on
        # this coarse mesh by a few percent, on the default cornea 13-20x (see the note).
        U = data["displacement"].T
        A = pod(U, MPI.COMM_SELF, truncation=Truncation(None, max_modes=K_r.shape[0])).basis_local
        C0 = A.reshape(-1, 3, A.shape[1])[data["contact_nodes"]].mean(axis=0)
        locked = 1.0 / (n @ C0 @ np.linalg.pinv(A.T @ (K0 @ A)) @ C0.T @ n)
        assert locked >= stiffness * (1 - 1e-9)


def test_artifact_content_matches_the_campaign(small_campaign, reduced):
    _, store, _ = small_campaign
    a = read_artifact(reduced)
    s = a["samples"]
    assert a.group_attrs["model"]["campaign_hash"] == store.manifest()["campaign_hash"]
    for i in range(len(s["points"])):
        data, attrs = store.read_position(i)
        np.testing.assert_allclose(s["points"][i], attrs["point"])
        np.testing.assert_allclose(
            s["force"][i, 1:], data["force"] @ attrs["direction"], rtol=1e-12
        )
        assert np.all(np.diff(s["force"][i]) > 0) and np.all(s["stiffness"][i] > 0)
        # POD eigenvalues: decay over many orders (thesis Figs. 2.4, 3.13).
        assert s["eigenvalues"][i][2] < 1e-5 * s["eigenvalues"][i][0]
    # The rendering surface: vertices are mesh nodes, with the canonical numbering.
    ops, _ = store.read_operators()
    np.testing.assert_allclose(
        ops["node_coordinates"][a["surface"]["nodes"]], a["surface"]["vertices"], atol=1e-12
    )


def test_reduce_refuses_an_unfinished_campaign(small_campaign, tmp_path):
    from hapticrom.offline.campaign.store import SnapshotStore
    from hapticrom.shared.errors import InputError

    _, store, _ = small_campaign
    partial = tmp_path / "partial"
    (partial / "solves").mkdir(parents=True)
    (partial / "manifest.json").write_bytes(store.manifest_path.read_bytes())
    (partial / "operators.h5").write_bytes(store.operators_path.read_bytes())
    (partial / "solves" / "position-0000.h5").write_bytes(store.position_path(0).read_bytes())
    with pytest.raises(InputError, match="not solved yet"):
        reduce_campaign(SnapshotStore(partial).root, tmp_path / "m.h5", MPI.COMM_SELF, False)
