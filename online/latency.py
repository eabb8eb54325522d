"""Latency of the online runtime, measured call by call (used by ``hapticrom bench``).

Each call is timed with ``time.perf_counter_ns`` (about 50 ns of its own);
Python's garbage collector is off during the loops, as in a real-time servo
thread. The baseline is the same step written in plain numpy
(:mod:`hapticrom.online.reference`), measured in the same run.
"""

from __future__ import annotations

import gc
import time
from pathlib import Path

import numpy as np
from numba import njit

from hapticrom.online.model import ReducedModel, load
from hapticrom.online.reference import NumpySimulator


def percentiles(ns: np.ndarray) -> dict[str, float]:
    """p50, p99 and max (microseconds) and the number of calls of latencies ``ns`` (ns)."""
    us = ns / 1e3
    return {
        "p50_us": float(np.percentile(us, 50)),
        "p99_us": float(np.percentile(us, 99)),
        "max_us": float(us.max()),
        "calls": int(us.size),
    }


def time_calls(fn, args_list) -> np.ndarray:
    """The latency (ns) of ``fn(args)`` for each of ``args_list``, call by call."""
    times = np.empty(len(args_list), dtype=np.int64)
    clock = time.perf_counter_ns
    for i, args in enumerate(args_list):
        t0 = clock()
        fn(args)
        times[i] = clock() - t0
    return times


def measure(
    path: str | Path,
    steps: int = 100_000,
    interpolation: str | None = None,
    baseline_steps: int = 20_000,
    response: str | None = None,
) -> dict:
    """Latencies (microseconds) of the runtime's calls on the artifact at ``path``.

    ``response``: "anm" or "curves" (None: the model's default, "anm" if present).
    """
    t0 = time.perf_counter()
    model: ReducedModel = load(path)
    load_seconds = time.perf_counter() - t0
    sim = model.simulator(interpolation, response)
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        calls = _time_runtime(model, sim, steps, baseline_steps)
    finally:
        if gc_was_enabled:
            gc.enable()
    result = {
        "artifact": str(path),
        "interpolation": sim.interpolation,
        "response": sim.response,
        "load_and_warm_up_s": load_seconds,
        **{name: percentiles(ns) for name, ns in calls.items()},
        "surface_vertices": len(model.vertices),
    }
    numpy, numba = result["numpy_step_displacement"], result["step_displacement"]
    result["speedup_p50"] = numpy["p50_us"] / numba["p50_us"]
    result["speedup_p99"] = numpy["p99_us"] / numba["p99_us"]
    return result


def _time_runtime(model: ReducedModel, sim, steps: int, baseline_steps: int) -> dict:
    """Latencies (ns) of each call the benchmark times, by name."""
    centre = model.sample_points[int(np.argmin(np.linalg.norm(model.plan_points, axis=1)))]
    sim.set_contact(centre)
    n = sim.contact_normal.copy()
    phase = np.linspace(0, 40 * np.pi, steps)
    depths = model.trained_depth * 0.5 * (1 - np.cos(phase))  # press and release, 20 times
    displacements = [np.ascontiguousarray(-dep * n) for dep in depths]
    calls = {"step_displacement": time_calls(sim.step_displacement, displacements)}
    forces = [np.ascontiguousarray(-f * n) for f in np.linspace(0, model.trained_force, 5000)]
    calls["step_force"] = time_calls(sim.step_force, forces)
    out = np.zeros_like(model.vertices)
    sim.step_displacement(-0.5 * model.trained_depth * n)
    calls["surface_displacement"] = time_calls(lambda _: sim.surface_displacement(out), range(2000))
    # An untrained contact, three neighbours: the centroid of the sample triangle nearest the
    # centre (at a sample only one neighbour's field is read: a third of the work).
    t = model.sample_triangles[np.argmin(np.linalg.norm(
        model.sample_points[model.sample_triangles].mean(axis=1) - centre, axis=1))]  # fmt: skip
    sim.set_contact(model.sample_points[t].mean(axis=0))
    sim.step_displacement(-0.5 * model.trained_depth * np.asarray(sim.contact_normal))
    calls["surface_untrained"] = time_calls(lambda _: sim.surface_displacement(out), range(2000))
    calls["surface_sliding"] = _time_sliding_surface(model, sim, out)
    calls["constant_work"] = _time_constant_work(np.median(calls["surface_untrained"]))
    lo, hi = model.plan_points.min(axis=0), model.plan_points.max(axis=0)
    slide = [
        model.plan_origin + (lo + (hi - lo) * t) @ model.plan_axes
        for t in np.linspace(0.1, 0.9, 5000)[:, None]
    ]
    calls["set_contact"] = time_calls(sim.set_contact, slide)
    # Position in, force out: the scripted oblique press, slide and lift, then the stiffness.
    from hapticrom.online.play import scripted_tips

    tips = list(scripted_tips(model, max(steps, 1000)))
    calls["step_position"] = time_calls(sim.step_position, tips)
    sim.step_position(tips[len(tips) // 2])  # in contact, mid-slide
    stiffness = np.zeros((3, 3))
    calls["stiffness"] = time_calls(lambda _: sim.stiffness(stiffness), range(20_000))
    rubbing = model.simulator(sim.interpolation, response=sim.response)
    rubbing.set_friction(0.4, 0.25)  # the slide slips, the press and the lift stick
    calls["step_position_friction"] = time_calls(rubbing.step_position, tips)
    rubbing.step_position(tips[len(tips) // 2])
    calls["stiffness_friction"] = time_calls(lambda _: rubbing.stiffness(stiffness), range(20_000))
    ref = NumpySimulator(model, sim.response, root="table")  # the kernels' algorithm
    ref.set_contact(centre)
    steps = displacements[:baseline_steps]
    calls["numpy_step_displacement"] = time_calls(ref.step_displacement, steps)
    return calls


def _time_sliding_surface(model: ReducedModel, sim, out) -> np.ndarray:
    """surface_displacement at a new contact every call (a tool sliding at render rate): 2,000
    loadable vertices of the trained region, half the trained depth; the contact set and the
    step taken outside the timing."""
    groups = np.asarray(model.artifact["surface"]["groups"])
    loadable = np.unique(model.triangles[groups == 1])
    points = model.vertices[loadable]
    points = points[model.inside_trained_region(points)]
    order = np.random.default_rng(0).integers(len(points), size=2000)
    ns = np.empty(len(order), dtype=np.int64)
    for k, i in enumerate(order):
        sim.set_contact(points[i])
        sim.step_displacement(-0.5 * model.trained_depth * np.asarray(sim.contact_normal))
        t0 = time.perf_counter_ns()
        sim.surface_displacement(out)
        ns[k] = time.perf_counter_ns() - t0
    return ns


@njit(cache=True, nogil=True)
def _constant_work(n, x):
    """n dependent multiply-adds: a call whose work never varies."""
    for _ in range(n):
        x = x * 0.999999 + 1e-7
    return x


def _time_constant_work(median_ns: float, calls: int = 10_000) -> np.ndarray:
    """Latencies (ns) of a call of constant work lasting ``median_ns``, the same way as the
    runtime's calls: its p99 is what the machine itself (timer ticks, the hypervisor) adds
    to a call of that length, the floor under the runtime's p99 (measured on a 2-vCPU VM:
    20, 30, 40 us of work give p99 22, 45, 57 us)."""
    _constant_work(10, 1.0)
    t0 = time.perf_counter_ns()
    _constant_work(1_000_000, 1.0)
    n = max(1, int(1_000_000 * median_ns / max(time.perf_counter_ns() - t0, 1)))
    return time_calls(lambda _: _constant_work(n, 1.0), range(calls))


TARGETS = {
    "step_displacement p99": ("step_displacement", "p99_us", 10.0),
    "surface_displacement p99": ("surface_displacement", "p99_us", 100.0),
    "surface_displacement at an untrained contact p99": ("surface_untrained", "p99_us", 50.0),
    "surface_displacement at a new contact every call p99": ("surface_sliding", "p99_us", 50.0),
    "set_contact p99": ("set_contact", "p99_us", 20.0),
    "step_position p99 (contact detection included)": ("step_position", "p99_us", 10.0),
    "stiffness p99": ("stiffness", "p99_us", 2.0),
    "step_position with friction p99": ("step_position_friction", "p99_us", 10.0),
    "stiffness with friction p99": ("stiffness_friction", "p99_us", 2.0),
}


def report(result: dict) -> str:
    """The result of :func:`measure` as a text table with the targets' verdicts."""
    lines = [
        f"{result['artifact']} ({result['interpolation']}, {result.get('response', 'curves')}, "
        f"{result['surface_vertices']} surface "
        f"vertices): load + warm-up {result['load_and_warm_up_s']:.2f} s (target 2 s)",
        f"{'call':28s} {'p50 us':>9s} {'p99 us':>9s} {'max us':>9s} {'calls':>8s}",
    ]
    keys = ("step_displacement", "step_force", "set_contact", "step_position", "stiffness",
            "step_position_friction", "stiffness_friction", "surface_displacement",
            "surface_untrained", "surface_sliding", "constant_work",
            "numpy_step_displacement")  # fmt: skip
    for key in keys:
        r = result[key]
        lines.append(
            f"{key:28s} {r['p50_us']:9.2f} {r['p99_us']:9.2f} {r['max_us']:9.1f} {r['calls']:8d}"
        )
    lines.append(
        f"numba step vs the numpy step: {result['speedup_p50']:.0f}x faster at p50, "
        f"{result['speedup_p99']:.0f}x at p99 (target 20x)"
    )
    for label, (key, stat, limit) in TARGETS.items():
        value = result[key][stat]
        verdict = "met" if value <= limit else "missed"
        lines.append(f"target {label} <= {limit:g} us: {value:.2f} us, {verdict}")
    floor = result["constant_work"]
    lines.append(
        f"this machine's tail: a call of constant work with the untrained surface's p50 "
        f"({floor['p50_us']:.1f} us) has p99 {floor['p99_us']:.1f} us"
    )
    return "\n".join(lines)
