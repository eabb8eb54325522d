"""Training campaigns: many full-order solves over tool positions, stored as snapshots.

A campaign (TOML, see ``examples/cornea-campaign.toml``) names the mesh, the
material, the control mode and load range, and the tool positions. Running it
solves the full load path at every position and stores the snapshots in a
:class:`~hapticrom.offline.campaign.store.SnapshotStore` directory.

Two-level parallelism: ``ranks_per_solve = K`` splits the N ranks into N/K
groups (MPI sub-communicators); each group solves its share of the positions,
with DOLFINx domain decomposition inside the group. A 25k-DOF solve stops
scaling at a handful of ranks, while a campaign has dozens of independent
positions. What is stored does not depend on N or K (canonical DOF order).

Progress is reported by world rank 0: a bar with an ETA, a line per solve
(Newton iterations, step cuts), a summary at the end.
"""

from __future__ import annotations

import datetime
import io
import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from mpi4py import MPI

from hapticrom import __version__
from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.config import (  # noqa: F401 (the campaign's names, re-exported)
    CONTROL_MODES,
    INNER_PRODUCTS,
    POD_METHODS,
    ANMConfig,
    CampaignConfig,
    CampaignLoad,
    PODConfig,
)
from hapticrom.offline.campaign.positions import (
    ToolPosition,
    plan_with_report,
    positions_table,
)
from hapticrom.offline.campaign.store import FORMAT, VERSION, SnapshotStore, csr_datasets
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.formulation import HyperelasticModel
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.fe.operators import (
    load_vector,
    lumped_volumes,
    reference_tangent,
    tangent_blocks,
)
from hapticrom.offline.fe.organ import load_organ
from hapticrom.offline.fe.sanity import (
    campaign_summary,
    check_refinement,
    dumps,
    summary_lines,
    warning_lines,
    write_json,
)
from hapticrom.offline.mpi import on_rank_zero, print0
from hapticrom.offline.progress import ProgressBar
from hapticrom.shared.checksum import file_digest
from hapticrom.shared.errors import HapticromError, InputError, SolverError

_TAG_REPORT, _TAG_DONE = 7301, 7302


# -- running -----------------------------------------------------------------------
@dataclass
class CampaignReport:
    """What a campaign run did: counts, failures, timing, the physics sanity."""

    positions: int
    solved_now: int
    resumed: int
    failed: list[int]
    wall_seconds: float
    ranks: int
    ranks_per_solve: int
    redone: list[int] = field(default_factory=list)  # stored damaged or failed: solved again
    sanity: dict | None = None  # physics sanity of every stored position (sanity.json)
    refinement: dict | None = None  # --refinement-check of position 0 (refinement.json)


def campaign_manifest(config: CampaignConfig, positions: list[ToolPosition]) -> dict[str, Any]:
    """The manifest.json of a campaign: its identity (hash, mesh digest), positions, units."""
    mesh = config.problem.mesh.file
    return {
        "format": FORMAT,
        "version": VERSION,
        "name": config.name,
        "campaign_hash": config.campaign_hash(),
        "campaign": json.loads(json.dumps(config.raw, default=str)),
        "mesh": {"file": str(Path(mesh).resolve()), "sha256": file_digest(mesh)},
        "positions": [
            {
                "index": p.index,
                "point": list(p.point),
                "normal": list(p.normal),
                "node_tag": int(p.node_tag),
                "source": p.source,
                "asked": None if p.asked is None else list(p.asked),
                "snap_distance": p.snap_distance,
            }
            for p in positions
        ],
        "units": {"length": "mm", "force": "N", "stress": "MPa"},
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": {"hapticrom": __version__},
    }


@dataclass
class _Plan:
    positions: list[ToolPosition]
    resumed: bool
    done: list[int]  # solved and intact
    redo: dict[int, str]  # stored but damaged or failed: why they are solved again
    snapping: str  # the snapping report of the positions
    note: str = ""  # the directory's earlier campaign, discarded since nothing was solved


def _plan(config: CampaignConfig, store: SnapshotStore, restart: bool) -> _Plan:
    """Check the whole campaign, then open (or create) its directory; see :class:`_Plan`."""
    surface = read_surface(config.problem.mesh.file, config.load.surface)
    positions, snapping = plan_with_report(surface, config.positions)
    validate_campaign(config)  # before the directory exists
    manifest = campaign_manifest(config, positions)
    note = ""
    if not restart and _holds_another_campaign_unsolved(store, manifest):
        restart = True
        note = (
            f"{store.root} held another campaign with no position solved: starting over "
            "(no --restart needed)"
        )
    resumed = store.open_or_create(manifest, restart=restart)
    done, redo = store.audit()
    planned = {p.index for p in positions}
    redo = {i: why for i, why in redo.items() if i in planned}
    return _Plan(positions, resumed, done, redo, snapping, note)


def _holds_another_campaign_unsolved(store: SnapshotStore, manifest: dict) -> bool:
    """The directory holds an intact manifest of another campaign and no position record."""
    if not store.manifest_path.is_file() or store.completed():
        return False
    return store.manifest()["campaign_hash"] != manifest["campaign_hash"]


def validate_campaign(config: CampaignConfig) -> None:
    """What the configuration alone cannot tell: the law, element and fibres against the mesh.

    Reads the mesh's sidecar only (no DOLFINx mesh): InputError before any
    directory or solve.
    """
    from hapticrom.meshes.msh import read_sidecar
    from hapticrom.offline.fe.formulation import choose_element
    from hapticrom.offline.fe.materials import make_law

    problem = config.problem
    info = read_sidecar(problem.mesh.file)
    law = make_law(problem.material.law, **problem.material.params)
    choose_element(str(info.get("cell_type")), problem.discretisation.element)
    if law.requires_fibres and not info.get("fibres"):
        raise InputError(
            f"material '{law.name}' needs fibre directions, and mesh "
            f"{Path(problem.mesh.file).name} has none: choose a mesh with fibres or another law"
        )


def _operators_damage(store: SnapshotStore) -> str | None:
    """Why the stored operators must be computed (again), or None if they are intact."""
    if not store.has_operators():
        return "missing"
    try:
        store.read_operators()
    except InputError as exc:
        return f"damaged: {exc}"
    return None


def _ensure_operators(config, organ, comm, group, group_index, store, say) -> None:
    """Compute and store K0 and the volumes (group 0) unless an intact copy is stored."""
    damage = on_rank_zero(comm, _operators_damage, store)
    if damage is None:
        return
    if damage != "missing":
        say(f"stored operators {damage}; computing them again")
    if group_index == 0:
        t0 = time.perf_counter()
        _write_operators(config, organ, group, store)
        if group.rank == 0:
            say(f"stored K0 and the volume weights ({time.perf_counter() - t0:.1f} s)")


def _write_operators(config: CampaignConfig, organ, group: MPI.Comm, store: SnapshotStore):
    """K0, volumes, coordinates and supports of the campaign's mesh (group 0 only)."""
    problem = config.problem
    from hapticrom.offline.fe.formulation import choose_element
    from hapticrom.offline.fe.materials import make_law

    law = make_law(problem.material.law, **problem.material.params)
    element = choose_element(organ.cell_type, problem.discretisation.element)
    model = HyperelasticModel(organ, law, element, problem.discretisation.quadrature_degree)
    order = CanonicalOrder(model.V)
    K0 = reference_tangent(model, order)
    blocks = tangent_blocks(model, order, CanonicalOrder(model.Q)) if model.p is not None else None
    volumes = lumped_volumes(model.V, order, model.quadrature_degree)
    coords = order.gather(model.V.tabulate_dof_coordinates().reshape(-1))
    supported = order.gather_blocks(organ.constrained_blocks(model.V))
    if group.rank == 0:
        mixed = {}
        if blocks is not None:  # for reduced models with a reduced pressure space
            mixed = {**csr_datasets("Kuu", blocks["Kuu"]), **csr_datasets("Kup", blocks["Kup"])}
            mixed["Kpp_diagonal"] = blocks["Kpp"]
        store.write_operators(
            {
                **csr_datasets("K0", K0),
                **mixed,
                "volumes": volumes,
                "node_coordinates": coords.reshape(-1, 3),
                "supported_nodes": supported,
            },
            {
                "element": element.name,
                "num_dofs": order.num_dofs,
                "units": "K0 N/mm, volumes mm^3, coordinates mm",
                "condensed_pressure": bool(model.p is not None),
            },
        )


@dataclass
class _LoadPath:
    """One position's converged states, gathered on the group's root (canonical order)."""

    snapshots: list[np.ndarray]  # displacement per converged increment (root only)
    pressures: list[np.ndarray]  # element-wise pressure per increment (root, mixed only)
    records: list  # StepRecord per converged increment
    forces: Any  # tool force per increment, N
    displacements: Any  # tool displacement per increment, mm
    status: str = "solved"
    message: str = ""


def _solve_load_path(model: FullOrderModel, order, pressure_order, group) -> _LoadPath:
    """Solve the whole load path, gathering each converged state to the group's root.

    A solve that fails keeps what converged; the position is marked failed.
    """
    path = _LoadPath([], [], [], [], [])

    def on_step(record, force, disp):
        u = order.gather(model.model.u.x.array)
        p = pressure_order.gather(model.model.p.x.array) if pressure_order else None
        if group.rank == 0:
            path.snapshots.append(u)
            if p is not None:
                path.pressures.append(p)

    try:
        result = model.solve(on_step=on_step)
        path.records, path.forces = result.records, result.force
        path.displacements = result.displacement
    except SolverError as exc:
        path.status, path.message = "failed", str(exc)
        path.records, path.forces, path.displacements = model.history
    return path


def _load_and_contact(config, model: FullOrderModel, order):
    """(The load vector at load factor 1 under force control, or of the further force
    tools beside a displacement-controlled one (None otherwise), the contact patch's local
    blocks); collective over the group."""
    force = config.load.mode == "force"
    if force or (config.load.mode == "displacement" and model.config.load.tools):
        model.set_load(1.0)
        blocks = model.patch.blocks(model.model.V) if force else model.patch_blocks
        return load_vector(model.model, order), blocks
    return None, model.patch_blocks


def _position_datasets(path: _LoadPath, order, pressure_order, contact, f, sanity) -> dict:
    """The datasets of a position's record (root of the group)."""
    n = order.num_dofs
    records = path.records
    datasets = {
        "displacement": np.array(path.snapshots).reshape(-1, n),
        "load_factor": np.array([r.load_factor for r in records]),
        "force": np.asarray(path.forces).reshape(-1, 3),
        "contact_displacement": np.asarray(path.displacements).reshape(-1, 3),
        "newton_iterations": np.array([r.newton_iterations for r in records], dtype=np.int64),
        "step_cuts": np.array([r.step_cuts for r in records], dtype=np.int64),
        "contact_nodes": contact,
    }
    if f is not None:
        datasets["load_vector"] = f
    if pressure_order is not None:  # element-wise pressure (MPa), canonical cell order
        datasets["pressure"] = np.array(path.pressures).reshape(-1, pressure_order.num_dofs)
    datasets.update(_sanity_datasets(sanity))
    return datasets


def _position_attrs(config, position, path: _LoadPath, sanity, seconds: float,
                    tools=()) -> dict:  # fmt: skip
    """The attributes of a position's record: its outcome, where and how it was loaded
    (``tools``: the further force tools, a row (point mm, force N) each, if any)."""
    attrs = {
        "status": path.status,
        "message": path.message,
        "point": np.asarray(position.point),
        "normal": np.asarray(position.normal),
        "direction": config.load.unit_direction(position),
        "mode": config.load.mode,
        "magnitude": config.load.magnitude,
        "units": "displacement mm, force N (tool on tissue), load_vector N",
        "seconds": seconds,
        "sanity": dumps(sanity.summary()),
    }
    if tools:
        attrs["tools"] = np.array([[*point, *force] for point, force in tools], float)
    return attrs


def solve_position(config, position, organ, group, tools=()):
    """One full load path; returns (datasets, attrs) on the group's root, None elsewhere.
    ``tools``: further force tools ((point, force) pairs, :class:`LoadConfig`) loaded
    with it (the load vector is then all of theirs)."""
    problem = replace(config.problem, load=replace(config.load.at(position), tools=tuple(tools)))
    t0 = time.perf_counter()
    model = FullOrderModel(problem, comm=group, organ=organ, verbose=False)
    try:
        order = CanonicalOrder(model.model.V)
        pressure_order = CanonicalOrder(model.model.Q) if model.model.p is not None else None
        path = _solve_load_path(model, order, pressure_order, group)
        f, contact_local = _load_and_contact(config, model, order)
        contact = order.gather_blocks(contact_local)
    finally:
        model.close()  # its factorisation, now: positions are solved one after another
    if group.rank != 0:
        return None
    datasets = _position_datasets(path, order, pressure_order, contact, f, model.sanity)
    seconds = time.perf_counter() - t0
    attrs = _position_attrs(config, position, path, model.sanity, seconds, problem.load.tools)
    return datasets, attrs


def _sanity_datasets(report) -> dict[str, np.ndarray]:
    """The per-step sanity measures of a position (offline/fe/sanity.py), one value per record."""
    steps = report.steps
    return {
        "sanity/j_min": np.array([s.j_min for s in steps], dtype=float),
        "sanity/stretch_min": np.array([s.stretch_min for s in steps], dtype=float),
        "sanity/inverted": np.array([s.inverted for s in steps], dtype=np.int64),
        "sanity/u_max": np.array([s.u_max for s in steps], dtype=float),
        "sanity/tangent_negative": np.array([s.tangent_negative for s in steps], dtype=np.int64),
    }


def campaign_sanity(store: SnapshotStore) -> dict:
    """The physics sanity of the stored positions (:func:`sanity.campaign_summary`); rank 0."""
    import h5py

    manifest = store.manifest()
    records = []
    for index in store.completed():
        with h5py.File(store.position_path(index), "r") as f:
            raw = f.attrs.get("sanity")
            point = [float(c) for c in f.attrs["point"]]
        records.append((index, point, json.loads(raw) if raw is not None else None))
    return campaign_summary(records, len(manifest["positions"]))


class ProgressLog:
    """World rank 0's log of the finished positions: a line each, and the progress bar.

    The root of every other group sends its reports to rank 0 (tag ``_TAG_REPORT``)
    and, when its share is done, an empty message (tag ``_TAG_DONE``); rank 0
    receives them between its own solves and waits for every group at the end.
    """

    def __init__(self, comm: MPI.Comm, groups: int, total: int, done: int, verbose: bool):
        self.comm, self.groups = comm, groups
        self.reports: list[dict] = []  # rank 0: every report of this run
        self.groups_done = 0
        self.bar = ProgressBar(total, already_done=done) if comm.rank == 0 else None
        if not verbose and self.bar is not None:
            self.bar.stream = io.StringIO()  # quiet runs (tests) keep the log in memory

    def add(self, report: dict) -> None:
        """A group's root: log a finished position (rank 0) or send it there."""
        if self.comm.rank == 0:
            self._announce(report)
            self._drain(block_until_done=False)
        else:
            self.comm.send(report, dest=0, tag=_TAG_REPORT)

    def close(self, group: MPI.Comm) -> None:
        """Every rank, once its group's share is done: rank 0 waits for the other groups."""
        if group.rank == 0 and self.comm.rank != 0:
            self.comm.send(None, dest=0, tag=_TAG_DONE)
        if self.comm.rank == 0:
            self._drain(block_until_done=True)

    def _announce(self, report: dict) -> None:
        """World rank 0: log a finished position and move the bar."""
        cuts = f", {report['cuts']} step cut(s)" if report["cuts"] else ""
        state = "" if report["status"] == "solved" else f"  FAILED: {report['message']}"
        point = tuple(round(c, 3) for c in report["point"])
        line = (
            f"position {report['index']:3d} {point} group {report['group']}: "
            f"{report['steps']} steps, {report['its']} Newton its{cuts}, "
            f"{report['seconds']:.1f} s{state}"
        )
        print(line, file=self.bar.stream, flush=True)
        for warning in report["warnings"]:
            print(f"  warning: {warning}", file=self.bar.stream, flush=True)
        self.bar.advance()
        self.reports.append(report)

    def _drain(self, block_until_done: bool) -> None:
        """World rank 0: take the other groups' messages (all of them, if blocking)."""
        status = MPI.Status()
        while True:
            if not block_until_done and not self.comm.iprobe(MPI.ANY_SOURCE, MPI.ANY_TAG, status):
                return
            if block_until_done and self.groups_done == self.groups - 1:
                return
            message = self.comm.recv(source=MPI.ANY_SOURCE, tag=MPI.ANY_TAG, status=status)
            if status.Get_tag() == _TAG_DONE:
                self.groups_done += 1
            else:
                self._announce(message)


@dataclass
class _Groups:
    """The world split into solve groups of ``ranks_per_solve`` ranks: how many, this
    rank's group's index and its communicator."""

    count: int
    index: int
    comm: MPI.Comm


def _split_groups(comm: MPI.Comm, ranks_per_solve: int) -> _Groups:
    """The solve groups (collective; ``ranks_per_solve`` divides the number of ranks)."""
    index = comm.rank // ranks_per_solve
    return _Groups(comm.size // ranks_per_solve, index, comm.Split(color=index, key=comm.rank))


def _position_report(position, group_index: int, datasets: dict, attrs: dict) -> dict:
    """What the log says of a solved (or failed) position."""
    return {
        "index": position.index,
        "point": list(position.point),
        "group": group_index,
        "steps": len(datasets["load_factor"]),
        "its": int(datasets["newton_iterations"].sum()),
        "cuts": int(datasets["step_cuts"].sum()),
        "seconds": attrs["seconds"],
        "status": attrs["status"],
        "message": attrs["message"],
        "warnings": warning_lines(json.loads(attrs["sanity"]), f"position {position.index}"),
    }


def _solve_share(config, mine, organ, groups: _Groups, store, log: ProgressLog, comm) -> None:
    """Solve and store this group's positions ``mine``; HapticromError on every rank if
    any group failed (naming the groups)."""
    error = None
    try:
        for position in mine:
            record = solve_position(config, position, organ, groups.comm)
            if groups.comm.rank == 0:
                datasets, attrs = record
                store.write_position(position.index, datasets, attrs)
                log.add(_position_report(position, groups.index, datasets, attrs))
    except HapticromError as exc:
        error = f"group {groups.index}: {exc}"
    finally:
        log.close(groups.comm)
    errors = [e for e in comm.allgather(error) if e]
    if errors:
        raise HapticromError("; ".join(errors))


def _print_summary(log, plan, failed, wall, comm, ranks_per_solve, sanity) -> None:
    """World rank 0: the closing lines of a campaign run."""
    solved = [r for r in log.reports if r["status"] == "solved"]
    per_solve = np.mean([r["seconds"] for r in solved]) if solved else math.nan
    print(
        f"campaign done: {len(log.reports)} solve(s) this run ({len(plan.done)} resumed), "
        f"{len(failed)} failed, {wall:.1f} s wall, {per_solve:.1f} s per solve "
        f"(one group), {comm.size} rank(s), {ranks_per_solve} per solve",
        *summary_lines(sanity),
        sep="\n",
        flush=True,
    )


def _campaign_line(config, plan, comm, groups: _Groups, ranks_per_solve) -> str:
    """The first line of a campaign run: what is solved, on how many ranks."""
    load = config.load
    return (
        f"campaign '{config.name}': {len(plan.positions)} tool positions "
        f"({len(plan.done)} already stored{', resuming' if plan.resumed else ''}), "
        f"{load.mode} control, {load.magnitude} "
        f"{'N' if load.mode == 'force' else 'mm'} in {load.steps} steps; "
        f"{comm.size} rank(s) in {groups.count} group(s) of {ranks_per_solve}"
    )


def run_campaign(
    config: CampaignConfig,
    out_dir: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    ranks_per_solve: int = 1,
    restart: bool = False,
    verbose: bool = True,
    refinement_check: bool = False,
) -> CampaignReport:
    """Solve every position of ``config`` not yet stored in ``out_dir``; see the module doc.

    ``refinement_check``: afterwards, solve position 0 again on the next finer built-in
    mesh (:func:`refinement_check_position`).
    """
    t_start = time.perf_counter()
    if ranks_per_solve < 1 or comm.size % ranks_per_solve:
        raise InputError(
            f"--ranks-per-solve {ranks_per_solve} must divide the number of ranks ({comm.size})"
        )
    say = (lambda s: print0(comm, s)) if verbose else (lambda s: None)
    store = SnapshotStore(out_dir)
    plan = on_rank_zero(comm, _plan, config, store, restart)
    groups = _split_groups(comm, ranks_per_solve)
    todo = [p for p in plan.positions if p.index not in set(plan.done)]
    say(_campaign_line(config, plan, comm, groups, ranks_per_solve))
    _announce_plan(plan, say)
    organ = load_organ(config.problem.mesh.file, groups.comm)
    _ensure_operators(config, organ, comm, groups.comm, groups.index, store, say)
    log = ProgressLog(comm, groups.count, len(plan.positions), len(plan.done), verbose)
    _solve_share(config, todo[groups.index :: groups.count], organ, groups, store, log, comm)
    failed = on_rank_zero(comm, _failed_positions, store)
    sanity = on_rank_zero(comm, _write_campaign_sanity, store)
    wall = time.perf_counter() - t_start
    if comm.rank == 0 and verbose:
        _print_summary(log, plan, failed, wall, comm, ranks_per_solve, sanity)
    refinement = None
    if refinement_check:
        first = next(p for p in plan.positions if p.index == 0)
        refinement = refinement_check_position(config, first, store, comm)
    return CampaignReport(
        refinement=refinement,
        positions=len(plan.positions),
        solved_now=len(todo),
        resumed=len(plan.done),
        failed=failed,
        wall_seconds=wall,
        ranks=comm.size,
        ranks_per_solve=ranks_per_solve,
        redone=sorted(plan.redo),
        sanity=sanity,
    )


def refinement_check_position(config, position: ToolPosition, store: SnapshotStore, comm):
    """The mesh-convergence check of one stored position, as ``solve --refinement-check``.

    The position's problem (its load, tool position and solver settings, as
    :func:`solve_position` built it) is solved on the next finer built-in mesh by
    the whole ``comm`` (the mesh and that solve in ``CAMPAIGN_DIR/refinement``) and
    compared with the stored record; the check goes to ``CAMPAIGN_DIR/refinement.json``.
    The stored positions are not touched.
    """
    from types import SimpleNamespace

    problem = replace(config.problem, load=config.load.at(position))

    def stored():
        data, _ = store.read_position(position.index)
        return SimpleNamespace(
            load_factor=data["load_factor"],
            force=data["force"],
            displacement=data["contact_displacement"],
        )

    coarse = on_rank_zero(comm, stored)
    return check_refinement(problem, coarse, store.root, comm, record="refinement.json")


def _announce_plan(plan: _Plan, say) -> None:
    """The positions and how snapping moved them (a new campaign), what is solved again."""
    if plan.note:
        say(plan.note)
    if not plan.done:
        say(positions_table(plan.positions))
        if plan.snapping:
            say(plan.snapping)
    for index, why in sorted(plan.redo.items()):
        say(f"position {index}: {why}; solving it again")


def _write_campaign_sanity(store: SnapshotStore) -> dict:
    """Summarise the stored positions' sanity into ``sanity.json`` of the campaign; rank 0."""
    summary = campaign_sanity(store)
    write_json(store.root / "sanity.json", summary)
    return summary


def _failed_positions(store: SnapshotStore) -> list[int]:
    import h5py

    failed = []
    for index in store.completed():
        with h5py.File(store.position_path(index), "r") as f:
            if f.attrs.get("status") != "solved":
                failed.append(index)
    return failed
