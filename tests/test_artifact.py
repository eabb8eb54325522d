"""The artifact: what the trainer writes is what the runtime reads; damage is named."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from tamper import copy, mutate, set_attribute

from hapticrom.shared.artifact import FORMAT_VERSION, SCHEMA, ArtifactError, read_artifact
from hapticrom.shared.checksum import array_digest
from hapticrom.shared.envelope import seal

pytestmark = pytest.mark.serial


@pytest.mark.parametrize("artifact", ["small_artifact", "force_artifact"])
def test_artifact_has_every_schema_field(artifact, request):
    """Every required field; the optional tool_stiffness where the campaign is force-
    controlled (force_artifact) and not where it is not (small_artifact)."""
    path = request.getfixturevalue(artifact)
    a = read_artifact(path)
    assert a.attrs["format"] == "hapticrom" and a.version == FORMAT_VERSION
    for group in SCHEMA:
        if group.required:
            assert group.name in a.groups
        for spec in group.fields if group.name in a.groups else ():
            assert spec.name in a[group.name] or not spec.required
    assert ("tool_stiffness" in a["samples"]) == (artifact == "force_artifact")
    with h5py.File(path) as f:
        for group in SCHEMA:
            if group.name in f:
                assert f[group.name].attrs["type"] == group.type
                for spec in group.fields:
                    if spec.name in f[group.name]:
                        assert f[group.name][spec.name].attrs["units"] == spec.units


def test_missing_file(tmp_path):
    with pytest.raises(ArtifactError, match="not found"):
        read_artifact(tmp_path / "nope.h5")


def test_truncated_file(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtifactError, match="truncated or appended to"):
        read_artifact(path)


def _flip_one_force_bit(f):
    force = f["samples/force"]
    values = force[()]
    values[1, 2] = np.nextafter(values[1, 2], np.inf)  # one bit
    force[...] = values


def test_bit_flip_is_caught_by_the_whole_file_checksum(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    with h5py.File(path, "r+") as f:
        _flip_one_force_bit(f)
    with pytest.raises(ArtifactError, match="fails its whole-file checksum"):
        read_artifact(path)


def test_bit_flip_behind_a_resealed_envelope_is_caught_by_the_dataset_checksum(
    small_artifact, tmp_path
):
    path = copy(small_artifact, tmp_path)
    mutate(path, _flip_one_force_bit)
    with pytest.raises(ArtifactError, match="samples/force fails its checksum"):
        read_artifact(path)


def test_raw_byte_flip_anywhere_is_refused(small_artifact, tmp_path):
    """Flip single bytes across the file (user block included): every flip is refused."""
    data = bytearray(small_artifact.read_bytes())
    rng = np.random.default_rng(7)
    for position in rng.integers(0, len(data), 40):
        path = tmp_path / "flip.h5"
        damaged = bytearray(data)
        damaged[position] ^= 0x10
        path.write_bytes(bytes(damaged))
        with pytest.raises(ArtifactError):
            read_artifact(path)


def test_unknown_major_version_is_refused(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    set_attribute(path, "/", "format_version", np.array([FORMAT_VERSION[0] + 1, 0]))
    with pytest.raises(ArtifactError, match=f"version {FORMAT_VERSION[0] + 1}.0 is not supported"):
        read_artifact(path)


def test_a_format_1_file_with_a_plane_chart_is_refused_with_how_to_re_reduce(
    small_artifact, tmp_path
):
    """Format 2 replaced the samples' plane chart by their triangulation on the surface: a
    1.4 file (its root and samples group say 1.x) is refused, naming the fix."""
    path = copy(small_artifact, tmp_path)

    def older(f):
        f.attrs["format_version"] = np.array([1, 4])
        f["samples"].attrs["version"] = np.array([1, 0])

    mutate(path, older)
    with pytest.raises(ArtifactError, match="1.4 is not supported.*hapticrom reduce CAMPAIGN_DIR"):
        read_artifact(path)


def test_newer_minor_version_loads(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)

    def newer(f):
        f.attrs["format_version"] = np.array([FORMAT_VERSION[0], FORMAT_VERSION[1] + 3])
        f["samples"].create_dataset("something_new", data=np.zeros(3))
        f["samples"].attrs["something_else"] = "new"

    mutate(path, newer)
    assert read_artifact(path).version[1] == FORMAT_VERSION[1] + 3


def test_missing_required_dataset_is_named(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    mutate(path, lambda f: f.__delitem__("samples/coefficients"))
    with pytest.raises(ArtifactError, match="samples/coefficients is missing"):
        read_artifact(path)


def test_wrong_shape_is_named(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)

    def shorter(f):
        bad = f["samples/stiffness"][()][:, :-1]
        del f["samples/stiffness"]
        d = f["samples"].create_dataset("stiffness", data=bad)
        d.attrs["units"] = "N/mm"
        d.attrs["sha256"] = array_digest(bad)

    mutate(path, shorter)
    with pytest.raises(ArtifactError, match="samples/stiffness has shape"):
        read_artifact(path)


def test_not_an_artifact(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["x"] = 1
    with pytest.raises(ArtifactError, match="no integrity envelope.*re-reduce it"):
        read_artifact(path)
    with h5py.File(path, "w", userblock_size=512) as f:
        f["x"] = 1
    seal(path)
    with pytest.raises(ArtifactError, match="lacks the attribute format"):
        read_artifact(path)


def test_the_written_spec_names_every_dataset():
    from pathlib import Path

    spec = (Path(__file__).parents[1] / "shared" / "ARTIFACT.md").read_text()
    for group in SCHEMA:
        assert f"`/{group.name}` (type `{group.type}`, version {group.version[0]}." in spec
        for field in group.fields:
            assert f"| `{field.name}` |" in spec, f"{group.name}/{field.name} is not documented"


def test_the_written_spec_states_every_rule_and_attribute():
    """ARTIFACT.md's `checked` columns and attribute names are the schema's (tested both ways)."""
    import re
    from pathlib import Path

    spec = (Path(__file__).parents[1] / "shared" / "ARTIFACT.md").read_text()
    sections = dict(re.findall(r"(?ms)^## `/(\w+)`(.*?)(?=^## |\Z)", spec))
    for group in SCHEMA:
        body = sections[group.name]
        for field in group.fields:
            checks = (("finite",) if field.dtype == "f" else ()) + field.checks
            row = re.search(rf"(?m)^\| `{field.name}` \|.*\| ([^|]*) \|$", body)
            assert row and row.group(1).strip() == (", ".join(checks) or "-"), field.name
        for attr in group.attrs:
            assert f"`{attr.name}`" in body, f"{group.name} attribute {attr.name} not documented"


def test_the_atomic_writer_leaves_the_target_alone_on_failure(tmp_path):
    """A failure while the content is written (or checked) leaves no partial file behind."""
    from hapticrom.shared.files import write_checksummed, write_hdf5_atomically

    target = tmp_path / "data.h5"
    target.write_bytes(b"previous\n")

    def fill(f):
        write_checksummed(f, "x", np.arange(3.0))
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_hdf5_atomically(target, fill)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.h5"]
    assert target.read_bytes() == b"previous\n"
    write_hdf5_atomically(target, lambda f: write_checksummed(f, "x", np.arange(3.0)))
    with h5py.File(target, "r") as f:
        assert f["x"].attrs["sha256"] == array_digest(np.arange(3.0))


def test_vertex_normals_point_out_of_a_tetrahedron():
    from hapticrom.shared.geometry import vertex_normals

    nodes = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward
    normals = vertex_normals(nodes, faces)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", normals, nodes - nodes.mean(axis=0)) > 0)
    assert not vertex_normals(np.vstack([nodes, [[5.0, 5, 5]]]), faces)[4].any()  # on no face
