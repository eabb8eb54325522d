"""The report's figures: PNGs drawn on ``Figure`` objects with the Agg canvas.

Never through pyplot, so nothing global (backend, open figures) changes. Needs matplotlib
(the ``report`` extra); :func:`require_matplotlib` says so when it is missing.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from hapticrom.online.model import ReducedModel
from hapticrom.report.content import RESPONSE_LABELS, normalised_spectrum, rom_forces
from hapticrom.report.heldout import HeldOutResults
from hapticrom.report.timing import LATENCY_TARGET
from hapticrom.shared.accuracy import target
from hapticrom.shared.errors import HapticromError

DPI = 110


@dataclass(frozen=True)
class Png:
    """One rendered figure: its file name in the report directory, bytes and alt text."""

    name: str
    data: bytes
    alt: str


# -- matplotlib, without pyplot --------------------------------------------------------------
def require_matplotlib() -> None:
    """HapticromError saying what to install when matplotlib is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise HapticromError(
            "hapticrom report draws its figures with matplotlib: pip install 'hapticrom[report]' "
            "(or pip install matplotlib)"
        ) from None


def new_figure(width: float, height: float, layout: str | None = "constrained"):
    """A Figure (inches) on its own Agg canvas, outside pyplot."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def render(fig, name: str, alt: str) -> Png:
    """The figure as PNG bytes, under ``name`` with ``alt`` text."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    return Png(name, buffer.getvalue(), alt)


# -- POD eigenvalues, load-displacement curves -------------------------------------------------
def eigenvalue_figure(model: ReducedModel, central: int) -> Png:
    """Per-sample POD spectra (the central sample highlighted), and the global one if any."""
    artifact = model.artifact
    per_sample = artifact["samples"]["eigenvalues"]
    has_global = "global" in artifact.groups
    fig = new_figure(11 if has_global else 6.5, 4.2)
    axes = fig.subplots(1, 2 if has_global else 1, squeeze=False)[0]
    ax = axes[0]
    index = np.arange(1, per_sample.shape[1] + 1)
    ratios = normalised_spectrum(per_sample)
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
    return render(fig, "eigenvalues.png", "POD eigenvalue decay, per sample and global")


def _plot_global_spectrum(ax, group: dict) -> None:
    ratio = normalised_spectrum(group["eigenvalues"])
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


def load_displacement_figure(model: ReducedModel, samples: list[int], response: str) -> Png:
    """The runtime's force along the indentation at ``samples`` against the stored curves."""
    from matplotlib.lines import Line2D

    knots = np.asarray(model.artifact["samples"]["depth"])
    fine = np.linspace(0.0, knots[-1], 201)  # the grid's end: the deepest sample's (2.3)
    radii = np.linalg.norm(model.plan_points, axis=1)
    fig = new_figure(7.5, 6.5)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[2.2, 1])
    for colour, i in enumerate(samples):
        c = f"C{colour}"
        top.plot(fine, rom_forces(model, i, fine, response), "-", color=c, lw=1.5)
        solved = knots <= model.solved_depth[i] * (1 + 1e-9)  # beyond: a continuation
        top.plot(knots[solved], model.force[i, solved], "o", color=c, mfc="none", ms=6)
        mark = np.flatnonzero(solved[1:]) + 1
        at_knots = rom_forces(model, i, knots[mark], response)
        error = 100 * (at_knots - model.force[i, mark]) / model.force[i, mark]
        bottom.plot(knots[mark], error, "o-", color=c, ms=4, lw=1)
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
    return render(fig, "load-displacement.png", "load-displacement curves, ROM vs full order")


# -- held-out errors, step latency -------------------------------------------------------------


def accuracy_figure(results: HeldOutResults, trained_depth: float) -> Png:
    """Force error vs depth at each held-out position; the field error beside it if known."""
    panels = [("force", 100 * results.errors, "|F_ROM - F_FEM| / F_FEM (%)")]
    if results.field is not None:
        panels.append(("field", 100 * results.field, "surface-field relative L2 error (%)"))
    fig = new_figure(7.5 if len(panels) == 1 else 12, 4.2)
    count = len(set(results.positions.tolist()))
    for ax, (quantity, errors, ylabel) in zip(fig.subplots(1, len(panels), squeeze=False)[0],
                                              panels, strict=True):  # fmt: skip
        _plot_errors(ax, results, errors, quantity)
        # force-controlled checks may press deeper; per step where the file says (format 3)
        if results.beyond is None and results.depths.max() > trained_depth:
            label = f"trained depth {trained_depth:.3g} mm (beyond: extrapolated)"
            ax.axvline(trained_depth, color="0.3", ls=":", lw=1, label=label)
        title = "Force" if quantity == "force" else "Surface-field"
        ax.set(
            xlabel="indentation depth (mm)",
            ylabel=ylabel,
            ylim=(0, None),
            title=f"{title} error at {count} held-out positions (one line each)",
        )
        _log_if_spread(ax, errors, quantity)
        ax.title.set_fontsize(10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="center right")  # the errors sit low, the targets high
    return render(fig, "held-out-error.png", "force and field errors at held-out positions")


def _log_if_spread(ax, errors: np.ndarray, quantity: str) -> None:
    """A logarithmic axis where one response's errors pass ten times the target (PODI's
    field off the liver's samples, 50-220 %): on a linear one the others lie flat on zero."""
    limit = max((target(quantity, name) or 0.0 for name in RESPONSE_LABELS), default=0.0)
    positive = errors[np.isfinite(errors) & (errors > 0)]
    if limit > 0 and positive.size and positive.max() > 10 * 100 * limit:
        ax.set_yscale("log")
        ax.set_ylim(max(positive.min() / 2, 1e-3), 2 * positive.max())


def _plot_errors(ax, results: HeldOutResults, errors: np.ndarray, quantity: str) -> None:
    """One line per position and response (dotted where the runtime clamped the contact to
    its trained region), open markers at the steps it extrapolated in depth, and each
    response's target (dashed)."""
    positions = list(dict.fromkeys(results.positions.tolist()))
    for c, name in enumerate(results.responses):
        for k, position in enumerate(positions):
            mask = results.positions == position
            order = np.argsort(results.depths[mask])
            depths, values = results.depths[mask][order], errors[mask, c][order]
            ax.plot(depths, values, ls=":" if position in results.outside else "-",
                    color=f"C{c}", alpha=0.6, lw=1, label=name if k == 0 else None)  # fmt: skip
            beyond = (np.zeros(len(depths), bool) if results.beyond is None
                      else results.beyond[mask, c][order])  # fmt: skip
            ax.plot(depths[~beyond], values[~beyond], "o", color=f"C{c}", alpha=0.6, ms=3)
            ax.plot(depths[beyond], values[beyond], "o", mfc="none", color=f"C{c}", alpha=0.8,
                    ms=4)  # fmt: skip
        limit = target(quantity, name)
        if c == 0 and results.outside & set(positions):
            ax.plot([], [], ls=":", color="0.4", label="outside the trained region")
        if c == 0 and results.beyond is not None and results.beyond.any():
            ax.plot([], [], "o", mfc="none", color="0.4", label="beyond the solved depth")
        if limit is not None:
            ax.axhline(
                100 * limit,
                color=f"C{c}",
                ls="--",
                lw=1,
                label=f"target {name}: {100 * limit:g} %",
            )


def latency_figure(us: np.ndarray, response: str) -> Png:
    """Histogram of the step latencies (us) with p50, p99 and the p99 target."""
    p50, p99, p999 = np.percentile(us, [50, 99, 99.9])
    target = LATENCY_TARGET
    upper = max(1.3 * p999, 1.2 * target)  # the rare long outliers would squash the bulk
    beyond = int(np.count_nonzero(us > upper))
    fig = new_figure(7.5, 4.0)
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
    return render(fig, "latency.png", "histogram of step_displacement latency")
