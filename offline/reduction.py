"""From a campaign's snapshots to reduced bases and reduced operators (thesis §2.2-2.3).

For every solved tool position (PODI, thesis §2.3.2) and for the whole
campaign (one global basis), the POD of the displacement snapshots gives a
basis A (N x n); the reduced operators are

    K_r = A^T K0 A   (n x n, N/mm),   f_r = A^T f   (n, N; force control),

and the contact rows of A (the rows of the DOFs the tool moves). The snapshot
matrix is distributed by canonical rows over the ranks; each rank reads only
its rows from the store.

Until the artifact issue lands, the export is a plain HDF5 file (format
``hapticrom-reduced-draft``); its layout is in :func:`write_reduced`.
"""

from __future__ import annotations

import datetime
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import scipy.sparse
from mpi4py import MPI

from hapticrom import __version__
from hapticrom.offline.campaign import CampaignConfig
from hapticrom.offline.dofs import owned_canonical_rows
from hapticrom.offline.mpi import on_rank_zero, print0
from hapticrom.offline.pod import PODResult, Truncation, pod
from hapticrom.offline.store import SnapshotStore, write_h5
from hapticrom.shared.errors import InputError

DRAFT_FORMAT = "hapticrom-reduced-draft"


@dataclass
class ReducedBasis:
    """A POD basis (this rank's rows) and its reduced operators (replicated)."""

    pod: PODResult
    K_r: np.ndarray  # (n, n) N/mm
    f_r: np.ndarray | None  # (P, n) N: A^T f for every position's load vector (force control)
    contact_rows: dict[int, np.ndarray]  # position -> (3 c, n) rows of A at its contact DOFs


@dataclass
class Snapshots:
    """This rank's rows [start, stop) of every solved position's snapshots."""

    start: int
    stop: int
    num_dofs: int
    positions: list[int]
    local: dict[int, np.ndarray]  # position -> (stop - start, steps)
    contact_nodes: dict[int, np.ndarray]
    load_vectors: dict[int, np.ndarray]  # position -> (stop - start,) rows of f
    records: dict[int, dict]  # position -> small per-step data (rank 0 only)


def _verify_all(store: SnapshotStore, indices: list[int]) -> list[int]:
    """Rank 0: check every record's checksums; return the solved positions."""
    solved = []
    for index in indices:
        _, attrs = store.read_position(index)  # raises on a damaged file
        if attrs["status"] == "solved":
            solved.append(index)
    store.read_operators()
    return solved


def read_snapshots(store: SnapshotStore, comm: MPI.Comm) -> Snapshots:
    manifest = store.manifest()
    indices = [p["index"] for p in manifest["positions"]]
    missing = sorted(set(indices) - set(on_rank_zero(comm, store.completed)))
    if missing:
        raise InputError(
            f"{store.root}: {len(missing)} position(s) not solved yet ({missing[:5]}...); "
            "run the campaign to completion first (it resumes where it stopped)"
        )
    solved = on_rank_zero(comm, _verify_all, store, indices)
    if not solved:
        raise InputError(f"{store.root}: no position was solved successfully")
    with h5py.File(store.operators_path, "r") as f:
        num_dofs = int(f.attrs["num_dofs"])
    start, stop = owned_canonical_rows(comm, num_dofs)
    local, contact, loads, records = {}, {}, {}, {}
    for index in solved:
        with h5py.File(store.position_path(index), "r") as f:
            local[index] = np.ascontiguousarray(f["displacement"][:, start:stop].T)
            contact[index] = f["contact_nodes"][()]
            if "load_vector" in f:
                loads[index] = f["load_vector"][start:stop]
            if comm.rank == 0:
                records[index] = {
                    k: f[k][()] for k in ("load_factor", "force", "contact_displacement")
                }
                records[index]["point"] = f.attrs["point"]
                records[index]["direction"] = f.attrs["direction"]
    return Snapshots(start, stop, num_dofs, solved, local, contact, loads, records)


def _read_operator_rows(store: SnapshotStore, start: int, stop: int):
    """Rows [start, stop) of K0 (CSR, all columns) and of the volume weights."""
    with h5py.File(store.operators_path, "r") as f:
        indptr = f["K0/indptr"][start : stop + 1]
        lo, hi = indptr[0], indptr[-1]
        K_rows = scipy.sparse.csr_matrix(
            (f["K0/data"][lo:hi], f["K0/indices"][lo:hi], indptr - lo),
            shape=(stop - start, int(f["K0/shape"][1])),
        )
        volumes = f["volumes"][start:stop]
    return K_rows, volumes


def _allgather_rows(comm: MPI.Comm, local: np.ndarray) -> np.ndarray:
    return np.concatenate(comm.allgather(local), axis=0)


def _reduce_operators(comm, result: PODResult, K_rows, snaps: Snapshots, positions) -> ReducedBasis:
    A_local = result.basis_local
    A = _allgather_rows(comm, A_local)  # N x n, small: needed for the columns of K0
    K_r = comm.allreduce(A_local.T @ (K_rows @ A), op=MPI.SUM)
    K_r = (K_r + K_r.T) / 2  # K0 is symmetric; remove rounding asymmetry
    f_r = None
    if snaps.load_vectors:
        f_r = np.array(
            [comm.allreduce(A_local.T @ snaps.load_vectors[i], op=MPI.SUM) for i in positions]
        )
    contact_rows = {}
    for i in positions:
        dofs = (3 * snaps.contact_nodes[i][:, None] + np.arange(3)).reshape(-1)
        contact_rows[i] = A[dofs]
    return ReducedBasis(result, K_r, f_r, contact_rows)


def reduce_campaign(
    campaign_dir: str | Path,
    out: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    verbose: bool = True,
) -> dict:
    """POD per position and global, reduced operators, export; returns a summary (rank 0)."""
    say = (lambda s: print0(comm, s)) if verbose else (lambda s: None)
    t0 = time.perf_counter()
    store = SnapshotStore(campaign_dir)
    manifest = on_rank_zero(comm, store.manifest)
    config = CampaignConfig.from_dict(manifest["campaign"], source=str(store.manifest_path))
    snaps = read_snapshots(store, comm)
    K_rows, volumes = _read_operator_rows(store, snaps.start, snaps.stop)
    weights = volumes if config.pod.inner_product == "volume" else None
    truncation = Truncation(
        eigenvalue_ratio=config.pod.eigenvalue_ratio,
        energy=config.pod.energy,
        max_modes=config.pod.max_modes,
    )
    say(
        f"reducing '{config.name}': {len(snaps.positions)} positions, {snaps.num_dofs} DOFs, "
        f"POD by {config.pod.method} ({config.pod.inner_product} inner product), "
        f"{comm.size} rank(s)"
    )
    per_position = {}
    for i in snaps.positions:
        result = pod(snaps.local[i], comm, weights, truncation, method=config.pod.method)
        per_position[i] = _reduce_operators(comm, result, K_rows, snaps, [i])
    Q = np.hstack([snaps.local[i] for i in snaps.positions])
    global_result = pod(Q, comm, weights, truncation, method=config.pod.method)
    global_basis = _reduce_operators(comm, global_result, K_rows, snaps, snaps.positions)
    bases = {i: _allgather_rows(comm, b.pod.basis_local) for i, b in per_position.items()}
    A_global = _allgather_rows(comm, global_result.basis_local)
    summary = None
    if comm.rank == 0:
        summary = write_reduced(
            Path(out), store, config, manifest, snaps, per_position, bases, global_basis, A_global
        )
        summary["seconds"] = time.perf_counter() - t0
        _print_spectra(config, snaps, per_position, global_basis)
        print(
            f"wrote {out} ({Path(out).stat().st_size / 1e6:.1f} MB) in {summary['seconds']:.1f} s"
        )
    return comm.bcast(summary, root=0)


def _print_spectra(config, snaps, per_position, global_basis) -> None:
    def spectrum(result: PODResult, count: int = 10) -> str:
        return " ".join(f"{v:.3g}" for v in result.eigenvalues[:count])

    for i, b in per_position.items():
        print(f"  position {i:3d}: {b.pod.n_modes} modes; eigenvalues {spectrum(b.pod)}")
    g = global_basis.pod
    print(f"  global: {g.n_modes} modes of {len(g.eigenvalues)}; eigenvalues {spectrum(g, 15)}")


def write_reduced(
    out: Path, store, config, manifest, snaps, per_position, bases, global_basis, A_global
) -> dict:
    """Write the draft reduced model (rank 0). Layout::

    /                attrs: format, version, name, campaign_hash, units, created, software
    /mesh/node_coordinates (N/3, 3) mm, /mesh/supported_nodes
    /positions/index, point, direction (P, 3)
    /positions/<i>/basis (N, n_i), eigenvalues, K_r (n_i, n_i), f_r (n_i,),
                   contact_nodes, contact_rows (3 c, n_i),
                   load_factor, force (steps, 3), contact_displacement (steps, 3)
    /global/basis (N, n), eigenvalues, K_r (n, n), f_r (P, n),
            /global/contact_rows/<i> (3 c_i, n)
    """
    operators, _ = store.read_operators()
    datasets = {
        "mesh/node_coordinates": operators["node_coordinates"],
        "mesh/supported_nodes": operators["supported_nodes"],
    }
    positions = snaps.positions
    datasets["positions/index"] = np.array(positions)
    datasets["positions/point"] = np.array([snaps.records[i]["point"] for i in positions])
    datasets["positions/direction"] = np.array([snaps.records[i]["direction"] for i in positions])
    for i in positions:
        b = per_position[i]
        g = f"positions/{i}"
        datasets[f"{g}/basis"] = bases[i]
        datasets[f"{g}/eigenvalues"] = b.pod.eigenvalues
        datasets[f"{g}/K_r"] = b.K_r
        if b.f_r is not None:
            datasets[f"{g}/f_r"] = b.f_r[0]
        datasets[f"{g}/contact_nodes"] = snaps.contact_nodes[i]
        datasets[f"{g}/contact_rows"] = b.contact_rows[i]
        for k in ("load_factor", "force", "contact_displacement"):
            datasets[f"{g}/{k}"] = snaps.records[i][k]
        datasets[f"global/contact_rows/{i}"] = global_basis.contact_rows[i]
    datasets["global/basis"] = A_global
    datasets["global/eigenvalues"] = global_basis.pod.eigenvalues
    datasets["global/K_r"] = global_basis.K_r
    if global_basis.f_r is not None:
        datasets["global/f_r"] = global_basis.f_r
    attrs = {
        "format": DRAFT_FORMAT,
        "version": 0,
        "name": config.name,
        "campaign_hash": manifest["campaign_hash"],
        "mode": config.load.mode,
        "units": "length mm, force N, stiffness N/mm",
        "pod_method": config.pod.method,
        "pod_inner_product": config.pod.inner_product,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": f"hapticrom {__version__}",
    }
    write_h5(out, datasets, attrs)
    return {
        "positions": len(positions),
        "modes": {i: per_position[i].pod.n_modes for i in positions},
        "global_modes": global_basis.pod.n_modes,
        "global_eigenvalues": global_basis.pod.eigenvalues.tolist(),
    }
