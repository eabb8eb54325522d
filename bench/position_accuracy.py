"""Position in, force out, against the full order: the runtime's ``step_position`` along
``hapticrom play``'s scripted oblique path, and a full-order solve with the same rigid
sphere at the same tip position at instants of it (issue "device in, force out").

    mpirun -n 2 python bench/position_accuracy.py out/cornea-sphere.h5 \\
        examples/cornea-campaign-sphere.toml [--instants 8] [--penalties 1e3 1e4 1e5] \\
        [--json out/position_accuracy.json]

The model must be trained with the sphere (``[load] mode = "sphere"``): the full order
is then the training's own contact, a rigid frictionless sphere by a penalty
(:mod:`hapticrom.offline.fe.sphere`). At each instant the sphere starts touching the
surface where the runtime's proxy is and moves straight to the tip: frictionless and
hyperelastic, the equilibrium at the tip does not depend on the way there. Compared:
the normal force (along the runtime's contact normal) and the tangential remainder.
The penalty's convergence: the force at the deepest instant for each ``--penalties``
value (the error falls as the overlap, like penalty^(-1/2)).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import h5py  # noqa: F401 - before dolfinx (HDF5 of the wheels)
import numpy as np
from mpi4py import MPI

TICKS = 1000  # the scripted path, as play runs it in one second at 1 kHz


def runtime_path(model_path: str):
    """(tips (T, 3), forces (T, 3), proxies (T, 3), normals (T, 3), in contact (T,)) of the
    runtime along the scripted path."""
    import hapticrom.online as online
    from hapticrom.online.play import scripted_tips

    model = online.load(model_path)
    sim = model.simulator()
    tips = scripted_tips(model, TICKS)
    out = [np.zeros((TICKS, 3)) for _ in range(4)] + [np.zeros(TICKS, dtype=bool)]
    for i, tip in enumerate(tips):
        out[1][i] = sim.step_position(tip)
        out[2][i], out[3][i], out[4][i] = sim.proxy, sim.contact_normal, sim.in_contact
    out[0][:] = tips
    return tuple(out)


def pick_instants(contact: np.ndarray, count: int) -> np.ndarray:
    """``count`` ticks spread evenly over the ticks in contact (not the first and last,
    where the depth is near zero and a relative error means little)."""
    ticks = np.flatnonzero(contact)
    return ticks[np.round(np.linspace(0.08, 0.92, count) * (len(ticks) - 1)).astype(int)]


def full_order_force(config, organ, tip, proxy, penalty, comm) -> np.ndarray:
    """The force on the tool (N) of the full order with the sphere at ``tip``, moved there
    straight from touching the surface at the proxy."""
    from hapticrom.offline.config import LoadConfig
    from hapticrom.offline.fe.fullorder import FullOrderModel

    move = np.asarray(tip) - np.asarray(proxy)
    radius = config.load.contact_radius
    touch = np.asarray(proxy) + radius * move / np.linalg.norm(move)
    load = LoadConfig(mode="sphere", sphere=tuple(move), contact_point=tuple(touch),
                      contact_radius=radius, penalty=penalty, steps=config.load.steps,
                      surface=config.load.surface)  # fmt: skip
    fom = FullOrderModel(replace(config.problem, load=load), comm, organ=organ, verbose=False)
    try:
        result = fom.solve()
    finally:
        fom.close()
    return -result.force[-1]  # the tool feels the opposite of what it exerts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("campaign", help="the model's campaign TOML (mesh, material, sphere)")
    parser.add_argument("--instants", type=int, default=8)
    parser.add_argument("--penalties", type=float, nargs="*", default=[1e3, 1e4, 1e5])
    parser.add_argument("--json")
    args = parser.parse_args()
    from hapticrom.offline.campaign.config import CampaignConfig
    from hapticrom.offline.fe.organ import load_organ

    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)
    config = CampaignConfig.from_toml(args.campaign)
    if config.load.mode != "sphere":
        raise SystemExit(f"{args.campaign}: [load] mode is {config.load.mode!r}, not 'sphere'")
    tips, forces, proxies, normals, contact = runtime_path(args.model)
    organ = load_organ(config.problem.mesh.file, comm)
    rows = []
    say(f"{'tick':>5s} {'depth mm':>9s} {'Fn ROM N':>11s} {'Fn FOM N':>11s} {'error':>8s} "
        f"{'Ft ROM':>9s} {'Ft FOM':>9s}")  # fmt: skip
    for tick in pick_instants(contact, args.instants):
        fom = full_order_force(config, organ, tips[tick], proxies[tick], config.load.penalty, comm)
        n = normals[tick]
        rom_n, fom_n = forces[tick] @ n, fom @ n
        row = {
            "tick": int(tick),
            "tip_mm": tips[tick].tolist(),
            "depth_mm": float((proxies[tick] - tips[tick]) @ n),
            "rom_normal_n": float(rom_n),
            "fom_normal_n": float(fom_n),
            "normal_error": float(abs(rom_n - fom_n) / abs(fom_n)),
            "rom_tangential_n": float(np.linalg.norm(forces[tick] - rom_n * n)),
            "fom_tangential_n": float(np.linalg.norm(fom - fom_n * n)),
        }
        rows.append(row)
        say(f"{tick:5d} {row['depth_mm']:9.4f} {rom_n:11.5e} {fom_n:11.5e} "
            f"{100 * row['normal_error']:7.2f}% {row['rom_tangential_n']:9.2e} "
            f"{row['fom_tangential_n']:9.2e}")  # fmt: skip
    worst = max(r["normal_error"] for r in rows)
    say(f"normal force: max error {100 * worst:.2f} % over {len(rows)} instants (target 3 %)")
    deepest = max(rows, key=lambda r: r["depth_mm"])
    penalties = []
    for kappa in args.penalties:
        t = deepest["tick"]
        f = full_order_force(config, organ, tips[t], proxies[t], kappa, comm) @ normals[t]
        penalties.append({"penalty": kappa, "fom_normal_n": float(f)})
        say(f"penalty {kappa:8.0e} N/mm^4: Fn {f:.6e} N at tick {t}")
    if args.json and comm.rank == 0:
        summary = {"instants": rows, "max_normal_error": worst, "penalty_study": penalties}
        Path(args.json).write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
