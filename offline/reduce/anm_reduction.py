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


def sample_series(config, samples, reduced, comm: MPI.Comm, say=lambda s: None):
    """SampleSeries for every sample (collective over ``comm``)."""
    from hapticrom.offline.reduce.reduction import _allgather_rows

    problem = config.problem
    organ = load_organ(problem.mesh.file, comm)
    law = make_law(problem.material.law, **problem.material.params)
    element = choose_element(organ.cell_type, problem.discretisation.element)
    model = HyperelasticModel(organ, law, element, problem.discretisation.quadrature_degree)
    residual = ComplexResidual(model)
    order_u = CanonicalOrder(model.V)
    order_p = CanonicalOrder(model.Q) if model.Q is not None else None
    options = ANMOptions(order=config.anm.order, tolerance=config.anm.tolerance)
    displacement_control = config.load.mode == "displacement"
    space_mode = "displacement" if displacement_control else "force"
    steps = config.load.steps
    load_factor = np.arange(1, steps + 1) / steps
    out = []
    for s, r in zip(samples, reduced, strict=True):
        t0 = time.perf_counter()
        U = _to_owned(order_u, _allgather_rows(comm, s.u_local))
        P = None
        if order_p is not None and s.p_local is not None:
            P = _to_owned(order_p, _allgather_rows(comm, s.p_local))
        truncation = Truncation(eigenvalue_ratio=config.pod.eigenvalue_ratio)
        if displacement_control:
            f, size = np.zeros(U.shape[0]), config.load.magnitude
        else:
            if s.load_local is None:
                raise InputError(f"sample {s.index}: the campaign stored no load vector")
            f, size = _to_owned(order_u, _allgather_rows(comm, s.load_local[:, None]))[:, 0], None
        space, scale = snapshot_space(
            comm, load_factor, U, P, space_mode, f, size, truncation
        )  # fmt: skip
        rr = ReducedResidual(residual, space, comm)
        branch = continuation(rr, scale, options)
        A_i = _to_owned(order_u, _allgather_rows(comm, r.basis_local))
        M = comm.allreduce(A_i.T @ np.column_stack([space.g, space.A]), op=MPI.SUM)
        n0 = space.n
        Y = np.array([sec.Y for sec in branch.sections])  # (S, N + 1, n0 + n_p + 1)
        lam = Y[:, :, -1]
        coefficients = lam[:, :, None] * M[:, 0] + Y[:, :, :n0] @ M[:, 1:].T
        load = lam * config.load.magnitude  # mm (displacement control) or N (force control)
        response = np.array([sec.response for sec in branch.sections])  # N or mm
        depth, force = (load, response) if displacement_control else (response, load)
        end = float(np.polynomial.polynomial.polyval(branch.sections[-1].a_max, depth[-1]))
        out.append(
            SampleSeries(
                a_max=np.array([sec.a_max for sec in branch.sections]),
                depth=depth,
                force=force,
                coefficients=coefficients,
                evaluations=rr.evaluations,
                seconds=time.perf_counter() - t0,
            )
        )
        say(
            f"  sample {s.index:3d}: ANM {len(branch.sections)} section(s) of order "
            f"{options.order} to depth {end:.4g} mm, "
            f"{rr.evaluations} residual evaluations, {out[-1].seconds:.1f} s"
        )
    return out


def artifact_group(series: list[SampleSeries], config) -> dict:
    """The artifact's optional ``anm`` group (see shared/ARTIFACT.md)."""
    counts = [len(s.a_max) for s in series]
    return {
        "section_offsets": np.r_[0, np.cumsum(counts)].astype(np.int64),
        "a_max": np.concatenate([s.a_max for s in series]),
        "depth": np.concatenate([s.depth for s in series]),
        "force": np.concatenate([s.force for s in series]),
        "coefficients": np.concatenate([s.coefficients for s in series]),
        "attrs": {
            "order": config.anm.order,
            "tolerance": config.anm.tolerance,
            "residual_evaluations": int(sum(s.evaluations for s in series)),
        },
    }
