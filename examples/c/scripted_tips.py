"""Write the scripted tool path of ``hapticrom play`` as a tip file for ``servo_loop --tips``.

The C example cannot call Python, and the path is placed on the model's offset surface
(:func:`hapticrom.online.play.scripted_tips`: approach, press at 30 degrees from the
normal, slide 2 mm across the centre of the trained region, lift), so it is computed here
once and read there: the tips the C host steps are then exactly those the Python
simulator steps (written with 17 significant digits: doubles round-trip).

    .venv/bin/python examples/c/scripted_tips.py out/cornea-soft.h5 build/tips.csv \\
        [--ticks 3000] [--rate 1000] [--tool-radius MM]

The file has the columns t, x, y, z (s, mm) of ``hapticrom play --path``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from hapticrom.online import load
from hapticrom.online.play import MAX_PATH_ROWS, scripted_tips
from hapticrom.shared.errors import HapticromError, InputError


def write_tips(path: Path, tips: np.ndarray, rate: float) -> None:
    """``tips`` (N, 3) mm as rows t, x, y, z of a CSV at ``path`` (one row per 1 / rate s)."""
    rows = np.column_stack([np.arange(len(tips)) / rate, tips])
    np.savetxt(path, rows, delimiter=",", header="t,x,y,z", comments="", fmt="%.17g")


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, help="the artifact (.h5)")
    parser.add_argument("out", type=Path, help="the tip file to write (.csv)")
    parser.add_argument("--ticks", type=int, default=3000, help="rows (default 3000)")
    parser.add_argument("--rate", type=float, default=1000.0, help="Hz, for t (default 1000)")
    parser.add_argument("--tool-radius", type=float, default=None,
                        help="mm (default: the artifact's training radius)")  # fmt: skip
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Write the tip file; 0, or 1 with one line naming the problem on stderr."""
    a = _arguments(argv)
    try:
        if not 1 <= a.ticks <= MAX_PATH_ROWS:
            raise InputError(f"--ticks must be 1 to {MAX_PATH_ROWS:,}, got {a.ticks}")
        if not 0.0 < a.rate < float("inf"):
            raise InputError(f"--rate must be a finite positive number (Hz), got {a.rate}")
        if not a.out.parent.is_dir():
            raise InputError(f"{a.out}: directory {a.out.parent} does not exist")
        model = load(a.model)
        try:
            tips = scripted_tips(model, a.ticks, radius=a.tool_radius)
        except ValueError as exc:  # the loadable surface is not under the region's centre
            raise InputError(
                f"{a.model}: the scripted path cannot be placed on it ({exc})"
            ) from None
        write_tips(a.out, tips, a.rate)
    except (HapticromError, OSError) as exc:
        print(f"scripted_tips: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
