"""Accuracy of the full-order HGO cornea: volumetric locking and mesh convergence.

    mpirun -n 2 python bench/cornea_accuracy.py [--out out/cornea-accuracy] [--skip-q2]

1. Locking (small load, 0.01 N on the apex through a rounded tip of radius
   0.5 mm, default mesh): apex deflection with plain trilinear hexahedra (Q1),
   the mixed Q1/P0 element (D = 1e-5 and 1e-3) and the Taylor-Hood Q2/Q1
   reference on the same mesh.
2. Mesh convergence of the haptic case: reaction force at 0.1 ... 0.5 mm of
   prescribed apex indentation (rigid tip of radius 0.5 mm) on the coarse,
   default and fine meshes, with the thesis' Table 2.2 FEM forces (its own
   mesh) for orientation. Writes ``curve-<mesh>.csv`` files and a plot
   ``cornea-indentation.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.meshes import generate
from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.fullorder import FullOrderModel

ROOT = Path(__file__).resolve().parents[1]
# Thesis Table 2.2, F_FEM (N) at prescribed indentation u (mm), on its own mesh.
THESIS_TABLE_2_2 = {0.1: 0.0055, 0.2: 0.0108, 0.3: 0.0158, 0.45: 0.0227}


def solve(mesh: Path, load: dict, element="Q1P0", D=1e-5, out=None):
    config = ProblemConfig.from_dict(
        {
            "mesh": {"file": str(mesh)},
            "material": {"law": "hgo", "D": D},
            "discretisation": {"element": element},
            "load": load,
            "output": {"xdmf": False},
        }
    )
    t0 = time.perf_counter()
    model = FullOrderModel(config, verbose=False)
    result = model.solve(out_dir=out)
    return model, result, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "out" / "cornea-accuracy"))
    parser.add_argument("--skip-q2", action="store_true", help="skip the Q2/Q1 reference")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    out = Path(args.out)
    meshes = {}
    for refinement in ("coarse", "default", "fine"):
        path = out / f"cornea-{refinement}.msh"
        if comm.rank == 0:
            generate("cornea", path, refinement=refinement)
        meshes[refinement] = path
    comm.barrier()

    def say(*a):
        if comm.rank == 0:
            print(*a, flush=True)

    say(f"HGO cornea (thesis Table 2.1), {comm.size} rank(s); units mm, N")
    say("\n1. Locking: apex deflection under 0.01 N (tip radius 0.5 mm), default mesh")
    force = {"mode": "force", "force": [0.0, 0.0, -0.01], "contact_radius": 0.5, "steps": 2}
    cases = [("Q1", 1e-5), ("Q1P0", 1e-5), ("Q1P0", 1e-3)]
    if not args.skip_q2:
        cases.append(("Q2Q1", 1e-5))
    deflection = {}
    for element, D in cases:
        model, result, seconds = solve(meshes["default"], force, element, D)
        deflection[element, D] = -result.displacement[-1, 2]
        dofs = result.num_dofs
        say(
            f"  {element:5s} D={D:<6g} apex deflection {deflection[element, D]:.5f} mm "
            f"({dofs['displacement']} + {dofs['pressure']} DOFs, {seconds:.1f} s)"
        )
    ref = deflection.get(("Q2Q1", 1e-5))
    q1p0 = deflection["Q1P0", 1e-5]
    if ref:
        say(f"  Q1P0 vs Q2Q1 (same mesh): {100 * (q1p0 - ref) / ref:+.2f} %")
    say(f"  Q1 vs Q1P0: {q1p0 / deflection['Q1', 1e-5]:.1f}x too stiff (volumetric locking)")
    d_change = (deflection["Q1P0", 1e-3] - q1p0) / q1p0
    say(f"  Q1P0, D = 1e-5 -> 1e-3: apex deflection changes by {100 * d_change:+.3f} %")

    say("\n2. Mesh convergence: reaction force (N) under prescribed apex indentation")
    indent = {
        "mode": "displacement",
        "displacement": [0.0, 0.0, -0.5],
        "contact_radius": 0.5,
        "steps": 10,
    }
    curves = {}
    for refinement, mesh in meshes.items():
        model, result, seconds = solve(mesh, indent, out=out / f"run-{refinement}")
        curves[refinement] = (-result.displacement[:, 2], -result.force[:, 2])
        nodes = model.organ.mesh.geometry.index_map().size_global
        say(
            f"  {refinement:8s} {nodes:6d} nodes, tip holds {model.patch_displacement.count:3d} "
            f"nodes: F(0.1) = {-result.force[1, 2]:.5f}  F(0.25) = {-result.force[4, 2]:.5f}  "
            f"F(0.5) = {-result.force[-1, 2]:.5f}  ({seconds:.1f} s)"
        )
    fine = curves["fine"][1][-1]
    for refinement in ("coarse", "default"):
        change = 100 * (curves[refinement][1][-1] - fine) / fine
        say(f"  {refinement} vs fine at 0.5 mm: {change:+.2f} %")
    say(f"  thesis Table 2.2 (its mesh): F(0.45) = {THESIS_TABLE_2_2[0.45]} N")

    if comm.rank == 0:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4.2))
        for refinement, (u, f) in curves.items():
            ax.plot(
                np.r_[0, u], np.r_[0, f], marker="o", ms=3, label=f"hapticrom, {refinement} mesh"
            )
        ax.plot(
            list(THESIS_TABLE_2_2),
            list(THESIS_TABLE_2_2.values()),
            "k^",
            label="thesis Table 2.2 (FEM)",
        )
        ax.set_xlabel("prescribed apex indentation (mm)")
        ax.set_ylabel("reaction force on the tool (N)")
        ax.set_title("HGO cornea, rigid tip of radius 0.5 mm")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "cornea-indentation.png", dpi=130)
        print(f"\nwrote {out / 'cornea-indentation.png'}")


if __name__ == "__main__":
    main()
