"""Cuts at run time: a cut region's topology and its patch coupled with the reduced model.

numpy only (the runtime's dependencies). The offline side exports, for a
cuttable region of the organ, its cells, their element stiffness matrices at
the reference tangent, the reduced basis rows at its nodes and which nodes
must stay continuous (the region's boundary and the supports). Here:

- :class:`CutTopology` cuts faces of the region one event at a time: the
  nodes inside the cut get one copy per side, the cut's front stays joined
  (the same rule as the explicit cut meshes of :mod:`hapticrom.meshes.cut`);
- :class:`CutPatch` builds the superimposed patch around the cut and the
  coupled system of thesis eq. 4.8 (reduced coordinates + the patch's local
  DOFs, with one DOF set per lip: Heaviside enrichment of a face-aligned cut),
  factorises it once per topology change, and solves it for a load.

Units: mm, N, N/mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HEX_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [0, 4, 7, 3], [1, 2, 6, 5]]
)


@dataclass
class CutRegion:
    """What the runtime knows of the cuttable region (region-local node numbering).

    ``coordinates`` (R, 3) mm; ``cells`` (C, 8) hexahedra; ``element_stiffness``
    (C, 24, 24) N/mm, DOFs 3 i + c of the cell's nodes in order; ``basis`` (3 R, G)
    rows of the reduced basis; ``fixed`` (R,) bool: nodes whose local field is
    zero (on the region's boundary or supported); ``reduced_stiffness`` (G, G).
    """

    coordinates: np.ndarray
    cells: np.ndarray
    element_stiffness: np.ndarray
    basis: np.ndarray
    fixed: np.ndarray
    reduced_stiffness: np.ndarray

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
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"cut region: inconsistent {', '.join(bad)}")


class CutTopology:
    """The region's cells with the cut faces opened (lip-aware connectivity)."""

    def __init__(self, region: CutRegion):
        self.region = region
        self.cells = region.cells.copy()
        self.origin = np.arange(len(region.coordinates))  # node -> region node it copies
        self.cut_faces: set[tuple[int, ...]] = set()  # in original region node ids

    def interior_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """The region's interior faces (original node ids, k x 4) and their two cells."""
        faces = self.region.cells[:, HEX_FACES].reshape(-1, 4)
        owner = np.repeat(np.arange(len(self.region.cells)), 6)
        keys = np.sort(faces, axis=1)
        order = np.lexsort(keys.T[::-1])
        same = np.all(keys[order][1:] == keys[order][:-1], axis=1)
        first, second = order[:-1][same], order[1:][same]
        return faces[first], np.column_stack([owner[first], owner[second]])

    def cut(self, faces: np.ndarray) -> np.ndarray:
        """Open interior ``faces`` (k, 4; original region node ids); return the new nodes."""
        faces = np.atleast_2d(np.asarray(faces, dtype=np.int64))
        self.cut_faces |= {tuple(sorted(f)) for f in faces}
        before = len(self.origin)
        for node in np.unique(faces):
            self._split(int(node))
        return np.arange(before, len(self.origin))

    def _split(self, original: int) -> None:
        """Regroup the cells around an original node by sides; one node copy per side."""
        cells_at = np.flatnonzero(np.any(self.origin[self.cells] == original, axis=1))
        parent = {int(c): int(c) for c in cells_at}

        def find(c):
            while parent[c] != c:
                parent[c] = parent[parent[c]]
                c = parent[c]
            return c

        seen: dict[tuple, int] = {}
        for c in cells_at:
            for f in self.region.cells[c][HEX_FACES]:
                if original not in f:
                    continue
                key = tuple(sorted(f))
                if key in self.cut_faces:
                    continue
                if key in seen:
                    parent[find(int(c))] = find(seen[key])
                else:
                    seen[key] = int(c)
        sides: dict[int, list[int]] = {}
        for c in cells_at:
            sides.setdefault(find(int(c)), []).append(int(c))
        groups = sorted(sides.values(), key=min)
        # The first side keeps the original node; each other side gets a node of its own,
        # reusing a copy it holds from an earlier cut if no other side took it already.
        used = {original}
        for c in groups[0]:
            self.cells[c][self.origin[self.cells[c]] == original] = original
        for component in groups[1:]:
            held = {int(n) for c in component for n in self.cells[c]
                    if self.origin[n] == original} - used  # fmt: skip
            if held:
                node = min(held)
            else:
                node = len(self.origin)
                self.origin = np.append(self.origin, original)
            used.add(node)
            for c in component:
                self.cells[c][self.origin[self.cells[c]] == original] = node

    @property
    def lip_nodes(self) -> np.ndarray:
        """Nodes (original and copies) of the region that exist more than once."""
        counts = np.bincount(self.origin, minlength=len(self.region.coordinates))
        return np.flatnonzero(counts[self.origin] > 1)


class CutPatch:
    """The factorised coupled system (thesis eq. 4.8) of one cut topology."""

    def __init__(self, topology: CutTopology, layers: int = 2):
        if layers < 1:
            raise ValueError(f"the patch needs at least one layer of cells, got {layers}")
        region = topology.region
        cells = topology.cells
        in_patch = np.any(np.isin(cells, topology.lip_nodes), axis=1)
        for _ in range(layers - 1):
            in_patch |= np.any(np.isin(cells, np.unique(cells[in_patch])), axis=1)
        outside = np.unique(cells[~in_patch])
        fixed = region.fixed[topology.origin]
        candidates = np.unique(cells[in_patch])
        nodes = candidates[~np.isin(candidates, outside) & ~fixed[candidates]]
        self.topology, self.cells, self.nodes = topology, np.flatnonzero(in_patch), nodes
        G = region.reduced_stiffness.shape[0]
        m = 3 * len(nodes)
        index = np.full(len(topology.origin), -1)
        index[nodes] = np.arange(len(nodes))
        K_zd = np.zeros((G, m))
        K_dd = np.zeros((m, m))
        for c in self.cells:
            Ke = region.element_stiffness[c]
            rows = (3 * topology.origin[cells[c]][:, None] + np.arange(3)).ravel()
            A_c = region.basis[rows]  # (24, G): the reduced field does not see the cut
            local = index[cells[c]]
            dofs = (3 * local[:, None] + np.arange(3)).ravel()
            keep = np.repeat(local >= 0, 3)
            K_zd[:, dofs[keep]] += A_c.T @ Ke[:, keep]
            K_dd[np.ix_(dofs[keep], dofs[keep])] += Ke[np.ix_(keep, keep)]
        K = np.block([[region.reduced_stiffness, K_zd], [K_zd.T, K_dd]])
        self.size, self.G = K.shape[0], G
        self.factor = np.linalg.cholesky((K + K.T) / 2)  # raises LinAlgError if not SPD

    @property
    def dofs(self) -> np.ndarray:
        return (3 * self.nodes[:, None] + np.arange(3)).ravel()

    def solve(self, load_reduced: np.ndarray, load_patch: np.ndarray) -> np.ndarray:
        """[zeta, d] for the reduced load A^T f (G,) and the load on the patch DOFs."""
        L = self.factor
        y = np.linalg.solve(L, np.r_[load_reduced, load_patch])
        return np.linalg.solve(L.T, y)

    def region_displacement(self, x: np.ndarray) -> np.ndarray:
        """Displacement (mm) of every node of the cut region (copies included), (R', 3)."""
        topology = self.topology
        region = topology.region
        rows = (3 * topology.origin[:, None] + np.arange(3)).ravel()
        u = region.basis[rows] @ x[: self.G]
        u[self.dofs] += x[self.G :]
        return u.reshape(-1, 3)
