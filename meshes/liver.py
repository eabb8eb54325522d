"""Tetrahedral liver-like body (mm).

No public liver mesh is reachable from here, so this is a synthetic organ of
realistic size (about 230 x 120 x 90 mm, about 1 litre): three fused
ellipsoids (a large right lobe, a bridging middle, a thin left lobe) cut by
a tilted plane that makes the flat visceral (inferior) surface and the sharp
anterior-inferior border. gmsh's OpenCASCADE kernel builds the solid and its
Delaunay mesher fills it with linear tetrahedra; the options are fixed and
single-threaded, so the mesh is the same on every run.

Axes (DICOM LPS): +x towards the patient's left (the right lobe is at -x),
+y posterior, +z superior; the surgeon looks from -y.

Surface groups, decided per boundary triangle:

* ``clamped``: centroid in the posterior quarter of the depth,
  y > y_max - ``clamped_depth_fraction`` (y_max - y_min) -- where the liver
  is held by the vena cava, the ligaments and the bare area;
* ``loadable``: not clamped and facing the front, outward normal n with
  n . (-y) > ``anterior_normal_min`` -- the anterior and antero-inferior
  surfaces a tool palpates;
* ``free``: the rest (the superior dome and the lateral sides).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .msh import BuiltMesh, boundary_faces, gmsh_model, require, resolve_params

# Lobes at scale 1: (centre, semi-axes), mm.
LOBES = (
    ((-40.0, 10.0, 0.0), (75.0, 60.0, 45.0)),  # right lobe
    ((0.0, 5.0, 8.0), (60.0, 50.0, 32.0)),  # bridge over the middle
    ((45.0, 0.0, 16.0), (70.0, 42.0, 20.0)),  # thin left lobe
)
# The visceral cut: the solid keeps the side n . x >= offset. The plane rises
# towards the left lobe and towards the front, making a wedge.
CUT_NORMAL = (-0.15, 0.3, 1.0)
CUT_POINT = (0.0, 0.0, -30.0)

LIVER_DEFAULTS: dict[str, Any] = {
    "scale": 1.0,  # uniform scale of the body
    "mesh_size": 7.65,  # target tetrahedron edge length, mm
    "clamped_depth_fraction": 0.25,  # posterior fraction of the depth that is clamped
    "anterior_normal_min": 0.2,  # loadable if n . (-y) exceeds this
}
LIVER_PRESETS = {
    "coarse": {"mesh_size": 15.5},
    "default": {},
    "fine": {"mesh_size": 5.0},
}

# gmsh options used to mesh; fixed so the result is reproducible.
MESHING_OPTIONS = {
    "General.Terminal": 0,
    "General.NumThreads": 1,
    "Mesh.Algorithm": 6,  # Frontal-Delaunay surfaces
    "Mesh.Algorithm3D": 1,  # Delaunay volume
    "Mesh.ElementOrder": 1,
    "Mesh.MeshSizeFromCurvature": 0,
    "Mesh.MeshSizeFromPoints": 0,
    "Mesh.MeshSizeExtendFromBoundary": 1,
    "Mesh.Optimize": 1,
    "Mesh.OptimizeNetgen": 0,
    "Mesh.RandomFactor": 1e-9,
    "Mesh.RandomSeed": 1,
}


def tetrahedralise(scale: float, mesh_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Build and mesh the liver solid with gmsh; return (nodes (n, 3) mm, tets (m, 4)).

    The nodes are those the tetrahedra use, numbered compactly in gmsh's
    node order; every tetrahedron is positively oriented.
    """
    import gmsh

    options = {**MESHING_OPTIONS, "Mesh.MeshSizeMin": mesh_size, "Mesh.MeshSizeMax": mesh_size}
    with gmsh_model("hapticrom-liver", options):
        occ = gmsh.model.occ
        lobes = []
        for centre, semi_axes in LOBES:
            c = [scale * v for v in centre]
            sphere = occ.addSphere(*c, 1.0)
            occ.dilate([(3, sphere)], *c, *(scale * a for a in semi_axes))
            lobes.append((3, sphere))
        body, _ = occ.fuse(lobes[:1], lobes[1:])
        # Half-space below the cut plane: a big box whose top face is rotated
        # onto the plane.
        normal = np.asarray(CUT_NORMAL) / np.linalg.norm(CUT_NORMAL)
        big = 1000.0 * scale
        box = occ.addBox(-big, -big, -big, 2 * big, 2 * big, big)
        axis = np.cross([0.0, 0.0, 1.0], normal)
        occ.rotate([(3, box)], 0, 0, 0, *axis, math.acos(normal[2]))
        occ.translate([(3, box)], *(scale * v for v in CUT_POINT))
        solid, _ = occ.cut(body, [(3, box)])
        occ.synchronize()
        require(len(solid) == 1, "liver: the lobes did not fuse into one solid")
        gmsh.model.mesh.generate(3)

        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        _, tet_tags = gmsh.model.mesh.getElementsByType(4)

    coords = coords.reshape(-1, 3)
    tets_by_tag = tet_tags.reshape(-1, 4)
    # Keep only nodes used by tetrahedra (drops geometry-only points) and
    # renumber them 0..n-1 in increasing gmsh tag order.
    used = np.unique(tets_by_tag)
    order = np.argsort(node_tags)
    position = np.searchsorted(node_tags[order], used)
    nodes = coords[order[position]]
    tets = np.searchsorted(used, tets_by_tag).astype(np.int64)
    flip = tet_volumes(nodes, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return nodes, tets


def tet_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (mm^3); positive for the gmsh/right-hand orientation."""
    x = nodes[tets]
    return (
        np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
        / 6.0
    )


def classify_surface(
    nodes: np.ndarray,
    tets: np.ndarray,
    clamped_depth_fraction: float,
    anterior_normal_min: float,
) -> dict[str, np.ndarray]:
    """Boundary triangles (outward) split into clamped / loadable / free (see module doc)."""
    faces = boundary_faces(tets)
    x = nodes[faces]
    centroid = x.mean(axis=1)
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    y_min, y_max = nodes[:, 1].min(), nodes[:, 1].max()
    clamped = centroid[:, 1] > y_max - clamped_depth_fraction * (y_max - y_min)
    loadable = ~clamped & (-normal[:, 1] > anterior_normal_min)
    return {
        "clamped": faces[clamped],
        "loadable": faces[loadable],
        "free": faces[~clamped & ~loadable],
    }


def front_contact_node(nodes: np.ndarray, loadable: np.ndarray) -> np.ndarray:
    """The loadable node nearest (in x, z) to the centroid of the surface seen from the front.

    The centroid is that of the loadable triangles projected onto the
    frontal (x, z) plane, weighted by projected area.
    """
    x = nodes[loadable]
    projected_area = 0.5 * np.abs(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])[:, 1])
    centre = (projected_area[:, None] * x.mean(axis=1)).sum(axis=0) / projected_area.sum()
    candidates = np.unique(loadable)
    offset = nodes[candidates][:, [0, 2]] - centre[[0, 2]]
    return nodes[candidates[np.argmin(np.einsum("ij,ij->i", offset, offset))]]


def build_liver(refinement: str = "default", **overrides: Any) -> BuiltMesh:
    """The liver-like body: tetrahedra, clamped at the back, loadable at the front (mm)."""
    p = resolve_params("liver", LIVER_DEFAULTS, LIVER_PRESETS, refinement, overrides)
    require(p["scale"] > 0, f"liver: scale must be > 0, got {p['scale']}")
    # The mesher's cost grows as (size / mesh_size)^3: bound it so a typo
    # cannot ask for millions of tetrahedra.
    require(
        p["mesh_size"] >= 2.0 * p["scale"],
        f"liver: mesh_size must be >= {2.0 * p['scale']} mm (2 mm x scale), got {p['mesh_size']}",
    )
    require(
        0 < p["clamped_depth_fraction"] < 1,
        f"liver: clamped_depth_fraction must be in (0, 1), got {p['clamped_depth_fraction']}",
    )
    require(
        0 <= p["anterior_normal_min"] < 1,
        f"liver: anterior_normal_min must be in [0, 1), got {p['anterior_normal_min']}",
    )
    nodes, tets = tetrahedralise(p["scale"], p["mesh_size"])
    groups = classify_surface(nodes, tets, p["clamped_depth_fraction"], p["anterior_normal_min"])
    require(
        len(groups["clamped"]) > 0 and len(groups["loadable"]) > 0,
        "liver: these parameters leave the clamped or the loadable surface empty",
    )
    contact = front_contact_node(nodes, groups["loadable"])
    return BuiltMesh(
        name="liver",
        params=p,
        nodes=nodes,
        cells=tets,
        facet_groups=groups,
        supports=[{"group": "clamped", "components": "xyz"}],
        fibres=None,
        default_contact_point=[float(c) for c in contact],
        description=(
            "Liver (synthetic): fused-ellipsoid right/middle/left lobes cut by a tilted visceral "
            f"plane, scale {p['scale']}, tetrahedra of size about {p['mesh_size']} mm. Axes: +x "
            "patient's left, +y posterior, +z superior. Boundary triangles with centroid in the "
            f"posterior {p['clamped_depth_fraction']} of the y-depth are clamped; the others "
            f"whose outward normal has n.(-y) > {p['anterior_normal_min']} are loadable "
            "(anterior and antero-inferior surface); the rest is free."
        ),
    )
