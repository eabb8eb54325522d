"""Accuracy of the reduced model at held-out tool positions against the full-order solver.

    mpirun -n 2 python bench/accuracy.py out/cornea.h5 [--positions 8] [--work DIR]

Held-out positions are the centroids of Delaunay triangles of the training
samples (snapped to surface nodes: never a training position), solved with the
full-order model exactly as in the training campaign (a campaign of their own,
resumable, in ``--work``). For each, the reduced model (PODI and Grassmann)
predicts the reaction force along the same indentation path; the table has the
layout of the thesis' Table 2.2: depth, F_ROM, F_FEM, error %, plus the
relative error of the surface displacement field. Target (issue "artifact and
online runtime"): at most 5 % force error over 0 to 0.5 mm.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign import CampaignConfig, run_campaign
from hapticrom.offline.store import SnapshotStore
from hapticrom.shared.artifact import read_artifact

TARGET = 0.05


def held_out_points(artifact, count: int) -> list[list[float]]:
    """Centroids of `count` sample triangles spread over the region, snapped to surface nodes."""
    samples = artifact["samples"]
    model = artifact.group_attrs["model"]
    surface = read_surface(model["mesh_file"], model["surface_group"])
    chart = samples["chart_points"]
    triangles = samples["triangles"]
    centroids = chart[triangles].mean(axis=1)
    order = np.argsort(np.arctan2(centroids[:, 1], centroids[:, 0]) + 10 * np.hypot(*centroids.T))
    picked = order[np.linspace(0, len(order) - 1, count).astype(int)]
    origin, axes = samples["chart_origin"], samples["chart_axes"]
    points = []
    trained = {tuple(np.round(p, 9)) for p in samples["points"]}
    for t in picked:
        x = origin + centroids[t] @ axes
        node = surface.nodes[np.argmin(np.linalg.norm(surface.nodes - x, axis=1))]
        if tuple(np.round(node, 9)) not in trained:
            points.append(node.tolist())
    return points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--positions", type=int, default=8)
    parser.add_argument("--work", help="held-out campaign directory (default: MODEL.heldout)")
    parser.add_argument("--json")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    artifact = read_artifact(args.model)
    work = Path(args.work or Path(args.model).with_suffix(".heldout"))

    campaign = json.loads(json.dumps(artifact.attrs["campaign"]))  # a deep copy
    points = held_out_points(artifact, args.positions) if comm.rank == 0 else None
    points = comm.bcast(points, root=0)
    campaign["positions"] = {"points": points}
    campaign.setdefault("campaign", {})["name"] = "held-out"
    campaign["mesh"]["file"] = artifact.group_attrs["model"]["mesh_file"]
    config = CampaignConfig.from_dict(campaign)
    run_campaign(config, work, comm, ranks_per_solve=1, verbose=comm.rank == 0)
    if comm.rank != 0:
        return

    import hapticrom.online as online

    model = online.load(args.model)
    store = SnapshotStore(work)
    nodes = artifact["surface"]["nodes"]
    rows, summary = [], {}
    for interpolation in ("podi", "grassmann"):
        sim = model.simulator(interpolation)
        worst, field_worst = 0.0, 0.0
        out = np.zeros_like(model.vertices)
        for i in store.completed():
            data, attrs = store.read_position(i)
            direction = np.asarray(attrs["direction"])
            sim.set_contact(np.asarray(attrs["point"]))
            for k in range(len(data["force"])):
                depth = float(data["contact_displacement"][k] @ direction)
                f_fem = float(data["force"][k] @ direction)
                f_rom = float(
                    sim.step_displacement(-depth * sim.contact_normal) @ sim.contact_normal
                )
                error = abs(f_rom - f_fem) / f_fem
                worst = max(worst, error)
                sim.surface_displacement(out)
                u = data["displacement"][k].reshape(-1, 3)[nodes]
                field_worst = max(field_worst, np.linalg.norm(out - u) / np.linalg.norm(u))
                if interpolation == "podi":
                    rows.append((i, attrs["point"], depth, f_rom, f_fem, 100 * error))
        summary[interpolation] = {"max_force_error": worst, "max_field_error": field_worst}

    print("\nheld-out positions (PODI), thesis Table 2.2 layout; units mm, N")
    header = ("pos", "x", "y", "z", "u (mm)", "F_ROM", "F_FEM", "err %")
    print(" ".join(f"{h:>{w}}" for h, w in zip(header, (3, 7, 7, 7, 7, 9, 9, 6), strict=True)))
    for i, p, depth, f_rom, f_fem, err in rows:
        if (
            abs(depth / model.depth_step - round(depth / model.depth_step)) < 1e-6
            and round(depth / model.depth_step) % 2 == 0
        ):  # every other depth keeps the table short
            print(
                f"{i:3d} {p[0]:7.3f} {p[1]:7.3f} {p[2]:7.3f} {depth:7.3f} {f_rom:9.5f} "
                f"{f_fem:9.5f} {err:6.2f}"
            )
    for name, s in summary.items():
        verdict = "met" if s["max_force_error"] <= TARGET else "missed"
        print(
            f"{name}: max force error {100 * s['max_force_error']:.2f} % (target "
            f"{100 * TARGET:.0f} %: {verdict}); max surface-field error "
            f"{100 * s['max_field_error']:.2f} % (relative L2 over the surface vertices)"
        )
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "rows": rows}, default=float))


if __name__ == "__main__":
    main()
