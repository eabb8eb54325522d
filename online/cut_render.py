"""What a renderer needs of the cuts: the lips' vertex copies and the split triangles.

numpy only. A cut opens the surface: each surface vertex on a lip gets a copy
(numbered after the model's V vertices), and the triangles on the copy's side
use it. Both are recomputed once per cut event (cached on the events' count).
"""

from __future__ import annotations

import numpy as np

from hapticrom.online.cutting import Cuts


class LipLayout:
    """The rendered surface's layout for the current cut state of ``cuts``.

    ``triangles`` (T, 3): the model's surface triangles.
    """

    def __init__(self, cuts: Cuts, triangles: np.ndarray):
        self.cuts = cuts
        self.triangles = np.asarray(triangles)
        self._layout_key = -1  # the cut events' count the caches below are of
        self._layout: tuple = ()
        self._triangles_key = -1
        self._split: np.ndarray | None = None

    def surface_layout(self) -> tuple:
        """(surface vertices in the region, their region nodes, lip copies (region nodes),
        the surface vertices the copies duplicate) for the current cut state."""
        cuts = self.cuts
        key = len(cuts.events)
        if self._layout_key != key:
            surface_region, topology = cuts.surface_region, cuts.topology
            nodes = len(cuts.region.coordinates)
            on = np.flatnonzero(surface_region >= 0)
            vertex_of = np.full(nodes, -1)
            vertex_of[surface_region[on]] = on
            copies = np.arange(nodes, len(topology.origin))
            duplicates = vertex_of[topology.origin[copies]]
            keep = duplicates >= 0
            self._layout = (on, surface_region[on], copies[keep], duplicates[keep])
            self._layout_key = key
        return self._layout

    def surface_triangles(self) -> np.ndarray:
        """The surface triangles with the lips split: a triangle on a copy's side of the cut
        uses that copy's lip vertex (numbered V + k, k as in ``surface_layout``'s copies)."""
        cuts = self.cuts
        key = len(cuts.events)
        if self._triangles_key != key:
            triangles = self.triangles.copy()
            _, _, copies, _ = self.surface_layout()
            vertex_of = np.full(len(cuts.topology.origin), -1)
            vertex_of[copies] = len(cuts.surface_region) + np.arange(len(copies))
            which, current = cuts.tool.region_triangles(cuts.topology)
            lip = vertex_of[current]
            triangles[which] = np.where(lip >= 0, lip, triangles[which])
            self._triangles_key, self._split = key, triangles
        return self._split
