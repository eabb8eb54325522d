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
incompressible tissue).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.shared.errors import InputError


@dataclass(frozen=True)
class CuttingConfig:
    centre: tuple[float, float, float]
    radius: float  # mm
    patch_layers: int = 2
    cut_force: float = 0.02  # N: the blade force above which a face is cut (thesis eq. 4.10)


def read_mesh_arrays(mesh_file):
    """(nodes (n, 3) mm, hexahedra (m, 8) in the file's node order, clamped nodes) on one rank."""
    from hapticrom.meshes.msh import _read_msh_group

    tags, coords, clamped, cells = _read_msh_group(Path(mesh_file), "clamped")
    order = np.argsort(tags)
    if not np.array_equal(tags[order], np.arange(1, len(tags) + 1)):
        raise InputError(f"{mesh_file}: node tags are not 1..n (not a hapticrom mesh?)")
    if cells.shape[1] != 8:
        raise InputError("cutting needs a hexahedral mesh")
    return coords[order], cells - 1, np.unique(clamped - 1)


def condensed_reduced_stiffness(comm: MPI.Comm, ops, A_local: np.ndarray, K_r=None) -> np.ndarray:
    """A^T K0 A with the pressure condensed element-wise (distributed rows of A).

    ``K_r``: A^T K A (K_uu if mixed) when already computed (``reduction.reduced_blocks``).
    """
    from hapticrom.offline.reduce.reduction import _allgather_rows, _sum

    K = K_r
    if K is None:
        A = _allgather_rows(comm, A_local)  # the operators' rows span all columns
        K = _sum(comm, A_local.T @ (ops.K @ A))
    if ops.mixed:
        B = _sum(comm, ops.Kup.T @ A_local)  # (cells, G) = K_pu A
        kpp = _allgather_rows(comm, ops.kpp)
        K = K - B.T @ (B / kpp[:, None])
    return (K + K.T) / 2


def cutting_group(
    config, cutting: CuttingConfig, basis: np.ndarray, reduced_stiffness, pressure=None
) -> dict:
    """The artifact group (rank 0, serial): region arrays and element matrices.

    ``pressure``: for an element-wise pressure, the global reduced pressure modes
    (``pressure_modes``, canonical cell rows) and the reduced blocks
    (``reduced_*`` datasets): the coupling then keeps the reduced pressure outside
    the cut patch (format 1.3).
    """
    from hapticrom.offline.cutting.element_matrices import (
        canonical_cell_index,
        condense,
        element_blocks,
    )
    from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
    from hapticrom.offline.fe.materials import make_law
    from hapticrom.offline.fe.organ import load_organ

    problem = config.problem
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
    matrices = condense(K_uu, k_up, k_pp)
    rows = (3 * region_nodes[:, None] + np.arange(3)).ravel()
    extra = {}
    if pressure is not None and k_up is not None:
        extra = {
            "element_displacement_stiffness": K_uu,
            "element_pressure_coupling": k_up,
            "element_pressure_stiffness": k_pp,
            "pressure_basis": pressure["pressure_modes"][canonical_cell_index(cells)[region_cells]],
            **{k: v for k, v in pressure.items() if k.startswith("reduced_")},
        }
    return {
        **extra,
        "nodes": region_nodes.astype(np.int64),
        "coordinates": nodes[region_nodes],
        "cells": local[cells[region_cells]].astype(np.int64),
        "element_stiffness": matrices,
        "basis": np.ascontiguousarray(basis[rows]),
        "fixed": fixed.astype(np.int8),
        "reduced_stiffness": reduced_stiffness,
        "attrs": {
            "centre": list(cutting.centre),
            "radius": cutting.radius,
            "patch_layers": cutting.patch_layers,
            "cut_force": cutting.cut_force,
            "cells_in_region": int(len(region_cells)),
        },
    }
