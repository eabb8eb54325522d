"""Physics sanity of a full-order load path: is the answer physical, and is the path smooth?

A converged Newton solve is not yet a physical answer: Saint Venant-Kirchhoff
softens without bound in compression (thesis ch. 5) and happily crushes a wall
to a tenth of its thickness, or converges on the far side of a snap-through
that force control jumped over. Every solve measures, after each converged
load step (MPI reductions over the owned cells: any number of ranks gives the
serial values):

- ``j_min``: the smallest volume ratio J = det F over the quadrature points;
- ``stretch_min``: the smallest principal stretch over the quadrature points
  (the square root of the smallest eigenvalue of C = F^T F), and the largest
  **compression** ``1 - stretch_min``: a length measure (0.88: a material line
  shortened to 12 % of its length), which sees a crushed wall even when J stays
  near 1 in nearly incompressible tissue (an inverted point counts as stretch
  0); ``where``: the reference midpoint (mm) of the cell where it occurs;
- ``inverted``: the number of cells with J <= 0 at a quadrature point;
- ``u_max``: the largest nodal displacement magnitude (mm);
- ``depth`` and ``force``: the contact patch's mean displacement (mm) and the
  tool's force (N) along the load direction;
- ``tangent_negative``: negative (or zero) eigenvalues of the tangent with the
  pressure condensed out (the inertia of an LDL^T factorisation by MUMPS minus
  the pressure unknowns, whose block is negative definite). Computed where the
  path softens (the step's secant compliance ``TANGENT_SOFTENING`` times the
  previous one's, or negative) and at the last step; -1 where not computed
  (elsewhere, or with an iterative linear solver: no factorisation).

The load path is judged from the secant compliance c_i = (depth_i -
depth_{i-1}) / (force_i - force_{i-1}) of each step (from the unloaded state):

- **jump** (snap-through): c_i > ``JUMP_FACTOR`` c_{i-1};
- **softening** (close to a limit point): c_i > ``SOFTENING_FACTOR`` c_1;
- **limit point**: a negative secant stiffness (the force falls while the
  depth grows, or the reverse): the path went past a maximum;
- **tangent**: an unstable (or singular) converged state;
- **compression** above ``COMPRESSION_LIMIT``, **volume** J below ``J_MIN_LIMIT``,
  **inversion** (any J <= 0).

Each flag carries a message with the numbers and the report a suggestion (another law, a
smaller load, a finer mesh: ``hapticrom solve --refinement-check`` solves the same
problem on the next finer built-in mesh, :func:`run_refinement_check`; ``hapticrom
campaign --refinement-check`` does so for the campaign's position 0).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

VERSION = 1
# A principal stretch below 0.5 (a material line halved) is beyond what soft tissue
# takes under a haptic tool and where SVK's compressive stiffness has already collapsed
# (its uniaxial stress peaks at a stretch of 1/sqrt(3) = 0.58).
COMPRESSION_LIMIT = 0.5
# Half the volume lost: impossible for nearly incompressible tissue (nu >= 0.45).
J_MIN_LIMIT = 0.5
# A step whose depth grows more than 3x faster per newton than in the previous step:
# smooth softening paths change by a few tens of percent per step.
JUMP_FACTOR = 3.0
# The secant stiffness below a quarter of the initial one: a limit point is close.
SOFTENING_FACTOR = 4.0
# Relative roundoff below which a force or depth increment counts as zero.
PATH_ROUNDOFF = 1e-9
# The tangent is factorised (LDL^T) at a step whose secant compliance exceeds the previous
# step's by this factor (or turns negative), and at the last step.
TANGENT_SOFTENING = 1.1
# Refinement check: final-step difference above which the mesh is called unconverged.
REFINEMENT_TOLERANCE = 0.05

THRESHOLDS = {
    "compression": COMPRESSION_LIMIT,
    "j_min": J_MIN_LIMIT,
    "jump_factor": JUMP_FACTOR,
    "softening_factor": SOFTENING_FACTOR,
}
KINDS = ("inversion", "volume", "compression", "tangent", "limit-point", "jump", "softening")
NOT_CHECKED = -1


@dataclass
class StepSanity:
    """The sanity measures of one converged load step (see the module doc)."""

    step: int
    load_factor: float
    depth: float  # mm, contact patch mean displacement along the load direction
    force: float  # N, tool on tissue along the load direction
    j_min: float
    stretch_min: float
    inverted: int
    u_max: float  # mm
    where: list[float]  # mm, reference midpoint of the most compressed cell
    newton_iterations: int = 0
    step_cuts: int = 0
    tangent_negative: int = NOT_CHECKED

    @property
    def compression(self) -> float:
        """Largest compression, 1 - smallest principal stretch."""
        return 1.0 - self.stretch_min

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {**asdict(self), "compression": self.compression}


@dataclass
class Flag:
    """One finding: ``kind`` (one of :data:`KINDS`) at ``step``, with its value and message.

    ``value`` by kind: inversion, the inverted cells; volume, J_min; compression,
    1 - stretch_min; tangent, the negative or zero eigenvalues; jump, c_i / c_{i-1};
    softening and limit-point, c_i / c_1 (negative past a limit point).
    """

    kind: str
    step: int
    load_factor: float
    value: float
    message: str


@dataclass
class SanityReport:
    """The per-step measures of one solve, what they flag, and a suggestion."""

    law: str
    mode: str
    steps: list[StepSanity]
    flags: list[Flag] = field(default_factory=list)
    suggestion: str = ""

    @property
    def flagged(self) -> bool:
        """Whether anything was flagged."""
        return bool(self.flags)

    def worst(self) -> dict[str, Any]:
        """The worst value of each measure over the load path."""
        return worst_values(self.steps)

    def warnings(self, label: str) -> list[str]:
        """One line per flag, then the suggestion, each starting with ``label``."""
        return warning_lines(self.summary(), label)

    def summary(self) -> dict[str, Any]:
        """Flags, worst values and suggestion (no per-step list): a campaign record's attribute."""
        return {
            "version": VERSION,
            "law": self.law,
            "mode": self.mode,
            "thresholds": THRESHOLDS,
            "flags": [asdict(f) for f in self.flags],
            "worst": self.worst(),
            "suggestion": self.suggestion,
        }

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {**self.summary(), "steps": [s.to_dict() for s in self.steps]}


def warning_lines(summary: dict, label: str) -> list[str]:
    """The flags of a :meth:`SanityReport.summary`, then its suggestion, after ``label``."""
    lines = [f"{label}: {f['message']}" for f in summary.get("flags", [])]
    if lines and summary.get("suggestion"):
        lines.append(f"{label}: {summary['suggestion']}")
    return lines


def judge(steps: list[StepSanity], law: str, mode: str, failure: str | None = None) -> SanityReport:
    """Flag what is unphysical in ``steps`` (see the module doc) and suggest a remedy.

    ``failure``: why the solve stopped early (None if it reached load factor 1):
    a path that softened before Newton failed ran into a limit point.
    """
    flags = _state_flags(steps) + _path_flags(steps)
    if failure is not None:
        flags = [f for f in flags if f.kind != "softening"] + _failure_flags(steps, failure)
    flags.sort(key=lambda f: KINDS.index(f.kind))
    return SanityReport(law, mode, steps, flags, suggest({f.kind for f in flags}, law))


def _at(s: StepSanity) -> str:
    return f"step {s.step} (load factor {s.load_factor:.3g})"


def _state_flags(steps: list[StepSanity]) -> list[Flag]:
    """Inversion, volume, compression and tangent flags, each at its worst step."""
    if not steps:
        return []
    flags = []
    inverted = [s for s in steps if s.inverted > 0]
    if inverted:
        s = inverted[0]
        message = (
            f"{s.inverted} inverted element(s) (J <= 0) from {_at(s)} on "
            f"(J_min {s.j_min:.3g}, near {_point(s.where)} mm)"
        )
        flags.append(Flag("inversion", s.step, s.load_factor, float(s.inverted), message))
    s = min(steps, key=lambda s: s.j_min)
    if 0 < s.j_min < J_MIN_LIMIT:
        message = (
            f"volume ratio J_min {s.j_min:.3g} at {_at(s)}: {1 - s.j_min:.0%} of a volume lost"
        )
        flags.append(Flag("volume", s.step, s.load_factor, s.j_min, message))
    s = max(steps, key=lambda s: s.compression)
    if s.compression > COMPRESSION_LIMIT:
        stretch = "an inverted element" if s.inverted else f"principal stretch {s.stretch_min:.3g}"
        message = (
            f"compression {s.compression:.0%} at {_at(s)} ({stretch}, "
            f"J_min {min(t.j_min for t in steps):.3g}, near {_point(s.where)} mm)"
        )
        flags.append(Flag("compression", s.step, s.load_factor, s.compression, message))
    unstable = [s for s in steps if s.tangent_negative > 0]
    if unstable:
        s = unstable[0]
        message = (
            f"the tangent has {s.tangent_negative} negative or zero eigenvalue(s) at {_at(s)}: "
            "an unstable equilibrium (buckling or a material instability)"
        )
        flags.append(Flag("tangent", s.step, s.load_factor, float(s.tangent_negative), message))
    return flags


def _point(x) -> str:
    return "(" + ", ".join(f"{c:.3g}" for c in x) + ")"


def secant_compliance(steps: list[StepSanity]) -> np.ndarray:
    """Secant compliance (mm/N) of each step from the previous converged state (from 0, 0).

    NaN where undefined (no force increment); negative: the stiffness changed sign.
    """
    depth = np.array([0.0] + [s.depth for s in steps])
    force = np.array([0.0] + [s.force for s in steps])
    dd, df = np.diff(depth), np.diff(force)
    dd[np.abs(dd) <= PATH_ROUNDOFF * max(np.abs(depth).max(), 1e-300)] = 0.0
    df[np.abs(df) <= PATH_ROUNDOFF * max(np.abs(force).max(), 1e-300)] = 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(df != 0, dd / np.where(df != 0, df, 1.0), np.nan)
    c[(df == 0) & (dd != 0)] = -np.inf  # the depth moved at a constant force: no stiffness
    return c


def _path_flags(steps: list[StepSanity]) -> list[Flag]:
    """Limit point, jump and softening flags from the secant compliances."""
    c = secant_compliance(steps)
    flags = []
    negative = np.flatnonzero(c < 0)
    if negative.size:
        s, before = steps[negative[0]], steps[negative[0] - 1] if negative[0] else None
        message = (
            f"limit point at {_at(s)}: the force went from "
            f"{before.force if before else 0.0:.4g} to {s.force:.4g} N while the depth went "
            f"from {before.depth if before else 0.0:.4g} to {s.depth:.4g} mm "
            "(the secant stiffness is negative)"
        )
        value = c[negative[0]] / c[0] if c[0] > 0 else c[negative[0]]
        flags.append(Flag("limit-point", s.step, s.load_factor, float(value), message))
        return flags  # the jumps and softening before it are the approach to that limit
    with np.errstate(divide="ignore", invalid="ignore"):
        jump = np.where((c[1:] > 0) & (c[:-1] > 0), c[1:] / c[:-1], np.nan)
        soft = np.where((c > 0) & (c[0] > 0), c / c[0], np.nan) if c.size else c
    if jump.size and np.nanmax(jump, initial=0.0) > JUMP_FACTOR:
        i = int(np.nanargmax(jump)) + 1
        s, before = steps[i], steps[i - 1]
        message = (
            f"load-path jump (snap-through) at {_at(s)}: the depth went from {before.depth:.4g} "
            f"to {s.depth:.4g} mm between {before.force:.4g} and {s.force:.4g} N, "
            f"{jump[i - 1]:.1f}x the previous step's rate ({s.step_cuts} step cut(s), "
            f"{s.newton_iterations} Newton iterations)"
        )
        flags.append(Flag("jump", s.step, s.load_factor, float(jump[i - 1]), message))
    elif soft.size and np.nanmax(soft, initial=0.0) > SOFTENING_FACTOR:
        i = int(np.nanargmax(soft))
        s = steps[i]
        message = (
            f"softening at {_at(s)}: the secant stiffness fell to {1 / soft[i]:.0%} of the "
            f"first step's ({s.depth:.3g} mm at {s.force:.3g} N): close to a limit point"
        )
        flags.append(Flag("softening", s.step, s.load_factor, float(soft[i]), message))
    return flags


def _failure_flags(steps: list[StepSanity], failure: str) -> list[Flag]:
    """A limit point when the path softened (or needed step cuts) before Newton failed."""
    c = secant_compliance(steps)
    if not steps or not (c[-1] > 0 and c[0] > 0) or np.any(c < 0):
        return []
    soft = float(c[-1] / c[0])
    if soft <= SOFTENING_FACTOR and not steps[-1].step_cuts:
        return []
    s = steps[-1]
    message = (
        f"limit point: the path stopped at {_at(s)} ({s.depth:.4g} mm at {s.force:.4g} N) with "
        f"the secant stiffness at {1 / soft:.0%} of the first step's; force control cannot "
        f"pass a maximum of the load ({failure})"
    )
    return [Flag("limit-point", s.step, s.load_factor, soft, message)]


def suggest(kinds: set[str], law: str) -> str:
    """What to try when ``kinds`` were flagged for material ``law`` ('' when nothing was)."""
    if not kinds:
        return ""
    if law == "svk":
        return (
            'SVK is unstable in compression (thesis ch. 5); try law = "neo-hookean", '
            "a smaller load or a finer mesh"
        )
    if kinds & {"inversion", "volume", "compression"}:
        return "try a smaller load or a finer mesh (hapticrom solve --refinement-check)"
    return (
        "try a smaller load, or displacement control (it follows a path through a limit "
        "point that force control jumps over)"
    )


def worst_values(steps: list[StepSanity]) -> dict[str, Any]:
    """The extreme of each measure over ``steps`` with the step it occurs at (JSON-ready)."""

    def at(s: StepSanity, value, **extra) -> dict[str, Any]:
        return {"value": value, "step": s.step, "load_factor": s.load_factor, **extra}

    if not steps:
        return {}
    j = min(steps, key=lambda s: s.j_min)
    k = max(steps, key=lambda s: s.compression)
    n = max(steps, key=lambda s: s.inverted)
    u = max(steps, key=lambda s: s.u_max)
    t = max(steps, key=lambda s: s.tangent_negative)
    worst = {
        "j_min": at(j, j.j_min),
        "compression": at(k, k.compression, stretch_min=k.stretch_min, where=list(k.where)),
        "inverted": at(n, n.inverted),
        "u_max": at(u, u.u_max, depth=u.depth),
        "tangent_negative": at(t, t.tangent_negative),
    }
    c = secant_compliance(steps)
    with np.errstate(divide="ignore", invalid="ignore"):
        jump = np.where((c[1:] > 0) & (c[:-1] > 0), c[1:] / c[:-1], np.nan)
    if jump.size and np.isfinite(jump).any():
        i = int(np.nanargmax(jump)) + 1
        worst["jump_ratio"] = at(steps[i], float(jump[i - 1]))
    return worst


# -- measuring (DOLFINx; imported lazily so the judging above needs numpy only) -----------
class SanityMonitor:
    """Measures :class:`StepSanity` of a :class:`~hapticrom.offline.fe.fullorder.FullOrderModel`.

    ``tangent``: "softening" (check the tangent where the path softens and at the last
    step), "every" (every step) or "never".
    """

    def __init__(self, fom, tangent: str = "softening"):
        import basix  # noqa: F401 - with dolfinx
        import dolfinx
        from dolfinx import fem

        model = fom.model
        mesh = model.organ.mesh
        self.fom, self.comm, self.steps = fom, mesh.comm, []
        points, _ = basix.make_quadrature(mesh.basix_cell(), model.quadrature_degree)
        self._F = fem.Expression(model.deformation_gradient(), points, comm=mesh.comm)
        tdim = mesh.topology.dim
        self._cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
        self._midpoints = dolfinx.mesh.compute_midpoints(mesh, tdim, self._cells)
        vector = np.asarray(fom.load_vector, dtype=float)
        norm = float(np.linalg.norm(vector))
        self.direction = vector / norm if norm > 0 else np.zeros(3)
        iterative = fom.config.solver.linear_solver == "iterative"
        self.tangent = "never" if iterative else tangent
        self._inertia = None

    def measure(self, record, force, disp) -> StepSanity:
        """The measures at the current (converged) state; appended to ``self.steps``."""
        j_min, stretch_min, inverted, where = self._kinematics()
        step = StepSanity(
            step=record.step,
            load_factor=float(record.load_factor),
            depth=float(np.dot(disp, self.direction)),
            force=float(np.dot(force, self.direction)),
            j_min=j_min,
            stretch_min=stretch_min,
            inverted=inverted,
            u_max=self._u_max(),
            where=where,
            newton_iterations=int(record.newton_iterations),
            step_cuts=int(record.step_cuts),
        )
        self.steps.append(step)
        if self._check_tangent_now(record):
            step.tangent_negative = self.tangent_negative()
        return step

    def _check_tangent_now(self, record) -> bool:
        """Every step, or where the path softens or turns back, and at the last step."""
        if self.tangent == "never":
            return False
        if self.tangent == "every" or record.load_factor >= 1 - 1e-12:
            return True
        c = secant_compliance(self.steps)
        return bool(c[-1] < 0 or (c.size >= 2 and c[-1] > TANGENT_SOFTENING * c[-2] > 0))

    def _kinematics(self) -> tuple[float, float, int, list[float]]:
        """(J_min, smallest principal stretch, inverted cells, where), reduced over ranks."""
        from mpi4py import MPI

        mesh = self.fom.model.organ.mesh
        local, where = (math.inf, math.inf, 0), [math.nan] * 3
        if self._cells.size:
            F = self._F.eval(mesh, self._cells).reshape(self._cells.size, -1, 3, 3)
            J = np.linalg.det(F)
            C = np.einsum("cqki,cqkj->cqij", F, F)
            stretch = np.sqrt(np.maximum(np.linalg.eigvalsh(C)[..., 0], 0.0))
            stretch = np.where(J > 0, stretch, 0.0).min(axis=1)  # inverted: fully compressed
            J = J.min(axis=1)
            worst = int(np.argmin(stretch))
            local = (float(J.min()), float(stretch[worst]), int(np.count_nonzero(J <= 0)))
            where = [float(c) for c in self._midpoints[worst]]
        j_min = self.comm.allreduce(local[0], op=MPI.MIN)
        inverted = self.comm.allreduce(local[2], op=MPI.SUM)
        candidates = self.comm.allgather((local[1], where))
        stretch_min, where = min(candidates, key=lambda c: c[0])
        return j_min, stretch_min, inverted, where

    def _u_max(self) -> float:
        from mpi4py import MPI

        V = self.fom.model.V
        owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        u = self.fom.model.u.x.array[:owned].reshape(-1, 3)
        local = float(np.linalg.norm(u, axis=1).max()) if u.size else 0.0
        return self.comm.allreduce(local, op=MPI.MAX)

    def tangent_negative(self) -> int:
        """Negative or zero eigenvalues of the pressure-condensed tangent at the current state."""
        from petsc4py import PETSc

        if self._inertia is None:
            self._inertia = _TangentInertia(self.fom)
        try:
            return self._inertia()
        except PETSc.Error:  # MUMPS out of memory or without inertia: not checked
            return NOT_CHECKED

    def report(self, failure: str | None = None) -> SanityReport:
        """The judged report of the steps recorded so far (``failure``: why the solve stopped)."""
        return judge(self.steps, self.fom.law.name, self.fom.config.load.mode, failure)


class _TangentInertia:
    """Inertia of the tangent by an LDL^T factorisation (MUMPS), on a copy of the matrix.

    With a mixed element the tangent is [[K_uu, K_up], [K_pu, K_pp]] with K_pp negative
    definite, so its inertia is the pressure count of negative eigenvalues plus the
    inertia of the condensed tangent K_uu - K_up K_pp^-1 K_pu (Haynsworth).
    """

    def __init__(self, fom):
        problem = fom.newton.problem
        self.forms, self.bcs = problem.J, fom.bcs
        self.A = problem.A.duplicate()
        self.pressure = fom.model.num_dofs()["pressure"]

    def __call__(self) -> int:
        from dolfinx.fem.petsc import assemble_matrix
        from petsc4py import PETSc

        A = self.A
        A.zeroEntries()
        assemble_matrix(A, self.forms, self.bcs, diag=1.0)
        A.assemble()
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        ksp = PETSc.KSP().create(A.comm)
        try:
            ksp.setOperators(A)
            ksp.setType("preonly")
            pc = ksp.getPC()
            pc.setType("cholesky")
            pc.setFactorSolverType("mumps")
            pc.setFactorSetUpSolverType()
            factors = pc.getFactorMatrix()
            factors.setMumpsIcntl(13, 1)  # inertia also correct in parallel
            factors.setMumpsIcntl(14, 100)
            factors.setMumpsIcntl(24, 1)  # null pivots counted
            pc.setUp()
            negative, zero, _ = factors.getInertia()
        finally:
            ksp.destroy()
        return int(negative) + int(zero) - self.pressure


# -- campaigns ---------------------------------------------------------------------------
WORST_PICK = {
    "j_min": min,
    "compression": max,
    "inverted": max,
    "u_max": max,
    "tangent_negative": max,
    "jump_ratio": max,
}


def campaign_summary(records: list[tuple[int, list[float], dict | None]], positions: int) -> dict:
    """The campaign's sanity: worst values over its positions and the flagged ones (JSON-ready).

    ``records``: (position index, point (mm), the position's :meth:`SanityReport.summary`
    or None when it has none), ``positions``: how many the campaign has.
    """
    checked = [(i, list(p), s) for i, p, s in records if s]
    worst = {}
    for key, pick in WORST_PICK.items():
        values = [(s["worst"][key], i) for i, _, s in checked if key in s.get("worst", {})]
        if values:
            entry, index = pick(values, key=lambda v: v[0]["value"])
            worst[key] = {**entry, "position": index}
    flagged = [
        {
            "position": i,
            "point": p,
            "kinds": [f["kind"] for f in s["flags"]],
            "messages": [f["message"] for f in s["flags"]],
            "suggestion": s.get("suggestion", ""),
        }
        for i, p, s in checked
        if s["flags"]
    ]
    suggestions = dict.fromkeys(f["suggestion"] for f in flagged if f["suggestion"])
    return {
        "version": VERSION,
        "thresholds": THRESHOLDS,
        "positions": positions,
        "checked": len(checked),
        "flagged": flagged,
        "worst": worst,
        "suggestion": "; ".join(suggestions),
    }


def summary_lines(summary: dict) -> list[str]:
    """A campaign summary as log lines: counts, worst values, suggestion."""
    worst, flagged = summary["worst"], summary["flagged"]
    parts = []
    if "compression" in worst:
        w = worst["compression"]
        parts.append(f"compression {w['value']:.0%} (position {w['position']}, step {w['step']})")
    if "j_min" in worst:
        parts.append(f"J_min {worst['j_min']['value']:.3g} (position {worst['j_min']['position']})")
    if "jump_ratio" in worst:
        w = worst["jump_ratio"]
        parts.append(
            f"largest step-to-step rate change {w['value']:.1f}x (position {w['position']})"
        )
    if worst.get("inverted", {}).get("value", 0) > 0:
        parts.append(f"{worst['inverted']['value']} inverted element(s)")
    head = f"physics sanity: {len(flagged)} of {summary['checked']} position(s) flagged"
    if flagged:
        counts: dict[str, int] = {}
        for f in flagged:
            for kind in f["kinds"]:
                counts[kind] = counts.get(kind, 0) + 1
        head += " (" + ", ".join(f"{k}: {n}" for k, n in counts.items()) + ")"
    lines = [head + ("; worst: " + ", ".join(parts) if parts else "")]
    if summary["suggestion"]:
        lines.append(f"physics sanity: {summary['suggestion']}")
    return lines


# -- the refinement check ------------------------------------------------------------------
class RefinementUnavailable(Exception):
    """The mesh is not a built-in refinement level with a finer one."""


def _builtin_presets() -> dict[str, tuple[dict, dict]]:
    from hapticrom.meshes import beam, liver, spherical_cap

    return {
        "cornea": (spherical_cap.CORNEA_DEFAULTS, spherical_cap.CORNEA_PRESETS),
        "hemisphere": (spherical_cap.HEMISPHERE_DEFAULTS, spherical_cap.HEMISPHERE_PRESETS),
        "beam": (beam.BEAM_DEFAULTS, beam.BEAM_PRESETS),
        "liver": (liver.LIVER_DEFAULTS, liver.LIVER_PRESETS),
    }


def next_finer_level(mesh_file: str | Path) -> tuple[str, str, str]:
    """(mesh name, its refinement level, the next finer level) of a built-in mesh file.

    The level is recognised from the sidecar's parameters (a preset, no overrides);
    RefinementUnavailable says why there is none (a user mesh, overridden
    parameters, an incision, already the finest level).
    """
    from hapticrom.meshes.msh import REFINEMENTS, read_sidecar

    info = read_sidecar(Path(mesh_file))
    name, params = info.get("name"), info.get("params", {})
    presets = _builtin_presets()
    if name not in presets:
        raise RefinementUnavailable(f"{Path(mesh_file).name} is not a built-in mesh")
    defaults, levels = presets[name]
    for level in REFINEMENTS:
        if params == {**defaults, **levels[level]}:
            break
    else:
        raise RefinementUnavailable(
            f"{Path(mesh_file).name} is a {name} mesh with parameters other than a built-in "
            f"refinement level ({', '.join(REFINEMENTS)}): no finer level to compare with"
        )
    if level == REFINEMENTS[-1]:
        raise RefinementUnavailable(f"{Path(mesh_file).name} is already the finest {name} mesh")
    return name, level, REFINEMENTS[REFINEMENTS.index(level) + 1]


def _generate(name: str, level: str, out: Path) -> None:
    from hapticrom.meshes import generate

    out.parent.mkdir(parents=True, exist_ok=True)
    generate(name, out, refinement=level)


def run_refinement_check(config, result, out_dir: str | Path, comm, log=print) -> dict:
    """Solve ``config`` again on the next finer built-in mesh; compare the last common step.

    ``result``: the :class:`~hapticrom.offline.fe.fullorder.SolveResult` on the configured
    mesh. The finer mesh and its solve (curve.csv, sanity.json) go to
    ``out_dir/refinement``. Returns a JSON-ready dict (``available`` False with a
    ``reason`` when there is no finer level).
    """
    from dataclasses import replace

    from hapticrom.offline.fe.fullorder import FullOrderModel
    from hapticrom.offline.mpi import on_rank_zero
    from hapticrom.shared.errors import SolverError

    try:
        name, level, finer = on_rank_zero(comm, next_finer_level, config.mesh.file)
    except RefinementUnavailable as exc:
        return {"available": False, "reason": str(exc)}
    where = Path(out_dir) / "refinement"
    mesh = where / f"{name}-{finer}.msh"
    on_rank_zero(comm, _generate, name, finer, mesh)
    log(f"refinement check: solving again on the {finer} {name} mesh ({mesh})")
    fine_config = replace(
        config, mesh=replace(config.mesh, file=mesh), output=replace(config.output, xdmf=False)
    )
    fom = FullOrderModel(fine_config, comm, verbose=False)
    status = "solved"
    try:
        fine = fom.solve(where)
    except SolverError as exc:
        status, fine = f"failed: {exc}", fom.partial_result()
    check = compare_solves(result, fine, REFINEMENT_TOLERANCE)
    check.update(
        available=True,
        mesh=name,
        level=level,
        finer=finer,
        finer_mesh=str(mesh),
        finer_status=status,
        finer_flags=[f.kind for f in fom.sanity.flags],
    )
    check["message"] = _refinement_message(check)
    return check


def check_refinement(
    config, result, out_dir: str | Path, comm, record: str = "sanity.json"
) -> dict:
    """:func:`run_refinement_check`, printed (rank 0) and recorded in ``out_dir/record``.

    ``sanity.json`` (a solve) gets a ``refinement`` key; any other ``record`` (a
    campaign's ``refinement.json``) is the check alone. ``result`` needs only
    ``load_factor``, ``force`` and ``displacement`` (a campaign's stored position).
    """
    from hapticrom.offline.mpi import print0

    check = run_refinement_check(config, result, out_dir, comm, log=lambda s: print0(comm, s))
    line = check.get("message") or f"refinement check: not available: {check['reason']}"
    prefix = "" if check.get("converged", True) else "warning: "
    print0(comm, prefix + line)
    if comm.rank == 0:
        path = Path(out_dir) / record
        if record == "sanity.json":
            data = json.loads(path.read_text()) if path.is_file() else {}
            write_json(path, {**data, "refinement": check})
        else:
            write_json(path, check)
    return check


def compare_solves(coarse, fine, tolerance: float) -> dict:
    """Force and displacement of two solves at the last load factor both reached."""
    common = [lam for lam in coarse.load_factor if np.any(np.abs(fine.load_factor - lam) < 1e-9)]
    if not common:
        return {"load_factor": None, "converged": False, "tolerance": tolerance}
    lam = float(common[-1])
    i = int(np.flatnonzero(np.abs(coarse.load_factor - lam) < 1e-9)[0])
    j = int(np.flatnonzero(np.abs(fine.load_factor - lam) < 1e-9)[0])
    out = {"load_factor": lam, "tolerance": tolerance}
    for key, a, b in (
        ("force", coarse.force[i], fine.force[j]),
        ("displacement", coarse.displacement[i], fine.displacement[j]),
    ):
        difference = float(np.linalg.norm(a - b))
        scale = float(np.linalg.norm(b))
        out[key] = {
            "coarse": [float(v) for v in a],
            "fine": [float(v) for v in b],
            "difference": difference,
            "relative": difference / scale if scale > 0 else 0.0,
        }
    out["converged"] = max(out["force"]["relative"], out["displacement"]["relative"]) <= tolerance
    return out


def _refinement_message(check: dict) -> str:
    head = f"refinement check ({check['level']} -> {check['finer']} {check['mesh']} mesh)"
    if check["load_factor"] is None:
        return f"{head}: the finer solve reached no common load step ({check['finer_status']})"
    parts = []
    for key, unit in (("displacement", "mm"), ("force", "N")):
        v = check[key]
        a, b = np.linalg.norm(v["coarse"]), np.linalg.norm(v["fine"])
        parts.append(f"|{key}| {a:.4g} vs {b:.4g} {unit} ({v['relative']:.1%} apart)")
    verdict = (
        "mesh-converged to the tolerance"
        if check["converged"]
        else f"NOT mesh-converged (tolerance {check['tolerance']:.0%}): use a finer mesh"
    )
    text = f"{head} at load factor {check['load_factor']:.3g}: {', '.join(parts)}: {verdict}"
    if check["finer_status"] != "solved":
        text += f"; the finer solve {check['finer_status']}"
    if check["finer_flags"]:
        text += f"; the finer mesh flags: {', '.join(check['finer_flags'])}"
    return text


def write_json(path: Path, data: dict) -> None:
    """Write ``data`` as JSON (finite numbers only: NaN and infinity become null)."""
    path.write_text(json.dumps(_finite(data), indent=1) + "\n")


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        return _finite(value.item())
    return value


def dumps(data: dict) -> str:
    """Compact JSON of ``data`` with non-finite numbers as null (for HDF5 attributes)."""
    return json.dumps(_finite(data), separators=(",", ":"))
