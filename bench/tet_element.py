"""Which tetrahedral element for organs: locking, accuracy against Taylor-Hood, cost per solve.

    mpirun -n 2 python bench/tet_element.py --out out/tet-element \\
        [--meshes coarse default] [--nu 0.48 0.499] [--elements P1 P2 P2P0 P2P1] [--steps N]
        [--contact-point X Y Z] [--no-tangent-check]
    python bench/tet_element.py --out out/tet-element --tables-from A.json B.json

The study in the README (about 25 min on 2 shared cores)::

    mpirun -n 2 python bench/tet_element.py --out out/tet-element/sweep --steps 2
    mpirun -n 2 python bench/tet_element.py --out out/tet-element/convergence \\
        --meshes default 6.4 fine --nu 0.48 --elements P2P0 P2P1 --steps 1 --no-tangent-check
    python bench/tet_element.py --out out/tet-element --tables-from \\
        out/tet-element/sweep/tet-element.json out/tet-element/convergence/tet-element.json

The liver palpation of ``examples/liver-neo-hookean-palpation.toml`` (compressible
neo-Hookean, E = 160 kPa, 1.2 N spread over a 10 mm tool tip on the anterior surface,
the posterior quarter clamped) solved with every tetrahedral element on the same mesh:

- ``P1``, ``P2``: displacement only (they lock as nu -> 0.5: too stiff);
- ``P2P0``: quadratic displacement, element-wise constant pressure;
- ``P2P1``: Taylor-Hood (quadratic displacement, continuous linear pressure), inf-sup
  stable and optimally convergent: the reference on each mesh.

The response is the contact patch's mean displacement along the 1.2 N load (the
palpation's depth), then the largest nodal displacement. Each is compared with P2P1 on
the same mesh and nu, and each element with itself on the finest mesh listed (the
discretisation error). Costs: Newton iterations, seconds per solve (the whole load path
as a campaign solve does it, including the physics sanity checks) and per Newton
iteration, DOFs and the MUMPS factors (entries, flops of one factorisation).

A mesh is a built-in refinement (``coarse``, ``default``, ``fine``) or a number: the
liver's ``mesh_size`` in mm (``6.4`` gives about 4,100 nodes and 19,500 tetrahedra).
Every mesh is loaded at the same contact point (``--contact-point``; default: the
default liver's default contact point, that of the palpation TOML). Writes
``OUT/tet-element.md`` and ``OUT/tet-element.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from mpi4py import MPI

from hapticrom.meshes import REFINEMENTS, build, generate
from hapticrom.offline.config import ProblemConfig, read_toml
from hapticrom.offline.fe.formulation import ELEMENTS
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.shared.errors import HapticromError

ROOT = Path(__file__).resolve().parents[1]
PALPATION = ROOT / "examples" / "liver-neo-hookean-palpation.toml"
REFERENCE = "P2P1"
# Locking-free: the depth's difference from Taylor-Hood moves by less than this between
# the smallest and the largest nu (a locking element stiffens as nu -> 0.5: P1 moves by
# tens of points, P2 by a few).
LOCKING_DRIFT = 0.005
# Adequate: the depth within this fraction of Taylor-Hood's on the same mesh, i.e. within
# what mesh refinement itself changes on these meshes (coarse -> default: 6 %), and far
# below the uncertainty of a liver's stiffness.
ADEQUATE = 0.05


def mesh_spec(text: str) -> tuple[str, str, dict]:
    """(label, refinement, parameters) of a ``--meshes`` entry: a refinement or a size."""
    if text in REFINEMENTS:
        return text, text, {}
    try:
        size = float(text)
    except ValueError:
        size = math.nan
    if not (math.isfinite(size) and size > 0):
        raise argparse.ArgumentTypeError(
            f"mesh {text!r}: give {', '.join(REFINEMENTS)} or a mesh_size in mm (a number > 0)"
        )
    return f"h{size:g}", "default", {"mesh_size": size}


def poisson_ratio(text: str) -> float:
    """A ``--nu`` entry: a number in [0, 0.5)."""
    try:
        nu = float(text)
    except ValueError:
        nu = math.nan
    if not 0 <= nu < 0.5:
        raise argparse.ArgumentTypeError(f"nu {text!r}: give a number in [0, 0.5)")
    return nu


def comm_size() -> int:
    """Ranks in this run."""
    return MPI.COMM_WORLD.size


def parse_args() -> argparse.Namespace:
    """The command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="output directory (meshes, .md, .json)")
    parser.add_argument("--meshes", type=mesh_spec, nargs="+", default=["coarse", "default"])
    parser.add_argument("--nu", type=poisson_ratio, nargs="+", default=[0.48, 0.499])
    tets = list(ELEMENTS["tetrahedron"])
    parser.add_argument("--elements", nargs="+", choices=tets, default=tets)
    parser.add_argument("--steps", type=int, help="load steps (default: the TOML's)")
    parser.add_argument(
        "--contact-point",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="mm (default: the default liver's default contact point, on every mesh)",
    )
    parser.add_argument(
        "--tables-from",
        nargs="+",
        metavar="JSON",
        help="solve nothing: merge earlier tet-element.json files into one table",
    )
    parser.add_argument(
        "--no-tangent-check",
        action="store_true",
        help="skip the sanity check's LDL^T of the last tangent (accuracy runs; a campaign "
        "solve does it)",
    )
    args = parser.parse_args()
    args.meshes = [m if isinstance(m, tuple) else mesh_spec(m) for m in args.meshes]
    if args.steps is not None and not 1 <= args.steps <= 1000:
        parser.error(f"--steps {args.steps}: give 1 ... 1000")
    if args.tables_from and comm_size() > 1:
        parser.error("--tables-from solves nothing: run it without mpirun")
    if args.contact_point is not None and not all(map(math.isfinite, args.contact_point)):
        parser.error(f"--contact-point {args.contact_point}: give three finite numbers (mm)")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        parser.error(f"--out {args.out}: exists and is not a directory")
    return args


def make_meshes(specs, out: Path, comm) -> dict[str, dict]:
    """Generate the liver meshes on rank 0; {label: {"path", "nodes", "cells", ...}}."""
    meshes, error = {}, None
    if comm.rank == 0:
        try:
            for label, refinement, params in specs:
                path = out / "meshes" / f"liver-{label}.msh"
                path.parent.mkdir(parents=True, exist_ok=True)
                sidecar = generate("liver", path, refinement=refinement, **params)
                meshes[label] = {
                    "path": str(path),
                    "mesh_size": sidecar["params"]["mesh_size"],
                    **sidecar["counts"],
                    "contact_point": sidecar["default_contact_point"],
                }
        except HapticromError as exc:
            error = str(exc)
    meshes, error = comm.bcast((meshes, error), root=0)
    if error:  # one message, from rank 0
        raise SystemExit(f"tet_element: {error}" if comm.rank == 0 else 2)
    return dict(sorted(meshes.items(), key=lambda item: item[1]["nodes"]))


def default_contact_point(comm) -> list[float]:
    """The default contact point of the default liver (the palpation TOML's point, mm)."""
    point = build("liver").default_contact_point if comm.rank == 0 else None
    return comm.bcast(point, root=0)


def palpation_config(mesh: dict, element: str, nu: float, steps, point) -> ProblemConfig:
    """The palpation TOML with this mesh, element, nu, contact point and steps; no fields."""
    data = read_toml(PALPATION)
    data["mesh"]["file"] = mesh["path"]
    data["material"]["nu"] = nu
    data["discretisation"] = {"element": element}
    data["load"]["contact_point"] = list(point)
    if steps is not None:
        data["load"]["steps"] = steps
    data["output"] = {"xdmf": False}
    return ProblemConfig.from_dict(data, base_dir=PALPATION.parent, source=str(PALPATION))


def factor_statistics(model: FullOrderModel) -> dict:
    """Entries and flops of the last MUMPS factorisation of the Newton solver (or None)."""
    from petsc4py import PETSc

    try:
        factors = model.newton.snes.getKSP().getPC().getFactorMatrix()
        entries = factors.getMumpsInfog(29)  # negative: millions of entries
        return {
            "factor_entries": entries if entries >= 0 else -entries * 1_000_000,
            "factor_flops": factors.getMumpsRinfog(3),
            "factor_memory_mb": factors.getMumpsInfog(22),  # sum over the ranks
        }
    except PETSc.Error:
        return {"factor_entries": None, "factor_flops": None, "factor_memory_mb": None}


def solve_case(config: ProblemConfig, comm, tangent_check: bool) -> dict:
    """Solve one palpation; the measures and costs of its last step."""
    comm.barrier()
    t0 = time.perf_counter()
    model = FullOrderModel(config, comm=comm, verbose=False)
    if not tangent_check:
        model.monitor.tangent = "never"
    result = model.solve()
    wall = time.perf_counter() - t0
    last = result.sanity.steps[-1]
    newton_seconds = sum(r.seconds for r in result.records)
    return {
        "dofs_u": result.num_dofs["displacement"],
        "dofs_p": result.num_dofs["pressure"],
        "steps": len(result.records),
        "step_cuts": sum(r.step_cuts for r in result.records),
        "newton_iterations": result.newton_iterations,
        "setup_seconds": result.setup_seconds,
        "jit_seconds": result.jit_seconds,
        "solve_seconds": result.solve_seconds,
        "seconds_per_iteration": newton_seconds / max(result.newton_iterations, 1),
        "sanity_seconds": result.solve_seconds - newton_seconds,
        "wall_seconds": wall,
        "force": last.force,
        "depth": last.depth,
        "u_max": last.u_max,
        "j_min": last.j_min,
        "tangent_negative": last.tangent_negative,
        "flags": [f.kind for f in result.sanity.flags],
        **factor_statistics(model),
    }


def relative(value: float, reference: float | None) -> float | None:
    """(value - reference) / reference, or None without a reference."""
    if reference is None or reference == 0:
        return None
    return (value - reference) / reference


def compare(rows: list[dict]) -> None:
    """Add to each row its differences from Taylor-Hood on the same mesh (``_vs_ref``) and
    on the finest mesh (``_vs_best``, the best reference), and from itself on the finest
    mesh (``_vs_finest``, the discretisation error)."""

    def find(mesh, element, nu):
        return next(
            (r for r in rows if (r["mesh"], r["element"], r["nu"]) == (mesh, element, nu)), None
        )

    finest = max(rows, key=lambda r: r["nodes"])["mesh"]
    for row in rows:
        ref = find(row["mesh"], REFERENCE, row["nu"])
        best = find(finest, REFERENCE, row["nu"])
        fine = find(finest, row["element"], row["nu"])
        for key in ("depth", "u_max"):
            row[f"{key}_vs_ref"] = relative(row[key], ref and ref[key])
            row[f"{key}_vs_best"] = relative(row[key], best and best[key])
            row[f"{key}_vs_finest"] = relative(row[key], fine and fine[key])
        flops = row["factor_flops"], ref and ref["factor_flops"]
        row["flops_vs_ref"] = flops[0] / flops[1] if all(flops) else None


def locking_drift(rows: list[dict]) -> float | None:
    """How far the depth's difference from Taylor-Hood moves from the smallest to the
    largest nu (the largest move over the meshes): a locking element stiffens with nu."""
    moves = []
    for mesh in {r["mesh"] for r in rows}:
        mine = sorted((r for r in rows if r["mesh"] == mesh), key=lambda r: r["nu"])
        if len(mine) > 1 and None not in (mine[0]["depth_vs_ref"], mine[-1]["depth_vs_ref"]):
            moves.append(abs(mine[-1]["depth_vs_ref"] - mine[0]["depth_vs_ref"]))
    return max(moves, default=None)


def recommend(rows: list[dict]) -> dict:
    """The locking-free element within ADEQUATE of Taylor-Hood with the cheapest factorisation."""
    verdict = {}
    for element in sorted({r["element"] for r in rows}):
        mine = [r for r in rows if r["element"] == element]
        diffs = [abs(r["depth_vs_ref"]) for r in mine if r["depth_vs_ref"] is not None]
        ratios = [r["flops_vs_ref"] for r in mine if r["flops_vs_ref"] is not None]
        verdict[element] = {
            "locking_drift": locking_drift(mine),
            "worst_depth_vs_ref": max(diffs, default=None),
            "flops_vs_ref": max(ratios, default=None),
        }
    eligible = [
        e
        for e, v in verdict.items()
        if v["locking_drift"] is not None
        and v["locking_drift"] <= LOCKING_DRIFT
        and v["worst_depth_vs_ref"] is not None
        and v["worst_depth_vs_ref"] <= ADEQUATE
        and v["flops_vs_ref"] is not None
    ]
    choice = min(eligible, key=lambda e: verdict[e]["flops_vs_ref"], default=None)
    return {
        "locking_drift_limit": LOCKING_DRIFT,
        "tolerance": ADEQUATE,
        "elements": verdict,
        "recommended": choice,
    }


def percent(x: float | None) -> str:
    """A signed percentage, or a dash."""
    return "-" if x is None else f"{100 * x:+.2f} %"


def magnitude(x: float | None) -> str:
    """An unsigned percentage, or a dash."""
    return "-" if x is None else f"{100 * x:.2f} %"


def points(x: float | None) -> str:
    """A difference of fractions in percentage points, or a dash."""
    return "-" if x is None else f"{100 * x:.2f} points"


def markdown(results: dict) -> str:
    """The results (rows, meshes, verdict, runs) as a markdown document."""
    rows, meshes, verdict, common = (results[k] for k in ("rows", "meshes", "verdict", "load"))
    lines = ["# Tetrahedral element for organs: liver palpation", ""]
    for run in results["runs"]:
        lines.append(
            f"- `{run['command']}`: {run['ranks']} rank(s), load average "
            f"{run['load_before']:.1f} before, {run['load_after']:.1f} after (cores shared)"
        )
    lines += [
        "",
        f"Load: {common['force']} N over a {common['contact_radius']} mm tool tip at "
        f"{[round(c, 2) for c in common['contact_point']]} mm; neo-Hookean, E = "
        f"{common['E']} MPa. depth: the contact patch's mean displacement along the load. "
        f"vs P2P1: against Taylor-Hood on the same mesh; vs best: against Taylor-Hood on the "
        "finest mesh; vs finest: against the same element on the finest mesh. s/solve: the "
        "load path (steps: its increments) with its sanity checks (LDL^T of the last tangent "
        "only where tangent = yes), no compilation; seconds on shared cores are noisy, the "
        "factorisation's flops are not.",
        "",
        "| mesh | nodes | tets | nu | element | DOFs u + p | steps | its | tangent | s/solve | "
        "s/it | factor entries | GFlop/fact. | depth (mm) | vs P2P1 | vs best | vs finest | "
        "u_max (mm) | vs P2P1 |",
        "|---|---:|---:|---:|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"
        "---:|---:|",
    ]
    for r in rows:
        m = meshes[r["mesh"]]
        entries = "-" if r["factor_entries"] is None else f"{r['factor_entries'] / 1e6:.1f} M"
        flops = "-" if r["factor_flops"] is None else f"{r['factor_flops'] / 1e9:.1f}"
        lines.append(
            f"| {r['mesh']} | {m['nodes']} | {m['cells']} | {r['nu']} | {r['element']} | "
            f"{r['dofs_u']} + {r['dofs_p']} | {r['steps']} | {r['newton_iterations']} | "
            f"{'yes' if r['tangent_check'] else 'no'} | {r['solve_seconds']:.1f} | "
            f"{r['seconds_per_iteration']:.2f} | {entries} | {flops} | {r['depth']:.5f} | "
            f"{percent(r['depth_vs_ref'])} | {percent(r['depth_vs_best'])} | "
            f"{percent(r['depth_vs_finest'])} | {r['u_max']:.5f} | {percent(r['u_max_vs_ref'])} |"
        )
    lines += ["", "Per element (over all meshes):", ""]
    for element, v in verdict["elements"].items():
        ratio = v["flops_vs_ref"]
        lines.append(
            f"- {element}: depth's difference from {REFERENCE} moves by "
            f"{points(v['locking_drift'])} from the smallest to the largest nu; largest "
            f"|difference| {magnitude(v['worst_depth_vs_ref'])}; factorisation flops "
            + ("-" if ratio is None else f"{ratio:.2f}x")
            + f" {REFERENCE}'s (largest ratio)"
        )
    lines += [
        "",
        f"Recommended (locking-free: moves by at most {100 * verdict['locking_drift_limit']:g} "
        f"point(s); within {100 * verdict['tolerance']:g} % of {REFERENCE} on every mesh; the "
        f"cheapest factorisation): **{verdict['recommended'] or 'none'}**.",
        "",
    ]
    return "\n".join(lines)


def merge(paths: list[str]) -> dict:
    """Rows, meshes and runs of earlier results (JSON); the first row of a case wins."""
    merged = {"rows": [], "meshes": {}, "runs": [], "load": None}
    seen = set()
    for path in paths:
        try:
            data = json.loads(Path(path).read_text())
            rows, meshes, runs, load = (data[k] for k in ("rows", "meshes", "runs", "load"))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"tet_element: {path}: not a tet_element JSON ({exc})") from None
        if merged["load"] not in (None, load):
            raise SystemExit(f"tet_element: {path}: another load or contact point than {paths[0]}")
        merged["load"] = load
        merged["runs"] += runs
        merged["meshes"].update(meshes)
        for row in rows:
            case = (row["mesh"], row["element"], row["nu"])
            if case not in seen:
                seen.add(case)
                merged["rows"].append(row)
    return merged


def solve_all(args, meshes: dict, point, comm) -> list[dict]:
    """Solve every (mesh, nu, element) case; the rows, printed as they come."""
    rows = []
    for label, mesh in meshes.items():
        for nu in args.nu:
            for element in args.elements:
                config = palpation_config(mesh, element, nu, args.steps, point)
                row = {"mesh": label, "nodes": mesh["nodes"], "nu": nu, "element": element}
                row["tangent_check"] = not args.no_tangent_check
                row.update(solve_case(config, comm, row["tangent_check"]))
                rows.append(row)
                if comm.rank == 0:
                    print(
                        f"{label:8s} nu={nu:<6g} {element:5s} {row['dofs_u']:7d} + "
                        f"{row['dofs_p']:6d} DOFs  depth {row['depth']:.5f} mm  u_max "
                        f"{row['u_max']:.5f} mm  {row['newton_iterations']:3d} its  "
                        f"{row['solve_seconds']:7.1f} s ({row['seconds_per_iteration']:.2f} s/it)",
                        flush=True,
                    )
    return rows


def run(args, comm) -> dict:
    """Generate the meshes, solve every case; the results (rows, meshes, runs, load)."""
    load_before = os.getloadavg()[0]
    meshes = make_meshes(args.meshes, Path(args.out), comm)
    point = args.contact_point or default_contact_point(comm)
    rows = solve_all(args, meshes, point, comm)
    toml = read_toml(PALPATION)
    command = f"mpirun -n {comm.size} python bench/tet_element.py {' '.join(sys.argv[1:])}"
    return {
        "rows": rows,
        "meshes": meshes,
        "runs": [
            {
                "command": command,
                "ranks": comm.size,
                "load_before": load_before,
                "load_after": os.getloadavg()[0],
            }
        ],
        "load": {
            "force": toml["load"]["force"],
            "contact_radius": toml["load"]["contact_radius"],
            "contact_point": list(point),
            "E": toml["material"]["E"],
        },
    }


def main() -> None:
    args = parse_args()
    comm = MPI.COMM_WORLD
    results = merge(args.tables_from) if args.tables_from else run(args, comm)
    if comm.rank != 0:
        return
    compare(results["rows"])
    results["verdict"] = recommend(results["rows"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    document = markdown(results)
    (out / "tet-element.md").write_text(document)
    (out / "tet-element.json").write_text(json.dumps(results, indent=1))
    print("\n" + document)
    print(f"wrote {out / 'tet-element.md'} and {out / 'tet-element.json'}")


if __name__ == "__main__":
    main()
