"""The cut patch coupled with the reduced model (thesis eq. 4.8): region data, factorisation.

numpy only. The offline side exports, for a cuttable region of the organ, its
cells, their element stiffness matrices at the reference tangent, the reduced
basis rows at its nodes and which nodes must stay continuous (the region's
boundary and the supports): a :class:`CutRegion`. :class:`CoupledPatch` builds
the superimposed patch around the cuts of a
:class:`~hapticrom.shared.cut_topology.CutTopology` and the coupled system
(reduced coordinates + the patch's local DOFs, with one DOF set per lip:
Heaviside enrichment of a face-aligned cut), factorises it once per topology
change, and solves it for a load. With an element-wise pressure
(:class:`PressureCoupling`) the reduced part keeps the reduced pressure basis
outside the patch, so nearly incompressible tissue does not lock; the patch's
cells keep their own pressures.

Units: mm, N, N/mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapticrom.shared.cut_topology import CutTopology
from hapticrom.shared.errors import InputError


@dataclass
class PressureCoupling:
    """What a consistent coupling needs when the element has an element-wise pressure.

    The reduced model keeps its pressure in a reduced basis (locking-free, as the
    reduced model everywhere else); the patch's cells keep their own pressure,
    condensed cell by cell. So the patch's cells are taken out of the reduced
    blocks and put back with their own pressures. Per region cell: ``displacement``
    K_uu,c (C, 24, 24) N/mm, ``coupling`` k_up,c (C, 24) mm^2, ``pressure`` k_pp,c
    (C,) mm^3/MPa (< 0), ``pressure_basis`` (C, P) the reduced pressure modes' cell
    values. Reduced, over the whole organ: ``reduced_displacement`` A^T K_uu A
    (G, G), ``reduced_coupling`` A^T K_up P (G, P), ``reduced_pressure`` P^T K_pp P (P, P).
    """

    displacement: np.ndarray
    coupling: np.ndarray
    pressure: np.ndarray
    pressure_basis: np.ndarray
    reduced_displacement: np.ndarray
    reduced_coupling: np.ndarray
    reduced_pressure: np.ndarray

    def outside(self, cells: np.ndarray, cell_basis: np.ndarray) -> tuple:
        """(A^T K_uu A, A^T K_up P, P^T K_pp P) of the cells not in ``cells``.

        ``cell_basis`` (len(cells), 24, G): the reduced basis rows at those cells' nodes.
        """
        psi = self.pressure_basis[cells]  # (c, P)
        G = cell_basis.shape[2]
        KA = self.displacement[cells] @ cell_basis  # (c, 24, G)
        A = self.reduced_displacement - cell_basis.reshape(-1, G).T @ KA.reshape(-1, G)
        coupling = np.einsum("cig,ci->cg", cell_basis, self.coupling[cells])
        B = self.reduced_coupling - coupling.T @ psi
        C = self.reduced_pressure - (self.pressure[cells][:, None] * psi).T @ psi
        return A, B, C

    def consistency(self, cells: int, modes: int) -> dict[str, bool]:
        """Which of its arrays fit a region of ``cells`` cells and ``modes`` global modes."""
        P = self.reduced_pressure.shape[0]
        C, G = cells, modes
        return {
            "displacement stiffness": self.displacement.shape == (C, 24, 24),
            "pressure coupling": self.coupling.shape == (C, 24),
            "pressure stiffness": self.pressure.shape == (C,),
            "pressure basis": self.pressure_basis.shape == (C, P),
            "reduced displacement": self.reduced_displacement.shape == (G, G),
            "reduced coupling": self.reduced_coupling.shape == (G, P),
            "reduced pressure": self.reduced_pressure.shape == (P, P),
            "pressure stiffness sign (k_pp < 0)": bool(np.all(self.pressure < 0)),
        }


@dataclass
class CutRegion:
    """What the runtime knows of the cuttable region (region-local node numbering).

    ``coordinates`` (R, 3) mm; ``cells`` (C, 8) hexahedra; ``element_stiffness``
    (C, 24, 24) N/mm, DOFs 3 i + c of the cell's nodes in order; ``basis`` (3 R, G)
    rows of the reduced basis; ``fixed`` (R,) bool: nodes whose local field is
    zero (on the region's boundary or supported); ``reduced_stiffness`` (G, G).
    Inconsistent shapes raise :class:`~hapticrom.shared.errors.InputError`.
    """

    coordinates: np.ndarray
    cells: np.ndarray
    element_stiffness: np.ndarray
    basis: np.ndarray
    fixed: np.ndarray
    reduced_stiffness: np.ndarray
    pressure: PressureCoupling | None = None

    def __post_init__(self):
        R, C = len(self.coordinates), len(self.cells)
        G = self.reduced_stiffness.shape[0]
        checks = {
            "cells": self.cells.shape == (C, 8) and self.cells.min() >= 0
            and self.cells.max() < R,
            "element_stiffness": self.element_stiffness.shape == (C, 24, 24),
            "basis": self.basis.shape == (3 * R, G),
            "fixed": self.fixed.shape == (R,),
            "reduced_stiffness": self.reduced_stiffness.shape == (G, G),
        }  # fmt: skip
        if self.pressure is not None:
            checks |= self.pressure.consistency(C, G)
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise InputError(f"cut region: inconsistent {', '.join(bad)}")

    def intact_topology(self) -> CutTopology:
        """The region's cells with nothing cut yet."""
        return CutTopology(self.cells, len(self.coordinates))


class CoupledPatch:
    """The factorised coupled system (thesis eq. 4.8) of one cut topology of a region.

    ``cells``: the patch's cells (region cell indices), ``nodes``: its nodes with
    local DOFs (in the topology's numbering), ``size``: unknowns (G reduced
    coordinates first, then 3 per node), ``factor``: the Cholesky factor.
    """

    def __init__(
        self,
        topology: CutTopology,
        region: CutRegion,
        layers: int = 2,
        patch_cells: np.ndarray | None = None,
    ):
        """``patch_cells``: use these cells instead of ``layers`` rings around the cut."""
        if layers < 1:
            raise InputError(f"the patch needs at least one layer of cells, got {layers}")
        self.region, self.topology = region, topology
        self.cells, self.nodes = self._select(topology, region, layers, patch_cells)
        self.G = region.reduced_stiffness.shape[0]
        K = self._assemble()
        self.size = K.shape[0]
        self.factor = np.linalg.cholesky((K + K.T) / 2)  # raises LinAlgError if not SPD

    @staticmethod
    def _select(topology: CutTopology, region: CutRegion, layers: int, patch_cells) -> tuple:
        """(the patch's cells, its nodes with local DOFs): ``layers`` rings of cells around
        the lips (or ``patch_cells``), and their nodes that are neither shared with the
        cells outside nor fixed."""
        cells = topology.cells
        if patch_cells is None:
            in_patch = np.any(np.isin(cells, topology.lip_nodes), axis=1)
            for _ in range(layers - 1):
                in_patch |= np.any(np.isin(cells, np.unique(cells[in_patch])), axis=1)
        else:
            in_patch = np.zeros(len(cells), dtype=bool)
            in_patch[patch_cells] = True
        outside = np.unique(cells[~in_patch])
        fixed = region.fixed[topology.origin]
        candidates = np.unique(cells[in_patch])
        nodes = candidates[~np.isin(candidates, outside) & ~fixed[candidates]]
        return np.flatnonzero(in_patch), nodes

    def _assemble(self) -> np.ndarray:
        """The coupled stiffness [[K_zz, K_dz^T], [K_dz, K_dd]] (N/mm)."""
        topology, region, G = self.topology, self.region, self.G
        m = 3 * len(self.nodes)
        index = np.full(len(topology.origin), -1)
        index[self.nodes] = np.arange(len(self.nodes))
        conn = topology.cells[self.cells]  # (c, 8) nodes of the patch cells, lips apart
        # The reduced field does not see the cut: each copy takes its original's rows.
        basis = region.basis[(3 * topology.origin[conn][:, :, None] + np.arange(3)).reshape(
            len(conn), 24)]  # (c, 24, G)  # fmt: skip
        Ke = region.element_stiffness[self.cells]  # (c, 24, 24)
        KA = Ke @ basis  # (c, 24, G); Ke is symmetric: (A_c^T Ke)^T
        if region.pressure is None:
            K_zz = region.reduced_stiffness.copy()
        else:
            # Reduced pressure outside the patch, the cells' own pressures inside it.
            A, B, C = region.pressure.outside(self.cells, basis)
            K_zz = A - B @ np.linalg.solve(C, B.T) + basis.reshape(-1, G).T @ KA.reshape(-1, G)
        dofs = (3 * index[conn][:, :, None] + np.arange(3)).reshape(len(conn), 24)
        keep = dofs >= 0
        K_dz = np.zeros((m, G))
        np.add.at(K_dz, dofs[keep], KA[keep])
        both = keep[:, :, None] & keep[:, None, :]
        rows = np.broadcast_to(dofs[:, :, None], both.shape)[both]
        columns = np.broadcast_to(dofs[:, None, :], both.shape)[both]
        K_dd = np.bincount(rows * m + columns, Ke[both], m * m).reshape(m, m)
        return np.block([[K_zz, K_dz.T], [K_dz, K_dd]])

    @property
    def dofs(self) -> np.ndarray:
        """The local DOFs' indices in a region displacement vector (3 per patch node)."""
        return (3 * self.nodes[:, None] + np.arange(3)).ravel()

    def solve(self, load_reduced: np.ndarray, load_patch: np.ndarray) -> np.ndarray:
        """[zeta, d] for the reduced load A^T f (G,) and the load on the patch DOFs."""
        L = self.factor
        y = solve_lower(L, np.r_[load_reduced, load_patch])
        return solve_lower(L, y, transposed=True)

    def region_displacement(self, x: np.ndarray) -> np.ndarray:
        """Displacement (mm) of every node of the cut region (copies included), (R', 3)."""
        topology, region = self.topology, self.region
        rows = (3 * topology.origin[:, None] + np.arange(3)).ravel()
        u = region.basis[rows] @ x[: self.G]
        u[self.dofs] += x[self.G :]
        return u.reshape(-1, 3)


def compliance(patch: CoupledPatch, B: np.ndarray) -> np.ndarray:
    """b^T K^-1 b for every column b of B, from the Cholesky factor: |L^-1 b|^2."""
    Y = solve_lower(patch.factor, B)
    return np.sum(Y * Y, axis=0)


def solve_lower(L: np.ndarray, B: np.ndarray, transposed: bool = False, block: int = 128):
    """L^-1 B (or L^-T B) for a lower-triangular L, by blocks.

    numpy has no triangular solve, and np.linalg.solve factorises L again (2/3 n^3):
    here only the diagonal blocks are solved, the rest is matrix products.
    """
    n = L.shape[0]
    Y = np.empty(B.shape)
    starts = list(range(0, n, block))
    if not transposed:
        for i0 in starts:
            i1 = min(i0 + block, n)
            rhs = B[i0:i1] - L[i0:i1, :i0] @ Y[:i0]
            Y[i0:i1] = np.linalg.solve(L[i0:i1, i0:i1], rhs)
    else:  # L^T is upper triangular: from the last block up
        for i0 in reversed(starts):
            i1 = min(i0 + block, n)
            rhs = B[i0:i1] - L[i1:, i0:i1].T @ Y[i1:]
            Y[i0:i1] = np.linalg.solve(L[i0:i1, i0:i1].T, rhs)
    return Y
