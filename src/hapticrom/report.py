"""A self-contained HTML report on a reduced-model artifact (``hapticrom report``).

What a computational-mechanics user checks before trusting a model: what the file holds,
how fast the POD spectra decay, whether the runtime reproduces the full-order
load-displacement curves, the force and surface-field errors at held-out positions (measured
by ``hapticrom accuracy``, against the targets of :mod:`hapticrom.shared.accuracy`), how long
a haptic step takes, and what the deformed organ looks like.
The figures are PNGs saved next to ``report.html`` and embedded in it (base64), so the HTML
file can be sent on its own. Units: mm, N, MPa; latencies in microseconds.

Needs matplotlib (part of the ``offline`` extra), but never imports the finite-element stack:
the report runs wherever the online runtime runs. Figures are drawn on ``Figure`` objects with
the Agg canvas, never through pyplot, so nothing global (backend, open figures) changes.
"""

from __future__ import annotations

import base64
import gc
import html
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from hapticrom.online.latency import TARGETS as LATENCY_TARGETS
from hapticrom.online.latency import _time_calls  # the same timing loop as `hapticrom bench`
from hapticrom.online.model import ReducedModel, load
from hapticrom.shared.accuracy import target, verdict
from hapticrom.shared.artifact import SCHEMA
from hapticrom.shared.errors import HapticromError

SUMMARY = "Model summary"
EIGENVALUES = "POD eigenvalue decay"
CURVES = "Load-displacement curves: ROM vs full order"
SANITY = "Physics sanity of the training"
HELD_OUT = "Force and surface-field error at held-out positions"
LATENCY = "Step latency"
DEFORMED = "Deformed surface"
SECTION_HEADINGS = (SUMMARY, SANITY, EIGENVALUES, CURVES, HELD_OUT, LATENCY, DEFORMED)

ACCURACY_COMMAND = "mpirun -n 2 hapticrom accuracy {model} --json accuracy.json"

RESPONSE_LABELS = {"anm": "POD-ANM series", "curves": "interpolated full-order curves"}
DPI = 110


@dataclass(frozen=True)
class Png:
    """One rendered figure: its file name in the report directory, bytes and alt text."""

    name: str
    data: bytes
    alt: str


@dataclass(frozen=True)
class HeldOutResults:
    """The content of ``hapticrom accuracy --json``: per-combination summary and force rows."""

    summary: dict[str, dict[str, float]]
    responses: list[str]  # names of the ROM force columns of the rows ("podi+curves", ...)
    positions: np.ndarray  # (R,) held-out position index
    points: np.ndarray  # (R, 3) mm
    depths: np.ndarray  # (R,) mm
    fem: np.ndarray  # (R,) N
    rom: np.ndarray  # (R, C) N, one column per response
    field: np.ndarray | None = None  # (R, C) relative L2 surface-field errors (format 2)

    @property
    def errors(self) -> np.ndarray:
        """Relative force errors (R, C); NaN where the full-order force is zero."""
        fem = np.where(self.fem > 0, self.fem, np.nan)[:, None]
        return np.abs(self.rom - fem) / fem


# -- matplotlib, without pyplot --------------------------------------------------------------
def _require_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise HapticromError(
            "hapticrom report draws its figures with matplotlib: pip install matplotlib "
            "(or pip install 'hapticrom[offline]')"
        ) from None


def _new_figure(width: float, height: float, layout: str | None = "constrained"):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _render(fig, name: str, alt: str) -> Png:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    return Png(name, buffer.getvalue(), alt)


# -- which samples to show -------------------------------------------------------------------
def central_sample(model: ReducedModel) -> int:
    """The sample nearest the chart origin (as ``hapticrom bench`` uses)."""
    return int(np.argmin(np.linalg.norm(model.chart_points, axis=1)))


def curve_samples(model: ReducedModel, count: int = 4) -> list[int]:
    """The central sample and others at radii spread evenly out to the rim of the region."""
    radii = np.linalg.norm(model.chart_points, axis=1)
    picked: list[int] = []
    for radius in np.linspace(0.0, radii.max(), min(count, len(radii))):
        distance = np.abs(radii - radius)
        distance[picked] = np.inf
        picked.append(int(np.argmin(distance)))
    return picked


# -- 1. model summary ------------------------------------------------------------------------
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
        ("indentation grid", f"{K} depths, 0 to {model.trained_depth:.4g} mm"),
        (
            "trained force at the deepest point",
            f"{model.force[:, -1].min():.4g} to {model.force[:, -1].max():.4g} N",
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


# -- 1b. physics sanity of the training ------------------------------------------------------
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


def _sanity_section(model: ReducedModel) -> str:
    sanity = model.artifact.attrs.get("sanity")
    if not isinstance(sanity, dict):
        return _section(
            SANITY,
            _paragraph(
                "Not recorded: this model was trained before the physics sanity checks "
                "(smallest J, compression, inverted elements, load-path jumps); train it again "
                "to see them."
            ),
        )
    flagged = flagged_rows(sanity)
    verdict = (
        f"{len(flagged)} of {sanity.get('positions', '?')} training position(s) flagged: "
        "the full-order solves this model distils are physically doubtful there."
        if flagged
        else f"No training position flagged ({sanity.get('checked', '?')} checked)."
    )
    parts = [_paragraph(_esc(verdict)), _table(["quantity", "worst", "where"], sanity_rows(sanity))]
    if flagged:
        parts.append(_table(["position", "flags", "first warning"], flagged[:20]))
        parts.append(_paragraph("<b>Suggestion:</b> " + _esc(sanity.get("suggestion", ""))))
    return _section(SANITY, *parts)


# -- 2. POD eigenvalues ----------------------------------------------------------------------
def _normalised_spectrum(eigenvalues: np.ndarray) -> np.ndarray:
    """lambda_k / lambda_1, with round-off (non-positive) values masked for a log axis."""
    ratio = eigenvalues / eigenvalues[..., :1]
    return np.where(ratio > 0, ratio, np.nan)


def discarded_energy(eigenvalues: np.ndarray, modes: int) -> np.ndarray:
    """Fraction of the snapshot energy (sum of eigenvalues) beyond the first ``modes``, per row."""
    positive = np.clip(eigenvalues, 0, None)
    return positive[..., modes:].sum(axis=-1) / positive.sum(axis=-1)


def eigenvalue_figure(model: ReducedModel, central: int) -> Png:
    artifact = model.artifact
    per_sample = artifact["samples"]["eigenvalues"]
    has_global = "global" in artifact.groups
    fig = _new_figure(11 if has_global else 6.5, 4.2)
    axes = fig.subplots(1, 2 if has_global else 1, squeeze=False)[0]
    ax = axes[0]
    index = np.arange(1, per_sample.shape[1] + 1)
    ratios = _normalised_spectrum(per_sample)
    for i, ratio in enumerate(ratios):
        ax.semilogy(
            index, ratio, color="0.6", alpha=0.45, lw=0.9, label="each sample" if i == 0 else None
        )
    ax.semilogy(
        index, ratios[central], "o-", color="C0", lw=1.6, ms=4, label=f"central sample {central}"
    )
    ax.axvline(
        model.num_modes + 0.5, color="C3", ls="--", lw=1, label=f"{model.num_modes} modes kept"
    )
    ratio = artifact.attrs.get("campaign", {}).get("pod", {}).get("eigenvalue_ratio")
    if ratio is not None:
        ax.axhline(ratio, color="C1", ls=":", lw=1.2, label=f"truncation ratio {ratio:g}")
    ax.set(
        xlabel="mode index k",
        ylabel=r"$\lambda_k / \lambda_1$",
        title=f"Per-sample POD spectra ({len(per_sample)} samples)",
    )
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)
    if has_global:
        _plot_global_spectrum(axes[1], artifact["global"])
    return _render(fig, "eigenvalues.png", "POD eigenvalue decay, per sample and global")


def _plot_global_spectrum(ax, group: dict) -> None:
    ratio = _normalised_spectrum(group["eigenvalues"])
    kept = group["reduced_stiffness"].shape[0]
    ax.semilogy(np.arange(1, len(ratio) + 1), ratio, color="C2", lw=1.4)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.axvline(kept + 0.5, color="C3", ls="--", lw=1, label=f"{kept} global modes kept")
    ax.set(
        xlabel="mode index k",
        ylabel=r"$\lambda_k / \lambda_1$",
        title="Global POD spectrum (all samples' snapshots)",
    )
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)


# -- 3. load-displacement curves ---------------------------------------------------------------
def rom_forces(
    model: ReducedModel, sample: int, depths: np.ndarray, response: str | None = None
) -> np.ndarray:
    """Normal force (N) of the runtime at ``depths`` (mm), contact at a sample's position."""
    sim = model.simulator(response=response)
    sim.set_contact(model.sample_points[sample])
    normal = sim.contact_normal.copy()
    return np.array([sim.step_displacement(-d * normal) @ normal for d in depths])


def load_displacement_figure(model: ReducedModel, samples: list[int], response: str) -> Png:
    from matplotlib.lines import Line2D

    knots = model.artifact["samples"]["depth"]
    fine = np.linspace(0.0, model.trained_depth, 201)
    radii = np.linalg.norm(model.chart_points, axis=1)
    fig = _new_figure(7.5, 6.5)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[2.2, 1])
    for colour, i in enumerate(samples):
        c = f"C{colour}"
        top.plot(fine, rom_forces(model, i, fine, response), "-", color=c, lw=1.5)
        top.plot(knots, model.force[i], "o", color=c, mfc="none", ms=6)
        at_knots = rom_forces(model, i, knots[1:], response)
        error = 100 * (at_knots - model.force[i, 1:]) / model.force[i, 1:]
        bottom.plot(knots[1:], error, "o-", color=c, ms=4, lw=1)
    sample_handles = [
        Line2D([], [], color=f"C{k}", lw=3, label=f"sample {i} (r = {radii[i]:.2f} mm)")
        for k, i in enumerate(samples)
    ]
    style_handles = [
        Line2D(
            [], [], color="k", marker="o", mfc="none", ls="none", label="full order (stored curve)"
        ),
        Line2D([], [], color="k", lw=1.5, label=f"ROM ({RESPONSE_LABELS[response]})"),
    ]
    top.legend(handles=sample_handles + style_handles, fontsize=8, loc="upper left")
    top.set(
        ylabel="normal force F (N)",
        xlim=(0, model.trained_depth * 1.02),
        ylim=(0, None),
        title="Indentation at training positions: ROM vs full order",
    )
    bottom.axhline(0, color="0.5", lw=0.8)
    bottom.set(xlabel="indentation depth (mm)", ylabel="ROM error at knots (%)")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    return _render(fig, "load-displacement.png", "load-displacement curves, ROM vs full order")


# -- 4. held-out accuracy --------------------------------------------------------------------
def read_accuracy(path: str | Path) -> HeldOutResults:
    """Read and check the JSON of ``hapticrom accuracy --json`` (or of the older
    ``bench/accuracy.py --json``, without per-row field errors); a bad file raises, naming it."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise HapticromError(
            f"accuracy file {path} not found; write it with "
            + ACCURACY_COMMAND.format(model="MODEL.h5")
        ) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise HapticromError(f"accuracy file {path} is not JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("summary"), dict):
        raise HapticromError(f"accuracy file {path} has no 'summary' object")
    rows = data.get("rows")
    if not isinstance(rows, list) or not rows:
        raise HapticromError(f"accuracy file {path} has no 'rows'")
    # One force per PODI combination is appended to each row, in the summary's order.
    responses = [name for name in data["summary"] if name.startswith("podi+")]
    try:
        table = [
            (
                int(r[0]),
                [float(x) for x in r[1]],
                float(r[2]),
                float(r[3]),
                [float(x) for x in r[4:]],
            )
            for r in rows
        ]
    except (TypeError, ValueError, IndexError) as exc:
        raise HapticromError(f"accuracy file {path}: a row is malformed ({exc})") from None
    if any(len(r[4]) != len(responses) or len(r[1]) != 3 for r in table):
        raise HapticromError(
            f"accuracy file {path}: each row needs [position, [x, y, z], depth, F_FEM] and one "
            f"force per PODI combination of the summary ({', '.join(responses) or 'none'})"
        )
    return HeldOutResults(
        summary=data["summary"],
        responses=responses,
        positions=np.array([r[0] for r in table]),
        points=np.array([r[1] for r in table]),
        depths=np.array([r[2] for r in table]),
        fem=np.array([r[3] for r in table]),
        rom=np.array([r[4] for r in table]),
        field=_field_errors(path, data.get("field_errors"), len(table), len(responses)),
    )


def _field_errors(path: Path, field, rows: int, columns: int) -> np.ndarray | None:
    """The per-row field errors (R, C), or None when the file has none (format 1)."""
    if field is None:
        return None
    try:
        array = np.array(field, dtype=float)
    except (TypeError, ValueError) as exc:
        raise HapticromError(f"accuracy file {path}: 'field_errors' is malformed ({exc})") from None
    if array.shape != (rows, columns):
        raise HapticromError(
            f"accuracy file {path}: 'field_errors' must have one row per row and one column per "
            f"PODI combination ({rows} x {columns}), got shape {array.shape}"
        )
    return array


def _error_cells(quantity: str, name: str, error: float) -> tuple[str, str, str]:
    """(error %, target %, verdict) of one quantity, the target from hapticrom.shared.accuracy."""
    limit = target(quantity, name)
    return (
        f"{100 * error:.2f}",
        "" if limit is None else f"{100 * limit:g}",
        verdict(error, limit),
    )


def accuracy_summary_rows(results: HeldOutResults) -> list[tuple[str, ...]]:
    """(combination, then error, target and verdict of the force and of the surface field)."""
    rows = []
    for name, s in results.summary.items():
        force = float(s.get("max_force_error", np.nan))
        field = float(s.get("max_field_error", np.nan))
        rows.append(
            (name, *_error_cells("force", name, force), *_error_cells("field", name, field))
        )
    return rows


def accuracy_position_rows(results: HeldOutResults) -> list[tuple[str, ...]]:
    """Per held-out position: where, deepest depth and force, worst force error of each
    response, then (when the file has them) worst field error of each response."""
    rows = []
    errors = results.errors
    columns = range(len(results.responses))
    for position in dict.fromkeys(results.positions.tolist()):
        mask = results.positions == position
        deepest = np.flatnonzero(mask)[np.argmax(results.depths[mask])]
        worst = [np.nanmax(errors[mask, c]) for c in columns]
        if results.field is not None:
            worst += [np.nanmax(results.field[mask, c]) for c in columns]
        rows.append(
            (
                str(position),
                *(f"{x:.3f}" for x in results.points[deepest]),
                f"{results.depths[deepest]:.3f}",
                f"{results.fem[deepest]:.5f}",
                *(f"{100 * w:.2f}" for w in worst),
            )
        )
    return rows


def accuracy_figure(results: HeldOutResults, trained_depth: float) -> Png:
    """Force error vs depth at each held-out position; the field error beside it if known."""
    panels = [("force", 100 * results.errors, "|F_ROM - F_FEM| / F_FEM (%)")]
    if results.field is not None:
        panels.append(("field", 100 * results.field, "surface-field relative L2 error (%)"))
    fig = _new_figure(7.5 if len(panels) == 1 else 12, 4.2)
    count = len(set(results.positions.tolist()))
    for ax, (quantity, errors, ylabel) in zip(fig.subplots(1, len(panels), squeeze=False)[0],
                                              panels, strict=True):  # fmt: skip
        _plot_errors(ax, results, errors, quantity)
        if results.depths.max() > trained_depth:  # force-controlled checks may press deeper
            label = f"trained depth {trained_depth:.3g} mm (beyond: extrapolated)"
            ax.axvline(trained_depth, color="0.3", ls=":", lw=1, label=label)
        title = "Force" if quantity == "force" else "Surface-field"
        ax.set(
            xlabel="indentation depth (mm)",
            ylabel=ylabel,
            ylim=(0, None),
            title=f"{title} error at {count} held-out positions (one line each)",
        )
        ax.title.set_fontsize(10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="center right")  # the errors sit low, the targets high
    return _render(fig, "held-out-error.png", "force and field errors at held-out positions")


def _plot_errors(ax, results: HeldOutResults, errors: np.ndarray, quantity: str) -> None:
    """One line per position and response, and each response's target (dashed)."""
    for c, name in enumerate(results.responses):
        for k, position in enumerate(dict.fromkeys(results.positions.tolist())):
            mask = results.positions == position
            order = np.argsort(results.depths[mask])
            ax.plot(
                results.depths[mask][order],
                errors[mask, c][order],
                "o-",
                color=f"C{c}",
                alpha=0.6,
                lw=1,
                ms=3,
                label=name if k == 0 else None,
            )
        limit = target(quantity, name)
        if limit is not None:
            ax.axhline(
                100 * limit,
                color=f"C{c}",
                ls="--",
                lw=1,
                label=f"target {name}: {100 * limit:g} %",
            )


# -- 5. step latency -------------------------------------------------------------------------
def step_latencies_us(model: ReducedModel, sample: int, steps: int) -> np.ndarray:
    """Microseconds of each ``step_displacement`` call, pressing and releasing 20 times.

    The garbage collector is off during the loop, as in a real-time servo thread.
    """
    sim = model.simulator()
    sim.set_contact(model.sample_points[sample])
    normal = sim.contact_normal.copy()
    phase = np.linspace(0, 40 * np.pi, steps)
    depths = model.trained_depth * 0.5 * (1 - np.cos(phase))
    displacements = [np.ascontiguousarray(-d * normal) for d in depths]
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        ns = _time_calls(sim.step_displacement, displacements)
    finally:
        if gc_was_enabled:
            gc.enable()
    return ns / 1e3


def latency_rows(us: np.ndarray) -> list[tuple[str, str]]:
    p50, p99, p999 = np.percentile(us, [50, 99, 99.9])
    target = LATENCY_TARGETS["step_displacement p99"][2]
    return [
        ("calls", f"{len(us):,}"),
        ("p50", f"{p50:.2f} us"),
        ("p99", f"{p99:.2f} us (target {target:g} us: {'met' if p99 <= target else 'missed'})"),
        ("p99.9", f"{p999:.2f} us"),
        ("max", f"{us.max():.1f} us"),
        ("mean", f"{us.mean():.2f} us"),
    ]


def latency_figure(us: np.ndarray, response: str) -> Png:
    p50, p99, p999 = np.percentile(us, [50, 99, 99.9])
    target = LATENCY_TARGETS["step_displacement p99"][2]
    upper = max(1.3 * p999, 1.2 * target)  # the rare long outliers would squash the bulk
    beyond = int(np.count_nonzero(us > upper))
    fig = _new_figure(7.5, 4.0)
    ax = fig.add_subplot()
    ax.hist(us[us <= upper], bins=120, color="C0", alpha=0.8)
    ax.set_yscale("log")
    ax.axvline(p50, color="C2", lw=1.5, label=f"p50 = {p50:.2f} us")
    ax.axvline(p99, color="C3", lw=1.5, label=f"p99 = {p99:.2f} us")
    ax.axvline(target, color="k", ls="--", lw=1, label=f"p99 target {target:g} us")
    note = f"; {beyond} calls beyond {upper:.1f} us not shown (max {us.max():.0f} us)"
    ax.set(
        xlabel="step_displacement time (us)",
        ylabel="calls",
        xlim=(0, upper),
        title=f"{len(us):,} steps ({RESPONSE_LABELS[response]}), gc off" + (note if beyond else ""),
    )
    ax.title.set_fontsize(9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return _render(fig, "latency.png", "histogram of step_displacement latency")


# -- 6. deformed surface ---------------------------------------------------------------------
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


@dataclass(frozen=True)
class View:
    """A camera for the deformed surface; ``cutaway`` removes the half nearer the camera
    through the contact point, so the cut edge shows the dent's profile."""

    name: str
    label: str
    elevation: float  # degrees
    azimuth: float  # degrees
    cutaway: bool = False
    height: float = 6.4  # inches (7.5 wide): a view along a flat organ needs less
    # The 3-D axes in figure fractions. They draw their box to fit the shorter side, so a
    # short figure gets axes taller than itself (their empty top and bottom are cut off).
    axes: tuple[float, float, float, float] = (0.0, 0.15, 1.0, 0.8)


VIEWS = (
    View("deformed-oblique", "oblique view", 35, -60),
    View(
        "deformed-side",
        "side view, cut through the contact point",
        elevation=8,
        azimuth=-90,
        cutaway=True,
        height=4.4,
        axes=(0.0, -0.28, 1.0, 1.7),
    ),
)


def far_half(vertices: np.ndarray, triangles: np.ndarray, point, azimuth: float) -> np.ndarray:
    """The triangles beyond the vertical plane through ``point`` facing a camera at ``azimuth``."""
    towards_camera = np.array([np.cos(np.radians(azimuth)), np.sin(np.radians(azimuth)), 0.0])
    centroids = vertices[triangles].mean(axis=1)
    return triangles[(centroids - point) @ towards_camera <= 0]


def surface_figure(model, displacement, factor, force, sample, view: View) -> Png:
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LightSource, Normalize
    from matplotlib.ticker import MaxNLocator
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    magnitude = np.linalg.norm(displacement, axis=1)
    positions = model.vertices + factor * displacement
    triangles = model.triangles
    if view.cutaway:
        triangles = far_half(model.vertices, triangles, model.sample_points[sample], view.azimuth)
    norm = Normalize(0.0, magnitude.max() or 1.0)
    cmap = colormaps["viridis"]
    fig = _new_figure(7.5, view.height, layout=None)
    ax = fig.add_axes(view.axes, projection="3d")
    colours = cmap(norm(magnitude[triangles].mean(axis=1)))
    faces = Poly3DCollection(
        positions[triangles],
        facecolors=colours,
        edgecolors=colours,  # thin edges of the face's own colour: no hairline gaps
        linewidths=0.2,
        shade=True,  # light and shade show the shape; colour alone would flatten it
        lightsource=LightSource(azdeg=315, altdeg=50),
    )
    ax.add_collection3d(faces)
    _fit_axes(ax, positions)
    ax.view_init(elev=view.elevation, azim=view.azimuth)
    ax.set(xlabel="x (mm)", ylabel="y (mm)", zlabel="z (mm)")
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.labelpad = 10  # clear of the tick labels, whatever the view
        axis.set_major_locator(MaxNLocator(5))  # a thin organ's axis would crowd its ticks
    if view.cutaway:  # the axis along the line of sight is seen edge-on: its ticks overlap
        ax.set(yticks=[], ylabel="")
    scale = "true scale" if factor == 1 else f"displacement magnified x{factor:g}"
    fig.suptitle(
        f"{view.label}\nindentation {model.trained_depth:.3g} mm at sample {sample}, "
        f"F = {force:.4g} N ({scale})",
        fontsize=10,
    )
    bar = fig.add_axes((0.25, 0.55 / view.height, 0.5, 0.15 / view.height))  # fixed inches
    fig.colorbar(
        ScalarMappable(norm=norm, cmap=cmap),
        cax=bar,
        orientation="horizontal",
        label="displacement magnitude |u| (mm, true scale)",
    )
    return _render(fig, f"{view.name}.png", f"deformed surface, {view.label}")


def _fit_axes(ax, positions: np.ndarray) -> None:
    """Limits around the points with equal scale on every axis (mm look like mm)."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    span = np.maximum(hi - lo, 0.05 * (hi - lo).max())  # a flat organ keeps a visible depth
    ax.set(
        xlim=(lo[0], lo[0] + span[0]), ylim=(lo[1], lo[1] + span[1]), zlim=(lo[2], lo[2] + span[2])
    )
    ax.set_box_aspect(span, zoom=1.1)


# -- HTML ------------------------------------------------------------------------------------
STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f3f3f3; } img { max-width: 100%; display: block; margin: 0.8em 0; }
code { background: #f3f3f3; padding: 0 0.25em; } .note { color: #555; }
"""


def _esc(value) -> str:
    return html.escape(str(value))


def _table(header: list[str], rows, numeric: set[int] = frozenset()) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = "".join(
        "<tr>"
        + "".join(
            f'<td class="num">{_esc(v)}</td>' if j in numeric else f"<td>{_esc(v)}</td>"
            for j, v in enumerate(row)
        )
        + "</tr>"
        for row in rows
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _image(png: Png) -> str:
    data = base64.b64encode(png.data).decode("ascii")
    return (
        f'<img src="data:image/png;base64,{data}" alt="{_esc(png.alt)}" title="{_esc(png.name)}">'
    )


def _paragraph(text: str) -> str:
    return f"<p>{text}</p>"


def _section(title: str, *parts: str) -> str:
    return f"<section><h2>{_esc(title)}</h2>\n" + "\n".join(parts) + "</section>"


def _summary_section(model: ReducedModel) -> str:
    datasets = dataset_rows(model.path)
    total = sum(r[5] for r in datasets)
    return _section(
        SUMMARY,
        _table(["quantity", "value"], summary_rows(model)),
        _paragraph(
            f"Datasets ({len(datasets)}, {total / 1e6:.1f} MB uncompressed); the "
            "format is specified in <code>shared/ARTIFACT.md</code>."
        ),
        _table(
            ["group", "dataset", "shape", "dtype", "units", "bytes", "meaning"],
            [(*r[:5], f"{r[5]:,}", r[6]) for r in datasets],
            numeric={5},
        ),
    )


def _eigenvalue_section(model: ReducedModel, png: Png) -> str:
    discarded = discarded_energy(model.artifact["samples"]["eigenvalues"], model.num_modes)
    return _section(
        EIGENVALUES,
        _paragraph(
            "POD eigenvalues of each sample's snapshots (one per load step), divided by the "
            f"largest. The modes beyond the {model.num_modes} kept ones hold a fraction "
            f"{discarded.max():.2e} of the snapshot energy (sum of the eigenvalues) at the "
            f"worst sample, {np.median(discarded):.2e} at the median one. Eigenvalues at "
            "round-off level (zero or negative) are not drawn."
        ),
        _image(png),
    )


def _curves_section(model, samples: list[int], response: str, png: Png) -> str:
    return _section(
        CURVES,
        _paragraph(
            f"Circles: the full-order force-depth curves stored in the artifact "
            f"(<code>samples/force</code>) at samples {', '.join(map(str, samples))}, the "
            "central one first. Lines: the online runtime's normal force "
            f"(<code>step_displacement</code>, {RESPONSE_LABELS[response]}) with the tool at "
            f"the same position, on 201 depths from 0 to {model.trained_depth:.4g} mm. "
            "Lower panel: the runtime's relative error at the stored depths."
            + (
                " (With the curves response the runtime interpolates these very curves, so "
                "at a sample it reproduces them to round-off.)"
                if response == "curves"
                else ""
            )
        ),
        _image(png),
    )


def _held_out_section(results: HeldOutResults | None, source: Path | None, png, model) -> str:
    if results is None:
        command = ACCURACY_COMMAND.format(model=model.path)
        return _section(
            HELD_OUT,
            _paragraph(
                "Not measured for this report. The held-out check solves the full-order model "
                "at tool positions between the training samples (needs the offline extra), "
                f"then compares the reduced model there:<br><code>{_esc(command)}</code><br>"
                "then run <code>hapticrom report MODEL.h5 --out DIR --accuracy accuracy.json"
                "</code>."
            ),
        )
    columns = [f"max force error {name} (%)" for name in results.responses]
    if results.field is not None:
        columns += [f"max field error {name} (%)" for name in results.responses]
    return _section(
        HELD_OUT,
        _paragraph(
            f"From <code>{_esc(source)}</code> (<code>hapticrom accuracy</code>): the relative "
            "error of the normal force along each held-out indentation, and the relative L2 "
            "error of the surface displacement field (over the surface vertices), at every load "
            f"step. Targets: {_esc(_targets_text())}. A missed target is information: it says "
            "where the model is not to be trusted."
        ),
        _table(
            [
                "combination",
                "max force error (%)",
                "target (%)",
                "verdict",
                "max surface-field error (%)",
                "target (%)",
                "verdict",
            ],
            accuracy_summary_rows(results),
            numeric={1, 2, 4, 5},
        ),
        _table(
            ["position", "x (mm)", "y (mm)", "z (mm)", "deepest (mm)", "F_FEM there (N)", *columns],
            accuracy_position_rows(results),
            numeric=set(range(1, 6 + len(columns))),
        ),
        _image(png),
    )


def _targets_text() -> str:
    """The targets of hapticrom.shared.accuracy in words."""
    parts = []
    for quantity, label in (("force", "force"), ("field", "surface field")):
        limits = {r: f"{100 * target(quantity, f'podi+{r}'):g} %" for r in RESPONSE_LABELS}
        if len(set(limits.values())) == 1:
            parts.append(f"{label} {next(iter(limits.values()))} for every response")
        else:
            by_response = [f"{limit} for {RESPONSE_LABELS[r]}" for r, limit in limits.items()]
            parts.append(f"{label} {' and '.join(by_response)}")
    return "; ".join(parts)


def _latency_section(us: np.ndarray, sample: int, response: str, png: Png) -> str:
    return _section(
        LATENCY,
        _paragraph(
            f"Each <code>step_displacement</code> call timed with "
            f"<code>time.perf_counter_ns</code> (about 50 ns of its own), the garbage collector "
            f"off, tool at sample {sample}, pressing from 0 to the trained depth and back 20 "
            f"times ({RESPONSE_LABELS[response]}). A 1 kHz haptic loop has 1,000 us per tick."
        ),
        _table(["statistic", "value"], latency_rows(us)),
        _image(png),
    )


def _deformed_section(pngs: list[Png], factor: float) -> str:
    scale = "at true scale" if factor == 1 else f"magnified x{factor:g} (colours: true mm)"
    return _section(
        DEFORMED,
        _paragraph(
            "The surface the runtime renders (<code>surface_displacement</code>) at the "
            f"trained depth, displacement {scale}."
        ),
        *(_image(png) for png in pngs),
    )


def _document(title: str, sections: list[str]) -> str:
    when = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{_esc(title)}</title><style>{STYLE}</style></head><body>\n"
        f"<h1>{_esc(title)}</h1>\n"
        f'<p class="note">Written by <code>hapticrom report</code> on {_esc(when)}. '
        "Units: mm, N, MPa; times in microseconds (us).</p>\n"
        + "\n".join(sections)
        + "\n</body></html>\n"
    )


# -- the report ------------------------------------------------------------------------------
def write_report(
    model_path: str | Path,
    out_dir: str | Path,
    accuracy: str | Path | None = None,
    latency_steps: int = 20_000,
) -> Path:
    """Write ``out_dir/report.html`` and its PNGs for the artifact at ``model_path``."""
    _require_matplotlib()
    if latency_steps < 1:
        raise HapticromError(f"--latency-steps must be positive, got {latency_steps}")
    held_out = read_accuracy(accuracy) if accuracy is not None else None  # fail before work
    model = load(model_path)
    response = model.simulator().response
    central = central_sample(model)
    samples = curve_samples(model)

    # Timed first, before the plotting has filled the heap and the caches.
    latencies = step_latencies_us(model, central, latency_steps)
    eigen_png = eigenvalue_figure(model, central)
    curves_png = load_displacement_figure(model, samples, response)
    accuracy_png = accuracy_figure(held_out, model.trained_depth) if held_out is not None else None
    latency_png = latency_figure(latencies, response)
    displacement, force = deformed_surface(model, central)
    factor = magnification(model.vertices, displacement)
    surface_pngs = [
        surface_figure(model, displacement, factor, force, central, view) for view in VIEWS
    ]

    sections = [
        _summary_section(model),
        _sanity_section(model),
        _eigenvalue_section(model, eigen_png),
        _curves_section(model, samples, response, curves_png),
        _held_out_section(held_out, accuracy, accuracy_png, model),
        _latency_section(latencies, central, response, latency_png),
        _deformed_section(surface_pngs, factor),
    ]
    name = model.artifact.group_attrs["model"].get("name", model.path.stem)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pngs = [eigen_png, curves_png, accuracy_png, latency_png, *surface_pngs]
    for png in pngs:
        if png is not None:
            (out_dir / png.name).write_bytes(png.data)
    report = out_dir / "report.html"
    report.write_text(_document(f"hapticrom report: {name}", sections), encoding="utf-8")
    return report
