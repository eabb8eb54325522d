"""The artifact's depth grid (format 2.3): to the deepest sample, each sample's own curve within
its solved depth and a linear continuation beyond it; the runtime flags a depth beyond its
contact's neighbours' solved depths as extrapolated.

Why: under force control a soft place reaches the trained force several times deeper than
the stiffest (the liver 6.3x); a grid that stopped at the shallowest sample's depth left the
runtime extrapolating every neighbour's curve there, though the campaign had solved them.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.offline.campaign.greedy import read_force_curve
from hapticrom.offline.reduce.interpolation import (
    MAX_GRID_REFINEMENT,
    extended_grid,
    monotone_slopes,
    on_common_grid,
    sample_on_grid,
)
from hapticrom.online import kernels, load
from hapticrom.online.simulator import Simulator

STEPS = 4


def force_controlled(stiffness: float, modes: int = 3):
    """A sample solved to 1 N in STEPS load steps on the curve F = k d^1.4: (depth, force,
    reduced coordinates (STEPS + 1, modes), each a smooth function of depth)."""
    force = np.linspace(0.0, 1.0, STEPS + 1)
    depth = (force / stiffness) ** (1 / 1.4)
    coefficients = np.column_stack([np.sin((m + 1) * depth) for m in range(modes)])
    return depth, force, coefficients


SAMPLES = [force_controlled(k) for k in (9.0, 2.0, 0.7)]  # ends 0.21, 0.61, 1.29 mm


def test_the_grid_goes_to_the_deepest_sample_at_the_common_spacing_or_finer():
    depths = [d for d, _, _ in SAMPLES]
    grid = extended_grid(depths)
    common, _ = on_common_grid(depths, [f for _, f, _ in SAMPLES])
    assert grid[0] == 0.0 and grid[-1] == max(d[-1] for d in depths)
    assert np.allclose(np.diff(grid), grid[1], rtol=1e-12)
    assert grid[1] <= common[1] * (1 + 1e-12)
    assert grid[1] > common[1] / 2  # no finer than needed: the stiffest keeps its 4 intervals
    assert np.count_nonzero(grid <= depths[0][-1]) >= STEPS + 1


def test_within_its_solved_depth_a_sample_keeps_its_own_curve():
    grid = extended_grid([d for d, _, _ in SAMPLES])
    for depth, force, coefficients in SAMPLES:
        f, c = sample_on_grid(depth, force, coefficients, grid)
        inside = grid <= depth[-1]
        np.testing.assert_allclose(f[inside], PchipInterpolator(depth, force)(grid[inside]),
                                   rtol=0, atol=1e-14)  # fmt: skip
        for m in range(coefficients.shape[1]):
            linear = np.interp(grid[inside], depth, coefficients[:, m])
            np.testing.assert_allclose(c[inside, m], linear, rtol=0, atol=1e-14)


def test_beyond_its_solved_depth_a_sample_goes_on_linearly():
    """Force with the cubic's end slope, coordinates along their last segment; the stored
    knot slopes there are that end slope (what the runtime continues with past the grid)."""
    grid = extended_grid([d for d, _, _ in SAMPLES])
    for depth, force, coefficients in SAMPLES[:2]:  # the deepest has nothing beyond
        f, c = sample_on_grid(depth, force, coefficients, grid)
        beyond = grid > depth[-1]
        assert np.count_nonzero(beyond) >= 2
        end_slope = PchipInterpolator(depth, force).derivative()(depth[-1])
        gap = grid[beyond] - depth[-1]
        np.testing.assert_allclose(f[beyond], force[-1] + end_slope * gap, rtol=1e-13)
        rate = (coefficients[-1] - coefficients[-2]) / (depth[-1] - depth[-2])
        np.testing.assert_allclose(c[beyond], coefficients[-1] + np.outer(gap, rate), rtol=1e-13)
        slopes = monotone_slopes(grid, f)
        first_after = int(np.argmax(beyond)) + 1  # both its secants lie beyond the end
        np.testing.assert_allclose(slopes[first_after:], end_slope, rtol=1e-9)


def test_equal_depths_keep_the_common_grid():
    """Displacement control (every sample on the same depths): the grid and curves of before."""
    depth = np.linspace(0.0, 0.5, STEPS + 1)
    forces = [k * depth**1.3 for k in (1.0, 2.0)]
    common, on_common = on_common_grid([depth, depth], forces)
    grid = extended_grid([depth, depth])
    np.testing.assert_array_equal(grid, common)
    for force, expected in zip(forces, on_common, strict=True):
        f, _ = sample_on_grid(depth, force, np.zeros((STEPS + 1, 2)), grid)
        np.testing.assert_allclose(f, expected, rtol=0, atol=1e-15)


def test_the_refinement_is_bounded():
    """A sample 100 times deeper than the stiffest: the grid stops refining at
    MAX_GRID_REFINEMENT (the table stays small; the stiffest then has fewer knots)."""
    shallow, deep = np.linspace(0.0, 0.01, STEPS + 1), np.linspace(0.0, 1.0, STEPS + 1)
    grid = extended_grid([shallow, deep])
    assert len(grid) == STEPS * MAX_GRID_REFINEMENT + 1 and grid[-1] == 1.0


# -- the trained artifact and the runtime ------------------------------------------------------
# The monotone cubic through a sample's solves, resampled on the grid and interpolated again by
# the runtime's Hermite, at the solves' depths, of the sample's largest force: 3.1e-4 here
# (at a ring sample's solved depth, inside a grid interval whose knot slopes see the turn to
# the continuation; 1e-4 at the first step), 2e-5 on the liver example.
RESAMPLING = 5e-4


@pytest.fixture(scope="module")
def model(force_artifact):
    return load(force_artifact)


def test_the_artifact_records_each_samples_solved_depth(model, force_campaign):
    """The force campaign on the coarse cornea: its samples reach 1.2 N at different depths;
    the grid ends at the deepest; the model's trained depth is the shallowest; each sample's
    trained force is the campaign's."""
    config, store, _ = force_campaign
    solved = []
    for i in store.completed():
        _, _, depth, force = read_force_curve(store, i, config.load.steps)
        solved.append(depth[-1])
    np.testing.assert_allclose(model.solved_depth, solved, rtol=1e-12)
    assert np.ptp(model.solved_depth) > 0.02 * model.solved_depth.max()
    assert model.depth_step * (model.force.shape[1] - 1) == pytest.approx(max(solved), rel=1e-12)
    assert model.trained_depth == pytest.approx(min(solved), rel=1e-12)
    np.testing.assert_allclose(model.sample_trained_force, config.load.magnitude, rtol=1e-3)


def test_at_a_sample_the_force_is_its_own_solve_to_its_solved_depth(model, force_campaign):
    """At each sample, the runtime's force at the sample's own solved depths (beyond the
    shallowest sample's too) against the full order's."""
    config, store, _ = force_campaign
    sim = Simulator(model, response="curves")
    for i in store.completed():
        point, push, depth, force = read_force_curve(store, i, config.load.steps)
        sim.set_contact(point)
        got = [np.linalg.norm(sim.step_displacement(d * push)) for d in depth[1:]]
        np.testing.assert_allclose(got, force[1:], rtol=0, atol=RESAMPLING * force.max())


def test_the_curves_flag_beyond_the_contacts_shallowest_neighbour(model):
    """At each sample, a depth (and a force) just within its own solved depth is not flagged
    and one just beyond is; at a contact inside a sample triangle the flag is at the smallest
    of its three. (POD-ANM flags beyond a neighbour's last section, its own range.)"""
    sim = Simulator(model, response="curves")
    for i, point in enumerate(model.sample_points):
        sim.set_contact(point)
        n = np.array(sim.contact_normal)
        solved = model.solved_depth[i]
        # its own: not a neighbour's through locate's rounding weights (6e-18: review)
        assert sim._buf[kernels.SOLVED_DEPTH] == solved, i
        sim.step_displacement(-(1 - 1e-3) * solved * n)
        assert not sim.beyond_trained_depth, i
        sim.step_displacement(-(1 + 1e-3) * solved * n)
        assert sim.beyond_trained_depth, i
        sim.step_force(-(1 - 1e-3) * model.sample_trained_force[i] * n)
        assert not sim.beyond_trained_depth, i
        sim.step_force(-model.sample_trained_force[i] * n)  # exactly: within rounding of it
        assert not sim.beyond_trained_depth, i
        sim.step_force(-(1 + 1e-3) * model.sample_trained_force[i] * n)
        assert sim.beyond_trained_depth, i
    for t in model.sample_triangles:
        sim.set_contact(model.sample_points[t].mean(axis=0))
        assert not sim.outside_trained_region
        assert sim._buf[kernels.SOLVED_DEPTH] == model.solved_depth[t].min()
        n = np.array(sim.contact_normal)
        sim.step_displacement(-(1 + 1e-3) * model.solved_depth[t].min() * n)
        assert sim.beyond_trained_depth
