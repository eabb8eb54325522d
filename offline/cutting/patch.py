"""A reduced model coupled with a superimposed finite-element patch around a cut (thesis ch. 4).

The displacement is the reduced field everywhere plus a local field on a patch
of cells around the cut (thesis eqs. 4.2-4.5),

    u = T A zeta + S d,

with A the reduced basis of the intact organ (N x n, zero on the supports), T
the map from intact to cut-mesh DOFs (each copy of a duplicated node takes its
original's value: A zeta is continuous across the cut) and S the injection of
the patch's local DOFs: every node of the patch cells that belongs to no cell
outside the patch (so u^L = 0 on the patch's outer boundary, eq. 4.3) and to
no support. Inside the cut the local DOFs come in pairs, one per lip: this is
the Heaviside enrichment of eq. 4.5 for a cut that runs along element faces
(a node's standard and enriched DOFs d + b, d - b are the two lips' values),
which is what cutting whole elements amounts to when the blade follows the
mesh. The Galerkin system at the reference tangent K0 (eqs. 4.8-4.9) is

    [ A^T K0 A        (T A)^T K0c S ] [zeta]   [ (T A)^T f ]
    [ S^T K0c (T A)   S^T K0c S     ] [ d  ] = [ S^T f     ]

with K0 and K0c the intact and cut meshes' tangents (canonical CSR, pressure
condensed element-wise): A^T K0 A is the intact reduced stiffness, since T A
does not see the cut. Everything is in canonical DOF order (node i of the
mesh file, DOFs 3 i + c); serial numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse

from hapticrom.shared.errors import InputError


@dataclass
class CutPatch:
    """The superimposed patch: its cells and the nodes that carry local DOFs (cut mesh)."""

    cells: np.ndarray  # cut-mesh cell indices
    nodes: np.ndarray  # cut-mesh nodes with local DOFs (interior to the patch, unsupported)

    @property
    def dofs(self) -> np.ndarray:
        """The patch's displacement DOFs (3 per node, canonical numbering)."""
        return (3 * self.nodes[:, None] + np.arange(3)).ravel()


def patch_around(cells: np.ndarray, seeds: np.ndarray, layers: int, supported) -> CutPatch:
    """Cells within ``layers`` node-neighbourhood rings of the ``seeds`` nodes (the cut).

    ``cells`` (m, 8) of the cut mesh; ``supported``: nodes held by supports.
    """
    if layers < 1:
        raise InputError(f"the patch needs at least one layer of cells, got {layers}")
    in_patch = np.any(np.isin(cells, seeds), axis=1)
    for _ in range(layers - 1):
        in_patch |= np.any(np.isin(cells, np.unique(cells[in_patch])), axis=1)
    patch_nodes = np.unique(cells[in_patch])
    outside_nodes = np.unique(cells[~in_patch])
    nodes = np.setdiff1d(np.setdiff1d(patch_nodes, outside_nodes), np.asarray(list(supported)))
    return CutPatch(cells=np.flatnonzero(in_patch), nodes=nodes)


def continuation_map(origin: np.ndarray) -> scipy.sparse.csr_matrix:
    """T: intact DOFs -> cut-mesh DOFs, each node copy taking its original's value."""
    rows = np.arange(3 * len(origin))
    cols = (3 * origin[:, None] + np.arange(3)).ravel()
    return scipy.sparse.csr_matrix(
        (np.ones(rows.size), (rows, cols)), shape=(3 * len(origin), 3 * (origin.max() + 1))
    )


@dataclass
class CoupledModel:
    """The factorised coupled system of one cut state (dense: n + 3 * patch nodes unknowns)."""

    n: int
    patch: CutPatch
    TA: np.ndarray  # (N_cut, n): the reduced basis on the cut mesh
    factor: tuple  # scipy.linalg.cho_factor of the coupled matrix

    def solve(self, f_cut: np.ndarray) -> np.ndarray:
        """Cut-mesh displacement (N_cut,) under the load f_cut (N, cut-mesh DOFs)."""
        dofs = self.patch.dofs
        rhs = np.r_[self.TA.T @ f_cut, f_cut[dofs]]
        x = scipy.linalg.cho_solve(self.factor, rhs)
        u = self.TA @ x[: self.n]
        u[dofs] += x[self.n :]
        return u

    @property
    def size(self) -> int:
        """Unknowns of the coupled system: reduced coordinates plus patch DOFs."""
        return self.n + self.patch.dofs.size


def couple(K_intact, K_cut, A: np.ndarray, origin: np.ndarray, patch: CutPatch) -> CoupledModel:
    """Assemble and factorise the coupled system (thesis eq. 4.8) for one patch."""
    T = continuation_map(origin)
    TA = np.asarray(T @ A)
    dofs = patch.dofs
    K_cols = K_cut[:, dofs].toarray()  # (N_cut, m)
    K_zz = A.T @ (K_intact @ A)
    K_zd = TA.T @ K_cols
    K_dd = K_cols[dofs]
    K = np.block([[K_zz, K_zd], [K_zd.T, K_dd]])
    K = (K + K.T) / 2
    try:
        factor = scipy.linalg.cho_factor(K)
    except np.linalg.LinAlgError:
        raise InputError(
            "the coupled reduced + patch stiffness is not positive definite "
            "(a patch node without support from the reduced field?)"
        ) from None
    return CoupledModel(n=A.shape[1], patch=patch, TA=TA, factor=factor)


def relative_l2(u: np.ndarray, reference: np.ndarray, weights: np.ndarray | None = None) -> float:
    """||u - reference|| / ||reference|| with optional per-DOF weights (e.g. lumped volumes)."""
    w = np.ones_like(reference) if weights is None else weights
    return float(np.sqrt(np.sum(w * (u - reference) ** 2) / np.sum(w * reference**2)))
