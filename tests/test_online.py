"""The online runtime: kernels against the plain-numpy reference, contact behaviour, bad input."""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest

import hapticrom.online as online
from hapticrom.online.model import inside_trained_region
from hapticrom.online.reference import NumpySimulator
from hapticrom.online.simulator import StepInputError

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(11)


@pytest.fixture(scope="module")
def model(small_artifact):
    return online.load(small_artifact)


def points_in_region(model, count):
    """Random points inside the samples' chart hull, lifted to the nearest sample's height."""
    chart = model.plan_points
    out = []
    for _ in range(count):
        tri = model.sample_triangles[RNG.integers(len(model.sample_triangles))]
        w = RNG.dirichlet(np.ones(3))
        x2 = w @ chart[tri]
        out.append(model.plan_origin + x2 @ model.plan_axes)
    return out


COMBINATIONS = [("podi", "curves"), ("grassmann", "curves"), ("podi", "anm")]


@pytest.mark.parametrize("interpolation,response", COMBINATIONS)
def test_kernels_match_the_numpy_reference(model, interpolation, response):
    sim = model.simulator(interpolation, response)
    ref = NumpySimulator(model, response)
    out = np.zeros_like(model.vertices)
    for point in points_in_region(model, 25):
        sim.set_contact(point)
        ref.set_contact(point)
        np.testing.assert_allclose(sim.contact_normal, ref.normal, atol=1e-14)
        for depth in RNG.uniform(-0.1, 1.3 * model.trained_depth, 6):
            d = -depth * sim.contact_normal + RNG.normal(0, 0.05, 3) * np.cross(
                sim.contact_normal, [1, 0, 0]
            )
            force = sim.step_displacement(d).copy()
            np.testing.assert_allclose(force, ref.step_displacement(d), rtol=1e-12, atol=1e-15)
            sim.surface_displacement(out)
            if interpolation == "podi":
                np.testing.assert_allclose(out, ref.surface_displacement(), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("interpolation,response", COMBINATIONS)
def test_reproduces_the_training_curves_at_the_samples(
    model, small_campaign, interpolation, response
):
    """At a sample, force and surface field are those of the full-order solve.

    For Grassmann this checks the log and exp maps: Exp(Log(A_i)) must span A_i.
    The POD-ANM series are the reduced model's own solution, not the stored
    curves: they must agree with full Newton to a small fraction of a percent.
    """
    _, store, _ = small_campaign
    sim = model.simulator(interpolation, response)
    rtol = 1e-10 if response == "curves" else 1e-3
    out = np.zeros_like(model.vertices)
    nodes = model.artifact["surface"]["nodes"]
    for i, point in enumerate(model.sample_points):
        data, attrs = store.read_position(i)
        sim.set_contact(point)
        for k in range(len(data["force"])):
            depth = data["contact_displacement"][k] @ attrs["direction"]
            force = sim.step_displacement(-depth * sim.contact_normal)
            np.testing.assert_allclose(
                force @ sim.contact_normal, data["force"][k] @ attrs["direction"], rtol=rtol
            )
            sim.surface_displacement(out)
            u = data["displacement"][k].reshape(-1, 3)[nodes]
            assert np.abs(out - u).max() <= 1e-3 * np.abs(u).max() + 1e-12


def test_step_force_inverts_step_displacement(model):
    sim = model.simulator()
    for point in points_in_region(model, 10):
        sim.set_contact(point)
        n = sim.contact_normal.copy()
        for depth in RNG.uniform(0.01, 1.2 * model.trained_depth, 5):
            force = sim.step_displacement(-depth * n).copy()
            d = sim.step_force(-force)  # push with the force the tissue resisted with
            assert -d @ n == pytest.approx(depth, rel=1e-10)


def test_sliding_contact_is_continuous(model):
    """A contact sliding across the sample triangles: no jumps in force or field."""
    sim = model.simulator()
    a, b = model.sample_points[1], model.sample_points[3]  # across the apex
    path = [a + t * (b - a) for t in np.linspace(0, 1, 2001)]
    forces, fields = [], []
    out = np.zeros_like(model.vertices)
    for p in path:
        sim.set_contact(p)
        forces.append(sim.step_displacement(-0.2 * sim.contact_normal).copy())
        fields.append(sim.surface_displacement(out).copy())
    jumps = np.linalg.norm(np.diff(forces, axis=0), axis=1)
    assert jumps.max() < 5 * np.median(jumps) + 1e-12  # no step bigger than the smooth change
    field_jumps = np.abs(np.diff(fields, axis=0)).max(axis=(1, 2))
    assert field_jumps.max() < 5 * np.median(field_jumps) + 1e-12


def test_outside_the_trained_region_is_clamped_and_flagged(model):
    sim = model.simulator()
    sim.set_contact(model.sample_points[0])
    assert not sim.outside_trained_region
    far = model.plan_origin + 50.0 * model.plan_axes[0]
    sim.set_contact(far)
    assert sim.outside_trained_region
    nodes, weights = sim.weights
    assert np.all(weights >= -1e-12) and weights.sum() == pytest.approx(1.0)
    force = sim.step_displacement(-0.1 * sim.contact_normal)
    assert np.all(np.isfinite(force)) and force @ sim.contact_normal > 0


def test_the_opposite_face_of_the_organ_is_outside_the_trained_region(model):
    """A contact on the cornea's posterior face, under the trained anterior region, is
    clamped and flagged, not given the anterior response a thickness above it; every
    anterior vertex that was inside stays inside with the same weights."""
    from hapticrom.shared.geometry import vertex_normals

    normals = vertex_normals(model.vertices, model.triangles)
    facing = normals @ model.sample_normals.mean(axis=0)
    without = inside_trained_region(model.sample_points, model.sample_normals,
                                    model.sample_triangles, model.vertices)  # fmt: skip
    inside = model.inside_trained_region(model.vertices)
    posterior = without & (facing < -0.9)
    assert posterior.sum() >= 10  # located through the tissue without the floors
    assert not inside[posterior].any()
    assert np.array_equal(inside[facing > 0.9], without[facing > 0.9])
    sim = model.simulator()
    for v in np.flatnonzero(posterior)[:5]:
        sim.set_contact(model.vertices[v])
        assert sim.outside_trained_region


def test_depth_flags(model):
    sim = model.simulator()
    sim.set_contact(model.sample_points[0])
    n = sim.contact_normal
    assert np.all(sim.step_displacement(+0.1 * n) == 0) and not sim.in_contact  # pulling away
    sim.step_displacement(-2 * model.trained_depth * n)
    assert sim.beyond_trained_depth and sim.in_contact
    sim.step_displacement(-0.5 * model.trained_depth * n)
    assert not sim.beyond_trained_depth


@pytest.mark.parametrize(
    "bad", [[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -1e6]], ids=["nan", "inf", "absurd"]
)
def test_bad_step_input_is_rejected_and_state_kept(model, bad):
    sim = model.simulator()
    sim.set_contact(model.sample_points[0])
    good = sim.step_displacement(-0.1 * sim.contact_normal).copy()
    depth = sim.depth
    with pytest.raises(StepInputError, match="state unchanged"):
        sim.step_displacement(np.array(bad, dtype=float))
    with pytest.raises(StepInputError):
        sim.step_force(np.array(bad, dtype=float) * 1e6)
    assert sim.depth == depth
    np.testing.assert_array_equal(sim.step_displacement(-0.1 * sim.contact_normal), good)
    with pytest.raises(StepInputError):
        sim.set_contact([np.nan, 0, 0])


def test_steps_allocate_nothing(model):
    sim = model.simulator()
    sim.set_contact(model.sample_points[0])
    d = -0.1 * sim.contact_normal
    out = np.zeros_like(model.vertices)
    for _ in range(100):
        sim.step_displacement(d)
        sim.surface_displacement(out)
    before = sys.getallocatedblocks()
    for _ in range(10000):
        first = sim.step_displacement(d)
        sim.surface_displacement(out)
    assert first is sim.step_displacement(d)  # the same buffer every call
    assert sys.getallocatedblocks() - before < 50


def test_surface_output_must_fit(model):
    sim = model.simulator()
    sim.set_contact(model.sample_points[0])
    with pytest.raises(ValueError, match="C-contiguous float64"):
        sim.surface_displacement(np.zeros((len(model.vertices), 3), dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        sim.surface_displacement(np.zeros((3, len(model.vertices))))


def test_simulator_needs_a_contact(model):
    with pytest.raises(RuntimeError, match="set_contact"):
        model.simulator().step_displacement(np.zeros(3))
    with pytest.raises(ValueError, match="interpolation"):
        model.simulator("nearest")


def test_numpy_baseline_of_the_anm_step_computes_the_same_force(model):
    """The latency baseline (numpy, the kernels' tables) agrees with the eigenvalue roots."""
    eigen = NumpySimulator(model, "anm")
    table = NumpySimulator(model, "anm", root="table")
    for point in points_in_region(model, 5):
        eigen.set_contact(point)
        table.set_contact(point)
        for depth in RNG.uniform(0.0, 1.2 * model.trained_depth, 5):
            d = -depth * eigen.normal
            np.testing.assert_allclose(
                table.step_displacement(d), eigen.step_displacement(d), rtol=1e-10, atol=1e-15
            )


def test_symmetric_eigen_matches_lapack():
    from hapticrom.online.kernels import symmetric_eigen

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 6, 12):
        X = rng.standard_normal((n, n))
        for G in (X @ X.T, X + X.T, np.diag(np.r_[np.ones(n - n // 2), 2 * np.ones(n // 2)])):
            values, V = symmetric_eigen(np.ascontiguousarray(G))
            np.testing.assert_allclose(
                np.sort(values), np.linalg.eigvalsh(G), atol=1e-12 * (1 + np.abs(G).max())
            )
            np.testing.assert_allclose(V.T @ V, np.eye(n), atol=1e-13)
            np.testing.assert_allclose(
                V @ np.diag(values) @ V.T, G, atol=1e-12 * (1 + np.abs(G).max())
            )


def test_kernels_compile_with_numpy_numba_h5py_only(small_artifact, tmp_path):
    """`pip install hapticrom` brings numpy, numba and h5py: no scipy, no offline stack.

    A fresh numba cache makes every kernel compile here (numba's LAPACK-backed
    np.linalg needs scipy: the kernels must not use it).
    """
    import os
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import sys, importlib.abc
        class _Block(importlib.abc.MetaPathFinder):
            BLOCKED = ("scipy", "dolfinx", "petsc4py", "slepc4py", "mpi4py", "ufl", "gmsh",
                       "matplotlib")
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in self.BLOCKED:
                    raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        sys.meta_path.insert(0, _Block())
        import numpy as np
        import hapticrom.online as online
        model = online.load({str(small_artifact)!r})
        for interpolation, response in (("podi", "anm"), ("grassmann", "curves")):
            sim = model.simulator(interpolation, response)
            sim.set_contact(model.sample_points[0])
            f = sim.step_displacement(-0.5 * model.trained_depth * sim.contact_normal)
            assert f @ sim.contact_normal > 0
        print("ok")
    """)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=600)  # fmt: skip
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


# -- the runtime's inputs, outputs, limits and threads (issue "the artifact is a trust boundary")
def _contact(model, response="curves", **limits):
    sim = model.simulator(response=response, **limits)
    sim.set_contact(model.sample_points[0])
    return sim


def test_step_inputs_of_other_types_take_the_slower_path_to_the_same_result(model):
    """Lists, tuples, float32, integers, read-only and strided arrays: the same force as
    the float64 (3,) array (converted into the simulator's own buffer)."""
    sim = _contact(model)
    d = np.round(-512 * model.trained_depth * sim.contact_normal) / 1024  # exact in float32
    expected = sim.step_displacement(d).copy()
    assert np.linalg.norm(expected) > 0
    frozen = d.copy()
    frozen.flags.writeable = False
    strided = np.repeat(d, 2)[::2]
    assert not strided.flags.c_contiguous
    for same in (d.tolist(), tuple(d), d.astype(np.float32).astype(np.float64), frozen, strided):
        np.testing.assert_array_equal(sim.step_displacement(same), expected)
    integers = np.array([0, 0, -1])
    f_int = sim.step_displacement(integers).copy()
    np.testing.assert_array_equal(sim.step_displacement(integers.astype(float)), f_int)
    f32 = d.astype(np.float32)
    np.testing.assert_array_equal(
        sim.step_displacement(f32), sim.step_displacement(f32.astype(np.float64))
    )
    push = -0.5 * model.trained_force * sim.contact_normal
    expected = sim.step_force(push).copy()
    np.testing.assert_array_equal(sim.step_force(push.tolist()), expected)
    sim.set_contact(tuple(model.sample_points[1]))
    normal = sim.contact_normal.copy()
    sim.set_contact(model.sample_points[1].astype(np.float32))
    np.testing.assert_allclose(sim.contact_normal, normal, atol=1e-6)


BAD_SHAPES = {
    "2": [0.0, -0.1],
    "4": np.array([0.0, 0.0, -0.1, 0.0]),
    "2-array": np.array([0.0, -0.1]),
    "3x1": np.zeros((3, 1)),
    "scalar": -0.1,
    "empty": np.zeros(0),
}


@pytest.mark.parametrize("bad", BAD_SHAPES.values(), ids=BAD_SHAPES.keys())
@pytest.mark.parametrize("response", ["curves", "anm"])
def test_wrong_shapes_are_refused_naming_the_shape(model, bad, response):
    """A (2,) array is never read past its end, a (4,) one never truncated: refused."""
    sim = _contact(model, response)
    sim.step_displacement(-0.1 * sim.contact_normal)
    buf = sim._buf.copy()
    shape = str(np.shape(bad))
    for step in (sim.step_displacement, sim.step_force, sim.set_contact):
        with pytest.raises(StepInputError, match=f"shape {re.escape(shape)}"):
            step(bad)
        np.testing.assert_array_equal(sim._buf, buf)  # state unchanged


@pytest.mark.parametrize(
    "bad",
    ["abc", None, [1.0, "a", 2.0], [[1.0], [2.0, 3.0]], np.zeros(3, complex), [True] * 3],
    ids=["str", "none", "mixed", "ragged", "complex", "bool"],
)
def test_non_numbers_are_refused(model, bad):
    sim = _contact(model)
    buf = sim._buf.copy()
    for step in (sim.step_displacement, sim.step_force, sim.set_contact):
        with pytest.raises(StepInputError, match="must be 3 numbers"):
            step(bad)
    np.testing.assert_array_equal(sim._buf, buf)


def test_kernels_check_the_length_before_reading(model):
    """Called directly, a step kernel refuses a short or long array (status 3), writes
    nothing, whatever lies after the array's end."""
    from hapticrom.online import kernels

    sim = _contact(model)
    for step in (kernels.step_displacement_curves, kernels.step_force_curves):
        for n in (0, 1, 2, 4):
            memory = np.full(8, -1e3)  # what a reader past the end would find
            buf = sim._buf.copy()
            assert step(memory[:n], buf) == kernels.WRONG_SHAPE
            np.testing.assert_array_equal(buf, sim._buf)


def test_errors_of_the_runtime_are_hapticrom_errors():
    from hapticrom.online import ScalpelInputError
    from hapticrom.online.simulator import SimulatorBusyError
    from hapticrom.shared.errors import HapticromError

    for error in (StepInputError, ScalpelInputError):
        assert issubclass(error, HapticromError) and issubclass(error, ValueError)
    assert issubclass(SimulatorBusyError, HapticromError)


def test_what_the_simulator_returns_cannot_be_written(model):
    """contact_normal and the steps' results are views of the state: read only."""
    sim = _contact(model)
    n = sim.contact_normal.copy()
    d = -0.5 * model.trained_depth * n
    force = sim.step_displacement(d)
    before = force.copy()
    displacement = sim.step_force(-before)
    for view in (sim.contact_normal, force, displacement):
        assert not view.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            view[0] = np.nan
    for leaked in (sim.contact_normal.view(), np.asarray(force)):
        with pytest.raises(ValueError):
            leaked[:] = np.nan
    np.testing.assert_array_equal(sim.contact_normal, n)
    np.testing.assert_array_equal(sim.step_displacement(d), before)
    vertices, triangles = sim.cut_surface()  # no scalpel: the model's own surface
    assert not vertices.flags.writeable and not triangles.flags.writeable


@pytest.mark.parametrize(
    "limit",
    [np.nan, np.inf, -np.inf, 0, 0.0, -1.0, "1", True, [1.0]],
    ids=["nan", "inf", "-inf", "0", "0.0", "negative", "str", "bool", "list"],
)
def test_limits_must_be_finite_positive_numbers(model, limit):
    from hapticrom.shared.errors import InputError

    for name in ("max_displacement", "max_force"):
        with pytest.raises(InputError, match=f"{name} must be"):
            model.simulator(**{name: limit})


def test_limits_default_and_explicit(model):
    sim = model.simulator()
    assert sim.max_displacement == pytest.approx(10 * model.trained_depth)
    assert sim.max_force == pytest.approx(10 * model.force[:, -1].max())
    sim = model.simulator(max_displacement=0.25 * model.trained_depth, max_force=np.float32(2))
    assert sim.max_displacement == 0.25 * model.trained_depth and sim.max_force == 2.0
    sim.set_contact(model.sample_points[0])
    with pytest.raises(StepInputError, match="limit"):
        sim.step_displacement(-0.3 * model.trained_depth * sim.contact_normal)
    with pytest.raises(AttributeError):
        sim.max_displacement = np.nan  # read only: the kernels' copy is the one in force


@pytest.mark.parametrize("response", ["curves", "anm"])
def test_step_force_never_returns_a_displacement_beyond_the_limit(model, response):
    """A force whose depth passes max_displacement is refused as a displacement past it
    is: StepInputError, and the state (depth, series sections, surface) unchanged."""
    limit = 0.5 * model.trained_depth
    sim = _contact(model, response, max_displacement=limit)
    n = sim.contact_normal.copy()
    inside = sim.step_displacement(-0.9 * limit * n)  # a force whose depth is within
    d = sim.step_force(-inside).copy()
    assert np.linalg.norm(d) == pytest.approx(0.9 * limit, rel=1e-9)
    depth, buf = sim.depth, sim._buf.copy()
    surface = sim.surface_displacement(np.zeros_like(model.vertices)).copy()
    too_far = model.simulator(response=response)
    too_far.set_contact(model.sample_points[0])
    push = too_far.step_displacement(-1.2 * limit * n).copy()  # its depth: 1.2 x the limit
    assert np.linalg.norm(push) < sim.max_force  # an acceptable force in itself
    with pytest.raises(StepInputError, match="beyond the displacement limit"):
        sim.step_force(-push)
    assert sim.depth == depth
    np.testing.assert_array_equal(sim._buf, buf)
    np.testing.assert_array_equal(sim.surface_displacement(np.zeros_like(model.vertices)),
                                  surface)  # fmt: skip
    for f in np.linspace(0, np.linalg.norm(push), 50):
        try:
            d = sim.step_force(-f * n)
        except StepInputError:
            continue
        assert np.linalg.norm(d) <= limit


def _model_arrays(model) -> dict:
    """Every array of the model a simulator reads (name: array)."""
    arrays = {k: v for k, v in vars(model).items() if isinstance(v, np.ndarray)}
    for group in ("anm", "grassmann"):
        for k, v in (getattr(model, group) or {}).items():
            if isinstance(v, np.ndarray):
                arrays[f"{group}.{k}"] = v
    return arrays


def test_simulators_on_threads_share_a_model_and_step_as_serially(model):
    """Two threads, each stepping its own simulator on one model, at the same time: the
    forces and surfaces of a serial run, and the model unchanged."""
    import threading

    before = {k: v.copy() for k, v in _model_arrays(model).items()}
    points = points_in_region(model, 40)
    depths = np.linspace(0.0, 1.1 * model.trained_depth, 25)

    def run(response, results, start=None):
        sim = model.simulator(response=response)
        out = np.zeros_like(model.vertices)
        if start is not None:
            start.wait()
        for point in points:
            sim.set_contact(point)
            for depth in depths:
                results.append(sim.step_displacement(-depth * sim.contact_normal).copy())
                results.append(sim.step_force(-results[-1]).copy())
            results.append(sim.surface_displacement(out).copy())

    serial = {r: [] for r in ("curves", "anm")}
    for response, results in serial.items():
        run(response, results)
    for pair in (("curves", "anm"), ("anm", "anm")):
        threaded = [[], []]
        start = threading.Barrier(2)
        threads = [threading.Thread(target=run, args=(r, out, start))
                   for r, out in zip(pair, threaded, strict=True)]  # fmt: skip
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for response, results in zip(pair, threaded, strict=True):
            assert len(results) == len(serial[response])
            for a, b in zip(results, serial[response], strict=True):
                np.testing.assert_array_equal(a, b)
    for name, array in _model_arrays(model).items():
        np.testing.assert_array_equal(array, before[name], err_msg=name)


def test_one_simulator_on_two_threads_is_refused(model):
    """While one thread is inside a step, every call of another thread raises
    SimulatorBusyError (without waiting); the first step ends normally."""
    import threading

    from hapticrom.online.simulator import SimulatorBusyError

    sim = _contact(model)
    d = -0.5 * model.trained_depth * sim.contact_normal
    expected = sim.step_displacement(d).copy()
    inside, release = threading.Event(), threading.Event()
    kernel = sim._step_displacement

    def slow_kernel(x, buf):  # a step that takes its time
        inside.set()
        release.wait(30)
        return kernel(x, buf)

    sim._step_displacement = slow_kernel
    results = []
    worker = threading.Thread(target=lambda: results.append(sim.step_displacement(d).copy()))
    worker.start()
    try:
        assert inside.wait(30)
        out = np.zeros_like(model.vertices)
        for call in (lambda: sim.step_displacement(d), lambda: sim.step_force(-expected),
                     lambda: sim.set_contact(model.sample_points[1]),
                     lambda: sim.surface_displacement(out)):  # fmt: skip
            with pytest.raises(SimulatorBusyError, match="another thread"):
                call()
    finally:
        release.set()
        worker.join()
    np.testing.assert_array_equal(results[0], expected)
    sim._step_displacement = kernel
    with pytest.raises(StepInputError):  # an error inside a call leaves the simulator free
        sim.step_displacement([np.nan, 0, 0])
    np.testing.assert_array_equal(sim.step_displacement(d), expected)


@pytest.mark.parametrize("interpolation,response", COMBINATIONS)
def test_a_read_only_model_steps_as_a_writable_one(small_artifact, interpolation, response):
    """Every kernel takes the model's arrays read only: a frozen model works the same."""
    frozen = online.load(small_artifact)
    for array in _model_arrays(frozen).values():
        array.flags.writeable = False
    writable = online.load(small_artifact)
    sims = [m.simulator(interpolation, response) for m in (frozen, writable)]
    outs = [np.zeros_like(frozen.vertices) for _ in sims]
    for point in points_in_region(frozen, 5):
        for depth in (0.2, 1.0):
            results = []
            for sim, out in zip(sims, outs, strict=True):
                sim.set_contact(point)
                f = sim.step_displacement(-depth * frozen.trained_depth * sim.contact_normal)
                results.append((f.copy(), sim.step_force(-f).copy(),
                                sim.surface_displacement(out).copy()))  # fmt: skip
            for a, b in zip(*results, strict=True):
                np.testing.assert_array_equal(a, b)


def test_a_loaded_model_is_read_only(model):
    """A simulator cannot change the model other simulators share."""
    writable = [name for name, a in _model_arrays(model).items() if a.flags.writeable]
    assert writable == []


def test_every_error_the_runtime_raises_is_a_simulator_error(model):
    """One error family: whatever a caller gets wrong at run time is a SimulatorError (a
    HapticromError), and keeps ValueError / RuntimeError for those who catch those."""
    from hapticrom.shared.errors import HapticromError, InputError, SimulatorError

    sim = model.simulator()
    out = np.zeros_like(model.vertices)
    raised = {}
    for name, call in {
        "step before contact": lambda: sim.step_displacement(np.zeros(3)),
        "force step before contact": lambda: sim.step_force(np.zeros(3)),
        "error estimate before contact": lambda: sim.error_estimate,
        "point not finite": lambda: sim.set_contact([np.nan, 0.0, 0.0]),
        "point of strings": lambda: sim.set_contact("abc"),
        "output of a wrong shape": lambda: sim.surface_displacement(out[:2]),
        "output of a wrong dtype": lambda: sim.surface_displacement(out.astype(np.float32)),
    }.items():
        with pytest.raises(HapticromError) as info:
            call()
        raised[name] = info.value
    sim.set_contact(model.sample_points[0])
    for name, call in {
        "displacement of a wrong shape": lambda: sim.step_displacement(np.zeros(2)),
        "force not finite": lambda: sim.step_force([0.0, np.inf, 0.0]),
        "displacement past the limit": lambda: sim.step_displacement(
            -2 * sim.max_displacement * sim.contact_normal
        ),
    }.items():
        with pytest.raises(HapticromError) as info:
            call()
        raised[name] = info.value
    for name, error in raised.items():
        assert isinstance(error, SimulatorError), name
    for name in (
        "step before contact",
        "force step before contact",
        "error estimate before contact",
    ):
        assert isinstance(raised[name], online.NoContactError | RuntimeError), name
    for name in ("output of a wrong shape", "output of a wrong dtype"):
        assert isinstance(raised[name], online.OutputArrayError | ValueError), name
    assert isinstance(raised["point not finite"], StepInputError | ValueError)
    for error in (online.StepInputError, online.ScalpelInputError, online.OutputArrayError):
        assert issubclass(error, SimulatorError) and issubclass(error, ValueError)
    for error in (online.SimulatorBusyError, online.NoContactError):
        assert issubclass(error, SimulatorError) and issubclass(error, RuntimeError)
    with pytest.raises(InputError):  # a simulator's configuration: the shared InputError
        model.simulator(max_force=-1.0)


@pytest.mark.parametrize("interpolation,response", COMBINATIONS)
def test_a_simulator_declares_its_state_in_init(model, interpolation, response):
    """No attribute appears after construction: every call works on declared state."""
    sim = model.simulator(interpolation, response)
    declared = set(vars(sim))
    out = np.zeros_like(model.vertices)
    for point in points_in_region(model, 3):
        sim.set_contact(point)
        f = sim.step_displacement(-0.5 * model.trained_depth * sim.contact_normal)
        sim.step_force(-f)
        sim.surface_displacement(out)
        assert sim.contact_stiffness > 0
    assert set(vars(sim)) == declared


def test_grassmann_frames_follow_the_contact(model):
    """The Grassmann frames are prepared for the surface of the current contact: after the
    contact moves, the surface is the one a fresh simulator gives there."""
    moved, fresh = (model.simulator("grassmann", "curves") for _ in range(2))
    a, b = points_in_region(model, 2)
    out, expected = np.zeros_like(model.vertices), np.zeros_like(model.vertices)
    depth = 0.5 * model.trained_depth
    moved.set_contact(a)
    moved.step_displacement(-depth * moved.contact_normal)
    first = moved.surface_displacement(out).copy()
    moved.set_contact(b)
    fresh.set_contact(b)
    for sim, o in ((moved, out), (fresh, expected)):
        sim.step_displacement(-depth * sim.contact_normal)
        sim.surface_displacement(o)
    np.testing.assert_array_equal(out, expected)
    assert np.abs(out - first).max() > 0  # the contact moved: another surface


def test_contact_stiffness_is_the_slope_of_the_force(model):
    """d force / d depth against a central difference of the steps: the series' slope at
    any depth, the curves' at their knots (between them it is interpolated linearly)."""
    knots = model.depth_step * np.array([2, 5, len(model.force[0]) + 1])
    series = np.array([0.3, 0.7, 1.2]) * model.trained_depth
    for response, depths in (("anm", series), ("curves", knots)):
        sim = _contact(model, response)
        n = sim.contact_normal.copy()
        for d in depths:
            h = 1e-6 * model.trained_depth
            f_hi = np.linalg.norm(sim.step_displacement(-(d + h) * n))
            f_lo = np.linalg.norm(sim.step_displacement(-(d - h) * n))
            sim.step_displacement(-d * n)
            slope = (f_hi - f_lo) / (2 * h)
            assert sim.contact_stiffness == pytest.approx(slope, rel=1e-4)
