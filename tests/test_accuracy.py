"""``hapticrom accuracy``: the held-out check of a reduced model against the full order.

Serial tests use the session's small model (5 positions on the coarse cornea, displacement
control); the MPI test runs the command on 2 ranks and compares it with a serial run.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline import accuracy
from hapticrom.shared.accuracy import FIELD_TARGET, FORCE_TARGETS, TARGETS
from hapticrom.shared.artifact import read_artifact


def model_surface(model: Path):
    artifact = read_artifact(model)
    info = artifact.group_attrs["model"]
    return artifact["samples"], read_surface(info["mesh_file"], info["surface_group"])


def node_index(surface, point) -> int:
    distances = np.linalg.norm(surface.nodes - np.asarray(point), axis=1)
    assert distances.min() < 1e-12, "not a surface node"
    return int(np.argmin(distances))


def with_positions(plan: accuracy.HeldOutPlan, positions) -> accuracy.HeldOutPlan:
    """The plan with other positions (the campaign's points follow)."""
    campaign = {**plan.campaign, "positions": {"points": [list(p.point) for p in positions]}}
    return dataclasses.replace(plan, positions=list(positions), campaign=campaign)


# -- selection -----------------------------------------------------------------------------
@pytest.mark.serial
def test_seed_gives_reproducible_distinct_positions_in_the_region(small_artifact):
    samples, surface = model_surface(small_artifact)
    trained = accuracy.trained_nodes(samples, surface)
    region = set(accuracy.region_nodes(samples, surface).tolist())
    assert len(trained) == len(samples["points"]) == 5
    candidates = region - trained
    assert len(candidates) >= 4, "the test model's region is too small to draw from"

    first = accuracy.random_positions(samples, surface, 3, seed=7)
    again = accuracy.random_positions(samples, surface, 3, seed=7)
    other = accuracy.random_positions(samples, surface, 3, seed=8)
    assert first == again
    assert [p.point for p in first] != [p.point for p in other]
    for positions in (first, other):
        nodes = [node_index(surface, p.point) for p in positions]
        assert len(set(nodes)) == 3  # distinct
        assert set(nodes) <= candidates  # in the trained region, never a training position
        assert all(p.moved == 0.0 and "seed" in p.source for p in positions)
    # Asking for more than there are gives all of them, each once.
    every = accuracy.random_positions(samples, surface, 10_000, seed=1)
    assert {node_index(surface, p.point) for p in every} == candidates


@pytest.mark.serial
def test_centroids_snap_to_region_nodes_and_say_how_far(small_artifact):
    samples, surface = model_surface(small_artifact)
    trained = accuracy.trained_nodes(samples, surface)
    region = set(accuracy.region_nodes(samples, surface).tolist())
    positions = accuracy.centroid_positions(samples, surface, 8)
    triangles = len(samples["triangles"])
    assert 1 <= len(positions) <= triangles
    nodes = [node_index(surface, p.point) for p in positions]
    assert len(set(nodes)) == len(nodes) and set(nodes) <= region - trained
    for p, node in zip(positions, nodes, strict=True):
        t = int(p.source.removeprefix("centroid of sample triangle "))
        plan = accuracy.plan_coordinates(samples, samples["points"])
        centroid = plan[samples["triangles"][t]].mean(axis=0)
        at = accuracy.plan_coordinates(samples, surface.nodes[node])
        assert p.moved == pytest.approx(np.linalg.norm(at - centroid), abs=1e-12)
    assert accuracy.centroid_positions(samples, surface, 8) == positions  # deterministic


@pytest.mark.serial
def test_softest_gives_the_region_nodes_nearest_the_softest_samples(small_artifact, tmp_path):
    """Brute force: for the samples by increasing force at the grid's end (a displacement-
    controlled model: every sample solved to the grid's end), the nearest untrained node of
    the region, each node once; the plan and its work directory say so."""
    samples, surface = model_surface(small_artifact)
    candidates = sorted(set(accuracy.region_nodes(samples, surface).tolist())
                        - accuracy.trained_nodes(samples, surface))  # fmt: skip
    expected = []
    for i in np.argsort(np.asarray(samples["force"])[:, -1], kind="stable"):
        d = [np.linalg.norm(surface.nodes[n] - samples["points"][i]) for n in candidates]
        node = candidates[int(np.argmin(d))]
        if node not in expected:
            expected.append(node)
    positions = accuracy.softest_positions(samples, surface, 3)
    assert [node_index(surface, p.point) for p in positions] == expected[:3]
    plan = accuracy.plan_held_out(small_artifact, 3, comm=MPI.COMM_SELF, method="softest")
    assert plan.method == "softest" and plan.positions == positions
    assert accuracy.default_work(tmp_path / "m.h5", 3, None, "softest").name == (
        "m.heldout-3-softest"
    )


# -- errors against the full order -----------------------------------------------------------
@pytest.mark.serial
def test_errors_are_against_a_full_order_solve(small_artifact, tmp_path):
    """At a training position the check finds ~0; at a held-out one, the full order's force
    (checked against an independent solve) differs from the ROM's."""
    from hapticrom.offline.campaign.positions import plan_positions
    from hapticrom.offline.fe.fullorder import FullOrderModel

    plan = accuracy.plan_held_out(small_artifact, 1, comm=MPI.COMM_SELF)
    samples, surface = model_surface(small_artifact)
    training = accuracy.HeldOutPosition(tuple(samples["points"][1]), 0.0, "training")
    plan = with_positions(plan, [training, plan.positions[0]])
    result = accuracy.run_accuracy(plan, tmp_path / "work", MPI.COMM_SELF, quiet=True)
    assert not result.failed and set(result.names) == {
        "transport+curves",
        "podi+curves",
        "grassmann+curves",
        "transport+anm",
        "podi+anm",
    }
    steps = {i: [s for s in result.steps if s.position == i] for i in (0, 1)}
    assert len(steps[0]) == len(steps[1]) == 4  # the campaign's 4 load steps

    def worst(i, name, quantity):
        if quantity == "force":
            return max(accuracy.force_error(s, name) for s in steps[i])
        return max(s.field[name] for s in steps[i])

    # displacement control: the training depths are the stored knots, reproduced exactly
    assert worst(0, "podi+curves", "force") < 1e-8
    assert worst(0, "podi+anm", "force") < 1e-3  # the series' own tolerance
    assert worst(0, "podi+curves", "field") < 1e-2  # the POD truncation only
    assert worst(0, "transport+curves", "field") < 1e-2  # and the chart's read-back
    for name in result.names:
        assert 1e-4 < worst(1, name, "force") < 0.2, name
        assert worst(1, name, "field") > 10 * worst(0, "podi+curves", "field"), name
    for response in ("curves", "anm"):  # the dent carried to the tool: 6 % against 50 %
        transported = worst(1, f"transport+{response}", "field")
        assert transported < worst(1, f"podi+{response}", "field") / 4, response

    # An independent full-order solve at the held-out position gives the same F_FEM.
    config = accuracy.held_out_config(plan)
    position = plan_positions(surface, config.positions)[1]
    problem = dataclasses.replace(config.problem, load=config.load.at(position))
    solve = FullOrderModel(problem, comm=MPI.COMM_SELF, verbose=False).solve()
    fem = solve.force @ config.load.unit_direction(position)
    np.testing.assert_allclose([s.f_fem for s in steps[1]], fem, rtol=1e-10)
    assert all(f > 0 for f in fem)
    # and the summary is the worst of the steps, with the targets of the one place
    for name, entry in result.summary.items():
        assert entry["steps_beyond_trained_depth"] == 0  # displacement control: trained depths
        assert entry["max_force_error"] == max(worst(0, name, "force"), worst(1, name, "force"))
        assert entry["force_target"] == FORCE_TARGETS[name.split("+")[1]]
        assert entry["field_target"] == FIELD_TARGET
        assert entry["field_verdict"] == ("met" if entry["max_field_error"] <= 0.03 else "missed")


@pytest.mark.serial
def test_command_prints_positions_tables_verdicts_and_writes_json(small_artifact, tmp_path):
    from hapticrom.report import read_accuracy

    out = tmp_path / "accuracy.json"
    args = ["accuracy", small_artifact, "--positions", "2", "--seed", "3"]
    code = "import sys\nfrom hapticrom.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    proc = subprocess.run(
        [sys.executable, "-c", code, *map(str, args), "--work", tmp_path / "w", "--json", out],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    assert "2 position(s) (random surface nodes of the trained region, seed 3)" in text
    assert "snap moved (mm)" in text and text.count("random surface node (seed 3)") == 2
    assert "campaign 'held-out': 2 tool positions" in text  # the campaign's progress
    assert "held-out position 0 at (" in text and "held-out position 1 at (" in text
    for name in ("transport+curves", "podi+curves", "grassmann+curves", "transport+anm",
                 "podi+anm"):  # fmt: skip
        line = next(row for row in text.splitlines() if row.startswith(name))
        target_force = f"{100 * FORCE_TARGETS[name.split('+')[1]]:.0f} %"
        assert target_force in line and "3 %" in line, line
        assert line.split().count("met") + line.split().count("missed") == 2, line

    def no_constants(name):  # NaN, Infinity: not JSON (a strict parser refuses them)
        raise AssertionError(f"{out} holds {name}")

    data = json.loads(out.read_text(), parse_constant=no_constants)
    assert data["format"] == "hapticrom-accuracy" and data["version"] == 3
    assert all(entry["max_force_error_outside"] is None for entry in data["summary"].values())
    assert data["targets"] == json.loads(json.dumps(TARGETS))
    assert data["selection"] == {"method": "random", "seed": 3, "requested": 2}
    assert len(data["positions"]) == 2 and len(data["rows"]) == 2 * 4
    for name, entry in data["summary"].items():
        assert 0 < entry["max_force_error"] < 0.2, name
        assert entry["field_target"] == FIELD_TARGET and entry["field_verdict"] in ("met", "missed")
    results = read_accuracy(out)  # what the report reads
    assert results.responses == ["transport+curves", "podi+curves", "transport+anm", "podi+anm"]
    assert results.field.shape == (8, 4) and np.all(results.field > 0)
    assert {tuple(p["point"]) for p in data["positions"]} == {tuple(r[1]) for r in data["rows"]}


@pytest.mark.serial
def test_anywhere_draws_the_whole_group_inside_and_outside(small_artifact, tmp_path):
    """--anywhere S: random nodes of the whole surface group but training positions, on both
    sides of the trained region, each labelled as the runtime classifies it."""
    from hapticrom.online import load

    samples, surface = model_surface(small_artifact)
    region = set(accuracy.region_nodes(samples, surface).tolist())
    trained = accuracy.trained_nodes(samples, surface)
    positions = accuracy.random_positions(samples, surface, 40, 5, "anywhere")
    nodes = [node_index(surface, p.point) for p in positions]
    assert len(set(nodes)) == 40 and not set(nodes) & trained
    assert 0 < sum(n in region for n in nodes) < 40  # both sides drawn
    sim = load(small_artifact).simulator()
    for p, n in zip(positions, nodes, strict=True):
        sim.set_contact(p.point)
        assert sim.outside_trained_region == (n not in region)
        assert p.source.endswith(", inside" if n in region else ", outside"), p.source
    every = accuracy.random_positions(samples, surface, 10_000, 5, "anywhere")
    assert len(every) == len(surface.nodes) - len(trained)
    plan = accuracy.plan_held_out(small_artifact, 40, 5, comm=MPI.COMM_SELF, method="anywhere")
    assert plan.method == "anywhere" and plan.positions == positions and plan.seed == 5
    assert accuracy.default_work(tmp_path / "m.h5", 4, 5, "anywhere").name == (
        "m.heldout-4-anywhere-seed5"
    )
    with pytest.raises(accuracy.InputError, match="held-out selection 'everywhere'"):
        accuracy.default_work(tmp_path / "m.h5", 4, 5, "everywhere")


def test_the_summary_splits_the_force_error_by_region():
    """The largest force error inside the region and outside it, each over its own positions'
    steps within the trained depth (a step beyond it counts in neither)."""
    name = "podi+curves"

    def step(position, error, beyond=False):
        return accuracy.Step(position, [0.0, 0.0, 0.0], 1.0, 1.0, force={name: 1.0 + error},
                             beyond={name: beyond}, field={name: 0.01})  # fmt: skip

    steps = [step(0, 0.01), step(0, 0.03), step(1, 0.02), step(2, 0.05), step(2, 0.5, True)]
    entry = accuracy.summarise(steps, [name], outside={1, 2})[name]
    assert entry["max_force_error_inside"] == pytest.approx(0.03)
    assert entry["max_force_error_outside"] == pytest.approx(0.05)
    assert entry["max_force_error"] == pytest.approx(0.05)
    assert np.isnan(accuracy.summarise(steps, [name])[name]["max_force_error_outside"])
    result = accuracy.AccuracyResult(None, steps, {name: entry}, [name], {}, [1, 2], {})
    text = "\n".join(accuracy.region_text(result))
    assert "1 position(s) inside the trained region, 2 outside it" in text
    assert "inside   3.00 %   outside   5.00 %" in text
    only_outside = dataclasses.replace(result, outside=[0, 1, 2])
    assert accuracy.region_text(only_outside) == []


# -- two ranks ----------------------------------------------------------------------------------
@pytest.mark.mpi
def test_two_ranks_give_the_serial_result(mesh_dir, tmp_path_factory):
    from conftest import campaign_toml

    from hapticrom.cli import main
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.reduce.reduction import reduce_campaign

    comm = MPI.COMM_WORLD
    if comm.size < 2:
        pytest.skip("run under mpirun -n 2")
    root = Path(comm.bcast(str(tmp_path_factory.mktemp("acc")) if comm.rank == 0 else None))
    model = root / "model.h5"
    if comm.rank == 0:
        (root / "c.toml").write_text(campaign_toml(mesh_dir / "cornea-coarse.msh", steps=3))
        config = CampaignConfig.from_toml(root / "c.toml")
        run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
        reduce_campaign(root / "store", model, MPI.COMM_SELF, verbose=False)
    comm.barrier()
    args = ["accuracy", str(model), "--positions", "2", "--work", str(root / "w2")]
    assert main([*args, "--json", str(root / "two.json")]) == 0
    if comm.rank != 0:
        return
    plan = accuracy.plan_held_out(model, 2, comm=MPI.COMM_SELF)
    serial = accuracy.run_accuracy(plan, root / "w1", MPI.COMM_SELF, quiet=True)
    two = json.loads((root / "two.json").read_text())
    assert len(two["rows"]) == len(serial.steps) == 2 * 3
    for row, step in zip(two["rows"], serial.steps, strict=True):
        assert row[0] == step.position and row[1] == step.point
        np.testing.assert_allclose(row[2:4], [step.depth, step.f_fem], rtol=1e-9)
        names = ("transport+curves", "podi+curves", "transport+anm", "podi+anm")
        np.testing.assert_allclose(row[4:], [step.force[n] for n in names], rtol=1e-9)


def test_softest_starts_at_the_deepest_solved_sample(force_artifact):
    """Force control (artifact 2.3): the softest sample is the one solved deepest; the first
    position is the untrained region node nearest it."""
    samples, surface = model_surface(force_artifact)
    solved = np.asarray(samples["solved_depth"])
    assert np.ptp(solved) > 0
    deepest = int(np.argmax(solved))
    candidates = sorted(set(accuracy.region_nodes(samples, surface).tolist())
                        - accuracy.trained_nodes(samples, surface))  # fmt: skip
    d = [np.linalg.norm(surface.nodes[n] - samples["points"][deepest]) for n in candidates]
    first = accuracy.softest_positions(samples, surface, 1)[0]
    assert node_index(surface, first.point) == candidates[int(np.argmin(d))]
    assert f"nearest sample {deepest} (solved to" in first.source


def test_outside_draws_nodes_of_the_tools_group_the_runtime_clamps(small_artifact, tmp_path):
    """--outside S: random nodes of the surface group that are neither in the trained region
    nor training positions, reproducible from S, each flagged outside by the runtime."""
    from hapticrom.online import load

    samples, surface = model_surface(small_artifact)
    region = set(accuracy.region_nodes(samples, surface).tolist())
    trained = accuracy.trained_nodes(samples, surface)
    positions = accuracy.random_positions(samples, surface, 5, 3, "outside")
    nodes = [node_index(surface, p.point) for p in positions]
    assert len(set(nodes)) == 5 and not (set(nodes) & (region | trained))
    again = accuracy.random_positions(samples, surface, 5, 3, "outside")
    assert [p.point for p in again] == [p.point for p in positions]
    sim = load(small_artifact).simulator()
    for p in positions:
        sim.set_contact(p.point)
        assert sim.outside_trained_region
    plan = accuracy.plan_held_out(small_artifact, 5, 3, comm=MPI.COMM_SELF, method="outside")
    assert plan.method == "outside" and plan.positions == positions and plan.seed == 3
    assert accuracy.default_work(tmp_path / "m.h5", 5, 3, "outside").name == (
        "m.heldout-5-outside-seed3"
    )
