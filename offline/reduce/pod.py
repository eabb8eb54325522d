"""Proper orthogonal decomposition (POD) of a row-distributed snapshot matrix.

The snapshot matrix ``Q`` (thesis eq. 2.6) has one row per finite-element
degree of freedom (N rows, in a fixed canonical order) and one column per
snapshot (M columns, M << N). Every MPI rank holds a contiguous block of rows,
rank 0 the first ones. The POD basis ``A = [phi_1 ... phi_n]`` (eq. 2.8) is made
of the leading eigenvectors of the two-point correlation operator
``c = Q Q^T W`` (eqs. 2.4-2.7, with ``W = I`` in the thesis), normalised so that
``A^T W A = I``.

Three ways to compute the same thing
------------------------------------
* **The N x N operator** ``Q Q^T W`` of eq. 2.7: an eigenproblem of the size of
  the mesh for at most M nonzero eigenvalues. Never formed here.
* **The method of snapshots** (``method="snapshots"``, the default): the nonzero
  eigenvalues of ``Q Q^T W`` are those of the M x M correlation matrix
  ``C = Q^T W Q``, and if ``C v = lambda v`` then ``phi = Q v / sqrt(lambda)`` is
  the corresponding W-orthonormal mode. The only work proportional to N is one
  tall-skinny product ``Q_local^T W_local Q_local`` per rank (N M^2 / p flops)
  and an ``MPI_Allreduce`` of M x M numbers; the eigenproblem is tiny. C is
  held as a distributed PETSc dense matrix and solved by SLEPc EPS (Hermitian).
* **The SVD** (``method="svd"``) of the distributed tall matrix ``W^{1/2} Q`` by
  SLEPc (thick-restart Lanczos bidiagonalisation, ``trlanczos``): the
  eigenvalues are ``sigma_i^2`` and ``A = W^{-1/2} U``. It never squares the
  singular values, so it is accurate far further down the spectrum, but every
  Lanczos step touches the N x M matrix twice and re-orthogonalises against
  all previous N-vectors. Measured at N = 26000 on one rank: 0.04-0.07 s
  against 0.01-0.02 s for the method of snapshots at M = 40, 0.7-8 s against
  0.2-0.6 s at M = 400 (the slow end when 320 modes are kept). SLEPc's
  ``lapack`` SVD forms the full N x N left factor: never the default.

Accuracy of the method of snapshots
-----------------------------------
Forming C squares the singular values. A backward-stable symmetric
eigensolver returns each eigenvalue of C with an absolute error of a modest
multiple of ``eps * lambda_1`` (``eps`` = 2.2e-16), so ``lambda_i`` is only
accurate to about ``eps * lambda_1 / lambda_i`` relatively: 2e-10 at
``1e-6 lambda_1``, 2e-8 at the thesis' cut ``1e-8 lambda_1`` (the measured
errors are about ten times smaller), nothing below ``~1e-15 lambda_1``. The
modes are perturbed by about ``eps * lambda_1 / gap`` and the vectors
``Q v / sqrt(lambda)`` lose W-orthogonality by about ``eps * lambda_1 /
lambda``, so the basis is re-orthonormalised (Cholesky QR:
``G = A^T W A = R^T R``, ``A <- A R^{-1}``, a second time if G was far from
I), which leaves the leading modes as they are and keeps every mode within
that same error. When the tail of the spectrum matters (eigenvalues below
~1e-8 lambda_1), use ``method="svd"``: accurate to about
``eps * sigma_1 / sigma_i``, i.e. ``2 eps sqrt(lambda_1 / lambda_i)`` on lambda.

Inner product W
---------------
``weights=None`` is the Euclidean nodal inner product of the thesis (eq. 2.5):
every degree of freedom counts the same, so a refined region of the mesh
weighs more in the POD than a coarse one of the same volume. Passing a lumped
mass matrix ``w`` (``W = diag(w)``, each rank its own rows) makes it the L2
inner product of the displacement fields: the modes then no longer depend on
how the mesh is graded, and ``A^T W A = I`` holds in that inner product. The
default stays Euclidean to reproduce the thesis; use lumped-mass weights for
graded meshes (liver, cornea with a refined apex).

Truncation
----------
``Truncation`` combines the thesis' rule (keep ``lambda_i >= 1e-8 lambda_1``),
an energy fraction (fewest modes whose eigenvalues sum to at least ``energy``
times the trace of C) and a cap ``max_modes``; the number kept is the smallest
over the criteria given, never more than the numerically nonzero eigenvalues
(see ``_noise_floor``), and at least 1. As a safeguard, trailing modes whose
vectors are numerically dependent on the previous ones (the smallest
eigenvalue of their W-Gram matrix below 1/4, which the noise floor should
prevent) are dropped, so ``PODResult.n_modes`` is the number actually kept.

SLEPc settings
--------------
EPS: ``krylovschur``, Hermitian, largest real eigenvalues, convergence test
relative to the matrix norm (``-eps_conv_norm``; the relative-to-eigenvalue
test cannot converge eigenvalues at round-off level), ``tol = 1e-14``. For
M <= 1000 all M eigenpairs are requested: Krylov-Schur then works on the whole
space (ncv = M) and finishes in one restart, as accurate as LAPACK and no
slower (M = 400: 0.07 s against 0.06 s for ``lapack`` on one rank, 0.07 s
against 0.13 s on two, where LAPACK solves a redundant copy on every rank).
Above that, or when only ``max_modes`` modes are asked for, fewer pairs are
requested and the number doubles until the truncation rule is decided.
SVD: ``trlanczos``, largest, ``tol = 1e-13`` relative to ``||W^{1/2} Q||_F`` (the
matrix is scaled to unit norm and the test is ``-svd_conv_abs``, which every
SVD type supports), starting with ``min(M, 32)`` (or ``max_modes``) triplets
and doubling likewise.
Everything can be changed from the PETSc options database under the prefix,
e.g. ``-hapticrom_pod_eps_type lapack`` or ``-hapticrom_pod_svd_type cross``;
the defaults are set through the API before ``setFromOptions``, never written
into the options database, so nothing leaks from one call to the next. The
numbers of requested pairs (``nev``/``nsv``, ``ncv``) are pod's to choose.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from mpi4py import MPI
from petsc4py import PETSc
from slepc4py import SLEPc

from hapticrom.shared.errors import InputError, SolverError

EPS_TOL = 1e-14  # EPS residual tolerance, relative to ||C|| (eps_conv_norm)
SVD_TOL = 1e-13  # SVD residual tolerance, relative to ||W^1/2 Q||_F (see _svd)
MAX_IT = 1000
FULL_SPECTRUM_M = 1000  # up to this M the EPS computes all M eigenpairs
SVD_FIRST_NSV = 32  # first number of singular triplets asked for by "svd"
METHODS = ("snapshots", "svd")
_EPS = float(np.finfo(float).eps)


@dataclass(frozen=True)
class Truncation:
    """How many modes to keep: the minimum over the criteria that are not None.

    ``eigenvalue_ratio``: keep ``lambda_i >= ratio * lambda_1`` (the thesis uses
    1e-8). ``energy``: keep the fewest modes whose eigenvalues sum to at least
    this fraction of the trace of C. ``max_modes``: at most this many modes.
    With every criterion None, all numerically nonzero modes are kept.
    """

    eigenvalue_ratio: float | None = 1e-8
    energy: float | None = None
    max_modes: int | None = None

    def __post_init__(self):
        for name in ("eigenvalue_ratio", "energy"):
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
                raise InputError(f"Truncation.{name} must be a number in (0, 1], got {value!r}")
            if not (math.isfinite(value) and 0.0 < value <= 1.0):
                raise InputError(f"Truncation.{name} must be in (0, 1], got {value!r}")
        m = self.max_modes
        if m is not None:
            if isinstance(m, bool) or not isinstance(m, int | np.integer) or m < 1:
                raise InputError(f"Truncation.max_modes must be an integer >= 1, got {m!r}")


@dataclass
class PODResult:
    """A POD basis and its spectrum; ``basis_local`` holds this rank's rows only.

    ``eigenvalues``: the computed eigenvalues of ``C = Q^T W Q`` in descending
    order (for the SVD methods ``sigma_i^2``; possibly fewer than M when only
    the leading ones were needed). ``energy[i]``: the cumulative fraction
    ``sum(eigenvalues[:i+1]) / trace``. ``basis_local``: this rank's rows of the
    N x n_modes basis A with ``A^T W A = I``; each mode's entry of largest
    magnitude is positive. ``noise_floor``: eigenvalues at or below it were
    treated as zero. ``solver``: the SLEPc type actually used.
    """

    eigenvalues: np.ndarray
    n_modes: int
    basis_local: np.ndarray
    trace: float
    energy: np.ndarray
    method: str
    seconds: float
    solver: str = ""
    noise_floor: float = 0.0
    weights_local: np.ndarray | None = field(default=None, repr=False)

    def coefficients(self, Q_local, comm) -> np.ndarray:
        """``A^T W Q`` (n_modes x M, identical on every rank) for rows ``Q_local``.

        ``A @ coefficients(Q)`` is the W-orthogonal projection of Q onto the
        basis; every rank must call this with its own rows, in the same order
        as the decomposition.
        """
        Q = np.asarray(Q_local, dtype=float)
        rows = self.basis_local.shape[0]
        message = None
        if Q.ndim != 2 or Q.shape[0] != rows:
            message = f"Q_local must have {rows} rows (this rank's basis rows), got {Q.shape}"
        _raise_if_any(comm, message)
        WQ = Q if self.weights_local is None else Q * self.weights_local[:, None]
        local = np.ascontiguousarray(self.basis_local.T @ WQ)
        out = np.empty_like(local)
        comm.Allreduce(local, out, op=MPI.SUM)
        return out


def pod(
    Q_local,
    comm,
    weights=None,
    truncation: Truncation = Truncation(),
    method: str = "snapshots",
    options_prefix: str = "hapticrom_pod_",
) -> PODResult:
    """POD of the snapshot matrix whose rows are distributed over ``comm``.

    ``Q_local``: this rank's contiguous block of rows (n_local x M; rank 0 the
    first rows). ``weights``: None (Euclidean) or this rank's positive
    diagonal of W (n_local,). ``method``: "snapshots" (SLEPc EPS on the M x M
    correlation matrix) or "svd" (SLEPc SVD of ``W^{1/2} Q``). Collective:
    every rank gets the same eigenvalues and its own rows of the basis.
    """
    Q, w, M, N, offset = _validate(Q_local, comm, weights, truncation, method, options_prefix)
    start = time.perf_counter()
    if method == "snapshots":
        lam, trace, floor, solver, T = _snapshots(Q, w, comm, M, truncation, options_prefix)
        A = Q @ T
    else:
        lam, trace, floor, solver, A = _svd(Q, w, comm, M, N, truncation, options_prefix)
    A = _w_orthonormalize(A, w, comm)
    _fix_signs(A, comm, offset)
    seconds = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
    return PODResult(
        eigenvalues=lam,
        n_modes=A.shape[1],
        basis_local=A,
        trace=trace,
        energy=np.cumsum(lam) / trace,
        method=method,
        seconds=seconds,
        solver=solver,
        noise_floor=floor,
        weights_local=w,
    )


def pressure_basis(P_local, comm, displacement_modes: int, method: str = "snapshots"):
    """Reduced pressure modes (this rank's rows) of pressure snapshots ``P_local``.

    The POD at eigenvalue ratio 1e-8, cut to at least 1 and at most
    ``ceil(displacement_modes / 2)`` modes: a few modes enforce incompressibility
    only where the snapshots do (see :mod:`.reduction`).
    """
    result = pod(P_local, comm, None, Truncation(eigenvalue_ratio=1e-8), method)
    return result.basis_local[:, : max(1, min(result.n_modes, math.ceil(displacement_modes / 2)))]


# --------------------------------------------------------------------------- input


def _raise_if_any(comm, message: str | None) -> None:
    """Raise InputError on every rank if any rank found a problem (no deadlock)."""
    messages = comm.allgather(message)
    for m in messages:
        if m is not None:
            raise InputError(m)


def _validate(Q_local, comm, weights, truncation, method, prefix):
    if not isinstance(truncation, Truncation):
        raise InputError(f"truncation must be a Truncation, got {type(truncation).__name__}")
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(prefix, str) or not prefix or not prefix.replace("_", "").isalnum():
        raise InputError(f"options_prefix must be a word such as 'hapticrom_pod_', got {prefix!r}")
    message = None
    Q = np.asarray(Q_local)
    w = None
    if Q.ndim != 2:
        message = f"Q_local must be a 2-D array (rows x snapshots), got shape {Q.shape}"
    elif not (np.issubdtype(Q.dtype, np.floating) or np.issubdtype(Q.dtype, np.integer)):
        message = f"Q_local must be real, got dtype {Q.dtype}"
    else:
        Q = np.ascontiguousarray(Q, dtype=float)
        if not np.isfinite(Q).all():
            message = "Q_local contains NaN or infinite values"
    if message is None and weights is not None:
        w = np.asarray(weights)
        real = np.issubdtype(w.dtype, np.floating) or np.issubdtype(w.dtype, np.integer)
        if w.shape != (Q.shape[0],) or not real:
            message = f"weights must have shape ({Q.shape[0]},) like Q_local's rows, got {w.shape}"
        else:
            w = np.ascontiguousarray(w, dtype=float)
            if not (np.isfinite(w).all() and (w > 0).all()):
                message = "weights must be finite and strictly positive"
    _raise_if_any(comm, message)
    shapes = comm.allgather(Q.shape)
    Ms = {s[1] for s in shapes}
    if len(Ms) != 1:
        raise InputError(f"every rank must hold the same number of snapshots, got {sorted(Ms)}")
    M = Ms.pop()
    N = sum(s[0] for s in shapes)
    if M == 0:
        raise InputError("Q has no snapshots (M = 0)")
    if N == 0:
        raise InputError("Q has no rows (N = 0)")
    local = float(np.einsum("ij,ij->", Q, Q)) if w is None else float(w @ (Q * Q).sum(axis=1))
    if comm.allreduce(local, op=MPI.SUM) == 0.0:
        raise InputError("Q is zero: there is nothing to decompose")
    offset = sum(s[0] for s in shapes[: comm.rank])
    return Q, w, M, N, offset


# ------------------------------------------------------------------- truncation


def _noise_floor(lam1: float, M: int, solver_error: float, squared: bool) -> float:
    """Eigenvalues at or below this are numerically zero.

    Method of snapshots (``squared=False``): the eigenvalues of ``fl(C)``
    carry an absolute error of a modest multiple of ``eps * lambda_1`` (the
    backward error of forming C by blocked sums and of the Hermitian
    eigensolver; measured <= 2 eps lambda_1 for exactly rank-deficient Q with
    N up to 1e5 and M up to 400), or ``solver_error`` (the EPS residual
    tolerance times ``||C|| = lambda_1``) if larger: floor =
    ``max(max(M, 16) eps lambda_1, solver_error)``. The factor M (at least 16)
    leaves a margin over the measured noise and bounds the loss of
    W-orthogonality of the modes ``Q v / sqrt(lambda)``, about
    ``eps lambda_1 / lambda``, by ``1 / max(M, 16)``.
    SVD (``squared=True``): the singular values carry an absolute error of a
    modest multiple of ``eps * sigma_1``, or ``solver_error`` (the residual
    tolerance times ``||W^{1/2} Q||_F``): the same floor on sigma, squared.
    """
    ref = math.sqrt(lam1) if squared else lam1
    floor = max(max(M, 16) * _EPS * ref, solver_error)
    return floor * floor if squared else floor


def _count(lam: np.ndarray, trace: float, t: Truncation, floor: float, complete: bool):
    """(modes to keep, whether that number is final) from the leading eigenvalues."""
    k = len(lam)
    final = complete
    below = np.flatnonzero(~(lam > floor))
    counts = [int(below[0]) if below.size else k]
    final |= below.size > 0
    if t.eigenvalue_ratio is not None:
        below = np.flatnonzero(lam < t.eigenvalue_ratio * lam[0])
        counts.append(int(below[0]) if below.size else k)
        final |= below.size > 0
    if t.energy is not None:
        hit = np.flatnonzero(np.cumsum(lam) >= t.energy * trace)
        counts.append(int(hit[0]) + 1 if hit.size else k)
        final |= hit.size > 0
    if t.max_modes is not None:
        counts.append(min(t.max_modes, k))
        final |= t.max_modes <= k
    return max(1, min(counts)), final


# ------------------------------------------------------------ SLEPc solvers


def _configure(solver, mat, defaults, tol: float, prefix: str) -> tuple[str, float]:
    """Set a SLEPc EPS or SVD up on ``mat``: the ``(setter, value)`` defaults and the
    tolerance through the API, then the options database under ``prefix`` (which may
    override them). Returns the solver type and the tolerance actually used."""
    solver.setOperators(mat)
    for setter, value in defaults:
        setter(value)
    solver.setTolerances(tol=tol, max_it=MAX_IT)
    solver.setOptionsPrefix(prefix)
    solver.setFromOptions()
    return solver.getType(), solver.getTolerances()[0]


def _snapshots(Q, w, comm, M, truncation, prefix):
    """Method of snapshots; returns (eigenvalues, trace, floor, type, T) with A = Q T."""
    Qs = Q if w is None else Q * np.sqrt(w)[:, None]
    C_local = np.ascontiguousarray(Qs.T @ Qs)  # the distributed N x M x M work
    C = np.empty_like(C_local)
    comm.Allreduce(C_local, C, op=MPI.SUM)
    C = 0.5 * (C + C.T)
    trace = comm.bcast(float(np.trace(C)), root=0)  # decisions use rank 0's numbers

    mat = PETSc.Mat().createDense(((PETSc.DECIDE, M), (PETSc.DECIDE, M)), comm=comm)
    mat.setUp()
    r0, r1 = mat.getOwnershipRange()
    mat.getDenseArray()[:] = C[r0:r1]
    mat.assemble()
    mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    eps = SLEPc.EPS().create(comm)
    vec = mat.createVecRight()
    try:
        defaults = (
            (eps.setProblemType, SLEPc.EPS.ProblemType.HEP),
            (eps.setType, SLEPc.EPS.Type.KRYLOVSCHUR),
            (eps.setWhichEigenpairs, SLEPc.EPS.Which.LARGEST_REAL),
            (eps.setConvergenceTest, SLEPc.EPS.Conv.NORM),
        )
        solver, tol = _configure(eps, mat, defaults, EPS_TOL, prefix)
        if M <= FULL_SPECTRUM_M:
            nev = M
        else:
            nev = min(M, max(64, truncation.max_modes or 0))
        if truncation.eigenvalue_ratio is None and truncation.energy is None:
            nev = min(nev, truncation.max_modes or M)

        def values(k):
            return np.array([float(np.real(eps.getEigenvalue(i))) for i in range(k)])

        def vectors(n):
            block = np.empty((r1 - r0, n))
            for i in range(n):
                eps.getEigenvector(i, vec)
                block[:, i] = vec.getArray(readonly=True)
            return np.vstack(comm.allgather(block))

        lam, n, floor = _adaptive(
            "EPS", eps, values, nev, M, trace, truncation, comm, tol, squared=False
        )
        V = vectors(n)
        T = V / np.sqrt(lam[:n])
    finally:
        eps.destroy()
        vec.destroy()
        mat.destroy()
    return lam, trace, floor, solver, T


def _svd(Q, w, comm, M, N, truncation, prefix):
    """SLEPc SVD of W^{1/2} Q; returns (sigma^2, trace, floor, type, A_local).

    The matrix handed to SLEPc is scaled to unit Frobenius norm and the
    convergence test is absolute: the tolerance is then relative to
    ``||W^{1/2} Q||_F`` for every SVD type (``-svd_conv_norm`` would fail for
    ``cross``/``cyclic``, whose operator is a shell matrix without a norm).
    """
    n_local = Q.shape[0]
    sqw = None if w is None else np.sqrt(w)
    Qs = Q if sqw is None else Q * sqw[:, None]
    trace = comm.allreduce(float(np.einsum("ij,ij->", Qs, Qs)), op=MPI.SUM)
    trace = comm.bcast(trace, root=0)  # decisions use rank 0's numbers
    scale = math.sqrt(trace)
    mat = PETSc.Mat().createDense(((n_local, N), (PETSc.DECIDE, M)), comm=comm)
    mat.setUp()
    mat.getDenseArray()[:] = Qs / scale
    mat.assemble()
    svd = SLEPc.SVD().create(comm)
    right, left = mat.createVecs()
    try:
        defaults = (
            (svd.setType, SLEPc.SVD.Type.TRLANCZOS),
            (svd.setWhichSingularTriplets, SLEPc.SVD.Which.LARGEST),
            (svd.setConvergenceTest, SLEPc.SVD.Conv.ABS),
        )
        solver, tol = _configure(svd, mat, defaults, SVD_TOL, prefix)
        n_total = min(M, N)
        nsv = min(n_total, truncation.max_modes or SVD_FIRST_NSV)

        def values(k):
            return np.array([(scale * svd.getValue(i)) ** 2 for i in range(k)])

        lam, n, floor = _adaptive(
            "SVD", svd, values, nsv, n_total, trace, truncation, comm, tol * scale, squared=True
        )
        U = np.empty((n_local, n))
        for i in range(n):
            svd.getSingularTriplet(i, left, right)
            U[:, i] = left.getArray(readonly=True)
    finally:
        svd.destroy()
        right.destroy()
        left.destroy()
        mat.destroy()
    A = U if sqw is None else U / sqw[:, None]
    return lam, trace, floor, solver, A


def _adaptive(kind, solver, values, n_ask, n_total, trace, truncation, comm, tol, squared):
    """Solve for ``n_ask`` leading pairs, doubling until the truncation is decided.

    ``tol``: the solver's residual tolerance, relative to ``||C|| = lambda_1``
    for the EPS (``squared=False``), absolute on sigma for the SVD.

    Returns the (rank-0, broadcast) eigenvalues, the number of modes to keep
    and the noise floor. Eigenvalue decisions are taken on rank 0 and
    broadcast, so every rank keeps the same modes.
    """
    while True:
        solver.setDimensions(n_ask, PETSc.DECIDE, PETSc.DECIDE)
        solver.solve()
        k = min(solver.getConverged(), n_total)
        lam = comm.bcast(values(k) if comm.rank == 0 else None, root=0)
        if k == 0 or not lam[0] > 0:
            raise SolverError(
                f"SLEPc {kind} ({solver.getType()}) converged no usable eigenvalue "
                f"(reason {solver.getConvergedReason()}); try its options under the prefix"
            )
        floor = _noise_floor(lam[0], n_total, tol if squared else tol * lam[0], squared)
        n, final = _count(lam, trace, truncation, floor, complete=k >= n_total)
        if final:
            return lam, n, floor
        if n_ask >= n_total:
            raise SolverError(
                f"SLEPc {kind} ({solver.getType()}) converged only {k} of the {n_ask} wanted "
                f"pairs before {solver.getIterationNumber()} iterations; raise its tolerance "
                "or max_it under the options prefix"
            )
        n_ask = 2 * max(n_ask, k)
        if 2 * n_ask >= n_total:  # ncv = 2 n_ask would span everything anyway
            n_ask = n_total


# ------------------------------------------------------------ basis clean-up


def _gram(A, w, comm):
    local = A.T @ (A if w is None else A * w[:, None])
    G = np.empty_like(local)
    comm.Allreduce(np.ascontiguousarray(local), G, op=MPI.SUM)
    return 0.5 * (G + G.T)


def _cholqr_factor(G):
    """(n kept, R^{-1}) for the longest leading block of G that is well conditioned.

    The smallest eigenvalue of a leading block can only decrease as it grows
    (Cauchy interlacing), so a bisection finds the longest block whose modes
    are still numerically independent (smallest eigenvalue >= 1/4).
    """
    n = G.shape[0]
    if np.linalg.eigvalsh(G)[0] < 0.25:
        lo, hi = 1, n  # block lo is fine (G[0,0] ~ 1), block hi is not
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if np.linalg.eigvalsh(G[:mid, :mid])[0] >= 0.25:
                lo = mid
            else:
                hi = mid
        n = lo
    R = np.linalg.cholesky(G[:n, :n]).T
    # The inverse of the small n x n factor, not a triangular solve per use: the solve
    # moves every artifact dataset built on the bases by ~1e-14 relative (measured),
    # and the artifacts stay bit for bit what earlier versions wrote.
    return n, np.linalg.inv(R)


def _w_orthonormalize(A, w, comm):
    """Cholesky QR of the basis in the W inner product (twice if far from I).

    The leading modes, the most accurate, change the least. Transforms are
    computed on rank 0 and broadcast, so all ranks apply identical ones.
    """
    for _ in range(2):
        G = _gram(A, w, comm)
        if comm.rank == 0:
            deviation = float(np.abs(G - np.eye(G.shape[0])).max())
            n, S = _cholqr_factor(G)
            payload = (deviation, n, S)
        else:
            payload = None
        deviation, n, S = comm.bcast(payload, root=0)
        A = A[:, :n] @ S
        # One pass leaves an error of about eps * cond(G) (tiny when G ~ I);
        # a second one is needed only when G was far from the identity.
        if deviation < 1e-3:
            break
    return np.ascontiguousarray(A)


def _fix_signs(A, comm, offset: int) -> None:
    """Make each mode's entry of largest magnitude positive, decided globally.

    Entries within a relative 1e-8 of the largest magnitude count as ties, and
    the one with the lowest global row index decides: round-off differences
    between runs on different numbers of ranks cannot flip a sign unless two
    entries differ by about 1e-8 relatively.
    """
    n = A.shape[1]
    absA = np.abs(A)
    local_max = absA.max(axis=0) if A.shape[0] else np.zeros(n)
    gmax = np.empty(n)
    comm.Allreduce(np.ascontiguousarray(local_max), gmax, op=MPI.MAX)
    cand_index = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
    cand_sign = np.zeros(n)
    if A.shape[0]:
        near = absA >= (1.0 - 1e-8) * gmax
        first = near.argmax(axis=0)  # lowest local row among the near-maximal ones
        cols = np.flatnonzero(near[first, np.arange(n)])
        cand_index[cols] = offset + first[cols]
        cand_sign[cols] = np.sign(A[first[cols], cols])
    gathered = comm.allgather((cand_index, cand_sign))
    indices = np.array([g[0] for g in gathered])
    signs = np.array([g[1] for g in gathered])
    owner = indices.argmin(axis=0)
    flip = signs[owner, np.arange(n)] < 0
    A[:, flip] *= -1.0


# ------------------------------------------------------------ numpy references


def pod_numpy(Q, weights=None, truncation: Truncation = Truncation()) -> PODResult:
    """Reference POD by numpy's SVD of the whole ``W^{1/2} Q`` (one process).

    Eigenvalues are ``sigma_i^2`` (accurate to about ``eps sigma_1 / sigma_i``
    relatively); the same truncation, noise floor (SVD form) and sign rule
    as :func:`pod`.
    """
    if not isinstance(truncation, Truncation):
        raise InputError(f"truncation must be a Truncation, got {type(truncation).__name__}")
    Q, w, *_ = _validate(Q, MPI.COMM_SELF, weights, truncation, "svd", "numpy")
    start = time.perf_counter()
    sqw = None if w is None else np.sqrt(w)
    Qs = Q if sqw is None else Q * sqw[:, None]
    U, s, _ = np.linalg.svd(Qs, full_matrices=False)
    lam = s**2
    trace = float(np.einsum("ij,ij->", Qs, Qs))
    floor = _noise_floor(lam[0], min(Q.shape), 0.0, squared=True)
    n, _ = _count(lam, trace, truncation, floor, complete=True)
    A = U[:, :n] if sqw is None else U[:, :n] / sqw[:, None]
    A = np.ascontiguousarray(A)
    _fix_signs(A, MPI.COMM_SELF, 0)
    return PODResult(
        eigenvalues=lam,
        n_modes=n,
        basis_local=A,
        trace=trace,
        energy=np.cumsum(lam) / trace,
        method="numpy-svd",
        seconds=time.perf_counter() - start,
        solver="numpy.linalg.svd",
        noise_floor=floor,
        weights_local=w,
    )


def principal_angles(A, B, weights=None) -> np.ndarray:
    """Principal angles (radians, ascending) between the column spaces of A and B.

    In the W inner product if ``weights`` (the diagonal of W) is given: the
    Euclidean angles of ``W^{1/2} A`` and ``W^{1/2} B``. scipy's
    ``subspace_angles`` uses cosines for the large angles and sines for the
    small ones, so angles near zero are accurate to ~eps, not to ~sqrt(eps) as
    arccos alone would give.
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if A.ndim != 2 or B.ndim != 2 or A.shape[0] != B.shape[0]:
        raise InputError(f"A and B must have the same number of rows, got {A.shape}, {B.shape}")
    if weights is not None:
        sw = np.sqrt(np.asarray(weights, dtype=float))
        if sw.shape != (A.shape[0],) or not np.isfinite(sw).all() or not (sw > 0).all():
            raise InputError("weights must be positive, one per row")
        A = A * sw[:, None]
        B = B * sw[:, None]
    return scipy.linalg.subspace_angles(A, B)[::-1]
