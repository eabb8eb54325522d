"""Element stiffness matrices at the reference tangent, for the online cut patch (N/mm).

The runtime's cut patch (thesis eq. 4.9) assembles the stiffness of the cells
around a cut with the lips' own DOFs, so it needs each cell's matrix, not the
assembled K0. They come from the same UFL energy as everything else: the
cells are coloured so that no two cells of a colour share a node, the tangent
is assembled once per colour with an indicator of that colour's cells in the
energy, and each cell's block is then its own. With an element-wise pressure
(Q1P0, P2P0) the pressure is condensed cell by cell, exactly as in K0:

    K_c = K_uu,c - k_up,c k_pu,c / k_pp,c .

Rows and columns follow the cell's nodes in the mesh file's order, 3 DOFs
(x, y, z) per node. Serial (the patch is a region of one mesh).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import ufl
from dolfinx import fem

from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.formulation import HyperelasticModel
from hapticrom.shared.errors import InputError


def colour_cells(cells: np.ndarray) -> np.ndarray:
    """A colour per cell such that cells of one colour share no node (greedy, by index)."""
    colours = np.full(len(cells), -1)
    node_colours: dict[int, set] = {}
    for c, nodes in enumerate(cells):
        taken = set().union(*(node_colours.get(int(n), set()) for n in nodes))
        colour = next(k for k in range(len(cells) + 1) if k not in taken)
        colours[c] = colour
        for n in nodes:
            node_colours.setdefault(int(n), set()).add(colour)
    return colours


def _assemble_csr(form) -> scipy.sparse.csr_matrix:
    """A serial PETSc assembly as scipy CSR (DOLFINx's own CSR cannot mix block sizes)."""
    from dolfinx.fem.petsc import assemble_matrix

    A = assemble_matrix(form)
    A.assemble()
    indptr, indices, data = A.getValuesCSR()
    out = scipy.sparse.csr_matrix((data, indices, indptr), shape=A.getSize())
    A.destroy()
    return out


def element_stiffness(model: HyperelasticModel, msh_cells: np.ndarray, cell_nodes: np.ndarray):
    """K_c (len, 3 k, 3 k) of the mesh-file cells ``msh_cells`` whose nodes are ``cell_nodes``.

    ``cell_nodes`` (len, k): the cells' canonical (mesh-file) node indices; the
    matrices follow that node order. The model's state should be the reference
    (u = 0, p = 0). The element-wise pressure, if any, is condensed.
    """
    return condense(*element_blocks(model, msh_cells, cell_nodes))


def condense(K_uu: np.ndarray, k_up: np.ndarray | None, k_pp: np.ndarray | None) -> np.ndarray:
    """K_uu - k_up k_up^T / k_pp per cell (K_uu itself without a pressure), symmetrised."""
    K = K_uu if k_up is None else K_uu - k_up[:, :, None] * k_up[:, None, :] / k_pp[:, None, None]
    return (K + np.swapaxes(K, 1, 2)) / 2


def element_blocks(model: HyperelasticModel, msh_cells: np.ndarray, cell_nodes: np.ndarray):
    """(K_uu,c (len, 3 k, 3 k) N/mm, k_up,c (len, 3 k) mm^2, k_pp,c (len,) mm^3/MPa).

    The cells' tangent blocks before the pressure is condensed; the last two are
    None for a displacement-only element. Arguments as :func:`element_stiffness`.
    """
    mesh = model.organ.mesh
    if mesh.comm.size != 1:
        raise InputError("element matrices are computed on one process")
    if model.element.displacement_degree != 1:
        raise InputError("element matrices are available for linear elements (Q1, Q1P0)")
    if model.p is not None and model.element.pressure != "DG0":
        raise InputError("only an element-wise pressure can be condensed per cell")
    original = np.asarray(mesh.topology.original_cell_index)
    local_of = {int(o): i for i, o in enumerate(original)}
    try:
        local_cells = np.array([local_of[int(c)] for c in msh_cells])
    except KeyError as exc:
        raise InputError(f"cell {exc.args[0]} is not a cell of this mesh") from None
    order = CanonicalOrder(model.V)
    chi = fem.Function(fem.functionspace(mesh, ("DG", 0)))
    energy = chi * model.strain_energy_density() * model.dx
    unknowns = model.unknowns
    residuals = [ufl.derivative(energy, w, ufl.TestFunction(w.function_space)) for w in unknowns]
    forms = [
        [fem.form(ufl.derivative(R, w, ufl.TrialFunction(w.function_space))) for w in unknowns]
        for R in residuals
    ]
    k = cell_nodes.shape[1]
    Kuu = np.zeros((len(msh_cells), 3 * k, 3 * k))
    mixed = model.p is not None
    kup = np.zeros((len(msh_cells), 3 * k)) if mixed else None
    kpp = np.zeros(len(msh_cells)) if mixed else None
    colours = colour_cells(cell_nodes)
    for colour in np.unique(colours):
        members = np.flatnonzero(colours == colour)
        chi.x.array[:] = 0.0
        chi.x.array[local_cells[members]] = 1.0
        blocks = [[_assemble_csr(f) for f in row] for row in forms]
        for m in members:
            c = local_cells[m]
            # This cell's displacement DOFs, ordered as the mesh file's nodes of the cell.
            cell_blocks = model.V.dofmap.cell_dofs(c)
            canonical = order.canonical_dofs(cell_blocks)
            position = {int(n): i for i, n in enumerate(canonical)}
            try:
                ordered = np.array([cell_blocks[position[int(n)]] for n in cell_nodes[m]])
            except KeyError:
                raise InputError(f"cell {msh_cells[m]}: its nodes do not match the mesh") from None
            dofs = (3 * ordered[:, None] + np.arange(3)).ravel()
            K = blocks[0][0][dofs][:, dofs].toarray()
            Kuu[m] = (K + K.T) / 2
            if mixed:
                q = model.Q.dofmap.cell_dofs(c)[0]
                kup[m] = blocks[0][1][dofs][:, [q]].toarray().ravel()
                kpp[m] = blocks[1][1][q, q]
    return Kuu, kup, kpp


def canonical_cell_index(cells: np.ndarray) -> np.ndarray:
    """Canonical index of each mesh-file cell: the order of an element-wise pressure's
    DOFs in snapshots and operators (cells sorted by their sorted node ids, as
    :class:`~hapticrom.offline.fe.dofs.CanonicalOrder` does for a DG0 space)."""
    keys = np.sort(cells, axis=1)
    order = np.lexsort(keys.T[::-1])
    index = np.empty(len(cells), dtype=np.int64)
    index[order] = np.arange(len(cells))
    return index
