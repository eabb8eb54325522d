"""Hexahedral spherical-cap shells: the cornea and the hemisphere (mm).

Both come from one construction. A structured O-grid quad mesh of the unit
disk (a central n x n block and four n x m blocks running out to the rim) is
mapped onto the sphere of radius R about the centre (0, 0, -R) by

    polar angle phi = s * phi_rim,   azimuth theta = angle of the disk point,

with s the distance of the disk point from the disk centre, so the disk
centre lands on the pole (the apex, at the origin) and the disk rim on the
circle phi = phi_rim. The shell is then extruded inwards through the local
thickness h(phi) = h_c + (h_rim - h_c) (phi / phi_rim)^2 in ``layers`` hex
layers: material point = centre + (R - (1 - t) h(phi)) dir(phi, theta),
t = 0 (posterior / inner surface) ... 1 (anterior / outer surface).

Surface groups: outer surface ``loadable``, inner surface ``free``, the rim
side faces ``clamped`` (the limbus for the cornea, the equator for the
hemisphere).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .msh import BuiltMesh, boundary_faces, require, resolve_params

# Weight of the elliptical square-to-disk map in the central O-grid block
# (0 = straight-sided square): bulging the block's sides a little keeps the
# outer blocks' cells at the block corners from being squeezed.
CORE_BULGE = 0.3

CORNEA_DEFAULTS: dict[str, Any] = {
    "radius": 7.8,  # anterior radius of curvature, mm
    "central_thickness": 0.55,  # mm
    "limbus_thickness": 0.7,  # mm
    "limbus_diameter": 11.5,  # diameter of the anterior rim circle, mm
    # Trilinear hexahedra bend too stiffly when they are much longer than thick;
    # at a fixed budget of ~8,500 nodes, 3 layers with a finer surface grid come
    # within 2 % of Q2/Q1 on the same mesh under apex indentation (6 layers on
    # an 18/12 grid: 5 %). See the foundation issue's note.
    "n": 24,  # cells along a side of the central O-grid block (even)
    "m": 16,  # cells radially in the outer O-grid blocks
    "layers": 3,  # hex layers through the thickness
}
CORNEA_PRESETS = {
    "coarse": {"n": 6, "m": 4, "layers": 2},
    "default": {},
    "fine": {"n": 36, "m": 24, "layers": 4},
}

HEMISPHERE_DEFAULTS: dict[str, Any] = {
    "radius": 25.0,  # outer radius, mm
    # mm, constant. The thesis does not give it. With SVK its 30 N pole load is not
    # physical on 10 mm either: 6.4 mm with inverted elements on the default mesh, a
    # snap-through on the fine one (meshes/README.md); neo-Hookean gives 2.5 mm.
    "thickness": 10.0,
    "n": 8,
    "m": 5,
    "layers": 2,
}
HEMISPHERE_PRESETS = {
    "coarse": {"n": 4, "m": 3, "layers": 2},
    "default": {},
    "fine": {"n": 16, "m": 10, "layers": 4},
}


def disk_ogrid(n: int, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Structured O-grid quad mesh of the unit disk.

    Returns ``(points (N, 2), quads (Q, 4) counter-clockwise, rim (4n,))``
    with N = (n+1)^2 + 4nm and Q = n^2 + 4nm; ``rim`` are the indices of the
    points on the unit circle. For even n a point sits exactly at the centre.
    """
    # Half-width of the central block, chosen so its cells are about as long
    # as the mean radial spacing of the outer blocks (mean gap ~ 1 - 1.2 a).
    half = 1.0 / (1.2 + 2.0 * m / n)

    # Central block: a square blended towards the elliptical square-to-disk
    # map, which keeps the corners at (+-half, +-half) and bulges the sides.
    # Exact integers over n, so for even n the middle value is exactly 0 and
    # the apex node lands exactly on the origin.
    xi = (2.0 * np.arange(n + 1) - n) / n
    eta_grid, xi_grid = np.meshgrid(xi, xi, indexing="ij")  # row j = eta, column i = xi
    xs, ys = xi_grid.ravel(), eta_grid.ravel()
    round_x = math.sqrt(2.0) * xs * np.sqrt(1.0 - ys**2 / 2.0)
    round_y = math.sqrt(2.0) * ys * np.sqrt(1.0 - xs**2 / 2.0)
    core = half * np.column_stack(
        [(1 - CORE_BULGE) * xs + CORE_BULGE * round_x, (1 - CORE_BULGE) * ys + CORE_BULGE * round_y]
    )

    def core_index(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return j * (n + 1) + i

    i0, j0 = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    i0, j0 = i0.ravel(), j0.ravel()
    core_quads = np.column_stack(
        [
            core_index(i0, j0),
            core_index(i0 + 1, j0),
            core_index(i0 + 1, j0 + 1),
            core_index(i0, j0 + 1),
        ]
    )

    # Perimeter of the central block, counter-clockwise from the corner
    # (-1, -1): south, east, north, west sides, n points each.
    side = np.repeat(np.arange(4), n)
    step = np.tile(np.arange(n), 4)
    i_per = np.select([side == 0, side == 1, side == 2], [step, n + 0 * step, n - step], 0 * step)
    j_per = np.select([side == 0, side == 1, side == 2], [0 * step, step, n + 0 * step], n - step)
    inner = core[core_index(i_per, j_per)]
    # Matching points on the unit circle: each side spans a quarter turn.
    u = (2.0 * step - n) / n
    theta = (side - 1) * (math.pi / 2.0) + u * (math.pi / 4.0)
    outer = np.column_stack([np.cos(theta), np.sin(theta)])

    # Ring levels 1..m: straight lines from the block boundary to the circle.
    weights = np.arange(1, m + 1) / m
    ring = (1.0 - weights)[:, None, None] * inner[None] + weights[:, None, None] * outer[None]
    points = np.vstack([core, ring.reshape(-1, 2)])

    first_ring = (n + 1) ** 2
    level_index = np.vstack(
        [core_index(i_per, j_per)[None], first_ring + np.arange(m * 4 * n).reshape(m, 4 * n)]
    )
    k = np.arange(4 * n)
    below, above = level_index[:-1], level_index[1:]
    # (inner k, outer k, outer k+1, inner k+1) runs radially out first, so it
    # is counter-clockwise.
    ring_quads = np.stack(
        [below[:, k], above[:, k], above[:, (k + 1) % (4 * n)], below[:, (k + 1) % (4 * n)]],
        axis=-1,
    ).reshape(-1, 4)
    quads = np.vstack([core_quads, ring_quads])
    return points, quads, level_index[-1].copy()


def cap_arrays(
    radius: float,
    central_thickness: float,
    rim_thickness: float,
    rim_polar_angle: float,
    n: int,
    m: int,
    layers: int,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Nodes (mm), hexahedra and surface groups of a spherical-cap shell.

    Outer surface through the origin (the pole), centre of curvature at
    (0, 0, -radius), rim at polar angle ``rim_polar_angle`` (rad). Node index
    = layer * (points per layer) + disk point index, layer 0 the inner
    surface.
    """
    disk, quads, rim = disk_ogrid(n, m)
    s = np.hypot(disk[:, 0], disk[:, 1])
    phi = s * rim_polar_angle
    # sin(phi)/s written through sinc so the disk centre needs no special case.
    sin_over_s = rim_polar_angle * np.sinc(phi / math.pi)
    direction = np.column_stack([sin_over_s * disk[:, 0], sin_over_s * disk[:, 1], np.cos(phi)])
    thickness = (
        central_thickness + (rim_thickness - central_thickness) * (phi / rim_polar_angle) ** 2
    )
    t = np.arange(layers + 1) / layers
    distance = radius - (1.0 - t)[:, None] * thickness[None, :]  # (layers+1, points)
    centre = np.array([0.0, 0.0, -radius])
    nodes = (centre + distance[:, :, None] * direction[None]).reshape(-1, 3)

    per_layer = len(disk)
    offsets = per_layer * np.arange(layers)[:, None, None]
    # A counter-clockwise quad seen from outside at the bottom (inner) and the
    # same quad one layer out on top is a positively oriented gmsh hexahedron.
    cells = np.concatenate(
        [quads[None] + offsets, quads[None] + offsets + per_layer], axis=2
    ).reshape(-1, 8)

    faces = boundary_faces(cells)
    layer_of = faces // per_layer
    outer = np.all(layer_of == layers, axis=1)
    inner = np.all(layer_of == 0, axis=1)
    on_rim = np.isin(faces % per_layer, rim).all(axis=1)
    assert np.all(outer ^ inner ^ on_rim), "every boundary face is outer, inner or rim"
    groups = {"clamped": faces[on_rim], "loadable": faces[outer], "free": faces[inner]}
    return nodes, cells, groups


def _check_counts(name: str, params: dict[str, Any]) -> None:
    require(
        params["n"] >= 2 and params["n"] % 2 == 0,
        f"{name}: n must be even and >= 2 (a node must sit on the apex), got {params['n']}",
    )
    require(params["m"] >= 1, f"{name}: m must be >= 1, got {params['m']}")
    require(params["layers"] >= 1, f"{name}: layers must be >= 1, got {params['layers']}")


def build_cornea(refinement: str = "default", **overrides: Any) -> BuiltMesh:
    """The cornea: a spherical-cap shell thickening towards the limbus (mm).

    Apex at the origin, centre of curvature at (0, 0, -radius), opening
    towards -z; the anterior surface's rim circle has diameter
    ``limbus_diameter``. Held at the limbus (clamped, xyz), loaded on the
    anterior surface, fibres following the spherical-cap rule.
    """
    p = resolve_params("cornea", CORNEA_DEFAULTS, CORNEA_PRESETS, refinement, overrides)
    radius = p["radius"]
    require(radius > 0, f"cornea: radius must be > 0 mm, got {radius}")
    for key in ("central_thickness", "limbus_thickness"):
        require(
            0 < p[key] < radius, f"cornea: {key} must be in (0, radius={radius}) mm, got {p[key]}"
        )
    require(
        0 < p["limbus_diameter"] <= 2 * radius,
        f"cornea: limbus_diameter must be in (0, 2*radius={2 * radius}] mm, "
        f"got {p['limbus_diameter']}",
    )
    _check_counts("cornea", p)
    rim_angle = math.asin(min(1.0, p["limbus_diameter"] / (2 * radius)))
    nodes, cells, groups = cap_arrays(
        radius,
        p["central_thickness"],
        p["limbus_thickness"],
        rim_angle,
        p["n"],
        p["m"],
        p["layers"],
    )
    return BuiltMesh(
        name="cornea",
        params=p,
        nodes=nodes,
        cells=cells,
        facet_groups=groups,
        supports=[{"group": "clamped", "components": "xyz"}],
        fibres={
            "rule": "spherical_cap",
            "centre": [0.0, 0.0, -radius],
            "m_axis": [1.0, 0.0, 0.0],
            "n_axis": [0.0, 1.0, 0.0],
        },
        default_contact_point=[0.0, 0.0, 0.0],
        description=(
            f"Cornea: spherical-cap shell, anterior radius {radius} mm about (0, 0, {-radius}), "
            f"apex at the origin, thickness {p['central_thickness']} mm at the apex growing "
            f"quadratically in the polar angle to {p['limbus_thickness']} mm at the limbus "
            f"(anterior rim diameter {p['limbus_diameter']} mm); O-grid n={p['n']}, m={p['m']}, "
            f"{p['layers']} hex layers. Limbus rim clamped, anterior surface loadable, "
            "posterior surface free."
        ),
    )


def build_hemisphere(refinement: str = "default", **overrides: Any) -> BuiltMesh:
    """A hemispherical shell of constant thickness, pole at the origin (mm).

    Outer radius ``radius`` about (0, 0, -radius), so the equator rim lies in
    the plane z = -radius; clamped (xyz) at the rim, loadable on the outer
    surface, inner surface free.
    """
    p = resolve_params("hemisphere", HEMISPHERE_DEFAULTS, HEMISPHERE_PRESETS, refinement, overrides)
    radius = p["radius"]
    require(radius > 0, f"hemisphere: radius must be > 0 mm, got {radius}")
    require(
        0 < p["thickness"] < radius,
        f"hemisphere: thickness must be in (0, radius={radius}) mm, got {p['thickness']}",
    )
    _check_counts("hemisphere", p)
    nodes, cells, groups = cap_arrays(
        radius, p["thickness"], p["thickness"], math.pi / 2, p["n"], p["m"], p["layers"]
    )
    return BuiltMesh(
        name="hemisphere",
        params=p,
        nodes=nodes,
        cells=cells,
        facet_groups=groups,
        supports=[{"group": "clamped", "components": "xyz"}],
        fibres=None,
        default_contact_point=[0.0, 0.0, 0.0],
        description=(
            f"Hemisphere: shell of outer radius {radius} mm about (0, 0, {-radius}), constant "
            f"thickness {p['thickness']} mm, outer pole at the origin; O-grid n={p['n']}, "
            f"m={p['m']}, {p['layers']} hex layers. Equator rim clamped, outer surface "
            "loadable, inner surface free."
        ),
    )
