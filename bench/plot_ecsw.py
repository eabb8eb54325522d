"""The ECSW trade-off as a plot (issue 18): sampled elements -> error and -> time of a
physics step, from ``bench/ecsw_tradeoff.py --local ... --out FILE.json`` runs.

    python bench/plot_ecsw.py RUN.json [RUN.json ...] --out ecsw.png

Left: the depth error (worst step of the converged path) against the sampled elements,
one line a held-out position, the Galerkin model on every element dashed. Right: the time
of a physics step (``--frames``: p50 and p99), with the issue's 1 ms (1 kHz) and 2 ms
(500 Hz) lines. Rows of several runs are merged (one run may hold the frames, another more
tolerances); a row without frames is left out of the right panel. Units: mm, N, ms.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def rows(paths) -> dict:
    """{position: {tolerance: row}}, later files' rows added where earlier ones had none and
    their frames kept where they have them."""
    out: dict = {}
    for path in paths:
        record = json.loads(Path(path).read_text())
        for row in record["results"]:
            kept = out.setdefault(row["position"], {}).setdefault(str(row["tolerance"]), {})
            frames = row.get("frames") if row.get("frames", {}).get("solver") else None
            kept.update({k: v for k, v in row.items() if k != "frames" and k not in kept})
            if frames:
                kept["frames"] = frames
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--out", default="ecsw-tradeoff.png")
    args = parser.parse_args()
    data = rows(args.runs)
    fig, (error_ax, time_ax) = plt.subplots(1, 2, figsize=(10, 4))
    for position, by_tolerance in sorted(data.items()):
        sampled = sorted((r for t, r in by_tolerance.items() if t != "galerkin"),
                         key=lambda r: r["elements"])  # fmt: skip
        line = error_ax.plot([r["elements"] for r in sampled],
                             [100 * r["depth_error"] for r in sampled], "o-",
                             label=f"position {position}")[0]  # fmt: skip
        galerkin = by_tolerance.get("galerkin")
        if galerkin:
            error_ax.axhline(100 * galerkin["depth_error"], ls="--", color=line.get_color())
        timed = [r for r in sampled if "frames" in r]
        for key, marker in (("p50_s", "o-"), ("p99_s", "^:")):
            time_ax.plot([r["elements"] for r in timed], [1e3 * r["frames"][key] for r in timed],
                         marker, color=line.get_color(),
                         label=f"position {position}, {key[:3]}")  # fmt: skip
    error_ax.axhline(3.0, color="k", lw=0.8)
    error_ax.set(xlabel="sampled elements", ylabel="depth error, worst step (%)",
                 title="error (dashed: Galerkin, every element)")  # fmt: skip
    for limit, label in ((1.0, "1 kHz"), (2.0, "500 Hz")):
        time_ax.axhline(limit, color="k", lw=0.8)
        time_ax.text(time_ax.get_xlim()[0], limit, label, va="bottom")
    time_ax.set(xlabel="sampled elements", ylabel="physics step (ms)", title="time a step")
    error_ax.legend(fontsize=8)
    time_ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
