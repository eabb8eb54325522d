"""PETSc SNES plumbing and incremental loading with automatic step cutting.

Options follow PETSc's conventions: every solver has an options prefix
(default ``hapticrom_``), so anything can be tuned from the command line
without code changes, e.g. ``-hapticrom_snes_rtol 1e-10`` or
``-hapticrom_snes_monitor``. Precedence: command line > ``[solver.petsc_options]``
of the configuration > the defaults below.

The converged reason is always checked: a diverged Newton solve is retried
with half the load increment, down to a floor, and never passes as an answer.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import NonlinearProblem, assemble_jacobian
from petsc4py import PETSc

from hapticrom.shared.errors import SolverError

# Full Newton with an LU factorisation by MUMPS: quadratic convergence and
# robustness for the indefinite mixed (saddle-point) systems.
DIRECT_OPTIONS = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "basic",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-10,
    "snes_stol": 1e-10,  # the residual of a locked or very stiff model floors at roundoff
    "snes_max_it": 25,
    # The first residual of a displacement-driven, nearly incompressible solve
    # jumps by orders of magnitude; PETSc's default divergence tolerance (1e4,
    # also what "-1" means) would call that divergence.
    "snes_divergence_tolerance": "unlimited",
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
    # MUMPS: let it enlarge its workspace instead of failing on large meshes.
    "mat_mumps_icntl_14": 100,
}

# For meshes too large for a direct factorisation: GMRES preconditioned by
# block Jacobi with incomplete LU on each rank (works for the indefinite mixed
# systems where algebraic multigrid does not), restarted often enough.
ITERATIVE_OPTIONS = {
    **{k: v for k, v in DIRECT_OPTIONS.items() if not k.startswith(("ksp_", "pc_", "mat_"))},
    "snes_rtol": 1e-9,
    "ksp_type": "gmres",
    "ksp_gmres_restart": 200,
    "ksp_rtol": 1e-10,
    "ksp_max_it": 5000,
    "pc_type": "bjacobi",
    "sub_pc_type": "ilu",
    "sub_pc_factor_levels": 2,
}

DEFAULT_OPTIONS = {"direct": DIRECT_OPTIONS, "iterative": ITERATIVE_OPTIONS}


def _option_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def configure(prefix: str, options: dict, snes: PETSc.SNES) -> None:
    """Apply ``options`` under ``prefix`` unless the command line already set them.

    The options this call inserts are removed again after ``setFromOptions``,
    so two solvers with the same prefix in one process do not leak settings.
    """
    db = PETSc.Options()
    inserted = []
    for key, value in options.items():
        name = f"{prefix}{key}"
        if not db.hasName(name):
            db.setValue(name, _option_value(value))
            inserted.append(name)
    try:
        snes.setFromOptions()
        snes.getKSP().setFromOptions()
    finally:
        for name in inserted:
            db.delValue(name)


@dataclass
class NewtonReport:
    """The outcome of one Newton solve: converged or not, why, iterations, residual, time."""

    converged: bool
    reason: int
    reason_name: str
    iterations: int
    residual_norm: float
    seconds: float


_REASONS = {
    getattr(PETSc.SNES.ConvergedReason, name): name
    for name in dir(PETSc.SNES.ConvergedReason)
    if not name.startswith("_")
}


class NewtonSolver:
    """One nonlinear solve F(w) = 0 by SNES for the blocks ``unknowns``."""

    def __init__(
        self,
        residuals: Sequence,
        unknowns: Sequence[fem.Function],
        bcs: Sequence[fem.DirichletBC],
        prefix: str = "hapticrom_",
        linear_solver: str = "direct",
        options: dict | None = None,
        jacobians=None,
    ):
        blocked = len(unknowns) > 1
        self.unknowns = list(unknowns)
        self.problem = NonlinearProblem(
            list(residuals) if blocked else residuals[0],
            self.unknowns if blocked else self.unknowns[0],
            bcs=list(bcs),
            J=jacobians if blocked else (jacobians[0][0] if jacobians else None),
            petsc_options_prefix=prefix,
            kind="mpi" if blocked else None,
        )
        configure(prefix, {**DEFAULT_OPTIONS[linear_solver], **(options or {})}, self.snes)
        self._set_fieldsplit_blocks()
        self._freeze_tangent = self._have_tangent = False
        self._bcs = list(bcs)
        problem = self.problem
        self.snes.setJacobian(self._assemble_tangent, problem.A, problem.P_mat)

    def _assemble_tangent(self, snes, x, J, P) -> None:
        """SNES Jacobian callback; a frozen tangent is left untouched, so PETSc
        keeps its factorisation (the matrix state does not change)."""
        if self._freeze_tangent and self._have_tangent:
            return
        problem = self.problem
        assemble_jacobian(snes, x, J, P, problem.u, problem.J, problem.preconditioner, self._bcs)
        self._have_tangent = True

    def _set_fieldsplit_blocks(self) -> None:
        """Name the displacement ("u") and pressure ("p") rows of the blocked system.

        Lets users choose a field-split solver from the command line, e.g. the
        exact elimination of an element-wise pressure (its block is diagonal,
        so ``selfp`` is the exact Schur complement)::

            -hapticrom_pc_type fieldsplit -hapticrom_pc_fieldsplit_type schur
            -hapticrom_pc_fieldsplit_schur_fact_type full
            -hapticrom_pc_fieldsplit_schur_precondition selfp
            -hapticrom_fieldsplit_p_pc_type jacobi
            -hapticrom_fieldsplit_u_pc_type cholesky
            -hapticrom_fieldsplit_u_pc_factor_mat_solver_type mumps

        (the same answers as the default LU; on the cornea not faster, since
        MUMPS already eliminates the pressure cheaply).
        """
        pc = self.snes.getKSP().getPC()
        if len(self.unknowns) < 2 or pc.getType() != PETSc.PC.Type.FIELDSPLIT:
            return
        x = self.problem.x
        start = x.getOwnershipRange()[0]
        sets, offset = [], start
        for w in self.unknowns:
            V = w.function_space
            n = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
            sets.append(PETSc.IS().createStride(n, first=offset, step=1, comm=x.comm))
            offset += n
        names = ["u", "p"]
        # Pressure first: fieldsplit's Schur complement eliminates the first split.
        pc.setFieldSplitIS(*[(names[i], sets[i]) for i in reversed(range(len(sets)))])

    @property
    def snes(self) -> PETSc.SNES:
        """The PETSc nonlinear solver."""
        return self.problem.solver

    def destroy(self) -> None:
        """Free the solver's PETSc objects now (its factorisation included).

        The SNES holds this object's tangent callback, a reference cycle through
        PETSc that Python's collector does not free: without this a campaign that
        solves one position after another in one process keeps every factorisation
        (0.5-0.8 GB per liver solve; a 28-solve greedy run was killed at 11.8 GB).
        """
        self.problem.__del__()  # DOLFINx's own release of the SNES, matrices, vectors

    def solve(self, modified: bool = False) -> NewtonReport:
        """Solve from the current state of the unknowns.

        ``modified=True``: modified Newton, one tangent (factorised once) at the
        initial state, reused in every iteration: cheaper per step when the
        factorisation dominates, linear instead of quadratic convergence.
        """
        t0 = time.perf_counter()
        self._freeze_tangent, self._have_tangent = modified, False
        self.problem.solve()
        reason = self.snes.getConvergedReason()
        finite = all(np.all(np.isfinite(w.x.array)) for w in self.unknowns)
        return NewtonReport(
            converged=reason > 0 and finite,
            reason=reason,
            reason_name=_REASONS.get(reason, str(reason)) if finite else "NAN_IN_SOLUTION",
            iterations=self.snes.getIterationNumber(),
            residual_norm=float(self.snes.getFunctionNorm()),
            seconds=time.perf_counter() - t0,
        )


@dataclass
class StepRecord:
    """One converged load increment."""

    step: int
    load_factor: float
    newton_iterations: int
    step_cuts: int  # failed attempts (halvings) before this increment converged
    seconds: float


class IncrementalLoading:
    """Drive the load factor from 0 to 1 in ``steps`` increments, halving on failure.

    ``set_load(lam)`` applies the load at factor ``lam``; ``on_step(record)`` is
    called after every converged increment (write output there). A failed
    increment restores the last converged state and retries with half the
    increment; after two converged sub-steps the increment grows back (up to
    the nominal one). An increment below nominal / 2**max_step_cuts raises SolverError.
    """

    def __init__(
        self,
        newton: NewtonSolver,
        set_load: Callable[[float], None],
        steps: int,
        max_step_cuts: int = 8,
        predictor: str = "secant",
        log: Callable[[str], None] = lambda s: None,
        modified_newton: bool = False,
    ):
        self.newton, self.set_load = newton, set_load
        self.steps, self.max_step_cuts, self.predictor = steps, max_step_cuts, predictor
        self.log = log
        self.modified_newton = modified_newton

    def _state(self) -> list[np.ndarray]:
        return [w.x.array.copy() for w in self.newton.unknowns]

    def _restore(self, state: list[np.ndarray]) -> None:
        for w, a in zip(self.newton.unknowns, state, strict=True):
            w.x.array[:] = a

    def _target(self, lam: float, dlam: float) -> float:
        """The next load factor, landing exactly on the nominal grid k/steps when close."""
        target = lam + dlam
        grid = round(target * self.steps) / self.steps
        if abs(target - grid) < 1e-9 * (1.0 / self.steps) and grid > lam:
            return grid
        return target

    def _predict(self, lam: float, target: float, now: list, previous) -> None:
        """Secant predictor: extrapolate the last two converged states to ``target``."""
        if self.predictor == "secant" and previous is not None and lam > previous[0]:
            ratio = (target - lam) / (lam - previous[0])
            for w, a, before in zip(self.newton.unknowns, now, previous[1], strict=True):
                w.x.array[:] = a + ratio * (a - before)

    def _attempt(self, target: float, converged_state: list) -> tuple[NewtonReport, int]:
        """Newton at load factor ``target`` (modified Newton falls back to full Newton);
        the report and the iterations of every attempt."""
        self.set_load(target)
        report = self.newton.solve(modified=self.modified_newton)
        iterations = report.iterations
        if not report.converged and self.modified_newton:
            # A frozen tangent may not reach the solution: full Newton before cutting.
            self.log(
                f"  modified Newton failed at load factor {target:.6g} ({report.reason_name}); "
                "retrying with full Newton"
            )
            self._restore(converged_state)
            self.set_load(target)
            report = self.newton.solve(modified=False)
            iterations += report.iterations
        return report, iterations

    def _diverged(self, target: float, report: NewtonReport, dlam: float, lam: float):
        """The error of an increment that failed at the smallest increment."""
        return SolverError(
            f"Newton diverged at load factor {target:.6g} ({report.reason_name}) even "
            f"with the smallest increment {dlam:.3g} ({self.max_step_cuts} halvings of "
            f"1/{self.steps}); the last converged state is at load factor {lam:.6g}"
            + (" (a limit point? force control cannot pass one)" if lam > 0 else "")
        )

    def run(self, on_step: Callable[[StepRecord], None]) -> list[StepRecord]:
        """Load from factor 0 to 1; ``on_step(record)`` after every converged increment."""
        nominal = 1.0 / self.steps
        # The smallest increment tried: max_step_cuts halvings of the nominal one.
        floor = nominal / 2**self.max_step_cuts
        lam, dlam = 0.0, nominal
        previous: tuple[float, list[np.ndarray]] | None = None  # (lam, state) one step back
        records: list[StepRecord] = []
        cuts, successes_since_cut = 0, 0
        while lam < 1.0 - 1e-12:
            dlam = min(dlam, 1.0 - lam)
            target = self._target(lam, dlam)
            converged_state = self._state()
            self._predict(lam, target, converged_state, previous)
            t0 = time.perf_counter()
            report, iterations = self._attempt(target, converged_state)
            if report.converged:
                previous, lam = (lam, converged_state), target
                record = StepRecord(len(records) + 1, lam, iterations, cuts,
                                    time.perf_counter() - t0)  # fmt: skip
                records.append(record)
                on_step(record)
                cuts = 0
                successes_since_cut += 1
                if dlam < nominal and successes_since_cut >= 2:
                    dlam = min(2 * dlam, nominal)
                    successes_since_cut = 0
                continue
            self._restore(converged_state)
            cuts += 1
            successes_since_cut = 0
            if dlam / 2 < floor * (1 - 1e-9):
                self.set_load(lam)
                raise self._diverged(target, report, dlam, lam)
            dlam /= 2
            self.log(
                f"  step cut: Newton failed at load factor {target:.6g} "
                f"({report.reason_name}, {report.iterations} its); "
                f"retrying with increment {dlam:.4g}"
            )
        return records
