"""A scripted tool path driven through the runtime as a servo loop would (``hapticrom play``).

Press at the centre of the trained region, slide across it at constant depth,
release; each servo tick moves the contact point (``set_contact``) and asks for
the force (``step_displacement``), paced in real time at ``rate`` Hz (busy
waiting, like a servo thread) or as fast as possible.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hapticrom.online.model import load


def tool_path(model, ticks: int, depth_fraction: float = 0.8):
    """Contact points (mm) and depths (mm) of press (25 %), slide (50 %), release (25 %)."""
    chart = model.plan_points
    centre = chart.mean(axis=0)
    half = 0.35 * (chart[:, 0].max() - chart[:, 0].min())
    t = np.linspace(0.0, 1.0, ticks)
    x = np.where(t < 0.25, -half, np.where(t > 0.75, half, -half + 2 * half * (t - 0.25) / 0.5))
    depth_max = depth_fraction * model.trained_depth
    depth = np.where(t < 0.25, t / 0.25, np.where(t > 0.75, (1 - t) / 0.25, 1.0)) * depth_max
    points = model.plan_origin + np.column_stack([centre[0] + x, np.full(ticks, centre[1])]) @ (
        model.plan_axes
    )
    return points, depth


def play(
    path: str | Path,
    rate: float = 1000.0,
    seconds: float = 3.0,
    interpolation: str | None = None,
    realtime: bool = True,
    say: Callable[[str], None] = print,
) -> dict:
    """Drive :func:`tool_path` through a simulator of the artifact at ``path`` as a servo
    loop would, ``rate`` Hz for ``seconds`` (paced in real time, or as fast as possible),
    reporting through ``say``; returns the achieved rate and the physics' latencies."""
    model = load(path)
    sim = model.simulator(interpolation)
    ticks = int(rate * seconds)
    say(f"playing {model.describe()}")
    pacing = "real time" if realtime else "free running"
    say(
        f"press - slide - release, {ticks} ticks at {rate:g} Hz ({pacing}); force from "
        + ("the POD-ANM series" if sim.response == "anm" else "the stored full-order curves")
    )
    forces, physics_ns, elapsed = _servo_loop(sim, model, ticks, rate, realtime, say)
    us = physics_ns / 1e3
    summary = {
        "ticks": ticks,
        "achieved_rate_hz": ticks / elapsed,
        "physics_p50_us": float(np.percentile(us, 50)),
        "physics_p99_us": float(np.percentile(us, 99)),
        "physics_max_us": float(us.max()),
        "max_force_n": float(np.linalg.norm(forces, axis=1).max()),
        "max_rate_hz": 1e6 / float(np.percentile(us, 99)),
    }
    say(
        f"achieved {summary['achieved_rate_hz']:.0f} Hz over {elapsed:.2f} s; physics per tick "
        f"(set_contact + step) p50 {summary['physics_p50_us']:.1f} us, p99 "
        f"{summary['physics_p99_us']:.1f} us, max {summary['physics_max_us']:.0f} us "
        f"(room for {summary['max_rate_hz']:.0f} Hz at p99); "
        f"peak force {summary['max_force_n']:.4f} N"
    )
    return summary


def _servo_loop(sim, model, ticks: int, rate: float, realtime: bool, say) -> tuple:
    """(forces (ticks, 3) N, physics time per tick (ns), seconds in all) of the loop."""
    points, depths = tool_path(model, ticks)
    forces = np.zeros((ticks, 3))
    physics_ns = np.zeros(ticks, dtype=np.int64)
    d = np.zeros(3)
    period = 1.0 / rate
    clock = time.perf_counter
    start = clock()
    for i in range(ticks):
        if realtime:
            target = start + i * period
            while clock() < target:
                pass
        t0 = time.perf_counter_ns()
        sim.set_contact(points[i])
        np.multiply(sim.contact_normal, -depths[i], out=d)
        forces[i] = sim.step_displacement(d)
        physics_ns[i] = time.perf_counter_ns() - t0
        if i % max(1, ticks // 15) == 0:
            outside = "  (outside trained region)" if sim.outside_trained_region else ""
            say(
                f"  t {i / rate:6.3f} s  contact {np.round(points[i], 3)} mm  "
                f"depth {depths[i]:.3f} mm  force {np.linalg.norm(forces[i]):.5f} N{outside}"
            )
    return forces, physics_ns, clock() - start
