"""Latency of the runtime while cutting: cut events, and steps without topology change.

    python bench/cutting_latency.py out/cornea-soft-cut.h5 [--steps 100000]

The artifact needs a cuttable region (campaign table ``[cutting]``). The
scalpel is put in the middle of the region with its blade along the surface,
pressed until it cuts, and slid along the blade (each new cut is an event:
faces, new nodes, patch unknowns, seconds). Then, with the cut open: p50 / p99
/ max of ``step_displacement`` (the scalpel held, pressing and releasing),
``set_contact`` + step (a tool sliding near the cut), ``surface_displacement``
(with the cut's field and lips) and ``scalpel()`` placed again at the same
position and at nearby ones (as a servo loop does every tick). Targets: step
p99 at most 100 us without topology change (issue "surgical cutting");
``scalpel()`` re-placement p99 at most 10 us (issue "the artifact is a trust
boundary").
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np

import hapticrom.online as online
from hapticrom.online.latency import percentiles, time_calls

TARGET_US = 100.0
REPLACE_TARGET_US = 10.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--steps", type=int, default=100_000)
    args = parser.parse_args()
    model = online.load(args.model)
    if model.cut_region is None:
        raise SystemExit(f"{args.model} has no cuttable region (campaign table [cutting])")
    attrs = model.artifact.group_attrs["cutting"]
    centre = np.asarray(attrs["centre"], dtype=float)
    vertex = int(np.argmin(np.linalg.norm(model.vertices - centre, axis=1)))
    start = model.vertices[vertex]
    radial = start - [0.0, 0.0, start[2]]
    blade = np.cross([0.0, 0.0, 1.0], radial / max(np.linalg.norm(radial), 1e-12))
    sim = model.simulator()
    sim.scalpel(start, blade)
    n = sim.contact_normal.copy()
    depth = 0.0
    t0 = time.perf_counter()
    while sim.last_cut is None and depth < model.trained_depth:
        depth += 0.01 * model.trained_depth
        sim.step_displacement(-depth * n)
    print(f"first cut at depth {depth:.3f} mm (cut force {attrs['cut_force']} N), "
          f"{time.perf_counter() - t0:.3f} s of pressing")  # fmt: skip
    for k in range(1, 6):  # slide along the blade: the cut grows
        sim.scalpel(start + 0.25 * k * blade, blade)
        sim.step_displacement(-depth * n)
    for e in sim.cut_events:
        print(f"  cut event: {e.faces} face(s), {e.new_nodes} new node(s), patch "
              f"{e.patch_unknowns} unknowns, {1e3 * e.seconds:.1f} ms")  # fmt: skip
    phase = np.linspace(0, 20 * np.pi, args.steps)
    pushes = [np.ascontiguousarray(-depth * 0.5 * (1 - np.cos(p)) * n) for p in phase]
    out = np.zeros_like(model.vertices)
    near = [start + 0.2 * np.sin(p) * blade + 0.2 * np.cos(p) * np.cross(n, blade)
            for p in np.linspace(0, 2 * np.pi, 5000)]  # fmt: skip
    count = len(sim.cut_events)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        step = time_calls(sim.step_displacement, pushes)

        def slide(p):
            sim.set_contact(p)
            sim.step_displacement(-0.5 * depth * n)

        sliding = time_calls(slide, near)
        sim.set_contact(start)
        sim.step_displacement(-depth * n)
        surface = time_calls(lambda _: sim.surface_displacement(out), range(200))
        same, nearby = _replacements(sim, start, blade, near)
    finally:
        if gc_was:
            gc.enable()
    assert len(sim.cut_events) == count, "a cut happened while measuring"
    print(f"{'call (cut open)':32s} {'p50 us':>9s} {'p99 us':>9s} {'max us':>9s} {'calls':>8s}")
    for name, ns in (("step_displacement", step), ("set_contact + step", sliding),
                     ("surface_displacement", surface), ("scalpel() again, same place", same),
                     ("scalpel() again, nearby", nearby)):  # fmt: skip
        r = percentiles(ns)
        print(f"{name:32s} {r['p50_us']:9.2f} {r['p99_us']:9.2f} {r['max_us']:9.1f} "
              f"{r['calls']:8d}")  # fmt: skip
    p99 = percentiles(step)["p99_us"]
    verdict = "met" if p99 <= TARGET_US else "missed"
    print(f"target step p99 <= {TARGET_US:g} us without topology change: {p99:.2f} us, {verdict}")
    p99 = max(percentiles(same)["p99_us"], percentiles(nearby)["p99_us"])
    verdict = "met" if p99 <= REPLACE_TARGET_US else "missed"
    print(f"target scalpel() re-placement p99 <= {REPLACE_TARGET_US:g} us: {p99:.2f} us, {verdict}")
    vertices, _, lips = sim.lip_vertices
    print(f"lips: {len(vertices)} duplicated surface vertices; largest opening "
          f"{1e3 * np.abs(lips - out[vertices]).max():.2f} um")  # fmt: skip
    background(sim, start, blade, n, depth)


def _replacements(sim, start, blade, near) -> tuple:
    """Latencies (ns) of scalpel() placed again at ``start`` and at the ``near`` points
    (placing does not cut: only a step pressing the blade does)."""
    sim.scalpel(start, blade)  # not the first call: that one sets the scalpel up
    blade = np.ascontiguousarray(blade, dtype=float)
    same = time_calls(lambda p: sim.scalpel(p, blade), [np.array(start, dtype=float)] * 5000)
    nearby = time_calls(lambda p: sim.scalpel(p, blade), near)
    return same, nearby


def background(sim, start, blade, n, depth) -> None:
    """A cut event on a worker thread while the servo loop steps on (1 kHz pacing)."""
    before = len(sim.cut_events)
    vertices = sim.model.vertices
    for k in range(6, 12):
        target = start + 0.25 * k * blade  # on the surface: the nearest vertex
        at = vertices[np.argmin(np.linalg.norm(vertices - target, axis=1))]
        sim.scalpel(at, blade, background=True)
        sim.step_displacement(-1.2 * depth * n)
        if sim.cut_pending:
            break
    if not sim.cut_pending:
        print("background cut: the blade found nothing more to cut here")
        return
    push = np.ascontiguousarray(-depth * n)
    ns, late = [], 0
    next_tick = time.perf_counter_ns()
    while sim.cut_pending:
        next_tick += 1_000_000  # 1 ms; sleep (the worker needs the GIL now and then), then spin
        time.sleep(max(0.0, (next_tick - time.perf_counter_ns()) / 1e9 - 2e-4))
        while time.perf_counter_ns() < next_tick:
            pass
        t0 = time.perf_counter_ns()
        sim.step_displacement(push)
        ns.append(time.perf_counter_ns() - t0)
        late += time.perf_counter_ns() > next_tick + 1_000_000
    event = sim.cut_events[-1]
    r = percentiles(np.asarray(ns))
    print(f"background cut: {len(sim.cut_events) - before} event(s), patch {event.patch_unknowns} "
          f"unknowns, {1e3 * event.seconds:.1f} ms on the worker; {len(ns)} steps at 1 kHz "
          f"meanwhile: p50 {r['p50_us']:.2f} us, p99 {r['p99_us']:.2f} us, "
          f"max {r['max_us']:.1f} us, {late} tick(s) missed")  # fmt: skip


if __name__ == "__main__":
    main()
