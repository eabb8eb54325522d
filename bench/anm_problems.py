"""POD-ANM against full Newton on the thesis' test problems (thesis ch. 3, Figs. 3.3-3.12).

    mpirun -n 2 python bench/anm_problems.py [--order 6] [--tolerance 1e-4] [--only NAME]

For each problem: full Newton (every increment a reference point, every other
one a snapshot), the POD-ANM continuation over the load range, and the first
section alone truncated at orders 1..N (one tangent at the reference state).
Writes out/anm/NAME/{anm-table.csv, anm-orders.csv, anm-curves.png} and a
summary table (Markdown) to out/anm/summary.md. Errors are relative to the
largest full-Newton response of the problem. Targets (issue "POD-ANM"): at
most 1 % inside the validity radius; the beam within 0.5 % of analytic
(tests/test_anm.py checks that one).
"""

from __future__ import annotations

import argparse
import math
import time
import tomllib
from pathlib import Path

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.mpi import print0
from hapticrom.offline.reduce.anm import ANMOptions
from hapticrom.offline.studies.anm import run_study

ROOT = Path(__file__).resolve().parents[1]
ISOTROPIC_CORNEA = {"E": 0.5, "nu": 0.49}  # MPa: isotropic stand-ins, not fitted to tissue

PROBLEMS = {
    "beam-svk": ("beam-svk.toml", {}),
    "beam-neo-hookean": ("beam-neo-hookean.toml", {}),
    "hemisphere-svk": ("hemisphere-svk-pinch.toml", {}),
    "cornea-svk": ("cornea-hgo-indent.toml", {"material": {"law": "svk", **ISOTROPIC_CORNEA}}),
    "cornea-neo-hookean": (
        "cornea-hgo-indent.toml",
        {"material": {"law": "neo-hookean", **ISOTROPIC_CORNEA}},
    ),
    "cornea-hgo": ("cornea-hgo-indent.toml", {}),
    "liver-neo-hookean": ("liver-neo-hookean-palpation.toml", {}),
}


def config_of(name: str) -> ProblemConfig:
    file, override = PROBLEMS[name]
    path = ROOT / "examples" / file
    data = tomllib.loads(path.read_text())
    for section, values in override.items():
        data[section] = values if section == "material" else {**data[section], **values}
    data.setdefault("output", {})["xdmf"] = False
    return ProblemConfig.from_dict(data, base_dir=path.parent, source=str(path))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--order", type=int, default=6)
    parser.add_argument("--tolerance", type=float, default=1e-4)
    parser.add_argument("--only", action="append", choices=sorted(PROBLEMS))
    parser.add_argument("--out", default=str(ROOT / "out" / "anm"))
    args = parser.parse_args()
    options = ANMOptions(order=args.order, tolerance=args.tolerance)
    rows = []
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    for name in args.only or PROBLEMS:
        print0(comm, f"\n== {name}")
        t0 = time.perf_counter()
        fom = FullOrderModel(config_of(name), comm, verbose=False)
        dofs = fom.model.num_dofs()
        result = run_study(fom, options, out_dir=Path(args.out) / name, verbose=comm.rank == 0)
        first = result.first_section_errors
        inside = [r["max_error_inside"] for r in first if not math.isnan(r["max_error_inside"])]
        rows.append(
            {
                "problem": name,
                "dofs": f"{dofs['displacement']}+{dofs['pressure']}",
                "modes": f"{result.modes[0]}+{result.modes[1]}",
                "sections": len(result.branch.sections),
                "evaluations": result.branch.evaluations,
                "newton_s": result.seconds["full_newton"],
                "anm_s": result.seconds["anm"],
                "error": 100 * result.continuation_error,
                "first_valid": first[-1]["validity_load"],
                "inside": 100 * max(inside) if inside else math.nan,
                "seconds": time.perf_counter() - t0,
            }
        )
    if comm.rank != 0:
        return
    lines = [
        f"POD-ANM (order {args.order}, tolerance {args.tolerance:g}) vs full Newton, "
        f"{comm.size} rank(s)",
        "",
        "| problem | DOFs (u+p) | modes (u+p) | sections | residual evals | Newton s | ANM s "
        "| max error % (continuation) | 1st section valid to load factor | max error % inside |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['problem']} | {r['dofs']} | {r['modes']} | {r['sections']} | "
            f"{r['evaluations']} | {r['newton_s']:.1f} | {r['anm_s']:.1f} | {r['error']:.4f} | "
            f"{r['first_valid']:.3f} | {r['inside']:.4f} |"
        )
    text = "\n".join(lines)
    print("\n" + text)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "summary.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
