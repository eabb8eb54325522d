"""The physics' error indicator online (issue 18): the sampling's error of a region's
hyper-reduced model, estimated on a second element sample trained apart.

A region's model sums its internal forces over ECSW's sample S1 with the constant tangent
C1 (:mod:`.hyperreduced`); the trainer also stores a check sample S2, ECSW's own selection
and weights at a tighter tolerance, with its own constant tangent C2 (both exact in their
linear part). S2 shares elements with S1 (the loaded ones): a sample kept apart from S1's
elements missed them (README, stop 46: 133-145 elements, eta 5-19 times the error). At a
state x = (q, pi) the two models' residuals differ by

    d(x) = (C2 - C1) x + sum_{S2} w_e g_e(x) - sum_{S1} w_e g_e(x)

(the load, the holders' penalty and the linear part cancel), the part of the full order's
internal force that S1 misses where S2 holds it. One Newton step on it, with the tangent
the physics factorised last, turns it into a displacement,

    eta = |(T^-1 d)_q| / |q|,

the relative error of the displacement field (Phi orthonormal: reduced norms are the
nodal L2 norms) that the sampling leaves, as far as S2 sees it. What eta cannot see: the
basis' truncation (a load the region's solves did not span; README, stop 46 measures
both).

Cost: the two samples' residuals (about 1.5 us an element). :func:`check_part` sums one of
``parts`` parts of each a call, so a physics step carries 1/parts of the estimate, and
the last part finishes it (the snapshot of the state taken at part 0: every part reads
the same state). Buffers (the caller's, reused; :class:`SamplingCheck` makes them): xq
(n,), xp (n_p,) the snapshot, sums, r (n + n_p,), then a Scratch's u, r_u, scalars.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hapticrom.online.dense_solve import _check_factors, _lu_solve
from hapticrom.online.haptic_newton import _readonly
from hapticrom.online.hyperreduced import (
    _F8_1D,
    _F8_2D,
    _RO,
    _SAMPLE,
    _SUMS,
    Scratch,
    _check_element_scratch,
    _check_sample,
    _residual_sum,
)
from hapticrom.shared.errors import InputError

UNFINISHED = -1.0  # check_part's answer before the last part


@njit(inline="always")
def _check_bounds(bounds, S, parts):
    if bounds.shape[0] != parts + 1 or bounds[0] != 0 or bounds[parts] != S:
        raise ValueError("both samples' bounds must run from 0 to their elements in as many parts")
    for k in range(parts):
        if bounds[k + 1] < bounds[k]:
            raise ValueError("bounds must not decrease")


@njit(inline="always")
def _add_part(dN, dV, Phi, Psi, params, weights, first, last, xq, xp, sign, sums, r, u, r_u,
              scalars):  # fmt: skip
    _residual_sum(dN, dV, Phi, Psi, params, weights, first, last, xq, xp, r, u, r_u, scalars)
    for i in range(sums.shape[0]):
        sums[i] += sign * r[i]


@njit(inline="always")
def _finish(difference, lu, pivots, xq, xp, sums) -> float:
    """eta from the summed sample difference: sums += (C2 - C1) x, solved in place."""
    n, size = xq.shape[0], sums.shape[0]
    for i in range(size):
        v = 0.0
        for j in range(size):
            v += difference[i, j] * (xq[j] if j < n else xp[j - n])
        sums[i] += v
    _lu_solve(lu, pivots[0], sums)
    step = state = 0.0
    for i in range(n):
        step += sums[i] * sums[i]
        state += xq[i] * xq[i]
    return np.sqrt(step) / max(np.sqrt(state), 1e-300)


_BOUNDS = "Array(int64, 1, 'C', readonly=True)"
_CHECK = (f"float64({_SAMPLE}, {_SAMPLE}, {_RO.format(2)}, {_BOUNDS}, {_BOUNDS}, int64, "
          f"{_RO.format(1)}, {_RO.format(1)}, {_F8_2D}, int64[:, ::1], {_F8_1D}, {_F8_1D}, "
          f"{_F8_1D}, {_F8_1D}, {_F8_2D}, {_F8_1D}, {_F8_1D})")  # fmt: skip


@njit(_CHECK, cache=True, nogil=True, fastmath=_SUMS)
def check_part(dN, dV, Phi, Psi, params, weights, dN2, dV2, Phi2, Psi2, params2, weights2,
               difference, bounds, bounds2, part, q, pi, lu, pivots, xq, xp, sums, r, u, r_u,
               scalars):  # fmt: skip
    """Part ``part`` of the estimate (the module's formula): at part 0 the state (q, pi) is
    copied to (xq, xp) and the sums zeroed; then S2's elements bounds2[part] to
    bounds2[part + 1] are added to the sums and S1's (bounds) subtracted, at (xq, xp).
    Returns eta after the last part (with the factors ``lu``, ``pivots[0]``: the physics'
    HapticNewton's), else UNFINISHED. Shapes are checked (ValueError)."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(dN, dV, Phi, Psi, params, weights, q, pi)
    _check_sample(dN2, dV2, Phi2, Psi2, params2, weights2, q, pi)
    if Phi2.shape[1] != m or xq.shape[0] != n or xp.shape[0] != n_p:
        raise ValueError("both samples must have the same element rows; xq, xp the state's")
    size = n + n_p
    if difference.shape[0] != size or difference.shape[1] != size:
        raise ValueError("difference must be square of n + n_p")
    if sums.shape[0] != size or r.shape[0] != size or lu.shape[0] != size:
        raise ValueError("sums, r and lu must be of n + n_p")
    if lu.shape[1] != size or pivots.shape[0] != 2 or pivots.shape[1] != size:
        raise ValueError("lu must be square of n + n_p and pivots (2, n + n_p)")
    parts = bounds.shape[0] - 1
    if parts < 1:
        raise ValueError("bounds must hold at least one part")
    _check_bounds(bounds, S, parts)
    _check_bounds(bounds2, Phi2.shape[0], parts)
    if not 0 <= part < parts:
        raise ValueError("part must be one of the bounds' parts")
    _check_element_scratch(m, u, r_u, scalars)
    _check_factors(lu, pivots[0])
    if part == 0:
        xq[:] = q
        xp[:] = pi
        sums[:] = 0.0
    _add_part(dN2, dV2, Phi2, Psi2, params2, weights2, bounds2[part], bounds2[part + 1], xq, xp,
              1.0, sums, r, u, r_u, scalars)  # fmt: skip
    _add_part(dN, dV, Phi, Psi, params, weights, bounds[part], bounds[part + 1], xq, xp, -1.0,
              sums, r, u, r_u, scalars)  # fmt: skip
    if part + 1 < parts:
        return UNFINISHED
    return _finish(difference, lu, pivots, xq, xp, sums)


MAX_PARTS = 100_000  # an estimate's parts: 100 s of steps at 1 kHz


def _shared(a) -> np.ndarray:
    """``a`` itself if it is already a read-only C float64 array (HapticNewton's sample:
    not held twice), else a read-only copy."""
    if isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous \
            and not a.flags.writeable:  # fmt: skip
        return a
    return _readonly(a)


class SamplingCheck:
    """The error indicator of a region's physics (the module's): ``sample`` its model's
    (dN, dV, Phi, Psi, params, weights) and ``linear`` its constant tangent, ``check`` and
    ``check_linear`` the check sample's; an estimate over ``parts`` calls of
    :meth:`advance` (the state read at the first). ``eta`` is the last finished estimate
    (NaN before the first, or if the check's sums were not finite)."""

    def __init__(self, sample, linear, check, check_linear, parts: int):
        integer = isinstance(parts, int | np.integer) and not isinstance(parts, bool)
        if not integer or not 1 <= parts <= MAX_PARTS:
            raise InputError(f"an estimate's steps must be an integer from 1 to {MAX_PARTS}, "
                             f"got {parts!r}")  # fmt: skip
        parts = int(parts)
        self.sample = tuple(_shared(a) for a in sample)
        self.check = tuple(_shared(a) for a in check)
        self.difference = _readonly(np.asarray(check_linear) - np.asarray(linear))
        S, S2 = len(self.sample[5]), len(self.check[5])
        self.bounds = _readonly(np.linspace(0, S, parts + 1), np.int64)
        self.bounds2 = _readonly(np.linspace(0, S2, parts + 1), np.int64)
        n, size = self.sample[2].shape[2], self.difference.shape[0]
        self.xq, self.xp = np.zeros(n), np.zeros(size - n)  # the state the parts read
        self.sums, self.r = np.zeros(size), np.zeros(size)
        self.scratch = Scratch(self.sample[2].shape[1] // 3, n)
        self.part = 0  # the part the next advance sums
        self.eta = np.nan

    def advance(self, q, pi, lu, pivots) -> None:
        """One part at (q, pi) (read at part 0); after the last, ``eta`` with the factors
        (``lu``, ``pivots``: HapticNewton's)."""
        s = self.scratch
        eta = check_part(*self.sample, *self.check, self.difference, self.bounds, self.bounds2,
                         self.part, q, pi, lu, pivots, self.xq, self.xp, self.sums, self.r,
                         s.u, s.r_u, s.scalars)  # fmt: skip
        self.part = (self.part + 1) % (len(self.bounds) - 1)
        if eta != UNFINISHED:
            self.eta = eta if np.isfinite(eta) else np.nan
