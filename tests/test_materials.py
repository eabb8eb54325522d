"""Material laws on homogeneous deformations: UFL stresses vs independent references.

The UFL strain energy of each law is differentiated by UFL (P = dPsi/dF,
S = F^-1 P) and evaluated at given deformation gradients; the references are
closed-form stresses (thesis eqs. 3.10, 3.31) and, for the fibre law, a
complex-step derivative of an independent numpy implementation of Psi(C).
"""

from __future__ import annotations

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from hapticrom.offline.fe.materials import (
    HolzapfelGasser,
    NeoHookean,
    SaintVenantKirchhoff,
    make_law,
)
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(20261122)


class StressEvaluator:
    """Psi, P and S of a law at a homogeneous F, compiled once (F, parameters are Constants)."""

    def __init__(self, law):
        self.domain = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1, mesh.CellType.hexahedron)
        self.F = fem.Constant(self.domain, np.eye(3))
        self.m0 = fem.Constant(self.domain, np.array([1.0, 0.0, 0.0]))
        self.n0 = fem.Constant(self.domain, np.array([0.0, 1.0, 0.0]))
        self.params = {k: fem.Constant(self.domain, v) for k, v in law.parameters().items()}
        Fv = ufl.variable(self.F)
        fibres = (self.m0, self.n0) if law.requires_fibres else None
        psi = law.strain_energy(Fv, self.params, fibres)
        P = ufl.diff(psi, Fv)
        S = ufl.inv(Fv) * P
        flat = [psi] + [P[i, j] for i in range(3) for j in range(3)]
        flat += [S[i, j] for i in range(3) for j in range(3)]
        self.expr = fem.Expression(ufl.as_vector(flat), np.array([[0.5, 0.5, 0.5]]))

    def __call__(self, F, m0=(1, 0, 0), n0=(0, 1, 0), **params):
        self.F.value[:] = F
        self.m0.value[:] = m0
        self.n0.value[:] = n0
        for k, v in params.items():
            self.params[k].value = v
        out = self.expr.eval(self.domain, np.array([0], dtype=np.int32)).ravel()
        return out[0], out[1:10].reshape(3, 3), out[10:19].reshape(3, 3)


@pytest.fixture(scope="module")
def hgo():
    return StressEvaluator(HolzapfelGasser())


@pytest.fixture(scope="module")
def hgo_tension_only():
    return StressEvaluator(HolzapfelGasser(fibre_tension_only=True))


@pytest.fixture(scope="module")
def neo_hookean():
    return StressEvaluator(NeoHookean(E=1.0, nu=0.25))


@pytest.fixture(scope="module")
def svk():
    return StressEvaluator(SaintVenantKirchhoff(E=1.0, nu=0.25))


def random_F(scale=0.25):
    while True:
        F = np.eye(3) + scale * RNG.standard_normal((3, 3))
        if np.linalg.det(F) > 0.5:
            return F


def random_rotation():
    Q, R = np.linalg.qr(RNG.standard_normal((3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    return Q if np.linalg.det(Q) > 0 else -Q


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def isochoric_stretch(a, lam):
    """Volume-preserving uniaxial stretch lam along unit vector a."""
    a = unit(a)
    A = np.outer(a, a)
    return lam * A + lam**-0.5 * (np.eye(3) - A)


# -- independent numpy reference for the HGO law (thesis eqs. 2.14-2.20) ---------
def psi_hgo_numpy(C, m0, n0, C1=0.1, D=1e-5, C2=0.0, k1=0.234, k2=29.917, k3=0.234, k4=29.917):
    J = np.sqrt(np.linalg.det(C))
    Cb = J ** (-2.0 / 3.0) * C
    I1 = np.trace(Cb)
    I2 = 0.5 * (I1**2 - np.trace(Cb @ Cb))
    I4 = m0 @ Cb @ m0
    I6 = n0 @ Cb @ n0
    return (
        np.log(J) ** 2 / D
        + C1 / 2 * (I1 - 3)
        + C2 / 2 * (I2 - 3)
        + k1 / (2 * k2) * (np.exp(k2 * (I4 - 1) ** 2) - 1)
        + k3 / (2 * k4) * (np.exp(k4 * (I6 - 1) ** 2) - 1)
    )


def S_complex_step(psi, C, h=1e-30, **kw):
    """S = 2 dPsi/dC, each component by a complex step (exact to rounding)."""
    S = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            Cc = C.astype(complex)
            Cc[i, j] += 1j * h
            S[i, j] = 2 * psi(Cc, **kw).imag / h
    return S


# -- tests -------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["svk", "neo_hookean", "hgo", "hgo_tension_only"])
def test_stress_free_reference(name, request):
    evaluate = request.getfixturevalue(name)
    psi, P, S = evaluate(np.eye(3), m0=unit([1, 1, 0]), n0=unit([1, -1, 0.2]))
    assert abs(psi) < 1e-14
    assert np.abs(P).max() < 1e-12 and np.abs(S).max() < 1e-12


@pytest.mark.parametrize("name", ["svk", "neo_hookean", "hgo"])
def test_objectivity_and_symmetry(name, request):
    evaluate = request.getfixturevalue(name)
    for _ in range(5):
        F = random_F(0.15)
        Q = random_rotation()
        m0, n0 = unit(RNG.standard_normal(3)), unit(RNG.standard_normal(3))
        psi, P, S = evaluate(F, m0, n0)
        psi_r, P_r, S_r = evaluate(Q @ F, m0, n0)
        scale = np.abs(S).max()
        assert np.abs(S - S.T).max() <= 1e-10 * scale, "second Piola-Kirchhoff stress not symmetric"
        assert abs(psi_r - psi) <= 1e-10 * abs(psi)
        assert np.abs(S_r - S).max() <= 1e-9 * scale, "S changes under a rotation of F"
        assert np.abs(P_r - Q @ P).max() <= 1e-9 * np.abs(P).max(), "P does not rotate with F"
        # Cauchy stress rotates: sigma(QF) = Q sigma(F) Q^T
        sigma = P @ F.T / np.linalg.det(F)
        sigma_r = P_r @ (Q @ F).T / np.linalg.det(F)
        assert np.abs(sigma_r - Q @ sigma @ Q.T).max() <= 1e-9 * np.abs(sigma).max()


def test_hgo_matches_complex_step_reference(hgo):
    worst = 0.0
    for _ in range(10):
        F = random_F(0.1)
        m0, n0 = unit(RNG.standard_normal(3)), unit(RNG.standard_normal(3))
        psi, _, S = hgo(F, m0, n0)
        C = F.T @ F
        S_ref = S_complex_step(psi_hgo_numpy, C, m0=m0, n0=n0)
        assert abs(psi - psi_hgo_numpy(C, m0, n0)) <= 1e-10 * abs(psi)
        worst = max(worst, np.abs(S - S_ref).max() / np.abs(S_ref).max())
    assert worst <= 1e-8, f"HGO S differs from the complex-step reference by {worst:.2e}"


def test_hgo_with_c2_and_other_parameters(hgo):
    params = dict(C1=0.05, D=1e-3, C2=0.02, k1=0.5, k2=10.0, k3=0.1, k4=5.0)
    F = random_F(0.1)
    m0, n0 = unit([1, 0.2, 0]), unit([0, 1, 0.3])
    _, _, S = hgo(F, m0, n0, **params)
    S_ref = S_complex_step(psi_hgo_numpy, F.T @ F, m0=m0, n0=n0, **params)
    assert np.abs(S - S_ref).max() <= 1e-8 * np.abs(S_ref).max()
    hgo(np.eye(3), **HolzapfelGasser().parameters())  # restore the defaults for other tests


def test_neo_hookean_matches_closed_form(neo_hookean):
    E, nu = 1.0, 0.25
    mu, lmbda = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    for _ in range(5):
        F = random_F()
        C = F.T @ F
        Ci = np.linalg.inv(C)
        S_ref = mu * (np.eye(3) - Ci) + lmbda * np.log(np.linalg.det(F)) * Ci  # thesis eq. 3.31
        _, _, S = neo_hookean(F)
        assert np.abs(S - S_ref).max() <= 1e-12 * np.abs(S_ref).max()


def test_svk_matches_closed_form(svk):
    E, nu = 1.0, 0.25
    mu, lmbda = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    for _ in range(5):
        F = random_F()
        Egl = (F.T @ F - np.eye(3)) / 2
        S_ref = lmbda * np.trace(Egl) * np.eye(3) + 2 * mu * Egl  # thesis eq. 3.10
        _, _, S = svk(F)
        assert np.abs(S - S_ref).max() <= 1e-12 * np.abs(S_ref).max()


def test_fibre_stiffening(hgo):
    """Stretching along a fibre family costs more than stretching across both."""
    m0, n0 = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    normal = np.array([0, 0, 1.0])
    for lam in (1.02, 1.05, 1.1):
        psi_along, _, S_along = hgo(isochoric_stretch(m0, lam), m0, n0)
        psi_across, _, S_across = hgo(isochoric_stretch(normal, lam), m0, n0)
        assert psi_along > 1.5 * psi_across
        assert m0 @ S_along @ m0 > 1.5 * (normal @ S_across @ normal) > 0


def test_fibre_tension_only_switch(hgo, hgo_tension_only):
    """Compressed fibres resist in the thesis' law and carry nothing with the switch on."""
    m0, n0 = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    normal = np.array([0, 0, 1.0])
    F = isochoric_stretch(normal, 1.1)  # both families shortened (I4b = I6b = 1/1.1)
    psi_c, _, _ = hgo(F, m0, n0)
    psi_t, _, _ = hgo_tension_only(F, m0, n0)
    neo = HolzapfelGasser().C1 / 2 * (np.trace(F.T @ F) - 3)  # J = 1: only the C1 term
    assert psi_t == pytest.approx(neo, rel=1e-12)
    assert psi_c > 1.05 * psi_t
    # In tension both variants agree.
    F = isochoric_stretch(unit([1, 1, 0]), 1.1)  # stretches both families
    assert hgo(F, m0, n0)[0] == pytest.approx(hgo_tension_only(F, m0, n0)[0], rel=1e-12)


@pytest.mark.parametrize(
    "name, params, message",
    [
        ("rubber", {}, "unknown material"),
        ("svk", {"E": -1.0, "nu": 0.3}, "E must be positive"),
        ("svk", {"E": 1.0, "nu": 0.5}, "nu must lie"),
        ("neo-hookean", {"E": 1.0}, "nu"),
        ("hgo", {"D": 0.0}, "D must be positive"),
        ("hgo", {"C1": -0.1}, "C1 must be positive"),
        ("hgo", {"k2": -3.0}, "k2 must be positive"),
        ("hgo", {"stiffness": 1.0}, "has no parameter stiffness"),
        ("hgo", {"C1": "soft"}, "must be a finite number"),
        ("hgo", {"C1": float("nan")}, "must be a finite number"),
        ("hgo", {"C1": 10**400}, "must be a finite number"),
    ],
)
def test_bad_material_input(name, params, message):
    with pytest.raises(InputError, match=message):
        make_law(name, **params)


def test_parameter_lookup():
    assert make_law("neo_hookean", E=2.0, nu=0.48).parameters() == {"E": 2.0, "nu": 0.48}
    assert HolzapfelGasser().parameters() == {
        "C1": 0.1, "D": 1e-5, "C2": 0.0, "k1": 0.234, "k2": 29.917, "k3": 0.234, "k4": 29.917,
    }  # fmt: skip
