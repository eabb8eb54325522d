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
import hashlib
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
from hapticrom.offline.campaign.positions import (
    PositionsSpec,
    ToolPosition,
    plan_with_report,
    positions_from_dict,
    positions_table,
)
from hapticrom.offline.campaign.store import FORMAT, VERSION, SnapshotStore, csr_datasets
from hapticrom.offline.config import (
    LOAD_COMMON_KEYS,
    LoadConfig,
    ProblemConfig,
    _Reader,
    load_common,
    read_toml,
)
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

CONTROL_MODES = ("displacement", "force")
INNER_PRODUCTS = ("euclidean", "volume")
POD_METHODS = ("snapshots", "svd")
_TAG_REPORT, _TAG_DONE = 7301, 7302


@dataclass(frozen=True)
class CampaignLoad:
    """The tool load of every position, scaled by a load factor from 0 to 1.

    ``magnitude``: mm (displacement control) or N (force control) at load factor 1;
    ``direction``: "normal" (into the surface, along its inward normal at the
    position) or a fixed vector (normalised).
    """

    mode: str
    magnitude: float
    direction: str | tuple[float, float, float] = "normal"
    contact_radius: float = 0.5
    surface: str = "loadable"
    steps: int = 10
    max_step_cuts: int = 8
    predictor: str = "secant"

    def unit_direction(self, position: ToolPosition) -> np.ndarray:
        if self.direction == "normal":
            return -np.asarray(position.normal, dtype=float)
        d = np.asarray(self.direction, dtype=float)
        return d / np.linalg.norm(d)

    def at(self, position: ToolPosition) -> LoadConfig:
        vector = tuple(float(v) for v in self.magnitude * self.unit_direction(position))
        return LoadConfig(
            mode=self.mode,
            contact_point=tuple(position.point),
            contact_radius=self.contact_radius,
            surface=self.surface,
            steps=self.steps,
            max_step_cuts=self.max_step_cuts,
            predictor=self.predictor,
            **{self.mode: vector},
        )


@dataclass(frozen=True)
class PODConfig:
    """Truncation and inner product of the POD (thesis §2.2.2: eigenvalue ratio 1e-8)."""

    eigenvalue_ratio: float | None = 1e-8
    energy: float | None = None
    max_modes: int | None = None
    inner_product: str = "euclidean"
    method: str = "snapshots"


@dataclass(frozen=True)
class ANMConfig:
    """POD-ANM series per sample (thesis ch. 3), computed by the reduction step."""

    enabled: bool = True
    order: int = 6
    tolerance: float = 1e-4


@dataclass(frozen=True)
class CampaignConfig:
    name: str
    problem: ProblemConfig  # mesh, material, discretisation, solver (its load is unused)
    load: CampaignLoad
    positions: PositionsSpec
    pod: PODConfig = PODConfig()
    anm: ANMConfig = ANMConfig()
    cutting: object = None  # CuttingConfig or None: the artifact's cuttable region
    raw: dict = field(default_factory=dict, compare=False)

    @classmethod
    def from_toml(cls, path: str | Path) -> CampaignConfig:
        path = Path(path)
        data = read_toml(path, "campaign file")
        return cls.from_dict(data, base_dir=path.parent, source=str(path))

    @classmethod
    def from_dict(cls, data: dict, base_dir: str | Path = ".", source: str = "campaign"):
        r = _Reader(source)
        known = {"campaign", "mesh", "material", "discretisation", "solver", "load"}
        r.keys(data, "", known | {"positions", "pod", "anm", "cutting"})
        problem = ProblemConfig.from_dict(
            {
                **{
                    k: data[k]
                    for k in ("mesh", "material", "discretisation", "solver")
                    if k in data
                },
                "load": {"mode": "force", "force": [0.0, 0.0, 0.0]},
                "output": {"xdmf": False},
            },
            base_dir=base_dir,
            source=source,
        )
        meta = r.table(data, "campaign")
        r.keys(meta, "campaign", {"name", "description"})
        name = meta.get("name", Path(source).stem)
        anm = _anm(r, r.table(data, "anm"))
        if anm.enabled and problem.material.params.get("fibre_tension_only") is True:
            r.fail(
                "anm",
                "the POD-ANM series need an analytic energy and fibre_tension_only = true "
                "switches the fibres on and off: set [anm] enabled = false or "
                "fibre_tension_only = false",
            )
        return cls(
            name=str(name),
            problem=problem,
            load=_campaign_load(r, r.table(data, "load", required=True)),
            positions=positions_from_dict(r.table(data, "positions", required=True)),
            pod=_pod(r, r.table(data, "pod")),
            anm=anm,
            cutting=_cutting(r, data["cutting"]) if "cutting" in data else None,
            raw=data,
        )

    def campaign_hash(self) -> str:
        """Identity of the campaign: its configuration and the bytes of its mesh.

        The ``[anm]`` and ``[cutting]`` tables are left out: they only change the
        reduction, not the solves.
        """
        solves = {k: v for k, v in self.raw.items() if k not in ("anm", "cutting")}
        h = hashlib.sha256(json.dumps(solves, sort_keys=True, default=str).encode())
        h.update(file_digest(self.problem.mesh.file).encode())
        return h.hexdigest()


def _campaign_load(r: _Reader, t: dict) -> CampaignLoad:
    """The campaign's [load] table; the keys it shares with a problem's are checked alike."""
    r.keys(t, "load", {"mode", "magnitude", "direction", *LOAD_COMMON_KEYS})
    mode = r.choice(t, "load", "mode", CONTROL_MODES, None)
    direction = t.get("direction", "normal")
    if direction != "normal":
        direction = r.vector(t, "load", "direction")
        if np.linalg.norm(direction) == 0:
            r.fail("load", "direction must not be the zero vector")
    return CampaignLoad(
        mode=mode,
        magnitude=r.number(t, "load", "magnitude", positive=True),
        direction=direction,
        **load_common(r, t),
    )


def _pod(r: _Reader, t: dict) -> PODConfig:
    r.keys(t, "pod", {"eigenvalue_ratio", "energy", "max_modes", "inner_product", "method"})
    ratio = r.number(t, "pod", "eigenvalue_ratio", 1e-8, positive=True)
    energy = t.get("energy")
    if energy is not None and not 0 < r.number(t, "pod", "energy") <= 1:
        r.fail("pod", f"energy must lie in (0, 1], got {energy}")
    max_modes = t.get("max_modes")
    if max_modes is not None:
        max_modes = r.number(t, "pod", "max_modes", positive=True, integer=True)
    return PODConfig(
        eigenvalue_ratio=ratio,
        energy=energy,
        max_modes=max_modes,
        inner_product=r.choice(t, "pod", "inner_product", INNER_PRODUCTS, "euclidean"),
        method=r.choice(t, "pod", "method", POD_METHODS, "snapshots"),
    )


def _anm(r: _Reader, t: dict) -> ANMConfig:
    r.keys(t, "anm", {"enabled", "order", "tolerance"})
    enabled = t.get("enabled", True)
    if not isinstance(enabled, bool):
        r.fail("anm", f"enabled must be true or false, got {enabled!r}")
    order = r.number(t, "anm", "order", 6, positive=True, integer=True)
    if not 1 <= order <= 15:
        r.fail("anm", f"order must be between 1 and 15, got {order}")
    tolerance = r.number(t, "anm", "tolerance", 1e-4, positive=True)
    if not tolerance < 1:
        r.fail("anm", f"tolerance must be below 1, got {tolerance}")
    return ANMConfig(enabled=enabled, order=order, tolerance=tolerance)


def _cutting(r: _Reader, t: dict):
    from hapticrom.offline.cutting.export import CuttingConfig

    r.keys(t, "cutting", {"centre", "radius", "patch_layers", "cut_force"})
    return CuttingConfig(
        centre=tuple(r.vector(t, "cutting", "centre", required=True)),
        radius=r.number(t, "cutting", "radius", positive=True),
        patch_layers=r.number(t, "cutting", "patch_layers", 2, positive=True, integer=True),
        cut_force=r.number(t, "cutting", "cut_force", 0.02, positive=True),
    )


# -- running -----------------------------------------------------------------------
@dataclass
class CampaignReport:
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


def _solve_position(config, position, organ, group):
    """One full load path; returns (datasets, attrs) on the group's root, None elsewhere."""
    problem = replace(config.problem, load=config.load.at(position))
    t0 = time.perf_counter()
    model = FullOrderModel(problem, comm=group, organ=organ, verbose=False)
    order = CanonicalOrder(model.model.V)
    pressure_order = CanonicalOrder(model.model.Q) if model.model.p is not None else None
    snapshots, pressures = [], []

    def on_step(record, force, disp):
        u = order.gather(model.model.u.x.array)
        p = pressure_order.gather(model.model.p.x.array) if pressure_order else None
        if group.rank == 0:
            snapshots.append(u)
            if p is not None:
                pressures.append(p)

    status, message = "solved", ""
    try:
        result = model.solve(on_step=on_step)
        records, forces, disps = result.records, result.force, result.displacement
    except SolverError as exc:  # keep what converged; the position is marked failed
        status, message = "failed", str(exc)
        records, forces, disps = model.history
    if config.load.mode == "force":
        model.set_load(1.0)
        f = load_vector(model.model, order)
        contact_local = model.patch.blocks(model.model.V)
    else:
        f = None
        contact_local = model.patch_blocks
    contact = order.gather_blocks(contact_local)
    if group.rank != 0:
        return None
    n = order.num_dofs
    datasets = {
        "displacement": np.array(snapshots).reshape(-1, n),
        "load_factor": np.array([r.load_factor for r in records]),
        "force": np.asarray(forces).reshape(-1, 3),
        "contact_displacement": np.asarray(disps).reshape(-1, 3),
        "newton_iterations": np.array([r.newton_iterations for r in records], dtype=np.int64),
        "step_cuts": np.array([r.step_cuts for r in records], dtype=np.int64),
        "contact_nodes": contact,
    }
    if f is not None:
        datasets["load_vector"] = f
    if pressure_order is not None:  # element-wise pressure (MPa), canonical cell order
        datasets["pressure"] = np.array(pressures).reshape(-1, pressure_order.num_dofs)
    datasets.update(_sanity_datasets(model.sanity))
    direction = config.load.unit_direction(position)
    attrs = {
        "status": status,
        "message": message,
        "point": np.asarray(position.point),
        "normal": np.asarray(position.normal),
        "direction": direction,
        "mode": config.load.mode,
        "magnitude": config.load.magnitude,
        "units": "displacement mm, force N (tool on tissue), load_vector N",
        "seconds": time.perf_counter() - t0,
        "sanity": dumps(model.sanity.summary()),
    }
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
    positions, resumed, done, redo = plan.positions, plan.resumed, plan.done, plan.redo
    n_groups = comm.size // ranks_per_solve
    group_index = comm.rank // ranks_per_solve
    group = comm.Split(color=group_index, key=comm.rank)
    todo = [p for p in positions if p.index not in set(done)]
    say(
        f"campaign '{config.name}': {len(positions)} tool positions "
        f"({len(done)} already stored{', resuming' if resumed else ''}), "
        f"{config.load.mode} control, {config.load.magnitude} "
        f"{'mm' if config.load.mode == 'displacement' else 'N'} in {config.load.steps} steps; "
        f"{comm.size} rank(s) in {n_groups} group(s) of {ranks_per_solve}"
    )
    _announce_plan(plan, say)

    organ = load_organ(config.problem.mesh.file, group)
    _ensure_operators(config, organ, comm, group, group_index, store, say)

    mine = todo[group_index::n_groups]
    bar = ProgressBar(len(positions), already_done=len(done)) if comm.rank == 0 else None
    if not verbose and bar is not None:
        bar.stream = io.StringIO()  # quiet runs (tests) keep the log in memory
    error = None
    reports = []

    def announce(report: dict) -> None:
        """World rank 0: log a finished position and move the bar."""
        cuts = f", {report['cuts']} step cut(s)" if report["cuts"] else ""
        state = "" if report["status"] == "solved" else f"  FAILED: {report['message']}"
        point = tuple(round(c, 3) for c in report["point"])
        line = (
            f"position {report['index']:3d} {point} group {report['group']}: "
            f"{report['steps']} steps, {report['its']} Newton its{cuts}, "
            f"{report['seconds']:.1f} s{state}"
        )
        print(line, file=bar.stream, flush=True)
        for warning in report["warnings"]:
            print(f"  warning: {warning}", file=bar.stream, flush=True)
        bar.advance()
        reports.append(report)

    def drain(block_until_done: bool) -> None:
        nonlocal groups_done
        status = MPI.Status()
        while True:
            if not block_until_done and not comm.iprobe(MPI.ANY_SOURCE, MPI.ANY_TAG, status):
                return
            if block_until_done and groups_done == n_groups - 1:
                return
            message = comm.recv(source=MPI.ANY_SOURCE, tag=MPI.ANY_TAG, status=status)
            if status.Get_tag() == _TAG_DONE:
                groups_done += 1
            else:
                announce(message)

    groups_done = 0
    try:
        for position in mine:
            record = _solve_position(config, position, organ, group)
            if group.rank == 0:
                datasets, attrs = record
                store.write_position(position.index, datasets, attrs)
                report = {
                    "index": position.index,
                    "point": list(position.point),
                    "group": group_index,
                    "steps": len(datasets["load_factor"]),
                    "its": int(datasets["newton_iterations"].sum()),
                    "cuts": int(datasets["step_cuts"].sum()),
                    "seconds": attrs["seconds"],
                    "status": attrs["status"],
                    "message": attrs["message"],
                    "warnings": warning_lines(
                        json.loads(attrs["sanity"]), f"position {position.index}"
                    ),
                }
                if comm.rank == 0:
                    announce(report)
                    drain(block_until_done=False)
                else:
                    comm.send(report, dest=0, tag=_TAG_REPORT)
    except HapticromError as exc:
        error = f"group {group_index}: {exc}"
    finally:
        if group.rank == 0 and comm.rank != 0:
            comm.send(None, dest=0, tag=_TAG_DONE)
        if comm.rank == 0:
            drain(block_until_done=True)
    errors = [e for e in comm.allgather(error) if e]
    if errors:
        raise HapticromError("; ".join(errors))

    failed = on_rank_zero(comm, _failed_positions, store)
    sanity = on_rank_zero(comm, _write_campaign_sanity, store)
    wall = time.perf_counter() - t_start
    if comm.rank == 0 and verbose:
        solved = [r for r in reports if r["status"] == "solved"]
        per_solve = np.mean([r["seconds"] for r in solved]) if solved else math.nan
        print(
            f"campaign done: {len(reports)} solve(s) this run ({len(done)} resumed), "
            f"{len(failed)} failed, {wall:.1f} s wall, {per_solve:.1f} s per solve "
            f"(one group), {comm.size} rank(s), {ranks_per_solve} per solve",
            *summary_lines(sanity),
            sep="\n",
            flush=True,
        )
    refinement = None
    if refinement_check:
        first = next(p for p in positions if p.index == 0)
        refinement = refinement_check_position(config, first, store, comm)
    return CampaignReport(
        refinement=refinement,
        positions=len(positions),
        solved_now=len(todo),
        resumed=len(done),
        failed=failed,
        wall_seconds=wall,
        ranks=comm.size,
        ranks_per_solve=ranks_per_solve,
        redone=sorted(redo),
        sanity=sanity,
    )


def refinement_check_position(config, position: ToolPosition, store: SnapshotStore, comm):
    """The mesh-convergence check of one stored position, as ``solve --refinement-check``.

    The position's problem (its load, tool position and solver settings, as
    :func:`_solve_position` built it) is solved on the next finer built-in mesh by
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
