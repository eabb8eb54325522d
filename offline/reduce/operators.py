"""Projecting the operators: each sample's POD basis and reduced stiffness, and the global ones.

Every function here is collective over ``comm``: the bases are distributed by
canonical rows (this rank's block), the reduced matrices are small and the same
on every rank. Why the pressure is reduced to a few modes rather than condensed
element-wise: see :mod:`.reduction`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

from hapticrom.offline.mpi import allgather_rows, allreduce_sum
from hapticrom.offline.reduce.inputs import OperatorRows, Sample
from hapticrom.offline.reduce.pod import PODResult, Truncation, pod, pressure_basis


@dataclass(frozen=True)
class PODSettings:
    """How the displacement PODs are computed: the inner product's weights (this rank's
    rows, None for Euclidean), the truncation rule and the method."""

    weights: np.ndarray | None
    truncation: Truncation
    method: str

    @classmethod
    def of(cls, pod_config, operators: OperatorRows) -> PODSettings:
        """The settings a campaign's ``[pod]`` table asks for."""
        c = pod_config
        weights = operators.volumes if c.inner_product == "volume" else None
        return cls(weights, Truncation(c.eigenvalue_ratio, c.energy, c.max_modes), c.method)

    def pod(self, Q_local: np.ndarray, comm: MPI.Comm, max_modes: int | None = None) -> PODResult:
        """The POD of ``Q_local``; ``max_modes``: exactly the first that many modes instead
        of the truncation rule (fewer only if the snapshots have fewer nonzero ones)."""
        truncation = self.truncation
        if max_modes is not None:
            truncation = Truncation(eigenvalue_ratio=None, max_modes=max_modes)
        return pod(Q_local, comm, self.weights, truncation, self.method)


def reduced_blocks(comm, ops: OperatorRows, A_local, P_local=None):
    """(A^T K A (N/mm), A^T K_up P (mm^2), P^T K_pp P (mm^3/MPa)); the last two are None
    for a displacement-only element or without a pressure basis P. K is K_uu if mixed."""
    A = allgather_rows(comm, A_local)
    K_r = allreduce_sum(comm, A_local.T @ (ops.K @ A))
    if not (ops.mixed and P_local is not None):
        return (K_r + K_r.T) / 2, None, None
    P = allgather_rows(comm, P_local)
    B = allreduce_sum(comm, A_local.T @ (ops.Kup @ P))
    Kpp = allreduce_sum(comm, P_local.T @ (ops.kpp[:, None] * P_local))  # < 0
    return (K_r + K_r.T) / 2, B, (Kpp + Kpp.T) / 2


def condense_reduced_pressure(K_r, B, Kpp) -> np.ndarray:
    """K_r - B Kpp^-1 B^T (K_r itself without a pressure basis), symmetrised."""
    if B is not None:
        K_r = K_r - B @ np.linalg.solve(Kpp, B.T)
    return (K_r + K_r.T) / 2


def reduced_stiffness(comm, ops: OperatorRows, A_local, P_local=None) -> np.ndarray:
    """A^T K A, with the pressure reduced to the basis P when the element has one (N/mm)."""
    return condense_reduced_pressure(*reduced_blocks(comm, ops, A_local, P_local))


def contact_rows(comm, A_local, rows, nodes) -> np.ndarray:
    """Mean of the basis rows (3 x n) over the contact nodes, from the distributed rows."""
    dofs = (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()
    mine = dofs[(dofs >= rows[0]) & (dofs < rows[1])] - rows[0]
    local = A_local[mine].reshape(-1, 3, A_local.shape[1]).sum(axis=0) if mine.size else 0.0
    return allreduce_sum(comm, np.zeros((3, A_local.shape[1])) + local) / len(nodes)


# -- per sample ---------------------------------------------------------------------
@dataclass
class ReducedSample:
    """One sample's reduced model: its basis (this rank's rows) and projected operators."""

    index: int
    pod: PODResult  # the POD by the truncation rule (its spectrum is reported)
    basis_local: np.ndarray  # (rows, n)
    coefficients: np.ndarray  # (K, n)
    reduced_stiffness: np.ndarray  # (n, n)
    contact_rows: np.ndarray  # (3, n)
    pressure_modes: int


def reduce_sample(comm, sample: Sample, first: PODResult, n: int, ops, rows, settings):
    """The ReducedSample of ``sample`` with ``n`` modes (``first``: its POD by the rule)."""
    full = first if first.n_modes == n else settings.pod(sample.u_local, comm, max_modes=n)
    A_local = full.basis_local[:, :n]
    W = settings.weights[:, None] if settings.weights is not None else 1.0
    coefficients = allreduce_sum(comm, (W * A_local).T @ sample.u_local).T  # (K - 1, n)
    P_local, n_p = None, 0
    if sample.p_local is not None:
        P_local = pressure_basis(sample.p_local, comm, n, settings.method)
        n_p = P_local.shape[1]
    return ReducedSample(
        index=sample.index,
        pod=first,
        basis_local=A_local,
        coefficients=np.vstack([np.zeros((1, n)), coefficients]),
        reduced_stiffness=reduced_stiffness(comm, ops, A_local, P_local),
        contact_rows=contact_rows(comm, A_local, rows, sample.contact_nodes),
        pressure_modes=n_p,
    )


def reduce_samples(comm, samples: list[Sample], ops, rows, settings: PODSettings):
    """Every sample's ReducedSample, and their common number of modes n."""
    # One n for all samples (interpolation needs equal dimensions): the largest count.
    first = [settings.pod(s.u_local, comm) for s in samples]
    n = max(r.n_modes for r in first)
    reduced = [
        reduce_sample(comm, s, r, n, ops, rows, settings)
        for s, r in zip(samples, first, strict=True)
    ]
    return reduced, n


# -- global -------------------------------------------------------------------------
@dataclass
class GlobalReduction:
    """The POD of every sample's snapshots together and its reduced operators.

    ``pressure_local``: this rank's rows of the reduced pressure modes (None without an
    element-wise pressure); ``blocks``: :func:`reduced_blocks`; ``stiffness``: the
    reduced stiffness with the reduced pressure condensed (N/mm).
    """

    pod: PODResult
    pressure_local: np.ndarray | None
    blocks: tuple
    stiffness: np.ndarray


def reduce_globally(comm, samples: list[Sample], ops, settings: PODSettings) -> GlobalReduction:
    """The global POD over all samples and its reduced stiffness."""
    global_pod = settings.pod(np.hstack([s.u_local for s in samples]), comm)
    P_local = None
    if ops.mixed:
        Qp = np.hstack([s.p_local for s in samples])
        P_local = pressure_basis(Qp, comm, global_pod.n_modes, settings.method)
    blocks = reduced_blocks(comm, ops, global_pod.basis_local, P_local)
    return GlobalReduction(global_pod, P_local, blocks, condense_reduced_pressure(*blocks))
