"""The online runtime's numba material kernels against the offline trainer's UFL laws.

The reference is the UFL energy of :mod:`hapticrom.offline.fe.materials` differentiated
by UFL (``ufl.diff`` on a ``ufl.variable`` F, twice) and evaluated by a DOLFINx
``fem.Expression`` on a one-cell mesh: energy, first Piola stress and tangent of the
whole law and of its split ``rest + kappa/2 theta^2``. Independent second checks:
central differences of the kernels themselves, the stress-free reference, frame
indifference, the fibre switch, no allocation, and that the runtime module stays free
of the finite-element stack.
"""

from __future__ import annotations

import numpy as np
import pytest
import ufl
from allocation_probe import BLOCK_FE_STACK, run_probe
from dolfinx import fem, mesh
from mpi4py import MPI

from hapticrom.offline.fe.materials import (
    HolzapfelGasser,
    NeoHookean,
    SaintVenantKirchhoff,
    make_law,
)
from hapticrom.online import material_kernels as mk
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(20261123)
RELATIVE = 1e-10  # kernels vs UFL, relative to the reference's largest entry

# Per law: the trainer's UFL law and parameter sets, the second of which weighs the rest
# part more against the volumetric term (hgo's default kappa = 2/D is 2e5 MPa).
OTHER_HGO = dict(C1=0.05, D=1e-2, C2=0.02, k1=0.5, k2=10.0, k3=0.1, k4=5.0)
CASES = {
    "svk": (SaintVenantKirchhoff(E=1.0, nu=0.3), [dict(E=1.0, nu=0.3), dict(E=3.0, nu=0.45)]),
    "neo-hookean": (NeoHookean(E=1.0, nu=0.3), [dict(E=1.0, nu=0.3), dict(E=3.0, nu=0.45)]),
    "hgo": (HolzapfelGasser(), [{}, OTHER_HGO]),
    "hgo-tension-only": (HolzapfelGasser(fibre_tension_only=True), [{}, OTHER_HGO]),
}


class UflLaw:
    """A law's energy, P and A (whole, rest and theta) from UFL at a homogeneous F.

    F, the fibres and the parameters are ``fem.Constant``s: one compiled expression
    serves every deformation gradient and parameter set.
    """

    def __init__(self, law):
        self.law = law
        self.domain = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1, mesh.CellType.hexahedron)
        self.F = fem.Constant(self.domain, np.eye(3))
        self.m0 = fem.Constant(self.domain, np.array([1.0, 0.0, 0.0]))
        self.n0 = fem.Constant(self.domain, np.array([0.0, 1.0, 0.0]))
        self.c = {k: fem.Constant(self.domain, v) for k, v in law.parameters().items()}
        Fv = ufl.variable(self.F)
        fibres = (self.m0, self.n0) if law.requires_fibres else None
        split = law.energy_split(Fv, self.c, fibres)
        entries = [split.kappa]
        for f in (law.strain_energy(Fv, self.c, fibres), split.rest, split.theta):
            P = ufl.diff(f, Fv)
            A = ufl.diff(P, Fv)
            entries += [f] + [P[i, j] for i in range(3) for j in range(3)]
            entries += [A[i, j, k, l] for i in range(3) for j in range(3)
                        for k in range(3) for l in range(3)]  # fmt: skip  # noqa: E741
        self.expr = fem.Expression(ufl.as_vector(entries), np.array([[0.5, 0.5, 0.5]]))

    def __call__(self, F, params, m0=(1.0, 0.0, 0.0), n0=(0.0, 1.0, 0.0)):
        """{"kappa": .., "whole"/"rest"/"theta": (value, P 3x3, A 9x9)}."""
        self.F.value[:] = F
        self.m0.value[:] = m0
        self.n0.value[:] = n0
        for k, constant in self.c.items():
            constant.value = params.get(k, self.law.parameters()[k])
        out = self.expr.eval(self.domain, np.array([0], dtype=np.int32)).ravel()
        parts = {"kappa": out[0]}
        for n, name in enumerate(("whole", "rest", "theta")):
            o = 1 + 91 * n
            parts[name] = (
                out[o],
                out[o + 1 : o + 10].reshape(3, 3),
                out[o + 10 : o + 91].reshape(9, 9),
            )
        return parts


@pytest.fixture(scope="module", params=list(CASES))
def law(request):
    return request.param, UflLaw(CASES[request.param][0])


def pack(name, params, m0=None, n0=None):
    """The kernels' packed parameters for a CASES entry."""
    if name.startswith("hgo"):
        extra = dict(m0=m0, n0=n0, fibre_tension_only=name == "hgo-tension-only")
        return mk.law_parameters("hgo", **params, **extra)
    return mk.law_parameters(name, **params)


def kernels(F, packed):
    """(energy, P, A) and (rest, dRest, d2Rest), (theta, dTheta, d2Theta) from the kernels."""
    F = np.ascontiguousarray(F)
    P, A = np.empty((3, 3)), np.empty((9, 9))
    mk.first_piola(F, packed, P)
    mk.tangent(F, packed, A)
    whole = (mk.energy(F, packed), P, A)
    Pr, Ar, Pt, At = np.empty((3, 3)), np.empty((9, 9)), np.empty((3, 3)), np.empty((9, 9))
    rest = (mk.rest_derivatives(F, packed, Pr, Ar), Pr, Ar)
    theta = (mk.theta_derivatives(F, packed, Pt, At), Pt, At)
    return {"whole": whole, "rest": rest, "theta": theta}


def random_unit():
    v = RNG.standard_normal(3)
    return v / np.linalg.norm(v)


def random_rotation():
    Q, R = np.linalg.qr(RNG.standard_normal((3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    return Q if np.linalg.det(Q) > 0 else -Q


def moderate_deformation():
    """det F in [0.7, 1.4], principal stretches in [0.7, 1.4]."""
    while True:
        F = np.eye(3) + 0.25 * RNG.standard_normal((3, 3))
        stretches = np.linalg.svd(F, compute_uv=False)
        if 0.7 <= np.linalg.det(F) <= 1.4 and 0.7 <= stretches.min() and stretches.max() <= 1.4:
            return F


def deformations(count=22):
    """count moderate deformation gradients and one near the identity (1 % strain: at
    0.1 % the rest energy, a difference of O(1) invariants, keeps only ~1e-10 of its
    digits in any implementation)."""
    near_identity = np.eye(3) + 1e-2 * RNG.standard_normal((3, 3))
    return [moderate_deformation() for _ in range(count)] + [near_identity]


def relative_error(value, reference):
    scale = np.abs(reference).max()
    return np.abs(np.asarray(value) - reference).max() / scale


# -- against UFL ---------------------------------------------------------------------------
def test_kernels_match_ufl(law):
    name, reference = law
    worst = {}
    for params in CASES[name][1]:
        for F in deformations():
            m0, n0 = random_unit(), random_unit()
            expected = reference(F, params, m0, n0)
            packed = pack(name, params, m0, n0)
            assert packed[mk.KAPPA] == pytest.approx(expected["kappa"], rel=1e-14)
            got = kernels(F, packed)
            for part in ("whole", "rest", "theta"):
                for n, what in enumerate(("value", "P", "A")):
                    error = relative_error(got[part][n], expected[part][n])
                    key = f"{part} {what}"
                    worst[key] = max(worst.get(key, 0.0), error)
    assert all(error <= RELATIVE for error in worst.values()), worst


def test_pure_rotation_stores_nothing_and_stiffens_as_ufl(law):
    """At a rotation Q the energy and stress vanish to rounding: that of theta (~1e-16)
    times kappa for the whole law, of the rest part's own moduli for the rest part. The
    switched fibres' tangent jumps by k1 dI4b (x) dI4b at I4b = 1, where a rotation
    leaves them (to rounding, on either side): that tangent is not compared there."""
    name, reference = law
    Q = random_rotation()
    for params in CASES[name][1]:
        m0, n0 = random_unit(), random_unit()
        expected = reference(Q, params, m0, n0)
        got = kernels(Q, pack(name, params, m0, n0))
        for part in ("whole", "rest"):
            value, P, A = got[part]
            modulus = np.abs(expected[part][2]).max()
            assert abs(value) <= 1e-12 * modulus
            assert np.abs(P).max() <= 1e-12 * modulus
            if name != "hgo-tension-only":
                assert relative_error(A, expected[part][2]) <= RELATIVE


# -- independent checks on the kernels alone ------------------------------------------------
def central_differences(F, packed):
    """dPsi/dF from energy() and d2Psi/dF2 from first_piola(), by central differences."""
    h = 1e-6
    P_fd, A_fd = np.empty((3, 3)), np.empty((9, 9))
    P_plus, P_minus = np.empty((3, 3)), np.empty((3, 3))
    for r in range(9):
        step = np.zeros(9)
        step[r] = h
        step = step.reshape(3, 3)
        P_fd.flat[r] = (mk.energy(F + step, packed) - mk.energy(F - step, packed)) / (2 * h)
        mk.first_piola(F + step, packed, P_plus)
        mk.first_piola(F - step, packed, P_minus)
        A_fd[:, r] = ((P_plus - P_minus) / (2 * h)).ravel()
    return P_fd, A_fd


@pytest.mark.parametrize("name", list(CASES))
def test_derivatives_match_central_differences(name):
    """P is the gradient of energy() and A the Jacobian of first_piola(): with a step of
    1e-6 the truncation (h^2/6 Psi''') and rounding (1e-16 Psi/h) errors stay below 1e-7
    of the largest entry for these stretches."""
    for params in CASES[name][1]:
        for F in deformations(4):
            packed = pack(name, params, random_unit(), random_unit())
            P, A = np.empty((3, 3)), np.empty((9, 9))
            mk.first_piola(F, packed, P)
            mk.tangent(F, packed, A)
            P_fd, A_fd = central_differences(F, packed)
            assert relative_error(P, P_fd) <= 1e-7
            assert relative_error(A, A_fd) <= 1e-7
            assert np.array_equal(A, A.T)


@pytest.mark.parametrize("name", list(CASES))
def test_split_and_combined_kernels_agree(name):
    """rest + kappa/2 theta^2 and its derivatives give the whole law; stress_and_tangent
    gives what energy, first_piola and tangent give."""
    params = CASES[name][1][1]
    F = moderate_deformation()
    packed = pack(name, params, random_unit(), random_unit())
    got = kernels(F, packed)
    kappa = packed[mk.KAPPA]
    (rest, P_rest, A_rest), (theta, g, H) = got["rest"], got["theta"]
    energy, P, A = got["whole"]
    assert rest + kappa / 2 * theta**2 == pytest.approx(energy, rel=1e-14)
    assert relative_error(P_rest + kappa * theta * g, P) <= 1e-14
    assert relative_error(A_rest + kappa * (np.outer(g, g) + theta * H), A) <= 1e-14
    P2, A2 = np.empty((3, 3)), np.empty((9, 9))
    assert mk.stress_and_tangent(F, packed, P2, A2) == pytest.approx(energy, rel=1e-15)
    assert relative_error(P2, P) <= 1e-15 and relative_error(A2, A) <= 1e-15


@pytest.mark.parametrize("name", list(CASES))
def test_stress_free_reference(name):
    """Psi(I) = 0 and P(I) = 0, to the rounding of the rest part's moduli (J = 1 exactly)."""
    for params in CASES[name][1]:
        packed = pack(name, params, random_unit(), random_unit())
        energy, P, _ = kernels(np.eye(3), packed)["whole"]
        modulus = np.abs(kernels(np.eye(3), packed)["rest"][2]).max()
        assert abs(energy) <= 1e-14 * modulus
        assert np.abs(P).max() <= 1e-13 * modulus


@pytest.mark.parametrize("name", list(CASES))
def test_frame_indifference(name):
    """Psi(QF) = Psi(F), P(QF) = Q P(F), A(QF)_ijkl = Q_ia Q_kb A(F)_ajbl."""
    for params in CASES[name][1]:
        packed = pack(name, params, random_unit(), random_unit())
        for F in deformations(5):
            Q = random_rotation()
            energy, P, A = kernels(F, packed)["whole"]
            energy_r, P_r, A_r = kernels(Q @ F, packed)["whole"]
            assert energy_r == pytest.approx(energy, rel=1e-12)
            assert relative_error(P_r, Q @ P) <= 1e-12
            A_rotated = np.einsum("ia,kb,ajbl->ijkl", Q, Q, A.reshape(3, 3, 3, 3))
            assert relative_error(A_r, A_rotated.reshape(9, 9)) <= 1e-12


def isochoric_stretch(direction, stretch):
    a = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    aa = np.outer(a, a)
    return stretch * aa + stretch**-0.5 * (np.eye(3) - aa)


def test_fibre_tension_only_switch():
    """A compressed fibre family contributes nothing with the switch on (energy, stress,
    tangent equal those of a law without that family) and resists without it."""
    e1, e2, e3 = np.eye(3)
    fibres = dict(m0=e1, n0=e2)
    switched = mk.law_parameters("hgo", **fibres, fibre_tension_only=True)
    smooth = mk.law_parameters("hgo", **fibres)
    only_m0 = mk.law_parameters("hgo", **fibres, k3=0.0)
    neither = mk.law_parameters("hgo", **fibres, k1=0.0, k3=0.0)

    def same(F, a, b):
        pairs = zip(kernels(F, a)["whole"], kernels(F, b)["whole"], strict=True)
        return all(relative_error(x, y) <= 1e-14 for x, y in pairs)

    both_shortened = isochoric_stretch(e3, 1.1)  # I4b = I6b = 1/1.1
    assert same(both_shortened, switched, neither)
    assert mk.energy(both_shortened, smooth) > 1.05 * mk.energy(both_shortened, neither)
    m0_stretched = isochoric_stretch(e1, 1.1)  # I4b = 1.21, I6b = 1/1.1
    assert same(m0_stretched, switched, only_m0)
    assert not same(m0_stretched, smooth, only_m0)
    both_stretched = isochoric_stretch([1.0, 1.0, 0.0], 1.1)  # I4b = I6b = 1.06
    assert same(both_stretched, switched, smooth)


@pytest.fixture(scope="module")
def hgo_points_kernel():
    """material_kernels._hgo_points compiled as the element kernel inlines it (the
    hyper-reduced sums' flags: reassociated, fused; numpy's error model)."""
    from numba import njit

    @njit(fastmath={"reassoc", "contract"}, error_model="numpy")
    def run(W, points, packed, p, dV):
        mk._hgo_points(W, points, packed, p, dV)

    return run


def hgo_points(run, Fs, packed, p, dV):
    """(P dV, rest, theta) at each point of Fs (points, 3, 3) from the columns of a stage
    buffer."""
    W = np.full((mk.POINT_ROWS, mk.MAX_POINTS), np.nan)  # a column not written stays NaN
    W[mk.POINT_F : mk.POINT_F + 9, : len(Fs)] = Fs.reshape(len(Fs), 9).T
    run(W, len(Fs), packed, p, dV)
    P = W[mk.POINT_P : mk.POINT_P + 9, : len(Fs)].T.reshape(-1, 3, 3)
    return P, W[mk.POINT_REST, : len(Fs)], W[mk.POINT_THETA, : len(Fs)]


@pytest.mark.parametrize("name", ["hgo", "hgo-tension-only"])
def test_hgo_at_every_point_at_once_is_the_law_point_by_point(name, hgo_points_kernel):
    """The residual's hgo at an element's points at once (vector lanes) gives, at each
    point, rest, theta and (dRest + p dTheta) dV of the law point by point (held to UFL
    above), to rounding: both parameter sets (C2 > 0 in the second), fibres stretched and
    compressed, the hexahedron's 8 points and the tetrahedron's 14."""
    for params in CASES[name][1]:
        packed = pack(name, params, random_unit(), random_unit())
        for points in (8, 14):
            Fs = np.array([isochoric_stretch(random_unit(), 1.1)] + deformations(points - 1)[1:])
            dV, p = RNG.uniform(0.1, 2.0, points), 0.05 * RNG.standard_normal()
            P, rest, theta = hgo_points(hgo_points_kernel, Fs, packed, p, dV)
            for F, Pq, rest_q, theta_q, v in zip(Fs, P, rest, theta, dV, strict=True):
                (rest_ref, P_rest, _), (theta_ref, g, _) = (kernels(F, packed)[k]
                                                            for k in ("rest", "theta"))  # fmt: skip
                assert rest_q == pytest.approx(rest_ref, rel=1e-13, abs=1e-15)
                assert theta_q == pytest.approx(theta_ref, rel=1e-13, abs=1e-15)
                assert relative_error(Pq, (P_rest + p * g) * v) <= 1e-13


def test_hgo_defaults_are_the_trainers():
    assert mk.HGO_DEFAULTS == HolzapfelGasser().parameters()


@pytest.mark.parametrize(
    "name, params, message",
    [
        ("rubber", {}, "unknown material"),
        ("svk", {"E": -1.0, "nu": 0.3}, "E must be positive"),
        ("svk", {"E": 1.0, "nu": 0.5}, "nu must lie"),
        ("neo-hookean", {"E": 1.0, "nu": -1.0}, "nu must lie"),
        ("neo-hookean", {"E": 1.0}, "missing parameter nu"),
        ("neo_hookean", {"E": 1.0, "nu": 0.3, "mu": 1.0}, "has no parameter mu"),
        ("svk", {"E": float("inf"), "nu": 0.3}, "parameter E must be a finite number"),
        ("svk", {"E": True, "nu": 0.3}, "parameter E must be a finite number"),
        ("hgo", {"D": 0.0}, "D must be positive"),
        ("hgo", {"C1": -0.1}, "C1 must be positive"),
        ("hgo", {"C2": -0.1}, "C2 must not be negative"),
        ("hgo", {"k3": -0.1}, "k3 must not be negative"),
        ("hgo", {"k2": -3.0}, "k2 must be positive"),
        ("hgo", {"C1": "soft"}, "parameter C1 must be a finite number"),
        ("hgo", {"C1": float("nan")}, "parameter C1 must be a finite number"),
        ("hgo", {"k4": 10**400}, "parameter k4 must be a finite number"),
        ("hgo", {"stiffness": 1.0}, "has no parameter stiffness"),
        ("hgo", {"fibre_tension_only": 1}, "fibre_tension_only must be true or false"),
    ],
)
def test_bad_parameters_refused_as_the_trainer_does(name, params, message):
    fibres = {"m0": [1.0, 0.0, 0.0], "n0": [0.0, 1.0, 0.0]} if name == "hgo" else {}
    with pytest.raises(InputError, match=message):
        mk.law_parameters(name, **params, **fibres)
    with pytest.raises(InputError):  # the UFL law refuses it too
        make_law(name, **params)


@pytest.mark.parametrize(
    "fibres, message",
    [
        ({"n0": [0.0, 1.0, 0.0]}, "no m0"),
        ({"m0": [1.0, 0.0, 0.0], "n0": [0.0, 2.0, 0.0]}, "n0 must be a unit vector"),
        ({"m0": [1.0, 0.0], "n0": [0.0, 1.0, 0.0]}, "m0 must be 3 finite numbers"),
        ({"m0": [1.0, 0.0, float("nan")], "n0": [0.0, 1.0, 0.0]}, "m0 must be 3 finite"),
        ({"m0": "x", "n0": [0.0, 1.0, 0.0]}, "m0 must be 3 finite numbers"),
    ],
)
def test_bad_fibres_refused(fibres, message):
    with pytest.raises(InputError, match=message):
        mk.law_parameters("hgo", **fibres)


def test_fibres_refused_for_isotropic_laws():
    with pytest.raises(InputError, match="has no parameter m0"):
        mk.law_parameters("svk", E=1.0, nu=0.3, m0=[1.0, 0.0, 0.0])


def test_kernels_refuse_wrong_shapes_and_flag_unknown_laws():
    packed = mk.law_parameters("svk", E=1.0, nu=0.3)
    with pytest.raises(ValueError, match="wrong shape"):
        mk.tangent(np.eye(3), packed, np.empty((3, 3)))
    with pytest.raises(ValueError, match="wrong shape"):
        mk.first_piola(np.eye(3), packed, np.empty((9, 9)))
    with pytest.raises(ValueError, match="F must be 3x3"):
        mk.energy(np.eye(2), packed)
    with pytest.raises(ValueError, match="PARAMETER_SIZE"):
        mk.energy(np.eye(3), packed[:-1].copy())
    unknown = packed.copy()
    unknown[mk.LAW] = 7.0
    A = np.zeros((9, 9))
    mk.tangent(np.eye(3), unknown, A)
    assert np.isnan(mk.energy(np.eye(3), unknown)) and np.isnan(A).all()


def test_kernels_accept_read_only_inputs():
    packed = mk.law_parameters("neo-hookean", E=1.0, nu=0.3)
    F = moderate_deformation()
    expected = mk.energy(F, packed)
    packed.flags.writeable = False
    F.flags.writeable = False
    assert mk.energy(F, packed) == expected


# -- the runtime stays small, and allocates nothing ----------------------------------------
def test_runtime_module_imports_no_fe_stack_and_allocates_nothing(tmp_path):
    """Compiled afresh (an empty numba cache) with the finite-element stack and scipy
    blocked; then numba's allocation counters (which see an allocating canary) do not
    move over 1000 calls of each kernel."""
    body = """
        from hapticrom.online import material_kernels as mk

        @njit
        def run(F, params, P, A, g, H, n):
            total = 0.0
            for _ in range(n):
                total += mk.energy(F, params)
                mk.first_piola(F, params, P)
                mk.tangent(F, params, A)
                total += mk.stress_and_tangent(F, params, P, A)
                total += mk.rest_derivatives(F, params, P, A)
                total += mk.theta_derivatives(F, params, g, H)
            return total

        F = np.eye(3) + 0.1 * np.arange(9.0).reshape(3, 3) / 9
        fibres = dict(m0=np.array([1.0, 0.0, 0.0]), n0=np.array([0.0, 1.0, 0.0]))
        laws = [mk.law_parameters("svk", E=1.0, nu=0.3),
                mk.law_parameters("neo-hookean", E=1.0, nu=0.3),
                mk.law_parameters("hgo", **fibres, C2=0.1, fibre_tension_only=True)]
        buffers = (np.empty((3, 3)), np.empty((9, 9)), np.empty((3, 3)), np.empty((9, 9)))
        for params in laws:
            same_allocations(run, F, params, *buffers)
        loaded = [m for m in ("ufl", "dolfinx", "scipy", "petsc4py") if m in sys.modules]
        assert not loaded, loaded
        print("ok")
    """
    run_probe(body, BLOCK_FE_STACK, {"NUMBA_CACHE_DIR": str(tmp_path / "numba")})


def test_theta_gradient_alone_is_the_law_s_bit_for_bit():
    """_theta_gradient (an element tangent's K_up at every point) writes what the law's
    theta part writes, bit for bit (theta_derivatives' g, held to UFL above), for every
    law at random deformations (J > 0: where the law is finite); NaN for an unknown law
    id."""
    from numba import njit

    @njit
    def theta_gradient(F, params, g):
        mk._theta_gradient(F, params, g)

    for name, (_, parameter_sets) in CASES.items():
        for params in parameter_sets:
            packed = pack(name, params, random_unit(), random_unit())
            for F in deformations(6):
                expected, g = np.empty((3, 3)), np.full((3, 3), np.nan)
                mk.theta_derivatives(np.ascontiguousarray(F), packed, expected, np.empty((9, 9)))
                theta_gradient(np.ascontiguousarray(F), packed, g)
                np.testing.assert_array_equal(g, expected, err_msg=name)
    unknown = mk.law_parameters("svk", E=1.0, nu=0.3)
    unknown[mk.LAW] = 99.0
    g = np.zeros((3, 3))
    theta_gradient(np.eye(3), unknown, g)
    assert np.isnan(g).all()
