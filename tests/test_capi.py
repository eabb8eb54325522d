"""The C ABI (include/hapticrom.h, capi/hapticrom.c, online/cabi.py) against the Python runtime.

Built with ``make capi`` (``make capi-asan`` for the sanitizer run). The example host
(examples/c/servo_loop.c: a servo thread at 1 kHz, a render thread at 60 Hz, CPython embedded)
runs as a subprocess; the ABI's calls one by one go through ctypes, in this process (the
library then uses this interpreter, as in a host that runs Python already).
"""

from __future__ import annotations

import ctypes
import fcntl
import functools
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import hapticrom
import hapticrom.online as online
from hapticrom.online import kernels
from hapticrom.shared.envelope import USERBLOCK

pytestmark = pytest.mark.serial
ROOT = Path(__file__).resolve().parents[1]
BUILD = ROOT / "build"


@functools.cache
def abi_module():
    """hapticrom.online.cabi, imported when a test needs it (not at collection: its entry
    points compile on a cold numba cache)."""
    from hapticrom.online import cabi

    return cabi


class _Statuses:
    """The ABI's status codes by name (cabi.STATUS, read when used)."""

    def __getitem__(self, name: str) -> int:
        return abi_module().STATUS[name]


S = _Statuses()
c_double3 = ctypes.c_double * 3


# -- building --------------------------------------------------------------------------------
def make(target: str) -> None:
    """``make target`` in the project (one at a time: pytest-xdist workers share build/)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    BUILD.mkdir(exist_ok=True)
    with open(BUILD / ".make.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = subprocess.run(["make", "-C", str(ROOT), target], env=env, capture_output=True,
                                text=True, timeout=900)  # fmt: skip
    assert result.returncode == 0, f"make {target} failed:\n{result.stdout}\n{result.stderr}"


@pytest.fixture(scope="module")
def built() -> Path:
    if shutil.which("gcc") is None or shutil.which("make") is None:
        pytest.skip("the C ABI needs gcc and make")
    if not sysconfig.get_config_var("Py_ENABLE_SHARED"):
        pytest.skip("embedding needs a Python built with --enable-shared (libpython3.12.so)")
    make("capi")
    return BUILD


# -- the ABI through ctypes ----------------------------------------------------------------------
class Options(ctypes.Structure):
    _fields_ = [("size", ctypes.c_uint32), ("interpolation", ctypes.c_int32),
                ("response", ctypes.c_int32), ("isolate", ctypes.c_int32),
                ("max_displacement", ctypes.c_double), ("max_force", ctypes.c_double),
                ("tool_radius", ctypes.c_double)]  # fmt: skip


class Info(ctypes.Structure):
    _fields_ = [("vertex_count", ctypes.c_uint64), ("triangle_count", ctypes.c_uint64),
                ("sample_count", ctypes.c_uint64), ("mode_count", ctypes.c_uint64),
                ("interpolation", ctypes.c_int32), ("response", ctypes.c_int32),
                ("trained_depth", ctypes.c_double), ("trained_force", ctypes.c_double),
                ("max_displacement", ctypes.c_double), ("max_force", ctypes.c_double),
                ("tool_radius", ctypes.c_double)]  # fmt: skip


class State(ctypes.Structure):
    _fields_ = [("normal", c_double3), ("force", c_double3), ("displacement", c_double3),
                ("depth", ctypes.c_double), ("flags", ctypes.c_uint32),
                ("has_contact", ctypes.c_uint32), ("sequence", ctypes.c_uint64),
                ("proxy", c_double3), ("contact_point", c_double3),
                ("in_contact", ctypes.c_uint32), ("saturated", ctypes.c_uint32),
                ("slipping", ctypes.c_uint32)]  # fmt: skip


def test_the_structs_here_are_the_headers():
    """The ctypes mirrors above have the header's layout (a field added there, not here, would
    make the other tests read garbage): every field's offset and each size, as gcc lays them."""
    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    lines = [f'    printf("%zu\\n", sizeof({name}));' for name in STRUCTS]
    lines += [f'    printf("%zu\\n", offsetof({name}, {field}));'
              for name, mirror in STRUCTS.items() for field, _ in mirror._fields_]  # fmt: skip
    source = "\n".join(["#include <stddef.h>", "#include <stdio.h>", '#include "hapticrom.h"',
                        "int main(void) {", *lines, "    return 0;", "}", ""])  # fmt: skip
    BUILD.mkdir(exist_ok=True)
    binary = BUILD / "struct-layout"
    command = ["gcc", "-std=c99", f"-I{ROOT / 'include'}", "-x", "c", "-", "-o", str(binary)]
    compiled = subprocess.run(command, input=source, capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stderr
    measured = subprocess.run([str(binary)], capture_output=True, text=True, check=True)
    expected = [ctypes.sizeof(mirror) for mirror in STRUCTS.values()]
    expected += [getattr(mirror, field).offset for mirror in STRUCTS.values()
                 for field, _ in mirror._fields_]  # fmt: skip
    assert [int(x) for x in measured.stdout.split()] == expected


STRUCTS = {"hapticrom_options": Options, "hapticrom_info": Info, "hapticrom_state": State}
_SIM, _P, _SIZE = ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t
PROTOTYPES = {
    "hapticrom_version": (ctypes.c_char_p, [ctypes.POINTER(ctypes.c_uint32)]),
    "hapticrom_last_error": (ctypes.c_char_p, []),
    "hapticrom_status_name": (ctypes.c_char_p, [ctypes.c_int]),
    "hapticrom_options_init": (None, [_P]),
    "hapticrom_load": (ctypes.c_int, [ctypes.c_char_p, _P, _P]),
    "hapticrom_free": (ctypes.c_int, [_SIM]),
    "hapticrom_set_friction": (ctypes.c_int, [_SIM] + [ctypes.c_double] * 3),
    "hapticrom_set_contact": (ctypes.c_int, [_SIM, _P]),
    "hapticrom_step_displacement": (ctypes.c_int, [_SIM, _P, _P]),
    "hapticrom_step_force": (ctypes.c_int, [_SIM, _P, _P]),
    "hapticrom_step_position": (ctypes.c_int, [_SIM, _P, _P]),
    "hapticrom_stiffness": (ctypes.c_int, [_SIM, _P]),
    "hapticrom_contact_stiffness": (ctypes.c_int, [_SIM, _P]),
    "hapticrom_error_estimate": (ctypes.c_int, [_SIM, _P]),
    "hapticrom_get_state": (ctypes.c_int, [_SIM, _P]),
    "hapticrom_surface": (ctypes.c_int, [_SIM, _P, _SIZE, _P]),
    "hapticrom_get_info": (ctypes.c_int, [_SIM, _P]),
    "hapticrom_surface_mesh": (ctypes.c_int, [_SIM, _P, _SIZE, _P, _SIZE]),
    "hapticrom_sample_points": (ctypes.c_int, [_SIM, _P, _SIZE]),
}


@pytest.fixture(scope="module")
def lib(built):
    library = ctypes.CDLL(str(built / "libhapticrom.so"))
    for name, (restype, argtypes) in PROTOTYPES.items():
        function = getattr(library, name)
        function.restype, function.argtypes = restype, argtypes
    return library


def ptr(a: np.ndarray):
    return a.ctypes.data


def last_error(lib) -> str:
    return lib.hapticrom_last_error().decode()


def options(lib, **fields) -> Options:
    o = Options()
    lib.hapticrom_options_init(ctypes.byref(o))
    o.isolate = 0  # the child-process parse is tested once, with its own load
    for key, value in fields.items():
        setattr(o, key, value)
    return o


def load(lib, path, **fields) -> int:
    sim = ctypes.c_uint64(12345)
    status = lib.hapticrom_load(str(path).encode(), ctypes.byref(options(lib, **fields)),
                                ctypes.byref(sim))  # fmt: skip
    assert status == S["OK"], last_error(lib)
    return sim.value


def state(lib, sim) -> State:
    s = State()
    assert lib.hapticrom_get_state(sim, ctypes.byref(s)) == S["OK"], last_error(lib)
    return s


def info(lib, sim) -> Info:
    i = Info()
    assert lib.hapticrom_get_info(sim, ctypes.byref(i)) == S["OK"], last_error(lib)
    return i


def refused(lib, status: int, expected: str, *words: str) -> None:
    """``status`` is the ABI's ``expected`` and the thread's message names the words."""
    message = last_error(lib)
    assert status == S[expected], f"{status} ({message}), expected {expected}"
    for word in words:
        assert word in message, message


@pytest.fixture(scope="module")
def model(small_artifact):
    return online.load(small_artifact)


def path_of(model, ticks: int = 40):
    """Contact points and depths across the trained region (press, slide, release)."""
    from hapticrom.online.play import tool_path

    return tool_path(model, ticks)


# -- the header against the Python side ---------------------------------------------------------
def header_values(prefix: str) -> dict[str, int]:
    text = (ROOT / "include" / "hapticrom.h").read_text()
    return {m[1]: int(m[2]) for m in re.finditer(rf"\b{prefix}([A-Z_]+) = (\d+)", text)}


def test_the_header_declares_what_the_python_side_returns(lib):
    cabi = abi_module()
    assert header_values("HAPTICROM_E_") | {"OK": header_values("HAPTICROM_")["OK"]} == cabi.STATUS
    flags = header_values("HAPTICROM_FLAG_")
    assert flags == {"BEYOND_DEPTH": kernels.FLAG_BEYOND_DEPTH,
                     "NO_CONTACT": kernels.FLAG_NO_CONTACT,
                     "OUTSIDE_REGION": kernels.FLAG_OUTSIDE_REGION}  # fmt: skip
    names = {"transport": "TRANSPORT", "podi": "PODI", "compliance": "COMPLIANCE", "anm": "ANM",
             "curves": "CURVES"}  # fmt: skip
    interpolations = header_values("HAPTICROM_INTERPOLATION_")
    responses = header_values("HAPTICROM_RESPONSE_")
    for code, name in cabi.INTERPOLATIONS.items():
        assert interpolations[names.get(name, "DEFAULT")] == code
    for code, name in cabi.RESPONSES.items():
        assert responses[names.get(name, "DEFAULT")] == code
    abi = ctypes.c_uint32()
    version = lib.hapticrom_version(ctypes.byref(abi)).decode()
    assert (abi.value, version) == (cabi.ABI_VERSION, hapticrom.__version__)
    text = (ROOT / "include" / "hapticrom.h").read_text()
    assert f"#define HAPTICROM_ABI_VERSION {cabi.ABI_VERSION}\n" in text
    for name, code in cabi.STATUS.items():
        expected = "HAPTICROM_OK" if name == "OK" else f"HAPTICROM_E_{name}"
        assert lib.hapticrom_status_name(code).decode() == expected
    assert lib.hapticrom_status_name(99).decode() == "unknown status"


# -- the same numbers as the Python runtime -------------------------------------------------------
def combinations(model) -> list[tuple[str, str]]:
    from hapticrom.online.model import field_interpolations

    interpolations = field_interpolations(model)
    responses = ["anm", "curves"] if model.anm is not None else ["curves"]
    return [(i, r) for i in interpolations for r in responses]


CODES = {"transport": 1, "podi": 2, "compliance": 3, "anm": 1, "curves": 2}


@pytest.mark.parametrize("artifact", ["small_artifact", "force_artifact"])
def test_every_call_gives_the_python_runtimes_numbers(lib, request, artifact):
    """set_contact, both steps, stiffness, error estimate, state and surface, for every
    interpolation and response the model has, along a path: the Python simulator's values
    (the force-controlled model has the compliance surface too)."""
    path = request.getfixturevalue(artifact)
    model = online.load(path)
    points, depths = path_of(model)
    names = combinations(model)
    assert ("compliance", "curves") in names or artifact == "small_artifact"
    for interpolation, response in names:
        sim = load(lib, path, interpolation=CODES[interpolation],
                   response=CODES[response])  # fmt: skip
        py = model.simulator(interpolation, response)
        i = info(lib, sim)
        assert (i.interpolation, i.response) == (CODES[interpolation], CODES[response])
        assert (i.vertex_count, i.sample_count) == (len(model.vertices), len(model.indicator))
        assert (i.max_displacement, i.max_force) == (py.max_displacement, py.max_force)
        surface, expected = np.zeros_like(model.vertices), np.zeros_like(model.vertices)
        force, x, value = c_double3(), c_double3(), ctypes.c_double()
        peak = 0.0
        for k, (p, depth) in enumerate(zip(points, depths, strict=True)):
            p = np.ascontiguousarray(p)
            assert lib.hapticrom_set_contact(sim, ptr(p)) == S["OK"], last_error(lib)
            py.set_contact(p)
            d = np.multiply(py.contact_normal, -depth)
            assert lib.hapticrom_step_displacement(sim, ptr(d), force) == S["OK"]
            np.testing.assert_array_equal(list(force), py.step_displacement(d))
            s = state(lib, sim)
            np.testing.assert_array_equal(list(s.normal), py.contact_normal)
            assert (s.depth, s.has_contact, s.sequence) == (py.depth, 1, 3 * k + 2)
            assert bool(s.flags & 4) == py.outside_trained_region
            assert lib.hapticrom_contact_stiffness(sim, ctypes.byref(value)) == S["OK"]
            assert value.value == py.contact_stiffness
            assert lib.hapticrom_error_estimate(sim, ctypes.byref(value)) == S["OK"]
            assert value.value == py.error_estimate
            assert lib.hapticrom_surface(sim, ptr(surface), surface.size, None) == S["OK"]
            np.testing.assert_array_equal(surface, py.surface_displacement(expected))
            peak = max(peak, np.abs(surface).max())
            push = np.multiply(py.contact_normal, -0.4 * model.trained_force * (k % 3))
            assert lib.hapticrom_step_force(sim, ptr(push), x) == S["OK"], last_error(lib)
            np.testing.assert_array_equal(list(x), py.step_force(push))
        assert peak > 0.1 * model.trained_depth  # the path pressed: a test that can fail
        assert lib.hapticrom_free(sim) == S["OK"]


def test_the_surface_mesh_and_samples_are_the_models(lib, model, small_artifact):
    sim = load(lib, small_artifact)
    vertices = np.zeros_like(model.vertices)
    triangles = np.zeros(model.triangles.shape, dtype=np.uint32)
    points = np.zeros_like(model.sample_points)
    assert lib.hapticrom_surface_mesh(sim, ptr(vertices), vertices.size, ptr(triangles),
                                      triangles.size) == S["OK"]  # fmt: skip
    assert lib.hapticrom_sample_points(sim, ptr(points), points.size) == S["OK"]
    np.testing.assert_array_equal(vertices, model.vertices)
    np.testing.assert_array_equal(triangles, model.triangles)
    np.testing.assert_array_equal(points, model.sample_points)
    assert lib.hapticrom_free(sim) == S["OK"]


# -- position in, force out ------------------------------------------------------------------------
def scripted(model, ticks: int, radius: float | None = None) -> np.ndarray:
    """Tips (ticks, 3) mm of play's scripted path: approach, press at 30 degrees, slide, lift."""
    from hapticrom.online.play import scripted_tips

    return np.ascontiguousarray(scripted_tips(model, ticks, radius=radius))


def position_configurations(model) -> list[dict]:
    """Each response with the training's radius, a larger radius, a depth limit the path
    passes (saturated): (load options, the Python simulator's arguments)."""
    responses = ["anm", "curves"] if model.anm is not None else ["curves"]
    limit = 0.3 * model.trained_depth
    return [{"response": r} for r in responses] + [
        {"response": responses[0], "tool_radius": 1.5 * model.contact_radius},
        {"response": responses[-1], "max_displacement": limit},
    ]


def assert_close(actual, expected, scale: float, what: str) -> None:
    """``actual`` equals ``expected`` to 1e-12 of ``scale`` (> 0)."""
    actual, expected = np.asarray(actual, dtype=float), np.asarray(expected, dtype=float)
    assert scale > 0 and np.abs(actual - expected).max() <= 1e-12 * scale, (what, actual, expected)


def test_step_position_gives_the_python_runtimes_forces_stiffness_and_state(
    lib, model, small_artifact
):
    """Position in, force out along play's scripted path (each response; a larger tool
    radius; a depth limit the path passes): the forces, the 3x3 stiffness and the state (in
    contact, proxy, contact point, depth, saturated) from C equal the Python simulator's;
    the rendered surface's state is the proxy of the step it was rendered at."""
    K, Kpy = np.zeros(9), np.zeros((3, 3))
    surface, expected = np.zeros_like(model.vertices), np.zeros_like(model.vertices)
    force, rendered = c_double3(), State()
    span = np.abs(model.vertices).max()  # positions are compared to 1e-12 of the organ's size
    for config in position_configurations(model):
        codes = {key: CODES.get(value, value) for key, value in config.items()}
        sim = load(lib, small_artifact, **codes)
        py = model.simulator(**config)
        assert info(lib, sim).tool_radius == py.tool_radius
        tips = scripted(model, 150, py.tool_radius)
        forces, expected_forces, touching, saturated, stiff = [], [], 0, 0, 0.0
        for k, tip in enumerate(tips):
            assert lib.hapticrom_step_position(sim, ptr(tip), force) == S["OK"], last_error(lib)
            forces.append(list(force))
            expected_forces.append(py.step_position(tip).copy())
            assert lib.hapticrom_stiffness(sim, ptr(K)) == S["OK"], last_error(lib)
            py.stiffness(Kpy)
            s = state(lib, sim)
            assert (s.in_contact, s.saturated, s.sequence) == (py.in_contact, py.saturated, k + 1)
            assert_close(s.proxy, py.proxy, span, "proxy")
            assert_close(s.contact_point, py.contact_point, span, "contact point")
            assert_close(s.depth, py.depth, model.trained_depth, "depth")
            assert_close(K, Kpy.ravel(), max(np.abs(Kpy).max(), 1e-300), "stiffness")
            touching, saturated = touching + py.in_contact, saturated + py.saturated
            stiff = max(stiff, np.abs(Kpy).max())
            if k % 10 == 5:  # the render call's state is the step's, proxy included
                assert lib.hapticrom_surface(sim, ptr(surface), surface.size,
                                             ctypes.byref(rendered)) == S["OK"]  # fmt: skip
                assert_close(surface, py.surface_displacement(expected), model.trained_depth,
                             "surface")  # fmt: skip
                assert (rendered.sequence, rendered.in_contact) == (k + 1, py.in_contact)
                assert_close(rendered.proxy, py.proxy, span, "rendered proxy")
        peak = np.abs(expected_forces).max()
        assert peak > 0.1 * model.trained_force and stiff > 0  # the path pressed
        assert 0 < touching < len(tips)  # and it was free too (approach, lift)
        assert (saturated > 0) == ("max_displacement" in config), (config, saturated)
        assert_close(forces, expected_forces, peak, "forces")
        assert lib.hapticrom_free(sim) == S["OK"]


def test_step_position_refuses_null_and_non_finite_tips_and_keeps_the_state(
    lib, model, small_artifact
):
    """NULL and NaN/infinite tips are refused (the state and the proxy untouched: the path
    goes on as if they had never come); a finite tip however far is never refused."""
    sim, py = load(lib, small_artifact), model.simulator()
    tips = scripted(model, 100)
    force, K = c_double3(), np.zeros(9)
    for tip in tips[:50]:  # into the slide: in contact
        assert lib.hapticrom_step_position(sim, ptr(tip), force) == S["OK"]
        py.step_position(tip)
    before = state(lib, sim)
    assert before.in_contact
    refused(lib, lib.hapticrom_step_position(sim, None, force), "NULL_ARGUMENT",
            "hapticrom_step_position", "tip is NULL")  # fmt: skip
    refused(lib, lib.hapticrom_step_position(sim, ptr(tips[50]), None), "NULL_ARGUMENT",
            "force is NULL")  # fmt: skip
    refused(lib, lib.hapticrom_stiffness(sim, None), "NULL_ARGUMENT", "hapticrom_stiffness")
    bad_tips = 0
    for bad in (np.nan, np.inf, -np.inf):
        for c in range(3):
            x = tips[50].copy()
            x[c] = bad
            refused(lib, lib.hapticrom_step_position(sim, ptr(x), force), "NOT_FINITE",
                    "hapticrom_step_position", "tool tip")  # fmt: skip
            bad_tips += 1
    after = state(lib, sim)
    assert after.sequence == before.sequence + bad_tips  # refused writing calls count
    for field, _ in State._fields_:
        if field != "sequence":
            assert np.array_equal(np.ravel(getattr(after, field)),
                                  np.ravel(getattr(before, field))), field  # fmt: skip
    far = [np.array([1e6, -1e6, 1e6]), tips[60] - 5 * model.trained_depth * py.contact_normal]
    for tip in [*tips[50:], *far, tips[0]]:  # on, then far away, deep inside, back out
        tip = np.ascontiguousarray(tip)
        assert lib.hapticrom_step_position(sim, ptr(tip), force) == S["OK"], last_error(lib)
        expected = py.step_position(tip)
        assert_close(list(force), expected, model.trained_force, "force after refusals")
        assert lib.hapticrom_stiffness(sim, ptr(K)) == S["OK"]
    assert lib.hapticrom_free(sim) == S["OK"]


# -- friction -----------------------------------------------------------------------------------
MU_S, MU_D = 0.5, 0.3


def newest_registered():
    """The Python simulator behind the simulator loaded last (the registry's newest key)."""
    registry = abi_module()._REGISTRY
    return registry[max(registry)].simulator


def friction_configurations(model) -> list[tuple[str, tuple[float, float, float]]]:
    """Each response with (MU_S, MU_D) and the default tangential stiffness (0 from C); one
    coefficient for both with a stiffer tangential spring: (response, C's arguments)."""
    responses = ["anm", "curves"] if model.anm is not None else ["curves"]
    return [(r, (MU_S, MU_D, 0.0)) for r in responses] + [(responses[-1], (0.4, 0.4, 1.5))]


def test_step_position_with_friction_gives_the_python_runtimes_forces_stiffness_and_state(
    lib, model, small_artifact
):
    """hapticrom_set_friction, then position in, force out along play's scripted path: the
    forces, the 3x3 stiffness (its tangential terms) and the state (slipping too) from C equal
    the Python simulator's after set_friction with the same numbers; the path stuck and
    slipped, and the friction changed the force and the stiffness."""
    K, Kpy, K0 = np.zeros(9), np.zeros((3, 3)), np.zeros((3, 3))
    force = c_double3()
    span = np.abs(model.vertices).max()
    for response, (mu_s, mu_d, kt) in friction_configurations(model):
        sim = load(lib, small_artifact, response=CODES[response])
        registered = newest_registered()
        py, frictionless = model.simulator(response=response), model.simulator(response=response)
        assert lib.hapticrom_set_friction(sim, mu_s, mu_d, kt) == S["OK"], last_error(lib)
        py.set_friction(mu_s, mu_d, kt or None)
        assert registered.friction == py.friction  # 0 from C: the simulator's default, 2/3
        assert state(lib, sim).sequence == 1  # a writing call
        tips = scripted(model, 150, py.tool_radius)
        forces, expected, plain = [], [], []
        slipped = stuck = 0
        tangential = stiff = 0.0
        for k, tip in enumerate(tips):
            assert lib.hapticrom_step_position(sim, ptr(tip), force) == S["OK"], last_error(lib)
            forces.append(list(force))
            expected.append(py.step_position(tip).copy())
            plain.append(frictionless.step_position(tip).copy())
            assert lib.hapticrom_stiffness(sim, ptr(K)) == S["OK"], last_error(lib)
            py.stiffness(Kpy)
            frictionless.stiffness(K0)
            s = state(lib, sim)
            assert (s.in_contact, s.slipping, s.saturated, s.sequence) == (
                py.in_contact, py.slipping, py.saturated, k + 2,
            )  # fmt: skip
            assert_close(s.proxy, py.proxy, span, "proxy")
            assert_close(s.contact_point, py.contact_point, span, "contact point")
            assert_close(s.depth, py.depth, model.trained_depth, "depth")
            assert_close(K, Kpy.ravel(), max(np.abs(Kpy).max(), 1e-300), "stiffness")
            slipped += py.slipping
            stuck += py.in_contact and not py.slipping
            stiff = max(stiff, np.abs(Kpy).max())
            tangential = max(tangential, np.abs(Kpy - K0).max())
        peak = np.abs(expected).max()
        assert peak > 0.1 * model.trained_force and slipped > 0 and stuck > 0, (slipped, stuck)
        assert np.abs(np.subtract(expected, plain)).max() > 0.01 * peak  # the friction acted
        assert tangential > 0.1 * stiff  # and the stiffness has its tangential terms
        assert_close(forces, expected, peak, "forces")
        assert lib.hapticrom_free(sim) == S["OK"]


NAN, INF = float("nan"), float("inf")
BAD_FRICTION = [  # hapticrom_set_friction's arguments, the status, words of the message
    ((NAN, MU_D, 0.0), "NOT_FINITE", "static friction coefficient"),
    ((MU_S, INF, 0.0), "NOT_FINITE", "dynamic friction coefficient"),
    ((MU_S, MU_D, NAN), "NOT_FINITE", "tangential_stiffness"),
    ((MU_S, MU_D, -INF), "NOT_FINITE", "tangential_stiffness"),
    ((-0.1, 0.0, 0.0), "INVALID_OPTION", "static friction coefficient"),
    ((MU_S, -MU_D, 0.0), "INVALID_OPTION", "dynamic friction coefficient"),
    ((MU_D, MU_S, 0.0), "INVALID_OPTION", "must not exceed the static one"),
    ((11.0, 1.0, 0.0), "INVALID_OPTION", "[0, 10"),
    ((MU_S, MU_D, -1.0), "INVALID_OPTION", "tangential_stiffness"),
    ((MU_S, MU_D, 11.0), "INVALID_OPTION", "at most 10"),
]


def test_set_friction_refuses_bad_coefficients_and_changes_nothing(lib, model, small_artifact):
    """NaN, infinite, negative, too large coefficients, dynamic above static, a made-up or
    a freed handle: a status and the simulator's own message, and nothing changes (not the
    state, not its number, not the friction: the path goes on as the Python simulator's
    with the friction set before the refusals)."""
    sim, py = load(lib, small_artifact), model.simulator()
    registered = newest_registered()
    assert lib.hapticrom_set_friction(sim, MU_S, MU_D, 0.0) == S["OK"], last_error(lib)
    py.set_friction(MU_S, MU_D)
    tips, force = scripted(model, 100), c_double3()
    for tip in tips[:50]:  # into the slide: in contact
        assert lib.hapticrom_step_position(sim, ptr(tip), force) == S["OK"]
        py.step_position(tip)
    before, friction = state(lib, sim), registered.friction
    assert before.in_contact and friction == py.friction
    for arguments, expected, words in BAD_FRICTION:
        refused(lib, lib.hapticrom_set_friction(sim, *arguments), expected,
                "hapticrom_set_friction", words, "nothing changed")  # fmt: skip
    refused(lib, lib.hapticrom_set_friction(0, MU_S, MU_D, 0.0), "BAD_HANDLE",
            "hapticrom_set_friction", "not a simulator handle")  # fmt: skip
    after = state(lib, sim)
    for field, _ in State._fields_:  # the sequence too: refused before anything was written
        assert np.array_equal(np.ravel(getattr(after, field)),
                              np.ravel(getattr(before, field))), field  # fmt: skip
    assert registered.friction == friction
    for tip in tips[50:]:
        assert lib.hapticrom_step_position(sim, ptr(tip), force) == S["OK"], last_error(lib)
        assert_close(list(force), py.step_position(tip), model.trained_force, "force")
        assert state(lib, sim).slipping == py.slipping
    assert lib.hapticrom_free(sim) == S["OK"]
    refused(lib, lib.hapticrom_set_friction(sim, MU_S, MU_D, 0.0), "BAD_HANDLE",
            "hapticrom_set_friction", "freed")  # fmt: skip


# -- bad input across the ABI --------------------------------------------------------------------
def test_loading_refuses_bad_paths_artifacts_and_options(lib, small_artifact, tmp_path):
    sim = ctypes.c_uint64(7)
    path = str(small_artifact).encode()
    refused(lib, lib.hapticrom_load(None, None, ctypes.byref(sim)), "NULL_ARGUMENT",
            "hapticrom_load", "artifact_path")  # fmt: skip
    assert sim.value == 0  # the out handle is cleared on failure
    refused(lib, lib.hapticrom_load(path, None, None), "NULL_ARGUMENT", "simulator")
    missing = str(tmp_path / "missing.h5").encode()
    refused(lib, lib.hapticrom_load(missing, None, ctypes.byref(sim)), "LOAD_FAILED",
            "missing.h5", "not found")  # fmt: skip
    damaged = bytearray(small_artifact.read_bytes())
    damaged[USERBLOCK + (len(damaged) - USERBLOCK) // 2] ^= 0x5A
    (tmp_path / "damaged.h5").write_bytes(bytes(damaged))
    corrupt = str(tmp_path / "damaged.h5").encode()
    refused(lib, lib.hapticrom_load(corrupt, None, ctypes.byref(sim)), "LOAD_FAILED",
            "damaged.h5", "checksum")  # fmt: skip
    assert sim.value == 0
    bad_options = [({"size": 8}, "options.size"), ({"isolate": 2}, "isolate"),
                   ({"interpolation": 4}, "interpolation"), ({"response": -1}, "response"),
                   ({"max_force": -1.0}, "max_force"),
                   ({"max_displacement": float("nan")}, "max_displacement"),
                   ({"tool_radius": -1.0}, "tool_radius"),
                   ({"tool_radius": float("inf")}, "tool_radius"),
                   ({"tool_radius": 1e9}, "tool radius")]  # fmt: skip
    for fields, word in bad_options:
        o = options(lib, **fields)
        refused(lib, lib.hapticrom_load(path, ctypes.byref(o), ctypes.byref(sim)),
                "INVALID_OPTION", word)  # fmt: skip
    assert abi_module().open_count() == 0  # nothing kept of a refused load


def test_the_default_load_parses_in_a_child_process(lib, small_artifact):
    sim = ctypes.c_uint64()
    assert lib.hapticrom_load(str(small_artifact).encode(), None, ctypes.byref(sim)) == S["OK"]
    assert lib.hapticrom_free(sim.value) == S["OK"]


def test_null_pointers_are_refused_by_every_call(lib, small_artifact):
    sim = load(lib, small_artifact)
    v = np.zeros(3)
    calls = {
        "hapticrom_set_contact": lambda: lib.hapticrom_set_contact(sim, None),
        "hapticrom_step_displacement": lambda: lib.hapticrom_step_displacement(sim, None, ptr(v)),
        "hapticrom_step_force": lambda: lib.hapticrom_step_force(sim, ptr(v), None),
        "hapticrom_step_position": lambda: lib.hapticrom_step_position(sim, None, ptr(v)),
        "hapticrom_stiffness": lambda: lib.hapticrom_stiffness(sim, None),
        "hapticrom_contact_stiffness": lambda: lib.hapticrom_contact_stiffness(sim, None),
        "hapticrom_error_estimate": lambda: lib.hapticrom_error_estimate(sim, None),
        "hapticrom_get_state": lambda: lib.hapticrom_get_state(sim, None),
        "hapticrom_surface": lambda: lib.hapticrom_surface(sim, None, 3, None),
        "hapticrom_get_info": lambda: lib.hapticrom_get_info(sim, None),
        "hapticrom_surface_mesh": lambda: lib.hapticrom_surface_mesh(sim, ptr(v), 3, None, 3),
        "hapticrom_sample_points": lambda: lib.hapticrom_sample_points(sim, None, 3),
    }
    for name, call in calls.items():
        refused(lib, call(), "NULL_ARGUMENT", name, "NULL")
    assert state(lib, sim).sequence == 0  # nothing was written
    assert lib.hapticrom_free(sim) == S["OK"]


def test_bad_numbers_are_refused_and_the_state_kept(lib, model, small_artifact):
    sim = load(lib, small_artifact, max_displacement=0.5 * model.trained_depth)
    out, value = c_double3(), ctypes.c_double()
    d = np.array([0.0, 0.0, -0.1 * model.trained_depth])
    refused(lib, lib.hapticrom_step_displacement(sim, ptr(d), out), "NO_CONTACT",
            "hapticrom_set_contact first")  # fmt: skip
    refused(lib, lib.hapticrom_step_force(sim, ptr(d), out), "NO_CONTACT")
    refused(lib, lib.hapticrom_contact_stiffness(sim, ctypes.byref(value)), "NO_CONTACT")
    refused(lib, lib.hapticrom_error_estimate(sim, ctypes.byref(value)), "NO_CONTACT")
    assert not state(lib, sim).has_contact
    p = np.ascontiguousarray(model.sample_points[0])
    assert lib.hapticrom_set_contact(sim, ptr(p)) == S["OK"]
    n = np.array(state(lib, sim).normal)
    assert lib.hapticrom_step_displacement(sim, ptr(-0.2 * model.trained_depth * n), out) == 0
    before = state(lib, sim)
    for bad in (np.nan, np.inf, -np.inf):
        x = np.array([0.0, bad, 0.0])
        refused(lib, lib.hapticrom_set_contact(sim, ptr(x)), "NOT_FINITE", "contact point")
        refused(lib, lib.hapticrom_step_displacement(sim, ptr(x), out), "NOT_FINITE",
                "displacement")  # fmt: skip
        refused(lib, lib.hapticrom_step_force(sim, ptr(x), out), "NOT_FINITE", "force")
    refused(lib, lib.hapticrom_step_displacement(sim, ptr(-model.trained_depth * n), out),
            "BEYOND_LIMIT", "limit")  # fmt: skip
    huge = -2 * model.force[:, -1].max() * n
    refused(lib, lib.hapticrom_step_force(sim, ptr(huge), out), "DISPLACEMENT_LIMIT",
            "max_displacement")  # fmt: skip
    after = state(lib, sim)
    for field in ("normal", "force", "displacement"):
        assert list(getattr(after, field)) == list(getattr(before, field))
    assert (after.depth, after.flags) == (before.depth, before.flags)
    assert lib.hapticrom_free(sim) == S["OK"]


def test_wrong_buffer_sizes_are_refused(lib, model, small_artifact):
    sim = load(lib, small_artifact)
    V, T, P = len(model.vertices), len(model.triangles), len(model.indicator)
    big = np.zeros(3 * max(V, T, P) + 3)
    triangles = np.zeros(3 * T + 3, dtype=np.uint32)
    for length in (0, 3 * V - 1, 3 * V + 3, V):
        refused(lib, lib.hapticrom_surface(sim, ptr(big), length, None), "WRONG_SIZE",
                f"3 x {V} vertices")  # fmt: skip
    refused(lib, lib.hapticrom_surface_mesh(sim, ptr(big), 3 * V, ptr(triangles), 3 * T + 3),
            "WRONG_SIZE", "triangles_length")  # fmt: skip
    refused(lib, lib.hapticrom_surface_mesh(sim, ptr(big), 3 * V - 3, ptr(triangles), 3 * T),
            "WRONG_SIZE", "vertices_length")  # fmt: skip
    refused(lib, lib.hapticrom_sample_points(sim, ptr(big), 3 * P + 3), "WRONG_SIZE", str(P))
    assert lib.hapticrom_free(sim) == S["OK"]


def test_calls_after_free_and_made_up_handles_are_refused(lib, model, small_artifact):
    sim = load(lib, small_artifact)
    assert abi_module().open_count() == 1
    assert lib.hapticrom_free(sim) == S["OK"]
    assert abi_module().open_count() == 0  # the Python side let go of the arrays
    v, out = np.zeros(3), np.zeros(3 * len(model.vertices))
    s, i, value = State(), Info(), ctypes.c_double()
    triangles = np.zeros(3 * len(model.triangles), dtype=np.uint32)
    reused = load(lib, small_artifact)  # likely the freed slot, a new generation
    magic = sim & ~((1 << 48) - 1)
    for handle in (sim, 0, 1, 2**64 - 1, magic, magic | (1 << 48) - 1, sim ^ (1 << 20)):
        if handle == reused:
            continue
        calls = [
            lib.hapticrom_set_contact(handle, ptr(v)),
            lib.hapticrom_step_displacement(handle, ptr(v), ptr(v)),
            lib.hapticrom_step_force(handle, ptr(v), ptr(v)),
            lib.hapticrom_step_position(handle, ptr(v), ptr(v)),
            lib.hapticrom_stiffness(handle, ptr(out)),
            lib.hapticrom_contact_stiffness(handle, ctypes.byref(value)),
            lib.hapticrom_error_estimate(handle, ctypes.byref(value)),
            lib.hapticrom_get_state(handle, ctypes.byref(s)),
            lib.hapticrom_surface(handle, ptr(out), out.size, None),
            lib.hapticrom_get_info(handle, ctypes.byref(i)),
            lib.hapticrom_surface_mesh(
                handle, ptr(out), out.size, ptr(triangles), triangles.size
            ),  # fmt: skip
            lib.hapticrom_sample_points(handle, ptr(out), 3),
            lib.hapticrom_set_friction(handle, MU_S, MU_D, 0.0),
            lib.hapticrom_free(handle),
        ]
        assert calls == [S["BAD_HANDLE"]] * len(calls), (hex(handle), calls)
    refused(lib, lib.hapticrom_free(sim), "BAD_HANDLE", "hapticrom_free")
    assert state(lib, reused).sequence == 0  # the live one is untouched
    assert lib.hapticrom_free(reused) == S["OK"]
    refused(lib, lib.hapticrom_free(reused), "BAD_HANDLE", "freed already")


# -- threads ---------------------------------------------------------------------------------------
def busy_seen(lib, sim, inside, probe, seconds: float = 20.0) -> tuple[int, dict]:
    """Run ``inside`` in a loop on a thread while this one calls ``probe``: the probe's
    statuses until it saw BUSY (or ``seconds`` passed)."""
    stop = threading.Event()
    worker_statuses: dict[int, int] = {}

    def work():
        while not stop.is_set():
            status = inside()
            worker_statuses[status] = worker_statuses.get(status, 0) + 1

    thread = threading.Thread(target=work)
    thread.start()
    seen: dict[int, int] = {}
    deadline = time.monotonic() + seconds
    try:
        while S["BUSY"] not in seen and time.monotonic() < deadline:
            status = probe()
            seen[status] = seen.get(status, 0) + 1
            if status == S["BUSY"]:
                message = last_error(lib)
    finally:
        stop.set()
        thread.join()
    assert S["BUSY"] in seen, f"no BUSY in {seconds} s: {seen}"
    assert "another thread" in message, message
    return seen, worker_statuses


def test_a_second_thread_inside_a_simulator_gets_busy(lib, model, small_artifact):
    """The servo calls are one thread's, the render calls another's: a second thread in either
    gets BUSY at once (and so does the first thread while the second is inside: on a loaded
    machine the second thread is preempted inside a call now and then; nothing but OK and
    BUSY either way)."""
    sim = load(lib, small_artifact)
    p = np.ascontiguousarray(model.sample_points[0])
    s, i = State(), Info()
    out = np.zeros(3 * len(model.vertices))
    assert lib.hapticrom_set_contact(sim, ptr(p)) == S["OK"]
    K, F = np.zeros(9), np.zeros(3)
    for inside, probe in [
        (lambda: lib.hapticrom_set_contact(sim, ptr(p)),
         lambda: lib.hapticrom_get_state(sim, ctypes.byref(s))),
        (lambda: lib.hapticrom_step_position(sim, ptr(p), ptr(F)),
         lambda: lib.hapticrom_stiffness(sim, ptr(K))),
        (lambda: lib.hapticrom_surface(sim, ptr(out), out.size, None),
         lambda: lib.hapticrom_get_info(sim, ctypes.byref(i))),
    ]:  # fmt: skip
        seen, worker = busy_seen(lib, sim, inside, probe)
        assert set(seen) <= {S["OK"], S["BUSY"]} and set(worker) <= {S["OK"], S["BUSY"]}
        assert worker.get(S["OK"], 0) > 0, (seen, worker)
    assert lib.hapticrom_free(sim) == S["OK"]


def test_free_while_another_thread_steps_never_crashes(lib, model, small_artifact):
    sim = load(lib, small_artifact)
    p = np.ascontiguousarray(model.sample_points[0])
    d = np.array([0.0, 0.0, 0.0])
    out = c_double3()
    statuses: list[int] = []
    started = threading.Event()

    def servo():
        while True:
            status = lib.hapticrom_set_contact(sim, ptr(p))
            if status == S["OK"]:
                status = lib.hapticrom_step_displacement(sim, ptr(d), out)
            statuses.append(status)
            started.set()
            if status != S["OK"]:
                return

    thread = threading.Thread(target=servo)
    thread.start()
    started.wait(10)
    assert lib.hapticrom_free(sim) == S["OK"]
    thread.join(10)
    assert not thread.is_alive()
    assert set(statuses[:-1]) == {S["OK"]} and statuses[-1] == S["BAD_HANDLE"]


def test_set_friction_while_the_servo_steps_waits_and_never_crashes(lib, model, small_artifact):
    """A servo thread stepping the path round and round while another thread sets the
    friction over and over (two settings in turn), then frees the simulator: every
    set_friction succeeds until the free (it waits for a step inside, it is never refused for
    the servo thread's sake), the servo's calls are OK (or BUSY: the nanoseconds of a
    write), the last friction set holds, and both threads end with BAD_HANDLE."""
    sim = load(lib, small_artifact)
    registered = newest_registered()
    tips = scripted(model, 100)
    settings = [(MU_S, MU_D, 0.0), (0.8, 0.2, 1.5)]
    servo_statuses: dict[int, int] = {}
    setter_statuses: list[int] = []
    stop_setting, freed = threading.Event(), threading.Event()

    def servo():
        force, k, done = c_double3(), 0, False
        while not done:  # the last call after the free: BAD_HANDLE
            done = freed.is_set()
            status = lib.hapticrom_step_position(sim, ptr(tips[k % len(tips)]), force)
            servo_statuses[status] = servo_statuses.get(status, 0) + 1
            k += 1

    def setter():
        k = 0
        while not (stop_setting.is_set() and k % 2 == 0):  # the last one set: settings[1]
            status = lib.hapticrom_set_friction(sim, *settings[k % 2])
            setter_statuses.append(status)
            k += 1
            if status != S["OK"]:
                return

    threads = [threading.Thread(target=servo), threading.Thread(target=setter)]
    for thread in threads:
        thread.start()
    try:
        time.sleep(1.0)
        stop_setting.set()
        threads[1].join(60)
        assert not threads[1].is_alive()
    finally:
        stop_setting.set()
        friction = registered.friction
        assert lib.hapticrom_free(sim) == S["OK"]
        freed.set()
        for thread in threads:
            thread.join(60)
    assert not any(thread.is_alive() for thread in threads)
    assert set(setter_statuses) == {S["OK"]} and len(setter_statuses) >= 2, setter_statuses
    py = model.simulator()
    py.set_friction(*settings[1])
    assert friction == py.friction
    assert set(servo_statuses) <= {S["OK"], S["BUSY"], S["BAD_HANDLE"]}, servo_statuses
    assert servo_statuses[S["OK"]] > 10 and servo_statuses[S["BAD_HANDLE"]] > 0, servo_statuses
    refused(lib, lib.hapticrom_set_friction(sim, *settings[0]), "BAD_HANDLE", "freed")


# -- the example host: C with CPython embedded ---------------------------------------------------
def run_example(binary: Path, model_path: Path, tmp: Path, *args: str, env=None):
    """Run the example host; (its stdout, the forces CSV rows, the rendered frames)."""
    forces, surfaces = tmp / "forces.csv", tmp / "surfaces.bin"
    result = subprocess.run(
        [str(binary), str(model_path), "--forces", str(forces), "--surfaces", str(surfaces),
         *args], capture_output=True, text=True, timeout=600, env=env or os.environ.copy(),
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    rows = np.loadtxt(forces, delimiter=",", skiprows=1)
    raw = np.fromfile(surfaces, dtype=np.uint8)
    V = int(raw[:8].view(np.uint64)[0])
    frames = raw[8:].reshape(-1, 8 + 24 * V)
    sequences = frames[:, :8].copy().view(np.uint64).ravel().astype(np.int64)
    fields = frames[:, 8:].copy().view(np.float64).reshape(len(frames), V, 3)
    return result, rows, sequences, fields


@pytest.fixture(scope="module")
def paced(built, small_artifact, tmp_path_factory):
    """The example as a haptic host runs it: 1 kHz servo, 60 Hz render, 2 s."""
    return run_example(built / "servo_loop", small_artifact, tmp_path_factory.mktemp("paced"))


def python_forces(model, rows) -> np.ndarray:
    """The Python runtime along the example's contact points and depths."""
    sim = model.simulator()
    forces = np.zeros((len(rows), 3))
    for k, row in enumerate(rows):
        sim.set_contact(np.ascontiguousarray(row[1:4]))
        forces[k] = sim.step_displacement(np.multiply(sim.contact_normal, -row[4]))
    return forces


def test_forces_from_c_equal_the_python_runtimes(model, paced):
    result, rows, _, _ = paced
    assert "2000 ticks" in result.stdout
    assert np.all(rows[:, 8] == 0)  # every tick's status
    forces, expected = rows[:, 5:8], python_forces(model, rows)
    scale = np.abs(expected).max()
    assert scale > 0.1 * model.trained_force  # the path pressed
    assert np.abs(forces - expected).max() <= 1e-12 * scale


def replayed_writes(model, rows, position: bool, friction=None):
    """The Python simulator replaying the example's ticks: (the state's number, the
    simulator) after each of the example's writes. A tick is set_contact (numbered rows[k,
    9]) and its step (one more), or with tips one step_position (numbered rows[k, 9]);
    ``friction``: set_friction's arguments, set before the first tick (as --friction)."""
    sim = model.simulator()
    if friction is not None:
        sim.set_friction(*friction)
    for row in rows:
        if position:
            sim.step_position(np.ascontiguousarray(row[1:4]))
            yield int(row[9]), sim
            continue
        sim.set_contact(np.ascontiguousarray(row[1:4]))
        yield int(row[9]), sim
        sim.step_displacement(np.multiply(sim.contact_normal, -row[4]))
        yield int(row[9]) + 1, sim


def python_surfaces(model, rows, wanted: set[int], position: bool,
                    friction=None) -> dict[int, np.ndarray]:  # fmt: skip
    """The Python simulator's surface at each wanted state of the example's path."""
    out, surfaces = np.zeros_like(model.vertices), {}
    for sequence, sim in replayed_writes(model, rows, position, friction):
        if sequence > max(wanted):
            break
        if sequence in wanted:
            surfaces[sequence] = sim.surface_displacement(out).copy()
    return surfaces


def assert_untorn(model, rows, sequences, fields, position: bool = False,
                  friction=None) -> None:  # fmt: skip
    """Every rendered frame is the Python surface of the state its sequence names."""
    assert np.all(np.diff(rows[:, 9]) == (1 if position else 2))  # the example's writes a tick
    expected = python_surfaces(model, rows, set(sequences.tolist()), position, friction)
    assert set(expected) == set(sequences.tolist())  # every frame is of a state of the path
    scale = max(np.abs(s).max() for s in expected.values())
    assert scale > 0
    for sequence, field in zip(sequences, fields, strict=True):
        assert np.abs(field - expected[sequence]).max() <= 1e-12 * scale, sequence


def test_the_render_thread_reads_whole_states_at_60_hz(model, paced):
    _, rows, sequences, fields = paced
    # ~120 frames at 60 Hz over 2 s (fewer on a loaded machine), from start to end of the path
    assert len(sequences) >= 30 and np.all(np.diff(sequences) >= 0)
    assert sequences[0] < 0.2 * rows[-1, 9] and sequences[-1] > 0.8 * rows[-1, 9]
    assert_untorn(model, rows, sequences, fields)


def test_a_free_running_servo_never_tears_the_rendered_surface(built, model, small_artifact,
                                                                tmp_path):  # fmt: skip
    """The servo thread as fast as it goes (50,000 ticks, writing nearly all the time), the
    renderer at 1 kHz: each surface is one state's, whichever the snapshot caught (a renderer
    that found no pause between the writes gets BUSY: the example skips that frame)."""
    result, rows, sequences, fields = run_example(
        built / "servo_loop", small_artifact, tmp_path, "--seconds", "0.05", "--rate", "1e6",
        "--render-rate", "1000",
    )  # fmt: skip
    assert len(rows) == 50000 and np.all(rows[:, 8] == 0)
    assert len(np.unique(sequences)) > 50, result.stdout  # many states caught in flight
    assert_untorn(model, rows, sequences, fields)


def write_tips(path: Path, tips: np.ndarray, rate: float = 1000.0) -> Path:
    """The tip file of ``tips`` (rows t, x, y, z) through examples/c/scripted_tips.py's writer."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("scripted_tips", SCRIPTED_TIPS)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.write_tips(path, tips, rate)
    return path


SCRIPTED_TIPS = ROOT / "examples" / "c" / "scripted_tips.py"


@pytest.fixture(scope="module")
def paced_position(built, model, small_artifact, tmp_path_factory):
    """The example position in, force out: play's scripted path written by
    examples/c/scripted_tips.py (2,000 tips), 1 kHz servo, 60 Hz render; and the tips."""
    tmp = tmp_path_factory.mktemp("paced-position")
    written = subprocess.run(
        [sys.executable, str(SCRIPTED_TIPS), str(small_artifact),
         str(tmp / "tips.csv"), "--ticks", "2000"], capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert written.returncode == 0, written.stderr
    run = run_example(built / "servo_loop", small_artifact, tmp, "--tips", str(tmp / "tips.csv"))
    return (*run, scripted(model, 2000))


def python_positions(model, rows, friction=None) -> dict[str, np.ndarray]:
    """The Python runtime's step_position along the example's tips (after set_friction(
    *friction), if given): forces, in contact, saturated, proxy, slipping."""
    sim = model.simulator()
    if friction is not None:
        sim.set_friction(*friction)
    out = {"forces": np.zeros((len(rows), 3)), "proxy": np.zeros((len(rows), 3)),
           "in_contact": np.zeros(len(rows)), "saturated": np.zeros(len(rows)),
           "slipping": np.zeros(len(rows))}  # fmt: skip
    for k, row in enumerate(rows):
        out["forces"][k] = sim.step_position(np.ascontiguousarray(row[1:4]))
        out["proxy"][k], out["in_contact"][k] = sim.proxy, sim.in_contact
        out["saturated"][k], out["slipping"][k] = sim.saturated, sim.slipping
    return out


def test_forces_from_cs_step_position_equal_the_python_runtimes(model, paced_position):
    """The example's servo thread, position in, force out, along play's scripted path: the
    tips it read are the path's, its forces, proxies and contact flags the Python
    simulator's."""
    result, rows, _, _, tips = paced_position
    assert "2000 ticks" in result.stdout and "position in, force out" in result.stdout
    np.testing.assert_array_equal(rows[:, 1:4], tips)  # 17 digits: the doubles round-trip
    assert np.all(rows[:, 8] == 0)  # every tick's status
    expected = python_positions(model, rows)
    scale = np.abs(expected["forces"]).max()
    assert scale > 0.1 * model.trained_force  # the path pressed
    assert 0 < expected["in_contact"].sum() < len(rows)  # and was free too
    assert_close(rows[:, 5:8], expected["forces"], scale, "forces")
    np.testing.assert_array_equal(rows[:, 10], expected["in_contact"])
    np.testing.assert_array_equal(rows[:, 11], expected["saturated"])
    assert_close(rows[:, 12:15], expected["proxy"], np.abs(model.vertices).max(), "proxy")
    assert not rows[:, 15].any()  # frictionless: never slipping


@pytest.fixture(scope="module")
def paced_friction(built, small_artifact, paced_position, tmp_path_factory):
    """The example position in, force out with --friction MU_S,MU_D: the same 2,000 tips
    (written by examples/c/scripted_tips.py's writer), 1 kHz servo, 60 Hz render."""
    tmp = tmp_path_factory.mktemp("paced-friction")
    tips = write_tips(tmp / "tips.csv", paced_position[4])
    return run_example(built / "servo_loop", small_artifact, tmp, "--tips", str(tips),
                       "--friction", f"{MU_S},{MU_D}")  # fmt: skip


def test_forces_from_cs_step_position_with_friction_equal_the_python_runtimes(
    model, paced_position, paced_friction
):
    """The example's servo thread with hapticrom_set_friction(MU_S, MU_D, 0) before the loop,
    along play's scripted path: its forces, proxies, contact and slipping flags are the
    Python simulator's after set_friction(MU_S, MU_D); the path stuck and slipped, and the
    friction changed the forces from the frictionless run's."""
    result, rows, _, _ = paced_friction
    assert f"friction: static {MU_S:g}, dynamic {MU_D:g}" in result.stdout, result.stdout
    np.testing.assert_array_equal(rows[:, 1:4], paced_position[4])
    assert np.all(rows[:, 8] == 0)  # every tick's status
    expected = python_positions(model, rows, (MU_S, MU_D))
    scale = np.abs(expected["forces"]).max()
    assert scale > 0.1 * model.trained_force  # the path pressed
    slipping = int(expected["slipping"].sum())
    assert 0 < slipping < expected["in_contact"].sum()  # it slid, and stuck too
    assert f"{slipping} slipping" in result.stdout, result.stdout
    assert_close(rows[:, 5:8], expected["forces"], scale, "forces")
    for column, name in ((10, "in_contact"), (11, "saturated"), (15, "slipping")):
        np.testing.assert_array_equal(rows[:, column], expected[name], name)
    assert_close(rows[:, 12:15], expected["proxy"], np.abs(model.vertices).max(), "proxy")
    frictionless = paced_position[1][:, 5:8]
    assert np.abs(rows[:, 5:8] - frictionless).max() > 0.01 * scale  # the friction acted


def test_the_render_thread_reads_whole_states_with_friction(model, paced_friction):
    """set_friction is a writing call (the first state's number is 1); every frame is the
    Python surface, friction on, of the state its sequence names."""
    _, rows, sequences, fields = paced_friction
    assert rows[0, 9] == 2 and len(sequences) >= 30
    assert_untorn(model, rows, sequences, fields, position=True, friction=(MU_S, MU_D))


def test_the_example_refuses_bad_friction(built, small_artifact):
    """--friction that is not 2 or 3 numbers: usage (2), before loading; numbers the library
    refuses: its status and message (1)."""
    for value in ("0.5", "0.5,x", "0.5,0.3,1,2", "0.5,0.3,", ""):
        command = [str(built / "servo_loop"), str(small_artifact), "--friction", value]
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert result.returncode == 2 and "usage" in result.stderr, (value, result.stderr)
    refusals = {"0.3,0.5": ["must not exceed", "HAPTICROM_E_INVALID_OPTION"],
                "nan,0.1": ["static friction coefficient", "HAPTICROM_E_NOT_FINITE"]}  # fmt: skip
    for value, words in refusals.items():
        command = [str(built / "servo_loop"), str(small_artifact), "--friction", value]
        result = subprocess.run(command, capture_output=True, text=True, timeout=600)
        assert result.returncode == 1, (value, result.stdout, result.stderr)
        for word in ["hapticrom_set_friction", *words]:
            assert word in result.stderr, (value, result.stderr)


def test_the_render_thread_reads_whole_states_of_step_position(model, paced_position):
    _, rows, sequences, fields, _ = paced_position
    assert len(sequences) >= 30 and np.all(np.diff(sequences) >= 0)
    assert sequences[0] < 0.2 * rows[-1, 9] and sequences[-1] > 0.8 * rows[-1, 9]
    assert_untorn(model, rows, sequences, fields, position=True)


def test_a_free_running_step_position_servo_never_tears_the_rendered_surface(
    built, model, small_artifact, tmp_path
):
    """As the set_contact servo above, with step_position: 50,000 tips as fast as it goes
    (the proxy's state is written too), the renderer at 1 kHz."""
    tips = write_tips(tmp_path / "tips.csv", scripted(model, 50000), rate=1e6)
    result, rows, sequences, fields = run_example(
        built / "servo_loop", small_artifact, tmp_path, "--tips", str(tips), "--rate", "1e6",
        "--render-rate", "1000",
    )  # fmt: skip
    assert len(rows) == 50000 and np.all(rows[:, 8] == 0)
    assert len(np.unique(sequences)) > 50, result.stdout
    assert_untorn(model, rows, sequences, fields, position=True)


def test_the_position_bench_reports_every_call(built, model, small_artifact, tmp_path):
    """``servo_loop --tips --bench`` (what make capi-bench runs): a latency line for each
    call, the contact and free ticks counted apart (they add up to the calls), and the
    constant work timed beside each surface, with both shares over 50 us."""
    tips = write_tips(tmp_path / "tips.csv", scripted(model, 300))
    command = [str(built / "servo_loop"), str(small_artifact), "--tips", str(tips), "--bench",
               "3000", "--bench-surfaces", "5"]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    calls = {m[1].strip(): int(m[2]) for m in re.finditer(r"^(.{20}) +(\d+) calls", result.stdout,
                                                          re.MULTILINE)}  # fmt: skip
    named = ("step_position", "stiffness", "get_state", "surface", "constant work")
    assert {k: calls[k] for k in named} == {
        "step_position": 3000,
        "stiffness": 3000,
        "get_state": 3000,
        "surface": 5,
        "constant work": 5,
    }
    assert re.search(r"^surface over 50 us: [\d.]+ % of calls, the constant work beside it "
                     r"[\d.]+ %$", result.stdout, re.MULTILINE), result.stdout  # fmt: skip
    assert calls["in contact"] + calls["free"] == 3000 and calls["in contact"] > 0


BAD_TIPS = {  # file content: words of the example's message
    "t,x,y,z\n0,1,2\n": ["line 2", "4 finite numbers"],
    "0,1,2,nan\n": ["line 1", "finite"],
    "0,1,2,3\n0,1,-inf,3\n": ["line 2"],
    "0,1,2,3,4\n": ["line 1"],
    "0,1,2,3x\n": ["line 1"],
    "0,1,2,\n": ["line 1"],
    "0,20000,0,0\n": ["line 1", "<= 10000"],
    "t,x,y,z\n": ["no rows"],
    "# a comment only\n\n": ["no rows"],
    "": ["no rows"],
    "0,1,2,3\n" + "0" * 5000 + "\n": ["line 2", "longer than 4096"],
    "0,1,2,3\n0,1\x00,2,3\n": ["line 2", "NUL"],
}


def test_a_bad_tip_file_is_refused_before_loading(built, small_artifact, tmp_path):
    """Each bad tip file: exit 1 and one message naming the file and the line, before the
    model is loaded (nothing runs)."""
    files = {}
    for i, content in enumerate(BAD_TIPS):
        files[tmp_path / f"bad{i}.csv"] = BAD_TIPS[content]
        (tmp_path / f"bad{i}.csv").write_bytes(content.encode())
    files[tmp_path / "missing.csv"] = ["No such file"]
    files[tmp_path] = ["--tips"]  # a directory
    for path, words in files.items():
        command = [str(built / "servo_loop"), str(small_artifact), "--tips", str(path)]
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert result.returncode == 1, (path, result.stdout, result.stderr)
        assert "loaded" not in result.stdout and str(path) in result.stderr, result.stderr
        for word in words:
            assert word in result.stderr, (path.name, result.stderr)


def test_a_host_without_its_python_gets_an_error_not_a_crash(built, small_artifact):
    """HAPTICROM_PYTHON naming no interpreter: the load fails with PYTHON and a message."""
    env = {**os.environ, "HAPTICROM_PYTHON": "/nonexistent/python"}
    result = subprocess.run([str(built / "servo_loop"), str(small_artifact)], env=env,
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert result.returncode == 1, result.stdout + result.stderr
    assert "no Python executable at '/nonexistent/python'" in result.stderr
    assert "HAPTICROM_E_PYTHON" in result.stderr


# -- sanitizers ------------------------------------------------------------------------------------
def sanitizer_available() -> str | None:
    """None if gcc builds and runs with AddressSanitizer here, else why not."""
    if shutil.which("gcc") is None:
        return "no gcc"
    probe = BUILD / "asan-probe"
    BUILD.mkdir(exist_ok=True)
    compiled = subprocess.run(["gcc", "-fsanitize=address", "-x", "c", "-", "-o", str(probe)],
                              input="int main(void) { return 0; }\n", capture_output=True,
                              text=True)  # fmt: skip
    if compiled.returncode != 0:
        return f"gcc cannot build with -fsanitize=address (libasan missing?): {compiled.stderr}"
    return None


def test_the_example_runs_clean_under_address_sanitizer(built, small_artifact, tmp_path):
    """AddressSanitizer and UBSan over the library and the example (the embedded interpreter
    and numpy/numba are not instrumented: LeakSanitizer ignores what they allocate, see
    capi/lsan.supp; a leak of the library or the example is reported)."""
    reason = sanitizer_available()
    if reason:
        pytest.skip(reason)
    make("capi-asan")
    env = os.environ.copy()
    env["ASAN_OPTIONS"] = "detect_leaks=1:abort_on_error=0:exitcode=99"
    env["UBSAN_OPTIONS"] = "print_stacktrace=1:halt_on_error=1:exitcode=98"
    env["LSAN_OPTIONS"] = f"suppressions={ROOT / 'capi' / 'lsan.supp'}:print_suppressions=0"
    env.pop("LD_PRELOAD", None)
    result, rows, sequences, _ = run_example(
        BUILD / "asan" / "servo_loop", small_artifact, tmp_path, "--seconds", "0.5",
        "--render-rate", "200", env=env,
    )  # fmt: skip
    assert "Sanitizer" not in result.stderr and "runtime error" not in result.stderr, result.stderr
    assert len(rows) == 500 and len(sequences) > 10


def test_step_position_and_the_tip_reader_run_clean_under_address_sanitizer(
    built, model, small_artifact, tmp_path
):
    """The example position in, force out (with friction) under AddressSanitizer and UBSan,
    on a tip file in every form the reader takes (a byte-order mark, CRLF line ends, a
    header, comments, blank lines), and the reader on each bad file."""
    reason = sanitizer_available()
    if reason:
        pytest.skip(reason)
    make("capi-asan")
    env = os.environ.copy()
    env["ASAN_OPTIONS"] = "detect_leaks=1:abort_on_error=0:exitcode=99"
    env["UBSAN_OPTIONS"] = "print_stacktrace=1:halt_on_error=1:exitcode=98"
    env["LSAN_OPTIONS"] = f"suppressions={ROOT / 'capi' / 'lsan.supp'}:print_suppressions=0"
    env.pop("LD_PRELOAD", None)
    binary = BUILD / "asan" / "servo_loop"
    for i, content in enumerate(BAD_TIPS):
        bad = tmp_path / f"bad{i}.csv"
        bad.write_bytes(content.encode())
        result = subprocess.run([str(binary), str(small_artifact), "--tips", str(bad)], env=env,
                                capture_output=True, text=True, timeout=60)  # fmt: skip
        assert result.returncode == 1 and "Sanitizer" not in result.stderr, result.stderr
    tips = scripted(model, 500)
    lines = [
        f"{0.001 * k!r}, {x!r},{y!r} ,{z!r}  # tick {k}"
        for k, (x, y, z) in enumerate(tips.tolist())
    ]
    text = "\ufeff# play's scripted path\r\n T, X, Y, Z\r\n\r\n" + "\r\n".join(lines)
    (tmp_path / "tips.csv").write_text(text, encoding="utf-8", newline="")
    result, rows, sequences, _ = run_example(binary, small_artifact, tmp_path, "--tips",
                                             str(tmp_path / "tips.csv"), "--friction",
                                             f"{MU_S},{MU_D},1.5", env=env)  # fmt: skip
    assert "Sanitizer" not in result.stderr and "runtime error" not in result.stderr, result.stderr
    np.testing.assert_array_equal(rows[:, 1:4], tips)
    assert np.all(rows[:, 8] == 0) and len(sequences) > 10
    assert rows[:, 15].any()  # the friction path ran: it slipped
