"""POD-ANM series of every campaign sample, for the artifact (thesis §3.4.5).

For each solved tool position the reduction already holds its snapshots (in
canonical rows). Here they are moved to the DOLFINx layout of one
:class:`~hapticrom.offline.fe.formulation.HyperelasticModel` of the campaign's
organ and material (the residual does not depend on the tool: the lifting of
the tool's displacement carries the position), the reduced space of the
sample is built (:func:`~hapticrom.offline.reduce.anm.snapshot_space`) and the
continuation covers the trained load range. Displacement control: the load is
the depth and the response the force; force control (a smooth pressure under
the tool): the load is the force and the response the work-conjugate mean
displacement under the tool, its depth. What the runtime needs per section:
the series of the depth (mm), of the normal force (N) and of the reduced
coordinates in the sample's artifact basis A_i (mm),

    c(a) = A_i^T u(a) = lam(a) A_i^T g + (A_i^T A_0) alpha(a),

whose projection error is that of the lifting and modes on A_i (both are
combinations of the same snapshots).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
from hapticrom.offline.fe.materials import make_law
from hapticrom.offline.fe.organ import load_organ
from hapticrom.offline.mpi import allgather_rows
from hapticrom.offline.reduce.anm import (
    ANMOptions,
    ComplexResidual,
    ReducedResidual,
    continuation,
    snapshot_space,
)
from hapticrom.offline.reduce.pod import Truncation
from hapticrom.shared.errors import InputError


@dataclass
class SampleSeries:
    """The sections of one sample's branch, ready for the artifact."""

    a_max: np.ndarray  # (S,)
    depth: np.ndarray  # (S, N + 1) mm
    force: np.ndarray  # (S, N + 1) N, tool on tissue along the push direction
    coefficients: np.ndarray  # (S, N + 1, n) mm, in the sample's artifact basis
    evaluations: int
    seconds: float


def _to_owned(order: CanonicalOrder, canonical: np.ndarray) -> np.ndarray:
    """Rows of a canonical (bs N, m) array that this rank owns in DOLFINx order."""
    bs = order.bs
    m = canonical.shape[1]
    return canonical.reshape(-1, bs, m)[order.owned].reshape(-1, m)


@dataclass
class SeriesSetting:
    """What every sample's continuation shares: the organ's residual at complex arguments,
    its DOF orders, the series options and the control."""

    residual: ComplexResidual
    order_u: CanonicalOrder
    order_p: CanonicalOrder | None
    options: ANMOptions
    displacement_control: bool


def series_setting(config, comm: MPI.Comm) -> SeriesSetting:
    """The campaign's organ and material as one model on ``comm`` (collective)."""
    problem = config.problem
    organ = load_organ(problem.mesh.file, comm)
    law = make_law(problem.material.law, **problem.material.params)
    element = choose_element(organ.cell_type, problem.discretisation.element)
    model = HyperelasticModel(organ, law, element, problem.discretisation.quadrature_degree)
    return SeriesSetting(
        residual=ComplexResidual(model),
        order_u=CanonicalOrder(model.V),
        order_p=CanonicalOrder(model.Q) if model.Q is not None else None,
        options=ANMOptions(order=config.anm.order, tolerance=config.anm.tolerance),
        displacement_control=config.load.mode == "displacement",
    )


def sample_space(config, sample, setting: SeriesSetting, comm: MPI.Comm):
    """The reduced space of one sample's snapshots in DOLFINx order, and its arclength scale."""
    U = _to_owned(setting.order_u, allgather_rows(comm, sample.u_local))
    P = None
    if setting.order_p is not None and sample.p_local is not None:
        P = _to_owned(setting.order_p, allgather_rows(comm, sample.p_local))
    truncation = Truncation(eigenvalue_ratio=config.pod.eigenvalue_ratio)
    if setting.displacement_control:
        f, size = np.zeros(U.shape[0]), config.load.magnitude
    else:
        if sample.load_local is None:
            raise InputError(f"sample {sample.index}: the campaign stored no load vector")
        load = allgather_rows(comm, sample.load_local[:, None])
        f, size = _to_owned(setting.order_u, load)[:, 0], None
    steps = config.load.steps
    load_factor = np.arange(1, steps + 1) / steps
    mode = "displacement" if setting.displacement_control else "force"
    return snapshot_space(comm, load_factor, U, P, mode, f, size, truncation)


def one_sample_series(config, sample, reduced, setting: SeriesSetting, comm) -> SampleSeries:
    """The continuation of one sample, its series in the sample's artifact basis."""
    t0 = time.perf_counter()
    space, scale = sample_space(config, sample, setting, comm)
    rr = ReducedResidual(setting.residual, space, comm)
    branch = continuation(rr, scale, setting.options)
    A_i = _to_owned(setting.order_u, allgather_rows(comm, reduced.basis_local))
    M = comm.allreduce(A_i.T @ np.column_stack([space.g, space.A]), op=MPI.SUM)
    n0 = space.n
    Y = np.array([sec.Y for sec in branch.sections])  # (S, N + 1, n0 + n_p + 1)
    lam = Y[:, :, -1]
    coefficients = lam[:, :, None] * M[:, 0] + Y[:, :, :n0] @ M[:, 1:].T
    load = lam * config.load.magnitude  # mm (displacement control) or N (force control)
    response = np.array([sec.response for sec in branch.sections])  # N or mm
    depth, force = (load, response) if setting.displacement_control else (response, load)
    return SampleSeries(
        a_max=np.array([sec.a_max for sec in branch.sections]),
        depth=depth,
        force=force,
        coefficients=coefficients,
        evaluations=rr.evaluations,
        seconds=time.perf_counter() - t0,
    )


def sample_series(config, samples, reduced, comm: MPI.Comm, say=lambda s: None):
    """SampleSeries for every sample (collective over ``comm``)."""
    setting = series_setting(config, comm)
    out = []
    for s, r in zip(samples, reduced, strict=True):
        series = one_sample_series(config, s, r, setting, comm)
        end = float(np.polynomial.polynomial.polyval(series.a_max[-1], series.depth[-1]))
        say(
            f"  sample {s.index:3d}: ANM {len(series.a_max)} section(s) of order "
            f"{setting.options.order} to depth {end:.4g} mm, "
            f"{series.evaluations} residual evaluations, {series.seconds:.1f} s"
        )
        out.append(series)
    return out
