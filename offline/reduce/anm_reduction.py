"""POD-ANM series of every campaign sample, for the artifact (thesis §3.4.5).

For each solved tool position the reduction already holds its snapshots (in
canonical rows). Here they are moved to the DOLFINx layout of one
:class:`~hapticrom.offline.fe.formulation.HyperelasticModel` of the campaign's
organ and material (the residual does not depend on the tool: the lifting of
the tool's displacement carries the position), the reduced space of the
sample is built (:func:`~hapticrom.offline.reduce.anm.snapshot_space`) and the
continuation covers the trained load range. Displacement control: the load is
the depth and the response the force; force control (a smooth pressure under
the tool): the load is the force and the response the work-conjugate mean
displacement under the tool, its depth. What the runtime needs per section:
the series of the depth (mm), of the normal force (N) and of the reduced
coordinates in the sample's artifact basis A_i (mm),

    c(a) = A_i^T u(a) = lam(a) A_i^T g + (A_i^T A_0) alpha(a),

whose projection error is that of the lifting and modes on A_i (both are
combinations of the same snapshots).

Distribution and reuse (:func:`sample_series`): the samples are independent, and one
sample's series is small (a few hundred residual evaluations of the organ), so the
ranks form groups of ``[anm] ranks_per_series`` (MPI sub-communicators, as the
campaign's solve groups) and each group computes its share of the samples with its
own DOLFINx model of the organ. A sample's branch (its sections in its own snapshot
space) depends on the sample's snapshots and load, the organ, material, element, load
range and series options; these are hashed into a key and the branch is stored under
it in the campaign directory (``anm-series/KEY.h5``, atomic and checksummed as the
snapshot store, verified when read). A later reduction with the same key reads it back
instead of computing it: as stored if the artifact basis is the same, else projected
onto the new basis (positions added can change the number of modes; that projection
costs a matrix product).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom import __version__
from hapticrom.meshes.msh import sidecar_path
from hapticrom.offline.campaign.run import ProgressLog
from hapticrom.offline.campaign.store import read_h5, write_h5
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
from hapticrom.offline.fe.materials import make_law
from hapticrom.offline.fe.organ import load_organ
from hapticrom.offline.mpi import allgather_rows, on_rank_zero
from hapticrom.offline.reduce.anm import (
    ANMOptions,
    ComplexResidual,
    ReducedResidual,
    continuation,
    snapshot_space,
)
from hapticrom.offline.reduce.pod import Truncation
from hapticrom.shared.checksum import array_digest, file_digest
from hapticrom.shared.errors import InputError

SERIES_FOLDER = "anm-series"  # in the campaign directory: one KEY.h5 per stored branch
# Part of every key: a change of what a stored branch means (its datasets, or how the key
# is made) must be a new version, so that older entries are never read as current ones.
SERIES_FORMAT = 1


@dataclass
class SampleSeries:
    """The sections of one sample's branch, ready for the artifact."""

    a_max: np.ndarray  # (S,)
    depth: np.ndarray  # (S, N + 1) mm
    force: np.ndarray  # (S, N + 1) N, tool on tissue along the push direction
    coefficients: np.ndarray  # (S, N + 1, n) mm, in the sample's artifact basis
    evaluations: int
    seconds: float


def _to_owned(order: CanonicalOrder, canonical: np.ndarray) -> np.ndarray:
    """Rows of a canonical (bs N, m) array that this rank owns in DOLFINx order."""
    bs = order.bs
    m = canonical.shape[1]
    return canonical.reshape(-1, bs, m)[order.owned].reshape(-1, m)


@dataclass
class SeriesSetting:
    """What every sample's continuation shares: the organ's residual at complex arguments,
    its DOF orders, the series options and the control."""

    residual: ComplexResidual
    order_u: CanonicalOrder
    order_p: CanonicalOrder | None
    options: ANMOptions
    displacement_control: bool


def anm_options(config) -> ANMOptions:
    """The series options of the campaign's ``[anm]`` table."""
    return ANMOptions(order=config.anm.order, tolerance=config.anm.tolerance)


def series_setting(config, comm: MPI.Comm) -> SeriesSetting:
    """The campaign's organ and material as one model on ``comm`` (collective)."""
    problem = config.problem
    organ = load_organ(problem.mesh.file, comm)
    law = make_law(problem.material.law, **problem.material.params)
    element = choose_element(organ.cell_type, problem.discretisation.element)
    model = HyperelasticModel(organ, law, element, problem.discretisation.quadrature_degree)
    return SeriesSetting(
        residual=ComplexResidual(model),
        order_u=CanonicalOrder(model.V),
        order_p=CanonicalOrder(model.Q) if model.Q is not None else None,
        options=anm_options(config),
        displacement_control=config.load.mode == "displacement",
    )


@dataclass
class SeriesInput:
    """The data of one sample that its series reads, whole (canonical rows, on every rank).

    ``U`` (bs N, K) displacement snapshots at the nominal steps (mm), ``P`` (cells, K)
    pressure snapshots (MPa) or None, ``load`` (bs N, 1) the load at load factor 1 (N,
    force control) or None, ``basis`` (bs N, n) the sample's artifact basis A_i.
    """

    index: int
    U: np.ndarray
    P: np.ndarray | None
    load: np.ndarray | None
    basis: np.ndarray


def gather_input(comm: MPI.Comm, sample, reduced) -> SeriesInput:
    """A sample's :class:`SeriesInput` from its rows spread over ``comm`` (collective)."""
    P = allgather_rows(comm, sample.p_local) if sample.p_local is not None else None
    load = None
    if sample.load_local is not None:
        load = allgather_rows(comm, sample.load_local[:, None])
    U = allgather_rows(comm, sample.u_local)
    return SeriesInput(sample.index, U, P, load, allgather_rows(comm, reduced.basis_local))


def sample_space(config, data: SeriesInput, setting: SeriesSetting, comm: MPI.Comm):
    """The reduced space of one sample's snapshots in DOLFINx order, and its arclength scale."""
    U = _to_owned(setting.order_u, data.U)
    P = None
    if setting.order_p is not None and data.P is not None:
        P = _to_owned(setting.order_p, data.P)
    truncation = Truncation(eigenvalue_ratio=config.pod.eigenvalue_ratio)
    if setting.displacement_control:
        f, size = np.zeros(U.shape[0]), config.load.magnitude
    else:
        if data.load is None:
            raise InputError(f"sample {data.index}: the campaign stored no load vector")
        f, size = _to_owned(setting.order_u, data.load)[:, 0], None
    steps = config.load.steps
    load_factor = np.arange(1, steps + 1) / steps
    mode = "displacement" if setting.displacement_control else "force"
    return snapshot_space(comm, load_factor, U, P, mode, f, size, truncation)


@dataclass
class SeriesBranch:
    """What projects a series onto any basis: the load factor ``lam`` (S, N + 1) and mode
    coefficients ``alpha`` (S, N + 1, n0) of its sections, and its snapshot space
    ``space`` = [g, A] (bs N, 1 + n0) in canonical rows (the group's root; None elsewhere).
    """

    lam: np.ndarray
    alpha: np.ndarray
    space: np.ndarray | None


def projected(lam: np.ndarray, alpha: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Coefficients (S, N + 1, n) of u(a) = lam(a) g + A alpha(a) in a basis B, given
    M = B^T [g, A]."""
    return lam[:, :, None] * M[:, 0] + alpha @ M[:, 1:].T


def one_sample_series(
    config, data: SeriesInput, setting: SeriesSetting, comm
) -> tuple[SampleSeries, SeriesBranch]:
    """The continuation of one sample: its series in the sample's artifact basis, and its
    branch (collective over ``comm``, the ranks of ``setting``'s model)."""
    t0 = time.perf_counter()
    space, scale = sample_space(config, data, setting, comm)
    rr = ReducedResidual(setting.residual, space, comm)
    branch = continuation(rr, scale, setting.options)
    A_i = _to_owned(setting.order_u, data.basis)
    M = comm.allreduce(A_i.T @ np.column_stack([space.g, space.A]), op=MPI.SUM)
    n0 = space.n
    Y = np.array([sec.Y for sec in branch.sections])  # (S, N + 1, n0 + n_p + 1)
    lam = Y[:, :, -1]
    coefficients = projected(lam, Y[:, :, :n0], M)
    load = lam * config.load.magnitude  # mm (displacement control) or N (force control)
    response = np.array([sec.response for sec in branch.sections])  # N or mm
    depth, force = (load, response) if setting.displacement_control else (response, load)
    series = SampleSeries(
        a_max=np.array([sec.a_max for sec in branch.sections]),
        depth=depth,
        force=force,
        coefficients=coefficients,
        evaluations=rr.evaluations,
        seconds=time.perf_counter() - t0,
    )
    columns = [setting.order_u.gather(v) for v in (space.g, *space.A.T)]
    canonical = np.column_stack(columns) if comm.rank == 0 else None
    return series, SeriesBranch(lam.copy(), Y[:, :, :n0].copy(), canonical)


# -- the key of a series and the stored series --------------------------------------------
def model_fingerprint(config) -> dict:
    """What every sample's branch depends on besides its own data (rank 0: reads the mesh).

    The organ (the bytes of the mesh and of its sidecar: supports, fibres), the material,
    the element and quadrature, the control and its load range, the truncation of the
    sample's snapshot space, every series option, and the software version.
    """
    problem, load = config.problem, config.load
    mesh = Path(problem.mesh.file)
    sidecar = sidecar_path(mesh)
    return {
        "format": SERIES_FORMAT,
        "software": __version__,
        "mesh": file_digest(mesh),
        "sidecar": file_digest(sidecar) if sidecar.is_file() else None,
        "law": problem.material.law,
        "params": problem.material.params,
        "element": problem.discretisation.element,
        "quadrature_degree": problem.discretisation.quadrature_degree,
        "load": {"mode": load.mode, "magnitude": load.magnitude, "steps": load.steps},
        "eigenvalue_ratio": config.pod.eigenvalue_ratio,
        "anm": dataclasses.asdict(anm_options(config)),
    }


def series_key(fingerprint: dict, data: SeriesInput) -> str:
    """Hex SHA-256 of everything one sample's branch depends on (identical on every rank).

    Not the artifact basis: it changes with the number of modes the other samples ask
    for (positions added), and by rounding with the number of ranks, while the branch
    does not; a stored branch is projected onto the current basis (:meth:`SeriesStore.read`).
    """
    h = hashlib.sha256(json.dumps(fingerprint, sort_keys=True, default=str).encode())
    for array in (data.U, data.P, data.load):
        h.update(b"none" if array is None else array_digest(array).encode())
    return h.hexdigest()


class SeriesStore:
    """The branches stored in a campaign directory, one ``anm-series/KEY.h5`` each: the
    series as the artifact took it, the artifact basis' digest, and the branch."""

    SERIES = ("a_max", "depth", "force", "coefficients")
    BRANCH = ("lam", "alpha", "space")

    def __init__(self, campaign_dir: str | Path):
        self.folder = Path(campaign_dir) / SERIES_FOLDER

    def path(self, key: str) -> Path:
        """The file of the branch stored under ``key``."""
        return self.folder / f"{key}.h5"

    def read(self, key: str, basis: np.ndarray, order: int) -> tuple[SampleSeries, bool] | None:
        """The series stored under ``key`` in the artifact basis ``basis`` (bs N, n), and
        whether it was projected onto it (stored for another basis); None if nothing is
        stored; InputError if the entry is damaged or not of order ``order``."""
        path = self.path(key)
        if not path.is_file():
            return None
        data, attrs = read_h5(path)  # checksums verified
        same_basis = attrs.get("basis") == array_digest(basis)
        problem = _entry_problem(data, attrs, key, order, basis.shape, same_basis)
        if problem:
            raise InputError(f"{path} is damaged: {problem}")
        coefficients = data["coefficients"]
        if not same_basis:
            M = basis.T @ data["space"]
            coefficients = projected(data["lam"], data["alpha"], M)
        series = SampleSeries(
            data["a_max"],
            data["depth"],
            data["force"],
            coefficients,
            evaluations=int(attrs["evaluations"]),
            seconds=float(attrs["seconds"]),
        )
        return series, not same_basis

    def write(self, key: str, data: SeriesInput, series: SampleSeries, branch: SeriesBranch):
        """Store a computed branch under ``key`` (atomic, checksummed); OSError if it cannot."""
        self.folder.mkdir(parents=True, exist_ok=True)
        datasets = {name: getattr(series, name) for name in self.SERIES}
        datasets.update({name: getattr(branch, name) for name in self.BRANCH})
        attrs = {
            "key": key,
            "basis": array_digest(data.basis),  # the coefficients' basis
            "sample": data.index,  # the position it was computed for (information only)
            "evaluations": series.evaluations,
            "seconds": series.seconds,
        }
        write_h5(self.path(key), datasets, attrs)


def _entry_problem(data, attrs, key, order, basis_shape, same_basis) -> str | None:
    """What is wrong with a stored entry (see :meth:`SeriesStore.read`), or None."""
    if attrs.get("key") != key:
        return f"it holds the branch of key {attrs.get('key')!r}"
    missing = [n for n in (*SeriesStore.SERIES, *SeriesStore.BRANCH) if n not in data]
    if missing:
        return f"no dataset {missing[0]}"
    S = data["a_max"].shape[0] if data["a_max"].ndim == 1 else 0
    n0 = data["alpha"].shape[-1]
    m = basis_shape[1] if same_basis else data["coefficients"].shape[-1]
    shapes = {
        "a_max": (S,),
        "depth": (S, order + 1),
        "force": (S, order + 1),
        "coefficients": (S, order + 1, m),
        "lam": (S, order + 1),
        "alpha": (S, order + 1, n0),
        "space": (basis_shape[0], n0 + 1),
    }
    for name, shape in shapes.items():
        array = data[name]
        if S == 0 or array.shape != shape or array.dtype.kind != "f":
            return f"{name} has shape {array.shape} ({array.dtype}), expected {shape} floats"
        if not np.all(np.isfinite(array)):
            return f"{name} is not finite"
    evaluations = attrs.get("evaluations")
    if not isinstance(evaluations, int | np.integer) or evaluations < 0:
        return f"evaluations is {evaluations!r}"
    if not np.all(data["a_max"] > 0):
        return "a validity radius is not positive"
    return None


def read_stored(store: SeriesStore, key: str, basis: np.ndarray, order: int, say):
    """Rank 0: what :meth:`SeriesStore.read` finds, None if the entry is damaged (the
    series is computed again, and that is said)."""
    try:
        return store.read(key, basis, order)
    except InputError as exc:
        say(f"  stored series not used: {exc}; computing it again")
        return None


# -- the groups and their shares ------------------------------------------------------------
@dataclass
class SeriesGroups:
    """The ranks split into groups computing series: how many, this rank's group's index
    and its communicator."""

    count: int
    index: int
    comm: MPI.Comm

    @property
    def size(self) -> int:
        """Ranks per group."""
        return self.comm.size


def series_groups(comm: MPI.Comm, ranks_per_series: int) -> SeriesGroups:
    """Groups of ``ranks_per_series`` ranks (at most ``comm.size``; collective).

    InputError unless the group size divides the number of ranks.
    """
    size = min(ranks_per_series, comm.size)
    if comm.size % size:
        raise InputError(
            f"[anm] ranks_per_series = {ranks_per_series} must divide the number of ranks "
            f"({comm.size})"
        )
    if size == comm.size:  # one group: the ranks as they are (bit for bit as before groups)
        return SeriesGroups(1, 0, comm)
    index = comm.rank // size
    return SeriesGroups(comm.size // size, index, comm.Split(color=index, key=comm.rank))


class SeriesLog(ProgressLog):
    """World rank 0 says each computed series' line as the groups finish them; the other
    groups' roots send theirs (the campaign's protocol, :class:`ProgressLog`)."""

    def __init__(self, comm: MPI.Comm, groups: int, say):
        super().__init__(comm, groups, total=0, done=0, verbose=False)
        self.say = say

    def _announce(self, report: str) -> None:
        self.say(report)


def _series_line(index: int, series: SampleSeries, order: int, groups: SeriesGroups) -> str:
    """The progress line of a computed series."""
    end = float(np.polynomial.polynomial.polyval(series.a_max[-1], series.depth[-1]))
    where = f", group {groups.index}" if groups.count > 1 else ""
    return (
        f"  sample {index:3d}: ANM {len(series.a_max)} section(s) of order "
        f"{order} to depth {end:.4g} mm, "
        f"{series.evaluations} residual evaluations, {series.seconds:.1f} s{where}"
    )


def compute_share(config, share, keys, groups: SeriesGroups, store, log) -> dict:
    """This group's series ``{index: series}`` for ``share`` (its SeriesInputs), each stored
    under its key by the group's root as soon as it is done (collective over the group)."""
    computed = {}
    if not share:
        return computed
    setting = series_setting(config, groups.comm)
    for data in share:
        series, branch = one_sample_series(config, data, setting, groups.comm)
        computed[data.index] = series
        if groups.comm.rank != 0:
            continue
        line = _series_line(data.index, series, setting.options.order, groups)
        if store is not None:
            try:
                store.write(keys[data.index], data, series, branch)
            except OSError as exc:  # storing is an optimisation: the series is still used
                line += f" (not stored: {exc})"
        log.add(line)
    return computed


def _share_of_group(comm, samples, reduced, todo: list[int], groups: SeriesGroups):
    """The SeriesInputs of this group's samples: the ``todo`` positions (in the lists of
    samples), round-robin over the groups (collective: every rank gathers every one)."""
    share = []
    for k, position in enumerate(todo):
        data = gather_input(comm, samples[position], reduced[position])
        if k % groups.count == groups.index:
            share.append(data)
    return share


def sample_series(config, samples, reduced, comm: MPI.Comm, say=lambda s: None, store_in=None):
    """SampleSeries for every sample, in sample order, on every rank (collective over ``comm``).

    ``store_in``: the campaign directory whose stored branches are reused and where the
    computed ones are stored (None: neither). The samples left to compute are dealt
    round-robin to groups of ``[anm] ranks_per_series`` ranks.
    """
    t0 = time.perf_counter()
    groups = series_groups(comm, config.anm.ranks_per_series)
    store = SeriesStore(store_in) if store_in is not None else None
    fingerprint = on_rank_zero(comm, model_fingerprint, config)
    keys, found, order = {}, [], config.anm.order
    for s, r in zip(samples, reduced, strict=True):
        data = gather_input(comm, s, r)
        keys[s.index] = series_key(fingerprint, data)
        hit = None
        if store is not None:
            hit = on_rank_zero(comm, read_stored, store, keys[s.index], data.basis, order, say)
        found.append(hit)
    todo = [k for k, hit in enumerate(found) if hit is None]
    reused = len(samples) - len(todo)
    if reused:
        projected = sum(hit[1] for hit in found if hit is not None)
        say(
            f"  reused {reused} stored series ({projected} projected onto a new basis) "
            f"from {store.folder}"
        )
    share = _share_of_group(comm, samples, reduced, todo, groups)
    computed = _compute_in_groups(config, share, keys, groups, store, comm, say)
    by_index = {s.index: hit[0] for s, hit in zip(samples, found, strict=True) if hit}
    by_index.update(computed)
    say(
        f"  POD-ANM series: {len(todo)} computed by {groups.count} group(s) of "
        f"{groups.size} rank(s), {reused} reused, {time.perf_counter() - t0:.1f} s"
    )
    return [by_index[s.index] for s in samples]


def _picklable(error: Exception | None) -> Exception | None:
    """``error`` if it can be sent to the other ranks, else a RuntimeError saying what it was."""
    try:
        pickle.dumps(error)
    except Exception:  # noqa: BLE001 - any pickling failure: send its text instead
        return RuntimeError(f"{type(error).__name__}: {error}")
    return error


def _compute_in_groups(config, share, keys, groups, store, comm, say) -> dict:
    """Every group's series, on every rank. An exception in any group is raised on every
    rank (the lowest rank's), once every group has finished its share: no rank is left
    waiting in a collective call."""
    log = SeriesLog(comm, groups.count, say)
    computed, error = {}, None
    try:
        computed = compute_share(config, share, keys, groups, store, log)
    except Exception as exc:  # noqa: BLE001 - raised on every rank below
        error = exc
    finally:
        log.close(groups.comm)
    errors = [e for e in comm.allgather(_picklable(error)) if e is not None]
    if errors:
        raise errors[0]
    merged = {}
    for part in comm.allgather(computed if groups.comm.rank == 0 else {}):
        merged.update(part)
    return merged
