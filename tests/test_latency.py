"""The latency bench's own measures: the host's gaps, the floor timed beside a call, and
the verdicts that name the host when the floor misses too (no timing is asserted)."""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.online import latency


def fake_clock(step_ns: int, gap_ns: int, every: int):
    """A clock that advances ``step_ns`` a read, and ``gap_ns`` more every ``every`` reads."""
    state = {"t": 0, "reads": 0}

    def clock():
        state["reads"] += 1
        state["t"] += step_ns + (gap_ns if state["reads"] % every == 0 else 0)
        return state["t"]

    return clock


def test_host_gaps_counts_the_clock_jumps():
    # 100 ns a read, a 30 us jump every 1,000 reads: 1,000 reads last 130 us, one gap.
    gaps = latency.host_gaps(0.13, 10_000, fake_clock(100, 30_000, 1000))
    assert gaps["per_second"] == pytest.approx(1 / 130e-6, rel=0.01)
    assert gaps["time_fraction"] == pytest.approx(30.1 / 130, rel=0.01)
    assert gaps["threshold_us"] == 10.0


def test_host_gaps_ignores_jumps_under_the_threshold():
    gaps = latency.host_gaps(0.01, 10_000, fake_clock(100, 9_000, 50))
    assert gaps["per_second"] == 0 and gaps["time_fraction"] == 0


def test_floor_is_timed_beside_each_call_after_its_setup():
    log = []
    times, floor = latency._time_beside_floor(
        lambda a: log.append(("call", a)), lambda a: log.append(("before", a)), list(range(300))
    )
    assert times.shape == floor.shape == (300,)
    assert (floor >= 0).all() and (times >= 0).all()
    timed = log[-600:]  # the timed loop, after the warm-up and the median's probe
    assert timed[0::2] == [("before", a) for a in range(300)]
    assert timed[1::2] == [("call", a) for a in range(300)]


def synthetic_result(untrained_p99: float, floor_p99: float, surface_share: float = 0.004,
                     floor_share: float = 0.003) -> dict:  # fmt: skip
    """A measure() result with every call at 1 us but the untrained surface and its floor."""
    calls = {"p50_us": 1.0, "p99_us": 1.0, "max_us": 1.0, "calls": 10}
    result = {key: dict(calls) for key in latency.CALLS}
    for key, floor_key in latency.FLOORS.items():
        result[key]["over_limit"] = result[floor_key]["over_limit"] = 0.0
    result["surface_untrained"] = {**calls, "p50_us": 20.0, "p99_us": untrained_p99,
                                   "over_limit": surface_share}  # fmt: skip
    result["constant_work"] = {**calls, "p50_us": 20.0, "p99_us": floor_p99,
                               "over_limit": floor_share}  # fmt: skip
    gaps = {"threshold_us": 10.0, "per_second": 500.0, "time_fraction": 0.01}
    result.update(artifact="a.h5", interpolation="transport", response="curves",
                  surface_vertices=4, load_and_warm_up_s=0.5, speedup_p50=1.0, speedup_p99=1.0,
                  host_gaps=gaps)  # fmt: skip
    return result


def untrained_line(text: str) -> str:
    return next(line for line in text.splitlines() if "at an untrained contact" in line)


@pytest.mark.parametrize(
    ("surface", "floor", "shares", "verdict", "host"),
    [
        (30.0, 24.0, (0.004, 0.003), "met", False),
        (60.0, 40.0, (0.012, 0.006), "missed", False),  # the floor met the limit
        (60.0, 55.0, (0.014, 0.011), "missed", True),
        (90.0, 55.0, (0.200, 0.011), "missed", False),  # far more of its calls over it
    ],
)
def test_verdict_names_the_host_only_when_its_floor_misses_as_often(
    surface, floor, shares, verdict, host
):
    line = untrained_line(latency.report(synthetic_result(surface, floor, *shares)))
    assert f"{surface:.2f} us, {verdict}" in line
    assert f"beside it: p99 {floor:.1f} us" in line
    assert ("the host's" in line) == host
    over = f"over 50 us: {100 * shares[0]:.2f} % of calls, constant work {100 * shares[1]:.2f} %"
    assert over in line


def test_report_gives_the_chance_a_call_meets_a_gap():
    text = latency.report(synthetic_result(30.0, 24.0))
    # 500 gaps a second, a call of 20 us: 1 % of calls
    assert "500 times a second (1.00 % of the time)" in text
    assert "a call of 20 us meets such a gap in about 1.0 % of calls" in text
    assert np.isfinite(latency.host_gaps(0.01)["per_second"])


def test_the_share_over_a_target_agrees_with_its_p99(small_artifact):
    """Each surface and its floor carry the share of calls over the target's limit, in the
    same unit as the p99: more than 1 % of calls over the limit puts the p99 over it (the
    converse need not hold: np.percentile interpolates between calls)."""
    result = latency.measure(small_artifact, steps=2000, baseline_steps=200)
    for key, stat, limit in latency.TARGETS.values():
        for name in (key, latency.FLOORS[key]) if key in latency.FLOORS else ():
            share, p99 = result[name]["over_limit"], result[name][stat]
            assert 0.0 <= share <= 1.0
            assert share <= 0.01 or p99 > limit, (name, share, p99)
    assert result["surface_untrained"]["calls"] == result["constant_work"]["calls"] == 2000
