"""The one place the artifact is assembled: the reduction's results laid out in the groups
and attributes of ``shared/ARTIFACT.md`` (rank 0, no MPI, no solves).

:class:`ReducedModel` holds what the reduction computed, as whole arrays;
:func:`artifact_content` turns it into the ``group -> {dataset -> array}``
mapping that :func:`~hapticrom.shared.artifact.write_artifact` checks against
the schema and writes; :func:`root_attributes` describes the file.
"""

from __future__ import annotations

import datetime
import json
from dataclasses import dataclass

import numpy as np

from hapticrom import __version__
from hapticrom.offline.campaign.config import CampaignConfig, CuttingConfig
from hapticrom.offline.cutting.export import CutOperators, CutRegion
from hapticrom.offline.fe.materials import make_law
from hapticrom.offline.fe.sanity import dumps
from hapticrom.offline.reduce.anm_reduction import SampleSeries
from hapticrom.offline.reduce.contact_fields import ContactFields
from hapticrom.offline.reduce.inputs import RenderSurface, Sample
from hapticrom.offline.reduce.interpolation import DepthGrid, GrassmannTangents
from hapticrom.offline.reduce.operators import GlobalReduction, ReducedSample
from hapticrom.offline.reduce.sample_triangulation import SampleTriangulation


@dataclass
class ReducedModel:
    """Everything the artifact holds, before it is laid out.

    ``surface``: the rendering mesh; ``sample_bases``, ``tangents`` and
    ``global_basis``: whole (N, n) arrays, gathered from the ranks' rows;
    ``series``/``cut``: None when the campaign asks for no POD-ANM series /
    cuttable region.
    """

    config: CampaignConfig
    manifest: dict
    samples: list[Sample]
    reduced: list[ReducedSample]
    modes: int
    global_reduction: GlobalReduction
    neighbourhoods: SampleTriangulation
    indicator: np.ndarray  # (P,) leave-one-out relative force error
    grassmann: GrassmannTangents
    grid: DepthGrid
    surface: RenderSurface
    sample_bases: list[np.ndarray]
    tangents: list[np.ndarray]
    global_basis: np.ndarray
    series: list[SampleSeries] | None = None
    cut: CutOperators | None = None
    tool_stiffness: np.ndarray | None = None  # (S, L) N/mm on each sample triangle's lattice
    contact_fields: ContactFields | None = None  # the tool's linear field at loadable vertices


def artifact_content(model: ReducedModel, region: CutRegion | None = None) -> dict:
    """The artifact's groups (``region``: the cuttable region when the campaign has one)."""
    dofs = model.surface.dofs
    content = {
        "model": {"attrs": model_attributes(model)},
        "surface": surface_group(model.surface),
        "samples": samples_group(model, dofs),
        "grassmann": grassmann_group(model, dofs),
        "global": global_group(model, dofs),
    }
    if model.contact_fields is not None:
        f = model.contact_fields
        content["contact_fields"] = {"vertices": f.vertices, "fields": f.fields,
                                     "sample_rows": f.sample_rows,
                                     "stiffness": f.stiffness,
                                     "edge_stiffness": f.edge_stiffness}  # fmt: skip
    if model.series is not None:
        content["anm"] = anm_group(model.series, model.config)
    if model.cut is not None and region is not None:
        content["cutting"] = cutting_group(
            region, model.config.cutting, model.global_basis, model.cut
        )
    return content


def model_attributes(model: ReducedModel) -> dict:
    """The ``model`` group's attributes: what was trained, on what, how."""
    config, manifest = model.config, model.manifest
    return {
        "name": config.name,
        "mode": config.load.mode,
        "contact_radius": config.load.contact_radius,
        "surface_group": config.load.surface,
        "material": material_parameters(config),
        "campaign_hash": manifest["campaign_hash"],
        "mesh_file": manifest["mesh"]["file"],
        "mesh_sha256": manifest["mesh"]["sha256"],
        "element": config.problem.discretisation.element,
        "modes": model.modes,
        "pod_method": config.pod.method,
        "pod_inner_product": config.pod.inner_product,
    }


def surface_group(surface: RenderSurface) -> dict:
    """The ``surface`` group: the rendering mesh."""
    return {
        "vertices": surface.vertices,
        "triangles": surface.triangles,
        "nodes": surface.nodes,
        "groups": surface.groups.astype(np.int8),
    }


def samples_group(model: ReducedModel, dofs: np.ndarray) -> dict:
    """The ``samples`` group: per sample, its position, force curve and reduced model."""
    where, reduced, grid = model.neighbourhoods, model.reduced, model.grid
    snapshots = len(model.samples[0].depth) - 1  # M: the load steps (the grid may be finer)
    return {
        "points": where.points,
        "normals": where.normals,
        "triangles": where.triangles,
        "indicator": model.indicator,
        "depth": grid.depth,
        "solved_depth": grid.solved_depth,
        "force": grid.force,
        "stiffness": grid.stiffness,
        "surface_basis": np.array([A[dofs] for A in model.sample_bases], dtype=np.float32),
        "coefficients": grid.coefficients,
        "reduced_stiffness": np.array([r.reduced_stiffness for r in reduced]),
        "contact_rows": np.array([r.contact_rows for r in reduced]),
        "eigenvalues": np.array([r.pod.eigenvalues[:snapshots] for r in reduced]),
        "attrs": {"pressure_modes": [r.pressure_modes for r in reduced]},
        **({} if model.tool_stiffness is None else {"tool_stiffness": model.tool_stiffness}),
    }


def grassmann_group(model: ReducedModel, dofs: np.ndarray) -> dict:
    """The ``grassmann`` group: the tangents' surface rows and the Gram matrices."""
    g = model.grassmann
    return {
        "reference": np.int64(model.neighbourhoods.reference),
        "tangent_surface": np.array([T[dofs] for T in model.tangents], dtype=np.float32),
        "gram_tangent_tangent": g.tangent_tangent,
        "gram_tangent_basis": g.tangent_basis,
        "gram_reference_basis": g.reference_basis,
    }


def global_group(model: ReducedModel, dofs: np.ndarray) -> dict:
    """The ``global`` group: the global basis' surface rows, its spectrum and stiffness."""
    g = model.global_reduction
    return {
        "surface_basis": model.global_basis[dofs].astype(np.float32),
        "eigenvalues": g.pod.eigenvalues,
        "reduced_stiffness": g.stiffness,
    }


def anm_group(series: list[SampleSeries], config: CampaignConfig) -> dict:
    """The optional ``anm`` group: every sample's sections, concatenated."""
    counts = [len(s.a_max) for s in series]
    return {
        "section_offsets": np.r_[0, np.cumsum(counts)].astype(np.int64),
        "a_max": np.concatenate([s.a_max for s in series]),
        "depth": np.concatenate([s.depth for s in series]),
        "force": np.concatenate([s.force for s in series]),
        "coefficients": np.concatenate([s.coefficients for s in series]),
        "attrs": {
            "order": config.anm.order,
            "tolerance": config.anm.tolerance,
            "residual_evaluations": int(sum(s.evaluations for s in series)),
        },
    }


def cutting_group(
    region: CutRegion, cutting: CuttingConfig, basis: np.ndarray, cut: CutOperators
) -> dict:
    """The optional ``cutting`` group: the region's arrays and element matrices.

    With an element-wise pressure, also the blocks before condensation and the
    reduced pressure modes at the region's cells: the coupling then keeps the
    reduced pressure outside the cut patch (format 1.3).
    """
    pressure = {}
    if cut.pressure_modes is not None and region.pressure_coupling is not None:
        pressure = {
            "element_displacement_stiffness": region.displacement_stiffness,
            "element_pressure_coupling": region.pressure_coupling,
            "element_pressure_stiffness": region.pressure_stiffness,
            "pressure_basis": cut.pressure_modes[region.pressure_cells],
            "reduced_displacement_stiffness": cut.displacement_stiffness,
            "reduced_pressure_coupling": cut.pressure_coupling,
            "reduced_pressure_stiffness": cut.pressure_stiffness,
        }
    return {
        **pressure,
        "nodes": region.nodes.astype(np.int64),
        "coordinates": region.coordinates,
        "cells": region.local_cells.astype(np.int64),
        "element_stiffness": region.element_stiffness,
        "basis": np.ascontiguousarray(basis[region.dofs]),
        "fixed": region.fixed.astype(np.int8),
        "reduced_stiffness": cut.element_condensed_stiffness,
        "attrs": {
            "centre": list(cutting.centre),
            "radius": cutting.radius,
            "patch_layers": cutting.patch_layers,
            "cut_force": cutting.cut_force,
            "cells_in_region": int(len(region.cells)),
        },
    }


def root_attributes(config: CampaignConfig, manifest: dict, sanity: dict) -> dict:
    """The file's root attributes: provenance, units, the campaign, its physics sanity."""
    return {
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": json.dumps(software_versions()),
        "units": json.dumps({"length": "mm", "force": "N", "stiffness": "N/mm"}),
        "campaign": json.dumps(manifest["campaign"], default=str),
        "description": f"contact ROM of campaign '{config.name}'",
        "sanity": dumps(sanity),  # physics sanity (offline/fe/sanity.py)
    }


def material_parameters(config: CampaignConfig) -> dict:
    """The law and every parameter it used, defaults included (MPa or dimensionless)."""
    material = config.problem.material
    law = make_law(material.law, **material.params)
    extra = {k: v for k, v in material.params.items() if isinstance(v, bool)}
    return {"law": law.name, **law.parameters(), **extra}


def software_versions() -> dict:
    """The versions of hapticrom and the libraries that computed the model."""
    versions = {"hapticrom": __version__}
    for module in ("dolfinx", "petsc4py", "slepc4py", "numpy", "h5py"):
        try:
            versions[module] = __import__(module).__version__
        except (ImportError, AttributeError):
            continue
    return versions
