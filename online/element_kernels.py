"""An element's residual and tangent in the trainer's mixed displacement-pressure model.

The kernels a hyper-reduced model (ECSW, issue 18) evaluates on its sampled elements, and
the offline trainer on every element to build the ECSW training matrix. The full-order
model (:mod:`hapticrom.offline.fe.formulation`) has the displacement u (Lagrange) and one
pressure p per cell (DG0); an element's energy is

    Pi_e(u, p) = int_e Psi_mix(F, p) dV,   Psi_mix = rest(F) + p theta(F) - p^2 / (2 kappa)

with F = I + grad u and the law's split ``rest``, ``theta``, ``kappa = params[KAPPA]`` of
:mod:`hapticrom.online.material_kernels`. Its derivatives, at the trainer's quadrature:

    r_u[3a + i] = dPi_e/du[a, i] = int (dRest + p dTheta)[i, j] dN_a/dX_j dV     (N)
    r_p         = dPi_e/dp       = int theta - p / kappa dV                      (mm^3)
    K_uu = dr_u/du (N/mm),  K_up = dr_u/dp = dr_p/du (mm^2),  K_pp = -V_e / kappa (mm^3/MPa)

and the energy Pi_e (mJ). At the element's own pressure p = kappa int theta dV / V_e
(r_p = 0) Pi_e is the condensed energy int rest dV + kappa / (2 V_e) (int theta dV)^2.

Elements are isoparametric: the reference nodal coordinates X (nodes x 3, mm) map the
reference cell, and u (nodes x 3, mm) is nodal. :func:`reference_element` tabulates, in
plain numpy, the shape-function gradients of the trilinear hexahedron (Q1P0, the cornea's)
and the quadratic tetrahedron (P2P0, the liver's) at the quadrature DOLFINx uses for the
trainer's forms: a tensor Gauss rule of degree 2 x the displacement degree on hexahedra,
Basix's degree-4 rule (Xiao-Gimbutas, 14 points) on tetrahedra, its points and weights
copied below (a test holds them to Basix's). Nodes follow Basix's order (not VTK's or
gmsh's: :data:`BASIX_FROM_GMSH` permutes a gmsh cell).

Layouts: an element's displacement rows are ``NODE_DOFS * a + i`` (node a, component i
= x, y, z); the scalars of an element are one float64 vector of ``SCALAR_SIZE`` entries
at the offsets ``PRESSURE_RESIDUAL`` ... ``VOLUME``; a tabulation's gradients are indexed
``[point, node, reference direction]``.

Every kernel has an explicit signature (compiled or loaded from numba's cache at import),
releases the GIL, allocates nothing (scratch lives on the stack) and writes into the
caller's arrays, every entry of each (no need to zero them). Inputs may be read-only. A
wrong shape raises ValueError before anything is written; an unknown law gives NaN.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import carray, njit

from hapticrom.online.material_kernels import (
    KAPPA,
    LAW,
    LAW_HGO,
    MAX_POINTS,
    PARAMETER_SIZE,
    POINT_F,
    POINT_P,
    POINT_REST,
    POINT_ROWS,
    POINT_THETA,
    _det_inverse_transpose,
    _evaluate,
    _hgo_points,
    _stack_doubles,
    _theta_gradient,
)
from hapticrom.shared.errors import InputError

NODE_DOFS = 3  # displacement rows per node: row NODE_DOFS * a + i is node a's component i
MAX_NODES = 27  # the kernels' stack scratch holds this many nodes (a Q2 hexahedron's)

# -- the scalars of an element: offsets into its float64 vector --------------------------------
PRESSURE_RESIDUAL = 0  # r_p = int theta - p / kappa dV (mm^3)
PRESSURE_STIFFNESS = 1  # K_pp = dr_p/dp = -V_e / kappa (mm^3/MPa)
ENERGY = 2  # Pi_e = int Psi_mix(F, p) dV (mJ)
VOLUME = 3  # V_e, the element's reference volume (mm^3)
SCALAR_SIZE = 4

# Node k of a Basix (DOLFINx) cell is node BASIX_FROM_GMSH[cell][k] of the gmsh (.msh)
# cell: X_basix = X_gmsh[BASIX_FROM_GMSH[cell]]. A gmsh hexahedron runs round each face
# (as VTK's); Basix's is a tensor product, node a at (a & 1, a >> 1 & 1, a >> 2).
BASIX_FROM_GMSH = {
    "hexahedron": np.array([0, 1, 3, 2, 4, 5, 7, 6]),
    "tetrahedron": np.array([0, 1, 2, 3, 8, 9, 5, 7, 6, 4]),  # the 10-node tetrahedron
}

# Basix's default rule of degree 4 on the reference tetrahedron (Xiao-Gimbutas), as
# basix.make_quadrature(CellType.tetrahedron, 4) gives it: DOLFINx integrates the P2
# forms with it, and a nonlinear integrand matches only at the same points.
_E, _A, _B, _C, _D = 0.5, 0.6984197043243866, 0.1005267652252045, 0.0568813795204234, 0.3143728734931922  # fmt: skip  # noqa: E501
_TETRAHEDRON_POINTS_4 = np.array([
    [0.0, _E, _E], [_E, 0.0, _E], [_E, _E, 0.0], [_E, 0.0, 0.0], [0.0, _E, 0.0], [0.0, 0.0, _E],
    [_A, _B, _B], [_B, _B, _B], [_B, _B, _A], [_B, _A, _B],
    [_C, _D, _D], [_D, _D, _D], [_D, _D, _C], [_D, _C, _D],
])  # fmt: skip
_TETRAHEDRON_WEIGHTS_4 = np.repeat(
    [0.003174603174603167, 0.014764970790496783, 0.022139791114265117], [6, 4, 4]
)

CELLS = {"hexahedron": 1, "tetrahedron": 2}  # the cells tabulated, and their degree


# -- reference elements (Python, plain numpy) -----------------------------------------------
class ReferenceElement(NamedTuple):
    """A reference cell's nodes, quadrature and shape-function gradients (read-only arrays).

    nodes (n, 3): the nodes' reference coordinates, Basix order.
    points (q, 3), weights (q,): the quadrature rule on the reference cell.
    gradients (q, n, 3): dN_a/dxi_d at each point, the kernels' ``gradients``.
    """

    cell: str
    nodes: np.ndarray
    points: np.ndarray
    weights: np.ndarray
    gradients: np.ndarray


def reference_element(cell: str, quadrature_degree: int | None = None, rule=None):
    """The :class:`ReferenceElement` of ``cell`` ("hexahedron": Q1, "tetrahedron": P2).

    The quadrature is the trainer's: degree ``2 *`` the displacement degree unless
    ``quadrature_degree`` says otherwise; hexahedra take any degree (Gauss-Legendre,
    (degree + 2) // 2 points a direction, as Basix), tetrahedra degree 4 only, or an
    explicit ``rule = (points (q, 3), weights (q,))`` on the reference cell.
    """
    if cell not in CELLS:
        raise InputError(f"no reference element for {cell!r}; choose one of {', '.join(CELLS)}")
    if rule is not None:
        points, weights = _checked_rule(rule)
    else:
        degree = 2 * CELLS[cell] if quadrature_degree is None else quadrature_degree
        points, weights = _quadrature(cell, degree)
    nodes = _NODES[cell]()
    gradients = shape_functions(cell, points)[1]
    arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (nodes, points, weights)]
    arrays.append(np.ascontiguousarray(gradients))
    for a in arrays:
        a.flags.writeable = False
    return ReferenceElement(cell, *arrays)


def _checked_rule(rule) -> tuple[np.ndarray, np.ndarray]:
    points, weights = (np.asarray(a, dtype=np.float64) for a in rule)
    good = points.ndim == 2 and points.shape[1] == 3 and weights.shape == (len(points),)
    if not (good and len(points) > 0 and np.isfinite(points).all() and np.isfinite(weights).all()):
        raise InputError("a quadrature rule is (points (q, 3), weights (q,)), finite, q > 0")
    return points, weights


def _quadrature(cell: str, degree: int) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(degree, int) or isinstance(degree, bool) or degree < 0:
        raise InputError(f"quadrature degree must be a non-negative integer, got {degree!r}")
    if cell == "tetrahedron":
        if degree != 4:
            raise InputError(f"tetrahedra carry Basix's degree-4 rule only (asked {degree}); "
                             "pass rule=(points, weights)")  # fmt: skip
        return _TETRAHEDRON_POINTS_4, _TETRAHEDRON_WEIGHTS_4
    x, w = np.polynomial.legendre.leggauss((degree + 2) // 2)
    x, w = (1.0 + x) / 2.0, w / 2.0  # on [0, 1]
    grid = np.meshgrid(x, x, x, indexing="ij")  # the first coordinate slowest, as Basix
    points = np.stack([g.ravel() for g in grid], axis=1)
    weights = np.einsum("i,j,k->ijk", w, w, w).ravel()
    return points, weights


def _hexahedron_nodes() -> np.ndarray:
    a = np.arange(8)
    return np.stack([a & 1, a >> 1 & 1, a >> 2], axis=1).astype(np.float64)


def _tetrahedron_nodes() -> np.ndarray:
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    midpoints = [(vertices[i] + vertices[j]) / 2 for i, j in _TETRAHEDRON_EDGES]
    return np.vstack([vertices, midpoints])


# Basix's edges of the tetrahedron, in the order of the P2 element's edge nodes 4..9.
_TETRAHEDRON_EDGES = ((2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1))
_NODES = {"hexahedron": _hexahedron_nodes, "tetrahedron": _tetrahedron_nodes}


def shape_functions(cell: str, points) -> tuple[np.ndarray, np.ndarray]:
    """(N (q, n), dN/dxi (q, n, 3)) of the Q1 hexahedron or the P2 tetrahedron at points."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if cell == "hexahedron":
        return _trilinear(points)
    if cell == "tetrahedron":
        return _quadratic_tetrahedron(points)
    raise InputError(f"no shape functions for {cell!r}; choose one of {', '.join(CELLS)}")


def _trilinear(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """N_a = prod_d (xi_d if node a's coordinate d is 1 else 1 - xi_d)."""
    corner = _hexahedron_nodes()  # (8, 3) of 0 and 1
    factors = np.where(corner[None], points[:, None], 1.0 - points[:, None])  # (q, 8, 3)
    slopes = 2.0 * corner - 1.0  # d factor / d xi_d
    values = factors.prod(axis=2)
    gradients = np.empty(factors.shape)
    for d in range(3):
        others = [e for e in range(3) if e != d]
        gradients[:, :, d] = slopes[None, :, d] * factors[:, :, others].prod(axis=2)
    return values, gradients


def _quadratic_tetrahedron(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices lambda (2 lambda - 1), edges 4 lambda_i lambda_j (barycentric lambda)."""
    lam = np.column_stack([1.0 - points.sum(axis=1), points])  # (q, 4)
    dlam = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    values = np.empty((len(points), 10))
    gradients = np.empty((len(points), 10, 3))
    values[:, :4] = lam * (2.0 * lam - 1.0)
    gradients[:, :4] = (4.0 * lam - 1.0)[:, :, None] * dlam[None]
    for e, (i, j) in enumerate(_TETRAHEDRON_EDGES):
        values[:, 4 + e] = 4.0 * lam[:, i] * lam[:, j]
        gradients[:, 4 + e] = 4.0 * (lam[:, j, None] * dlam[i] + lam[:, i, None] * dlam[j])
    return values, gradients


# -- the kernels' pieces ----------------------------------------------------------------------
@njit(inline="always")
def _physical_gradients(X, reference, q, dN):
    """dN[a, j] = dN_a/dX_j at point q (J^-T dN_a/dxi, J[i, d] = dX_i/dxi_d); returns det J."""
    n = X.shape[0]
    j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
    for a in range(n):
        d0, d1, d2 = reference[q, a, 0], reference[q, a, 1], reference[q, a, 2]
        x0, x1, x2 = X[a, 0], X[a, 1], X[a, 2]
        j00 += x0 * d0
        j01 += x0 * d1
        j02 += x0 * d2
        j10 += x1 * d0
        j11 += x1 * d1
        j12 += x1 * d2
        j20 += x2 * d0
        j21 += x2 * d1
        j22 += x2 * d2
    det, G = _det_inverse_transpose((j00, j01, j02, j10, j11, j12, j20, j21, j22))
    for a in range(n):  # dN_a/dX_j = sum_d J^-1[d, j] dN_a/dxi_d = sum_d G[j, d] dN_a/dxi_d
        d0, d1, d2 = reference[q, a, 0], reference[q, a, 1], reference[q, a, 2]
        for j in range(3):
            dN[a, j] = G[3 * j] * d0 + G[3 * j + 1] * d1 + G[3 * j + 2] * d2
    return det


@njit(inline="always")
def _deformation_gradient(u, dN, F):
    """F = I + sum_a u_a (x) dN_a/dX."""
    for i in range(3):
        for j in range(3):
            v = 1.0 if i == j else 0.0
            for a in range(u.shape[0]):
                v += u[a, i] * dN[a, j]
            F[i, j] = v


@njit(inline="always")
def _add_stiffness(dN, A, dV, B, K_uu):
    """The upper block triangle (b >= a) of K_uu += dV dN_a,j A[3i + j, 3k + l] dN_b,l,
    through B[i, 3k + l] = dV sum_j dN_a,j A[3i + j, 3k + l] (27 products a node)."""
    n = dN.shape[0]
    for a in range(n):
        g0, g1, g2 = dN[a, 0] * dV, dN[a, 1] * dV, dN[a, 2] * dV
        for i in range(3):
            for s in range(9):
                B[i, s] = g0 * A[3 * i, s] + g1 * A[3 * i + 1, s] + g2 * A[3 * i + 2, s]
        for b in range(a, n):
            h0, h1, h2 = dN[b, 0], dN[b, 1], dN[b, 2]
            for i in range(3):
                row = 3 * a + i
                for k in range(3):
                    s = 3 * k
                    K_uu[row, 3 * b + k] += B[i, s] * h0 + B[i, s + 1] * h1 + B[i, s + 2] * h2


@njit(inline="always")
def _mirror(K_uu):
    """The lower triangle from the upper: K_uu exactly symmetric (the diagonal blocks,
    computed whole, are so only to rounding)."""
    m = K_uu.shape[0]
    for row in range(m):
        for column in range(row + 1, m):
            K_uu[column, row] = K_uu[row, column]


@njit(inline="always")
def _add_point(dN, dV, u, p, params, F, P, g, A, B, r_u, K_uu, K_up):
    """One quadrature point's terms of r_u and (unless None) K_uu's upper block triangle and
    K_up; returns its (rest + p theta, theta). Per point one law evaluation gives the mixed
    stress dRest + p dTheta and tangent d2Rest + p d2Theta (rest weighted 1, kappa 0, theta
    p), and dTheta alone (material_kernels' _theta_gradient: a second law evaluation cost
    11 of an element tangent's 117 us, stop 51)."""
    _deformation_gradient(u, dN, F)
    if K_uu is not None:
        rest, theta = _evaluate(F, params, (1.0, 0.0, p), P, A)
        _theta_gradient(F, params, g)
    else:
        rest, theta = _evaluate(F, params, (1.0, 0.0, p), P, None)
    for a in range(u.shape[0]):
        g0, g1, g2 = dN[a, 0] * dV, dN[a, 1] * dV, dN[a, 2] * dV
        for i in range(3):
            r_u[3 * a + i] += P[i, 0] * g0 + P[i, 1] * g1 + P[i, 2] * g2
            if K_uu is not None:
                K_up[3 * a + i] += g[i, 0] * g0 + g[i, 1] * g1 + g[i, 2] * g2
    if K_uu is not None:
        _add_stiffness(dN, A, dV, B, K_uu)
    return rest + p * theta, theta


@njit(inline="always")
def _start(r_u, K_uu, K_up):
    r_u[:] = 0.0
    if K_uu is not None:
        K_uu[:, :] = 0.0
        K_up[:] = 0.0


@njit(inline="always")
def _finish(p, inverse_kappa, energy, volumetric, volume, K_uu, scalars):
    """K_uu's lower triangle and the scalars from the points' sums."""
    if K_uu is not None:
        _mirror(K_uu)
    scalars[PRESSURE_RESIDUAL] = volumetric - p * inverse_kappa * volume
    scalars[PRESSURE_STIFFNESS] = -volume * inverse_kappa
    scalars[ENERGY] = energy - 0.5 * p * p * inverse_kappa * volume
    scalars[VOLUME] = volume


@njit(inline="always")  # inlined: the buffers are on the integrating function's stack
def _point_scratch():
    """A point's buffers: F, P, g (3, 3), A (9, 9), B (3, 9)."""
    return (carray(_stack_doubles(9), (3, 3)), carray(_stack_doubles(9), (3, 3)),
            carray(_stack_doubles(9), (3, 3)), carray(_stack_doubles(81), (9, 9)),
            carray(_stack_doubles(27), (3, 9)))  # fmt: skip


@njit(nogil=True)  # not inlined: the residual's None outputs prune their branches
def _integrate(X, u, p, params, reference, weights, r_u, K_uu, K_up, scalars):
    """The element's r_u, scalars and (unless None) K_uu, K_up; see the module's formulas.
    The physical gradients are computed at every point from X (see _integrate_mapped)."""
    n = X.shape[0]
    dN = carray(_stack_doubles(81), (MAX_NODES, 3))  # 81 = 3 MAX_NODES: a literal for the stack
    F, P, g, A, B = _point_scratch()
    _start(r_u, K_uu, K_up)
    energy = volumetric = volume = 0.0
    for q in range(weights.shape[0]):
        dV = weights[q] * abs(_physical_gradients(X, reference, q, dN))
        mixed, theta = _add_point(dN[:n], dV, u, p, params, F, P, g, A, B, r_u, K_uu, K_up)
        energy += dV * mixed
        volumetric += dV * theta
        volume += dV
    _finish(p, 1.0 / params[KAPPA], energy, volumetric, volume, K_uu, scalars)


# the stack buffers of _residual_points, their sizes literals (numba's stack wants them)
_STACK_SIZES = (POINT_ROWS * MAX_POINTS, 3 * MAX_NODES * MAX_POINTS, MAX_POINTS)
assert _STACK_SIZES == (464, 1296, 16), _STACK_SIZES
# The shapes _residual_points' loops run over as literals, (lanes, nodes): the points padded
# to the lanes, for the hexahedron and the quadratic tetrahedron (MAX_POINTS lanes and the
# element's nodes otherwise). Loops over run-time counts of 8 points and 8 nodes are mostly
# their scalar remainders (LLVM's vector body takes 16 or more a pass); both literal, the
# loops unroll whole. Measured on the demo's held region (414 hexahedra, an AMD EPYC), the
# residual's element part: 333 -> 259 us (min); either literal alone: 325-332 us.
POINT_SHAPES = ((8, 8), (MAX_POINTS, 10))


# Not inlined: compiled once and called by every sum over elements (inlined beside the
# point-by-point path, it made each caller's compilation 3.5 times longer: 5.7 -> 20 s for
# the residual alone, measured). The sums' flags (hyperreduced's _SUMS), so that the sums
# over the points vectorise; numpy's error model, so that no division tests its divisor
# (a test is a branch, which stops a loop's vectorisation): a zero J or kappa here gives
# inf or NaN, which the callers refuse as not finite, instead of raising (the
# point-by-point path, tangents and more than MAX_POINTS points, still raises at J = 0).
@njit(nogil=True, fastmath={"reassoc", "contract"}, error_model="numpy")
def _residual_points(dN, dV, u, p, params, r_u, scalars):
    """:func:`_integrate_mapped`'s residual for an hgo element, its points in vector lanes
    (material_kernels' stage buffer W): F at every point, the law at every point
    (``_hgo_points``), then r_u; over one of POINT_SHAPES' literal shapes if the element
    fits it. The stack buffers are made here, once for the three inlined shapes."""
    points, n = dV.shape[0], u.shape[0]
    W = carray(_stack_doubles(464), (POINT_ROWS, MAX_POINTS))  # literals: _STACK_SIZES
    stage = (W, carray(_stack_doubles(1296), (MAX_NODES, 3, MAX_POINTS)),
             carray(_stack_doubles(16), (MAX_POINTS,)))  # fmt: skip
    hexahedron, tetrahedron = POINT_SHAPES
    if points <= hexahedron[0] and n == hexahedron[1]:
        _residual_lanes(dN, dV, u, p, params, r_u, scalars, stage, hexahedron[0],
                        hexahedron[1])  # fmt: skip
    elif points <= tetrahedron[0] and n == tetrahedron[1]:
        _residual_lanes(dN, dV, u, p, params, r_u, scalars, stage, tetrahedron[0],
                        tetrahedron[1])  # fmt: skip
    else:
        _residual_lanes(dN, dV, u, p, params, r_u, scalars, stage, MAX_POINTS, n)


@njit(inline="always")
def _residual_lanes(dN, dV, u, p, params, r_u, scalars, stage, lanes, n):
    """:func:`_residual_points` over ``lanes`` columns (at least the points) and the n
    nodes (u's; literals in a call where they can be), in ``stage``'s buffers (W, dNt,
    dVl): the gradients copied point-minor (dNt) so that every loop over the lanes reads
    contiguous entries; a padded lane has no gradient (F = I, a finite law) and no volume
    (dVl = 0: it adds exact zeros)."""
    points = dV.shape[0]
    W, dNt, dVl = stage
    for q in range(lanes):
        dVl[q] = dV[q] if q < points else 0.0
        for a in range(n):
            for j in range(3):
                dNt[a, j, q] = dN[q, a, j] if q < points else 0.0
    for r in range(9):  # F = I + sum_a u_a (x) dN_a
        i, j = r // 3, r % 3
        for q in range(lanes):
            W[POINT_F + r, q] = 1.0 if i == j else 0.0
        for a in range(n):
            ua = u[a, i]
            for q in range(lanes):
                W[POINT_F + r, q] += ua * dNt[a, j, q]
    _hgo_points(W, lanes, params, p, dVl)
    energy = volumetric = volume = 0.0
    for q in range(lanes):
        energy += dVl[q] * (W[POINT_REST, q] + p * W[POINT_THETA, q])
        volumetric += dVl[q] * W[POINT_THETA, q]
        volume += dVl[q]
    for a in range(n):  # r_u[3a + i] = sum over the points of (P dV)[i, j] dN_a,j
        for i in range(3):
            v = 0.0
            for j in range(3):
                for q in range(lanes):
                    v += W[POINT_P + 3 * i + j, q] * dNt[a, j, q]
            r_u[3 * a + i] = v
    _finish(p, 1.0 / params[KAPPA], energy, volumetric, volume, None, scalars)


@njit(inline="always")  # compiled into its caller, with its flags (hyperreduced's _SUMS)
def _integrate_mapped(dN, dV, u, p, params, r_u, K_uu, K_up, scalars):
    """:func:`_integrate` with the element's physical gradients dN (points, nodes, 3) and
    point volumes dV (points,) given (:func:`element_geometry`'s): the same sums without
    the map's Jacobian at every point, for a model that evaluates its elements many times.
    An hgo element's residual alone takes :func:`_residual_points`."""
    if K_uu is None and params[LAW] == LAW_HGO and dV.shape[0] <= MAX_POINTS:
        if u.shape[0] <= MAX_NODES:
            _residual_points(dN, dV, u, p, params, r_u, scalars)
            return
    F, P, g, A, B = _point_scratch()
    _start(r_u, K_uu, K_up)
    energy = volumetric = volume = 0.0
    for q in range(dV.shape[0]):
        mixed, theta = _add_point(dN[q], dV[q], u, p, params, F, P, g, A, B, r_u, K_uu, K_up)
        energy += dV[q] * mixed
        volumetric += dV[q] * theta
        volume += dV[q]
    _finish(p, 1.0 / params[KAPPA], energy, volumetric, volume, K_uu, scalars)


@njit(inline="always")
def _check(X, u, params, reference, weights, r_u, scalars):
    n = X.shape[0]
    if X.shape[1] != 3 or n < 1 or n > MAX_NODES:
        raise ValueError("X must be (nodes, 3) with 1 to MAX_NODES nodes")
    if u.shape[0] != n or u.shape[1] != 3:
        raise ValueError("u must have X's shape (nodes, 3)")
    if params.shape[0] < PARAMETER_SIZE:
        raise ValueError("params must have PARAMETER_SIZE entries")
    if reference.shape[0] < 1 or reference.shape[1] != n or reference.shape[2] != 3:
        raise ValueError("gradients must be (points, nodes, 3) with X's nodes")
    if weights.shape[0] != reference.shape[0]:
        raise ValueError("weights must have one entry a point of gradients")
    if r_u.shape[0] != 3 * n or scalars.shape[0] != SCALAR_SIZE:
        raise ValueError("an output array has the wrong shape (r_u: 3 nodes, SCALAR_SIZE)")


# -- the kernels --------------------------------------------------------------------------
ro_f8_1d = "Array(float64, 1, 'C', readonly=True)"
ro_f8_2d = "Array(float64, 2, 'C', readonly=True)"
ro_f8_3d = "Array(float64, 3, 'C', readonly=True)"
f8_1d = "float64[::1]"
f8_2d = "float64[:, ::1]"
_INPUTS = f"{ro_f8_2d}, {ro_f8_2d}, float64, {ro_f8_1d}, {ro_f8_3d}, {ro_f8_1d}"


@njit(f"void({_INPUTS}, {f8_1d}, {f8_1d})", cache=True, nogil=True)
def element_residual(X, u, p, params, gradients, weights, r_u, scalars):
    """r_u (3 nodes, N) and the scalars (SCALAR_SIZE) of the element at (u, p).

    X, u: (nodes, 3) mm; p: MPa; params: the packed law (material_kernels.law_parameters);
    gradients (points, nodes, 3), weights (points,): a :class:`ReferenceElement`'s.
    """
    _check(X, u, params, gradients, weights, r_u, scalars)
    _integrate(X, u, p, params, gradients, weights, r_u, None, None, scalars)


@njit(f"void({_INPUTS}, {f8_1d}, {f8_2d}, {f8_1d}, {f8_1d})", cache=True, nogil=True)
def element_residual_tangent(X, u, p, params, gradients, weights, r_u, K_uu, K_up, scalars):
    """:func:`element_residual` and the tangent blocks K_uu (3 nodes x 3 nodes, N/mm,
    symmetric) and K_up (3 nodes, mm^2); K_pp is scalars[PRESSURE_STIFFNESS]."""
    _check(X, u, params, gradients, weights, r_u, scalars)
    m = 3 * X.shape[0]
    if K_uu.shape[0] != m or K_uu.shape[1] != m or K_up.shape[0] != m:
        raise ValueError("an output array has the wrong shape (K_uu: 3 nodes square, K_up)")
    _integrate(X, u, p, params, gradients, weights, r_u, K_uu, K_up, scalars)


@njit(f"void({ro_f8_3d}, {ro_f8_3d}, {ro_f8_1d}, float64[:, :, :, ::1], {f8_2d})", cache=True,
      nogil=True)  # fmt: skip
def element_geometry(X, gradients, weights, dN, dV):
    """Each element's physical shape-function gradients dN[e, point] (nodes, 3; 1/mm) and
    point volumes dV[e, point] = weight |det J| (mm^3), for E elements X (E, nodes, 3) of
    the reference tabulation ``gradients``, ``weights``: what :func:`_integrate` computes at
    every point, once (a hyper-reduced model's sampled elements, :mod:`.hyperreduced`)."""
    E, n = X.shape[0], X.shape[1]
    points = weights.shape[0]
    if X.shape[2] != 3 or n < 1:  # no stack scratch here: any number of nodes
        raise ValueError("X must be (elements, nodes, 3) with at least one node")
    if gradients.shape[0] != points or gradients.shape[1] != n or gradients.shape[2] != 3:
        raise ValueError("gradients must be (points, nodes, 3) with X's nodes, one weight a point")
    if dN.shape[0] != E or dN.shape[1] != points or dN.shape[2] != n or dN.shape[3] != 3:
        raise ValueError("dN must be (elements, points, nodes, 3) and dV (elements, points)")
    if dV.shape[0] != E or dV.shape[1] != points:
        raise ValueError("dN must be (elements, points, nodes, 3) and dV (elements, points)")
    for e in range(E):
        for q in range(points):
            dV[e, q] = weights[q] * abs(_physical_gradients(X[e], gradients, q, dN[e, q]))
