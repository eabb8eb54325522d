"""Greedy training: solve, estimate the interpolation error, add positions where it is worst.

A campaign with ``[positions.greedy]`` (:class:`~.positions.GreedyMode`) starts from the
table's other positions (points, polar, farthest) and goes in rounds:

1. the campaign machinery (:func:`~.run.run_campaign`) solves every planned position not
   yet stored, in the same resumable directory;
2. rank 0 reads the solved positions' force curves (normal reaction against indentation
   depth at the nominal load steps), puts them on one depth grid (monotone cubic,
   :func:`~hapticrom.offline.reduce.interpolation.on_common_grid`, as the reduction's
   indicator) and
   computes the leave-one-out indicator of every sample
   (:func:`~hapticrom.offline.reduce.indicator.leave_one_out`, the one the artifact stores);
3. it stops when every sample's indicator is at most ``target``, when ``max_solves``
   positions are solved, or when the worst triangles hold no free surface node; otherwise
   it ranks the samples' triangles on the surface by the mean indicator of their corners and
   snaps the centroids of the worst ``per_round`` of them to the nearest surface nodes not
   yet taken (:func:`worst_triangle_nodes`), and the next round solves them.

State and crash safety: the manifest is the one record of what the directory holds. Each
round rewrites it atomically with the positions planned so far (the added ones last, source
``"greedy"``, so earlier positions keep their indices) and the history of the rounds
(``manifest["greedy"]``), before any of the new positions is solved. A rerun (``hapticrom
train`` again after a crash or a stop) reads the added positions back from the manifest,
checks they are what the table plans, solves what is missing and goes on; a round whose
indicator is computed again replaces its history entry. ``greedy.json`` in the campaign
directory is a copy of the history for people and ``bench/greedy_history.py``.

The history, per round: ``solves`` (positions stored, failed ones included), ``solved``,
``max_indicator``/``mean_indicator`` (relative force error), the worst position, every
sample's indicator, the positions added and why the loop stopped. Units: mm, N.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.positions import GreedyMode, plan_positions
from hapticrom.offline.campaign.run import CampaignReport, campaign_manifest, run_campaign
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.mpi import on_rank_zero, print0
from hapticrom.offline.reduce.indicator import leave_one_out
from hapticrom.offline.reduce.inputs import nominal_steps, surface_mesh
from hapticrom.offline.reduce.interpolation import on_common_grid
from hapticrom.offline.reduce.sample_triangulation import triangulate_samples
from hapticrom.offline.reduce.tool_stiffness import sample_stiffness
from hapticrom.online.model import locate_points
from hapticrom.shared.checksum import array_digest
from hapticrom.shared.errors import InputError
from hapticrom.shared.files import write_text_atomically

FORMAT, VERSION = "hapticrom-greedy", 1
HISTORY_FILE = "greedy.json"
# Positions are compared (the manifest's against the table's plan) to this distance, mm.
SAME_POINT = 1e-9


# -- force curves (rank 0, the stored records) -------------------------------------------------
@dataclass
class ForceCurves:
    """Solved positions' force curves on one uniform depth grid.

    ``indices`` (P,) their positions in the campaign; ``points`` (P, 3) mm; ``normals``
    (P, 3) outward (against the push, as the reduction takes them); ``depth`` (K,) mm,
    from 0; ``force`` (P, K) N, the normal reaction on the tool.
    """

    indices: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    force: np.ndarray


def _verified(f: h5py.File, name: str) -> np.ndarray:
    """Dataset ``name`` of a stored record, its checksum verified (InputError if damaged)."""
    data = f[name][()]
    if array_digest(data) != f[name].attrs.get("sha256"):
        raise InputError(f"{f.filename}: dataset {name} fails its checksum (damaged file)")
    return data


def read_force_curve(store: SnapshotStore, index: int, steps: int):
    """(point (3,), push direction (3,), depth (K,), force (K,)) of a stored position at its
    nominal load steps, depth and force along the push direction, both from 0 (mm, N)."""
    with h5py.File(store.position_path(index), "r") as f:
        take = nominal_steps(_verified(f, "load_factor"), steps, index)
        direction = np.asarray(f.attrs["direction"], dtype=float)
        depth = np.r_[0.0, _verified(f, "contact_displacement")[take] @ direction]
        force = np.r_[0.0, _verified(f, "force")[take] @ direction]
        return np.asarray(f.attrs["point"], dtype=float), direction, depth, force


def solved_indices(store: SnapshotStore, indices) -> list[int]:
    """The positions among ``indices`` whose stored solve converged."""
    solved = []
    for index in indices:
        with h5py.File(store.position_path(index), "r") as f:
            if f.attrs.get("status") == "solved":
                solved.append(int(index))
    return solved


def read_force_curves(store: SnapshotStore, indices, steps: int) -> ForceCurves:
    """The force curves of the stored positions ``indices`` on one depth grid."""
    read = [read_force_curve(store, i, steps) for i in indices]
    grid, force = on_common_grid([r[2] for r in read], [r[3] for r in read])
    points = np.array([r[0] for r in read])
    normals = -np.array([r[1] for r in read])
    return ForceCurves(np.asarray(indices, dtype=np.int64), points, normals, grid, force)


def organ_surface(store: SnapshotStore, mesh_file: Path):
    """The organ's surface (vertices, triangles, groups) as the reduction renders it."""
    with h5py.File(store.operators_path, "r") as f:
        coordinates = _verified(f, "node_coordinates")
    return surface_mesh(Path(mesh_file), coordinates)


# -- where to add (pure numpy) -----------------------------------------------------------------
@dataclass(frozen=True)
class Pick:
    """A surface node chosen for a new position: ``node`` (index into the candidate nodes),
    from sample ``triangle`` whose corners' mean indicator is ``score``."""

    node: int
    triangle: int
    score: float


def worst_triangle_nodes(
    sample_points, sample_triangles, indicator, nodes, taken, count: int
) -> list[Pick]:
    """Up to ``count`` new positions: the worst sample triangles' centroids snapped to nodes.

    Triangles (S, 3) of the samples (P, 3) mm are ranked by the mean ``indicator`` (P,) of
    their corners, worst first (ties: the lower triangle index). Each centroid goes to the
    nearest of ``nodes`` (k, 3) mm not in ``taken`` (indices into ``nodes``) nor picked
    before, provided that node is nearer the centroid than every corner of the triangle: a
    farther node would duplicate a sample rather than fill the triangle's gap, and the
    triangle is skipped (the surface mesh cannot resolve it further).
    """
    points = np.asarray(sample_points, dtype=float)
    triangles = np.asarray(sample_triangles, dtype=np.int64).reshape(-1, 3)
    nodes = np.asarray(nodes, dtype=float)
    score = np.asarray(indicator, dtype=float)[triangles].mean(axis=1)
    order = np.lexsort((np.arange(len(triangles)), -score))
    free = np.ones(len(nodes), dtype=bool)
    free[list(taken)] = False
    picks: list[Pick] = []
    for t in order:
        if len(picks) >= count or not free.any():
            break
        centroid = points[triangles[t]].mean(axis=0)
        candidates = np.flatnonzero(free)
        distance = np.linalg.norm(nodes[candidates] - centroid, axis=1)
        nearest = int(np.argmin(distance))
        corners = np.linalg.norm(points[triangles[t]] - centroid, axis=1).min()
        if distance[nearest] < corners:
            node = int(candidates[nearest])
            free[node] = False
            picks.append(Pick(node, int(t), float(score[t])))
    return picks


def uncovered_nodes(samples, nodes, taken, count: int, reach: float) -> list[Pick]:
    """Up to ``count`` nodes (k, 3) mm, not in ``taken``, that the samples' triangulation
    (``samples``: points, normals, triangles) does not cover and that lie farther than
    ``reach`` mm from every sample: the farthest first, each pick counting as a sample for
    the next (farthest-point sampling of the holes and the uncovered rim; a narrow band
    outside the border's chords is left alone). Their ``triangle`` is -1."""
    nodes = np.asarray(nodes, dtype=float)
    inside = locate_points(samples.points, samples.normals, samples.triangles, nodes)[2]
    free = ~inside
    free[list(taken)] = False
    distance = np.min(np.linalg.norm(nodes[:, None] - samples.points[None], axis=2), axis=1)
    picks: list[Pick] = []
    while len(picks) < count and free.any():
        node = int(np.flatnonzero(free)[np.argmax(distance[free])])
        if distance[node] <= reach:
            break
        picks.append(Pick(node, -1, float("inf")))
        free[node] = False
        distance = np.minimum(distance, np.linalg.norm(nodes - nodes[node], axis=1))
    return picks


# -- one round's decision (rank 0) -------------------------------------------------------------
def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def stop_reason(greedy: GreedyMode, solves: int, indicator: np.ndarray) -> str | None:
    """Why the loop stops after a round with ``solves`` positions, or None to go on."""
    if np.all(np.isfinite(indicator)) and float(np.max(indicator)) <= greedy.target:
        return "target reached"
    if solves >= greedy.max_solves:
        return "max_solves reached"
    return None


def _history(manifest: dict, where: Path) -> list[dict]:
    """The rounds recorded in a manifest (none for a campaign not yet greedy), checked."""
    block = manifest.get("greedy", {"history": []})
    history = block.get("history") if isinstance(block, dict) else None
    if not isinstance(history, list) or not all(
        isinstance(h, dict) and type(h.get("solves")) is int for h in history
    ):
        raise InputError(f"{where} is damaged: its greedy history is not a list of rounds")
    return history


def _round_entry(curves: ForceCurves, indicator: np.ndarray, solves: int) -> dict:
    """The history entry of a round, before its decision."""
    worst = int(np.argmax(np.where(np.isfinite(indicator), indicator, np.inf)))
    return {
        "solves": solves,
        "solved": len(curves.indices),
        "max_indicator": _finite_or_none(np.max(indicator)),
        "mean_indicator": _finite_or_none(np.mean(indicator)),
        "worst_position": int(curves.indices[worst]),
        "indicator": {
            str(int(i)): _finite_or_none(e) for i, e in zip(curves.indices, indicator, strict=True)
        },
        "depth_mm": float(curves.depth[-1]),
    }


def near_supports(config, nodes: np.ndarray) -> set[int]:
    """The indices of ``nodes`` within the tool's radius of a clamped node: no position to
    add there (a rigid tip on the hemisphere's clamped rim does not move: zero depth, no
    force curve, and the indicator's interpolation failed on it)."""
    clamped = read_surface(config.problem.mesh.file, "clamped").nodes
    gap = np.min(np.linalg.norm(nodes[:, None] - clamped[None], axis=2), axis=1)
    return set(np.flatnonzero(gap < config.load.contact_radius).tolist())


def _additions(config, manifest: dict, curves: ForceCurves, indicator, surface, count,
               cover_only: bool = False) -> list:  # fmt: skip
    """The positions added after a round: up to ``count`` picks (history entries), on the
    load's surface group, from the samples' triangles on the organ's ``surface`` (only
    uncovered nodes if ``cover_only``: the target holds inside)."""
    load_surface = read_surface(config.problem.mesh.file, config.load.surface)
    tags = [int(p["node_tag"]) for p in manifest["positions"]]
    taken = set(np.searchsorted(load_surface.node_tags, tags).tolist())
    samples = triangulate_samples(
        curves.points, curves.normals, surface.vertices, surface.triangles, surface.groups
    )
    # Coverage first (up to half the round): a hole or an uncovered rim farther than half
    # the samples' median spacing from every sample gets no triangle, so no indicator.
    t = samples.triangles
    spacing = np.median(np.linalg.norm(curves.points[t] - curves.points[np.roll(t, 1, 1)], axis=2))
    picks = []
    taken |= near_supports(config, load_surface.nodes)
    if config.positions.greedy.cover:
        share = count if cover_only else max(1, count // 2)
        picks = uncovered_nodes(samples, load_surface.nodes, taken, share, spacing / 2)
    taken |= {p.node for p in picks}
    if not cover_only:
        picks += worst_triangle_nodes(curves.points, samples.triangles, indicator,
                                      load_surface.nodes, taken, count - len(picks))  # fmt: skip
    first = len(manifest["positions"])
    return [
        {
            "index": first + k,
            "point": [float(c) for c in load_surface.nodes[p.node]],
            "node_tag": int(load_surface.node_tags[p.node]),
            "triangle": (
                [int(curves.indices[c]) for c in samples.triangles[p.triangle]]
                if p.triangle >= 0
                else None  # a node the samples did not cover yet
            ),
            "triangle_indicator": _finite_or_none(p.score),
        }
        for k, p in enumerate(picks)
    ]


def assess_round(config: CampaignConfig, store: SnapshotStore, seconds: float) -> dict:
    """Rank 0, after a round's solves: the indicator, the decision, the positions added.

    Writes the manifest (the added positions planned, the history) and then ``greedy.json``;
    returns the round's history entry (``stop``: why the loop stops, or None).
    """
    t0 = time.perf_counter()
    greedy = config.positions.greedy
    manifest = store.manifest()
    solves = len(manifest["positions"])
    curves = read_force_curves(store, solved_indices(store, range(solves)), config.load.steps)
    surface = organ_surface(store, config.problem.mesh.file)
    stiffness = None  # force control: the indicator of the runtime's scaled blend (2.1)
    if config.load.mode == "force":
        stiffness = sample_stiffness(config, store, curves.points, -curves.normals, surface)
    indicator = leave_one_out(curves.points, curves.normals, surface, curves.force, stiffness)
    entry = _round_entry(curves, indicator, solves)
    entry["stop"] = stop_reason(greedy, solves, indicator)
    entry["added"] = []
    # ``cover``: the target holds where there are samples; holes and rim still get positions
    # (the liver stopped at 16 solves covering a quarter of its loadable surface without).
    cover_only = entry["stop"] == "target reached" and greedy.cover and solves < greedy.max_solves
    if entry["stop"] is None or cover_only:
        count = min(greedy.per_round, greedy.max_solves - solves)
        entry["added"] = _additions(config, manifest, curves, indicator, surface, count,
                                    cover_only)  # fmt: skip
        if entry["added"]:
            entry["stop"] = None
        elif not cover_only:
            entry["stop"] = "no surface node left between the samples"
    history = [h for h in _history(manifest, store.manifest_path) if h["solves"] < solves]
    entry["round"] = len(history)
    entry["seconds"] = {"solves": seconds, "indicator": time.perf_counter() - t0}
    history.append(entry)
    added = [tuple(a["point"]) for a in entry["added"]]
    write_manifest(store, with_added(config, config.positions.added + tuple(added)), history)
    write_history(store, config, history)
    return entry


# -- the directory's state (rank 0) ------------------------------------------------------------
def with_added(config: CampaignConfig, added) -> CampaignConfig:
    """``config`` with the greedy positions ``added`` (mm, in order) after its own; the same
    campaign (hash) as ``config``."""
    positions = replace(config.positions, added=tuple(tuple(a) for a in added))
    return replace(config, positions=positions)


def planned(config: CampaignConfig):
    """The tool positions ``config`` plans, the greedy ones last."""
    surface = read_surface(config.problem.mesh.file, config.load.surface)
    return plan_positions(surface, config.positions)


def write_manifest(store: SnapshotStore, config: CampaignConfig, history: list[dict]) -> None:
    """Rewrite the manifest with ``config``'s planned positions and the greedy history
    (atomic; its creation time kept)."""
    old = store.manifest()
    manifest = campaign_manifest(config, planned(config))
    greedy = config.positions.greedy
    manifest["created"] = old.get("created", manifest["created"])
    manifest["greedy"] = {
        "target": greedy.target,
        "max_solves": greedy.max_solves,
        "per_round": greedy.per_round,
        "history": history,
    }
    write_text_atomically(store.manifest_path, json.dumps(manifest, indent=2) + "\n")


def write_history(store: SnapshotStore, config: CampaignConfig, history: list[dict]) -> None:
    """``greedy.json``: the history of the rounds, for people and the benchmarks (atomic)."""
    greedy = config.positions.greedy
    data = {
        "format": FORMAT,
        "version": VERSION,
        "campaign": config.name,
        "campaign_hash": config.campaign_hash(),
        "target": greedy.target,
        "max_solves": greedy.max_solves,
        "per_round": greedy.per_round,
        "stop": history[-1]["stop"] if history else None,
        "rounds": history,
    }
    write_text_atomically(store.root / HISTORY_FILE, json.dumps(data, indent=1) + "\n")


def resume(config: CampaignConfig, store: SnapshotStore, restart: bool) -> tuple:
    """The greedy positions the directory already planned (mm, in order; none for a new or
    restarted campaign, or another campaign, which :func:`run_campaign` deals with).

    InputError if the manifest's positions are not what the table plans with them.
    """
    if restart or not store.manifest_path.is_file():
        return ()
    manifest = store.manifest()
    if manifest["campaign_hash"] != config.campaign_hash():
        return ()
    _history(manifest, store.manifest_path)
    stored = manifest["positions"]
    added = tuple(tuple(p["point"]) for p in stored if p.get("source") == "greedy")
    plan = planned(with_added(config, added))
    same = len(plan) == len(stored) and all(
        np.linalg.norm(np.subtract(p.point, s["point"])) <= SAME_POINT
        for p, s in zip(plan, stored, strict=True)
    )
    if not same:
        raise InputError(
            f"{store.manifest_path}: its {len(stored)} positions are not the {len(plan)} "
            "the campaign's table and greedy positions plan (edited by hand?); pass "
            "--restart to start over"
        )
    return added


# -- the loop (every rank) ---------------------------------------------------------------------
@dataclass
class GreedyReport:
    """A greedy run: its rounds (the history, this run's and earlier ones), why it stopped,
    the last round's campaign report and the wall time of this run (s)."""

    history: list[dict]
    stop: str
    campaign: CampaignReport
    wall_seconds: float


def progress_line(entry: dict, greedy: GreedyMode) -> str:
    """One line per round: solves, the indicator's max and mean, what happens next."""

    def percent(value):
        return "inf" if value is None else f"{100 * value:.2f} %"

    added = entry["added"]
    if entry["stop"]:
        then = f"stop: {entry['stop']}"
    else:
        then = f"adding {len(added)} position(s) {added[0]['index']}..{added[-1]['index']}"
    return (
        f"greedy round {entry['round']}: {entry['solves']} solves ({entry['solved']} solved), "
        f"indicator max {percent(entry['max_indicator'])} (position {entry['worst_position']}), "
        f"mean {percent(entry['mean_indicator'])}, target {100 * greedy.target:g} %; {then}"
    )


def run_greedy(
    config: CampaignConfig,
    out_dir: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    ranks_per_solve: int = 1,
    restart: bool = False,
    verbose: bool = True,
    refinement_check: bool = False,
) -> GreedyReport:
    """Greedy training of ``config`` (it has ``[positions.greedy]``) in the campaign
    directory ``out_dir``, resumed where it stopped; see the module doc. Collective."""
    greedy = config.positions.greedy
    if greedy is None:
        raise InputError(f"campaign '{config.name}' has no [positions.greedy] table")
    t0 = time.perf_counter()
    store = SnapshotStore(out_dir)
    added = on_rank_zero(comm, resume, config, store, restart)
    if added and verbose:
        print0(comm, f"greedy: resuming with {len(added)} position(s) added earlier")
    while True:
        round_config = with_added(config, added)
        report = run_campaign(
            round_config, out_dir, comm, ranks_per_solve, restart, verbose, refinement_check
        )
        restart = refinement_check = False  # the first round only
        entry = on_rank_zero(comm, assess_round, round_config, store, report.wall_seconds)
        if verbose:
            print0(comm, progress_line(entry, greedy))
        if entry["stop"]:
            break
        added = added + tuple(tuple(a["point"]) for a in entry["added"])
    history = on_rank_zero(comm, lambda: _history(store.manifest(), store.manifest_path))
    return GreedyReport(history, entry["stop"], report, time.perf_counter() - t0)
