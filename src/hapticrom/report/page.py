"""The report as HTML: tables, embedded PNGs, one section per heading, the document."""

from __future__ import annotations

import base64
import html
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hapticrom.online.model import ReducedModel
from hapticrom.online.simulator import default_interpolation
from hapticrom.report.content import (
    RESPONSE_LABELS,
    dataset_rows,
    discarded_energy,
    flagged_rows,
    sanity_rows,
    summary_rows,
)
from hapticrom.report.field_comparison import DESCRIPTIONS, HELD_OUT_COMMAND
from hapticrom.report.figures import Png
from hapticrom.report.heldout import (
    ACCURACY_COMMAND,
    HeldOutResults,
    accuracy_position_rows,
    accuracy_summary_rows,
    targets_text,
)
from hapticrom.report.timing import latency_rows


@dataclass(frozen=True)
class Facts:
    """What the sections say besides the model's own content (chosen or measured)."""

    response: str  # the runtime's force: "anm" or "curves"
    central: int  # the sample of the latency and of the deformed surface
    samples: list[int]  # the samples of the load-displacement curves
    latencies: np.ndarray  # us, one per timed step
    factor: float  # magnification of the deformed surface
    held_out: HeldOutResults | None = None
    held_out_source: Path | None = None  # the accuracy JSON
    field_caption: str | None = None  # of the held-out field comparison (--held-out)
    field_source: Path | None = None  # its held-out campaign directory


@dataclass(frozen=True)
class Figures:
    """The report's PNGs, section by section."""

    eigenvalues: Png
    curves: Png
    held_out: Png | None
    latency: Png
    surfaces: list[Png]
    field: Png | None = None  # the held-out field comparison (--held-out)

    def all(self) -> list[Png]:
        """Every PNG drawn, in the order of the sections."""
        pngs = [self.eigenvalues, self.curves, self.held_out, self.field, self.latency,
                *self.surfaces]  # fmt: skip
        return [png for png in pngs if png is not None]


SUMMARY = "Model summary"
EIGENVALUES = "POD eigenvalue decay"
CURVES = "Load-displacement curves: ROM vs full order"
SANITY = "Physics sanity of the training"
HELD_OUT = "Force and surface-field error at held-out positions"
FIELD = "Rendered surface vs full order at a held-out position"
LATENCY = "Step latency"
DEFORMED = "Deformed surface"
SECTION_HEADINGS = (SUMMARY, SANITY, EIGENVALUES, CURVES, HELD_OUT, FIELD, LATENCY, DEFORMED)

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f3f3f3; } img { max-width: 100%; display: block; margin: 0.8em 0; }
code { background: #f3f3f3; padding: 0 0.25em; } .note { color: #555; }
"""


# -- HTML building blocks ----------------------------------------------------------------------
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


# -- the sections ----------------------------------------------------------------------------
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
            f"step. Targets: {_esc(targets_text())}. A missed target is information: it says "
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


def _field_section(caption: str | None, source: Path | None, png, model) -> str:
    if png is None:
        command = HELD_OUT_COMMAND.format(model=model.path)
        return _section(
            FIELD,
            _paragraph(
                "Not drawn for this report. It compares the surface the runtime renders with "
                "the full-order one at a held-out tool position; the held-out solves come from "
                f"<code>{_esc(command)}</code> (written to MODEL.heldout-8 by default), then run "
                "<code>hapticrom report MODEL.h5 --out DIR --held-out MODEL.heldout-8</code>."
            ),
        )
    runtime = default_interpolation(model)  # the figure's runtime panel (field_comparison)
    if runtime == "podi":
        shown = (
            "the runtime's interpolation of the surface field, <i>podi</i> "
            f"({DESCRIPTIONS['podi']}, the default: the model has neither a surface "
            "chart nor contact fields)"
        )
    else:
        shown = (
            f"the runtime's two interpolations of the surface field, <i>{_esc(runtime)}</i> "
            f"({DESCRIPTIONS[runtime]}, the default) and <i>podi</i> "
            f"({DESCRIPTIONS['podi']})"
        )
    return _section(
        FIELD,
        _paragraph(
            f"From the full-order solves in <code>{_esc(source)}</code>. Top: |u| in plan "
            "view (along the samples' mean normal; white dots: the training samples; red +: "
            f"the tool; dashed: the cross-section), the full order and {shown}. Bottom: the "
            "displacement into the organ along the dashed line."
        ),
        _image(png),
        _paragraph(_esc(caption)),
    )


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


def sections(model: ReducedModel, facts: Facts, figures: Figures) -> list[str]:
    """The sections in the order of :data:`SECTION_HEADINGS`, as HTML."""
    return [
        _summary_section(model),
        _sanity_section(model),
        _eigenvalue_section(model, figures.eigenvalues),
        _curves_section(model, facts.samples, facts.response, figures.curves),
        _held_out_section(facts.held_out, facts.held_out_source, figures.held_out, model),
        _field_section(facts.field_caption, facts.field_source, figures.field, model),
        _latency_section(facts.latencies, facts.central, facts.response, figures.latency),
        _deformed_section(figures.surfaces, facts.factor),
    ]


def document(title: str, sections: list[str]) -> str:
    """The whole HTML page: title, style, the note on units, the sections."""
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
