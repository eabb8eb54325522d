"""Greedy training (offline/campaign/greedy.py): the ``[positions.greedy]`` table, where the
positions go, and a small greedy run on the coarse hemisphere that extends, resumes and
stays consistent with the artifact it is reduced into."""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import replace

import h5py
import numpy as np
import pytest
from conftest import ROOT
from mpi4py import MPI

from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.greedy import (
    HISTORY_FILE,
    on_common_grid,
    run_greedy,
    stop_reason,
    worst_triangle_nodes,
)
from hapticrom.offline.campaign.positions import GreedyMode, positions_from_dict
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

POSITIONS = {"points": [[0.0, 0.0, 0.0]], "farthest": {"n": 5}}  # asks for up to 6
GREEDY = {"target": 0.02, "max_solves": 10, "per_round": 2}


# -- the table ---------------------------------------------------------------------------------
def test_the_greedy_table_is_read():
    spec = positions_from_dict({**POSITIONS, "greedy": GREEDY})
    assert spec.greedy == GreedyMode(0.02, 10, 2)
    assert positions_from_dict({**POSITIONS, "greedy": {**GREEDY, "per_round": 1}}).greedy
    assert positions_from_dict(POSITIONS).greedy is None
    default = positions_from_dict({**POSITIONS, "greedy": {"target": 0.1, "max_solves": 6}})
    assert default.greedy.per_round == 4


@pytest.mark.parametrize(
    "change, words",
    [
        ({"target": 0.0}, "target must lie in (0, 1), got 0.0"),
        ({"target": 1.0}, "target must lie in (0, 1), got 1.0"),
        ({"target": -0.01}, "target must lie in (0, 1)"),
        ({"target": float("nan")}, "target must be a finite number"),
        ({"target": "2 %"}, "target must be a finite number"),
        ({"max_solves": 5}, "max_solves = 5 is fewer than the initial positions"),
        ({"max_solves": 0}, "max_solves must be positive"),
        ({"max_solves": 10.0}, "max_solves must be a finite integer"),
        ({"per_round": 0}, "per_round must be positive, got 0"),
        ({"per_round": True}, "per_round must be a finite integer"),
        ({"rounds": 3}, "unknown key(s) rounds"),
        ({"target": None}, "missing target"),
    ],
)
def test_bad_greedy_tables_are_refused_in_one_line(change, words):
    greedy = {k: v for k, v in {**GREEDY, **change}.items() if v is not None}
    with pytest.raises(InputError) as caught:
        positions_from_dict({**POSITIONS, "greedy": greedy})
    message = str(caught.value)
    assert words in message and "\n" not in message
    assert message.startswith("[positions")


def test_check_summarises_the_greedy_example():
    import tomllib

    from hapticrom.offline.check import check_config

    example = ROOT / "examples" / "hemisphere-greedy.toml"
    greedy = tomllib.loads(example.read_text())["positions"]["greedy"]
    line = check_config(example)
    assert f"then greedy up to {greedy['max_solves']} solves" in line
    assert f"(indicator target {100 * greedy['target']:g} %)" in line and line.endswith(": OK")


def base_campaign(mesh) -> dict:
    """A small indentation campaign on the coarse hemisphere (no series: quick to reduce)."""
    return {
        "campaign": {"name": "greedy-test"},
        "mesh": {"file": str(mesh)},
        "material": {"law": "neo-hookean", "E": 2.0, "nu": 0.48},
        "load": {"mode": "displacement", "magnitude": 1.0, "contact_radius": 4.0, "steps": 2},
        "positions": {
            "farthest": {"n": 5, "centre": [0.0, 0.0, 0.0], "radius": 14.0},
            "greedy": {"target": 1e-4, "max_solves": 7, "per_round": 2},
        },
        "anm": {"enabled": False},
    }


def with_greedy(data: dict, **greedy) -> dict:
    changed = copy.deepcopy(data)
    changed["positions"]["greedy"].update(greedy)
    return changed


def test_the_greedy_table_leaves_the_campaign_hash_alone(mesh_dir):
    """Changing the target or budget extends the same directory; other positions do not."""
    data = base_campaign(mesh_dir / "hemisphere-coarse.msh")
    config = CampaignConfig.from_dict(data)
    more = CampaignConfig.from_dict(with_greedy(data, max_solves=20, target=0.5, per_round=3))
    plain = copy.deepcopy(data)
    del plain["positions"]["greedy"]
    other = copy.deepcopy(data)
    other["positions"]["farthest"]["n"] = 4
    assert more.campaign_hash() == config.campaign_hash()
    assert CampaignConfig.from_dict(plain).campaign_hash() == config.campaign_hash()
    assert CampaignConfig.from_dict(other).campaign_hash() != config.campaign_hash()


# -- the decisions (pure numpy) ----------------------------------------------------------------
def grid_nodes(n: int = 9, spacing: float = 1.0) -> np.ndarray:
    """An n x n grid of nodes in the plane z = 0 (row-major: index = n * j + i)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    return np.column_stack([i.ravel(), j.ravel(), np.zeros(n * n)]) * spacing


def node_at(nodes, x, y) -> int:
    return int(np.flatnonzero(np.all(np.isclose(nodes[:, :2], [x, y]), axis=1))[0])


def test_the_worst_triangles_centroids_go_to_the_nearest_free_nodes():
    nodes = grid_nodes()
    corners = [(0, 0), (6, 0), (0, 6), (6, 6)]
    samples = np.array([nodes[node_at(nodes, *c)] for c in corners])
    triangles = np.array([[0, 1, 2], [1, 3, 2]])
    indicator = np.array([0.1, 0.5, 0.2, 0.9])
    taken = {node_at(nodes, *c) for c in corners}
    picks = worst_triangle_nodes(samples, triangles, indicator, nodes, taken, count=2)
    # the ranking: the mean of the corners' indicators, worst first
    means = indicator[triangles].mean(axis=1)
    assert [p.triangle for p in picks] == list(np.argsort(-means))
    for p in picks:  # each the nearest node to its centroid (brute force over every node)
        centroid = samples[triangles[p.triangle]].mean(axis=0)
        distances = np.linalg.norm(nodes - centroid, axis=1)
        assert distances[p.node] == pytest.approx(distances.min())
        assert p.score == pytest.approx(means[p.triangle])
    only = worst_triangle_nodes(samples, triangles, indicator, nodes, taken, count=1)
    assert [p.node for p in only] == [picks[0].node]


def test_a_taken_node_gives_way_to_the_next_nearest_free_one():
    nodes = grid_nodes()
    samples = np.array([nodes[node_at(nodes, *c)] for c in [(0, 0), (6, 0), (0, 6)]])
    triangles = np.array([[0, 1, 2]])
    taken = {node_at(nodes, *c) for c in [(0, 0), (6, 0), (0, 6), (2, 2)]}  # (2, 2): centroid's
    picks = worst_triangle_nodes(samples, triangles, np.ones(3), nodes, taken, count=1)
    free = np.setdiff1d(np.arange(len(nodes)), list(taken))
    distances = np.linalg.norm(nodes[free] - samples.mean(axis=0), axis=1)
    assert len(picks) == 1 and picks[0].node in free
    assert np.linalg.norm(nodes[picks[0].node] - samples.mean(axis=0)) == pytest.approx(
        distances.min()
    )


def test_a_triangle_the_mesh_cannot_refine_is_skipped():
    """Samples on neighbouring nodes: the nearest free node is no nearer the centroid than
    the corners, so nothing is added there; a wide triangle next to it is refined instead."""
    nodes = grid_nodes()
    tight = [(0, 0), (1, 0), (0, 1)]
    wide = [(1, 0), (7, 0), (0, 1)]
    samples = np.array([nodes[node_at(nodes, *c)] for c in tight + wide])
    taken = {node_at(nodes, *c) for c in tight + wide}
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    indicator = np.array([0.9, 0.9, 0.9, 0.1, 0.1, 0.1])  # the tight one is the worst
    picks = worst_triangle_nodes(samples, triangles, indicator, nodes, taken, count=2)
    assert [p.triangle for p in picks] == [1]
    assert worst_triangle_nodes(samples, triangles[:1], indicator, nodes, taken, count=2) == []


def test_stop_reasons():
    greedy = GreedyMode(target=0.02, max_solves=10, per_round=2)
    assert stop_reason(greedy, 6, np.array([0.01, 0.02])) == "target reached"
    assert stop_reason(greedy, 6, np.array([0.01, 0.021])) is None
    assert stop_reason(greedy, 10, np.array([0.01, 0.5])) == "max_solves reached"
    assert stop_reason(greedy, 6, np.array([0.0, np.inf])) is None


def test_curves_go_on_the_shallowest_common_grid():
    """Monotone cubic interpolation reproduces straight lines: the slopes come back exactly."""
    depths = [np.linspace(0, 2.0, 5), np.linspace(0, 1.5, 5), np.array([0, 0.2, 0.9, 1.3, 1.4])]
    slopes = [3.0, 5.0, 7.0]
    grid, force = on_common_grid(depths, [k * d for k, d in zip(slopes, depths, strict=True)])
    np.testing.assert_allclose(grid, np.linspace(0.0, 1.4, 5))
    np.testing.assert_allclose(force, np.outer(slopes, grid), rtol=1e-12, atol=1e-12)


# -- a small greedy run ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def greedy_run(mesh_dir, tmp_path_factory):
    """A greedy run on the coarse hemisphere: 5 initial positions, at most 7 solves."""
    config = CampaignConfig.from_dict(base_campaign(mesh_dir / "hemisphere-coarse.msh"))
    out = tmp_path_factory.mktemp("greedy") / "store"
    report = run_greedy(config, out, MPI.COMM_SELF, verbose=False)
    return config, SnapshotStore(out), report


def decisions(history: list[dict]) -> list[dict]:
    """The rounds without their timings (a round decided again takes other times)."""
    return [{k: v for k, v in h.items() if k != "seconds"} for h in history]


def solve_seconds(store: SnapshotStore) -> dict[int, float]:
    """Each stored record's solve time: changes when a position is solved again."""
    seconds = {}
    for index in store.completed():
        with h5py.File(store.position_path(index), "r") as f:
            seconds[index] = float(f.attrs["seconds"])
    return seconds


def test_greedy_run_appends_positions_and_records_its_history(greedy_run):
    config, store, report = greedy_run
    manifest = store.manifest()
    positions = manifest["positions"]
    sources = [p["source"] for p in positions]
    assert sources[:5] == ["farthest"] * 5 and set(sources[5:]) == {"greedy"}
    assert len(positions) == 7 and report.stop == "max_solves reached"
    assert len({p["node_tag"] for p in positions}) == 7  # never a node twice
    history = json.loads((store.root / HISTORY_FILE).read_text())["rounds"]
    assert history == manifest["greedy"]["history"] == report.history
    assert [h["solves"] for h in history] == [5, 7]
    added = [a["index"] for h in history for a in h["added"]]
    assert added == [5, 6]
    for h in history:
        values = list(h["indicator"].values())
        assert h["max_indicator"] == pytest.approx(max(values))
        assert h["mean_indicator"] == pytest.approx(np.mean(values))
        for a in h["added"]:  # an added position lies in the triangle it came from
            corners = np.array([positions[i]["point"] for i in a["triangle"]])
            point = np.array(a["point"])
            centroid = corners.mean(axis=0)
            assert (
                np.linalg.norm(point - centroid) < np.linalg.norm(corners - centroid, axis=1).min()
            )


def test_the_trainer_and_the_artifact_agree_on_the_indicator(greedy_run, tmp_path):
    """The reduction stores the indicator of the final samples: the last round's."""
    from hapticrom.offline.reduce.reduction import reduce_campaign
    from hapticrom.shared.artifact import read_artifact

    config, store, report = greedy_run
    out = tmp_path / "greedy.h5"
    reduce_campaign(store.root, out, MPI.COMM_SELF, verbose=False, reduction=config)
    stored = read_artifact(out)["samples"]["indicator"]
    last = report.history[-1]["indicator"]
    assert len(stored) == len(last) == 7
    np.testing.assert_allclose(stored, [last[str(i)] for i in range(7)], rtol=1e-10)


def test_a_rerun_solves_nothing_and_a_larger_budget_extends(greedy_run, tmp_path):
    config, store, report = greedy_run
    root = tmp_path / "store"
    shutil.copytree(store.root, root)
    copy_store = SnapshotStore(root)
    before = solve_seconds(copy_store)
    again = run_greedy(config, root, MPI.COMM_SELF, verbose=False)
    assert again.campaign.solved_now == 0
    assert decisions(again.history) == decisions(report.history)
    more = CampaignConfig.from_dict(with_greedy(config.raw, max_solves=8))
    extended = run_greedy(more, root, MPI.COMM_SELF, verbose=False)
    after = solve_seconds(copy_store)
    assert {i: after[i] for i in before} == before  # the old positions were not solved again
    assert sorted(after) == list(range(8)) and extended.campaign.solved_now == 1
    assert [h["solves"] for h in extended.history] == [5, 7, 8]
    assert extended.history[:1] == report.history[:1]  # the 7-solve round was decided again


def test_a_crash_before_the_new_positions_are_solved_resumes_them(greedy_run, tmp_path):
    """The manifest lists the added positions before they are solved: lose their records
    (a crash after the decision) and a rerun solves exactly those."""
    config, store, report = greedy_run
    root = tmp_path / "store"
    shutil.copytree(store.root, root)
    for index in (5, 6):
        SnapshotStore(root).position_path(index).unlink()
    before = solve_seconds(SnapshotStore(root))
    again = run_greedy(config, root, MPI.COMM_SELF, verbose=False)
    assert again.campaign.solved_now == 2
    after = solve_seconds(SnapshotStore(root))
    assert {i: after[i] for i in before} == before
    assert again.history[-1]["indicator"] == pytest.approx(report.history[-1]["indicator"])


def test_a_manifest_edited_by_hand_is_refused(greedy_run, tmp_path):
    config, store, _ = greedy_run
    root = tmp_path / "store"
    shutil.copytree(store.root, root)
    path = SnapshotStore(root).manifest_path
    manifest = json.loads(path.read_text())
    manifest["positions"][6]["source"] = "farthest"  # no longer an added position
    path.write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="not the 6 the campaign's table and greedy"):
        run_greedy(config, root, MPI.COMM_SELF, verbose=False)
    manifest["positions"][6]["source"] = "greedy"
    manifest["greedy"]["history"] = "lost"
    path.write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="greedy history is not a list of rounds"):
        run_greedy(config, root, MPI.COMM_SELF, verbose=False)


@pytest.mark.parametrize("cover", [True, False])
def test_a_target_met_at_the_start_still_covers_the_surface_when_asked(mesh_dir, tmp_path,
                                                                      cover):  # fmt: skip
    """A target every sample meets at once: with ``cover`` the rounds go on, adding only
    nodes the samples do not cover, until none is left or the budget is spent; without, the
    first round stops."""
    data = with_greedy(base_campaign(mesh_dir / "hemisphere-coarse.msh"), target=0.99,
                       max_solves=7, cover=cover)  # fmt: skip
    report = run_greedy(CampaignConfig.from_dict(data), tmp_path / "store", MPI.COMM_SELF,
                        verbose=False)  # fmt: skip
    first = report.history[0]
    assert first["max_indicator"] <= 0.99
    if not cover:
        assert len(report.history) == 1 and report.stop == "target reached"
        return
    assert first["added"] and all(a["triangle"] is None for a in first["added"])
    assert report.history[-1]["solves"] > first["solves"]


def test_run_greedy_needs_the_greedy_table(greedy_run, tmp_path):
    config, _, _ = greedy_run
    plain = replace(config, positions=replace(config.positions, greedy=None))
    with pytest.raises(InputError, match=r"has no \[positions.greedy\] table"):
        run_greedy(plain, tmp_path / "store", MPI.COMM_SELF, verbose=False)


def test_uncovered_nodes_fill_the_farthest_gaps_first():
    """A 20 mm square surface trained on its lower-left quarter only: ``cover`` picks the
    farthest uncovered node first (the far corner), then the next farthest from every
    sample and pick, never a covered node, and nothing within ``reach``."""
    from hapticrom.offline.campaign.greedy import uncovered_nodes
    from hapticrom.offline.reduce.sample_triangulation import triangulate_samples

    g = np.linspace(0.0, 20.0, 21)
    nodes = np.array([(x, y, 0.0) for x in g for y in g])
    index = np.arange(len(nodes)).reshape(21, 21)
    faces = np.vstack([
        np.column_stack([index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()]),
        np.column_stack([index[:-1, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()]),
    ])  # fmt: skip
    taken = [int(index[i, j]) for i in (0, 5, 10) for j in (0, 5, 10)]
    normals = np.tile([0.0, 0.0, 1.0], (len(nodes), 1))
    samples = triangulate_samples(
        nodes[taken], normals[taken], nodes, faces, np.ones(len(faces), dtype=int)
    )
    picks = uncovered_nodes(samples, nodes, set(taken), 3, reach=2.5)
    assert [p.node for p in picks][0] == index[20, 20]
    assert all(p.triangle == -1 for p in picks) and len(picks) == 3
    chosen = nodes[[p.node for p in picks]]
    assert np.all(chosen.max(axis=1) > 10.0)  # outside the trained quarter
    assert uncovered_nodes(samples, nodes, set(taken), 3, reach=100.0) == []
