"""The tool's linear surface field at every loadable vertex: what the runtime's "compliance"
surface puts the dent under the tool with (artifact group ``contact_fields``, format 2.2).

Why: between samples PODI blends the three neighbours' fields, each a dent where that
neighbour was trained, so an untrained contact draws three shallow dents around the tool.
The linear response to the tool's own load, K0 u = g(x), is a dent exactly under the tool at
any x, and one back-substitution per point once K0 is factorised. The runtime renders

    u(x, d) = sum_j w_j A_j c_j(d) + d (phi(x) - sum_j w_j phi_j)

the PODI blend plus the linear dent at the contact minus the blend of the linear dents at the
neighbours: the linear part comes from the solve at x, only the nonlinear remainder is
blended. phi is per unit depth (the campaign's depth measure, the tool's weighted mean
displacement), so at a sample the correction vanishes and the trained field is drawn.
Measured with the campaigns' own held-out solves (prototype, README "The rendered
surface"): the liver's surface field 38 % -> 0.8 %, the cornea's 14 % -> 3 %.

phi(x) is linear between the vertices of the surface triangle under the contact (their
fields are a few per cent of the dent's width apart).

The tool's linear stiffness, which
scales the force outside the trained region, is stored at the vertices and at the midpoints
of the loadable triangles' edges (format 2.4), for a quadratic interpolant. At a vertex on
the loadable group's border the tool's load loses the part of its patch beyond the group,
and the stiffness drops within a fraction of an edge (on the liver 1.26 N/mm against 1.50 at
its neighbours; linear between them it was 4 % low at the middle of an edge, 1.379 against
the solve's 1.439 N/mm, and that put the force 2.7 % off at a held-out place). So the edges
that touch the group's border with the free surface are solved at their midpoints; elsewhere
a midpoint gets the mean of its corners, and the quadratic is the linear interpolant. Inside
the group the stiffness between nodes oscillates at the element's scale on a coarse mesh
(the test cornea's midpoints 11-25 % above their corners, an artefact of the
discretisation), which a quadratic turned into 3 % force steps where a contact leaves the
region near a sample; at a clamped border it climbs steeply towards the supports (the test
cornea: 0.3 N/mm at a node an edge from its rim, 3-4 at the rim, 6 between), and a quadratic
overshoots it (70 % off a quarter edge from the rim, the linear interpolant 60 %).

The fields are stored whole, V x 3 floats a loadable vertex, so a model whose fields pass
``MAX_BYTES`` gets none (the cornea demo: 2,161 vertices x 4,514, 117 MB; it keeps the
transported field).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hapticrom.offline.reduce.tool_stiffness import (
    LOADABLE,
    ToolLoads,
    free_dofs,
    linear_responses,
)
from hapticrom.shared.artifact_rules import MAX_FIELD_SUM, contact_field_reach
from hapticrom.shared.geometry import triangle_edges, vertex_normals

CLAMPED, FREE = 0, 2  # RenderSurface.groups (LOADABLE is 1)
MAX_BYTES = 32_000_000  # float32 fields beyond this are not written (see module)
SAME_POINT = 1e-9  # mm: a sample this close to a loadable vertex is that vertex


@dataclass(frozen=True)
class ContactFields:
    """The ``contact_fields`` group: per row, a surface vertex and its field per unit depth."""

    vertices: np.ndarray  # (R,) int64 surface vertex of each row
    fields: np.ndarray  # (R, 3V) float32, mm per mm of depth, surface DOF order
    sample_rows: np.ndarray  # (P,) int64 the row of each sample
    stiffness: np.ndarray  # (R,) N/mm the tool's linear stiffness W^2 / (g^T K0^-1 g) there
    # (TL, 3) N/mm the same at the midpoint of each loadable triangle's edge opposite each
    # corner (the surface's loadable triangles in order)
    edge_stiffness: np.ndarray


def free_border(surface) -> np.ndarray:
    """The loadable group's vertices on its border with the free surface: in a free face
    too, and in no clamped face."""
    groups, triangles = surface.groups, surface.triangles
    shared = np.intersect1d(triangles[groups == LOADABLE], triangles[groups == FREE])
    return np.setdiff1d(shared, triangles[groups == CLAMPED])


def edge_stiffness(K0, supported_nodes, loads, surface, vertices, pushes,
                   stiffness) -> np.ndarray:  # fmt: skip
    """(TL, 3) N/mm: the tool's linear stiffness at the midpoint of each loadable triangle's
    edge opposite each corner: solved (pushed along the normalised mean of its two vertices'
    ``pushes``) where the edge touches the loadable group's border with the free surface
    (:func:`free_border`), else the mean of its vertices' ``stiffness`` (see the module). One
    value per distinct edge."""
    from hapticrom.offline.reduce.tool_stiffness import linear_stiffness

    triangles = surface.triangles[surface.groups == LOADABLE]
    edges, index = triangle_edges(triangles)
    row_of = np.full(len(surface.vertices), -1, dtype=np.int64)
    row_of[vertices] = np.arange(len(vertices))
    rows = row_of[edges]  # (E, 2)
    values = 0.5 * (stiffness[rows[:, 0]] + stiffness[rows[:, 1]])
    border = np.isin(edges, free_border(surface)).any(axis=1)
    if border.any():
        middles = 0.5 * (surface.vertices[edges[border, 0]] + surface.vertices[edges[border, 1]])
        push = pushes[rows[border, 0]] + pushes[rows[border, 1]]
        push /= np.linalg.norm(push, axis=1, keepdims=True)
        values[border] = linear_stiffness(K0, supported_nodes, loads, middles, push)
    return values[index]


def field_points(surface, sample_points, sample_normals, direction) -> tuple:
    """(rows' vertices (R,), pushes (R, 3), sample_rows (P,)): every vertex of a loadable
    triangle, pushed as the campaign pushes (minus the outward vertex normal, or the campaign's
    fixed ``direction``); a sample's vertex pushed exactly as that sample was, so that the
    runtime's correction vanishes there. ValueError if a sample is at no loadable vertex."""
    loadable = surface.triangles[surface.groups == LOADABLE]
    vertices = np.unique(loadable).astype(np.int64)
    if direction == "normal":
        pushes = -vertex_normals(surface.vertices, loadable)[vertices]
    else:
        fixed = np.asarray(direction, dtype=float)
        pushes = np.tile(fixed / np.linalg.norm(fixed), (len(vertices), 1))
    sample_rows = np.empty(len(sample_points), dtype=np.int64)
    for i, (p, n) in enumerate(zip(sample_points, sample_normals, strict=True)):
        gap = np.linalg.norm(surface.vertices[vertices] - p, axis=1)
        row = int(np.argmin(gap))
        if gap[row] > SAME_POINT:
            raise ValueError(f"sample {i} at {np.round(p, 4).tolist()} mm is at no loadable vertex")
        sample_rows[i] = row
        pushes[row] = -n  # a sample's normal is minus its push, in either mode
    return vertices, pushes, sample_rows


def contact_fields(config, store, surface, sample_points, sample_normals,
                   say=print) -> ContactFields | None:  # fmt: skip
    """The linear field of the tool centred at every loadable vertex (rank 0; K0 from the
    campaign's store), or None: for a campaign that is not force-controlled (its depth is
    the rigid patch's or the sphere's advance, not the weighted mean of the tool's load, so
    phi per unit depth would be per another depth: review), where they would pass
    MAX_BYTES, or where they would pass the artifact's bound (MAX_FIELD_SUM)."""
    from hapticrom.offline.campaign.store import csr_from

    if config.load.mode != "force":
        say(f"no contact fields: the campaign is {config.load.mode}-controlled (force only)")
        return None
    vertices, pushes, sample_rows = field_points(surface, sample_points, sample_normals,
                                                 config.load.direction)  # fmt: skip
    size = 4 * len(vertices) * surface.dofs.size
    if size > MAX_BYTES:
        say(f"no contact fields: {len(vertices)} loadable vertices would take "
            f"{size / 1e6:.0f} MB (at most {MAX_BYTES / 1e6:.0f})")  # fmt: skip
        return None
    t0 = time.perf_counter()
    data, _ = store.read_operators()
    K0 = csr_from(data, "K0")
    free = free_dofs(K0.shape[0], data["supported_nodes"])
    row_of = np.full(K0.shape[0], -1)
    row_of[free] = np.arange(len(free))
    rows = row_of[surface.dofs]  # each surface DOF's row among the free ones (-1: a support's)
    moving = rows >= 0
    fields = np.zeros((len(vertices), surface.dofs.size), dtype=np.float32)
    stiffness = np.empty(len(vertices))
    points = surface.vertices[vertices]
    for chunk, G, X, W in linear_responses(K0, data["supported_nodes"], ToolLoads(config),
                                           points, pushes):  # fmt: skip
        depth = np.einsum("ij,ij->j", G, X) / W  # the campaign's measure: g^T u / W
        fields[chunk.start : chunk.stop, moving] = (X[rows[moving]] / depth).T
        stiffness[chunk.start : chunk.stop] = W / depth  # tool_stiffness.linear_stiffness's
    edges = edge_stiffness(K0, data["supported_nodes"], ToolLoads(config), surface, vertices,
                           pushes, stiffness)  # fmt: skip
    reach = contact_field_reach(fields, sample_rows)
    if not reach <= MAX_FIELD_SUM:  # the reader would refuse the file
        say(f"no contact fields: a row plus a sample's reach {reach:.3g} per unit depth (at "
            f"most {MAX_FIELD_SUM:.3g})")  # fmt: skip
        return None
    say(f"the tool's linear field at {len(vertices)} loadable vertices "
        f"({fields.nbytes / 1e6:.1f} MB) and the tool's stiffness there and at the loadable "
        f"group's border edges, in {time.perf_counter() - t0:.1f} s")  # fmt: skip
    return ContactFields(vertices, fields, sample_rows, stiffness, edges)
