"""The hyper-reduced internal forces: a reduced mixed model's residual and tangent summed
over the elements ECSW sampled (issue 18), for an online reduced Newton.

The reduced state is (q, pi): displacement u = Phi q (Phi: n global modes) and element
pressure p = Psi pi (Psi: n_p global pressure modes, one row a cell). The reduced mixed
residual (the trainer's, :mod:`hapticrom.online.element_kernels`, projected) splits into a
part linear in (u, p), whose reduced matrices are exact and small, and the rest:

    R_q  = L_uu q + L_up pi + sum_e w_e Phi_e^T (r_u,e(u_e, p_e) - K0_e u_e - k0_e p_e) - f
    R_pi = L_up^T q - M pi  + sum_e w_e Psi_e (Theta_e(u_e) - k0_e . u_e)

with K0_e, k0_e the element's tangent blocks at rest (u = 0, p = 0), L_uu = sum_e Phi_e^T
K0_e Phi_e and L_up = sum_e Phi_e^T k0_e Psi_e over every element, M = sum_e V_e / kappa_e
Psi_e^T Psi_e, and Theta_e = int_e theta dV. The sum over e is ECSW's: the sampled elements
with their weights w_e. Sampling only the nonlinear rest matters for a nearly
incompressible tissue: there the pressure rows Theta are a sum of terms that nearly cancel,
which a few weighted elements reproduce poorly, while their linear part (the divergence of
u) is exact here (bench/ecsw_tradeoff.py measures both). With K0 = k0 = 0 the split is off
and the whole residual is sampled.

:func:`sampled_residual_tangent` is that sum and its derivative in (q, pi), and
:func:`sampled_residual` the sum alone; the caller adds the linear matrices and the load.
:func:`element_contributions` gives each sampled element's term apart, unweighted: the
columns of ECSW's training matrix. Layouts, for S sampled elements of ``nodes`` nodes
(m = 3 nodes rows, node-major as the element kernels'):

    X (S, nodes, 3) reference nodes (mm); Phi (S, m, n) basis rows; Psi (S, n_p) the cell's
    pressure-basis row; params (S, PARAMETER_SIZE); weights (S,); K0 (S, m, m); k0 (S, m);
    gradients, quadrature (points, nodes, 3), (points,): the reference element's.

Outputs r (n + n_p) and K (n + n_p, n + n_p), q rows first; every entry written. The
caller's :class:`Scratch` holds the element buffers: nothing is allocated per call.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hapticrom.online.element_kernels import (
    MAX_NODES,
    PRESSURE_RESIDUAL,
    SCALAR_SIZE,
    VOLUME,
    _integrate,
)
from hapticrom.online.material_kernels import KAPPA, PARAMETER_SIZE


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
        self.T = np.zeros((m, modes))  # the element's K_nl Phi_e

    def buffers(self) -> tuple:
        return self.u, self.r_u, self.K_uu, self.K_up, self.scalars, self.T


@njit(inline="always")
def _element_state(Phi, Psi, s, q, pi, u):
    """u = Phi[s] q as (nodes, 3); returns p = Psi[s] . pi."""
    m, n = Phi.shape[1], Phi.shape[2]
    for row in range(m):
        v = 0.0
        for j in range(n):
            v += Phi[s, row, j] * q[j]
        u[row // 3, row % 3] = v
    p = 0.0
    for j in range(pi.shape[0]):
        p += Psi[s, j] * pi[j]
    return p


@njit(inline="always")
def _residual_nonlinear_part(K0, k0, s, u, p, r_u, scalars, kappa):
    """r_u -= K0 u + k0 p in place; returns the nonlinear part of Theta_e."""
    m = r_u.shape[0]
    theta = scalars[PRESSURE_RESIDUAL] + p * scalars[VOLUME] / kappa
    for row in range(m):
        linear = k0[s, row] * p
        for column in range(m):
            linear += K0[s, row, column] * u[column // 3, column % 3]
        r_u[row] -= linear
        theta -= k0[s, row] * u[row // 3, row % 3]
    return theta


@njit(inline="always")
def _element_residual(X, Phi, Psi, params, K0, k0, gradients, quadrature, s, q, pi, u, r_u,
                      scalars):  # fmt: skip
    """Sampled element s's nonlinear residual at (q, pi): r_u in place; returns Theta's."""
    p = _element_state(Phi, Psi, s, q, pi, u)
    _integrate(X[s], u, p, params[s], gradients, quadrature, r_u, None, None, scalars)
    return _residual_nonlinear_part(K0, k0, s, u, p, r_u, scalars, params[s, KAPPA])


@njit(inline="always")
def _add_projected(Phi, Psi, s, weight, theta, r_u, r):
    """r += weight (Phi[s]^T r_u, Psi[s] theta): an element's term of the reduced residual."""
    m, n = Phi.shape[1], Phi.shape[2]
    for i in range(n):
        v = 0.0
        for row in range(m):
            v += Phi[s, row, i] * r_u[row]
        r[i] += weight * v
    for k in range(Psi.shape[1]):
        r[n + k] += weight * Psi[s, k] * theta


@njit(inline="always")
def _nonlinear_parts(K0, k0, s, u, p, r_u, K_uu, K_up, scalars, kappa):
    """:func:`_residual_nonlinear_part`, and K_uu -= K0, K_up -= k0 in place."""
    theta = _residual_nonlinear_part(K0, k0, s, u, p, r_u, scalars, kappa)
    m = r_u.shape[0]
    for row in range(m):
        K_up[row] -= k0[s, row]
        for column in range(m):
            K_uu[row, column] -= K0[s, row, column]
    return theta


@njit(inline="always")
def _accumulate(Phi, Psi, s, weight, theta, r_u, K_uu, K_up, T, r, K):
    """r += w (Phi^T r_u, Psi theta); K += w (Phi^T K_uu Phi, Phi^T K_up Psi, sym.)."""
    m, n, n_p = Phi.shape[1], Phi.shape[2], Psi.shape[1]
    for row in range(m):  # T = K_uu Phi
        for j in range(n):
            T[row, j] = 0.0
        for column in range(m):
            a = K_uu[row, column]
            for j in range(n):
                T[row, j] += a * Phi[s, column, j]
    for i in range(n):
        v = 0.0
        t = 0.0
        for row in range(m):
            v += Phi[s, row, i] * r_u[row]
            t += Phi[s, row, i] * K_up[row]
        r[i] += weight * v
        for j in range(i, n):  # the upper triangle: Phi^T T is symmetric
            a = 0.0
            for row in range(m):
                a += Phi[s, row, i] * T[row, j]
            K[i, j] += weight * a
        for k in range(n_p):
            K[i, n + k] += weight * t * Psi[s, k]
    for k in range(n_p):
        r[n + k] += weight * Psi[s, k] * theta


@njit(inline="always")
def _symmetrize(K):
    """The lower triangle of K from its upper one (the q-q block's and the q-pi block)."""
    size = K.shape[0]
    for i in range(size):
        for j in range(i + 1, size):
            K[j, i] = K[i, j]


_RO = "Array(float64, {}, 'C', readonly=True)"
_F8_1D, _F8_2D = "float64[::1]", "float64[:, ::1]"
# X, Phi, Psi, params, weights, K0, k0, gradients, quadrature, q, pi
_INPUTS = ", ".join(_RO.format(d) for d in (3, 3, 2, 2, 1, 3, 2, 3, 1, 1, 1))


@njit(inline="always")
def _check_sample(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature, q, pi):
    """The inputs' shapes agree (ValueError otherwise): _integrate trusts them."""
    S, m, n = Phi.shape
    if X.shape[0] != S or Psi.shape[0] != S or params.shape[0] != S or weights.shape[0] != S:
        raise ValueError("X, Phi, Psi, params and weights must have one row a sampled element")
    if X.shape[1] * 3 != m or X.shape[2] != 3 or params.shape[1] < PARAMETER_SIZE:
        raise ValueError("Phi must have 3 rows a node of X; params PARAMETER_SIZE columns")
    if K0.shape[0] != S or K0.shape[1] != m or K0.shape[2] != m or k0.shape[0] != S:
        raise ValueError("K0 must be (S, m, m) and k0 (S, m)")
    if k0.shape[1] != m or q.shape[0] != n or pi.shape[0] != Psi.shape[1]:
        raise ValueError("k0 must be (S, m); q (n,) and pi (n_p,) as Phi's and Psi's columns")
    if X.shape[1] > MAX_NODES or gradients.shape[1] != X.shape[1] or gradients.shape[2] != 3:
        raise ValueError("gradients must be (points, nodes, 3) with X's nodes, at most MAX_NODES")
    if quadrature.shape[0] != gradients.shape[0]:
        raise ValueError("quadrature must have one weight a point of gradients")


@njit(inline="always")
def _check_element_scratch(m, u, r_u, scalars):
    if u.shape[0] * 3 != m or u.shape[1] != 3 or r_u.shape[0] != m:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")
    if scalars.shape[0] != SCALAR_SIZE:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")


@njit(f"void({_INPUTS}, {_F8_1D}, {_F8_2D}, {_F8_2D}, {_F8_1D}, {_F8_2D}, {_F8_1D}, {_F8_1D}, "
      f"{_F8_2D})", cache=True, nogil=True)  # fmt: skip
def sampled_residual_tangent(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature,
                             q, pi, r, K, u, r_u, K_uu, K_up, scalars, T):  # fmt: skip
    """The sampled elements' sums of the module's formulas at (q, pi) into r, K; the last
    six arguments are a :class:`Scratch`'s buffers. Shapes are checked (ValueError)."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature, q, pi)
    if r.shape[0] != n + n_p or K.shape[0] != n + n_p or K.shape[1] != n + n_p:
        raise ValueError("r must be (n + n_p,) and K square of that size")
    _check_element_scratch(m, u, r_u, scalars)
    if K_uu.shape[0] != m or K_uu.shape[1] != m or K_up.shape[0] != m:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")
    if T.shape[0] != m or T.shape[1] != n:
        raise ValueError("the scratch does not fit these elements and modes (Scratch)")
    r[:] = 0.0
    K[:, :] = 0.0
    for s in range(S):
        p = _element_state(Phi, Psi, s, q, pi, u)
        _integrate(X[s], u, p, params[s], gradients, quadrature, r_u, K_uu, K_up, scalars)
        theta = _nonlinear_parts(K0, k0, s, u, p, r_u, K_uu, K_up, scalars, params[s, KAPPA])
        _accumulate(Phi, Psi, s, weights[s], theta, r_u, K_uu, K_up, T, r, K)
    _symmetrize(K)


@njit(f"void({_INPUTS}, {_F8_1D}, {_F8_2D}, {_F8_1D}, {_F8_1D})", cache=True, nogil=True)
def sampled_residual(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature, q, pi, r,
                     u, r_u, scalars):  # fmt: skip
    """The residual part of :func:`sampled_residual_tangent` alone (no tangent: an order
    of n fewer operations an element), into r: the iterations of a modified Newton, whose
    tangent is an earlier one. u, r_u, scalars: a :class:`Scratch`'s."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature, q, pi)
    if r.shape[0] != n + n_p:
        raise ValueError("r must be (n + n_p,)")
    _check_element_scratch(m, u, r_u, scalars)
    r[:] = 0.0
    for s in range(S):
        theta = _element_residual(X, Phi, Psi, params, K0, k0, gradients, quadrature, s, q, pi,
                                  u, r_u, scalars)  # fmt: skip
        _add_projected(Phi, Psi, s, weights[s], theta, r_u, r)


@njit(f"void({_INPUTS}, {_F8_2D}, {_F8_2D}, {_F8_1D}, {_F8_1D})", cache=True, nogil=True)
def element_contributions(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature,
                          q, pi, out, u, r_u, scalars):  # fmt: skip
    """Each sampled element's own term of the sums, unweighted: out[s] = (Phi_s^T r_nl,
    Psi_s Theta_nl) at (q, pi), (S, n + n_p) - ECSW's training columns (``weights`` is
    read for its shape only). u, r_u, scalars: a :class:`Scratch`'s."""
    S, m, n = Phi.shape
    n_p = Psi.shape[1]
    _check_sample(X, Phi, Psi, params, weights, K0, k0, gradients, quadrature, q, pi)
    if out.shape[0] != S or out.shape[1] != n + n_p:
        raise ValueError("out must be (S, n + n_p)")
    _check_element_scratch(m, u, r_u, scalars)
    for s in range(S):
        theta = _element_residual(X, Phi, Psi, params, K0, k0, gradients, quadrature, s, q, pi,
                                  u, r_u, scalars)  # fmt: skip
        out[s, :] = 0.0
        _add_projected(Phi, Psi, s, 1.0, theta, r_u, out[s])
