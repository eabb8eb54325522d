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
stored), the surface mesh for rendering, the samples' triangulation on the
loadable surface (the neighbourhood structure for interpolation), and the
tangent vectors for Grassmann interpolation. The
snapshot matrix is distributed by canonical rows; each rank reads only its rows.

The reductor :func:`reduce_campaign` runs these steps in order, each in its module:

1. read the configuration and the samples (:mod:`.inputs`);
2. project the operators, per sample and global (:mod:`.operators`);
3. the POD-ANM series (:mod:`.anm_reduction`) and the cuttable region's
   operators (:mod:`hapticrom.offline.cutting.export`), when the campaign asks;
4. the samples' triangulation on the surface (:mod:`.sample_triangulation`), the
   Grassmann tangents, the common depth grid (:mod:`.interpolation`);
5. assemble the artifact (:mod:`.assemble`, the one place) and write it (rank 0).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.run import campaign_sanity
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.cutting.export import cut_operators, cut_region
from hapticrom.offline.mpi import allgather_rows, on_rank_zero, print0
from hapticrom.offline.reduce.anm_reduction import sample_series
from hapticrom.offline.reduce.assemble import ReducedModel, artifact_content, root_attributes
from hapticrom.offline.reduce.contact_fields import contact_fields
from hapticrom.offline.reduce.indicator import leave_one_out
from hapticrom.offline.reduce.inputs import (
    OperatorRows,
    campaign_config,
    read_samples,
    surface_mesh,
)
from hapticrom.offline.reduce.interpolation import (
    artifact_depth_grid,
    grassmann_tangents,
    on_common_grid,
)
from hapticrom.offline.reduce.operators import PODSettings, reduce_globally, reduce_samples
from hapticrom.offline.reduce.sample_triangulation import triangulate_samples
from hapticrom.offline.reduce.tool_stiffness import stiffness_lattice
from hapticrom.shared.artifact import write_artifact


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
    config = campaign_config(store, manifest, reduction)
    model = reduce(store, manifest, config, comm, say)
    on_rank_zero(comm, write_model, out, model, store)
    summary = on_rank_zero(comm, reduction_summary, model, out, time.perf_counter() - t0)
    if verbose and comm.rank == 0:
        print_spectra(model)
        print(
            f"wrote {out} ({summary['bytes'] / 1e6:.1f} MB; {summary['samples']} samples x "
            f"{model.modes} modes, {len(model.surface.vertices)} surface vertices) in "
            f"{summary['seconds']:.1f} s",
            flush=True,
        )
    return summary


def reduce(store: SnapshotStore, manifest: dict, config: CampaignConfig, comm, say):
    """Every step before the assembly: the ReducedModel of the campaign (collective)."""
    samples, layout = read_samples(store, manifest, config, comm)
    ops = OperatorRows(store, layout)
    settings = PODSettings.of(config.pod, ops)
    say(
        f"reducing '{config.name}': {len(samples)} samples, {layout.num_dofs} DOFs, POD by "
        f"{settings.method} ({config.pod.inner_product} inner product), {comm.size} rank(s)"
    )
    reduced, n = reduce_samples(comm, samples, ops, layout.rows, settings)
    global_reduction = reduce_globally(comm, samples, ops, settings)
    series = cut = None
    if config.anm.enabled:
        anm = config.anm
        say(f"POD-ANM series per sample (order {anm.order}, tolerance {anm.tolerance:g})")
        series = sample_series(config, samples, reduced, comm, say, store_in=store.root)
    if config.cutting is not None:
        g = global_reduction
        cut = cut_operators(comm, ops, g.pod.basis_local, g.pressure_local, g.blocks)
    surface = on_rank_zero(comm, surface_mesh, config.problem.mesh.file, ops.node_coordinates)
    neighbourhoods = on_rank_zero(comm, sample_neighbourhoods, samples, surface)
    grassmann = grassmann_tangents(comm, reduced, neighbourhoods.reference)
    grid = artifact_depth_grid(samples, reduced)
    where = neighbourhoods
    tool_stiffness = at_samples = None
    if config.load.mode == "force":  # the depth the campaign measures is the linear solve's
        tool_stiffness, at_samples = on_rank_zero(comm, stiffness_lattice, config, store, where,
                                                  surface, say=say)  # fmt: skip
    fields = on_rank_zero(comm, contact_fields, config, store, surface, where.points,
                          where.normals, say=say)  # fmt: skip
    # on the depths every sample reached, as the greedy trainer's (not the continued tails)
    _, common_force = on_common_grid([s.depth for s in samples], [s.force for s in samples])
    indicator = on_rank_zero(comm, leave_one_out, where.points, where.normals, surface,
                             common_force, at_samples)  # fmt: skip
    return ReducedModel(
        config=config,
        manifest=manifest,
        samples=samples,
        reduced=reduced,
        modes=n,
        global_reduction=global_reduction,
        neighbourhoods=neighbourhoods,
        grassmann=grassmann,
        grid=grid,
        indicator=indicator,
        surface=surface,
        sample_bases=[allgather_rows(comm, r.basis_local) for r in reduced],
        tangents=[allgather_rows(comm, t) for t in grassmann.tangents_local],
        global_basis=allgather_rows(comm, global_reduction.pod.basis_local),
        series=series,
        cut=cut,
        tool_stiffness=tool_stiffness,
        contact_fields=fields,
    )


def sample_neighbourhoods(samples, surface):
    """The samples' triangulation on the loadable surface (the runtime's neighbourhoods)."""
    points = np.array([s.point for s in samples])
    normals = -np.array([s.direction for s in samples])  # outward: against the push
    return triangulate_samples(points, normals, surface.vertices, surface.triangles, surface.groups)


def write_model(out: str | Path, model: ReducedModel, store: SnapshotStore) -> None:
    """Rank 0: the cuttable region's element matrices, the assembly, the file.

    ``write_artifact`` leaves nothing behind when it fails (e.g. on a full disk).
    """
    config = model.config
    region = None
    if model.cut is not None:
        region = cut_region(config.problem, config.cutting)
    sanity = campaign_sanity(store)
    write_artifact(
        out, artifact_content(model, region), root_attributes(config, model.manifest, sanity)
    )


def reduction_summary(model: ReducedModel, out: str | Path, seconds: float) -> dict:
    """What :func:`reduce_campaign` returns: the sizes, spectra, time and file size."""
    g = model.global_reduction.pod
    return {
        "samples": len(model.samples),
        "modes": model.modes,
        "pressure_modes": [r.pressure_modes for r in model.reduced],
        "global_modes": g.n_modes,
        "global_eigenvalues": g.eigenvalues.tolist(),
        "sample_eigenvalues": {r.index: r.pod.eigenvalues.tolist() for r in model.reduced},
        "seconds": seconds,
        "bytes": Path(out).stat().st_size,
    }


def print_spectra(model: ReducedModel) -> None:
    """The leading POD eigenvalues of every sample and of the global POD."""

    def spectrum(values, count=8):
        return " ".join(f"{v:.3g}" for v in values[:count])

    for r in model.reduced:
        print(f"  sample {r.index:3d}: eigenvalues {spectrum(r.pod.eigenvalues)}")
    g = model.global_reduction.pod
    head = spectrum(g.eigenvalues, 12)
    print(f"  global: {g.n_modes} modes of {len(g.eigenvalues)}; eigenvalues {head}")
