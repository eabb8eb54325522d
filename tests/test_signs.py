"""One sign convention (shared/ARTIFACT.md, "Signs"), checked wherever the code crosses it.

n is the outward normal at the contact; pushing in is along -n. A force pushed into
the tissue gives a positive depth, a force on the tool along +n, a force on the
tissue along -n, and a positive normal contact force F_n in the artifact.
"""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.online import load
from hapticrom.shared.artifact import read_artifact

pytestmark = pytest.mark.serial


@pytest.fixture(scope="module")
def model(small_artifact):
    return load(small_artifact)


def test_artifact_normals_point_out_of_the_tissue_the_full_order_pushes_into(
    small_artifact, small_campaign
):
    """samples/normals = -(the campaign's push direction): outward."""
    _, store, _ = small_campaign
    normals = read_artifact(small_artifact)["samples"]["normals"]
    for i, n in enumerate(normals):
        _, attrs = store.read_position(i)
        np.testing.assert_allclose(n, -np.asarray(attrs["direction"]), atol=1e-12)
    assert np.all(normals[:, 2] > 0)  # the cornea's cap faces +z


def test_artifact_forces_and_depths_are_positive_when_pushing_in(small_artifact, small_campaign):
    """F_n = n . (force on the tool) = -n . (force on the tissue, as the full order stores it)."""
    _, store, _ = small_campaign
    a = read_artifact(small_artifact)
    samples, anm = a["samples"], a["anm"]
    assert samples["depth"][-1] > 0 and np.all(np.diff(samples["depth"]) > 0)
    assert np.all(samples["force"][:, 1:] > 0)
    end = [
        np.polynomial.polynomial.polyval(a, c)
        for a, c in zip(anm["a_max"], anm["force"], strict=True)
    ]
    assert np.all(np.array(end) > 0) and np.all(anm["force"][:, 0] >= -1e-12)  # series values
    data, attrs = store.read_position(0)
    n = samples["normals"][0]
    on_tissue = data["force"][-1]  # full order: the force the tool exerts on the tissue
    assert on_tissue @ n < 0  # along -n
    np.testing.assert_allclose(-on_tissue @ n, samples["force"][0, -1], rtol=1e-9)


@pytest.mark.parametrize("response", ["anm", "curves"])
def test_step_displacement_pushing_in(model, response):
    sim = model.simulator(response=response)
    sim.set_contact(model.sample_points[0])
    n = sim.contact_normal.copy()
    on_tool = sim.step_displacement(-0.5 * model.trained_depth * n).copy()
    assert sim.depth == pytest.approx(0.5 * model.trained_depth)
    assert on_tool @ n > 0 and np.linalg.norm(np.cross(on_tool, n)) < 1e-12
    assert sim.contact_stiffness > 0
    surface = sim.surface_displacement(np.zeros_like(model.vertices))
    under = np.argmin(np.linalg.norm(model.vertices - model.sample_points[0], axis=1))
    assert surface[under] @ n < 0  # the tissue moves in, along -n
    # Pulling out of the tissue is no contact: no force.
    assert np.all(sim.step_displacement(0.1 * n) == 0) and sim.depth == 0


@pytest.mark.parametrize("response", ["anm", "curves"])
def test_step_force_pushing_in_is_newtons_third_law(model, response):
    sim = model.simulator(response=response)
    sim.set_contact(model.sample_points[0])
    n = sim.contact_normal.copy()
    on_tissue = -0.5 * model.trained_force * n  # the tool pushes the tissue in
    d = sim.step_force(on_tissue).copy()
    assert d @ n < 0 and sim.depth > 0  # the tool moves in
    on_tool = sim.step_displacement(d)  # the same state, displacement-controlled
    np.testing.assert_allclose(on_tool, -on_tissue, rtol=1e-6)
