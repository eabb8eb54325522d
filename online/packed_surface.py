"""The rendered surface from packed arrays: one layout for the Python simulator and the C ABI.

A surface reads up to 32 arrays, the model's and its scratch. Their addresses are packed
once into one int64 array and their shapes into another (``dims``, DIMS an array), in the
order of :data:`SURFACE_ARRAYS` (:func:`pack` of :func:`surface_arrays`); a surface is then
one call on four arguments. C's cfuncs (:mod:`~hapticrom.online.cabi`) get the two as
pointers; Python's :data:`ENTRIES` get them as arrays (``Simulator.surface_displacement``
and a ``SurfaceRenderer``, for the transported and the PODI surfaces). Both run the same
bodies (:func:`transport_anm` ... :func:`compliance_curves`), which view the addresses as
arrays (``numba.carray``: no copy) and call :mod:`~hapticrom.online.surface_kernels`.

Why Python goes through them too: numba's dispatch of the transported kernel's 21
arguments took 1.4 us, the coefficients' own call 0.35 us, and Python's lookups around the
two about 1 us more. On the cornea demo's untrained contact, one call on the packed arrays
is 16.7 against 19.8 us (min over 20,000 calls, one process), the surface bit for bit the
same.

The entries trust their addresses and shapes: only :func:`pack` makes them, from arrays that
the :class:`~hapticrom.online.renderer.SurfaceWork` holding them keeps alive (its scratch
and the model's arrays, each checked against its :data:`LAYOUT` entry; a copy of the work
packs its own). Never call an entry with arrays of your own.
"""

from __future__ import annotations

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

from hapticrom.online import surface_kernels as sk
from hapticrom.shared.errors import ArtifactError

# -- the layout ------------------------------------------------------------------------------
# The arrays in their packed order: name, dtype, number of dimensions, and what it holds (a
# name missing from a configuration's surface_arrays is packed as a null address and a zero
# shape). pack() checks every array against its entry: the bodies view the bytes as that.
_f8, _f4, _i8, _i2 = (
    np.dtype(np.float64),
    np.dtype(np.float32),
    np.dtype(np.int64),
    np.dtype(np.int16),
)
LAYOUT = (
    ("coefficients_out", _f8, 2),  # (3, n) scratch: the neighbours' reduced coordinates
    ("coefficients", _f8, 3),  # curves: (P, K, n); POD-ANM: ANM_COEFFICIENTS
    ("series", _f8, 3),  # POD-ANM: the series' coefficients (Z, N1, n); curves: unused
    ("surface_basis_t", _f4, 3),  # (P, n, 3V)
    ("node_basis", _i2, 4),  # transport: the chart's (P, n, 3, N) (the others too)
    ("mode_scale", _f8, 2),  # (P, n): the modes' scales
    ("sample_grid", _f8, 2),  # (P, 2): the samples' places on the chart's grid, in nodes
    ("sample_normals", _f8, 2),  # (P, 3)
    ("chart_shape", _i8, 1),  # (3,)
    ("chart_blocks", _i8, 1),  # (B,): the first nodes of the runs the neighbours are summed on
    ("halo", _i8, 1),  # (1,)
    ("charted", _i8, 1),  # (C,)
    ("charted_node", _i8, 1),  # (C,)
    ("charted_frac", _f4, 2),  # (2, C)
    ("uncharted", _i8, 1),  # (U,)
    ("chart_grid", _f4, 2),  # (N, 4) scratch
    ("neighbours", _i8, 2),  # (3, 2) scratch
    ("terms", _f4, 2),  # (3, terms_width(n)) scratch
    ("sample_points", _f8, 2),  # compliance: (P, 3)
    ("surface_vertices", _f8, 2),  # (V, 3)
    ("field_triangles", _i8, 2),  # (TL, 3), the loadable triangles
    ("contact_fields", _f4, 2),  # (R, 3V)
    ("triangle_rows", _i8, 2),  # (TL, 3)
    ("sample_rows", _i8, 1),  # (P,)
    ("surface_weights", _f8, 1),  # (3,) scratch
    ("triangle_grid", _f8, 1),  # (7,): origin, cell size, dims of the triangles' grid
    ("grid_starts", _i8, 1),  # (cells + 1,)
    ("grid_ids", _i8, 1),  # (entries,)
    ("read_weights", _f4, 2),  # transport: (4, C) scratch
    ("read_cells", _i8, 1),  # (C,) scratch
    ("uncharted_basis", _f4, 3),  # transport: (P, n, 3U)
    ("uncharted_sum", _f8, 1),  # (3U,) scratch
)
ANM_COEFFICIENTS = (_i8, 1)  # POD-ANM's "coefficients": the sections' offsets (P + 1,)
SURFACE_ARRAYS = tuple(name for name, _, _ in LAYOUT)
DIMS = 4
(A_COEFFICIENTS_OUT, A_COEFFICIENTS, A_SERIES, A_BASIS_T, A_NODE_BASIS, A_MODE_SCALE,
 A_SAMPLE_GRID,
 A_SAMPLE_NORMALS, A_SHAPE, A_BLOCKS, A_HALO, A_CHARTED, A_CHARTED_NODE,
 A_CHARTED_FRAC, A_UNCHARTED, A_CHART_GRID, A_NEIGHBOURS, A_TERMS, A_SAMPLE_POINTS,
 A_SURFACE_VERTICES, A_FIELD_TRIANGLES, A_CONTACT_FIELDS, A_TRIANGLE_ROWS, A_SAMPLE_ROWS,
 A_SURFACE_WEIGHTS, A_GRID, A_GRID_STARTS, A_GRID_IDS, A_READ_WEIGHTS,
 A_READ_CELLS, A_UNCHARTED_BASIS, A_UNCHARTED_SUM) = range(len(SURFACE_ARRAYS))  # fmt: skip


@njit(inline="always")
def _view1(arrays, dims, i, dtype):
    return carray(arrays[i], (dims[DIMS * i],), dtype)


@njit(inline="always")
def _view2(arrays, dims, i, dtype):
    return carray(arrays[i], (dims[DIMS * i], dims[DIMS * i + 1]), dtype)


@njit(inline="always")
def _view3(arrays, dims, i, dtype):
    d = DIMS * i
    return carray(arrays[i], (dims[d], dims[d + 1], dims[d + 2]), dtype)


@njit(inline="always")
def _view4(arrays, dims, i, dtype):
    d = DIMS * i
    return carray(arrays[i], (dims[d], dims[d + 1], dims[d + 2], dims[d + 3]), dtype)


@njit(inline="always")
def _anm_coefficients(arrays, dims, buf):
    c = _view2(arrays, dims, A_COEFFICIENTS_OUT, np.float64)
    sk.anm_coefficients(buf, _view1(arrays, dims, A_COEFFICIENTS, np.int64),
                        _view3(arrays, dims, A_SERIES, np.float64), c)  # fmt: skip
    return c


@njit(inline="always")
def _curves_coefficients(arrays, dims, buf):
    c = _view2(arrays, dims, A_COEFFICIENTS_OUT, np.float64)
    sk.curves_coefficients(buf, _view3(arrays, dims, A_COEFFICIENTS, np.float64), c)
    return c


@njit(inline="always")
def _transported(arrays, dims, buf, c, out):
    """``surface_kernels.transported_surface`` on the packed arrays."""
    sk.transported_surface(
        buf, c, _view4(arrays, dims, A_NODE_BASIS, np.int16),
        _view2(arrays, dims, A_MODE_SCALE, np.float64),
        _view2(arrays, dims, A_SAMPLE_GRID, np.float64),
        _view2(arrays, dims, A_SAMPLE_NORMALS, np.float64),
        _view1(arrays, dims, A_SHAPE, np.int64), _view1(arrays, dims, A_BLOCKS, np.int64),
        _view1(arrays, dims, A_HALO, np.int64)[0],
        _view1(arrays, dims, A_CHARTED, np.int64), _view1(arrays, dims, A_CHARTED_NODE, np.int64),
        _view2(arrays, dims, A_CHARTED_FRAC, np.float32),
        _view1(arrays, dims, A_UNCHARTED, np.int64),
        _view3(arrays, dims, A_UNCHARTED_BASIS, np.float32),
        _view2(arrays, dims, A_CHART_GRID, np.float32),
        _view2(arrays, dims, A_NEIGHBOURS, np.int64), _view2(arrays, dims, A_TERMS, np.float32),
        _view2(arrays, dims, A_READ_WEIGHTS, np.float32),
        _view1(arrays, dims, A_READ_CELLS, np.int64),
        _view1(arrays, dims, A_UNCHARTED_SUM, np.float64), out,
    )  # fmt: skip


@njit(inline="always")
def _linear_dent(arrays, dims, buf, out):
    """``surface_kernels.add_linear_dent`` on the packed arrays, the contact located on the
    loadable surface at every call (a surface call keeps no state between calls)."""
    weights = _view1(arrays, dims, A_SURFACE_WEIGHTS, np.float64)
    triangle = sk.locate_on_surface(
        buf, _view2(arrays, dims, A_SAMPLE_POINTS, np.float64),
        _view2(arrays, dims, A_SAMPLE_NORMALS, np.float64),
        _view2(arrays, dims, A_SURFACE_VERTICES, np.float64),
        _view2(arrays, dims, A_FIELD_TRIANGLES, np.int64),
        _view1(arrays, dims, A_GRID, np.float64), _view1(arrays, dims, A_GRID_STARTS, np.int64),
        _view1(arrays, dims, A_GRID_IDS, np.int64), weights,
    )  # fmt: skip
    sk.add_linear_dent(buf, triangle, weights, _view2(arrays, dims, A_CONTACT_FIELDS, np.float32),
                       _view2(arrays, dims, A_TRIANGLE_ROWS, np.int64),
                       _view1(arrays, dims, A_SAMPLE_ROWS, np.int64), out)  # fmt: skip


# -- the bodies, one a surface: C's cfuncs and Python's entries run these ---------------------
@njit(inline="always")
def transport_anm(arrays, dims, state, out):
    """The transported surface, POD-ANM's coefficients, of the state into out (V, 3) mm."""
    _transported(arrays, dims, state, _anm_coefficients(arrays, dims, state), out)


@njit(inline="always")
def transport_curves(arrays, dims, state, out):
    """As :func:`transport_anm`, the stored curves' coefficients."""
    _transported(arrays, dims, state, _curves_coefficients(arrays, dims, state), out)


@njit(inline="always")
def podi_anm(arrays, dims, state, out):
    """PODI's blend of the three neighbours' fields, POD-ANM's coefficients."""
    c = _anm_coefficients(arrays, dims, state)
    sk.blended_surface(state, c, _view3(arrays, dims, A_BASIS_T, np.float32), out)


@njit(inline="always")
def podi_curves(arrays, dims, state, out):
    """As :func:`podi_anm`, the stored curves' coefficients."""
    c = _curves_coefficients(arrays, dims, state)
    sk.blended_surface(state, c, _view3(arrays, dims, A_BASIS_T, np.float32), out)


@njit(inline="always")
def compliance_anm(arrays, dims, state, out):
    """PODI's blend plus the linear dent at the contact, POD-ANM's coefficients."""
    podi_anm(arrays, dims, state, out)
    _linear_dent(arrays, dims, state, out)


@njit(inline="always")
def compliance_curves(arrays, dims, state, out):
    """As :func:`compliance_anm`, the stored curves' coefficients."""
    podi_curves(arrays, dims, state, out)
    _linear_dent(arrays, dims, state, out)


# -- Python's entries: the packed arrays as int64 arrays ----------------------------------------
def _data_as(context, builder, signature, args):
    data = context.make_array(signature.args[0])(context, builder, args[0]).data
    return builder.bitcast(data, context.get_value_type(signature.return_type))


@intrinsic
def _addresses_of(typingctx, addresses):
    """An int64 array's data as the ``void **`` the bodies read the arrays' addresses from."""
    if isinstance(addresses, types.Array) and addresses.dtype == types.int64:
        return types.CPointer(types.voidptr)(addresses), _data_as
    return None


@intrinsic
def _shapes_of(typingctx, dims):
    """An int64 array's data as the ``int64 *`` the bodies read the arrays' shapes from."""
    if isinstance(dims, types.Array) and dims.dtype == types.int64:
        return types.CPointer(types.int64)(dims), _data_as
    return None


# Four explicit functions, not one factory's closures: numba names a cached function's
# files by its qualified name and line, so closures would share (and overwrite) them.
_ENTRY = "void(int64[::1], int64[:, ::1], float64[::1], float64[:, ::1])"


@njit(_ENTRY, cache=True, nogil=True)
def _transport_anm(addresses, dims, buf, out):
    transport_anm(_addresses_of(addresses), _shapes_of(dims), buf, out)


@njit(_ENTRY, cache=True, nogil=True)
def _transport_curves(addresses, dims, buf, out):
    transport_curves(_addresses_of(addresses), _shapes_of(dims), buf, out)


@njit(_ENTRY, cache=True, nogil=True)
def _podi_anm(addresses, dims, buf, out):
    podi_anm(_addresses_of(addresses), _shapes_of(dims), buf, out)


@njit(_ENTRY, cache=True, nogil=True)
def _podi_curves(addresses, dims, buf, out):
    podi_curves(_addresses_of(addresses), _shapes_of(dims), buf, out)


# (interpolation, response) -> entry(addresses, dims, buf, out) with pack()'s two arrays. The
# compliance surface keeps its own Python path (it locates the contact once per contact).
ENTRIES = {
    ("transport", "anm"): _transport_anm,
    ("transport", "curves"): _transport_curves,
    ("podi", "anm"): _podi_anm,
    ("podi", "curves"): _podi_curves,
}


# -- packing -----------------------------------------------------------------------------------
def surface_arrays(model, interpolation: str, response: str, work) -> dict[str, np.ndarray]:
    """The arrays a surface of ``interpolation`` and ``response`` reads, by SURFACE_ARRAYS
    name: the model's and the scratch of ``work`` (a ``renderer.SurfaceWork``: a thread's own,
    so a surface never writes what another thread's calls write)."""
    m = model
    if response == "anm":
        arrays = {"coefficients": m.anm["offsets"], "series": m.anm["coefficients"]}
    else:
        arrays = {"coefficients": m.coefficients}
    arrays["coefficients_out"] = work.coefficients
    arrays["surface_basis_t"] = m.surface_basis_t
    if interpolation == "transport":
        ch = m.chart
        arrays |= {
            "node_basis": ch.node_basis, "mode_scale": ch.mode_scale,
            "sample_grid": ch.sample_grid,
            "sample_normals": m.sample_normals, "chart_shape": ch.shape,
            "chart_blocks": ch.blocks, "halo": work.chart_halo, "charted": ch.charted,
            "charted_node": ch.charted_node, "charted_frac": ch.charted_frac,
            "uncharted": ch.uncharted, "chart_grid": work.chart_grid,
            "neighbours": work.chart_neighbours, "terms": work.chart_terms,
            "read_weights": work.chart_weights, "read_cells": work.chart_cells,
            "uncharted_basis": ch.uncharted_basis, "uncharted_sum": work.uncharted_sum,
        }  # fmt: skip
    if interpolation == "compliance":
        f = m.contact_fields
        arrays |= {
            "sample_points": m.sample_points, "sample_normals": m.sample_normals,
            "surface_vertices": m.vertices, "field_triangles": f["triangles"],
            "contact_fields": f["fields"], "triangle_rows": f["triangle_rows"],
            "sample_rows": f["sample_rows"], "surface_weights": work.surface_weights,
            "triangle_grid": f["grid"], "grid_starts": f["grid_starts"], "grid_ids": f["grid_ids"],
        }  # fmt: skip
    return arrays


def pack(arrays: dict[str, np.ndarray], response: str = "curves") -> tuple[np.ndarray, np.ndarray]:
    """(addresses (A,) int64, shapes (A, DIMS) int64) in SURFACE_ARRAYS order; an array the
    configuration does not read is a null address and a zero shape. ArtifactError naming
    the array if one is not the dtype and dimensions of its LAYOUT entry (a model built by
    hand skips the load's conversions; the bodies would read its bytes as another type)."""
    addresses = np.zeros(len(LAYOUT), dtype=np.int64)
    dims = np.zeros((len(LAYOUT), DIMS), dtype=np.int64)
    for i, (name, dtype, ndim) in enumerate(LAYOUT):
        a = arrays.get(name)
        if a is None:
            continue
        if name == "coefficients" and response == "anm":
            dtype, ndim = ANM_COEFFICIENTS
        if not isinstance(a, np.ndarray) or a.dtype != dtype or a.ndim != ndim:
            raise ArtifactError(
                f"the surface's {name} must be a {ndim}-d {dtype} array, got "
                f"{getattr(a, 'ndim', '?')}-d {getattr(a, 'dtype', type(a).__name__)}"
            )
        addresses[i] = address(a)
        dims[i, : a.ndim] = a.shape
    return addresses, dims


def address(a: np.ndarray) -> int:
    """The address of a C-contiguous array's data (ValueError for any other)."""
    if not a.flags.c_contiguous:
        raise ValueError("internal: an array handed to C must be C-contiguous")
    return a.ctypes.data
