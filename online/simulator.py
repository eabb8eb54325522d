"""The haptic simulator: one tool in contact with one reduced organ model (mm, N).

A haptic servo loop (OpenHaptics, CHAI3D) calls the physics about 1,000
times a second with a position and expects a force back::

    sim = hapticrom.online.load("cornea.h5").simulator()
    force = sim.step_position(tip)          # the tool tip's centre in, reaction force out
    sim.surface_displacement(vertex_disp)   # for rendering, into a caller-owned (V, 3) array

``step_position`` finds the contact itself (a spherical tip and a proxy on the surface:
:mod:`hapticrom.online.proxy`). A host with its own collision detection gives the contact
point and the tool's displacement from it instead::

    sim.set_contact(point)                  # where the tool touches (may slide)
    force = sim.step_displacement(d)        # tool displacement in, reaction force out

The model is the PODI contact model of the artifact: the samples' force-depth
curves and reduced fields, interpolated over the tool position (barycentric in
the samples' triangulation on the surface) and over the depth (monotone cubic for forces). A
displacement step is frictionless: the normal component of ``d`` indents the tissue and
the force is along the surface normal; to follow the tool sideways, move the
contact point (``set_contact`` every step is fine: it is microseconds). ``step_position``
adds Coulomb friction when asked (``set_friction``).

The rendered surface (``interpolation``): "transport" (the default where the model has a
chart) carries each neighbour's field to the contact before the blend, so the dent is under
the tool (:mod:`hapticrom.online.surface_chart`); "compliance" (the default otherwise, where
the artifact has contact fields) adds the tool's linear dent at the contact to the blend and
takes off its blend at the neighbours (:mod:`hapticrom.offline.reduce.contact_fields`);
"podi" blends them where each was trained; "grassmann" interpolates the bases.

Work that depends only on the contact point happens in ``set_contact`` (one
kernel call; the Grassmann frames, which only the surface needs, at the first
``surface_displacement`` after it). The steps allocate nothing: they write
into buffers owned by the simulator and return read-only views of those
(``step_displacement`` returns the same (3,) array every call: copy it to keep it).

Inputs (points, displacements, forces, the scalpel's position and blade): a 1-D
float64 numpy array of 3 elements goes straight to the kernel (any strides,
read-only or not: the fast path). Anything else that holds 3 numbers (a list, a
tuple, a float32 or integer array) takes a slower path: it is copied into a
(3,) float64 buffer of the simulator first (``np.asarray`` for a list or tuple:
about a microsecond more, and that allocates). Any other shape ((2,), (4,),
(3, 1), a scalar) or anything not numbers (strings, complex, bool, objects)
raises :class:`StepInputError` (``ScalpelInputError`` for the scalpel) naming
it, and changes nothing. A step before any contact raises ``NoContactError``, a
wrong ``out`` array ``OutputArrayError``: every error a call raises is a
:class:`~hapticrom.shared.errors.SimulatorError` (a ``HapticromError``; those
about inputs are ``ValueError`` too, the others ``RuntimeError``).

Threads: a simulator is driven by one thread at a time. Calls from a second
thread while one is inside a step, ``set_contact``, ``scalpel``, ``stiffness`` or
``surface_displacement`` raise :class:`SimulatorBusyError` (they are not queued:
a servo loop must not wait). Simulators on one shared :class:`ReducedModel` may
run on as many threads as you like, in parallel: the model is only read (the
step kernels release the GIL).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from hapticrom.online import kernels, proxy
from hapticrom.online.model import INTERPOLATIONS, RESPONSES, ReducedModel
from hapticrom.online.renderer import (
    SurfaceRenderer,
    SurfaceWork,
    check_surface_out,
    surface_of,
)
from hapticrom.online.scalpel import CuttingController, readonly
from hapticrom.shared.errors import (
    InputError,
    NoContactError,
    OutputArrayError,
    ScalpelInputError,
    SimulatorBusyError,
    StepInputError,
)

__all__ = ["ScalpelInputError", "Simulator", "SimulatorBusyError", "StepInputError"]

_NDARRAY, _F8 = np.ndarray, np.dtype(np.float64)
_KEPT = "state unchanged"
_place_scalpel, _NO_VERTEX = kernels.place_scalpel, kernels.NO_VERTEX  # no lookups per call
_step_position, _stiffness = proxy.step_position, proxy.stiffness


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


MAX_FRICTION = 10.0  # friction coefficients and the tangential stiffness ratio: at most this
_STIFFNESS_OUT = "a writeable, C-contiguous float64 numpy array of shape (3, 3)"


def _described(out) -> str:
    """What is wrong with an ``out`` array, for its error: type, dtype, shape and flags."""
    if not isinstance(out, np.ndarray):
        return type(out).__name__
    flags = [] if out.flags.writeable else ["read-only"]
    flags += [] if out.flags.c_contiguous else ["not C-contiguous"]
    return f"{out.dtype} {out.shape}" + (f" ({', '.join(flags)})" if flags else "")


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


def _coefficient(value, name: str) -> float:
    """A friction coefficient: a finite real number in [0, MAX_FRICTION]."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"the {name} must be a number, got {value!r}")
    if not (math.isfinite(value) and 0.0 <= value <= MAX_FRICTION):
        raise InputError(f"the {name} must be finite and in [0, {MAX_FRICTION}]; got {value!r}")
    return float(value)


def friction_values(static, dynamic=None, tangential_stiffness=None) -> tuple[float, ...]:
    """(mu_s, mu_d, tangential stiffness ratio) of ``Simulator.set_friction``'s arguments,
    checked (the one validator: the C ABI's ``hapticrom_set_friction`` calls it too);
    InputError naming the culprit."""
    mu_s = _coefficient(static, "static friction coefficient")
    mu_d = mu_s if dynamic is None else _coefficient(dynamic, "dynamic friction coefficient")
    if mu_d > mu_s:
        raise InputError(
            f"the dynamic friction coefficient ({mu_d!r}) must not exceed the static one "
            f"({mu_s!r}): a sliding contact would hold more than a stuck one"
        )
    ratio = _limit(tangential_stiffness, 2.0 / 3.0, "tangential_stiffness", "x normal")
    if ratio > MAX_FRICTION:
        raise InputError(
            f"tangential_stiffness must be at most {MAX_FRICTION} (times the normal contact "
            f"stiffness); got {ratio!r}"
        )
    return mu_s, mu_d, ratio


def _check_config(model: ReducedModel, interpolation: str, response: str | None) -> str:
    """The response to use (the model's default if None); InputError if they do not fit."""
    if interpolation == "transport" and model.chart is None:
        raise InputError(
            "this model has no surface chart (one plan view cannot hold its samples and "
            "surface, see hapticrom.online.surface_chart): use interpolation='podi'"
        )
    if response is None:
        response = "anm" if model.anm is not None else "curves"
    if response not in RESPONSES:
        raise InputError(f"response must be one of {RESPONSES}, got {response!r}")
    if response == "anm" and model.anm is None:
        raise InputError("this artifact carries no POD-ANM series (format 1.1 'anm' group)")
    if response == "anm" and interpolation == "grassmann":
        raise InputError(
            "the POD-ANM response has no Grassmann field; use interpolation='transport' or 'podi'"
        )
    if interpolation not in INTERPOLATIONS:
        raise InputError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    if interpolation == "grassmann" and model.grassmann is None:
        raise InputError("this artifact carries no Grassmann tangents")
    if interpolation == "compliance" and model.contact_fields is None:
        raise InputError(
            "this artifact carries no contact fields (format 2.2 'contact_fields' group; "
            "reduce its campaign again, or use interpolation='podi')"
        )
    return response


def default_interpolation(model: ReducedModel) -> str:
    """The rendered surface a model gets unless asked: "transport" where it has a chart
    (the cornea demo: 2.4 % against 3 % for "compliance", README), else "compliance" where it
    has the contact fields (the liver: 0.8 % against PODI's 38 %), else "podi"."""
    if model.chart is not None:
        return "transport"
    return "compliance" if model.contact_fields is not None else "podi"


def _outside_part(model: ReducedModel) -> tuple | None:
    """:func:`kernels.outside_part`'s arguments: the loadable triangles' corners and linear
    stiffness and their grid (a contact outside the trained region is scaled by them), or
    None without the stiffness (artifact 2.3)."""
    f = model.contact_fields
    if f is None or f["stiffness_nodes"] is None:
        return None
    corners = model.vertices[f["triangles"]]
    return (corners, f["stiffness_nodes"], f["grid"], f["grid_starts"], f["grid_ids"],
            model.contact_radius)  # fmt: skip


def _state_buffer(model: ReducedModel, anm: dict | None, max_displacement: float,
                  max_force: float) -> np.ndarray:  # fmt: skip
    """A new simulator's state buffer (layout: :mod:`hapticrom.online.kernels`)."""
    k = kernels
    K = model.force.shape[1]
    n1, smax, q = (anm["n1"], anm["smax"], anm["section_knots"]) if anm else (0, 0, 0)
    buf = np.zeros(k.buffer_size(K, n1, smax, q))
    if anm:
        buf[k.ANM_BASE] = k.CURVE + 2 * K
        buf[k.ANM_N1] = n1
        buf[k.ANM_SMAX] = smax
        buf[k.SECTION_KNOTS] = q
        for j in range(3):  # no sample's records in the blocks yet
            buf[k.CURVE + 2 * K + j * k.anm_block_size(q, smax) + k.BLOCK_SAMPLE] = -1.0
    buf[k.STEP] = model.depth_step
    buf[k.MAX_DISPLACEMENT] = buf[k.MAX_DEPTH] = max_displacement
    buf[k.MAX_FORCE] = max_force
    buf[k.KNOTS] = K
    buf[k.PLACED : k.PLACED + 2] = k.NO_VERTEX  # no scalpel placed
    buf[k.PLACEMENT : k.PLACEMENT + 6] = np.nan
    return buf


class Simulator:
    """Mutable contact state on an immutable :class:`ReducedModel`.

    Limits (absurd inputs are refused with :class:`StepInputError`, the state
    unchanged): ``max_displacement`` (mm, default 10x the trained depth, the depth every
    sample was solved to; it also sets how far beside the loadable surface's border
    ``step_position`` fades out) bounds the
    tool displacement a displacement step takes and the one a force step returns (a
    force that would push the tool further is refused); ``max_force`` (N, default
    10x the largest trained force) bounds the force a force step takes. Each is None (the
    default) or a finite positive number; anything else raises ``InputError``.

    Threads: one simulator is stepped by one thread at a time (a call while another
    thread is inside one raises :class:`SimulatorBusyError`); simulators sharing one
    model may step on parallel threads.

    Cutting: the first ``scalpel()`` call composes a
    :class:`~hapticrom.online.scalpel.CuttingController` into the simulator
    (``cutting``); everything the cuts change goes through it.
    """

    def __init__(
        self,
        model: ReducedModel,
        interpolation: str | None = None,
        max_displacement: float | None = None,
        max_force: float | None = None,
        response: str | None = None,
        tool_radius: float | None = None,
    ):
        if interpolation is None:
            interpolation = default_interpolation(model)
        response = _check_config(model, interpolation, response)
        self.model, self.interpolation, self.response = model, interpolation, response
        anm = model.anm if response == "anm" else None
        max_displacement = _limit(
            max_displacement, 10 * model.trained_depth, "max_displacement", "mm"
        )
        max_force = _limit(max_force, 10 * model.sample_trained_force.max(), "max_force", "N")
        k = kernels
        self._buf = _state_buffer(model, anm, max_displacement, max_force)
        # What the caller sees: views of the buffer that cannot be written through.
        self._normal_out = readonly(self._buf[k.NORMAL : k.NORMAL + 3])
        self._force = self._buf[k.FORCE : k.FORCE + 3]
        self._force_out = readonly(self._force)
        self._displacement = self._buf[k.DISPLACEMENT : k.DISPLACEMENT + 3]
        self._displacement_out = readonly(self._displacement)
        self._weights = self._buf[k.WEIGHTS : k.WEIGHTS + 3]
        self._samples = self._buf[k.SAMPLES : k.SAMPLES + 3]  # the contact's three samples
        self._input = np.zeros(3)  # the slower path's copy of a step input
        self._point, self._blade_input = np.zeros(3), np.zeros(3)  # ... of a point, a blade
        # The model's arrays set_contact reads, packed into one read-only array.
        self._table = k.contact_table(
            model.sample_points, model.sample_normals, model.force, model.stiffness,
            model.solved_depth, model.sample_triangles,
            *((anm["records"], anm["offsets"]) if anm else (None, None)),
            tool_stiffness=model.tool_stiffness, floors=model.sample_floors,
            outside=_outside_part(model),
        )  # fmt: skip
        # bound once: no lookups per step
        self._step_displacement = k.step_displacement_anm if anm else k.step_displacement_curves
        self._step_force = k.step_force_anm if anm else k.step_force_curves
        self._work = SurfaceWork(model, interpolation, response)  # the surface's scratch
        # Writing calls add 1 before and after: a SurfaceRenderer copies the state whole.
        self._sequence = 0
        self._controlled = "displacement"  # the last step's control (the cuts' field needs it)
        self.cutting: CuttingController | None = None  # the scalpel, from its first placement
        # step_position's sphere against the offset sheet, and the proxy's state on it.
        self.tool_radius = _limit(tool_radius, model.contact_radius, "tool_radius", "mm")
        self._sheet = model.contact_sheet(self.tool_radius)
        self._proxy = np.zeros(proxy.state_size(self._sheet))
        self._proxy_out = readonly(self._proxy[proxy.STATE_PROXY : proxy.STATE_PROXY + 3])
        self._foot_out = readonly(self._proxy[proxy.STATE_FOOT : proxy.STATE_FOOT + 3])
        # True while a thread is inside a call. A flag, not a lock: a lock's acquire and
        # release cost more than half a step. Under CPython's GIL nothing runs between its
        # test and its setting, so a second thread always sees it (the steps' kernels let
        # the GIL go; a free-threaded Python could miss a race).
        self._inside = False

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
        self._sequence += 1  # odd: the state is being written
        try:
            p = point
            if type(p) is not _NDARRAY or p.dtype is not _F8 or p.ndim != 1:
                p = _as_vector(p, self._point, "contact point (mm)", StepInputError)
            region = kernels.prepare_contact(p, self._table, self._buf)
            if region < _NO_VERTEX:
                self._refuse_point(-region, p, point)
            if self.cutting is not None:
                self.cutting.moved(region)  # a plain contact; scalpel() arms the blade again
        finally:
            self._sequence += 1
            self._inside = False

    def _refuse_point(self, status: int, p: np.ndarray, point) -> None:
        """Raise the error of a contact point the kernel refused (the state is unchanged)."""
        if status == kernels.WRONG_SHAPE:
            raise StepInputError(
                f"contact point (mm) must be 3 numbers, shape (3,); got shape {p.shape}; {_KEPT}"
            )
        raise StepInputError(f"contact point (mm) must be 3 finite numbers, got {point!r}; {_KEPT}")

    # -- steps -------------------------------------------------------------------
    def _converted(self, value, what: str) -> np.ndarray:
        """A step input that is not a 1-D float64 array, copied into a buffer (or refused)."""
        return _as_vector(value, self._input, what, StepInputError)

    def _refuse(self, status: int, what: str, value, limit: float) -> None:
        """Raise the error of a step's status (the state is unchanged)."""
        if status == kernels.NO_CONTACT_POINT:
            raise NoContactError("call set_contact(point) before stepping")
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
        self._sequence += 1  # odd: the state is being written
        try:
            try:  # a 1-D float64 array goes straight in; anything else: TypeError
                status = self._step_displacement(d, self._buf)
            except TypeError:  # the slower path: converted into a buffer, or refused
                status = self._step_displacement(self._converted(d, "displacement (mm)"), self._buf)
            if status:
                self._refuse(status, "displacement (mm)", d, self.max_displacement)
            self._controlled = "displacement"
            if self.cutting is not None:
                self.cutting.displacement_stepped(self._force)
            return self._force_out
        finally:
            self._sequence += 1
            self._inside = False

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
        self._sequence += 1  # odd: the state is being written
        try:
            if self.cutting is not None:  # cut tissue yields more: a nearer depth limit
                self.cutting.limit_depth()
            x = f  # a 1-D float64 array goes straight in; anything else: TypeError below
            try:
                status = self._step_force(x, self._buf)
            except TypeError:  # the slower path: converted into a buffer, or refused
                x = self._converted(x, "force (N)")
                status = self._step_force(x, self._buf)
            if status:
                self._refuse(status, "force (N)", f, self.max_force)
            self._controlled = "force"
            if self.cutting is not None:
                self.cutting.force_stepped(x, self._displacement)
            return self._displacement_out
        finally:
            self._sequence += 1
            self._inside = False

    def step_position(self, tip) -> np.ndarray:
        """Tool tip centre ``tip`` (mm) in, reaction force on the tool (N) out: position in,
        force out, as a haptic device's servo loop calls it.

        The tip is a sphere of ``tool_radius`` (the training's by default); the proxy
        finds the contact, slides it over the surface as the tip moves, releases it when
        the tip leaves, and never lets it pass through the organ (see
        :mod:`hapticrom.online.proxy`). Out of contact the force is zero (``in_contact``
        False). A displacement beyond ``max_displacement`` is held at it (``saturated``),
        not refused: a servo loop must get a force every tick. A tip that is not 3
        finite numbers raises StepInputError (the state unchanged). The returned array
        (read only) is reused by the next call. A placed scalpel stays armed while the
        proxy is at the cut region's vertex it was placed at (``scalpel(sim.contact_point,
        blade)`` each tick follows the tool), and cuts as under a displacement step.
        """
        if self._inside:
            self._busy("step_position")
        self._inside = True
        self._sequence += 1  # odd: the state is being written
        try:
            try:  # a 1-D float64 array goes straight in; anything else: TypeError
                region = _step_position(tip, self._sheet, self._proxy, self._table, self._buf)
            except TypeError:  # the slower path: converted into a buffer, or refused
                p = self._converted(tip, "tool tip (mm)")
                region = _step_position(p, self._sheet, self._proxy, self._table, self._buf)
            if region < _NO_VERTEX:
                status = -region if region != -kernels.POSITION_NOT_FINITE else kernels.NOT_FINITE
                self._refuse(status, "tool tip (mm)", tip, math.inf)
            self._controlled = "displacement"
            if self.cutting is not None and self._proxy[proxy.STATE_MODE] == proxy.TOUCHING:
                cutting = self.cutting
                # The proxy slides every tick: the blade stays armed while it is on the region
                # vertex the scalpel was placed at (as a displacement step after scalpel()),
                # and is disarmed once it leaves it (as set_contact elsewhere does).
                if not (cutting.armed and region >= 0 and region == cutting.vertex):
                    cutting.moved(region)
                cutting.displacement_stepped(self._force)
            return self._force_out
        finally:
            self._sequence += 1
            self._inside = False

    def stiffness(self, out: np.ndarray) -> np.ndarray:
        """The 3x3 contact stiffness K (N/mm) of the last step into ``out`` (a C-contiguous
        float64 (3, 3) array): the force on the tool near the tip x is F(x + dx) ~ F - K dx,
        for hosts that step the physics slower than the device loop and extrapolate.
        Frictionless: K = dF/ddepth n n^T (softened by the cuts at the contact, as the force
        is); zero out of contact. SimulatorBusyError while another thread is inside a call."""
        if self._inside:  # a step half done: the slope of one contact, the normal of another
            self._busy("stiffness")
        self._inside = True
        try:
            try:
                status = _stiffness(self._buf, out)
            except TypeError:
                status = kernels.WRONG_SHAPE
            if status:
                raise OutputArrayError(f"out must be {_STIFFNESS_OUT}; got {_described(out)}")
            if self.cutting is not None:
                out *= self.cutting.ratio
            return out
        finally:
            self._inside = False

    def set_friction(self, static: float, dynamic: float | None = None,
                     tangential_stiffness: float | None = None) -> None:  # fmt: skip
        """Coulomb friction for ``step_position`` (frictionless, 0, by default): the proxy
        sticks while the tangential force is at most ``static`` times the normal force and
        slides with ``dynamic`` (default: ``static``) times it otherwise (stick-slip; as
        OpenHaptics' and CHAI3D's static and dynamic friction). The tangential force while
        stuck is a spring from the frictionless proxy to the stuck one, of stiffness
        ``tangential_stiffness`` times the normal contact stiffness (default 2/3: Mindlin's
        2 (1 - nu) / (2 - nu) for incompressible tissue). The rendered field stays the normal
        indentation (the model's): the tissue's drag is in the force only. ``stiffness``
        gives the tangential terms. Coefficients must be finite, 0 <= dynamic <= static <=
        MAX_FRICTION; else InputError, nothing changed."""
        if self._inside:
            self._busy("set_friction")
        self._inside = True  # a step must not read the coefficients half written
        try:
            values = friction_values(static, dynamic, tangential_stiffness)
            self._buf[kernels.FRICTION : kernels.FRICTION + 3] = values
        finally:
            self._inside = False

    @property
    def friction(self) -> tuple[float, float, float]:
        """(static, dynamic coefficient, tangential stiffness ratio) of ``set_friction``."""
        mu_s, mu_d, ratio = self._buf[kernels.FRICTION : kernels.FRICTION + 3]
        return float(mu_s), float(mu_d), float(ratio)

    @property
    def slipping(self) -> bool:
        """Whether the last ``step_position`` slid with friction (False: stuck, or none)."""
        return bool(self._buf[kernels.SLIPPING])

    @property
    def proxy(self) -> np.ndarray:
        """Where the tool's centre would be if the tissue did not yield (mm; read only): on
        the surface offset by the tool radius in contact, the tip itself when free."""
        return self._proxy_out

    @property
    def contact_point(self) -> np.ndarray:
        """Where ``step_position``'s tool touches the undeformed surface (mm; read only): the
        proxy's foot, the point the contact model is evaluated at."""
        return self._foot_out

    @property
    def saturated(self) -> bool:
        """Whether the last ``step_position`` held the displacement at ``max_displacement``."""
        return bool(self._proxy[proxy.STATE_SATURATED])

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
        changes then. The first call sets the scalpel up (milliseconds; an artifact
        without a cuttable region raises ``InputError``); placing it again, e.g.
        every servo tick, costs a few microseconds and allocates nothing (float64
        (3,) arrays in).
        """
        if self._inside:
            self._busy("scalpel")
        self._inside = True
        self._sequence += 1  # odd: the state is being written
        try:
            cutting = self.cutting
            if cutting is None:  # kept once a placement succeeds
                cutting = CuttingController(self.model, self._buf, self._table)
            p, b = position, blade_direction
            # The blade's frame and the contact in one call; nothing written if refused.
            try:  # 1-D float64 arrays go straight in; anything else: TypeError
                region = _place_scalpel(p, b, cutting.table, self._buf)
            except TypeError:  # the slower path: converted into buffers, or refused
                p = _as_vector(p, self._point, "scalpel position (mm)", ScalpelInputError)
                b = _as_vector(b, self._blade_input, "blade direction", ScalpelInputError)
                region = _place_scalpel(p, b, cutting.table, self._buf)
            if region < _NO_VERTEX:
                raise cutting.placement_error(-region, p, b)
            if self.cutting is None:
                self.cutting, self._table = cutting, cutting.table
            cutting.placed(region, background)
        finally:
            self._sequence += 1
            self._inside = False

    @property
    def last_cut(self):
        """The last cut event (``CutEvent``: faces, new nodes, patch size, seconds), or None."""
        return None if self.cutting is None else self.cutting.last_cut

    @property
    def cut_error(self) -> Exception | None:
        """The last cut that failed (an exception; it changed nothing), or None."""
        return None if self.cutting is None else self.cutting.cut_error

    @property
    def cut_stiffness_ratio(self) -> float:
        """The cuts' softening at the contact: cut / intact stiffness under the tool (1 uncut)."""
        return 1.0 if self.cutting is None else self.cutting.ratio

    @property
    def cut_pending(self) -> bool:
        """Whether a background cut is being prepared (see ``scalpel(background=True)``)."""
        return self.cutting is not None and self.cutting.cuts.pending

    def finish_cuts(self) -> None:
        """Wait for the background cuts and put them in force (e.g. before rendering a frame
        that must show them)."""
        if self.cutting is None:
            return
        if self._inside:
            self._busy("finish_cuts")
        self._inside = True
        try:
            self.cutting.finish()
        finally:
            self._inside = False

    @property
    def cut_events(self) -> list:
        """Every topology change so far (CutEvent: faces, new nodes, patch size, seconds)."""
        return [] if self.cutting is None else list(self.cutting.cuts.events)

    def __reduce__(self):
        """Refused: copied or pickled, the outputs (views into the state buffer) would come
        apart from the copy's buffer, and the surface's packed addresses are the original's."""
        raise TypeError(
            "a Simulator cannot be copied or pickled: make another with model.simulator(...) "
            "and replay the calls that brought this one to its state"
        )

    # -- rendering -------------------------------------------------------------------
    def renderer(self) -> SurfaceRenderer:
        """A render thread's view of this simulator: its ``surface(out)`` renders the state of
        one whole step while the servo thread steps on (no torn frames, no waiting servo).
        One per render thread; see :mod:`hapticrom.online.renderer`."""
        return SurfaceRenderer(self)

    def surface_displacement(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` (V, 3) float64 with the surface vertices' displacement (mm), on the
        thread that steps (another thread: :meth:`renderer`)."""
        check_surface_out(self.model, out)
        if self._inside:
            self._busy("surface_displacement")
        self._inside = True
        try:
            self._surface(out)
        finally:
            self._inside = False
        return out

    def _surface(self, out: np.ndarray) -> None:
        surface_of(self._buf, self._work, out)
        if self.cutting is not None:
            self.cutting.add_field(out, self._force, self.depth, self._controlled)

    def cut_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, triangles) to render with the cut open: the model's surface vertices,
        then the lip copies (``lip_vertices`` order), and the triangles re-indexed so each lip
        uses its own vertices. Without a cut, the model's surface. Read only."""
        if self.cutting is None:
            return readonly(self.model.vertices), readonly(self.model.triangles)
        return self.cutting.surface()

    @property
    def lip_vertices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cut's second lip for rendering: (surface vertex each copies, its reference
        position (mm), its displacement (mm) at the last ``surface_displacement``)."""
        if self.cutting is None:
            return readonly(np.zeros(0, dtype=np.int64)), np.zeros((0, 3)), np.zeros((0, 3))
        displacement, vertices = self.cutting.rendered_lips
        return readonly(vertices), self.model.vertices[vertices], readonly(displacement)

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
        return float(kernels.contact_stiffness(self._buf))

    @property
    def outside_trained_region(self) -> bool:
        """Whether the contact point lies outside the trained region (clamped to it)."""
        return bool(int(self._buf[kernels.FLAGS]) & kernels.FLAG_OUTSIDE_REGION)

    @property
    def beyond_trained_depth(self) -> bool:
        """Whether the last step went deeper than the trained range (extrapolated): for the
        curves, deeper than the smallest solved depth of the contact's neighbours; for
        POD-ANM, past a neighbour's last section."""
        return bool(int(self._buf[kernels.FLAGS]) & kernels.FLAG_BEYOND_DEPTH)

    @property
    def error_estimate(self) -> float:
        """The error indicator at the contact (relative force error, 1): the samples'
        leave-one-out errors blended with the contact's weights (artifact
        ``samples/indicator``). It overestimates the error between well-spaced samples
        (see README, "Interpolation on the surface"); outside the trained region it is
        the border's. NoContactError before the first ``set_contact``."""
        if self._buf[kernels.CONTACTS] == 0:
            raise NoContactError(
                "error_estimate: no contact point yet; call set_contact(point) first"
            )
        w, i = self._weights, self._samples
        e = self.model.indicator
        return float(w[0] * e[int(i[0])] + w[1] * e[int(i[1])] + w[2] * e[int(i[2])])

    @property
    def in_contact(self) -> bool:
        """Whether the tool pressed the tissue at the last step (False: it pulled away, or
        nothing was stepped yet)."""
        if self._buf[kernels.CONTACTS] == 0:  # no contact yet: nothing pressed
            return False
        return not (int(self._buf[kernels.FLAGS]) & kernels.FLAG_NO_CONTACT)

    @property
    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(sample indices, barycentric weights) of the current contact."""
        return self._samples.astype(np.int64), self._weights.copy()
