"""Step latency of the runtime, timed call by call with ``hapticrom bench``'s own loop
(:func:`hapticrom.online.latency.time_calls`) and judged by its target."""

from __future__ import annotations

import gc

import numpy as np

from hapticrom.online.latency import TARGETS, time_calls
from hapticrom.online.model import ReducedModel

LATENCY_TARGET = TARGETS["step_displacement p99"][2]  # us, p99 of step_displacement
PRESSES = 20  # press-and-release cycles over the timed steps


def step_latencies_us(model: ReducedModel, sample: int, steps: int) -> np.ndarray:
    """Microseconds of each ``step_displacement`` call, pressing and releasing 20 times.

    The garbage collector is off during the loop, as in a real-time servo thread.
    """
    sim = model.simulator()
    sim.set_contact(model.sample_points[sample])
    normal = sim.contact_normal.copy()
    phase = np.linspace(0, 2 * PRESSES * np.pi, steps)
    depths = model.trained_depth * 0.5 * (1 - np.cos(phase))
    displacements = [np.ascontiguousarray(-d * normal) for d in depths]
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        ns = time_calls(sim.step_displacement, displacements)
    finally:
        if gc_was_enabled:
            gc.enable()
    return ns / 1e3


def latency_rows(us: np.ndarray) -> list[tuple[str, str]]:
    """(statistic, value) rows: calls, p50, p99 against the target, p99.9, max, mean."""
    p50, p99, p999 = np.percentile(us, [50, 99, 99.9])
    verdict = "met" if p99 <= LATENCY_TARGET else "missed"
    return [
        ("calls", f"{len(us):,}"),
        ("p50", f"{p50:.2f} us"),
        ("p99", f"{p99:.2f} us (target {LATENCY_TARGET:g} us: {verdict})"),
        ("p99.9", f"{p999:.2f} us"),
        ("max", f"{us.max():.1f} us"),
        ("mean", f"{us.mean():.2f} us"),
    ]
