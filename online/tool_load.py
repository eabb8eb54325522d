"""The training's soft tool tip as a load on the cut region's surface (numpy only; mm, N).

The cut's softening is the ratio of the tissue's compliance under a unit tool
load with the cuts and without them (:mod:`hapticrom.online.cutting`). The tool
presses as the training's soft tip does: a traction of profile
(1 - r^2 / a^2)^2 within its radius a, along the inward normal at its centre,
1 N in all, integrated over the region's surface triangles (6-point rule,
linear shapes), each lip taking the traction of its own side of the cut.
"""

from __future__ import annotations

import numpy as np

from hapticrom.online.coupled_patch import CoupledPatch, CutRegion
from hapticrom.shared.cut_topology import CutTopology

# Degree-4 symmetric quadrature on a triangle (Dunavant): barycentric points, weights (sum 1).
_A, _B = 0.445948490915965, 0.091576213509771
TRIANGLE_RULE = (
    np.array([[_A, _A, 1 - 2 * _A], [_A, 1 - 2 * _A, _A], [1 - 2 * _A, _A, _A],
              [_B, _B, 1 - 2 * _B], [_B, 1 - 2 * _B, _B], [1 - 2 * _B, _B, _B]]),
    np.array([0.223381589678011] * 3 + [0.109951743655322] * 3),
)  # fmt: skip


class ToolLoad:
    """Unit tool loads centred on surface vertices, as right-hand sides of a patch.

    ``model``: the reduced model (its surface), ``region``: the cut region,
    ``surface_region`` (V,): each surface vertex's region node or -1, ``normals``
    (V, 3): outward unit vertex normals, ``radius``: the tool tip's (mm).
    """

    def __init__(self, model, region: CutRegion, surface_region: np.ndarray,
                 normals: np.ndarray, radius: float):  # fmt: skip
        self.model, self.region, self.radius = model, region, float(radius)
        self.normals = normals
        self.groups = np.asarray(model.artifact["surface"]["groups"])
        # The surface triangles wholly in the region, the one region cell holding each and
        # where its corners are in that cell: (which, cell, position). Read by workers.
        self.triangle_cells = _triangle_cells(np.asarray(model.triangles), surface_region,
                                              region.cells)  # fmt: skip

    def region_triangles(self, topology: CutTopology) -> tuple[np.ndarray, np.ndarray]:
        """(indices of the surface triangles wholly in the region, their nodes in
        ``topology``'s numbering: a triangle on a copy's side of a cut uses the copy)."""
        which, cell, position = self.triangle_cells
        return which, topology.cells[cell[:, None], position]

    def surface_quadrature(self, topology: CutTopology):
        """(loadable region triangles in ``topology``'s numbering (T, 3), their quadrature
        points (T, 6, 3) mm, and weights (T, 6) mm^2), for tool tractions.

        Only the loadable surface counts (a tool touches the anterior surface, not the
        posterior one, however thin the tissue). A lip copy's triangles are those of
        its own side of the cut.
        """
        which, triangles = self.region_triangles(topology)
        triangles = triangles[self.groups[which] == 1]
        x = self.region.coordinates[topology.origin[triangles]]  # (T, 3, 3)
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        points = np.einsum("qi,tij->tqj", TRIANGLE_RULE[0], x)
        return triangles, points, area[:, None] * TRIANGLE_RULE[1]

    def loads(self, patch: CoupledPatch, vertices: np.ndarray) -> np.ndarray:
        """Right-hand sides (patch.size, len(vertices)) of a unit tool force centred on
        each of ``vertices``.

        A point load would not do (at a lip its compliance is the local, singular
        response), nor would a load on one lip only: each lip takes the traction of
        its own side of the surface; nor a nodal lumping, on a mesh as coarse as the tool.
        """
        topology, G = patch.topology, patch.G
        nodes, W = self._spread(topology, vertices)
        direction = -self.normals[vertices]  # (k, 3)
        rows = (3 * topology.origin[nodes][:, None] + np.arange(3)).ravel()
        basis = patch.region.basis[rows].reshape(len(nodes), 3, G)
        B = np.zeros((patch.size, len(vertices)))
        for j in range(3):
            B[:G] += (basis[:, j, :].T @ W) * direction[:, j]
        index = np.full(len(topology.origin), -1)
        index[patch.nodes] = np.arange(len(patch.nodes))
        local = index[nodes]
        on_patch = np.flatnonzero(local >= 0)
        for j in range(3):
            B[G + 3 * local[on_patch] + j] = W[on_patch] * direction[:, j]
        return B

    def _spread(self, topology: CutTopology, vertices: np.ndarray) -> tuple:
        """(the loaded nodes, W (nodes, k)): each tool's traction spread to the triangles'
        nodes by the linear shapes, columns summing to 1."""
        triangles, points, weights = self.surface_quadrature(topology)
        nodes, triangles = np.unique(triangles, return_inverse=True)
        triangles = triangles.reshape(-1, 3)
        centres = self.model.vertices[vertices]
        # Traction at every quadrature point for every tool centre: (T * 6, k).
        x = points.reshape(-1, 3)
        s = (np.sum(x * x, axis=1)[:, None] + np.sum(centres * centres, axis=1)[None, :]
             - 2.0 * x @ centres.T) / self.radius**2  # fmt: skip
        traction = weights.reshape(-1, 1) * np.where(s < 1.0, (1.0 - s) ** 2, 0.0)
        corner = np.einsum("qc,tqk->tck", TRIANGLE_RULE[0], traction.reshape(len(triangles), 6, -1))
        W = np.zeros((len(nodes), len(vertices)))
        np.add.at(W, triangles.ravel(), corner.reshape(-1, len(vertices)))
        W /= np.maximum(W.sum(axis=0), 1e-300)
        return nodes, W


def _triangle_cells(triangles: np.ndarray, surface_region: np.ndarray, cells: np.ndarray):
    """(surface triangles wholly in the region, the region cell holding each, the
    positions of its three corners in that cell)."""
    nodes = surface_region[triangles]
    which = np.flatnonzero(np.all(nodes >= 0, axis=1))
    cells_at: dict[int, set] = {}
    for c, cell_nodes in enumerate(cells.tolist()):
        for n in cell_nodes:
            cells_at.setdefault(n, set()).add(c)
    cell = np.full(len(which), -1)
    for i, (a, b, c) in enumerate(nodes[which].tolist()):
        # The one region cell holding the three nodes of a surface triangle.
        holding = cells_at.get(a, set()) & cells_at.get(b, set()) & cells_at.get(c, set())
        cell[i] = min(holding, default=-1)
    keep = cell >= 0
    which, cell = which[keep], cell[keep]
    position = np.argmax(cells[cell][:, None, :] == nodes[which][:, :, None], axis=2)
    return which, cell, position
