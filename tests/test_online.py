"""The online runtime: kernels against the plain-numpy reference, contact behaviour, bad input."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import hapticrom.online as online
from hapticrom.online.reference import NumpySimulator
from hapticrom.online.simulator import StepInputError

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(11)


@pytest.fixture(scope="module")
def model(small_artifact):
    return online.load(small_artifact)


def points_in_region(model, count):
    """Random points inside the samples' chart hull, lifted to the nearest sample's height."""
    chart = model.chart_points
    out = []
    for _ in range(count):
        tri = model.sample_triangles[RNG.integers(len(model.sample_triangles))]
        w = RNG.dirichlet(np.ones(3))
        x2 = w @ chart[tri]
        out.append(model.chart_origin + x2 @ model.chart_axes)
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
    far = model.chart_origin + 50.0 * model.chart_axes[0]
    sim.set_contact(far)
    assert sim.outside_trained_region
    nodes, weights = sim.weights
    assert np.all(weights >= -1e-12) and weights.sum() == pytest.approx(1.0)
    force = sim.step_displacement(-0.1 * sim.contact_normal)
    assert np.all(np.isfinite(force)) and force @ sim.contact_normal > 0


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
    """The latency baseline (numpy, the kernels' Newton) agrees with the eigenvalue roots."""
    eigen = NumpySimulator(model, "anm")
    newton = NumpySimulator(model, "anm", root="newton")
    for point in points_in_region(model, 5):
        eigen.set_contact(point)
        newton.set_contact(point)
        for depth in RNG.uniform(0.0, 1.2 * model.trained_depth, 5):
            d = -depth * eigen.normal
            np.testing.assert_allclose(
                newton.step_displacement(d), eigen.step_displacement(d), rtol=1e-10, atol=1e-15
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
