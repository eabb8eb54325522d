"""The hyper-reduced mixed model against the full order it reduces.

A force-controlled HGO campaign on the coarse cornea, solved by the trainer (DOLFINx):
with bases that span a position's own full-order states, those states are a root of the
reduced equations, and the reduced Newton (element kernels summed over every element)
must find them along the load path. The linear split must not change the solution, and
ECSW's sampled elements must keep it close.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.reduce.ecsw import ecsw
from hapticrom.offline.reduce.ecsw_indicator import enriched_basis, error_indicator
from hapticrom.offline.reduce.ecsw_model import (
    HyperReducedModel,
    ModifiedNewton,
    condensed_internal_force,
    group_nodes,
    mesh_elements,
    modal_derivatives,
    rest_operators,
    rest_tangents,
    supremizers,
    training_matrix,
)
from hapticrom.online import element_kernels as ek
from hapticrom.online import material_kernels as mk
from hapticrom.online.haptic_newton import HapticNewton
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

CAMPAIGN = """
[campaign]
name = "ecsw-model"
[mesh]
file = "{mesh}"
[material]
law = "hgo"
[load]
mode = "force"
magnitude = 0.02
direction = "normal"
contact_radius = 0.6
steps = 4
[solver]  # the full order solved tighter than the campaigns' default (snes_atol 1e-10 N)
petsc_options = {{ snes_rtol = 1e-12, snes_atol = 1e-15, snes_stol = 1e-14 }}
[positions]
points = [[0.0, 0.0, 0.0], [1.0, 0.5, 0.0]]
"""


@pytest.fixture(scope="module")
def campaign(mesh_dir, tmp_path_factory):
    root = tmp_path_factory.mktemp("ecsw-model")
    path = root / "campaign.toml"
    path.write_text(CAMPAIGN.format(mesh=mesh_dir / "cornea-coarse.msh"))
    config = CampaignConfig.from_toml(path)
    run_campaign(config, root / "store", verbose=False)
    store = SnapshotStore(root / "store")
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    return store, mesh, rest_tangents(mesh)


def position(store, index):
    data, _ = store.read_position(index)
    return data["displacement"], data["pressure"], data["load_vector"], data["load_factor"]


def spanning_bases(U, P):
    """Orthonormal bases of the states' own span: the states are exact in them."""
    return np.linalg.qr(U.T)[0], np.linalg.qr(P.T)[0]


@pytest.mark.parametrize("split", [True, False])
def test_reduced_newton_finds_the_full_order_states(campaign, split):
    store, mesh, rest = campaign
    U, P, f, factors = position(store, 1)
    Phi, Psi = spanning_bases(U, P)
    model = HyperReducedModel(mesh, Phi, Psi, split=split, rest=rest)
    Q, Pi, iterations = model.solve(Phi.T @ f, factors, tolerance=1e-12)
    u_error = np.linalg.norm(Q @ Phi.T - U, axis=1) / np.linalg.norm(U, axis=1)
    p_error = np.linalg.norm(Pi @ Psi.T - P, axis=1) / np.linalg.norm(P, axis=1)
    # the full order's own Newton tolerance bounds how well its states solve these equations
    assert u_error.max() <= 1e-8, u_error
    assert p_error.max() <= 1e-8, p_error
    assert max(iterations) <= 8  # quadratic convergence from the previous step


def test_sampled_model_stays_close(campaign):
    """ECSW on the sampled contributions at both positions' states (tolerance 1e-4): the
    sampled model's load path within 1 % of the Galerkin model's on all the elements, and
    of the full order's, with fewer elements."""
    store, mesh, rest = campaign
    states = [position(store, i) for i in store.completed()]
    U_all = np.vstack([s[0] for s in states])
    Phi, Psi = spanning_bases(U_all, np.vstack([s[1] for s in states]))
    reduced = [(Phi.T @ u, Psi.T @ p) for U, P, _, _ in states for u, p in zip(U, P, strict=True)]
    G, _ = training_matrix(mesh, Phi, Psi, reduced, rest=rest)
    assert G.shape == (len(reduced) * (Phi.shape[1] + Psi.shape[1]), len(mesh.X))
    sampling = ecsw(G, tolerance=1e-4)
    assert len(sampling.elements) < 0.25 * len(mesh.X)  # 50 of 264 when written
    full = HyperReducedModel(mesh, Phi, Psi, rest=rest)
    sampled = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights, rest=rest)
    U, _, f, factors = states[0]
    reference = full.solve(Phi.T @ f, factors)[0] @ Phi.T
    got = sampled.solve(Phi.T @ f, factors)[0] @ Phi.T
    assert np.linalg.norm(got - reference) <= 1e-2 * np.linalg.norm(reference)
    assert np.linalg.norm(got - U) <= 1e-2 * np.linalg.norm(U)


def sampled_on_both(campaign):
    """ECSW at 1e-4 on both positions' own states (as test_sampled_model_stays_close):
    the sampled model, its bases, and position 0's load path."""
    store, mesh, rest = campaign
    states = [position(store, i) for i in store.completed()]
    Phi, Psi = spanning_bases(np.vstack([s[0] for s in states]), np.vstack([s[1] for s in states]))
    reduced = [(Phi.T @ u, Psi.T @ p) for U, P, _, _ in states for u, p in zip(U, P, strict=True)]
    sampling = ecsw(training_matrix(mesh, Phi, Psi, reduced, rest=rest)[0], tolerance=1e-4)
    model = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights, rest=rest)
    return model, Phi, states[0]


def test_tangent_slices_sum_to_the_tangent(campaign):
    """The linear part and the sampled tangent over consecutive parts of the sample add up
    to the model's tangent; the residual alone is the residual of the residual and tangent."""
    model, Phi, (U, P, f, _) = sampled_on_both(campaign)
    q, pi, load = Phi.T @ U[-1], np.full(model.n_p, 0.01), Phi.T @ f
    r, K = model.residual_tangent(q, pi, load)
    bounds = [0, 1, model.sampled_elements // 2, model.sampled_elements]
    summed = model.linear_tangent()
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        summed += model.sampled_tangent(q, pi, slice(a, b))
    np.testing.assert_allclose(summed, K, rtol=0, atol=1e-12 * np.abs(K).max())
    np.testing.assert_allclose(model.residual(q, pi, load), r, rtol=0,
                               atol=1e-12 * np.abs(r).max())  # fmt: skip
    assert np.abs(K - model.linear_tangent()).max() > 1e-3 * np.abs(K).max()  # nonlinear here


def test_split_model_is_the_sampled_nonlinear_terms_plus_the_exact_linear_part(campaign):
    """The model sums whole element terms and subtracts the sample's weighted share of the
    linear matrices in the reduced space (online/hyperreduced.py's doc): its residual and
    tangent are, to rounding, the per-element formulas: L_uu q + L_up pi + sum_e w_e
    Phi_e^T (r_u - K0 u - k0 p) - f and L_up^T q - M pi + sum_e w_e Psi_e (Theta - k0 . u),
    assembled here in numpy over the element kernel (which maps its own points), with
    random weights on 40 random elements; without the split, the plain weighted sums."""
    store, mesh, rest = campaign
    U, P, f, _ = position(store, 0)
    Phi, Psi = spanning_bases(U, P)
    rng = np.random.default_rng(20261124)
    elements = rng.choice(len(mesh.X), 40, replace=False)
    weights = rng.uniform(0.5, 3.0, 40)
    q, pi, load = Phi.T @ U[-1], Psi.T @ P[-1] + 0.01, Phi.T @ f
    K0, k0, volumes = rest
    n, n_p = Phi.shape[1], Psi.shape[1]
    M = np.einsum("e,ek,el->kl", volumes / mesh.params[:, mk.KAPPA], Psi[mesh.cell], Psi[mesh.cell])
    L_uu = np.einsum("emi,emk,ekj->ij", Phi[mesh.rows], K0, Phi[mesh.rows])
    L_up = np.einsum("emi,em,ek->ik", Phi[mesh.rows], k0, Psi[mesh.cell])
    for split in (True, False):
        r_ref, K_ref = np.zeros(n + n_p), np.zeros((n + n_p, n + n_p))
        r_ref[:n] = L_uu @ q + L_up @ pi - load if split else -load
        r_ref[n:] = L_up.T @ q - M @ pi if split else -M @ pi
        magnitude = np.abs(r_ref) + np.abs(np.concatenate([load, M @ pi]))  # of the terms
        K_ref[:n, :n], K_ref[:n, n:] = (L_uu, L_up) if split else (0.0, 0.0)
        K_ref[n:, :n], K_ref[n:, n:] = K_ref[:n, n:].T, -M
        for e, w in zip(elements, weights, strict=True):
            Phi_e, Psi_e = Phi[mesh.rows[e]], Psi[mesh.cell[e]]
            u, p = Phi_e @ q, Psi_e @ pi
            m = len(u)
            r_u, K_uu, K_up, scalars = np.empty(m), np.empty((m, m)), np.empty(m), np.empty(4)
            ek.element_residual_tangent(mesh.X[e], u.reshape(-1, 3), p, mesh.params[e],
                                        mesh.reference.gradients, mesh.reference.weights, r_u,
                                        K_uu, K_up, scalars)  # fmt: skip
            kappa = mesh.params[e, mk.KAPPA]
            Theta = scalars[ek.PRESSURE_RESIDUAL] + p * scalars[ek.VOLUME] / kappa
            K0_e, k0_e = (K0[e], k0[e]) if split else (0.0 * K_uu, 0.0 * K_up)
            r_ref[:n] += w * Phi_e.T @ (r_u - K0_e @ u - k0_e * p)
            r_ref[n:] += w * Psi_e * (Theta - k0_e @ u)
            magnitude[:n] += w * np.abs(Phi_e.T @ r_u)
            magnitude[n:] += w * np.abs(Psi_e) * scalars[ek.VOLUME]  # J's scale, not ln J's
            K_ref[:n, :n] += w * Phi_e.T @ (K_uu - K0_e) @ Phi_e
            block = w * np.outer(Phi_e.T @ (K_up - k0_e), Psi_e)
            K_ref[:n, n:] += block
            K_ref[n:, :n] += block.T
        model = HyperReducedModel(mesh, Phi, Psi, elements, weights, split=split, rest=rest)
        r, K = model.residual_tangent(q, pi, load)
        # N and mm^3 rows apart, each to 1e-12 of the sum of its terms' sizes. Theta is the
        # integral of ln J with J within about 1e-6 of 1 (kappa 2e5 MPa): its rounding is
        # J's, eps V_e, so the pi rows are held to the sizes of Psi_e V_e
        for rows in (slice(0, n), slice(n, None)):
            scale = magnitude[rows].max()
            np.testing.assert_allclose(r[rows], r_ref[rows], rtol=0, atol=1e-12 * scale)
            scale = np.abs(K_ref[rows]).max()
            np.testing.assert_allclose(K[rows], K_ref[rows], rtol=0, atol=1e-12 * scale)
    # not trivially: the split model differs from the unsplit one at this sample
    unsplit = HyperReducedModel(mesh, Phi, Psi, elements, weights, split=False, rest=rest)
    split_model = HyperReducedModel(mesh, Phi, Psi, elements, weights, rest=rest)
    a, b = unsplit.residual(q, pi, load), split_model.residual(q, pi, load)
    assert np.abs(a - b)[n:].max() > 1e-3 * np.abs(b[n:]).max()


def test_sampled_sums_carry_a_nan(campaign):
    """No fastmath flag assumes finite numbers: a NaN in the state reaches the residual and
    the tangent (the Newtons refuse such a step)."""
    model, Phi, (U, _, f, _) = sampled_on_both(campaign)
    q = Phi.T @ U[-1]
    q[0] = np.nan
    r, K = model.residual_tangent(q, np.zeros(model.n_p), Phi.T @ f)
    assert np.isnan(r[: model.n]).all() and np.isnan(K[: model.n, : model.n]).any()
    assert np.isnan(model.residual(q, np.zeros(model.n_p), Phi.T @ f)).any()


def test_modified_newton_frames_reach_newtons_states(campaign):
    """Frames of a tenth of a load step each, the residual alone with an earlier tangent:
    at each stored load factor the state of the model's Newton, with fewer tangents than
    half the frames (18 of 40 when written: 6-12 iterations a frame)."""
    model, Phi, (_, _, f, factors) = sampled_on_both(campaign)
    load = Phi.T @ f
    Q = model.solve(load, factors, tolerance=1e-12)[0]
    newton = ModifiedNewton(model, tolerance=1e-9, refresh_after=10)
    q, pi = np.zeros(model.n), np.zeros(model.n_p)
    frames = np.linspace(0.0, factors[-1], 10 * len(factors) + 1)[1:]
    for k, factor in enumerate(frames):
        assert newton.frame(q, pi, factor * load) is not None, factor
        if (k + 1) % 10 == 0:
            expected = Q[k // 10]
            assert np.linalg.norm(q - expected) <= 1e-8 * np.linalg.norm(expected), factor
    assert newton.tangents < len(frames) / 2 and newton.residuals > len(frames), newton.tangents
    with pytest.raises(InputError, match="at least 1"):
        ModifiedNewton(model, refresh_after=0)


def test_haptic_steps_settle_on_the_equilibrium(campaign):
    """Fixed-cost steps (one modified iteration, the tangent built over three steps) along
    a ramp lag the equilibrium, and settle on the model's own once the load holds."""
    model, Phi, (_, _, f, factors) = sampled_on_both(campaign)
    load = Phi.T @ f
    expected = model.solve(load, factors, tolerance=1e-12)[0][-1]
    haptic = HapticNewton(model.sample, model.linear, iterations=1, slices=3)
    q, pi = np.zeros(model.n), np.zeros(model.n_p)
    for factor in np.linspace(0.0, factors[-1], 41)[1:]:
        haptic.step(q, pi, factor * load)
    lag = np.linalg.norm(q - expected) / np.linalg.norm(expected)
    for _ in range(60):
        haptic.step(q, pi, factors[-1] * load)
    settled = np.linalg.norm(q - expected) / np.linalg.norm(expected)
    assert settled <= 1e-9 < lag, (lag, settled)
    assert haptic.last_update <= 1e-9


def test_newtons_refuse_a_step_that_leaves_the_finite_numbers(campaign):
    """A load that is not finite: the step says so, and the state and the kept tangent are
    as they were (the haptic loop keeps its last good state)."""
    model, Phi, (_, _, f, _) = sampled_on_both(campaign)
    q, pi = np.zeros(model.n), np.zeros(model.n_p)
    bad = np.full(model.n, np.nan)
    haptic = HapticNewton(model.sample, model.linear, iterations=1, slices=2)
    assert haptic.step(q, pi, 0.1 * (Phi.T @ f))
    q0, pi0, part, building = q.copy(), pi.copy(), haptic.part, haptic.building.copy()
    lu, pivots = haptic.lu.copy(), haptic.pivots.copy()
    assert not haptic.step(q, pi, bad)
    assert np.array_equal(q, q0) and np.array_equal(pi, pi0)
    assert haptic.part == part and np.array_equal(haptic.building, building)
    assert np.array_equal(haptic.lu, lu) and np.array_equal(haptic.pivots, pivots)
    newton = ModifiedNewton(model)
    assert newton.frame(q, pi, 0.1 * (Phi.T @ f)) is not None
    q0, factors = q.copy(), newton.factors
    assert newton.frame(q, pi, bad) is None
    assert np.array_equal(q, q0) and newton.factors is factors
    with pytest.raises(InputError, match="slices"):
        HapticNewton(model.sample, model.linear, slices=model.sampled_elements + 1)


def test_training_columns_sum_to_the_model(campaign):
    """Each column of G is one element's term: G 1 (unscaled) is the sampled sum of the
    model on every element, at each state."""
    store, mesh, rest = campaign
    U, P, _, _ = position(store, 0)
    Phi, Psi = spanning_bases(U, P)
    q, pi = Phi.T @ U[-1], Psi.T @ P[-1]
    G, scale = training_matrix(mesh, Phi, Psi, [(q, pi)], rest=rest)
    full = HyperReducedModel(mesh, Phi, Psi, rest=rest)
    r, _ = full.residual_tangent(q, pi, np.zeros(full.n))
    n = full.n
    linear = np.concatenate([full.L_uu @ q + full.L_up @ pi, full.L_up.T @ q - full.M @ pi])
    np.testing.assert_allclose(G.sum(axis=1) / scale, r - linear, rtol=1e-11,
                               atol=1e-13 * np.abs(r - linear).max())  # fmt: skip
    assert np.abs((r - linear)[:n]).max() > 0 and np.abs((r - linear)[n:]).max() > 0


def test_refuses_bad_samplings(campaign):
    store, mesh, rest = campaign
    U, P, _, _ = position(store, 0)
    Phi, Psi = spanning_bases(U, P)
    for elements, weights in (([0, 1], [1.0]), ([0], [0.0]), ([0], [-1.0])):
        with pytest.raises(InputError, match="positive weight"):
            HyperReducedModel(mesh, Phi, Psi, elements, weights, rest=rest)
    for elements in ([len(mesh.X)], [-1]):
        with pytest.raises(InputError, match="indices of the mesh"):
            HyperReducedModel(mesh, Phi, Psi, elements, [1.0], rest=rest)
    with pytest.raises(InputError, match="listed twice"):
        HyperReducedModel(mesh, Phi, Psi, [3, 3], [1.0, 1.0], rest=rest)


def test_rest_operators_are_the_models_linear_part(campaign):
    """The assembled rest operators projected on the bases are the model's exact linear
    matrices; the condensed stiffness is A + Bt C^-1 Bt^T; supremizers solve A s = Bt psi
    on the free rows."""
    store, mesh, rest = campaign
    U, P, _, _ = position(store, 0)
    Phi, Psi = spanning_bases(U, P)
    model = HyperReducedModel(mesh, Phi, Psi, rest=rest)
    operators = rest_operators(mesh, rest)
    close = dict(rtol=1e-12, atol=0)
    np.testing.assert_allclose(Phi.T @ (operators.A @ Phi), model.L_uu,
                               atol=1e-12 * np.abs(model.L_uu).max(), rtol=0)  # fmt: skip
    np.testing.assert_allclose(Phi.T @ (operators.Bt @ Psi), model.L_up,
                               atol=1e-12 * np.abs(model.L_up).max(), rtol=0)  # fmt: skip
    np.testing.assert_allclose(Psi.T @ (operators.compliance[:, None] * Psi), model.M, **close)
    x = np.random.default_rng(3).standard_normal(operators.A.shape[0])
    Bx = operators.Bt.T @ x
    expected = operators.A @ x + operators.Bt @ (Bx / operators.compliance)
    np.testing.assert_allclose(operators.condensed() @ x, expected, rtol=1e-12,
                               atol=1e-12 * np.abs(expected).max())  # fmt: skip
    free = np.flatnonzero(np.abs(U).max(axis=0) > 0)
    S = supremizers(operators, Psi, free)
    residual = (operators.A @ S - operators.Bt @ Psi)[free]
    assert np.abs(residual).max() <= 1e-9 * np.abs(operators.Bt @ Psi).max()
    fixed = np.setdiff1d(np.arange(len(S)), free)
    assert np.all(S[fixed] == 0.0)


def test_group_nodes_hold_the_tool_loads(campaign, mesh_dir):
    """The loadable group's nodes (canonical numbering, coordinates) carry every stored
    tool load, and their coordinates are the elements' own."""
    store, mesh, _ = campaign
    nodes, xyz = group_nodes(mesh_dir / "cornea-coarse.msh", "loadable")
    for i in store.completed():
        f = position(store, i)[2].reshape(-1, 3)
        loaded = np.flatnonzero(np.abs(f).max(axis=1) > 0)
        assert loaded.size and np.isin(loaded, nodes).all()
    element_xyz = np.zeros((int(mesh.rows.max()) // 3 + 1, 3))
    element_xyz[mesh.rows[:, ::3].ravel() // 3] = mesh.X.reshape(-1, 3)
    np.testing.assert_allclose(xyz, element_xyz[nodes], rtol=0, atol=1e-12)
    assert len(nodes) < len(element_xyz)  # a surface group, not the whole mesh


def test_condensed_internal_force_is_the_full_orders(campaign):
    """At the full order's states (DOLFINx, mixed u-p) the condensed internal force equals
    the tool's load on every free row: the condensation p = kappa Theta / V is the full
    order's own pressure."""
    store, mesh, _ = campaign
    U, _, f, factors = position(store, 1)
    free = np.flatnonzero(np.abs(U).max(axis=0) > 0)
    for u, factor in zip(U, factors, strict=True):
        internal = condensed_internal_force(mesh, u)
        load = factor * f
        # the full order stops at its own tolerances (snes_stol 1e-14 on u here), which
        # kappa = 2/D turns into force through the pressure: measured 1.2e-8 of the load
        assert np.abs(internal[free] - load[free]).max() <= 1e-7 * np.abs(load).max()


def condensed_tangent_times(mesh, u, a):
    """K_c(u) a from the tangent kernel: K_uu + K_up K_up^T / (V / kappa) per element, at
    the condensed pressure (a second path to the force's derivatives)."""
    ref, out = mesh.reference, np.zeros(u.size)
    m = mesh.rows.shape[1]
    r, K, k, s = np.empty(m), np.empty((m, m)), np.empty(m), np.empty(4)
    for e in range(len(mesh.X)):
        rows = mesh.rows[e]
        u_e = np.ascontiguousarray(u[rows].reshape(-1, 3))
        args = (mesh.X[e], u_e)
        ek.element_residual(*args, 0.0, mesh.params[e], ref.gradients, ref.weights, r, s)
        p = mesh.params[e, mk.KAPPA] * s[ek.PRESSURE_RESIDUAL] / s[ek.VOLUME]
        ek.element_residual_tangent(*args, p, mesh.params[e], ref.gradients, ref.weights,
                                    r, K, k, s)  # fmt: skip
        out[rows] += K @ a[rows] + k * (k @ a[rows]) / -s[ek.PRESSURE_STIFFNESS]
    return out


def test_modal_derivatives_are_the_tangents_derivative(campaign):
    """-D^2 f[a, b] (modal_derivatives with the identity for K^-1) against the central
    difference of the tangent kernel's K_c(t b) a in t: two paths to the same third
    derivative of the energy."""
    store, mesh, _ = campaign
    U, _, _, _ = position(store, 0)
    Phi = np.linalg.qr(U[[1, 3]].T)[0]  # two directions of the organ's own response
    derivatives = modal_derivatives(mesh, Phi, lambda x: x, size=5e-3)
    assert derivatives.shape == (U.shape[1], 3)  # (0, 0), (0, 1), (1, 1)
    scale = 5e-3 / np.abs(Phi).max()
    a, b = scale * Phi[:, 0], scale * Phi[:, 1]
    t = 1e-3
    zero = np.zeros_like(a)
    tangent = (condensed_tangent_times(mesh, zero + t * b, a)
               - condensed_tangent_times(mesh, zero - t * b, a)) / (2 * t)  # fmt: skip
    expected = -tangent / scale**2
    got = derivatives[:, 1]
    assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max()


def linear_solution(campaign, scale=1e-6):
    """The full order's solution in the linear range (element-condensed rest stiffness,
    exact for one pressure a cell) under position 0's load times ``scale``: (u, p, f)."""
    store, mesh, rest = campaign
    U, _, f, _ = position(store, 0)
    operators = rest_operators(mesh, rest)
    free = np.flatnonzero(np.abs(U).max(axis=0) > 0)
    K = operators.condensed()[free][:, free].tocsc()
    u = np.zeros(len(f))
    u[free] = scipy.sparse.linalg.spsolve(K, scale * f[free])
    return u, operators.Bt.T @ u / operators.compliance, scale * f


@pytest.mark.parametrize("phi_holds", [True, False])
def test_indicator_is_the_error_when_the_enriched_basis_holds_the_solution(campaign, phi_holds):
    """In the linear range (1e-5 of the campaign's load), every element integrated, the
    enriched space holding the full order's (u*, p*): eta is the true error
    ||u* - Phi q|| / ||Phi q|| (a Newton step in W lands on the Galerkin solution in W,
    which is u*), at the state's tangent and at rest; with Phi holding u* too, eta is the
    nonlinearity's share alone (2e-6 when written)."""
    store, mesh, rest = campaign
    u, p, f = linear_solution(campaign, 1e-5)
    U1 = position(store, 1)[0]
    Phi = np.linalg.qr((np.vstack([U1, u]) if phi_holds else U1).T)[0]
    Psi = np.linalg.qr(np.vstack([position(store, 0)[1], p]).T)[0]
    model = HyperReducedModel(mesh, Phi, Psi, rest=rest)
    q, pi, _ = model.solve(Phi.T @ f, [1.0])
    error = np.linalg.norm(u - Phi @ q[0]) / np.linalg.norm(Phi @ q[0])
    for at_state in (True, False):
        indicator = error_indicator(mesh, Phi, Psi, u[:, None], rest=rest, at_state=at_state)
        assert indicator.basis.shape[1] == Phi.shape[1] + (0 if phi_holds else 1)
        eta = indicator.estimate(q[0], pi[0], indicator.basis.T @ f)
        if phi_holds:
            assert error < 1e-5 and eta < 1e-5
        else:
            assert error > 0.1  # the test means something: Phi misses most of u*
            assert abs(eta / error - 1.0) < 1e-5


@pytest.mark.parametrize("order", ["in-span last", "in-span first", "repeated"])
def test_enriched_basis_keeps_phi_and_drops_its_span(order):
    """W starts with Phi itself, is orthonormal, spans every enrichment column, and a
    direction already in Phi's span (or a repeated column), wherever it stands, adds
    nothing."""
    rng = np.random.default_rng(5)
    Phi = np.linalg.qr(rng.standard_normal((60, 4)))[0]
    a, b = rng.standard_normal((60, 1)), rng.standard_normal((60, 1))
    inside = Phi @ rng.standard_normal((4, 1))
    columns = {"in-span last": [a, b, inside], "in-span first": [inside, a, b],
               "repeated": [a, a, b]}[order]  # fmt: skip
    extra = np.hstack(columns)
    W = enriched_basis(Phi, extra)
    assert W.shape == (60, 6)
    assert np.array_equal(W[:, :4], Phi)
    np.testing.assert_allclose(W.T @ W, np.eye(6), atol=1e-13)
    assert np.linalg.norm(extra - W @ (W.T @ extra)) <= 1e-12 * np.linalg.norm(extra)


def test_sampled_indicator_reads_the_error(campaign):
    """Along position 0's path with a basis of position 1's states and position 0's first
    three (errors 0.3-2.6 %), W adding position 0's last: eta at the state's tangent within
    a factor of two of the true error at every step, on every element and on a second
    sample at 1e-4 (effectivities 0.86-1.05 and 0.97-1.05 when written); an excluded second
    sample has none of the model's elements."""
    store, mesh, rest = campaign
    U0, P0, f, factors = position(store, 0)
    U1, P1, _, _ = position(store, 1)
    Phi = np.linalg.qr(np.vstack([U1, U0[:3]]).T)[0]
    Psi = np.linalg.qr(np.vstack([P0, P1]).T)[0]
    pairs = ((U0, P0), (U1, P1))
    states = [(Phi.T @ u, Psi.T @ p) for U, P in pairs for u, p in zip(U, P, strict=True)]
    sampling = ecsw(training_matrix(mesh, Phi, Psi, states, rest=rest)[0], tolerance=1e-3)
    model = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights, rest=rest)
    whole = error_indicator(mesh, Phi, Psi, U0.T, rest=rest)
    sampled = error_indicator(mesh, Phi, Psi, U0.T, states, 1e-4, rest=rest)
    assert sampled.enriched.sampled_elements < len(mesh.X) // 2
    Q, Pi, _ = model.solve(Phi.T @ f, factors)
    for q, pi, c, u in zip(Q, Pi, factors, U0, strict=True):
        error = np.linalg.norm(Phi @ q - u) / np.linalg.norm(Phi @ q)
        for indicator in (whole, sampled):
            eta = indicator.estimate(q, pi, c * (indicator.basis.T @ f))
            assert 0.5 < eta / error < 2.0, (c, eta, error)
    apart = error_indicator(mesh, Phi, Psi, U0.T, states, 1e-4, sampling.elements, rest=rest)
    assert not set(apart.enriched.elements) & set(sampling.elements)
    assert 0.0 <= apart.fit < 1.0
    assert np.isfinite(apart.estimate(Q[-1], Pi[-1], factors[-1] * (apart.basis.T @ f)))
    with pytest.raises(InputError, match="states must be on Phi"):
        error_indicator(mesh, Phi, Psi, U0.T, [(q[:-1], pi) for q, pi in states], rest=rest)
