"""POD-ANM (thesis ch. 3): generic Taylor coefficients of the UFL residual, and the series.

References independent of the ANM code: the real residual forms of the Newton
solver, finite differences of the residual, exact polynomial structure (SVK is
cubic in the displacement), the analytic uniaxial solution of the beam, and
the full-order Newton solution.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from dolfinx import fem
from dolfinx.la import InsertMode
from test_beam import LENGTH, TRACTION, analytic_stretches, beam_config

from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.reduce.anm import (
    ANMOptions,
    ComplexResidual,
    ReducedResidual,
    continuation,
)
from hapticrom.offline.studies.anm import reduced_space, run_study, solve_with_snapshots
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
ROOT = Path(__file__).resolve().parents[1]


def cornea_config(mesh_dir, law="hgo", steps=6, **material) -> ProblemConfig:
    d = tomllib.loads((ROOT / "examples" / "cornea-hgo-indent.toml").read_text())
    d["mesh"]["file"] = str(mesh_dir / "cornea-coarse.msh")
    d["load"]["steps"] = steps
    if law != "hgo":
        d["material"] = {"law": law, "E": 0.5, "nu": 0.49}
    d["material"].update(material)
    return ProblemConfig.from_dict(d)


@pytest.fixture(scope="module")
def cornea(mesh_dir):
    fom = FullOrderModel(cornea_config(mesh_dir), verbose=False)
    snaps = solve_with_snapshots(fom)
    space, scale = reduced_space(fom, snaps)
    return fom, snaps, ReducedResidual(ComplexResidual(fom.model), space, fom.comm), scale


def _real_residual(fom, u_owned, p_owned):
    """The Newton solver's own (real) residual forms at the given state."""
    model = fom.model
    for w, values in zip(model.unknowns, (u_owned, p_owned), strict=False):
        w.x.array[: values.size] = values
        w.x.scatter_forward()
    out = []
    for form, w in zip(model.residual_forms(include_load=False), model.unknowns, strict=True):
        b = fem.assemble_vector(fem.form(form))
        b.scatter_reverse(InsertMode.add)
        out.append(b.array[: w.x.index_map.size_local * w.x.block_size].copy())
    return out


def test_complex_residual_equals_the_real_residual_at_real_states(cornea):
    fom, snaps, r, _ = cornea
    u, p = 1.1 * snaps.u[:, -1], 0.5 * snaps.p[:, -1]  # not an equilibrium: R != 0
    Ru, Rp = r.residual(u.astype(complex), p.astype(complex))
    Ru_real, Rp_real = _real_residual(fom, u, p)
    assert np.abs(Ru.imag).max() <= 1e-12 * np.abs(Ru_real).max()
    np.testing.assert_allclose(Ru.real, Ru_real, rtol=0, atol=1e-12 * np.abs(Ru_real).max())
    np.testing.assert_allclose(Rp.real, Rp_real, rtol=0, atol=1e-12 * np.abs(Rp_real).max())


def test_taylor_coefficients_match_finite_differences(cornea):
    """Coefficients 1 and 2 of r along a quadratic path, vs central differences of r."""
    _, _, r, _ = cornea
    rng = np.random.default_rng(1)
    y0 = np.zeros(r.size)
    y0[-1] = 0.4  # a strained state: 0.2 mm of indentation
    Y = np.array([y0, 0.05 * rng.standard_normal(r.size), 0.02 * rng.standard_normal(r.size)])
    c = r.taylor(Y, 4, rho=0.2)

    def at(a):
        return r(Y[0] + a * Y[1] + a**2 * Y[2]).real

    h = 1e-3
    d1 = (at(h) - at(-h)) / (2 * h)
    d2 = (at(h) - 2 * at(0.0) + at(-h)) / h**2
    # Richardson: eliminate the O(h^2) error of both differences.
    d1_half = (at(h / 2) - at(-h / 2)) / h
    d2_half = (at(h / 2) - 2 * at(0.0) + at(-h / 2)) / (h / 2) ** 2
    d1 = (4 * d1_half - d1) / 3
    d2 = (4 * d2_half - d2) / 3
    scale = np.abs(c[1]).max()
    np.testing.assert_allclose(c[0], at(0.0), rtol=0, atol=1e-10 * np.abs(at(0.0)).max())
    np.testing.assert_allclose(c[1], d1, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(c[2], d2 / 2, rtol=0, atol=1e-5 * np.abs(c[2]).max())
    # A mutation check: the coefficients of another path differ.
    assert np.abs(r.taylor(Y * [[1], [1], [1.1]], 2, rho=0.2)[2] - c[2]).max() > 1e-3 * scale


def test_taylor_coefficients_of_a_cubic_energy_are_exact(mesh_dir):
    """SVK: the residual is cubic in u, so along a linear path it is a cubic in a."""
    fom = FullOrderModel(cornea_config(mesh_dir, law="svk", steps=2), verbose=False)
    snaps = solve_with_snapshots(fom)
    space, _ = reduced_space(fom, snaps)
    r = ReducedResidual(ComplexResidual(fom.model), space, fom.comm)
    rng = np.random.default_rng(2)
    Y = np.array([np.zeros(r.size), rng.standard_normal(r.size)])
    Y[1, space.n : -1] *= 0.1  # pressure modes, MPa
    c = r.taylor(Y, 6, rho=0.3)
    scale = np.abs(c).max()
    assert np.abs(c[4:]).max() <= 1e-11 * scale  # nothing above the cubic
    assert np.abs(c[3]).max() >= 1e-6 * scale  # but a cubic term (mutation guard)
    for a in (0.7, -1.3):  # outside the circle too: the cubic is entire
        exact = r(Y[0] + a * Y[1]).real
        series = sum(c[k] * a**k for k in range(4))
        np.testing.assert_allclose(series, exact, rtol=0, atol=1e-10 * np.abs(exact).max())


def test_tangent_by_complex_step_matches_finite_differences(cornea):
    _, _, r, _ = cornea
    y0 = np.zeros(r.size)
    y0[-1] = 0.6
    J = r.jacobian(y0)
    for j in range(r.size):
        e = np.zeros(r.size)
        e[j] = h = 1e-6
        fd = (r(y0 + e).real - r(y0 - e).real) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=0, atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize("law", ["svk", "neo-hookean"])
def test_beam_anm_rom_matches_the_analytic_stretch(mesh_dir, law):
    """Thesis Figs. 3.3-3.4: axial stretch of the ANM-ROM vs analytic, load factor 0 to 1."""
    fom = FullOrderModel(beam_config(mesh_dir, law), verbose=False)
    result = run_study(fom, ANMOptions(order=6, tolerance=1e-4), verbose=False)
    branch = result.branch
    assert branch.load_range[1] >= 1.0
    for lam in np.linspace(0.05, 1.0, 20):
        stretch = 1 + branch.response_at(lam) / LENGTH
        exact = analytic_stretches(law, lam * TRACTION)[0]
        assert abs(stretch - exact) / exact <= 5e-3  # the bound
        # and at the level of the validity tolerance (measured: 1.4e-5 at worst)
        assert abs(stretch - exact) / exact <= 1e-4, (lam, stretch, exact)
    # Order 1 alone is the linear model: visibly wrong at load factor 1 (large strain).
    linear = continuation(
        ReducedResidual(ComplexResidual(fom.model), *reduced_space(fom, result.reference)[:1],
                        fom.comm),
        reduced_space(fom, result.reference)[1],
        ANMOptions(order=1),
    )  # fmt: skip
    exact = analytic_stretches(law, TRACTION)[0]
    assert abs(1 + linear.response_at(1.0) / LENGTH - exact) / exact > 0.02


def test_cornea_anm_follows_full_newton_with_hgo(cornea):
    """Displacement control, HGO: the continuation reproduces the Newton reaction force."""
    fom, snaps, r, scale = cornea
    branch = continuation(r, scale, ANMOptions(order=6, tolerance=1e-4))
    assert branch.load_range[1] >= 1.0
    force = np.array([branch.response_at(lam) for lam in snaps.load_factor])
    np.testing.assert_allclose(force, snaps.response, rtol=1e-3)
    # Within each section, the series' validity radius keeps the residual small.
    for s in branch.sections:
        res = r(s.state(s.a_max)).real[: r.size - 1]
        assert np.linalg.norm(res) <= 1e-3 * np.linalg.norm(r.jacobian(s.Y[0])[: r.size - 1, -1])


def test_tension_only_fibres_are_refused(mesh_dir):
    fom = FullOrderModel(cornea_config(mesh_dir, fibre_tension_only=True, steps=2), verbose=False)
    with pytest.raises(InputError, match="analytic"):
        ComplexResidual(fom.model)


def test_campaign_anm_table_is_validated_and_not_part_of_the_campaign_identity(mesh_dir):
    import tomllib as toml

    from conftest import campaign_toml

    from hapticrom.offline.campaign.run import CampaignConfig

    base = toml.loads(campaign_toml(mesh_dir / "cornea-coarse.msh"))
    config = CampaignConfig.from_dict(base)
    assert config.anm.enabled and config.anm.order == 6
    tuned = CampaignConfig.from_dict({**base, "anm": {"order": 10, "tolerance": 1e-5}})
    assert tuned.anm.order == 10
    assert tuned.campaign_hash() == config.campaign_hash()  # the solves are the same
    for bad in ({"order": 0}, {"order": 3.5}, {"tolerance": 2.0}, {"enabled": "yes"}, {"x": 1}):
        with pytest.raises(InputError, match="anm"):
            CampaignConfig.from_dict({**base, "anm": bad})


def test_force_controlled_campaign_gets_series_the_runtime_follows(mesh_dir, tmp_path):
    """A soft tip (force control): the artifact's series reproduce the full-order curves."""
    from conftest import campaign_toml

    import hapticrom.online as online
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.campaign.store import SnapshotStore
    from hapticrom.offline.reduce.reduction import reduce_campaign

    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=4, per_ring=3)
    text = text.replace('mode = "displacement"', 'mode = "force"').replace(
        "magnitude = 0.3", "magnitude = 0.01"
    )
    (tmp_path / "c.toml").write_text(text)
    config = CampaignConfig.from_toml(tmp_path / "c.toml")
    from mpi4py import MPI

    run_campaign(config, tmp_path / "store", MPI.COMM_SELF, verbose=False)
    reduce_campaign(tmp_path / "store", tmp_path / "m.h5", MPI.COMM_SELF, verbose=False)
    model = online.load(tmp_path / "m.h5")
    assert model.anm is not None
    sim = model.simulator(response="anm")
    store = SnapshotStore(tmp_path / "store")
    for i, point in enumerate(model.sample_points):
        data, attrs = store.read_position(i)
        sim.set_contact(point)
        direction = attrs["direction"]
        for k in range(len(data["force"])):
            depth = data["contact_displacement"][k] @ direction
            force = sim.step_displacement(-depth * sim.contact_normal) @ sim.contact_normal
            assert force == pytest.approx(data["force"][k] @ direction, rel=1e-3)
            push = sim.step_force(-(data["force"][k] @ direction) * sim.contact_normal)
            assert -push @ sim.contact_normal == pytest.approx(depth, rel=1e-3)


def test_order_ten_series(mesh_dir):
    """The issue asks for orders up to at least 10: same beam, one section of order 10."""
    fom = FullOrderModel(beam_config(mesh_dir, "neo-hookean"), verbose=False)
    result = run_study(fom, ANMOptions(order=10, tolerance=1e-6), verbose=False)
    assert result.branch.sections[0].order == 10
    for lam in (0.3, 0.7, 1.0):
        stretch = 1 + result.branch.response_at(lam) / LENGTH
        exact = analytic_stretches("neo-hookean", lam * TRACTION)[0]
        assert abs(stretch - exact) / exact <= 1e-4
