"""The full order's rigid sphere (``[load] mode = "sphere"``, offline/fe/sphere.py): the
contact force against the supports' reaction (global equilibrium), the overlap against
the penalty's bound, the force against the derivative of the contact energy, the
configuration's checks."""

from __future__ import annotations

import numpy as np
import pytest
from dolfinx import fem

from hapticrom.offline.config import LoadConfig, ProblemConfig
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

SOLVE = """
[mesh]
file = "{mesh}"
[material]
law = "hgo"
[load]
mode = "sphere"
contact_point = [0.0, 0.0, 0.0]
contact_radius = 0.6
sphere = [0.0, 0.0, -0.15]
steps = 3
"""


@pytest.fixture(scope="module")
def solved(mesh_dir, tmp_path_factory):
    from mpi4py import MPI

    from hapticrom.offline.fe.fullorder import FullOrderModel

    path = tmp_path_factory.mktemp("sphere") / "sphere.toml"
    path.write_text(SOLVE.format(mesh=mesh_dir / "cornea-coarse.msh"))
    fom = FullOrderModel(ProblemConfig.from_toml(path), MPI.COMM_SELF, verbose=False)
    result = fom.solve()
    return fom, result


def test_the_sphere_s_force_balances_the_supports(solved):
    """The supports hold what the sphere pushes: the internal forces summed over the
    supported nodes (assembled without the contact term) equal minus the pressure's
    integral, to the solver's tolerance. The push is along -z at the apex (frictionless,
    symmetric: no sideways force)."""
    from hapticrom.offline.fe.contact import ReactionForce

    fom, result = solved
    internal = fom.model.residual_forms(include_load=False)[0]
    supports = fom.organ.constrained_blocks(fom.model.V)
    reaction = ReactionForce(internal, fom.model.V, supports)()
    force = fom.sphere.force()
    np.testing.assert_allclose(result.force[-1], force)
    assert force[2] < 0 and abs(force[0]) + abs(force[1]) < 1e-6 * abs(force[2])
    np.testing.assert_allclose(reaction, -force, rtol=1e-5, atol=1e-9 * abs(force[2]))


def test_the_force_grows_with_the_depth_and_the_overlap_is_small(solved):
    fom, result = solved
    depth = -result.displacement[:, 2]
    push = -result.force[:, 2]
    assert np.all(np.diff(depth) > 0) and np.all(np.diff(push) > 0)
    # The overlap a pressure p leaves is sqrt(p / kappa): at the nodes in contact, between
    # that of the mean pressure over the contact area and twice it (a peak of 1.5 to 4
    # times the mean), and small against the depth: the sphere is nearly rigid.
    area = fom.sphere.contact_area()
    mean = np.sqrt(push[-1] / area / fom.config.load.penalty)
    x = fom.model.V.tabulate_dof_coordinates() + fom.model.u.x.array.reshape(-1, 3)
    overlap = fom.config.load.contact_radius - np.linalg.norm(x - fom.sphere.centre.value, axis=1)
    assert 0.5 * mean < overlap.max() < 2.0 * mean
    assert overlap.max() < 0.05 * depth[-1]


def test_the_force_is_the_derivative_of_the_contact_energy(solved):
    """f_i = -dPi_c/dc_i at the solved field (central differences of the assembled energy
    in the sphere's centre): the pressure's form and the energy's agree."""
    fom, _ = solved
    sphere = fom.sphere
    energy = fem.form(sphere.energy)
    centre = sphere.centre.value.copy()
    force = sphere.force()
    eps = 1e-6
    for i in range(3):
        values = []
        for sign in (1, -1):
            moved = centre.copy()
            moved[i] += sign * eps
            sphere.move(moved)
            values.append(fem.assemble_scalar(energy))
        sphere.move(centre)
        # The tissue is pushed away from the centre: moving the centre along +e_i raises
        # the energy where the tissue lies along +e_i.
        derivative = (values[0] - values[1]) / (2 * eps)
        np.testing.assert_allclose(derivative, force[i], rtol=1e-4, atol=1e-6 * abs(force[2]))


@pytest.mark.parametrize(
    "load,message",
    [
        ('mode = "sphere"\ncontact_radius = 0.5', "missing sphere"),
        ('mode = "sphere"\nsphere = [0, 0, -0.1]\npenalty = -1', "penalty"),
        ('mode = "displacement"\ndisplacement = [0, 0, -0.1]\npenalty = 1e4', "penalty is given"),
    ],
)
def test_a_bad_sphere_load_is_refused(tmp_path, load, message):
    path = tmp_path / "bad.toml"
    path.write_text(f'[mesh]\nfile = "x.msh"\n[material]\nlaw = "hgo"\n[load]\n{load}\n')
    with pytest.raises(InputError, match=message):
        ProblemConfig.from_toml(path)


def test_a_sphere_campaign_has_no_anm_and_a_penalty_only_with_the_sphere(tmp_path):
    from hapticrom.offline.campaign.config import CampaignConfig

    base = """[campaign]\nname = "s"\n[mesh]\nfile = "x.msh"\n[material]\nlaw = "hgo"
[load]\n{load}\n[positions]\npoints = [[0.0, 0.0, 0.0]]\n{anm}"""
    path = tmp_path / "c.toml"
    path.write_text(base.format(load='mode = "sphere"\nmagnitude = 0.3', anm=""))
    with pytest.raises(InputError, match=r"\[anm\] enabled = false"):
        CampaignConfig.from_toml(path)
    path.write_text(base.format(load='mode = "sphere"\nmagnitude = 0.3\npenalty = 1e5',
                                anm="[anm]\nenabled = false"))  # fmt: skip
    config = CampaignConfig.from_toml(path)
    assert config.load.penalty == 1e5
    load = config.load
    position = type("P", (), {"point": (0.0, 0.0, 0.0), "normal": (0.0, 0.0, 1.0)})()
    solve = load.at(position)
    assert isinstance(solve, LoadConfig) and solve.mode == "sphere" and solve.penalty == 1e5
    np.testing.assert_allclose(solve.sphere, [0.0, 0.0, -0.3])
    path.write_text(base.format(load='mode = "force"\nmagnitude = 0.3\npenalty = 1e5', anm=""))
    with pytest.raises(InputError, match="penalty is given"):
        CampaignConfig.from_toml(path)
