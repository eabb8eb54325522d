"""The offline trainer's hyperelastic laws as numba kernels: energy, first Piola stress, tangent.

The same three laws as :mod:`hapticrom.offline.fe.materials` (its UFL energies are the
reference the tests hold these kernels to): Saint Venant-Kirchhoff ``svk``, compressible
neo-Hookean ``neo-hookean`` and the Holzapfel-Gasser two-fibre law ``hgo``. Every law's
energy splits as ``Psi(F) = rest(F) + kappa/2 * theta(F)**2`` with a scalar volumetric
strain ``theta`` (``tr E`` for svk, ``ln J`` otherwise) and a modulus ``kappa``, so that
a mixed (pressure) formulation can take ``rest`` and ``theta`` apart:
:func:`rest_derivatives` and :func:`theta_derivatives` give each part with its first and
second derivatives, ``params[KAPPA]`` the modulus.

A law and its parameters travel as one float64 vector of ``PARAMETER_SIZE`` entries,
packed by :func:`law_parameters` (which refuses bad values); the offsets are
:mod:`hapticrom.shared.material_layout`'s. Derivatives are with respect to F (3x3,
row-major): the first Piola stress ``P[i, j] = dPsi/dF[i, j]`` and the tangent
``A[3*i + j, 3*k + l] = d2Psi/dF[i, j] dF[k, l]`` (9x9, symmetric). All written
analytically from the invariants (``dI1/dF = 2 F``, ``dJ/dF = J F^-T``,
``d(F^-T)[i, j]/dF[k, l] = -F^-1[j, k] F^-1[l, i]``, and for an isochoric invariant
``Ib = J^p I``: ``dIb = J^p (dI + p I F^-T)``).

Every kernel has an explicit signature (compiled or loaded from numba's cache at import),
releases the GIL, allocates nothing (small fixed-size tuples live in registers, a
tangent's 9-vectors in a stack buffer) and writes into the caller's arrays. F and the
parameters may be read-only. Units: MPa (energies in mJ/mm^3). ``ln J`` and
``J**(-2/3)`` make neo-Hookean and hgo NaN at det F <= 0; an unknown law id gives NaN
everywhere. A wrong shape raises ValueError before anything is read or written.
"""

from __future__ import annotations

import math

import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from hapticrom.online.vector_math import vexp, vexpm1, vlog
from hapticrom.shared.errors import InputError
from hapticrom.shared.material_layout import (  # the packed row's layout, named once
    C1,
    C2,
    K1,
    K2,
    K3,
    K4,
    KAPPA,
    LAW,
    LAW_HGO,
    LAW_IDS,
    LAW_NEO_HOOKEAN,
    LAW_SVK,
    M0,
    MU,
    N0,
    PARAMETER_SIZE,
    TENSION_ONLY,
    UNIT_TOLERANCE,
)

ALIASES = {"neohookean": "neo-hookean", "neo_hookean": "neo-hookean"}
ALIASES["saint-venant-kirchhoff"] = "svk"

# What a kernel evaluates, as weights (of rest, of kappa, of theta alone): the whole energy,
# its rest part, or theta. Floats, not an int switch: one compiled law serves all three.
_WHOLE, _REST, _THETA = (1.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)

# The hgo defaults: those of hapticrom.offline.fe.materials.HolzapfelGasser (a test checks).
HGO_DEFAULTS = {"C1": 0.1, "D": 1e-5, "C2": 0.0, "k1": 0.234, "k2": 29.917}
HGO_DEFAULTS.update(k3=0.234, k4=29.917)


# -- packing (Python) --------------------------------------------------------------------------
def law_parameters(name: str, **params) -> np.ndarray:
    """The packed parameter vector (``PARAMETER_SIZE`` float64) of law ``name``.

    svk and neo-hookean take ``E`` (MPa) and ``nu``; hgo takes ``C1, D, C2, k1, k2, k3,
    k4`` (defaults as the trainer's), the unit fibre directions ``m0``, ``n0`` (required)
    and ``fibre_tension_only`` (default False). An InputError names anything wrong.
    """
    if not isinstance(name, str):
        raise InputError(f"material name must be a string, got {name!r}")
    key = ALIASES.get(name.lower(), name.lower())
    if key not in LAW_IDS:
        raise InputError(f"unknown material '{name}'; choose one of {', '.join(sorted(LAW_IDS))}")
    packed = np.zeros(PARAMETER_SIZE)
    packed[LAW] = LAW_IDS[key]
    if key == "hgo":
        _pack_hgo(packed, params)
    else:
        _pack_isotropic(packed, key, params)
    return packed


def _refuse(key: str, condition: bool, message: str) -> None:
    if not condition:
        raise InputError(f"material '{key}': {message}")


def _check_names(key: str, params: dict, known: set[str]) -> None:
    unknown = sorted(set(params) - known)
    _refuse(
        key,
        not unknown,
        f"has no parameter {', '.join(unknown)}; its parameters are {', '.join(sorted(known))}",
    )


def _number(key: str, name: str, value) -> float:
    finite = isinstance(value, int | float) and not isinstance(value, bool)
    try:
        finite = finite and math.isfinite(value)
    except OverflowError:  # an integer beyond float range
        finite = False
    _refuse(key, finite, f"parameter {name} must be a finite number, got {value!r}")
    return float(value)


def _pack_isotropic(packed: np.ndarray, key: str, params: dict) -> None:
    _check_names(key, params, {"E", "nu"})
    missing = sorted({"E", "nu"} - set(params))
    _refuse(key, not missing, f"missing parameter {', '.join(missing)}")
    E, nu = _number(key, "E", params["E"]), _number(key, "nu", params["nu"])
    _refuse(key, E > 0, f"E must be positive (got {E} MPa)")
    _refuse(key, -1 < nu < 0.5, f"nu must lie in (-1, 0.5) (got {nu})")
    packed[MU] = E / (2 * (1 + nu))
    packed[KAPPA] = E * nu / ((1 + nu) * (1 - 2 * nu))  # lambda


def _pack_hgo(packed: np.ndarray, params: dict) -> None:
    key = "hgo"
    _check_names(key, params, {*HGO_DEFAULTS, "m0", "n0", "fibre_tension_only"})
    values = {k: _number(key, k, params.get(k, v)) for k, v in HGO_DEFAULTS.items()}
    _refuse(key, values["C1"] > 0, f"C1 must be positive (got {values['C1']} MPa)")
    _refuse(key, values["D"] > 0, f"D must be positive (got {values['D']} 1/MPa)")
    _refuse(key, values["C2"] >= 0, f"C2 must not be negative (got {values['C2']} MPa)")
    for k in ("k1", "k3"):
        _refuse(key, values[k] >= 0, f"{k} must not be negative")
    for k in ("k2", "k4"):
        _refuse(key, values[k] > 0, f"{k} must be positive")
    tension_only = params.get("fibre_tension_only", False)
    _refuse(key, isinstance(tension_only, bool), "fibre_tension_only must be true or false")
    packed[KAPPA] = 2 / values["D"]
    packed[C1], packed[C2] = values["C1"], values["C2"]
    packed[K1], packed[K2], packed[K3], packed[K4] = (values[k] for k in ("k1", "k2", "k3", "k4"))
    packed[M0 : M0 + 3] = _fibre_direction(params, "m0")
    packed[N0 : N0 + 3] = _fibre_direction(params, "n0")
    packed[TENSION_ONLY] = float(tension_only)


def _fibre_direction(params: dict, name: str) -> np.ndarray:
    _refuse("hgo", name in params, f"needs the fibre directions m0, n0 (no {name})")
    try:
        v = np.array(params[name], dtype=np.float64)
    except (TypeError, ValueError):
        v = np.full(0, np.nan)
    good = v.shape == (3,) and bool(np.isfinite(v).all())
    _refuse("hgo", good, f"{name} must be 3 finite numbers, got {params[name]!r}")
    norm = float(np.linalg.norm(v))
    unit = abs(norm - 1) <= UNIT_TOLERANCE
    _refuse("hgo", unit, f"{name} must be a unit vector (|{name}| = {norm})")
    return v


# -- small fixed-size algebra on 9-tuples (3x3 row-major) -------------------------------------
@intrinsic
def _stack_doubles(typingctx, count):
    """A pointer to ``count`` (a literal int) float64 on the calling function's stack: a
    kernel's scratch that allocates nothing (numba.carray views it as an array)."""
    if not isinstance(count, types.IntegerLiteral):
        return None

    def codegen(context, builder, signature, args):
        double = context.get_value_type(types.float64)
        return cgutils.alloca_once(builder, double, size=count.literal_value)

    return types.CPointer(types.float64)(count), codegen


@njit(inline="always")
def _store(work, row, X):
    """work[row, :] = the 9-tuple X."""
    for r in range(9):
        work[row, r] = X[r]


@njit(inline="always")
def _matrix(F):
    return (F[0, 0], F[0, 1], F[0, 2], F[1, 0], F[1, 1], F[1, 2], F[2, 0], F[2, 1], F[2, 2])


@njit(inline="always")
def _product(X, Y):
    """X Y."""
    return (X[0] * Y[0] + X[1] * Y[3] + X[2] * Y[6], X[0] * Y[1] + X[1] * Y[4] + X[2] * Y[7],
            X[0] * Y[2] + X[1] * Y[5] + X[2] * Y[8], X[3] * Y[0] + X[4] * Y[3] + X[5] * Y[6],
            X[3] * Y[1] + X[4] * Y[4] + X[5] * Y[7], X[3] * Y[2] + X[4] * Y[5] + X[5] * Y[8],
            X[6] * Y[0] + X[7] * Y[3] + X[8] * Y[6], X[6] * Y[1] + X[7] * Y[4] + X[8] * Y[7],
            X[6] * Y[2] + X[7] * Y[5] + X[8] * Y[8])  # fmt: skip


@njit(inline="always")
def _transpose(X):
    return (X[0], X[3], X[6], X[1], X[4], X[7], X[2], X[5], X[8])


@njit(inline="always")
def _frobenius(X, Y):
    """X : Y."""
    return (X[0] * Y[0] + X[1] * Y[1] + X[2] * Y[2] + X[3] * Y[3] + X[4] * Y[4]
            + X[5] * Y[5] + X[6] * Y[6] + X[7] * Y[7] + X[8] * Y[8])  # fmt: skip


@njit(inline="always")
def _apply(X, v0, v1, v2):
    """X v for v = (v0, v1, v2)."""
    return (X[0] * v0 + X[1] * v1 + X[2] * v2, X[3] * v0 + X[4] * v1 + X[5] * v2,
            X[6] * v0 + X[7] * v1 + X[8] * v2)  # fmt: skip


@njit(inline="always")
def _combination(a, X, b, Y):
    """a X + b Y."""
    return (a * X[0] + b * Y[0], a * X[1] + b * Y[1], a * X[2] + b * Y[2], a * X[3] + b * Y[3],
            a * X[4] + b * Y[4], a * X[5] + b * Y[5], a * X[6] + b * Y[6], a * X[7] + b * Y[7],
            a * X[8] + b * Y[8])  # fmt: skip


@njit(inline="always")
def _scaled(a, X):
    """a X."""
    return (a * X[0], a * X[1], a * X[2], a * X[3], a * X[4], a * X[5], a * X[6], a * X[7],
            a * X[8])  # fmt: skip


@njit(inline="always")
def _outer(u, v):
    """u (x) v (3-vectors)."""
    return (u[0] * v[0], u[0] * v[1], u[0] * v[2], u[1] * v[0], u[1] * v[1], u[1] * v[2],
            u[2] * v[0], u[2] * v[1], u[2] * v[2])  # fmt: skip


@njit(inline="always")
def _cofactors(F):
    """cof F = J F^-T (row-major 9-tuple)."""
    return (F[4] * F[8] - F[5] * F[7], F[5] * F[6] - F[3] * F[8], F[3] * F[7] - F[4] * F[6],
            F[2] * F[7] - F[1] * F[8], F[0] * F[8] - F[2] * F[6], F[1] * F[6] - F[0] * F[7],
            F[1] * F[5] - F[2] * F[4], F[2] * F[3] - F[0] * F[5],
            F[0] * F[4] - F[1] * F[3])  # fmt: skip


@njit(inline="always")
def _det_inverse_transpose(F):
    """J = det F and F^-T = cof F / J (row-major 9-tuple)."""
    c = _cofactors(F)
    J = F[0] * c[0] + F[1] * c[1] + F[2] * c[2]
    return J, _scaled(1.0 / J, c)


@njit(inline="always")
def _weights(part, kappa, theta):
    """(rest weight w, and the volumetric term's a, b, c) so that a kernel evaluates
    P = w dRest + a dTheta and A = w d2Rest + b dTheta (x) dTheta + c d2Theta:
    the whole energy, its rest part or theta alone (``part``: _WHOLE, _REST, _THETA)."""
    w, k, t = part[0], part[1] * kappa, part[2]
    return w, k * theta + t, k, k * theta + t


# -- the laws: (rest, theta), writing P and A (unless None) as _weights says ----------------
# Not inlined: each is compiled once per (P, A) kind and shared by the kernels (a None
# output's branch is pruned at compile time). fastmath=False is explicit: numba otherwise
# gives a callee the flags of whichever caller compiles it first (the hyper-reduced sums'
# reassociation), so a law's rounding would depend on numba's cache state. A tangent is
# symmetric: its upper triangle is computed from 9-vectors in a stack buffer (a tuple
# indexed by a loop variable would cost a branch per read) and mirrored.
@njit(nogil=True, fastmath=False)
def _svk(Fa, params, part, P, A):
    """rest = mu E:E, theta = tr E, E = (F^T F - I)/2; dTheta = F, d2Theta = identity."""
    F = _matrix(Fa)
    mu = params[MU]
    C = _product(_transpose(F), F)
    E = (0.5 * (C[0] - 1.0), 0.5 * C[1], 0.5 * C[2], 0.5 * C[3], 0.5 * (C[4] - 1.0),
         0.5 * C[5], 0.5 * C[6], 0.5 * C[7], 0.5 * (C[8] - 1.0))  # fmt: skip
    rest = mu * _frobenius(E, E)
    theta = E[0] + E[4] + E[8]
    w, a, b, c = _weights(part, params[KAPPA], theta)
    if P is not None:  # dRest = 2 mu F E
        FE = _product(F, E)
        for r in range(9):
            P[r // 3, r % 3] = 2.0 * w * mu * FE[r] + a * F[r]
    if A is not None:  # d2Rest = mu (2 delta_ik E_lj + F_il F_kj + (F F^T)_ik delta_jl)
        work = carray(_stack_doubles(27), (3, 9))
        _store(work, 0, F)
        _store(work, 1, _scaled(2.0 * w * mu, E))
        _store(work, 2, _scaled(w * mu, _product(F, _transpose(F))))
        _svk_tangent(work, w * mu, b, c, A)
    return rest, theta


@njit(inline="always")
def _svk_tangent(work, wmu, b, c, A):
    """A = wmu F_il F_kj + b F (x) F + delta_ik E2_lj + delta_jl (B_ik + c delta_ik) with the
    work rows F, E2 = 2 wmu E, B = wmu F F^T."""
    F, E2, B = work[0], work[1], work[2]
    for i in range(3):
        for j in range(3):
            r = 3 * i + j
            for k in range(i, 3):  # the upper triangle s >= r
                for l in range(j if k == i else 0, 3):  # noqa: E741 - F[k, l]
                    s = 3 * k + l
                    v = wmu * F[3 * i + l] * F[3 * k + j] + b * F[r] * F[s]
                    if i == k:
                        v += E2[3 * l + j]
                    if j == l:
                        v += B[3 * i + k]
                        if i == k:
                            v += c
                    A[r, s] = v
                    A[s, r] = v


@njit(nogil=True, fastmath=False)
def _neo_hookean(Fa, params, part, P, A):
    """rest = mu/2 (F:F - 3) - mu ln J, theta = ln J; dTheta = F^-T, d2Theta = -F^-1_jk F^-1_li."""
    F = _matrix(Fa)
    mu = params[MU]
    J, G = _det_inverse_transpose(F)
    lnJ = math.log(J)
    rest = 0.5 * mu * (_frobenius(F, F) - 3.0) - mu * lnJ
    w, a, b, c = _weights(part, params[KAPPA], lnJ)
    if P is not None:
        for r in range(9):
            P[r // 3, r % 3] = w * mu * (F[r] - G[r]) + a * G[r]
    if A is not None:  # w mu delta_ik delta_jl + (w mu - c) F^-1_jk F^-1_li + b G_ij G_kl
        work = carray(_stack_doubles(9), (1, 9))
        _store(work, 0, G)
        Gw = work[0]
        h = w * mu - c
        for i in range(3):
            for j in range(3):
                r = 3 * i + j
                for k in range(i, 3):  # the upper triangle s >= r
                    for l in range(j if k == i else 0, 3):  # noqa: E741 - F[k, l]
                        s = 3 * k + l
                        v = h * Gw[3 * k + j] * Gw[3 * i + l] + b * Gw[r] * Gw[s]
                        if r == s:
                            v += w * mu
                        A[r, s] = v
                        A[s, r] = v
    return rest, lnJ


@njit(inline="always")
def _fibre(I, k_stiff, k_exp, tension_only):
    """A fibre family's energy k1/(2 k2) (exp(k2 (I - 1)^2) - 1) and its first and second
    derivatives in I; nothing while unstretched (I <= 1) if tension_only."""
    x = I - 1.0
    if tension_only and x <= 0.0:
        return 0.0, 0.0, 0.0
    q = k_exp * x * x
    e_minus_1 = math.expm1(q)  # exact near I = 1, where exp(q) - 1 would cancel
    e = e_minus_1 + 1.0
    return 0.5 * k_stiff / k_exp * e_minus_1, k_stiff * x * e, k_stiff * e * (1.0 + 2.0 * q)


@njit(inline="always")
def _fibre_lanes(I, k_stiff, k_exp, tension_only):
    """:func:`_fibre`'s energy and first derivative with no branch and no call (an
    unstretched fibre's x taken as 0 gives its zeros; vector_math's expm1): a loop over
    points that calls it vectorises."""
    x = I - 1.0
    x = 0.0 if tension_only and x <= 0.0 else x
    e_minus_1 = vexpm1(k_exp * x * x)
    return 0.5 * k_stiff / k_exp * e_minus_1, k_stiff * x * (e_minus_1 + 1.0)


@njit(nogil=True, fastmath=False)
def _hgo(Fa, params, part, P, A):
    """rest = C1/2 (I1b - 3) + C2/2 (I2b - 3) + fibre(I4b) + fibre(I6b), theta = ln J.

    Each isochoric invariant is Ib = J^p I (p = -2/3, or -4/3 for I2b). With weights
    c = dRest/dIb J^p, G = F^-T: dRest = U + s1 G, U = sum c dI, s1 = sum c p I; and
    d2Rest = sum c d2I + V (x) G + G (x) V + s1 d2lnJ + s2 G (x) G + sum f'' dIb (x) dIb
    with V = sum c p dI, s2 = sum c p^2 I (the fibres' f'' only: the others are linear).
    """
    F = _matrix(Fa)
    J, G = _det_inverse_transpose(F)
    lnJ = math.log(J)
    w, a, b, c = _weights(part, params[KAPPA], lnJ)
    p1, p2 = -2.0 / 3.0, -4.0 / 3.0
    g1 = math.exp(p1 * lnJ)  # J^(-2/3)
    g2 = g1 * g1
    tension_only = params[TENSION_ONLY] != 0.0
    m = (params[M0], params[M0 + 1], params[M0 + 2])
    n = (params[N0], params[N0 + 1], params[N0 + 2])
    C = _product(_transpose(F), F)
    I1 = C[0] + C[4] + C[8]
    I2 = 0.5 * (I1 * I1 - _frobenius(C, C))
    Fm, Fn = _apply(F, m[0], m[1], m[2]), _apply(F, n[0], n[1], n[2])
    I4 = Fm[0] * Fm[0] + Fm[1] * Fm[1] + Fm[2] * Fm[2]  # m . C m
    I6 = Fn[0] * Fn[0] + Fn[1] * Fn[1] + Fn[2] * Fn[2]
    Fm_m, Fn_n = _outer(Fm, m), _outer(Fn, n)  # dI4/dF = 2 (F m) (x) m
    f4, df4, ddf4 = _fibre(g1 * I4, params[K1], params[K2], tension_only)
    f6, df6, ddf6 = _fibre(g1 * I6, params[K3], params[K4], tension_only)
    rest = 0.5 * params[C1] * (g1 * I1 - 3.0) + 0.5 * params[C2] * (g2 * I2 - 3.0) + f4 + f6
    c1, c2 = w * 0.5 * params[C1] * g1, w * 0.5 * params[C2] * g2
    c4, c6 = w * df4 * g1, w * df6 * g1
    s1 = p1 * (c1 * I1 + c4 * I4 + c6 * I6) + p2 * c2 * I2
    half_dI2 = _combination(I1, F, -1.0, _product(F, C))  # dI2/dF = 2 (I1 F - F C)
    fibres = _combination(c4, Fm_m, c6, Fn_n)
    if P is not None:
        U = _combination(2.0 * c1, F, 2.0 * c2, half_dI2)
        for r in range(9):
            P[r // 3, r % 3] = U[r] + 2.0 * fibres[r] + (s1 + a) * G[r]
    if A is not None:
        work = carray(_stack_doubles(63), (7, 9))
        _store(work, 0, F)
        _store(work, 1, G)
        V = _combination(2.0 * p1 * c1, F, 2.0 * p2 * c2, half_dI2)
        _store(work, 2, _combination(1.0, V, 2.0 * p1, fibres))
        _store(work, 3, _combination(2.0 * g1, Fm_m, p1 * g1 * I4, G))  # dI4b
        _store(work, 4, _combination(2.0 * g1, Fn_n, p1 * g1 * I6, G))  # dI6b
        M = (c1 + c2 * (I1 - C[0]), -c2 * C[1], -c2 * C[2], -c2 * C[3], c1 + c2 * (I1 - C[4]),
             -c2 * C[5], -c2 * C[6], -c2 * C[7], c1 + c2 * (I1 - C[8]))  # fmt: skip
        fibre_blocks = _combination(c4, _outer(m, m), c6, _outer(n, n))
        _store(work, 5, _combination(2.0, M, 2.0, fibre_blocks))
        _store(work, 6, _product(F, _transpose(F)))
        s2 = p1 * p1 * (c1 * I1 + c4 * I4 + c6 * I6) + p2 * p2 * c2 * I2
        _hgo_tangent(work, (s2 + b, s1 + c, w * ddf4, w * ddf6, 2.0 * c2), A)
    return rest, lnJ


@njit(inline="always")
def _hgo_tangent(work, terms, A):
    """A = V (x) G + G (x) V + gg G (x) G - h F^-1_jk F^-1_li + e4 dI4b (x) dI4b
    + e6 dI6b (x) dI6b + delta_ik M_jl + the I2 term's c2 d2I2 outside M:
    2 c2 (2 F (x) F - F_il F_kj - B_ik delta_jl), B = F F^T."""
    F, G, V, dI4b, dI6b, M, B = work[0], work[1], work[2], work[3], work[4], work[5], work[6]
    gg, h, e4, e6, c2x2 = terms
    for i in range(3):
        for j in range(3):
            r = 3 * i + j
            for k in range(i, 3):  # the upper triangle s >= r
                for l in range(j if k == i else 0, 3):  # noqa: E741 - F[k, l]
                    s = 3 * k + l
                    v = V[r] * G[s] + G[r] * V[s] + gg * G[r] * G[s]
                    v -= h * G[3 * k + j] * G[3 * i + l]
                    v += e4 * dI4b[r] * dI4b[s] + e6 * dI6b[r] * dI6b[s]
                    v += c2x2 * (2.0 * F[r] * F[s] - F[3 * i + l] * F[3 * k + j])
                    if j == l:
                        v -= c2x2 * B[3 * i + k]
                    if i == k:
                        v += M[3 * j + l]
                    A[r, s] = v
                    A[s, r] = v


# -- a law at every point of an element at once (the residual of a hyper-reduced step) -------
# The points' stage buffer W (POINT_ROWS, MAX_POINTS): a row a quantity, a column a point, so
# that a loop over the points is a loop over contiguous entries and vectorises (four points
# a 256-bit instruction). The element kernel writes F's rows; the law writes P dV's, rest's
# and theta's; the rows from _POINT_LAW on are the law's own.
MAX_POINTS = 16  # columns: the hexahedron's 8 points and the tetrahedron's 14 fit
POINT_F, POINT_P = 0, 9  # F and (dRest + p dTheta) dV: 9 rows each, row-major 3x3
POINT_REST, POINT_THETA = 18, 19  # rest(F) and theta(F)
_POINT_LAW = 20
# hgo's own rows: J and the invariants, then 1/J, J^(-2/3) and the fibres' weights
_PJ, _PI1, _PI2, _PI4, _PI6, _PINV, _PG1, _PC4, _PC6 = range(_POINT_LAW, _POINT_LAW + 9)
POINT_ROWS = _POINT_LAW + 9


# Inlined, unlike the laws above: in its caller W is a stack buffer of constant shape, so
# LLVM sees that its rows do not overlap and vectorises; passed to a compiled function of
# its own, W's rows are at a stride known only at run time, and no loop vectorised
# (measured: no 256-bit instruction, with fastmath or without). Its rounding is therefore
# its caller's flags' (hyperreduced's _SUMS: sums reassociated, products fused).
@njit(inline="always")
def _hgo_points(W, points, params, p, dV):
    """:func:`_hgo`'s rest, theta and (its P with part (1, 0, p)) dV at the first ``points``
    columns of W from their F rows: three loops over the points, none with a branch or a
    call, so that each vectorises (the second's exp, expm1 and log vector_math's, its
    division untested: its caller's numba error model must be numpy's)."""
    m0, m1, m2 = params[M0], params[M0 + 1], params[M0 + 2]
    n0, n1, n2 = params[N0], params[N0 + 1], params[N0 + 2]
    for q in range(points):  # J and the invariants
        F = (W[0, q], W[1, q], W[2, q], W[3, q], W[4, q], W[5, q], W[6, q], W[7, q], W[8, q])
        cof = _cofactors(F)
        C = _product(_transpose(F), F)
        I1 = C[0] + C[4] + C[8]
        Fm, Fn = _apply(F, m0, m1, m2), _apply(F, n0, n1, n2)
        W[_PJ, q] = F[0] * cof[0] + F[1] * cof[1] + F[2] * cof[2]
        W[_PI1, q] = I1
        W[_PI2, q] = 0.5 * (I1 * I1 - _frobenius(C, C))
        W[_PI4, q] = Fm[0] * Fm[0] + Fm[1] * Fm[1] + Fm[2] * Fm[2]
        W[_PI6, q] = Fn[0] * Fn[0] + Fn[1] * Fn[1] + Fn[2] * Fn[2]
    tension_only = params[TENSION_ONLY] != 0.0
    for q in range(points):  # 1/J, ln J, J^(-2/3), the fibres (vector_math's, no calls)
        J = W[_PJ, q]
        lnJ = vlog(J)
        g1 = vexp(-2.0 / 3.0 * lnJ)
        f4, df4 = _fibre_lanes(g1 * W[_PI4, q], params[K1], params[K2], tension_only)
        f6, df6 = _fibre_lanes(g1 * W[_PI6, q], params[K3], params[K4], tension_only)
        W[POINT_THETA, q] = lnJ
        W[_PINV, q] = 1.0 / J
        W[_PG1, q] = g1
        W[_PC4, q], W[_PC6, q] = df4 * g1, df6 * g1
        isotropic = 0.5 * params[C1] * (g1 * W[_PI1, q] - 3.0)
        W[POINT_REST, q] = isotropic + 0.5 * params[C2] * (g1 * g1 * W[_PI2, q] - 3.0) + f4 + f6
    p1, p2 = -2.0 / 3.0, -4.0 / 3.0
    for q in range(points):  # P dV, as _hgo's P (rest weight 1, a = p), F^-T = cof F / J
        F = (W[0, q], W[1, q], W[2, q], W[3, q], W[4, q], W[5, q], W[6, q], W[7, q], W[8, q])
        g1, c4, c6 = W[_PG1, q], W[_PC4, q], W[_PC6, q]
        c1, c2 = 0.5 * params[C1] * g1, 0.5 * params[C2] * g1 * g1
        I1 = W[_PI1, q]
        s1 = p1 * (c1 * I1 + c4 * W[_PI4, q] + c6 * W[_PI6, q]) + p2 * c2 * W[_PI2, q]
        half_dI2 = _combination(I1, F, -1.0, _product(F, _product(_transpose(F), F)))
        U = _combination(2.0 * c1, F, 2.0 * c2, half_dI2)
        Fm, Fn = _apply(F, m0, m1, m2), _apply(F, n0, n1, n2)
        fibres = _combination(c4, _outer(Fm, (m0, m1, m2)), c6, _outer(Fn, (n0, n1, n2)))
        G = _scaled(W[_PINV, q], _cofactors(F))
        for r in range(9):
            W[POINT_P + r, q] = (U[r] + 2.0 * fibres[r] + (s1 + p) * G[r]) * dV[q]


# Compiled apart without flags, as the laws: its bits are theirs.
@njit(nogil=True, fastmath=False)
def _theta_gradient(Fa, params, g):
    """g = dTheta/dF alone: what _evaluate(F, params, _THETA, g, None) writes where the law
    is finite (J > 0; there it wrote NaN, here F^-T is inf or of the wrong sign: the same
    point's P and A are NaN), without the rest of the law (an element tangent's K_up needs
    it at every point): F for svk (theta = tr E), F^-T for neo-hookean and hgo (theta =
    ln J), NaN for an unknown law."""
    law = params[LAW]
    if law == LAW_SVK:
        G = _matrix(Fa)
    elif law == LAW_NEO_HOOKEAN or law == LAW_HGO:
        G = _det_inverse_transpose(_matrix(Fa))[1]
    else:
        g[:, :] = np.nan
        return
    for r in range(9):
        g[r // 3, r % 3] = G[r]


@njit(inline="always")
def _evaluate(F, params, part, P, A):
    """(rest, theta) of the law params[LAW]; P and A written unless None (NaN: unknown law)."""
    law = params[LAW]
    if law == LAW_SVK:
        return _svk(F, params, part, P, A)
    if law == LAW_NEO_HOOKEAN:
        return _neo_hookean(F, params, part, P, A)
    if law == LAW_HGO:
        return _hgo(F, params, part, P, A)
    if P is not None:
        P[:, :] = np.nan
    if A is not None:
        A[:, :] = np.nan
    return np.nan, np.nan


@njit(inline="always")
def _check(F, params):
    if F.shape[0] != 3 or F.shape[1] != 3:
        raise ValueError("F must be 3x3")
    if params.shape[0] < PARAMETER_SIZE:
        raise ValueError("params must have PARAMETER_SIZE entries")


@njit(inline="always")
def _check_out(X, size):
    if X.shape[0] != size or X.shape[1] != size:
        raise ValueError("an output array has the wrong shape (P: 3x3, A: 9x9)")


# -- the kernels --------------------------------------------------------------------------
ro_f8_1d = "Array(float64, 1, 'C', readonly=True)"
ro_f8_2d = "Array(float64, 2, 'C', readonly=True)"
f8_2d = "float64[:, ::1]"


@njit(f"float64({ro_f8_2d}, {ro_f8_1d})", cache=True, nogil=True)
def energy(F, params):
    """Psi(F) = rest + kappa/2 theta^2 (MPa)."""
    _check(F, params)
    rest, theta = _evaluate(F, params, _WHOLE, None, None)
    return rest + 0.5 * params[KAPPA] * theta * theta


@njit(f"void({ro_f8_2d}, {ro_f8_1d}, {f8_2d})", cache=True, nogil=True)
def first_piola(F, params, P_out):
    """P_out (3x3) = dPsi/dF, the first Piola-Kirchhoff stress (MPa)."""
    _check(F, params)
    _check_out(P_out, 3)
    _evaluate(F, params, _WHOLE, P_out, None)


@njit(f"void({ro_f8_2d}, {ro_f8_1d}, {f8_2d})", cache=True, nogil=True)
def tangent(F, params, A_out):
    """A_out (9x9) = d2Psi/dF2, row 3*i + j and column 3*k + l for F[i, j], F[k, l] (MPa)."""
    _check(F, params)
    _check_out(A_out, 9)
    _evaluate(F, params, _WHOLE, None, A_out)


@njit(f"float64({ro_f8_2d}, {ro_f8_1d}, {f8_2d}, {f8_2d})", cache=True, nogil=True)
def stress_and_tangent(F, params, P_out, A_out):
    """Psi (returned), P_out = dPsi/dF and A_out = d2Psi/dF2 in one call (a Newton step's)."""
    _check(F, params)
    _check_out(P_out, 3)
    _check_out(A_out, 9)
    rest, theta = _evaluate(F, params, _WHOLE, P_out, A_out)
    return rest + 0.5 * params[KAPPA] * theta * theta


@njit(f"float64({ro_f8_2d}, {ro_f8_1d}, {f8_2d}, {f8_2d})", cache=True, nogil=True)
def rest_derivatives(F, params, P_out, A_out):
    """The rest part of the energy (returned), its gradient P_out and Hessian A_out."""
    _check(F, params)
    _check_out(P_out, 3)
    _check_out(A_out, 9)
    return _evaluate(F, params, _REST, P_out, A_out)[0]


@njit(f"float64({ro_f8_2d}, {ro_f8_1d}, {f8_2d}, {f8_2d})", cache=True, nogil=True)
def theta_derivatives(F, params, g_out, H_out):
    """The volumetric strain theta (returned), its gradient g_out and Hessian H_out."""
    _check(F, params)
    _check_out(g_out, 3)
    _check_out(H_out, 9)
    return _evaluate(F, params, _THETA, g_out, H_out)[1]
