"""Can a global reduced basis answer a tool where it was not trained? The linear test that
comes before any hyper-reduction (issue 18).

    python bench/basis_span.py CAMPAIGN.toml CAMPAIGN_DIR [--held-out 6] [--modes 20,40,80,160]
        [--pressure-modes 10] [--global-bases campaign,bumps,both] [--local 1,1.5]
        [--local-directions nearest|xyz] [--out FILE.json]

At the held-out positions of a force-controlled campaign (every ``len/held-out``-th, as
``bench/ecsw_tradeoff.py``), the exact linear response to the stored tool load, u = K^-1 f
(K: the full order's stiffness at rest, the element pressure condensed exactly), against
the Galerkin model on a basis Phi: its compliance f^T u_r / f^T u (1: exact, < 1: too
stiff) and its field error (relative L2 over the nodes, the largest). Bases, from the
training positions only:

- ``campaign``: the POD of the campaign's nonlinear states (what a global POD of the
  trained samples gives);
- ``bumps``: the POD of the linear responses to the tool's smooth load, (1 - r^2/R^2)^2
  over radius R (the campaign's contact radius), lumped at the loadable surface's nodes,
  centred at each of them within 1.5 R of a training position, along that position's load
  direction: a dense, cheap family (one factorisation, a solve a node) that covers the
  trained part of the surface, gaps between positions included;
- ``both``: the two together.

- ``local R`` (``--local``, radii in mm): a basis a held-out position, the POD of the
  responses to bumps centred at the surface nodes within R of it, along the nearest
  training position's load direction or along x, y and z each (``--local-directions
  xyz``: any load direction; the held-out load itself is never read).

Reduced models: ``condensed`` (Phi^T K Phi: displacement only, the pressure condensed per
element before reduction), ``mixed`` (the pressure on ``--pressure-modes`` POD modes of the
basis' own pressures) and ``mixed+sup`` (with supremizers A^-1 Bt psi added to Phi).
Prints one row a basis, size and model. Serial. Units: mm, N, MPa.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py  # noqa: F401  (before dolfinx: see the README)
import numpy as np
import scipy.sparse.linalg

from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.reduce.ecsw_model import (
    group_nodes,
    mesh_elements,
    rest_operators,
    rest_tangents,
    supremizers,
)
from hapticrom.offline.reduce.ecsw_regions import pod


def held_out_split(positions: list[int], count: int) -> tuple[list[int], list[int]]:
    """(training, held-out): every ``len / count``-th position held out, from the middle of
    the first stride."""
    stride = max(len(positions) // max(count, 1), 1)
    held_out = positions[stride // 2 :: stride][:count]
    return [i for i in positions if i not in held_out], held_out


def bump_loads(
    surface, points, directions, radius: float, N: int, reach: float = 1.5
) -> np.ndarray:
    """(N, centres): unit smooth loads (1 - r^2/R^2)^2 lumped at the ``surface`` nodes
    (indices, coordinates), centred at each surface node within ``reach`` R of a trained
    position ``points`` (mm), along the nearest position's load ``directions``."""
    nodes, xyz = surface
    near = np.linalg.norm(xyz[:, None] - points[None], axis=2)  # (surface node, position)
    centres = np.flatnonzero(near.min(axis=1) <= reach * radius)
    direction = directions[near[centres].argmin(axis=1)]
    distance = np.linalg.norm(xyz[centres][:, None] - xyz[None], axis=2)  # (centre, node)
    weight = np.clip(1.0 - distance**2 / radius**2, 0.0, None) ** 2
    weight /= weight.sum(axis=1, keepdims=True)
    F = np.zeros((N, len(centres)))
    for i in range(3):
        F[3 * nodes + i] = (weight * direction[:, i][:, None]).T
    return F


def contact_points(store, positions) -> tuple[np.ndarray, np.ndarray]:
    """(points (mm), load directions) of the campaign's ``positions``, (count, 3) each."""
    attrs = [store.read_position(i)[1] for i in positions]
    points = np.array([a["point"] for a in attrs], dtype=float)
    return points, np.array([a["direction"] for a in attrs], dtype=float)


def training_bumps(config, store, training, N) -> np.ndarray:
    """The bump loads around the ``training`` positions on the campaign's loadable group."""
    surface = group_nodes(config.problem.mesh.file, config.load.surface)
    points, directions = contact_points(store, training)
    return bump_loads(surface, points, directions, config.load.contact_radius, N)


def reduced_compliances(Phi, Psi, operators, K, cases, free) -> dict:
    """Per model: (compliance ratios, relative L2 field errors) over the held-out cases."""
    models = {"condensed": (Phi, None)}
    if Psi is not None:
        models["mixed"] = (Phi, Psi)
        stable = np.linalg.qr(np.hstack([Phi, supremizers(operators, Psi, free)]))[0]
        models["mixed+sup"] = (stable, Psi)
    out = {}
    for name, (V, P) in models.items():
        if P is None:
            K_r = V.T @ (K @ V)
        else:
            B = V.T @ (operators.Bt @ P)
            C = P.T @ (operators.compliance[:, None] * P)
            K_r = V.T @ (operators.A @ V) + B @ np.linalg.solve(C, B.T)
        ratios, errors = [], []
        for f, u in cases:
            u_r = V @ np.linalg.solve(K_r, V.T @ f)
            ratios.append(float(f @ u_r / (f @ u)))
            errors.append(float(np.linalg.norm(u_r - u) / np.linalg.norm(u)))
        out[name] = (ratios, errors)
    return out


def local_bases(
    config, store, training, held_out, cases, reach, args, solve, operators, K, free
) -> list[dict]:
    """Per held-out position, the POD of the responses to bumps centred within ``reach``
    mm of it (along the nearest training position's load direction, or along x, y and z:
    the held-out load is not read): the compliance and field error of the condensed model
    at each size."""
    surface = group_nodes(config.problem.mesh.file, config.load.surface)
    points, directions = contact_points(store, training)
    held_out_points = contact_points(store, held_out)[0]
    radius = config.load.contact_radius
    ratios, errors, sizes, measured_at = {}, {}, [], {}
    for i, point, case in zip(held_out, held_out_points, cases, strict=True):
        nearest = directions[np.linalg.norm(points - point, axis=1).argmin()]
        along = np.eye(3) if args.local_directions == "xyz" else nearest[None]
        loads = np.hstack([bump_loads(surface, point[None], d[None], radius, K.shape[0],
                                      reach=reach / radius) for d in along])  # fmt: skip
        basis = pod(solve(loads))
        sizes.append(basis.shape[1])
        for n in (int(m) for m in args.modes.split(",")):
            if n <= basis.shape[1]:
                measured = reduced_compliances(basis[:, :n], None, operators, K, [case], free)
                measured_at.setdefault(n, []).append(i)  # fewer bumps than n: left out
                ratios.setdefault(n, []).extend(measured["condensed"][0])
                errors.setdefault(n, []).extend(measured["condensed"][1])
    out = []
    for n in ratios:
        name = f"local {reach:g}"
        out.append({"basis": name, "n": n, "model": "condensed", "compliance": ratios[n],
                    "field_error": errors[n], "positions": measured_at[n],
                    "bumps": sizes})  # fmt: skip
        print(f"{name:>9s} {n:4d} {'condensed':>10s} {min(ratios[n]):6.3f}..{max(ratios[n]):5.3f} "
              f"{max(errors[n]):12.3f}  ({len(ratios[n])} positions, {min(sizes)}-{max(sizes)} "
              "bumps)", flush=True)  # fmt: skip
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config")
    parser.add_argument("campaign")
    parser.add_argument("--held-out", type=int, default=6)
    parser.add_argument("--modes", default="20,40,80,160")
    parser.add_argument("--pressure-modes", type=int, default=10)
    parser.add_argument("--local", default="",
                        help="radii (mm): a basis a held-out position, of the responses to "
                        "bumps centred within that radius of it")  # fmt: skip
    parser.add_argument("--local-directions", choices=("nearest", "xyz"), default="nearest",
                        help="the local bumps along the nearest training position's load, "
                        "or along x, y and z each (any direction)")  # fmt: skip
    parser.add_argument("--global-bases", default="campaign,bumps,both",
                        help="the global bases measured ('' for none)")  # fmt: skip
    parser.add_argument("--out")
    args = parser.parse_args()
    t0 = time.perf_counter()
    config = CampaignConfig.from_toml(args.config)
    store = SnapshotStore(args.campaign)
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    operators = rest_operators(mesh, rest_tangents(mesh))
    K = operators.condensed()
    positions = store.completed()
    training, held_out = held_out_split(positions, args.held_out)
    data = {i: store.read_position(i)[0] for i in positions}
    states = np.hstack([data[i]["displacement"].T for i in training])
    free = np.flatnonzero(np.abs(states).max(axis=1) > 0)  # the supports' rows stay zero
    lu = scipy.sparse.linalg.splu(K[free][:, free].tocsc())

    def solve(F):
        out = np.zeros((K.shape[0],) + F.shape[1:])
        out[free] = lu.solve(F[free])
        return out

    cases = [(data[i]["load_vector"], solve(data[i]["load_vector"])) for i in held_out]
    loads = training_bumps(config, store, training, K.shape[0])
    responses = solve(loads)
    pressures = {  # the element-condensed pressure of each response, canonical cells
        "campaign": np.hstack([data[i]["pressure"].T for i in training]),
        "bumps": (operators.Bt.T @ responses) / operators.compliance[:, None],
    }
    pressures["both"] = np.hstack([pressures["campaign"], pressures["bumps"]])
    bases = {"campaign": pod(states), "bumps": pod(responses)}
    bases["both"] = pod(np.hstack([states, responses]))
    pressure_bases = {k: pod(v)[:, : args.pressure_modes] for k, v in pressures.items()}
    print(f"{len(free)} free rows, {len(training)} training / {len(held_out)} held-out "
          f"positions, {loads.shape[1]} bump responses; {time.perf_counter() - t0:.0f} s to "
          "set up")  # fmt: skip
    print(f"{'basis':>9s} {'n':>4s} {'model':>10s} {'compliance':>13s} {'field error':>12s}")
    results = []
    for name, basis in bases.items():
        if name not in args.global_bases.split(","):
            continue
        for n in (int(m) for m in args.modes.split(",")):
            if n > basis.shape[1]:
                continue
            measured = reduced_compliances(basis[:, :n], pressure_bases[name], operators, K,
                                           cases, free)  # fmt: skip
            for model, (ratios, errors) in measured.items():
                results.append({"basis": name, "n": n, "model": model, "compliance": ratios,
                                "field_error": errors})  # fmt: skip
                print(f"{name:>9s} {n:4d} {model:>10s} {min(ratios):6.3f}..{max(ratios):5.3f} "
                      f"{max(errors):12.3f}", flush=True)  # fmt: skip
    for reach in (float(r) for r in args.local.split(",") if r):
        results += local_bases(config, store, training, held_out, cases, reach, args, solve,
                               operators, K, free)  # fmt: skip
    if args.out:
        record = {"arguments": vars(args), "held_out": held_out, "results": results}
        Path(args.out).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
