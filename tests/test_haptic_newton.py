"""The compiled haptic step (:mod:`hapticrom.online.haptic_newton`) and its dense LU
(:mod:`hapticrom.online.dense_solve`), without DOLFINx.

The LU against numpy's LAPACK solve, on saddle-point matrices that need its pivoting. The
step on test_hyperreduced's synthetic meshes against the same schedule written in numpy:
the sums element by element in Python over the element kernel (that module's reference),
the solves by numpy.linalg.solve, the tangent summed over the parts at each step's state
and used from the step after the one that factorises it. Then: the steps settle on
Newton's equilibrium, a step that meets NaN is refused with nothing changed, a tangent
that does not factorise is dropped and counted, wrong inputs refused before anything is
written, and no allocation.
"""

from __future__ import annotations

import numpy as np
import pytest
from allocation_probe import run_probe
from conftest import reseed
from test_hyperreduced import MODES, PRESSURE_MODES, make_problem, numpy_sums, readonly, sample

from hapticrom.online.dense_solve import lu_factor, lu_solve
from hapticrom.online.haptic_newton import (
    ELEMENT_TANGENT_RATE,
    REFUSED,
    HapticNewton,
    haptic_step,
    part_bounds,
)
from hapticrom.online.hyperreduced import Scratch, sampled_residual_tangent
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(20261125)
SIZE = MODES + PRESSURE_MODES
SINGLE_ROUNDING = 1e-5  # float32's epsilon 6e-8 times a sum's terms (m = 24 to 30) and more


# -- the LU -------------------------------------------------------------------------------------
def saddle_matrix(n: int, n_p: int) -> np.ndarray:
    """[[0, B^T], [B, A]] with A symmetric positive definite: the zero diagonal block
    first, which needs row exchanges."""
    G = RNG.standard_normal((n, n))
    A, B = G @ G.T + n * np.eye(n), RNG.standard_normal((n, n_p))
    return np.block([[np.zeros((n_p, n_p)), B.T], [B, A]])


@pytest.mark.parametrize("shape", [(1, 0), (6, 3), (50, 20)])
def test_lu_solves_as_lapack(shape):
    reseed(RNG, f"lu-{shape}")
    M = saddle_matrix(*shape) if shape[1] else np.array([[3.0]])
    b = RNG.standard_normal(len(M))
    lu, pivots, x = M.copy(), np.full(len(M), -1, np.int64), b.copy()
    assert lu_factor(lu, pivots)
    lu_solve(lu, pivots, x)
    expected = np.linalg.solve(M, b)
    assert np.abs(x - expected).max() <= 1e-11 * np.abs(expected).max()
    if shape[1]:
        assert (pivots != np.arange(len(M))).any()  # the zero block made it exchange rows


def test_lu_refuses_singular_and_non_finite_matrices():
    """Singular to working precision (an exact zero column; a repeated row; a random rank-19
    matrix of size 20, whose last pivot is rounding) or an entry not finite anywhere."""
    reseed(RNG, "lu-refusals")
    M = saddle_matrix(6, 3)
    zero_column, repeated = M.copy(), M.copy()
    zero_column[:, 4] = 0.0
    repeated[4] = repeated[2]
    rank_19 = RNG.standard_normal((20, 19)) @ RNG.standard_normal((19, 20))
    off_pivot = np.eye(9)
    off_pivot[0, 5] = np.inf
    for bad in (zero_column, repeated, rank_19, np.where(np.eye(9) == 1, np.nan, M), off_pivot):
        assert not lu_factor(bad.copy(), np.zeros(len(bad), np.int64))
    with pytest.raises(ValueError, match="square"):
        lu_factor(np.zeros((3, 4)), np.zeros(3, np.int64))
    lu, pivots = M.copy(), np.zeros(9, np.int64)
    assert lu_factor(lu, pivots)
    b = np.ones(9)
    for wrong_pivots, wrong_b in ((pivots[:8], b), (pivots, b[:8])):
        with pytest.raises(ValueError, match="square"):
            lu_solve(lu, wrong_pivots, wrong_b)
    corrupt = pivots.copy()
    corrupt[3] = 9
    with pytest.raises(ValueError, match="pivot"):
        lu_solve(lu, corrupt, b)
    zero_diagonal = lu.copy()
    zero_diagonal[5, 5] = 0.0
    with pytest.raises(ValueError, match="diagonal"):
        lu_solve(zero_diagonal, pivots, b)
    assert np.array_equal(b, np.ones(9))


# -- the step -----------------------------------------------------------------------------------
@pytest.fixture(scope="module", params=["hex-hgo", "tet-hgo-incompressible", "hex-mixed-laws"])
def model(request):
    """(problem, elements, weights, sample, linear, a load scale): every element sampled
    but the first, weights in [0.5, 2]; the constant tangent [[0, 0], [0, -M]]."""
    reseed(RNG, f"haptic-{request.param}")
    problem = make_problem(request.param)
    elements = np.arange(1, problem.elements)
    weights = RNG.uniform(0.5, 2.0, len(elements))
    linear = np.zeros((SIZE, SIZE))
    volumes = RNG.uniform(1.0, 2.0, PRESSURE_MODES)
    linear[MODES:, MODES:] = -np.diag(volumes / problem.params[:, 1].max())
    _, K = numpy_sums(problem, elements, weights, np.zeros(MODES), np.zeros(PRESSURE_MODES))
    return problem, elements, weights, sample(problem, elements, weights), linear, K[:MODES, :MODES]


def loads(stiffness, steps: int) -> list[np.ndarray]:
    """A ramp to the load of a state of |q| about 1 (|grad u| up to 0.05-0.15)."""
    target = stiffness @ RNG.standard_normal(MODES)
    return [readonly(k / steps * target) for k in range(1, steps + 1)]


def reference_steps(problem, elements, weights, linear, load_path, iterations, slices):
    """The module's schedule in numpy: the states after each step."""
    bounds = part_bounds(len(elements), slices, SIZE, problem.rows.shape[1], MODES)
    sums = lambda part, x: numpy_sums(problem, elements[part], weights[part], x[:MODES],  # noqa: E731
                                      x[MODES:])  # fmt: skip
    tangent = sums(slice(None), np.zeros(SIZE))[1] + linear
    x, building, part, states = np.zeros(SIZE), linear.copy(), 0, []
    for load in load_path:
        for _ in range(iterations):
            r = sums(slice(None), x)[0] + linear @ x
            r[:MODES] -= load
            x = x + np.linalg.solve(tangent, -r)
        building += sums(slice(bounds[part], bounds[part + 1]), x)[1]
        part += 1
        if part == slices:
            tangent, building, part = building, linear.copy(), 0
        states.append(x.copy())
    return states


@pytest.mark.parametrize("iterations, slices", [(1, 3), (2, 1), (1, 5)])
def test_steps_follow_the_numpy_schedule(model, iterations, slices):
    problem, elements, weights, inputs, linear, stiffness = model
    reseed(RNG, f"schedule-{iterations}-{slices}")
    slices = min(slices, len(elements))  # the tetrahedra's sample has 2 elements
    path = loads(stiffness, 4 * slices + 1)
    expected = reference_steps(problem, elements, weights, linear, path, iterations, slices)
    solver = HapticNewton(inputs, linear, iterations, slices, precision="double")
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    for k, (load, x) in enumerate(zip(path, expected, strict=True)):
        assert solver.step(q, pi, load), k
        assert np.abs(q - x[:MODES]).max() <= 1e-10 * np.abs(x[:MODES]).max(), k
        assert np.abs(pi - x[MODES:]).max() <= 1e-10 * np.abs(x[MODES:]).max(), k
        assert solver.part == (k + 1) % slices
    assert solver.failed_factorisations == 0


@pytest.mark.parametrize("elements, parts, size", [(414, 30, 102), (414, 1, 102), (40, 7, 20),
                                                   (5, 5, 300), (1000, 20, 60)])  # fmt: skip
def test_the_parts_cost_alike_with_the_factorisation_in_the_last(elements, parts, size):
    """part_bounds runs from 0 to the elements without decreasing, and the parts, the
    factorisation's element-equivalents counted in the last (the model's, recomputed here),
    differ by at most one element and a half, unless the factorisation alone outweighs a
    part (then the last keeps one element, the others even): no part is empty. Equal parts
    would put the whole factorisation on the last step."""
    m, n = 24, 72
    bounds = part_bounds(elements, parts, size, m, n)
    assert bounds.dtype == np.int64 and len(bounds) == parts + 1
    assert bounds[0] == 0 and bounds[-1] == elements and (np.diff(bounds) >= 1).all()
    factorisation = size**3 / 3 / ((m * m * n + m * n * n / 2) / ELEMENT_TANGENT_RATE)
    costs = np.diff(bounds).astype(float)
    costs[-1] += factorisation
    if factorisation <= (elements + factorisation) / parts:
        assert costs.max() - costs.min() <= 1.5, costs
    else:
        assert bounds[-2] == elements - 1 and np.ptp(np.diff(bounds)[:-1]) <= 1


def newton_equilibrium(problem, elements, weights, linear, load) -> np.ndarray:
    x = np.zeros(SIZE)
    for _ in range(30):
        r, K = numpy_sums(problem, elements, weights, x[:MODES], x[MODES:])
        r += linear @ x
        r[:MODES] -= load
        delta = np.linalg.solve(K + linear, -r)
        x += delta
        if np.linalg.norm(delta) <= 1e-14 * np.linalg.norm(x):
            return x
    raise AssertionError("Newton did not converge")


@pytest.mark.parametrize("precision", ["single", "double"])
def test_steps_settle_on_the_equilibrium(model, precision):
    """Under a held load the fixed-cost steps converge to Newton's root (in numpy); the
    last update goes to 0. With the tangent's projection in single precision too: the
    tangent steers, the residual (double) decides where the steps stop."""
    problem, elements, weights, inputs, linear, stiffness = model
    reseed(RNG, "settle")
    load = loads(stiffness, 1)[0]
    expected = newton_equilibrium(problem, elements, weights, linear, load)
    solver = HapticNewton(inputs, linear, 1, 2, precision=precision)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    for _ in range(60):
        assert solver.step(q, pi, load)
    assert np.abs(q - expected[:MODES]).max() <= 1e-10 * np.abs(expected[:MODES]).max()
    assert np.abs(pi - expected[MODES:]).max() <= 1e-10 * np.abs(expected[MODES:]).max()
    assert solver.last_update <= 1e-10


def test_a_single_precision_tangent_part_is_the_double_one_rounded(model):
    """From the same state under the same load, the tangent part (half the elements: the
    step does not factorise it) summed with its q-q projection in single precision is the
    double one to float32's rounding of the products' sums (relative to the block's
    largest entry), its q-pi block and residual (double in both) bit for bit."""
    _, elements, _, inputs, linear, stiffness = model
    reseed(RNG, "single-part")
    load = loads(stiffness, 2)[0]
    parts = {}
    for precision in ("single", "double"):
        solver = HapticNewton(inputs, linear, 1, 2, precision=precision)
        q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
        assert solver.step(q, pi, load)  # the rest's factors in both: the same state
        parts[precision] = solver.K.copy(), solver.r.copy(), q
    (K1, r1, q1), (K2, r2, q2) = parts["single"], parts["double"]
    assert np.array_equal(q1, q2) and np.array_equal(r1, r2)
    n = MODES
    assert np.array_equal(K1[:n, n:], K2[:n, n:]) and np.array_equal(K1[n:, :n], K2[n:, :n])
    error = np.abs(K1[:n, :n] - K2[:n, :n]).max() / np.abs(K2[:n, :n]).max()
    assert 0 < error <= SINGLE_ROUNDING, error
    assert np.array_equal(K1, K1.T)


def test_a_double_precision_tangent_part_is_the_sampled_sums_over_its_elements(model):
    """precision="double": a step's tangent part (the first part's elements) is
    sampled_residual_tangent's r and K over those elements at the step's state, bit for
    bit (the same operations in the same order)."""
    _, _, _, inputs, linear, stiffness = model
    reseed(RNG, "double-part")
    solver = HapticNewton(inputs, linear, 1, 2, precision="double")
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    assert solver.step(q, pi, loads(stiffness, 2)[0]) and solver.part == 1
    first, last = solver.bounds[:2]
    part = tuple(readonly(a[first:last]) for a in solver.sample)
    r, K = np.full(SIZE, np.nan), np.full((SIZE, SIZE), np.nan)
    scratch = Scratch(solver.sample[2].shape[1] // 3, MODES)
    sampled_residual_tangent(*part, readonly(q), readonly(pi), r, K, *scratch.buffers())
    assert np.array_equal(solver.K, K) and np.array_equal(solver.r, r)


def solver_state(solver, q, pi) -> list[np.ndarray]:
    return [a.copy() for a in (q, pi, solver.counters, solver.lu, solver.pivots, solver.building)]


def test_a_step_meeting_nan_is_refused_and_changes_nothing(model):
    _, _, _, inputs, linear, stiffness = model
    reseed(RNG, "nan")
    solver = HapticNewton(inputs, linear, 1, 2)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    for load in loads(stiffness, 4)[:4]:  # through a factorisation: lu is not the rest's
        assert solver.step(q, pi, load)
    before, update = solver_state(solver, q, pi), solver.last_update
    bad = loads(stiffness, 1)[0].copy()
    bad[2] = np.nan
    assert not solver.step(q, pi, bad)
    assert haptic_step(*arguments(solver, q, pi, readonly(bad)).values()) == REFUSED
    for a, b in zip(before, solver_state(solver, q, pi), strict=True):
        assert np.array_equal(a, b)
    assert solver.last_update == update


@pytest.mark.parametrize("slices", [1, 3])
def test_undo_takes_a_step_back_bit_for_bit(model, slices):
    """keep, step, undo: the counters, factors, pivots and the tangent being built are
    those before the step, bit for bit, at a part in the middle of a tangent and at the
    part that finishes one; undo without keep is refused."""
    _, elements, _, inputs, linear, stiffness = model
    reseed(RNG, f"undo-{slices}")
    slices = min(slices, len(elements))
    solver = HapticNewton(inputs, linear, 1, slices)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    with pytest.raises(InputError, match="keep"):
        solver.undo()
    path = loads(stiffness, 2 * slices + 2)

    def kept(s):  # pivots' row 1 is the factorisation's scratch
        return [a.copy() for a in (s.counters, s.lu, s.pivots[0], s.building)]

    for load in path[:-1]:
        assert solver.step(q, pi, load)
        before = kept(solver)
        solver.keep()
        assert solver.step(q.copy(), pi.copy(), path[-1])
        solver.undo()
        for a, b in zip(before, kept(solver), strict=True):
            assert np.array_equal(a, b)


def test_a_step_whose_tangent_part_is_not_finite_is_refused(model):
    """A load a thousand times the ramp's: the update is finite but inverts elements, so
    the tangent part at the new state is not (on the step that would factorise)."""
    _, _, _, inputs, linear, stiffness = model
    reseed(RNG, "part-nan")
    solver = HapticNewton(inputs, linear, 1, 2)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    load = loads(stiffness, 4)[0]
    assert solver.step(q, pi, load) and solver.part == 1
    before = solver_state(solver, q, pi)
    assert not solver.step(q, pi, readonly(1e3 * load))
    assert not np.isfinite(solver.K).all()  # the part's, not the update's, refusal
    for a, b in zip(before, solver_state(solver, q, pi), strict=True):
        assert np.array_equal(a, b)


def test_a_tangent_that_does_not_factorise_is_dropped(model):
    """The built tangent made singular before its last part (every entry -1e300, which
    the part's entries do not change: rank one): the last factors stay, the failure is
    counted and a new tangent is started."""
    _, _, _, inputs, linear, stiffness = model
    reseed(RNG, "singular")
    solver = HapticNewton(inputs, linear, 1, 2)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    load = loads(stiffness, 8)[0]
    assert solver.step(q, pi, load) and solver.part == 1  # the first part summed
    lu, pivots = solver.lu.copy(), solver.pivots[0].copy()
    solver.building[:] = -1e300
    assert solver.step(q, pi, load)
    assert solver.failed_factorisations == 1 and solver.part == 0
    assert np.array_equal(solver.lu, lu) and np.array_equal(solver.pivots[0], pivots)
    assert np.array_equal(solver.building, linear)


def readonly_single(a) -> np.ndarray:
    a = np.array(a, dtype=np.float32, order="C")
    a.flags.writeable = False
    return a


def arguments(solver, q, pi, load) -> dict:
    names = ("dN", "dV", "Phi", "Psi", "params", "weights")
    scratch = ("u", "r_u", "K_uu", "K_up", "scalars")
    projection = ("PhiQ", "Kw", "TQ", "Kqq")
    return {**dict(zip(names, solver.sample, strict=True)), "node_rows": solver.nodes[0],
            "slots": solver.nodes[1], "linear": solver.linear,
            "bounds": solver.bounds, "iterations": solver.iterations, "load": load, "q": q,
            "pi": pi, "counters": solver.counters, "lu": solver.lu, "pivots": solver.pivots,
            "building": solver.building, "x": solver.x, "r": solver.r, "K": solver.K,
            "node_u": solver.node_u, "node_forces": solver.node_forces,
            **dict(zip(scratch, solver.scratch.buffers()[:-1], strict=True)),
            **dict(zip(projection, solver.projection, strict=True))}  # fmt: skip


def test_the_residual_reads_each_shared_node_once(model):
    """The sample's distinct node rows (shared_nodes): fewer than its elements' nodes (the
    synthetic mesh's elements share nodes), and every element's rows read back from them
    bit for bit."""
    _, _, _, inputs, linear, _ = model
    solver = HapticNewton(inputs, linear, 1, 1)
    node_rows, slots = solver.nodes
    Phi = solver.sample[2]
    S, m, n = Phi.shape
    assert len(node_rows) < S * m // 3
    assert np.array_equal(node_rows[slots].reshape(S, m, n), Phi)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    args = arguments(solver, q, pi, readonly(np.zeros(MODES)))
    for bad in (len(node_rows), -1):  # one past the last row, and before the first
        outside = slots.copy()
        outside[-1, -1] = bad
        args["slots"] = readonly_int(outside)
        before = solver_state(solver, q, pi) + [solver.node_u.copy()]
        with pytest.raises(ValueError, match="a slot is not a row of node_rows"):
            haptic_step(*args.values())
        for a, b in zip(before, solver_state(solver, q, pi) + [solver.node_u], strict=True):
            assert np.array_equal(a, b, equal_nan=True)


def readonly_int(values) -> np.ndarray:
    a = np.array(values, dtype=np.int64)
    a.flags.writeable = False
    return a


@pytest.mark.parametrize("name, wrong, message", [
    ("load", lambda S: readonly(np.zeros(MODES + 1)), "load"),
    ("q", lambda S: np.zeros(MODES + 1), r"q \(n,\)"),
    ("x", lambda S: np.zeros(SIZE + 1), "x must"),
    ("r", lambda S: np.zeros(SIZE - 1), "r must"),
    ("K", lambda S: np.zeros((SIZE, SIZE - 1)), "K square"),
    ("linear", lambda S: readonly(np.zeros((SIZE, SIZE + 1))), "square"),
    ("lu", lambda S: np.zeros((SIZE - 1, SIZE - 1)), "square"),
    ("building", lambda S: np.zeros((SIZE, 2)), "square"),
    ("bounds", lambda S: readonly_int([0, S - 1]), "bounds"),
    ("bounds", lambda S: readonly_int([1, S]), "bounds"),
    ("bounds", lambda S: readonly_int([0]), "bounds"),
    ("bounds", lambda S: readonly_int([0, S, 1, S]), "bounds"),
    ("counters", lambda S: np.array([2, 0], np.int64), "counters"),
    ("counters", lambda S: np.array([-1, 0], np.int64), "counters"),
    ("counters", lambda S: np.zeros(1, np.int64), "counters"),
    ("iterations", lambda S: 0, "iterations"),
    ("pivots", lambda S: np.full((2, SIZE), SIZE, np.int64), "pivot"),
    ("pivots", lambda S: np.zeros((1, SIZE), np.int64), "pivots"),
    ("lu", lambda S: np.zeros((SIZE, SIZE)), "diagonal"),
    ("u", lambda S: np.zeros((2, 3)), "scratch"),
    ("r_u", lambda S: np.zeros(2), "scratch"),
    ("K_uu", lambda S: np.zeros((2, 2)), "scratch"),
    ("K_up", lambda S: np.zeros(2), "scratch"),
    ("scalars", lambda S: np.zeros(1), "scratch"),
    ("TQ", lambda S: np.zeros((3, 3), np.float32), "scratch"),
    ("PhiQ", lambda S: readonly_single(np.zeros((S, 3, MODES))), "PhiQ"),
    ("Kw", lambda S: np.zeros((3, 3), np.float32), "Kw"),
    ("Kqq", lambda S: np.zeros((MODES, MODES + 1), np.float32), "Kqq"),
    ("slots", lambda S: readonly_int(np.zeros((S, 1))), "slots"),
    ("node_rows", lambda S: readonly(np.zeros((1, 3, MODES + 1))), "node_rows"),
    ("node_u", lambda S: np.zeros((1, 3)), "node_u"),
    ("node_forces", lambda S: np.zeros((1, 2)), "node_forces"),
])  # fmt: skip
def test_wrong_inputs_refused_before_writing(model, name, wrong, message):
    _, _, _, inputs, linear, stiffness = model
    solver = HapticNewton(inputs, linear, 1, 2)
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    args = arguments(solver, q, pi, loads(stiffness, 4)[0])
    args[name] = wrong(len(inputs[0]))
    before = solver_state(solver, q, pi) + [solver.x.copy()]
    with pytest.raises(ValueError, match=message):
        haptic_step(*args.values())
    for a, b in zip(before, solver_state(solver, q, pi) + [solver.x], strict=True):
        assert np.array_equal(a, b, equal_nan=True)


def test_projection_buffers_narrower_than_the_padded_rows_refused(model):
    """In single precision the rows are padded (MODES -> 16 columns) and the tiles write
    TQ (m, 16) and Kqq (16, 16): buffers of Phi's width, or rows narrower than Phi, would be
    read or written past their ends; refused before anything is written."""
    _, _, _, inputs, linear, stiffness = model
    solver = HapticNewton(inputs, linear, 1, 2)
    PhiQ = solver.projection[0]
    m, N = PhiQ.shape[1:]
    assert N == 16 > MODES
    q, pi = np.zeros(MODES), np.zeros(PRESSURE_MODES)
    for name, wrong in (("TQ", np.zeros((m, MODES), np.float32)),
                        ("Kqq", np.zeros((MODES, MODES), np.float32)),
                        ("PhiQ", readonly_single(PhiQ[:, :, : MODES - 1]))):  # fmt: skip
        args = arguments(solver, q, pi, loads(stiffness, 4)[0])
        args[name] = wrong
        before = solver_state(solver, q, pi) + [solver.x.copy()]
        with pytest.raises(ValueError, match=name):
            haptic_step(*args.values())
        for a, b in zip(before, solver_state(solver, q, pi) + [solver.x], strict=True):
            assert np.array_equal(a, b, equal_nan=True)


def test_constructor_refusals(model):
    _, _, _, inputs, linear, _ = model
    S = len(inputs[0])
    cases = [((inputs[:5], linear), {}, "sample"),
             ((inputs, linear[:-1]), {}, "linear"),
             ((inputs, np.where(np.eye(SIZE) == 1, np.nan, linear)), {}, "linear"),
             ((inputs, linear), {"iterations": 0}, "iterations"),
             ((inputs, linear), {"iterations": True}, "iterations"),
             ((inputs, linear), {"slices": 0}, "slices"),
             ((inputs, linear), {"slices": S + 1}, "slices"),
             ((inputs, linear), {"slices": 2.0}, "slices"),
             ((inputs[:5] + (-inputs[5],), linear), {"slices": 1}, "weights"),
             ((inputs[:2] + (np.nan * inputs[2],) + inputs[3:], linear), {"slices": 1}, "Phi"),
             ((inputs[:2] + (0 * inputs[2],) + inputs[3:], linear), {"slices": 1},
              "singular"),
             ((inputs, linear), {"slices": 1, "precision": "half"}, "precision"),
             ((inputs, linear), {"slices": 1, "precision": ["single"]}, "precision"),
             ((inputs[:2] + (inputs[2] * 1e39 / np.abs(inputs[2]).max(),) + inputs[3:],
               linear), {"slices": 1}, "overflows")]  # fmt: skip
    for args, kwargs, message in cases:
        with pytest.raises(InputError, match=message):
            HapticNewton(*args, **kwargs)


def test_allocates_nothing():
    """numba's allocation counters (which see an allocating canary) move as much over 1000
    steps from a compiled driver as over one (the boxing of the driver's arguments)."""
    body = """
        from hapticrom.online import element_kernels as ek, material_kernels as mk
        from hapticrom.online.haptic_newton import HapticNewton, haptic_step

        @njit
        def run(dN, dV, Phi, Psi, params, w, node_rows, slots, linear, bounds, load, q, pi,
                counters, lu, pivots, building, x, r, K, node_u, node_forces, u, r_u, K_uu,
                K_up, scalars, PhiQ, Kw, TQ, Kqq, n):
            total = 0.0
            for _ in range(n):
                total += haptic_step(dN, dV, Phi, Psi, params, w, node_rows, slots, linear,
                                     bounds, 2, load, q, pi, counters, lu, pivots, building,
                                     x, r, K, node_u, node_forces, u, r_u, K_uu, K_up,
                                     scalars, PhiQ, Kw, TQ, Kqq)
            return total

        rng = np.random.default_rng(1)
        ref = ek.reference_element("hexahedron")
        S, n, n_p = 3, 4, 2
        X = np.array([ref.nodes + 0.02 * rng.standard_normal(ref.nodes.shape) for _ in range(S)])
        X.flags.writeable = False
        dN, dV = np.empty((S, len(ref.weights), 8, 3)), np.empty((S, len(ref.weights)))
        ek.element_geometry(X, ref.gradients, ref.weights, dN, dV)
        law = mk.law_parameters("hgo", m0=np.array([1.0, 0, 0]), n0=np.array([0, 1.0, 0]))
        sample = (dN, dV, 0.01 * rng.standard_normal((S, 24, n)), rng.standard_normal((S, n_p)),
                  [law] * S, [1.0, 2.0, 0.5])
        linear = np.zeros((n + n_p, n + n_p))
        linear[n:, n:] = -np.eye(n_p)
        solver = HapticNewton(sample, linear, 2, 2)
        q, pi, load = np.zeros(n), np.zeros(n_p), 1e-4 * rng.standard_normal(n)
        load.flags.writeable = False
        same_allocations(run, *solver.sample, *solver.nodes, solver.linear, solver.bounds,
                         load, q, pi, solver.counters, solver.lu, solver.pivots,
                         solver.building, solver.x, solver.r, solver.K, solver.node_u,
                         solver.node_forces, *solver.scratch.buffers()[:-1],
                         *solver.projection)
        assert np.isfinite(q).all() and np.abs(q).max() > 0
        print("ok")
    """
    run_probe(body)
