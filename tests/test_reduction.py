"""POD of a real campaign (SLEPc vs numpy) and the reduced operators of the export."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.offline.pod import Truncation, pod, pod_numpy, principal_angles
from hapticrom.offline.reduction import DRAFT_FORMAT, reduce_campaign
from hapticrom.offline.store import csr_from

pytestmark = pytest.mark.serial


@pytest.fixture(scope="module")
def reduced(small_campaign, tmp_path_factory):
    _, store, _ = small_campaign
    out = tmp_path_factory.mktemp("reduced") / "model.h5"
    summary = reduce_campaign(store.root, out, MPI.COMM_SELF, verbose=False)
    return store, out, summary


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


def test_export_holds_bases_and_reduced_operators(reduced):
    store, out, summary = reduced
    ops, _ = store.read_operators()
    K0 = csr_from(ops, "K0")
    with h5py.File(out, "r") as f:
        assert f.attrs["format"] == DRAFT_FORMAT
        assert list(f["positions/index"][()]) == store.completed()
        for i in store.completed():
            g = f[f"positions/{i}"]
            A = g["basis"][()]
            data, _ = store.read_position(i)
            assert A.shape == (K0.shape[0], summary["modes"][i])
            np.testing.assert_allclose(A.T @ A, np.eye(A.shape[1]), atol=1e-12)
            np.testing.assert_allclose(g["K_r"][()], A.T @ (K0 @ A), rtol=1e-10, atol=1e-10)
            dofs = (3 * data["contact_nodes"][:, None] + np.arange(3)).ravel()
            np.testing.assert_array_equal(g["contact_rows"][()], A[dofs])
            # The basis reproduces the position's snapshots (to the truncation error).
            U = data["displacement"].T
            projection = A @ (A.T @ U)
            assert np.linalg.norm(U - projection) <= 1e-3 * np.linalg.norm(U)
            np.testing.assert_array_equal(g["force"][()], data["force"])
        A = f["global/basis"][()]
        assert A.shape[1] == summary["global_modes"]
        np.testing.assert_allclose(f["global/K_r"][()], A.T @ (K0 @ A), rtol=1e-10, atol=1e-10)
        assert f["mesh/node_coordinates"].shape == (K0.shape[0] // 3, 3)


def test_reduce_refuses_an_unfinished_campaign(small_campaign, tmp_path):
    from hapticrom.offline.store import SnapshotStore
    from hapticrom.shared.errors import InputError

    _, store, _ = small_campaign
    partial = tmp_path / "partial"
    (partial / "solves").mkdir(parents=True)
    (partial / "manifest.json").write_bytes(store.manifest_path.read_bytes())
    (partial / "operators.h5").write_bytes(store.operators_path.read_bytes())
    (partial / "solves" / "position-0000.h5").write_bytes(store.position_path(0).read_bytes())
    with pytest.raises(InputError, match="not solved yet"):
        reduce_campaign(SnapshotStore(partial).root, tmp_path / "m.h5", MPI.COMM_SELF, False)
