"""VTK XML files for ParaView from numpy arrays: PolyData (``.vtp``) and collections (``.pvd``).

numpy and the standard library only, so the runtime (``pip install hapticrom``) can write
them without VTK or meshio. Data arrays are inline binary (VTK XML format 1.0,
``header_type="UInt64"``): each is the base64 of an 8-byte little-endian byte count
followed by the array's little-endian bytes, uncompressed. Unlike raw appended data, a
file stays well-formed XML, so any XML parser reads it back (``xml.etree``); base64 costs a
third more space than raw bytes.

Cells of a PolyData piece are ordered as VTK orders them: verts, then polys; cell data
arrays run over that order.
"""

from __future__ import annotations

import base64
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

# numpy dtype -> VTK XML type name; anything else is converted to float64 or int64.
_VTK_TYPES = {
    "f4": "Float32",
    "f8": "Float64",
    "i1": "Int8",
    "u1": "UInt8",
    "i4": "Int32",
    "u4": "UInt32",
    "i8": "Int64",
    "u8": "UInt64",
}


def _little_endian(values) -> np.ndarray:
    """``values`` as a C-ordered little-endian array of a type VTK knows."""
    a = np.asarray(values)
    if a.dtype.kind == "b":
        a = a.astype(np.uint8)
    elif a.dtype.str[1:] not in _VTK_TYPES:
        a = a.astype(np.float64 if a.dtype.kind == "f" else np.int64)
    return np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))


def _encoded(a: np.ndarray) -> str:
    raw = a.tobytes()
    return base64.b64encode(np.uint64(len(raw)).astype("<u8").tobytes() + raw).decode("ascii")


def data_array(name: str, values, components: int | None = None) -> ET.Element:
    """A ``<DataArray>`` of ``values``: (N,) one component, (N, C) C components (or
    ``components`` given, for a flat array)."""
    a = _little_endian(values)
    if components is None:
        components = 1 if a.ndim <= 1 else int(np.prod(a.shape[1:]))
    attrs = {"type": _VTK_TYPES[a.dtype.str[1:]], "Name": name}
    if components != 1:
        attrs["NumberOfComponents"] = str(components)
    attrs["format"] = "binary"
    element = ET.Element("DataArray", attrs)
    element.text = _encoded(a)
    return element


def string_array(name: str, strings: Iterable[str]) -> ET.Element:
    """A vtkStringArray (``<Array type="String">``) for FieldData: each string's UTF-8
    bytes and a terminating zero, the layout VTK's XML reader expects."""
    strings = list(strings)
    raw = np.frombuffer(b"".join(s.encode("utf-8") + b"\0" for s in strings), dtype=np.uint8)
    attrs = {"type": "String", "Name": name, "NumberOfTuples": str(len(strings))}
    element = ET.Element("Array", {**attrs, "format": "binary"})
    element.text = _encoded(raw)
    return element


def _cells(tag: str, cells) -> ET.Element:
    """``<Verts>`` / ``<Polys>``: connectivity and offsets (int32 if they fit, else int64)."""
    cells = np.asarray(cells)
    if cells.ndim == 1:  # vertices: one point per cell
        cells = cells[:, None]
    size = cells.size
    kind = np.int32 if max(size, int(cells.max(initial=0))) < 2**31 - 1 else np.int64
    element = ET.Element(tag)
    element.append(data_array("connectivity", cells.reshape(-1).astype(kind)))
    offsets = np.arange(1, len(cells) + 1, dtype=kind) * cells.shape[1]
    element.append(data_array("offsets", offsets))
    return element


def _attributes(tag: str, arrays: Mapping[str, np.ndarray] | None, count: int, vectors=None):
    """``<PointData>`` / ``<CellData>``: one array per name, ``count`` tuples each."""
    element = ET.Element(tag, {"Vectors": vectors} if vectors else {})
    for name, values in (arrays or {}).items():
        if len(values) != count:
            raise ValueError(f"{tag} array {name!r} has {len(values)} tuples, not {count}")
        element.append(data_array(name, values))
    return element


def polydata(
    points,
    *,
    verts=None,
    polys=None,
    point_data: Mapping[str, np.ndarray] | None = None,
    cell_data: Mapping[str, np.ndarray] | None = None,
    field_data: Mapping[str, object] | None = None,
    vectors: str | None = None,
    comment: str | None = None,
) -> ET.ElementTree:
    """A PolyData document: ``points`` (N, 3); ``verts`` (N_v,) point indices drawn as
    points; ``polys`` (N_p, k) polygons (triangles: k = 3, counter-clockwise seen from
    outside); point/cell data arrays by name; field data by name (a str or list of str
    becomes a string array, anything else a numeric one); ``vectors`` names the point
    array ParaView treats as the active vectors (Warp By Vector); ``comment`` goes into
    the file as an XML comment, readable in any text editor."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    root = ET.Element(
        "VTKFile",
        {"type": "PolyData", "version": "1.0", "byte_order": "LittleEndian",
         "header_type": "UInt64"},
    )  # fmt: skip
    if comment:
        root.append(ET.Comment(f" {comment.replace('--', '- -')} "))  # '--' ends a comment
    poly = ET.SubElement(root, "PolyData")
    if field_data:
        poly.append(_field_data(field_data))
    counts = {
        "Verts": 0 if verts is None else len(verts),
        "Polys": 0 if polys is None else len(polys),
    }
    piece = ET.SubElement(
        poly,
        "Piece",
        {"NumberOfPoints": str(len(points)), "NumberOfVerts": str(counts["Verts"]),
         "NumberOfLines": "0", "NumberOfStrips": "0", "NumberOfPolys": str(counts["Polys"])},
    )  # fmt: skip
    piece.append(_attributes("PointData", point_data, len(points), vectors))
    piece.append(_attributes("CellData", cell_data, counts["Verts"] + counts["Polys"]))
    ET.SubElement(piece, "Points").append(data_array("Points", points))
    for tag, cells in (("Verts", verts), ("Polys", polys)):
        if cells is not None and len(cells):
            piece.append(_cells(tag, cells))
    return ET.ElementTree(root)


def _field_data(field_data: Mapping[str, object]) -> ET.Element:
    """``<FieldData>``: a str or list of str is a string array; a number or (N,) array N
    tuples of one value; an (N, C) array N tuples of C components."""
    element = ET.Element("FieldData")
    for name, value in field_data.items():
        if isinstance(value, str) or (
            isinstance(value, (list, tuple)) and value and isinstance(value[0], str)
        ):
            element.append(string_array(name, [value] if isinstance(value, str) else value))
            continue
        a = np.asarray(value)
        a = a.reshape(-1) if a.ndim < 2 else a.reshape(len(a), -1)
        array = data_array(name, a)
        array.set("NumberOfTuples", str(len(a)))
        element.append(array)
    return element


def write_polydata(path: str | Path, points, **kwargs) -> Path:
    """Write :func:`polydata` (same arguments) to ``path`` (``.vtp``); return the path."""
    path = Path(path)
    tree = polydata(points, **kwargs)
    ET.indent(tree, space=" ")
    tree.write(path, encoding="utf-8", xml_declaration=True)
    return path


def write_collection(path: str | Path, datasets: Iterable[tuple[float, str | Path]]) -> Path:
    """Write a ParaView collection (``.pvd``): one ``<DataSet>`` per (time, file); files are
    written relative to the collection's folder, so the folder can be moved whole."""
    path = Path(path)
    root = ET.Element("VTKFile", {"type": "Collection", "version": "0.1"})
    collection = ET.SubElement(root, "Collection")
    for time, file in datasets:
        file = Path(file)
        relative = file.relative_to(path.parent) if file.is_absolute() else file
        ET.SubElement(
            collection,
            "DataSet",
            {"timestep": repr(float(time)), "group": "", "part": "0", "file": relative.as_posix()},
        )
    tree = ET.ElementTree(root)
    ET.indent(tree, space=" ")
    tree.write(path, encoding="utf-8", xml_declaration=True)
    return path
