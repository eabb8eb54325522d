"""Position in, force out: the proxy's geometry against brute force and analytic spheres,
then ``Simulator.step_position`` on a trained model (first contact, release, no pop-through,
starting inside, a random walk, the stiffness)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import hapticrom.online as online
from hapticrom.online import proxy
from hapticrom.online.simulator import StepInputError
from hapticrom.shared.errors import OutputArrayError

pytestmark = pytest.mark.serial
RHO = 8.0  # the cap's radius of curvature (mm), about a cornea's


def cap(half: float = 3.0, n: int = 31, rho: float = RHO):
    """A spherical cap z = sqrt(rho^2 - x^2 - y^2) - rho over a lattice, outward +z, every
    triangle loadable: (vertices, triangles, groups)."""
    x = np.linspace(-half, half, n)
    X, Y = np.meshgrid(x, x, indexing="ij")
    Z = np.sqrt(rho**2 - X**2 - Y**2) - rho
    vertices = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    triangles = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return vertices, triangles, np.ones(len(triangles), dtype=np.int8)


def nearest_brute_force(p, points, triangles):
    """The distance from p to a triangle mesh by another route than the kernel's: the
    plane projection where it falls inside, else the nearest point of the three edges."""
    a, b, c = (points[triangles[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    h = np.einsum("ij,ij->i", p - a, n)
    x = p - h[:, None] * n
    inside = np.ones(len(a), dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, x - u), n) >= 0
    best = np.where(inside, np.abs(h), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        s = np.clip(np.einsum("ij,ij->i", p - u, e) / np.einsum("ij,ij->i", e, e), 0, 1)
        best = np.minimum(best, np.linalg.norm(p - (u + s[:, None] * e), axis=1))
    return best.min()


def sheet_of(radius=0.5, **kw):
    vertices, triangles, groups = cap(**kw)
    table = proxy.contact_surface(vertices, triangles, groups, radius)
    views = proxy.sheet_views(table)
    offset, tri = views[0].reshape(-1, 3), views[3].reshape(-1, 3).astype(np.int64)
    return table, offset, tri


def test_the_walk_finds_the_nearest_point_of_the_sheet():
    """From outside (the convex side) the walk ends at the nearest point of the whole sheet.
    From inside, every facet whose plane holds the tip's foot is a local minimum of the
    distance: the walk stops at one, as far as a facet's sagitta (h^2 / (8 rho)) from the
    nearest, and the foot is on the facet (a continuous proxy, not a jump)."""
    table, offset, tri = sheet_of()
    rng = np.random.default_rng(3)
    where = np.zeros(4)
    h = np.linalg.norm(offset[tri[:, 1]] - offset[tri[:, 0]], axis=1).max()
    outside = 0
    for _ in range(400):
        p = np.array([*rng.uniform(-2.5, 2.5, 2), rng.uniform(-1.5, 1.5)])
        proxy.walk(p, table, int(rng.integers(len(tri))), where)  # from anywhere on the sheet
        t, u, v, w = int(where[0]), *where[1:]
        x = u * offset[tri[t, 0]] + v * offset[tri[t, 1]] + w * offset[tri[t, 2]]
        assert min(u, v, w) >= -1e-12 and abs(u + v + w - 1) < 1e-12
        distance, nearest = np.linalg.norm(p - x), nearest_brute_force(p, offset, tri)
        if np.linalg.norm(p - [0, 0, -RHO]) > RHO + 0.5:
            outside += 1
            np.testing.assert_allclose(distance, nearest, rtol=1e-9, atol=1e-12)
        else:
            assert nearest - 1e-12 <= distance <= nearest + h**2 / (8 * RHO)
    assert outside > 50


def test_the_offset_sheet_is_the_sphere_grown_by_the_radius():
    """The sheet of a cap of radius rho offset by R lies on the sphere of radius rho + R
    (its vertices exactly; its flat triangles within their sagitta, about h^2 / (8 rho))."""
    table, offset, tri = sheet_of(radius=0.5)
    centre = np.array([0.0, 0.0, -RHO])
    interior = np.unique(tri[proxy.sheet_views(table)[4].reshape(-1, 3).min(axis=1) >= 0])
    r = np.linalg.norm(offset[interior] - centre, axis=1)
    np.testing.assert_allclose(r, RHO + 0.5, atol=2e-3)  # vertex normals: area-weighted


def test_a_segment_enters_the_sheet_from_outside_only():
    table, offset, tri = sheet_of()
    state = np.zeros(proxy.state_size(table))
    top = np.sqrt((RHO + 0.5) ** 2 - 0.1**2 - 0.2**2) - RHO  # the offset sphere there
    h = np.linalg.norm(offset[tri[:, 1]] - offset[tri[:, 0]], axis=1).max()
    t, s = proxy.first_crossing(np.array([0.1, 0.2, 3.0]), (0.1, 0.2, -3.0), table, state)
    assert t >= 0 and abs(3.0 - 6.0 * s - top) < h**2 / (2 * RHO)  # found where it enters
    t, _ = proxy.first_crossing(np.array([0.1, 0.2, -3.0]), (0.1, 0.2, 3.0), table, state)
    assert t < 0  # leaving: not a contact
    t, _ = proxy.first_crossing(np.array([0.1, 0.2, 3.0]), (0.1, 0.2, 1.0), table, state)
    assert t < 0  # above it all the way
    # A segment through a shared edge or vertex of the lattice still finds a triangle.
    vertex = offset[len(offset) // 2]
    t, s = proxy.first_crossing(vertex + [0, 0, 1.0], tuple(vertex - [0, 0, 1.0]), table, state)
    assert t >= 0 and abs(s - 0.5) < 1e-9


def test_the_grid_is_bounded_for_a_huge_triangle():
    """One triangle 1000x the others would list itself in millions of cells: the cells grow."""
    vertices, triangles, groups = cap()
    vertices = np.vstack([vertices, [[-3000, -3000, -50], [3000, -3000, -50], [0, 3000, -50]]])
    triangles = np.vstack([triangles, [[len(vertices) - 3, len(vertices) - 2, len(vertices) - 1]]])
    table = proxy.contact_surface(vertices, triangles, np.ones(len(triangles)), 0.5)
    views = proxy.sheet_views(table)
    assert len(views[9]) <= 4_000_000 and len(views[8]) <= 200_001


# -- the simulator -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def model(small_artifact):
    return online.load(small_artifact)


def above(model, point, height):
    """A tip position ``height`` (mm) above the surface point along the model's normal there."""
    sim = model.simulator()
    sim.set_contact(point)
    return np.asarray(point) + height * np.asarray(sim.contact_normal), np.array(sim.contact_normal)


def test_a_press_is_a_displacement_step_at_the_proxy_s_foot(model):
    """The depth is the tip's distance behind the offset sheet (brute force over its
    triangles); the force is a plain simulator's at that contact point and depth."""
    sim, plain = model.simulator(), model.simulator()
    views = proxy.sheet_views(sim._sheet)
    offset, tri = views[0].reshape(-1, 3), views[3].reshape(-1, 3).astype(np.int64)
    tip0, n = above(model, model.sample_points[0], 2.0)
    touched = 0
    for height in np.linspace(2.0, -0.2, 23):
        tip = tip0 + (height - 2.0) * n
        force = sim.step_position(tip)
        if not sim.in_contact:
            assert not force.any()
            continue
        touched += 1
        # Along the blended normal rather than the facet's: on this coarse mesh (1.2 mm
        # facets on a 7.8 mm sphere) they are up to 5 degrees apart, cos 5 deg = 0.996.
        np.testing.assert_allclose(
            sim.depth, nearest_brute_force(tip, offset, tri), rtol=5e-3, atol=1e-12
        )
        plain.set_contact(sim.contact_point)
        expected = plain.step_displacement(-sim.depth * np.asarray(plain.contact_normal))
        np.testing.assert_allclose(force, expected, rtol=1e-12, atol=1e-15)
    assert touched > 5 and sim.depth > 0.5 * sim.tool_radius


def test_first_contact_comes_when_the_sphere_reaches_the_surface(model):
    """Approaching along the normal, contact starts within one step of where the sphere's
    edge reaches the surface (a distance of one radius, measured by brute force)."""
    sim = model.simulator()
    tip0, n = above(model, model.sample_points[0], 1.5)
    s = model.artifact["surface"]
    loadable = np.asarray(s["triangles"])[np.asarray(s["groups"]) == 1]
    step = 0.01
    for i in range(300):
        tip = tip0 - i * step * n
        sim.step_position(tip)
        if sim.in_contact:
            break
    gap = nearest_brute_force(tip, model.vertices, loadable)
    assert sim.in_contact and sim.tool_radius - 2 * step < gap <= sim.tool_radius


def test_lifting_releases(model):
    sim = model.simulator()
    assert not sim.in_contact  # nothing pressed yet
    tip0, n = above(model, model.sample_points[0], 1.0)
    sim.step_position(tip0)
    sim.step_position(tip0 - 1.3 * n)
    assert sim.in_contact and sim.depth > 0
    force = sim.step_position(tip0)
    assert not sim.in_contact and not force.any() and sim.depth == 0
    np.testing.assert_array_equal(sim.proxy, tip0)  # free: the proxy is the tip


def test_a_fast_move_through_the_organ_stays_on_its_near_side(model):
    """A tip that jumps from above the cornea to below it in one tick is in contact with
    the anterior surface (pushed back out, held at the displacement limit), not free."""
    sim = model.simulator()
    tip0, n = above(model, model.sample_points[0], 2.0)
    sim.step_position(tip0)
    force = sim.step_position(tip0 - 5.0 * n)  # 3 mm deep: the cornea is 0.6 mm thick
    assert sim.in_contact and sim.saturated
    assert force @ n > 0  # outward, back towards where it came from
    # On the anterior sheet, where the tip entered it, give or take a facet: from inside,
    # the nearest point of a flat facet tilts off the entry point (by 0.3 mm on this mesh).
    views = proxy.sheet_views(sim._sheet)
    offset, tri = views[0].reshape(-1, 3), views[3].reshape(-1, 3).astype(np.int64)
    edge = np.linalg.norm(offset[tri[:, 1]] - offset[tri[:, 0]], axis=1).max()
    entry = tip0 - (2.0 - sim.tool_radius) * n
    assert np.linalg.norm(sim.proxy - entry) < edge and (sim.proxy - entry) @ n > -0.1


def test_a_tip_that_starts_inside_feels_nothing_until_it_enters_again(model):
    sim = model.simulator()
    tip0, n = above(model, model.sample_points[0], -0.3)  # under the surface
    for k in range(20):
        force = sim.step_position(tip0 + 0.01 * k * np.cross(n, [1.0, 0, 0]))
        assert not sim.in_contact and not force.any()
    sim.step_position(tip0 + 2.0 * n)  # out
    assert not sim.in_contact
    force = sim.step_position(tip0)  # and in again: now it is a contact
    assert sim.in_contact and force @ n > 0


def test_sliding_under_the_surface_is_continuous_and_never_pops_through(model):
    """A slide across the trained region at a fixed height below the surface (crossing
    many sheet triangles, edges and vertices): always in contact, the force's change per
    tick bounded by the stiffness times the move, the proxy on the near side."""
    sim = model.simulator()
    a, b = model.sample_points[1], model.sample_points[3]
    tip_a, n = above(model, a, 2.0)
    sim.step_position(tip_a)
    forces, proxies = [], []
    for s in np.linspace(0, 1, 2001):
        point = (1 - s) * a + s * b
        tip, normal = above(model, point, sim.tool_radius - 0.2)
        forces.append(sim.step_position(tip).copy())
        proxies.append(sim.proxy @ normal - point @ normal)
        assert sim.in_contact
    forces = np.array(forces)
    jumps = np.linalg.norm(np.diff(forces, axis=0), axis=1)
    typical = np.linalg.norm(forces, axis=1).max()
    assert jumps.max() < 0.02 * typical  # 2000 ticks: a smooth change, no snag at an edge
    assert min(proxies) > 0.5 * sim.tool_radius  # above the surface: never the far side


def test_a_random_walk_keeps_the_state_sane(model):
    """Fast moves in and out, beyond the trained region and through the organ: no NaN,
    forces bounded, and afterwards a press gives a fresh simulator's force."""
    sim, rng = model.simulator(), np.random.default_rng(7)
    lo, hi = model.vertices.min(axis=0) - 2.0, model.vertices.max(axis=0) + 2.0
    tip = 0.5 * (lo + hi)
    limit = sim.max_displacement
    biggest = 0.0
    for i in range(100_000):
        if i % 1000 == 0:  # now and then a jump anywhere in the box
            tip = rng.uniform(lo, hi)
        else:
            tip = np.clip(tip + rng.normal(0, 0.05, 3), lo, hi)
        force = sim.step_position(tip)
        biggest = max(biggest, float(np.abs(force).max()))
        assert np.all(np.isfinite(force))
        assert sim.depth <= limit
    assert biggest > 0  # it touched
    fresh = model.simulator()
    tip0, n = above(model, model.sample_points[0], 2.0)
    for s in (sim, fresh):
        s.step_position(tip0)
        s.step_position(tip0 - 2.2 * n)
    press = tip0 - 2.2 * n
    np.testing.assert_allclose(sim.step_position(press), fresh.step_position(press))


def test_bad_tips_are_refused_and_nothing_changes(model):
    sim = model.simulator()
    tip0, n = above(model, model.sample_points[0], 0.2)
    good = sim.step_position(tip0).copy()
    state = sim._proxy.copy()
    for bad in ([np.nan, 0, 0], [0, np.inf, 0], [1, 2], "abc", [[1, 2, 3]]):
        with pytest.raises(StepInputError):
            sim.step_position(bad)
    np.testing.assert_array_equal(sim._proxy, state)
    np.testing.assert_array_equal(sim.step_position(tip0), good)


def test_step_position_allocates_nothing(model):
    sim = model.simulator()
    tip0, n = above(model, model.sample_points[0], 0.3)
    tips = [np.ascontiguousarray(tip0 - 0.001 * k * n) for k in range(400)]
    K = np.zeros((3, 3))
    for tip in tips:
        sim.step_position(tip)
        sim.stiffness(K)
    before = sys.getallocatedblocks()
    for _ in range(20):
        for tip in tips:
            sim.step_position(tip)
            sim.stiffness(K)
    assert sys.getallocatedblocks() - before < 50


def test_the_stiffness_is_the_force_s_derivative(model):
    """K against central differences of step_position's force along the normal, K n n^T
    symmetric positive semidefinite, zero out of contact."""
    sim = model.simulator()
    tip0, n = above(model, model.sample_points[0], 2.0)
    sim.step_position(tip0)
    tip = tip0 - (2.0 + 0.15) * n
    sim.step_position(tip)
    K = sim.stiffness(np.zeros((3, 3)))
    eps = 1e-5
    plus = sim.step_position(tip + eps * n).copy()
    minus = sim.step_position(tip - eps * n).copy()
    # The normal term; the proxy's slide and the normal's turn are of order 1 % of it.
    np.testing.assert_allclose(-(plus - minus) / (2 * eps), K @ n, atol=0.01 * np.abs(K @ n).max())
    np.testing.assert_allclose(K, K.T)
    assert np.linalg.eigvalsh(K).min() > -1e-12
    sim.step_position(tip0)
    assert not sim.stiffness(np.zeros((3, 3))).any()
    for bad in (np.zeros((3, 3), dtype=np.float32), np.zeros((2, 3)), np.zeros(9), [[0] * 3] * 3):
        with pytest.raises(OutputArrayError):
            sim.stiffness(bad)


def test_tool_radius_must_be_positive(model):
    from hapticrom.shared.errors import InputError

    assert model.simulator().tool_radius == model.contact_radius
    assert model.simulator(tool_radius=0.25).tool_radius == 0.25
    for bad in (0.0, -1.0, np.nan, "big"):
        with pytest.raises(InputError):
            model.simulator(tool_radius=bad)


def test_a_render_thread_draws_whole_steps_while_the_servo_steps(model):
    """A servo thread steps step_position along the scripted path while a render thread
    draws through sim.renderer(): every rendered surface is the surface of one whole step
    (equal to the bit to the surface a second simulator renders from that step's copied
    state), and both threads run without a busy error."""
    import threading
    import time

    from hapticrom.online.play import scripted_tips
    from hapticrom.online.renderer import SurfaceWork, surface_of

    sim = model.simulator()
    tips = scripted_tips(model, 2000)
    states = {0: sim._buf.copy()}  # the state after each writing call, by sequence

    def servo():  # about 2 kHz, as a servo loop paces itself
        for tip in tips:
            sim.step_position(tip)
            states[sim._sequence // 2] = sim._buf.copy()
            time.sleep(0.0003)

    renderer = sim.renderer()
    frames = []

    def render():
        out = np.zeros_like(model.vertices)
        while thread.is_alive() or not frames:
            frames.append((renderer.surface(out).copy(), renderer.sequence))

    thread = threading.Thread(target=servo)
    drawer = threading.Thread(target=render)
    thread.start()
    drawer.start()
    thread.join()
    drawer.join()
    work = SurfaceWork(model, sim.interpolation, sim.response)
    expected = np.zeros_like(model.vertices)
    distinct = {sequence for _, sequence in frames}
    assert len(distinct) > 5  # the frames caught the servo at many different steps
    for surface, sequence in frames:
        surface_of(states[sequence], work, expected)
        np.testing.assert_array_equal(surface, expected)


def test_si_units_are_the_simulator_in_metres(model):
    """SIUnits: the same forces for positions in m, stiffness in N/m, surfaces in m; bad
    inputs refused by the simulator itself (no broadcasting of a scalar)."""
    from hapticrom.online.units import SIUnits

    mm, si = model.simulator(), SIUnits(model.simulator())
    tip0, n = above(model, model.sample_points[0], 1.0)
    for height in (1.0, 0.2, -0.1):
        tip = tip0 + (height - 1.0) * n
        np.testing.assert_array_equal(si.step_position(tip / 1e3), mm.step_position(tip))
    np.testing.assert_allclose(si.depth * 1e3, mm.depth, rtol=1e-15)
    np.testing.assert_allclose(si.proxy * 1e3, mm.proxy, rtol=1e-15)
    K_si, K_mm = si.stiffness(np.zeros((3, 3))), mm.stiffness(np.zeros((3, 3)))
    np.testing.assert_allclose(K_si, 1e3 * K_mm, rtol=1e-15)
    u_si = si.surface_displacement(np.zeros_like(model.vertices))
    u_mm = mm.surface_displacement(np.zeros_like(model.vertices))
    np.testing.assert_allclose(u_si * 1e3, u_mm, rtol=1e-14, atol=1e-18)
    push = -0.5 * model.trained_force * np.asarray(mm.contact_normal)
    np.testing.assert_allclose(si.step_force(push) * 1e3, mm.step_force(push), rtol=1e-15)
    for bad in (5.0, [1e-3], np.array([1e-3]), "abc", [np.nan, 0, 0]):
        with pytest.raises(StepInputError):
            si.step_position(bad)
