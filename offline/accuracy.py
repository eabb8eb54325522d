"""The held-out check of a reduced model (``hapticrom accuracy``).

The full-order model is solved at tool positions the model was not trained on, exactly as
in its training campaign (a campaign of its own, resumable, in a work directory); at each
of them the online runtime predicts the normal force along the same indentation path and
the surface displacement, with every combination the artifact supports (PODI and
Grassmann fields with the stored curves; PODI with the POD-ANM series). The errors are
stated against the targets of :mod:`hapticrom.shared.accuracy` with a verdict.

Held-out positions, inside the trained region (but with ``outside``) and never a training
position:

- by default, the centroids of sample triangles spread over the region (thesis Table 2.2
  layout: one per triangle, in the order of angle and radius), snapped to the nearest
  surface node;
- with a seed, surface nodes drawn at random (``numpy.random.default_rng(seed)``) among
  those of the tool's surface group that the runtime locates inside the samples'
  triangulation on the surface;
- ``softest``: the node of that region nearest each of the softest samples (the deepest
  solved, then the least force at the depth grid's end): under force control the places
  that reach the trained force deepest, where the runtime extrapolates in depth;
- ``outside`` (with a seed): random nodes of the tool's surface group that the runtime
  does *not* locate inside the triangulation (it clamps a contact there to the border):
  what a tool gets there;
- ``anywhere`` (with a seed): random nodes of the whole tool's surface group, inside the
  region or not: the force a tool meets anywhere it can touch, the summary split by region.

Selection is numpy; the solves go through :func:`~hapticrom.offline.campaign.run.run_campaign`
(its progress bar); the comparison uses the online runtime; output is a text table on
rank 0 and a JSON file that ``hapticrom report --accuracy`` reads. Units: mm, N.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.meshes.msh import Surface, read_surface
from hapticrom.offline.mpi import on_rank_zero
from hapticrom.online.kernels import face_floors
from hapticrom.online.model import inside_trained_region
from hapticrom.shared.accuracy import QUANTITIES, TARGETS, target, verdict
from hapticrom.shared.artifact_rules import solved_depths
from hapticrom.shared.errors import HapticromError, InputError
from hapticrom.shared.geometry import plan_view, vertex_normals

FORMAT, VERSION = "hapticrom-accuracy", 3  # 3: transport columns, dent, deepest, beyond
# how the held-out nodes are chosen -> the work directory's tag (N positions, seed S)
SELECTIONS = {
    "centroids": "{count}",
    "random": "{count}-seed{seed}",
    "softest": "{count}-softest",
    "outside": "{count}-outside-seed{seed}",
    "anywhere": "{count}-anywhere-seed{seed}",
}
RANDOM_NODES = {"random": "region", "outside": "outside", "anywhere": "anywhere"}
RESPONSE_COLUMNS = {"curves": "curves", "anm": "ANM"}


@dataclass(frozen=True)
class HeldOutPosition:
    """A held-out tool position: a surface node (mm), how far the snap moved it, why chosen."""

    point: tuple[float, float, float]
    moved: float  # mm, in plan view, from the chosen point to the node (0: a node was drawn)
    source: str


@dataclass(frozen=True)
class HeldOutPlan:
    """What to solve: the training campaign with the held-out positions instead of its own."""

    model: str
    campaign: dict
    positions: list[HeldOutPosition]
    method: str  # one of SELECTIONS
    seed: int | None
    requested: int


@dataclass
class Step:
    """One load step at one held-out position: full order and each combination's ROM."""

    position: int
    point: list[float]
    depth: float  # mm, along the load direction
    f_fem: float  # N, normal force of the full-order model
    force: dict[str, float] = field(default_factory=dict)  # N, per combination
    dent: dict[str, float] = field(default_factory=dict)  # relative error of the dent under
    # the tool (the normal displacement of the surface node at the tool), per combination
    deepest: dict[str, float] = field(default_factory=dict)  # mm from the tool to the
    # rendered dent's deepest surface node, per combination
    deepest_gap: dict[str, float] = field(default_factory=dict)  # mm from the full order's
    # deepest surface node to the rendered one's, per combination
    deepest_fem: float = 0.0  # mm from the tool to the full order's deepest surface node
    beyond: dict[str, bool] = field(default_factory=dict)  # the runtime extrapolated in depth
    element: float = 0.0  # mm, the longest surface edge at the tool: "one element"
    # last: the attribute named field hides dataclasses.field below it
    field: dict[str, float] = field(default_factory=dict)  # relative L2 error, per combination


# -- selection (numpy) -------------------------------------------------------------------
def plan_coordinates(samples: dict, x: np.ndarray) -> np.ndarray:
    """Coordinates (..., 2) mm of points ``x`` (..., 3) in the samples' plan view
    (:func:`~hapticrom.shared.geometry.plan_view`): for ordering and distances only."""
    origin, axes, _ = plan_view(samples["points"], samples["normals"])
    return (np.asarray(x) - origin) @ axes.T


def trained_nodes(samples: dict, surface: Surface) -> set[int]:
    """Indices of the surface nodes that are training positions."""
    d = np.linalg.norm(surface.nodes[None, :, :] - samples["points"][:, None, :], axis=2)
    return {int(i) for i in np.argmin(d, axis=1)}


def region_nodes(samples: dict, surface: Surface) -> np.ndarray:
    """Surface nodes of the trained region: where the runtime locates a contact inside the
    samples' triangulation on the surface (not clamped, nor beneath a triangle's floor:
    ``samples["floors"]``, the runtime's from the whole surface, else from the loadable
    surface alone)."""
    floors = samples.get("floors")
    if floors is None:
        floors = face_floors(samples["points"], samples["normals"], samples["triangles"],
                             surface.nodes, surface.normals, surface.faces)  # fmt: skip
    inside = inside_trained_region(
        samples["points"], samples["normals"], samples["triangles"], surface.nodes, floors
    )
    return np.flatnonzero(inside)


def centroid_positions(samples: dict, surface: Surface, count: int) -> list[HeldOutPosition]:
    """Up to ``count`` centroids of sample triangles spread over the region, snapped to nodes.

    Triangles are ordered by angle and radius and ``count`` of them picked evenly along that
    order. A centroid goes to the nearest node of the trained region (:func:`region_nodes`:
    the nearest node of the whole surface may lie just outside it, where the runtime clamps);
    one whose node is a training position or already taken gives way to the next unpicked
    triangle.
    """
    triangles = samples["triangles"]
    centroids = plan_coordinates(samples, samples["points"])[triangles].mean(axis=1)
    centroids3 = samples["points"][triangles].mean(axis=1)
    order = np.argsort(np.arctan2(centroids[:, 1], centroids[:, 0]) + 10 * np.hypot(*centroids.T))
    spread = order[np.linspace(0, len(order) - 1, min(count, len(order))).astype(int)]
    picked = {int(t) for t in spread}
    candidates = [int(t) for t in spread] + [int(t) for t in order if int(t) not in picked]
    region = region_nodes(samples, surface)
    taken, positions = trained_nodes(samples, surface), []
    for t in candidates if len(region) else []:
        x = centroids3[t]
        node = int(region[np.argmin(np.linalg.norm(surface.nodes[region] - x, axis=1))])
        if node in taken:
            continue
        taken.add(node)
        moved = float(np.linalg.norm(plan_coordinates(samples, surface.nodes[node]) - centroids[t]))
        point = tuple(float(c) for c in surface.nodes[node])
        positions.append(HeldOutPosition(point, moved, f"centroid of sample triangle {t}"))
        if len(positions) == count:
            break
    return positions


def random_positions(
    samples: dict, surface: Surface, count: int, seed: int, where: str = "region"
) -> list[HeldOutPosition]:
    """Up to ``count`` distinct surface nodes, not training positions, drawn with
    ``numpy.random.default_rng(seed)`` among those of ``where``: "region", the trained
    region; "outside", the tool's surface group outside it (where the runtime clamps a
    contact to the region's border: between the outermost samples and the group's border,
    and in the holes); "anywhere", the whole group."""
    trained = trained_nodes(samples, surface)
    region = region_nodes(samples, surface)
    nodes = {"region": region, "outside": np.setdiff1d(np.arange(len(surface.nodes)), region),
             "anywhere": np.arange(len(surface.nodes))}[where]  # fmt: skip
    candidates = [int(n) for n in nodes if int(n) not in trained]
    if not candidates:
        return []
    rng = np.random.default_rng(seed)
    picked = rng.choice(candidates, size=min(count, len(candidates)), replace=False)
    inside = set(region.tolist())
    what = {"region": "random surface node", "outside": "outside the trained region",
            "anywhere": "random node of the surface group"}[where]  # fmt: skip
    return [
        HeldOutPosition(
            tuple(float(c) for c in surface.nodes[n]),
            0.0,
            f"{what} (seed {seed})"
            + ("" if where != "anywhere" else ", inside" if n in inside else ", outside"),
        )
        for n in picked
    ]


def softest_positions(samples: dict, surface: Surface, count: int) -> list[HeldOutPosition]:
    """Up to ``count`` distinct nodes of the trained region, not training positions: the
    nearest to each sample in the order of its softness, softest first: the deepest solved
    depth (artifact 2.3), then the least force at the depth grid's end."""
    trained = trained_nodes(samples, surface)
    region = np.array([int(n) for n in region_nodes(samples, surface) if int(n) not in trained])
    force = np.asarray(samples["force"])[:, -1]
    solved = solved_depths(samples)
    depth_end = float(np.asarray(samples["depth"])[-1])
    order = np.lexsort((force, -np.round(solved / depth_end, 9)))  # rounding: no tie-breaker
    positions, taken = [], set()
    for i in order if len(region) else []:
        gaps = np.linalg.norm(surface.nodes[region] - np.asarray(samples["points"])[i], axis=1)
        node = int(region[np.argmin(gaps)])
        if node in taken:
            continue
        taken.add(node)
        why = (f"nearest sample {i} (solved to {solved[i]:.3g} mm, {force[i]:.3g} N at the "
               f"grid's end, {gaps.min():.3g} mm away)")  # fmt: skip
        positions.append(HeldOutPosition(tuple(float(c) for c in surface.nodes[node]), 0.0, why))
        if len(positions) == count:
            break
    return positions


# -- the plan (rank 0: the artifact and the mesh) -------------------------------------------
def _mesh_file(model: str, info: dict) -> Path:
    """The mesh the model was trained on, checked against the digest the artifact records."""
    from hapticrom.shared.checksum import file_digest

    if "mesh_file" not in info:
        raise InputError(f"{model} does not name the mesh it was trained on (mesh_file)")
    mesh = Path(info["mesh_file"])
    if not mesh.is_file():
        raise InputError(
            f"{model} was trained on {mesh}, which is not found: the held-out solves need it"
        )
    if "mesh_sha256" in info and file_digest(mesh) != info["mesh_sha256"]:
        raise InputError(
            f"{mesh} has changed since {model} was trained on it (SHA-256 differs): "
            "held-out solves on it would not test this model"
        )
    return mesh


def _plan(model: str, count: int, seed: int | None, method: str) -> HeldOutPlan:
    from hapticrom.shared.artifact import read_artifact

    artifact = read_artifact(model)
    info, samples = artifact.group_attrs["model"], dict(artifact["samples"])
    vertices = np.asarray(artifact["surface"]["vertices"], dtype=np.float64)
    faces = np.asarray(artifact["surface"]["triangles"], dtype=np.int64)
    samples["floors"] = face_floors(samples["points"], samples["normals"], samples["triangles"],
                                    vertices, vertex_normals(vertices, faces), faces)  # fmt: skip
    if "campaign" not in artifact.attrs:
        raise InputError(f"{model} does not record its training campaign: nothing to repeat")
    mesh = _mesh_file(model, info)
    surface = read_surface(mesh, info["surface_group"])
    if method == "softest":
        positions = softest_positions(samples, surface, count)
    elif method == "centroids":
        positions = centroid_positions(samples, surface, count)
    else:
        positions = random_positions(samples, surface, count, seed, RANDOM_NODES[method])
    if not positions:
        where = {"outside": "outside the trained region", "anywhere": "of the surface group"}
        raise InputError(f"{model}: no surface node {where.get(method, 'of the trained region')}"
                         " is left to hold out")  # fmt: skip
    campaign = json.loads(json.dumps(artifact.attrs["campaign"]))  # a deep copy
    campaign.pop("cutting", None)  # the solves only
    campaign["positions"] = {"points": [list(p.point) for p in positions]}
    campaign.setdefault("campaign", {})["name"] = "held-out"
    campaign["mesh"]["file"] = str(mesh)
    return HeldOutPlan(str(model), campaign, positions, method, seed, count)


def selection(seed: int | None, method: str | None) -> tuple[int | None, str]:
    """(seed, method) with the defaults: centroids without a seed, random nodes of the
    region with one; the random selections need a seed (0 if none is given)."""
    method = method or ("centroids" if seed is None else "random")
    if method not in SELECTIONS:
        raise InputError(f"held-out selection {method!r}: expected one of {', '.join(SELECTIONS)}")
    if method in RANDOM_NODES:
        return (seed or 0), method
    return None, method


def plan_held_out(model: str, count: int, seed: int | None = None, comm=MPI.COMM_WORLD,
                  method: str | None = None):  # fmt: skip
    """The held-out positions of ``model`` chosen by ``method`` (:data:`SELECTIONS`; default:
    centroids without a seed, random region nodes with one). Rank 0 reads; every rank gets
    the plan."""
    seed, method = selection(seed, method)
    return on_rank_zero(comm, _plan, str(model), count, seed, method)


def default_work(model: str | Path, count: int, seed: int | None,
                 method: str | None = None) -> Path:  # fmt: skip
    """MODEL.heldout-N (centroids), MODEL.heldout-N-seedS, MODEL.heldout-N-softest,
    MODEL.heldout-N-outside-seedS or MODEL.heldout-N-anywhere-seedS: one directory per
    selection."""
    seed, method = selection(seed, method)
    return Path(model).with_suffix(".heldout-" + SELECTIONS[method].format(count=count, seed=seed))


# -- the full-order solves --------------------------------------------------------------------
def held_out_config(plan: HeldOutPlan):
    """The campaign configuration of the held-out solves."""
    from hapticrom.offline.campaign.config import CampaignConfig

    return CampaignConfig.from_dict(plan.campaign, source=f"held-out campaign of {plan.model}")


def solve_held_out(plan: HeldOutPlan, work, comm=MPI.COMM_WORLD, restart=False, verbose=True):
    """Run the held-out campaign in ``work`` (resumable, the campaign's progress bar on rank
    0 when ``verbose``); its CampaignReport."""
    from hapticrom.offline.campaign.run import run_campaign

    return run_campaign(held_out_config(plan), work, comm, restart=restart, verbose=verbose)


# -- the comparison (rank 0, online runtime) ----------------------------------------------------
def combinations(model) -> list[str]:
    """The interpolation + response combinations the model offers: its rendered surfaces
    (:func:`~hapticrom.online.model.field_interpolations`) with each response, and
    Grassmann with the curves."""
    from hapticrom.online.model import field_interpolations

    fields = field_interpolations(model)
    names = [f"{field}+curves" for field in fields]
    if model.grassmann:
        names.append("grassmann+curves")
    if model.anm:
        names += [f"{field}+anm" for field in fields]
    return names


def relative_l2(approx: np.ndarray, exact: np.ndarray) -> float:
    """||approx - exact|| / ||exact|| (NaN for an exact zero)."""
    norm = float(np.linalg.norm(exact))
    return float(np.linalg.norm(approx - exact)) / norm if norm > 0 else float("nan")


def dent_under_tool(field: np.ndarray, normal: np.ndarray, vertices: np.ndarray,
                    tool: int) -> tuple[float, float]:  # fmt: skip
    """(the normal displacement into the organ of the surface node at the tool, mm; the
    distance from the tool to the node that moves in deepest, mm)."""
    deepest = deepest_node(field, normal)
    dent = -float(field[tool] @ normal)
    return dent, float(np.linalg.norm(vertices[deepest] - vertices[tool]))


def deepest_node(field: np.ndarray, normal: np.ndarray) -> int:
    """The surface node that moves in deepest along -normal."""
    return int(np.argmax(-(field @ normal)))


def element_size(model, vertex: int) -> float:
    """The longest surface edge (mm) at a vertex: "one element" from it."""
    t = model.triangles[np.any(model.triangles == vertex, axis=1)]
    p = model.vertices[t]
    return float(np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2))) if len(t) else 0.0


def compare_position(model, index: int, data: dict, attrs: dict) -> tuple[list[Step], bool]:
    """Every load step of one held-out solve against each combination; and whether the
    runtime clamped the contact (outside its trained region)."""
    direction = np.asarray(attrs["direction"])
    point = np.asarray(attrs["point"])
    steps = [
        Step(index, point.tolist(), float(u @ direction), float(f @ direction))
        for u, f in zip(data["contact_displacement"], data["force"], strict=True)
    ]
    nodes = model.artifact["surface"]["nodes"]
    tool = int(np.argmin(np.linalg.norm(model.vertices - point, axis=1)))
    for step in steps:
        step.element = element_size(model, tool)
    out = np.zeros_like(model.vertices)
    outside = False
    # a held-out place may go deeper than the default limit (10x the shallowest sample's
    # depth: the liver outside its region to 4.8 mm): what the model answers there is measured
    reach = max(10 * model.trained_depth, 1.01 * max((s.depth for s in steps), default=0.0))
    for name in combinations(model):
        sim = model.simulator(*name.split("+"), max_displacement=reach)
        sim.set_contact(point)
        outside |= bool(sim.outside_trained_region)
        for step, u in zip(steps, data["displacement"], strict=True):
            normal = sim.contact_normal.copy()
            step.force[name] = float(sim.step_displacement(-step.depth * normal) @ normal)
            # a depth the runtime extrapolates to (not one at the last knot but for rounding)
            step.beyond[name] = sim.beyond_trained_depth and (
                step.depth > (1 + 1e-6) * model.trained_depth
            )
            sim.surface_displacement(out)
            exact = u.reshape(-1, 3)[nodes]
            step.field[name] = relative_l2(out, exact)
            dent, step.deepest[name] = dent_under_tool(out, normal, model.vertices, tool)
            exact_dent, step.deepest_fem = dent_under_tool(exact, normal, model.vertices, tool)
            ours, theirs = deepest_node(out, normal), deepest_node(exact, normal)
            step.deepest_gap[name] = float(np.linalg.norm(model.vertices[ours]
                                                          - model.vertices[theirs]))  # fmt: skip
            step.dent[name] = abs(dent - exact_dent) / exact_dent if exact_dent > 0 else np.nan
    return steps, outside


def _nanmax(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return max(finite) if finite else float("nan")


def force_error(step: Step, name: str) -> float:
    """Relative normal-force error of combination ``name`` at a step (NaN at zero force)."""
    if step.f_fem <= 0:
        return float("nan")
    return abs(step.force[name] - step.f_fem) / step.f_fem


def summarise(steps: list[Step], names: list[str], outside=frozenset()) -> dict[str, dict]:
    """Per combination, over the steps within its trained depth (the others are counted, and
    their largest force and field errors given apart): the largest force and field errors
    with their targets and verdicts, the largest error of the dent under the tool and the
    farthest its deepest node lies from the tool (mm); the largest force error inside the
    trained region and outside it (positions in ``outside``, NaN where there are none).
    The deepest node is "within one element" where it is within one element of the tool or
    of the full order's own deepest node: pressed near the liver's thin border, the whole
    lobe swings and the full order's deepest node lies tens of millimetres away."""
    summary = {}
    for name in names:
        within = [s for s in steps if not s.beyond.get(name, False)]
        errors = {
            "force": [force_error(s, name) for s in within],
            "field": [s.field[name] for s in within],
        }
        beyond = [s for s in steps if s.beyond.get(name, False)]
        entry = {
            "steps_beyond_trained_depth": len(beyond),
            # the extrapolated steps apart: the force continued with the end slope, the
            # field's coordinates linearly (a soft place reaches the trained force deeper)
            "max_force_error_beyond": _nanmax([force_error(s, name) for s in beyond]),
            "max_field_error_beyond": _nanmax([s.field[name] for s in beyond]),
            "max_force_error_inside": _nanmax(
                [force_error(s, name) for s in within if s.position not in outside]
            ),
            "max_force_error_outside": _nanmax(
                [force_error(s, name) for s in within if s.position in outside]
            ),
            "max_dent_error": _nanmax([s.dent.get(name, np.nan) for s in within]),
            "max_deepest_distance_mm": _nanmax([s.deepest.get(name, np.nan) for s in within]),
            "max_deepest_fem_mm": _nanmax([s.deepest_fem for s in within]),
            "deepest_within_one_element": all(
                min(s.deepest.get(name, np.inf), s.deepest_gap.get(name, np.inf)) <= s.element
                for s in within
            ),
        }
        for quantity, values in errors.items():
            finite = [v for v in values if np.isfinite(v)]
            worst = max(finite) if finite else float("nan")
            limit = target(quantity, name)
            entry[f"max_{quantity}_error"] = worst
            entry[f"{quantity}_target"] = limit
            entry[f"{quantity}_verdict"] = verdict(worst, limit)
        summary[name] = entry
    return summary


@dataclass
class AccuracyResult:
    """A held-out check: the plan, every compared step, the summary per combination."""

    plan: HeldOutPlan
    steps: list[Step]
    summary: dict[str, dict]
    names: list[str]
    failed: dict[int, str]  # held-out position -> why its full-order solve failed
    outside: list[int]  # positions the runtime clamped to its trained region
    seconds: dict[str, float]


def compare(plan: HeldOutPlan, work: str | Path, failed: list[int]) -> AccuracyResult:
    """The reduced model against every solved held-out position stored in ``work``."""
    import hapticrom.online as online
    from hapticrom.offline.campaign.store import SnapshotStore

    t0 = time.perf_counter()
    model = online.load(plan.model)
    store = SnapshotStore(work)
    steps, outside, why = [], [], {}
    for index in store.completed():
        data, attrs = store.read_position(index)
        if index in failed or attrs.get("status") != "solved":
            why[index] = str(attrs.get("message") or attrs.get("status"))
            continue
        position_steps, clamped = compare_position(model, index, data, attrs)
        steps.extend(position_steps)
        if clamped:
            outside.append(index)
    names = combinations(model)
    seconds = {"comparison": time.perf_counter() - t0}
    summary = summarise(steps, names, set(outside))
    return AccuracyResult(plan, steps, summary, names, why, outside, seconds)


# -- output (rank 0) -------------------------------------------------------------------------------
def positions_text(plan: HeldOutPlan) -> str:
    """The held-out positions with how far the snap to a surface node moved each (mm)."""
    if plan.method == "centroids":
        how = (
            "centroids of sample triangles, snapped to the nearest surface node of the trained "
            "region; 'snap moved': from the centroid to the node, in plan view"
        )
    elif plan.method == "softest":
        how = "the trained region's nodes nearest the softest samples"
    elif plan.method == "outside":
        how = (f"random surface nodes outside the trained region, seed {plan.seed}: the "
               "runtime clamps the contact to the region's border")  # fmt: skip
    elif plan.method == "anywhere":
        how = (f"random nodes of the tool's whole surface group, seed {plan.seed}: inside the "
               "trained region or outside it (where the runtime clamps the contact)")  # fmt: skip
    else:
        how = f"random surface nodes of the trained region, seed {plan.seed}"
    lines = [
        f"held-out check of {plan.model}: {len(plan.positions)} position(s) ({how})"
        + (f"; asked for {plan.requested}" if len(plan.positions) < plan.requested else ""),
        f"{'pos':>4} {'x':>8} {'y':>8} {'z':>8}  {'snap moved (mm)':>15}  chosen as",
    ]
    for i, p in enumerate(plan.positions):
        x, y, z = p.point
        lines.append(f"{i:4d} {x:8.3f} {y:8.3f} {z:8.3f}  {p.moved:15.3f}  {p.source}")
    return "\n".join(lines)


def _blended_names(names: list[str]) -> list[str]:
    """The combinations whose forces the JSON rows carry (all but Grassmann's, whose force
    is PODI's)."""
    return [n for n in names if not n.startswith("grassmann+")]


def _responses(names: list[str]) -> dict[str, str]:
    """Per response, the first combination of it (its force column)."""
    first = {}
    for name in _blended_names(names):
        first.setdefault(name.split("+")[1], name)
    return first


def steps_text(result: AccuracyResult) -> str:
    """A table per held-out position (thesis Table 2.2 layout): the force per response,
    then the field error of every combination."""
    forces, fields = _responses(result.names), result.names
    head = f"{'u (mm)':>8} {'F_FEM (N)':>10}"
    for response in forces:
        head += f" {'F_' + RESPONSE_COLUMNS[response] + ' (N)':>12} {'err %':>6}"
    for name in fields:
        head += f" {name:>17}"
    blocks = []
    for index in dict.fromkeys(s.position for s in result.steps):
        rows = [s for s in result.steps if s.position == index]
        x, y, z = rows[0].point
        note = "  (outside the trained region: clamped)" if index in result.outside else ""
        lines = [f"\nheld-out position {index} at ({x:.3f}, {y:.3f}, {z:.3f}) mm{note}", head]
        lines.append(f"{'':>8} {'':>10}" + " " * 20 * len(forces) + " field %".rjust(18))
        for s in rows:
            line = f"{s.depth:8.4f} {s.f_fem:10.5f}"
            for name in forces.values():
                err = 100 * force_error(s, name)
                line += f" {s.force[name]:12.5f} {err:6.2f}"
            for name in fields:
                line += f" {100 * s.field[name]:17.2f}"
            lines.append(line)
        blocks.append("\n".join(lines))
    for index, why in sorted(result.failed.items()):
        blocks.append(f"\nheld-out position {index}: the full-order solve failed ({why})")
    return "\n".join(blocks)


def summary_text(result: AccuracyResult) -> str:
    """The summary table of a check: largest errors, targets and verdicts."""
    positions = len({s.position for s in result.steps})
    lines = [
        f"\nsummary: largest errors over {positions} held-out position(s) and every load step",
        f"{'combination':<18} {'force':>8} {'target':>7} {'verdict':<8}"
        f" {'field':>8} {'target':>7} {'verdict':<8}",
    ]
    for name, s in result.summary.items():
        cells = []
        for quantity in ("force", "field"):
            limit = s[f"{quantity}_target"]
            limit_text = "-" if limit is None else f"{100 * limit:g} %"
            cells.append(
                f"{100 * s[f'max_{quantity}_error']:6.2f} % {limit_text:>7} "
                f"{s[f'{quantity}_verdict']:<8}"
            )
        lines.append(f"{name:<18} " + " ".join(cells))
    lines += [f"  {q}: {meaning}" for q, meaning in QUANTITIES.items()]
    lines += region_text(result)
    lines.append(
        f"\n{'combination':<18} {'dent under tool':>15} {'deepest node from tool':>23}"
        f" {'beyond trained depth: steps, force, field':>42}"
    )
    for name, s in result.summary.items():
        where = "within one element" if s["deepest_within_one_element"] else "beyond one element"
        beyond = f"{s['steps_beyond_trained_depth']:>12d}"
        if s["steps_beyond_trained_depth"]:
            beyond += (f" {100 * s['max_force_error_beyond']:8.2f} %"
                       f" {100 * s['max_field_error_beyond']:7.2f} %")  # fmt: skip
        lines.append(
            f"{name:<18} {100 * s['max_dent_error']:13.2f} % "
            f"{s['max_deepest_distance_mm']:8.3f} mm ({where}) {beyond}"
        )
    lines.append(
        "  dent under tool: max relative error of the normal displacement of the surface node "
        "at the tool; deepest node: the farthest, over the steps, that the rendered dent's "
        "deepest surface node lies from the tool (the full order's own: "
        f"{_nanmax([s['max_deepest_fem_mm'] for s in result.summary.values()]):.3f} mm); "
        "within one element: of the tool or of the full order's deepest node, at every step; "
        "beyond trained depth: the steps the runtime extrapolates in depth, left out above, "
        "and their largest errors"
    )
    lines.append(
        "  verdicts are information: a missed target says where the model is not to be "
        "trusted, not that the check failed"
    )
    return "\n".join(lines)


def region_text(result: AccuracyResult) -> list[str]:
    """The largest force errors inside the trained region and outside it, per response,
    when the check has positions on both sides (``--anywhere``)."""
    positions = {s.position for s in result.steps}
    outside = positions & set(result.outside)
    if not outside or outside == positions:
        return []
    lines = [f"\nforce by region: {len(positions) - len(outside)} position(s) inside the trained "
             f"region, {len(outside)} outside it (clamped to its border)"]  # fmt: skip
    for name in _responses(result.names).values():
        s = result.summary[name]
        lines.append(f"{name:<18} inside {100 * s['max_force_error_inside']:6.2f} %   outside "
                     f"{100 * s['max_force_error_outside']:6.2f} %")  # fmt: skip
    return lines


def result_json(result: AccuracyResult) -> dict:
    """The JSON of ``hapticrom accuracy --json`` (read by ``hapticrom report --accuracy``).

    ``rows``: [position, [x, y, z], depth, F_FEM, one F_ROM per combination of the summary
    but Grassmann's, in its order] (format 1 had these, and the summary's max errors, only);
    ``field_errors``: the relative L2 field error of the same combinations, row by row.
    """
    podi = _blended_names(result.names)
    plan = result.plan
    return {
        "format": FORMAT,
        "version": VERSION,
        "model": plan.model,
        "selection": {"method": plan.method, "seed": plan.seed, "requested": plan.requested},
        "positions": [
            {"position": i, "point": list(p.point), "snap_moved_mm": p.moved, "source": p.source}
            for i, p in enumerate(plan.positions)
        ],
        "targets": TARGETS,
        "columns": ["position", "point_mm", "depth_mm", "force_fem_n"]
        + [f"force_{name}_n" for name in podi],
        "summary": result.summary,
        "rows": [
            [s.position, s.point, s.depth, s.f_fem, *(s.force[n] for n in podi)]
            for s in result.steps
        ],  # fmt: skip
        "field_errors": [[s.field[n] for n in podi] for s in result.steps],
        "dent_errors": [[s.dent[n] for n in podi] for s in result.steps],
        "deepest_mm": [[s.deepest[n] for n in podi] for s in result.steps],
        "deepest_gap_mm": [[s.deepest_gap[n] for n in podi] for s in result.steps],
        "deepest_fem_mm": [s.deepest_fem for s in result.steps],
        "beyond_trained_depth": [[s.beyond[n] for n in podi] for s in result.steps],
        "failed": {str(i): why for i, why in result.failed.items()},
        "outside_trained_region": result.outside,
        "seconds": result.seconds,
    }


def strict_json(value):
    """``value`` with every non-finite float as None: JSON has no NaN (a strict parser
    refuses ``NaN``; an error is NaN where a check has no step of its kind, e.g. the force
    error outside the region when every position is inside)."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, np.generic):
        return strict_json(value.item())
    return value


def write_json(result: AccuracyResult, path: str | Path) -> None:
    """Write the JSON atomically: a failed write leaves the old file (or nothing)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        text = json.dumps(strict_json(result_json(result)), indent=1, allow_nan=False)
        tmp.write_text(text + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise HapticromError(f"cannot write {path}: {exc.strerror or exc}") from None


# -- the check ----------------------------------------------------------------------------------
def run_accuracy(
    plan: HeldOutPlan,
    work: str | Path,
    comm=MPI.COMM_WORLD,
    restart: bool = False,
    json_path: str | Path | None = None,
    quiet: bool = False,
) -> AccuracyResult | None:
    """Solve, compare, print (rank 0) and write the JSON; the result on rank 0, None elsewhere."""
    if comm.rank == 0 and not quiet:
        print(positions_text(plan), flush=True)
    t0 = time.perf_counter()
    report = solve_held_out(plan, work, comm, restart, verbose=not quiet)
    solves = time.perf_counter() - t0
    if comm.rank != 0:
        return None
    result = compare(plan, work, report.failed)
    result.seconds["solves"] = solves
    if not quiet:
        print(steps_text(result) + "\n" + summary_text(result), flush=True)
        print(
            f"held-out solves {solves:.1f} s wall ({comm.size} rank(s)), "
            f"comparison {result.seconds['comparison']:.1f} s",
            flush=True,
        )
    if json_path is not None:
        write_json(result, json_path)
        if not quiet:
            print(f"wrote {json_path}", flush=True)
    return result
