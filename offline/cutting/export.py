"""The artifact's cuttable region: what the runtime's cut patch needs (shared/ARTIFACT.md).

A ball (``centre``, ``radius``, mm) of the organ: the cells whose centroids lie
in it, their element stiffness matrices at the reference tangent
(:mod:`.element_matrices`), the rows of the global reduced basis at their
nodes, which nodes must keep the reduced field (the region's boundary and the
supports), and the global reduced stiffness with the pressure condensed
element-wise, consistent with the element matrices (eq. 4.8's K^zeta-zeta).
With an element-wise pressure, also the blocks before condensation and the
global reduced pressure basis, so the runtime can keep the reduced pressure
outside its patch (the element-condensed reduced stiffness locks nearly
incompressible tissue). The artifact group itself is laid out by
:mod:`hapticrom.offline.reduce.assemble`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.meshes.msh import read_msh_group
from hapticrom.offline.campaign.config import CuttingConfig
from hapticrom.offline.mpi import allgather_rows, allreduce_sum
from hapticrom.shared.errors import InputError


def read_mesh_arrays(mesh_file):
    """(nodes (n, 3) mm, hexahedra (m, 8) in the file's node order, clamped nodes) on one rank."""
    tags, coords, clamped, cells = read_msh_group(Path(mesh_file), "clamped")
    order = np.argsort(tags)
    if not np.array_equal(tags[order], np.arange(1, len(tags) + 1)):
        raise InputError(f"{mesh_file}: node tags are not 1..n (not a hapticrom mesh?)")
    if cells.shape[1] != 8:
        raise InputError("cutting needs a hexahedral mesh")
    return coords[order], cells - 1, np.unique(clamped - 1)


# -- the global reduced operators of the region (collective) ------------------------------
def condensed_reduced_stiffness(comm: MPI.Comm, ops, A_local: np.ndarray, K_r=None) -> np.ndarray:
    """A^T K0 A with the pressure condensed element-wise (distributed rows of A).

    ``K_r``: A^T K A (K_uu if mixed) when already computed
    (:func:`~hapticrom.offline.reduce.operators.reduced_blocks`).
    """
    K = K_r
    if K is None:
        A = allgather_rows(comm, A_local)  # the operators' rows span all columns
        K = allreduce_sum(comm, A_local.T @ (ops.K @ A))
    if ops.mixed:
        B = allreduce_sum(comm, ops.Kup.T @ A_local)  # (cells, G) = K_pu A
        kpp = allgather_rows(comm, ops.kpp)
        K = K - B.T @ (B / kpp[:, None])
    return (K + K.T) / 2


@dataclass
class CutOperators:
    """The global reduced operators the cuttable region carries (whole arrays, every rank).

    ``element_condensed_stiffness``: A^T K0 A, the pressure condensed element-wise
    (N/mm). With an element-wise pressure (else None): the global reduced pressure
    modes (canonical cell rows) and the reduced blocks A^T K_uu A, A^T K_up P, P^T K_pp P.
    """

    element_condensed_stiffness: np.ndarray
    pressure_modes: np.ndarray | None = None
    displacement_stiffness: np.ndarray | None = None
    pressure_coupling: np.ndarray | None = None
    pressure_stiffness: np.ndarray | None = None


def cut_operators(comm: MPI.Comm, ops, A_local, P_local, blocks) -> CutOperators:
    """The region's global operators from the global basis' rows ``A_local``, its pressure
    modes' rows ``P_local`` (or None) and its :func:`reduced_blocks` (collective)."""
    K_uu, K_up, K_pp = blocks
    condensed = condensed_reduced_stiffness(comm, ops, A_local, K_uu)
    if P_local is None:
        return CutOperators(condensed)
    # The coupling keeps the reduced pressure (ARTIFACT.md).
    return CutOperators(condensed, allgather_rows(comm, P_local), K_uu, K_up, K_pp)


# -- the region's cells and element matrices (rank 0, serial) ------------------------------
@dataclass
class CutRegion:
    """The cells of the cuttable region and their element matrices.

    ``cells`` (Rc,): mesh-file cell indices; ``nodes`` (Rn,): canonical nodes (sorted);
    ``coordinates`` (Rn, 3) mm; ``local_cells`` (Rc, 8): region node indices; ``fixed``
    (Rn,): the node keeps the reduced field; ``element_stiffness`` (Rc, 24, 24) N/mm with
    the pressure condensed per cell; the blocks before condensation K_uu, k_up, k_pp
    (the last two None without a pressure); ``pressure_cells`` (Rc,): each cell's
    canonical index (its row of the pressure modes).
    """

    cells: np.ndarray
    nodes: np.ndarray
    coordinates: np.ndarray
    local_cells: np.ndarray
    fixed: np.ndarray
    element_stiffness: np.ndarray
    displacement_stiffness: np.ndarray
    pressure_coupling: np.ndarray | None
    pressure_stiffness: np.ndarray | None
    pressure_cells: np.ndarray

    @property
    def dofs(self) -> np.ndarray:
        """The canonical DOFs of the region's nodes, 3 per node (x, y, z)."""
        return (3 * self.nodes[:, None] + np.arange(3)).ravel()


def cut_region(problem, cutting: CuttingConfig) -> CutRegion:
    """The region of ``cutting`` in the organ of ``problem`` (a ProblemConfig), on one rank."""
    # DOLFINx only here: CuttingConfig is read with the campaign's configuration.
    from hapticrom.offline.cutting.element_matrices import (
        canonical_cell_index,
        condense,
        element_blocks,
    )
    from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
    from hapticrom.offline.fe.materials import make_law
    from hapticrom.offline.fe.organ import load_organ

    nodes, cells, clamped = read_mesh_arrays(problem.mesh.file)
    centroid = nodes[cells].mean(axis=1)
    inside = np.linalg.norm(centroid - np.asarray(cutting.centre), axis=1) <= cutting.radius
    region_cells = np.flatnonzero(inside)
    if region_cells.size == 0:
        raise InputError(f"no cell lies within {cutting.radius} mm of {list(cutting.centre)}")
    region_nodes = np.unique(cells[region_cells])
    local = np.full(len(nodes), -1)
    local[region_nodes] = np.arange(len(region_nodes))
    fixed = np.isin(region_nodes, cells[~inside]) | np.isin(region_nodes, clamped)
    organ = load_organ(problem.mesh.file, MPI.COMM_SELF)
    law = make_law(problem.material.law, **problem.material.params)
    element = choose_element(organ.cell_type, problem.discretisation.element)
    model = HyperelasticModel(organ, law, element, problem.discretisation.quadrature_degree)
    K_uu, k_up, k_pp = element_blocks(model, region_cells, cells[region_cells])
    return CutRegion(
        cells=region_cells,
        nodes=region_nodes,
        coordinates=nodes[region_nodes],
        local_cells=local[cells[region_cells]],
        fixed=fixed,
        element_stiffness=condense(K_uu, k_up, k_pp),
        displacement_stiffness=K_uu,
        pressure_coupling=k_up,
        pressure_stiffness=k_pp,
        pressure_cells=canonical_cell_index(cells)[region_cells],
    )
