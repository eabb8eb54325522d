"""POD-ANM of one problem against full Newton: the curves and error tables of thesis ch. 3.

:func:`run_study` solves the full-order problem by Newton (every increment a
reference point), builds the reduced space from the snapshots of every other
increment (so half of the reference points are not snapshots), runs the ANM
continuation in the reduced space and compares the load-response curves:

- per order k = 1..N, the first section alone (one tangent, at the reference
  state) truncated at order k, inside its validity radius;
- the continuation at order N over the whole load range.

Units: load factor (1 = the problem's load), force N, displacement mm.
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.la import InsertMode

from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.mpi import print0
from hapticrom.offline.reduce.anm import (
    ANMOptions,
    Branch,
    ComplexResidual,
    ReducedResidual,
    ReducedSpace,
    continuation,
    root,
    snapshot_space,
    validity_radius,
)
from hapticrom.offline.reduce.pod import Truncation


@dataclass
class Snapshots:
    """Owned rows of the converged states of a full Newton solve, and its curve."""

    load_factor: np.ndarray  # (K,)
    u: np.ndarray  # (rows, K) mm
    p: np.ndarray | None  # (cells, K) MPa
    response: np.ndarray  # (K,) tool force along the tool (N) or displacement along the load (mm)


def _owned(w: fem.Function) -> np.ndarray:
    im = w.function_space.dofmap.index_map
    return w.x.array[: im.size_local * w.function_space.dofmap.index_map_bs].copy()


def load_direction(fom: FullOrderModel) -> np.ndarray:
    """Unit vector along the problem's load vector."""
    v = fom.load_vector
    return v / np.linalg.norm(v)


def solve_with_snapshots(fom: FullOrderModel) -> Snapshots:
    """Full Newton over the configured increments, keeping every converged state."""
    lams, us, ps, responses = [], [], [], []
    direction = load_direction(fom)
    displacement_control = fom.config.load.mode == "displacement"

    def keep(record, force, disp):
        lams.append(record.load_factor)
        us.append(_owned(fom.model.u))
        ps.append(_owned(fom.model.p) if fom.model.p is not None else None)
        responses.append(float((force if displacement_control else disp) @ direction))

    fom.solve(on_step=keep)
    p = np.column_stack(ps) if ps and ps[0] is not None else None
    return Snapshots(np.array(lams), np.column_stack(us), p, np.array(responses))


def external_load(fom: FullOrderModel) -> np.ndarray:
    """Owned rows of the external load vector at load factor 1 (N), zero for a tool patch."""
    model = fom.model
    if fom.config.load.mode == "displacement":
        return np.zeros(_owned(model.u).size)
    fom.set_load(1.0)
    form = fem.form(ufl.derivative(model.external_work(), model.u, ufl.TestFunction(model.V)))
    b = fem.assemble_vector(form)
    b.scatter_reverse(InsertMode.add)
    fom.set_load(0.0)
    return _owned_array(b.array, model.V)


def _owned_array(array, V):
    return array[: V.dofmap.index_map.size_local * V.dofmap.index_map_bs].copy()


def reduced_space(
    fom: FullOrderModel, snaps: Snapshots, truncation: Truncation | None = None
) -> tuple[ReducedSpace, np.ndarray]:
    """The reduced space of a full-order problem's snapshots; see :func:`snapshot_space`."""
    if fom.config.load.mode == "displacement":
        mode, size = "displacement", float(np.linalg.norm(fom.load_vector))
    else:
        mode, size = "force", None
    return snapshot_space(
        fom.comm, snaps.load_factor, snaps.u, snaps.p, mode, external_load(fom), size, truncation
    )


@dataclass
class StudyResult:
    """The study's reference, continuation, error tables, space sizes and timings."""

    reference: Snapshots
    branch: Branch
    first_section_errors: list[dict]  # per order
    continuation_error: float  # max relative error over the reference points
    modes: tuple[int, int]  # (n, n_p)
    seconds: dict


def _relative_errors(branch_or_section, lams, reference, scale):
    return np.abs(np.array([branch_or_section(l) for l in lams]) - reference) / scale


def every_other(snaps: Snapshots) -> Snapshots:
    """The snapshots of every other increment (the first, third, ...)."""
    return Snapshots(
        snaps.load_factor[::2],
        snaps.u[:, ::2],
        None if snaps.p is None else snaps.p[:, ::2],
        snaps.response[::2],
    )


def first_section_errors(branch: Branch, reference: Snapshots, options: ANMOptions, say):
    """Per order k = 1..N: the first section truncated at order k, its validity load and
    its largest error (relative to max |response|) at the reference points inside it."""
    lams, ref = reference.load_factor, reference.response
    size = float(np.abs(ref).max())
    first = branch.sections[0]
    per_order = []
    for k in range(1, options.order + 1):
        a_max = (
            validity_radius(first.Y[: k + 1], branch.scale, options.tolerance)
            if k >= 2
            else math.nan
        )
        section = first.truncated(k, a_max if math.isfinite(a_max) else first.a_max)
        lam_max = float(section.load(section.a_max)) if math.isfinite(a_max) else math.nan
        inside = lams[lams <= lam_max] if math.isfinite(lam_max) else lams[:0]
        err_inside = float(
            _relative_errors(
                lambda l, s=section: _single(s, l), inside, ref[: inside.size], size
            ).max()
        ) if inside.size else math.nan  # fmt: skip
        per_order.append({"order": k, "validity_load": lam_max, "max_error_inside": err_inside})
        say(
            f"  first section, order {k:2d}: valid to load factor {lam_max:.4g}, "
            f"max error inside {100 * err_inside:.3f} %"
        )
    return per_order


def run_study(
    fom: FullOrderModel,
    options: ANMOptions | None = None,
    truncation: Truncation | None = None,
    out_dir: str | Path | None = None,
    verbose: bool = True,
) -> StudyResult:
    """The study of the module docstring on one full-order problem (collective)."""
    comm = fom.comm
    options = options or ANMOptions()
    say = (lambda s: print0(comm, s)) if verbose else (lambda s: None)
    t0 = time.perf_counter()
    snaps = solve_with_snapshots(fom)
    t_full = time.perf_counter() - t0
    train = every_other(snaps)  # the other increments are held out
    t0 = time.perf_counter()
    space, scale = reduced_space(fom, train, truncation)
    residual = ReducedResidual(ComplexResidual(fom.model), space, comm)
    t_setup = time.perf_counter() - t0
    say(
        f"POD-ANM: {space.n} displacement + {space.n_p} pressure modes from "
        f"{train.load_factor.size} snapshots; order {options.order}, "
        f"tolerance {options.tolerance:g}"
    )
    t0 = time.perf_counter()
    branch = continuation(residual, scale, options)
    t_anm = time.perf_counter() - t0
    say(
        f"continuation: {len(branch.sections)} section(s) to load factor "
        f"{branch.load_range[1]:.4g}, {branch.evaluations} residual evaluations, {t_anm:.2f} s"
    )
    size = float(np.abs(snaps.response).max())
    errors = _relative_errors(branch.response_at, snaps.load_factor, snaps.response, size)
    per_order = first_section_errors(branch, snaps, options, say)
    say(
        f"continuation at order {options.order}: max error {100 * errors.max():.4f} % "
        "of max |response| at the full-Newton points"
    )
    result = StudyResult(
        snaps, branch, per_order, float(errors.max()), (space.n, space.n_p),
        {"full_newton": t_full, "setup": t_setup, "anm": t_anm},
    )  # fmt: skip
    if out_dir is not None and comm.rank == 0:
        for path in write_report(result, Path(out_dir), space, options.order):
            say(f"wrote {path}")
    return result


def _single(section, load):
    """Response of one section at a load factor (root-find on that section alone)."""
    return float(section.value(root(section, load)))


def _labels(mode: str) -> tuple[str, str]:
    if mode == "displacement":
        return "tool depth (mm)", "tool force along the tool (N)"
    return "load (N)", "displacement along the load (mm)"


def write_report(result: StudyResult, out: Path, space: ReducedSpace, order: int) -> list[Path]:
    """anm-table.csv (every reference point), anm-orders.csv and anm-curves.png, on rank 0."""
    out.mkdir(parents=True, exist_ok=True)
    ref, branch = result.reference, result.branch
    first = branch.sections[0]
    size = float(np.abs(ref.response).max())
    table = out / "anm-table.csv"
    with open(table, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["load_factor", "load", "snapshot", "full_newton", "anm_rom", "error_percent"])
        for k, (lam, r) in enumerate(zip(ref.load_factor, ref.response, strict=True)):
            rom = branch.response_at(lam)
            w.writerow([f"{lam:.6g}", f"{lam * space.load_size:.6g}", int(k % 2 == 0),
                        f"{r:.8g}", f"{rom:.8g}", f"{100 * abs(rom - r) / size:.4g}"])  # fmt: skip
    orders = out / "anm-orders.csv"
    with open(orders, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["order", "validity_load_factor", "max_error_inside_percent"])
        for row in result.first_section_errors:
            w.writerow([row["order"], f"{row['validity_load']:.6g}",
                        f"{100 * row['max_error_inside']:.4g}"])  # fmt: skip
    png = out / "anm-curves.png"
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xlabel, ylabel = _labels(space.mode)
    fig, ax = plt.subplots(figsize=(7, 5))
    a_lin = 1.0 / max(first.Y[1, -1], 1e-12)  # where the order-1 line reaches load factor 1
    a = np.linspace(0.0, 1.2 * a_lin, 400)
    for k in range(1, order + 1):
        lam = np.polynomial.polynomial.polyval(a, first.Y[: k + 1, -1])
        val = np.polynomial.polynomial.polyval(a, first.response[: k + 1])
        keep = (lam >= 0) & (lam <= 1.05) & (np.abs(val) <= 1.5 * size)
        ax.plot(lam[keep] * space.load_size, val[keep], lw=0.8, label=f"one section, order {k}")
    grid = np.linspace(0.0, min(1.0, branch.load_range[1]), 200)
    ax.plot(grid * space.load_size, [branch.response_at(g) for g in grid], "k-", lw=2,
            label=f"ANM-ROM, {len(branch.sections)} sections of order {order}")  # fmt: skip
    ax.plot(ref.load_factor * space.load_size, ref.response, "o", mfc="none", color="C3",
            label="full Newton")  # fmt: skip
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)
    return [table, orders, png]
