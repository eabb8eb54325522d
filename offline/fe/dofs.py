"""A numbering of displacement DOFs that does not depend on how the mesh is partitioned.

DOLFINx numbers DOFs by rank ownership, so the same mesh on 1, 2 or 64 ranks
(or in an MPI sub-communicator of a campaign) gives different global numbers.
Snapshots, stiffness matrices and reduced bases must not depend on that: they
are stored in the **canonical order** defined here.

Each node (block of 3 DOFs, x y z) of a vector Lagrange space of degree <= 2 is
attached to one mesh entity (vertex, edge, face or cell). Its key is the sorted
list of the *input* indices (the order in the .msh file) of that entity's
vertices. Canonical order: vertices first, by input index (so for linear
elements the canonical node order is the mesh file's node order), then the
other entities by their sorted vertex lists. Canonical DOF ``3*i + c`` is
component c of canonical node i.
"""

from __future__ import annotations

import dolfinx
import numpy as np
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from hapticrom.shared.errors import InputError

MAX_ENTITY_VERTICES = 8


def _node_keys(V: fem.FunctionSpace) -> np.ndarray:
    """Keys (num local blocks, 1 + 8) int64: entity dimension, then sorted input vertex ids."""
    mesh = V.mesh
    topology = mesh.topology
    tdim = topology.dim
    num_vertices = topology.index_map(0).size_local + topology.index_map(0).num_ghosts
    topology.create_connectivity(0, tdim)
    vertex_nodes = dolfinx.mesh.entities_to_geometry(
        mesh, 0, np.arange(num_vertices, dtype=np.int32)
    )[:, 0]
    input_index = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[vertex_nodes]

    im = V.dofmap.index_map
    keys = np.full((im.size_local + im.num_ghosts, 1 + MAX_ENTITY_VERTICES), -1, dtype=np.int64)
    cell_dofs = V.dofmap.list
    layout = V.dofmap.dof_layout
    for dim in range(tdim + 1):
        topology.create_connectivity(tdim, dim)
        topology.create_connectivity(dim, 0)
        cell_to_entity = topology.connectivity(tdim, dim)
        entity_to_vertex = topology.connectivity(dim, 0)
        num_local_entities = dolfinx.cpp.mesh.cell_num_entities(topology.cell_type, dim)
        for local_entity in range(num_local_entities):
            positions = layout.entity_dofs(dim, local_entity)
            if len(positions) == 0:
                continue
            if len(positions) > 1:
                raise InputError("canonical DOF order supports Lagrange degree <= 2 only")
            blocks = cell_dofs[:, positions[0]]
            entities = cell_to_entity.array.reshape(len(cell_dofs), -1)[:, local_entity]
            offsets = entity_to_vertex.offsets
            nv = offsets[1] - offsets[0]
            verts = entity_to_vertex.array.reshape(-1, nv)[entities]
            ids = np.sort(input_index[verts], axis=1)
            keys[blocks, 0] = dim
            keys[blocks, 1 : 1 + nv] = ids
    if np.any(keys[:, 0] < 0):
        raise RuntimeError("a DOF is attached to no mesh entity")
    return keys


class CanonicalOrder:
    """Canonical node numbering of a Lagrange space (block size bs = 3 for
    displacements, 1 for an element-wise pressure), on every rank.

    Attributes:
        num_nodes: global number of nodes (blocks); DOFs are bs * num_nodes.
        canonical_of_global: (num_nodes,) canonical index of each DOLFINx global block.
        owned: canonical indices of this rank's owned blocks, in local order.
    """

    def __init__(self, V: fem.FunctionSpace):
        self.bs = V.dofmap.index_map_bs
        if self.bs not in (1, 3):
            raise ValueError("CanonicalOrder expects a scalar or a 3-component vector space")
        self.V, self.comm = V, V.mesh.comm
        im = V.dofmap.index_map
        self.size_local = im.size_local
        self.num_nodes = im.size_global
        keys = _node_keys(V)[: im.size_local]
        first = im.local_range[0]
        all_keys = np.concatenate(self.comm.allgather(keys))
        all_globals = np.concatenate(
            self.comm.allgather(np.arange(first, first + im.size_local, dtype=np.int64))
        )
        order = np.lexsort(all_keys.T[::-1])  # by dimension, then vertex ids
        sorted_keys = all_keys[order]
        if np.any(np.all(sorted_keys[1:] == sorted_keys[:-1], axis=1)):
            raise RuntimeError("two DOF nodes share a canonical key")
        self.canonical_of_global = np.empty(self.num_nodes, dtype=np.int64)
        self.canonical_of_global[all_globals[order]] = np.arange(self.num_nodes)
        self.owned = self.canonical_of_global[first : first + im.size_local]
        counts = self.comm.allgather(im.size_local)
        self._counts = np.asarray(counts) * self.bs
        # Where each rank's owned nodes go in canonical order (for gathers to any root).
        self._positions = np.concatenate(self.comm.allgather(self.owned))

    @property
    def num_dofs(self) -> int:
        """Global number of DOFs, bs * num_nodes."""
        return self.bs * self.num_nodes

    def canonical_dofs(self, local_blocks: np.ndarray) -> np.ndarray:
        """Canonical node indices of local block indices (owned or ghost)."""
        im = self.V.dofmap.index_map
        global_blocks = im.local_to_global(np.asarray(local_blocks, dtype=np.int32))
        return self.canonical_of_global[global_blocks]

    def global_dofs_to_canonical(self, dofs: np.ndarray) -> np.ndarray:
        """DOLFINx global (unblocked) DOF numbers -> canonical DOF numbers."""
        # (for bs = 3: node i's components are canonical DOFs 3 i, 3 i + 1, 3 i + 2)
        dofs = np.asarray(dofs, dtype=np.int64)
        bs = self.bs
        return bs * self.canonical_of_global[dofs // bs] + dofs % bs

    def gather(self, values: np.ndarray, root: int = 0) -> np.ndarray | None:
        """Owned DOF values (bs * size_local, local order) -> canonical (bs N,) array on root."""
        local = np.ascontiguousarray(values[: self.bs * self.size_local], dtype=np.float64)
        if self.comm.rank != root:
            self.comm.Gatherv(local, None, root=root)
            return None
        received = np.empty(self._counts.sum(), dtype=np.float64)
        self.comm.Gatherv(local, (received, self._counts), root=root)
        out = np.empty((self.num_nodes, self.bs))
        out[self._positions] = received.reshape(-1, self.bs)
        return out.reshape(-1)

    def gather_blocks(self, local_blocks: np.ndarray, root: int = 0) -> np.ndarray | None:
        """Sorted unique canonical node indices of a set of local blocks, on root."""
        owned = local_blocks[local_blocks < self.size_local]
        found = self.comm.gather(self.canonical_dofs(owned), root=root)
        return None if found is None else np.unique(np.concatenate(found))

    def scatter_owned(self, canonical: np.ndarray) -> np.ndarray:
        """This rank's owned values (bs * size_local,) from a full canonical (bs N,) array."""
        return np.asarray(canonical).reshape(-1, self.bs)[self.owned].reshape(-1)


def owned_canonical_rows(comm: MPI.Comm, n: int) -> tuple[int, int]:
    """The contiguous block [start, stop) of n canonical rows this rank holds in the POD.

    PETSc's split (``PetscSplitOwnership``): the first ``n % size`` ranks hold one row more.
    Collective.
    """
    local, _ = PETSc.Sys.splitOwnership(n, comm=comm)
    start = comm.exscan(local) or 0  # rank 0 receives None
    return start, start + local
