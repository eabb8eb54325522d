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
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hapticrom.shared.errors import InputError

LOAD_MODES = ("force", "displacement", "traction")
LINEAR_SOLVERS = ("direct", "iterative")
PREDICTORS = ("secant", "none")
NEWTON_STRATEGIES = ("full", "modified")


@dataclass(frozen=True)
class MeshConfig:
    file: Path


@dataclass(frozen=True)
class MaterialConfig:
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
    """

    mode: str
    force: tuple[float, float, float] | None = None
    displacement: tuple[float, float, float] | None = None
    traction: tuple[float, float, float] | None = None
    contact_point: tuple[float, float, float] | None = None
    contact_radius: float = 0.5
    surface: str = "loadable"
    steps: int = 10
    max_step_cuts: int = 8
    predictor: str = "secant"

    @property
    def vector(self) -> tuple[float, float, float]:
        """The load at factor 1: N (force), mm (displacement) or MPa (traction)."""
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
    xdmf: bool = True


@dataclass(frozen=True)
class ProblemConfig:
    mesh: MeshConfig
    material: MaterialConfig
    load: LoadConfig
    discretisation: DiscretisationConfig = DiscretisationConfig()
    solver: SolverConfig = SolverConfig()
    output: OutputConfig = OutputConfig()

    @classmethod
    def from_toml(cls, path: str | Path) -> ProblemConfig:
        path = Path(path)
        return cls.from_dict(read_toml(path), base_dir=path.parent, source=str(path))

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], base_dir: str | Path = ".", source: str = "configuration"
    ) -> ProblemConfig:
        reader = _Reader(source)
        reader.keys(data, "", {"mesh", "material", "load", "discretisation", "solver", "output"})
        mesh = _mesh(reader, reader.table(data, "mesh", required=True), Path(base_dir))
        material = _material(reader, reader.table(data, "material", required=True))
        load = _load(reader, reader.table(data, "load", required=True))
        disc = _discretisation(reader, reader.table(data, "discretisation"))
        solver = _solver(reader, reader.table(data, "solver"))
        out = reader.table(data, "output")
        reader.keys(out, "output", {"xdmf"})
        output = OutputConfig(xdmf=reader.boolean(out, "output", "xdmf", True))
        return cls(mesh, material, load, disc, solver, output)


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


class _Reader:
    """Small typed accessors that name the file and key in every error."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, message: str):
        raise InputError(
            f"{self.source}: [{where}] {message}" if where else f"{self.source}: {message}"
        )

    def keys(self, table: dict, where: str, allowed: set[str]) -> None:
        unknown = sorted(set(table) - allowed)
        if unknown:
            self.fail(
                where, f"unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}"
            )

    def table(self, data: dict, name: str, required: bool = False) -> dict:
        if name not in data:
            if required:
                self.fail("", f"missing table [{name}]")
            return {}
        if not isinstance(data[name], dict):
            self.fail(name, "must be a table")
        return data[name]

    def number(self, table, where, key, default=None, positive=False, integer=False):
        if key not in table:
            if default is None:
                self.fail(where, f"missing {key}")
            return default
        v = table[key]
        ok = isinstance(v, int) if integer else isinstance(v, int | float)
        if isinstance(v, bool) or not ok or not math.isfinite(v):
            self.fail(
                where, f"{key} must be a finite {'integer' if integer else 'number'}, got {v!r}"
            )
        if positive and v <= 0:
            self.fail(where, f"{key} must be positive, got {v}")
        return v

    def vector(self, table, where, key, required=False):
        if key not in table:
            if required:
                self.fail(where, f"missing {key} = [x, y, z]")
            return None
        v = table[key]
        if (
            not isinstance(v, list)
            or len(v) != 3
            or any(isinstance(c, bool) or not isinstance(c, int | float) for c in v)
            or not all(math.isfinite(c) for c in v)
        ):
            self.fail(where, f"{key} must be three finite numbers [x, y, z], got {v!r}")
        return tuple(float(c) for c in v)

    def choice(self, table, where, key, choices, default):
        v = table.get(key, default)
        if v not in choices:
            self.fail(where, f"{key} must be one of {', '.join(choices)}, got {v!r}")
        return v

    def boolean(self, table, where, key, default):
        v = table.get(key, default)
        if not isinstance(v, bool):
            self.fail(where, f"{key} must be true or false, got {v!r}")
        return v


def _mesh(r: _Reader, t: dict, base_dir: Path) -> MeshConfig:
    r.keys(t, "mesh", {"file"})
    if not isinstance(t.get("file"), str):
        r.fail("mesh", 'missing file = "path/to/mesh.msh" (generate one with `hapticrom mesh`)')
    path = Path(t["file"])
    return MeshConfig(file=path if path.is_absolute() else (base_dir / path))


def _material(r: _Reader, t: dict) -> MaterialConfig:
    if not isinstance(t.get("law"), str):
        r.fail("material", 'missing law = "svk" | "neo-hookean" | "hgo"')
    params = {k: v for k, v in t.items() if k != "law"}
    # The law and its parameters are checked here, before any mesh is read or any
    # output directory created (ufl is pure Python: still no DOLFINx or PETSc).
    from hapticrom.offline.fe.materials import make_law

    try:
        make_law(t["law"], **params)
    except InputError as exc:
        r.fail("material", str(exc))
    return MaterialConfig(law=t["law"], params=params)


# Keys of the [load] table shared by a problem configuration and a campaign, and
# the bounds of the integer ones (inclusive), checked by :func:`load_common`.
LOAD_COMMON_KEYS = ("contact_radius", "surface", "steps", "max_step_cuts", "predictor")
LOAD_STEPS = (1, 100_000)
LOAD_MAX_STEP_CUTS = (0, 16)


def _load(r: _Reader, t: dict) -> LoadConfig:
    r.keys(t, "load", {"mode", *LOAD_MODES, "contact_point", *LOAD_COMMON_KEYS})
    mode = r.choice(t, "load", "mode", LOAD_MODES, None)
    vectors = {m: r.vector(t, "load", m, required=(m == mode)) for m in LOAD_MODES}
    for m in LOAD_MODES:
        if m != mode and vectors[m] is not None:
            r.fail("load", f"{m} is given but mode is {mode!r}")
    return LoadConfig(
        mode=mode,
        contact_point=r.vector(t, "load", "contact_point"),
        **load_common(r, t),
        **vectors,
    )


def load_common(r: _Reader, t: dict) -> dict[str, Any]:
    """The [load] keys a problem configuration and a campaign share, validated.

    One validator for both, so a campaign is bounded exactly as the problem
    configuration it becomes at every position (:class:`LoadConfig`).
    """
    surface = t.get("surface", "loadable")
    if not isinstance(surface, str) or not surface:
        r.fail("load", f"surface must be the name of a surface group, got {surface!r}")
    return {
        "contact_radius": r.number(t, "load", "contact_radius", 0.5, positive=True),
        "surface": surface,
        "steps": _bounded(r, t, "steps", 10, *LOAD_STEPS),
        "max_step_cuts": _bounded(r, t, "max_step_cuts", 8, *LOAD_MAX_STEP_CUTS),
        "predictor": r.choice(t, "load", "predictor", PREDICTORS, "secant"),
    }


def _bounded(r: _Reader, t: dict, key: str, default: int, low: int, high: int) -> int:
    value = r.number(t, "load", key, default, integer=True)
    if not low <= value <= high:
        r.fail("load", f"{key} must lie in [{low}, {high}], got {value}")
    return value


def _discretisation(r: _Reader, t: dict) -> DiscretisationConfig:
    r.keys(t, "discretisation", {"element", "quadrature_degree"})
    element = t.get("element", "auto")
    if not isinstance(element, str):
        r.fail("discretisation", "element must be a name such as Q1P0")
    qd = t.get("quadrature_degree")
    if qd is not None:
        qd = r.number(t, "discretisation", "quadrature_degree", positive=True, integer=True)
    return DiscretisationConfig(element=element, quadrature_degree=qd)


def _solver(r: _Reader, t: dict) -> SolverConfig:
    r.keys(t, "solver", {"options_prefix", "linear_solver", "newton", "petsc_options"})
    prefix = t.get("options_prefix", "hapticrom_")
    if not isinstance(prefix, str) or not prefix or not prefix.replace("_", "").isalnum():
        r.fail(
            "solver",
            f"options_prefix must be a non-empty word such as 'hapticrom_', got {prefix!r}",
        )
    options = t.get("petsc_options", {})
    if not isinstance(options, dict):
        r.fail("solver", "petsc_options must be a table of PETSc option names and values")
    return SolverConfig(
        options_prefix=prefix,
        linear_solver=r.choice(t, "solver", "linear_solver", LINEAR_SOLVERS, "direct"),
        newton=r.choice(t, "solver", "newton", NEWTON_STRATEGIES, "full"),
        petsc_options=dict(options),
    )
