"""What the report says about a model, as rows of text and arrays: no matplotlib, no HTML.

The samples it shows, the summary and dataset tables, the physics sanity of the training,
the POD energy left out, and the runtime's answers (forces along an indentation, the
deformed surface). Units: mm, N, MPa.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from hapticrom.online.model import ReducedModel
from hapticrom.shared.artifact import SCHEMA

RESPONSE_LABELS = {"anm": "POD-ANM series", "curves": "interpolated full-order curves"}


# -- which samples to show -------------------------------------------------------------------
def central_sample(model: ReducedModel) -> int:
    """The sample nearest the centre of the plan view (as ``hapticrom bench`` uses)."""
    return int(np.argmin(np.linalg.norm(model.plan_points, axis=1)))


def curve_samples(model: ReducedModel, count: int = 4) -> list[int]:
    """The central sample and others at radii spread evenly out to the rim of the region."""
    radii = np.linalg.norm(model.plan_points, axis=1)
    picked: list[int] = []
    for radius in np.linspace(0.0, radii.max(), min(count, len(radii))):
        distance = np.abs(radii - radius)
        distance[picked] = np.inf
        picked.append(int(np.argmin(distance)))
    return picked


# -- model summary ------------------------------------------------------------------------
def _load_description(campaign: dict) -> str:
    load_spec = campaign.get("load", {})
    mode = load_spec.get("mode", "?")
    unit = {"force": "N", "displacement": "mm"}.get(mode, "")
    parts = [f"{mode}-controlled, magnitude {load_spec.get('magnitude', '?')} {unit}".strip()]
    if "contact_radius" in load_spec:
        parts.append(f"tool radius {load_spec['contact_radius']} mm")
    if "steps" in load_spec:
        parts.append(f"{load_spec['steps']} steps")
    return ", ".join(parts)


def summary_rows(model: ReducedModel) -> list[tuple[str, str]]:
    """(quantity, value) pairs describing the model, units in the values."""
    artifact = model.artifact
    info = artifact.group_attrs["model"]
    campaign = artifact.attrs.get("campaign", {})
    size = model.path.stat().st_size
    extent = np.ptp(model.vertices, axis=0)
    P, K = model.force.shape
    pressure = artifact.group_attrs["samples"].get("pressure_modes")
    return [
        ("name", str(info.get("name", "?"))),
        ("description", str(artifact.attrs.get("description", ""))),
        ("file", f"{model.path} ({size / 1e6:.1f} MB, {size:,} bytes)"),
        ("format version", f"{artifact.version[0]}.{artifact.version[1]}"),
        ("created", str(artifact.attrs.get("created", "?"))),
        ("material", json.dumps(info.get("material", {}))),
        ("element", str(info.get("element", "?"))),
        ("campaign load", _load_description(campaign)),
        ("samples (tool positions)", f"{P}"),
        ("indentation grid", f"{K} depths, 0 to {model.depth_step * (K - 1):.4g} mm"),
        (
            "depth solved to",
            f"{model.solved_depth.min():.4g} to {model.solved_depth.max():.4g} mm",
        ),
        (
            "trained force at the deepest point",
            f"{model.sample_trained_force.min():.4g} to {model.sample_trained_force.max():.4g} N",
        ),
        ("POD modes per sample", _modes_description(model, info, pressure)),
        ("surface", f"{len(model.vertices):,} vertices, {len(model.triangles):,} triangles"),
        ("organ extent (x, y, z)", " x ".join(f"{e:.3g}" for e in extent) + " mm"),
        ("mesh", f"{info.get('mesh_file', '?')}"),
        ("optional groups", _optional_groups(artifact) or "none"),
    ]


def _modes_description(model: ReducedModel, info: dict, pressure) -> str:
    text = (
        f"{model.num_modes} displacement modes ({info.get('pod_method', '?')}, "
        f"{info.get('pod_inner_product', '?')} inner product)"
    )
    if pressure is not None and len(pressure):
        low, high = int(np.min(pressure)), int(np.max(pressure))
        text += f"; {low if low == high else f'{low} to {high}'} pressure modes"
    return text


def _optional_groups(artifact) -> str:
    parts = []
    if "grassmann" in artifact.groups:
        parts.append("grassmann (Grassmann interpolation)")
    if "anm" in artifact.groups:
        attrs = artifact.group_attrs["anm"]
        sections = len(artifact["anm"]["a_max"])
        parts.append(
            f"anm (POD-ANM, order {attrs.get('order')}, tolerance {attrs.get('tolerance')}, "
            f"{sections} sections)"
        )
    if "global" in artifact.groups:
        parts.append(f"global ({artifact['global']['reduced_stiffness'].shape[0]} global modes)")
    return "; ".join(parts)


def dataset_rows(path: Path) -> list[tuple[str, str, str, str, str, int, str]]:
    """(group, dataset, shape, dtype, units, bytes, meaning) of every dataset in the file.

    Read from the file itself (not the schema) so that datasets of a newer minor version,
    which the reader ignores, are listed too; in the schema's order, unknown ones last.
    """
    order = {(g.name, f.name): i for i, (g, f) in enumerate(_schema_fields())}
    meanings = {(g.name, f.name): f.meaning for g, f in _schema_fields()}
    rows = []
    with h5py.File(path, "r") as f:
        for group_name, group in f.items():
            if not isinstance(group, h5py.Group):
                continue
            for name, dset in group.items():
                if not isinstance(dset, h5py.Dataset):
                    continue
                units = dset.attrs.get("units", "")
                units = units.decode() if isinstance(units, bytes) else str(units)
                meaning = meanings.get((group_name, name), "(not in this reader's schema)")
                rows.append(
                    (
                        group_name,
                        name,
                        str(dset.shape),
                        str(dset.dtype),
                        units,
                        dset.nbytes,
                        meaning,
                    )
                )
    return sorted(rows, key=lambda r: (order.get((r[0], r[1]), len(order)), r[0], r[1]))


def _schema_fields():
    return [(group, spec) for group in SCHEMA for spec in group.fields]


# -- physics sanity of the training ------------------------------------------------------
SANITY_QUANTITIES = (  # key of the artifact's `sanity` JSON, label, format
    ("j_min", "smallest J = det F", "{:.3g}"),
    ("compression", "largest compression (1 - smallest stretch)", "{:.0%}"),
    ("inverted", "inverted elements (J <= 0)", "{:d}"),
    ("u_max", "largest |u| (mm)", "{:.3g}"),
    ("jump_ratio", "largest step-to-step rate change", "{:.2g}x"),
    ("tangent_negative", "negative tangent eigenvalues (-1: not checked)", "{:d}"),
)


def sanity_rows(sanity: dict) -> list[tuple[str, str, str]]:
    """(quantity, worst value, where) from the artifact's `sanity` attribute (data from a file:
    anything of the wrong type is shown as '?', never trusted)."""
    worst = sanity.get("worst") if isinstance(sanity.get("worst"), dict) else {}
    rows = []
    for key, label, fmt in SANITY_QUANTITIES:
        entry = worst.get(key)
        if not isinstance(entry, dict):
            continue
        value = entry.get("value")
        try:
            shown = fmt.format(value)
        except (TypeError, ValueError):
            shown = "?"
        where = ", ".join(
            f"{k} {entry[k]}" for k in ("position", "step", "load_factor") if k in entry
        )
        rows.append((label, shown, where))
    return rows


def flagged_rows(sanity: dict) -> list[tuple[str, str, str]]:
    """(position, kinds, first message) of each flagged position."""
    flagged = sanity.get("flagged") if isinstance(sanity.get("flagged"), list) else []
    rows = []
    for item in flagged:
        if isinstance(item, dict):
            kinds = item.get("kinds") if isinstance(item.get("kinds"), list) else []
            messages = item.get("messages") if isinstance(item.get("messages"), list) else [""]
            rows.append((str(item.get("position", "?")), ", ".join(map(str, kinds)),
                         str(messages[0]) if messages else ""))  # fmt: skip
    return rows


# -- POD eigenvalues ----------------------------------------------------------------------
def normalised_spectrum(eigenvalues: np.ndarray) -> np.ndarray:
    """lambda_k / lambda_1, with round-off (non-positive) values masked for a log axis."""
    ratio = eigenvalues / eigenvalues[..., :1]
    return np.where(ratio > 0, ratio, np.nan)


def discarded_energy(eigenvalues: np.ndarray, modes: int) -> np.ndarray:
    """Fraction of the snapshot energy (sum of eigenvalues) beyond the first ``modes``, per row."""
    positive = np.clip(eigenvalues, 0, None)
    return positive[..., modes:].sum(axis=-1) / positive.sum(axis=-1)


# -- load-displacement curves ---------------------------------------------------------------
def rom_forces(
    model: ReducedModel, sample: int, depths: np.ndarray, response: str | None = None
) -> np.ndarray:
    """Normal force (N) of the runtime at ``depths`` (mm), contact at a sample's position."""
    sim = model.simulator(response=response)
    sim.set_contact(model.sample_points[sample])
    normal = sim.contact_normal.copy()
    return np.array([sim.step_displacement(-d * normal) @ normal for d in depths])


# -- deformed surface ---------------------------------------------------------------------
def deformed_surface(model: ReducedModel, sample: int) -> tuple[np.ndarray, float]:
    """Surface displacement (V, 3) mm and normal force (N) at the trained depth at a sample."""
    sim = model.simulator()
    sim.set_contact(model.sample_points[sample])
    normal = sim.contact_normal.copy()
    force = float(sim.step_displacement(-model.trained_depth * normal) @ normal)
    out = np.zeros_like(model.vertices)
    sim.surface_displacement(out)
    return out, force


def magnification(vertices: np.ndarray, displacement: np.ndarray) -> float:
    """1, or a round factor (1, 2, 5 x 10^k) that makes the largest displacement about 10 %
    of the organ's size when it is under 5 % of it (otherwise the dent is invisible)."""
    size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    largest = float(np.linalg.norm(displacement, axis=1).max())
    if largest == 0 or largest >= 0.05 * size:
        return 1.0
    wanted = 0.1 * size / largest
    decade = 10 ** np.floor(np.log10(wanted))
    return float(max(m * decade for m in (1, 2, 5) if m * decade <= wanted))
