"""``hapticrom.export``: ParaView files of a reduced model, read back with a plain XML parser.

The files are decoded here independently of :mod:`hapticrom.vtk` (base64 of a UInt64
byte count and the little-endian values) and compared with the artifact and the runtime.
A coarse cornea with a cuttable region (SVK, no POD-ANM) is trained once (~15 s).
"""

from __future__ import annotations

import base64
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from hapticrom.export import export_model, make_cut
from hapticrom.online.play import tool_path
from hapticrom.shared.errors import ArtifactError, InputError

pytestmark = pytest.mark.serial
R = 7.8  # mm, anterior radius of the cornea
FRAMES = 6
TYPES = {"Float32": "<f4", "Float64": "<f8", "Int8": "i1", "UInt8": "u1", "Int32": "<i4",
         "Int64": "<i8", "UInt32": "<u4", "UInt64": "<u8"}  # fmt: skip


def decode(element) -> np.ndarray:
    """A binary inline DataArray: base64 of (UInt64 byte count, values)."""
    raw = base64.b64decode(element.text)
    size = int.from_bytes(raw[:8], "little")
    assert len(raw) == 8 + size
    if element.get("type") == "String":
        return np.array(raw[8:].split(b"\0")[:-1])
    values = np.frombuffer(raw[8:], dtype=TYPES[element.get("type")])
    components = int(element.get("NumberOfComponents", "1"))
    return values.reshape(-1, components) if components > 1 else values


def read(path) -> tuple[ET.Element, dict[str, dict[str, np.ndarray]]]:
    """(root, arrays by section: Points, PointData, CellData, FieldData, Verts, Polys)."""
    root = ET.parse(path).getroot()
    assert root.get("type") == "PolyData" and root.get("header_type") == "UInt64"
    sections = {}
    for tag in ("FieldData", "PointData", "CellData", "Points", "Verts", "Polys"):
        section = root.find(f".//{tag}")
        if section is not None:
            sections[tag] = {a.get("Name"): decode(a) for a in section}
    return root, sections


def note(sections) -> str:
    return sections["FieldData"]["note"][0].decode()


def cells(sections, tag: str) -> np.ndarray:
    c = sections[tag]
    offsets = c["offsets"]
    k = int(offsets[0])
    np.testing.assert_array_equal(offsets, k * np.arange(1, len(offsets) + 1))
    return c["connectivity"].reshape(-1, k)


def on_surface(rho, degrees=0.0):
    a = np.radians(degrees)
    return np.array([rho * np.cos(a), rho * np.sin(a), -R + np.sqrt(R * R - rho * rho)])


@pytest.fixture(scope="module")
def artifact(mesh_dir, tmp_path_factory):
    """A reduced model of the coarse cornea with a cuttable region (as tests/test_scalpel)."""
    from conftest import campaign_toml
    from mpi4py import MPI

    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.reduce.reduction import reduce_campaign

    root = tmp_path_factory.mktemp("export-model")
    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=2, per_ring=3)
    text = text.replace('law = "hgo"', 'law = "svk"\nE = 0.5\nnu = 0.45')
    text += f"\n[anm]\nenabled = false\n[cutting]\ncentre = {on_surface(4.6).tolist()}\n"
    text += "radius = 2.5\ncut_force = 1e-4\npatch_layers = 1\n"
    (root / "c.toml").write_text(text)
    config = CampaignConfig.from_toml(root / "c.toml")
    run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
    reduce_campaign(root / "store", root / "m.h5", MPI.COMM_SELF, verbose=False)
    return root / "m.h5"


@pytest.fixture(scope="module")
def model(artifact):
    import hapticrom.online as online

    return online.load(artifact)


@pytest.fixture(scope="module")
def exported(artifact, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "nested" / "dir"  # created, parents too
    return out, export_model(artifact, out, frames=FRAMES)


def test_every_file_is_written_and_parses(model, exported):
    out, paths = exported
    names = sorted(p.relative_to(out).as_posix() for p in paths)
    frames = [f"sequence/frame_{i:04d}.vtp" for i in range(FRAMES)]
    expected = ["cut.vtp", "cut_lips.vtp", "modes.vtp", "samples.vtp", "sequence.pvd"]
    assert names == sorted(expected + ["surface.vtp"] + frames)
    V, T = len(model.vertices), len(model.triangles)
    for path in paths:
        if path.suffix == ".vtp":
            root, sections = read(path)
            piece = root.find(".//Piece")
            assert len(sections["Points"]["Points"]) == int(piece.get("NumberOfPoints"))
            assert "units" in sections["FieldData"] and note(sections)
    piece = ET.parse(out / "surface.vtp").getroot().find(".//Piece")
    assert (piece.get("NumberOfPoints"), piece.get("NumberOfPolys")) == (str(V), str(T))


def test_surface_and_samples_are_the_artifacts(model, exported):
    out, _ = exported
    _, s = read(out / "surface.vtp")
    np.testing.assert_array_equal(s["Points"]["Points"], model.vertices)
    np.testing.assert_array_equal(cells(s, "Polys"), model.triangles)
    surface = model.artifact["surface"]
    np.testing.assert_array_equal(s["PointData"]["node"], surface["nodes"])
    np.testing.assert_array_equal(s["CellData"]["group"], surface["groups"])
    _, s = read(out / "samples.vtp")
    P = len(model.sample_points)
    np.testing.assert_array_equal(s["Points"]["Points"], model.sample_points)
    np.testing.assert_array_equal(cells(s, "Verts").reshape(-1), np.arange(P))
    np.testing.assert_array_equal(cells(s, "Polys"), model.sample_triangles)
    np.testing.assert_array_equal(s["PointData"]["normal"], model.sample_normals)
    np.testing.assert_array_equal(s["PointData"]["force_N"], model.force)
    np.testing.assert_array_equal(s["PointData"]["trained_force_N"], model.sample_trained_force)
    np.testing.assert_array_equal(s["PointData"]["solved_depth_mm"], model.solved_depth)
    np.testing.assert_array_equal(s["FieldData"]["depth_mm"], model.artifact["samples"]["depth"])


def test_modes_are_the_global_basis_rows(model, exported):
    out, _ = exported
    root, s = read(out / "modes.vtp")
    basis = np.asarray(model.artifact["global"]["surface_basis"])
    V, G = len(model.vertices), basis.shape[1]
    names = [f"mode_{m:02d}" for m in range(G)]
    assert list(s["PointData"]) == names
    assert root.find(".//PointData").get("Vectors") == "mode_00"  # Warp By Vector at once
    for m, name in enumerate(names):
        mode = s["PointData"][name]
        assert mode.dtype == np.float32 and mode.shape == (V, 3)
        np.testing.assert_array_equal(mode.reshape(-1), basis[:, m])  # bit for bit
    assert "/global/surface_basis" in note(s) and f"all {G} modes" in note(s)
    np.testing.assert_array_equal(
        s["FieldData"]["eigenvalues_mm2"], model.artifact["global"]["eigenvalues"]
    )


def test_the_sequence_is_the_runtime_played_step_by_step(model, exported):
    out, _ = exported
    collection = ET.parse(out / "sequence.pvd").getroot()
    datasets = collection.findall("./Collection/DataSet")
    assert [d.get("file") for d in datasets] == [
        f"sequence/frame_{i:04d}.vtp" for i in range(FRAMES)
    ]
    times = [float(d.get("timestep")) for d in datasets]
    assert times[0] == 0.0 and times[-1] == pytest.approx(3.0) and np.all(np.diff(times) > 0)
    # The same steps through a fresh simulator, as hapticrom play takes them.
    sim = model.simulator()
    points, depths = tool_path(model, FRAMES)
    expected = np.zeros_like(model.vertices)
    moved = 0.0
    for i, dataset in enumerate(datasets):
        sim.set_contact(points[i])
        force = sim.step_displacement(-depths[i] * sim.contact_normal).copy()
        sim.surface_displacement(expected)
        root, s = read(out / dataset.get("file"))
        assert root.find(".//PointData").get("Vectors") == "displacement_mm"
        np.testing.assert_array_equal(s["PointData"]["displacement_mm"], expected)
        np.testing.assert_array_equal(s["FieldData"]["force_on_tool_N"].reshape(-1), force)
        np.testing.assert_array_equal(s["FieldData"]["tool_point_mm"].reshape(-1), points[i])
        assert s["FieldData"]["time_s"][0] == times[i]
        moved = max(moved, np.abs(expected).max())
    assert moved > 0  # the press shows


def test_the_cut_surface_opens_two_lips(model, exported):
    out, _ = exported
    _, s = read(out / "cut.vtp")
    V = len(model.vertices)
    sim = make_cut(model)[0]  # the same scalpel strokes again: the runtime's answer
    expected = sim.surface_displacement(np.zeros_like(model.vertices))
    vertices, triangles = sim.cut_surface()
    copied, positions, lip_displacement = sim.lip_vertices
    assert len(copied) > 0 and "face(s) cut" in note(s)
    np.testing.assert_array_equal(s["Points"]["Points"], vertices)
    np.testing.assert_array_equal(s["Points"]["Points"][V:], model.vertices[copied])
    np.testing.assert_array_equal(cells(s, "Polys"), triangles)
    displacement = s["PointData"]["displacement_mm"]
    np.testing.assert_array_equal(displacement, np.vstack([expected, lip_displacement]))
    lip = s["PointData"]["lip"]
    assert (lip[copied] == 1).all() and (lip[V:] == 2).all() and (lip == 0).sum() == V - len(copied)
    _, lips = read(out / "cut_lips.vtp")
    side = lips["PointData"]["side"]
    opened = lips["PointData"]["displacement_mm"]
    np.testing.assert_array_equal(opened[side == 1], displacement[copied])
    np.testing.assert_array_equal(opened[side == 2], displacement[V:])
    np.testing.assert_array_equal(lips["Points"]["Points"], np.vstack([positions, positions]))
    assert np.abs(opened[side == 1] - opened[side == 2]).max() > 0  # the lips part


@pytest.mark.parametrize("frames", [0, -1, 10_001, 2.5, True, "3", None])
def test_bad_frames_are_refused_before_the_model_is_read(tmp_path, frames):
    with pytest.raises(InputError, match="frames must"):
        export_model(tmp_path / "missing.h5", tmp_path / "out", frames=frames)
    assert not (tmp_path / "out").exists()


def test_bad_out_is_refused_before_the_model_is_read(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory\n")
    with pytest.raises(InputError, match="exists and is not a directory"):
        export_model(tmp_path / "missing.h5", blocker)
    with pytest.raises(InputError, match="is not a directory"):
        export_model(tmp_path / "missing.h5", blocker / "below")
    with pytest.raises(InputError, match="cut must be"):
        export_model(tmp_path / "missing.h5", tmp_path / "out", cut="yes")
    assert blocker.read_text() == "not a directory\n"
    with pytest.raises(ArtifactError):  # a good out, a bad model: the loader's error
        export_model(tmp_path / "missing.h5", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_one_frame_and_no_cut(artifact, tmp_path):
    paths = export_model(artifact, tmp_path / "e", frames=1, cut=False)
    assert not (tmp_path / "e" / "cut.vtp").exists()
    assert sorted(p.name for p in paths) == sorted(
        ["surface.vtp", "samples.vtp", "modes.vtp", "frame_0000.vtp", "sequence.pvd"]
    )
    datasets = ET.parse(tmp_path / "e" / "sequence.pvd").getroot().findall(".//DataSet")
    assert [d.get("timestep") for d in datasets] == ["0.0"]


def test_without_a_global_basis_the_central_samples_modes(model, tmp_path):
    from dataclasses import replace

    from hapticrom.export import write_modes

    groups = {k: v for k, v in model.artifact.groups.items() if k != "global"}
    bare = replace(model, artifact=replace(model.artifact, groups=groups))
    _, s = read(write_modes(bare, tmp_path / "modes.vtp"))
    chart = model.plan_points
    central = int(np.argmin(np.linalg.norm(chart - chart.mean(axis=0), axis=1)))
    assert f"/samples/surface_basis[{central}]" in note(s)
    assert len(s["PointData"]) == model.num_modes
    for m in range(model.num_modes):
        mode = s["PointData"][f"mode_{m:02d}"].reshape(-1)
        np.testing.assert_array_equal(mode, model.surface_basis[central][:, m])
