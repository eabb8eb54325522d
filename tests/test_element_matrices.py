"""Element stiffness matrices for the cut patch, against the assembled reference tangent K0."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.meshes import build
from hapticrom.offline.cutting.element_matrices import (
    canonical_cell_index,
    colour_cells,
    element_blocks,
    element_stiffness,
)
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
from hapticrom.offline.fe.materials import make_law
from hapticrom.offline.fe.operators import reference_tangent, tangent_blocks
from hapticrom.offline.fe.organ import load_organ
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial


@pytest.fixture(scope="module", params=["hgo", "svk"])
def cornea(mesh_dir, request):
    from mpi4py import MPI

    organ = load_organ(mesh_dir / "cornea-coarse.msh", MPI.COMM_SELF)
    law = make_law(request.param) if request.param == "hgo" else make_law("svk", E=0.5, nu=0.45)
    model = HyperelasticModel(organ, law, choose_element("hexahedron", "Q1P0"))
    return model, build("cornea", "coarse")


def test_element_matrices_assemble_to_the_reference_tangent(cornea):
    model, mesh = cornea
    Ke = element_stiffness(model, np.arange(len(mesh.cells)), mesh.cells)
    K0 = reference_tangent(model, CanonicalOrder(model.V))
    dofs = (3 * mesh.cells[:, :, None] + np.arange(3)).reshape(len(mesh.cells), -1)
    rows = np.repeat(dofs, dofs.shape[1], axis=1).ravel()
    cols = np.tile(dofs, dofs.shape[1]).ravel()
    K = scipy.sparse.csr_matrix((Ke.ravel(), (rows, cols)), shape=K0.shape)
    assert abs(K - K0).max() <= 1e-12 * abs(K0).max()
    # Each is symmetric and free of stress at the reference: rigid motions cost nothing.
    for c in (0, len(mesh.cells) // 2, len(mesh.cells) - 1):
        np.testing.assert_allclose(Ke[c], Ke[c].T, atol=1e-14 * np.abs(Ke[c]).max())
        x = mesh.nodes[mesh.cells[c]]
        for motion in (np.tile(np.eye(3)[0], 8), np.cross([0.0, 0.0, 1.0], x).ravel()):
            assert np.abs(Ke[c] @ motion).max() <= 1e-10 * np.abs(Ke[c]).max()
        assert np.linalg.eigvalsh(Ke[c]).min() >= -1e-10 * np.abs(Ke[c]).max()


def test_element_blocks_assemble_to_the_mixed_tangent(cornea):
    """K_uu,c, k_up,c, k_pp,c before condensation: DOLFINx's canonical blocks, cell by cell
    (the pressure DOF of mesh-file cell c is canonical_cell_index(cells)[c])."""
    model, mesh = cornea
    cells = mesh.cells
    K_uu, k_up, k_pp = element_blocks(model, np.arange(len(cells)), cells)
    reference = tangent_blocks(model, CanonicalOrder(model.V), CanonicalOrder(model.Q))
    pressure_dof = canonical_cell_index(cells)
    dofs = (3 * cells[:, :, None] + np.arange(3)).reshape(len(cells), -1)
    Kuu = reference["Kuu"]
    rows = np.repeat(dofs, dofs.shape[1], axis=1).ravel()
    cols = np.tile(dofs, dofs.shape[1]).ravel()
    assembled = scipy.sparse.csr_matrix((K_uu.ravel(), (rows, cols)), shape=Kuu.shape)
    assert abs(assembled - Kuu).max() <= 1e-12 * abs(Kuu).max()
    np.testing.assert_allclose(k_pp, reference["Kpp"][pressure_dof], rtol=1e-12)
    assert np.all(k_pp < 0)  # minus volume over bulk modulus
    Kup = reference["Kup"].tocsc()
    for c in (0, len(cells) // 3, len(cells) - 1):
        column = Kup[:, pressure_dof[c]].toarray().ravel()
        assert np.abs(column[dofs[c]] - k_up[c]).max() <= 1e-12 * np.abs(column).max()
        assert np.count_nonzero(np.delete(column, dofs[c])) == 0  # no other cell's DOFs
    # Condensed, they are the element stiffness.
    condensed = K_uu - k_up[:, :, None] * k_up[:, None, :] / k_pp[:, None, None]
    np.testing.assert_allclose(
        element_stiffness(model, np.arange(3), cells[:3]), condensed[:3],
        atol=1e-12 * np.abs(condensed).max(),
    )  # fmt: skip


def test_a_region_and_its_order(cornea):
    model, mesh = cornea
    subset = np.array([7, 3, 100])
    Ke = element_stiffness(model, subset, mesh.cells[subset])
    full = element_stiffness(model, np.arange(len(mesh.cells)), mesh.cells)
    np.testing.assert_allclose(Ke, full[subset], rtol=0, atol=1e-14 * np.abs(full).max())
    # Reversing a cell's node order reverses the matrix's node blocks.
    flipped = mesh.cells[[7]][:, ::-1]
    K_flip = element_stiffness(model, np.array([7]), flipped)[0]
    perm = (3 * np.arange(8)[::-1][:, None] + np.arange(3)).ravel()
    np.testing.assert_allclose(K_flip, full[7][perm][:, perm], atol=1e-14 * np.abs(full).max())
    with pytest.raises(InputError, match="not a cell"):
        element_stiffness(model, np.array([10**6]), mesh.cells[:1])


def test_colours_share_no_node():
    cells = build("cornea", "coarse").cells
    colours = colour_cells(cells)
    for colour in np.unique(colours):
        nodes = cells[colours == colour].ravel()
        assert len(nodes) == len(np.unique(nodes))
    assert colours.max() + 1 <= 27  # hexahedra: at most 27 cells meet
