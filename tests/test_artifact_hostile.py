"""Hostile artifacts: every damaged or crafted file is refused with one ArtifactError.

The attacks recompute every checksum (tests/tamper.py), so they reach the
reader's structure and value checks; the fuzz test flips bytes with no such
help. Loading goes through ``hapticrom.online.load`` (reader, model set-up and
kernel warm-up) wherever the runtime would, so nothing escapes as another
exception, crashes the interpreter or hands a NaN to a kernel.
"""

from __future__ import annotations

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from tamper import copy, mutate, rewrite, set_attribute

from hapticrom.online import load
from hapticrom.shared.artifact import SCHEMA, ArtifactError, read_artifact
from hapticrom.shared.checksum import array_digest
from hapticrom.shared.envelope import USERBLOCK

pytestmark = pytest.mark.serial


def refused(path, match: str) -> None:
    """Refused by ``load`` (in this process: the child-process isolation has tests of its own
    and would only add a second parse to each of the many cases here)."""
    with pytest.raises(ArtifactError, match=match):
        load(path, isolate=False)


def present_fields(artifact_path, dtype: str):
    with h5py.File(artifact_path, "r") as f:
        return [
            f"{g.name}/{spec.name}"
            for g in SCHEMA
            if g.name in f
            for spec in g.fields
            if spec.dtype == dtype and spec.name in f[g.name]
        ]


# -- values (checksums recomputed) -------------------------------------------------------
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_refused_in_every_float_dataset(small_artifact, tmp_path, value):
    for name in present_fields(small_artifact, "f"):
        path = copy(small_artifact, tmp_path)

        def poison(a):
            a.reshape(-1)[a.size // 2] = value
            return a

        rewrite(path, name, poison)
        refused(path, f"{name} has NaN or infinite values")


def _bad_integers(spec, symbols):
    """Values that break each rule of an integer field ("repeat": a value twice)."""
    for check in spec.checks:
        rule, _, arg = check.partition(":")
        if rule == "index":
            yield from (-1, symbols[arg])
        elif rule == "choice":
            yield from (-1, max(int(v) for v in arg.split(",")) + 1)
        elif rule == "nonnegative":
            yield -1
        elif rule == "distinct":
            yield "repeat"


def test_every_rule_of_every_integer_dataset_is_enforced(small_artifact, tmp_path):
    symbols = read_artifact(small_artifact).symbols
    tried = 0
    for group in SCHEMA:
        for spec in group.fields:
            name = f"{group.name}/{spec.name}"
            if spec.dtype != "i" or name not in present_fields(small_artifact, "i"):
                continue
            for bad in _bad_integers(spec, symbols):
                path = copy(small_artifact, tmp_path)

                def set_bad(a, bad=bad):
                    flat = a.reshape(-1)
                    flat[-1] = flat[0] if bad == "repeat" else bad
                    return a

                rewrite(path, name, set_bad)
                refused(path, name)
                tried += 1
    assert tried >= 10


def third_on_an_edge(t: np.ndarray) -> np.ndarray:
    """The triangles plus two more on the first triangle's edge (b, c), with samples not
    in it: that edge then has three triangles (or more)."""
    _, b, c = t[0]
    others = sorted(set(np.unique(t).tolist()) - set(t[0].tolist()))[:2]
    return np.vstack([t, [[b, c, d] for d in others]])


@pytest.mark.parametrize(
    "name, change, match",
    [
        ("samples/force", lambda a: -a, "samples/force has negative values"),
        ("samples/force", lambda a: a[:, ::-1].copy(), "samples/force"),
        ("samples/force", lambda a: 1000 * a, "anm.* sample 0"),
        ("samples/stiffness", lambda a: -a, "samples/stiffness has negative values"),
        ("samples/normals", lambda a: 0 * a, "samples/normals has rows that are not unit"),
        ("samples/triangles", lambda t: t[:, ::-1].copy(), "not facing along its samples"),
        ("samples/triangles", lambda t: third_on_an_edge(t), "edge in more than two"),
        ("samples/triangles", lambda t: np.vstack([t, t[:1, [1, 2, 0]]]), "triangle twice"),
        ("samples/depth", lambda a: 0 * a, "samples/depth must start at 0 and increase"),
        ("samples/depth", lambda a: a**2, "samples/depth must be uniform"),
        ("samples/reduced_stiffness", lambda a: a + np.triu(a, 1), "is not symmetric"),
        ("anm/force", lambda a: -a, "anm/force"),
        ("anm/force", lambda a: 1000 * a, "anm"),
        ("anm/depth", lambda a: -a, "anm"),
        ("anm/a_max", lambda a: -a, "anm/a_max has values that are not positive"),
        ("anm/section_offsets", lambda a: a[::-1].copy(), "anm/section_offsets"),
        ("surface/groups", lambda a: a + 3, "surface/groups has values other than 0,1,2"),
        ("grassmann/reference", lambda a: np.int64(-1), "grassmann/reference has indices"),
    ],
)
def test_semantic_attacks_with_valid_checksums_are_refused(
    small_artifact, tmp_path, name, change, match
):
    path = copy(small_artifact, tmp_path)
    rewrite(path, name, change)
    refused(path, match)


def test_degenerate_geometry_is_refused(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)

    def collapse_sample(f):  # sample 1 moved onto sample 0: a zero-area sample triangle
        for key in ("points",):
            a = f[f"samples/{key}"][()]
            a[1] = a[0]
            del f[f"samples/{key}"]
            d = f["samples"].create_dataset(key, data=a)
            d.attrs["units"], d.attrs["sha256"] = "mm", array_digest(a)

    mutate(path, collapse_sample)
    refused(path, "degenerate")
    path = copy(small_artifact, tmp_path)
    rewrite(path, "surface/triangles", lambda t: np.column_stack([t[:, 0], t[:, 0], t[:, 2]]))
    refused(path, "surface/triangles has a degenerate")


# -- attributes ----------------------------------------------------------------------
@pytest.mark.parametrize(
    "obj, key, value, match",
    [
        ("/", "format_version", "1.4", "attribute format_version of root must be a list"),
        ("/", "format_version", np.array([1, 4, 0]), "format_version of root must be"),
        ("samples", "version", np.array([1.5, 0.0]), "version of samples must be a list of int"),
        ("model", "contact_radius", np.nan, "contact_radius of model must be a finite number"),
        ("model", "contact_radius", -0.5, "contact_radius of model must be positive"),
        ("model", "contact_radius", "0.5", "contact_radius of model must be a finite number"),
        ("model", "mode", "magnetic", "mode of model must be one of displacement, force"),
        ("model", "material", "[" * 100000 + "]" * 100000, "material of model must be a JSON"),
        ("model", "material", "not json", "material of model must be a JSON"),
        ("model", "name", b"\xff\xfe", "name of model must be a UTF-8 string"),
        ("anm", "order", 0, "order of anm must lie in"),
        ("anm", "order", 7, "series' order do not fit"),
        ("samples", "type", "contact-samples-v9", "group samples has type"),
        ("samples", "pressure_modes", np.array([[1, 2]]), "pressure_modes of samples must be"),
    ],
)
def test_hostile_attributes_are_refused(small_artifact, tmp_path, obj, key, value, match):
    path = copy(small_artifact, tmp_path)
    set_attribute(path, obj, key, value)
    refused(path, match)


def test_units_are_compared_with_the_schema(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    set_attribute(path, "samples/force", "units", "kN")
    refused(path, "samples/force has units 'kN', expected 'N'")


def test_huge_attribute_is_refused_before_it_is_read(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    set_attribute(path, "model", "modes", np.zeros(1 << 15, dtype=np.int8))
    refused(path, "attribute modes of model has")


# -- structure ----------------------------------------------------------------------------
def _replace(f, name, make):
    parent, _, key = name.rpartition("/")
    del f[name]
    make(f[parent or "/"], key)


def test_a_group_where_a_dataset_belongs_is_refused(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    mutate(path, lambda f: _replace(f, "samples/force", lambda g, k: g.create_group(k)))
    refused(path, "samples/force is not a dataset")
    path = copy(small_artifact, tmp_path)
    mutate(path, lambda f: _replace(f, "anm", lambda g, k: g.create_dataset(k, data=[1.0])))
    refused(path, "anm is not a group")


@pytest.mark.parametrize("kind", ["soft", "external", "external-loop"])
def test_links_are_refused(small_artifact, tmp_path, kind):
    path = copy(small_artifact, tmp_path)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as o:
        o["force"] = read_artifact(small_artifact)["samples"]["force"]
    make = {
        "soft": lambda g, k: g.__setitem__(k, h5py.SoftLink("/samples/stiffness")),
        "external": lambda g, k: g.__setitem__(k, h5py.ExternalLink(str(other), "/force")),
        "external-loop": lambda g, k: g.__setitem__(k, h5py.ExternalLink(str(path), "/x")),
    }[kind]
    mutate(path, lambda f: _replace(f, "samples/force", make))
    refused(path, "samples/force is a (SoftLink|ExternalLink): only data inside the file")


@pytest.mark.parametrize("target", ["file", "fifo", "proc"])
def test_external_raw_storage_is_refused_without_opening_it(small_artifact, tmp_path, target):
    path = copy(small_artifact, tmp_path)
    force = read_artifact(small_artifact)["samples"]["force"]
    source = {"file": tmp_path / "raw.bin", "fifo": tmp_path / "fifo", "proc": None}[target]
    if target == "file":
        source.write_bytes(force.tobytes())
    elif target == "fifo":
        os.mkfifo(source)  # opening it for reading would block forever
    name = "/proc/self/environ" if source is None else str(source)

    def external(g, k):
        d = g.create_dataset(k, shape=force.shape, dtype=force.dtype, external=[(name, 0, 4096)])
        d.attrs["units"], d.attrs["sha256"] = "N", array_digest(force)

    mutate(path, lambda f: _replace(f, "samples/force", external))
    refused(path, "samples/force is stored outside the file")


def test_virtual_datasets_are_refused(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    force = read_artifact(small_artifact)["samples"]["force"]
    other = tmp_path / "source.h5"
    with h5py.File(other, "w") as o:
        o["force"] = force

    def virtual(g, k):
        layout = h5py.VirtualLayout(shape=force.shape, dtype=force.dtype)
        layout[...] = h5py.VirtualSource(str(other), "force", shape=force.shape)
        d = g.create_virtual_dataset(k, layout)
        d.attrs["units"], d.attrs["sha256"] = "N", array_digest(force)

    mutate(path, lambda f: _replace(f, "samples/force", virtual))
    refused(path, "samples/force is stored outside the file")


def test_size_bomb_is_refused_before_allocation(small_artifact, tmp_path):
    """256 GiB declared, nothing stored: refused from the metadata, nothing allocated."""
    path = copy(small_artifact, tmp_path)
    P = len(read_artifact(small_artifact)["samples"]["points"])

    def bomb(g, k):  # M is first defined by this dataset, so its shape fits the schema
        d = g.create_dataset(k, shape=(P, (1 << 38) // (8 * P)), dtype="<f8")
        d.attrs["units"], d.attrs["sha256"] = "mm^2", "0" * 64

    mutate(path, lambda f: _replace(f, "samples/eigenvalues", bomb))
    refused(path, "samples/eigenvalues declares .* bytes but stores 0")


def test_chunked_or_compressed_data_is_refused(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    force = read_artifact(small_artifact)["samples"]["force"]

    def compressed(g, k):
        d = g.create_dataset(k, data=force, compression="gzip")
        d.attrs["units"], d.attrs["sha256"] = "N", array_digest(force)

    mutate(path, lambda f: _replace(f, "samples/force", compressed))
    refused(path, "samples/force is chunked or filtered")


@pytest.mark.parametrize("dtype", ["<f2", ">f8", "complex128", "S8"])
def test_unexpected_dtypes_are_refused(small_artifact, tmp_path, dtype):
    path = copy(small_artifact, tmp_path)
    rewrite(path, "samples/force", lambda a: a.astype(dtype))
    refused(path, "samples/force has dtype")


# -- the file itself --------------------------------------------------------------------------
def test_what_is_not_a_regular_file_is_refused_without_reading(tmp_path):
    fifo = tmp_path / "model.h5"
    os.mkfifo(fifo)
    refused(fifo, "is not a regular file")
    refused(tmp_path, "is not a regular file")
    link = tmp_path / "environ.h5"
    link.symlink_to("/proc/self/environ")
    refused(link, "not a hapticrom artifact")


def test_appended_bytes_are_refused(small_artifact, tmp_path):
    path = copy(small_artifact, tmp_path)
    with open(path, "ab") as fh:
        fh.write(b"\0" * 16)
    refused(path, "truncated or appended to")


def test_fuzz_1000_byte_flips_over_the_whole_file(small_artifact, tmp_path):
    """Random single-byte flips anywhere (envelope included): each one is refused.

    The flips are not re-sealed: this is damage, which the whole-file digest
    catches before h5py parses anything (crafted files are the tests above;
    ``bench/fuzz_artifact.py`` flips bytes behind a re-sealed envelope).
    """
    data = small_artifact.read_bytes()
    rng = np.random.default_rng(2026)
    positions = np.concatenate(
        [rng.integers(0, USERBLOCK, 100), rng.integers(USERBLOCK, len(data), 900)]
    )
    path = tmp_path / "fuzz.h5"
    outcomes = {}
    for position in positions:
        damaged = bytearray(data)
        damaged[position] ^= int(rng.integers(1, 256))
        path.write_bytes(bytes(damaged))
        try:
            load(path, isolate=False)
            outcome = "loaded"
        except ArtifactError as exc:
            outcome = str(exc).split(": ", 1)[-1].split(" (")[0][:40]
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    assert "loaded" not in outcomes, outcomes
    assert sum(outcomes.values()) == 1000


def test_a_crafted_file_cannot_crash_the_interpreter(small_artifact, tmp_path):
    """Flips in HDF5's structure behind a re-sealed envelope, loaded by a child process: refused
    or loaded, never a crash, a hang or another exception (bench/fuzz_artifact.py runs more;
    with --in-process it shows the crashes the isolation catches)."""
    script = os.path.join(os.path.dirname(__file__), "..", "bench", "fuzz_artifact.py")
    result = subprocess.run(
        [sys.executable, script, str(small_artifact), "--flips", "60", "--seed", "3",
         "--mode", "metadata", "--workdir", str(tmp_path)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    assert "uncaught 0, crashed 0, hung 0" in result.stdout, result.stdout


def test_a_reading_process_that_dies_is_an_artifact_error(small_artifact, tmp_path):
    from pathlib import Path

    from hapticrom.shared.artifact import check_isolated

    crash = [sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"]
    with pytest.raises(ArtifactError, match="crashed the reading process \\(signal 11\\)"):
        check_isolated(b"", Path("x.h5"), command=crash)
    path = copy(small_artifact, tmp_path)  # the child's own refusal comes through verbatim
    set_attribute(path, "samples/force", "units", "kN")
    with pytest.raises(ArtifactError, match="samples/force has units 'kN'"):
        read_artifact(path, isolate=True)


def test_the_smallest_slope_rule_matches_dense_sampling():
    """The exact minimum of p' on [0, a] (ends and critical points) against 200,001 samples."""
    from numpy.polynomial import polynomial as poly

    from hapticrom.shared.artifact_rules import min_slope

    rng = np.random.default_rng(0)
    c = rng.standard_normal((100, 7))
    a = rng.uniform(0.1, 2.0, 100)
    c[5, -1], c[6, -2:] = 0.0, 0.0  # lower-degree rows take the one-by-one path
    dense = [
        poly.polyval(np.linspace(0, a[z], 200_001), poly.polyder(c[z])).min() for z in range(100)
    ]
    np.testing.assert_allclose(min_slope(c, a), dense, atol=1e-8)


# -- the red team's breaks (each loaded, then misbehaved, before its rule existed) -------------
def test_a_huge_sparse_file_is_refused_before_it_is_read(tmp_path):
    path = tmp_path / "huge.h5"
    with open(path, "wb") as fh:
        fh.truncate(3 << 30)  # 3 GiB of holes: no disk, but a read would allocate them
    refused(path, "over the .* limit")
    with open(path, "r+b") as fh:  # a plausible header that lies about the size
        fh.truncate(1 << 20)
        fh.write(b"hapticrom-envelope 1\nbytes 999\nsha256 " + b"0" * 64 + b"\n")
    refused(path, "has 1048576 bytes, its envelope says 999")


def test_opposite_normals_of_neighbouring_samples_are_refused(small_artifact, tmp_path):
    """Their blend on the shared edge is the zero vector: set_contact divided by it."""
    path = copy(small_artifact, tmp_path)
    t = read_artifact(small_artifact)["samples"]["triangles"][0]

    def flip(n):
        n[t[1]] = -n[t[0]]
        return n

    rewrite(path, "samples/normals", flip)
    refused(path, "normals of neighbouring samples differ by more than 80 degrees")


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda s: s * np.r_[np.ones(s.shape[1] - 1), 0.0], "must end positive"),  # 1/0
        (lambda s: s + np.r_[np.zeros(s.shape[1] - 1), 1e300], "exceeds 3x an adjacent secant"),
        (lambda s: s + 1e6, "exceeds 3x an adjacent secant"),
    ],
)
def test_stiffness_that_would_make_the_cubic_overshoot_is_refused(
    small_artifact, tmp_path, change, match
):
    path = copy(small_artifact, tmp_path)
    rewrite(path, "samples/stiffness", change)
    refused(path, match)


def test_a_series_that_runs_away_beyond_its_last_section_is_refused(small_artifact, tmp_path):
    """The last section flattens in depth at a_max while its force still rises: within 1 % of
    the curves everywhere trained, 1e13 times the trained force beyond (the red team's)."""
    from numpy.polynomial import polynomial as poly

    path = copy(small_artifact, tmp_path)

    def flatten(f):
        off = f["anm/section_offsets"][()]
        depth, force, a_max = (f[f"anm/{k}"][()] for k in ("depth", "force", "a_max"))
        for z in off[1:] - 1:
            d0, f0 = depth[z, 0], force[z, 0]
            d1, f1 = poly.polyval(a_max[z], depth[z]), poly.polyval(a_max[z], force[z])
            depth[z], force[z], a_max[z] = 0.0, 0.0, 1.0
            depth[z, :3] = d0, 2 * (d1 - d0) + 8 * np.spacing(2 * (d1 - d0)), -(d1 - d0)
            force[z, :3] = f0, 2.01 * (f1 - f0), -(f1 - f0)
        for key, values in (("depth", depth), ("force", force), ("a_max", a_max)):
            _replace(f, f"anm/{key}", lambda g, k, v=values: _dataset(g, k, v))

    mutate(path, flatten)
    refused(path, "end slope is")


def _dataset(g, key, values):
    units = {"depth": "mm", "force": "N", "a_max": "1"}[key]
    d = g.create_dataset(key, data=values)
    d.attrs["units"], d.attrs["sha256"] = units, array_digest(values)


@pytest.mark.parametrize(
    "name, scale, message",
    [
        ("samples/coefficients", 1e300, "surface is not finite or beyond the simulator's limit"),
        # the surface chart's fit overflows single precision first, and names the dataset
        ("samples/surface_basis", 3e38, "samples/surface_basis: its modes overflow single"),
    ],
)
def test_a_field_that_overflows_away_from_sample_0_is_refused(
    small_artifact, tmp_path, name, scale, message
):
    """Huge but finite values at sample 1 only: the sweep renders every sample and blend."""
    path = copy(small_artifact, tmp_path)

    def huge(a):
        a = a.astype(np.float64) if a.dtype == np.float32 and scale < 1e38 else a
        a[1] = np.sign(a[1]) * scale
        return a

    rewrite(path, name, huge)
    if name == "samples/coefficients":  # the series' own coordinates of sample 1 too
        offsets = read_artifact(small_artifact)["anm"]["section_offsets"]
        rewrite(path, "anm/coefficients", lambda c: _scale_rows(c, offsets[1], offsets[2]))
    refused(path, message)


def _scale_rows(c, start, stop):
    c[start:stop] = np.sign(c[start:stop]) * 1e300
    return c


def test_absurd_but_consistent_scales_are_refused(small_artifact, tmp_path):
    """A model of a tissue 1e305 times stiffer: finite, monotone, consistent, absurd."""
    path = copy(small_artifact, tmp_path)
    for name in ("samples/force", "samples/stiffness", "anm/force"):
        rewrite(path, name, lambda a: a * 1e305)
    refused(path, r"largest force not in \(0, 100000\] N")


# -- the tool's stiffness lattice (samples/tool_stiffness, format 2.1) --------------------------
TOOL_STIFFNESS = "samples/tool_stiffness"


def _lattice_point(k: np.ndarray, *weights: int) -> int:
    """The column of ``k`` (S, L) holding the lattice point of weights (m - i - j, i, j)."""
    from hapticrom.shared.lattice import lattice_subdivisions, lattice_weights

    return [tuple(w) for w in lattice_weights(lattice_subdivisions(k.shape[1]))].index(weights)


def _inner_point(k: np.ndarray) -> int:
    """A lattice point next to corner 0 inside the triangle, away from every point the load
    sweep touches (corners, edge midpoints, centroid): (m - 2, 1, 1)."""
    from hapticrom.shared.lattice import lattice_subdivisions

    m = lattice_subdivisions(k.shape[1])
    assert m >= 4  # (m - 2, 1, 1) is then in none of the sweep's sub-triangles
    return _lattice_point(k, m - 2, 1, 1)


@pytest.mark.parametrize("columns", [1, 2, 44, 66 * 67 // 2])  # m = 0, none, none, 65
def test_tool_stiffness_of_no_lattice_size_is_refused(force_artifact, tmp_path, columns):
    path = copy(force_artifact, tmp_path)
    rewrite(path, TOOL_STIFFNESS, lambda k: np.resize(k, (len(k), columns)))
    refused(path, f"{TOOL_STIFFNESS} has {columns} points per triangle, not those of a lattice")


@pytest.mark.parametrize("value", [0.0, -0.1])
def test_tool_stiffness_that_is_not_positive_is_refused(force_artifact, tmp_path, value):
    path = copy(force_artifact, tmp_path)

    def put(k):
        k[0, _inner_point(k)] = value
        return k

    rewrite(path, TOOL_STIFFNESS, put)
    refused(path, f"{TOOL_STIFFNESS} has values that are not positive")


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", ["corner", "inner"])
def test_tool_stiffness_that_is_not_finite_is_refused(force_artifact, tmp_path, value, where):
    """The generic finite test runs on small_artifact, which has no tool_stiffness."""
    path = copy(force_artifact, tmp_path)

    def put(k):
        k[-1, 0 if where == "corner" else _inner_point(k)] = value
        return k

    rewrite(path, TOOL_STIFFNESS, put)
    refused(path, f"{TOOL_STIFFNESS} has NaN or infinite values")


@pytest.mark.parametrize("factor", [1.5, 1 + 1e-9])
@pytest.mark.parametrize("corner", [0, 1, 2])
def test_tool_stiffness_of_a_sample_that_differs_between_its_triangles_is_refused(
    force_artifact, tmp_path, corner, factor
):
    """One triangle's value at one of its corners changed: the sample's own curve is then no
    longer reproduced from that triangle, and the force jumps across its edges."""
    from hapticrom.shared.lattice import lattice_corners, lattice_subdivisions

    t = read_artifact(force_artifact)["samples"]["triangles"]
    sample = t[0, corner]
    assert np.count_nonzero(t == sample) >= 2  # the sample has another triangle
    path = copy(force_artifact, tmp_path)

    def change(k):
        k[0, lattice_corners(lattice_subdivisions(k.shape[1]))[corner]] *= factor
        return k

    rewrite(path, TOOL_STIFFNESS, change)
    refused(path, f"{TOOL_STIFFNESS} differs at a sample between its triangles")


@pytest.mark.parametrize("factor", [1000.0, 10.5])
def test_tool_stiffness_that_varies_over_10_fold_in_a_triangle_is_refused(
    force_artifact, tmp_path, factor
):
    """A value ``factor`` times the triangle's smallest, at a lattice point the sweep does not
    touch (with every other value unchanged, the corners stay consistent)."""
    path = copy(force_artifact, tmp_path)

    def spike(k):
        k[1, _inner_point(k)] = factor * k[1].min()
        return k

    rewrite(path, TOOL_STIFFNESS, spike)
    refused(path, f"{TOOL_STIFFNESS} varies more than 10-fold in a triangle")


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda k: np.vstack([k, k[:1]]), r"has shape \(\d+, \d+\), expected \(\d+, \d+\)"),
        (lambda k: k[:-1].copy(), r"has shape \(\d+, \d+\), expected \(\d+, \d+\)"),
        (lambda k: k[0].copy(), r"has shape \(\d+,\), expected rank 2"),
        (lambda k: k[..., None].copy(), r"has shape \(\d+, \d+, 1\), expected rank 2"),
    ],
    ids=["S+1 rows", "S-1 rows", "rank 1", "rank 3"],
)
def test_tool_stiffness_of_the_wrong_shape_is_refused(force_artifact, tmp_path, change, match):
    path = copy(force_artifact, tmp_path)
    rewrite(path, TOOL_STIFFNESS, change)
    refused(path, f"{TOOL_STIFFNESS} {match}")


def test_without_tool_stiffness_a_2_0_file_loads_and_blends_the_curves_plainly(
    force_artifact, tmp_path
):
    """The dataset removed (and the versions set back to 2.0): the file loads, and its
    forces are those of the plain blend w_i, bit for bit; they differ from the scaled ones."""
    import dataclasses

    from hapticrom.online.simulator import Simulator

    path = copy(force_artifact, tmp_path)

    def strip(f):
        del f[TOOL_STIFFNESS]
        f.attrs["format_version"] = np.array([2, 0], dtype=np.int64)
        f["samples"].attrs["version"] = np.array([2, 0], dtype=np.int64)

    mutate(path, strip)
    old = load(path, isolate=False)
    assert old.tool_stiffness is None
    scaled = load(force_artifact, isolate=False)
    assert scaled.tool_stiffness is not None
    plain = dataclasses.replace(scaled, tool_stiffness=None)
    rng = np.random.default_rng(21)
    p, t = scaled.sample_points, scaled.sample_triangles
    for response in ["curves"] + (["anm"] if scaled.anm else []):
        sims = [Simulator(m, response=response) for m in (old, plain, scaled)]
        largest_difference = 0.0
        for _ in range(20):
            point = rng.dirichlet(np.ones(3)) @ p[t[rng.integers(len(t))]]
            forces = []
            for sim in sims:
                sim.set_contact(point)
                n = np.array(sim.contact_normal)
                forces.append(np.array(sim.step_displacement(-0.5 * scaled.trained_depth * n)))
            assert np.all(np.isfinite(forces[0])) and np.linalg.norm(forces[0]) > 0
            np.testing.assert_array_equal(forces[0], forces[1])
            largest_difference = max(largest_difference, np.max(np.abs(forces[2] - forces[0])))
        assert largest_difference > 1e-3 * scaled.force[:, -1].max(), response


# -- the red team's, on values the rules pass (each loaded, then misbehaved at the runtime) ----
def _contacts_in_triangles(model, count: int, seed: int):
    rng = np.random.default_rng(seed)
    p, t = model.sample_points, model.sample_triangles
    for _ in range(count):
        yield rng.dirichlet(np.ones(3)) @ p[t[rng.integers(len(t))]]


def test_tool_stiffness_at_the_largest_double_is_refused_or_gives_finite_forces(
    force_artifact, tmp_path
):
    """Every value 1.797e308 (finite, positive, equal): the lattice interpolant rounds to
    inf at some contacts, the curve weights are inf and the force NaN (about 5 % of the
    contacts inside the triangles; the sweep's points happen to be exact)."""
    from hapticrom.online.simulator import Simulator

    path = copy(force_artifact, tmp_path)
    rewrite(path, TOOL_STIFFNESS, lambda k: np.full_like(k, np.finfo(np.float64).max))
    try:
        model = load(path, isolate=False)
    except ArtifactError as exc:
        assert TOOL_STIFFNESS in str(exc)
        return
    sim = Simulator(model, response="curves")
    for point in _contacts_in_triangles(model, 400, seed=1):
        sim.set_contact(point)
        n = np.array(sim.contact_normal)
        force = sim.step_displacement(-0.5 * model.trained_depth * n)
        assert np.all(np.isfinite(force)), (point.tolist(), force)


def test_tool_stiffness_that_underflows_in_a_sub_triangle_is_refused_or_still_pushes_back(
    force_artifact, tmp_path
):
    """The three lattice points of one sub-triangle at the smallest subnormal (5e-324), the
    others 99x that (within the factor 100): at the sub-triangle's centroid each of the
    interpolant's terms rounds to 0, so every curve weight is 0. The force in contact is then
    zero, and step_force (response "curves") raised ZeroDivisionError, not a SimulatorError."""
    from hapticrom.online.simulator import Simulator
    from hapticrom.shared.errors import SimulatorError
    from hapticrom.shared.lattice import lattice_subdivisions

    m = lattice_subdivisions(read_artifact(force_artifact)["samples"]["tool_stiffness"].shape[1])
    tiny = [(m - 2, 1, 1), (m - 3, 2, 1), (m - 3, 1, 2)]  # away from the sweep's points
    path = copy(force_artifact, tmp_path)

    def underflow(k):
        v = np.full_like(k, 99 * 5e-324)
        v[:, [_lattice_point(k, *w) for w in tiny]] = 5e-324
        return v

    rewrite(path, TOOL_STIFFNESS, underflow)
    try:
        model = load(path, isolate=False)
    except ArtifactError as exc:
        assert TOOL_STIFFNESS in str(exc)
        return
    weights = np.mean(tiny, axis=0) / m  # the sub-triangle's centroid, in triangle 0
    point = weights @ model.sample_points[model.sample_triangles[0]]
    for response in ["curves"] + (["anm"] if model.anm else []):
        sim = Simulator(model, response=response)
        sim.set_contact(point)
        n = np.array(sim.contact_normal)
        try:
            sim.step_force(-0.5 * model.trained_force * n)
        except SimulatorError:
            pass  # a refusal the runtime documents (the state is unchanged)
        except Exception as exc:  # noqa: BLE001 - what the runtime must never raise
            pytest.fail(f"{response}: step_force raised {type(exc).__name__}: {exc}")
        force = sim.step_displacement(-0.5 * model.trained_depth * n)
        assert np.linalg.norm(force) > 0, response


def test_tool_stiffness_peak_between_the_sweep_points_is_refused_or_within_the_force_limit(
    force_artifact, tmp_path
):
    """One lattice point 99x the others (the rule allows 100x): the load's sweep, which
    vouches for forces within the simulator's limit (10x the trained force) inside the
    trained region, touches only corners, edge midpoints and centroids; at the peak the
    force is about 99x the plain blend."""
    from hapticrom.online.simulator import Simulator
    from hapticrom.shared.lattice import lattice_subdivisions, lattice_weights

    path = copy(force_artifact, tmp_path)

    def peak(k):
        v = np.ones_like(k)
        v[:, _inner_point(k)] = 99.0
        return v

    rewrite(path, TOOL_STIFFNESS, peak)
    try:
        model = load(path, isolate=False)
    except ArtifactError as exc:
        assert TOOL_STIFFNESS in str(exc) or "simulator's limit" in str(exc)
        return
    m = lattice_subdivisions(model.tool_stiffness.shape[1])
    sim = Simulator(model, response="curves")
    p, t = model.sample_points, model.sample_triangles
    for corners in t:
        for w in lattice_weights(m) / m:  # every lattice point
            sim.set_contact(w @ p[corners])
            n = np.array(sim.contact_normal)
            force = sim.step_displacement(-model.trained_depth * n)
            assert np.linalg.norm(force) <= sim.max_force, (w, np.linalg.norm(force))


# -- the contact fields (format 2.2), on values the generic rules pass --------------------------
FIELDS = "contact_fields"


def _a_vertex_that_is_not_loadable(artifact_path) -> int:
    s = read_artifact(artifact_path)["surface"]
    loadable = np.unique(s["triangles"][s["groups"] == 1])
    return int(np.setdiff1d(np.arange(len(s["vertices"])), loadable)[0])


def test_contact_field_rows_that_are_not_the_loadable_vertices_are_refused(
    force_artifact, tmp_path
):
    """A row moved to a vertex of no loadable triangle: the runtime reads the rows of the
    loadable triangle under the contact, so one of those would be missing."""
    other = _a_vertex_that_is_not_loadable(force_artifact)
    path = copy(force_artifact, tmp_path)

    def move(v):
        v[len(v) // 2] = other
        return v

    rewrite(path, f"{FIELDS}/vertices", move)
    refused(path, f"{FIELDS}/vertices are not the loadable triangles' vertices")


def test_contact_field_sample_rows_at_other_vertices_are_refused(force_artifact, tmp_path):
    """Two samples' rows swapped (still distinct, in range): the correction would no longer
    vanish at a sample, and the trained field would not be drawn there."""
    path = copy(force_artifact, tmp_path)

    def swap(rows):
        rows[[0, 1]] = rows[[1, 0]]
        return rows

    rewrite(path, f"{FIELDS}/sample_rows", swap)
    refused(path, f"{FIELDS}/sample_rows name a vertex that is not at its sample")


@pytest.mark.parametrize("value", [1e30, -2e3, 1e3 * (1 + 1e-6)])
def test_contact_fields_beyond_a_thousand_per_unit_depth_are_refused(
    force_artifact, tmp_path, value
):
    path = copy(force_artifact, tmp_path)

    def put(f):
        f[-1, f.shape[1] // 3] = value
        return f

    rewrite(path, f"{FIELDS}/fields", put)
    refused(path, f"{FIELDS}/fields has values beyond")


def test_without_contact_fields_a_2_1_file_loads_with_its_old_default(force_artifact, tmp_path):
    """The group removed (the version set back to 2.1): the file loads, asks for no
    compliance surface, and draws what it drew before."""
    from hapticrom.online.simulator import Simulator
    from hapticrom.shared.errors import InputError

    path = copy(force_artifact, tmp_path)

    def strip(f):
        del f[FIELDS]
        f.attrs["format_version"] = np.array([2, 1], dtype=np.int64)

    mutate(path, strip)
    old = load(path, isolate=False)
    assert old.contact_fields is None
    assert Simulator(old).interpolation == ("transport" if old.chart is not None else "podi")
    with pytest.raises(InputError, match="no contact fields"):
        Simulator(old, "compliance")


# -- the red team's, on the contact fields: each file passes every rule -------------------------
def _field_rows_at(model, point):
    """The rows and weights of the loadable triangle nearest ``point`` (the numpy reference)."""
    from hapticrom.online.reference import nearest_on_triangles

    f = model.contact_fields
    t, beta = nearest_on_triangles(point, model.vertices, f["triangles"])
    return f["triangle_rows"][t], beta


def test_a_contact_field_row_the_sweep_misses_is_refused(force_artifact, tmp_path):
    """One row at 999 (the rule allows 1000): the vertex of a loadable triangle that contacts
    inside the trained region read (at weight ~0.9), but no sweep point (samples, centroids,
    edge midpoints) does. It loaded before the reach rule, and a contact there drew 999 d at
    that vertex: 362 mm at the trained depth against the simulator's 3.9 mm limit."""
    from hapticrom.online.model import sweep_points

    honest = load(force_artifact, isolate=False)
    swept = set(honest.contact_fields["sample_rows"].tolist())
    for point in sweep_points(honest):
        rows, beta = _field_rows_at(honest, point)
        swept |= set(rows[beta > 0].tolist())
    weight, row = 0.0, -1
    for point in _contacts_in_triangles(honest, 400, seed=5):
        for r, w in zip(*_field_rows_at(honest, point), strict=True):
            if int(r) not in swept and w > weight:
                weight, row = w, int(r)
    assert weight > 0.5, "a row the contacts read with weight, the sweep never"
    path = copy(force_artifact, tmp_path)

    def put(fields):
        fields[row] = 999.0
        return fields

    rewrite(path, f"{FIELDS}/fields", put)
    refused(path, f"{FIELDS}/fields: a row's largest value plus a sample's reach")


def test_a_far_vertex_of_no_loadable_triangle_does_not_stall_the_contact_field_surface(
    force_artifact, tmp_path
):
    """A vertex of no loadable triangle moved 1e4 mm above the organ (within MAX_LENGTH; no
    rule bounds such vertices, and no loadable one moves): the triangles' grid is built over
    every surface vertex, so it grows to 6 x 6 x 4,439 cells of empty space, and a contact
    set above the organ searches ring after ring of them: 0.6 s a surface (the Python
    renderer once per contact, the C ABI's surface at every call), against 30 us."""
    import time

    from hapticrom.online.simulator import Simulator

    s = read_artifact(force_artifact)["surface"]
    v, t, g = s["vertices"], s["triangles"], s["groups"]
    other = np.setdiff1d(np.arange(len(v)), np.unique(t[g == 1]))
    k, far = int(other[np.argmin(v[other, 2])]), 1e4
    path = copy(force_artifact, tmp_path)

    def move(x):
        x[k, 2] = far
        return x

    rewrite(path, "surface/vertices", move)
    try:
        model = load(path, isolate=False)
    except ArtifactError as exc:
        assert "surface" in str(exc)
        return
    sim = Simulator(model, "compliance", response="curves")
    out = np.zeros_like(model.vertices)
    took = []
    for x in (0.0, 1.0, -1.0):  # a new contact each: located again
        sim.set_contact(np.array([x, 0.0, far]))
        sim.step_displacement(-0.5 * model.trained_depth * np.array(sim.contact_normal))
        start = time.perf_counter()
        sim.surface_displacement(out)
        took.append(time.perf_counter() - start)
    assert np.all(np.isfinite(out))
    assert min(took) < 0.05, took


def test_a_contact_field_sample_row_at_a_second_vertex_is_refused(force_artifact, tmp_path):
    """A loadable vertex far from sample 0 (no neighbour of its vertex, at no sample) moved
    onto sample 0's point, and sample 0's row pointed at it: still "the vertex at the
    sample's point". The runtime's triangle there is the sample's own vertex's, so the
    correction d (phi_B - phi_A) did not vanish at the sample: 1.1 mm off the trained
    field (whose largest value is 0.46 mm), within the sweep's limit."""
    a = read_artifact(force_artifact)
    s, c = a["surface"], a["contact_fields"]
    rows, sample_rows = c["vertices"], c["sample_rows"]
    b = int(rows[sample_rows[0]])
    neighbours = np.unique(s["triangles"][np.any(s["triangles"] == b, axis=1)])
    pool = np.setdiff1d(rows, np.r_[neighbours, rows[sample_rows]])
    moved = int(pool[np.argmax(np.linalg.norm(s["vertices"][pool] - s["vertices"][b], axis=1))])
    path = copy(force_artifact, tmp_path)

    def onto_the_sample(x):
        x[moved] = x[b]
        return x

    def to_the_moved_row(r):
        r[0] = int(np.flatnonzero(rows == moved)[0])
        return r

    rewrite(path, "surface/vertices", onto_the_sample)
    rewrite(path, f"{FIELDS}/sample_rows", to_the_moved_row)
    refused(path, f"{FIELDS}: a sample's point is at more than one loadable vertex")


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_contact_fields_that_are_not_finite_are_refused(force_artifact, tmp_path, value):
    """The generic finite test runs on small_artifact, which has no contact fields."""
    path = copy(force_artifact, tmp_path)

    def put(f):
        f[len(f) // 2, 7] = value
        return f

    rewrite(path, f"{FIELDS}/fields", put)
    refused(path, f"{FIELDS}/fields has NaN or infinite values")


@pytest.mark.parametrize("name, symbol", [("vertices", "V"), ("sample_rows", "Lv")])
@pytest.mark.parametrize("bad", ["negative", "size"])
def test_contact_field_indices_out_of_range_are_refused(force_artifact, tmp_path, name, symbol,
                                                         bad):  # fmt: skip
    a = read_artifact(force_artifact)
    size = len(a["surface"]["vertices"]) if symbol == "V" else len(a[FIELDS]["vertices"])
    path = copy(force_artifact, tmp_path)

    def put(v):
        v[-1] = -1 if bad == "negative" else size
        return v

    rewrite(path, f"{FIELDS}/{name}", put)
    refused(path, rf"{FIELDS}/{name} has indices outside \[0, {size}\)")


# -- each sample's solved depth (samples/solved_depth, format 2.3) -----------------------------
SOLVED = "samples/solved_depth"


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d, grid: np.r_[0.5 * grid[1], d[1:]], "has values outside"),  # before a knot
        (lambda d, grid: np.r_[1.01 * grid[-1], d[1:]], "has values outside"),  # past the end
        (lambda d, grid: 0.9 * d, "no sample reaches the depth grid's end"),
        (lambda d, grid: np.r_[-d[0], d[1:]], "not positive"),
    ],
)
def test_solved_depths_off_the_grid_are_refused(force_artifact, tmp_path, change, match):
    path = copy(force_artifact, tmp_path)
    with h5py.File(path, "r") as f:
        grid = f["samples/depth"][()]
    rewrite(path, SOLVED, lambda d: change(d, grid))
    refused(path, f"{SOLVED}.*{match}|{match}")


def test_without_solved_depths_every_sample_is_solved_to_the_grids_end(force_artifact, tmp_path):
    """A 2.2 file (the dataset removed): every sample's solved depth is the grid's end, so no
    depth on the grid is flagged as extrapolated, and the forces are the same."""
    from hapticrom.online.simulator import Simulator

    path = copy(force_artifact, tmp_path)

    def strip(f):
        del f[SOLVED]
        f.attrs["format_version"] = np.array([2, 2], dtype=np.int64)
        f["samples"].attrs["version"] = np.array([2, 1], dtype=np.int64)

    mutate(path, strip)
    old, new = load(path, isolate=False), load(force_artifact, isolate=False)
    end = old.depth_step * (old.force.shape[1] - 1)
    np.testing.assert_array_equal(old.solved_depth, end)
    assert old.trained_depth == end and new.trained_depth < end
    a, b = Simulator(old, response="curves"), Simulator(new, response="curves")
    for point in old.sample_points:
        a.set_contact(point)
        b.set_contact(point)
        d = -0.999 * end * np.array(a.contact_normal)
        np.testing.assert_array_equal(a.step_displacement(d), b.step_displacement(d))
        assert not a.beyond_trained_depth


@pytest.mark.parametrize("value", [1e-12, 1e12, 0.0])
def test_contact_field_stiffness_outside_its_range_is_refused(force_artifact, tmp_path, value):
    """contact_fields/stiffness scales a contact outside the region: within 1e-9..1e9 N/mm
    (a ratio of two would overflow or vanish beyond), positive."""
    path = copy(force_artifact, tmp_path)

    def put(k):
        k[len(k) // 2] = value
        return k

    rewrite(path, "contact_fields/stiffness", put)
    refused(path, "contact_fields/stiffness (has values outside|has values that are not positive)")


@pytest.mark.parametrize("value", [1e-12, 1e12])
def test_edge_stiffness_outside_its_range_is_refused(force_artifact, tmp_path, value):
    """contact_fields/edge_stiffness (format 2.4) within the stiffness range, as the
    vertices' (the same value in both triangles of the edge, so that only the range fails)."""
    path = copy(force_artifact, tmp_path)
    rewrite(
        path,
        "contact_fields/edge_stiffness",
        np.full_like(read_artifact(force_artifact)["contact_fields"]["edge_stiffness"], value),
    )
    refused(path, "contact_fields/edge_stiffness has values outside")


def test_edge_stiffness_that_differs_across_an_edge_is_refused(force_artifact, tmp_path):
    """The two triangles of an edge hold one value (the quadratic is continuous across it):
    one of them changed by 1e-12 relative is refused."""
    path = copy(force_artifact, tmp_path)

    def put(k):
        k[0, 0] *= 1 + 1e-12
        return k

    rewrite(path, "contact_fields/edge_stiffness", put)
    refused(path, "contact_fields/edge_stiffness differs between the two triangles of an edge")


def test_edge_stiffness_needs_the_vertices_and_a_row_per_loadable_triangle(force_artifact,
                                                                          tmp_path):  # fmt: skip
    path = copy(force_artifact, tmp_path)
    mutate(path, lambda f: f["contact_fields"].__delitem__("stiffness"))
    refused(path, "contact_fields/edge_stiffness needs contact_fields/stiffness")
    path = copy(force_artifact, tmp_path, "short.h5")
    rewrite(path, "contact_fields/edge_stiffness", lambda k: k[:-1])
    refused(path, r"contact_fields/edge_stiffness has \d+ rows, expected one per loadable")


def test_a_file_without_edge_stiffness_reads_as_the_linear_interpolant(force_artifact, tmp_path):
    """A 2.3 file (no edge_stiffness): the midpoints are the corners' means, and the force
    outside the region is the linear interpolant's; here, where the trainer wrote the means
    too (no free border on the test cornea), exactly the 2.4 file's force."""
    from hapticrom.online.simulator import Simulator

    path = copy(force_artifact, tmp_path)
    mutate(path, lambda f: f["contact_fields"].__delitem__("edge_stiffness"))
    old, new = load(path, isolate=False), load(force_artifact, isolate=False)
    nodes = old.contact_fields["stiffness_nodes"]
    np.testing.assert_allclose(nodes[:, 3], 0.5 * (nodes[:, 1] + nodes[:, 2]), rtol=1e-15)
    np.testing.assert_array_equal(nodes, new.contact_fields["stiffness_nodes"])
    a, b = Simulator(old, response="curves"), Simulator(new, response="curves")
    points = old.vertices[np.unique(old.contact_fields["triangles"])]
    for point in points[~old.inside_trained_region(points)][:8]:
        a.set_contact(point)
        b.set_contact(point)
        d = -0.5 * old.trained_depth * np.array(a.contact_normal)
        np.testing.assert_array_equal(a.step_displacement(d), b.step_displacement(d))


def test_a_curve_that_is_not_linear_beyond_its_solved_depth_is_refused(force_artifact, tmp_path):
    """A file claiming a sample (a ring sample; the centre is the deepest) was solved to its
    first knot only: its stored curve beyond is the cubic through its solves."""
    path = copy(force_artifact, tmp_path)
    with h5py.File(path, "r") as f:
        first = f["samples/depth"][1]
    rewrite(path, SOLVED, lambda d: np.r_[d[0], first, d[2:]])  # sample 0 reaches the end
    refused(path, "sample 1's curve is not linear beyond its solved depth")


def test_a_continuation_steeper_than_the_solves_is_refused(force_artifact, tmp_path):
    """Beyond a (claimed) solved depth at knot 2, a linear force rising 10 times the
    steepest solved secant: where no sweep looks, a soft place would feel it."""
    path = copy(force_artifact, tmp_path)
    with h5py.File(path, "r") as f:
        depth, force, c = (
            f["samples/depth"][()],
            f["samples/force"][()],
            f["samples/coefficients"][()],
        )
    steepest = np.max(np.diff(force[1, :3])) / depth[1]

    def steep(f):
        f[1, 3:] = f[1, 2] + 10 * steepest * (depth[3:] - depth[2])
        return f

    def straight(a):
        a[1, 3:] = a[1, 2] + np.outer(depth[3:] - depth[2], (c[1, 2] - c[1, 1]) / depth[1])
        return a

    rewrite(path, SOLVED, lambda d: np.r_[d[0], depth[2], d[2:]])
    rewrite(path, "samples/force", steep)
    rewrite(path, "samples/coefficients", straight)
    refused(path, "sample 1's force beyond its solved depth rises 10x its steepest solved")


def test_a_field_that_runs_away_at_the_grids_end_is_refused(force_artifact, tmp_path):
    """The deepest sample's coordinates at the grid's end times 1e6 (its own range: no
    linearity to check there): load's sweep takes the surface at the deepest solved depth."""
    path = copy(force_artifact, tmp_path)
    with h5py.File(path, "r") as f:
        deepest = int(np.argmax(f[SOLVED][()]))

    def huge(c):
        c[deepest, -1] *= 1e6
        return c

    rewrite(path, "samples/coefficients", huge)
    refused(path, "surface is not finite or beyond the simulator's limit")
