"""Full-order operators for the reduced models, in canonical DOF order (N/mm, mm^3, N).

- The tangent stiffness at the reference state, K0 (thesis ch. 2: the reduced
  linear model is A^T K0 A). With an element-wise pressure (Q1P0, P2P0) the
  pressure is condensed out exactly, K0 = K_uu - K_up K_pp^-1 K_pu (K_pp is
  diagonal), so K0 acts on displacements only. No boundary condition is applied:
  reduced bases vanish on the supports, which is what imposes them.
- Lumped volume weights (the row sums of the consistent mass matrix with unit
  density, mm^3), for an L2-like inner product in the POD.
- External load vectors of a force-controlled tool at load factor 1.

Each is assembled on the mesh's communicator and returned on rank 0 as a
``scipy.sparse.csr_matrix`` or a numpy array in canonical order.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_matrix
from dolfinx.la import InsertMode
from petsc4py import PETSc

from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.formulation import HyperelasticModel
from hapticrom.shared.errors import InputError


def _to_canonical_csr(
    A: PETSc.Mat, rows_order: CanonicalOrder, cols_order: CanonicalOrder | None = None
) -> scipy.sparse.csr_matrix | None:
    """Gather a PETSc matrix to rank 0 with rows and columns in canonical order."""
    cols_order = cols_order or rows_order
    indptr, cols, vals = A.getValuesCSR()
    rstart, _ = A.getOwnershipRange()
    rows = rstart + np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
    rows = rows_order.global_dofs_to_canonical(rows)
    cols = cols_order.global_dofs_to_canonical(cols)
    gathered = rows_order.comm.gather((rows, cols, vals), root=0)
    if gathered is None:
        return None
    rows, cols, vals = (np.concatenate(part) for part in zip(*gathered, strict=True))
    shape = (rows_order.num_dofs, cols_order.num_dofs)
    K = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=shape)
    K.sum_duplicates()
    K.sort_indices()
    return K


def _require_condensable(model: HyperelasticModel) -> None:
    if model.p is not None and model.element.pressure != "DG0":
        raise InputError(
            f"element {model.element.name}: only an element-wise (DG0) pressure can be "
            "condensed out of the tangent; use Q1P0/P2P0 or a displacement-only element"
        )


def tangent_blocks(model: HyperelasticModel, order_u: CanonicalOrder, order_p: CanonicalOrder):
    """The blocks of the mixed tangent at the model's state, canonical, on rank 0.

    Returns ``{"Kuu": CSR (N/mm), "Kup": CSR (mm^2), "Kpp": diagonal (mm^3/MPa)}``
    (K_pu = K_up^T: the tangent is the Hessian of an energy); None off rank 0.
    """
    _require_condensable(model)
    residuals = model.residual_forms(include_load=False)
    forms = model.jacobian_forms(residuals)
    mats = {}
    for name, (i, j) in {"Kuu": (0, 0), "Kup": (0, 1), "Kpp": (1, 1)}.items():
        M = assemble_matrix(fem.form(forms[i][j]))
        M.assemble()
        if name == "Kpp":
            d = M.getDiagonal()
            mats[name] = order_p.gather(d.getArray())
            d.destroy()
        else:
            mats[name] = _to_canonical_csr(M, order_u, order_p if j == 1 else order_u)
        M.destroy()
    return mats if order_u.comm.rank == 0 else None


def reference_tangent(model: HyperelasticModel, order: CanonicalOrder):
    """K0 (N/mm) at the state of ``model`` (normally u = 0, p = 0), pressure condensed.

    Returns the canonical CSR matrix on rank 0 (None elsewhere).
    """
    _require_condensable(model)
    residuals = model.residual_forms(include_load=False)
    blocks = model.jacobian_forms(residuals)
    Kuu = assemble_matrix(fem.form(blocks[0][0]))
    Kuu.assemble()
    if model.p is not None:
        Kup, Kpu, Kpp = (
            assemble_matrix(fem.form(blocks[i][j])) for i, j in ((0, 1), (1, 0), (1, 1))
        )
        for M in (Kup, Kpu, Kpp):
            M.assemble()
        inv_diag = Kpp.getDiagonal()
        inv_diag.reciprocal()
        Kup.diagonalScale(R=inv_diag)  # K_up K_pp^-1: K_pp is diagonal for DG0 pressures
        correction = Kup.matMult(Kpu)
        Kuu.axpy(-1.0, correction, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        for M in (Kup, Kpu, Kpp, correction):
            M.destroy()
    K = _to_canonical_csr(Kuu, order)
    Kuu.destroy()
    return K


def lumped_volumes(V: fem.FunctionSpace, order: CanonicalOrder, quadrature_degree: int):
    """Row sums of the unit-density mass matrix (mm^3) per DOF, canonical, on rank 0."""
    v = ufl.TestFunction(V)
    ones = fem.Constant(V.mesh, np.ones(3))
    dx = ufl.Measure("dx", domain=V.mesh, metadata={"quadrature_degree": quadrature_degree})
    b = fem.assemble_vector(fem.form(ufl.dot(ones, v) * dx))
    b.scatter_reverse(InsertMode.add)
    return order.gather(b.array)


def load_vector(model: HyperelasticModel, order: CanonicalOrder):
    """d(external work)/du at the model's current traction (N per DOF), canonical, on rank 0."""
    v = ufl.TestFunction(model.V)
    form = fem.form(ufl.derivative(model.external_work(), model.u, v))
    b = fem.assemble_vector(form)
    b.scatter_reverse(InsertMode.add)
    return order.gather(b.array)
