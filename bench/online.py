"""Latency of the online runtime against the same step in plain numpy, in one run.

    python bench/online.py out/cornea.h5 [--steps 100000] [--json out.json]

p50 / p99 / max of step_displacement over >= 100,000 calls, step_force,
set_contact (sliding), surface_displacement, and load + warm-up with a warm
numba cache, for each rendered surface the model offers (transported, compliance,
PODI; Grassmann with the stored curves) with the stored curves and the POD-ANM series
(if the artifact has them). Targets (issue "artifact and
online runtime"): step p99 <= 10 us; >= 20x faster than the numpy step;
surface_displacement <= 100 us; load + warm-up <= 2 s; issue 15: surface_displacement
at an untrained contact (three neighbours) p99 <= 50 us, set_contact p99 <= 20 us; issue 16:
step_position along the scripted oblique path (contact detection and proxy included) p99
<= 10 us, stiffness p99 <= 2 us.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hapticrom.online.latency import measure, report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--json")
    args = parser.parse_args()
    results = {}
    from hapticrom.shared.artifact import read_artifact

    # Not hapticrom.online.load: importing the kernels here would hide their load time.
    from hapticrom.shared.errors import InputError

    groups = read_artifact(args.model).groups
    fields = ["transport", "compliance", "podi"]
    combos = [(field, "curves") for field in fields] + [("grassmann", "curves")]
    if "anm" in groups:
        combos += [(field, "anm") for field in fields]
    for interpolation, response in combos:
        key = f"{interpolation}+{response}"
        try:
            results[key] = measure(args.model, args.steps, interpolation, response=response)
        except InputError as exc:  # the model has no chart, or no contact fields
            print(f"{key}: not measured ({exc})\n")
            continue
        print(report(results[key]))
        print()
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
