"""The runtime's scalpel: cut events, softening, lips, bad input (coarse cornea, SVK)."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.serial
R = 7.8  # mm, anterior radius of the cornea


def on_surface(rho, degrees=0.0):
    a = np.radians(degrees)
    return np.array([rho * np.cos(a), rho * np.sin(a), -R + np.sqrt(R * R - rho * rho)])


@pytest.fixture(scope="module")
def model(mesh_dir, tmp_path_factory):
    from conftest import campaign_toml
    from mpi4py import MPI

    import hapticrom.online as online
    from hapticrom.offline.campaign import CampaignConfig, run_campaign
    from hapticrom.offline.reduction import reduce_campaign

    root = tmp_path_factory.mktemp("scalpel")
    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=2, per_ring=3)
    text = text.replace('law = "hgo"', 'law = "svk"\nE = 0.5\nnu = 0.45')
    centre = on_surface(4.6).tolist()
    text += f"\n[anm]\nenabled = false\n[cutting]\ncentre = {centre}\nradius = 2.5\n"
    text += "cut_force = 1e-4\npatch_layers = 1\n"
    (root / "c.toml").write_text(text)
    config = CampaignConfig.from_toml(root / "c.toml")
    run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
    reduce_campaign(root / "store", root / "m.h5", MPI.COMM_SELF, verbose=False)
    return online.load(root / "m.h5")


def test_pressing_the_blade_cuts_and_softens(model):
    sim = model.simulator()
    intact = model.simulator()
    point = on_surface(4.6)
    sim.scalpel(point, [0.0, 1.0, 0.0])  # blade along the limbus
    intact.set_contact(point)
    n = sim.contact_normal.copy()
    assert sim.last_cut is None
    forces = []
    for depth in (0.005, 0.01, 0.02, 0.04):
        forces.append(sim.step_displacement(-depth * n).copy())
        f_intact = intact.step_displacement(-depth * n)
        if sim.last_cut is not None:
            # Cut: the tissue is softer there than the intact one (never stiffer).
            assert np.linalg.norm(forces[-1]) < np.linalg.norm(f_intact)
    assert sim.last_cut is not None and sim.last_cut.faces > 0
    events = sim.cut_events
    assert sum(e.new_nodes for e in events) > 0 and events[-1].patch_unknowns > 0
    # Sliding along the blade extends the cut; steps without a new cut change nothing.
    sim.scalpel(on_surface(4.6, 8.0), [0.0, 1.0, 0.0])
    sim.step_displacement(-0.04 * n)
    assert len(sim.cut_events) >= len(events)
    count = len(sim.cut_events)
    sim.step_displacement(-0.04 * n)
    assert len(sim.cut_events) == count  # the same faces are not cut twice
    # The rendered surface shows the two lips, apart.
    out = np.zeros_like(model.vertices)
    sim.surface_displacement(out)
    vertices, positions, displacement = sim.lip_vertices
    assert len(vertices) > 0
    np.testing.assert_array_equal(positions, model.vertices[vertices])
    assert np.abs(displacement - out[vertices]).max() > 0
    # A renderer's view: the lips split the triangles, each side uses its own vertices.
    all_vertices, triangles = sim.cut_surface()
    V = len(model.vertices)
    assert len(all_vertices) == V + len(vertices) and len(triangles) == len(model.triangles)
    used = np.unique(triangles)
    assert np.all(np.isin(np.arange(V, V + len(vertices)), used))  # every lip copy is drawn
    assert np.all(np.isin(vertices, used))  # and so is the other lip
    changed = np.any(triangles != model.triangles, axis=1)
    np.testing.assert_array_equal(all_vertices[triangles[changed]],
                                  model.vertices[model.triangles[changed]])  # fmt: skip


def test_bad_scalpel_input_leaves_the_state_alone(model):
    from hapticrom.online.cutting import ScalpelInputError

    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    sim.step_displacement(-0.03 * sim.contact_normal)
    before = (len(sim.cut_events), sim.contact_normal.copy(), sim.depth)
    for position, blade, message in (
        ([0.0, 0.0, 5.0], [0.0, 1.0, 0.0], "off the organ"),
        (on_surface(4.6), [0.0, 0.0, 0.0], "zero or along"),
        (on_surface(4.6), on_surface(4.6) - [0.0, 0.0, -R], "zero or along"),  # the normal
        ([np.nan, 0.0, 0.0], [0.0, 1.0, 0.0], "finite"),
    ):
        with pytest.raises(ScalpelInputError, match=message):
            sim.scalpel(position, blade)
        assert len(sim.cut_events) == before[0]
        np.testing.assert_array_equal(sim.contact_normal, before[1])
        assert sim.depth == before[2]


def test_artifact_without_a_region_refuses_the_scalpel(small_artifact):
    import hapticrom.online as online

    sim = online.load(small_artifact).simulator()
    with pytest.raises(ValueError, match="cuttable region"):
        sim.scalpel([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])


def test_reduce_again_with_other_reduction_tables_only(small_campaign, tmp_path, mesh_dir):
    """`hapticrom reduce --campaign`: [anm]/[cutting] may change, the solves may not."""
    from conftest import campaign_toml
    from mpi4py import MPI

    from hapticrom.offline.campaign import CampaignConfig
    from hapticrom.offline.reduction import reduce_campaign
    from hapticrom.shared.errors import InputError

    _, store, _ = small_campaign
    other = tmp_path / "other.toml"
    other.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh").replace("0.3", "0.25"))
    with pytest.raises(InputError, match="another campaign"):
        reduce_campaign(store.root, tmp_path / "x.h5", MPI.COMM_SELF, verbose=False,
                        reduction=CampaignConfig.from_toml(other))  # fmt: skip
    same = tmp_path / "same.toml"
    same.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh") + "\n[anm]\nenabled = false\n")
    reduce_campaign(store.root, tmp_path / "y.h5", MPI.COMM_SELF, verbose=False,
                    reduction=CampaignConfig.from_toml(same))  # fmt: skip
    import hapticrom.online as online

    assert online.load(tmp_path / "y.h5").anm is None


def test_force_control_yields_more_where_cut(model):
    sim, intact = model.simulator(), model.simulator()
    point = on_surface(4.6)
    sim.scalpel(point, [0.0, 1.0, 0.0])
    for depth in (0.01, 0.02, 0.04):
        sim.step_displacement(-depth * sim.contact_normal)
    assert sim.cut_events
    intact.set_contact(point)
    push = -0.5 * model.trained_force * sim.contact_normal
    d_cut = sim.step_force(push).copy()
    d_intact = intact.step_force(push).copy()
    ratio = sim._cutting.ratio[sim._vertex]  # cut / intact stiffness at the contact
    assert ratio < 1
    np.testing.assert_allclose(np.linalg.norm(d_cut), np.linalg.norm(d_intact) / ratio)
