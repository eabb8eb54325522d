"""Limbal relaxing incision (thesis §4.5.1): reduced model + cut patch vs the cut meshed explicitly.

:func:`run_study` (serial) builds the intact cornea and the same cornea with
the incision meshed explicitly (:mod:`hapticrom.meshes.cut`); trains a reduced
basis on the intact organ (force-controlled soft-tip loads at positions around
the incision, as the thesis trained on point loads near where the surgeon
works); then, for a tool load at a held-out position next to the incision,
compares the displacement of

- the full-order nonlinear solve on the cut mesh (the reference),
- the reduced model coupled with the cut patch (:mod:`.cutting`, linear at K0),
- the reduced model alone, blind to the cut,

as relative L2 differences over all nodes, and writes pictures.
Units: mm, N, MPa.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hapticrom.meshes import build
from hapticrom.meshes.cut import LimbalArc, cut_mesh, limbal_arc
from hapticrom.meshes.msh import write_msh
from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.cutting.patch import couple, patch_around, relative_l2
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.fe.operators import load_vector, reference_tangent

MATERIAL = {"law": "svk", "E": 0.5, "nu": 0.45}  # thesis ch. 4: Saint Venant-Kirchhoff cornea
ANTERIOR_RADIUS = 7.8  # mm, the cornea generator's default


@dataclass
class CuttingStudy:
    """The study's settings: mesh, incision, tool load, training positions, patch."""

    refinement: str = "default"
    incision: LimbalArc = field(default_factory=lambda: LimbalArc(5.2, -30.0, 30.0, 0.7))
    force: float = 0.002  # N, soft tip, normal to the surface (about 0.04 mm: nearly linear)
    tip_radius: float = 0.5  # mm
    # Where the scalpel works: along the incision (rho mm, degrees), and a ring inside it.
    training: tuple = ((4.8, (-30, -15, 0, 15, 30)), (4.4, (-30, 0, 30)))
    test_point: tuple = (4.8, 0.0)  # rho (mm), angle (degrees)
    patch_layers: int = 3
    steps: int = 2
    # The patch also covers the tool's contact (the cells within its radius): the
    # scalpel is the tool, and local DOFs under it hold a dent the basis lacks.
    patch_at_tool: bool = False


def surface_point(rho: float, degrees: float) -> list[float]:
    """The anterior surface point at distance rho from the axis, at an angle about z."""
    a = np.radians(degrees)
    z = -ANTERIOR_RADIUS + np.sqrt(ANTERIOR_RADIUS**2 - rho**2)
    return [rho * np.cos(a), rho * np.sin(a), float(z)]


def inward_normal(point) -> list[float]:
    """Unit inward normal of the anterior sphere at ``point``."""
    c = np.array([0.0, 0.0, -ANTERIOR_RADIUS])
    n = c - np.asarray(point)
    return (n / np.linalg.norm(n)).tolist()


def _config(mesh_file: Path, point, study: CuttingStudy) -> ProblemConfig:
    force = (study.force * np.asarray(inward_normal(point))).tolist()
    return ProblemConfig.from_dict({
        "mesh": {"file": str(mesh_file)},
        "material": MATERIAL,
        "load": {"mode": "force", "contact_point": point, "contact_radius": study.tip_radius,
                 "force": force, "steps": study.steps},
        "output": {"xdmf": False},
    })  # fmt: skip


def _solve(mesh_file, point, study, comm) -> tuple[list[np.ndarray], FullOrderModel]:
    fom = FullOrderModel(_config(mesh_file, point, study), comm, verbose=False)
    order = CanonicalOrder(fom.model.V)
    states = []
    fom.solve(on_step=lambda r, f, d: states.append(order.gather(fom.model.u.x.array)))
    return states, fom


def meshes(study: CuttingStudy, work: Path):
    """The intact and the cut cornea, written to ``work``: (intact, cut, origin, files)."""
    work.mkdir(parents=True, exist_ok=True)
    intact = build("cornea", study.refinement)
    cut, origin = cut_mesh(intact, limbal_arc(intact, study.incision))
    files = {}
    for name, m in (("intact", intact), ("cut", cut)):
        files[name] = write_msh(work / f"cornea-{name}.msh", m.nodes, m.cells, m.facet_groups,
                                m.sidecar())  # fmt: skip
    return intact, cut, origin, files


def tangent_and_load(mesh_file: Path, point, study: CuttingStudy, comm):
    """K0 (canonical CSR) and the tool's load vector at load factor 1 (N) on one mesh."""
    fom = FullOrderModel(_config(mesh_file, point, study), comm, verbose=False)
    order = CanonicalOrder(fom.model.V)
    fom.set_load(1.0)
    f = load_vector(fom.model, order)
    fom.set_load(0.0)
    return reference_tangent(fom.model, order), f


def supported_nodes(intact, origin) -> set:
    """Nodes of the cut mesh held by the limbus support (copies of held nodes too)."""
    held = set(np.unique(intact.facet_groups["clamped"]).tolist())
    return held | {i for i in range(len(origin)) if origin[i] in held}


def lip_nodes(origin: np.ndarray) -> np.ndarray:
    """Cut-mesh nodes that exist twice (an original and its copy): the cut's lips."""
    return np.flatnonzero(np.bincount(origin)[origin] > 1)


def linear_solve(K, f, supported: set) -> np.ndarray:
    """K u = f with the supported nodes held (the linear full-order model)."""
    import scipy.sparse.linalg

    held = (3 * np.array(sorted(supported))[:, None] + np.arange(3)).ravel()
    free = np.setdiff1d(np.arange(K.shape[0]), held)
    u = np.zeros(K.shape[0])
    u[free] = scipy.sparse.linalg.spsolve(K[free][:, free].tocsc(), f[free])
    return u


def training_basis(study: CuttingStudy, mesh_file: Path, comm) -> tuple[np.ndarray, int]:
    """The reduced basis trained on the intact organ (SVD, eigenvalues above 1e-10 of the
    first) from every state at the training positions, and the number of snapshots."""
    snapshots = []
    for rho, angles in study.training:
        for angle in angles:
            states, _ = _solve(mesh_file, surface_point(rho, angle), study, comm)
            snapshots += states
    Q = np.column_stack(snapshots)
    U, s, _ = np.linalg.svd(Q, full_matrices=False)
    n = int(np.sum(s**2 >= 1e-10 * s[0] ** 2))
    return U[:, :n], Q.shape[1]


def patch_seeds(study: CuttingStudy, cut, origin: np.ndarray, point) -> np.ndarray:
    """The nodes the patch grows from: the cut's lips (and the tool's contact, if asked)."""
    seeds = lip_nodes(origin)
    if study.patch_at_tool:
        # The cells under the tool: those with a node within its radius (or at the
        # nearest node, on a mesh coarser than the tool).
        distance = np.linalg.norm(cut.nodes - np.asarray(point), axis=1)
        under = np.union1d(np.flatnonzero(distance <= study.tip_radius), [np.argmin(distance)])
        seeds = np.union1d(seeds, cut.cells[np.any(np.isin(cut.cells, under), axis=1)])
    return seeds


def lip_pairs(intact, origin: np.ndarray) -> np.ndarray:
    """(original, copy) node pairs of the cut mesh, one row per duplicated node."""
    first_copy = len(intact.nodes)
    return np.column_stack([origin[first_copy:], np.arange(first_copy, len(origin))])


def opening(u: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """The distance (mm) between each node and its copy in the displacement ``u``."""
    v = u.reshape(-1, 3)
    return np.linalg.norm(v[pairs[:, 1]] - v[pairs[:, 0]], axis=1)


def _errors(u_ref, u_coupled, u_blind, u_linear, pairs) -> dict:
    """The relative L2 errors against the reference and the openings of the cut."""
    return {
        "error_coupled": relative_l2(u_coupled, u_ref),
        "error_blind": relative_l2(u_blind, u_ref),
        "error_linear_full_order": relative_l2(u_linear, u_ref),
        "max_opening_reference_mm": float(opening(u_ref, pairs).max()),
        "max_opening_coupled_mm": float(opening(u_coupled, pairs).max()),
        "max_displacement_mm": float(np.abs(u_ref).max()),
    }


def run_study(study: CuttingStudy, work: Path, comm=None, out: Path | None = None) -> dict:
    """The study of the module docstring (meshes in ``work``, figures in ``out``): sizes,
    errors and timings."""
    from mpi4py import MPI

    comm = comm or MPI.COMM_SELF
    timings = {}
    intact, cut, origin, files = meshes(study, work)
    t0 = time.perf_counter()
    A, snapshot_count = training_basis(study, files["intact"], comm)
    timings["training_s"] = time.perf_counter() - t0
    point = surface_point(*study.test_point)
    t0 = time.perf_counter()
    u_ref = _solve(files["cut"], point, study, comm)[0][-1]
    timings["full_order_cut_s"] = time.perf_counter() - t0
    K_cut, f_cut = tangent_and_load(files["cut"], point, study, comm)
    K_intact, _ = tangent_and_load(files["intact"], point, study, comm)
    supported = supported_nodes(intact, origin)
    t0 = time.perf_counter()
    seeds = patch_seeds(study, cut, origin, point)
    patch = patch_around(cut.cells, seeds, study.patch_layers, supported)
    coupled = couple(K_intact, K_cut, A, origin, patch)
    timings["couple_and_factorise_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    u_coupled = coupled.solve(f_cut)
    timings["coupled_solve_s"] = time.perf_counter() - t0
    u_blind = coupled.TA @ np.linalg.solve(A.T @ (K_intact @ A), coupled.TA.T @ f_cut)
    u_linear = linear_solve(K_cut, f_cut, supported)
    pairs = lip_pairs(intact, origin)
    result = {
        "refinement": study.refinement,
        "nodes": len(cut.nodes),
        "cut_faces": int(len(limbal_arc(intact, study.incision))),
        "duplicated_nodes": int(len(pairs)),
        "modes": A.shape[1],
        "snapshots": snapshot_count,
        "patch_cells": int(patch.cells.size),
        "patch_dofs": int(patch.dofs.size),
        "coupled_unknowns": coupled.size,
        **_errors(u_ref, u_coupled, u_blind, u_linear, pairs),
        "timings": timings,
    }
    if out is not None:
        figures = _figures(out, cut, u_ref, u_coupled, u_blind, pairs, point)
        result["figures"] = [str(p) for p in figures]
    return result


def draw_magnitude(fig, ax, x, triangles, u, point, half_width: float, vmax: float, title: str):
    """|u| (mm) over surface ``triangles`` seen from above, around ``point`` (mm)."""
    magnitude = np.linalg.norm(np.reshape(u, (-1, 3)), axis=1)
    t = ax.tripcolor(x[:, 0], x[:, 1], triangles, magnitude, shading="gouraud", vmin=0, vmax=vmax)
    ax.set_aspect("equal")
    ax.set_xlim(point[0] - half_width, point[0] + half_width)
    ax.set_ylim(point[1] - half_width, point[1] + half_width)
    ax.set_title(title)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    fig.colorbar(t, ax=ax, label="|u| (mm)", shrink=0.8)


def _figures(out: Path, cut, u_ref, u_coupled, u_blind, pairs, point) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    x = cut.nodes
    faces = np.vstack([cut.facet_groups["loadable"]])
    tri = np.vstack([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
    near = np.linalg.norm(x[tri].mean(axis=1)[:, :2] - np.asarray(point)[:2], axis=1) < 2.0
    fields = {"full order, cut meshed": u_ref, "reduced + cut patch": u_coupled,
              "reduced, blind to the cut": u_blind}  # fmt: skip
    vmax = max(np.linalg.norm(u.reshape(-1, 3), axis=1).max() for u in fields.values())
    fig = plt.figure(figsize=(15, 5))
    for k, (title, u) in enumerate(fields.items()):
        ax = fig.add_subplot(1, 3, k + 1)
        draw_magnitude(fig, ax, x, tri[near], u, point, 2.2, vmax, title)
        ax.plot(x[pairs[:, 1], 0], x[pairs[:, 1], 1], "k.", ms=2)
    fig.suptitle("anterior surface near the limbal incision (dots: the cut)")
    fig.tight_layout()
    p1 = out / "cut-displacement.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)

    angle = np.degrees(np.arctan2(x[pairs[:, 0], 1], x[pairs[:, 0], 0]))
    depth = ANTERIOR_RADIUS - np.linalg.norm(x[pairs[:, 0]] - [0, 0, -ANTERIOR_RADIUS], axis=1)
    top = depth < 1e-6
    fig, ax = plt.subplots(figsize=(7, 4))
    for title, u, style in (("full order, cut meshed", u_ref, "o"),
                            ("reduced + cut patch", u_coupled, "-")):  # fmt: skip
        v = u.reshape(-1, 3)
        gap = np.linalg.norm(v[pairs[top, 1]] - v[pairs[top, 0]], axis=1)
        order = np.argsort(angle[top])
        ax.plot(angle[top][order], 1e3 * gap[order], style, label=title)
    ax.set_xlabel("position along the incision (degrees about the axis)")
    ax.set_ylabel("lip separation at the surface (um)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    p2 = out / "cut-opening.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [p1, p2]
