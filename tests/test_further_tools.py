"""Several force tools at once on the full order (issue 18's references: two instruments,
a pinch, an oblique press), on the coarse cornea.

The tools' dead loads add: the load vector of two tools is the sum of each alone's, to
round-off (overlapping disks included), and in the linear range the tissue's equilibrium
under both is the sum of each's. Beside a first tool under displacement control (one that
holds its patch: grasping forceps) they press as alone, and the holder's reaction opposes
them. A further tool that is not a force, or beside a sphere, is refused.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.positions import ToolPosition
from hapticrom.offline.campaign.run import solve_position
from hapticrom.offline.config import LoadConfig, ProblemConfig
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.fe.operators import load_vector
from hapticrom.offline.fe.organ import load_organ
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

APEX, SIDE = (0.0, 0.0, 0.0), (1.0, 0.5, 0.0)  # mm: on the coarse cornea's loadable cap


def problem(mesh_dir, point, force, tools=()) -> ProblemConfig:
    config = ProblemConfig.from_dict({
        "mesh": {"file": str(mesh_dir / "cornea-coarse.msh")},
        "material": {"law": "hgo"},
        "load": {"mode": "force", "force": list(force), "contact_point": list(point),
                 "contact_radius": 0.8, "steps": 3},
    })  # fmt: skip
    return replace(config, load=replace(config.load, tools=tuple(tools)))


def nodal_load(config) -> np.ndarray:
    """The load vector at factor 1 (N a DOF, canonical order)."""
    model = FullOrderModel(config, verbose=False)
    model.set_load(1.0)
    f = load_vector(model.model, CanonicalOrder(model.model.V))
    model.close()
    return f


@pytest.mark.parametrize("second", [SIDE, (0.3, 0.2, 0.0)], ids=["apart", "overlapping"])
def test_loads_add(mesh_dir, second):
    """Two tools' load vector is the sum of each alone's; a tangential force too."""
    press, oblique = (0.0, 0.0, -0.01), (0.004, -0.002, -0.008)
    both = nodal_load(problem(mesh_dir, APEX, press, [(second, oblique)]))
    apart = nodal_load(problem(mesh_dir, APEX, press)) + nodal_load(
        problem(mesh_dir, second, oblique)
    )
    assert np.linalg.norm(both - apart) <= 1e-13 * np.linalg.norm(apart)
    total = both.reshape(-1, 3).sum(axis=0)  # a dead load: its resultant is the forces' sum
    np.testing.assert_allclose(total, np.add(press, oblique), rtol=0, atol=1e-14)


def solved_displacement(config) -> np.ndarray:
    model = FullOrderModel(config, verbose=False)
    result = model.solve()
    u = model.model.u.x.array.copy()
    model.close()
    return u, (result, model.further_forces(1.0))


def test_two_tools_superpose_in_the_linear_range(mesh_dir):
    """Forces of 1e-5 N keep the tissue linear: the two tools' equilibrium is the sum of
    each tool's alone (to the nonlinearity, measured 5e-5 when written), far from either
    (0.32 and 0.72 of it away); the first tool's force is reported beside its depth, the
    second's apart."""
    press, side = (0.0, 0.0, -1e-5), (3e-6, 0.0, -5e-6)
    both, (result, further) = solved_displacement(problem(mesh_dir, APEX, press, [(SIDE, side)]))
    first, _ = solved_displacement(problem(mesh_dir, APEX, press))
    second, _ = solved_displacement(problem(mesh_dir, SIDE, side))
    error = np.linalg.norm(both - first - second) / np.linalg.norm(both)
    assert error <= 1e-3, error
    assert min(np.linalg.norm(both - first), np.linalg.norm(both - second)) > 0.2 * np.linalg.norm(
        both
    )
    np.testing.assert_allclose(result.force[-1], press, rtol=1e-12, atol=0)
    np.testing.assert_allclose(further, [side], rtol=1e-12, atol=0)


def held(mesh_dir, press) -> ProblemConfig:
    """The first tool holds its patch at SIDE in place (displacement control, zero), a
    further one presses at APEX: grasping forceps beside a probe."""
    config = problem(mesh_dir, APEX, press)
    load = replace(config.load, mode="displacement", displacement=(0.0, 0.0, 0.0), force=None,
                   contact_point=SIDE, tools=((APEX, press),))  # fmt: skip
    return replace(config, load=load)


def solved_depth(config, press) -> tuple[float, FullOrderModel]:
    """The pressing tool's depth after the load path: the load-weighted mean displacement
    along its force, u . f / |force| (the benches' depth; f its load vector), and the
    model (to be closed)."""
    model = FullOrderModel(config, verbose=False)
    result = model.solve()
    model.set_load(1.0)
    order = CanonicalOrder(model.model.V)
    f = load_vector(model.model, order)
    depth = order.gather(model.model.u.x.array) @ f / np.linalg.norm(press)
    return float(depth), model, result, f


def test_a_held_tool_beside_a_pressing_one(mesh_dir):
    """The held patch does not move; the load vector is the pressing tool's alone; the
    holder pulls up against a downward press (it keeps the tissue beside the probe from
    following it), and the probe sinks less than without the holder."""
    press = (0.0, 0.0, -0.01)
    depth_held, model, result, f = solved_depth(held(mesh_dir, press), press)
    u = model.model.u.x.array.reshape(-1, 3)
    assert len(model.patch_blocks) > 0 and not u[model.patch_blocks].any()
    np.testing.assert_allclose(f.reshape(-1, 3).sum(axis=0), press, rtol=0, atol=1e-14)
    holder = result.force[-1]  # the holder's force on the tissue: its reaction
    model.close()
    depth_alone, alone, _, _ = solved_depth(problem(mesh_dir, APEX, press), press)
    alone.close()
    assert holder[2] > 0.05 * abs(press[2]), holder
    assert 0.0 < depth_held < depth_alone, (depth_held, depth_alone)


def test_further_tools_are_forces_only(mesh_dir):
    config = problem(mesh_dir, APEX, (0.0, 0.0, -0.01), [(SIDE, (0.0, 0.0, -0.01))])
    load = LoadConfig(mode="displacement", displacement=(0.0, 0.0, -0.1), contact_point=APEX,
                      tools=config.load.tools)  # fmt: skip
    sphere = replace(load, mode="sphere", displacement=None, sphere=(0.0, 0.0, -0.1))
    with pytest.raises(InputError, match="further tools are force loads"):
        FullOrderModel(replace(config, load=sphere), verbose=False)
    for bad in [(SIDE,), (SIDE, (0.0, np.nan, -0.01)), (SIDE, (0.0, -0.01)), "tool"]:
        with pytest.raises(InputError, match=r"load.tools\[0\]: a \(point, force\) pair"):
            FullOrderModel(problem(mesh_dir, APEX, (0.0, 0.0, -0.01), [bad]), verbose=False)
    off = problem(mesh_dir, APEX, (0.0, 0.0, -0.01), [((0.0, 0.0, 5.0), (0.0, 0.0, -0.01))])
    with pytest.raises(InputError, match="off the 'loadable' surface"):
        FullOrderModel(off, verbose=False)


def campaign_position(mesh_dir, tmp_path, point) -> tuple:
    """(A force campaign on the coarse cornea, its position at the surface node nearest
    ``point``, the organ)."""
    from conftest import FORCE_CAMPAIGN

    path = tmp_path / "campaign.toml"
    mesh = mesh_dir / "cornea-coarse.msh"
    path.write_text(FORCE_CAMPAIGN.format(name="further-tools", mesh=mesh, points=[list(point)]))
    config = CampaignConfig.from_toml(path)
    surface = read_surface(config.problem.mesh.file, config.load.surface)
    k = int(np.argmin(np.linalg.norm(surface.nodes - np.array(point), axis=1)))
    position = ToolPosition(-1, tuple(surface.nodes[k]), tuple(surface.normals[k]),
                            int(surface.node_tags[k]), "point")  # fmt: skip
    return config, position, load_organ(config.problem.mesh.file, MPI.COMM_SELF)


def test_solve_position_records_its_tools(mesh_dir, tmp_path):
    """A position solved with further tools says so in its attributes (a row of point and
    force each), and their load is in its load vector; without, no such attribute."""
    config, position, organ = campaign_position(mesh_dir, tmp_path, APEX)
    side = (0.0, 0.0, -2e-3)
    data, attrs = solve_position(config, position, organ, MPI.COMM_SELF, [(SIDE, side)])
    plain, alone = solve_position(config, position, organ, MPI.COMM_SELF)
    assert attrs["status"] == alone["status"] == "solved"
    np.testing.assert_array_equal(attrs["tools"], [[*SIDE, *side]])
    assert "tools" not in alone
    extra = (data["load_vector"] - plain["load_vector"]).reshape(-1, 3).sum(axis=0)
    np.testing.assert_allclose(extra, side, rtol=1e-10, atol=1e-15)


def test_solve_position_of_a_held_tool_records_the_pressing_load(mesh_dir, tmp_path):
    """A position whose tool holds its patch (displacement control, zero) beside a
    pressing tool: its load vector is the pressing tool's alone, its contact nodes the held
    patch, which does not move (the benches' --held-tool reference)."""
    config, position, organ = campaign_position(mesh_dir, tmp_path, SIDE)
    config = replace(config, load=replace(config.load, mode="displacement", magnitude=0.0))
    press = (0.0, 0.0, -5e-3)
    data, attrs = solve_position(config, position, organ, MPI.COMM_SELF, [(APEX, press)])
    assert attrs["status"] == "solved"
    total = data["load_vector"].reshape(-1, 3).sum(axis=0)
    np.testing.assert_allclose(total, press, rtol=0, atol=1e-14)
    held = data["contact_nodes"]
    U = data["displacement"].reshape(len(data["displacement"]), -1, 3)
    assert len(held) > 0 and not U[:, held].any() and U[-1].any()
