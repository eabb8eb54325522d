"""The held physics step's cost, balanced tangent parts against equal ones in the same run
(issue 18): a region of ``hapticrom physics`` pressed by a ramp to a load, then held, and
``HapticNewton.step`` timed at that state for two solvers stepped in turn from it, one
with ``part_bounds``' parts (the last smaller by the factorisation that follows it), one
with equal parts (the bounds before stop 51).

    python bench/held_step.py OUT/physics.h5 [--region 0] [--holder X,Y,Z]
        [--press X,Y,Z] [--force N] [--ramp 60] [--steps 3000] [--slices 30]

The defaults are the demo's held region at position 30 (``bench/physics_regions.py ...
--positions 30 --held 2 --out out/cornea-soft-physics-hold-p30.h5``): the holder and the
press point (mm), 0.02 N along -z. Prints, per solver, the step's min, p10, p50, p99 and
the steps that finish a tangent (and factorise it) against the others; then the ratios
equal / balanced. Serial; run alone for the times. Units: mm, N, us.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hapticrom.cli.args import float_in, int_in
from hapticrom.cli.offline_commands import centre_point
from hapticrom.online.haptic_newton import HapticNewton
from hapticrom.online.model import load


def point(text: str) -> np.ndarray:
    """X,Y,Z (mm) as the CLI's ``--at`` reads it."""
    return np.array(centre_point(text))


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--region", type=int_in(0, 10**6), default=0)
    parser.add_argument("--holder", type=point, default=point("-3.907,-2.311,-1.457"))
    parser.add_argument("--no-holder", action="store_true", help="a region built without one")
    parser.add_argument("--press", type=point, default=point("-2.232,-1.734,-0.53"))
    parser.add_argument("--force", type=float_in(0.0, 1e3, "N"), default=0.02, help="N along -z")
    parser.add_argument(
        "--ramp", type=int_in(1, 10**6), default=60, help="steps to the load (2/3 ramp)"
    )
    parser.add_argument("--steps", type=int_in(100, 10**7), default=3000)
    parser.add_argument("--slices", type=int_in(1, 10**6), default=30)
    return parser.parse_args()


def held_state(args):
    """The physics after the ramp: its Newton, and the state and load it holds."""
    model = load(args.model, isolate=False)
    holders = [] if args.no_holder else [args.holder]
    physics = model.physics(region=args.region, holders=holders, slices=args.slices)
    rise = max(1, 2 * args.ramp // 3)
    for k in range(1, args.ramp + 1):
        physics.press(0, args.press, np.array([0.0, 0.0, -args.force * min(k, rise) / rise]))
        if not physics.step():
            raise SystemExit(f"the ramp's step {k} was refused: a load beyond the region's?")
    return physics.newton, physics.q, physics.pi, physics.load.copy()


def main() -> None:
    args = parse()
    newton, q, pi, held_load = held_state(args)
    slices = len(newton.bounds) - 1
    balanced = HapticNewton(newton.sample, newton.linear, newton.iterations, slices)
    equal = HapticNewton(newton.sample, newton.linear, newton.iterations, slices)
    S = len(newton.sample[5])
    equal.bounds = np.linspace(0, S, slices + 1).astype(np.int64)  # stop 50's parts
    equal.bounds.flags.writeable = False
    solvers = {"balanced": balanced, "equal": equal}
    states = {name: (q.copy(), pi.copy()) for name in solvers}
    for name, solver in solvers.items():
        if not solver.refresh(*states[name]):
            raise SystemExit("the held state's tangent does not factorise")
    times = {name: np.empty(args.steps) for name in solvers}
    finishing = {name: np.zeros(args.steps, bool) for name in solvers}
    for k in range(args.steps):
        for name, solver in solvers.items():
            finishing[name][k] = solver.part == slices - 1
            state = states[name]
            start = time.perf_counter_ns()
            taken = solver.step(state[0], state[1], held_load)
            times[name][k] = (time.perf_counter_ns() - start) / 1e3
            if not taken:
                raise SystemExit(f"{name}: step {k} refused")
    summary = {}
    for name, solver in solvers.items():
        t, last = times[name][args.steps // 20 :], finishing[name][args.steps // 20 :]
        parts = np.diff(solver.bounds)
        summary[name] = np.percentile(t, [0, 10, 50, 99])
        print(f"{name:9s} parts {parts[0]}/{parts[-2]}/{parts[-1]} (first/second last/last): "
              "step min %.0f p10 %.0f p50 %.0f p99 %.0f us" % tuple(summary[name]),
              f"| finishing a tangent min {t[last].min():.0f} p50 {np.median(t[last]):.0f},"
              f" others min {t[~last].min():.0f} p50 {np.median(t[~last]):.0f} us")  # fmt: skip
    ratio = summary["equal"] / summary["balanced"]
    print(
        "equal / balanced: "
        + ", ".join(
            f"{k} {v:.3f}" for k, v in zip(("min", "p10", "p50", "p99"), ratio, strict=True)
        )
    )
    drift = np.abs(states["equal"][0] - states["balanced"][0]).max()
    print(f"held states differ by {drift / np.abs(states['balanced'][0]).max():.1e} (relative)")


if __name__ == "__main__":
    main()
