"""Tests of the mesh generators (hapticrom.meshes): counts, validity, groups, geometry, files."""

from __future__ import annotations

import functools
import json
import math
from collections import Counter

import numpy as np
import pytest

from hapticrom.meshes import MESHES, build, generate, read_sidecar
from hapticrom.meshes.fibres import fibre_directions
from hapticrom.meshes.msh import gmsh_home_guard
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

NAMES = ("cornea", "hemisphere", "beam", "liver")

# Outward-oriented faces of the gmsh hexahedron / tetrahedron, written out
# again here so the test does not trust the generators' own table.
HEX_FACES = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (0, 4, 7, 3), (1, 2, 6, 5))
TET_FACES = ((0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3))
# Each hexahedron corner with its three edge neighbours, right-handed.
HEX_CORNERS = {
    0: (1, 3, 4),
    1: (2, 0, 5),
    2: (3, 1, 6),
    3: (0, 2, 7),
    4: (7, 5, 0),
    5: (4, 6, 1),
    6: (5, 7, 2),
    7: (6, 4, 3),
}


def built(name: str, refinement: str = "coarse"):
    """The mesh built once per test session (the same arguments always hit the cache)."""
    return _built(name, refinement)


@functools.cache
def _built(name: str, refinement: str):
    return build(name, refinement)


def cell_faces(cells: np.ndarray) -> list[tuple[int, ...]]:
    table = HEX_FACES if cells.shape[1] == 8 else TET_FACES
    return [tuple(int(v) for v in cell[list(face)]) for cell in cells for face in table]


def boundary_face_keys(cells: np.ndarray) -> set[tuple[int, ...]]:
    """Faces (as sorted node tuples) that belong to exactly one cell."""
    counts = Counter(tuple(sorted(face)) for face in cell_faces(cells))
    return {key for key, count in counts.items() if count == 1}


def corner_jacobians(nodes: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    x = nodes[hexes]
    dets = []
    for corner, (a, b, c) in HEX_CORNERS.items():
        e1, e2, e3 = (x[:, k] - x[:, corner] for k in (a, b, c))
        dets.append(np.einsum("ij,ij->i", np.cross(e1, e2), e3))
    return np.array(dets)


def tet_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    x = nodes[tets]
    return (
        np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6
    )


def group_nodes(mesh, group: str) -> np.ndarray:
    return mesh.nodes[np.unique(mesh.facet_groups[group])]


# --- counts ------------------------------------------------------------------------------

COUNT_RANGES = {
    ("cornea", "coarse"): ((200, 800), (100, 700)),
    ("cornea", "default"): ((8000, 9000), (6000, 7600)),
    ("hemisphere", "coarse"): ((100, 600), (50, 448)),
    ("hemisphere", "default"): ((600, 800), (400, 500)),
    ("beam", "coarse"): ((99, 99), (40, 40)),
    ("beam", "default"): ((1025, 1025), (640, 640)),
    ("liver", "coarse"): ((350, 700), (1000, 3000)),
    ("liver", "default"): (
        (int(2900 * 0.85), int(2900 * 1.15)),
        (int(10500 * 0.85), int(10500 * 1.15)),
    ),
}


@pytest.mark.parametrize(("name", "refinement"), sorted(COUNT_RANGES))
def test_counts_in_range(name, refinement):
    mesh = built(name, refinement)
    (nodes_lo, nodes_hi), (cells_lo, cells_hi) = COUNT_RANGES[name, refinement]
    assert nodes_lo <= len(mesh.nodes) <= nodes_hi
    assert cells_lo <= len(mesh.cells) <= cells_hi
    assert mesh.cells.shape[1] == (4 if name == "liver" else 8)
    # Every node is used by a cell.
    assert np.array_equal(np.unique(mesh.cells), np.arange(len(mesh.nodes)))


# --- validity and groups -----------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_cells_positively_oriented(name):
    mesh = built(name)
    if mesh.cells.shape[1] == 8:
        assert corner_jacobians(mesh.nodes, mesh.cells).min() > 0
    else:
        assert tet_volumes(mesh.nodes, mesh.cells).min() > 0


@pytest.mark.parametrize("name", NAMES)
def test_groups_partition_the_boundary(name):
    mesh = built(name)
    expected = boundary_face_keys(mesh.cells)
    seen: list[tuple[int, ...]] = []
    for group, faces in mesh.facet_groups.items():
        assert group in ("clamped", "loadable", "free")
        seen += [tuple(sorted(int(v) for v in face)) for face in faces]
    assert len(seen) == len(set(seen)), "a boundary face is in two groups"
    assert set(seen) == expected
    assert len(mesh.facet_groups["clamped"]) > 0 and len(mesh.facet_groups["loadable"]) > 0


@pytest.mark.parametrize("name", NAMES)
def test_boundary_faces_point_outwards(name):
    mesh = built(name)
    owner = {}
    for index, cell in enumerate(mesh.cells):
        for face in HEX_FACES if mesh.cells.shape[1] == 8 else TET_FACES:
            owner[tuple(sorted(int(cell[k]) for k in face))] = index
    for faces in mesh.facet_groups.values():
        x = mesh.nodes[faces]
        normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
        cells = [owner[tuple(sorted(int(v) for v in face))] for face in faces]
        away = x.mean(axis=1) - mesh.nodes[mesh.cells[cells]].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", normal, away) > 0)


@pytest.mark.parametrize("name", NAMES)
def test_sidecar_contents(name):
    mesh = built(name)
    sidecar = mesh.sidecar()
    assert sidecar["format"] == "hapticrom-mesh" and sidecar["version"] == 1
    assert sidecar["name"] == name and sidecar["units"] == "mm"
    assert sidecar["cell_type"] == ("tetrahedron" if name == "liver" else "hexahedron")
    assert sidecar["counts"] == {"nodes": len(mesh.nodes), "cells": len(mesh.cells)}
    assert sidecar["surface_groups"] == ["clamped", "loadable", "free"]
    json.dumps(sidecar)  # plain types only
    # The contact point is a node of the loadable surface.
    contact = np.array(sidecar["default_contact_point"])
    assert np.any(np.all(group_nodes(mesh, "loadable") == contact, axis=1))
    # Point supports name existing nodes.
    for support in sidecar["supports"]:
        assert set(support["components"]) <= set("xyz")
        if "point" in support:
            assert np.any(np.all(mesh.nodes == np.array(support["point"]), axis=1))
        else:
            assert support["group"] in sidecar["surface_groups"]


# --- geometry ----------------------------------------------------------------------------


def test_cornea_geometry():
    mesh = built("cornea", "default")
    radius, centre = 7.8, np.array([0.0, 0.0, -7.8])
    assert np.any(np.all(mesh.nodes == 0.0, axis=1)), "no node exactly at the apex"
    anterior = group_nodes(mesh, "loadable")
    assert np.allclose(np.linalg.norm(anterior - centre, axis=1), radius, rtol=0, atol=1e-9)
    on_axis = mesh.nodes[np.hypot(mesh.nodes[:, 0], mesh.nodes[:, 1]) == 0.0]
    assert on_axis[:, 2].max() == 0.0
    assert on_axis[:, 2].min() == pytest.approx(-0.55, abs=1e-12)
    assert np.hypot(anterior[:, 0], anterior[:, 1]).max() == pytest.approx(5.75, abs=1e-9)
    clamped = group_nodes(mesh, "clamped")
    offset = clamped - centre
    polar = np.arctan2(np.hypot(offset[:, 0], offset[:, 1]), offset[:, 2])
    assert np.allclose(polar, math.asin(5.75 / 7.8), rtol=0, atol=1e-9)
    distance = np.linalg.norm(offset, axis=1)
    assert distance.min() == pytest.approx(radius - 0.7, abs=1e-9)
    assert distance.max() == pytest.approx(radius, abs=1e-9)
    assert np.all(mesh.nodes[:, 2] <= 1e-12)


def test_hemisphere_geometry():
    mesh = built("hemisphere", "default")
    centre = np.array([0.0, 0.0, -25.0])
    outer = np.linalg.norm(group_nodes(mesh, "loadable") - centre, axis=1)
    inner = np.linalg.norm(group_nodes(mesh, "free") - centre, axis=1)
    assert np.allclose(outer, 25.0, rtol=0, atol=1e-9)
    assert np.allclose(inner, 15.0, rtol=0, atol=1e-9)
    assert np.allclose(group_nodes(mesh, "clamped")[:, 2], -25.0, rtol=0, atol=1e-9)
    assert np.any(np.all(mesh.nodes == 0.0, axis=1))


def test_beam_geometry():
    mesh = built("beam", "default")
    assert np.array_equal(mesh.nodes.min(axis=0), [0.0, -20.0, -20.0])
    assert np.array_equal(mesh.nodes.max(axis=0), [400.0, 20.0, 20.0])
    assert np.all(group_nodes(mesh, "clamped")[:, 0] == 0.0)
    assert np.all(group_nodes(mesh, "loadable")[:, 0] == 400.0)
    assert mesh.default_contact_point == [400.0, 0.0, 0.0]
    assert corner_jacobians(mesh.nodes, mesh.cells).min() > 0
    # A uniform lateral contraction satisfies every support exactly.
    for support in mesh.supports[1:]:
        point = np.array(support["point"])
        contraction = {"x": 0.0, "y": -0.1 * point[1], "z": -0.1 * point[2]}
        assert all(contraction[c] == 0.0 for c in support["components"])


def test_liver_closed_surface_and_volume():
    mesh = built("liver", "default")
    triangles = np.vstack(list(mesh.facet_groups.values()))
    vertices = np.unique(triangles)
    edges = {
        tuple(sorted(e))
        for t in triangles.tolist()
        for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))
    }
    assert len(vertices) - len(edges) + len(triangles) == 2
    x = mesh.nodes[triangles]
    enclosed = np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6
    volume = tet_volumes(mesh.nodes, mesh.cells).sum()
    assert enclosed == pytest.approx(volume, rel=1e-10)
    assert 0.8e6 < volume < 1.4e6  # about a litre
    extent = mesh.nodes.max(axis=0) - mesh.nodes.min(axis=0)
    assert 180 < extent[0] < 260 and 90 < extent[1] < 160 and 70 < extent[2] < 120

    def area(faces):
        y = mesh.nodes[faces]
        return 0.5 * np.linalg.norm(np.cross(y[:, 1] - y[:, 0], y[:, 2] - y[:, 0]), axis=1).sum()

    clamped_fraction = area(mesh.facet_groups["clamped"]) / area(triangles)
    assert 0.15 <= clamped_fraction <= 0.25
    # The contact point faces the front, near the middle of the body's width.
    contact = np.array(mesh.default_contact_point)
    assert contact[1] < mesh.nodes[:, 1].mean()
    assert abs(contact[0] - mesh.nodes[:, 0].mean()) < 0.25 * extent[0]


# --- fibres ------------------------------------------------------------------------------


def test_cornea_fibres():
    mesh = built("cornea", "default")
    spec = mesh.sidecar()["fibres"]
    assert spec["rule"] == "spherical_cap" and spec["centre"] == [0.0, 0.0, -7.8]
    m0, n0 = fibre_directions(spec, mesh.nodes)
    assert np.allclose(np.linalg.norm(m0, axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.allclose(np.linalg.norm(n0, axis=1), 1.0, rtol=0, atol=1e-12)
    normal = mesh.nodes - np.array(spec["centre"])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    assert np.abs(np.einsum("ij,ij->i", m0, normal)).max() < 1e-12
    assert np.abs(np.einsum("ij,ij->i", n0, normal)).max() < 1e-12
    cosine = np.einsum("ij,ij->i", m0, n0)
    apex = np.all(mesh.nodes == 0.0, axis=1)
    assert np.abs(cosine[apex]).max() < 1e-15
    assert np.abs(cosine).max() < 0.5


def test_fibre_spec_errors():
    x = np.array([[0.0, 0.0, 0.0]])
    with pytest.raises(InputError):
        fibre_directions(None, x)
    with pytest.raises(InputError, match="rule"):
        fibre_directions({"rule": "helical"}, x)
    with pytest.raises(InputError):
        fibre_directions({"rule": "spherical_cap", "centre": [0, 0, -1]}, x)


# --- files -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_generate_is_reproducible(name, tmp_path):
    pytest.importorskip("gmsh")
    first = generate(name, tmp_path / "a" / f"{name}.msh", "coarse")
    second = generate(name, tmp_path / "b" / f"{name}.msh", "coarse")
    assert first == second
    assert (tmp_path / "a" / f"{name}.msh").read_bytes() == (
        tmp_path / "b" / f"{name}.msh"
    ).read_bytes()
    assert read_sidecar(tmp_path / "a" / f"{name}.msh") == first


def test_liver_default_reproducible():
    pytest.importorskip("gmsh")
    again = build("liver", "default")
    mesh = built("liver", "default")
    assert np.array_equal(again.nodes, mesh.nodes) and np.array_equal(again.cells, mesh.cells)


def test_params_override(tmp_path):
    pytest.importorskip("gmsh")
    sidecar = generate("cornea", tmp_path / "c.msh", "coarse", layers=4)
    n, m = sidecar["params"]["n"], sidecar["params"]["m"]
    assert sidecar["params"]["layers"] == 4
    assert sidecar["counts"]["nodes"] == 5 * ((n + 1) ** 2 + 4 * n * m)
    assert sidecar["counts"]["cells"] == 4 * (n * n + 4 * n * m)


def test_existing_gmsh_session_is_left_alone(tmp_path):
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("caller")
        binary_before = gmsh.option.getNumber("Mesh.Binary")
        generate("beam", tmp_path / "beam.msh", "coarse")
        generate("liver", tmp_path / "liver.msh", "coarse")
        assert gmsh.isInitialized()
        assert gmsh.model.getCurrent() == "caller"
        assert gmsh.option.getNumber("Mesh.Binary") == binary_before
    finally:
        gmsh.finalize()


def test_nothing_written_under_home(tmp_path, monkeypatch):
    pytest.importorskip("gmsh")
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    generate("beam", tmp_path / "out" / "beam.msh", "coarse")
    generate("liver", tmp_path / "out" / "liver.msh", "coarse")
    assert list(home.iterdir()) == []


@pytest.mark.parametrize("name", NAMES)
def test_dolfinx_reads_the_mesh(name, tmp_path):
    pytest.importorskip("gmsh")
    MPI = pytest.importorskip("mpi4py.MPI")
    dolfinx_gmsh = pytest.importorskip("dolfinx.io.gmsh")
    path = tmp_path / f"{name}.msh"
    generate(name, path, "coarse")
    mesh = built(name)
    boundary = sum(len(f) for f in mesh.facet_groups.values())
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        with gmsh_home_guard():  # read_from_msh starts gmsh, which writes $HOME/.fltk
            data = dolfinx_gmsh.read_from_msh(path, comm, 0, gdim=3)
        groups = data.physical_groups
        assert {"tissue", "clamped", "loadable", "free"} <= set(groups)
        assert groups["tissue"].dim == 3 and groups["clamped"].dim == 2
        assert data.mesh.topology.index_map(3).size_global == len(mesh.cells)
        assert data.mesh.geometry.index_map().size_global == len(mesh.nodes)
        tagged = comm.allreduce(len(data.facet_tags.values), op=MPI.SUM)
        assert tagged == boundary
        for group, faces in mesh.facet_groups.items():
            count = np.count_nonzero(data.facet_tags.values == groups[group].tag)
            assert comm.allreduce(count, op=MPI.SUM) == len(faces)


# --- bad input ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "refinement", "params", "message"),
    [
        ("kidney", "default", {}, "cornea"),
        ("cornea", "medium", {}, "coarse"),
        ("cornea", "default", {"central_thickness": -0.5}, "central_thickness"),
        ("cornea", "default", {"limbus_thickness": 7.8}, "limbus_thickness"),
        ("cornea", "default", {"limbus_diameter": 20.0}, "limbus_diameter"),
        ("cornea", "default", {"n": 7}, "even"),
        ("cornea", "default", {"layers": 0}, "layers"),
        ("cornea", "default", {"layers": 2.5}, "integer"),
        ("cornea", "default", {"thickness": 0.5}, "valid"),
        ("hemisphere", "default", {"thickness": 25.0}, "thickness"),
        ("hemisphere", "default", {"radius": -1.0}, "radius"),
        ("beam", "default", {"ny": 3}, "even"),
        ("beam", "default", {"length": 0.0}, "length"),
        ("liver", "default", {"mesh_size": 0.1}, "mesh_size"),
        ("liver", "default", {"clamped_depth_fraction": 1.5}, "clamped_depth_fraction"),
    ],
)
def test_bad_input_raises(name, refinement, params, message, tmp_path):
    with pytest.raises(InputError, match=message):
        generate(name, tmp_path / "x.msh", refinement, **params)
    assert not (tmp_path / "x.msh").exists()


def test_bad_paths_and_sidecars(tmp_path):
    with pytest.raises(InputError, match=".msh"):
        generate("beam", tmp_path / "beam.vtk", "coarse")
    with pytest.raises(InputError, match="not found"):
        read_sidecar(tmp_path / "missing.msh")
    (tmp_path / "other.json").write_text(json.dumps({"format": "something-else", "version": 1}))
    with pytest.raises(InputError, match="hapticrom-mesh"):
        read_sidecar(tmp_path / "other.msh")
    (tmp_path / "newer.json").write_text(json.dumps({"format": "hapticrom-mesh", "version": 2}))
    with pytest.raises(InputError, match="version"):
        read_sidecar(tmp_path / "newer.msh")


def test_registry_names():
    assert set(MESHES) == {"cornea", "beam", "hemisphere", "liver"}
