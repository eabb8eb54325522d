"""ECSW on a trained campaign: tolerance -> sampled elements -> error -> time, at held-out
positions, beside the Galerkin model on every element (issue 18).

    python bench/ecsw_tradeoff.py CAMPAIGN.toml CAMPAIGN_DIR [--modes 20] [--pressure-modes 10]
        [--basis campaign|bumps|both|derivatives] [--linear-modes 20] [--derivatives-of 20]
        [--campaign-modes 0] [--supremizers] [--split linear|none] [--held-out 6] [--steps 2,5,10]
        [--tolerances 0.1,0.03,0.01,0.003] [--local MM [--local-neighbours 3]
        [--local-solves MM,MM --solves-per-distance 3 --state-modes 30]] [--out FILE.json]

1. Bases from the training positions (all but every ``len/held-out``-th): the leading
   ``--modes`` left singular vectors of their stored states (``--basis campaign``), of the
   linear responses to smooth tool loads centred at every node their loads touch
   (``bumps``, as ``bench/basis_span.py``), of both, or ``--linear-modes`` of those
   responses, the POD of their modal derivatives and ``--campaign-modes`` of the states,
   ``--modes`` in all (``derivatives``: corrections right to second order,
   ``offline/reduce/ecsw_model.modal_derivatives``),
   and ``--pressure-modes`` of the element pressures of the same; ``--supremizers``
   adds to the displacement basis A^-1 B^T psi for each pressure mode psi (A: the rest
   stiffness without its volumetric part, B: the divergence), the classical cure of a
   mixed reduced basis that is not inf-sup stable.
2. ECSW's training matrix (``offline/reduce/ecsw_model.training_matrix``) at the training
   states of ``--steps``, projected on the bases: each element's contribution to the
   reduced residual, all of it (``--split none``) or its part nonlinear in (u, p)
   (``linear``: the linear part is exact through small matrices).
3. At each tolerance: the sampled elements; at the held-out states, the error of the
   weighted sums against the full ones relative to the whole residual's rows (displacement
   rows u, pressure rows p); the reduced Newton along each held-out position's load path,
   its tool depth against the full order's (the largest relative error over the steps that
   converged), its field (relative L2 over the nodes at the last of them) and the share of
   the steps that converged ("solved"); the time of one residual and
   tangent (the online kernel, p50 and p99 of 300 calls). The first row is the Galerkin
   model on every element: the basis' own error, which no sampling can remove.

``--local MM`` measures local bases instead: for
each held-out position, ``--linear-modes`` of the responses to bumps centred within MM of
it along x, y and z, the derivatives of the leading ``--derivatives-of``,
``--campaign-modes`` of the states of the ``--local-neighbours`` nearest training
positions, ``--state-modes`` of the states of full-order solves at
``--solves-per-distance`` surface nodes about each ``--local-solves`` distance from it (the
campaign's load path there: nonlinear snapshots of the region itself), supremizers if
asked; per position the distance of the full order's last state from the basis' span
(``span``: the best any model on it could do) and one row for the Galerkin model, then,
with ``--local-solves``, one for ECSW at each ``--tolerances`` trained on those solves'
states.

Prints a table; ``--out`` writes it as JSON. Serial. Units: mm, N, MPa.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py  # noqa: F401  (before dolfinx: see the README)
import numpy as np
import scipy.sparse.linalg
from basis_span import (
    bump_loads,
    contact_points,
    held_out_split,
    pod,
    training_bumps,
)  # bench/, beside this script
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.positions import ToolPosition
from hapticrom.offline.campaign.run import solve_position
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.fe.organ import load_organ
from hapticrom.offline.reduce.ecsw import ecsw
from hapticrom.offline.reduce.ecsw_model import (
    HyperReducedModel,
    group_nodes,
    mesh_elements,
    modal_derivatives,
    rest_operators,
    rest_tangents,
    supremizers,
    training_matrix,
)


def bases(store, training, args, mesh, rest, config):
    """(Phi, Psi) from the training positions: the POD of the campaign's states, of the
    linear responses to smooth tool loads at every loaded node (``bench/basis_span.py``),
    of both, or the leading ``--linear-modes`` of those responses with the POD of their
    modal derivatives (``derivatives``); the pressure modes of the same (the condensed
    pressures of the linear responses and derivatives); supremizers if asked."""
    data = [store.read_position(i)[0] for i in training]
    U = np.vstack([d["displacement"] for d in data]).T
    P = np.vstack([d["pressure"] for d in data]).T
    free = np.flatnonzero(np.abs(U).max(axis=1) > 0)  # the supports' rows stay zero
    operators = rest_operators(mesh, rest)
    if args.basis != "campaign":
        solve = rest_solver(operators, free)
        responses = solve(training_bumps(config, store, training, operators.A.shape[0]))
        if args.basis == "derivatives":
            blocks = [(U, P, args.campaign_modes)]
            return derivative_bases(args, mesh, operators, solve, responses, blocks, free)
        pressures = condensed_pressures(operators, responses)
        if args.basis == "bumps":
            U, P = responses, pressures
        else:
            U, P = np.hstack([U, responses]), np.hstack([P, pressures])
    Phi = pod(U)[:, : args.modes]
    Psi = pod(P)[:, : args.pressure_modes]
    if args.supremizers:
        Phi = np.linalg.qr(np.hstack([Phi, supremizers(operators, Psi, free)]))[0]
    return Phi, Psi


def rest_solver(operators, free):
    """F -> K^-1 F on the ``free`` rows (zero elsewhere), K the condensed stiffness at rest:
    one factorisation."""
    K = operators.condensed()
    factor = scipy.sparse.linalg.splu(K[free][:, free].tocsc())

    def solve(F):
        out = np.zeros(F.shape)
        out[free] = factor.solve(F[free])
        return out

    return solve


def derivative_bases(args, mesh, operators, solve, responses, blocks, free):
    """``--linear-modes`` of the responses, the POD of the modal derivatives of the
    leading ``--derivatives-of`` of them (none if 0) and, for each of ``blocks`` (states
    (N, k), their pressures (cells, k), modes), that many POD modes of the states,
    ``--modes`` in all (then supremizers if asked); the pressure modes of the condensed
    pressures of the responses and derivatives and the pressures of the blocks used."""
    linear = pod(responses)[:, : args.linear_modes]
    parts, pressures = [linear], [condensed_pressures(operators, responses)]
    count = args.modes - args.linear_modes - sum(modes for _, _, modes in blocks)
    if args.derivatives_of and count:
        derivatives = modal_derivatives(mesh, linear[:, : args.derivatives_of], solve)
        parts.append(pod(derivatives)[:, :count])
        pressures.append(condensed_pressures(operators, derivatives))
    for U, P, modes in blocks:
        if modes:
            parts.append(pod(U)[:, :modes])
            pressures.append(P)
    Psi = pod(np.hstack(pressures))[:, : args.pressure_modes]
    if args.supremizers:
        parts.append(supremizers(operators, Psi, free))
    return np.linalg.qr(np.hstack(parts))[0], Psi


def condensed_pressures(operators, U) -> np.ndarray:
    """Each column's element pressures condensed linearly: p_e = (B^T u)_e / (V_e / kappa)."""
    return operators.Bt.T @ U / operators.compliance[:, None]


def local_galerkin(store, training, held_out, args, mesh, rest, config) -> list[dict]:
    """Per held-out position, a basis of its own (``--local`` mm): the responses to bumps
    centred within that distance of it, along x, y and z (its load is not read), their
    modal derivatives, the states of the nearest training positions, those of full-order
    solves around it (``--local-solves``) and supremizers as ``derivative_bases``; the
    Galerkin model on every element along its load path."""
    data = [store.read_position(i)[0] for i in training]
    U = np.vstack([d["displacement"] for d in data]).T
    free = np.flatnonzero(np.abs(U).max(axis=1) > 0)
    operators = rest_operators(mesh, rest)
    solve = rest_solver(operators, free)
    surface = group_nodes(config.problem.mesh.file, config.load.surface)
    radius, results = config.load.contact_radius, []
    points = contact_points(store, training)[0]
    held_out_points = contact_points(store, held_out)[0]
    paths = held_out_paths(store, held_out)
    for i, point, path in zip(held_out, held_out_points, paths, strict=True):
        loads = np.hstack([bump_loads(surface, point[None], d[None], radius, U.shape[0],
                                      reach=args.local / radius) for d in np.eye(3)])  # fmt: skip
        near = np.argsort(np.linalg.norm(points - point, axis=1))[: args.local_neighbours]
        blocks = [(*neighbour_states(data, near, args.campaign_modes), args.campaign_modes)]
        t = time.perf_counter()
        if args.local_solves:
            blocks.append((*nearby_solves(config, point, args), args.state_modes))
        solved_s = time.perf_counter() - t
        Phi, Psi = derivative_bases(args, mesh, operators, solve, solve(loads), blocks, free)
        built = time.perf_counter() - t - solved_s
        last = path[0][-1]  # the full order's last state: how far from the basis' span
        span = float(np.linalg.norm(last - Phi @ (Phi.T @ last)) / np.linalg.norm(last))
        head = {"position": i, "bumps": loads.shape[1], "modes": Phi.shape[1],
                "pressure_modes": Psi.shape[1], "solves_s": solved_s, "build_s": built,
                "span_error": span}  # fmt: skip
        print(f"position {i:3d}: {loads.shape[1]} bumps, {Phi.shape[1]} + {Psi.shape[1]} modes "
              f"(solves {solved_s:.0f} s, basis {built:.0f} s), span of the last state "
              f"{span:.2e}", flush=True)  # fmt: skip
        training_states = []  # ECSW's: the nearby solves' states, reduced
        if args.local_solves and args.tolerances:
            U_solved, P_solved, _ = blocks[-1]
            pairs = zip(U_solved.T, P_solved.T, strict=True)
            training_states = [(Phi.T @ u, Psi.T @ p) for u, p in pairs]
        for row in local_rows(mesh, Phi, Psi, path, training_states, args, rest):
            results.append({**head, **row})
    return results


def local_rows(mesh, Phi, Psi, path, states, args, rest):
    """The Galerkin model on every element, then ECSW at each of ``--tolerances`` trained on
    ``states`` (reduced (q, pi) pairs; none: the Galerkin model alone), along ``path``: one
    printed line and one dict each."""
    split = args.split == "linear"
    tolerances = ["galerkin"] + ([float(v) for v in args.tolerances.split(",")] if states else [])
    G = training_matrix(mesh, Phi, Psi, states, split=split, rest=rest)[0] if states else None
    for tolerance in tolerances:
        if tolerance == "galerkin":
            model = HyperReducedModel(mesh, Phi, Psi, split=split, rest=rest)
        else:
            sampling = ecsw(G, tolerance=tolerance)
            model = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights,
                                      split=split, rest=rest)  # fmt: skip
        solved = solve_paths(model, Phi, [path])
        p50, p99 = kernel_times(model, *states[-1]) if states else (None, None)
        ratios = solved["depth_ratios"][0]
        ends = f"{ratios[0]:.3f}/{ratios[-1]:.3f}" if ratios else "-"
        timing = f", residual and tangent p50/p99 {1e3 * p50:.2f}/{1e3 * p99:.2f} ms" if p50 else ""
        print(f"  {tolerance!s:>8s}: {model.sampled_elements:5d} elements, depth error "
              f"{solved['depth_error']:.2e} (ratio first/last {ends}), field "
              f"{solved['field_error']:.2e}, solved {solved['converged']:.0%}{timing}",
              flush=True)  # fmt: skip
        yield {"tolerance": tolerance, "elements": model.sampled_elements, **solved,
               "p50_s": p50, "p99_s": p99}  # fmt: skip


def neighbour_states(data, near, modes) -> tuple[np.ndarray, np.ndarray]:
    """The stored states and pressures of the training positions ``near`` (indices into
    ``data``, each position's own count: a cut step stores more)."""
    U = np.vstack([data[k]["displacement"] for k in near]).T
    if U.shape[1] < modes:
        raise SystemExit(f"--campaign-modes {modes}: the {len(near)} nearest positions store "
                         f"only {U.shape[1]} states")  # fmt: skip
    return U, np.vstack([data[k]["pressure"] for k in near]).T


def nearby_solves(config, point, args) -> tuple[np.ndarray, np.ndarray]:
    """The states and pressures (N, k), (cells, k) of full-order solves of the campaign's
    load path at ``--solves-per-distance`` loadable surface nodes about each of the
    ``--local-solves`` distances (mm) from ``point``, spread round it (each next node the
    farthest from those chosen): nonlinear snapshots of the region itself."""
    surface = read_surface(config.problem.mesh.file, config.load.surface)
    organ = load_organ(config.problem.mesh.file, MPI.COMM_SELF)
    distance = np.linalg.norm(surface.nodes - point, axis=1)
    states, pressures = [], []
    for d in (float(v) for v in args.local_solves.split(",")):
        ring = np.flatnonzero(np.abs(distance - d) <= 0.25 * d)
        if len(ring) < args.solves_per_distance:
            raise SystemExit(f"--local-solves {d:g}: {len(ring)} surface nodes within 25 % of "
                             f"that distance, {args.solves_per_distance} asked")  # fmt: skip
        chosen = [ring[np.argmin(np.abs(distance[ring] - d))]]
        while len(chosen) < args.solves_per_distance:
            xyz = surface.nodes[ring]
            gap = np.linalg.norm(xyz[:, None] - surface.nodes[chosen][None], axis=2).min(axis=1)
            chosen.append(ring[np.argmax(gap)])
        for node in chosen:
            position = ToolPosition(-1, tuple(surface.nodes[node]), tuple(surface.normals[node]),
                                    int(surface.node_tags[node]), "point")  # fmt: skip
            datasets, _ = solve_position(config, position, organ, MPI.COMM_SELF)
            states.append(datasets["displacement"])
            pressures.append(datasets["pressure"])
    return np.vstack(states).T, np.vstack(pressures).T


def held_out_paths(store, held_out):
    """Per held-out position: (displacements (steps, N), pressures, load vector, factors,
    depths along the path: the load-weighted mean displacement along the load, mm)."""
    paths = []
    for i in held_out:
        data, _ = store.read_position(i)
        f = data["load_vector"]
        force = np.linalg.norm(f.reshape(-1, 3).sum(axis=0))
        U = data["displacement"]
        paths.append((U, data["pressure"], f, data["load_factor"], U @ f / force, force))
    return paths


def solve_paths(model, Phi, paths) -> dict:
    """The reduced Newton along each held-out path: the worst depth error over the steps
    that converged, the field error at the last of them, the fraction of steps converged,
    and per position the reduced over the full order's depth at each converged step."""
    depth, field, iterations, converged, total, ratios = 0.0, 0.0, [], 0, 0, []
    for U, _, f, factors, depths, force in paths:
        Q, _, its = model.solve(Phi.T @ f, factors, tolerance=1e-8, partial=True)
        total += len(factors)
        converged += len(Q)
        if not len(Q):
            ratios.append([])
            continue
        u = Q @ Phi.T
        k = len(Q)
        ratios.append((u @ f / force / depths[:k]).tolist())
        depth = max(depth, float(np.abs(u @ f / force / depths[:k] - 1.0).max()))
        field = max(field, float(np.linalg.norm(u[-1] - U[k - 1]) / np.linalg.norm(U[k - 1])))
        iterations.append(float(np.mean(its)))
    newton = float(np.mean(iterations)) if iterations else None
    return {"depth_error": depth, "field_error": field, "newton": newton,
            "converged": converged / total, "depth_ratios": ratios}  # fmt: skip


def kernel_times(model, q, pi) -> tuple[float, float]:
    """(p50, p99) of one residual and tangent (s)."""
    times = []
    for _ in range(300):
        t = time.perf_counter()
        model.residual_tangent(q, pi, np.zeros(model.n))
        times.append(time.perf_counter() - t)
    return float(np.percentile(times, 50)), float(np.percentile(times, 99))


def row_errors(G, scale, w, totals, n) -> tuple[float, float]:
    """The weighted sums' error relative to the whole residual's rows, u and p apart."""
    width = len(scale)
    error = (G @ w - G.sum(axis=1)) / np.tile(scale, len(G) // width)
    error = error.reshape(-1, width)
    return tuple(
        float(np.linalg.norm(error[:, b]) / np.linalg.norm(totals[:, b]))
        for b in (slice(0, n), slice(n, width))
    )


def whole_rows(model, states) -> np.ndarray:
    """The reduced residual's rows without load or the exact p / kappa part, per state."""
    out = []
    for q, pi in states:
        r, _ = model.residual_tangent(q, pi, np.zeros(model.n))
        r[model.n :] += model.M @ pi
        out.append(r)
    return np.array(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config")
    parser.add_argument("campaign")
    parser.add_argument("--modes", type=int, default=20)
    parser.add_argument("--pressure-modes", type=int, default=10)
    parser.add_argument("--basis", choices=("campaign", "bumps", "both", "derivatives"),
                        default="campaign")  # fmt: skip
    parser.add_argument("--linear-modes", type=int, default=20,
                        help="derivatives: the linear modes, derivatives added")  # fmt: skip
    parser.add_argument("--derivatives-of", type=int, default=20,
                        help="derivatives: of the leading linear modes")  # fmt: skip
    parser.add_argument("--campaign-modes", type=int, default=0,
                        help="derivatives: campaign POD modes added")  # fmt: skip
    parser.add_argument("--supremizers", action="store_true")
    parser.add_argument("--split", choices=("none", "linear"), default="linear")
    parser.add_argument("--held-out", type=int, default=6)
    parser.add_argument("--tolerances", default="0.1,0.03,0.01,0.003")
    parser.add_argument("--steps", default="2,5,10")
    parser.add_argument("--local", type=float, default=0.0,
                        help="mm: a derivatives basis a held-out position from bumps this "
                        "close to it (the Galerkin model only)")  # fmt: skip
    parser.add_argument("--local-neighbours", type=int, default=3,
                        help="--local: the campaign modes from the states of this many "
                        "nearest training positions")  # fmt: skip
    parser.add_argument("--local-solves", default="",
                        help="--local: mm, full-order solves about these distances from "
                        "each held-out position, their states' POD in its basis")  # fmt: skip
    parser.add_argument("--solves-per-distance", type=int, default=3)
    parser.add_argument("--state-modes", type=int, default=0,
                        help="--local-solves: POD modes of their states")  # fmt: skip
    parser.add_argument("--out")
    args = parser.parse_args()
    derived = args.modes - args.linear_modes - args.campaign_modes - args.state_modes
    uses_derivatives = args.basis == "derivatives" or args.local
    if uses_derivatives and (derived < 0 or args.derivatives_of > args.linear_modes):
        parser.error("--basis derivatives and --local: --modes must be at least "
                     "--linear-modes + --campaign-modes + --state-modes, and --derivatives-of "
                     "at most --linear-modes")  # fmt: skip
    if args.local_solves and not (args.local and args.state_modes > 0):
        parser.error("--local-solves needs --local and --state-modes")
    t0 = time.perf_counter()
    config = CampaignConfig.from_toml(args.config)
    store = SnapshotStore(args.campaign)
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    rest = rest_tangents(mesh)
    positions = store.completed()
    training, held_out = held_out_split(positions, args.held_out)
    if args.local:
        results = local_galerkin(store, training, held_out, args, mesh, rest, config)
        if args.out:
            record = {"arguments": vars(args), "held_out": held_out, "results": results}
            Path(args.out).write_text(json.dumps(record, indent=1))
        return
    Phi, Psi = bases(store, training, args, mesh, rest, config)
    n, split = Phi.shape[1], args.split == "linear"
    steps = [int(s) - 1 for s in args.steps.split(",")]

    def states(indices):
        out = []
        for i in indices:
            data, _ = store.read_position(i)
            for k in steps:
                out.append((Phi.T @ data["displacement"][k], Psi.T @ data["pressure"][k]))
        return out

    G, scale = training_matrix(mesh, Phi, Psi, states(training), split=split, rest=rest)
    H, held_scale = training_matrix(mesh, Phi, Psi, states(held_out), split=split, rest=rest)
    galerkin = HyperReducedModel(mesh, Phi, Psi, split=split, rest=rest)
    totals = whole_rows(galerkin, states(held_out))
    paths = held_out_paths(store, held_out)
    q_last, pi_last = states(held_out[:1])[-1]
    print(f"{len(mesh.X)} elements, {len(training)} training / {len(held_out)} held-out "
          f"positions, {args.basis} basis, {n} + {Psi.shape[1]} modes (supremizers: "
          f"{args.supremizers}), G "
          f"{G.shape[0]} x {G.shape[1]}, split: {args.split}; {time.perf_counter() - t0:.0f} s "
          "to set up")  # fmt: skip
    columns = ("tolerance", "elements", "rows u", "rows p", "depth", "field", "newton", "solved",
               "p50 ms", "p99 ms")  # fmt: skip
    widths = (9, 8, 8, 8, 8, 8, 6, 6, 7, 7)  # the rows' below
    print(" ".join(f"{c:>{w}s}" for c, w in zip(columns, widths, strict=True)))
    results = []
    for tolerance in ["galerkin"] + [float(t) for t in args.tolerances.split(",")]:
        if tolerance == "galerkin":
            model, count, errors = galerkin, len(mesh.X), (0.0, 0.0)
        else:
            sampling = ecsw(G, tolerance=tolerance)
            w = np.zeros(G.shape[1])
            w[sampling.elements] = sampling.weights
            errors = row_errors(H, held_scale, w, totals, n)
            model = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights,
                                      split=split, rest=rest)  # fmt: skip
            count = len(sampling.elements)
        solved = solve_paths(model, Phi, paths)
        p50, p99 = kernel_times(model, q_last, pi_last)
        results.append({"tolerance": tolerance, "elements": count, "rows_u": errors[0],
                        "rows_p": errors[1], **solved, "p50_s": p50, "p99_s": p99})  # fmt: skip
        label = tolerance if isinstance(tolerance, str) else f"{tolerance:g}"
        newton = "-" if solved["newton"] is None else f"{solved['newton']:.1f}"
        print(f"{label:>9s} {count:8d} {errors[0]:8.2e} {errors[1]:8.2e} "
              f"{solved['depth_error']:8.2e} {solved['field_error']:8.2e} {newton:>6s} "
              f"{solved['converged']:6.0%} "
              f"{1e3 * p50:7.2f} {1e3 * p99:7.2f}", flush=True)  # fmt: skip
        ends = [f"{r[0]:.2f}/{r[-1]:.2f}" if r else "-" for r in solved["depth_ratios"]]
        print(f"{'':9s} depth ratio, first/last step per position: {' '.join(ends)}")
    if args.out:
        record = {"arguments": vars(args), "held_out": held_out, "results": results}
        Path(args.out).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
