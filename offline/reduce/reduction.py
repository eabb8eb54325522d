"""From a campaign's snapshots to the reduced-model artifact (thesis §2.2-2.3).

For every solved tool position (a *sample*):

- POD of its displacement snapshots (the nominal load steps) gives a basis A
  (N x n; n is the same for every sample: the largest count the truncation
  rule asks for), and the reduced coordinates c_k = A^T u_k of each state;
- POD of its element-wise pressure snapshots gives a small pressure basis P
  (n_p <= ceil(n/2) modes), and the reduced stiffness with a reduced pressure,

      K_r = A^T K_uu A - (A^T K_up P) (P^T K_pp P)^-1 (P^T K_pu A).

  Condensing the element-wise pressure first (K0 = K_uu - K_up K_pp^-1 K_pu,
  then A^T K0 A) makes the reduced model lock: POD modes of nearly
  incompressible finite-strain states violate the linearised element-wise
  constraint at second order, and kappa/mu = 2e6 turns that into a 13-20x too
  stiff contact (measured on the cornea). A few reduced pressure modes enforce
  incompressibility only where the snapshots do. K_r then reproduces the full
  linear model's contact stiffness at the samples (test).
- the contact force curve (normal reaction on the tool against indentation
  depth) with monotone-cubic slopes, and the mean basis rows at its contact nodes.

Plus a global POD over all samples (spectra reported; its reduced stiffness
stored), the surface mesh for rendering, a 2-D chart of the sample positions
with its Delaunay triangulation (the neighbourhood structure for
interpolation), and the tangent vectors for Grassmann interpolation. The
snapshot matrix is distributed by canonical rows; each rank reads only its rows.
"""

from __future__ import annotations

import datetime
import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import scipy.sparse
from mpi4py import MPI

from hapticrom import __version__
from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.run import CampaignConfig, campaign_sanity
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.fe.dofs import owned_canonical_rows
from hapticrom.offline.fe.sanity import dumps
from hapticrom.offline.mpi import on_rank_zero, print0
from hapticrom.offline.reduce.pod import PODResult, Truncation, pod
from hapticrom.shared.artifact import write_artifact
from hapticrom.shared.errors import HapticromError, InputError


# -- reading the store -------------------------------------------------------------
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


def _verify_all(store: SnapshotStore, indices: list[int]) -> list[int]:
    """Rank 0: check every record's checksums; return the solved positions."""
    solved = []
    for index in indices:
        _, attrs = store.read_position(index)  # raises on a damaged file
        if attrs["status"] == "solved":
            solved.append(index)
    store.read_operators()
    return solved


def _nominal_steps(load_factor: np.ndarray, steps: int, index: int) -> np.ndarray:
    """Rows of the records at load factors k/steps (extra sub-steps from cuts are skipped)."""
    rows = []
    for k in range(1, steps + 1):
        hit = np.flatnonzero(np.abs(load_factor - k / steps) < 1e-9)
        if hit.size == 0:
            raise InputError(f"position {index}: no converged state at load factor {k}/{steps}")
        rows.append(hit[0])
    return np.asarray(rows)


def read_samples(store: SnapshotStore, config: CampaignConfig, comm: MPI.Comm):
    manifest = on_rank_zero(comm, store.manifest)
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
        num_cells = int(f["Kpp_diagonal"].shape[0]) if "Kpp_diagonal" in f else 0
    rows = owned_canonical_rows(comm, num_dofs)
    cell_rows = owned_canonical_rows(comm, num_cells)
    samples = []
    for index in solved:
        with h5py.File(store.position_path(index), "r") as f:
            take = _nominal_steps(f["load_factor"][()], config.load.steps, index)
            u = np.ascontiguousarray(f["displacement"][:, rows[0] : rows[1]][take].T)
            p = None
            if num_cells and "pressure" in f:
                p = np.ascontiguousarray(f["pressure"][:, cell_rows[0] : cell_rows[1]][take].T)
            direction = np.asarray(f.attrs["direction"], dtype=float)
            depth = np.r_[0.0, f["contact_displacement"][()][take] @ direction]
            force = np.r_[0.0, f["force"][()][take] @ direction]
            load = f["load_vector"][rows[0] : rows[1]] if "load_vector" in f else None
            samples.append(
                Sample(index, u, p, f["contact_nodes"][()], depth, force,
                       np.asarray(f.attrs["point"]), direction, load)
            )  # fmt: skip
    return samples, rows, cell_rows, num_dofs


class OperatorRows:
    """This rank's rows of the stored operators (canonical CSR row blocks)."""

    def __init__(self, store: SnapshotStore, rows, cell_rows):
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


# -- reduced operators --------------------------------------------------------------
def _allgather_rows(comm: MPI.Comm, local: np.ndarray) -> np.ndarray:
    return np.concatenate(comm.allgather(local), axis=0)


def _sum(comm, a):
    return comm.allreduce(np.asarray(a), op=MPI.SUM)


def reduced_blocks(comm, ops: OperatorRows, A_local, P_local=None):
    """(A^T K A (N/mm), A^T K_up P (mm^2), P^T K_pp P (mm^3/MPa)); the last two are None
    for a displacement-only element or without a pressure basis P. K is K_uu if mixed."""
    A = _allgather_rows(comm, A_local)
    K_r = _sum(comm, A_local.T @ (ops.K @ A))
    if not (ops.mixed and P_local is not None):
        return (K_r + K_r.T) / 2, None, None
    P = _allgather_rows(comm, P_local)
    B = _sum(comm, A_local.T @ (ops.Kup @ P))
    Kpp = _sum(comm, P_local.T @ (ops.kpp[:, None] * P_local))  # < 0
    return (K_r + K_r.T) / 2, B, (Kpp + Kpp.T) / 2


def reduced_stiffness(comm, ops: OperatorRows, A_local, P_local=None) -> np.ndarray:
    """A^T K A, with the pressure reduced to the basis P when the element has one (N/mm)."""
    return condense_reduced_pressure(*reduced_blocks(comm, ops, A_local, P_local))


def condense_reduced_pressure(K_r, B, Kpp) -> np.ndarray:
    """K_r - B Kpp^-1 B^T (K_r itself without a pressure basis), symmetrised."""
    if B is not None:
        K_r = K_r - B @ np.linalg.solve(Kpp, B.T)
    return (K_r + K_r.T) / 2


def _pod_fixed(Q_local, comm, weights, n, method):
    """The first n POD modes (fewer only if the snapshots have fewer nonzero ones)."""
    return pod(Q_local, comm, weights, Truncation(eigenvalue_ratio=None, max_modes=n), method)


@dataclass
class ReducedSample:
    index: int
    pod: PODResult
    basis_local: np.ndarray  # (rows, n)
    coefficients: np.ndarray  # (K, n)
    reduced_stiffness: np.ndarray  # (n, n)
    contact_rows: np.ndarray  # (3, n)
    pressure_modes: int


def _contact_rows(comm, A_local, rows, nodes) -> np.ndarray:
    """Mean of the basis rows (3 x n) over the contact nodes, from the distributed rows."""
    dofs = (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()
    mine = dofs[(dofs >= rows[0]) & (dofs < rows[1])] - rows[0]
    local = A_local[mine].reshape(-1, 3, A_local.shape[1]).sum(axis=0) if mine.size else 0.0
    return _sum(comm, np.zeros((3, A_local.shape[1])) + local) / len(nodes)


def reduce_samples(comm, samples, ops, rows, truncation, weights, method):
    # One n for all samples (interpolation needs equal dimensions): the largest count.
    first = [pod(s.u_local, comm, weights, truncation, method) for s in samples]
    n = max(r.n_modes for r in first)
    reduced = []
    for s, r in zip(samples, first, strict=True):
        full = r if r.n_modes == n else _pod_fixed(s.u_local, comm, weights, n, method)
        A_local = full.basis_local[:, :n]
        W = weights[:, None] if weights is not None else 1.0
        coefficients = _sum(comm, (W * A_local).T @ s.u_local).T  # (K - 1, n)
        P_local, n_p = None, 0
        if s.p_local is not None:
            pr = pod(s.p_local, comm, None, Truncation(eigenvalue_ratio=1e-8), method)
            n_p = max(1, min(pr.n_modes, math.ceil(n / 2)))
            P_local = pr.basis_local[:, :n_p]
        reduced.append(
            ReducedSample(
                index=s.index,
                pod=r,
                basis_local=A_local,
                coefficients=np.vstack([np.zeros((1, n)), coefficients]),
                reduced_stiffness=reduced_stiffness(comm, ops, A_local, P_local),
                contact_rows=_contact_rows(comm, A_local, rows, s.contact_nodes),
                pressure_modes=n_p,
            )
        )
    return reduced, n


# -- Grassmann tangents -------------------------------------------------------------
def grassmann_tangents(comm, reduced: list[ReducedSample], reference: int):
    """Log-map tangent vectors Gamma_i at the reference basis, and the small Gram matrices.

    Gamma_i = U atan(S) V^T with U S V^T the SVD of (I - A0 A0^T) A_i (A0^T A_i)^-1
    (thesis §2.3.1), computed from distributed rows through n x n Gram matrices.
    """
    A0 = reduced[reference].basis_local
    tangents = []
    for r in reduced:
        M = _sum(comm, A0.T @ r.basis_local)  # A0^T A_i
        X = (r.basis_local - A0 @ M) @ np.linalg.inv(M)
        lam, V = np.linalg.eigh(_sum(comm, X.T @ X))  # X^T X = V S^2 V^T
        s = np.sqrt(np.clip(lam, 0.0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(s > 1e-14, np.arctan(s) / s, 1.0)  # atan(S) S^-1 -> 1 as S -> 0
        tangents.append(X @ (V * scale) @ V.T)  # U atan(S) V^T = X V S^-1 atan(S) V^T
    P = len(reduced)
    n = A0.shape[1]
    gtt = np.zeros((P, P, n, n))
    gtb = np.zeros((P, P, n, n))
    grb = np.zeros((P, n, n))
    for i in range(P):
        grb[i] = _sum(comm, A0.T @ reduced[i].basis_local)
        for j in range(P):
            gtt[i, j] = _sum(comm, tangents[i].T @ tangents[j])
            gtb[i, j] = _sum(comm, tangents[i].T @ reduced[j].basis_local)
    return tangents, gtt, gtb, grb


# -- surface and chart --------------------------------------------------------------
def surface_mesh(mesh_file: Path, node_coordinates: np.ndarray):
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
    return vertices, triangles.astype(np.int32), nodes.astype(np.int64), np.concatenate(groups)


def chart_and_triangulation(points: np.ndarray, normals: np.ndarray):
    """A plane through the samples (normal = their mean normal) and its Delaunay triangles."""
    from scipy.spatial import Delaunay

    origin = points.mean(axis=0)
    n = normals.mean(axis=0)
    n /= np.linalg.norm(n)
    t1 = np.eye(3)[np.argmin(np.abs(n))]
    t1 -= (t1 @ n) * n
    t1 /= np.linalg.norm(t1)
    axes = np.vstack([t1, np.cross(n, t1)])
    chart = (points - origin) @ axes.T
    if len(points) < 3:
        raise InputError("the artifact needs at least 3 tool positions (a triangle) to interpolate")
    triangles = Delaunay(chart).simplices.astype(np.int32)
    return origin, axes, chart, triangles


def monotone_slopes(depth: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Slopes (N/mm) of the monotone piecewise-cubic Hermite interpolant (Fritsch-Carlson)."""
    from scipy.interpolate import PchipInterpolator

    return PchipInterpolator(depth, force).derivative()(depth)


# -- the whole reduction --------------------------------------------------------------
def reduce_campaign(
    campaign_dir: str | Path,
    out: str | Path,
    comm: MPI.Comm = MPI.COMM_WORLD,
    verbose: bool = True,
    reduction: CampaignConfig | None = None,
) -> dict:
    """POD per sample and global, reduced operators, the artifact; returns a summary.

    ``reduction``: a campaign configuration whose ``[anm]`` and ``[cutting]`` tables
    replace the stored ones (they do not change the solves, so a campaign can be
    reduced again with other options); it must describe the same campaign.
    """
    say = (lambda s: print0(comm, s)) if verbose else (lambda s: None)
    t0 = time.perf_counter()
    store = SnapshotStore(campaign_dir)
    manifest = on_rank_zero(comm, store.manifest)
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
    config = replace(config, problem=replace(config.problem, mesh=mesh))
    samples, rows, cell_rows, num_dofs = read_samples(store, config, comm)
    ops = OperatorRows(store, rows, cell_rows)
    weights = ops.volumes if config.pod.inner_product == "volume" else None
    truncation = Truncation(config.pod.eigenvalue_ratio, config.pod.energy, config.pod.max_modes)
    method = config.pod.method
    say(
        f"reducing '{config.name}': {len(samples)} samples, {num_dofs} DOFs, POD by {method} "
        f"({config.pod.inner_product} inner product), {comm.size} rank(s)"
    )
    reduced, n = reduce_samples(comm, samples, ops, rows, truncation, weights, method)
    Q = np.hstack([s.u_local for s in samples])
    global_pod = pod(Q, comm, weights, truncation, method)
    global_P = None
    if ops.mixed:
        Qp = np.hstack([s.p_local for s in samples])
        gp = pod(Qp, comm, None, Truncation(eigenvalue_ratio=1e-8), method)
        global_P = gp.basis_local[:, : max(1, min(gp.n_modes, math.ceil(global_pod.n_modes / 2)))]
    global_blocks = reduced_blocks(comm, ops, global_pod.basis_local, global_P)
    global_K = condense_reduced_pressure(*global_blocks)

    series = None
    if config.anm.enabled:
        from hapticrom.offline.reduce.anm_reduction import sample_series

        anm = config.anm
        say(f"POD-ANM series per sample (order {anm.order}, tolerance {anm.tolerance:g})")
        series = sample_series(config, samples, reduced, comm, say)
    cut_stiffness = cut_pressure = None
    if config.cutting is not None:
        from hapticrom.offline.cutting.export import condensed_reduced_stiffness

        K_uu, K_up, K_pp = global_blocks
        cut_stiffness = condensed_reduced_stiffness(comm, ops, global_pod.basis_local, K_uu)
        if global_P is not None:  # the coupling keeps the reduced pressure (ARTIFACT.md)
            cut_pressure = {
                "pressure_modes": _allgather_rows(comm, global_P),
                "reduced_displacement_stiffness": K_uu,
                "reduced_pressure_coupling": K_up,
                "reduced_pressure_stiffness": K_pp,
            }
    points = np.array([s.point for s in samples])
    normals = -np.array([s.direction for s in samples])  # outward: against the push
    origin, axes, chart, triangles = chart_and_triangulation(points, normals)
    reference = int(np.argmin(np.linalg.norm(chart, axis=1)))  # the most central sample
    tangents, gtt, gtb, grb = grassmann_tangents(comm, reduced, reference)
    bases = [_allgather_rows(comm, r.basis_local) for r in reduced]
    tangent_full = [_allgather_rows(comm, t) for t in tangents]
    global_basis = _allgather_rows(comm, global_pod.basis_local)
    summary = error = None
    if comm.rank == 0:
        vertices, surface_triangles, nodes, groups = surface_mesh(
            config.problem.mesh.file, ops.node_coordinates
        )
        surface_dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        depth_grid, forces, slopes, coefficients = _common_grid(samples, reduced)
        content = {
            "model": {
                "attrs": {
                    "name": config.name,
                    "mode": config.load.mode,
                    "contact_radius": config.load.contact_radius,
                    "surface_group": config.load.surface,
                    "material": _material(config),
                    "campaign_hash": manifest["campaign_hash"],
                    "mesh_file": manifest["mesh"]["file"],
                    "mesh_sha256": manifest["mesh"]["sha256"],
                    "element": config.problem.discretisation.element,
                    "modes": n,
                    "pod_method": method,
                    "pod_inner_product": config.pod.inner_product,
                }
            },
            "surface": {
                "vertices": vertices,
                "triangles": surface_triangles,
                "nodes": nodes,
                "groups": groups.astype(np.int8),
            },
            "samples": {
                "points": points,
                "normals": normals,
                "chart_origin": origin,
                "chart_axes": axes,
                "chart_points": chart,
                "triangles": triangles,
                "depth": depth_grid,
                "force": forces,
                "stiffness": slopes,
                "surface_basis": np.array([A[surface_dofs] for A in bases], dtype=np.float32),
                "coefficients": coefficients,
                "reduced_stiffness": np.array([r.reduced_stiffness for r in reduced]),
                "contact_rows": np.array([r.contact_rows for r in reduced]),
                "eigenvalues": np.array(
                    [r.pod.eigenvalues[: len(depth_grid) - 1] for r in reduced]
                ),
                "attrs": {"pressure_modes": [r.pressure_modes for r in reduced]},
            },
            "grassmann": {
                "reference": np.int64(reference),
                "tangent_surface": np.array(
                    [T[surface_dofs] for T in tangent_full], dtype=np.float32
                ),
                "gram_tangent_tangent": gtt,
                "gram_tangent_basis": gtb,
                "gram_reference_basis": grb,
            },
            "global": {
                "surface_basis": global_basis[surface_dofs].astype(np.float32),
                "eigenvalues": global_pod.eigenvalues,
                "reduced_stiffness": global_K,
            },
        }
        if series is not None:
            from hapticrom.offline.reduce.anm_reduction import artifact_group

            content["anm"] = artifact_group(series, config)
        if cut_stiffness is not None:
            from hapticrom.offline.cutting.export import cutting_group

            content["cutting"] = cutting_group(
                config, config.cutting, global_basis, cut_stiffness, cut_pressure
            )
        root = {
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "software": json.dumps(_software()),
            "units": json.dumps({"length": "mm", "force": "N", "stiffness": "N/mm"}),
            "campaign": json.dumps(manifest["campaign"], default=str),
            "description": f"contact ROM of campaign '{config.name}'",
            "sanity": dumps(campaign_sanity(store)),  # physics sanity (offline/fe/sanity.py)
        }
        error = _write_model(out, content, root)
    if comm.rank == 0 and error is None:
        summary = {
            "samples": len(samples),
            "modes": n,
            "pressure_modes": [r.pressure_modes for r in reduced],
            "global_modes": global_pod.n_modes,
            "global_eigenvalues": global_pod.eigenvalues.tolist(),
            "sample_eigenvalues": {r.index: r.pod.eigenvalues.tolist() for r in reduced},
            "seconds": time.perf_counter() - t0,
            "bytes": Path(out).stat().st_size,
        }
        if verbose:
            _print_spectra(reduced, global_pod)
            print(
                f"wrote {out} ({summary['bytes'] / 1e6:.1f} MB; {len(samples)} samples x {n} "
                f"modes, {len(vertices)} surface vertices) in {summary['seconds']:.1f} s",
                flush=True,
            )
    summary, error = comm.bcast((summary, error), root=0)
    if error is not None:
        raise error
    return summary


def _write_model(out: str | Path, content: dict, root: dict) -> HapticromError | None:
    """Write the artifact (``write_artifact`` leaves nothing behind when it fails, e.g. on a
    full disk). The error is returned, not raised, so that rank 0 can hand it to the others.
    """
    try:
        write_artifact(out, content, root)
    except HapticromError as exc:
        return exc
    return None


def _common_grid(samples: list[Sample], reduced: list[ReducedSample]):
    """Force curves and reduced coordinates on one uniform depth grid.

    Under displacement control every sample's grid is already this one; under
    force control each sample reached its own depths and is resampled
    (monotone cubic for the force, linear for the coordinates).
    """
    from scipy.interpolate import PchipInterpolator

    K = len(samples[0].depth)
    top = min(s.depth[-1] for s in samples)
    grid = np.linspace(0.0, top, K)
    forces = np.array([PchipInterpolator(s.depth, s.force)(grid) for s in samples])
    slopes = np.array([monotone_slopes(grid, f) for f in forces])
    coefficients = np.array(
        [
            np.column_stack([np.interp(grid, s.depth, c) for c in r.coefficients.T])
            for s, r in zip(samples, reduced, strict=True)
        ]
    )
    return grid, forces, slopes, coefficients


def _material(config) -> dict:
    """The law and every parameter it used, defaults included (MPa or dimensionless)."""
    from hapticrom.offline.fe.materials import make_law

    material = config.problem.material
    law = make_law(material.law, **material.params)
    extra = {k: v for k, v in material.params.items() if isinstance(v, bool)}
    return {"law": law.name, **law.parameters(), **extra}


def _software() -> dict:
    versions = {"hapticrom": __version__}
    for module in ("dolfinx", "petsc4py", "slepc4py", "numpy", "h5py"):
        try:
            versions[module] = __import__(module).__version__
        except (ImportError, AttributeError):
            continue
    return versions


def _print_spectra(reduced, global_pod) -> None:
    def spectrum(values, count=8):
        return " ".join(f"{v:.3g}" for v in values[:count])

    for r in reduced:
        print(f"  sample {r.index:3d}: eigenvalues {spectrum(r.pod.eigenvalues)}")
    g = global_pod
    head = spectrum(g.eigenvalues, 12)
    print(f"  global: {g.n_modes} modes of {len(g.eigenvalues)}; eigenvalues {head}")
