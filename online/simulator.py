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
return those (``step_displacement`` returns the same (3,) array every call:
copy it to keep it). Pass float64 arrays of shape (3,) to avoid conversions.
"""

from __future__ import annotations

import warnings

import numpy as np

from hapticrom.online import kernels
from hapticrom.online.model import INTERPOLATIONS, RESPONSES, ReducedModel


class StepInputError(ValueError):
    """A step input was NaN, infinite or absurd; the simulator state is unchanged."""


_STATUS = {
    1: "is not finite (NaN or infinite)",
    2: "is beyond the simulator's input limit",
}


class Simulator:
    """Mutable contact state on an immutable :class:`ReducedModel`.

    Limits (absurd inputs are rejected): ``max_displacement`` (mm, default 10x
    the trained depth) and ``max_force`` (N, default 10x the trained force).
    """

    def __init__(
        self,
        model: ReducedModel,
        interpolation: str = "podi",
        max_displacement: float | None = None,
        max_force: float | None = None,
        response: str | None = None,
    ):
        if response is None:
            response = "anm" if model.anm is not None else "curves"
        if response not in RESPONSES:
            raise ValueError(f"response must be one of {RESPONSES}, got {response!r}")
        if response == "anm" and model.anm is None:
            raise ValueError("this artifact carries no POD-ANM series (format 1.1 'anm' group)")
        if response == "anm" and interpolation == "grassmann":
            raise ValueError("the POD-ANM response blends fields by PODI; use interpolation='podi'")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(
                f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}"
            )
        if interpolation == "grassmann" and model.grassmann is None:
            raise ValueError("this artifact carries no Grassmann tangents")
        self.model, self.interpolation, self.response = model, interpolation, response
        self.max_displacement = float(max_displacement or 10 * model.trained_depth)
        self.max_force = float(max_force or 10 * model.force[:, -1].max())
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
        self._buf[k.MAX_DISPLACEMENT] = self.max_displacement
        self._buf[k.MAX_FORCE] = self.max_force
        self._buf[k.KNOTS] = K
        self._normal = self._buf[k.NORMAL : k.NORMAL + 3]  # views into the buffer
        self._force = self._buf[k.FORCE : k.FORCE + 3]
        self._displacement = self._buf[k.DISPLACEMENT : k.DISPLACEMENT + 3]
        self._curve = self._buf[k.CURVE : k.CURVE + K]
        self._slope = self._buf[k.CURVE + K : k.CURVE + 2 * K]
        self._chart = np.zeros(2)
        self._weights = np.zeros(3)
        self._vertices = np.zeros(3, dtype=np.int64)
        # bound once: no lookups per step
        self._step_displacement = k.step_displacement_anm if anm else k.step_displacement
        self._step_force = k.step_force_anm if anm else k.step_force
        self._scratch = np.zeros(3 + 3 * n)  # depth weights + three n-vectors
        self._frames = np.zeros((5, n, n))  # Grassmann: V cos S, V S^-1 sin S, R_0..R_2
        self._contact = False
        self._cutting = None  # online.cutting.Scalpel once the scalpel is used
        self._blade = None  # unit blade direction while the scalpel is in contact
        self._across = None  # unit normal of the blade's plane
        self._armed = False  # the blade may still cut at this placement
        self._background = False  # cut events on a worker thread (scalpel(background=True))
        self._vertex = -1  # region surface vertex at the contact (while cutting), or -1
        self.last_cut = None  # the last CutEvent
        self.cut_error = None  # the last cut that failed (an exception), if any
        self._lips = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64))  # second lip, rendered
        self._controlled = "displacement"  # the last step's control: the cut's field needs it

    # -- contact -----------------------------------------------------------------
    def set_contact(self, point) -> None:
        """Put (or slide) the tool's contact at ``point`` (mm, on or near the surface).

        Outside the trained region the contact is clamped to the nearest trained
        point (``outside_trained_region`` is then True).
        """
        m = self.model
        p = np.asarray(point, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise StepInputError(f"contact point must be 3 finite numbers (mm), got {point!r}")
        np.dot(m.chart_axes, p - m.chart_origin, out=self._chart)
        flag = kernels.locate(
            self._chart, m.chart_points, m.sample_triangles, self._weights, self._vertices
        )
        kernels.prepare_curves(
            self._weights, self._vertices, m.sample_normals, m.force, m.stiffness,
            self._normal, self._curve, self._slope,
        )  # fmt: skip
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
        self._buf[kernels.FLAGS] = flag
        self._contact = True
        if self._cutting is not None:
            self._armed = False  # a plain contact; scalpel() arms the blade again
            self._vertex = self._cutting.region_vertex(p)

    # -- steps -------------------------------------------------------------------
    def _check(self, status: int, what: str, value) -> None:
        if status == -1:
            raise RuntimeError("call set_contact(point) before stepping")
        raise StepInputError(f"{what} {value!r} {_STATUS[status]}; state unchanged")

    def step_displacement(self, d) -> np.ndarray:
        """Tool displacement ``d`` (mm, from the contact point) -> reaction force on the tool (N).

        The force points out of the tissue (along the outward normal). The
        returned array is reused by the next call.
        """
        status = self._step_displacement(d, self._buf) if self._contact else -1
        if status:
            self._check(status, "displacement", d)
        self._controlled = "displacement"
        if self._cutting is not None:
            self._cut_step(self._force)
            if self._vertex >= 0:
                self._force *= self._cutting.ratio[self._vertex]
        return self._force

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
        changes then.
        """
        from hapticrom.online.cutting import Scalpel

        m = self.model
        # Scalpel() raises ValueError for an artifact without a cuttable region.
        scalpel = self._cutting if self._cutting is not None else Scalpel(m)
        p = np.asarray(position, dtype=float)
        vertex = int(np.argmin(np.sum((m.vertices - p) ** 2, axis=1))) if p.shape == (3,) else 0
        normal = scalpel.normals[vertex]
        blade = scalpel.check(position, blade_direction, normal)[1]
        self._cutting = scalpel
        self.set_contact(p)
        self._vertex, self._scalpel_vertex = scalpel.region_vertex(p), vertex
        across = np.cross(blade, normal)
        self._blade, self._across = blade, across / np.linalg.norm(across)
        self._armed, self._background = True, bool(background)

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
        if self._cutting is not None:
            event = self._cutting.finish()
            if event is not None:
                self.last_cut = event

    @property
    def cut_events(self) -> list:
        """Every topology change so far (CutEvent: faces, new nodes, patch size, seconds)."""
        return [] if self._cutting is None else list(self._cutting.events)

    def step_force(self, f) -> np.ndarray:
        """Force the tool applies to the tissue ``f`` (N) -> tool displacement (mm)."""
        status = self._step_force(f, self._buf) if self._contact else -1
        if status:
            self._check(status, "force", f)
        self._controlled = "force"
        if self._cutting is not None:
            self._cut_step(f)
            if self._vertex >= 0:
                # Linear scaling: the cut tissue yields 1 / ratio times more under the same force.
                self._displacement /= self._cutting.ratio[self._vertex]
        return self._displacement

    def surface_displacement(self, out: np.ndarray) -> np.ndarray:
        """Fill ``out`` (V, 3) float64 with the surface vertices' displacement (mm)."""
        m = self.model
        if out.shape != m.vertices.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
            raise ValueError(
                f"out must be a C-contiguous float64 array of shape {m.vertices.shape}, "
                f"got {out.dtype} {out.shape}"
            )
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
        return out

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
        uses its own vertices. Without a cut, the model's surface."""
        m = self.model
        if self._cutting is None or self._cutting.patch is None:
            return m.vertices, m.triangles
        _, _, _, duplicated = self._cutting.surface_layout()
        vertices = np.vstack([m.vertices, m.vertices[duplicated]])
        return vertices, self._cutting.surface_triangles()

    @property
    def lip_vertices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cut's second lip for rendering: (surface vertex each copies, its reference
        position (mm), its displacement (mm) at the last ``surface_displacement``)."""
        displacement, vertices = self._lips
        return vertices, self.model.vertices[vertices], displacement

    # -- what the simulator can read ---------------------------------------------
    @property
    def contact_normal(self) -> np.ndarray:
        """Outward unit surface normal at the contact (interpolated)."""
        return self._normal

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
