"""A self-contained HTML report on a reduced-model artifact (``hapticrom report``).

What a computational-mechanics user checks before trusting a model: what the file holds,
how fast the POD spectra decay, whether the runtime reproduces the full-order
load-displacement curves, the force and surface-field errors at held-out positions (measured
by ``hapticrom accuracy``, against the targets of :mod:`hapticrom.shared.accuracy`), how long
a haptic step takes, and what the deformed organ looks like.
The figures are PNGs saved next to ``report.html`` and embedded in it (base64), so the HTML
file can be sent on its own. Units: mm, N, MPa; latencies in microseconds.

Needs matplotlib (the ``report`` extra: ``pip install 'hapticrom[report]'``), but never
imports the finite-element stack nor :mod:`hapticrom.offline`: the report runs wherever the
online runtime runs. The parts:

- :mod:`~hapticrom.report.content` -- what is said about the model, as rows and arrays;
- :mod:`~hapticrom.report.heldout` -- the accuracy JSON, its tables, the shared targets;
- :mod:`~hapticrom.report.timing` -- the step latency (``hapticrom bench``'s timing loop);
- :mod:`~hapticrom.report.figures`, :mod:`~hapticrom.report.surface` -- the PNGs (Agg
  canvas, never pyplot: nothing global changes);
- :mod:`~hapticrom.report.field_comparison` -- the rendered surface against the full order
  at a held-out position (``--held-out DIR``);
- :mod:`~hapticrom.report.page` -- the HTML.
"""

from __future__ import annotations

from pathlib import Path

from hapticrom.online.model import ReducedModel, load
from hapticrom.report.content import (
    central_sample,
    curve_samples,
    deformed_surface,
    flagged_rows,
    magnification,
    sanity_rows,
)
from hapticrom.report.field_comparison import (
    FieldComparison,
    field_figure,
    held_out_comparison,
    require_held_out_dir,
)
from hapticrom.report.field_comparison import caption as field_caption
from hapticrom.report.figures import (
    accuracy_figure,
    eigenvalue_figure,
    latency_figure,
    load_displacement_figure,
    require_matplotlib,
)
from hapticrom.report.heldout import HeldOutResults, read_accuracy
from hapticrom.report.page import SECTION_HEADINGS, Facts, Figures, document, sections
from hapticrom.report.surface import VIEWS, surface_figure
from hapticrom.report.timing import step_latencies_us
from hapticrom.shared.errors import HapticromError

__all__ = [
    "SECTION_HEADINGS",
    "HeldOutResults",
    "flagged_rows",
    "read_accuracy",
    "sanity_rows",
    "write_report",
]


def write_report(
    model_path: str | Path,
    out_dir: str | Path,
    accuracy: str | Path | None = None,
    latency_steps: int = 20_000,
    held_out_dir: str | Path | None = None,
) -> Path:
    """Write ``out_dir/report.html`` and its PNGs for the artifact at ``model_path``; with
    ``held_out_dir`` (a campaign directory of ``hapticrom accuracy``) also the rendered
    surface against the full order at one of its positions."""
    require_matplotlib()
    if latency_steps < 1:
        raise HapticromError(f"--latency-steps must be positive, got {latency_steps}")
    held_out = read_accuracy(accuracy) if accuracy is not None else None  # fail before work
    if held_out_dir is not None:
        held_out_dir = require_held_out_dir(held_out_dir, model_path)
    model = load(model_path)
    comparison = None if held_out_dir is None else held_out_comparison(model, held_out_dir)
    central = central_sample(model)
    # Timed first, before the plotting has filled the heap and the caches.
    latencies = step_latencies_us(model, central, latency_steps)
    displacement, force = deformed_surface(model, central)
    facts = Facts(
        response=model.simulator().response,
        central=central,
        samples=curve_samples(model),
        latencies=latencies,
        factor=magnification(model.vertices, displacement),
        held_out=held_out,
        held_out_source=None if accuracy is None else Path(accuracy),
        field_caption=None if comparison is None else field_caption(model, comparison),
        field_source=held_out_dir,
    )
    figures = draw(model, facts, displacement, force, comparison)
    name = model.artifact.group_attrs["model"].get("name", model.path.stem)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for png in figures.all():
        (out_dir / png.name).write_bytes(png.data)
    report = out_dir / "report.html"
    html = document(f"hapticrom report: {name}", sections(model, facts, figures))
    report.write_text(html, encoding="utf-8")
    return report


def draw(model: ReducedModel, facts: Facts, displacement, force: float,
         comparison: FieldComparison | None = None) -> Figures:  # fmt: skip
    """Every figure of the report; ``displacement`` (mm) and ``force`` (N) at the trained
    depth at the central sample; ``comparison``: the held-out field comparison, if any."""
    held_out = facts.held_out
    return Figures(
        eigenvalues=eigenvalue_figure(model, facts.central),
        curves=load_displacement_figure(model, facts.samples, facts.response),
        held_out=None if held_out is None else accuracy_figure(held_out, model.trained_depth),
        latency=latency_figure(facts.latencies, facts.response),
        surfaces=[
            surface_figure(model, displacement, facts.factor, force, facts.central, view)
            for view in VIEWS
        ],
        field=None if comparison is None else field_figure(model, comparison),
    )
