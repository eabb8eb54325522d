"""Tests of meshes.msh.read_surface and the tool-position planning of offline.positions."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hapticrom.meshes import build, generate
from hapticrom.meshes.msh import face_area_vectors, gmsh_home_guard, read_surface, write_msh
from hapticrom.offline.campaign.positions import (
    FarthestSampler,
    PolarSampler,
    PositionsSpec,
    plan_positions,
    positions_from_dict,
    positions_table,
)
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

CORNEA_CENTRE = np.array([0.0, 0.0, -7.8])  # centre of curvature of the anterior surface, mm
CORNEA_RADIUS = 7.8
EXAMPLE = """
[positions]
points = [[0.0, 0.0, 0.0]]
snap_tolerance = 1.0
[[positions.polar]]
centre = [0.0, 0.0, 0.0]
radius = 3.0
rings = 3
per_ring = [6, 12, 18]
[[positions.farthest]]
n = 10
centre = [0.0, 0.0, 0.0]
radius = 3.0
"""
POLAR_37 = PolarSampler(centre=(0.0, 0.0, 0.0), radius=3.0, rings=3, per_ring=[6, 12, 18])


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """(name, refinement) -> (.msh path, sidecar), generated once for this module."""
    d = tmp_path_factory.mktemp("positions-meshes")
    wanted = [("cornea", "coarse"), ("cornea", "default"), ("beam", "coarse")]
    wanted += [("beam", "default"), ("liver", "coarse")]
    out = {}
    for name, refinement in wanted:
        path = d / f"{name}-{refinement}.msh"
        out[name, refinement] = (path, generate(name, path, refinement))
    return out


@pytest.fixture(scope="module")
def cornea(meshes):
    """The anterior (loadable) surface of the default cornea."""
    return read_surface(meshes["cornea", "default"][0])


def pairwise_min(points: np.ndarray) -> float:
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    d[np.diag_indices(len(points))] = np.inf
    return float(d.min())


def node_spacing(surface, centre, radius) -> float:
    """The longest face edge among the faces whose centroid lies within ``radius`` of ``centre``."""
    corners = surface.nodes[surface.faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    near = np.linalg.norm(corners.mean(axis=1) - centre, axis=1) <= radius
    return float(edges[near].max())


# --- read_surface -----------------------------------------------------------------------------


@pytest.mark.parametrize("refinement", ["coarse", "default"])
def test_cornea_anterior_surface(meshes, refinement):
    path, sidecar = meshes["cornea", refinement]
    s = read_surface(path)
    assert s.group == "loadable"
    # The anterior surface is one of layers + 1 identical node sheets.
    assert len(s.nodes) == sidecar["counts"]["nodes"] // (sidecar["params"]["layers"] + 1)
    assert s.nodes.dtype == np.float64 and s.node_tags.dtype == np.int64
    assert s.faces.dtype == np.int64 and s.faces.shape[1] == 4
    assert np.all(np.diff(s.node_tags) > 0) and s.node_tags[0] >= 1
    assert set(np.unique(s.faces)) == set(range(len(s.nodes)))
    radial = s.nodes - CORNEA_CENTRE
    distance = np.linalg.norm(radial, axis=1)
    np.testing.assert_allclose(distance, CORNEA_RADIUS, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-12)
    error = np.linalg.norm(s.normals - radial / distance[:, None], axis=1)
    # At the limbus rim the average is one-sided: off by about half a cell's angle.
    rim = np.hypot(s.nodes[:, 0], s.nodes[:, 1]) > 5.75 - 1e-9
    assert rim.sum() > 0
    if refinement == "default":
        assert error[~rim].max() < 1e-2
        assert error[rim].max() < 2e-2
    else:
        assert error[~rim].max() < 2e-2
        assert error[rim].max() < 0.1


def test_beam_end_face_normals_exact(meshes):
    s = read_surface(meshes["beam", "coarse"][0], "loadable")
    assert len(s.nodes) == 9  # 2 x 2 quadrangles
    assert np.all(s.nodes[:, 0] == 400.0)
    assert np.array_equal(s.normals, np.tile([1.0, 0.0, 0.0], (len(s.nodes), 1)))
    clamped = read_surface(meshes["beam", "coarse"][0], "clamped")
    assert np.array_equal(clamped.normals, np.tile([-1.0, 0.0, 0.0], (len(clamped.nodes), 1)))


def test_liver_groups_are_outward(meshes):
    path = meshes["liver", "coarse"][0]
    s = read_surface(path)
    assert s.faces.shape[1] == 3
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-12)
    # Every loadable face has n.(-y) > 0.2, so any weighted mean of them does too.
    assert np.all(s.normals @ [0.0, -1.0, 0.0] > 0.2)
    # The three groups close the organ: outward faces give a positive enclosed volume
    # (divergence theorem), about the 1.03 litres of the generator.
    volume = 0.0
    for group in ("clamped", "loadable", "free"):
        g = read_surface(path, group)
        centres = g.nodes[g.faces].mean(axis=1)
        volume += np.einsum("ij,ij->", face_area_vectors(g.nodes, g.faces), centres) / 3.0
    assert volume == pytest.approx(1.03e6, rel=0.05)


def test_read_surface_errors(meshes, tmp_path):
    path = meshes["beam", "coarse"][0]
    with pytest.raises(InputError, match="not found"):
        read_surface(tmp_path / "absent.msh")
    with pytest.raises(InputError, match="'nope'"):
        read_surface(path, "nope")
    with pytest.raises(InputError, match="'tissue'.*not 2-dimensional"):
        read_surface(path, "tissue")
    junk = tmp_path / "junk.msh"
    junk.write_text("not a mesh\n")
    with pytest.raises(InputError, match="junk.msh"):
        read_surface(junk)


def test_read_surface_rejects_inward_faces(tmp_path):
    mesh = build("beam", "coarse")
    groups = dict(mesh.facet_groups)
    groups["loadable"] = groups["loadable"][:, ::-1]  # reversed winding: inward normals
    path = write_msh(tmp_path / "flipped.msh", mesh.nodes, mesh.cells, groups, mesh.sidecar())
    with pytest.raises(InputError, match="point inwards"):
        read_surface(path)
    read_surface(path, "clamped")  # the untouched groups still read


def test_read_surface_leaves_gmsh_session_alone(meshes):
    gmsh = pytest.importorskip("gmsh")
    with gmsh_home_guard():
        gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("caller")
        models = gmsh.model.list()
        read_surface(meshes["beam", "coarse"][0])
        assert gmsh.isInitialized()
        assert gmsh.model.getCurrent() == "caller"
        assert gmsh.model.list() == models
    finally:
        gmsh.finalize()


# --- planning ---------------------------------------------------------------------------------


def test_polar_grid_on_cornea(cornea):
    positions = plan_positions(cornea, PositionsSpec(samplers=[POLAR_37]))
    assert len(positions) == 1 + 6 + 12 + 18
    assert [p.index for p in positions] == list(range(37))
    assert len({p.node_tag for p in positions}) == 37
    assert {p.source for p in positions} == {"polar"}
    apex = positions[0]
    assert apex.point == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(apex.normal, (0.0, 0.0, 1.0), atol=1e-12)
    points = np.array([p.point for p in positions])
    distance = np.linalg.norm(points, axis=1)
    h = node_spacing(cornea, np.zeros(3), 4.0)
    assert distance.max() <= 3.0 + h
    # Each ring near its radius: snapped to nodes, and a little inside it on the sphere.
    for ring, (start, stop) in enumerate([(1, 7), (7, 19), (19, 37)], start=1):
        assert np.all(np.abs(distance[start:stop] - ring) <= h + 0.1 * ring)
    # Symmetric about the apex's normal axis: the ring points' centroid is on it.
    centroid = points[1:].mean(axis=0)
    assert np.hypot(centroid[0], centroid[1]) < 0.1 * h
    # The first ring point lies along +x (the first tangent), the second at +60 degrees.
    assert points[1][0] > 0.9 and abs(points[1][1]) < h
    assert points[2][1] > 0.5


def test_polar_tangent_frame_on_beam_end(meshes):
    # The end face's normal is +x, so the first tangent falls back to y; t2 = x cross y = z.
    s = read_surface(meshes["beam", "default"][0])
    sampler = PolarSampler(centre=(400.0, 0.0, 0.0), radius=20.0, rings=2, per_ring=4)
    points = [p.point for p in plan_positions(s, PositionsSpec(samplers=[sampler]))]
    assert points[:5] == [
        (400.0, 0.0, 0.0),
        (400.0, 10.0, 0.0),
        (400.0, 0.0, 10.0),
        (400.0, -10.0, 0.0),
        (400.0, 0.0, -10.0),
    ]
    assert len(points) == 9


def test_farthest_sampling_spreads(cornea):
    n, radius = 10, 3.0
    sampler = FarthestSampler(n=n, centre=(0.0, 0.0, 0.0), radius=radius)
    positions = plan_positions(cornea, PositionsSpec(samplers=[sampler]))
    assert len(positions) == n and {p.source for p in positions} == {"farthest"}
    assert positions[0].point == (0.0, 0.0, 0.0)  # starts at the node nearest the centre
    chosen = np.array([p.point for p in positions])
    assert np.linalg.norm(chosen, axis=1).max() <= radius
    candidates = cornea.nodes[np.linalg.norm(cornea.nodes, axis=1) <= radius]
    rng = np.random.default_rng(12345)
    random_mins = [
        pairwise_min(candidates[rng.choice(len(candidates), n, replace=False)]) for _ in range(200)
    ]
    assert pairwise_min(chosen) > max(random_mins)


def test_farthest_without_centre_uses_all_nodes(cornea):
    positions = plan_positions(cornea, PositionsSpec(samplers=[FarthestSampler(n=5)]))
    assert len(positions) == 5
    # The cornea's area-weighted centroid is on the axis, nearest the apex node.
    assert positions[0].point == (0.0, 0.0, 0.0)
    rim = np.array([p.point for p in positions[1:]])
    np.testing.assert_allclose(np.hypot(rim[:, 0], rim[:, 1]), 5.75, atol=1e-9)


def test_farthest_with_more_requested_than_candidates(cornea):
    sampler = FarthestSampler(n=1000, centre=(0.0, 0.0, 0.0), radius=0.3)
    positions = plan_positions(cornea, PositionsSpec(samplers=[sampler]))
    inside = np.count_nonzero(np.linalg.norm(cornea.nodes, axis=1) <= 0.3)
    assert 1 < len(positions) == inside


def test_explicit_points_snap_and_fail_off_surface(cornea):
    positions = plan_positions(cornea, PositionsSpec(points=[(0.02, -0.01, 0.4)]))
    assert len(positions) == 1
    assert positions[0].point == (0.0, 0.0, 0.0) and positions[0].source == "point"
    with pytest.raises(InputError, match=r"points\[1\].*snap_tolerance"):
        plan_positions(cornea, PositionsSpec(points=[(0.0, 0.0, 0.0), (0.0, 0.0, 2.0)]))
    with pytest.raises(InputError, match=r"points\[0\]"):
        plan_positions(cornea, PositionsSpec(points=[(0.0, 0.0, 0.4)], snap_tolerance=0.1))
    with pytest.raises(InputError, match="polar centre"):
        off = PolarSampler(centre=(0.0, 0.0, 3.0), radius=1.0, rings=1, per_ring=4)
        plan_positions(cornea, PositionsSpec(samplers=[off]))
    with pytest.raises(InputError, match="no node"):
        far = FarthestSampler(n=3, centre=(0.0, 0.0, 50.0), radius=1.0)
        plan_positions(cornea, PositionsSpec(samplers=[far]))


def test_duplicates_keep_the_first(cornea):
    spec = PositionsSpec(
        points=[(0.0, 0.0, 0.0), (0.0, 0.0, 0.01)],
        samplers=[POLAR_37, POLAR_37, FarthestSampler(n=1, centre=(0.0, 0.0, 0.0))],
    )
    positions = plan_positions(cornea, spec)
    assert len(positions) == 37
    assert positions[0].source == "point" and positions[0].point == (0.0, 0.0, 0.0)
    assert {p.source for p in positions[1:]} == {"polar"}
    assert [p.index for p in positions] == list(range(37))


def test_example_table_and_determinism(meshes, cornea):
    spec = positions_from_dict(tomllib.loads(EXAMPLE)["positions"])
    assert spec.points == ((0.0, 0.0, 0.0),) and spec.snap_tolerance == 1.0
    assert spec.samplers[0] == POLAR_37
    assert spec.samplers[1] == FarthestSampler(n=10, centre=(0.0, 0.0, 0.0), radius=3.0)
    first = plan_positions(cornea, spec)
    again = plan_positions(read_surface(meshes["cornea", "default"][0]), spec)
    assert first == again
    assert positions_table(first) == positions_table(again)
    # The explicit apex, 36 ring points, then the farthest sampler's 9 new nodes.
    assert [p.source for p in first].count("polar") == 36
    assert len(first) == 1 + 36 + 9


def test_sampler_order_follows_the_table():
    polar = {"centre": [0, 0, 0], "radius": 1, "rings": 1, "per_ring": 3}
    spec = positions_from_dict({"farthest": [{"n": 2}], "polar": [polar]})
    assert spec.samplers == (FarthestSampler(n=2), PolarSampler((0.0, 0.0, 0.0), 1.0, 1, 3))
    # A single table is accepted as well as an array of tables.
    assert positions_from_dict({"polar": polar}).samplers == spec.samplers[1:]


def test_positions_table(cornea):
    positions = plan_positions(cornea, PositionsSpec(samplers=[POLAR_37]))
    text = positions_table(positions)
    lines = text.splitlines()
    assert lines[0].split() == ["index", "source", "x", "y", "z", "from", "#0"]
    assert len(lines) == 1 + 37 + 1 and "37 positions" in lines[-1]
    last = lines[-2].split()
    assert last[0] == "36" and last[1] == "polar"
    expected = np.linalg.norm(np.array(positions[-1].point) - positions[0].point)
    assert float(last[5]) == pytest.approx(expected, abs=1e-3)


POLAR = {"centre": [0.0, 0.0, 0.0], "radius": 3.0, "rings": 3, "per_ring": [6, 12, 18]}


@pytest.mark.parametrize(
    ("table", "words"),
    [
        ({}, ["no positions"]),
        ({"points": []}, ["no positions"]),
        ({"points": [[0.0, 0.0, 0.0]], "radius": 2.0}, ["[positions]", "unknown", "radius"]),
        ({"points": [[0.0, 0.0]]}, ["points[0]", "three finite numbers"]),
        ({"points": [[0.0, "a", 0.0]]}, ["points[0]", "number"]),
        ({"points": "origin"}, ["points", "list"]),
        ({"points": [[0, 0, 0]], "snap_tolerance": -1.0}, ["snap_tolerance", "positive"]),
        ({"points": [[0, 0, 0]], "snap_tolerance": "1"}, ["snap_tolerance", "number"]),
        ({"polar": [{**POLAR, "radus": 3.0}]}, ["positions.polar", "#1", "unknown", "radus"]),
        ({"polar": [{**POLAR, "radius": "3"}]}, ["positions.polar", "radius", "number"]),
        ({"polar": [{**POLAR, "radius": 0.0}]}, ["radius", "positive"]),
        ({"polar": [POLAR, {**POLAR, "rings": -1}]}, ["#2", "rings", "positive"]),
        ({"polar": [{**POLAR, "rings": 2.0}]}, ["rings", "integer"]),
        ({"polar": [{**POLAR, "rings": True}]}, ["rings", "integer"]),
        ({"polar": [{**POLAR, "per_ring": [6, 12]}]}, ["per_ring", "2 entries", "rings = 3"]),
        ({"polar": [{**POLAR, "per_ring": [6, 0, 18]}]}, ["per_ring", "positive"]),
        ({"polar": [{**POLAR, "include_centre": 1}]}, ["include_centre", "true or false"]),
        ({"polar": [{"radius": 3.0, "rings": 3, "per_ring": 6}]}, ["missing", "centre"]),
        ({"polar": 3}, ["polar", "tables"]),
        ({"polar": [3]}, ["positions.polar", "must be a table"]),
        ({"farthest": [{"n": 0}]}, ["positions.farthest", "n", "positive"]),
        ({"farthest": [{"n": 4, "radius": 2.0}]}, ["radius", "centre"]),
        ({"farthest": [{"n": 4, "centre": [0, 0, 0], "radius": -2.0}]}, ["radius", "positive"]),
        ({"farthest": [{"centre": [0, 0, 0]}]}, ["missing", "n"]),
        ({"farthest": [{"n": 4, "centre": [0, 0]}]}, ["centre", "three finite numbers"]),
    ],
)
def test_bad_tables(table, words):
    with pytest.raises(InputError) as error:
        positions_from_dict(table)
    message = str(error.value)
    assert "\n" not in message
    for word in words:
        assert word in message, (word, message)


def test_bad_table_names_where():
    with pytest.raises(InputError, match=r"\[campaign.positions\]"):
        positions_from_dict({"point": [[0, 0, 0]]}, where="campaign.positions")
    with pytest.raises(InputError, match="must be a table"):
        positions_from_dict([1, 2, 3])
