"""Cut topology shared by the explicit cut meshes and the runtime's scalpel (numpy only).

:class:`CutTopology` opens interior faces of a cell mesh one cut event at a time:
the nodes inside the cut get one copy per side, the cut's front (its edges inside
the tissue) stays joined. :mod:`hapticrom.meshes.cut` meshes a cut with it (the
full-order reference), :mod:`hapticrom.online.cutting` cuts at run time with it:
the two are the same cut by construction.
"""

from __future__ import annotations

import numpy as np

# The faces of a hexahedron as local node indices (gmsh order), outward.
HEX_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [0, 4, 7, 3], [1, 2, 6, 5]]
)


class CutTopology:
    """Cells with cut faces opened (lip-aware connectivity), one cut event at a time.

    ``cells`` (m, k): node indices of the intact cells; ``num_nodes``: how many
    nodes there are; ``local_faces``: each cell's faces as local node indices
    (hexahedra by default, gmsh order). New nodes are numbered from ``num_nodes``
    on; ``origin`` maps every node to the intact node it copies.
    """

    def __init__(self, cells: np.ndarray, num_nodes: int, local_faces: np.ndarray = HEX_FACES):
        self.intact = np.asarray(cells)
        self.local_faces = np.asarray(local_faces)
        self.cells = self.intact.copy()
        self.origin = np.arange(num_nodes)  # node -> intact node it copies
        self.cut_faces: set[tuple[int, ...]] = set()  # in intact node ids

    def copy(self) -> CutTopology:
        """An independent copy (the intact cells and local faces are shared: never changed)."""
        other = CutTopology.__new__(CutTopology)
        other.intact, other.local_faces = self.intact, self.local_faces
        other.cells, other.origin = self.cells.copy(), self.origin.copy()
        other.cut_faces = set(self.cut_faces)
        return other

    def interior_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """The interior faces (intact node ids, (f, k)) and their two cells."""
        nf, k = self.local_faces.shape
        faces = self.intact[:, self.local_faces].reshape(-1, k)
        owner = np.repeat(np.arange(len(self.intact)), nf)
        keys = np.sort(faces, axis=1)
        order = np.lexsort(keys.T[::-1])
        same = np.all(keys[order][1:] == keys[order][:-1], axis=1)
        first, second = order[:-1][same], order[1:][same]
        return faces[first], np.column_stack([owner[first], owner[second]])

    def cut(self, faces: np.ndarray) -> np.ndarray:
        """Open interior ``faces`` ((f, k), intact node ids); return the new nodes."""
        faces = np.atleast_2d(np.asarray(faces, dtype=np.int64))
        self.cut_faces |= {tuple(sorted(f)) for f in faces}
        before = len(self.origin)
        for node in np.unique(faces):
            self._split(int(node))
        return np.arange(before, len(self.origin))

    def _sides(self, original: int) -> list[list[int]]:
        """The cells around an original node grouped by the sides the cuts leave (each
        side's cells stay joined through faces that are not cut), by lowest cell first."""
        cells_at = np.flatnonzero(np.any(self.origin[self.cells] == original, axis=1))
        parent = {int(c): int(c) for c in cells_at}

        def find(c):
            while parent[c] != c:
                parent[c] = parent[parent[c]]
                c = parent[c]
            return c

        seen: dict[tuple, int] = {}
        for c in cells_at:
            for f in self.intact[c][self.local_faces]:
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
        return sorted(sides.values(), key=min)

    def _split(self, original: int) -> None:
        """Regroup the cells around an original node by sides; one node copy per side."""
        groups = self._sides(original)
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
        """Nodes (originals and copies) that exist more than once."""
        return np.flatnonzero(np.bincount(self.origin)[self.origin] > 1)
