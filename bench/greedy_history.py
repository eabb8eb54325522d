"""The greedy trainer's history against the true error at held-out positions.

    mpirun -n 2 python bench/greedy_history.py MODEL.h5 --out DIR [--held-out 12]
        [--campaign-dir DIR] [--work DIR]

For a model trained greedily (``[positions.greedy]``, ``hapticrom train``), with its
campaign directory (default ``MODEL.campaign``, as ``train`` writes it):

1. held-out positions, solved once (full order, through the campaign machinery, resumable
   in ``--work``, default ``MODEL.greedy-heldout-N``): ``--held-out`` surface nodes spread
   over the whole trained region by farthest-point sampling among the load surface's nodes
   that the final model locates inside its samples' triangulation and that are no training
   position;
2. for every round of the history (its first ``solves`` positions, the ones solved): the
   samples' triangulation on the surface, the runtime's location of each held-out position
   in it and the blend of the samples' force curves with its weights, on one depth grid;
   the true error at a held-out position is max_k |F_blend(d_k) - F(d_k)| / max_k F(d_k),
   the relative force error the indicator estimates;
3. the indicator's effectivity, indicator / true error: per round the largest indicator
   (the trainer's stopping figure) over the largest true error, and at the held-out
   positions the blended indicator sum_i w_i e_i (``sim.error_estimate``) over the true
   error there (median, min, max over the positions).

Writes ``DIR/greedy_history.md`` (the table), ``DIR/greedy_history.json`` and
``DIR/greedy_history.png`` (solves against the indicator and the true error, log scale).
Units: mm, N; errors are fractions (1 = 100 %).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.greedy import (
    FORMAT,
    HISTORY_FILE,
    VERSION,
    on_common_grid,
    organ_surface,
    read_force_curve,
    solved_indices,
)
from hapticrom.offline.campaign.run import run_campaign
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.mpi import on_rank_zero, print0
from hapticrom.offline.reduce.indicator import leave_one_out
from hapticrom.offline.reduce.sample_triangulation import triangulate_samples
from hapticrom.offline.reduce.tool_stiffness import sample_stiffness
from hapticrom.online.model import locate_points
from hapticrom.shared.errors import HapticromError, InputError
from hapticrom.shared.files import read_versioned_json, write_text_atomically

DEFAULT_HELD_OUT = 12


# -- held-out positions (rank 0) ---------------------------------------------------------------
def farthest_points(points: np.ndarray, count: int) -> list[int]:
    """``count`` indices of ``points`` (n, 3) spread by farthest-point sampling, from the point
    nearest their centroid (ties: the lowest index)."""
    picked = [int(np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    gap = np.linalg.norm(points - points[picked[0]], axis=1)
    while len(picked) < min(count, len(points)):
        picked.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.linalg.norm(points - points[picked[-1]], axis=1))
    return picked


def held_out_points(store: SnapshotStore, manifest: dict, config, count: int) -> np.ndarray:
    """(count, 3) mm: load-surface nodes inside the final samples' triangulation, no training
    position, spread by farthest-point sampling."""
    load = read_surface(manifest["mesh"]["file"], config.load.surface)
    curves = training_curves(store, manifest, config, len(manifest["positions"]))
    surface = organ_surface(store, manifest["mesh"]["file"])
    final = triangulate_samples(
        curves["points"], curves["normals"], surface.vertices, surface.triangles, surface.groups
    )
    inside = locate_points(final.points, final.normals, final.triangles, load.nodes)[2]
    trained = {int(p["node_tag"]) for p in manifest["positions"]}
    free = np.flatnonzero(inside & ~np.isin(load.node_tags, list(trained)))
    if len(free) == 0:
        raise InputError("no surface node of the trained region is left to hold out")
    return load.nodes[free[farthest_points(load.nodes[free], count)]]


def held_out_config(manifest: dict, points: np.ndarray) -> CampaignConfig:
    """The training campaign with the held-out points as its only positions."""
    campaign = copy.deepcopy(manifest["campaign"])
    campaign.pop("cutting", None)
    campaign["positions"] = {"points": points.tolist()}
    campaign.setdefault("campaign", {})["name"] = "greedy-held-out"
    campaign["mesh"]["file"] = manifest["mesh"]["file"]
    return CampaignConfig.from_dict(campaign, source="held-out campaign")


# -- curves and errors (rank 0) ------------------------------------------------------------------
def training_curves(store: SnapshotStore, manifest: dict, config, solves: int) -> dict:
    """The solved positions among the first ``solves``: indices, points, outward normals,
    depths and forces (each its own depths)."""
    indices = solved_indices(store, range(solves))
    read = [read_force_curve(store, i, config.load.steps) for i in indices]
    return {
        "indices": indices,
        "points": np.array([r[0] for r in read]),
        "normals": -np.array([r[1] for r in read]),
        "depths": [r[2] for r in read],
        "forces": [r[3] for r in read],
    }


def round_errors(training: dict, held: dict, surface, stiffness: dict | None = None) -> dict:
    """One round: the indicator of its samples, the true error at every held-out position,
    the blended indicator there and whether the runtime locates it inside the region.
    ``stiffness``: None, or the tool's linear stiffness of every training position (by
    index; the held-out positions' in ``held["stiffness"]``): the curves are then blended
    with the weights w_j k(x) / k_j, k(x) the held-out position's own (the runtime reads it
    from its lattice, within 2.4 % on the liver: ``hapticrom accuracy`` measures the
    runtime itself)."""
    n = len(training["indices"])
    grid, force = on_common_grid(
        training["depths"] + held["depths"], training["forces"] + held["forces"]
    )
    samples, truth = force[:n], force[n:]
    k_samples, k_held = np.ones(n), np.ones(len(truth))
    if stiffness is not None:
        k_samples = np.array([stiffness[i] for i in training["indices"]])
        k_held = held["stiffness"]
    indicator = leave_one_out(training["points"], training["normals"], surface, samples,
                              None if stiffness is None else k_samples)  # fmt: skip
    tri = triangulate_samples(
        training["points"],
        training["normals"],
        surface.vertices,
        surface.triangles,
        surface.groups,
    )
    corners, weights, inside = locate_points(tri.points, tri.normals, tri.triangles, held["points"])
    scaled = samples / k_samples[:, None]
    predicted = k_held[:, None] * np.einsum("hc,hck->hk", weights, scaled[corners])
    error = np.max(np.abs(predicted - truth), axis=1) / np.max(truth, axis=1)
    blended = np.einsum("hc,hc->h", weights, indicator[corners])
    return {
        "indicator": indicator,
        "error": error,
        "blended": blended,
        "inside": inside,
        "depth": float(grid[-1]),
    }


def round_row(entry: dict, errors: dict) -> dict:
    """A row of the table: the trainer's figures, the true error, the effectivities."""
    ratio = errors["blended"] / errors["error"]
    finite = ratio[np.isfinite(ratio)]
    return {
        "round": entry["round"],
        "solves": entry["solves"],
        "solved": entry["solved"],
        "added": len(entry["added"]),
        "max_indicator": entry["max_indicator"],
        "mean_indicator": entry["mean_indicator"],
        "max_indicator_recomputed": float(np.max(errors["indicator"])),
        "max_error": float(np.max(errors["error"])),
        "mean_error": float(np.mean(errors["error"])),
        "max_over_max": float(np.max(errors["indicator"]) / np.max(errors["error"])),
        "blended_over_true": {
            "median": float(np.median(finite)) if finite.size else None,
            "min": float(np.min(finite)) if finite.size else None,
            "max": float(np.max(finite)) if finite.size else None,
        },
        "held_out_outside": int(np.sum(~errors["inside"])),
        "error_per_position": errors["error"].tolist(),
        "blended_indicator_per_position": errors["blended"].tolist(),
        "depth_mm": errors["depth"],
    }


# -- output (rank 0) -----------------------------------------------------------------------------
def _pct(value) -> str:
    return "inf" if value is None or not np.isfinite(value) else f"{100 * value:.2f}"


def markdown(rows: list[dict], meta: dict) -> str:
    """The table of the rounds, with what was measured how."""
    lines = [
        f"Greedy history of `{meta['model']}` ({meta['held_out']} held-out positions, "
        f"indicator target {100 * meta['target']:g} %, stop: {meta['stop']})",
        "",
        "| round | solves | added | max indicator % | mean indicator % | max true error % | "
        "mean true error % | max/max | blended/true median [min, max] | held-out outside |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        b = r["blended_over_true"]
        spread = (
            "-" if b["median"] is None else f"{b['median']:.2f} [{b['min']:.2f}, {b['max']:.2f}]"
        )
        lines.append(
            f"| {r['round']} | {r['solves']} | {r['added']} | {_pct(r['max_indicator'])} | "
            f"{_pct(r['mean_indicator'])} | {_pct(r['max_error'])} | {_pct(r['mean_error'])} | "
            f"{r['max_over_max']:.2f} | {spread} | {r['held_out_outside']} |"
        )
    lines += [
        "",
        "true error: max over the depth grid of |blended - full order| / max full-order force "
        "at a held-out position; max/max: the largest indicator (recomputed on the depth grid "
        "shared with the held-out curves) over the largest true error; "
        "blended/true: sum_i w_i e_i (sim.error_estimate) over the true error at each held-out "
        "position (> 1: the indicator overestimates).",
    ]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], target: float, path: Path) -> None:
    """Solves against the indicator (max, mean) and the true held-out error (max, mean)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    solves = [r["solves"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for key, style, label in (
        ("max_indicator", "o-", "max indicator (trainer)"),
        ("mean_indicator", "o--", "mean indicator"),
        ("max_error", "s-", "max true error (held out)"),
        ("mean_error", "s--", "mean true error"),
    ):
        values = [np.nan if r[key] is None else 100 * r[key] for r in rows]
        ax.semilogy(solves, values, style, label=label)
    ax.axhline(100 * target, color="grey", lw=0.8, ls=":", label="target")
    for axis in (ax.yaxis.set_major_formatter, ax.yaxis.set_minor_formatter):
        axis(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.set_xlabel("solves")
    ax.set_ylabel("relative force error (%)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# -- the benchmark ---------------------------------------------------------------------------------
def read_inputs(model: Path, campaign_dir: Path):
    """Rank 0: the campaign's manifest, configuration and greedy history, checked against the
    model (same campaign)."""
    from hapticrom.shared.artifact import read_artifact

    store = SnapshotStore(campaign_dir)
    manifest = store.manifest()
    history = read_versioned_json(campaign_dir / HISTORY_FILE, FORMAT, VERSION, "history")
    trained = read_artifact(model).group_attrs["model"].get("campaign_hash")
    if trained != manifest["campaign_hash"]:
        raise InputError(f"{model} was not trained on the campaign in {campaign_dir}")
    campaign = copy.deepcopy(manifest["campaign"])
    campaign["mesh"]["file"] = manifest["mesh"]["file"]  # resolved: the loads assemble on it
    config = CampaignConfig.from_dict(campaign, source=str(store.manifest_path))
    return manifest, config, history


def compare_rounds(store, manifest, config, history, work: Path) -> list[dict]:
    """Rank 0: a row per round of the history against the held-out solves in ``work``."""
    held_store = SnapshotStore(work)
    held_indices = solved_indices(held_store, held_store.completed())
    read = [read_force_curve(held_store, i, config.load.steps) for i in held_indices]
    held = {
        "points": np.array([r[0] for r in read]),
        "pushes": np.array([r[1] for r in read]),
        "depths": [r[2] for r in read],
        "forces": [r[3] for r in read],
    }
    surface = organ_surface(store, manifest["mesh"]["file"])
    stiffness = None  # force control: the runtime's blend scaled by the tool's stiffness
    if config.load.mode == "force":  # every position's once (one factorisation of K0)
        last = training_curves(store, manifest, config, max(h["solves"] for h in history["rounds"]))
        k = sample_stiffness(config, store, np.vstack([last["points"], held["points"]]),
                             np.vstack([-last["normals"], held["pushes"]]), surface)  # fmt: skip
        stiffness = dict(zip(last["indices"], k[: len(last["indices"])], strict=True))
        held["stiffness"] = k[len(last["indices"]) :]
    rows = []
    for entry in history["rounds"]:
        training = training_curves(store, manifest, config, entry["solves"])
        rows.append(round_row(entry, round_errors(training, held, surface, stiffness)))
    return rows


def main(argv=None) -> int:
    """Solve the held-out positions, compare every round, write the table, JSON and plot."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", type=Path, help="a model trained greedily (.h5)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--held-out", type=int, default=DEFAULT_HELD_OUT, help="held-out positions")
    p.add_argument("--campaign-dir", type=Path, help="default: MODEL with suffix .campaign")
    p.add_argument("--work", type=Path, help="held-out solves (default MODEL.greedy-heldout-N)")
    args = p.parse_args(argv)
    if args.held_out < 1:
        p.error(f"--held-out must be at least 1, got {args.held_out}")
    comm = MPI.COMM_WORLD
    campaign_dir = args.campaign_dir or args.model.with_suffix(".campaign")
    work = args.work or args.model.with_suffix(f".greedy-heldout-{args.held_out}")
    store = SnapshotStore(campaign_dir)
    t0 = time.perf_counter()
    manifest, config, history = on_rank_zero(comm, read_inputs, args.model, campaign_dir)
    points = on_rank_zero(comm, held_out_points, store, manifest, config, args.held_out)
    run_campaign(held_out_config(manifest, points), work, comm)
    solves = time.perf_counter() - t0
    rows = on_rank_zero(comm, compare_rounds, store, manifest, config, history, work)
    if comm.rank == 0:
        write_outputs(args, rows, history, points, solves, time.perf_counter() - t0 - solves)
    return 0


def write_outputs(args, rows, history, points, solves: float, comparison: float) -> None:
    """Rank 0: the markdown table (printed too), the JSON and the plot in ``args.out``."""
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {
        "model": str(args.model),
        "held_out": len(points),
        "target": history["target"],
        "stop": history["stop"],
    }
    table = markdown(rows, meta)
    write_text_atomically(args.out / "greedy_history.md", table)
    data = {
        **meta,
        "held_out_points": points.tolist(),
        "rounds": rows,
        "seconds": {"held_out_solves": solves, "comparison": comparison},
    }
    write_text_atomically(args.out / "greedy_history.json", json.dumps(data, indent=1) + "\n")
    plot(rows, history["target"], args.out / "greedy_history.png")
    print(table, flush=True)
    print(f"held-out solves {solves:.1f} s, comparison {comparison:.1f} s; wrote {args.out}")


if __name__ == "__main__":
    try:
        sys.exit(main())
    except HapticromError as exc:
        print0(MPI.COMM_WORLD, f"greedy_history: error: {exc}")
        sys.exit(2)
