"""ECSW on a trained campaign: tolerance -> sampled elements -> error -> time, at held-out
positions, beside the Galerkin model on every element (issue 18).

    python bench/ecsw_tradeoff.py CAMPAIGN.toml CAMPAIGN_DIR [--modes 20] [--pressure-modes 10]
        [--basis campaign|bumps|both|derivatives] [--linear-modes 20] [--derivatives-of 20]
        [--campaign-modes 0] [--supremizers] [--split linear|none] [--held-out 6] [--steps 2,5,10]
        [--tolerances 0.1,0.03,0.01,0.003] [--local MM [--local-neighbours 3]] [--out FILE.json]

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

``--local MM`` measures local bases instead (the Galerkin model only, no ECSW yet): for
each held-out position, ``--linear-modes`` of the responses to bumps centred within MM of
it along x, y and z, the derivatives of the leading ``--derivatives-of``,
``--campaign-modes`` of the states of the ``--local-neighbours`` nearest training
positions, supremizers if asked; one row a position with the distance of the full
order's last state from the basis' span (``span``: the best any model on it could do).

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

from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.store import SnapshotStore
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
            return derivative_bases(args, mesh, operators, solve, responses, U, P, free)
        pressures = (operators.Bt.T @ responses) / operators.compliance[:, None]
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


def derivative_bases(args, mesh, operators, solve, responses, U, P, free):
    """``--linear-modes`` of the responses, the POD of the modal derivatives of the
    leading ``--derivatives-of`` of them and ``--campaign-modes`` of the campaign's states,
    ``--modes`` in all (then supremizers if asked); the pressure modes of the condensed
    pressures of the first two and the campaign's."""
    linear = pod(responses)[:, : args.linear_modes]
    derivatives = modal_derivatives(mesh, linear[:, : args.derivatives_of], solve)
    count = args.modes - args.linear_modes - args.campaign_modes
    Phi = np.hstack([linear, pod(derivatives)[:, :count], pod(U)[:, : args.campaign_modes]])
    condensed = operators.Bt.T @ np.hstack([responses, derivatives]) / operators.compliance[:, None]
    pressures = np.hstack([condensed, P]) if args.campaign_modes else condensed
    Psi = pod(pressures)[:, : args.pressure_modes]
    if args.supremizers:
        Phi = np.hstack([Phi, supremizers(operators, Psi, free)])
    return np.linalg.qr(Phi)[0], Psi


def local_galerkin(store, training, held_out, args, mesh, rest, config) -> list[dict]:
    """Per held-out position, a basis of its own (``--local`` mm): the responses to bumps
    centred within that distance of it, along x, y and z (its load is not read), their
    modal derivatives, the states of the nearest training positions and supremizers as
    ``derivative_bases``; the Galerkin model on every element along its load path."""
    data = [store.read_position(i)[0] for i in training]
    U = np.vstack([d["displacement"] for d in data]).T
    P = np.vstack([d["pressure"] for d in data]).T
    # each position's columns of U and P: its stored states (a cut step stores more)
    start = np.cumsum([0] + [len(d["load_factor"]) for d in data])
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
        U_near = np.hstack([U[:, start[k] : start[k + 1]] for k in near])
        P_near = np.hstack([P[:, start[k] : start[k + 1]] for k in near])
        if U_near.shape[1] < args.campaign_modes:
            raise SystemExit(f"--campaign-modes {args.campaign_modes}: the {len(near)} nearest "
                             f"positions store only {U_near.shape[1]} states")  # fmt: skip
        t = time.perf_counter()
        Phi, Psi = derivative_bases(args, mesh, operators, solve, solve(loads), U_near, P_near,
                                    free)  # fmt: skip
        model = HyperReducedModel(mesh, Phi, Psi, split=args.split == "linear", rest=rest)
        built = time.perf_counter() - t
        solved = solve_paths(model, Phi, [path])
        ratios = solved["depth_ratios"][0]
        last = path[0][-1]  # the full order's last state: how far from the basis' span
        span = float(np.linalg.norm(last - Phi @ (Phi.T @ last)) / np.linalg.norm(last))
        results.append({"position": i, "bumps": loads.shape[1], "modes": Phi.shape[1],
                        "build_s": built, "span_error": span, **solved})  # fmt: skip
        ends = f"{ratios[0]:.3f}/{ratios[-1]:.3f}" if ratios else "-"
        print(f"position {i:3d}: {loads.shape[1]} bumps, {Phi.shape[1]} + {Psi.shape[1]} modes "
              f"({built:.0f} s), depth error {solved['depth_error']:.2e} (ratio first/last "
              f"{ends}), field {solved['field_error']:.2e} (span {span:.2e}), solved "
              f"{solved['converged']:.0%}", flush=True)  # fmt: skip
    return results


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
    parser.add_argument("--out")
    args = parser.parse_args()
    derived = args.modes - args.linear_modes - args.campaign_modes
    if args.basis == "derivatives" and (derived < 0 or args.derivatives_of > args.linear_modes):
        parser.error("--basis derivatives: --modes must be at least --linear-modes + "
                     "--campaign-modes, and --derivatives-of at most --linear-modes")  # fmt: skip
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
