"""The rendered tissue against the full order at one held-out tool position (issue 15).

``hapticrom accuracy`` measures how far the runtime's surface field is from the full-order
one; this figure shows where. Among the solved positions of a held-out campaign directory
(``hapticrom accuracy`` writes one: MODEL.heldout-N) it picks the load step, within the
trained depth, where PODI's field is farthest from the full order (relative L2 over the
surface vertices, as the check measures it), and draws there:

- |u| in plan view (the samples' mean normal towards the viewer, as
  :func:`~hapticrom.shared.geometry.plan_view`): full order | the runtime's default field
  (:func:`~hapticrom.online.simulator.default_interpolation`: "transport" where the model
  has a chart, "compliance" where it has contact fields) | its "podi" field, on one colour
  scale, only the triangles facing the viewer (a cornea or a liver has a lower sheet too,
  which would show through). A model whose default is PODI itself (neither chart nor
  contact fields) gets two panels, full order | podi;
- a cross-section: the displacement into the organ (along the contact's inward normal) on
  the straight plan-view line through the tool and the nearest other training sample, where
  PODI's blend leaves a dent of its own.

The campaign files are read here with h5py (checksums verified), not through
``hapticrom.offline``: the report runs without the finite-element stack. Units: mm.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from hapticrom.online.model import ReducedModel, load
from hapticrom.online.simulator import default_interpolation
from hapticrom.report.content import RESPONSE_LABELS
from hapticrom.report.figures import Png, new_figure, render, require_matplotlib
from hapticrom.shared.checksum import array_digest
from hapticrom.shared.errors import InputError, StepInputError
from hapticrom.shared.geometry import face_area_vectors

# What each runtime field is, in the words of the report page (page._field_section).
DESCRIPTIONS = {
    "transport": "each neighbouring sample's field carried to the contact",
    "compliance": "the tool's linear dent at the contact plus PODI's blend of the nonlinear rest",
    "podi": "blended where each was trained",
}
# The lines of the cross-section: colour, style, width.
STYLES = {
    "full order": ("k", "-", 2.4),
    "transport": ("C0", "-", 1.6),
    "compliance": ("C2", "-", 1.6),
    "podi": ("C1", "--", 1.6),
}
PNG_NAME = "held-out-field.png"
# A triangle steeper than this to the line of sight is seen edge-on: it belongs to no sheet
# of the plan view (the cornea's rim, the liver's flanks).
FACING = math.cos(math.radians(80.0))
SECTION_POINTS = 401  # along the cross-section line
SECTION_HALF_WIDTH = 4.0  # in distances from the tool to the nearest other sample
WINDOW = 1.3  # the plan views' half side, in section half widths
HELD_OUT_COMMAND = "mpirun -n 2 hapticrom accuracy {model}"


# -- the held-out campaign directory ------------------------------------------------------
@dataclass(frozen=True)
class HeldOutSolve:
    """One solved held-out position: the full-order field at the model's surface vertices."""

    index: int
    point: np.ndarray  # (3,) mm, where the tool pressed
    depths: np.ndarray  # (steps,) mm, the contact's displacement along the load direction
    surface: np.ndarray  # (steps, V, 3) mm, the full-order displacement of the vertices


def require_held_out_dir(work: str | Path, model_path: str | Path) -> Path:
    """``work`` as a Path if it is a directory; InputError naming it (and how to write one)
    if not. Cheap: called before the model is loaded."""
    work = Path(work)
    if not work.is_dir():
        raise InputError(
            f"held-out directory {work} not found; write one with "
            + HELD_OUT_COMMAND.format(model=model_path)
        )
    return work


def solved_positions(model: ReducedModel, work: str | Path) -> list[HeldOutSolve]:
    """Every solved position of the campaign directory ``work``, checked against ``model``;
    InputError naming the directory (or the file) when it is missing, of another mesh,
    damaged or holds no solved position."""
    work = require_held_out_dir(work, model.path)
    _check_same_mesh(model, work)
    nodes = np.asarray(model.artifact["surface"]["nodes"], dtype=np.int64)
    solves = [_read_solve(path, nodes) for path in sorted((work / "solves").glob("position-*.h5"))]
    solves = [solve for solve in solves if solve is not None]
    if not solves:
        raise InputError(
            f"held-out directory {work} holds no solved position (solves/position-*.h5 with "
            "status 'solved')"
        )
    return solves


def _check_same_mesh(model: ReducedModel, work: Path) -> None:
    """InputError unless ``work`` is a campaign on the model's mesh: the full-order fields are
    indexed by the mesh's nodes, another mesh's would be read as nonsense."""
    manifest = work / "manifest.json"
    try:
        data = json.loads(manifest.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise InputError(
            f"held-out directory {work} is not a campaign (no manifest.json)"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{manifest} cannot be read as JSON ({exc})") from None
    mesh = data.get("mesh") if isinstance(data, dict) else None
    held = mesh.get("sha256") if isinstance(mesh, dict) else None
    trained = model.artifact.group_attrs["model"].get("mesh_sha256")
    if not isinstance(held, str):
        raise InputError(f"{manifest} names no mesh (mesh.sha256)")
    if trained is not None and held != trained:
        raise InputError(
            f"held-out directory {work} was solved on another mesh than {model.path} "
            f"(mesh sha256 {held[:12]}... against {str(trained)[:12]}...)"
        )


def _read_solve(path: Path, nodes: np.ndarray) -> HeldOutSolve | None:
    """The solve stored in ``path`` if it is complete and solved, else None; InputError
    naming the file if it is damaged or misshapen."""
    try:
        with h5py.File(path, "r") as f:
            if not f.attrs.get("complete", False) or f.attrs.get("status") != "solved":
                return None
            point = _finite_vector(f.attrs.get("point"), path, "point")
            direction = _finite_vector(f.attrs.get("direction"), path, "direction")
            index = int(f.attrs["index"])
            displacement = _checked(f, "displacement", path)
            contact = _checked(f, "contact_displacement", path)
    except InputError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        # h5py reports damaged metadata with any of these, not only OSError
        raise InputError(f"{path} cannot be read as HDF5 ({exc})") from None
    steps = len(contact)
    if contact.shape != (steps, 3) or displacement.ndim != 2 or len(displacement) != steps:
        raise InputError(f"{path}: displacement and contact_displacement disagree in shape")
    if displacement.shape[1] % 3 or displacement.shape[1] // 3 <= nodes.max():
        raise InputError(
            f"{path}: displacement has {displacement.shape[1]} columns, not 3 per node of the "
            f"model's mesh (its surface reaches node {nodes.max()})"
        )
    if not (np.isfinite(displacement).all() and np.isfinite(contact).all()):
        raise InputError(f"{path}: the stored displacements are not all finite")
    surface = displacement.reshape(steps, -1, 3)[:, nodes]
    return HeldOutSolve(index, point, contact @ direction, surface)


def _finite_vector(value, path: Path, name: str) -> np.ndarray:
    vector = np.asarray(value if value is not None else [], dtype=np.float64)
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise InputError(f"{path}: attribute {name} must be three finite numbers")
    return vector


def panels(runtime: str) -> tuple[str, ...]:
    """The fields shown, left to right: the full order, the runtime's default interpolation
    ``runtime`` and PODI; PODI once when it is the default itself."""
    return ("full order", "podi") if runtime == "podi" else ("full order", runtime, "podi")


def _checked(f: h5py.File, name: str, path: Path) -> np.ndarray:
    data = f[name][()]
    if array_digest(data) != f[name].attrs.get("sha256"):
        raise InputError(f"{path}: dataset {name} fails its checksum (damaged file)")
    return np.asarray(data, dtype=np.float64)


# -- the step to show and the three fields ---------------------------------------------------
@dataclass(frozen=True)
class FieldComparison:
    """The full-order and runtime surface fields at one held-out position and depth."""

    index: int  # the held-out position
    point: np.ndarray  # (3,) mm
    step: int  # 0-based load step of the solve
    steps: int
    depth: float  # mm
    normal: np.ndarray  # (3,) the outward normal at the contact (the runtime's)
    response: str  # the runtime's force response ("anm" or "curves")
    runtime: str  # the model's default interpolation: "transport", "compliance" or "podi"
    fields: dict[str, np.ndarray]  # self.panels -> (V, 3) mm
    outside: bool  # the runtime clamped the contact to its trained region

    @property
    def panels(self) -> tuple[str, ...]:
        """The fields compared, left to right (:func:`panels`)."""
        return panels(self.runtime)

    @property
    def runtime_fields(self) -> tuple[str, ...]:
        """The runtime's fields compared: the default interpolation, then PODI (once)."""
        return self.panels[1:]

    def error(self, name: str) -> float:
        """Relative L2 error of a runtime field against the full order (surface vertices)."""
        return relative_l2(self.fields[name], self.fields["full order"])


def relative_l2(approx: np.ndarray, exact: np.ndarray) -> float:
    """||approx - exact|| / ||exact|| (NaN for an exact zero)."""
    norm = float(np.linalg.norm(exact))
    return float(np.linalg.norm(approx - exact)) / norm if norm > 0 else float("nan")


def worst_podi_step(model: ReducedModel, solves: list[HeldOutSolve], response: str):
    """(solve, step) where PODI's field error is largest among the steps within the trained
    depth, preferring positions inside the trained region; InputError if there is none."""
    out = np.zeros_like(model.vertices)
    best, best_key = None, None
    for solve in solves:
        sim = model.simulator("podi", response)
        sim.set_contact(solve.point)
        inside = not sim.outside_trained_region
        for k, depth in enumerate(solve.depths):
            normal = sim.contact_normal.copy()
            try:
                sim.step_displacement(-depth * normal)
            except StepInputError:  # deeper than the runtime accepts: not a step to show
                continue
            if sim.beyond_trained_depth:
                continue
            error = relative_l2(sim.surface_displacement(out), solve.surface[k])
            if np.isfinite(error) and (best_key is None or (inside, error) > best_key):
                best, best_key = (solve, k), (inside, error)
    if best is None:
        raise InputError(
            "no held-out step lies within the model's trained depth "
            f"({model.trained_depth:.4g} mm) with a nonzero full-order field"
        )
    return best


def compare_fields(model: ReducedModel, solve: HeldOutSolve, step: int, response: str,
                   runtime: str | None = None):  # fmt: skip
    """The full-order field and the runtime's ``runtime`` (default: the model's default
    interpolation) and PODI fields at ``step``."""
    runtime = default_interpolation(model) if runtime is None else runtime
    fields = {"full order": solve.surface[step]}
    normal, outside = None, False
    for name in panels(runtime)[1:]:
        sim = model.simulator(name, response)
        sim.set_contact(solve.point)
        normal = sim.contact_normal.copy()
        sim.step_displacement(-solve.depths[step] * normal)
        fields[name] = sim.surface_displacement(np.zeros_like(model.vertices))
        outside = sim.outside_trained_region
    return FieldComparison(
        solve.index, solve.point, step, len(solve.depths), float(solve.depths[step]), normal,
        response, runtime, fields, outside,
    )  # fmt: skip


def held_out_comparison(model: ReducedModel, work: str | Path) -> FieldComparison:
    """The comparison the figure shows: the held-out step where PODI's field is worst, the
    runtime's default interpolation and PODI there."""
    solves = solved_positions(model, work)
    response = "anm" if model.anm else "curves"  # the runtime's default force
    solve, step = worst_podi_step(model, solves, response)
    return compare_fields(model, solve, step, response)


# -- plan view and cross-section ----------------------------------------------------------
@dataclass(frozen=True)
class PlanView:
    """The surface seen along the samples' mean normal: plan coordinates (V, 2) mm, the
    triangles facing the viewer (lowest first, so the upper sheet is drawn last) and
    their heights towards the viewer."""

    plan: np.ndarray
    triangles: np.ndarray
    heights: np.ndarray  # (V,) mm along the line of sight, towards the viewer


def plan_view_of(model: ReducedModel) -> PlanView:
    """The model's surface in its plan view, the triangles that face the viewer only."""
    towards_viewer = np.cross(model.plan_axes[0], model.plan_axes[1])
    relative = model.vertices - model.plan_origin
    area = face_area_vectors(model.vertices, model.triangles)
    facing = area @ towards_viewer > FACING * np.linalg.norm(area, axis=1)
    triangles = model.triangles[facing]
    heights = relative @ towards_viewer
    triangles = triangles[np.argsort(heights[triangles].mean(axis=1), kind="stable")]
    return PlanView(relative @ model.plan_axes.T, triangles, heights)


def locate_on_sheet(view: PlanView, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For plan points (N, 2): the facing triangle holding each (the highest where sheets
    overlap; -1 where none does) and its barycentric weights (N, 3)."""
    a, b, c = (view.plan[view.triangles[:, j]] for j in range(3))
    e1, e2 = b - a, c - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # > 0: a facing triangle keeps its turn
    height = view.heights[view.triangles].mean(axis=1)
    found = np.full(len(points), -1)
    weights = np.zeros((len(points), 3))
    for i, p in enumerate(points):
        w = p - a
        l1 = (w[:, 0] * e2[:, 1] - w[:, 1] * e2[:, 0]) / det
        l2 = (e1[:, 0] * w[:, 1] - e1[:, 1] * w[:, 0]) / det
        inside = np.flatnonzero((l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9))
        if len(inside):
            t = inside[np.argmax(height[inside])]
            found[i], weights[i] = t, (1.0 - l1[t] - l2[t], l1[t], l2[t])
    return found, weights


@dataclass(frozen=True)
class Section:
    """The displacement into the organ (mm) along a plan-view line through the tool."""

    tool: np.ndarray  # (2,) mm, the tool in plan view
    direction: np.ndarray  # (2,) the line's unit direction in plan view
    distance: np.ndarray  # (N,) mm along the line from the tool
    inward: dict[str, np.ndarray]  # the comparison's panels -> (N,) mm, NaN off the sheet
    sample: int  # the training sample the line runs towards
    sample_distance: float  # mm from the tool in plan view

    def error(self, name: str) -> float:
        """Relative L2 error of a runtime field's profile against the full order's, over
        the points of the line on the facing sheet."""
        exact = self.inward["full order"]
        on = np.isfinite(exact)
        return relative_l2(self.inward[name][on], exact[on])


def cross_section(model: ReducedModel, view: PlanView, comparison: FieldComparison) -> Section:
    """The section through the tool towards the nearest training sample other than one at
    the tool itself, out to :data:`SECTION_HALF_WIDTH` times that distance either side."""
    tool = (comparison.point - model.plan_origin) @ model.plan_axes.T
    offsets = model.plan_points - tool
    distances = np.linalg.norm(offsets, axis=1)
    apart = distances > 1e-6 * max(float(np.ptp(view.plan)), 1.0)  # not the tool's own sample
    sample = int(np.flatnonzero(apart)[np.argmin(distances[apart])])
    direction = offsets[sample] / distances[sample]
    reach = SECTION_HALF_WIDTH * distances[sample]
    distance = np.linspace(-reach, reach, SECTION_POINTS)
    found, weights = locate_on_sheet(view, tool + distance[:, None] * direction)
    corners = view.triangles[np.maximum(found, 0)]
    inward = {}
    for name, field in comparison.fields.items():
        depth_in = -(field @ comparison.normal)
        values = np.einsum("ij,ij->i", weights, depth_in[corners])
        inward[name] = np.where(found >= 0, values, np.nan)
    return Section(tool, direction, distance, inward, sample, float(distances[sample]))


# -- the figure --------------------------------------------------------------------------------
def field_figure(model: ReducedModel, comparison: FieldComparison) -> Png:
    """Plan views of |u| (full order, the runtime's default, PODI) on one colour scale above
    the cross-section through the tool."""
    from matplotlib import colormaps
    from matplotlib.colors import Normalize

    view = plan_view_of(model)
    section = cross_section(model, view, comparison)
    shown = np.unique(view.triangles)
    magnitudes = {name: np.linalg.norm(f, axis=1) for name, f in comparison.fields.items()}
    top = max(float(m[shown].max()) for m in magnitudes.values())
    norm, cmap = Normalize(0.0, top or 1.0), colormaps["viridis"]
    fig = new_figure(13, 8.6)
    names = comparison.panels
    grid = fig.add_gridspec(2, len(names), height_ratios=[1.3, 1])
    axes = [fig.add_subplot(grid[0, j]) for j in range(len(names))]
    for ax, name in zip(axes, names, strict=True):
        _plan_panel(ax, model, view, magnitudes[name], norm, cmap, section)
        error = "" if name == "full order" else f" (error {100 * comparison.error(name):.1f} %)"
        ax.set_title(("" if name == "full order" else "runtime ") + name + error, fontsize=10)
    fig.colorbar(axes[0].collections[0], ax=axes, shrink=0.85, label="|u| (mm)")
    _section_panel(fig.add_subplot(grid[1, :]), section, comparison)
    fig.suptitle(
        f"Held-out position {comparison.index}, indentation {comparison.depth:.3g} mm "
        f"(step {comparison.step + 1} of {comparison.steps}): the rendered surface vs the "
        "full order",
        fontsize=11,
    )
    words = [name if name != "podi" else "PODI" for name in names]
    alt = (
        "surface displacement at a held-out position: "
        + (" and ".join(words) if len(words) < 3 else f"{words[0]}, {words[1]} and {words[2]}")
        + " in plan view, and a cross-section through the tool"
    )
    return render(fig, PNG_NAME, alt)


def _plan_panel(ax, model, view: PlanView, magnitude, norm, cmap, section: Section) -> None:
    """|u| on the facing triangles near the tool, the samples, the tool and the section."""
    x, y = view.plan[:, 0], view.plan[:, 1]
    ax.tripcolor(x, y, view.triangles, magnitude, shading="gouraud", norm=norm, cmap=cmap)
    samples = model.plan_points
    ax.plot(samples[:, 0], samples[:, 1], "o", color="w", mec="k", mew=0.5, ms=4)
    ends = section.tool + np.outer(section.distance[[0, -1]], section.direction)
    ax.plot(ends[:, 0], ends[:, 1], "--", color="w", lw=1.2)
    ax.plot(*section.tool, "+", color="C3", ms=14, mew=2.5)
    half = WINDOW * section.distance[-1]  # the dent, not the whole organ
    ax.set(
        xlim=(section.tool[0] - half, section.tool[0] + half),
        ylim=(section.tool[1] - half, section.tool[1] + half),
        xlabel="plan x (mm)",
        ylabel="plan y (mm)",
        aspect="equal",
    )
    ax.tick_params(labelsize=8)


def _section_panel(ax, section: Section, comparison: FieldComparison) -> None:
    """The inward displacement of the fields compared along the line through the tool."""
    for name in comparison.panels:
        colour, line, width = STYLES[name]
        label = name if name == "full order" else f"runtime {name}"
        ax.plot(section.distance, section.inward[name], line, color=colour, lw=width, label=label)
    ax.axvline(0.0, color="C3", lw=1, label="tool (+)")
    ax.axvline(
        section.sample_distance, color="0.4", ls=":", lw=1.2,
        label=f"training sample {section.sample}",
    )  # fmt: skip
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set(
        xlabel="distance along the dashed line, from the tool towards the sample (mm)",
        ylabel="displacement into the organ, -u.n (mm)",
        title="Cross-section through the tool towards the nearest other training sample "
        f"(n: the outward normal at the contact; {RESPONSE_LABELS[comparison.response]})",
    )
    ax.title.set_fontsize(10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")


def caption(model: ReducedModel, comparison: FieldComparison) -> str:
    """One paragraph: where, how deep, the runtime fields' relative L2 errors over the
    surface and along the cross-section."""
    section = cross_section(model, plan_view_of(model), comparison)
    x, y, z = comparison.point
    clamped = " (outside the trained region: the runtime clamps the contact there)"
    names = comparison.runtime_fields
    label = {name: "PODI" if name == "podi" else name for name in names}
    surface = ", ".join(f"{label[n]} {100 * comparison.error(n):.2f} %" for n in names)
    along = ", ".join(f"{label[n]} {100 * section.error(n):.2f} %" for n in names)
    return (
        f"Held-out position {comparison.index} at ({x:.3g}, {y:.3g}, {z:.3g}) mm, step "
        f"{comparison.step + 1} of {comparison.steps}, indentation {comparison.depth:.3g} mm "
        f"(trained to {model.trained_depth:.3g} mm){clamped if comparison.outside else ''}: "
        "of the steps within the trained depth, the one where PODI's surface field is "
        "farthest from the full order. Relative L2 error of the field over all surface "
        f"vertices: {surface}; of the displacement into the organ along the cross-section: "
        f"{along}. The plan views show |u| of the sheet facing "
        f"the viewer within {WINDOW * section.distance[-1]:.3g} mm of the tool; the errors "
        "count every component of every vertex."
    )


def write_field_comparison(model_path: str | Path, work: str | Path, out_dir: str | Path):
    """Write the figure as ``out_dir/held-out-field.png``; return (its path, its caption).
    Nothing is written when the model or the held-out directory is refused."""
    require_matplotlib()
    require_held_out_dir(work, model_path)
    model = load(model_path)
    comparison = held_out_comparison(model, work)
    png = field_figure(model, comparison)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / png.name
    path.write_bytes(png.data)
    return path, caption(model, comparison)
