"""A physics step of fixed cost for a haptic loop on a hyper-reduced model (issue 18), in
one compiled call: no Python, LAPACK or allocation between the sums.

The model is :mod:`.hyperreduced`'s: R(q, pi) = the sampled sums + ``linear`` (q, pi) -
(load, 0), its tangent the sampled sums' derivative + ``linear``; the residual is summed
over the sample's distinct nodes (each node's displacement and force once), the tangent's
parts element by element. A step from (q, pi):

1. ``iterations`` modified Newton iterations on the residual alone, with the last
   factorised tangent;
2. the tangent of one part of the sampled elements (``bounds[part]`` to
   ``bounds[part + 1]``) at the step's new state, added to the tangent being built; after
   the last part, that tangent (with ``linear``) factorised for the next steps.

The factorised tangent is therefore at most 2 x parts steps old; the state lags equilibrium
by what the iterations leave (it settles on it once the load holds). The first tangent is
the rest's (:class:`HapticNewton`). The factorisation is not given a step of its own: one
more step of age made the held steps diverge on test_ecsw_model's cornea at 3 parts
(measured: the same schedule in numpy diverged, this one settles to 1e-14).

A step whose updated state or tangent part is not finite is refused: :func:`haptic_step`
returns ``REFUSED`` and q, pi and the kept state are as they were. A built tangent that
does not factorise (an entry not finite, or singular to working precision: see
:func:`~hapticrom.online.dense_solve._lu_factor`) is dropped: the last factors stay and
``counters[FAILED_FACTORISATIONS]`` counts it. Buffers (all the caller's, reused, none
overlapping another: :class:`HapticNewton` makes them so), between steps:

    counters (COUNTER_SIZE,) int64: PART, the part the next step sums,
      FAILED_FACTORISATIONS;
    lu (size, size), pivots (2, size): the factorised tangent and its pivots (row 0, as
      dense_solve.lu_factor leaves them; row 1 the factorisation's scratch); building
      (size, size): the tangent being summed (``linear`` plus the parts before PART);
    x, r (size,), K (size, size): the step's state, residual and part; node_u,
      node_forces (N, 3): the residual's displacement and force of each of the sample's
      N distinct nodes (node_rows (N, 3, n) and slots (S, nodes) after the sample:
      :func:`~hapticrom.online.hyperreduced.shared_nodes`'); then a
    :class:`~hapticrom.online.hyperreduced.Scratch`'s buffers but T; then PhiQ (S, m, N)
    (Phi's rows in the precision of the tangent parts' q-q projection, float64 or float32,
    padded to N >= n columns for its register tiles: :func:`projection_rows`) and that
    projection's buffers Kw (m, m), TQ (m, N), Kqq (N, N); size = n + n_p.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hapticrom.online.dense_solve import _check_factors, _lu_factor, _lu_solve, lu_factor
from hapticrom.online.hyperreduced import (
    _F8_1D,
    _F8_2D,
    _RO,
    _SAMPLE,
    _SUMS,
    Scratch,
    _check_nodes,
    _check_sample,
    _check_tangent_outputs,
    _residual_nodes,
    _tangent_part,
    sampled_residual_tangent,
    shared_nodes,
)
from hapticrom.online.vector_tiles import TILE_BYTES
from hapticrom.shared.errors import InputError

PART, FAILED_FACTORISATIONS, COUNTER_SIZE = 0, 1, 2  # offsets into the counters
# the tangent parts' q-q projection: "single" took it 232 -> 151 us a part on the demo's
# held region in loops (stop 50; in register tiles since stop 52, single's Phi padded to 16
# columns' multiples) and leaves where the steps settle unchanged (the residual decides)
PRECISIONS = {"single": np.float32, "double": np.float64}
REFUSED = -1.0  # haptic_step's answer to a step it refused


@njit(inline="always")
def _finite(a) -> bool:
    for v in a.flat:
        if not np.isfinite(v):
            return False
    return True


@njit(inline="always")
def _negative_residual(linear, x, load, r):
    """r = -(r + linear x - (load, 0)): the right-hand side of a Newton update."""
    size, n = x.shape[0], load.shape[0]
    for i in range(size):
        v = r[i]
        for j in range(size):
            v += linear[i, j] * x[j]
        if i < n:
            v -= load[i]
        r[i] = -v


@njit(inline="always")
def _relative_update(delta, x, n) -> float:
    """|delta q| / |q| (q = x[:n]), the last update against the state."""
    step = state = 0.0
    for i in range(n):
        step += delta[i] * delta[i]
        state += x[i] * x[i]
    return np.sqrt(step) / max(np.sqrt(state), 1e-300)


@njit(inline="always")
def _check_step(linear, bounds, load, counters, lu, pivots, building, x, n, S):
    size = linear.shape[0]
    square = linear.shape[1] == size and lu.shape[0] == size and lu.shape[1] == size
    if not (square and building.shape[0] == size and building.shape[1] == size):
        raise ValueError("linear, lu, building must be square of n + n_p (the Scratch's)")
    if x.shape[0] != size or pivots.shape[0] != 2 or pivots.shape[1] != size:
        raise ValueError("x must be (n + n_p,) and pivots (2, n + n_p)")
    if load.shape[0] != n or counters.shape[0] != COUNTER_SIZE:
        raise ValueError("load must be (n,) and counters (COUNTER_SIZE,)")
    parts = bounds.shape[0] - 1
    if parts < 1 or bounds[0] != 0 or bounds[parts] != S:
        raise ValueError("bounds must run from 0 to the sampled elements")
    for k in range(parts):
        if bounds[k + 1] < bounds[k]:
            raise ValueError("bounds must not decrease")
    if not 0 <= counters[PART] < parts:
        raise ValueError("counters[PART] must be a part of bounds")
    _check_factors(lu, pivots[0])


@njit(inline="always")
def _next_tangent(linear, counters, lu, pivots, building, K):
    """After the last part: building factorised into lu (else dropped and counted), and a
    new sum started."""
    size = linear.shape[0]
    for i in range(size):
        for j in range(size):
            K[i, j] = building[i, j]
            building[i, j] = linear[i, j]
    if _lu_factor(K, pivots[1]):
        lu[:, :] = K
        pivots[0, :] = pivots[1]
    else:
        counters[FAILED_FACTORISATIONS] += 1
    counters[PART] = 0


_I8_1D, _I8_2D = "int64[::1]", "int64[:, ::1]"


def _step_signature(precision: str) -> str:
    """haptic_step's types, its tangent's q-q block projected in ``precision``."""
    low = f"Array({precision}, 3, 'C', readonly=True), {precision}[:, ::1], {precision}[:, ::1]"
    return (f"float64({_SAMPLE}, {_RO.format(3)}, Array(int64, 2, 'C', readonly=True), "
            f"{_RO.format(2)}, Array(int64, 1, 'C', readonly=True), "
            f"int64, {_RO.format(1)}, {_F8_1D}, {_F8_1D}, {_I8_1D}, {_F8_2D}, {_I8_2D}, {_F8_2D}, "
            f"{_F8_1D}, {_F8_1D}, {_F8_2D}, {_F8_2D}, {_F8_2D}, {_F8_2D}, {_F8_1D}, {_F8_2D}, "
            f"{_F8_1D}, {_F8_1D}, {low}, {precision}[:, ::1])")  # fmt: skip


@njit(inline="always")
def _check_projection(PhiQ, Kw, TQ, Kqq, S, m, n):
    """PhiQ (S, m, N), N >= n (Phi's columns, padded for the projection's tiles); Kw (m, m),
    TQ (m, N), Kqq (N, N)."""
    N = PhiQ.shape[2]
    if PhiQ.shape[0] != S or PhiQ.shape[1] != m or N < n:
        raise ValueError("PhiQ must be Phi's shape or wider; Kw (m, m), TQ (m, N), Kqq (N, N)")
    if Kw.shape[0] != m or Kw.shape[1] != m or TQ.shape[0] != m or TQ.shape[1] != N:
        raise ValueError("PhiQ must be Phi's shape or wider; Kw (m, m), TQ (m, N), Kqq (N, N)")
    if Kqq.shape[0] != N or Kqq.shape[1] != N:
        raise ValueError("PhiQ must be Phi's shape or wider; Kw (m, m), TQ (m, N), Kqq (N, N)")


@njit([_step_signature("float64"), _step_signature("float32")], cache=True, nogil=True,
      fastmath=_SUMS)  # fmt: skip
def haptic_step(dN, dV, Phi, Psi, params, weights, node_rows, slots, linear, bounds,
                iterations, load, q, pi, counters, lu, pivots, building, x, r, K, node_u,
                node_forces, u, r_u, K_uu, K_up, scalars, PhiQ, Kw, TQ, Kqq):  # fmt: skip
    """One step under ``load`` (n,) from (q, pi), updated in place (the module's steps and
    buffers); returns the last iteration's |delta q| / |q|, or REFUSED (nothing changed).
    The tangent part's q-q block is projected in PhiQ's precision (float64 or float32;
    PhiQ: Phi rounded to it, maybe padded: :func:`projection_rows`; Kw, TQ, Kqq its
    buffers). Shapes and slots are checked (ValueError) before anything is written; that
    node_rows and slots are Phi's (shared_nodes') and PhiQ is Phi rounded (and padded) is
    not (it would cost what they save): else the residual and the tangent are of two
    bases. :class:`HapticNewton` makes them itself."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(dN, dV, Phi, Psi, params, weights, q, pi)
    _check_nodes(node_rows, slots, node_u, node_forces, S, m, n)
    # TQ is (m, N >= n) here (_check_projection): its first n columns stand for Scratch.T
    _check_tangent_outputs(m, n, n_p, r, K, u, r_u, K_uu, K_up, scalars, TQ[:, :n])
    _check_projection(PhiQ, Kw, TQ, Kqq, S, m, n)
    _check_step(linear, bounds, load, counters, lu, pivots, building, x, n, S)
    if iterations < 1:
        raise ValueError("iterations must be at least 1")
    x[:n] = q
    x[n:] = pi
    update = 0.0
    for _ in range(iterations):
        _residual_nodes(dN, dV, node_rows, slots, Psi, params, weights, x[:n], x[n:], r, node_u,
                        node_forces, u, r_u, scalars)  # fmt: skip
        _negative_residual(linear, x, load, r)
        _lu_solve(lu, pivots[0], r)
        for i in range(n + n_p):
            x[i] += r[i]
        if not _finite(x):  # x is the step's own: q, pi unchanged
            return REFUSED
        update = _relative_update(r, x, n)
    part = counters[PART]
    _tangent_part(dN, dV, Phi, Psi, params, weights, bounds[part], bounds[part + 1], x[:n],
                  x[n:], r, K, u, r_u, K_uu, K_up, scalars, PhiQ, Kw, TQ, Kqq)  # fmt: skip
    if not _finite(K):
        return REFUSED
    for i in range(n + n_p):
        for j in range(n + n_p):
            building[i, j] += K[i, j]
    counters[PART] = part + 1
    if part + 1 == bounds.shape[0] - 1:
        _next_tangent(linear, counters, lu, pivots, building, K)
    q[:] = x[:n]
    pi[:] = x[n:]
    return update


# An element's tangent (law, stiffness and tiled projection), modelled by its projection's
# multiply-add count m^2 n + m n^2 / 2, against the factorisation's size^3 / 3, in time:
# 2.6 times as many a microsecond, measured on the demo's held region after the tiles (stop
# 52, an AMD EPYC): an element's tangent 7.8 us for 104k, the factorisation of 102 unknowns
# with its copies about 70 us for 354k.
ELEMENT_TANGENT_RATE = 2.6


def part_bounds(elements: int, parts: int, size: int, nodes_rows: int, modes: int) -> np.ndarray:
    """The tangent's parts as bounds (parts + 1 int64 from 0 to ``elements``): equal in cost
    with the factorisation (size = n + n_p) that the step of the last part adds counted in
    that part, in elements of equal cost. A step's cost is what the loop waits on, so its
    largest, not its mean, is the one to lower. The model: size^3 / 3 multiply-adds for the
    factorisation, (m^2 n + m n^2 / 2) / ELEMENT_TANGENT_RATE for an element's tangent (m =
    ``nodes_rows``, its rows; n = ``modes``): 8.9 elements on the demo's held region (102;
    24, 72; measured about 9). The last part keeps an element even where the factorisation
    outweighs a part: an empty one would make the factorisation a step of its own, one
    more step of the tangent's age (the module's note: that diverged at 3 parts)."""
    element = max(1.0, (nodes_rows**2 * modes + nodes_rows * modes**2 / 2) / ELEMENT_TANGENT_RATE)
    factorisation = size**3 / 3 / element
    per_part = (elements + factorisation) / parts
    last = min(elements, max(1, round(per_part - factorisation)))
    bounds = np.empty(parts + 1, np.int64)
    bounds[:-1] = np.rint(np.linspace(0, elements - last, parts))
    bounds[-1] = elements
    return bounds


def projection_rows(Phi, dtype) -> np.ndarray:
    """Phi's rows for the tangent parts' q-q projection in ``dtype``. float64: Phi itself,
    so that a part is :func:`~hapticrom.online.hyperreduced.sampled_residual_tangent`'s
    sums over its elements bit for bit (register tiles where n is a multiple of 8, as
    there). float32: rounded, and padded with zero columns to a whole number of a vector
    tile's 16 lanes (vector_tiles; the demo's held region: 72 -> 80), so that the
    projection always runs in register tiles. InputError if Phi overflows float32."""
    if np.dtype(dtype) == np.float64:
        return Phi
    S, m, n = Phi.shape
    lanes = TILE_BYTES // np.dtype(dtype).itemsize
    rows = np.zeros((S, m, -(-n // lanes) * lanes), dtype)
    with np.errstate(over="ignore"):  # an overflow is refused below
        rows[:, :, :n] = Phi
    if not np.isfinite(rows).all():
        raise InputError("the sample's Phi overflows single precision: precision='double'")
    rows.flags.writeable = False
    return rows


def _readonly(a, dtype=np.float64) -> np.ndarray:
    a = np.array(a, dtype=dtype, order="C")
    a.flags.writeable = False
    return a


class HapticNewton:
    """The haptic loop's physics on a hyper-reduced model: :func:`haptic_step` with its
    buffers. ``sample``: the model's (dN, dV, Phi, Psi, params, weights) (a
    ``HyperReducedModel``'s ``.sample``, or an artifact's), ``linear`` (n + n_p square) its
    constant tangent; ``iterations`` a step, the tangent in ``slices`` parts (the defaults
    1 and 20: stop 42's two-tool measurement; the Python class it replaced had 2 and 10),
    the last smaller by the factorisation after it (:func:`part_bounds`). The first
    tangent is the rest's. ``precision``: the tangent parts' q-q block projected in
    "single" (float32: Phi's rows rounded and padded, twice the vector lanes; the default,
    see PRECISIONS) or "double". InputError for values the class checks (the counts,
    non-finite arrays, weights, a rest tangent that does not factorise, the precision);
    sample shapes that do not agree raise the kernels' ValueError."""

    def __init__(self, sample, linear, iterations: int = 1, slices: int = 20,
                 precision: str = "single"):  # fmt: skip
        if len(sample) != 6:
            raise InputError("sample must be (dN, dV, Phi, Psi, params, weights)")
        self.sample = tuple(_readonly(a) for a in sample)
        for name, a in zip(("dN", "dV", "Phi", "Psi", "params", "weights"), self.sample,
                           strict=True):  # fmt: skip
            if not np.isfinite(a).all():
                raise InputError(f"the sample's {name} must be finite")
        if not (self.sample[5] > 0).all():
            raise InputError("the sample's weights must be positive")
        S, m, n = self.sample[2].shape
        size = n + self.sample[3].shape[1]
        self.linear = _readonly(linear)
        if self.linear.shape != (size, size) or not np.isfinite(self.linear).all():
            raise InputError(f"linear must be finite and square of n + n_p = {size}")
        for name, value, low, high in (("iterations", iterations, 1, None),
                                       ("slices", slices, 1, S)):  # fmt: skip
            integer = isinstance(value, int | np.integer) and not isinstance(value, bool)
            if not integer or value < low or (high is not None and value > high):
                upto = f" to the sampled elements ({high})" if high is not None else ""
                raise InputError(f"{name} must be an integer from {low}{upto}")
        if not isinstance(precision, str) or precision not in PRECISIONS:
            raise InputError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.iterations = int(iterations)
        self.bounds = _readonly(part_bounds(S, slices, size, m, n), np.int64)
        self.counters = np.zeros(COUNTER_SIZE, np.int64)
        self.lu, self.building = np.empty((size, size)), self.linear.copy()
        self.pivots = np.zeros((2, size), np.int64)
        self.x, self.r, self.K = np.empty(size), np.empty(size), np.empty((size, size))
        self.scratch = Scratch(m // 3, n)
        # the rest's tangent; the kernel checks the sample's shapes (before shared_nodes)
        sampled_residual_tangent(*self.sample, np.zeros(n), np.zeros(size - n), self.r,
                                 self.K, *self.scratch.buffers())  # fmt: skip
        # the sample's distinct nodes (the residual's) and their displacements and forces
        node_rows, slots = shared_nodes(self.sample[2])
        self.nodes = (_readonly(node_rows), _readonly(slots, np.int64))
        self.node_u, self.node_forces = np.empty((len(node_rows), 3)), np.empty((len(node_rows), 3))
        # the tangent parts' q-q projection: Phi's rows and the buffers in its precision
        low = PRECISIONS[precision]
        self.precision = precision
        PhiQ = projection_rows(self.sample[2], low)
        N = PhiQ.shape[2]
        self.projection = (PhiQ, np.empty((m, m), low), np.empty((m, N), low),
                           np.empty((N, N), low))  # fmt: skip
        self._element_buffers = (*self.scratch.buffers()[:-1], *self.projection)  # T: TQ's
        np.add(self.K, self.linear, out=self.lu)
        if not lu_factor(self.lu, self.pivots[0]):
            raise InputError("the model's tangent at rest is singular: no first step")
        self.last_update = np.inf  # the last step's |delta q| / |q|
        # keep / undo: the counters before a step, and the factors and the tangent being
        # built before a step that finishes a tangent (copied then only)
        self._kept_counters = np.zeros(COUNTER_SIZE, np.int64)
        self._kept_lu, self._kept_building = np.empty((size, size)), np.empty((size, size))
        self._kept_pivots = np.zeros(size, np.int64)
        self._kept = False  # a keep() that undo() may take back

    def refresh(self, q, pi) -> bool:
        """The whole tangent at (q, pi), factorised now (one call of every part: the cost of
        ``slices`` steps' parts at once), the tangent being built dropped; False if it does
        not factorise (then the last factors stay)."""
        sampled_residual_tangent(*self.sample, q, pi, self.r, self.K, *self.scratch.buffers())
        np.add(self.K, self.linear, out=self.building)
        factored = lu_factor(self.building, self.pivots[1])
        if factored:
            self.lu[:] = self.building
            self.pivots[0] = self.pivots[1]
        self.building[:] = self.linear
        self.counters[PART] = 0
        return bool(factored)

    def keep(self) -> None:
        """Remember the tangent's state before a step, for :meth:`undo`: the counters and
        the tangent being built (one copy of it), and before a step that finishes a
        tangent the factors too."""
        np.copyto(self._kept_counters, self.counters)
        np.copyto(self._kept_building, self.building)
        self._kept = True
        if self.counters[PART] == len(self.bounds) - 2:
            np.copyto(self._kept_lu, self.lu)
            np.copyto(self._kept_pivots, self.pivots[0])

    def undo(self) -> None:
        """Take back, bit for bit, the tangent's change by the one step taken since
        :meth:`keep`; the state is the caller's to restore. A caller that drops a step's
        state drops its part too: else a tangent at a state thrown away would steer the
        next steps. InputError without a :meth:`keep` before it."""
        if not self._kept:
            raise InputError("undo takes back a step taken after keep(); none was kept")
        if self._kept_counters[PART] == len(self.bounds) - 2:
            np.copyto(self.lu, self._kept_lu)
            np.copyto(self.pivots[0], self._kept_pivots)
        np.copyto(self.building, self._kept_building)
        np.copyto(self.counters, self._kept_counters)
        self._kept = False

    @property
    def part(self) -> int:
        """The tangent part the next step sums."""
        return int(self.counters[PART])

    @property
    def failed_factorisations(self) -> int:
        return int(self.counters[FAILED_FACTORISATIONS])

    def step(self, q, pi, load) -> bool:
        """One step under ``load`` (n,) from (q, pi) (float64, contiguous), updated in place;
        False if it was refused (then nothing changed)."""
        update = haptic_step(*self.sample, *self.nodes, self.linear, self.bounds,
                             self.iterations, load, q, pi, self.counters, self.lu, self.pivots,
                             self.building, self.x, self.r, self.K, self.node_u,
                             self.node_forces, *self._element_buffers)  # fmt: skip
        if update == REFUSED:
            return False
        self.last_update = update
        return True
