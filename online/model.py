"""A loaded reduced model: the verified artifact's arrays, laid out for the kernels (mm, N)."""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hapticrom.online.proxy import contact_surface, triangle_grid
from hapticrom.online.surface_chart import surface_chart
from hapticrom.shared.artifact import SCHEMA, Artifact, ArtifactError, read_artifact
from hapticrom.shared.artifact_rules import MAX_LENGTH, solved_depths
from hapticrom.shared.errors import InputError
from hapticrom.shared.geometry import plan_view, vertex_normals

# "transport" (the default): each neighbour's field carried to the contact before the blend
# (online/surface_chart.py); "podi": blended where each was trained; "grassmann": the bases.
INTERPOLATIONS = ("transport", "podi", "grassmann", "compliance")
RESPONSES = ("anm", "curves")
MAX_SHEETS = 8  # contact sheets (tool radii) a model keeps for new simulators


def _f8(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _f4(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _i8(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


@dataclass
class ReducedModel:
    """Everything a :class:`~hapticrom.online.simulator.Simulator` needs, read-only.

    Attributes (P samples, K depths, n modes, V surface vertices):
        vertices (V, 3), triangles (T, 3): the surface to render, mm.
        sample_points, sample_normals (P, 3), sample_triangles (S, 3): where the samples
        are, and their triangulation on the surface (the neighbourhoods).
        indicator (P,): each sample's leave-one-out relative force error.
        plan_origin (3,), plan_axes (2, 3), plan_points (P, 2): a plan view of the
        samples (:func:`~hapticrom.shared.geometry.plan_view`), for plots and paths only.
        depth_step: the uniform indentation grid spacing (mm); trained_depth, trained_force.
        solved_depth (P,): the depth each sample was solved to (mm; artifact 2.3: the grid
        goes to the deepest, and beyond its own a sample's curve goes on linearly);
        sample_trained_force (P,): each sample's force there (N).
        force, stiffness (P, K): normal reaction force curves (N) and slopes (N/mm).
        surface_basis (P, 3V, n) float32, coefficients (P, K, n): surface field;
        surface_basis_t (P, n, 3V): the same transposed, for the PODI kernel.
        chart: the plan-view grid that carries each neighbour's field to the contact
        (:class:`~hapticrom.online.surface_chart.SurfaceChart`), built at load; None where
        one plan view cannot hold the samples (then the surface is PODI's blend).
        anm: the POD-ANM sections (artifact 1.1) as kernel records, or None.
        tool_stiffness (S, L): the tool's linear stiffness on each sample triangle's
        lattice (artifact 2.1, ``shared/lattice.py``), N/mm, or None: the force curves
        are blended with the weights w_i k(x) / k_i.
        contact_fields: the tool's linear surface field per unit depth at every loadable
        vertex (artifact 2.2, :func:`_contact_fields`), or None: the "compliance" surface.
        sample_floors (S,): how far beneath each sample triangle a contact may lie, mm
        (:func:`~hapticrom.online.kernels.face_floors`: not on or just above the organ's
        opposite face), built at load.
    """

    path: Path
    artifact: Artifact
    vertices: np.ndarray
    triangles: np.ndarray
    sample_points: np.ndarray
    sample_normals: np.ndarray
    sample_triangles: np.ndarray
    indicator: np.ndarray
    depth_step: float
    force: np.ndarray
    stiffness: np.ndarray
    surface_basis: np.ndarray
    coefficients: np.ndarray
    grassmann: dict | None
    anm: dict | None = None  # POD-ANM series: offsets, records, coefficients, n1, smax
    cut_region: object = None  # online.coupled_patch.CutRegion of its cuttable region
    tool_stiffness: np.ndarray | None = None  # (S, L) N/mm, the curves' scaling (2.1)
    contact_fields: dict | None = None  # the tool's linear fields (2.2): _contact_fields
    solved_depth: np.ndarray | None = None  # (P,) mm (2.3); None: the grid's end for each

    def __post_init__(self):
        from hapticrom.online import kernels

        if self.solved_depth is None:
            self.solved_depth = np.full(len(self.sample_points), self.depth_step *
                                        (self.force.shape[1] - 1))  # fmt: skip

        def forces_at(depths):  # the kernel's own curves
            rows = zip(self.force, self.stiffness, depths, strict=True)
            return np.array([kernels.hermite(f.copy(), k.copy(), self.depth_step, d)
                             for f, k, d in rows])  # fmt: skip

        self.sample_trained_force = forces_at(self.solved_depth)
        self._force_at_trained_depth = forces_at(np.full(len(self.force), self.trained_depth))
        self.surface_basis_t = np.ascontiguousarray(self.surface_basis.transpose(0, 2, 1))
        try:
            self.sample_floors = kernels.face_floors(
                self.sample_points, self.sample_normals, self.sample_triangles, self.vertices,
                vertex_normals(self.vertices, self.triangles), self.triangles,
            )  # fmt: skip
        except ValueError as error:  # a crafted surface or triangulation: too much work
            raise ArtifactError(f"{self.path}: {error}") from None
        self.plan_origin, self.plan_axes, self.plan_points = plan_view(
            self.sample_points, self.sample_normals
        )
        self.chart = surface_chart(
            self.vertices, self.triangles, self.sample_points, self.sample_normals,
            self.sample_triangles, self.surface_basis,
        )  # fmt: skip
        self._sheets: dict[float, np.ndarray] = {}
        self.contact_sheet(self.contact_radius)  # built at load: refused here if it cannot be
        if self.grassmann is not None:
            tangents = self.grassmann["tangents"]
            self.grassmann["tangents_t"] = np.ascontiguousarray(tangents.transpose(0, 2, 1))
        self._freeze()

    def inside_trained_region(self, points) -> np.ndarray:
        """(N,) True where a point (N, 3) mm is located inside the samples' triangulation, as
        ``set_contact`` does (not clamped to its border)."""
        return inside_trained_region(self.sample_points, self.sample_normals,
                                     self.sample_triangles, points, self.sample_floors)  # fmt: skip

    def _freeze(self) -> None:
        """Every array read-only: simulators share the model, none may change it."""
        chart = vars(self.chart) if self.chart is not None else {}
        tables = [vars(self), chart, self.grassmann or {}, self.anm or {},
                  self.contact_fields or {}]  # fmt: skip
        for table in tables:
            for value in table.values():
                if isinstance(value, np.ndarray):
                    value.flags.writeable = False

    @classmethod
    def from_artifact(cls, artifact: Artifact) -> ReducedModel:
        """The model of a verified artifact (arrays converted to the kernels' dtypes)."""
        surface, samples = artifact["surface"], artifact["samples"]
        step = float(samples["depth"][1])  # uniform from 0 (artifact_rules)
        grassmann = None
        if "grassmann" in artifact.groups:
            g = artifact["grassmann"]
            grassmann = {
                "reference": int(g["reference"]),
                "tangents": _f4(g["tangent_surface"]),
                "gtt": _f8(g["gram_tangent_tangent"]),
                "gtb": _f8(g["gram_tangent_basis"]),
                "grb": _f8(g["gram_reference_basis"]),
            }
        anm = _anm_records(artifact) if "anm" in artifact.groups else None
        cut_region = _cut_region(artifact) if "cutting" in artifact.groups else None
        return cls(
            path=artifact.path,
            artifact=artifact,
            vertices=_f8(surface["vertices"]),
            triangles=_i8(surface["triangles"]),
            sample_points=_f8(samples["points"]),
            sample_normals=_f8(samples["normals"]),
            sample_triangles=_i8(samples["triangles"]),
            indicator=_f8(samples["indicator"]),
            depth_step=step,
            force=_f8(samples["force"]),
            stiffness=_f8(samples["stiffness"]),
            surface_basis=_f4(samples["surface_basis"]),
            coefficients=_f8(samples["coefficients"]),
            grassmann=grassmann,
            anm=anm,
            cut_region=cut_region,
            tool_stiffness=_f8(samples["tool_stiffness"]) if "tool_stiffness" in samples else None,
            solved_depth=_f8(solved_depths(samples)),
            contact_fields=(
                _contact_fields(artifact) if "contact_fields" in artifact.groups else None
            ),
        )

    @property
    def trained_depth(self) -> float:
        """The depth every sample was solved to (mm): the shallowest sample's (artifact 2.3:
        the grid goes on to the deepest's)."""
        return float(self.solved_depth.min())

    @property
    def trained_force(self) -> float:
        """The force every sample reaches within the trained depth (N): the smallest of the
        samples' forces at it (under force control the softest's, below the campaign's force;
        ``sample_trained_force`` holds each one's at its own solved depth)."""
        return float(self._force_at_trained_depth.min())

    @property
    def contact_radius(self) -> float:
        """The training tool tip's radius (mm): the default of ``step_position``'s sphere."""
        return float(self.artifact.group_attrs["model"]["contact_radius"])

    def contact_sheet(self, radius: float) -> np.ndarray:
        """The loadable surface offset by a tool tip's ``radius`` (mm), as the proxy's table
        (:func:`~hapticrom.online.proxy.contact_surface`); built once per radius, and the
        last MAX_SHEETS radii kept (the training's always). InputError for a radius that
        is not a number in (0, MAX_LENGTH] mm, ArtifactError for a surface that makes no
        sheet."""
        if isinstance(radius, bool) or not isinstance(radius, numbers.Real):
            raise InputError(f"tool radius must be a number (mm), got {radius!r}")
        radius = float(radius)
        if not 0.0 < radius <= MAX_LENGTH:  # NaN fails too: a NaN key would never be found
            if radius == self.contact_radius:
                raise ArtifactError(
                    f"{self.path}: attribute contact_radius of model ({radius!r} mm) is beyond "
                    f"{MAX_LENGTH:g} mm"
                )
            raise InputError(f"tool radius must lie in (0, {MAX_LENGTH:g}] mm, got {radius!r}")
        sheet = self._sheets.get(radius)
        if sheet is None:
            groups = np.asarray(self.artifact["surface"]["groups"])
            try:
                sheet = contact_surface(self.vertices, self.triangles, groups, radius)
            except ValueError as exc:
                raise ArtifactError(f"{self.path}: {exc}") from None
            # A host that makes simulators of ever new radii must not grow the shared model
            # (each simulator holds its own sheet: dropping one here frees it with them).
            others = [r for r in list(self._sheets) if r != self.contact_radius]
            for old in others[: max(0, len(others) - (MAX_SHEETS - 2))]:
                self._sheets.pop(old, None)
            self._sheets[radius] = sheet
        return sheet

    @property
    def num_modes(self) -> int:
        """Modes per sample, n."""
        return self.surface_basis.shape[2]

    def physics(self, region: int = 0, holders=(), iterations: int = 1, slices: int = 30,
                estimate_steps: int = 100, precision: str = "single"):  # fmt: skip
        """Region ``region`` of the hyper-reduced physics (artifact format 2.5, group
        ``hyperreduced``), ``holders`` gripping the surface at those points (mm): a
        :class:`~hapticrom.online.physics.HyperReducedPhysics` (``iterations`` and
        ``slices`` and ``precision`` its Newton's, ``estimate_steps`` the steps an error
        estimate is spread over: ``physics.error_estimate()``)."""
        from hapticrom.online.physics import HyperReducedPhysics

        return HyperReducedPhysics(self, region, holders, iterations, slices, estimate_steps,
                                   precision)  # fmt: skip

    def simulator(self, interpolation: str | None = None, response: str | None = None, **limits):
        """A new simulator state on this model (models are shared, simulators are not).

        ``interpolation`` of the rendered surface: "transport" (each neighbour's field
        carried to the contact, then blended: the dent under the tool; the default where the
        model has a chart), "podi" (blended where each was trained; the default otherwise)
        or "grassmann" (the bases interpolated; stored curves only).

        ``response``: "anm" (the POD-ANM series; the default when the artifact has
        them) or "curves" (the stored full-order force curves).
        """
        from hapticrom.online.simulator import Simulator

        return Simulator(self, interpolation, response=response, **limits)

    def describe(self) -> str:
        """One line: the campaign's name, sizes, trained range and the artifact's version."""
        a = self.artifact
        return (
            f"{a.group_attrs['model'].get('name', '?')}: {len(self.sample_points)} samples, "
            f"{self.num_modes} modes, {len(self.vertices)} surface vertices; trained to "
            f"{self.trained_depth:.3g} mm / {self.sample_trained_force.max():.3g} N "
            f"(artifact {a.version[0]}.{a.version[1]}, {self.path})"
        )


# PressureCoupling's fields: the /cutting datasets they are read from (format 1.3).
_COUPLING = {
    "displacement": "element_displacement_stiffness",
    "coupling": "element_pressure_coupling",
    "pressure": "element_pressure_stiffness",
    "pressure_basis": "pressure_basis",
    "reduced_displacement": "reduced_displacement_stiffness",
    "reduced_coupling": "reduced_pressure_coupling",
    "reduced_pressure": "reduced_pressure_stiffness",
}


def _cut_region(artifact: Artifact):
    """The cuttable region (format 1.2; 1.3 adds its pressure coupling) for
    :mod:`hapticrom.online.coupled_patch`."""
    from hapticrom.online.coupled_patch import CutRegion, PressureCoupling

    c = artifact["cutting"]
    pressure = None
    coupling = [spec.name for group in SCHEMA if group.name == "cutting"
                for spec in group.fields if not spec.required]  # fmt: skip
    missing = [name for name in coupling if name not in c]
    if 0 < len(missing) < len(coupling):
        raise ArtifactError(
            f"{artifact.path}: incomplete pressure coupling in /cutting: "
            f"missing {', '.join(missing)}"
        )
    if not missing:
        pressure = PressureCoupling(**{field: _f8(c[name]) for field, name in _COUPLING.items()})
    try:
        return CutRegion(
            coordinates=_f8(c["coordinates"]),
            cells=_i8(c["cells"]),
            element_stiffness=_f8(c["element_stiffness"]),
            basis=_f8(c["basis"]),
            fixed=np.asarray(c["fixed"]) != 0,
            reduced_stiffness=_f8(c["reduced_stiffness"]),
            pressure=pressure,
        )
    except ValueError as exc:
        raise ArtifactError(f"{artifact.path}: {exc}") from None


def _contact_fields(artifact: Artifact) -> dict:
    """The kernel's view of ``contact_fields``: ``fields`` (R, 3V) float32, ``sample_rows``
    (P,), the loadable triangles (TL, 3) as vertex indices and as rows (``triangle_rows``),
    a uniform grid of them (``grid``, ``grid_starts``, ``grid_ids``: where the surface
    looks for the triangle under the contact), and the tool's linear stiffness at their
    corners and edges' midpoints (``stiffness_nodes`` (TL, 6): the corners, then the edge
    opposite each; the midpoints the mean of their corners in files before 2.4, so that
    the quadratic is the linear interpolant; or None)."""
    c, s = artifact["contact_fields"], artifact["surface"]
    triangles = _i8(s["triangles"][np.asarray(s["groups"]) == 1])
    row_of = np.full(len(s["vertices"]), -1, dtype=np.int64)
    row_of[np.asarray(c["vertices"])] = np.arange(len(c["vertices"]))
    # The grid spans the loadable triangles only: a far vertex elsewhere would stretch it into
    # thousands of empty cells, each searched (red team: 0.6 s a contact, against 30 us).
    used = np.unique(triangles)
    local = np.searchsorted(used, triangles)
    origin, size, dims, starts, ids = triangle_grid(_f8(s["vertices"])[used], local, 200_000)
    return {
        "fields": _f4(c["fields"]),
        "sample_rows": _i8(c["sample_rows"]),
        "triangles": triangles,
        "triangle_rows": np.ascontiguousarray(row_of[triangles]),
        "grid": np.array([*origin, size, *dims], dtype=np.float64),  # the triangles' grid
        "grid_starts": _i8(starts),
        "grid_ids": _i8(ids),
        "stiffness_nodes": _stiffness_nodes(c, row_of[triangles]),
    }


def _stiffness_nodes(c, rows: np.ndarray) -> np.ndarray | None:
    """(TL, 6) N/mm: the tool's linear stiffness at each loadable triangle's corners (format
    2.3) and at the midpoints of the edges opposite them (2.4; before, the corners' means),
    or None without it."""
    if "stiffness" not in c:
        return None
    corners = np.asarray(c["stiffness"], dtype=np.float64)[rows]
    if "edge_stiffness" in c:
        edges = np.asarray(c["edge_stiffness"], dtype=np.float64)
    else:
        edges = 0.5 * (corners[:, [1, 2, 0]] + corners[:, [2, 0, 1]])
    return np.ascontiguousarray(np.hstack([corners, edges]))


def _anm_records(artifact: Artifact) -> dict:
    """The kernels' per-section records (see online/kernels.py) from the artifact's series:
    each section tabulated for the steps' Hermite interpolation."""
    from hapticrom.online.kernels import tabulate_series

    a = artifact["anm"]
    offsets = _i8(a["section_offsets"])
    depth, force, a_max = _f8(a["depth"]), _f8(a["force"]), _f8(a["a_max"])
    counts = np.diff(offsets)  # offsets, a_max and monotone sections: artifact_rules
    records, knots, errors = tabulate_series(depth, force, a_max)
    n1 = depth.shape[1]
    return {
        "offsets": offsets,
        "records": _f8(records),
        "coefficients": _f8(a["coefficients"]),
        "n1": int(n1),
        "smax": int(counts.max()),
        "section_knots": knots,
        "tabulation_error": errors,  # (N, a): the largest between knots
        "order": int(artifact.group_attrs["anm"]["order"]),
    }


def load(path: str | Path, isolate: bool = True) -> ReducedModel:
    """Load and verify a reduced-model artifact, then sweep it with every kernel.

    Anything wrong with the file, found by the reader or by the sweep, is an
    ``ArtifactError``. The sweep also compiles the kernels (or loads them from
    the cache), so the servo loop never compiles. ``isolate``: HDF5 parses the
    file in a child process first, so that a crafted file that crashes HDF5's C
    code cannot crash this one (about 0.5 s; ``False`` in a host with no Python
    interpreter to start).
    """
    artifact = read_artifact(path, isolate=isolate)
    try:
        model = ReducedModel.from_artifact(artifact)
        sweep(model)
    except ArtifactError:
        raise
    except Exception as exc:  # noqa: BLE001 - a file's fault until proven otherwise
        raise ArtifactError(
            f"{path}: the model cannot be set up ({type(exc).__name__}: {exc})"
        ) from None
    return model


def sweep_points(model: ReducedModel) -> np.ndarray:
    """Where the sweep touches: every sample, every sample triangle's centroid and the
    midpoints of its edges (the blends of two and three samples' data)."""
    p, t = model.sample_points, model.sample_triangles
    edges = np.unique(np.sort(np.stack([t, np.roll(t, 1, axis=1)], axis=2).reshape(-1, 2)), axis=0)
    return np.vstack([p, p[t].mean(axis=1), 0.5 * (p[edges[:, 0]] + p[edges[:, 1]])])


def field_interpolations(model: ReducedModel) -> list[str]:
    """The rendered surfaces a model offers with either response (Grassmann aside): the
    transported field where it has a chart, the compliance field where it has contact
    fields, and PODI's blend always."""
    chart = ["transport"] if model.chart is not None else []
    fields = ["compliance"] if model.contact_fields is not None else []
    return chart + fields + ["podi"]


def sweep(model: ReducedModel) -> None:
    """Every response at every sweep point, at the trained depth and force and 1.5x them, and
    the surface at the deepest sample's solved depth: forces, displacements and surfaces
    finite and within the simulator's limits (10x the trained depth and force). Catches what
    no rule on single datasets sees (a field that overflows in the blend of two samples, a
    force that runs away beyond the trained depth)."""
    fields = field_interpolations(model)
    # the deepest solved depth, where the simulator takes it (a review's tampered coefficients
    # beyond 1.5x the shallowest drew 3.9e6 mm there, and the sweep did not go that deep)
    deepest = min(float(model.solved_depth.max()), 10 * model.trained_depth)
    combos = [(field, "curves") for field in fields]
    if model.grassmann:
        combos.append(("grassmann", "curves"))
    if model.anm:
        combos += [(field, "anm") for field in fields]
    surface = np.empty_like(model.vertices)
    for interpolation, response in combos:
        sim = model.simulator(interpolation, response)
        for point in sweep_points(model):
            sim.set_contact(point)
            n = np.array(sim.contact_normal)
            for scale in (1.0, 1.5):  # the trained end and beyond: the largest values
                force = sim.step_displacement(-scale * model.trained_depth * n)
                _within(model, response, "force", force, sim.max_force)
                _within(model, response, "surface", sim.surface_displacement(surface),
                        sim.max_displacement)  # fmt: skip
                d = sim.step_force(-scale * model.trained_force * n)
                _within(model, response, "displacement", d, sim.max_displacement)
            if deepest > model.trained_depth:  # the grid's end (2.3): the surface only (a
                # stiff place's force there, continued far past its own solves, may pass
                # the force limit without fault)
                sim.step_displacement(-deepest * n)  # within 10x that depth, as at the
                # trained depth (the 4k organ's lobe swings 1.4x the depth there: legitimate)
                _within(model, response, "surface", sim.surface_displacement(surface),
                        10 * deepest)  # fmt: skip


def _within(model: ReducedModel, response: str, what: str, value: np.ndarray, limit: float):
    if not (np.all(np.isfinite(value)) and np.max(np.abs(value)) <= limit):
        raise ArtifactError(
            f"{model.path}: the model's {response} {what} is not finite or beyond the "
            f"simulator's limit ({limit:.3g}) inside the trained region"
        )


def locate_points(sample_points, sample_normals, sample_triangles, queries, floors=None):
    """Where the runtime puts contacts at points (N, 3) mm in the samples' triangulation on
    the surface (:func:`~hapticrom.online.kernels.locate`; ``floors``: the model's
    ``sample_floors``, as its simulators): their three samples (N, 3), weights (N, 3) and
    whether each lies inside (not clamped to the border) (N,)."""
    from hapticrom.online import kernels

    points, normals = _f8(np.ravel(sample_points)), _f8(np.ravel(sample_normals))
    triangles = _f8(np.ravel(sample_triangles))
    planes = _f8(np.ravel(kernels.triangle_planes(sample_points, sample_triangles, floors)))
    edges = _f8(np.ravel(kernels.border_edges(sample_triangles)))
    where, scratch = np.zeros(2), np.zeros(3)
    queries = _f8(np.reshape(queries, (-1, 3)))
    samples, weights = np.zeros((len(queries), 3)), np.zeros((len(queries), 3))
    inside = np.zeros(len(queries), dtype=bool)
    for i, q in enumerate(queries):
        flag = kernels.locate(
            q, points, normals, triangles, planes, edges, weights[i], samples[i], where, scratch
        )
        inside[i] = flag == 0
    return samples.astype(np.int64), weights, inside


def inside_trained_region(sample_points, sample_normals, sample_triangles, queries,
                          floors=None) -> np.ndarray:  # fmt: skip
    """(N,) True where a point (N, 3) mm lies in the samples' triangulation on the surface, as
    the runtime locates a contact (with the model's ``floors``): where ``set_contact`` would
    not clamp it."""
    return locate_points(sample_points, sample_normals, sample_triangles, queries, floors)[2]
