"""ECSW on a trained campaign: tolerance -> sampled elements -> error -> time, at held-out
positions, beside the Galerkin model on every element (issue 18).

    python bench/ecsw_tradeoff.py CAMPAIGN.toml CAMPAIGN_DIR [--modes 20] [--pressure-modes 10]
        [--basis campaign|bumps|both|derivatives] [--linear-modes 20] [--derivatives-of 20]
        [--campaign-modes 0] [--supremizers] [--split linear|none] [--held-out 6] [--steps 2,5,10]
        [--tolerances 0.1,0.03,0.01,0.003] [--local MM [--local-neighbours 3]
        [--local-solves MM,MM --solves-per-distance 3 --state-modes 30]
        [--frames 100 [--frame-solver haptic|modified] [--frame-iterations 1]
        [--tangent-slices 10] [--refresh-after 3] [--frame-tolerance 1e-6]]
        [--second-tool MM [--second-force 0.5] [--second-basis single|paired|both]
        | --pinch N | --oblique FRACTION | --held-tool MM]] [--out FILE.json]

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
states. With ``--frames``, each row's model also runs the held-out path as that many
physics steps of a haptic loop (``haptic_frames``: the time of a step, how far its state
lags the equilibrium).

Load cases beside the campaign's (each held-out position's reference a full-order solve
under it, and the nearby solves under the same kind of load): ``--second-tool`` (a second
tool that far away), ``--pinch`` (nine forces at neighbouring nodes, thesis §3.4.3),
``--oblique`` (a tangential force beside the tool's; the snapshots' in other directions),
``--held-tool`` (a tool that far away holds its patch in place while the position's
presses: grasping forceps beside a probe; the snapshots pair a press about the position
with a holder about the holder's node, and each reduced model holds the held-out holder's
patch by a penalty, ``hold``).

Prints a table; ``--out`` writes it as JSON. Serial. Units: mm, N, MPa.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import h5py  # noqa: F401  (before dolfinx: see the README)
import numpy as np
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
from hapticrom.offline.reduce.ecsw_indicator import error_indicator
from hapticrom.offline.reduce.ecsw_model import (
    HyperReducedModel,
    ModifiedNewton,
    group_nodes,
    mesh_elements,
    modal_derivatives,
    rest_operators,
    rest_solver,
    rest_tangents,
    supremizers,
    training_matrix,
)
from hapticrom.offline.reduce.ecsw_physics import HOLD_STIFFNESS, linear_stiffness
from hapticrom.offline.reduce.ecsw_regions import RegionSolves, region_model
from hapticrom.online.haptic_newton import HapticNewton
from hapticrom.online.physics import rotation_rows


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


def derivative_bases(args, mesh, operators, solve, responses, blocks, free, extra=None):
    """``--linear-modes`` of the responses, the POD of the modal derivatives of the
    leading ``--derivatives-of`` of them (none if 0) and, for each of ``blocks`` (states
    (N, k), their pressures (cells, k), modes), that many POD modes of the states,
    ``--modes`` in all (then supremizers if asked); the pressure modes of the condensed
    pressures of the responses (if any linear mode is used) and derivatives (if computed,
    used or not) and the pressures of the blocks used."""
    linear = pod(responses)[:, : args.linear_modes] if args.linear_modes else None
    parts = [linear] if args.linear_modes else []
    pressures = [condensed_pressures(operators, responses)] if args.linear_modes else []
    count = args.modes - args.linear_modes - sum(modes for _, _, modes in blocks)
    if args.derivatives_of:
        derivatives = modal_derivatives(mesh, linear[:, : args.derivatives_of], solve)
        if count:
            parts.append(pod(derivatives)[:, :count])
        pressures.append(condensed_pressures(operators, derivatives))
    for U, P, modes in blocks:
        if modes:
            parts.append(pod(U)[:, :modes])
            pressures.append(P)
    if extra is not None:  # further displacement modes kept whole (--held-tool's)
        parts.append(extra)
        pressures.append(condensed_pressures(operators, extra))
    Psi = pod(np.hstack(pressures))[:, : args.pressure_modes]
    if args.supremizers:
        parts.append(supremizers(operators, Psi, free))
    return np.linalg.qr(np.hstack(parts))[0], Psi


def condensed_pressures(operators, U) -> np.ndarray:
    """Each column's element pressures condensed linearly: p_e = (B^T u)_e / (V_e / kappa)."""
    return operators.Bt.T @ U / operators.compliance[:, None]


def local_models(store, training, held_out, args, mesh, rest, config) -> list[dict]:
    """Per held-out position, a basis of its own (``--local`` mm): the responses to bumps
    centred within that distance of it, along x, y and z (its load is not read), their
    modal derivatives, the states of the nearest training positions, those of full-order
    solves around it (``--local-solves``) and supremizers as ``derivative_bases``; along its
    load path the Galerkin model on every element, then ECSW trained on the solves' states
    (``local_rows``)."""
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
    solver = NearbySolver(config, args) if args.local_solves else None
    for i, point, path in zip(held_out, held_out_points, paths, strict=True):
        loads = np.zeros((U.shape[0], 0))  # the bumps: only if linear modes are used
        if args.linear_modes:
            reach = args.local / radius
            loads = np.hstack([bump_loads(surface, point[None], d[None], radius, U.shape[0],
                                          reach=reach) for d in np.eye(3)])  # fmt: skip
        near = np.argsort(np.linalg.norm(points - point, axis=1))[: args.local_neighbours]
        blocks = [(*neighbour_states(data, near, args.campaign_modes), args.campaign_modes)]
        path, centres, forbidden, head = held_out_case(solver, point, path, args)
        held_nodes = head.pop("held_nodes", None)  # --held-tool: the holder's patch
        head = {"position": i, **head}
        t = time.perf_counter()
        blocks += nearby_blocks(solver, centres, forbidden, args) if solver else []
        for U_solved, _, modes in blocks[1:]:
            if U_solved.shape[1] < modes:
                raise SystemExit(f"--state-modes {modes}: the solves about position {i} "
                                 f"converged {U_solved.shape[1]} states")  # fmt: skip
        solved_s = time.perf_counter() - t
        holder = None  # --held-tool: the responses to a force (and couple) at the holder
        if held_nodes is not None:
            forces = [bump_loads(surface, centres[1][None], d[None], radius, U.shape[0],
                                 reach=1e-9) for d in np.eye(3)]  # fmt: skip
            if args.hold == "rigid":
                forces.append(couple_loads(node_coordinates(mesh), held_nodes, U.shape[0]))
            if args.hold == "nodes":  # a unit force at each held node, along x, y and z
                forces = [node_loads(held_nodes, U.shape[0])]
            holder = solve(np.hstack(forces))
        Phi, Psi = derivative_bases(args, mesh, operators, solve, solve(loads), blocks, free,
                                    holder)  # fmt: skip
        built = time.perf_counter() - t - solved_s
        last = path[0][-1]  # the full order's last state: how far from the basis' span
        span = float(np.linalg.norm(last - Phi @ (Phi.T @ last)) / np.linalg.norm(last))
        head |= {"bumps": loads.shape[1], "modes": Phi.shape[1], "pressure_modes": Psi.shape[1],
                 "solves_s": solved_s, "build_s": built, "span_error": span}  # fmt: skip
        print(f"position {i:3d}: {loads.shape[1]} bumps, {Phi.shape[1]} + {Psi.shape[1]} modes "
              f"(solves {solved_s:.0f} s, basis {built:.0f} s), span of the last state "
              f"{span:.2e}", flush=True)  # fmt: skip
        training_states = []  # ECSW's: the nearby solves' states, reduced
        if solver and args.tolerances:
            for U_solved, P_solved, _ in blocks[1:]:
                pairs = zip(U_solved.T, P_solved.T, strict=True)
                training_states += [(Phi.T @ u, Psi.T @ p) for u, p in pairs]
        tails = [pod(U)[:, m : m + args.indicator_modes] for U, _, m in blocks if m]
        enrichment = np.hstack(tails) if args.indicator_modes and tails else None
        for row in local_rows(mesh, Phi, Psi, path, training_states, args, rest, enrichment,
                              held_nodes):  # fmt: skip
            results.append({**head, **row})
    return results


def held_out_case(solver, point, path, args) -> tuple:
    """(path, centres, forbidden nodes, record) of a held-out position's load case: its
    stored path (the campaign's tool alone); with ``--second-tool`` the full order under both
    tools at once (the basis: about both); with ``--pinch`` or ``--oblique`` under that load
    at its node (``NearbySolver.case_tools``). The forbidden nodes are the held-out tools'
    own: no snapshot is centred there."""
    if not (args.second_tool or args.pinch or args.oblique or args.held_tool):
        return path, [point], [], {}
    node = solver.nearest(point)
    if args.held_tool:
        holder = solver.second_tool(point, args.held_tool, 1.0)[0]
        centres = [point, solver.surface.nodes[holder]]
        path, held_nodes = solver.held_path(holder, node)
        print(f"  a holder at {np.round(centres[1], 3).tolist()} mm, "
              f"{np.linalg.norm(centres[1] - point):.2f} mm away, its patch "
              f"{len(held_nodes)} nodes", flush=True)  # fmt: skip
        return path, centres, [node, holder], {"holder": centres[1].tolist(),
                                               "held_nodes": held_nodes}  # fmt: skip
    if args.second_tool:
        second_node, second = solver.second_tool(point, args.second_tool, args.second_force)
        centres = [point, solver.surface.nodes[second_node]]
        forbidden, tools = [node, second_node], [second]
        print(f"  a second tool at {np.round(second[0], 3).tolist()} mm, "
              f"{np.linalg.norm(centres[1] - point):.2f} mm away, force "
              f"{np.round(second[1], 4).tolist()} N", flush=True)  # fmt: skip
    else:
        centres, forbidden, tools = [point], [node], solver.case_tools(node, args)
        total = solver.tool(node, 1.0)[1] + np.sum([f for _, f in tools], axis=0)
        print(f"  {'pinch' if args.pinch else 'oblique press'}: {len(tools) + 1} forces, total "
              f"{np.round(total, 4).tolist()} N", flush=True)  # fmt: skip
    head = {"tools": [[*p, *f] for p, f in tools]}
    return solver.path(node, tools), centres, forbidden, head


def nearby_blocks(solver, centres, forbidden, args) -> list[tuple]:
    """The full-order snapshots about the held-out tools (``centres``: one, or two with
    ``--second-tool``), a (states, pressures, modes kept) block each: ``--second-basis
    single``: the single-tool solves about each centre; ``paired``: one block of two-tool
    solves, the first tool at a node about the first centre and the second at a node about
    the second (the k-th of each, ``--second-force`` of the campaign's force along its
    normal); ``both``: all three. With ``--pinch`` or ``--oblique``: one block of that load
    at each nearby node (the k-th oblique press along its own direction)."""
    if args.held_tool and args.held_basis == "free":  # presses alone about the first centre
        return [(*solver.states(centres[0], forbidden), args.state_modes)]
    if args.held_tool:  # the k-th press about the first centre, held about the second
        presses = solver.nodes(centres[0], forbidden)
        holders = solver.nodes(centres[1], [*forbidden, *presses])
        solved = [solver.solve(b, tools=[solver.tool(a, 1.0)], config=solver.held)
                  for a, b in zip(presses, holders, strict=True)]  # fmt: skip
        return [stacked(solved, args.state_modes)]
    if args.pinch or args.oblique:  # the held-out load's kind at each nearby node
        nodes = solver.nodes(centres[0], forbidden)
        return [stacked([solver.solve(n, solver.case_tools(n, args, k))
                         for k, n in enumerate(nodes)], args.state_modes)]  # fmt: skip
    basis = args.second_basis if len(centres) == 2 else "single"
    single = [(*solver.states(c, forbidden), args.state_modes) for c in centres
              if basis != "paired"]  # fmt: skip
    if basis == "single":
        return single
    first = solver.nodes(centres[0], forbidden)  # never both tools on one node
    pairs = zip(first, solver.nodes(centres[1], [*forbidden, *first]), strict=True)
    solved = [solver.solve(a, tools=[solver.tool(b, args.second_force)]) for a, b in pairs]
    return single + [stacked(solved, args.state_modes)]


def stacked(solved, modes) -> tuple:
    """A block of solves: (states (N, k), pressures (cells, k), modes kept)."""
    return (np.vstack([d["displacement"] for d in solved]).T,
            np.vstack([d["pressure"] for d in solved]).T, modes)  # fmt: skip


def local_rows(mesh, Phi, Psi, path, states, args, rest, enrichment=None, held_nodes=None):
    """The Galerkin model on every element, then ECSW at each of ``--tolerances`` trained on
    ``states`` (reduced (q, pi) pairs; none: the Galerkin model alone), along ``path``: one
    printed line and one dict each; with ``enrichment`` (N, k) the error indicator of each
    (``indicator_row``); with ``held_nodes`` each model holds them (``hold``)."""
    split = args.split == "linear"
    tolerances = ["galerkin"] + (args.tolerances if states else [])
    G = training_matrix(mesh, Phi, Psi, states, split=split, rest=rest)[0] if states else None
    galerkin_states = None  # the Galerkin model's along the path (--check-tolerance)
    for tolerance in tolerances:
        if tolerance == "galerkin":
            model = HyperReducedModel(mesh, Phi, Psi, split=split, rest=rest)
            if args.check_tolerance:
                galerkin_states = model.solve(Phi.T @ path[2], path[3], 1e-10, partial=True)[0]
        else:
            sampling = ecsw(G, tolerance=tolerance)
            model = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights,
                                      split=split, rest=rest)  # fmt: skip
        if held_nodes is not None:
            hold(model, Phi, held_nodes, args.hold, node_coordinates(mesh))
        solved = solve_paths(model, Phi, [path])
        p50, p99 = kernel_times(model, *states[-1]) if states else (None, None)
        ratios = solved["depth_ratios"][0]
        ends = f"{ratios[0]:.3f}/{ratios[-1]:.3f}" if ratios else "-"
        timing = f", residual and tangent p50/p99 {1e3 * p50:.2f}/{1e3 * p99:.2f} ms" if p50 else ""
        print(f"  {tolerance!s:>8s}: {model.sampled_elements:5d} elements, depth error "
              f"{solved['depth_error']:.2e} (ratio first/last {ends}), field "
              f"{solved['field_error']:.2e}, solved {solved['converged']:.0%}{timing}",
              flush=True)  # fmt: skip
        row = {"tolerance": tolerance, "elements": model.sampled_elements, **solved,
               "p50_s": p50, "p99_s": p99}  # fmt: skip
        if args.frames:
            row["frames"] = haptic_frames(model, Phi, path, args)
        if args.check_tolerance and tolerance != "galerkin" and held_nodes is None:
            check = region_model(mesh, rest, Phi, Psi, G, args.check_tolerance)
            row["check"] = check_row(model, check, Phi, path, galerkin_states)
        if enrichment is not None:
            bases = (Phi, Psi, enrichment)
            sampled = None if tolerance == "galerkin" else states
            row["indicator"] = indicator_row(model, bases, sampled, path, args, mesh, rest)
        yield row


def hold(model, Phi, nodes, kind, coordinates) -> None:
    """A holder that keeps the mean displacement of ``nodes`` (canonical: its patch) in
    place, in the reduced space: the energy k/2 |A q|^2, a constant k A^T A in the model's
    constant tangent (so in its residual, its Newton's and HapticNewton's), A (3, n) the
    patch's mean rows, k ``HOLD_STIFFNESS`` times the model's linear stiffness against a
    force spread over the patch (the runtime's ``hold_stiffness`` takes the stiffest of
    its region's tools instead, offline/reduce/ecsw_physics.py: the same scale). With the
    nodes' reference ``coordinates`` (``--hold rigid``) A also holds the patch's
    least-squares rotation (``rotation_rows``, 3 more rows); ``--hold nodes``: A is every
    held node's rows (3 a node), the basis carrying the response to a unit force at each
    (their reactions, exactly at the linear step). The patch's rigid motion, not
    each node: a basis holds no states with the patch exactly still (its solves hold
    patches about it): a penalty on each held row (without the responses below) left the
    depth 79.5 % short at position 6 (README, stop 42). The basis carries the responses to
    a force (and couple) at the holder for its reaction. (Until stop 43 k was 1e4 of the
    largest diagonal entry of the q-q matrix: only about 20 times the patch's own stiffness
    on the test cornea; on the demo's held case both give the same errors, README.)
    """
    nodes = np.asarray(nodes)
    rows = Phi.reshape(-1, 3, Phi.shape[1])[nodes]  # (patch, 3, n)
    A = rows.reshape(-1, Phi.shape[1]) if kind == "nodes" else rows.mean(axis=0)
    k = HOLD_STIFFNESS * float(linear_stiffness(model, A).max())
    if kind == "rigid":
        A = np.vstack([A, rotation_rows(coordinates[nodes], rows)])
    model.linear[: model.n, : model.n] += k * (A.T @ A)


def node_loads(nodes, N) -> np.ndarray:
    """(N, 3 len(nodes)): a unit force at each of ``nodes`` (canonical) along x, y, z."""
    F = np.zeros((N, 3 * len(nodes)))
    F[3 * np.repeat(nodes, 3) + np.tile(np.arange(3), len(nodes)), np.arange(F.shape[1])] = 1.0
    return F


def couple_loads(coordinates, nodes, N) -> np.ndarray:
    """(N, 3): couples about x, y and z on the patch ``nodes`` (canonical; their reference
    ``coordinates``): f_i = e x r_i / sum |r_i|^2 about the patch's centroid (zero net
    force; their moment J e / sum |r_i|^2, unit on a round patch: they only feed the
    basis)."""
    r = coordinates[nodes] - coordinates[nodes].mean(axis=0)
    F = np.zeros((N, 3))
    for axis, e in enumerate(np.eye(3)):
        F.reshape(-1, 3, 3)[nodes, :, axis] = np.cross(e, r) / (r**2).sum()
    return F


def node_coordinates(mesh) -> np.ndarray:
    """(nodes, 3): each canonical node's reference position (mm), from the elements'."""
    X = np.zeros((int(mesh.rows.max()) // 3 + 1, 3))
    X[mesh.rows[:, 0::3] // 3] = mesh.X
    return X


def indicator_row(model, bases, states, path, args, mesh, rest) -> dict:
    """The error indicator of ``model`` (``states`` None: the Galerkin model's, on every
    element; else on a second sample trained at ``states``, ``--indicator-tolerance``,
    apart from the model's with ``--indicator-apart``) against the true error along the
    held-out ``path``: at each step the model's Newton converged, eta and the error
    ||Phi q - u|| / ||Phi q|| (u the full order's; eta's norm), their ratio (the
    effectivity); the time of one estimate (p50, p99). ``bases``: the model's Phi and Psi
    and the enrichment."""
    Phi, Psi, enrichment = bases
    galerkin = states is None
    apart = model.elements if args.indicator_apart else ()
    options = {} if galerkin else {"tolerance": args.indicator_tolerance, "exclude": apart}
    indicator = error_indicator(mesh, Phi, Psi, enrichment, states,
                                split=args.split == "linear", rest=rest, **options)  # fmt: skip
    if indicator.enriched.n == Phi.shape[1]:
        raise SystemExit("--indicator-modes: the blocks' further modes add nothing to the basis")
    U, _, f, factors, _, _ = path
    Q, Pi, _ = model.solve(Phi.T @ f, factors, tolerance=1e-10, partial=True)
    load = indicator.basis.T @ f
    eta = [indicator.estimate(q, pi, c * load) for q, pi, c in zip(Q, Pi, factors, strict=False)]
    pairs = zip(Q, U, strict=False)  # U: every step; Q: those that converged
    error = [float(np.linalg.norm(Phi @ q - u) / np.linalg.norm(q)) for q, u in pairs]
    times = []
    for _ in range((10 if galerkin else 300) if len(Q) else 0):
        t = time.perf_counter()
        indicator.estimate(Q[-1], Pi[-1], factors[len(Q) - 1] * load)
        times.append(time.perf_counter() - t)
    ratio = [e / t for e, t in zip(eta, error, strict=True) if t > 0]
    out = {"eta": eta, "error": error, "enriched_modes": indicator.enriched.n,
           "elements": indicator.enriched.sampled_elements, "fit": indicator.fit,
           "effectivity": [min(ratio), max(ratio)] if ratio else None,
           **{f"{k}_s": float(np.percentile(times, v)) if times else None
              for k, v in (("p50", 50), ("p99", 99))}}  # fmt: skip
    if ratio:
        print(f"    indicator ({out['enriched_modes']} modes, {out['elements']} elements, fit "
              f"{indicator.fit:.1e}): at the last step eta {eta[-1]:.2e}, error "
              f"{error[-1]:.2e}; effectivity {min(ratio):.2f}-{max(ratio):.2f} over "
              f"{len(ratio)} steps; estimate p50/p99 {1e3 * out['p50_s']:.2f}/"
              f"{1e3 * out['p99_s']:.2f} ms", flush=True)  # fmt: skip
    return out


def check_row(model, check, Phi, path, galerkin) -> dict:
    """The runtime's error indicator (``online/sampling_check.py``) of ``model`` with the
    ``check`` model's sample along the held-out ``path``: at each step the model converged,
    eta = |(T^-1 d)_q| / |q|, d the two models' residual difference at the state and T the
    model's tangent there (the runtime's; and, to compare, the check model's), against
    the sampling's error (the ``galerkin`` states': |q - q_G| / |q|) and the true one
    (|Phi q - u| / |Phi q|, u the full order's)."""
    U, _, f, factors, _, _ = path
    load = Phi.T @ f
    Q, Pi, _ = model.solve(load, factors, tolerance=1e-10, partial=True)
    rows = {"eta": [], "eta_check_tangent": [], "sampling_error": [], "error": []}
    for k, (q, pi) in enumerate(zip(Q, Pi, strict=True)):
        r, T = model.residual_tangent(q, pi, factors[k] * load)
        r_check, T_check = check.residual_tangent(q, pi, factors[k] * load)
        for name, tangent in (("eta", T), ("eta_check_tangent", T_check)):
            delta = np.linalg.solve(tangent, r_check - r)[: model.n]
            rows[name].append(float(np.linalg.norm(delta) / np.linalg.norm(q)))
        if k < len(galerkin):
            gap = np.linalg.norm(q - galerkin[k])
            rows["sampling_error"].append(float(gap / np.linalg.norm(q)))
        rows["error"].append(float(np.linalg.norm(Phi @ q - U[k]) / np.linalg.norm(q)))
    out = {"elements": check.sampled_elements, **rows}
    if len(Q):
        last = {name: values[-1] for name, values in rows.items() if values}
        print(f"    check sample ({check.sampled_elements} elements): at the last step eta "
              f"{last['eta']:.2e} (with the check's tangent {last['eta_check_tangent']:.2e}), "
              f"sampling error {last.get('sampling_error', np.nan):.2e}, true error "
              f"{last['error']:.2e}", flush=True)  # fmt: skip
    return out


def haptic_frames(model, Phi, path, args) -> dict:
    """The held-out load path as ``--frames`` physics steps of a haptic loop (the load
    ramped to its last factor in equal increments, each step from the last: a press of that
    many ms at 1 kHz), then held until the state is within 1e-6 of the model's equilibrium
    (at most 100 steps). ``--frame-solver haptic``: :class:`HapticNewton`, a fixed cost a
    step (``--frame-iterations``, ``--tangent-slices``), the state lagging; ``modified``:
    :class:`ModifiedNewton`, each step converged (``--frame-tolerance``,
    ``--refresh-after``). The time of a step (p50, p99, max), the evaluations, and at the
    ramp's last step the lag behind the equilibrium and the depth and field errors against
    the full order's last state."""
    U, _, f, factors, depths, force = path
    load = Phi.T @ f
    q_end = model.solve(load, factors, tolerance=1e-10, partial=True)[0]
    if len(q_end) < len(factors):
        print("    frames: the model's own Newton did not reach the last step")
        return {}
    if args.frame_solver == "haptic":
        slices = min(args.tangent_slices, model.sampled_elements)
        solver = HapticNewton(model.sample, model.linear, args.frame_iterations, slices)

        def step(q, pi, load):
            if not solver.step(q, pi, load):
                raise SystemExit("--frame-solver haptic: a step left the finite numbers")
    else:
        solver = ModifiedNewton(model, args.frame_tolerance, refresh_after=args.refresh_after)
        solver.frame(np.zeros(model.n), np.zeros(model.n_p), 0.0 * load)  # the rest tangent
        solver.residuals = solver.tangents = 0

        def step(q, pi, load):
            if solver.frame(q, pi, load) is None:
                raise SystemExit("--frame-solver modified: a frame did not converge")

    q, pi, times = np.zeros(model.n), np.zeros(model.n_p), []
    for factor in np.linspace(0.0, factors[-1], args.frames + 1)[1:]:
        t = time.perf_counter()
        step(q, pi, factor * load)
        times.append(time.perf_counter() - t)
    u, gap = Phi @ q, lambda: float(np.linalg.norm(q - q_end[-1]) / np.linalg.norm(q_end[-1]))
    out = {"solver": args.frame_solver, "frames": args.frames, "lag": gap(),
           "depth_error": float(abs(u @ f / force / depths[-1] - 1.0)),
           "field_error": float(np.linalg.norm(u - U[-1]) / np.linalg.norm(U[-1])),
           **{f"{k}_s": float(np.percentile(times, v)) for k, v in (("p50", 50), ("p99", 99))},
           "max_s": max(times)}  # fmt: skip
    if args.frame_solver == "modified":
        out |= {"residuals": solver.residuals, "tangents": solver.tangents}
    settle = 0
    while gap() > 1e-6 and settle < 100:
        step(q, pi, factors[-1] * load)
        settle += 1
    out["settle_steps"] = settle
    counts = (f", {out['residuals'] / args.frames:.2f} residuals a step and {out['tangents']} "
              "tangents in all" if args.frame_solver == "modified" else "")  # fmt: skip
    print(f"    {args.frames} steps ({args.frame_solver}{counts}): step p50/p99/max "
          f"{1e3 * out['p50_s']:.2f}/{1e3 * out['p99_s']:.2f}/{1e3 * out['max_s']:.2f} ms; at "
          f"the last, lag {out['lag']:.1e}, depth error {out['depth_error']:.2e}, field "
          f"{out['field_error']:.2e}; settled to 1e-6 in {settle} steps", flush=True)  # fmt: skip
    return out


def neighbour_states(data, near, modes) -> tuple[np.ndarray, np.ndarray]:
    """The stored states and pressures of the training positions ``near`` (indices into
    ``data``, each position's own count: a cut step stores more)."""
    U = np.vstack([data[k]["displacement"] for k in near]).T
    if U.shape[1] < modes:
        raise SystemExit(f"--campaign-modes {modes}: the {len(near)} nearest positions store "
                         f"only {U.shape[1]} states")  # fmt: skip
    return U, np.vstack([data[k]["pressure"] for k in near]).T


class NearbySolver(RegionSolves):
    """Full-order solves of the campaign's load path at ``--solves-per-distance`` loadable
    surface nodes about each ``--local-solves`` distance (mm) from a point: nonlinear
    snapshots of the region itself (``RegionSolves``, the product's), and the bench's
    load cases."""

    def __init__(self, config, args):
        further = args.pinch or args.oblique or args.second_tool or args.held_tool
        if further and config.load.mode != "force":
            raise SystemExit("--second-tool, --pinch, --oblique and --held-tool add force "
                             "tools: the "
                             f"campaign's load is '{config.load.mode}', not force")  # fmt: skip
        # --pinch: the campaign's tool at the centre node presses with a pinch's force
        load = replace(config.load, magnitude=args.pinch) if args.pinch else config.load
        super().__init__(replace(config, load=load), args.local_solves, args.solves_per_distance)

    def states(self, point, forbidden=()) -> tuple[np.ndarray, np.ndarray]:
        """The states and pressures (N, k), (cells, k) of the solves about ``point``, at
        none of the ``forbidden`` nodes."""
        solved = [self.solve(node) for node in self.nodes(point, forbidden)]
        return (np.vstack([d["displacement"] for d in solved]).T,
                np.vstack([d["pressure"] for d in solved]).T)  # fmt: skip

    def case_tools(self, node, args, k=None) -> list[tuple]:
        """The further tools of a pinch or an oblique press at surface ``node`` (the
        campaign's tool on it is the first force): ``--pinch``, the eight nearest free
        loadable nodes, each pressing with the same force along the campaign's direction
        there (thesis §3.4.3: nine neighbouring nodes, 0.014 N each; a snapshot's pinch,
        centred 0.25 or 0.5 mm away, shares some of the held-out pinch's nodes, as a
        single tool's nearby solves share its bump); ``--oblique``, a tangential force
        on the same point, ``--oblique`` of the campaign's along the surface (the k-th
        snapshot at azimuth k x 120 degrees from the tangent nearest x, the held-out press
        (k None) at 45 degrees: a direction no snapshot has)."""
        s = self.surface
        if args.pinch:
            return self.pinch_tools(node, args.pinch)  # the product's (hapticrom physics)
        normal = np.asarray(s.normals[node], float)
        e1 = np.eye(3)[0] - normal[0] * normal  # x on the tangent plane
        if np.linalg.norm(e1) < 0.1:  # a normal near x: y's
            e1 = np.eye(3)[1] - normal[1] * normal
        e1 /= np.linalg.norm(e1)
        azimuth = np.radians(45.0 if k is None else 120.0 * k)
        tangent = np.cos(azimuth) * e1 + np.sin(azimuth) * np.cross(normal, e1)
        force = args.oblique * self.config.load.magnitude * tangent
        return [(self.position(node).point, tuple(float(v) for v in force))]

    def held_path(self, holder, node) -> tuple:
        """The full order with the campaign's force at surface ``node`` while a tool holds
        its patch at ``holder`` in place: a held-out path as ``path``'s (the depth the
        pressing tool's), and the held patch's nodes (canonical)."""
        data = self.solve(holder, tools=[self.tool(node, 1.0)], config=self.held)
        f, U = data["load_vector"], data["displacement"]
        force = np.linalg.norm(f.reshape(-1, 3).sum(axis=0))
        path = (U, data["pressure"], f, data["load_factor"], U @ f / force, force)
        return path, np.asarray(data["contact_nodes"], dtype=np.int64)

    def path(self, node, tools=()) -> tuple:
        """The full order under the campaign's tool at surface ``node`` and the further
        ``tools`` at once: a held-out path as ``held_out_paths``'."""
        data = self.solve(node, tools=tools)
        f, U = data["load_vector"], data["displacement"]
        force = np.linalg.norm(f.reshape(-1, 3).sum(axis=0))
        return U, data["pressure"], f, data["load_factor"], U @ f / force, force


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


# The --frames options: (flag, type, default, help).
FRAME_OPTIONS = (
    ("--frames", int, 0, "--local: each held-out path as this many haptic steps"),
    ("--frame-iterations", int, 1, "haptic: modified Newton iterations a step"),
    ("--tangent-slices", int, 10, "haptic: the steps a tangent is built over"),
    ("--refresh-after", int, 3, "modified: iterations before a tangent"),
    ("--frame-tolerance", float, 1e-6, "modified: the update relative to the state"),
)


def parse_arguments() -> argparse.Namespace:
    """The command line, checked: lists parsed, counts consistent, options that need
    another refused without it."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config")
    parser.add_argument("campaign")
    parser.add_argument("--modes", type=int, default=20)
    parser.add_argument("--pressure-modes", type=int, default=10)
    parser.add_argument("--basis", choices=("campaign", "bumps", "both", "derivatives"),
                        default="campaign", help="the global basis (not --local)")  # fmt: skip
    parser.add_argument("--linear-modes", type=int, default=20,
                        help="derivatives and --local: the linear modes")  # fmt: skip
    parser.add_argument("--derivatives-of", type=int, default=20,
                        help="derivatives and --local: of the leading linear modes")  # fmt: skip
    parser.add_argument("--campaign-modes", type=int, default=0,
                        help="derivatives and --local: campaign POD modes added")  # fmt: skip
    parser.add_argument("--supremizers", action="store_true")
    parser.add_argument("--split", choices=("none", "linear"), default="linear")
    parser.add_argument("--held-out", type=int, default=6)
    parser.add_argument("--tolerances", default="0.1,0.03,0.01,0.003",
                        help="ECSW's; '' for the Galerkin model alone (--local)")  # fmt: skip
    parser.add_argument("--steps", default="2,5,10",
                        help="global basis: ECSW's training states (not --local)")  # fmt: skip
    parser.add_argument("--local", type=float, default=0.0,
                        help="mm: a derivatives basis a held-out position from bumps this "
                        "close to it")  # fmt: skip
    parser.add_argument("--local-neighbours", type=int, default=3,
                        help="--local: the campaign modes from the states of this many "
                        "nearest training positions")  # fmt: skip
    parser.add_argument("--local-solves", default="",
                        help="--local: mm, full-order solves about these distances from "
                        "each held-out position, their states' POD in its basis")  # fmt: skip
    parser.add_argument("--solves-per-distance", type=int, default=None,
                        help="--local-solves: solves at each distance (3)")  # fmt: skip
    parser.add_argument("--state-modes", type=int, default=None,
                        help="--local-solves: POD modes of their states")  # fmt: skip
    parser.add_argument("--second-tool", type=float, default=0.0,
                        help="--local-solves: mm, a second tool this far from each held-out "
                        "position, loaded with it; the solves about both")  # fmt: skip
    parser.add_argument("--held-tool", type=float, default=0.0,
                        help="--local-solves: mm, a tool this far from each held-out position "
                        "holds its patch in place while the position's tool presses")  # fmt: skip
    parser.add_argument(
        "--hold",
        choices=("mean", "rigid", "nodes"),
        default="mean",
        help="--held-tool: the reduced holder keeps its patch's mean "
        "displacement, its rigid motion (the mean and the rotation), or each node "
        "(the basis gaining the response to a force at each)",
    )
    parser.add_argument("--held-basis", choices=("held", "free"), default="held",
                        help="--held-tool: the solves about the press each beside a holder "
                        "about the holder's node, or alone (the holder's reaction then "
                        "from the responses of --hold only)")  # fmt: skip
    parser.add_argument("--second-force", type=float, default=None,
                        help="--second-tool: its force, of the campaign's (0.5)")  # fmt: skip
    parser.add_argument("--second-basis", choices=("single", "paired", "both"),
                        default="single", help="--second-tool: the solves about the two "
                        "tools: each alone, in pairs (both tools at once), or both")  # fmt: skip
    parser.add_argument("--pinch", type=float, default=0.0,
                        help="--local-solves: N, a held-out load of nine forces this large at "
                        "neighbouring nodes (thesis §3.4.3: 0.014); the solves: pinches about "
                        "it")  # fmt: skip
    parser.add_argument("--oblique", type=float, default=0.0,
                        help="--local-solves: a tangential force beside the tool's, this "
                        "fraction of it; the solves: oblique presses about it")  # fmt: skip
    parser.add_argument("--indicator-modes", type=int, default=0,
                        help="--local-solves: the error indicator, on the basis enriched by "
                        "this many further POD modes of each block kept in it")  # fmt: skip
    parser.add_argument("--indicator-tolerance", type=float, default=1e-3,
                        help="--indicator-modes: ECSW's tolerance of its sample")  # fmt: skip
    parser.add_argument("--indicator-apart", action="store_true",
                        help="--indicator-modes: a sample apart from the model's")  # fmt: skip
    parser.add_argument("--check-tolerance", type=float, default=0.0,
                        help="--local-solves: the runtime's error indicator (its check sample: "
                        "ECSW at this tolerance, trained apart) at each ECSW "
                        "row, against the sampling's and the true error")  # fmt: skip
    frames = parser.add_argument_group("haptic steps (haptic_frames)")
    frames.add_argument("--frame-solver", choices=("haptic", "modified"), default="haptic")
    for flag, kind, default, text in FRAME_OPTIONS:
        frames.add_argument(flag, type=kind, default=default, help=text)
    parser.add_argument("--out")
    args = parser.parse_args()
    try:
        args.tolerances = [float(v) for v in args.tolerances.split(",") if v.strip()]
        args.steps = [int(v) for v in args.steps.split(",")]
        args.local_solves = [float(v) for v in args.local_solves.split(",") if v.strip()]
    except ValueError as exc:
        parser.error(f"--tolerances, --steps and --local-solves are comma-separated numbers: {exc}")
    check_arguments(parser, args)
    return args


def check_arguments(parser, args) -> None:
    """Refuse what the bench cannot honour, naming the option."""
    counts = ("modes", "pressure_modes", "linear_modes", "derivatives_of", "campaign_modes")
    for name in counts:
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} must be at least 0")
    if args.local_solves:
        if not args.local:
            parser.error("--local-solves needs --local")
        if min(args.local_solves) <= 0:
            parser.error("--local-solves: distances must be positive (0 would solve the "
                         "held-out position itself)")  # fmt: skip
        if args.solves_per_distance is None:
            args.solves_per_distance = 3
        if args.solves_per_distance < 1 or not args.state_modes or args.state_modes < 1:
            parser.error("--local-solves needs --solves-per-distance >= 1 and --state-modes >= 1")
    elif args.solves_per_distance is not None or args.state_modes is not None:
        parser.error("--solves-per-distance and --state-modes need --local-solves")
    args.state_modes = args.state_modes or 0
    for name in ("second_tool", "held_tool"):
        if getattr(args, name) and not args.local_solves or not getattr(args, name) >= 0:
            parser.error(f"--{name.replace('_', '-')} needs --local-solves, and a positive "
                         "distance (mm)")  # fmt: skip
    cases = [n for n in ("second_tool", "pinch", "oblique", "held_tool") if getattr(args, n)]
    if len(cases) > 1:
        parser.error("--second-tool, --pinch, --oblique and --held-tool: one load case at a "
                     "time")  # fmt: skip
    if (args.pinch or args.oblique) and not args.local_solves:
        parser.error("--pinch and --oblique need --local-solves (the snapshots about the load)")
    if not (np.isfinite(args.pinch) and args.pinch >= 0 and 0 <= args.oblique <= 10):
        parser.error("--pinch: a force (N) > 0; --oblique: a fraction of the tool's, in (0, 10]")
    if args.indicator_modes and not args.local_solves or args.indicator_modes < 0:
        parser.error("--indicator-modes needs --local-solves, and a count >= 0")
    if not 0 < args.indicator_tolerance < 1:
        parser.error("--indicator-tolerance: in (0, 1)")
    if args.check_tolerance and not (args.local_solves and 0 < args.check_tolerance < 1):
        parser.error("--check-tolerance needs --local-solves, and lies in (0, 1)")
    if args.indicator_apart and not (args.indicator_modes and args.tolerances):
        parser.error("--indicator-apart needs --indicator-modes and ECSW --tolerances")
    if args.held_basis != "held" and not args.held_tool:
        parser.error("--held-basis needs --held-tool")
    if args.second_basis != "single" and not args.second_tool:
        parser.error("--second-basis needs --second-tool")
    if args.second_force is not None and not args.second_tool:
        parser.error("--second-force needs --second-tool")
    args.second_force = 0.5 if args.second_force is None else args.second_force
    if not 0 < args.second_force <= 10:
        parser.error("--second-force: a fraction of the campaign's force, in (0, 10]")
    if args.frames and not args.local or args.frames < 0:
        parser.error("--frames needs --local, and --frames >= 0")
    if min(args.refresh_after, args.frame_iterations, args.tangent_slices) < 1:
        parser.error("--refresh-after, --frame-iterations and --tangent-slices: at least 1")
    if not (args.basis == "derivatives" or args.local):
        return
    # --state-modes a block of nearby solves: per tool, or the pairs', or all three
    regions = {"single": 2, "paired": 1, "both": 3}[args.second_basis] if args.second_tool else 1
    derived = args.modes - args.linear_modes - args.campaign_modes - regions * args.state_modes
    if derived < 0 or args.derivatives_of > args.linear_modes:
        parser.error("--basis derivatives and --local: --modes must be at least "
                     "--linear-modes + --campaign-modes + --state-modes (a block each, see "
                     "--second-basis), and --derivatives-of at most --linear-modes")  # fmt: skip
    if derived and not args.derivatives_of:
        parser.error(f"--derivatives-of 0: {derived} modes left for derivatives; --modes must "
                     "be --linear-modes + --campaign-modes + --state-modes")  # fmt: skip


def main() -> None:
    args = parse_arguments()
    t0 = time.perf_counter()
    config = CampaignConfig.from_toml(args.config)
    store = SnapshotStore(args.campaign)
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    rest = rest_tangents(mesh)
    training, held_out = held_out_split(store.completed(), args.held_out)
    if args.local:
        results = local_models(store, training, held_out, args, mesh, rest, config)
    else:
        results = global_rows(store, training, held_out, args, mesh, rest, config, t0)
    if args.out:
        record = {"arguments": vars(args), "held_out": held_out, "results": results}
        Path(args.out).write_text(json.dumps(record, indent=1))


def global_rows(store, training, held_out, args, mesh, rest, config, t0) -> list[dict]:
    """One basis from the training positions (``bases``); the Galerkin model, then ECSW at
    each of ``--tolerances`` trained on the states of ``--steps``, at the held-out
    positions: one printed row and one dict each."""
    Phi, Psi = bases(store, training, args, mesh, rest, config)
    n, split = Phi.shape[1], args.split == "linear"
    steps = [s - 1 for s in args.steps]

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
    for tolerance in ["galerkin"] + args.tolerances:
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
    return results


if __name__ == "__main__":
    main()
