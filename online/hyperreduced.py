"""The hyper-reduced internal forces: a reduced mixed model's residual and tangent summed
over the elements ECSW sampled (issue 18), for an online reduced Newton.

The reduced state is (q, pi): displacement u = Phi q (Phi: n global modes) and element
pressure p = Psi pi (Psi: n_p global pressure modes, one row a cell). The reduced mixed
residual (the trainer's, :mod:`hapticrom.online.element_kernels`, projected) is

    R_q  = L_q q + L_qp pi + sum_e w_e Phi_e^T r_u,e(u_e, p_e) - f
    R_pi = L_qp^T q - M pi + sum_e w_e Psi_e Theta_e(u_e)

with Theta_e = int_e theta dV, M = sum_e V_e / kappa_e Psi_e^T Psi_e over every element,
and the sum over e ECSW's: the sampled elements with their weights w_e. The model chooses
the linear matrices L_q, L_qp. Sampling only the nonlinear rest matters for a nearly
incompressible tissue (the pressure rows Theta are a sum of terms that nearly cancel, which
a few weighted elements reproduce poorly, while their linear part, the divergence of u, is
exact; bench/ecsw_tradeoff.py measures both): with K0_e, k0_e the element's tangent blocks
at rest, the model takes L_q = sum_all Phi_e^T K0_e Phi_e - sum_e w_e Phi_e^T K0_e Phi_e
and L_qp likewise with k0_e Psi_e, which is the sampled sum of r_u,e - K0_e u_e - k0_e p_e
and Theta_e - k0_e . u_e plus the exact linear part, summed in the reduced space (an n x n
product a call instead of an m x m one an element). :func:`element_contributions` gives
each element's nonlinear term apart, unweighted: the columns of ECSW's training matrix.

:func:`sampled_residual_tangent` is the sum and its derivative in (q, pi), and
:func:`sampled_residual` the sum alone; the caller adds the linear matrices and the load.
Layouts, for S sampled elements of ``nodes`` nodes (m = 3 nodes rows, node-major as the
element kernels'):

    dN (S, points, nodes, 3) physical gradients and dV (S, points) point volumes (mm^3):
    element_kernels.element_geometry's; Phi (S, m, n) basis rows; Psi (S, n_p) the cell's
    pressure-basis row; params (S, PARAMETER_SIZE); weights (S,); K0 (S, m, m), k0 (S, m).

Outputs r (n + n_p) and K (n + n_p, n + n_p), q rows first; every entry written. The
caller's :class:`Scratch` holds the element buffers: nothing is allocated per call. The
kernels are compiled with ``_SUMS``: sums may be reassociated and products fused, so that
the sums over modes and an element's sums over its points and nodes (the element kernel's
``_integrate_mapped``, inlined) vectorise; results differ from sequential sums by
rounding. No flag assumes finite numbers: a NaN still reaches the output. The material
laws are compiled apart without these flags (material_kernels), whatever numba's cache
holds, except hgo's at every point of an element at once (``_hgo_points``, the residual's:
inlined so that it vectorises). Measured on 325 HGO hexahedra at 50 + 20 modes
(/proc/cpuinfo: an Intel Xeon): the residual 1.9 -> 1.5 us an element with the element
kernel inlined under these flags; on the demo's held region (414 hexahedra, 72 + 30
modes; an AMD EPYC) 2.1 -> 1.6 us with hgo's points in vector lanes (stop 49).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hapticrom.online.element_kernels import (
    PRESSURE_RESIDUAL,
    SCALAR_SIZE,
    VOLUME,
    _integrate_mapped,
)
from hapticrom.online.material_kernels import KAPPA, PARAMETER_SIZE
from hapticrom.online.vector_tiles import (
    TILE_ROWS,
    tile,
    tile_add,
    tile_fma,
    tile_lanes,
    tile_store,
    tile_zero,
)

_SUMS = {"reassoc", "contract"}  # numba fastmath flags of the sums over modes


class Scratch:
    """The per-element buffers of :func:`sampled_residual_tangent` for ``nodes``-node
    elements and n modes: made once, reused every call."""

    def __init__(self, nodes: int, modes: int):
        m = 3 * nodes
        self.u = np.zeros((nodes, 3))  # the element's displacement
        self.r_u = np.zeros(m)
        self.K_uu = np.zeros((m, m))
        self.K_up = np.zeros(m)
        self.scalars = np.zeros(SCALAR_SIZE)
        self.T = np.zeros((m, modes))  # the element's weighted K_uu Phi_e

    def buffers(self) -> tuple:
        return self.u, self.r_u, self.K_uu, self.K_up, self.scalars, self.T


def shared_nodes(Phi) -> tuple[np.ndarray, np.ndarray]:
    """The sample's distinct node rows and where each element's nodes are among them:
    (node_rows (N, 3, n), slots (S, nodes) int64), node_rows[slots[s, a]] equal to
    Phi[s, 3a : 3a + 3] for every element s and node a. Sampled elements share nodes (the
    demo's held region: 3,312 element nodes, 1,076 distinct), and :func:`_residual_nodes`
    computes each node's displacement and projects its force once. Rows equal in value are
    one node whether or not they are one mesh node: the sums are the same."""
    Phi = np.ascontiguousarray(Phi, dtype=np.float64)
    S, m, n = Phi.shape
    distinct, slots = np.unique(Phi.reshape(S * (m // 3), 3 * n), axis=0, return_inverse=True)
    return (np.ascontiguousarray(distinct.reshape(-1, 3, n)),
            np.ascontiguousarray(slots.reshape(S, m // 3), dtype=np.int64))  # fmt: skip


@njit(inline="always")
def _element_pressure(Psi, s, pi):
    """p = Psi[s] . pi."""
    p = 0.0
    for j in range(pi.shape[0]):
        p += Psi[s, j] * pi[j]
    return p


@njit(inline="always")
def _element_state(Phi, Psi, s, q, pi, u):
    """u = Phi[s] q as (nodes, 3); returns p = Psi[s] . pi."""
    m, n = Phi.shape[1], Phi.shape[2]
    for row in range(m):
        v = 0.0
        for j in range(n):
            v += Phi[s, row, j] * q[j]
        u[row // 3, row % 3] = v
    return _element_pressure(Psi, s, pi)


@njit(inline="always")
def _theta(scalars, p, kappa):
    """Theta_e = int theta dV from the element's scalars (r_p = Theta_e - p V_e / kappa)."""
    return scalars[PRESSURE_RESIDUAL] + p * scalars[VOLUME] / kappa


@njit(inline="always")
def _add_projected(Phi, Psi, s, weight, theta, r_u, r):
    """r += weight (Phi[s]^T r_u, Psi[s] theta): an element's term of the reduced residual
    (the rows outside, so that the modes are the contiguous inner loop)."""
    m, n = Phi.shape[1], Phi.shape[2]
    for row in range(m):
        a = weight * r_u[row]
        for i in range(n):
            r[i] += a * Phi[s, row, i]
    for k in range(Psi.shape[1]):
        r[n + k] += weight * Psi[s, k] * theta


@njit(inline="always")
def _add_coupling(Phi, Psi, s, weight, K_up, K):
    """K[:n, n:] += weight Phi^T K_up Psi: an element's q-pi block."""
    m, n, n_p = Phi.shape[1], Phi.shape[2], Psi.shape[1]
    for i in range(n):
        t = 0.0
        for row in range(m):
            t += Phi[s, row, i] * K_up[row]
        t *= weight
        for k in range(n_p):
            K[i, n + k] += t * Psi[s, k]


@njit(inline="always")
def _add_projected_stiffness(PhiQ, s, weight, K_uu, Kw, TQ, Kqq):
    """Kqq's upper triangle += weight Phi^T K_uu Phi over PhiQ's N columns (Phi's, or Phi's
    padded: a padded column only gives Kqq entries past Phi's), in the precision of PhiQ,
    Kw, TQ and Kqq (Phi's rows rounded to it; Kw = weight K_uu first, in that precision; Kw
    may be K_uu itself). Where N is a whole number of a vector's lanes, in register tiles
    (:func:`_tiled_projection`, which also writes the diagonal blocks' lower triangles: no
    caller reads them): 85 -> 23 us for 12 of the demo held region's elements in float32
    (stop 52). Else the loops below: the modes their contiguous inner loops, counted from 0
    (numba's index wraparound then folds away and they vectorise), over a node's 3 rows at
    a time."""
    m, n = PhiQ.shape[1], PhiQ.shape[2]
    for row in range(m):
        for c in range(m):
            Kw[row, c] = weight * K_uu[row, c]
    if n % tile_lanes(PhiQ) == 0:
        _tiled_projection(PhiQ[s], Kw, TQ, Kqq)
        return
    for row in range(m):  # TQ = Kw PhiQ
        for j in range(n):
            TQ[row, j] = 0.0
        for c in range(0, m, 3):
            a0, a1, a2 = Kw[row, c], Kw[row, c + 1], Kw[row, c + 2]
            for j in range(n):
                TQ[row, j] += a0 * PhiQ[s, c, j] + a1 * PhiQ[s, c + 1, j] + a2 * PhiQ[s, c + 2, j]
    for i in range(n):
        for c in range(0, m, 3):
            b0, b1, b2 = PhiQ[s, c, i], PhiQ[s, c + 1, i], PhiQ[s, c + 2, i]
            for j in range(n - i):
                Kqq[i, i + j] += b0 * TQ[c, i + j] + b1 * TQ[c + 1, i + j] + b2 * TQ[c + 2, i + j]


@njit(inline="always")
def _tiled_projection(P, Kw, TQ, Kqq):
    """TQ = Kw P and Kqq += P^T TQ on its upper block triangle (the diagonal blocks whole),
    P (m, N) an element's rows, N a whole number of tile lanes (vector_tiles): each tile of
    TILE_ROWS x lanes summed over the m rows in registers. TQ's rows past the last whole
    tile one at a time."""
    m, N = P.shape
    lanes = tile_lanes(P)
    acc = tile(P)
    whole = m - m % TILE_ROWS
    for i in range(0, whole, TILE_ROWS):
        for jb in range(N // lanes):
            tile_zero(acc)
            for c in range(m):
                tile_fma(acc, P, c, jb * lanes, Kw[i, c], Kw[i + 1, c], Kw[i + 2, c], Kw[i + 3, c])
            tile_store(acc, TQ, i, jb * lanes)
    for row in range(whole, m):
        for j in range(N):
            TQ[row, j] = 0.0
        for c in range(m):
            a = Kw[row, c]
            for j in range(N):
                TQ[row, j] += a * P[c, j]
    blocks = N // lanes
    for ib in range(N // TILE_ROWS):
        i = ib * TILE_ROWS
        first = i // lanes  # the row's diagonal block: the blocks left of it are below it
        for jb in range(blocks - first):
            j = (first + jb) * lanes
            tile_zero(acc)
            for c in range(m):
                tile_fma(acc, TQ, c, j, P[c, i], P[c, i + 1], P[c, i + 2], P[c, i + 3])
            tile_add(acc, Kqq, i, j)


@njit(inline="always")
def _symmetrize(K):
    """The lower triangle of K from its upper one (the q-q block's and the q-pi block)."""
    size = K.shape[0]
    for i in range(size):
        for j in range(i + 1, size):
            K[j, i] = K[i, j]


@njit(inline="always")
def _nonlinear_part(K0, k0, s, u, p, r_u, theta):
    """r_u -= K0 u + k0 p in place; returns theta - k0 . u (the element's nonlinear terms)."""
    m = r_u.shape[0]
    for row in range(m):
        linear = k0[s, row] * p
        for column in range(m):
            linear += K0[s, row, column] * u[column // 3, column % 3]
        r_u[row] -= linear
        theta -= k0[s, row] * u[row // 3, row % 3]
    return theta


@njit(inline="always")
def _residual_sum(dN, dV, Phi, Psi, params, weights, first, last, q, pi, r, u, r_u, scalars):
    """r = the sum over the sampled elements first..last - 1 (shapes checked by the caller)."""
    r[:] = 0.0
    for s in range(first, last):
        p = _element_state(Phi, Psi, s, q, pi, u)
        _integrate_mapped(dN[s], dV[s], u, p, params[s], r_u, None, None, scalars)
        _add_projected(Phi, Psi, s, weights[s], _theta(scalars, p, params[s, KAPPA]), r_u, r)


@njit(inline="always")
def _residual_nodes(dN, dV, node_rows, slots, Psi, params, weights, q, pi, r, node_u,
                    node_forces, u, r_u, scalars):  # fmt: skip
    """:func:`_residual_sum` over every sampled element, each distinct node's displacement
    computed and its force projected once (:func:`shared_nodes`), not once an element it
    belongs to: an order of n fewer operations a shared node (shapes checked by the
    caller). The same sums in another order."""
    n = node_rows.shape[2]
    for a in range(node_rows.shape[0]):  # node_u = node_rows q
        for i in range(3):
            v = 0.0
            for j in range(n):
                v += node_rows[a, i, j] * q[j]
            node_u[a, i] = v
            node_forces[a, i] = 0.0
    r[:] = 0.0
    for s in range(slots.shape[0]):
        for b in range(slots.shape[1]):
            for i in range(3):
                u[b, i] = node_u[slots[s, b], i]
        p = _element_pressure(Psi, s, pi)
        _integrate_mapped(dN[s], dV[s], u, p, params[s], r_u, None, None, scalars)
        for b in range(slots.shape[1]):
            for i in range(3):
                node_forces[slots[s, b], i] += weights[s] * r_u[3 * b + i]
        theta = _theta(scalars, p, params[s, KAPPA])
        for k in range(Psi.shape[1]):
            r[n + k] += weights[s] * Psi[s, k] * theta
    for a in range(node_rows.shape[0]):  # r[:n] = node_rows^T node_forces
        for i in range(3):
            f = node_forces[a, i]
            for j in range(n):
                r[j] += f * node_rows[a, i, j]


@njit(inline="always")
def _tangent_part(dN, dV, Phi, Psi, params, weights, first, last, q, pi, r, K, u, r_u, K_uu,
                  K_up, scalars, PhiQ, Kw, TQ, Kqq):  # fmt: skip
    """r and K = the sums over the sampled elements first..last - 1 (shapes checked by the
    caller): a whole tangent, or a slice of one (:mod:`.haptic_newton`). The q-q block is
    projected in PhiQ's precision (PhiQ: Phi's rows in it; Kw, TQ, Kqq buffers in it, which
    in float64 may be K_uu, T and K themselves): in float32, twice the vector lanes a
    product. A modified Newton's tangent steers its iterations, the residual decides where
    they stop."""
    n = Phi.shape[2]
    r[:] = 0.0
    K[:, :] = 0.0
    Kqq[:, :] = 0.0
    for s in range(first, last):
        p = _element_state(Phi, Psi, s, q, pi, u)
        _integrate_mapped(dN[s], dV[s], u, p, params[s], r_u, K_uu, K_up, scalars)
        theta = _theta(scalars, p, params[s, KAPPA])
        _add_projected(Phi, Psi, s, weights[s], theta, r_u, r)
        _add_coupling(Phi, Psi, s, weights[s], K_up, K)
        _add_projected_stiffness(PhiQ, s, weights[s], K_uu, Kw, TQ, Kqq)
    for i in range(n):
        for j in range(i, n):
            K[i, j] = Kqq[i, j]
    _symmetrize(K)


_RO = "Array(float64, {}, 'C', readonly=True)"
_F8_1D, _F8_2D = "float64[::1]", "float64[:, ::1]"
# dN, dV, Phi, Psi, params, weights
_SAMPLE = ", ".join(_RO.format(d) for d in (4, 2, 3, 2, 2, 1))
_STATE = f"{_RO.format(1)}, {_RO.format(1)}"  # q, pi


@njit(inline="always")
def _check_sample(dN, dV, Phi, Psi, params, weights, q, pi):
    """The inputs' shapes agree (ValueError otherwise): the element kernel trusts them."""
    S, m, n = Phi.shape
    if dN.shape[0] != S or dV.shape[0] != S or Psi.shape[0] != S or params.shape[0] != S:
        raise ValueError("dN, dV, Phi, Psi, params and weights must have one row a sampled element")
    if weights.shape[0] != S:
        raise ValueError("dN, dV, Phi, Psi, params and weights must have one row a sampled element")
    if dN.shape[2] * 3 != m or dN.shape[3] != 3 or params.shape[1] < PARAMETER_SIZE:
        raise ValueError("Phi must have 3 rows a node of dN; params PARAMETER_SIZE columns")
    if dN.shape[1] != dV.shape[1]:
        raise ValueError("dN and dV must have the same points")
    if q.shape[0] != n or pi.shape[0] != Psi.shape[1]:
        raise ValueError("q (n,) and pi (n_p,) must have Phi's and Psi's columns")


@njit(inline="always")
def _check_nodes(node_rows, slots, node_u, node_forces, S, m, n):
    """node_rows (N, 3, n), slots (S, m / 3) of rows of node_rows (every one read: a slot
    outside would read outside), node_u and node_forces (N, 3)."""
    N = node_rows.shape[0]
    if node_rows.shape[1] != 3 or node_rows.shape[2] != n:
        raise ValueError("node_rows must be (N, 3, n) and slots (S, nodes): shared_nodes'")
    if slots.shape[0] != S or slots.shape[1] * 3 != m:
        raise ValueError("node_rows must be (N, 3, n) and slots (S, nodes): shared_nodes'")
    if node_u.shape[0] != N or node_u.shape[1] != 3:
        raise ValueError("node_u and node_forces must be (N, 3), N node_rows' nodes")
    if node_forces.shape[0] != N or node_forces.shape[1] != 3:
        raise ValueError("node_u and node_forces must be (N, 3), N node_rows' nodes")
    for s in range(S):
        for b in range(slots.shape[1]):
            if not 0 <= slots[s, b] < N:
                raise ValueError("a slot is not a row of node_rows")


@njit(inline="always")
def _check_element_scratch(m, u, r_u, scalars):
    if u.shape[0] * 3 != m or u.shape[1] != 3 or r_u.shape[0] != m:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")
    if scalars.shape[0] != SCALAR_SIZE:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")


@njit(inline="always")
def _check_tangent_outputs(m, n, n_p, r, K, u, r_u, K_uu, K_up, scalars, T):
    """r (n + n_p,), K square of that size and a Scratch for m element rows and n modes."""
    if r.shape[0] != n + n_p or K.shape[0] != n + n_p or K.shape[1] != n + n_p:
        raise ValueError("r must be (n + n_p,) and K square of that size")
    _check_element_scratch(m, u, r_u, scalars)
    if K_uu.shape[0] != m or K_uu.shape[1] != m or K_up.shape[0] != m:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")
    if T.shape[0] != m or T.shape[1] != n:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")


@njit(f"void({_SAMPLE}, {_STATE}, {_F8_1D}, {_F8_2D}, {_F8_2D}, {_F8_1D}, {_F8_2D}, {_F8_1D}, "
      f"{_F8_1D}, {_F8_2D})", cache=True, nogil=True, fastmath=_SUMS)  # fmt: skip
def sampled_residual_tangent(dN, dV, Phi, Psi, params, weights, q, pi, r, K, u, r_u, K_uu,
                             K_up, scalars, T):  # fmt: skip
    """The sampled elements' sums of the module's formulas at (q, pi) into r, K; the last
    six arguments are a :class:`Scratch`'s buffers. Shapes are checked (ValueError)."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(dN, dV, Phi, Psi, params, weights, q, pi)
    _check_tangent_outputs(m, n, n_p, r, K, u, r_u, K_uu, K_up, scalars, T)
    _tangent_part(dN, dV, Phi, Psi, params, weights, 0, S, q, pi, r, K, u, r_u, K_uu, K_up,
                  scalars, Phi, K_uu, T, K)  # fmt: skip


@njit(f"void({_SAMPLE}, {_STATE}, {_F8_1D}, {_F8_2D}, {_F8_1D}, {_F8_1D})", cache=True,
      nogil=True, fastmath=_SUMS)  # fmt: skip
def sampled_residual(dN, dV, Phi, Psi, params, weights, q, pi, r, u, r_u, scalars):
    """The residual part of :func:`sampled_residual_tangent` alone (no tangent: an order
    of n fewer operations an element), into r: the iterations of a modified Newton, whose
    tangent is an earlier one. u, r_u, scalars: a :class:`Scratch`'s."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(dN, dV, Phi, Psi, params, weights, q, pi)
    if r.shape[0] != n + n_p:
        raise ValueError("r must be (n + n_p,)")
    _check_element_scratch(m, u, r_u, scalars)
    _residual_sum(dN, dV, Phi, Psi, params, weights, 0, S, q, pi, r, u, r_u, scalars)


@njit(f"void({_SAMPLE}, {_RO.format(3)}, {_RO.format(2)}, {_STATE}, {_F8_2D}, {_F8_2D}, "
      f"{_F8_1D}, {_F8_1D})", cache=True, nogil=True, fastmath=_SUMS)  # fmt: skip
def element_contributions(dN, dV, Phi, Psi, params, weights, K0, k0, q, pi, out, u, r_u,
                          scalars):  # fmt: skip
    """Each element's own nonlinear term, unweighted: out[s] = (Phi_s^T (r_u - K0_s u_s -
    k0_s p_s), Psi_s (Theta_s - k0_s . u_s)) at (q, pi), (S, n + n_p) - ECSW's training
    columns (``weights`` is read for its shape only). u, r_u, scalars: a :class:`Scratch`'s."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(dN, dV, Phi, Psi, params, weights, q, pi)
    if K0.shape[0] != S or K0.shape[1] != m or K0.shape[2] != m:
        raise ValueError("K0 must be (S, m, m) and k0 (S, m)")
    if k0.shape[0] != S or k0.shape[1] != m:
        raise ValueError("K0 must be (S, m, m) and k0 (S, m)")
    if out.shape[0] != S or out.shape[1] != n + n_p:
        raise ValueError("out must be (S, n + n_p)")
    _check_element_scratch(m, u, r_u, scalars)
    for s in range(S):
        p = _element_state(Phi, Psi, s, q, pi, u)
        _integrate_mapped(dN[s], dV[s], u, p, params[s], r_u, None, None, scalars)
        theta = _nonlinear_part(K0, k0, s, u, p, r_u, _theta(scalars, p, params[s, KAPPA]))
        out[s, :] = 0.0
        _add_projected(Phi, Psi, s, 1.0, theta, r_u, out[s])
