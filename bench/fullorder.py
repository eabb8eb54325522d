"""Benchmark of the full-order solver: the default HGO cornea, indentation 0 -> 0.5 mm.

Runs ``examples/cornea-hgo-indent.toml`` (default mesh, 10 displacement steps)
with full and modified Newton on 1 and 2 ranks, each in a fresh ``mpirun``,
and prints seconds per load step and per Newton iteration, form-compilation
(JIT) time separately (cold: an empty cache; warm: the project's cache), and
ratios against the baseline measured in the same run (full Newton, 1 rank).

    python bench/fullorder.py [--ranks 1 2] [--steps 10] [--json out.json]

Target (issue "Foundation"): at most 1.0 s per load step on 2 ranks at about
25-32k DOF.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "examples" / "cornea-hgo-indent.toml"
TARGET_SECONDS_PER_STEP = 1.0


def worker(newton: str, steps: int, out: str) -> None:
    from mpi4py import MPI

    from hapticrom.offline.config import ProblemConfig
    from hapticrom.offline.fe.fullorder import FullOrderModel

    config = ProblemConfig.from_toml(CONFIG)
    config = ProblemConfig.from_dict(
        {
            "mesh": {"file": str(config.mesh.file)},
            "material": {"law": config.material.law, **config.material.params},
            "discretisation": {"element": config.discretisation.element},
            "load": {
                "mode": "displacement",
                "displacement": list(config.load.displacement),
                "contact_point": list(config.load.contact_point),
                "contact_radius": config.load.contact_radius,
                "steps": steps,
            },
            "solver": {"newton": newton},
        }
    )
    comm = MPI.COMM_WORLD
    model = FullOrderModel(config, comm=comm, verbose=False)
    result = model.solve()
    step_seconds = [r.seconds for r in result.records]
    its = [r.newton_iterations for r in result.records]
    summary = {
        "ranks": comm.size,
        "newton": newton,
        "dofs": result.num_dofs,
        "setup_seconds": result.setup_seconds,
        "jit_seconds": result.jit_seconds,
        "solve_seconds": result.solve_seconds,
        "steps": len(step_seconds),
        "seconds_per_step": result.solve_seconds / len(step_seconds),
        "seconds_per_step_after_first": sum(step_seconds[1:]) / max(len(step_seconds) - 1, 1),
        "newton_iterations": sum(its),
        "seconds_per_iteration": result.solve_seconds / sum(its),
        "force_z_final": float(result.force[-1, 2]),
    }
    if comm.rank == 0:
        Path(out).write_text(json.dumps(summary))


def run(ranks: int, newton: str, steps: int, cache: Path) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        out = f.name
    env = {**os.environ, "XDG_CACHE_HOME": str(cache), "OPENBLAS_NUM_THREADS": "1"}
    mpirun = shutil.which("mpirun", path=str(Path(sys.executable).parent)) or "mpirun"
    cmd = [mpirun, "-n", str(ranks), sys.executable, __file__, "--worker", newton]
    cmd += ["--steps", str(steps), "--out", out]
    subprocess.run(cmd, check=True, env=env, cwd=ROOT)
    result = json.loads(Path(out).read_text())
    os.unlink(out)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--json", help="also write the results here")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker, args.steps, args.out)
        return

    if not (ROOT / "meshes" / "cornea.msh").is_file():
        sys.exit("meshes/cornea.msh is missing: run `make meshes` first")
    warm = Path(os.environ.get("XDG_CACHE_HOME", ROOT / ".cache"))
    with tempfile.TemporaryDirectory() as cold:
        cold_run = run(1, "full", 1, Path(cold))  # compiles every form from scratch
    rows = [run(n, newton, args.steps, warm) for n in args.ranks for newton in ("full", "modified")]
    base = next(r for r in rows if r["ranks"] == min(args.ranks) and r["newton"] == "full")

    dofs = base["dofs"]
    print(
        f"\nHGO cornea (default mesh), indentation 0 -> 0.5 mm in {args.steps} steps: "
        f"{dofs['displacement']} displacement + {dofs['pressure']} pressure DOFs"
    )
    print(
        f"form compilation (JIT): {cold_run['jit_seconds']:.1f} s cold (empty cache), "
        f"{base['jit_seconds']:.2f} s warm; mesh and set-up {base['setup_seconds']:.2f} s"
    )
    header = (
        f"{'ranks':>5} {'newton':>9} {'its':>4} {'s/step':>7} {'s/step*':>8} {'s/it':>6} "
        f"{'speed-up':>8} {'target':>7}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        speedup = base["seconds_per_step"] / r["seconds_per_step"]
        ok = "met" if r["seconds_per_step"] <= TARGET_SECONDS_PER_STEP else "missed"
        print(
            f"{r['ranks']:>5} {r['newton']:>9} {r['newton_iterations']:>4} "
            f"{r['seconds_per_step']:>7.3f} {r['seconds_per_step_after_first']:>8.3f} "
            f"{r['seconds_per_iteration']:>6.3f} {speedup:>7.2f}x {ok:>7}"
        )
    print(
        "s/step*: excluding the first step (which also analyses the sparsity pattern); "
        f"speed-up against {base['ranks']} rank(s), full Newton; "
        f"target {TARGET_SECONDS_PER_STEP} s/step on 2 ranks."
    )
    forces = {(r["ranks"], r["newton"]): r["force_z_final"] for r in rows}
    spread = max(forces.values()) - min(forces.values())
    print(f"final force_z {base['force_z_final']:.6e} N; spread across runs {spread:.1e} N")
    if args.json:
        Path(args.json).write_text(json.dumps({"cold": cold_run, "runs": rows}, indent=2))


if __name__ == "__main__":
    main()
