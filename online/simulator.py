"""The haptic simulator: one tool in contact with one reduced organ model (mm, N).

A haptic servo loop (OpenHaptics, CHAI3D) calls the physics about 1,000
times a second with a position and expects a force back::

    sim = hapticrom.online.load("cornea.h5").simulator()
    sim.set_contact(point)                  # where the tool touches (may slide)
    force = sim.step_displacement(d)        # tool displacement in, reaction force out
    sim.surface_displacement(vertex_disp)   # for rendering, into a caller-owned (V, 3) array

The model is the PODI contact model of the artifact: the samples' force-depth
curves and reduced fields, interpolated over the tool position (barycentric in
the samples' Delaunay chart) and over the depth (monotone cubic for forces). The
contact is frictionless: the normal component of ``d`` indents the tissue and
the force is along the surface normal; to follow the tool sideways, move the
contact point (``set_contact`` every step is fine: it is microseconds).

Work that depends only on the contact point happens in ``set_contact``. The
steps allocate nothing: they write into buffers owned by the simulator and
return read-only views of those (``step_displacement`` returns the same (3,)
array every call: copy it to keep it).

Inputs (points, displacements, forces, the scalpel's position and blade): a 1-D
float64 numpy array of 3 elements goes straight to the kernel (any strides,
read-only or not: the fast path). Anything else that holds 3 numbers (a list, a
tuple, a float32 or integer array) takes a slower path: it is copied into a
(3,) float64 buffer of the simulator first (``np.asarray`` for a list or tuple:
about a microsecond more, and that allocates). Any other shape ((2,), (4,),
(3, 1), a scalar) or anything not numbers (strings, complex, bool, objects)
raises :class:`StepInputError` (``ScalpelInputError`` for the scalpel) naming
it, and changes nothing.

Threads: a simulator is driven by one thread at a time. Calls from a second
thread while one is inside a step, ``set_contact``, ``scalpel`` or
``surface_displacement`` raise :class:`SimulatorBusyError` (they are not queued:
a servo loop must not wait). Simulators on one shared :class:`ReducedModel` may
run on as many threads as you like, in parallel: the model is only read (the
step kernels release the GIL).
"""

from __future__ import annotations

import math
import numbers
import warnings

import numpy as np

from hapticrom.online import kernels
from hapticrom.online.cutting import Scalpel, ScalpelInputError
from hapticrom.online.model import INTERPOLATIONS, RESPONSES, ReducedModel
from hapticrom.shared.errors import HapticromError, InputError


class StepInputError(HapticromError, ValueError):
    """A step input was of a wrong shape, not numbers, NaN, infinite or absurd; the
    simulator state is unchanged."""


class SimulatorBusyError(HapticromError, RuntimeError):
    """Another thread is inside this simulator: one simulator, one thread at a time."""


_NDARRAY, _F8 = np.ndarray, np.dtype(np.float64)
_KEPT = "state unchanged"


def _as_vector(value, out: np.ndarray, what: str, error: type[Exception]) -> np.ndarray:
    """``value`` (3 numbers) copied into ``out`` (3,) float64: the inputs' slower path."""
    try:
        a = value if isinstance(value, np.ndarray) else np.asarray(value)
    except (TypeError, ValueError):  # e.g. a ragged list
        raise error(f"{what} must be 3 numbers, shape (3,); got {value!r:.80}; {_KEPT}") from None
    if a.dtype.kind not in "iuf":
        raise error(
            f"{what} must be 3 numbers, shape (3,); got {value!r:.80} (dtype {a.dtype}); {_KEPT}"
        )
    if a.shape != (3,):
        raise error(f"{what} must be 3 numbers, shape (3,); got shape {a.shape}; {_KEPT}")
    out[:] = a
    return out


def _readonly(a: np.ndarray) -> np.ndarray:
    """A view of ``a`` that cannot be written through."""
    view = a.view()
    view.flags.writeable = False
    return view


def _limit(value, default: float, name: str, unit: str) -> float:
    """A simulator limit: None (the default) or a finite positive number."""
    if value is None:
        if not (math.isfinite(default) and default > 0):  # a model trained to nothing
            raise InputError(f"the model gives no default {name} ({default!r} {unit}); pass one")
        return float(default)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{name} must be a positive number ({unit}) or None, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise InputError(
            f"{name} must be finite and positive ({unit}), or None for the default "
            f"({default:.3g} {unit}); got {value!r}"
        )
    return float(value)


def _check_config(model: ReducedModel, interpolation: str, response: str | None) -> str:
    """The response to use (the model's default if None); InputError if they do not fit."""
    if response is None:
        response = "anm" if model.anm is not None else "curves"
    if response not in RESPONSES:
        raise InputError(f"response must be one of {RESPONSES}, got {response!r}")
    if response == "anm" and model.anm is None:
        raise InputError("this artifact carries no POD-ANM series (format 1.1 'anm' group)")
    if response == "anm" and interpolation == "grassmann":
        raise InputError("the POD-ANM response blends fields by PODI; use interpolation='podi'")
    if interpolation not in INTERPOLATIONS:
        raise InputError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    if interpolation == "grassmann" and model.grassmann is None:
        raise InputError("this artifact carries no Grassmann tangents")
    return response


class Simulator:
    """Mutable contact state on an immutable :class:`ReducedModel`.

    Limits (absurd inputs are refused with :class:`StepInputError`, the state
    unchanged): ``max_displacement`` (mm, default 10x the trained depth) bounds the
    tool displacement a displacement step takes and the one a force step returns (a
    force that would push the tool further is refused); ``max_force`` (N, default
    10x the trained force) bounds the force a force step takes. Each is None (the
    default) or a finite positive number; anything else raises ``InputError``.

    Threads: one simulator is stepped by one thread at a time (a call while another
    thread is inside one raises :class:`SimulatorBusyError`); simulators sharing one
    model may step on parallel threads.
    """

    def __init__(
        self,
        model: ReducedModel,
        interpolation: str = "podi",
        max_displacement: float | None = None,
        max_force: float | None = None,
        response: str | None = None,
    ):
        response = _check_config(model, interpolation, response)
        self.model, self.interpolation, self.response = model, interpolation, response
        max_displacement = _limit(
            max_displacement, 10 * model.trained_depth, "max_displacement", "mm"
        )
        max_force = _limit(max_force, 10 * model.force[:, -1].max(), "max_force", "N")
        K, n = model.force.shape[1], model.num_modes
        k = kernels
        anm = model.anm if response == "anm" else None
        n1, smax = (anm["n1"], anm["smax"]) if anm else (0, 0)
        self._buf = np.zeros(k.buffer_size(K, n1, smax))  # the state the steps read and write
        if anm:
            self._buf[k.ANM_BASE] = k.CURVE + 2 * K
            self._buf[k.ANM_N1] = n1
            self._buf[k.ANM_SMAX] = smax
        self._buf[k.STEP] = model.depth_step
        self._buf[k.MAX_DISPLACEMENT] = self._buf[k.MAX_DEPTH] = max_displacement
        self._buf[k.MAX_FORCE] = max_force
        self._buf[k.KNOTS] = K
        self._normal = self._buf[k.NORMAL : k.NORMAL + 3]  # views into the buffer
        self._force = self._buf[k.FORCE : k.FORCE + 3]
        self._displacement = self._buf[k.DISPLACEMENT : k.DISPLACEMENT + 3]
        self._curve = self._buf[k.CURVE : k.CURVE + K]
        self._slope = self._buf[k.CURVE + K : k.CURVE + 2 * K]
        # What the caller sees: views that cannot be written through (made once).
        self._normal_out = _readonly(self._normal)
        self._force_out = _readonly(self._force)
        self._displacement_out = _readonly(self._displacement)
        self._input = np.zeros(3)  # the slower path's copy of a step input
        self._point, self._blade_input = np.zeros(3), np.zeros(3)  # ... of a point, a blade
        # The last scalpel placement (position, blade): placing it there again only re-arms it.
        self._placement = np.full(6, np.nan)
        self._chart = self._buf[k.CHART : k.CHART + 2]
        self._weights = self._buf[k.WEIGHTS : k.WEIGHTS + 3]
        self._vertices = np.zeros(3, dtype=np.int64)
        # The model's arrays set_contact reads, in one read-only array (one to pass).
        self._table = k.contact_table(
            model.chart_origin, model.chart_axes, model.chart_points, model.sample_normals,
            model.force, model.stiffness,
        )  # fmt: skip
        # bound once: no lookups per step
        self._step_displacement = k.step_displacement_anm if anm else k.step_displacement
        self._step_force = k.step_force_anm if anm else k.step_force
        self._scratch = np.zeros(3 + 3 * n)  # depth weights + three n-vectors
        self._frames = np.zeros((5, n, n))  # Grassmann: V cos S, V S^-1 sin S, R_0..R_2
        self._contact = False
        # True while a thread is inside a call. A flag, not a lock: a lock's acquire and
        # release cost more than half a step. Under CPython's GIL nothing runs between its
        # test and its setting, so a second thread always sees it (the steps' kernels let
        # the GIL go; a free-threaded Python could miss a race).
        self._inside = False
        self._init_cutting()

    def _init_cutting(self) -> None:
        self._cutting = None  # online.cutting.Scalpel once the scalpel is used
        f = kernels.FRAME  # the scalpel's unit blade direction, unit normal of its plane
        self._blade, self._across = self._buf[f : f + 3], self._buf[f + 3 : f + 6]
        self._armed = False  # the blade may still cut at this placement
        self._background = False  # cut events on a worker thread (scalpel(background=True))
        self._vertex = -1  # region surface vertex at the contact (while cutting), or -1
        self._scalpel_vertex = -1  # the surface vertex under the scalpel
        self.last_cut = None  # the last CutEvent
        self.cut_error = None  # the last cut that failed (an exception), if any
        self._lips = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64))  # second lip, rendered
        self._controlled = "displacement"  # the last step's control: the cut's field needs it

    @property
    def max_displacement(self) -> float:
        """The displacement limit (mm): of a displacement step's input, a force step's output."""
        return float(self._buf[kernels.MAX_DISPLACEMENT])

    @property
    def max_force(self) -> float:
        """The force limit (N) of a force step's input."""
        return float(self._buf[kernels.MAX_FORCE])

    def _busy(self, call: str):
        raise SimulatorBusyError(
            f"{call}: another thread is inside this simulator; a simulator is driven by one "
            "thread at a time (give each thread its own simulator: they may share the model)"
        )

    # -- contact -----------------------------------------------------------------
    def set_contact(self, point) -> None:
        """Put (or slide) the tool's contact at ``point`` (mm, on or near the surface).

        Outside the trained region the contact is clamped to the nearest trained
        point (``outside_trained_region`` is then True).
        """
        if self._inside:
            self._busy("set_contact")
        self._inside = True
        try:
            p = point
            if type(p) is not _NDARRAY or p.dtype is not _F8 or p.ndim != 1:
                p = _as_vector(p, self._point, "contact point (mm)", StepInputError)
            self._contact_at(p, point)
            self._placement[0] = np.nan  # the scalpel's contact is gone
            if self._cutting is not None:
                self._armed = False  # a plain contact; scalpel() arms the blade again
                self._vertex = self._cutting.region_vertex(p)
        finally:
            self._inside = False

    def _contact_at(self, p: np.ndarray, point) -> None:
        """The contact at ``p`` (a 1-D float64 array): everything that depends on it only."""
        m = self.model
        status = kernels.prepare_contact(
            p, self._table, m.sample_triangles, self._vertices, self._buf
        )
        if status == -kernels.WRONG_SHAPE:
            raise StepInputError(
                f"contact point (mm) must be 3 numbers, shape (3,); got shape {p.shape}; {_KEPT}"
            )
        if status:
            raise StepInputError(
                f"contact point (mm) must be 3 finite numbers, got {point!r}; {_KEPT}"
            )
        self._contact_series()

    def _contact_series(self) -> None:
        """What else depends on the contact: the POD-ANM sections, the Grassmann frames."""
        m = self.model
        if self.response == "anm":
            a = m.anm
            kernels.prepare_anm(
                self._weights, self._vertices, a["offsets"], a["records"], self._buf
            )
            kernels.anm_force(self._buf, self.depth)  # sections for the surface at this depth
        if self.interpolation == "grassmann":
            g = m.grassmann
            kernels.prepare_grassmann(
                self._weights, self._vertices, g["gtt"], g["gtb"], g["grb"], self._frames
            )
        self._contact = True

    # -- steps -------------------------------------------------------------------
    def _refuse(self, status: int, what: str, value, limit: float) -> None:
        """Raise the error of a step's status (the state is unchanged)."""
        if status == -1:
            raise RuntimeError("call set_contact(point) before stepping")
        if status == kernels.WRONG_SHAPE:
            raise StepInputError(
                f"{what} must be 3 numbers, shape (3,); got shape {np.shape(value)}; {_KEPT}"
            )
        if status == kernels.DISPLACEMENT_LIMIT:
            raise StepInputError(
                f"{what} {value!r} would push the tool beyond the displacement limit "
                f"({self.max_displacement:.3g} mm); {_KEPT}"
            )
        if status == kernels.BEYOND_LIMIT:
            raise StepInputError(
                f"{what} {value!r} is longer than the simulator's limit ({limit:.3g}); {_KEPT}"
            )
        raise StepInputError(f"{what} {value!r} is not finite (NaN or infinite); {_KEPT}")

    def step_displacement(self, d) -> np.ndarray:
        """Tool displacement ``d`` (mm, from the contact point) -> reaction force on the tool (N).

        The force points out of the tissue (along the outward normal). The
        returned array (read only) is reused by the next call. A displacement
        longer than ``max_displacement`` is refused (StepInputError).
        """
        if self._inside:
            self._busy("step_displacement")
        self._inside = True
        try:
            if not self._contact:
                self._refuse(-1, "displacement (mm)", d, 0.0)
            x = d  # a 1-D float64 array goes straight in; anything else: TypeError below
            try:
                status = self._step_displacement(x, self._buf)
            except TypeError:  # the slower path: converted into a buffer, or refused
                x = _as_vector(x, self._input, "displacement (mm)", StepInputError)
                status = self._step_displacement(x, self._buf)
            if status:
                self._refuse(status, "displacement (mm)", d, self.max_displacement)
            self._controlled = "displacement"
            if self._cutting is not None:
                self._cut_step(self._force)
                if self._vertex >= 0:
                    self._force *= self._cutting.ratio[self._vertex]
            return self._force_out
        finally:
            self._inside = False

    # -- cutting -------------------------------------------------------------------
    def scalpel(self, position, blade_direction, background: bool = False) -> None:
        """Put the scalpel at ``position`` (mm, on the surface) with its blade along
        ``blade_direction`` (its component in the surface plane is used).

        Then step as with any tool: when the force in the blade's plane exceeds
        the artifact's cut force, the faces under the blade are cut whole and the
        cut patch is rebuilt (``last_cut`` says what it cost). That takes 0.1 s or
        more: with ``background=True`` it runs on a worker thread and the steps go
        on with the cut state before it, until a step finds the new one ready
        (``cut_pending`` says whether one is on its way). A position off the
        organ or a blade along the normal raises ``ScalpelInputError``; nothing
        changes then. The first call sets the scalpel up (milliseconds); placing
        it again, e.g. every servo tick, costs a few microseconds and allocates
        nothing (float64 (3,) arrays in).
        """
        if self._inside:
            self._busy("scalpel")
        self._inside = True
        try:
            # Scalpel() raises InputError for an artifact without a cuttable region.
            scalpel = self._cutting if self._cutting is not None else Scalpel(self.model)
            p, b = position, blade_direction
            if type(p) is not _NDARRAY or p.dtype is not _F8 or p.ndim != 1:
                p = _as_vector(p, self._point, "scalpel position (mm)", ScalpelInputError)
            if type(b) is not _NDARRAY or b.dtype is not _F8 or b.ndim != 1:
                b = _as_vector(b, self._blade_input, "blade direction", ScalpelInputError)
            last = self._placement
            if (len(p) == 3 and len(b) == 3 and p[0] == last[0] and p[1] == last[1]
                    and p[2] == last[2] and b[0] == last[3] and b[1] == last[4]
                    and b[2] == last[5]):  # fmt: skip
                self._armed, self._background = True, bool(background)  # same place: re-arm
                return
            floats, ints = scalpel.tables
            status = kernels.place_scalpel(
                p,
                b,
                floats,
                ints,
                self._table,
                self.model.sample_triangles,
                self._vertices,
                self._buf,
            )  # the blade's frame and the contact in one call; nothing written if refused
            if status:
                raise scalpel.placement_error(status, p, b)
            self._cutting = scalpel
            self._contact_series()
            placed = kernels.PLACED
            self._scalpel_vertex = int(self._buf[placed])
            self._vertex = int(self._buf[placed + 1])
            self._armed, self._background = True, bool(background)
            last[:3], last[3:] = p, b
        finally:
            self._inside = False

    def _cut_step(self, force) -> None:
        """After a step while cutting: install a ready background cut; cut if the force
        (N, on the tool or on the tissue) in the blade's plane passes the cut force.

        A cut that fails (e.g. a patch that is no longer positive definite) changes
        nothing: the error is kept in ``cut_error`` and the servo loop goes on.
        """
        scalpel = self._cutting
        try:
            if scalpel._pending:  # a background cut: install it once ready (between steps)
                event = scalpel.poll()
                if event is not None:
                    self.last_cut = event
            if self._armed:
                f0, f1, f2 = force
                a0, a1, a2 = self._across
                across = f0 * a0 + f1 * a1 + f2 * a2
                if f0 * f0 + f1 * f1 + f2 * f2 - across * across > scalpel.cut_force**2:
                    # Once per placement: an unmoved scalpel has nothing new under it, and
                    # the steps stay cheap until scalpel() places it again.
                    self._armed = False
                    vertex = self._scalpel_vertex
                    faces = scalpel.faces_under(
                        self.model.vertices[vertex], self._blade, scalpel.normals[vertex]
                    )
                    event = scalpel.cut(faces, wait=not self._background)
                    if event is not None:
                        self.last_cut = event
        except Exception as exc:  # noqa: BLE001 - the servo loop must not stop here
            self.cut_error = exc
            warnings.warn(f"a cut failed and was not made: {exc!r}", RuntimeWarning, stacklevel=3)

    @property
    def cut_stiffness_ratio(self) -> float:
        """The cuts' softening at the contact: cut / intact stiffness under the tool (1 uncut)."""
        if self._cutting is None or self._vertex < 0:
            return 1.0
        return float(self._cutting.ratio[self._vertex])

    @property
    def cut_pending(self) -> bool:
        """Whether a background cut is being prepared (see ``scalpel(background=True)``)."""
        return self._cutting is not None and self._cutting.pending

    def finish_cuts(self) -> None:
        """Wait for the background cuts and put them in force (e.g. before rendering a frame
        that must show them)."""
        if self._cutting is None:
            return
        if self._inside:
            self._busy("finish_cuts")
        self._inside = True
        try:
            event = self._cutting.finish()
            if event is not None:
                self.last_cut = event
        finally:
            self._inside = False

    @property
    def cut_events(self) -> list:
        """Every topology change so far (CutEvent: faces, new nodes, patch size, seconds)."""
        return [] if self._cutting is None else list(self._cutting.events)

    def step_force(self, f) -> np.ndarray:
        """Force the tool applies to the tissue ``f`` (N) -> tool displacement (mm).

        The returned array (read only) is reused by the next call. A force longer
        than ``max_force``, or one that would push the tool further than
        ``max_displacement`` (cuts included), is refused (StepInputError). Only a cut
        made by this very step can soften the tissue past the limit: the displacement
        is then held at it.
        """
        if self._inside:
            self._busy("step_force")
        self._inside = True
        try:
            if not self._contact:
                self._refuse(-1, "force (N)", f, 0.0)
            x = f  # a 1-D float64 array goes straight in; anything else: TypeError below
            if self._cutting is not None:  # cut tissue yields 1 / ratio times more: less depth
                ratio = self._cutting.ratio[self._vertex] if self._vertex >= 0 else 1.0
                self._buf[kernels.MAX_DEPTH] = self._buf[kernels.MAX_DISPLACEMENT] * ratio
            try:
                status = self._step_force(x, self._buf)
            except TypeError:  # the slower path: converted into a buffer, or refused
                x = _as_vector(x, self._input, "force (N)", StepInputError)
                status = self._step_force(x, self._buf)
            if status:
                self._refuse(status, "force (N)", f, self.max_force)
            self._controlled = "force"
            if self._cutting is not None:
                self._cut_step(x)
                if self._vertex >= 0:
                    self._scale_displacement(self._cutting.ratio[self._vertex])
            return self._displacement_out
        finally:
            self._inside = False

    def _scale_displacement(self, ratio: float) -> None:
        """Linear scaling: the cut tissue yields 1 / ratio times more under the same force;
        held at the displacement limit (a cut of this step may have softened it past)."""
        d = self._displacement
        d /= ratio
        size = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        limit = self._buf[kernels.MAX_DISPLACEMENT]
        if size > limit:
            d *= limit / size

    def surface_displacement(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` (V, 3) float64 with the surface vertices' displacement (mm)."""
        m = self.model
        if out.shape != m.vertices.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
            raise ValueError(
                f"out must be a C-contiguous float64 array of shape {m.vertices.shape}, "
                f"got {out.dtype} {out.shape}"
            )
        if self._inside:
            self._busy("surface_displacement")
        self._inside = True
        try:
            self._surface(out)
        finally:
            self._inside = False
        return out

    def _surface(self, out: np.ndarray) -> None:
        m = self.model
        if self.response == "anm":
            a = m.anm
            kernels.surface_anm(
                self._vertices, a["offsets"], self._buf, a["coefficients"], m.surface_basis_t,
                self._scratch, out,
            )  # fmt: skip
        elif self.interpolation == "grassmann":
            g = m.grassmann
            kernels.surface_grassmann(
                self.depth, m.depth_step, self._weights, self._vertices, g["reference"],
                m.surface_basis_t, g["tangents_t"], self._frames, m.coefficients, self._scratch,
                out,
            )  # fmt: skip
        else:
            kernels.surface_podi(
                self.depth, m.depth_step, self._weights, self._vertices, m.surface_basis_t,
                m.coefficients, self._scratch, out,
            )  # fmt: skip
        if self._cutting is not None and self._cutting.patch is not None:
            self._add_cut_field(out)

    def _add_cut_field(self, out: np.ndarray) -> None:
        """The cuts' displacement (per unit force, times the current force) and the lips.

        Under displacement control the reduced model's field is that of the intact
        tissue at the tool's depth, while the cut tissue reaches that depth at a
        lower force: the cut's field already holds the extra depth (its compliance
        increase times the force), so the intact part is scaled down to the depth
        the intact tissue would have under that force (linear, as the cut's field).
        """
        scalpel = self._cutting
        field = scalpel.cut_field(self._vertex) if self._vertex >= 0 else None
        on, region_of_on, copies, lip_vertices = scalpel.surface_layout()
        force = float(np.linalg.norm(self._force))
        if field is not None and self._controlled == "displacement" and self.depth > 0:
            extra = force * scalpel.extra_compliance[self._vertex]
            out *= max(0.0, 1.0 - extra / self.depth)
        base = out[lip_vertices]
        if field is not None:
            out[on] += force * field[region_of_on]
            base = base + force * field[copies]
        self._lips = (base, lip_vertices)

    def cut_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, triangles) to render with the cut open: the model's surface vertices,
        then the lip copies (``lip_vertices`` order), and the triangles re-indexed so each lip
        uses its own vertices. Without a cut, the model's surface. Read only."""
        m = self.model
        if self._cutting is None or self._cutting.patch is None:
            return _readonly(m.vertices), _readonly(m.triangles)
        _, _, _, duplicated = self._cutting.surface_layout()
        vertices = np.vstack([m.vertices, m.vertices[duplicated]])
        return _readonly(vertices), _readonly(self._cutting.surface_triangles())

    @property
    def lip_vertices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cut's second lip for rendering: (surface vertex each copies, its reference
        position (mm), its displacement (mm) at the last ``surface_displacement``)."""
        displacement, vertices = self._lips
        return _readonly(vertices), self.model.vertices[vertices], _readonly(displacement)

    # -- what the simulator can read ---------------------------------------------
    @property
    def contact_normal(self) -> np.ndarray:
        """Outward unit surface normal at the contact (interpolated; read only, and it
        changes with the contact: copy it to keep it)."""
        return self._normal_out

    @property
    def depth(self) -> float:
        """Current indentation depth (mm)."""
        return float(self._buf[kernels.DEPTH])

    @property
    def contact_stiffness(self) -> float:
        """d force / d depth at the current depth (N/mm): for the haptic loop's stability."""
        if self.response == "anm":
            return float(self._buf[kernels.ANM_SLOPE])
        m = self.model
        step = m.depth_step
        x = self.depth / step
        k = min(int(x), len(self._slope) - 2)
        t = min(x - k, 1.0)
        return float((1 - t) * self._slope[k] + t * self._slope[k + 1])

    @property
    def outside_trained_region(self) -> bool:
        return bool(int(self._buf[kernels.FLAGS]) & kernels.FLAG_OUTSIDE_REGION)

    @property
    def beyond_trained_depth(self) -> bool:
        return bool(int(self._buf[kernels.FLAGS]) & kernels.FLAG_BEYOND_DEPTH)

    @property
    def in_contact(self) -> bool:
        return not (int(self._buf[kernels.FLAGS]) & kernels.FLAG_NO_CONTACT)

    @property
    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(sample indices, barycentric weights) of the current contact."""
        return self._vertices.copy(), self._weights.copy()
