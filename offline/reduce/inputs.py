"""What the reduction reads: the campaign's configuration, its samples, the operators' rows
and the rendering surface.

The snapshot matrix is distributed by canonical rows (:func:`owned_canonical_rows`);
each rank reads only its rows of the stored snapshots and operators.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import scipy.sparse
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.fe.dofs import owned_canonical_rows
from hapticrom.offline.mpi import on_rank_zero
from hapticrom.shared.errors import InputError


def campaign_config(
    store: SnapshotStore, manifest: dict, reduction: CampaignConfig | None
) -> CampaignConfig:
    """The stored campaign's configuration, with ``reduction``'s ``[anm]`` and ``[cutting]``
    tables if given (they do not change the solves; InputError if it describes another
    campaign), and the mesh file the campaign ran on."""
    config = CampaignConfig.from_dict(manifest["campaign"], source=str(store.manifest_path))
    if reduction is not None:
        if reduction.campaign_hash() != manifest["campaign_hash"]:
            raise InputError(
                f"{store.root} holds another campaign than the configuration given (its "
                "solves, material, mesh or positions differ)"
            )
        config = replace(config, anm=reduction.anm, cutting=reduction.cutting)
    # The campaign's relative mesh path was resolved when it ran; use that file.
    mesh = replace(config.problem.mesh, file=Path(manifest["mesh"]["file"]))
    return replace(config, problem=replace(config.problem, mesh=mesh))


# -- the samples ---------------------------------------------------------------------
@dataclass
class Sample:
    """One solved position: this rank's rows of its nominal-step snapshots."""

    index: int
    u_local: np.ndarray  # (rows, K - 1) displacement snapshots, mm
    p_local: np.ndarray | None  # (cell rows, K - 1) pressure snapshots, MPa
    contact_nodes: np.ndarray
    depth: np.ndarray  # (K,) indentation along the push direction, mm, depth[0] = 0
    force: np.ndarray  # (K,) normal reaction on the tool, N, force[0] = 0
    point: np.ndarray
    direction: np.ndarray  # unit push direction (into the tissue)
    load_local: np.ndarray | None = None  # force control: this rank's rows of the load, N


@dataclass
class Layout:
    """How the stored arrays are split over the ranks: this rank's canonical DOF rows and
    pressure cell rows, [start, stop), and the global sizes."""

    rows: tuple[int, int]
    cell_rows: tuple[int, int]
    num_dofs: int
    num_cells: int  # 0: no element-wise pressure


def _verify_all(store: SnapshotStore, indices: list[int]) -> list[int]:
    """Rank 0: check every record's checksums; return the solved positions."""
    solved = []
    for index in indices:
        _, attrs = store.read_position(index)  # raises on a damaged file
        if attrs["status"] == "solved":
            solved.append(index)
    store.read_operators()
    return solved


def nominal_steps(load_factor: np.ndarray, steps: int, index: int) -> np.ndarray:
    """Rows of the records at load factors k/steps (extra sub-steps from cuts are skipped)."""
    rows = []
    for k in range(1, steps + 1):
        hit = np.flatnonzero(np.abs(load_factor - k / steps) < 1e-9)
        if hit.size == 0:
            raise InputError(f"position {index}: no converged state at load factor {k}/{steps}")
        rows.append(hit[0])
    return np.asarray(rows)


def solved_positions(store: SnapshotStore, manifest: dict, comm: MPI.Comm) -> list[int]:
    """The positions solved successfully, once every record is stored and intact (collective)."""
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
    return solved


def layout(store: SnapshotStore, comm: MPI.Comm) -> Layout:
    """This rank's share of the stored operators' rows (collective)."""
    with h5py.File(store.operators_path, "r") as f:
        num_dofs = int(f.attrs["num_dofs"])
        num_cells = int(f["Kpp_diagonal"].shape[0]) if "Kpp_diagonal" in f else 0
    rows = owned_canonical_rows(comm, num_dofs)
    cell_rows = owned_canonical_rows(comm, num_cells)
    return Layout(rows, cell_rows, num_dofs, num_cells)


def read_sample(store: SnapshotStore, index: int, steps: int, layout: Layout) -> Sample:
    """This rank's rows of position ``index``'s snapshots at the nominal load steps."""
    (r0, r1), (c0, c1) = layout.rows, layout.cell_rows
    with h5py.File(store.position_path(index), "r") as f:
        take = nominal_steps(f["load_factor"][()], steps, index)
        u = np.ascontiguousarray(f["displacement"][:, r0:r1][take].T)
        p = None
        if layout.num_cells and "pressure" in f:
            p = np.ascontiguousarray(f["pressure"][:, c0:c1][take].T)
        direction = np.asarray(f.attrs["direction"], dtype=float)
        depth = np.r_[0.0, f["contact_displacement"][()][take] @ direction]
        force = np.r_[0.0, f["force"][()][take] @ direction]
        load = f["load_vector"][r0:r1] if "load_vector" in f else None
        return Sample(index, u, p, f["contact_nodes"][()], depth, force,
                      np.asarray(f.attrs["point"]), direction, load)  # fmt: skip


def read_samples(
    store: SnapshotStore, manifest: dict, config: CampaignConfig, comm: MPI.Comm
) -> tuple[list[Sample], Layout]:
    """Every solved sample (this rank's rows) and the row layout (collective)."""
    solved = solved_positions(store, manifest, comm)
    rows = layout(store, comm)
    return [read_sample(store, index, config.load.steps, rows) for index in solved], rows


class OperatorRows:
    """This rank's rows of the stored operators (canonical CSR row blocks)."""

    def __init__(self, store: SnapshotStore, layout: Layout):
        rows, cell_rows = layout.rows, layout.cell_rows
        with h5py.File(store.operators_path, "r") as f:
            self.mixed = "Kuu/data" in f
            self.K = self._csr(f, "Kuu" if self.mixed else "K0", *rows)
            self.Kup = self._csr(f, "Kup", *rows) if self.mixed else None
            self.kpp = f["Kpp_diagonal"][cell_rows[0] : cell_rows[1]] if self.mixed else None
            self.volumes = f["volumes"][rows[0] : rows[1]]
            self.node_coordinates = f["node_coordinates"][()]

    @staticmethod
    def _csr(f, name, start, stop):
        indptr = f[f"{name}/indptr"][start : stop + 1]
        lo, hi = indptr[0], indptr[-1]
        return scipy.sparse.csr_matrix(
            (f[f"{name}/data"][lo:hi], f[f"{name}/indices"][lo:hi], indptr - lo),
            shape=(stop - start, int(f[f"{name}/shape"][1])),
        )


# -- the rendering surface ----------------------------------------------------------------
@dataclass
class RenderSurface:
    """Every boundary face of the organ as triangles, for rendering.

    ``vertices`` (V, 3) mm; ``triangles`` (T, 3) int32; ``nodes`` (V,) int64 canonical
    node of each vertex; ``groups`` (T,) 0 clamped, 1 loadable, 2 free.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    nodes: np.ndarray
    groups: np.ndarray

    @property
    def dofs(self) -> np.ndarray:
        """The canonical DOFs of the vertices, 3 per vertex (x, y, z)."""
        return (3 * self.nodes[:, None] + np.arange(3)).ravel()


def surface_mesh(mesh_file: Path, node_coordinates: np.ndarray) -> RenderSurface:
    """Rendering surface: every boundary face (quads split), vertex -> canonical node."""
    faces, groups, tags, coords = [], [], [], []
    for g, name in enumerate(("clamped", "loadable", "free")):
        try:
            s = read_surface(mesh_file, name)
        except InputError:
            if name == "free":
                continue
            raise
        tags.append(s.node_tags)
        coords.append(s.nodes)
        f = s.node_tags[s.faces]  # faces as node tags
        if f.shape[1] == 4:  # split each quad along its 0-2 diagonal
            f = np.vstack([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
        faces.append(f)
        groups.append(np.full(len(f), g))
    all_tags, first = np.unique(np.concatenate(tags), return_index=True)
    vertices = np.concatenate(coords)[first]
    triangles = np.searchsorted(all_tags, np.concatenate(faces))
    nodes = all_tags - 1  # gmsh tag t is input node t - 1, canonical node t - 1 (vertices first)
    if not np.allclose(node_coordinates[nodes], vertices, rtol=0, atol=1e-9):
        raise RuntimeError("surface vertices do not match the canonical node coordinates")
    return RenderSurface(
        vertices, triangles.astype(np.int32), nodes.astype(np.int64), np.concatenate(groups)
    )
