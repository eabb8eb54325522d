"""POD (offline/reduce/pod.py) on synthetic snapshot matrices of known structure.

``Q = U diag(s) V^T`` with U (N x r) orthonormal (W-orthonormal in the weighted
cases) and V (M x r) orthonormal, both random and seeded: the exact POD
eigenvalues are ``s**2`` and the exact modes the columns of U.

Which eigenvalues the method of snapshots resolves: forming and solving
``C = Q^T W Q`` leaves an absolute error of at most about ``10 eps lambda_1``
on each eigenvalue (the backward error of the Hermitian eigensolver; in
practice much less), i.e. a relative error ``10 eps lambda_1 / lambda_i``. That
is below 1e-8 for ``lambda_i >= 2.2e-7 lambda_1``: the relative 1e-8 checks of
the method of snapshots use the kept eigenvalues with ``lambda_i >= 1e-6
lambda_1`` (RESOLVED_8); the smaller kept ones (down to the thesis' cut 1e-8)
are checked to ``10 eps lambda_1`` absolutely. The SVD methods do not square
the singular values and resolve every kept eigenvalue to 1e-8 relatively.
"""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.offline.reduce.pod import PODResult, Truncation, pod, pod_numpy, principal_angles
from hapticrom.shared.errors import InputError

N, M = 3000, 40
S_DECAY = np.logspace(0, -5, M)  # eigenvalues 1 ... 1e-10 (about 1.8 apart)
# The eigenvalues of the thesis' Fig. 2.4 (cornea, one load position).
THESIS_EIGENVALUES = np.array([9.02e4, 690.0, 27.0, 2.63, 0.221, 0.0028])
EPS = np.finfo(float).eps
RESOLVED_8 = 1e-6  # lambda_i / lambda_1 above which snapshots give 1e-8 relative
RESOLVED_10 = 1e-4  # ... and 1e-10 relative (10 eps / 1e-10 = 2.2e-5, with margin)


def synthetic(n_rows=N, s=S_DECAY, m=None, seed=0, weights=None):
    """Q = U diag(s) V^T with U^T W U = I; returns (Q, U)."""
    rng = np.random.default_rng(seed)
    r = len(s)
    m = r if m is None else m
    U = np.linalg.qr(rng.standard_normal((n_rows, r)))[0]
    V = np.linalg.qr(rng.standard_normal((m, r)))[0]
    if weights is not None:
        U = U / np.sqrt(weights)[:, None]
    return (U * s) @ V.T, U


def lumped_mass(n_rows=N, seed=1):
    """Positive weights spread over a factor 40, like a lumped mass on a graded mesh."""
    return np.random.default_rng(seed).uniform(0.05, 2.0, n_rows)


def rank_deficient():
    """Rank 10 with duplicated, rescaled and zero columns; M = 40."""
    Q0, _ = synthetic(s=np.logspace(0, -3, 10), seed=3)
    Q = np.hstack([Q0, Q0[:, :10], np.zeros((N, 8)), 2.0 * Q0[:, 2:8], Q0[:, :6] - Q0[:, 4:10]])
    assert Q.shape == (N, 40) and np.linalg.matrix_rank(Q) == 10
    return Q


def split_rows(n_rows, comm):
    """Deliberately uneven contiguous row blocks: rank r gets a share (r + 1)."""
    shares = np.arange(1, comm.size + 1)
    cuts = np.concatenate([[0], np.round(np.cumsum(shares) / shares.sum() * n_rows)]).astype(int)
    return cuts[comm.rank], cuts[comm.rank + 1]


def check_snapshot_eigenvalues(lam, ref, n):
    """Kept eigenvalues of the method of snapshots against a reference (see module doc)."""
    lam, ref = lam[:n], ref[:n]
    resolved = ref >= RESOLVED_8 * ref[0]
    assert resolved.sum() >= min(n, 20)
    np.testing.assert_allclose(lam[resolved], ref[resolved], rtol=1e-8, atol=0)
    tail = ~resolved  # tiny kept eigenvalues: the absolute accuracy of the method
    np.testing.assert_allclose(lam[tail], ref[tail], rtol=0, atol=10 * EPS * ref[0])


def projection_error(result: PODResult, Q, weights=None) -> float:
    """||Q - A A^T W Q||_W^2 (one process)."""
    E = Q - result.basis_local @ result.coefficients(Q, MPI.COMM_SELF)
    return float(((E**2).sum(axis=1) * (1.0 if weights is None else weights)).sum())


def w_gram(A, weights=None):
    return A.T @ (A if weights is None else A * weights[:, None])


# ----------------------------------------------------------------- accuracy


@pytest.mark.serial
def test_snapshots_match_numpy_svd():
    Q, U = synthetic()
    ref = pod_numpy(Q)
    res = pod(Q, MPI.COMM_SELF)
    assert res.method == "snapshots" and res.solver == "krylovschur"
    # The thesis' rule keeps lambda >= 1e-8 lambda_1: s >= 1e-4, 32 of the 40.
    assert res.n_modes == ref.n_modes == int((S_DECAY**2 >= 1e-8).sum()) == 32
    check_snapshot_eigenvalues(res.eigenvalues, ref.eigenvalues, res.n_modes)
    check_snapshot_eigenvalues(res.eigenvalues, S_DECAY**2, res.n_modes)
    np.testing.assert_allclose(ref.eigenvalues[:32], S_DECAY[:32] ** 2, rtol=1e-10)
    assert principal_angles(res.basis_local, ref.basis_local).max() < 1e-6
    assert principal_angles(res.basis_local, U[:, :32]).max() < 1e-6
    assert len(res.eigenvalues) == M and res.energy.shape == (M,)
    assert res.trace == pytest.approx((S_DECAY**2).sum(), rel=1e-12)
    assert res.eigenvalues.sum() == pytest.approx(res.trace, rel=1e-12)
    assert res.energy[-1] == pytest.approx(1.0, rel=1e-12)
    assert np.all(np.diff(res.eigenvalues) <= 0) and res.seconds >= 0


@pytest.mark.serial
def test_slepc_svd_matches_numpy_svd():
    Q, _ = synthetic()
    ref = pod_numpy(Q)
    res = pod(Q, MPI.COMM_SELF, method="svd")
    assert res.method == "svd" and res.solver == "trlanczos"
    assert res.n_modes == ref.n_modes == 32
    n = res.n_modes
    np.testing.assert_allclose(res.eigenvalues[:n], ref.eigenvalues[:n], rtol=1e-8)
    assert principal_angles(res.basis_local, ref.basis_local).max() < 1e-6
    # Same sign rule: the bases agree column by column, not just as subspaces.
    assert np.abs(res.basis_local - ref.basis_local).max() < 1e-8


@pytest.mark.serial
@pytest.mark.parametrize("weighted", [False, True])
def test_eps_and_svd_methods_agree(weighted):
    w = lumped_mass() if weighted else None
    Q, _ = synthetic(weights=w)
    eps = pod(Q, MPI.COMM_SELF, weights=w)
    svd = pod(Q, MPI.COMM_SELF, weights=w, method="svd")
    assert eps.n_modes == svd.n_modes == 32
    check_snapshot_eigenvalues(eps.eigenvalues, svd.eigenvalues, eps.n_modes)
    assert principal_angles(eps.basis_local, svd.basis_local, w).max() < 1e-6
    # Modes of well-separated, resolved eigenvalues agree one by one (same signs).
    resolved = svd.eigenvalues[: eps.n_modes] >= RESOLVED_8
    A, B = eps.basis_local[:, resolved], svd.basis_local[:, resolved]
    assert np.abs(A - B).max() < 1e-8


@pytest.mark.serial
@pytest.mark.parametrize("method", ["snapshots", "svd"])
@pytest.mark.parametrize("weighted", [False, True])
def test_basis_orthonormal_and_projection_error(method, weighted):
    w = lumped_mass() if weighted else None
    Q, U = synthetic(weights=w)
    res = pod(Q, MPI.COMM_SELF, weights=w, method=method)
    n = res.n_modes
    A = res.basis_local
    assert A.shape == (N, n) and np.isfinite(A).all()
    np.testing.assert_allclose(w_gram(A, w), np.eye(n), rtol=0, atol=1e-12)
    # Sign rule: each mode's largest entry is positive.
    assert np.all(A[np.abs(A).argmax(axis=0), np.arange(n)] > 0)
    # ||Q - A A^T W Q||_W^2 = the sum of the discarded eigenvalues.
    discarded = (S_DECAY[n:] ** 2).sum()
    assert projection_error(res, Q, w) == pytest.approx(discarded, rel=1e-6)
    assert res.trace - res.eigenvalues[:n].sum() == pytest.approx(discarded, rel=1e-6)
    assert principal_angles(A, U[:, :n], w).max() < 1e-6


@pytest.mark.serial
def test_weighted_pod_is_the_l2_pod():
    w = lumped_mass()
    Q, U = synthetic(weights=w)
    ref = pod_numpy(Q, weights=w)
    res = pod(Q, MPI.COMM_SELF, weights=w)
    check_snapshot_eigenvalues(res.eigenvalues, S_DECAY**2, res.n_modes)
    np.testing.assert_allclose(ref.eigenvalues[:32], S_DECAY[:32] ** 2, rtol=1e-10)
    np.testing.assert_allclose(w_gram(ref.basis_local, w), np.eye(32), atol=1e-12)
    assert principal_angles(res.basis_local, ref.basis_local, w).max() < 1e-6
    # The Euclidean POD of the same Q is a different decomposition.
    euclid = pod_numpy(Q)
    assert abs(euclid.eigenvalues[0] / ref.eigenvalues[0] - 1) > 1e-3


@pytest.mark.serial
def test_thesis_spectrum_keeps_all_six_modes():
    Q, _ = synthetic(s=np.sqrt(THESIS_EIGENVALUES), m=30, seed=7)
    for method in ("snapshots", "svd"):
        res = pod(Q, MPI.COMM_SELF, method=method)
        # 0.0028 / 9.02e4 = 3.1e-8 >= 1e-8: the thesis' cut keeps all six.
        assert res.n_modes == 6
        np.testing.assert_allclose(res.eigenvalues[:4], THESIS_EIGENVALUES[:4], rtol=1e-8)
        np.testing.assert_allclose(res.eigenvalues[:6], THESIS_EIGENVALUES, rtol=1e-6)
    assert pod(Q, MPI.COMM_SELF, truncation=Truncation(eigenvalue_ratio=1e-7)).n_modes == 5


# --------------------------------------------------------------- truncation


@pytest.mark.serial
@pytest.mark.parametrize("method", ["snapshots", "svd", "numpy"])
def test_truncation_rules(method):
    Q, _ = synthetic()
    lam = S_DECAY**2
    cum = np.cumsum(lam) / lam.sum()

    def n_modes(**kwargs):
        t = Truncation(**kwargs)
        if method == "numpy":
            return pod_numpy(Q, truncation=t).n_modes
        return pod(Q, MPI.COMM_SELF, truncation=t, method=method).n_modes

    # Ratios and energies chosen away from any eigenvalue / partial sum.
    assert n_modes(eigenvalue_ratio=3e-5) == int((lam >= 3e-5).sum()) == 18
    assert n_modes(eigenvalue_ratio=1.0) == 1
    e = 0.9995
    expected = int(np.argmax(cum >= e)) + 1
    assert n_modes(eigenvalue_ratio=None, energy=e) == expected == 13
    assert n_modes(eigenvalue_ratio=None, max_modes=7) == 7
    assert n_modes(eigenvalue_ratio=None, max_modes=1) == 1
    # The minimum over the criteria given.
    assert n_modes(eigenvalue_ratio=3e-5, energy=e, max_modes=20) == 13  # energy decides
    assert n_modes(eigenvalue_ratio=3e-5, energy=e, max_modes=4) == 4  # max_modes decides
    assert n_modes(eigenvalue_ratio=1e-3, energy=0.999999999, max_modes=30) == 12  # ratio
    # Only the numerical rank limits: 40 nonzero eigenvalues, all kept.
    assert n_modes(eigenvalue_ratio=None) == 40
    assert n_modes(eigenvalue_ratio=None, energy=1.0) == 40
    assert n_modes(eigenvalue_ratio=None, max_modes=1000) == 40


@pytest.mark.serial
@pytest.mark.parametrize("method", ["snapshots", "svd", "numpy"])
@pytest.mark.parametrize("ratio", [None, 1e-8])
def test_rank_deficient_snapshots(method, ratio):
    Q = rank_deficient()
    t = Truncation(eigenvalue_ratio=ratio)
    res = (
        pod_numpy(Q, truncation=t)
        if method == "numpy"
        else pod(Q, MPI.COMM_SELF, truncation=t, method=method)
    )
    ref = pod_numpy(Q, truncation=t)
    assert res.n_modes == 10  # no mode from a zero eigenvalue
    assert np.isfinite(res.basis_local).all() and np.isfinite(res.eigenvalues).all()
    assert np.all(res.eigenvalues[10:] <= res.noise_floor)
    assert res.eigenvalues[9] > 1e3 * res.noise_floor
    np.testing.assert_allclose(res.eigenvalues[:10], ref.eigenvalues[:10], rtol=1e-8)
    np.testing.assert_allclose(w_gram(res.basis_local), np.eye(10), atol=1e-12)
    assert projection_error(res, Q) < 1e-20 * res.trace
    assert principal_angles(res.basis_local, ref.basis_local).max() < 1e-6


@pytest.mark.serial
def test_single_snapshot_and_tiny_problems():
    rng = np.random.default_rng(4)
    q = rng.standard_normal((50, 1))
    for method in ("snapshots", "svd"):
        res = pod(q, MPI.COMM_SELF, method=method)
        assert res.n_modes == 1
        assert res.eigenvalues[0] == pytest.approx(float(q[:, 0] @ q[:, 0]), rel=1e-12)
        np.testing.assert_allclose(
            np.abs(res.basis_local[:, 0]), np.abs(q[:, 0]) / np.linalg.norm(q)
        )
    # More snapshots than rows: the rank is N.
    Q = rng.standard_normal((5, 12))
    for method in ("snapshots", "svd"):
        res = pod(Q, MPI.COMM_SELF, truncation=Truncation(eigenvalue_ratio=None), method=method)
        assert res.n_modes == 5
        np.testing.assert_allclose(res.basis_local.T @ res.basis_local, np.eye(5), atol=1e-12)


@pytest.mark.serial
def test_partial_and_adaptive_spectra():
    """Fewer pairs than M when only max_modes is asked for; doubling when more are needed."""
    Q, _ = synthetic()
    res = pod(Q, MPI.COMM_SELF, truncation=Truncation(eigenvalue_ratio=None, max_modes=3))
    assert res.n_modes == 3 and 3 <= len(res.eigenvalues) <= M
    np.testing.assert_allclose(res.eigenvalues[:3], S_DECAY[:3] ** 2, rtol=1e-12)
    # SVD: 70 slowly decaying singular values, all kept, > the 32 asked for first.
    s = np.logspace(0, -2, 70)
    Q, U = synthetic(n_rows=2000, s=s, m=90, seed=5)
    res = pod(Q, MPI.COMM_SELF, method="svd")
    assert res.n_modes == 70
    np.testing.assert_allclose(res.eigenvalues[:70], s**2, rtol=1e-10)
    assert principal_angles(res.basis_local, U).max() < 1e-8


@pytest.mark.serial
def test_eps_partial_spectrum_doubling(monkeypatch):
    """The path for M > FULL_SPECTRUM_M: 64 eigenpairs first, doubling until decided."""
    import hapticrom.offline.reduce.pod as pod_module

    monkeypatch.setattr(pod_module, "FULL_SPECTRUM_M", 100)
    s = np.logspace(0, -2, 200)
    Q, U = synthetic(n_rows=2000, s=s, m=300, seed=6)
    res = pod(Q, MPI.COMM_SELF)
    assert res.n_modes == 200 and len(res.eigenvalues) == 300
    np.testing.assert_allclose(res.eigenvalues[:200], s**2, rtol=1e-8)
    assert principal_angles(res.basis_local, U).max() < 1e-6
    # The energy rule is decided from the first 64 pairs.
    res = pod(Q, MPI.COMM_SELF, truncation=Truncation(eigenvalue_ratio=None, energy=0.5))
    cum = np.cumsum(s**2) / (s**2).sum()
    assert res.n_modes == int(np.argmax(cum >= 0.5)) + 1
    assert 64 <= len(res.eigenvalues) < 300


# ------------------------------------------------------------- PETSc options


@pytest.mark.serial
def test_slepc_types_from_options_do_not_leak():
    from petsc4py import PETSc

    Q, _ = synthetic()
    ref = pod(Q, MPI.COMM_SELF)
    opts = PETSc.Options()
    prefix = "test_pod_opts_"
    try:
        opts[f"{prefix}eps_type"] = "lapack"
        opts[f"{prefix}svd_type"] = "cross"
        lap = pod(Q, MPI.COMM_SELF, options_prefix=prefix)
        cross = pod(Q, MPI.COMM_SELF, options_prefix=prefix, method="svd")
    finally:
        del opts[f"{prefix}eps_type"]
        del opts[f"{prefix}svd_type"]
    assert lap.solver == "lapack" and cross.solver == "cross"
    check_snapshot_eigenvalues(lap.eigenvalues, ref.eigenvalues, ref.n_modes)
    assert principal_angles(lap.basis_local, ref.basis_local).max() < 1e-6
    # Nothing left behind: the same prefix gives the defaults again.
    assert pod(Q, MPI.COMM_SELF, options_prefix=prefix).solver == "krylovschur"
    assert not any(k.startswith(prefix) for k in opts.getAll())


# ------------------------------------------------------------- bad input


@pytest.mark.serial
@pytest.mark.parametrize(
    "kwargs",
    [
        {"eigenvalue_ratio": 0.0},
        {"eigenvalue_ratio": -1e-8},
        {"eigenvalue_ratio": 2.0},
        {"eigenvalue_ratio": float("nan")},
        {"eigenvalue_ratio": "1e-8"},
        {"energy": 0.0},
        {"energy": 1.5},
        {"energy": float("inf")},
        {"max_modes": 0},
        {"max_modes": 2.5},
        {"max_modes": True},
    ],
)
def test_bad_truncation(kwargs):
    with pytest.raises(InputError):
        Truncation(**kwargs)


@pytest.mark.serial
def test_bad_input():
    Q, _ = synthetic(n_rows=200, s=np.logspace(0, -2, 5))
    comm = MPI.COMM_SELF
    bad = Q.copy()
    bad[3, 2] = np.nan
    with pytest.raises(InputError, match="NaN"):
        pod(bad, comm)
    with pytest.raises(InputError, match="NaN"):
        pod_numpy(bad)
    with pytest.raises(InputError, match="M = 0"):
        pod(np.zeros((200, 0)), comm)
    with pytest.raises(InputError, match="zero"):
        pod(np.zeros((200, 4)), comm)
    with pytest.raises(InputError, match="2-D"):
        pod(Q[:, 0], comm)
    with pytest.raises(InputError, match="real"):
        pod(Q + 1j, comm)
    for w in (np.zeros(200), -np.ones(200), np.ones(199), np.full(200, np.nan)):
        with pytest.raises(InputError, match="weights"):
            pod(Q, comm, weights=w)
    with pytest.raises(InputError, match="method"):
        pod(Q, comm, method="qr")
    with pytest.raises(InputError, match="Truncation"):
        pod(Q, comm, truncation={"max_modes": 3})
    with pytest.raises(InputError, match="options_prefix"):
        pod(Q, comm, options_prefix="-bad prefix")
    res = pod(Q, comm)
    with pytest.raises(InputError, match="rows"):
        res.coefficients(Q[:100], comm)


@pytest.mark.serial
def test_principal_angles():
    e = np.eye(6)
    for t in (0.0, 1e-10, 1e-4, 0.7, np.pi / 2):
        B = np.cos(t) * e[:, [0]] + np.sin(t) * e[:, [1]]
        angles = principal_angles(e[:, [0, 2]], B)
        assert angles.shape == (1,)
        assert angles[0] == pytest.approx(t, rel=1e-10, abs=1e-15)
    # Invariant under a change of basis; W-weighted version.
    rng = np.random.default_rng(0)
    A = rng.standard_normal((30, 4))
    assert principal_angles(A, A @ rng.standard_normal((4, 4))).max() < 1e-7
    B = rng.standard_normal((30, 3))
    w = rng.uniform(0.5, 2, 30)
    sw = np.sqrt(w)[:, None]
    angles = principal_angles(A, B)
    assert angles.shape == (3,) and np.all(np.diff(angles) >= 0) and angles[0] > 0.1
    np.testing.assert_allclose(principal_angles(A / sw, B / sw, w), angles, rtol=1e-12)


# ------------------------------------------------------------------- MPI


def distributed_vs_serial(method, weights, truncation):
    comm = MPI.COMM_WORLD
    Q, _ = synthetic(weights=weights)  # the same global Q on every rank (seeded)
    r0, r1 = split_rows(N, comm)
    w_local = None if weights is None else weights[r0:r1]
    serial = pod(Q, MPI.COMM_SELF, weights=weights, truncation=truncation, method=method)
    par = pod(Q[r0:r1], comm, weights=w_local, truncation=truncation, method=method)
    assert par.basis_local.shape == (r1 - r0, par.n_modes)
    A = np.vstack(comm.allgather(par.basis_local))
    return comm, Q, (r0, r1), serial, par, A


@pytest.mark.mpi
@pytest.mark.parametrize("method", ["snapshots", "svd"])
@pytest.mark.parametrize("weighted", [False, True])
def test_distributed_equals_serial(method, weighted):
    w = lumped_mass() if weighted else None
    # For the method of snapshots, cut where every kept eigenvalue is resolved
    # to 1e-10 relative (lambda >= 1e-4 lambda_1); the SVD resolves the thesis' cut.
    ratio = RESOLVED_10 if method == "snapshots" else 1e-8
    comm, Q, (r0, r1), serial, par, A = distributed_vs_serial(method, w, Truncation(ratio))
    n = serial.n_modes
    assert par.n_modes == n == int((S_DECAY**2 >= ratio).sum())
    np.testing.assert_allclose(par.eigenvalues[:n], serial.eigenvalues[:n], rtol=1e-10)
    assert par.trace == pytest.approx(serial.trace, rel=1e-13)
    # Every rank returns bitwise the same eigenvalues.
    for other in comm.allgather(par.eigenvalues):
        assert np.array_equal(other, par.eigenvalues)
    # The gathered basis is the serial basis, signs included.
    assert np.abs(A - serial.basis_local).max() < 1e-8
    np.testing.assert_allclose(w_gram(A, w), np.eye(n), atol=1e-12)
    # Coefficients A^T W Q from row blocks: replicated, equal to the serial ones.
    coef = par.coefficients(Q[r0:r1], comm)
    np.testing.assert_allclose(coef, serial.coefficients(Q, MPI.COMM_SELF), rtol=0, atol=1e-10)
    for other in comm.allgather(coef):
        assert np.array_equal(other, coef)


@pytest.mark.mpi
def test_distributed_thesis_cut_and_rank_deficiency():
    comm = MPI.COMM_WORLD
    # The thesis' cut with the method of snapshots: same modes kept, and the
    # smallest kept eigenvalues agree to the method's absolute accuracy.
    _, _, _, serial, par, A = distributed_vs_serial("snapshots", None, Truncation())
    assert par.n_modes == serial.n_modes == 32
    check_snapshot_eigenvalues(par.eigenvalues, serial.eigenvalues, 32)
    assert principal_angles(A, serial.basis_local).max() < 1e-6
    # Rank-deficient Q split over ranks (M = 40 rows of C over the ranks too).
    Q = rank_deficient()
    r0, r1 = split_rows(N, comm)
    for method in ("snapshots", "svd"):
        res = pod(Q[r0:r1], comm, truncation=Truncation(eigenvalue_ratio=None), method=method)
        assert res.n_modes == 10 and np.isfinite(res.basis_local).all()
        A = np.vstack(comm.allgather(res.basis_local))
        np.testing.assert_allclose(A.T @ A, np.eye(10), atol=1e-12)


@pytest.mark.mpi
def test_ranks_without_rows():
    """Rank 0 holds every row, the others none (and fewer rows of C than ranks)."""
    comm = MPI.COMM_WORLD
    Q, _ = synthetic(n_rows=50, s=np.logspace(0, -2, 3))
    local = Q if comm.rank == 0 else Q[:0]
    for method in ("snapshots", "svd"):
        serial = pod(Q, MPI.COMM_SELF, method=method)
        res = pod(local, comm, method=method)
        assert res.n_modes == 3 and res.basis_local.shape == (local.shape[0], 3)
        # lambda >= 1e-4 lambda_1: resolved to 1e-10 (RESOLVED_10)
        np.testing.assert_allclose(res.eigenvalues[:3], serial.eigenvalues[:3], rtol=1e-10)
        A = np.vstack(comm.allgather(res.basis_local))
        assert np.abs(A - serial.basis_local).max() < 1e-8


@pytest.mark.mpi
def test_distributed_bad_input_raises_on_every_rank():
    comm = MPI.COMM_WORLD
    Q, _ = synthetic(n_rows=300, s=np.logspace(0, -2, 5))
    r0, r1 = split_rows(300, comm)
    local = Q[r0:r1].copy()
    if comm.rank == comm.size - 1:  # only one rank sees the NaN
        local[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        pod(local, comm)
    w = np.ones(r1 - r0)
    if comm.rank == 0:
        w[0] = 0.0
    with pytest.raises(InputError, match="weights"):
        pod(Q[r0:r1], comm, weights=w)
    # Inconsistent snapshot counts between ranks (only meaningful on > 1 rank).
    if comm.size > 1:
        cols = 5 if comm.rank == 0 else 4
        with pytest.raises(InputError, match="same number of snapshots"):
            pod(Q[r0:r1, :cols], comm)
