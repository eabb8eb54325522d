"""The full-order model: one organ, one material, one tool load, solved by Newton (mm, N, MPa).

:class:`FullOrderModel` wires together the mesh (:mod:`.organ`), the material
law (:mod:`.materials`), the discretisation (:mod:`.formulation`), the tool
load (:mod:`.contact`) and the SNES solver (:mod:`.solver`);
:meth:`FullOrderModel.solve` runs the incremental loading and returns the
load-displacement curve, writing ``curve.csv`` and XDMF fields if asked.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.contact import ContactPatch, NodalMean, ReactionForce, WeightedMean
from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
from hapticrom.offline.fe.materials import make_law
from hapticrom.offline.fe.organ import OrganMesh, load_organ
from hapticrom.offline.fe.output import CurveWriter, FieldWriter
from hapticrom.offline.fe.sanity import SanityMonitor, SanityReport, write_json
from hapticrom.offline.fe.solver import IncrementalLoading, NewtonSolver, StepRecord
from hapticrom.offline.fe.sphere import SphereIndenter
from hapticrom.offline.mpi import print0
from hapticrom.shared.errors import InputError, SolverError


@dataclass
class SolveResult:
    """Load-displacement curve of a solve and its timings."""

    records: list[StepRecord]
    force: np.ndarray  # (steps, 3) N, tool on tissue
    displacement: np.ndarray  # (steps, 3) mm, contact patch mean
    load_factor: np.ndarray  # (steps,)
    num_dofs: dict[str, int]
    setup_seconds: float  # mesh, spaces, patch (no compilation)
    jit_seconds: float  # form compilation (FFCx/CFFI, or the JIT cache)
    solve_seconds: float
    sanity: SanityReport | None = None  # physics sanity of the load path (offline/fe/sanity.py)

    @property
    def newton_iterations(self) -> int:
        """Newton iterations over all converged increments."""
        return sum(r.newton_iterations for r in self.records)


class FullOrderModel:
    """A configured full-order problem, ready to :meth:`solve`."""

    def __init__(
        self,
        config: ProblemConfig,
        comm: MPI.Comm = MPI.COMM_WORLD,
        organ: OrganMesh | None = None,
        verbose: bool = True,
    ):
        t0 = time.perf_counter()
        self.config, self.comm, self.verbose = config, comm, verbose
        # Validate what needs no mesh first, so a bad file fails fast and cheap.
        self.law = make_law(config.material.law, **config.material.params)
        self.organ = organ if organ is not None else load_organ(config.mesh.file, comm)
        self.element = choose_element(self.organ.cell_type, config.discretisation.element)
        self.model = HyperelasticModel(
            self.organ, self.law, self.element, config.discretisation.quadrature_degree
        )
        self._setup_load()
        self.setup_seconds = time.perf_counter() - t0

        t0 = time.perf_counter()
        residuals = self.model.residual_forms()
        jacobians = self.model.jacobian_forms(residuals)
        self.newton = NewtonSolver(
            residuals,
            self.model.unknowns,
            self.bcs,
            prefix=config.solver.options_prefix,
            linear_solver=config.solver.linear_solver,
            options=config.solver.petsc_options,
            jacobians=jacobians,
        )
        self.reaction = None
        if config.load.mode == "sphere":
            self.patch_displacement = self.sphere_advance
        elif config.load.mode == "displacement":
            residual_u = self.newton.problem.F
            residual_u = residual_u[0] if len(residuals) > 1 else residual_u
            self.reaction = ReactionForce(residual_u, self.model.V, self.patch_blocks)
            self.patch_displacement = NodalMean(self.model.u, self.patch_blocks)
        else:
            self.patch_displacement = WeightedMean(
                self.model.u, self.patch.weight(), self.model.ds(self.model.LOAD_TAG)
            )
        self.monitor = SanityMonitor(self)
        self.sanity: SanityReport | None = None
        self.history = ([], [], [])
        self.jit_seconds = time.perf_counter() - t0

    # -- load ------------------------------------------------------------------
    def _setup_load(self) -> None:
        load, organ, model = self.config.load, self.organ, self.model
        self.sphere = None
        self.further = []  # further tools (force, traction, int w dA): _setup_load_region
        if load.tools and load.mode not in ("force", "displacement"):
            raise InputError(f"further tools are force loads beside a force or displacement "
                             f"tool; this load is '{load.mode}'")  # fmt: skip
        if load.mode == "sphere":
            self._setup_sphere()
            return
        if load.mode == "traction":
            self.patch = ContactPatch.whole_group(organ, load.surface)
        else:
            point = load.contact_point
            if point is None:
                point = organ.default_contact_point()
            self.patch = ContactPatch.around_point(organ, point, load.contact_radius, load.surface)
        if load.mode != "displacement" or load.tools:
            # under displacement control the first patch carries no traction (the model's
            # stays zero): the region is the further tools' (a held tool beside pressing ones)
            self._setup_load_region()
        self.bcs = organ.supports(model.V)
        self.patch_blocks = self.patch.blocks(model.V)
        self.load_vector = np.asarray(load.vector, dtype=float)
        self.tool_bc_value = None
        if load.mode == "displacement":
            # The patch moves rigidly with the tool; nodes also held by a support keep
            # the support (a tool does not pull a clamped rim).
            held = organ.constrained_blocks(model.V)
            blocks = np.setdiff1d(self.patch_blocks, held)
            self.tool_bc_value = fem.Constant(organ.mesh, np.zeros(3))
            self.bcs.append(fem.dirichletbc(self.tool_bc_value, blocks, model.V))
            self.patch_blocks = blocks

    def _setup_load_region(self) -> None:
        """The dead load's region: the patch's facets and every further tool's (``load.tools``),
        each further tool a traction of its own on its own disk (``further``: its force,
        its traction and int w dA)."""
        load, organ, model = self.config.load, self.organ, self.model
        for k, tool in enumerate(load.tools):
            try:
                pair = np.asarray(tool, dtype=float)
            except (TypeError, ValueError):  # ragged or not numbers
                pair = None
            if pair is None or pair.shape != (2, 3) or not np.isfinite(pair).all():
                raise InputError(f"load.tools[{k}]: a (point, force) pair of 3 finite numbers "
                                 f"each (mm, N), not {tool!r}")  # fmt: skip
        patches = [ContactPatch.around_point(organ, point, load.contact_radius, load.surface)
                   for point, _ in load.tools]  # fmt: skip
        facets = np.concatenate([self.patch.facets] + [p.facets for p in patches])
        model.set_load_region(facets, self.patch.weight())
        for patch, (_, force) in zip(patches, load.tools, strict=True):
            traction = fem.Constant(organ.mesh, np.zeros(3))
            model.further_loads.append((traction, patch.weight()))
            area = fem.assemble_scalar(fem.form(patch.weight() * model.ds(model.LOAD_TAG)))
            area = organ.mesh.comm.allreduce(area, op=MPI.SUM)
            if not area > 0:
                raise InputError(f"the tool at {patch.point.tolist()} mm carries no load on "
                                 "this mesh: increase contact_radius")  # fmt: skip
            self.further.append((np.asarray(force, dtype=float), traction, area))

    def _setup_sphere(self) -> None:
        """A rigid sphere touching the surface at the contact point, moving along the load
        vector (:mod:`.sphere`); the supports are the only Dirichlet conditions."""
        load, organ = self.config.load, self.organ
        point = load.contact_point
        if point is None:
            point = organ.default_contact_point()
        self.patch = ContactPatch.around_point(organ, point, load.contact_radius, load.surface)
        self.load_vector = np.asarray(load.vector, dtype=float)
        length = float(np.linalg.norm(self.load_vector))
        if not length > 0:
            raise SolverError("sphere = [0, 0, 0]: the sphere must move")
        start = np.asarray(point, dtype=float) - load.contact_radius * self.load_vector / length
        self.sphere = SphereIndenter(self.model, load.contact_radius, start, load.penalty,
                                     load.surface)  # fmt: skip
        self.model.contact_energies.append(self.sphere.energy)
        self.bcs = organ.supports(self.model.V)
        self.patch_blocks = self.patch.blocks(self.model.V)
        self.tool_bc_value = None
        self._load_factor = 0.0

    def sphere_advance(self) -> np.ndarray:
        """How far the sphere has moved from touching the surface (mm): the 'depth' vector."""
        return self._load_factor * self.load_vector

    def set_load(self, load_factor: float) -> None:
        """Apply the load at ``load_factor`` (prescribed displacement or traction)."""
        mode = self.config.load.mode
        if mode == "sphere":
            self._load_factor = float(load_factor)
            self.sphere.move(self.sphere.start + load_factor * self.load_vector)
        elif mode == "displacement":
            self.tool_bc_value.value[:] = load_factor * self.load_vector
            for force, traction, area in self.further:
                traction.value[:] = load_factor * force / area
        elif mode == "force":
            # Dead traction load_factor * F * w(X) / int w dA: sums to load_factor * F.
            area = self.patch_displacement.integral
            self.model.traction.value[:] = load_factor * self.load_vector / area
            for force, traction, area in self.further:
                traction.value[:] = load_factor * force / area
        else:
            self.model.traction.value[:] = load_factor * self.load_vector

    def tool_force(self, load_factor: float) -> np.ndarray:
        """Force the tool exerts on the tissue (N); the first tool's, beside its depth
        (further tools' are ``further_forces``)."""
        mode = self.config.load.mode
        if mode == "displacement":
            return self.reaction()
        if mode == "sphere":
            return self.sphere.force()
        if mode == "force":
            return load_factor * self.load_vector
        return load_factor * self.load_vector * self.patch_displacement.integral

    def further_forces(self, load_factor: float) -> np.ndarray:
        """The forces of the further tools on the tissue (tools, 3), N."""
        return load_factor * np.array([f for f, _, _ in self.further]).reshape(-1, 3)

    # -- solve -----------------------------------------------------------------
    def close(self) -> None:
        """Free the solver's PETSc objects now (see :meth:`NewtonSolver.destroy`); the model
        cannot solve afterwards. For loops that build one model after another."""
        self.newton.destroy()

    def describe(self) -> str:
        """One line: mesh, element, DOFs, law and load."""
        dofs = self.model.num_dofs()
        load = self.config.load
        units = {"force": "N", "displacement": "mm", "traction": "MPa", "sphere": "mm"}[load.mode]
        return (
            f"{self.organ.path.name}: {self.organ.cell_type}, element {self.element.name}, "
            f"{dofs['displacement']} displacement + {dofs['pressure']} pressure DOFs on "
            f"{self.comm.size} rank(s); material {self.law.name}; "
            f"{load.mode} load {list(load.vector)} {units} {self._patch_summary()} "
            f"in {load.steps} steps"
        )

    def _patch_summary(self) -> str:
        if self.config.load.mode == "sphere":
            load = self.config.load
            return (
                f"(rigid sphere of radius {load.contact_radius} mm, "
                f"penalty {load.penalty:g} N/mm^4)"
            )
        if self.config.load.mode == "displacement":
            return f"on {self.patch_displacement.count} node(s) within {self.patch.radius} mm"
        where = (
            f"within {self.patch.radius} mm" if self.patch.radius else f"on '{self.patch.group}'"
        )
        integral = self.patch_displacement.integral
        return f"{where} ({self.patch.num_facets} facets, int w dA {integral:.4g} mm^2)"

    def _open_outputs(self, out_dir):
        """curve.csv and fields.xdmf writers in ``out_dir`` (None, None without one)."""
        if out_dir is None:
            return None, None
        out_dir = Path(out_dir)
        if self.comm.rank == 0:
            out_dir.mkdir(parents=True, exist_ok=True)
        self.comm.barrier()
        curve = CurveWriter(out_dir / "curve.csv", self.comm)
        fields = None
        if self.config.output.xdmf:
            fields = FieldWriter(
                out_dir / "fields.xdmf", self.model.u, self.model.p, self.model.fibres
            )
            fields.write(0.0)
        return curve, fields

    def solve(self, out_dir: str | Path | None = None, on_step=None) -> SolveResult:
        """Run the incremental loading; write curve.csv, sanity.json, fields.xdmf in ``out_dir``.

        ``on_step(record, force, disp)`` is called after every converged
        increment, on every rank. If the solve fails, ``self.history`` still holds
        the converged increments (records, forces, displacements) and
        ``self.sanity`` their physics sanity (:mod:`hapticrom.offline.fe.sanity`).
        """
        comm, load = self.comm, self.config.load
        log = (lambda s: print0(comm, s)) if self.verbose else (lambda s: None)
        log(self.describe())
        curve, fields = self._open_outputs(out_dir)
        records, forces, disps = [], [], []
        self.history = (records, forces, disps)
        self.monitor.steps = []
        user_hook = on_step

        def on_step(record: StepRecord) -> None:
            force = self.tool_force(record.load_factor)
            disp = self.patch_displacement()
            records.append(record)
            forces.append(force)
            disps.append(disp)
            self.monitor.measure(record, force, disp)
            if user_hook is not None:
                user_hook(record, force, disp)
            if curve is not None:
                curve.write(record, force, disp)
            if fields is not None:
                fields.write(record.load_factor)
            log(self._step_line(record, force, disp))

        stepper = IncrementalLoading(
            self.newton,
            self.set_load,
            load.steps,
            load.max_step_cuts,
            load.predictor,
            log,
            modified_newton=self.config.solver.newton == "modified",
        )
        t0 = time.perf_counter()
        try:
            stepper.run(on_step)
        except SolverError as exc:
            self._finish_sanity(out_dir, failure=str(exc))
            raise
        finally:
            if curve is not None:
                curve.close()
            if fields is not None:
                fields.close()
        result = self.partial_result(time.perf_counter() - t0)
        self._finish_sanity(out_dir)
        result.sanity = self.sanity
        log(
            f"done: {len(records)} increments, {result.newton_iterations} Newton iterations, "
            f"{result.solve_seconds:.2f} s solving (+{self.jit_seconds:.2f} s compiling forms)"
        )
        return result

    @staticmethod
    def _step_line(record: StepRecord, force, disp) -> str:
        cut = f", {record.step_cuts} cut(s)" if record.step_cuts else ""
        return (
            f"step {record.step:3d}  load factor {record.load_factor:.4f}  "
            f"force [{force[0]: .4e} {force[1]: .4e} {force[2]: .4e}] N  "
            f"disp [{disp[0]: .4e} {disp[1]: .4e} {disp[2]: .4e}] mm  "
            f"{record.newton_iterations} Newton its{cut}  {record.seconds:.2f} s"
        )

    def partial_result(self, solve_seconds: float = 0.0) -> SolveResult:
        """The converged increments so far (``self.history``) as a :class:`SolveResult`."""
        records, forces, disps = self.history
        return SolveResult(
            records=list(records),
            force=np.array(forces).reshape(-1, 3),
            displacement=np.array(disps).reshape(-1, 3),
            load_factor=np.array([r.load_factor for r in records]),
            num_dofs=self.model.num_dofs(),
            setup_seconds=self.setup_seconds,
            jit_seconds=self.jit_seconds,
            solve_seconds=solve_seconds,
            sanity=self.sanity,
        )

    def _finish_sanity(self, out_dir, failure: str | None = None) -> None:
        """Judge the load path; write sanity.json into ``out_dir``; print the warnings."""
        self.sanity = self.monitor.report(failure)
        if self.comm.rank != 0:
            return
        if out_dir is not None:
            write_json(Path(out_dir) / "sanity.json", self.sanity.to_dict())
        if self.verbose:
            for line in self.sanity.warnings("warning"):
                print(line, flush=True)


def solve_config(config: ProblemConfig, out_dir=None, comm=MPI.COMM_WORLD, verbose=True):
    """Build and solve the full-order model of ``config``; see :class:`FullOrderModel`."""
    return FullOrderModel(config, comm, verbose=verbose).solve(out_dir)
