"""Explicitly meshed cuts (the full-order reference of surgical cutting): topology and opening."""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.meshes import build
from hapticrom.meshes.cut import LimbalArc, cut_mesh, interior_faces, limbal_arc
from hapticrom.meshes.msh import boundary_faces, write_msh
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
ARC = LimbalArc(radius=5.2, start=-30.0, end=30.0, depth=0.7)


def _hex_volumes(nodes, cells):
    """Signed volumes of trilinear hexahedra by the 5-tetrahedron split (positive: valid)."""
    x = nodes[cells]
    tets = [(0, 1, 3, 4), (1, 2, 3, 6), (1, 4, 5, 6), (3, 4, 6, 7), (1, 3, 4, 6)]
    vol = 0.0
    for a, b, c, d in tets:
        vol = (
            vol
            + np.einsum(
                "ij,ij->i", x[:, b] - x[:, a], np.cross(x[:, c] - x[:, a], x[:, d] - x[:, a])
            )
            / 6.0
        )
    return vol


def test_limbal_cut_duplicates_the_inner_nodes_only():
    mesh = build("cornea", "default")
    faces, pairs = interior_faces(mesh.cells)
    selected = limbal_arc(mesh, ARC)
    cut, origin = cut_mesh(mesh, selected)
    cut_faces = faces[selected]
    # One ring of 26 columns x 2 of the 3 layers, just inside the limbus, within the arc.
    assert len(selected) == 52
    centroid = mesh.nodes[cut_faces].mean(axis=1)
    assert np.all(np.abs(np.hypot(centroid[:, 0], centroid[:, 1]) - ARC.radius) < 0.1)
    added = len(cut.nodes) - len(mesh.nodes)
    copies = slice(len(mesh.nodes), None)
    np.testing.assert_array_equal(cut.nodes[copies], mesh.nodes[origin[copies]])
    # Duplicated: the cut's nodes not on its front. Front nodes are those of cut faces that
    # also lie on an uncut face shared by cells of both sides; count them independently:
    # nodes of the cut surface minus the nodes on its boundary edges inside the tissue.
    edge_count: dict[tuple, int] = {}
    for f in cut_faces:
        for k in range(4):
            e = tuple(sorted((f[k], f[(k + 1) % 4])))
            edge_count[e] = edge_count.get(e, 0) + 1
    boundary_edges = [e for e, c in edge_count.items() if c == 1]
    surface_nodes = {n for f in mesh.facet_groups["loadable"] for n in f}
    front = {n for e in boundary_edges for n in e if not (set(e) <= surface_nodes)}
    assert added == len(set(cut_faces.ravel()) - front)
    # Two lips per cut face join the free surface; the other groups are unchanged in size.
    assert len(cut.facet_groups["free"]) == len(mesh.facet_groups["free"]) + 2 * len(selected)
    for g in ("clamped", "loadable"):
        assert len(cut.facet_groups[g]) == len(mesh.facet_groups[g])
    assert len(boundary_faces(cut.cells)) == len(boundary_faces(mesh.cells)) + 2 * len(selected)
    assert np.all(_hex_volumes(cut.nodes, cut.cells) > 0)
    # Every cell still uses nodes at the same places.
    np.testing.assert_array_equal(cut.nodes[cut.cells], mesh.nodes[mesh.cells])


def test_bad_incisions_are_refused():
    mesh = build("cornea", "coarse")
    with pytest.raises(InputError, match="depth"):
        LimbalArc(radius=5.0, start=0, end=30, depth=1.5)
    with pytest.raises(InputError, match="angles"):
        LimbalArc(radius=5.0, start=30, end=0)
    with pytest.raises(InputError, match="no faces"):
        limbal_arc(mesh, LimbalArc(radius=20.0, start=0, end=30))
    with pytest.raises(InputError, match="nothing to cut"):
        cut_mesh(mesh, np.array([], dtype=int))
    with pytest.raises(InputError, match="cornea"):
        limbal_arc(build("beam", "coarse"), ARC)


def test_the_cut_opens_under_a_tool_next_to_it(tmp_path):
    """Full-order solves with and without the cut: the lips separate, the front holds."""
    from scipy.spatial import cKDTree

    import hapticrom.offline  # noqa: F401 - h5py and MPI first
    from hapticrom.offline.config import ProblemConfig
    from hapticrom.offline.fe.fullorder import FullOrderModel

    mesh = build("cornea", "coarse")
    cut, origin = cut_mesh(mesh, limbal_arc(mesh, ARC))
    paths = {}
    for name, m in (("intact", mesh), ("cut", cut)):
        paths[name] = write_msh(tmp_path / f"{name}.msh", m.nodes, m.cells, m.facet_groups,
                                m.sidecar())  # fmt: skip
    R, rho = 7.8, 4.6
    point = [rho, 0.0, -R + np.sqrt(R * R - rho * rho)]
    results = {}
    for name, path in paths.items():
        config = ProblemConfig.from_dict({
            "mesh": {"file": str(path)},
            "material": {"law": "svk", "E": 0.5, "nu": 0.45},
            "load": {"mode": "displacement", "contact_point": point, "contact_radius": 0.8,
                     "displacement": [0.0, 0.0, -0.05], "steps": 1},
        })  # fmt: skip
        fom = FullOrderModel(config, verbose=False)
        result = fom.solve()
        x = fom.model.V.tabulate_dof_coordinates()
        results[name] = (x, fom.model.u.x.array.reshape(-1, 3).copy(), result.force[-1])
    x, u, force_cut = results["cut"]
    pairs = cKDTree(x).query_pairs(1e-9, output_type="ndarray")
    assert len(pairs) == len(cut.nodes) - len(mesh.nodes)  # only duplicates coincide
    jump = np.linalg.norm(u[pairs[:, 0]] - u[pairs[:, 1]], axis=1)
    assert jump.max() > 1e-3 * np.abs(u).max()  # the lips move apart
    # The cut tissue is softer: the same indentation needs less force.
    force_intact = results["intact"][2]
    assert abs(force_cut[2]) < abs(force_intact[2])


def test_cli_meshes_an_incision(tmp_path, capsys):
    import json

    from hapticrom.cli import main

    out = tmp_path / "cornea-lri.msh"
    assert main(["mesh", "cornea", "--refinement", "coarse", "--out", str(out),
                 "--limbal-incision", "5.2", "-30", "30", "0.7"]) == 0  # fmt: skip
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["params"]["limbal_incision"] == {
        "radius": 5.2, "start": -30.0, "end": 30.0, "depth": 0.7
    }  # fmt: skip
    assert sidecar["counts"]["nodes"] > build("cornea", "coarse").nodes.shape[0]
    assert main(["mesh", "cornea", "--refinement", "coarse", "--out", str(out),
                 "--limbal-incision", "5.2", "30", "0", "0.7"]) == 2  # fmt: skip
    assert "incision angles" in capsys.readouterr().err
