"""Coulomb friction under ``Simulator.step_position``: stick, slip and stick-slip against the
friction law at every step, the tangential stiffness against differences of the force,
the proxy's slip against the tangential force, and bad coefficients refused."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import hapticrom.online as online
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
MU_S, MU_D = 0.5, 0.3


@pytest.fixture(scope="module")
def model(small_artifact):
    return online.load(small_artifact)


@pytest.fixture(params=["curves", "anm"])
def response(request, model):
    if request.param == "anm" and model.anm is None:
        pytest.skip("the small artifact has no POD-ANM series")
    return request.param


def pressed(model, response, depth=0.15, friction=(MU_S, MU_D)):
    """A simulator whose tool is pressed ``depth`` (mm) into the surface at sample 0,
    straight down the normal; the tip, the normal and a unit tangent there."""
    sim = model.simulator(response=response)
    if friction is not None:
        sim.set_friction(*friction)
    probe = model.simulator()
    probe.set_contact(model.sample_points[0])
    n = np.array(probe.contact_normal)
    tangent = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    tangent /= np.linalg.norm(tangent)
    top = model.sample_points[0] + (sim.tool_radius + 1.0) * n
    sim.step_position(top)
    tip = top - (1.0 + depth) * n
    for s in np.linspace(0, 1, 11)[1:]:  # pressed in ten ticks, straight down
        sim.step_position(top - s * (1.0 + depth) * n)
    return sim, tip, n, tangent


def split(sim):
    """The force on the tool as (normal part along the model's normal, tangential vector)."""
    force, m = np.array(sim._force), np.array(sim.contact_normal)
    fn = force @ m
    return fn, force - fn * m


def test_a_small_sideways_move_sticks_with_a_spring_force(model, response):
    """Within the static cone the proxy stays put and the tangential force changes by -k_t
    times the move across the normal, k_t = 2/3 of the normal contact stiffness. (Pressing
    along the model's normal, a few degrees off the sheet's on this coarse mesh, already
    drags the tissue a little: the force's change is what a sideways move adds.)"""
    sim, tip, n, tangent = pressed(model, response)
    proxy0 = sim.proxy.copy()
    fn0, ft0 = split(sim)
    assert fn0 > 0 and np.linalg.norm(ft0) <= MU_S * fn0
    shift = 0.002
    sim.step_position(tip + shift * tangent)
    assert not sim.slipping
    np.testing.assert_array_equal(sim.proxy, proxy0)
    fn, ft = split(sim)
    m = np.array(sim.contact_normal)
    move = shift * (tangent - (tangent @ m) * m)
    kt = 2.0 / 3.0 * sim.contact_stiffness
    # the goal (the sheet's point nearest the tip) moves as the tip does, to the sheet's
    # curvature: R / (R + depth) on a sphere, about 2 % here
    np.testing.assert_allclose(ft - ft0, -kt * move, atol=0.03 * kt * shift)
    assert np.linalg.norm(ft) <= MU_S * fn


@pytest.mark.parametrize("seed", [0, 1])
def test_a_slide_obeys_the_friction_law_at_every_step(model, response, seed):
    """Slide sideways at a steady rate, stop, then slide back: stuck steps keep |F_t| <=
    mu_s F_n, slipping steps have |F_t| = mu_d F_n exactly and the tangential force against
    the proxy's slide. The proxy sticks, breaks away at the static cone, slides steadily on
    the dynamic one (no stick-slip buzz), sticks when the tip turns back until the tip has
    crossed from one cone to the other, (mu_s + mu_d) F_n / k_t, then slides back."""
    sim, tip, n, tangent = pressed(model, response)
    frictionless, *_ = pressed(model, response, friction=None)  # its proxy: the goal
    rng = np.random.default_rng(seed)
    direction = np.cross(n, rng.normal(size=3))
    direction /= np.linalg.norm(direction)
    speed = 0.001  # mm per tick
    offsets = np.concatenate([np.arange(1, 601), np.full(50, 600), np.arange(599, 0, -1)])
    states, last_proxy, lags, cones = [], sim.proxy.copy(), [], []
    for step in offsets:
        p = tip + speed * step * direction
        sim.step_position(p)
        frictionless.step_position(p)
        assert sim.in_contact
        fn, ft = split(sim)
        assert fn > 0
        if sim.slipping:
            np.testing.assert_allclose(np.linalg.norm(ft), MU_D * fn, rtol=1e-12)
            slide = sim.proxy - last_proxy
            # the force on the tool opposes the proxy's slide; the proxy moves from the next
            # step on when the cone was reached this step (the stick test's one step of lag)
            assert slide @ ft < 0 or (not slide.any() and not states[-1])
        else:
            assert np.linalg.norm(ft) <= MU_S * fn * (1 + 1e-12)
        kt = 2 / 3 * sim.contact_stiffness
        lags.append((frictionless.proxy - sim.proxy) @ direction * kt / fn)
        states.append(sim.slipping)
        cones.append(fn / kt)
        last_proxy = sim.proxy.copy()
    states, lags = np.array(states), np.array(lags)
    first = int(np.argmax(states))
    assert 0 < first < 600 and states[first + 1 : 600].all()  # broke away, then slid on
    np.testing.assert_allclose(lags[first - 1], MU_S, rtol=0.05)  # at the static cone
    np.testing.assert_allclose(lags[first + 5 : 600], MU_D, rtol=0.02)  # on the dynamic one
    back = states[650:]  # turned back: stuck until the tip crossed both cones, then sliding
    again = int(np.argmax(back))
    assert not back[:again].any() and back[again + 1 :].all()
    crossed = speed * again / ((MU_S + MU_D) * np.mean(cones[650 : 650 + again]))
    assert 0.9 < crossed < 1.1, crossed
    np.testing.assert_allclose(lags[650 + again + 5 :], -MU_D, rtol=0.02)


def test_equal_coefficients_slide_steadily(model, response):
    """mu_s = mu_d: once the cone is reached the proxy slips at every step, |F_t| = mu F_n."""
    sim, tip, n, tangent = pressed(model, response, friction=(0.4, 0.4))
    slipping = []
    for step in range(1, 601):
        sim.step_position(tip + 0.001 * step * tangent)
        slipping.append(sim.slipping)
    first = slipping.index(True)
    assert all(slipping[first + 2 :])  # (one step of lag while the cone is reached)
    fn, ft = split(sim)
    np.testing.assert_allclose(np.linalg.norm(ft), 0.4 * fn, rtol=1e-12)


def test_no_friction_is_the_frictionless_proxy(model, response):
    """set_friction(0) gives the frictionless step_position bit for bit."""
    a, tip, n, tangent = pressed(model, response, friction=(0.0, 0.0))
    b, *_ = pressed(model, response, friction=None)
    for step in range(200):
        p = tip + 0.002 * step * tangent
        np.testing.assert_array_equal(a.step_position(p), b.step_position(p))
        np.testing.assert_array_equal(a.proxy, b.proxy)
        assert not a.slipping


def test_the_stuck_stiffness_is_the_force_s_derivative(model, response):
    """Stuck, K = k n n^T + k_t (I - n n^T): central differences of the force in the normal
    and both tangential directions (the proxy stays put, so the force is a function of the
    tip), to the terms the stiffness leaves out (dk_t/ddepth times the offset)."""
    sim, tip, n, tangent = pressed(model, response)
    other = np.cross(n, tangent)
    sim.step_position(tip + 0.003 * tangent)
    K = sim.stiffness(np.zeros((3, 3)))
    kn, m = sim.contact_stiffness, np.array(sim.contact_normal)
    base = tip + 0.003 * tangent
    eps = 1e-6
    for e in (n, tangent, other):
        plus = sim.step_position(base + eps * e).copy()
        minus = sim.step_position(base - eps * e).copy()
        assert not sim.slipping
        dF = -(plus - minus) / (2 * eps)
        np.testing.assert_allclose(e @ dF, e @ K @ e, rtol=0.03)
        # Off the diagonal, K takes the model's normal for the sheet's (a few degrees apart
        # on this coarse mesh: the goal moves across the sheet as the tip moves along n).
        np.testing.assert_allclose(dF, K @ e, atol=0.05 * np.abs(K).max())
    across = tangent - (tangent @ m) * m
    np.testing.assert_allclose(across @ K @ across, 2 / 3 * kn * (across @ across), rtol=1e-12)


def test_the_slipping_stiffness_is_the_force_s_derivative(model, response):
    """Slipping, from one state, the force of a step to the tip moved by +-eps against K
    (not symmetric: along the slip the tangential force stays mu_d F_n)."""
    sim, tip, n, tangent = pressed(model, response, friction=(0.3, 0.3))
    for step in range(1, 401):
        sim.step_position(tip + 0.001 * step * tangent)
    assert sim.slipping
    base = tip + 0.4 * tangent
    saved = sim._proxy.copy(), sim._buf.copy()

    def force_at(p):
        sim._proxy[:], sim._buf[:] = saved
        f = sim.step_position(p).copy()
        assert sim.slipping
        return f

    sim._proxy[:], sim._buf[:] = saved
    sim.step_position(base + 0.001 * tangent)
    K = sim.stiffness(np.zeros((3, 3)))
    centre = base + 0.001 * tangent
    eps = 1e-6
    for e in (n, tangent, np.cross(n, tangent)):
        dF = (force_at(centre + eps * e) - force_at(centre - eps * e)) / (2 * eps)
        np.testing.assert_allclose(-dF, K @ e, atol=0.05 * np.abs(K).max())
    assert abs(tangent @ K @ tangent) < 0.05 * np.abs(K).max()  # along the slip: nothing


def test_release_and_a_new_contact_start_stuck(model, response):
    sim, tip, n, tangent = pressed(model, response, friction=(0.3, 0.3))
    for step in range(1, 401):
        sim.step_position(tip + 0.001 * step * tangent)
    assert sim.slipping
    sim.step_position(tip + 3.0 * n)
    assert not sim.in_contact and not sim.slipping
    assert not sim.stiffness(np.zeros((3, 3))).any()
    fresh, *_ = pressed(model, response, friction=(0.3, 0.3))
    sim.step_position(tip + (1.0 + 0.15) * n)  # back in from above, as pressed() did
    for s in np.linspace(0, 1, 11)[1:]:
        sim.step_position(tip + (1.0 + 0.15) * n - s * (1.0 + 0.15) * n)
    np.testing.assert_allclose(sim._force, fresh._force, rtol=1e-9, atol=1e-15)


def test_a_random_walk_with_friction_stays_sane(model, response):
    sim, rng = model.simulator(response=response), np.random.default_rng(3)
    sim.set_friction(0.8, 0.5)
    lo, hi = model.vertices.min(axis=0) - 2.0, model.vertices.max(axis=0) + 2.0
    tip, slipped, stuck = 0.5 * (lo + hi), 0, 0
    for i in range(50_000):
        jump = i % 1000 == 0
        tip = rng.uniform(lo, hi) if jump else np.clip(tip + rng.normal(0, 0.05, 3), lo, hi)
        force = sim.step_position(tip)
        assert np.all(np.isfinite(force))
        if sim.in_contact and sim.depth > 0:
            fn, ft = split(sim)
            bound = 0.8 * fn * (1 + 1e-12)
            assert np.linalg.norm(ft) <= bound
            slipped += sim.slipping
            stuck += not sim.slipping
    assert slipped > 100 and stuck > 100


def test_friction_allocates_nothing(model):
    sim, tip, n, tangent = pressed(model, None)
    K = np.zeros((3, 3))
    tips = [np.ascontiguousarray(tip + 0.002 * k * tangent) for k in range(400)]
    for p in tips:
        sim.step_position(p)
        sim.stiffness(K)
    before = sys.getallocatedblocks()
    for p in tips:
        sim.step_position(p)
        sim.stiffness(K)
    assert sys.getallocatedblocks() - before < 50


@pytest.mark.parametrize(
    "args",
    [(np.nan,), (-0.1,), (11.0,), (True,), ("0.5",), (0.3, 0.5), (0.5, np.inf), (0.5, -1.0),
     (0.5, 0.3, 0.0), (0.5, 0.3, -1.0), (0.5, 0.3, np.nan), (0.5, 0.3, 20.0)],
)  # fmt: skip
def test_bad_coefficients_are_refused_and_nothing_changes(model, args):
    sim = model.simulator()
    sim.set_friction(0.2, 0.1)
    with pytest.raises(InputError):
        sim.set_friction(*args)
    assert sim.friction == (0.2, 0.1, pytest.approx(2 / 3))
