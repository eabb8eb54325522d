"""Configuration of a full-order solve, read from TOML (units: mm, N, MPa).

Pure Python: a wrong file fails here with one clear :class:`InputError`, before
DOLFINx or PETSc are imported. Example (``examples/cornea-hgo-indent.toml``)::

    [mesh]
    file = "../meshes/cornea.msh"     # relative to this file

    [material]
    law = "hgo"                       # svk | neo-hookean | hgo
    C1 = 0.1                          # remaining parameters: the law's defaults

    [load]
    mode = "displacement"             # force | displacement | traction
    contact_point = [0.0, 0.0, 0.0]   # mm; default: the mesh's default contact point
    contact_radius = 0.5              # mm
    displacement = [0.0, 0.0, -0.5]   # mm at load factor 1
    steps = 10

    [solver]
    options_prefix = "hapticrom_"     # then tune with -hapticrom_snes_rtol 1e-10
    [solver.petsc_options]
    snes_max_it = 30

Each table is a typed model (:mod:`hapticrom.offline.tables`): :class:`MeshTable`,
:class:`MaterialTable`, :class:`LoadTable`, :class:`DiscretisationTable`,
:class:`SolverTable`, :class:`OutputTable`, gathered by :class:`SolveFile`. A campaign
(:mod:`hapticrom.offline.campaign.config`) reuses them; its ``[load]`` shares
:class:`LoadCommon`. What comes out are the frozen dataclasses below.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, PlainValidator, WithJsonSchema, model_validator

from hapticrom.offline.tables import (
    Table,
    boolean,
    choice,
    integer,
    invalid,
    number,
    rule,
    text,
    validate,
    vector,
)
from hapticrom.shared.errors import InputError

LOAD_MODES = ("force", "displacement", "traction", "sphere")
LINEAR_SOLVERS = ("direct", "iterative")
PREDICTORS = ("secant", "none")
NEWTON_STRATEGIES = ("full", "modified")


@dataclass(frozen=True)
class MeshConfig:
    """The organ's Gmsh file (``hapticrom mesh``)."""

    file: Path


@dataclass(frozen=True)
class MaterialConfig:
    """A material law by name and its parameters (MPa), as written in the file."""

    law: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DiscretisationConfig:
    """``element``: auto, or Q1 | Q1P0 | Q2 | Q2Q1 | Q2P0 (hexahedra), P1 | P2 | P2P0 | P2P1 (tets).

    auto is Q1P0 on hexahedra and P2P0 on tetrahedra: locking-free and with an
    element-wise pressure that condenses out exactly.
    """

    element: str = "auto"
    quadrature_degree: int | None = None


@dataclass(frozen=True)
class LoadConfig:
    """The tool load, scaled by a load factor that goes from 0 to 1 in ``steps`` steps.

    - ``force``: a force ``force`` (N) spread as a uniform dead traction over the
      contact patch (the loadable facets within ``contact_radius`` mm of
      ``contact_point``).
    - ``displacement``: the contact patch is moved by ``displacement`` (mm); the
      reaction force on the tool comes from the residual (the haptic case).
    - ``traction``: a uniform dead traction ``traction`` (MPa) on the whole
      surface group ``surface`` (the beam benchmark).
    - ``sphere``: a rigid frictionless sphere of radius ``contact_radius`` that touches
      the surface at ``contact_point`` and moves by ``sphere`` (mm); contact by a penalty
      ``penalty`` (N/mm^4: contact pressure per overlap squared, :mod:`.fe.sphere`).

    ``tools`` (``force`` or ``displacement``): further force tools at once, each a (contact
    point, force) pair spread over its own disk of ``contact_radius``, all scaled by the
    same load factor (two instruments, a pinch, issue 18's references); beside a
    ``displacement`` first tool they press while it holds (grasps) its patch, moved by
    ``displacement`` (zero: held in place). Set in code, not read from a file.
    """

    mode: str
    force: tuple[float, float, float] | None = None
    displacement: tuple[float, float, float] | None = None
    traction: tuple[float, float, float] | None = None
    sphere: tuple[float, float, float] | None = None
    contact_point: tuple[float, float, float] | None = None
    penalty: float = 1e4
    contact_radius: float = 0.5
    surface: str = "loadable"
    steps: int = 10
    max_step_cuts: int = 8
    predictor: str = "secant"
    tools: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()

    @property
    def vector(self) -> tuple[float, float, float]:
        """The load at factor 1: N (force), mm (displacement, sphere) or MPa (traction)."""
        return getattr(self, self.mode)


@dataclass(frozen=True)
class SolverConfig:
    """``newton``: full (a new tangent every iteration, quadratic convergence) or
    modified (one tangent per load step, factorised once: cheaper steps when the
    factorisation dominates; a step it cannot converge is retried with full Newton).
    """

    options_prefix: str = "hapticrom_"
    linear_solver: str = "direct"
    newton: str = "full"
    petsc_options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class OutputConfig:
    """What a solve writes besides its record: ``xdmf``, the displacement path."""

    xdmf: bool = True


@dataclass(frozen=True)
class ProblemConfig:
    """A full-order solve: mesh, material, load, discretisation, solver and output."""

    mesh: MeshConfig
    material: MaterialConfig
    load: LoadConfig
    discretisation: DiscretisationConfig = DiscretisationConfig()
    solver: SolverConfig = SolverConfig()
    output: OutputConfig = OutputConfig()

    @classmethod
    def from_toml(cls, path: str | Path) -> ProblemConfig:
        """Read and check a solve configuration file (paths relative to its folder)."""
        path = Path(path)
        return cls.from_dict(read_toml(path), base_dir=path.parent, source=str(path))

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], base_dir: str | Path = ".", source: str = "configuration"
    ) -> ProblemConfig:
        """Check ``data`` (as from tomllib) against :class:`SolveFile`; InputError naming
        ``source``, the table and the key otherwise."""
        return validate(SolveFile, data, source).problem(Path(base_dir))


def read_toml(path: Path, what: str = "configuration file") -> dict[str, Any]:
    """Parse a TOML file; InputError if it is missing, unreadable, not UTF-8 or not TOML."""
    if not path.is_file():
        raise InputError(f"{what} {path} not found")
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise InputError(f"{what} {path} cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{path}: not valid TOML (not UTF-8 text: byte 0x{exc.object[exc.start]:02x} "
            f"at offset {exc.start})"
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None


# --- the tables ---------------------------------------------------------------------------

# Bounds (inclusive) of the integer [load] keys shared by a problem and a campaign.
LOAD_STEPS = (1, 100_000)
LOAD_MAX_STEP_CUTS = (0, 16)

# The value types of the keys (offline/tables.py), shared with the campaign's tables.
Positive = number(gt=0)
PositiveInteger = integer(ge=1)
Vector = vector()
Boolean = boolean()
MeshPath = text('a path such as "../meshes/cornea.msh"')
LawName = text("a material law such as svk, neo-hookean or hgo")
SurfaceName = text("the name of a surface group")
Steps = integer(ge=LOAD_STEPS[0], le=LOAD_STEPS[1])
StepCuts = integer(ge=LOAD_MAX_STEP_CUTS[0], le=LOAD_MAX_STEP_CUTS[1])
Predictor = choice(PREDICTORS)
LoadMode = choice(LOAD_MODES)
ElementName = text("a name such as Q1P0")
OptionsPrefix = text(
    "a non-empty word such as 'hapticrom_'",
    accept=lambda v: v.replace("_", "").isalnum(),
    pattern="^_*[A-Za-z0-9][A-Za-z0-9_]*$",
)
LinearSolver = choice(LINEAR_SOLVERS)
NewtonStrategy = choice(NEWTON_STRATEGIES)


class MeshTable(Table):
    """``[mesh]``: the Gmsh file of the organ (``hapticrom mesh``), relative to the config."""

    missing = {"file": 'file = "path/to/mesh.msh" (generate one with `hapticrom mesh`)'}
    file: MeshPath = Field(
        description="Gmsh .msh file of the organ, relative to this file (`hapticrom mesh`)"
    )

    def config(self, base_dir: Path) -> MeshConfig:
        """The mesh file, relative paths taken from ``base_dir``."""
        path = Path(self.file)
        return MeshConfig(file=path if path.is_absolute() else (base_dir / path))


def _material_schema(schema: dict[str, Any]) -> None:
    """The JSON Schema of ``[material]``: one branch per law, with its parameters and defaults
    (from the laws' dataclasses; their bounds are checked by the laws)."""
    from dataclasses import MISSING, fields

    from hapticrom.offline.fe.materials import ALIASES, LAWS

    schema.pop("additionalProperties", None)
    branches = []
    for name, law in sorted(LAWS.items()):
        names = [name, *sorted(alias for alias, key in ALIASES.items() if key == name)]
        params, required = {}, ["law"]
        for f in fields(law):
            kind = "boolean" if f.type in ("bool", bool) else "number"
            params[f.name] = {"type": kind}
            if f.default is MISSING:
                required.append(f.name)
            else:
                params[f.name]["default"] = f.default
        branches.append(
            {
                "title": name,
                "description": (law.__doc__ or name).strip().splitlines()[0],
                "properties": {"law": {"enum": names}, **params},
                "required": required,
                "additionalProperties": False,
            }
        )
    schema["oneOf"] = branches


class MaterialTable(Table, extra="allow", json_schema_extra=_material_schema):
    """``[material]``: ``law`` and its parameters (MPa), checked by the law itself.

    The parameters a law takes, their defaults and bounds are the law's
    (:func:`hapticrom.offline.fe.materials.make_law`); the JSON Schema lists them per law.
    """

    missing = {"law": 'law = "svk" | "neo-hookean" | "hgo"'}
    law: LawName = Field(description="the strain-energy law: svk | neo-hookean | hgo")

    @model_validator(mode="after")
    def _law(self) -> MaterialTable:
        """The law accepts the parameters (names, types, bounds), before any mesh is read."""
        from hapticrom.offline.fe.materials import make_law

        rule(lambda: make_law(self.law, **self.params))
        return self

    @property
    def params(self) -> dict[str, Any]:
        """The law's parameters as written (every key but ``law``)."""
        return dict(self.model_extra or {})

    def config(self) -> MaterialConfig:
        """The law's name and parameters."""
        return MaterialConfig(law=self.law, params=self.params)


class LoadCommon(Table):
    """The ``[load]`` keys a problem configuration and a campaign share.

    One model for both, so a campaign is bounded exactly as the problem
    configuration it becomes at every position (:class:`LoadConfig`).
    """

    contact_radius: Positive = Field(
        0.5, description="mm: the tool holds (or presses) the surface within this radius"
    )
    surface: SurfaceName = Field(
        "loadable", description="the mesh's surface group the tool acts on"
    )
    steps: Steps = Field(10, description="load steps from load factor 0 to 1")
    max_step_cuts: StepCuts = Field(
        8, description="times a load step may be halved when Newton fails"
    )
    predictor: Predictor = Field(
        "secant", description="first guess of a load step: secant extrapolation or none"
    )

    def common(self) -> dict[str, Any]:
        """These keys' values, as keyword arguments of :class:`LoadConfig`."""
        return {key: getattr(self, key) for key in LOAD_COMMON_KEYS}


LOAD_COMMON_KEYS = tuple(LoadCommon.model_fields)


class LoadTable(LoadCommon):
    """``[load]`` of a solve: the mode and its vector at load factor 1 (see :class:`LoadConfig`)."""

    missing = {"mode": 'mode = "force" | "displacement" | "traction" | "sphere"'}
    mode: LoadMode = Field(
        description="force (N) | displacement (mm) | traction (MPa) | sphere (mm)"
    )
    force: Vector | None = Field(None, description="N at load factor 1 (mode = force)")
    displacement: Vector | None = Field(
        None, description="mm at load factor 1 (mode = displacement)"
    )
    traction: Vector | None = Field(
        None, description="MPa at load factor 1 on the whole surface (mode = traction)"
    )
    sphere: Vector | None = Field(
        None,
        description="mm: the rigid sphere's move at load factor 1, from touching the surface "
        "at contact_point (mode = sphere; its radius is contact_radius)",
    )
    penalty: Positive | None = Field(
        None,
        description="N/mm^4: the sphere's contact pressure per overlap squared (mode = sphere; "
        "default 1e4)",
    )
    contact_point: Vector | None = Field(
        None, description="mm; default: the mesh's default contact point"
    )

    @model_validator(mode="after")
    def _one_vector(self) -> LoadTable:
        """The mode's vector is given, and no other mode's."""
        for mode in LOAD_MODES:
            given = getattr(self, mode) is not None
            if mode == self.mode and not given:
                raise invalid(f"missing {mode} = [x, y, z]")
            if mode != self.mode and given:
                raise invalid(f"{mode} is given but mode is {self.mode!r}")
        if self.penalty is not None and self.mode != "sphere":
            raise invalid(f"penalty is given but mode is {self.mode!r} (it is the sphere's)")
        return self

    def config(self) -> LoadConfig:
        """The load of the solve."""
        vectors = {mode: getattr(self, mode) for mode in LOAD_MODES}
        penalty = {} if self.penalty is None else {"penalty": self.penalty}
        return LoadConfig(
            mode=self.mode, contact_point=self.contact_point, **self.common(), **vectors, **penalty
        )


class DiscretisationTable(Table):
    """``[discretisation]``: the finite element and the quadrature (see
    :class:`DiscretisationConfig`)."""

    element: ElementName = Field(
        "auto",
        description="auto | Q1 | Q1P0 | Q2 | Q2Q1 | Q2P0 (hexahedra) | P1 | P2 | P2P0 | P2P1 "
        "(tetrahedra); checked against the mesh when it is read",
    )
    quadrature_degree: PositiveInteger | None = Field(
        None, description="default: from the element and the law"
    )

    def config(self) -> DiscretisationConfig:
        """The element and quadrature degree."""
        return DiscretisationConfig(element=self.element, quadrature_degree=self.quadrature_degree)


def _petsc_options(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise invalid(f"must be a table of PETSc option names and values, got {value!r}")
    return dict(value)


PetscOptions = Annotated[
    dict,
    PlainValidator(_petsc_options),
    WithJsonSchema(
        {"type": "object", "additionalProperties": {"type": ["string", "number", "boolean"]}}
    ),
]


class SolverTable(Table):
    """``[solver]``: Newton strategy, linear solver, PETSc options (:class:`SolverConfig`)."""

    options_prefix: OptionsPrefix = Field(
        "hapticrom_", description="PETSc options prefix (-hapticrom_snes_rtol ...)"
    )
    linear_solver: LinearSolver = Field("direct", description="direct | iterative")
    newton: NewtonStrategy = Field(
        "full", description="full (a tangent per iteration) | modified (one per load step)"
    )
    petsc_options: PetscOptions = Field(
        default_factory=dict, description="PETSc option names (without prefix) and values"
    )

    def config(self) -> SolverConfig:
        """The solver settings."""
        return SolverConfig(
            options_prefix=self.options_prefix,
            linear_solver=self.linear_solver,
            newton=self.newton,
            petsc_options=dict(self.petsc_options),
        )


class OutputTable(Table):
    """``[output]``: what a solve writes besides its record."""

    xdmf: Boolean = Field(True, description="write the displacement path as XDMF")

    def config(self) -> OutputConfig:
        """The output settings."""
        return OutputConfig(xdmf=self.xdmf)


class SolveFile(Table):
    """A solve configuration file (``hapticrom solve CONFIG``): its tables."""

    mesh: MeshTable
    material: MaterialTable
    load: LoadTable
    discretisation: DiscretisationTable = DiscretisationTable()
    solver: SolverTable = SolverTable()
    output: OutputTable = OutputTable()

    def problem(self, base_dir: Path) -> ProblemConfig:
        """The :class:`ProblemConfig`; a relative mesh path is taken from ``base_dir``."""
        return ProblemConfig(
            self.mesh.config(base_dir),
            self.material.config(),
            self.load.config(),
            self.discretisation.config(),
            self.solver.config(),
            self.output.config(),
        )
