"""ParaView files of a reduced model (``hapticrom export MODEL.h5 --out DIR``).

What :func:`export_model` writes into ``DIR`` (VTK XML PolyData, :mod:`hapticrom.vtk`):

- ``surface.vtp``: the surface the runtime renders (``/surface``): vertices (mm),
  triangles, the mesh node of each vertex and the surface group of each triangle.
- ``samples.vtp``: the training samples (``/samples``) as points, with their outward
  normals, force curves and stiffness, and the Delaunay triangles that blend them.
- ``modes.vtp``: the surface with the POD modes as point vectors, ``mode_00`` ... (the
  global basis ``/global/surface_basis``; without one, the central sample's basis).
- ``sequence.pvd`` + ``sequence/frame_NNNN.vtp``: the scripted tool path of ``hapticrom
  play`` (press, slide, release) stepped through the runtime, the surface displacement of
  every frame as ``displacement_mm``; the collection's times are those of ``play``.
- ``cut.vtp`` + ``cut_lips.vtp`` (``cut=True`` and a model with a cuttable region): the
  scalpel placed, pressed and slid as ``bench/cutting_latency.py`` does, and the opened
  surface with both lips.

Every file carries FieldData ``note`` (what it is and where in the artifact it comes
from) and ``units``; array names end in their unit (``_mm``, ``_N``, ``_N_per_mm``).
Only the runtime's public API is used (``load``, ``Simulator``): numpy and h5py suffice.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hapticrom.cli.outputs import check_writable
from hapticrom.online.model import ReducedModel, load
from hapticrom.online.play import tool_path
from hapticrom.shared.errors import InputError
from hapticrom.vtk import write_collection, write_polydata

MAX_FRAMES = 10_000
PLAY_SECONDS = 3.0  # `hapticrom play`'s default duration: the sequence's times span it
UNITS = "lengths mm, forces N, stiffnesses N/mm; mode arrays dimensionless (unit POD vectors)"
GROUP_NAMES = "0 clamped, 1 loadable (the tool may touch it), 2 free"
CUT_DEPTH_STEP = 0.01  # of the trained depth: the scalpel presses in these steps until it cuts
CUT_SLIDES, CUT_SLIDE_MM = 5, 0.25  # then slides along the blade, as the cutting bench does


def export_model(model: Path, out: Path, *, frames: int = 20, cut: bool = True) -> list[Path]:
    """Write ParaView files of a reduced model into `out` (created); return the paths written.

    ``model``: an artifact, loaded by the runtime's verifying loader (``ArtifactError`` if
    it is not a valid one). ``frames``: frames of the played sequence, 1 to 10,000.
    ``cut``: also cut with the scalpel, if the model has a cuttable region. A bad
    ``frames``, ``cut`` or ``out`` raises ``InputError`` before the model is read.
    """
    frames = _check_frames(frames)
    if not isinstance(cut, bool | np.bool_):
        raise InputError(f"export: cut must be True or False, got {cut!r}")
    out = _check_out(out)
    reduced = load(model)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"export --out {out}: cannot create it ({exc.strerror or exc})") from None
    written = [
        write_surface(reduced, out / "surface.vtp"),
        write_samples(reduced, out / "samples.vtp"),
        write_modes(reduced, out / "modes.vtp"),
    ]
    written += write_sequence(reduced, out, frames)
    if cut and reduced.cut_region is not None:
        written += write_cut(reduced, out)
    return written


# -- inputs --------------------------------------------------------------------------
def _check_frames(frames) -> int:
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer):
        raise InputError(f"export --frames must be an integer, got {frames!r}")
    if not 1 <= frames <= MAX_FRAMES:
        raise InputError(f"export --frames must lie in [1, {MAX_FRAMES:,}], got {frames:,}")
    return int(frames)


def _check_out(out) -> Path:
    """A directory that exists or can be created, in which a file can be created: checked
    with a probe file (permission bits say nothing for root or read-only mounts)."""
    try:
        out = Path(out)
    except TypeError:
        raise InputError(f"export --out must be a directory path, got {out!r}") from None
    if out.exists() and not out.is_dir():
        raise InputError(f"export --out {out} exists and is not a directory")
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"export --out {out}: {existing} is not a directory")
    check_writable(existing, f"export --out {out}", InputError)
    return out


def _name(model: ReducedModel) -> str:
    return str(model.artifact.group_attrs["model"].get("name", "?"))


# -- the model's arrays --------------------------------------------------------------
def write_surface(model: ReducedModel, path: Path) -> Path:
    """The rendered surface (``/surface``): vertices (mm), triangles, ``node`` (the mesh
    node of each vertex) and the cell array ``group`` of each triangle."""
    surface = model.artifact["surface"]
    return write_polydata(
        path,
        model.vertices,
        polys=model.triangles,
        point_data={"node": surface["nodes"]},
        cell_data={"group": surface["groups"]},
        field_data={
            "note": f"surface of the reduced model {_name(model)} (artifact /surface): "
            f"reference positions in mm; cell array 'group': {GROUP_NAMES}",
            "units": UNITS,
            "model": model.describe(),
        },
        comment=f"hapticrom export: surface of {_name(model)} (/surface), mm",
    )


def write_samples(model: ReducedModel, path: Path) -> Path:
    """The training samples (``/samples``) as points: ``normal``, the force curve
    ``force_N`` (one component per depth of the grid), ``solved_depth_mm`` (the depth each
    was solved to), ``trained_force_N`` there and ``stiffness_N_per_mm`` at the grid's end;
    the sample triangles as polygons."""
    samples = model.artifact["samples"]
    depth = np.asarray(samples["depth"])
    return write_polydata(
        path,
        model.sample_points,
        verts=np.arange(len(model.sample_points)),
        polys=model.sample_triangles,
        point_data={
            "normal": model.sample_normals,
            "force_N": model.force,
            "solved_depth_mm": model.solved_depth,
            "trained_force_N": model.sample_trained_force,
            "stiffness_N_per_mm": model.stiffness[:, -1],
            "sample": np.arange(len(model.sample_points)),
        },
        field_data={
            "note": "training samples of the reduced model (artifact /samples): tool positions "
            "(mm) with the outward normal (the tool pushes along minus it); force_N: normal "
            "contact force at each depth of depth_mm; polygons: the samples' triangles on the "
            "surface whose three samples the runtime blends",
            "depth_mm": depth,
            "units": UNITS,
        },
        vectors="normal",
        comment=f"hapticrom export: {len(depth)} depths per sample, up to {depth[-1]:g} mm",
    )


def mode_arrays(model: ReducedModel) -> tuple[dict[str, np.ndarray], str, np.ndarray]:
    """The surface modes as (V, 3) arrays by name, a note saying which they are, and
    their POD eigenvalues (mm^2).

    The global POD basis (``/global/surface_basis``, (3V, G): row 3 i + c is vertex i,
    component c) when the artifact has it, every column; else the basis of the sample
    nearest the chart's centre (``/samples/surface_basis``)."""
    V = len(model.vertices)
    if "global" in model.artifact.groups:
        basis = np.asarray(model.artifact["global"]["surface_basis"])
        note = (
            f"mode_NN: column NN of /global/surface_basis, the global POD basis over all "
            f"samples' snapshots restricted to the surface (all {basis.shape[1]} modes the "
            f"artifact stores; float32 as stored). Eigenvalues: eigenvalues_mm2 "
            f"(/global/eigenvalues). The per-sample bases (/samples/surface_basis, "
            f"{model.num_modes} modes at each of {len(model.sample_points)} samples) are not "
            f"written here."
        )
        eigenvalues = np.asarray(model.artifact["global"]["eigenvalues"])
    else:
        chart = model.plan_points
        sample = int(np.argmin(np.linalg.norm(chart - chart.mean(axis=0), axis=1)))
        basis = model.surface_basis[sample]
        note = (
            f"mode_NN: column NN of /samples/surface_basis[{sample}], the POD basis of the "
            f"sample nearest the centre of the samples' plan view (this artifact has no "
            f"/global basis); the "
            f"other {len(model.sample_points) - 1} samples' bases are not written here."
        )
        eigenvalues = np.asarray(model.artifact["samples"]["eigenvalues"])[sample]
    arrays = {f"mode_{m:02d}": basis[:, m].reshape(V, 3) for m in range(basis.shape[1])}
    return arrays, note + f" eigenvalues_mm2: {len(eigenvalues)} values", eigenvalues


def write_modes(model: ReducedModel, path: Path) -> Path:
    """The surface with each POD mode as a point vector array (see :func:`mode_arrays`)."""
    arrays, note, eigenvalues = mode_arrays(model)
    return write_polydata(
        path,
        model.vertices,
        polys=model.triangles,
        point_data=arrays,
        field_data={"note": note, "eigenvalues_mm2": eigenvalues, "units": UNITS},
        vectors="mode_00",
        comment=f"hapticrom export: {len(arrays)} POD modes of {_name(model)}. {note}",
    )


# -- the played sequence -------------------------------------------------------------
def played_sequence(model: ReducedModel, frames: int) -> Iterator[dict]:
    """``hapticrom play``'s scripted path in ``frames`` ticks through a fresh simulator
    (its default interpolation and response, as ``play``): per frame, the time (s), tool
    point and depth (mm), the force on the tool (N) and the surface displacement (mm)."""
    sim = model.simulator()
    points, depths = tool_path(model, frames)
    displacement = np.zeros_like(model.vertices)
    d = np.zeros(3)
    for i in range(frames):
        sim.set_contact(points[i])
        np.multiply(sim.contact_normal, -depths[i], out=d)  # as play: along -n
        force = sim.step_displacement(d).copy()
        sim.surface_displacement(displacement)
        yield {
            "time": PLAY_SECONDS * i / max(frames - 1, 1),
            "point": points[i],
            "depth": float(depths[i]),
            "force": force,
            "displacement": displacement.copy(),
        }


def write_sequence(model: ReducedModel, out: Path, frames: int) -> list[Path]:
    """One ``sequence/frame_NNNN.vtp`` per frame of :func:`played_sequence` and the
    collection ``sequence.pvd`` (times in s), which ParaView plays."""
    folder = out / "sequence"
    folder.mkdir(exist_ok=True)
    written, entries = [], []
    for i, frame in enumerate(played_sequence(model, frames)):
        path = write_polydata(
            folder / f"frame_{i:04d}.vtp",
            model.vertices,
            polys=model.triangles,
            point_data={"displacement_mm": frame["displacement"]},
            field_data={
                "note": "hapticrom play's press-slide-release path stepped through the "
                "runtime: displacement_mm is Simulator.surface_displacement after "
                "set_contact(tool_point_mm) and step_displacement(-depth_mm * normal)",
                "time_s": frame["time"],
                "tool_point_mm": frame["point"].reshape(1, 3),
                "depth_mm": frame["depth"],
                "force_on_tool_N": frame["force"].reshape(1, 3),
                "units": UNITS,
            },
            vectors="displacement_mm",
        )
        written.append(path)
        entries.append((frame["time"], path.relative_to(out)))
    written.append(write_collection(out / "sequence.pvd", entries))
    return written


# -- cutting -------------------------------------------------------------------------
def blade_direction(model: ReducedModel, at: np.ndarray) -> np.ndarray:
    """The blade along the circle about the organ's z axis through ``at`` (the cutting
    bench's choice: along the cornea's limbus); the plan view's first axis on the axis."""
    radial = at - np.array([0.0, 0.0, at[2]])
    if np.linalg.norm(radial) < 1e-9 * max(1.0, float(np.abs(model.vertices).max())):
        return np.array(model.plan_axes[0], dtype=float)
    return np.cross([0.0, 0.0, 1.0], radial / np.linalg.norm(radial))


def make_cut(model: ReducedModel):
    """A simulator with the scalpel placed at the vertex nearest the cuttable region's
    centre, pressed in steps until it cuts (at most the trained depth), then slid along
    the blade: (simulator, scalpel position, blade, depth)."""
    centre = np.asarray(model.artifact.group_attrs["cutting"]["centre"], dtype=float)
    start = model.vertices[np.argmin(np.linalg.norm(model.vertices - centre, axis=1))].copy()
    blade = blade_direction(model, start)
    sim = model.simulator()
    sim.scalpel(start, blade)
    normal = sim.contact_normal.copy()
    depth = 0.0
    while sim.last_cut is None and depth < model.trained_depth:
        depth += CUT_DEPTH_STEP * model.trained_depth
        sim.step_displacement(-depth * normal)
    for k in range(1, CUT_SLIDES + 1):
        # On the surface: the vertex nearest the point along the blade's tangent line.
        target = start + CUT_SLIDE_MM * k * blade
        at = model.vertices[np.argmin(np.linalg.norm(model.vertices - target, axis=1))]
        sim.scalpel(at, blade)
        sim.step_displacement(-depth * normal)
    sim.finish_cuts()
    return sim, start, blade, depth


def write_cut(model: ReducedModel, out: Path) -> list[Path]:
    """``cut.vtp``: the surface opened by :func:`make_cut` (the model's vertices, then the
    second lip's copies), its displacement and ``lip`` (0 off the cut, 1 first lip, 2
    second); ``cut_lips.vtp``: both lips' vertices as points."""
    sim, start, blade, depth = make_cut(model)
    displacement = sim.surface_displacement(np.zeros_like(model.vertices))
    vertices, triangles = sim.cut_surface()
    copied, positions, lip_displacement = sim.lip_vertices
    V = len(model.vertices)
    lip = np.zeros(len(vertices), dtype=np.uint8)
    lip[copied], lip[V:] = 1, 2
    events = sim.cut_events
    made = f"{len(events)} cut event(s), {sum(e.faces for e in events)} face(s) cut"
    fields = {
        "note": f"the surface cut open by the runtime's scalpel ({made}): placed at "
        "scalpel_position_mm with its blade along blade_direction, pressed to depth_mm, slid "
        f"{CUT_SLIDES} x {CUT_SLIDE_MM} mm along the blade; vertices: the model's surface, then "
        "the second lip's copies (Simulator.cut_surface, lip_vertices)",
        "scalpel_position_mm": start.reshape(1, 3),
        "blade_direction": blade.reshape(1, 3),
        "depth_mm": depth,
        "cut_force_N": float(model.artifact.group_attrs["cutting"]["cut_force"]),
        "largest_opening_mm": float(
            np.linalg.norm(lip_displacement - displacement[copied], axis=1).max(initial=0.0)
        ),
        "units": UNITS,
    }
    cut = write_polydata(
        out / "cut.vtp",
        vertices,
        polys=triangles,
        point_data={
            "displacement_mm": np.vstack([displacement, lip_displacement]),
            "lip": lip,
        },
        field_data=fields,
        vectors="displacement_mm",
        comment=f"hapticrom export: cut surface of {_name(model)}, {made}",
    )
    both = np.vstack([positions, positions])
    lips = write_polydata(
        out / "cut_lips.vtp",
        both,
        verts=np.arange(len(both)),
        point_data={
            "displacement_mm": np.vstack([displacement[copied], lip_displacement]),
            "side": np.repeat(np.array([1, 2], dtype=np.uint8), len(copied)),
            "surface_vertex": np.concatenate([copied, copied]),
        },
        field_data={**fields, "note": "the cut's two lips: side 1 the model's vertices, "
                    "side 2 their copies; each pair starts at the same reference position"},
        vectors="displacement_mm",
    )  # fmt: skip
    return [cut, lips]
