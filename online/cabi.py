"""The C ABI's Python side: ``numba.cfunc`` entry points and the handles C keeps of them.

``libhapticrom.so`` (``capi/hapticrom.c``, header ``include/hapticrom.h``) embeds CPython,
imports this module once and then calls the entry points below through plain C function
pointers (``cfunc.address``): a servo call never touches the interpreter or the GIL. There
is one implementation of the physics: each entry point views the caller's raw pointers as
arrays (``numba.carray``: no copy, no allocation) and calls the runtime's own ``@njit``
kernels (:mod:`~hapticrom.online.kernels`, :mod:`~hapticrom.online.proxy`,
:mod:`~hapticrom.online.surface_kernels`) on the very state buffer, proxy state and tables a
:class:`~hapticrom.online.simulator.Simulator` steps. A surface runs the bodies of
:mod:`~hapticrom.online.packed_surface` on its packed arrays, as Python's surfaces do.

Loading (:func:`open_simulator`, called by ``hapticrom_load`` under the GIL) builds a
Simulator and returns the *handle*: one int64 array (its fields named by
:data:`HANDLE_FIELDS`, which C looks up by name at start) of the entry points' addresses,
the arrays' addresses and sizes and the model's sizes. The Python objects behind those
addresses stay alive in a registry until :func:`free_simulator`.

Every entry point returns an ABI status (``STATUS``, the header's ``hapticrom_status``): the
kernels' status codes are translated here, so C knows nothing of the state buffer's layout.

To add an entry point: one ``cfunc`` below, its address (and the addresses of the arrays it
reads) as new fields of :data:`HANDLE_FIELDS` and :func:`_handle` (bump :data:`ABI_VERSION`),
and one C wrapper in ``capi/hapticrom.c`` that calls it between ``enter`` and ``leave``
(inside ``write_begin`` / ``write_end`` if it writes the state buffer or the proxy's state,
so that the renderer's snapshot stays whole).

Friction (``hapticrom_set_friction``) is the one setting C changes after the load: it is
not a servo call. :func:`validate_friction` (under the GIL) runs the validator of
:meth:`Simulator.set_friction <hapticrom.online.simulator.Simulator.set_friction>`
(:func:`~hapticrom.online.simulator.friction_values`: one validator, one default, nothing
written to the live buffer, which is the servo thread's); C then writes the triple it
resolved to with the entry point :func:`store_friction`, under the servo thread's busy flag
and the sequence lock, never waiting for the GIL while it holds the flag.

The renderer's snapshot is the state buffer (all a surface reads) and the head of the
proxy's state (:data:`PROXY_HEAD` doubles: the proxy and its contact point, so that a host
draws the tool where the surface it renders was dented; the stamps after it are the proxy's
scratch). C copies both as opaque doubles: only :func:`read_state` knows their layouts.

Cutting (the scalpel) and the Grassmann surface are not part of this ABI. A kernel that
raised (a float division by zero: the artifact's checks and the load's sweep rule those out)
would make numba's cfunc wrapper take the GIL to report it. Units: mm, N, N/mm.
"""

from __future__ import annotations

import itertools
import math
import os
import sys
from dataclasses import dataclass

import numpy as np
from numba import carray, cfunc, njit, types

from hapticrom.online import kernels as k
from hapticrom.online import packed_surface as ps
from hapticrom.online import proxy as px
from hapticrom.online.model import ReducedModel, load
from hapticrom.online.packed_surface import address
from hapticrom.online.renderer import SurfaceWork
from hapticrom.online.simulator import Simulator, friction_values
from hapticrom.shared.errors import ArtifactError, HapticromError, InputError

ABI_VERSION = 3  # the header's HAPTICROM_ABI_VERSION: bumped on any change of the handle

# The ABI's status codes (include/hapticrom.h, enum hapticrom_status; a test compares them).
STATUS = {
    "OK": 0,
    "NULL_ARGUMENT": 1,
    "NOT_FINITE": 2,
    "BEYOND_LIMIT": 3,
    "DISPLACEMENT_LIMIT": 4,
    "WRONG_SIZE": 5,
    "NO_CONTACT": 6,
    "BUSY": 7,
    "BAD_HANDLE": 8,
    "LOAD_FAILED": 9,
    "INVALID_OPTION": 10,
    "TOO_MANY": 11,
    "PYTHON": 12,
    "INTERNAL": 13,
}
OK = STATUS["OK"]
_NOT_FINITE, _BEYOND, _DISPLACEMENT_LIMIT = (
    STATUS["NOT_FINITE"], STATUS["BEYOND_LIMIT"], STATUS["DISPLACEMENT_LIMIT"],
)  # fmt: skip
_NO_CONTACT, _INTERNAL = STATUS["NO_CONTACT"], STATUS["INTERNAL"]

# The options' enumerations (hapticrom_options): 0 is the model's default.
INTERPOLATIONS = {0: None, 1: "transport", 2: "podi", 3: "compliance"}
RESPONSES = {0: None, 1: "anm", 2: "curves"}
CODES = {name: code for code, name in INTERPOLATIONS.items() if name}

# read_state's output: normal (3), force (3), displacement (3), depth, flags, contacts prepared
# so far (0: no contact point yet), in contact (1/0), step_position's proxy (3), its contact
# point (3), saturated (1/0), slipping with friction (1/0; since ABI 3)
STATE_SIZE = 21
PROXY_HEAD = px.STATE_STAMPS  # the proxy state's doubles a snapshot copies (all but the stamps)

_f8p, _i8p = types.CPointer(types.float64), types.CPointer(types.int64)
_pointers = types.CPointer(types.voidptr)
_status = types.int32


# -- statuses ----------------------------------------------------------------------------------
@njit(inline="always")
def _abi_status(kernel_status):
    """A step kernel's status as an ABI status."""
    if kernel_status == k.OK:
        return OK
    if kernel_status == k.NOT_FINITE:
        return _NOT_FINITE
    if kernel_status == k.BEYOND_LIMIT:
        return _BEYOND
    if kernel_status == k.DISPLACEMENT_LIMIT:
        return _DISPLACEMENT_LIMIT
    if kernel_status == k.NO_CONTACT_POINT:
        return _NO_CONTACT
    return _INTERNAL  # WRONG_SHAPE cannot happen: carray views are (3,)


@njit(inline="always")
def _copy3(buf, start, out):
    out[0], out[1], out[2] = buf[start], buf[start + 1], buf[start + 2]


# -- the servo thread's entry points -------------------------------------------------------------
@cfunc(_status(_f8p, _f8p, types.int64, _f8p, types.int64), cache=True)
def set_contact(point, table, table_size, buf, buf_size):
    """``Simulator.set_contact``: the contact at point (3,) mm; NOT_FINITE if it is not."""
    region = k.prepare_contact(carray(point, (3,)), carray(table, (table_size,)),
                               carray(buf, (buf_size,)))  # fmt: skip
    return OK if region >= k.NO_VERTEX else _NOT_FINITE


@cfunc(_status(_f8p, _f8p, types.int64, _f8p), cache=True)
def step_displacement_anm(d, buf, buf_size, force):
    """``Simulator.step_displacement`` (POD-ANM): displacement (3,) mm in, force (3,) N out."""
    state = carray(buf, (buf_size,))
    status = k.step_displacement_anm(carray(d, (3,)), state)
    if status == k.OK:
        _copy3(state, k.FORCE, force)
    return _abi_status(status)


@cfunc(_status(_f8p, _f8p, types.int64, _f8p), cache=True)
def step_displacement_curves(d, buf, buf_size, force):
    """``Simulator.step_displacement`` (stored curves): displacement (3,) in, force (3,) out."""
    state = carray(buf, (buf_size,))
    status = k.step_displacement_curves(carray(d, (3,)), state)
    if status == k.OK:
        _copy3(state, k.FORCE, force)
    return _abi_status(status)


@cfunc(_status(_f8p, _f8p, types.int64, _f8p), cache=True)
def step_force_anm(f, buf, buf_size, displacement):
    """``Simulator.step_force`` (POD-ANM): force (3,) N in, tool displacement (3,) mm out."""
    state = carray(buf, (buf_size,))
    status = k.step_force_anm(carray(f, (3,)), state)
    if status == k.OK:
        _copy3(state, k.DISPLACEMENT, displacement)
    return _abi_status(status)


@cfunc(_status(_f8p, _f8p, types.int64, _f8p), cache=True)
def step_force_curves(f, buf, buf_size, displacement):
    """``Simulator.step_force`` (stored curves): force (3,) in, displacement (3,) out."""
    state = carray(buf, (buf_size,))
    status = k.step_force_curves(carray(f, (3,)), state)
    if status == k.OK:
        _copy3(state, k.DISPLACEMENT, displacement)
    return _abi_status(status)


@cfunc(_status(_f8p, types.int64, _f8p), cache=True)
def contact_stiffness(buf, buf_size, out):
    """``Simulator.contact_stiffness`` (N/mm) into out[0]; NO_CONTACT before a contact."""
    state = carray(buf, (buf_size,))
    if state[k.CONTACTS] == 0.0:
        return _NO_CONTACT
    out[0] = k.contact_stiffness(state)
    return OK


@cfunc(_status(_f8p, types.int64, _f8p, types.int64, _f8p), cache=True)
def error_estimate(buf, buf_size, indicator, samples, out):
    """``Simulator.error_estimate`` (relative force error) into out[0]: the samples'
    leave-one-out errors blended with the contact's weights; NO_CONTACT before a contact."""
    state = carray(buf, (buf_size,))
    e = carray(indicator, (samples,))
    if state[k.CONTACTS] == 0.0:
        return _NO_CONTACT
    w, s = k.WEIGHTS, k.SAMPLES
    i0, i1, i2 = int(state[s]), int(state[s + 1]), int(state[s + 2])
    if not (0 <= i0 < samples and 0 <= i1 < samples and 0 <= i2 < samples):
        return _INTERNAL
    out[0] = state[w] * e[i0] + state[w + 1] * e[i1] + state[w + 2] * e[i2]
    return OK


@cfunc(_status(_f8p, _f8p, types.int64, _f8p, types.int64, _f8p, types.int64, _f8p, types.int64,
               _f8p), cache=True)  # fmt: skip
def step_position(tip, sheet, sheet_size, proxy, proxy_size, table, table_size, buf, buf_size,
                  force):  # fmt: skip
    """``Simulator.step_position``: the tool tip's centre (3,) mm in, force (3,) N out (zero
    when free). A finite tip is never refused (a displacement past the limit is held at it:
    saturated); NOT_FINITE (nothing written) otherwise."""
    state = carray(buf, (buf_size,))
    region = px.step_position(carray(tip, (3,)), carray(sheet, (sheet_size,)),
                              carray(proxy, (proxy_size,)), carray(table, (table_size,)),
                              state)  # fmt: skip
    if region >= k.NO_VERTEX:
        _copy3(state, k.FORCE, force)
        return OK
    return _NOT_FINITE if region == -k.POSITION_NOT_FINITE else _INTERNAL


@cfunc(_status(_f8p, types.int64, _f8p), cache=True)
def stiffness(buf, buf_size, out):
    """``Simulator.stiffness``: the 3x3 contact stiffness K (N/mm, row-major) of the last
    step into out (9): F(tip + dx) ~ F - K dx; zero out of contact."""
    status = px.stiffness(carray(buf, (buf_size,)), carray(out, (3, 3)))
    return OK if status == k.OK else _INTERNAL  # WRONG_SHAPE cannot happen: out is (3, 3)


@njit(inline="always")
def _touching(state):
    """Whether the last step pressed the tissue: a contact point and no FLAG_NO_CONTACT."""
    return state[k.CONTACTS] > 0.0 and not (int(state[k.FLAGS]) & k.FLAG_NO_CONTACT)


@cfunc(_status(_f8p, types.int64, _f8p, types.int64, _f8p), cache=True)
def read_state(buf, buf_size, proxy, proxy_size, out):
    """The state a caller may read (STATE_SIZE doubles, see there) of the state buffer and
    the proxy's state (its first PROXY_HEAD doubles at least)."""
    state = carray(buf, (buf_size,))
    p = carray(proxy, (proxy_size,))
    _copy3(state, k.NORMAL, out)
    for c in range(3):
        out[3 + c] = state[k.FORCE + c]
        out[6 + c] = state[k.DISPLACEMENT + c]
        out[13 + c] = p[px.STATE_PROXY + c]
        out[16 + c] = p[px.STATE_FOOT + c]
    out[9] = state[k.DEPTH]
    out[10] = state[k.FLAGS]
    out[11] = state[k.CONTACTS]
    out[12] = 1.0 if _touching(state) else 0.0
    out[19] = p[px.STATE_SATURATED]
    out[20] = state[k.SLIPPING]
    return OK


@cfunc(_status(_f8p, _f8p, types.int64), cache=True)
def store_friction(values, buf, buf_size):
    """``hapticrom_set_friction``'s write: values (3,), the (static, dynamic coefficient,
    tangential stiffness ratio) that :func:`validate_friction` resolved, into the state
    buffer where ``Simulator.set_friction`` keeps them."""
    state = carray(buf, (buf_size,))
    for c in range(3):
        state[k.FRICTION + c] = values[c]
    return OK


# -- the rendered surface: packed_surface's bodies on the caller's pointers -------------------
_surface_signature = _status(_pointers, _i8p, _f8p, types.int64, _f8p, types.int64)


@cfunc(_surface_signature, cache=True)
def surface_transport_anm(arrays, dims, buf, buf_size, out, vertices):
    """``Simulator.surface_displacement`` ("transport", POD-ANM) of the state ``buf`` into
    out (V, 3) mm; ``arrays`` and ``dims``: :func:`packed_surface.pack`'s addresses and
    shapes."""
    ps.transport_anm(arrays, dims, carray(buf, (buf_size,)), carray(out, (vertices, 3)))
    return OK


@cfunc(_surface_signature, cache=True)
def surface_transport_curves(arrays, dims, buf, buf_size, out, vertices):
    """As :func:`surface_transport_anm`, the stored curves' coefficients."""
    ps.transport_curves(arrays, dims, carray(buf, (buf_size,)), carray(out, (vertices, 3)))
    return OK


@cfunc(_surface_signature, cache=True)
def surface_podi_anm(arrays, dims, buf, buf_size, out, vertices):
    """``Simulator.surface_displacement`` ("podi", POD-ANM) into out (V, 3) mm."""
    ps.podi_anm(arrays, dims, carray(buf, (buf_size,)), carray(out, (vertices, 3)))
    return OK


@cfunc(_surface_signature, cache=True)
def surface_podi_curves(arrays, dims, buf, buf_size, out, vertices):
    """``Simulator.surface_displacement`` ("podi", stored curves) into out (V, 3) mm."""
    ps.podi_curves(arrays, dims, carray(buf, (buf_size,)), carray(out, (vertices, 3)))
    return OK


@cfunc(_surface_signature, cache=True)
def surface_compliance_anm(arrays, dims, buf, buf_size, out, vertices):
    """``Simulator.surface_displacement`` ("compliance", POD-ANM) into out (V, 3) mm: the
    contact located on the loadable surface at every call (a surface call keeps no state
    between calls)."""
    ps.compliance_anm(arrays, dims, carray(buf, (buf_size,)), carray(out, (vertices, 3)))
    return OK


@cfunc(_surface_signature, cache=True)
def surface_compliance_curves(arrays, dims, buf, buf_size, out, vertices):
    """``Simulator.surface_displacement`` ("compliance", stored curves) into out (V, 3) mm."""
    ps.compliance_curves(arrays, dims, carray(buf, (buf_size,)), carray(out, (vertices, 3)))
    return OK


SURFACES = {
    ("compliance", "anm"): surface_compliance_anm,
    ("compliance", "curves"): surface_compliance_curves,
    ("transport", "anm"): surface_transport_anm,
    ("transport", "curves"): surface_transport_curves,
    ("podi", "anm"): surface_podi_anm,
    ("podi", "curves"): surface_podi_curves,
}

# -- the handle: what C keeps of a simulator -------------------------------------------------------
HANDLE_FIELDS = (
    "abi",  # ABI_VERSION
    "key",  # the registry's key (free_simulator)
    # entry points (addresses of the cfuncs)
    "set_contact", "step_displacement", "step_force", "contact_stiffness", "error_estimate",
    "read_state", "surface", "step_position", "stiffness", "set_friction",
    # the state buffer, its render-side copy, the table, the model's arrays (addresses)
    "buf", "buf_size", "snapshot", "table", "table_size", "indicator", "samples",
    # step_position's sheet (read only), the proxy's state, the head a snapshot copies (its
    # length in doubles) and the render side's copy of it
    "sheet", "sheet_size", "proxy", "proxy_size", "proxy_head", "proxy_snapshot",
    "surface_arrays", "surface_dims", "vertices", "vertex_count", "triangles", "triangle_count",
    "sample_points", "modes",
    # what the options resolved to: 1 transport / 2 podi / 3 compliance, 1 anm / 2 curves
    "interpolation", "response",
    # float64 values, their bits: trained depth (mm), trained force (N), limits (mm, N)
    "trained_depth", "trained_force", "max_displacement", "max_force", "tool_radius",
)  # fmt: skip
H = {name: i for i, name in enumerate(HANDLE_FIELDS)}


@dataclass
class _Entry:
    """One open simulator: everything the handle's addresses point into."""

    model: ReducedModel
    simulator: Simulator
    arrays: list[np.ndarray]  # kept alive: the handle holds their addresses
    handle: np.ndarray


_REGISTRY: dict[int, _Entry] = {}
_KEYS = itertools.count(1)


def _bits(x: float) -> int:
    """A float64's bits as an int64 (the handle is one int64 array)."""
    return int(np.array(x, dtype=np.float64).view(np.int64))


def _handle(key: int, sim: Simulator) -> tuple[np.ndarray, list[np.ndarray]]:
    """The handle of ``sim`` and the arrays it points into."""
    m = sim.model
    # the render side's own scratch: a surface never writes what the servo thread's calls write
    work = SurfaceWork(m, sim.interpolation, sim.response)
    addresses, dims = work.addresses, work.dims
    snapshot = np.zeros_like(sim._buf)
    proxy_snapshot = np.zeros(PROXY_HEAD)
    points = np.ascontiguousarray(m.sample_points)
    kept = [*work.arrays.values(), addresses, dims, snapshot, proxy_snapshot, points]
    anm = sim.response == "anm"
    values = {
        "abi": ABI_VERSION, "key": key,
        "set_contact": set_contact.address,
        "step_displacement": (step_displacement_anm if anm else step_displacement_curves).address,
        "step_force": (step_force_anm if anm else step_force_curves).address,
        "contact_stiffness": contact_stiffness.address, "error_estimate": error_estimate.address,
        "read_state": read_state.address,
        "surface": SURFACES[sim.interpolation, sim.response].address,
        "step_position": step_position.address, "stiffness": stiffness.address,
        "set_friction": store_friction.address,
        "buf": address(sim._buf), "buf_size": sim._buf.size, "snapshot": address(snapshot),
        "table": address(sim._table), "table_size": sim._table.size,
        "sheet": address(sim._sheet), "sheet_size": sim._sheet.size,
        "proxy": address(sim._proxy), "proxy_size": sim._proxy.size, "proxy_head": PROXY_HEAD,
        "proxy_snapshot": address(proxy_snapshot),
        "indicator": address(m.indicator), "samples": len(m.indicator),
        "surface_arrays": address(addresses), "surface_dims": address(dims),
        "vertices": address(m.vertices), "vertex_count": len(m.vertices),
        "triangles": address(m.triangles), "triangle_count": len(m.triangles),
        "sample_points": address(points), "modes": m.num_modes,
        "interpolation": CODES[sim.interpolation],
        "response": 1 if anm else 2,
        "trained_depth": _bits(m.trained_depth), "trained_force": _bits(m.trained_force),
        "max_displacement": _bits(sim.max_displacement), "max_force": _bits(sim.max_force),
        "tool_radius": _bits(sim.tool_radius),
    }  # fmt: skip
    handle = np.array([values[name] for name in HANDLE_FIELDS], dtype=np.int64)
    return handle, kept


def _limit(value: float) -> float | None:
    """A limit (the tool radius, the tangential stiffness) from C: 0 is the default (None);
    anything else is checked by the Simulator (finite, positive; the radius also at most
    MAX_LENGTH, the tangential stiffness MAX_FRICTION)."""
    return None if value == 0.0 else value


def _options(interpolation: int, response: int) -> tuple[str | None, str | None]:
    if interpolation not in INTERPOLATIONS:
        raise InputError(
            f"interpolation must be 0 (the model's default), 1 (transport), 2 (podi) or 3 "
            f"(compliance); got "
            f"{interpolation} (Grassmann and the scalpel are not in this ABI)"
        )
    if response not in RESPONSES:
        raise InputError(
            f"response must be 0 (the model's default), 1 (anm) or 2 (curves); got {response}"
        )
    return INTERPOLATIONS[interpolation], RESPONSES[response]


def _check_isolation(isolate: bool) -> None:
    """InputError if the HDF5 parse cannot go to a child process: it runs ``sys.executable``,
    which in a host that embeds Python itself (runSofa, a game engine) is the host."""
    exe = sys.executable or ""
    if isolate and not (os.path.basename(exe).startswith("python") and os.access(exe, os.X_OK)):
        raise InputError(
            f"options.isolate = 1 parses the file in a child process of sys.executable, and "
            f"{exe!r} is not a Python interpreter (a host that embeds Python): set isolate = 0"
        )


def open_simulator(path: str, interpolation: int, response: int, max_displacement: float,
                   max_force: float, isolate: bool,
                   tool_radius: float = 0.0) -> tuple[int, str, bytes]:  # fmt: skip
    """``hapticrom_load``: load the artifact at ``path`` and make a simulator on it
    (``tool_radius``: step_position's sphere, mm; 0 the artifact's training radius).

    Returns (status, message, handle bytes): OK, "" and the handle (int64, HANDLE_FIELDS);
    or an ABI status and one line naming the problem (LOAD_FAILED: the artifact is missing,
    damaged or refused; INVALID_OPTION: an option is wrong) and no handle. Never raises.
    """
    try:
        interpolation_name, response_name = _options(interpolation, response)
        _check_isolation(bool(isolate))
        model = load(path, isolate=bool(isolate))
        limits = {"max_displacement": _limit(max_displacement), "max_force": _limit(max_force),
                  "tool_radius": _limit(tool_radius)}  # fmt: skip
        sim = Simulator(model, interpolation_name, response=response_name, **limits)
        key = next(_KEYS)
        handle, kept = _handle(key, sim)
    except ArtifactError as exc:
        return STATUS["LOAD_FAILED"], str(exc), b""
    except InputError as exc:
        return STATUS["INVALID_OPTION"], str(exc), b""
    except HapticromError as exc:  # e.g. no process to isolate the HDF5 parse in
        return STATUS["LOAD_FAILED"], str(exc), b""
    except Exception as exc:  # noqa: BLE001 - C gets a status and a message, never a raise
        return STATUS["INTERNAL"], f"{type(exc).__name__}: {exc}", b""
    _REGISTRY[key] = _Entry(model, sim, kept, handle)
    return OK, "", handle.tobytes()


def free_simulator(key: int) -> bool:
    """``hapticrom_free``: forget the simulator ``key`` (its arrays may go); False if unknown."""
    return _REGISTRY.pop(key, None) is not None


_NO_FRICTION = (0.0, 0.0, 0.0)


def validate_friction(
    key: int, static: float, dynamic: float, tangential_stiffness: float
) -> tuple[int, str, tuple[float, float, float]]:
    """``hapticrom_set_friction``'s check, under the GIL: ``Simulator.set_friction``'s own
    validator (:func:`~hapticrom.online.simulator.friction_values`; tangential stiffness 0:
    its default, 2/3), which writes nothing (the live buffer is the servo thread's).

    Returns (status, message, values): OK, "" and the (static, dynamic, ratio) the
    simulator's own check resolved (C writes them with :func:`store_friction`); or
    NOT_FINITE (an argument is NaN or infinite) or INVALID_OPTION (out of range, dynamic
    above static) with the simulator's message, BAD_HANDLE if ``key`` was freed meanwhile.
    Never raises."""
    if key not in _REGISTRY:
        return STATUS["BAD_HANDLE"], "the simulator was freed", _NO_FRICTION
    try:
        values = friction_values(static, dynamic, _limit(tangential_stiffness))
    except InputError as exc:
        finite = all(math.isfinite(x) for x in (static, dynamic, tangential_stiffness))
        return (STATUS["INVALID_OPTION"] if finite else _NOT_FINITE), str(exc), _NO_FRICTION
    except Exception as exc:  # noqa: BLE001 - C gets a status and a message, never a raise
        return _INTERNAL, f"{type(exc).__name__}: {exc}", _NO_FRICTION
    return OK, "", values


def open_count() -> int:
    """How many simulators are open (what the registry keeps alive)."""
    return len(_REGISTRY)
