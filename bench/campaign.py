"""Benchmark of training campaigns and of the POD.

    python bench/campaign.py [--quick] [--json out.json]

1. Wall time of the default cornea campaign (``examples/cornea-campaign.toml``:
   37 positions x 10 steps) on 1 rank, on 2 ranks with one rank per solve
   (N=2, K=1: two groups solve different positions) and on 2 ranks with both
   cooperating on each solve (N=2, K=2). Parallel efficiency from 1 to 2 ranks
   = T(1) / (2 T(2)). Each run is a fresh ``mpirun`` into an empty directory.
2. POD time on one rank for the campaign's global snapshot matrix and for one
   position: SLEPc (method of snapshots with EPS; SVD with trlanczos) against
   numpy's SVD, with the eigenvalue agreement.

Targets (issue "Training campaigns"): the default campaign in at most 15 min
on 2 ranks; parallel efficiency from 1 to 2 ranks at least 80 %.
``--quick`` runs 7 positions x 5 steps instead (a smoke test of the script).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CAMPAIGN = ROOT / "examples" / "cornea-campaign.toml"
TARGET_WALL_2_RANKS = 15 * 60.0
TARGET_EFFICIENCY = 0.80


def campaign_file(quick: bool, directory: Path) -> Path:
    data = tomllib.loads(CAMPAIGN.read_text())
    data["mesh"]["file"] = str((CAMPAIGN.parent / data["mesh"]["file"]).resolve())
    if quick:
        data["load"]["steps"] = 5
        data["positions"]["polar"] = [
            {"centre": [0.0, 0.0, 0.0], "radius": 2.0, "rings": 1, "per_ring": 6,
             "include_centre": False}
        ]  # fmt: skip
    path = directory / "campaign.toml"
    path.write_text(_toml(data))
    return path


def _toml(data: dict, prefix: str = "") -> str:
    """Tiny TOML writer for the campaign's tables (values: str, number, bool, lists)."""
    lines, tables = [], []
    for key, value in data.items():
        if isinstance(value, dict):
            tables.append((key, value))
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            for item in value:
                lines.append(f"\n[[{prefix}{key}]]")
                lines += [f"{k} = {json.dumps(v)}" for k, v in item.items()]
        else:
            lines.append(f"{key} = {json.dumps(value)}")
    out = "\n".join(lines)
    for key, value in tables:
        out += f"\n\n[{prefix}{key}]\n" + _toml(value, prefix=f"{prefix}{key}.")
    return out


def run(ranks: int, per_solve: int, toml: Path, out: Path) -> float:
    mpirun = shutil.which("mpirun", path=str(Path(sys.executable).parent)) or "mpirun"
    hapticrom = str(Path(sys.executable).parent / "hapticrom")
    cmd = [mpirun, "-n", str(ranks), hapticrom, "campaign", str(toml), "--out", str(out)]
    cmd += ["--ranks-per-solve", str(per_solve)]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def pod_timings(store_dir: Path) -> dict:
    from mpi4py import MPI

    from hapticrom.offline.campaign.store import SnapshotStore
    from hapticrom.offline.reduce.pod import Truncation, pod, pod_numpy, principal_angles

    store = SnapshotStore(store_dir)
    blocks = [store.read_position(i)[0]["displacement"].T for i in store.completed()]
    results = {}
    for label, Q in (("global", np.hstack(blocks)), ("one position", blocks[0])):
        t = Truncation(eigenvalue_ratio=1e-8)
        timings, outcome = {}, {}
        for method in ("snapshots", "svd"):
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                outcome[method] = pod(Q, MPI.COMM_SELF, None, t, method=method)
                best = min(best, time.perf_counter() - t0)
            timings[method] = best
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            reference = pod_numpy(Q, None, t)
            best = min(best, time.perf_counter() - t0)
        timings["numpy"] = best
        n = reference.n_modes
        agreement = {
            m: {
                "eigenvalue_rel": float(
                    np.max(np.abs(r.eigenvalues[:n] - reference.eigenvalues[:n])
                           / reference.eigenvalues[:n])
                ),
                "max_angle": float(np.max(principal_angles(r.basis_local, reference.basis_local))),
            }
            for m, r in outcome.items()
        }  # fmt: skip
        results[label] = {
            "shape": list(Q.shape),
            "modes": n,
            "seconds": timings,
            "agreement": agreement,
            "eigenvalues": reference.eigenvalues[: max(n, 12)].tolist(),
        }
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json")
    args = parser.parse_args()
    if not (ROOT / "meshes" / "cornea.msh").is_file():
        sys.exit("meshes/cornea.msh is missing: run `make meshes` first")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        toml = campaign_file(args.quick, tmp)
        walls = {}
        for ranks, per_solve in ((1, 1), (2, 1), (2, 2)):
            walls[ranks, per_solve] = run(ranks, per_solve, toml, tmp / f"n{ranks}k{per_solve}")
            print(
                f"campaign on N={ranks}, K={per_solve}: {walls[ranks, per_solve]:.1f} s", flush=True
            )
        pods = pod_timings(tmp / "n1k1")
    print()
    efficiency = {k: walls[1, 1] / (2 * walls[2, k]) for k in (1, 2)}
    for k in (1, 2):
        ok = "met" if walls[2, k] <= TARGET_WALL_2_RANKS else "missed"
        eff_ok = "met" if efficiency[k] >= TARGET_EFFICIENCY else "missed"
        print(
            f"N=2 K={k}: {walls[2, k]:.1f} s (target {TARGET_WALL_2_RANKS:.0f} s: {ok}); "
            f"speed-up {walls[1, 1] / walls[2, k]:.2f}x, efficiency {100 * efficiency[k]:.0f} % "
            f"(target {100 * TARGET_EFFICIENCY:.0f} %: {eff_ok})"
        )
    for label, r in pods.items():
        s = r["seconds"]
        a = r["agreement"]
        eig = [a[m]["eigenvalue_rel"] for m in ("snapshots", "svd")]
        angle = [a[m]["max_angle"] for m in ("snapshots", "svd")]
        print(
            f"POD {label} {r['shape'][0]} x {r['shape'][1]}, {r['modes']} modes: "
            f"SLEPc snapshots/EPS {1e3 * s['snapshots']:.1f} ms, "
            f"SLEPc SVD {1e3 * s['svd']:.1f} ms, numpy SVD {1e3 * s['numpy']:.1f} ms; "
            f"vs numpy (EPS / SVD): eigenvalues {eig[0]:.1e} / {eig[1]:.1e} relative, "
            f"largest principal angle {angle[0]:.1e} / {angle[1]:.1e} rad"
        )
        print(f"  eigenvalues: {' '.join(f'{v:.3g}' for v in r['eigenvalues'])}")
    if args.json:
        Path(args.json).write_text(
            json.dumps({"walls": {f"N{n}K{k}": v for (n, k), v in walls.items()}, "pod": pods},
                       indent=2)
        )  # fmt: skip


if __name__ == "__main__":
    main()
