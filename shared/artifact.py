"""The reduced-model artifact: one HDF5 file that the trainer writes and the runtime reads.

The written specification is ``shared/ARTIFACT.md``; :data:`SCHEMA` below is
its machine-readable form (names, shapes, dtypes, units), used by both the
writer and the reader so they cannot disagree. numpy, h5py and json only.

Versioning (as zarr and anndata do): the root carries ``format = "hapticrom"``
and ``format_version = [major, minor]``; every group carries its ``type`` and
``version``. A reader refuses an unknown major version and names it; a newer
minor version only adds optional content, which an older reader ignores.
Every dataset carries the SHA-256 of its contents (``sha256`` attribute),
verified on load: a truncated or bit-flipped file raises, naming the dataset.
The writer writes a temporary file and renames it, so a crash never leaves a
file that loads.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hapticrom.shared.checksum import array_digest
from hapticrom.shared.errors import HapticromError

FORMAT = "hapticrom"
FORMAT_VERSION = (1, 3)  # 1.1: the anm group; 1.2: the cutting group; 1.3: its pressure coupling


class ArtifactError(HapticromError):
    """A file is not a valid hapticrom artifact; the message names the problem."""


@dataclass(frozen=True)
class Field:
    """One dataset of the schema. ``shape`` uses symbols resolved per file (P, K, n, V, T, S...)."""

    name: str
    dtype: str  # numpy kind: "f" float, "i" integer
    shape: tuple[str | int, ...]
    units: str
    meaning: str
    required: bool = True


@dataclass(frozen=True)
class Group:
    name: str
    type: str
    version: tuple[int, int]
    fields: tuple[Field, ...]
    required: bool = True
    attrs: tuple[str, ...] = field(default_factory=tuple)


SCHEMA: tuple[Group, ...] = (
    Group(
        "model",
        "contact-rom",
        (1, 0),
        (),
        attrs=("name", "mode", "contact_radius", "surface_group", "material", "campaign_hash"),
    ),
    Group(
        "surface",
        "surface-mesh",
        (1, 0),
        (
            Field("vertices", "f", ("V", 3), "mm", "reference positions of the surface vertices"),
            Field("triangles", "i", ("T", 3), "1", "vertex indices, outward (counter-clockwise)"),
            Field("nodes", "i", ("V",), "1", "canonical node of each vertex (DOFs 3 i + c)"),
            Field("groups", "i", ("T",), "1", "0 clamped, 1 loadable, 2 free"),
        ),
    ),
    Group(
        "samples",
        "contact-samples",
        (1, 0),
        (
            Field("points", "f", ("P", 3), "mm", "tool positions of the training samples"),
            Field("normals", "f", ("P", 3), "1", "outward unit surface normals there"),
            Field("chart_origin", "f", (3,), "mm", "origin of the 2-D interpolation chart"),
            Field("chart_axes", "f", (2, 3), "1", "orthonormal chart axes (chart = axes (x - o))"),
            Field("chart_points", "f", ("P", 2), "mm", "samples in chart coordinates"),
            Field("triangles", "i", ("S", 3), "1", "Delaunay triangles of the chart points"),
            Field("depth", "f", ("K",), "mm", "indentation grid, uniform, depth[0] = 0"),
            Field("force", "f", ("P", "K"), "N", "normal reaction force on the tool at each depth"),
            Field("stiffness", "f", ("P", "K"), "N/mm", "d force / d depth (monotone cubic)"),
            Field("surface_basis", "f", ("P", "3V", "n"), "1", "POD basis rows at the vertices"),
            Field("coefficients", "f", ("P", "K", "n"), "mm", "reduced coordinates at each depth"),
            Field("reduced_stiffness", "f", ("P", "n", "n"), "N/mm", "A^T K0 A, reduced pressure"),
            Field("contact_rows", "f", ("P", 3, "n"), "1", "mean basis rows at the contact nodes"),
            Field("eigenvalues", "f", ("P", "M"), "mm^2", "POD eigenvalues (M snapshots)"),
        ),
    ),
    Group(
        "grassmann",
        "grassmann-tangents",
        (1, 0),
        (
            Field("reference", "i", (), "1", "index of the reference sample"),
            Field("tangent_surface", "f", ("P", "3V", "n"), "1", "log-map tangents, surface rows"),
            Field("gram_tangent_tangent", "f", ("P", "P", "n", "n"), "1", "Gamma_i^T Gamma_j"),
            Field("gram_tangent_basis", "f", ("P", "P", "n", "n"), "1", "Gamma_i^T A_j"),
            Field("gram_reference_basis", "f", ("P", "n", "n"), "1", "A_ref^T A_j"),
        ),
        required=False,
    ),
    Group(
        "anm",
        "anm-series",
        (1, 0),
        (
            Field("section_offsets", "i", ("P1",), "1", "sample i's sections: offsets[i]:[i+1]"),
            Field("a_max", "f", ("Z",), "1", "validity radius of each section (path parameter)"),
            Field("depth", "f", ("Z", "N1"), "mm", "series of the depth in a, order 0..N"),
            Field("force", "f", ("Z", "N1"), "N", "series of the normal force on the tool"),
            Field("coefficients", "f", ("Z", "N1", "n"), "mm", "series of the reduced coordinates"),
        ),
        required=False,
        attrs=("order", "tolerance"),
    ),
    Group(
        "cutting",
        "cut-region",
        (1, 1),
        (
            Field("nodes", "i", ("Rn",), "1", "canonical node of each region node"),
            Field("coordinates", "f", ("Rn", 3), "mm", "reference positions of the region nodes"),
            Field("cells", "i", ("Rc", 8), "1", "region hexahedra, region node indices"),
            Field("element_stiffness", "f", ("Rc", 24, 24), "N/mm", "cell matrices at K0"),
            Field("basis", "f", ("3Rn", "G"), "1", "global POD basis rows at the region nodes"),
            Field("fixed", "i", ("Rn",), "1", "1: node keeps the reduced field (boundary)"),
            Field("reduced_stiffness", "f", ("G", "G"), "N/mm", "A^T K0 A, element pressure"),
            # 1.1 (format 1.3): an element-wise pressure, for a locking-free coupling.
            *(
                Field(name, "f", shape, units, meaning, required=False)
                for name, shape, units, meaning in (
                    ("element_displacement_stiffness", ("Rc", 24, 24), "N/mm", "cell K_uu"),
                    ("element_pressure_coupling", ("Rc", 24), "mm^2", "cell k_up"),
                    ("element_pressure_stiffness", ("Rc",), "mm^3/MPa", "cell k_pp (< 0)"),
                    ("pressure_basis", ("Rc", "Gp"), "1", "reduced pressure modes' cell values"),
                    ("reduced_displacement_stiffness", ("G", "G"), "N/mm", "A^T K_uu A"),
                    ("reduced_pressure_coupling", ("G", "Gp"), "mm^2", "A^T K_up P"),
                    ("reduced_pressure_stiffness", ("Gp", "Gp"), "mm^3/MPa", "P^T K_pp P"),
                )
            ),
        ),
        required=False,
        attrs=("patch_layers", "cut_force"),
    ),
    Group(
        "global",
        "global-basis",
        (1, 0),
        (
            Field("surface_basis", "f", ("3V", "G"), "1", "global POD basis rows at the vertices"),
            Field("eigenvalues", "f", ("Mg",), "mm^2", "global POD eigenvalues"),
            Field("reduced_stiffness", "f", ("G", "G"), "N/mm", "A^T K0 A, reduced pressure"),
        ),
        required=False,
    ),
)


def _encode(value):
    if isinstance(value, dict | list | tuple) and not (
        isinstance(value, tuple | list) and all(isinstance(v, int | float) for v in value)
    ):
        return json.dumps(value, default=str)
    return value


def write_artifact(path: str | Path, content: dict[str, dict[str, Any]], root_attrs: dict) -> None:
    """Write ``content`` (group -> {dataset name -> array, "attrs" -> dict}) atomically.

    Validates against :data:`SCHEMA` first, so a writer bug cannot produce a
    file the reader refuses.
    """
    path = Path(path)
    _validate_content(content)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    with h5py.File(tmp, "w") as f:
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
                array = np.asarray(content[group.name][spec.name])
                dset = g.create_dataset(spec.name, data=array)
                dset.attrs["units"] = spec.units
                dset.attrs["sha256"] = array_digest(array)
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)


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


def _check_fields(group: Group, arrays: dict[str, np.ndarray], symbols: dict[str, int], where):
    for spec in group.fields:
        if not spec.required and spec.name not in arrays:
            continue
        if spec.name not in arrays:
            raise ArtifactError(f"{where}: required dataset {group.name}/{spec.name} is missing")
        a = arrays[spec.name]
        if a.dtype.kind not in ("iu" if spec.dtype == "i" else spec.dtype):
            raise ArtifactError(
                f"{where}: {group.name}/{spec.name} has dtype {a.dtype}, expected kind {spec.dtype}"
            )
        for dim, size in zip(spec.shape, a.shape, strict=False):
            if isinstance(dim, str) and dim not in symbols and dim[:1] != "3":
                symbols[dim] = size
        expected = _resolve(spec.shape, symbols, where)
        if a.shape != expected:
            raise ArtifactError(
                f"{where}: {group.name}/{spec.name} has shape {a.shape}, expected {expected}"
            )


def _validate_content(content: dict) -> None:
    symbols: dict[str, int] = {}
    for group in SCHEMA:
        if group.name not in content:
            if group.required:
                raise ArtifactError(f"artifact content lacks the group {group.name}")
            continue
        arrays = {k: np.asarray(v) for k, v in content[group.name].items() if k != "attrs"}
        _check_fields(group, arrays, symbols, "artifact content")


@dataclass
class Artifact:
    """A loaded, verified artifact: arrays by group, attributes by group, root attributes."""

    path: Path
    version: tuple[int, int]
    attrs: dict[str, Any]
    groups: dict[str, dict[str, np.ndarray]]
    group_attrs: dict[str, dict[str, Any]]

    def __getitem__(self, name: str) -> dict[str, np.ndarray]:
        return self.groups[name]


def _decode(value):
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value[:1] in "[{":
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return value


def read_artifact(path: str | Path) -> Artifact:
    """Load and verify an artifact; raise :class:`ArtifactError` naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"artifact {path} not found")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ArtifactError(
            f"{path} is not a readable HDF5 file (truncated or damaged?): {exc}"
        ) from None
    with f:
        if f.attrs.get("format") != FORMAT:
            raise ArtifactError(f"{path} is not a hapticrom artifact (format attribute missing)")
        version = tuple(int(v) for v in np.asarray(f.attrs.get("format_version", (0, 0))))
        if version[0] != FORMAT_VERSION[0]:
            raise ArtifactError(
                f"{path}: artifact format version {version[0]}.{version[1]} is not supported "
                f"(this runtime reads major version {FORMAT_VERSION[0]})"
            )
        groups, group_attrs, symbols = {}, {}, {}
        for group in SCHEMA:
            if group.name not in f:
                if group.required:
                    raise ArtifactError(f"{path}: required group {group.name} is missing")
                continue
            g = f[group.name]
            if g.attrs.get("type") != group.type:
                raise ArtifactError(
                    f"{path}: group {group.name} has type {g.attrs.get('type')!r}, "
                    f"expected {group.type!r}"
                )
            gversion = tuple(int(v) for v in np.asarray(g.attrs.get("version", (0, 0))))
            if gversion[0] != group.version[0]:
                raise ArtifactError(
                    f"{path}: group {group.name} version {gversion[0]}.{gversion[1]} is not "
                    f"supported (this runtime reads {group.version[0]}.x)"
                )
            for key in group.attrs:
                if key not in g.attrs:
                    raise ArtifactError(f"{path}: group {group.name} lacks attribute {key}")
            arrays = {}
            for spec in group.fields:
                if not spec.required and spec.name not in g:
                    continue
                if spec.name not in g:
                    raise ArtifactError(
                        f"{path}: required dataset {group.name}/{spec.name} is missing"
                    )
                dset = g[spec.name]
                try:
                    array = dset[()]
                except OSError as exc:
                    raise ArtifactError(
                        f"{path}: dataset {group.name}/{spec.name} cannot be read ({exc})"
                    ) from None
                if array_digest(array) != dset.attrs.get("sha256"):
                    raise ArtifactError(
                        f"{path}: dataset {group.name}/{spec.name} fails its checksum (damaged)"
                    )
                arrays[spec.name] = array
            _check_fields(group, arrays, symbols, str(path))
            groups[group.name] = arrays
            group_attrs[group.name] = {k: _decode(v) for k, v in g.attrs.items()}
        attrs = {k: _decode(v) for k, v in f.attrs.items()}
    return Artifact(path, version, attrs, groups, group_attrs)
