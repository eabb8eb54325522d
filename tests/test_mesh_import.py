"""``hapticrom mesh import``: every input format, quadratic cells, units, rules, bad meshes.

Meshes come from the project's own generators (the beam's structured box, split into
tetrahedra here; the liver; the beam's .msh) and are written with meshio in each format.
What the importer wrote is read back with gmsh (hapticrom.meshes.msh) and checked against
references computed here: boundary faces counted from the cells, expected group sizes from
the grid, the generators' own groups.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import tomllib
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

meshio = pytest.importorskip("meshio")
pytest.importorskip("gmsh")

from hapticrom.meshes import build, generate  # noqa: E402
from hapticrom.meshes.beam import box_arrays  # noqa: E402
from hapticrom.meshes.importer import import_mesh  # noqa: E402
from hapticrom.meshes.msh import read_msh_group, read_sidecar, read_surface  # noqa: E402
from hapticrom.shared.errors import InputError  # noqa: E402

pytestmark = pytest.mark.serial

ROOT = Path(__file__).resolve().parents[1]
# The box: x in [0, 20], y and z in [-5, 5] (mm), 4 x 2 x 2 cells.
BOX = {"length": 20.0, "width": 10.0, "height": 10.0, "nx": 4, "ny": 2, "nz": 2}
# Outward faces of the gmsh/VTK hexahedron and tetrahedron, written out again here.
HEX_FACES = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (0, 4, 7, 3), (1, 2, 6, 5))
TET_FACES = ((0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3))
# (format for meshio.write, extension): every format the importer reads.
FORMATS = [
    ("vtk", ".vtk"),
    ("vtu", ".vtu"),
    ("gmsh22", ".msh"),
    ("gmsh", ".msh"),  # MSH 4.1
    ("medit", ".mesh"),
    ("abaqus", ".inp"),
]
RULES = """
[clamped]
[[clamped.box]]
name = "end x=0"
min = [-0.5, -6.0, -6.0]
max = [0.5, 6.0, 6.0]
[loadable]
[[loadable.normal_cone]]
name = "top"
axis = [0.0, 0.0, 1.0]
max_angle = 10.0
"""
BOX_RULES = """
[clamped]
[[clamped.box]]
min = [-0.5, -6.0, -6.0]
max = [0.5, 6.0, 6.0]
[loadable]
[[loadable.box]]
min = [-1.0, -6.0, 4.9]
max = [21.0, 6.0, 5.1]
"""


# --- meshes made here ------------------------------------------------------------------------


def hex_box(**overrides):
    """Nodes (mm) and positively oriented hexahedra of the beam generator's box."""
    nodes, hexes, _ = box_arrays(**{**BOX, **overrides})
    return nodes, hexes


def signed_tet_volumes(nodes, tets):
    x = nodes[tets]
    return np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])


def tet_box(**overrides):
    """The box split into 6 tetrahedra per hexahedron (Kuhn: conforming), positively oriented."""
    nodes, hexes = hex_box(**overrides)
    corner = {(0, 0, 0): 0, (1, 0, 0): 1, (1, 1, 0): 2, (0, 1, 0): 3}
    corner |= {(0, 0, 1): 4, (1, 0, 1): 5, (1, 1, 1): 6, (0, 1, 1): 7}
    tets = []
    for order in itertools.permutations(range(3)):
        path, bits = [corner[0, 0, 0]], [0, 0, 0]
        for axis in order:
            bits[axis] = 1
            path.append(corner[tuple(bits)])
        tets.append(hexes[:, path])
    tets = np.vstack(tets)
    flip = signed_tet_volumes(nodes, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return nodes, tets


def write(path: Path, nodes, blocks, file_format: str) -> Path:
    """Write cell ``blocks`` [(meshio type, cells)] with meshio (its notes go to stderr)."""
    meshio.write(path, meshio.Mesh(nodes, blocks), file_format=file_format)
    return path


def rules_file(tmp_path: Path, text: str = RULES, name: str = "rules.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def face_keys(cells: np.ndarray) -> Counter:
    table = HEX_FACES if cells.shape[1] == 8 else TET_FACES
    return Counter(tuple(sorted(int(v) for v in cell[list(f)])) for cell in cells for f in table)


def read_back(path: Path) -> dict:
    """Coordinates, cells and group faces of a written mesh, as gmsh reads them."""
    out = {}
    for group in ("clamped", "loadable", "free"):
        try:
            tags, coords, faces, cells = read_msh_group(path, group)
        except InputError:
            faces = np.empty((0, 3), dtype=np.int64)
        out[group] = faces
    order = np.argsort(tags)
    out["tags"], out["nodes"], out["cells"] = tags[order], coords[order], cells
    return out


def assert_groups_partition_boundary(mesh: dict) -> None:
    """Every boundary face (one cell) in exactly one group; no other face in any group."""
    boundary = {key for key, n in face_keys(mesh["cells"]).items() if n == 1}
    seen = Counter(
        tuple(sorted(int(v) for v in face))
        for group in ("clamped", "loadable", "free")
        for face in mesh[group]
    )
    assert set(seen) == boundary
    assert max(seen.values()) == 1


def group_xyz(mesh: dict, group: str) -> np.ndarray:
    """(faces, corners, 3) coordinates of a group read back."""
    index = np.searchsorted(mesh["tags"], mesh[group])
    return mesh["nodes"][index]


def no_files(directory: Path) -> bool:
    return not any(directory.iterdir())


# --- every format, tetrahedra and hexahedra -----------------------------------------------------


@pytest.mark.parametrize("kind", ["tetra", "hexahedron"])
@pytest.mark.parametrize(("file_format", "ext"), FORMATS, ids=[f for f, _ in FORMATS])
def test_every_format_imports(tmp_path, kind, file_format, ext):
    nodes, cells = tet_box() if kind == "tetra" else hex_box()
    source = write(tmp_path / f"box{ext}", nodes, [(kind, cells)], file_format)
    out = tmp_path / "out" / "box.msh"
    report = import_mesh(source, out, rules_file(tmp_path))

    mesh = read_back(out)
    assert len(mesh["cells"]) == len(cells) and len(mesh["nodes"]) == len(nodes)
    np.testing.assert_array_equal(mesh["nodes"], nodes)  # file order kept, exact coordinates
    assert_groups_partition_boundary(mesh)
    per_square = 2 if kind == "tetra" else 1  # a tetrahedral box face: two triangles
    nx, ny, nz = BOX["nx"], BOX["ny"], BOX["nz"]
    assert len(mesh["clamped"]) == ny * nz * per_square
    assert len(mesh["loadable"]) == nx * ny * per_square
    assert np.all(group_xyz(mesh, "clamped")[..., 0] == 0.0)
    assert np.all(group_xyz(mesh, "loadable")[..., 2] == BOX["height"] / 2)
    top = read_surface(out, "loadable")  # also checks that the faces point outwards
    np.testing.assert_allclose(top.normals, np.tile([0.0, 0.0, 1.0], (len(top.nodes), 1)))
    info = read_sidecar(out)
    assert info["cell_type"] == ("tetrahedron" if kind == "tetra" else "hexahedron")
    assert info["counts"] == {"nodes": len(nodes), "cells": len(cells)}
    assert info["supports"] == [{"group": "clamped", "components": "xyz"}]
    assert info["surface_groups"] == ["clamped", "loadable", "free"]
    assert info["name"] == "box" and info["params"]["scale"] == 1.0
    assert report.groups == {g: len(mesh[g]) for g in ("clamped", "loadable", "free")}


def test_hapticrom_msh_reimports_with_its_own_groups(tmp_path):
    """The beam generator's own binary MSH 4.1 (with boundary quadrangles, ignored)."""
    generated = tmp_path / "beam.msh"
    generate("beam", generated, "coarse")
    rules = rules_file(
        tmp_path,
        "[clamped]\n[clamped.box]\nmin = [-1, -30, -30]\nmax = [1, 30, 30]\n"
        "[loadable]\n[loadable.half_space]\npoint = [399, 0, 0]\nnormal = [1, 0, 0]\n",
    )
    report = import_mesh(generated, tmp_path / "again.msh", rules)
    boundary = sum(len(f) for f in build("beam", "coarse").facet_groups.values())
    assert report.source.ignored == {"quad": boundary}
    original, again = read_back(generated), read_back(tmp_path / "again.msh")
    for group in ("clamped", "loadable", "free"):
        np.testing.assert_array_equal(again[group], original[group])
    np.testing.assert_array_equal(again["cells"], original["cells"])


def test_liver_example_rules_reproduce_the_generator(tmp_path):
    """examples/mesh-import-rules.toml on the default liver written as VTU gives back the
    liver generator's own groups and default contact point."""
    liver = build("liver")
    source = write(tmp_path / "liver.vtu", liver.nodes, [("tetra", liver.cells)], "vtu")
    out = tmp_path / "liver.msh"
    import_mesh(source, out, ROOT / "examples" / "mesh-import-rules.toml")
    mesh = read_back(out)
    for group in ("clamped", "loadable", "free"):
        expected = {tuple(sorted(f + 1)) for f in liver.facet_groups[group]}  # gmsh tags
        assert {tuple(sorted(f)) for f in mesh[group]} == expected, group
    info = read_sidecar(out)
    assert info["default_contact_point"] == liver.default_contact_point
    assert info["name"] == "liver-imported"


# --- units, quadratic cells, orientation -------------------------------------------------------


def test_cm_mesh_with_scale_matches_the_mm_mesh(tmp_path):
    nodes, tets = tet_box()
    mm = write(tmp_path / "mm.vtu", nodes, [("tetra", tets)], "vtu")
    cm = write(tmp_path / "cm.vtu", nodes / 10.0, [("tetra", tets)], "vtu")
    rules = rules_file(tmp_path, BOX_RULES)
    import_mesh(mm, tmp_path / "mm.msh", rules)
    report = import_mesh(cm, tmp_path / "cm.msh", rules, scale=10.0)
    a, b = read_back(tmp_path / "mm.msh"), read_back(tmp_path / "cm.msh")
    np.testing.assert_allclose(b["nodes"], a["nodes"], rtol=1e-15, atol=1e-14)
    for group in ("clamped", "loadable", "free"):
        np.testing.assert_array_equal(b[group], a[group])
    assert len(a["loadable"]) == BOX["nx"] * BOX["ny"] * 2
    assert report.scale == 10.0 and read_sidecar(tmp_path / "cm.msh")["params"]["scale"] == 10.0
    # The rules are in mm: without --scale the cm mesh lies outside the clamped box.
    with pytest.raises(InputError, match=r"\[\[loadable.box\]\] #1 selects no boundary face"):
        import_mesh(cm, tmp_path / "unscaled.msh", rules)


def edges_of(cells: np.ndarray, pairs) -> np.ndarray:
    return np.unique(np.sort(cells[:, np.array(pairs)].reshape(-1, 2), axis=1), axis=0)


def with_higher_order(nodes, cells, kind: str):
    """Quadratic cells on the same corners: a new node per edge (and per face and cell for
    hexahedron27) at its midpoint, in meshio's (VTK) node order; (nodes, cells, new count)."""
    edges = {
        "tetra10": [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)],
        "hexahedron20": [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4)]
        + [(0, 4), (1, 5), (2, 6), (3, 7)],
    }
    edges["hexahedron27"] = edges["hexahedron20"]
    unique = edges_of(cells, edges[kind])
    extra = [nodes[unique].mean(axis=1)]
    local = np.sort(cells[:, np.array(edges[kind])], axis=2)
    ids = len(nodes) + np.array(
        [np.flatnonzero(np.all(unique == e, axis=1))[0] for e in local.reshape(-1, 2)]
    ).reshape(len(cells), -1)
    columns = [cells, ids]
    if kind == "hexahedron27":  # faces in VTK's order (-x, +x, -y, +y, -z, +z), then centre
        faces = [(0, 3, 7, 4), (1, 2, 6, 5), (0, 1, 5, 4), (3, 2, 6, 7), (0, 1, 2, 3), (4, 5, 6, 7)]
        keys = np.sort(cells[:, np.array(faces)], axis=2)
        face_keys_, face_ids = np.unique(keys.reshape(-1, 4), axis=0, return_inverse=True)
        start = len(nodes) + len(unique)
        extra.append(nodes[face_keys_].mean(axis=1))
        columns.append(start + face_ids.reshape(len(cells), 6))
        extra.append(nodes[cells].mean(axis=1))
        columns.append((start + len(face_keys_) + np.arange(len(cells)))[:, None])
    new_nodes = np.vstack([nodes, *extra])
    return new_nodes, np.hstack(columns), len(new_nodes) - len(nodes)


@pytest.mark.parametrize(
    ("kind", "file_format", "ext"),
    [
        ("tetra10", "vtu", ".vtu"),
        ("tetra10", "gmsh22", ".msh"),
        ("tetra10", "abaqus", ".inp"),
        ("hexahedron20", "vtu", ".vtu"),
        ("hexahedron20", "abaqus", ".inp"),
        ("hexahedron27", "vtu", ".vtu"),
        ("hexahedron27", "gmsh", ".msh"),
    ],
)
def test_quadratic_cells_keep_their_corners(tmp_path, kind, file_format, ext):
    nodes, cells = tet_box() if kind == "tetra10" else hex_box()
    linear_kind = "tetra" if kind == "tetra10" else "hexahedron"
    linear = write(tmp_path / "linear.vtu", nodes, [(linear_kind, cells)], "vtu")
    quad_nodes, quad_cells, added = with_higher_order(nodes, cells, kind)
    source = write(tmp_path / f"quadratic{ext}", quad_nodes, [(kind, quad_cells)], file_format)
    rules = rules_file(tmp_path)
    import_mesh(linear, tmp_path / "linear.msh", rules)
    report = import_mesh(source, tmp_path / "quadratic.msh", rules)
    a, b = read_back(tmp_path / "linear.msh"), read_back(tmp_path / "quadratic.msh")
    np.testing.assert_array_equal(b["nodes"], a["nodes"])
    np.testing.assert_array_equal(b["cells"], a["cells"])
    for group in ("clamped", "loadable", "free"):
        np.testing.assert_array_equal(b[group], a[group])
    assert len(report.source.higher_order) == added and report.unused_nodes == 0
    summary = "\n".join(report.lines())
    assert f"quadratic {kind}: corner nodes kept" in summary
    assert f"dropped {added:,} higher-order" in summary


def test_a_wholly_inverted_mesh_is_reoriented(tmp_path):
    nodes, hexes = hex_box()
    mirrored = hexes[:, [0, 3, 2, 1, 4, 7, 6, 5]]
    write(tmp_path / "ok.vtu", nodes, [("hexahedron", hexes)], "vtu")
    write(tmp_path / "mirror.vtu", nodes, [("hexahedron", mirrored)], "vtu")
    rules = rules_file(tmp_path)
    assert not import_mesh(tmp_path / "ok.vtu", tmp_path / "ok.msh", rules).reoriented
    report = import_mesh(tmp_path / "mirror.vtu", tmp_path / "mirror.msh", rules)
    assert report.reoriented and "reoriented" in "\n".join(report.lines())
    a, b = read_back(tmp_path / "ok.msh"), read_back(tmp_path / "mirror.msh")
    np.testing.assert_array_equal(b["cells"], a["cells"])
    np.testing.assert_array_equal(b["loadable"], a["loadable"])


def test_unused_nodes_are_dropped(tmp_path):
    nodes, tets = tet_box()
    stray = np.array([[100.0, 100.0, 100.0], [-50.0, 0.0, 0.0]])
    # Stray nodes first: the rest are renumbered, in file order.
    source = write(tmp_path / "s.vtk", np.vstack([stray, nodes]), [("tetra", tets + 2)], "vtk")
    report = import_mesh(source, tmp_path / "s.msh", rules_file(tmp_path))
    assert report.unused_nodes == 2 and "dropped 2 unused" in "\n".join(report.lines())
    np.testing.assert_array_equal(read_back(tmp_path / "s.msh")["nodes"], nodes)


# --- the rules ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("file_format", "ext", "base"), [("vtu", ".vtu", 0), ("gmsh22", ".msh", 1)]
)
def test_node_lists_count_from_their_base(tmp_path, file_format, ext, base):
    nodes, tets = tet_box()
    source = write(tmp_path / f"box{ext}", nodes, [("tetra", tets)], file_format)
    ids = (np.flatnonzero(nodes[:, 0] == 0.0) + base).tolist()
    by_ids = RULES.replace(
        '[[clamped.box]]\nname = "end x=0"\nmin = [-0.5, -6.0, -6.0]\nmax = [0.5, 6.0, 6.0]',
        f"[[clamped.nodes]]\nids = {ids}\nbase = {base}",
    )
    import_mesh(source, tmp_path / "box.msh", rules_file(tmp_path))
    import_mesh(source, tmp_path / "ids.msh", rules_file(tmp_path, by_ids, "ids.toml"))
    a, b = read_back(tmp_path / "box.msh"), read_back(tmp_path / "ids.msh")
    assert len(b["clamped"]) == BOX["ny"] * BOX["nz"] * 2
    np.testing.assert_array_equal(b["clamped"], a["clamped"])


def test_clamped_wins_over_loadable(tmp_path):
    nodes, hexes = hex_box()
    source = write(tmp_path / "box.vtu", nodes, [("hexahedron", hexes)], "vtu")
    # The first column of cells (x < 5): its top faces are in both groups' selections.
    rules = RULES.replace("max = [0.5, 6.0, 6.0]", "max = [5.0, 6.0, 6.0]")
    report = import_mesh(source, tmp_path / "o.msh", rules_file(tmp_path, rules))
    mesh = read_back(tmp_path / "o.msh")
    top = np.all(group_xyz(mesh, "clamped")[..., 2] == BOX["height"] / 2, axis=1)
    assert np.count_nonzero(top) == BOX["ny"]  # the top faces of the first column: clamped
    assert np.all(group_xyz(mesh, "loadable")[..., 0].min(axis=1) >= 5.0)
    assert report.groups["loadable"] == (BOX["nx"] - 1) * BOX["ny"]
    assert_groups_partition_boundary(mesh)


def test_default_contact_point(tmp_path):
    nodes, hexes = hex_box()
    source = write(tmp_path / "box.vtu", nodes, [("hexahedron", hexes)], "vtu")
    import_mesh(source, tmp_path / "a.msh", rules_file(tmp_path))
    # The top face's centroid (10, 0, 5) is a node.
    assert read_sidecar(tmp_path / "a.msh")["default_contact_point"] == [10.0, 0.0, 5.0]
    given = 'default_contact_point = [15.4, 2.0, 5.3]\nname = "boxy"\n' + RULES
    report = import_mesh(source, tmp_path / "b.msh", rules_file(tmp_path, given, "b.toml"))
    assert read_sidecar(tmp_path / "b.msh")["default_contact_point"] == [15.0, 0.0, 5.0]
    assert report.contact_snap == pytest.approx(np.sqrt(0.4**2 + 2.0**2 + 0.3**2), rel=1e-12)
    assert read_sidecar(tmp_path / "b.msh")["name"] == "boxy"


def test_components_and_fibres_reach_the_sidecar(tmp_path):
    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    text = RULES.replace("[clamped]", '[clamped]\ncomponents = "zx"') + (
        '[fibres]\nrule = "spherical_cap"\ncentre = [10.0, 0.0, -40.0]\n'
        "m_axis = [1.0, 0.0, 0.0]\nn_axis = [0.0, 1.0, 0.0]\n"
    )
    import_mesh(source, tmp_path / "o.msh", rules_file(tmp_path, text))
    info = read_sidecar(tmp_path / "o.msh")
    assert info["supports"] == [{"group": "clamped", "components": "zx"}]
    assert info["fibres"] == {
        "rule": "spherical_cap",
        "centre": [10.0, 0.0, -40.0],
        "m_axis": [1.0, 0.0, 0.0],
        "n_axis": [0.0, 1.0, 0.0],
    }


# --- bad meshes: one clear error each, nothing written ----------------------------------------


def three_cells_on_a_face():
    """Two tetrahedra on one side of a triangle and one on the other."""
    nodes = np.array(
        [[0, 0, 0], [10, 0, 0], [0, 10, 0], [2, 2, 10], [3, 3, -10], [2, 3, 12]], dtype=float
    )
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 4], [0, 1, 2, 5]])
    flip = signed_tet_volumes(nodes, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return nodes, [("tetra", tets)]


def cubes_meeting_at_an_edge():
    """Five unit cells of a 2 x 2 x 2 grid, face-connected, two of which share only an edge."""
    nodes, hexes = hex_box(length=20.0, width=20.0, height=20.0, nx=2, ny=2, nz=2)
    keep = [0, 4, 5, 7, 3]  # (i, j, k): (0,0,0), (0,0,1), (1,0,1), (1,1,1), (1,1,0)
    return nodes, [("hexahedron", hexes[keep])]


def bad_mesh(case: str):
    """(nodes, blocks, meshio format, extension) of a broken mesh."""
    nodes, tets = tet_box()
    nodes_h, hexes = hex_box()
    if case == "mixed orientation":
        tets[5] = tets[5][[0, 2, 1, 3]]
    elif case == "mostly inverted":
        tets = tets[:, [0, 2, 1, 3]]
        tets[5] = tets[5][[0, 2, 1, 3]]
    elif case == "degenerate":
        face = [tets[0][list(TET_FACES[0])]]  # any triangle, and its centroid: a flat cell
        nodes = np.vstack([nodes, nodes[face[0]].mean(axis=0)])
        tets = np.vstack([tets, [[*face[0], len(nodes) - 1]]])
    elif case == "repeated node":
        tets[3, 1] = tets[3, 0]
    elif case == "duplicate cell":
        tets = np.vstack([tets, tets[:1]])
    elif case == "tangled":
        hexes[2] = hexes[2][[0, 1, 3, 2, 4, 5, 6, 7]]
        return nodes_h, [("hexahedron", hexes)], "vtu", ".vtu"
    elif case == "three cells on a face":
        return (*three_cells_on_a_face(), "vtu", ".vtu")
    elif case == "non-manifold edge":
        return (*cubes_meeting_at_an_edge(), "vtu", ".vtu")
    elif case == "two bodies":
        nodes = np.vstack([nodes, nodes + [50.0, 0.0, 0.0]])
        tets = np.vstack([tets, tets + len(nodes) // 2])
    elif case == "unmerged nodes":
        nodes, tets = nodes[tets.ravel()], np.arange(tets.size).reshape(-1, 4)
    elif case == "surface only":
        tris = [k for k, n in face_keys(tets).items() if n == 1]
        return nodes, [("triangle", np.array(tris))], "vtk", ".vtk"
    elif case == "tets and hexes":
        return nodes, [("tetra", tets), ("hexahedron", hexes)], "vtu", ".vtu"
    elif case == "wedges":
        return nodes_h, [("wedge", hexes[:, [0, 1, 2, 4, 5, 6]])], "vtu", ".vtu"
    elif case == "non-finite":
        nodes[7, 1] = np.nan
    elif case == "node out of range":
        tets[9, 2] = len(nodes) + 3
    return nodes, [("tetra", tets)], "vtu", ".vtu"


BAD_MESHES = {
    "mixed orientation": r"inverted volume cell #5 \(0-based, file order\) at .*: 1 of 96 cells "
    r"are inverted",
    "mostly inverted": r"mixed orientation: volume cell #5 .* is positive: 95 of 96 cells are "
    r"inverted",
    "degenerate": r"degenerate volume cell #96 .*volume ~ 0",
    "repeated node": r"degenerate volume cell #3 .*a node repeats",
    "duplicate cell": r"volume cells #0 and #96 are the same cell",
    "tangled": r"tangled volume cell #2 .*both signs",
    "three cells on a face": r"non-manifold mesh: the face of file nodes \[0, 1, 2\] is shared "
    r"by 3 cells \(#0, #1, #2\)",
    "non-manifold edge": r"non-manifold boundary: the edge of file nodes \[4, 13\] at "
    r"\(10, 0, -5\) lies on 4 boundary faces",
    "two bodies": r"2 disconnected bodies \(cells per body: 96, 96\).*import one body per file",
    "unmerged nodes": r"nodes 0 and 64 \(0-based\) coincide at \(0, -5, -5\) mm \(within "
    r".*; 384 such node\(s\)\).*merge duplicate nodes",
    "surface only": r"has no volume cells \(only triangle 80\): a surface mesh",
    "tets and hexes": r"mixed cell types tetra \(96\) and hexahedron \(16\)",
    "wedges": r"unsupported cell type\(s\) wedge \(16\)",
    "non-finite": r"node 7 \(0-based\) has a non-finite coordinate",
    "node out of range": r"volume cell #9 refers to a node that does not exist",
}


@pytest.mark.parametrize("case", sorted(BAD_MESHES))
def test_bad_meshes_are_refused_and_nothing_is_written(tmp_path, case):
    nodes, blocks, file_format, ext = bad_mesh(case)
    source = write(tmp_path / f"bad{ext}", nodes, blocks, file_format)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(InputError, match=BAD_MESHES[case]) as caught:
        import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path))
    assert str(source) in str(caught.value)
    assert no_files(out_dir)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.mesh", "MeshVersionFormatted 2\nDimension 3\nVertices\n0\nEnd\n", "no nodes"),
        (
            "nocells.msh",
            "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n1\n1 0 0 0\n$EndNodes\n"
            "$Elements\n0\n$EndElements\n",
            "empty mesh: it has no cells",
        ),
        ("zero.vtu", "", r"empty \(0 bytes\)"),
        ("garbage.vtu", "<VTKFile>not xml at all", "cannot read .*garbage.vtu as VTU"),
        ("garbage.inp", "*NODE\n1, a, b, c\n", "cannot read .*garbage.inp as Abaqus"),
        ("organ.stl", "solid x\nendsolid x\n", r"unknown mesh file extension '.stl'"),
    ],
)
def test_unreadable_and_empty_files(tmp_path, name, content, message):
    source = tmp_path / name
    source.write_text(content)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(InputError, match=message):
        import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path))
    with pytest.raises(InputError, match="not found"):
        import_mesh(tmp_path / "missing.vtu", out_dir / "organ.msh", rules_file(tmp_path))
    assert no_files(out_dir)


FAR_BOX = '[[clamped.box]]\nname = "far"\nmin = [100, 100, 100]\nmax = [101, 101, 101]\n'
BAD_RULES = [
    (RULES.replace("[clamped]\n", "[clamped]\n" + FAR_BOX), r"\[\[clamped.box\]\] #1 'far' "),
    (
        RULES.replace(
            "[loadable]", "[loadable]\n[[loadable.box]]\nmin = [-1, -6, -6]\nmax = [0.5, 6, 6]"
        ),
        r"\[\[loadable.box\]\] #1 selects 8 face\(s\), all of them clamped",
    ),
    (
        "[clamped]\n[loadable]\n[[loadable.box]]\nmin = [0, 0, 0]\nmax = [1, 1, 1]\n",
        "no clamped face: .*free rigid body",
    ),
    (RULES.split("[loadable]")[0] + "[loadable]\n", "no loadable face"),
    (
        RULES.replace("[loadable]", "[loadable]\n[[loadable.nodes]]\nids = [1, 45]\nbase = 0"),
        r"\[\[loadable.nodes\]\] #1: node id 45 is not a node of the input \(with base = 0 the "
        r"ids run from 0 to 44\)",
    ),
    (
        "default_contact_point = [10.0, 0.0, 25.0]\n" + RULES,
        r"default_contact_point \[10.0, 0.0, 25.0\] is 20 mm from the nearest loadable node",
    ),
    (
        RULES + "[fibres]\nrule = 'spherical_cap'\ncentre = [CENTRE]\nm_axis = [1, 0, 0]\n"
        "n_axis = [0, 1, 0]\n",
        r"\[fibres\] fibre directions are undefined at the spherical ",
    ),
    # the file itself
    ("colour = 'red'\n" + RULES, r"unknown key\(s\) colour; allowed: clamped, default_contact"),
    (RULES.replace("[loadable]", "[free]\n[loadable]"), r"unknown key\(s\) free"),
    (
        RULES.replace("max = [0.5, 6.0, 6.0]", "max = [-1.0, 6.0, 6.0]"),
        r"\[\[clamped.box\]\] #1 min \[-0.5, -6.0, -6.0\] must not exceed max",
    ),
    (
        RULES.replace("axis = [0.0, 0.0, 1.0]", "axis = [0, 0, 0]"),
        r"\[\[loadable.normal_cone\]\] #1 axis must not be the zero vector",
    ),
    (RULES.replace("max_angle = 10.0", "max_angle = 200"), r"max_angle must lie in \(0, 180\]"),
    (RULES.replace("max_angle = 10.0", "max_angle = nan"), r"max_angle must be a finite number"),
    (
        RULES.replace("[clamped]", "[clamped]\ncomponents = 'xxy'"),
        r"\[clamped\] components must be one to three of x, y, z",
    ),
    (
        RULES.replace("[loadable]", "[loadable]\n[[loadable.nodes]]\nids = [1, 2]\nbase = 2"),
        r"\[\[loadable.nodes\]\] #1 base must lie in \[0, 1\], got 2",
    ),
    (
        RULES.replace("[loadable]", "[loadable]\n[[loadable.nodes]]\nids = [1.5]\nbase = 0"),
        r"ids must be a finite integer, got 1.5",
    ),
    # beyond int64: refused by the table, not an OverflowError when selecting
    (
        RULES.replace(
            "[loadable]",
            "[loadable]\n[[loadable.nodes]]\nids = [1, 99999999999999999999]\nbase = 0",
        ),
        r"\[\[loadable.nodes\]\] #1 ids must lie in \[0, 9007199254740991\], got "
        r"99999999999999999999",
    ),
    # lengths whose square underflows or overflows: refused by the table, naming the key
    (
        RULES.replace("axis = [0.0, 0.0, 1.0]", "axis = [1e-200, 0, 1e-200]"),
        r"\[\[loadable.normal_cone\]\] #1 axis must have a length in \[1e-100, 1e\+100\], got "
        r"1.41e-200",
    ),
    (
        RULES.replace(
            "[loadable]",
            "[loadable]\n[[loadable.half_space]]\npoint = [0, 0, 0]\nnormal = [0, 1e200, 1e200]",
        ),
        r"\[\[loadable.half_space\]\] #1 normal must have a length in .*got 1.41e\+200",
    ),
    (RULES.split("[loadable]")[0], r"missing table \[loadable\]"),
    ("[clamped\n", "not valid TOML"),
]


@pytest.mark.parametrize(("text", "message"), BAD_RULES, ids=range(len(BAD_RULES)))
def test_bad_rules_are_refused_and_nothing_is_written(tmp_path, text, message):
    nodes, tets = tet_box()
    centre = ", ".join(str(c) for c in nodes[tets[0]].mean(axis=0))
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    rules = rules_file(tmp_path, text.replace("CENTRE", centre))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(InputError, match=message) as caught:
        import_mesh(source, out_dir / "organ.msh", rules)
    assert str(caught.value).startswith(f"{rules}: ")
    assert no_files(out_dir)


def test_check_refuses_what_import_refuses(tmp_path):
    """``hapticrom check`` validates a rules file with the same table: a node id beyond
    int64 or a tiny axis is refused there, before any mesh is read."""
    from hapticrom.offline.check import check_config

    ids = rules_file(
        tmp_path, RULES + "[[loadable.nodes]]\nids = [18446744073709551616]\nbase = 1\n"
    )
    with pytest.raises(InputError, match=r"\[\[loadable.nodes\]\] #1 ids must lie in \[0, "):
        check_config(ids)
    axis = rules_file(tmp_path, RULES.replace("[0.0, 0.0, 1.0]", "[0, 1e-120, 0]"), "axis.toml")
    with pytest.raises(InputError, match=r"#1 axis must have a length in \[1e-100, "):
        check_config(axis)
    unit = rules_file(tmp_path, RULES.replace("[0.0, 0.0, 1.0]", "[0, 0, 1e-90]"), "unit.toml")
    assert check_config(unit).endswith(": OK")  # within the bounds: only the direction counts


def test_no_rules_and_bad_outputs_are_refused(tmp_path):
    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(InputError, match="needs --rules RULES.toml.*free rigid body"):
        import_mesh(source, out_dir / "organ.msh", None)
    with pytest.raises(InputError, match="must be a .msh file"):
        import_mesh(source, out_dir / "organ.vtu", rules_file(tmp_path))
    for scale in (0.0, -2.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="--scale must be a positive number"):
            import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path), scale=scale)
    (tmp_path / "adir.vtu").mkdir()
    with pytest.raises(InputError, match=r"mesh file .*adir.vtu is a directory"):
        import_mesh(tmp_path / "adir.vtu", out_dir / "organ.msh", rules_file(tmp_path))
    assert no_files(out_dir)


def test_a_sidecar_name_taken_by_a_directory_is_refused_first(tmp_path):
    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    out_dir = tmp_path / "out"
    (out_dir / "organ.json").mkdir(parents=True)
    with pytest.raises(InputError, match=r"its sidecar .*organ.json is an existing directory"):
        import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path))
    assert [p.name for p in out_dir.iterdir()] == ["organ.json"]
    assert not any((out_dir / "organ.json").iterdir())


def test_the_writer_refuses_directories_and_removes_its_partial_files(tmp_path):
    """write_msh itself: a sidecar name taken by a directory is refused before any work; a
    failure after the partial .msh is written (here its partial sidecar's name is a
    directory) removes the partial .msh."""
    from hapticrom.meshes.msh import write_msh

    nodes, tets = tet_box()
    (tmp_path / "organ.json").mkdir()
    with pytest.raises(InputError, match=r"cannot write mesh file .*organ.json: it is a directory"):
        write_msh(tmp_path / "organ.msh", nodes, tets, {}, {"name": "organ"})
    partial = f".other.partial-{os.getpid()}.json"  # the writer's, named by process
    (tmp_path / partial).mkdir()
    with pytest.raises(IsADirectoryError):
        write_msh(tmp_path / "other.msh", nodes, tets, {}, {"name": "other"})
    assert sorted(p.name for p in tmp_path.iterdir()) == [partial, "organ.json"]
    (tmp_path / partial).rmdir()
    write_msh(tmp_path / "other.msh", nodes, tets, {}, {"name": "other"})  # the writer works
    assert sorted(p.name for p in tmp_path.iterdir()) == ["organ.json", "other.json", "other.msh"]


# --- coincident nodes, far or tiny coordinates, graded meshes -----------------------------------


@pytest.mark.parametrize("where", ["interior", "surface"])
def test_coincident_nodes_are_refused(tmp_path, where):
    """A node copied (same coordinates, or 1e-12 mm away) and used by the cells on one side
    of it: a slit inside the body (interior) or a crack reaching the surface (surface), which
    would become boundary faces. Refused naming the node and its copy."""
    nodes, tets = tet_box()
    target = [10.0, 0.0, 0.0] if where == "interior" else [10.0, 0.0, 5.0]
    node = int(np.flatnonzero(np.all(nodes == target, axis=1))[0])
    above = (nodes[tets].mean(axis=1)[:, 1] > 0) & np.any(tets == node, axis=1)
    assert 0 < np.count_nonzero(above) < np.count_nonzero(np.any(tets == node, axis=1))
    for offset in (0.0, 1e-12):
        copy = nodes[node] + [offset, 0.0, 0.0]
        split = tets.copy()
        split[above] = np.where(split[above] == node, len(nodes), split[above])
        source = write(tmp_path / "slit.vtu", np.vstack([nodes, copy]), [("tetra", split)], "vtu")
        out_dir = tmp_path / "out"
        out_dir.mkdir(exist_ok=True)
        expected = (
            rf"nodes {node} and {len(nodes)} \(0-based\) coincide at \(10, 0, {target[2]:g}\) "
            r"mm .*2 such node\(s\)\).*merge duplicate nodes"
        )
        with pytest.raises(InputError, match=expected):
            import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path))
        assert no_files(out_dir)


def test_coordinates_beyond_the_artifacts_bound_are_refused(tmp_path):
    """The artifact refuses points beyond MAX_LENGTH (mm): refused at import, after --scale,
    naming the node; an unused node out there does not matter."""
    from hapticrom.shared.artifact_rules import MAX_LENGTH

    nodes, tets = tet_box()
    rules = rules_file(tmp_path, BOX_RULES)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    shifted = nodes.copy()
    shifted[:, 1] += MAX_LENGTH - 5.0 + 1e-3  # y in [MAX_LENGTH - 10, MAX_LENGTH + 1e-3]
    cases = [
        (shifted, 1.0, r"lies at \(.*, 1e\+04, .*\) mm \(file coordinates x --scale 1\)"),
        (nodes + 1e15, 1.0, r"lies at \(1e\+15, 1e\+15, 1e\+15\) mm"),
        (nodes, MAX_LENGTH / 10.0, r"lies at \(1\.5e\+04, .*x --scale 1000\)"),
        (nodes * 1e10, 1e300, r"lies at \(.*inf.*\) mm \(file coordinates x --scale 1e\+300\)"),
    ]
    for points, scale, message in cases:
        source = write(tmp_path / "far.vtu", points, [("tetra", tets)], "vtu")
        with np.errstate(over="ignore"):
            beyond = np.flatnonzero(np.abs(points * scale).max(axis=1) > MAX_LENGTH)
        expected = (
            rf"node {beyond[0]} \(0-based\) {message}.*beyond the {MAX_LENGTH:g} mm .*"
            rf"\({len(beyond)} such node\(s\)\)"
        )
        with pytest.raises(InputError, match=expected):
            import_mesh(source, out_dir / "organ.msh", rules, scale=scale)
    assert no_files(out_dir)
    # Within the bound (and a stray unused node far beyond it): imported.
    inside = nodes + [0.0, 0.0, MAX_LENGTH - 5.0]
    inside_rules = BOX_RULES.replace("4.9]", f"{MAX_LENGTH - 0.1}]").replace(
        "5.1]", f"{MAX_LENGTH + 0.1}]"
    )
    inside_rules = inside_rules.replace("6.0, 6.0]", f"6.0, {MAX_LENGTH + 6}]")
    source = write(tmp_path / "in.vtu", np.vstack([inside, [1e15, 0, 0]]), [("tetra", tets)], "vtu")
    import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path, inside_rules, "in.toml"))
    assert read_back(out_dir / "organ.msh")["nodes"][:, 2].max() == MAX_LENGTH


def test_a_mesh_scaled_to_nothing_is_refused(tmp_path):
    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(InputError, match=r"the mesh spans 2e-299 mm .*x --scale 1e-300\), less "):
        import_mesh(source, out_dir / "organ.msh", rules_file(tmp_path), scale=1e-300)
    assert no_files(out_dir)


def graded_hex_box(spacing: np.ndarray):
    """A hexahedral box whose cells have the given widths along x, y and z (mm)."""
    g = np.concatenate([[0.0], np.cumsum(spacing)])
    n = len(spacing)
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    i, j, k = (a.ravel() for a in np.meshgrid(*[np.arange(n)] * 3, indexing="ij"))

    def at(di, dj, dk):
        return ((i + di) * (n + 1) + j + dj) * (n + 1) + k + dk

    corners = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1)]
    corners.append((0, 1, 1))
    return grid, np.stack([at(*c) for c in corners], axis=1)


CONE_RULES = """
[clamped]
[[clamped.normal_cone]]
axis = [0, 0, -1]
max_angle = 30
[loadable]
[[loadable.normal_cone]]
axis = [0, 0, 1]
max_angle = 30
"""


def test_a_graded_mesh_is_not_degenerate(tmp_path):
    """Cubes from 0.02 to 10 mm (a 500-fold volume range cubed): each cell is judged by its own
    shape, not against the mean; a layer of plates (1e-7 of their width) is still refused."""
    spacing = np.geomspace(0.02, 10.0, 8)
    nodes, hexes = graded_hex_box(spacing)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    rules = rules_file(tmp_path, CONE_RULES)
    source = write(tmp_path / "graded.vtu", nodes, [("hexahedron", hexes)], "vtu")
    report = import_mesh(source, out_dir / "graded.msh", rules)
    assert report.cells == 8**3 and report.groups["clamped"] == report.groups["loadable"] == 64
    np.testing.assert_array_equal(read_back(out_dir / "graded.msh")["nodes"], nodes)

    flat = spacing.copy()
    flat[-1] = 0.02 * 1e-7  # the last layer in x, y and z: plates, needles and flakes
    nodes, hexes = graded_hex_box(flat)
    source = write(tmp_path / "flat.vtu", nodes, [("hexahedron", hexes)], "vtu")
    plates = np.flatnonzero(np.any(nodes[hexes].max(axis=1) == nodes.max(axis=0), axis=1))
    with pytest.raises(InputError, match=rf"degenerate volume cell #{plates[0]} .*volume ~ 0 "):
        import_mesh(source, tmp_path / "flat.msh", rules)


# --- downstream and the command line -------------------------------------------------------


def test_check_recognises_a_rules_file():
    from hapticrom.offline.check import check_config, config_kind

    example = ROOT / "examples" / "mesh-import-rules.toml"
    assert config_kind(tomllib.loads(example.read_text())) == "mesh-import-rules"
    assert check_config(example) == (
        f"{example}: mesh-import-rules 'liver-imported', 1 clamped selector (xyz), "
        "1 loadable selector: OK"
    )


def test_load_organ_reads_an_imported_mesh(tmp_path):
    MPI = pytest.importorskip("mpi4py.MPI")
    from hapticrom.offline.fe.organ import load_organ

    nodes, tets = tet_box()
    source = write(tmp_path / "box.inp", nodes, [("tetra", tets)], "abaqus")
    report = import_mesh(source, tmp_path / "organ.msh", rules_file(tmp_path))
    organ = load_organ(tmp_path / "organ.msh", MPI.COMM_SELF)
    assert organ.cell_type == "tetrahedron"
    assert organ.mesh.topology.index_map(3).size_global == len(tets)
    for group, count in report.groups.items():
        assert len(organ.facets(group)) == count
    np.testing.assert_array_equal(organ.default_contact_point(), [10.0, 0.0, 5.0])


def test_command_line(tmp_path, capsys):
    from hapticrom.cli import main

    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes / 10.0, [("tetra", tets)], "vtu")
    out = tmp_path / "organ" / "box.msh"
    args = ["mesh", "import", source, "--out", out, "--rules", rules_file(tmp_path, BOX_RULES)]
    assert main([str(a) for a in [*args, "--scale", "10"]]) == 0
    text = capsys.readouterr().out
    assert f"imported {source} (VTU, 96 tetra)" in text
    assert re.search(r"faces +clamped 8, loadable 16, free 56 \(of 80 boundary faces\)", text)
    assert "scale  10 " in text
    assert json.loads(out.with_suffix(".json").read_text())["counts"]["cells"] == 96

    out.unlink()
    out.with_suffix(".json").unlink()
    assert main([str(a) for a in args]) == 2  # rules in mm, mesh in cm, no --scale
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "selects no boundary face" in err[0], err
    assert not out.exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--refinement", "fine"], "mesh import takes no --refinement"),
        ([], "mesh import needs --rules RULES.toml"),
        (["--rules", "r.toml", "--scale", "0"], "argument --scale: must be above 0"),
    ],
)
def test_command_line_refusals(tmp_path, capsys, extra, message):
    from hapticrom.cli import main

    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    rules_file(tmp_path, RULES, "r.toml")
    extra = [str(tmp_path / e) if e == "r.toml" else e for e in extra]
    out = tmp_path / "out" / "box.msh"
    try:
        code = main(["mesh", "import", str(source), "--out", str(out), *extra])
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not out.parent.exists()


def test_command_line_out_is_a_directory(tmp_path, capsys):
    """--out naming an existing directory: the example is a .msh file in it."""
    from hapticrom.cli import main

    nodes, tets = tet_box()
    source = write(tmp_path / "box.vtu", nodes, [("tetra", tets)], "vtu")
    out = tmp_path / "organ.msh"
    out.mkdir()
    args = ["mesh", "import", source, "--out", out, "--rules", rules_file(tmp_path)]
    assert main([str(a) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    example = f"is a directory; give a file name, e.g. {out / out.name}"
    assert len(err) == 1 and err[0].endswith(example), err
    assert not any(out.iterdir())


def test_built_in_meshes_refuse_import_options(tmp_path, capsys):
    from hapticrom.cli import main

    assert main(["mesh", "beam", "--out", str(tmp_path / "b.msh"), "--scale", "10"]) == 2
    assert "mesh beam takes no --scale" in capsys.readouterr().err
    assert main(["mesh", "beam", str(tmp_path / "x.vtu"), "--out", str(tmp_path / "b.msh")]) == 2
    assert "mesh beam takes no INPUT" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_a_cm_mesh_imported_with_box_rules_trains_into_a_model(tmp_path):
    """End to end: a hexahedral box written in cm (VTU), imported with ``--scale 10`` and box
    rules, trained (four positions on its top, serial) and reduced; the runtime loads the
    artifact and reproduces a sample's stored force at the trained depth."""
    from mpi4py import MPI

    from hapticrom.offline.campaign.config import CampaignConfig
    from hapticrom.offline.campaign.run import run_campaign
    from hapticrom.offline.reduce.reduction import reduce_campaign
    from hapticrom.online import load

    nodes, hexes = hex_box()
    cm = write(tmp_path / "box-cm.vtu", nodes / 10.0, [("hexahedron", hexes)], "vtu")
    import_mesh(cm, tmp_path / "box.msh", rules_file(tmp_path, BOX_RULES), scale=10.0)
    campaign = tmp_path / "campaign.toml"
    campaign.write_text(f"""
[campaign]
name = "imported-box"
[mesh]
file = "{tmp_path / "box.msh"}"
[material]
law = "neo-hookean"
E = 0.05
nu = 0.45
[load]
mode = "force"
magnitude = 0.05
contact_radius = 4.0
steps = 2
[[positions.farthest]]
n = 4
centre = [12.5, 0.0, 5.0]
radius = 6.0
[anm]
enabled = false
""")
    config = CampaignConfig.from_toml(campaign)
    run_campaign(config, tmp_path / "store", verbose=False)
    reduce_campaign(tmp_path / "store", tmp_path / "box.h5", MPI.COMM_SELF, verbose=False)
    model = load(tmp_path / "box.h5")
    sim = model.simulator(response="curves")
    sim.set_contact(model.sample_points[0])
    force = sim.step_displacement(-model.solved_depth[0] * sim.contact_normal)
    assert np.linalg.norm(force) == pytest.approx(model.sample_trained_force[0], rel=1e-9)
    # the trained force, to the resampling of its curve on the grid (tests/test_depth_grid.py)
    assert model.sample_trained_force[0] == pytest.approx(config.load.magnitude, rel=5e-4)
    assert np.all(model.sample_points[:, 2] == pytest.approx(5.0))  # mm, on the top face
