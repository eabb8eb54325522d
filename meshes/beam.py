"""Hexahedral cantilever beam: a structured box (mm).

x in [0, length], y in [-width/2, width/2], z in [-height/2, height/2].
The face x = 0 is ``clamped``, the end face x = length ``loadable``, the four
lateral faces ``free``. The beam is held axially only (x on the clamped face)
plus the fewest point constraints that remove rigid motion, so a uniform
lateral contraction u_y = c y, u_z = c z is not blocked:

* node (0, 0, 0): y and z fixed (no translation in y, z);
* node (0, 0, height/2): y fixed (no rotation about x).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .msh import BuiltMesh, boundary_faces, require, resolve_params

BEAM_DEFAULTS: dict[str, Any] = {
    "length": 400.0,  # along x, mm
    "width": 40.0,  # along y, mm
    "height": 40.0,  # along z, mm
    "nx": 40,
    "ny": 4,  # even: a node line at y = 0
    "nz": 4,  # even: a node line at z = 0
}
BEAM_PRESETS = {
    "coarse": {"nx": 10, "ny": 2, "nz": 2},
    "default": {},
    "fine": {"nx": 80, "ny": 8, "nz": 8},
}


def box_arrays(
    length: float, width: float, height: float, nx: int, ny: int, nz: int
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Nodes (mm), hexahedra and surface groups of the structured box.

    Node index = i + (nx+1) (j + (ny+1) k) for grid indices (i, j, k) along
    (x, y, z).
    """
    # Exact grid coordinates: integer over integer, so y = 0 and z = 0 are
    # exact zeros for even ny, nz.
    x = length * np.arange(nx + 1) / nx
    y = width * (2.0 * np.arange(ny + 1) - ny) / (2.0 * ny)
    z = height * (2.0 * np.arange(nz + 1) - nz) / (2.0 * nz)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    nodes = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])

    def index(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        return i + (nx + 1) * (j + (ny + 1) * k)

    k, j, i = (
        a.ravel() for a in np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    )
    # gmsh order: bottom face (z = k) counter-clockwise seen from +z, then top.
    cells = np.column_stack(
        [
            index(i, j, k),
            index(i + 1, j, k),
            index(i + 1, j + 1, k),
            index(i, j + 1, k),
            index(i, j, k + 1),
            index(i + 1, j, k + 1),
            index(i + 1, j + 1, k + 1),
            index(i, j + 1, k + 1),
        ]
    )

    faces = boundary_faces(cells)
    grid_i = faces % (nx + 1)
    clamped = np.all(grid_i == 0, axis=1)
    loaded = np.all(grid_i == nx, axis=1)
    groups = {
        "clamped": faces[clamped],
        "loadable": faces[loaded],
        "free": faces[~clamped & ~loaded],
    }
    return nodes, cells, groups


def build_beam(refinement: str = "default", **overrides: Any) -> BuiltMesh:
    """The cantilever beam mesh, clamped axially at x = 0, loaded at x = length (mm)."""
    p = resolve_params("beam", BEAM_DEFAULTS, BEAM_PRESETS, refinement, overrides)
    for key in ("length", "width", "height"):
        require(p[key] > 0, f"beam: {key} must be > 0 mm, got {p[key]}")
    require(p["nx"] >= 1, f"beam: nx must be >= 1, got {p['nx']}")
    for key in ("ny", "nz"):
        require(
            p[key] >= 2 and p[key] % 2 == 0,
            f"beam: {key} must be even and >= 2 (nodes on the mid-planes), got {p[key]}",
        )
    nodes, cells, groups = box_arrays(
        p["length"], p["width"], p["height"], p["nx"], p["ny"], p["nz"]
    )
    half_height = p["height"] / 2
    return BuiltMesh(
        name="beam",
        params=p,
        nodes=nodes,
        cells=cells,
        facet_groups=groups,
        supports=[
            {"group": "clamped", "components": "x"},
            {"point": [0.0, 0.0, 0.0], "components": "yz"},
            {"point": [0.0, 0.0, half_height], "components": "y"},
        ],
        fibres=None,
        default_contact_point=[p["length"], 0.0, 0.0],
        description=(
            f"Beam: box {p['length']} x {p['width']} x {p['height']} mm, x from 0, y and z "
            f"centred; {p['nx']} x {p['ny']} x {p['nz']} hexahedra. Face x=0 clamped axially "
            "(plus point supports against rigid motion), face x=length loadable, lateral "
            "faces free."
        ),
    )
