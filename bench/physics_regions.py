"""The product path of issue 18 on a trained campaign: ``hapticrom physics`` at campaign
positions, each region pressed at its centre with that position's stored load path as
haptic steps, against the stored full-order solve (not among the region's own solves).

    python bench/physics_regions.py MODEL.h5 CAMPAIGN_DIR [--positions 6,18,30]
        [--pair MM [--second-force 0.5] | --held MM [--lift MM] | --pinch N
         | --oblique FRACTION]
        [--out out/physics.h5] [--frames 100]
        [--skip-build] [--slices 30] [--estimate-steps 100 [--estimate-cost]]
        [-- hapticrom physics options]

``--pair MM``: two tools, the position's and a second at the free loadable node nearest MM
away pressing with ``--second-force`` of the campaign's force, each region a ``--pair``
region of the two sites, the reference a full-order solve under both (solved here).
``--pinch N``: nine forces of N (the position's node and the eight nearest loadable nodes,
thesis §3.4.3), each region a ``--pinch`` region, the reference the full order under the
pinch (solved here), the depth the nine forces' load-weighted displacement.
``--oblique FRACTION``: the position's tool with a tangential force of FRACTION of its own
on the same point at 45 degrees from the tangent nearest x (a direction none of the
region's solves has: they are at 0, 120 and 240), each region an ``--oblique`` region
(``--oblique-force FRACTION``), the reference the full order under both (solved here),
the runtime pressing one tool with their sum, the depth the load-weighted displacement.
``--held MM``: the position's tool presses while a holder MM away grips (``--held``
regions, ``physics(region, holders=[...])``), the reference the full order with the
holder's patch held in place (solved here). ``--lift MM`` (with ``--held``): the
regions' solves also lift (``hapticrom physics --lift``), and the steps grasp-and-lift
instead, nothing pressing, the holder moved MM against the campaign's direction (out of
the surface along its normal for "normal"; ``physics.move_holder``), against the full
order with that patch so moved (solved here): the field, and the holder's force against
the full order's tool force.

Per region: the sampled elements, the modes, the depth error (the tool's load-weighted mean
displacement along its force, as the campaign's) and the surface field's relative L2 error
at the last load, after ``--frames`` steps of the ramp and as many held; the time of each
``physics.step()`` (p50, p99, max), its tangent built in ``--slices`` parts; the depth
(or, lifted, the field) at the ramp's last step, which lags the load; and the physics' own
error estimate at the end (``physics.error_estimate()``, over ``--estimate-steps`` steps;
NaN for a file without check samples); with ``--estimate-cost`` the step's p50 and p99
with and without the estimate, stepped alternately in the same run, and their ratios.
Writes OUT with suffix .json. Serial; run alone for the times. Units: mm, N.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py  # noqa: F401  (before dolfinx: see the README)
import numpy as np

from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.online.model import load


def parse_arguments() -> tuple[argparse.Namespace, list[str]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("campaign")
    parser.add_argument("--positions", default="6,18,30")
    parser.add_argument("--out", default="out/physics.h5")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--skip-build", action="store_true", help="OUT exists: only step it")
    parser.add_argument("--pair", type=float, default=0.0, help="mm: a second tool this far")
    parser.add_argument("--second-force", type=float, default=0.5)
    parser.add_argument("--held", type=float, default=0.0, help="mm: a holder this far")
    parser.add_argument("--pinch", type=float, default=0.0,
                        help="N: a pinch of nine forces this large (thesis: 0.014)")  # fmt: skip
    parser.add_argument(
        "--oblique",
        type=float,
        default=0.0,
        help="a tangential force, of the campaign's (the stop-40 bench: 0.5)",
    )
    parser.add_argument("--lift", type=float, default=0.0, help="mm: --held's holder lifts")
    parser.add_argument("--slices", type=int, default=30, help="the tangent's parts (physics')")
    parser.add_argument("--estimate-steps", type=int, default=100,
                        help="the steps an error estimate takes (physics')")  # fmt: skip
    parser.add_argument("--estimate-cost", action="store_true",
                        help="also step each region with and without the estimate, "
                        "alternately: the step's cost of it (not with --lift)")  # fmt: skip
    args, extra = parser.parse_known_args()
    if sum(bool(v) for v in (args.pair, args.held, args.pinch, args.oblique)) > 1:
        parser.error("--pair, --held, --pinch or --oblique, one of them")
    if not (np.isfinite(args.oblique) and 0 <= args.oblique <= 10):
        parser.error("--oblique: a fraction in (0, 10] of the campaign's force")
    if not (np.isfinite(args.pinch) and 0 <= args.pinch <= 100):
        parser.error("--pinch: a force in (0, 100] N")
    if args.lift and not (args.held and 0 < args.lift <= 10):
        parser.error("--lift needs --held, and at most 10 mm (hapticrom physics --lift's)")
    try:
        args.positions = [int(v) for v in args.positions.split(",")]
    except ValueError:
        parser.error("--positions: comma-separated campaign position indices")
    if min(args.frames, args.slices, args.estimate_steps) < 1:
        parser.error("--frames, --slices and --estimate-steps must be at least 1")
    return args, [v for v in extra if v != "--"]


def ramp_factors(factors, frames) -> list[float]:
    """The load factors of ``frames`` steps to the last of ``factors``, then as many held."""
    return list(np.linspace(0.0, factors[-1], frames + 1)[1:]) + [factors[-1]] * frames


def ramped(physics, load, factors, frames) -> tuple[np.ndarray, np.ndarray]:
    """The region ramped to the last of the load ``factors`` in ``frames`` steps, then held
    as long, ``load(factor)`` applying the loads before each step: each step's time (ms),
    the first left out, and the state q at the ramp's last step (what lags the load)."""
    times, ramp_end = [], None
    for factor in ramp_factors(factors, frames):
        load(factor)
        t0 = time.perf_counter_ns()
        if not physics.step():
            raise SystemExit("a physics step was refused")
        times.append(time.perf_counter_ns() - t0)
        if len(times) == frames:
            ramp_end = physics.q.copy()
    return np.array(times[1:]) / 1e6, ramp_end


def pressed(physics, tools, factors, frames) -> tuple[np.ndarray, np.ndarray]:
    """``ramped`` under each tool's force (``tools``: (point, force) pairs)."""

    def press(factor):
        for k, (point, force) in enumerate(tools):
            physics.press(k, point, factor * np.asarray(force))

    return ramped(physics, press, factors, frames)


def estimate_cost(model, region, holders, tools, factors, args) -> dict:
    """The step's cost with and without the error estimate, measured in one run: two
    physics of the region (``--estimate-steps`` and 0) pressed alike, their steps taken
    alternately (each timed), ``--frames`` of the ramp and as many held, three times."""
    both = [model.physics(region=region, holders=holders, slices=args.slices,
                          estimate_steps=steps) for steps in (args.estimate_steps, 0)]  # fmt: skip
    times: list[list[int]] = [[], []]
    for factor in ramp_factors(factors, args.frames) * 3:
        for physics, spent in zip(both, times, strict=True):
            for k, (point, force) in enumerate(tools):
                physics.press(k, point, factor * np.asarray(force))
            t0 = time.perf_counter_ns()
            if not physics.step():
                raise SystemExit("a physics step was refused")
            spent.append(time.perf_counter_ns() - t0)
    out = {name: timing(np.array(spent[1:]) / 1e6)
           for name, spent in zip(("with", "without"), times, strict=True)}  # fmt: skip
    out["p99_ratio"] = out["with"]["p99_ms"] / out["without"]["p99_ms"]
    out["p50_ratio"] = out["with"]["p50_ms"] / out["without"]["p50_ms"]
    print(f"  the estimate's cost: step p50/p99 {out['with']['p50_ms']:.3f}/"
          f"{out['with']['p99_ms']:.3f} ms with it, {out['without']['p50_ms']:.3f}/"
          f"{out['without']['p99_ms']:.3f} without (ratios {out['p50_ratio']:.3f}, "
          f"{out['p99_ratio']:.3f})", flush=True)  # fmt: skip
    return out


def timing(ms) -> dict:
    """The steps' times (ms): p50, p99, max."""
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max())}  # fmt: skip


def two_tools(store, point, args) -> tuple:
    """([(point, force)] of the campaign's tool at ``point`` and the second, the full
    order's datasets under both, the first tool's own load vector)."""
    from mpi4py import MPI

    from hapticrom.offline.reduce.ecsw_regions import RegionSolves
    from hapticrom.offline.reduce.inputs import campaign_config
    from hapticrom.offline.reduce.tool_stiffness import ToolLoads

    config = campaign_config(store, store.manifest(), None)
    solves = RegionSolves(config, (), 1)
    node = solves.nearest(point)
    second_node, second = solves.second_tool(point, args.pair, args.second_force)
    first = solves.tool(node, 1.0)
    t = time.perf_counter()
    data = solves.solve(node, tools=[second])
    print(f"  the full order under two tools at {np.round(first[0], 3).tolist()} and "
          f"{np.round(second[0], 3).tolist()} mm ({time.perf_counter() - t:.0f} s, "
          f"rank {MPI.COMM_WORLD.rank})", flush=True)  # fmt: skip
    g, W = ToolLoads(config).at(first[0], first[1])  # the first tool's load: its depth's
    return [first, second], data, g / W


def held_case(store, point, args) -> tuple:
    """([(point, force)] of the campaign's tool at ``point``, the full order's datasets
    with a holder's patch ``--held`` mm away held in place, the press's load vector; the
    holder's point)."""
    from mpi4py import MPI

    from hapticrom.offline.reduce.ecsw_regions import RegionSolves
    from hapticrom.offline.reduce.inputs import campaign_config

    solves = RegionSolves(campaign_config(store, store.manifest(), None), (), 1)
    node = solves.nearest(point)
    holder = solves.second_tool(point, args.held, 1.0)[1][0]
    press = solves.tool(node, 1.0)
    t = time.perf_counter()
    data = solves.solve(solves.nearest(holder), tools=[press], config=solves.held)
    print(f"  the full order pressed at {np.round(press[0], 3).tolist()} mm, held at "
          f"{np.round(holder, 3).tolist()} mm ({time.perf_counter() - t:.0f} s, "
          f"rank {MPI.COMM_WORLD.rank})", flush=True)  # fmt: skip
    return [press], data, data["load_vector"], np.asarray(holder)


def pinch_case(store, point, args) -> tuple:
    """([(point, force)] of a pinch's nine tools about ``point``: the campaign's tool there
    with ``--pinch`` N and the eight of ``RegionSolves.pinch_tools``, the full order's
    datasets under them, their load vector)."""
    from hapticrom.offline.reduce.ecsw_regions import RegionSolves
    from hapticrom.offline.reduce.inputs import campaign_config

    solves = RegionSolves(campaign_config(store, store.manifest(), None), (), 1)
    node = solves.nearest(point)
    tools, pinching = solves.pinch(node, args.pinch)
    t = time.perf_counter()
    data = solves.solve(node, tools=tools[1:], config=pinching)
    print(f"  the full order pinched about {np.round(tools[0][0], 3).tolist()} mm, nine "
          f"forces of {args.pinch} N ({time.perf_counter() - t:.0f} s)", flush=True)  # fmt: skip
    return tools, data, data["load_vector"]


def oblique_case(store, point, args) -> tuple:
    """([(point, force)]: the campaign's tool at ``point`` and the ``--oblique`` tangential
    force at 45 degrees, as one tool, the full order's datasets under both, their load
    vector, the unit directions of the press and of the tangential force)."""
    from hapticrom.offline.reduce.ecsw_regions import RegionSolves
    from hapticrom.offline.reduce.inputs import campaign_config

    solves = RegionSolves(campaign_config(store, store.manifest(), None), (), 1)
    node = solves.nearest(point)
    press, tangential = solves.tool(node, 1.0), solves.oblique_tool(node, 45.0, args.oblique)
    t = time.perf_counter()
    data = solves.solve(node, tools=[tangential])
    print(f"  the full order pressed obliquely at {np.round(press[0], 3).tolist()} mm "
          f"({time.perf_counter() - t:.0f} s)", flush=True)  # fmt: skip
    force = np.asarray(press[1]) + np.asarray(tangential[1])
    directions = [np.asarray(f) / np.linalg.norm(f) for f in (press[1], tangential[1])]
    return [(press[0], tuple(force))], data, data["load_vector"], directions


def node_components(vertices, point, u, full, directions) -> dict:
    """The errors of the surface vertex nearest ``point``'s displacement ``u`` against the
    full order's along each of ``directions`` (the press's, the tangential force's), each
    of the full order's component there: the oblique press's normal and tangential parts
    apart (its depth weighs them together)."""
    k = int(np.argmin(np.linalg.norm(vertices - point, axis=1)))
    errors = [float((u[k] - full[k]) @ d / (full[k] @ d)) for d in directions]
    return {"normal_error": errors[0], "tangential_error": errors[1]}


def holder_force_error(physics, data) -> tuple[np.ndarray, np.ndarray, float]:
    """(the physics' first holder's force on the tissue (N), the full order's holder's
    reaction at the end of ``data``'s path, their relative difference)."""
    pull, reaction = physics.holder_force(0), np.asarray(data["force"][-1])
    return pull, reaction, float(np.linalg.norm(pull - reaction) / np.linalg.norm(reaction))


def lifted(store, model, region, i, holder, args) -> dict:
    """Grasp-and-lift at ``region``: the holder at ``holder`` (mm) moved ``--lift`` mm
    against the campaign's direction over ``--frames`` steps, then held as long, against
    the full order so lifted (its tool under displacement control, its patch moved)."""
    from dataclasses import replace

    from hapticrom.offline.reduce.ecsw_regions import RegionSolves
    from hapticrom.offline.reduce.inputs import campaign_config

    config = campaign_config(store, store.manifest(), None)
    solves = RegionSolves(config, (), 1)
    node = solves.nearest(holder)
    load = replace(config.load, mode="displacement", magnitude=-args.lift)  # out of the surface
    data = solves.solve(node, config=replace(config, load=load))
    vector = load.magnitude * load.unit_direction(solves.position(node))
    factors = data["load_factor"]
    physics = model.physics(region=region, holders=[holder], slices=args.slices,
                            estimate_steps=args.estimate_steps)  # fmt: skip
    ms, ramp_end = ramped(physics, lambda factor: physics.move_holder(0, factor * vector),
                          factors, args.frames)  # fmt: skip
    u = np.zeros_like(physics.vertices)
    physics.surface_displacement(u)
    full = data["displacement"][-1].reshape(-1, 3)[model.artifact["surface"]["nodes"]]
    lagging = (physics.surface_basis @ ramp_end).reshape(-1, 3)
    pull, reaction, force_error = holder_force_error(physics, data)
    row = {"position": i, "lift_mm": args.lift, "elements": len(physics.newton.sample[0]),
           "field_error": float(np.linalg.norm(u - full) / np.linalg.norm(full)),
           "ramp_end_field_error": float(np.linalg.norm(lagging - full) / np.linalg.norm(full)),
           "force_error": force_error,
           "holder_force": pull.tolist(), "full_force": reaction.tolist(), **timing(ms),
           "refreshes": physics.refreshes, "error_estimate": physics.error_estimate()}  # fmt: skip
    print(f"position {i:3d}, lifted {args.lift} mm: field {100 * row['field_error']:.2f} % "
          f"(estimated {100 * row['error_estimate']:.2f} %), "
          f"holder force {np.round(pull, 5).tolist()} N against the full order's "
          f"{np.round(reaction, 5).tolist()} ({100 * row['force_error']:.2f} %), step "
          f"p50/p99/max {row['p50_ms']:.2f}/{row['p99_ms']:.2f}/{row['max_ms']:.2f} ms, "
          f"{physics.refreshes} fresh tangents; at the ramp's last step: field "
          f"{100 * row['ramp_end_field_error']:.2f} %", flush=True)  # fmt: skip
    return row


def main() -> None:
    args, options = parse_arguments()
    store = SnapshotStore(args.campaign)
    points = [np.asarray(store.read_position(i)[1]["point"], float) for i in args.positions]
    case_of = two_tools if args.pair else held_case if args.held else None
    case_of = pinch_case if args.pinch else oblique_case if args.oblique else case_of
    cases = [case_of(store, point, args) if case_of else None for point in points]
    if not args.skip_build:
        from hapticrom.cli import main as hapticrom

        at = ["--at=" + ",".join(f"{v:.9g}" for v in p) for p in points]
        if args.pair:
            at = ["--pair=" + ",".join(f"{v:.9g}" for v in (*p, *case[0][1][0]))
                  for p, case in zip(points, cases, strict=True)]  # fmt: skip
            options = ["--second-force", str(args.second_force), *options]
        if args.held:
            at = ["--held=" + ",".join(f"{v:.9g}" for v in (*p, *case[3]))
                  for p, case in zip(points, cases, strict=True)]  # fmt: skip
            options = ["--lift", str(args.lift), *options] if args.lift else options
        if args.pinch:
            at = [a.replace("--at=", "--pinch=") for a in at]
            options = ["--pinch-force", str(args.pinch), *options]
        if args.oblique:
            at = [a.replace("--at=", "--oblique=") for a in at]
            options = ["--oblique-force", str(args.oblique), *options]
        t = time.perf_counter()
        if hapticrom(["physics", args.model, args.campaign, *at, "--out", args.out, *options]):
            raise SystemExit("hapticrom physics failed")
        print(f"hapticrom physics: {time.perf_counter() - t:.0f} s", flush=True)
    model = load(args.out, isolate=False)
    nodes = model.artifact["surface"]["nodes"]
    if args.lift:
        pairs = enumerate(zip(args.positions, cases, strict=True))
        rows = [lifted(store, model, region, i, case[3], args) for region, (i, case) in pairs]
        Path(args.out).with_suffix(".lift.json").write_text(json.dumps(rows, indent=1))
        return
    rows = []
    for region, (i, point, case) in enumerate(zip(args.positions, points, cases, strict=True)):
        data = store.read_position(i)[0] if case is None else case[1]
        f, factors = data["load_vector"], data["load_factor"]
        if case is None:
            force = f.reshape(-1, 3).sum(axis=0)
            tools = [(point, force)]
        else:
            tools = case[0]
            force = np.asarray(tools[0][1])
            f = case[2]  # the first tool's own load vector: its depth, as the campaign's
        holders = [case[3]] if args.held else []
        physics = model.physics(region=region, holders=holders, slices=args.slices,
                                estimate_steps=args.estimate_steps)  # fmt: skip
        ms, ramp_end = pressed(physics, tools, factors, args.frames)
        u = np.zeros_like(physics.vertices)
        physics.surface_displacement(u)
        full = data["displacement"][-1]
        tool = physics.tool_load(point, force)
        if args.pinch or args.oblique:  # the forces' load-weighted displacement
            tool = physics.load / factors[-1]  # per unit factor, as f
        depth, lagging = tool @ physics.q / (f @ full), tool @ ramp_end / (f @ full)
        field = full.reshape(-1, 3)[nodes]
        row = {"position": i, "elements": len(physics.newton.sample[0]), "modes": physics.q.size,
               "pressure_modes": physics.pi.size, "depth_error": float(depth - 1),
               "ramp_end_depth_error": float(lagging - 1),
               "field_error": float(np.linalg.norm(u - field) / np.linalg.norm(field)),
               **timing(ms), "refreshes": physics.refreshes,
               "error_estimate": physics.error_estimate()}  # fmt: skip
        if args.held:  # the holder's force on the tissue against the full order's reaction
            pull, reaction, row["holder_force_error"] = holder_force_error(physics, data)
            print(f"  the holder's force {np.round(pull, 5).tolist()} N against the full "
                  f"order's {np.round(reaction, 5).tolist()} "
                  f"({row['holder_force_error']:.2%})")  # fmt: skip
        if args.oblique:  # the pressed vertex's move along the press and the tangential force
            row.update(node_components(physics.vertices, point, u, field, case[3]))
            print(f"  at the pressed vertex: along the press {row['normal_error']:+.2%}, "
                  f"along the tangential force {row['tangential_error']:+.2%}")  # fmt: skip
        if args.estimate_cost:
            row["estimate_cost"] = estimate_cost(model, region, holders, tools, factors, args)
        print(f"position {i:3d}: {row['elements']} elements, {row['modes']} + "
              f"{row['pressure_modes']} modes, depth {100 * row['depth_error']:+.2f} %, field "
              f"{100 * row['field_error']:.2f} % (estimated {100 * row['error_estimate']:.2f} "
              f"%), step p50/p99/max {row['p50_ms']:.2f}/{row['p99_ms']:.2f}/"
              f"{row['max_ms']:.2f} ms, {physics.refreshes} fresh tangents; at the ramp's last "
              f"step: depth {100 * lagging - 100:+.2f} %", flush=True)  # fmt: skip
        rows.append(row)
    Path(args.out).with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
