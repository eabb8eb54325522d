"""The reduced-model artifact: one HDF5 file that the trainer writes and the runtime reads.

The written specification is ``shared/ARTIFACT.md``; :data:`SCHEMA` below is
its machine-readable form (names, shapes, dtypes, units, value rules), used by
both the writer and the reader so they cannot disagree. numpy, h5py and json only.

Versioning (as zarr and anndata do): the root carries ``format = "hapticrom"``
and ``format_version = [major, minor]``; every group carries its ``type`` and
``version``. A reader refuses an unknown major version and names it; a newer
minor version only adds optional content, which an older reader ignores.

The file is a trust boundary: it comes from elsewhere and drives a haptic motor.
A whole-file SHA-256 in the HDF5 user block (``shared/envelope.py``) is checked
before HDF5 parses a byte; then only hard-linked groups and datasets stored
inside the file, with the schema's dtype, shape and units, are read; every
dataset's own digest is checked; every value the runtime uses is checked
against the rules of :mod:`hapticrom.shared.artifact_rules`. Any failure, of
any kind, is an :class:`ArtifactError` naming the dataset or attribute. The
writer writes a temporary file, reads it back with this reader and renames
it, so a crash or a writer bug never leaves a file that loads.
"""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hapticrom.shared.checksum import array_digest
from hapticrom.shared.envelope import MAX_BYTES, USERBLOCK, read_verified, seal
from hapticrom.shared.errors import ArtifactError, HapticromError
from hapticrom.shared.files import write_checksummed, write_hdf5_atomically
from hapticrom.shared.material_layout import PARAMETER_SIZE

__all__ = [
    "SCHEMA",
    "ROOT_ATTRS",
    "Artifact",
    "ArtifactError",
    "read_artifact",
    "with_group",
    "write_artifact",
]

FORMAT = "hapticrom"
# 1.1: the anm group; 1.2: the cutting group; 1.3: its pressure coupling;
# 1.4: the integrity envelope (whole-file digest in the user block), required by this reader;
# 2.0: the samples' triangulation on the surface replaces the plane chart (samples 2.0);
# 2.1: the tool's linear stiffness on a lattice of each sample triangle (samples 2.1);
# 2.2: the tool's linear surface field at the loadable vertices (contact_fields);
# 2.3: the depth grid to the deepest sample, each sample's solved depth (samples 2.2); the
# tool's linear stiffness at the loadable vertices (contact_fields 1.1);
# 2.4: and at the midpoints of the loadable triangles' edges (contact_fields 1.2);
# 2.5: the hyper-reduced physics of regions of the surface (hyperreduced);
# 2.6: the nodes its holders grip, P2's mid-side nodes too, and whether a holder keeps its
# patch's cupping (hyperreduced 1.1);
# 2.7: each region's check sample, the runtime's error indicator (hyperreduced 1.2).
# 2.8: a held region's holder patch and the force patterns it holds it in (hyperreduced 1.3).
FORMAT_VERSION = (2, 8)
# What a reader says about a file of another major version.
REREDUCE = (
    "re-reduce its campaign with this version: hapticrom reduce CAMPAIGN_DIR --out MODEL.h5 "
    "(the stored solves are reused; nothing is solved again)"
)


@dataclass(frozen=True)
class Field:
    """One dataset of the schema. ``shape`` uses symbols resolved per file (P, K, n, V, T, S...).

    ``checks``: value rules (``artifact_rules.FIELD_RULES``) on top of "finite", which every
    float dataset must be.
    """

    name: str
    dtype: str  # numpy kind: "f" float, "i" integer
    shape: tuple[str | int, ...]
    units: str
    meaning: str
    required: bool = True
    checks: tuple[str, ...] = ()


@dataclass(frozen=True)
class Attr:
    """One attribute of a group (or of the root). ``kind``: str, json, float, int, ints, floats."""

    name: str
    kind: str
    meaning: str
    required: bool = False
    checks: tuple[str, ...] = ()


@dataclass(frozen=True)
class Group:
    """One group of the schema: its name, type, version, datasets and attributes."""

    name: str
    type: str
    version: tuple[int, int]
    fields: tuple[Field, ...]
    required: bool = True
    attrs: tuple[Attr, ...] = field(default_factory=tuple)


ROOT_ATTRS: tuple[Attr, ...] = (
    Attr("format", "str", "the string hapticrom", required=True),
    Attr("format_version", "ints", "[major, minor]", required=True, checks=("pair",)),
    Attr("created", "str", "ISO 8601 time of writing (UTC)"),
    Attr("software", "json", "versions of the software that wrote it"),
    Attr("units", "json", "the unit system (mm, N, MPa)"),
    Attr("campaign", "json", "the training campaign's configuration"),
    Attr("description", "str", "free text"),
    Attr("sanity", "json", "physics sanity of the training: worst J, compression, jumps"),
)
GROUP_ATTRS: tuple[Attr, ...] = (
    Attr("type", "str", "the group's type", required=True),
    Attr("version", "ints", "the group's [major, minor]", required=True, checks=("pair",)),
)


def _fields(*rows, required: bool = True) -> tuple[Field, ...]:
    """Fields from (name, dtype, shape, units, meaning[, checks]) rows."""
    return tuple(Field(*row[:5], required=required, checks=tuple(row[5:])) for row in rows)


# One row per dataset, as the tables of ARTIFACT.md.
# fmt: off
SCHEMA: tuple[Group, ...] = (
    Group(
        "model",
        "contact-rom",
        (1, 0),
        (),
        attrs=(
            Attr("name", "str", "campaign name", True),
            Attr("mode", "str", "control of the training", True,
                 ("choice:displacement,force,sphere",)),  # fmt: skip
            Attr("contact_radius", "float", "tool tip radius (mm)", True, ("positive",)),
            Attr("surface_group", "str", "surface group the tool touches", True),
            Attr("material", "json", "law and parameters (MPa)", True),
            Attr("campaign_hash", "str", "SHA-256 of the campaign", True),
            Attr("mesh_file", "str", "the mesh trained on"),
            Attr("mesh_sha256", "str", "its SHA-256"),
            Attr("element", "str", "finite element of the training"),
            Attr("modes", "int", "modes per sample", checks=("positive",)),
            Attr("pod_method", "str", "POD method"),
            Attr("pod_inner_product", "str", "POD inner product"),
        ),
    ),
    Group(
        "surface",
        "surface-mesh",
        (1, 0),
        _fields(
            ("vertices", "f", ("V", 3), "mm", "reference positions of the surface vertices"),
            ("triangles", "i", ("T", 3), "1", "vertex indices, outward (counter-clockwise)",
             "index:V"),
            ("nodes", "i", ("V",), "1", "canonical node of each vertex (DOFs 3 i + c)",
             "nonnegative", "distinct"),
            ("groups", "i", ("T",), "1", "0 clamped, 1 loadable, 2 free", "choice:0,1,2"),
        ),
    ),
    Group(
        "samples",
        "contact-samples",
        (2, 2),
        _fields(
            ("points", "f", ("P", 3), "mm", "tool positions of the training samples"),
            ("normals", "f", ("P", 3), "1", "outward unit surface normals there", "unit"),
            ("triangles", "i", ("S", 3), "1",
             "the samples' triangles on the surface, outward (counter-clockwise)", "index:P"),
            ("indicator", "f", ("P",), "1",
             "leave-one-out relative force error of each sample from its neighbours",
             "nonnegative"),
            ("depth", "f", ("K",), "mm", "indentation grid, uniform, depth[0] = 0"),
            ("force", "f", ("P", "K"), "N", "normal contact force F_n at each depth (>= 0)",
             "nonnegative"),
            ("stiffness", "f", ("P", "K"), "N/mm", "d force / d depth (monotone cubic)",
             "nonnegative"),
            ("surface_basis", "f", ("P", "3V", "n"), "1", "POD basis rows at the vertices"),
            ("coefficients", "f", ("P", "K", "n"), "mm", "reduced coordinates at each depth"),
            ("reduced_stiffness", "f", ("P", "n", "n"), "N/mm", "A^T K0 A, reduced pressure",
             "symmetric"),
            ("contact_rows", "f", ("P", 3, "n"), "1", "mean basis rows at the contact nodes"),
            ("eigenvalues", "f", ("P", "M"), "mm^2", "POD eigenvalues (M snapshots)"),
        ) + _fields(
            # group version 2.1 (format 2.1): what the force curves are scaled by
            ("tool_stiffness", "f", ("S", "L"), "N/mm",
             "the tool's linear stiffness at each sample triangle's lattice points",
             "positive"),
            # group version 2.2 (format 2.3): where each sample's curve is its own solve
            ("solved_depth", "f", ("P",), "mm",
             "the depth each sample was solved to (beyond it its curve goes on linearly)",
             "positive"),
            required=False,
        ),
        attrs=(
            Attr("pressure_modes", "ints", "size of each reduced pressure basis"),
        ),
    ),
    Group(
        "grassmann",
        "grassmann-tangents",
        (1, 0),
        _fields(
            ("reference", "i", (), "1", "index of the reference sample", "index:P"),
            ("tangent_surface", "f", ("P", "3V", "n"), "1", "log-map tangents, surface rows"),
            ("gram_tangent_tangent", "f", ("P", "P", "n", "n"), "1", "Gamma_i^T Gamma_j"),
            ("gram_tangent_basis", "f", ("P", "P", "n", "n"), "1", "Gamma_i^T A_j"),
            ("gram_reference_basis", "f", ("P", "n", "n"), "1", "A_ref^T A_j"),
        ),
        required=False,
    ),
    Group(
        "anm",
        "anm-series",
        (1, 0),
        _fields(
            ("section_offsets", "i", ("P1",), "1", "sample i's sections: offsets[i]:[i+1]",
             "nonnegative"),
            ("a_max", "f", ("Z",), "1", "validity radius of each section (path parameter)",
             "positive"),
            ("depth", "f", ("Z", "N1"), "mm", "series of the depth in a, order 0..N"),
            ("force", "f", ("Z", "N1"), "N", "series of the normal contact force F_n"),
            ("coefficients", "f", ("Z", "N1", "n"), "mm", "series of the reduced coordinates"),
        ),
        required=False,
        attrs=(
            Attr("order", "int", "series order N", True, ("range:1,30",)),
            Attr("tolerance", "float", "validity criterion of a section", True, ("positive",)),
            Attr("residual_evaluations", "int", "cost of the series", checks=("nonnegative",)),
        ),
    ),
    Group(
        "cutting",
        "cut-region",
        (1, 1),
        _fields(
            ("nodes", "i", ("Rn",), "1", "canonical node of each region node",
             "nonnegative", "distinct"),
            ("coordinates", "f", ("Rn", 3), "mm", "reference positions of the region nodes"),
            ("cells", "i", ("Rc", 8), "1", "region hexahedra, region node indices", "index:Rn"),
            ("element_stiffness", "f", ("Rc", 24, 24), "N/mm", "cell matrices at K0", "symmetric"),
            ("basis", "f", ("3Rn", "G"), "1", "global POD basis rows at the region nodes"),
            ("fixed", "i", ("Rn",), "1", "1: node keeps the reduced field (boundary)",
             "choice:0,1"),
            ("reduced_stiffness", "f", ("G", "G"), "N/mm", "A^T K0 A, element pressure",
             "symmetric"),
        ) + _fields(
            # group version 1.1 (format 1.3): element-wise pressure, locking-free
            ("element_displacement_stiffness", "f", ("Rc", 24, 24), "N/mm", "cell K_uu",
             "symmetric"),
            ("element_pressure_coupling", "f", ("Rc", 24), "mm^2", "cell k_up"),
            ("element_pressure_stiffness", "f", ("Rc",), "mm^3/MPa", "cell k_pp (< 0)", "negative"),
            ("pressure_basis", "f", ("Rc", "Gp"), "1", "reduced pressure modes' cell values"),
            ("reduced_displacement_stiffness", "f", ("G", "G"), "N/mm", "A^T K_uu A", "symmetric"),
            ("reduced_pressure_coupling", "f", ("G", "Gp"), "mm^2", "A^T K_up P"),
            ("reduced_pressure_stiffness", "f", ("Gp", "Gp"), "mm^3/MPa", "P^T K_pp P",
             "symmetric"),
            required=False,
        ),
        required=False,
        attrs=(
            Attr("centre", "floats", "centre of the region (mm)", checks=("length:3",)),
            Attr("radius", "float", "radius of the region (mm)", checks=("positive",)),
            Attr("patch_layers", "int", "rings of cells in a cut patch", True, ("range:1,64",)),
            Attr("cut_force", "float", "blade force that cuts (N)", True, ("positive",)),
            Attr("cells_in_region", "int", "region cells", checks=("positive",)),
        ),
    ),
    Group(
        "contact_fields",
        "linear-contact-fields",
        (1, 2),
        _fields(
            ("vertices", "i", ("Lv",), "1", "the surface vertex the tool is centred at, a row",
             "index:V", "distinct"),
            ("fields", "f", ("Lv", "3V"), "1",
             "the linear surface displacement per unit depth of the tool there"),
            ("sample_rows", "i", ("P",), "1", "the row of each sample", "index:Lv", "distinct"),
        ) + _fields(
            # group version 1.1 (format 2.3): what a contact outside the region is scaled by
            ("stiffness", "f", ("Lv",), "N/mm", "the tool's linear stiffness there",
             "positive"),
            # group version 1.2 (format 2.4): with the vertices', a quadratic interpolant
            ("edge_stiffness", "f", ("Tl", 3), "N/mm",
             "the same at the midpoint of each loadable triangle's edge opposite each corner",
             "positive"),
            required=False,
        ),
        required=False,
    ),
    Group(
        "hyperreduced",
        "ecsw-physics",
        (1, 3),
        _fields(
            ("centres", "f", ("Hr", 3), "mm", "the centre of each region"),
            ("radii", "f", ("Hr",), "mm", "how far from its centre a region's tools may be",
             "positive"),
            ("element_offsets", "i", ("Hr1",), "1",
             "region r's sampled elements: rows offsets[r]:[r+1]", "nonnegative"),
            ("element_nodes", "f", ("He", "Hk", 3), "mm",
             "the sampled elements' reference nodes (Basix order)"),
            ("weights", "f", ("He",), "1", "ECSW's weight of each sampled element", "positive"),
            ("basis_rows", "f", ("He", "3Hk", "Hq"), "1",
             "the region's displacement basis at each element's nodes"),
            ("pressure_rows", "f", ("He", "Hp"), "1",
             "the region's pressure basis at each element's cell"),
            ("parameters", "f", ("He", PARAMETER_SIZE), "packed",
             "each element's law and parameters (shared/material_layout.py)"),
            ("constant_tangent", "f", ("Hr", "Hs", "Hs"), "N/mm",
             "each region's constant part of the reduced mixed tangent", "symmetric"),
            ("surface_basis", "f", ("Hr", "3V", "Hq"), "1",
             "each region's displacement basis at the surface vertices"),
            ("load_offsets", "i", ("Hr1",), "1",
             "region r's load vertices: rows offsets[r]:[r+1]", "nonnegative"),
            ("load_vertices", "i", ("Hl",), "1", "a surface vertex where a tool may press",
             "index:V"),
            ("tool_loads", "f", ("Hl", 3, "Hq"), "1",
             "the reduced load of a unit force (N) along x, y, z of the tool centred there"),
        ) + _fields(
            # group version 1.1 (format 2.6): the nodes a holder grips, mid-side ones too
            ("grip_offsets", "i", ("Hr1",), "1",
             "region r's grip nodes: rows offsets[r]:[r+1]", "nonnegative"),
            ("grip_nodes", "f", ("Hg", 3), "mm", "a node of the loadable facets a holder may grip"),
            ("grip_rows", "f", ("Hg", 3, "Hq"), "1",
             "the region's displacement basis at that node"),
            required=False,
        ) + _fields(
            # group version 1.2 (format 2.7): the error indicator's second sample
            ("check_element_offsets", "i", ("Hr1",), "1",
             "region r's check elements: rows offsets[r]:[r+1]", "nonnegative"),
            ("check_element_nodes", "f", ("Hc", "Hk", 3), "mm",
             "the check sample's reference nodes (Basix order)"),
            ("check_weights", "f", ("Hc",), "1", "ECSW's weight of each check element",
             "positive"),
            ("check_basis_rows", "f", ("Hc", "3Hk", "Hq"), "1",
             "the region's displacement basis at each check element's nodes"),
            ("check_pressure_rows", "f", ("Hc", "Hp"), "1",
             "the region's pressure basis at each check element's cell"),
            ("check_parameters", "f", ("Hc", PARAMETER_SIZE), "packed",
             "each check element's law and parameters"),
            ("check_constant_tangent", "f", ("Hr", "Hs", "Hs"), "N/mm",
             "each region's constant tangent with the check sample", "symmetric"),
            required=False,
        ) + _fields(
            # group version 1.3 (format 2.8): a held region's holder and its hold patterns
            ("hold_offsets", "i", ("Hr1",), "1",
             "region r's hold nodes: rows offsets[r]:[r+1] (none: no held holder)",
             "nonnegative"),
            ("hold_nodes", "i", ("Hh",), "1",
             "a node the region's holder grips: a row of the region's grip nodes",
             "nonnegative"),
            ("hold_reactions", "f", ("Hh", 3, "Hm"), "1",
             "the force patterns the holder holds its patch in, orthonormal over its DOFs"),
            ("hold_ranks", "i", ("Hr",), "1", "how many of hold_reactions' columns are the "
             "region's (the rest zero)", "nonnegative"),  # fmt: skip
            required=False,
        ),
        required=False,
        attrs=(
            Attr("cell", "str", "the elements' cell", True, ("choice:hexahedron,tetrahedron",)),
            Attr("hold_stiffness", "float", "a holder's penalty of its patch's rigid motion "
                 "(N/mm)", True, ("positive",)),  # fmt: skip
            Attr("tolerance", "float", "ECSW's tolerance", checks=("positive",)),
            Attr("holder_cupping", "int", "1: a holder also keeps its patch's cupping (the "
                 "regions' bases carry its responses)", checks=("range:0,1",)),  # fmt: skip
        ),
    ),
    Group(
        "global",
        "global-basis",
        (1, 0),
        _fields(
            ("surface_basis", "f", ("3V", "G"), "1", "global POD basis rows at the vertices"),
            ("eigenvalues", "f", ("Mg",), "mm^2", "global POD eigenvalues"),
            ("reduced_stiffness", "f", ("G", "G"), "N/mm", "A^T K0 A, reduced pressure",
             "symmetric"),
        ),
        required=False,
    ),
)
# fmt: on
# fmt: on


def _encode(value):
    if isinstance(value, dict | list | tuple) and not (
        isinstance(value, tuple | list) and all(isinstance(v, int | float) for v in value)
    ):
        return json.dumps(value, default=str)
    return value


# -- writing -------------------------------------------------------------------------
def write_artifact(path: str | Path, content: dict[str, dict[str, Any]], root_attrs: dict) -> None:
    """Write ``content`` (group -> {dataset name -> array, "attrs" -> dict}) atomically.

    Validates shapes against :data:`SCHEMA` first, then writes a temporary file,
    seals it (the envelope), reads it back with :func:`read_artifact` (so a
    writer bug cannot produce a file the reader refuses), renames it and fsyncs
    the directory. On any failure nothing is left behind and the target is
    unchanged; an I/O failure (a full disk, a read-only directory) is a
    :class:`HapticromError` naming the file.
    """
    path = Path(path)
    _validate_content(content)

    def sealed_and_readable(tmp: Path) -> None:
        seal(tmp)
        read_artifact(tmp)

    try:
        write_hdf5_atomically(
            path,
            lambda f: _write_groups(f, content, root_attrs),
            check=sealed_and_readable,
            userblock_size=USERBLOCK,
        )
    except OSError as exc:
        raise HapticromError(f"cannot write the artifact {path}: {exc.strerror or exc}") from None


def with_group(artifact: Artifact, name: str, group: dict) -> tuple[dict, dict]:
    """(content, root attributes) for :func:`write_artifact`: ``artifact``'s groups with
    ``group`` (datasets and "attrs") as ``name`` (replacing one of that name)."""
    if name not in {g.name for g in SCHEMA}:
        raise ArtifactError(f"the schema has no group {name}")
    content = {g: {**arrays, "attrs": dict(artifact.group_attrs.get(g, {}))}
               for g, arrays in artifact.groups.items()}  # fmt: skip
    content[name] = group
    root = {k: v for k, v in artifact.attrs.items() if k not in ("format", "format_version")}
    return content, root


def _write_groups(f: h5py.File, content: dict, root_attrs: dict) -> None:
    f.attrs["format"] = FORMAT
    f.attrs["format_version"] = np.asarray(FORMAT_VERSION, dtype=np.int64)
    for key, value in root_attrs.items():
        f.attrs[key] = _encode(value)
    for group in SCHEMA:
        if group.name not in content:
            continue
        g = f.create_group(group.name)
        g.attrs["type"] = group.type
        g.attrs["version"] = np.asarray(group.version, dtype=np.int64)
        for key, value in content[group.name].get("attrs", {}).items():
            g.attrs[key] = _encode(value)
        for spec in group.fields:
            if not spec.required and spec.name not in content[group.name]:
                continue
            array = content[group.name][spec.name]
            write_checksummed(g, spec.name, array, {"units": spec.units})


def _resolve(shape, symbols: dict[str, int], where: str) -> tuple[int, ...]:
    out = []
    for dim in shape:
        if isinstance(dim, int):
            out.append(dim)
        elif dim[:1] == "3" and dim[1:] in symbols:
            out.append(3 * symbols[dim[1:]])
        elif dim in symbols:
            out.append(symbols[dim])
        else:
            raise ArtifactError(f"{where}: unknown dimension {dim}")
    return tuple(out)


_DTYPES = {  # what a reader accepts: plain little-endian numbers, nothing else
    "f": ("<f4", "<f8"),
    "i": ("|i1", "<i2", "<i4", "<i8", "|u1", "<u2", "<u4"),
}


def _check_meta(group: Group, spec: Field, dtype: np.dtype, shape, symbols, where) -> None:
    """A dataset's dtype and shape against the schema (resolving new symbols from it)."""
    name = f"{group.name}/{spec.name}"
    if np.dtype(dtype).str not in _DTYPES[spec.dtype]:
        raise ArtifactError(
            f"{where}: {name} has dtype {dtype}, expected one of {', '.join(_DTYPES[spec.dtype])}"
        )
    if len(shape) != len(spec.shape):
        raise ArtifactError(f"{where}: {name} has shape {shape}, expected rank {len(spec.shape)}")
    for dim, size in zip(spec.shape, shape, strict=True):
        if isinstance(dim, str) and dim not in symbols and dim[:1] != "3":
            symbols[dim] = int(size)
    expected = _resolve(spec.shape, symbols, where)
    if tuple(shape) != expected:
        raise ArtifactError(f"{where}: {name} has shape {tuple(shape)}, expected {expected}")


def _validate_content(content: dict) -> None:
    symbols: dict[str, int] = {}
    for group in SCHEMA:
        if group.name not in content:
            if group.required:
                raise ArtifactError(f"artifact content lacks the group {group.name}")
            continue
        for spec in group.fields:
            if spec.name not in content[group.name]:
                if spec.required:
                    raise ArtifactError(f"artifact content lacks {group.name}/{spec.name}")
                continue
            a = np.asarray(content[group.name][spec.name])
            _check_meta(group, spec, a.dtype, a.shape, symbols, "artifact content")


# -- reading -------------------------------------------------------------------------
@dataclass
class Artifact:
    """A loaded, verified artifact: arrays by group, attributes by group, root attributes.

    Only what the schema names is read: unknown datasets and attributes (a newer
    minor version's) are ignored.
    """

    path: Path
    version: tuple[int, int]
    attrs: dict[str, Any]
    groups: dict[str, dict[str, np.ndarray]]
    group_attrs: dict[str, dict[str, Any]]
    symbols: dict[str, int] = field(default_factory=dict)

    def __getitem__(self, name: str) -> dict[str, np.ndarray]:
        return self.groups[name]


def read_artifact(path: str | Path, max_bytes: int = MAX_BYTES, isolate: bool = False) -> Artifact:
    """Load and verify an artifact; raise :class:`ArtifactError` naming what is wrong.

    Nothing else escapes: whatever a damaged or hostile file makes h5py or numpy
    raise is reported as an ``ArtifactError`` naming the dataset or attribute
    being read. ``isolate``: parse the verified bytes in a child process first
    (:func:`check_isolated`), so that a crafted HDF5 structure that crashes
    HDF5's C code kills the child, not this process.
    """
    path = Path(path)
    data = read_verified(path, max_bytes)
    if isolate:
        check_isolated(data, path)
    return parse_verified(data, path)


def parse_verified(data: bytes, path: Path, values: bool = True) -> Artifact:
    """The artifact in ``data`` (bytes whose envelope checked out), checked value by value
    (``values=False``: the structure only, what HDF5 parses)."""
    from hapticrom.shared.artifact_rules import check_values

    reading = _Reading(path, len(data))
    try:
        with h5py.File(io.BytesIO(data), "r") as f:
            artifact = reading.artifact(f)
        reading.where = "values"
        if values:
            check_values(artifact)
    except ArtifactError:
        raise
    except Exception as exc:  # noqa: BLE001 - the promise: one error type, naming the culprit
        raise ArtifactError(
            f"{path}: {reading.where} cannot be read ({type(exc).__name__}: {exc})"
        ) from None
    return artifact


# The child reads the bytes from its standard input: the very bytes this process verified and
# will parse (never the path again), so the child's verdict holds for them.
CHILD = (
    "import sys; from pathlib import Path; from hapticrom.shared import artifact as a\n"
    "try: a.parse_verified(sys.stdin.buffer.read(), Path(sys.argv[1]), values=False)\n"
    "except a.ArtifactError as e: sys.stderr.write(str(e)); sys.exit(2)"
)
CHILD_TIMEOUT = 300.0  # seconds; the demo model takes about 1 s


def check_isolated(data: bytes, path: Path, command: list[str] | None = None) -> None:
    """Parse ``data`` in a child Python process: its ``ArtifactError`` is raised here; its death
    by a signal (a segfault in HDF5 on a crafted structure) or a hang is an ``ArtifactError``
    too. HDF5 parses identical bytes identically, so what the child survived this process can
    parse. Needs an interpreter at ``sys.executable`` (an embedding host may have none: it
    loads with ``isolate=False``)."""
    command = command or [sys.executable, "-c", CHILD, str(path)]
    try:
        child = subprocess.run(command, input=data, capture_output=True, timeout=CHILD_TIMEOUT)
    except subprocess.TimeoutExpired:
        raise ArtifactError(f"{path}: reading it hung for {CHILD_TIMEOUT:g} s") from None
    except OSError as exc:
        raise HapticromError(
            f"cannot start a process to check {path} ({exc.strerror}); "
            "load it in this process with isolate=False"
        ) from None
    if child.returncode == 2:
        raise ArtifactError(child.stderr.decode("utf-8", errors="replace").strip())
    if child.returncode < 0:
        raise ArtifactError(
            f"{path}: its HDF5 structure crashed the reading process (signal {-child.returncode})"
        )
    if child.returncode != 0:
        tail = child.stderr.decode("utf-8", errors="replace").strip().splitlines()[-1:]
        raise ArtifactError(f"{path}: the reading process failed ({' '.join(tail)})")


class _Reading:
    """One pass over a verified file: structure first, then the data."""

    def __init__(self, path: Path, size: int):
        self.path, self.size = path, size
        self.where = "the file"  # what is being read, for the error message

    def fail(self, message: str) -> ArtifactError:
        return ArtifactError(f"{self.path}: {message}")

    def artifact(self, f: h5py.File) -> Artifact:
        attrs = self.attributes(f, ROOT_ATTRS, "root")
        if attrs["format"] != FORMAT:
            raise self.fail("not a hapticrom artifact (format attribute)")
        version = tuple(attrs["format_version"])
        if version[0] != FORMAT_VERSION[0]:
            raise self.fail(
                f"artifact format version {version[0]}.{version[1]} is not supported "
                f"(this runtime reads major version {FORMAT_VERSION[0]}); {REREDUCE}"
            )
        handles, group_attrs, symbols = {}, {}, {}
        for group in SCHEMA:  # every shape and storage checked before any data is read
            g = self.member(f, group.name, h5py.Group, group.required)
            if g is None:
                continue
            group_attrs[group.name] = self.group_attributes(g, group)
            handles[group.name] = {
                spec.name: dset
                for spec in group.fields
                if (dset := self.dataset(g, group, spec, symbols)) is not None
            }
        groups = {
            name: {key: self.read(name, key, dset) for key, dset in datasets.items()}
            for name, datasets in handles.items()
        }
        return Artifact(self.path, version, attrs, groups, group_attrs, symbols)

    def member(self, parent, name: str, kind, required: bool):
        """``parent[name]`` if it is a hard link to a ``kind`` (group or dataset)."""
        self.where = f"{parent.name.rstrip('/')}/{name}".lstrip("/")
        link = parent.get(name, getlink=True)
        if link is None:
            if required:
                what = "dataset" if kind is h5py.Dataset else "group"
                raise self.fail(f"required {what} {self.where} is missing")
            return None
        if not isinstance(link, h5py.HardLink):
            raise self.fail(f"{self.where} is a {type(link).__name__}: only data inside the file")
        obj = parent[name]
        if not isinstance(obj, kind):
            raise self.fail(f"{self.where} is not a {kind.__name__.lower()}")
        return obj

    def group_attributes(self, g: h5py.Group, group: Group) -> dict:
        attrs = self.attributes(g, GROUP_ATTRS + group.attrs, group.name)
        if attrs["type"] != group.type:
            raise self.fail(
                f"group {group.name} has type {attrs['type']!r}, expected {group.type!r}"
            )
        major, minor = attrs.pop("version")
        if major != group.version[0]:
            raise self.fail(
                f"group {group.name} version {major}.{minor} is not supported "
                f"(this runtime reads {group.version[0]}.x)"
            )
        attrs.pop("type")
        return attrs

    def attributes(self, obj, specs: tuple[Attr, ...], owner: str) -> dict:
        from hapticrom.shared.artifact_rules import attribute_value

        out = {}
        for spec in specs:
            self.where = f"attribute {spec.name} of {owner}"
            if spec.name not in obj.attrs:
                if spec.required:
                    raise self.fail(f"{owner} lacks the attribute {spec.name}")
                continue
            out[spec.name] = attribute_value(obj.attrs, spec, self.fail, self.where)
        return out

    def dataset(self, g: h5py.Group, group: Group, spec: Field, symbols: dict):
        dset = self.member(g, spec.name, h5py.Dataset, spec.required)
        if dset is None:
            return None
        name = self.where
        if dset.is_virtual or dset.external:
            raise self.fail(f"{name} is stored outside the file")
        plist = dset.id.get_create_plist()
        if plist.get_nfilters() or plist.get_layout() not in (
            h5py.h5d.CONTIGUOUS,
            h5py.h5d.COMPACT,
        ):
            raise self.fail(f"{name} is chunked or filtered (the writer stores data contiguously)")
        _check_meta(group, spec, dset.dtype, dset.shape, symbols, str(self.path))
        nbytes = math.prod(int(d) for d in dset.shape) * dset.dtype.itemsize  # no int64 wrap
        stored = dset.id.get_storage_size()
        if nbytes > self.size or (plist.get_layout() == h5py.h5d.CONTIGUOUS and stored != nbytes):
            raise self.fail(f"{name} declares {nbytes} bytes but stores {stored}")
        units = _text(dset.attrs.get("units"))
        if units != spec.units:
            raise self.fail(f"{name} has units {units!r}, expected {spec.units!r}")
        return dset

    def read(self, group: str, name: str, dset: h5py.Dataset) -> np.ndarray:
        self.where = f"{group}/{name}"
        array = dset[()]
        if array_digest(array) != _text(dset.attrs.get("sha256")):
            raise self.fail(f"dataset {group}/{name} fails its checksum (damaged)")
        array = np.asarray(array)
        array.setflags(write=False)  # what the runtime shares between simulators
        return array


def _text(value) -> str | None:
    """A string attribute as str (h5py returns str or bytes), anything else None."""
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    return value if isinstance(value, str) else None
