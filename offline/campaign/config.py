"""The campaign configuration: its TOML tables, read and checked before anything runs.

A campaign (TOML, see ``examples/cornea-campaign.toml``) names the mesh, the
material, the control mode and load range, and the tool positions; running it
is :func:`hapticrom.offline.campaign.run.run_campaign`.

The tables are typed models (:mod:`hapticrom.offline.tables`), gathered by
:class:`CampaignFile`: ``[mesh]``, ``[material]``, ``[discretisation]`` and
``[solver]`` are a solve's (:mod:`hapticrom.offline.config`), ``[load]``
(:class:`CampaignLoadTable`) shares a solve's :class:`~hapticrom.offline.config.LoadCommon`
keys, ``[positions]`` is :class:`~hapticrom.offline.campaign.positions.PositionsTable`;
``[campaign]``, ``[pod]``, ``[anm]`` and ``[cutting]`` are the campaign's own.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import (
    Field,
    PlainValidator,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from hapticrom.offline.campaign.positions import PositionsSpec, PositionsTable, ToolPosition
from hapticrom.offline.config import (
    Boolean,
    DiscretisationTable,
    LoadCommon,
    LoadConfig,
    MaterialTable,
    MeshTable,
    OutputConfig,
    Positive,
    PositiveInteger,
    ProblemConfig,
    SolverTable,
    Vector,
    read_toml,
)
from hapticrom.offline.tables import (
    VECTOR_SCHEMA,
    Table,
    check_vector,
    choice,
    integer,
    invalid,
    number,
    text,
    validate,
)
from hapticrom.shared.checksum import file_digest

CONTROL_MODES = ("displacement", "force", "sphere")
INNER_PRODUCTS = ("euclidean", "volume")
POD_METHODS = ("snapshots", "svd")
ANM_ORDERS = (1, 15)


@dataclass(frozen=True)
class CampaignLoad:
    """The tool load of every position, scaled by a load factor from 0 to 1.

    ``magnitude``: mm (displacement control, a rigid sphere's move) or N (force
    control) at load factor 1; ``direction``: "normal" (into the surface, along its
    inward normal at the position) or a fixed vector (normalised). ``sphere``: a rigid
    frictionless sphere of radius ``contact_radius`` touching the surface at the
    position and moving ``magnitude`` along the direction (contact by the penalty
    ``penalty``, N/mm^4): the tool of ``Simulator.step_position``.
    """

    mode: str
    magnitude: float
    direction: str | tuple[float, float, float] = "normal"
    contact_radius: float = 0.5
    surface: str = "loadable"
    steps: int = 10
    max_step_cuts: int = 8
    predictor: str = "secant"
    penalty: float = 1e4

    def unit_direction(self, position: ToolPosition) -> np.ndarray:
        """The unit vector the tool pushes along at ``position``."""
        if self.direction == "normal":
            return -np.asarray(position.normal, dtype=float)
        d = np.asarray(self.direction, dtype=float)
        return d / np.linalg.norm(d)

    def at(self, position: ToolPosition) -> LoadConfig:
        """The load of the full-order solve at ``position``."""
        vector = tuple(float(v) for v in self.magnitude * self.unit_direction(position))
        return LoadConfig(
            mode=self.mode,
            contact_point=tuple(position.point),
            contact_radius=self.contact_radius,
            surface=self.surface,
            steps=self.steps,
            max_step_cuts=self.max_step_cuts,
            predictor=self.predictor,
            **({"penalty": self.penalty} if self.mode == "sphere" else {}),
            **{self.mode: vector},
        )


@dataclass(frozen=True)
class PODConfig:
    """Truncation and inner product of the POD (thesis §2.2.2: eigenvalue ratio 1e-8)."""

    eigenvalue_ratio: float | None = 1e-8
    energy: float | None = None
    max_modes: int | None = None
    inner_product: str = "euclidean"
    method: str = "snapshots"


@dataclass(frozen=True)
class ANMConfig:
    """POD-ANM series per sample (thesis ch. 3), computed by the reduction step."""

    enabled: bool = True
    order: int = 6
    tolerance: float = 1e-4
    ranks_per_series: int = 1  # the ranks form groups of this size, each computes some samples


@dataclass(frozen=True)
class CuttingConfig:
    """The ``[cutting]`` table of a campaign: where the organ can be cut, and how."""

    centre: tuple[float, float, float]
    radius: float  # mm
    patch_layers: int = 2
    cut_force: float = 0.02  # N: the blade force above which a face is cut (thesis eq. 4.10)


@dataclass(frozen=True)
class CampaignConfig:
    """A training campaign: the solve at every tool position, and how the reduction goes.

    ``raw`` is the file's data as read: the manifest keeps it and
    :meth:`campaign_hash` hashes it.
    """

    name: str
    problem: ProblemConfig  # mesh, material, discretisation, solver (its load is unused)
    load: CampaignLoad
    positions: PositionsSpec
    pod: PODConfig = PODConfig()
    anm: ANMConfig = ANMConfig()
    cutting: CuttingConfig | None = None  # the artifact's cuttable region
    raw: dict = field(default_factory=dict, compare=False)

    @classmethod
    def from_toml(cls, path: str | Path) -> CampaignConfig:
        """Read and check a campaign file (paths relative to its folder)."""
        path = Path(path)
        data = read_toml(path, "campaign file")
        return cls.from_dict(data, base_dir=path.parent, source=str(path))

    @classmethod
    def from_dict(cls, data: dict, base_dir: str | Path = ".", source: str = "campaign"):
        """Check ``data`` (as from tomllib) against :class:`CampaignFile`; InputError naming
        ``source``, the table and the key otherwise."""
        return validate(CampaignFile, data, source).config(data, Path(base_dir), source)

    def campaign_hash(self) -> str:
        """Identity of the campaign: its configuration and the bytes of its mesh.

        The ``[anm]`` and ``[cutting]`` tables are left out: they only change the
        reduction, not the solves. So is ``[positions.greedy]``: it says how many
        positions the greedy trainer may add (they are listed in the manifest), not how
        a position is solved, so a greedy run extends the same directory when its target
        or budget changes.
        """
        solves = {k: v for k, v in self.raw.items() if k not in ("anm", "cutting")}
        positions = solves.get("positions")
        if isinstance(positions, dict) and "greedy" in positions:
            solves["positions"] = {k: v for k, v in positions.items() if k != "greedy"}
        h = hashlib.sha256(json.dumps(solves, sort_keys=True, default=str).encode())
        h.update(file_digest(self.problem.mesh.file).encode())
        return h.hexdigest()


# --- the tables ---------------------------------------------------------------------------

# The value types of the campaign's own keys (offline/tables.py).
CampaignName = text("a non-empty name")
Description = text("a string", accept=lambda v: True)
ControlMode = choice(CONTROL_MODES)
EnergyFraction = number(gt=0, le=1)
InnerProduct = choice(INNER_PRODUCTS)
PODMethod = choice(POD_METHODS)
ANMOrder = integer(ge=ANM_ORDERS[0], le=ANM_ORDERS[1])
ANMTolerance = number(gt=0, lt=1)


class CampaignTable(Table):
    """``[campaign]``: its name (default: the file's stem) and a description."""

    name: CampaignName | None = Field(None, description="default: the file's stem")
    description: Description | None = Field(None, description="one line for people")


def _direction(value: Any) -> str | tuple[float, float, float]:
    if value == "normal":
        return "normal"
    if isinstance(value, str):
        raise invalid(f'must be "normal" or three finite numbers [x, y, z], got {value!r}')
    return check_vector(value, nonzero=True)


Direction = Annotated[
    str | tuple[float, float, float],
    PlainValidator(_direction),
    WithJsonSchema({"anyOf": [{"const": "normal"}, VECTOR_SCHEMA]}),
]


class CampaignLoadTable(LoadCommon):
    """``[load]`` of a campaign: one load for every position (see :class:`CampaignLoad`)."""

    missing = {
        "mode": 'mode = "displacement" | "force" | "sphere"',
        "magnitude": "magnitude (mm or N)",
    }
    mode: ControlMode = Field(
        description="displacement (mm) | force (N) control | sphere (mm: a rigid sphere)"
    )
    magnitude: Positive = Field(description="mm or N at load factor 1")
    direction: Direction = Field(
        "normal", description='"normal" (into the surface at each position) or [x, y, z]'
    )
    penalty: Positive | None = Field(
        None,
        description="N/mm^4: the sphere's contact pressure per overlap squared (mode = sphere; "
        "default 1e4)",
    )

    @model_validator(mode="after")
    def _penalty_is_the_sphere_s(self) -> CampaignLoadTable:
        if self.penalty is not None and self.mode != "sphere":
            raise invalid(f"penalty is given but mode is {self.mode!r} (it is the sphere's)")
        return self

    def config(self) -> CampaignLoad:
        """The campaign's load."""
        penalty = {} if self.penalty is None else {"penalty": self.penalty}
        return CampaignLoad(
            mode=self.mode, magnitude=self.magnitude, direction=self.direction,
            **self.common(), **penalty,
        )  # fmt: skip


class PODTable(Table):
    """``[pod]``: truncation and inner product of the POD (see :class:`PODConfig`)."""

    eigenvalue_ratio: Positive = Field(1e-8, description="drop modes below this ratio")
    energy: EnergyFraction | None = Field(None, description="keep this energy fraction")
    max_modes: PositiveInteger | None = Field(None, description="at most this many modes")
    inner_product: InnerProduct = Field("euclidean", description="euclidean | volume")
    method: PODMethod = Field("snapshots", description="snapshots | svd")

    def config(self) -> PODConfig:
        """The POD settings."""
        return PODConfig(**{key: getattr(self, key) for key in type(self).model_fields})


class ANMTable(Table):
    """``[anm]``: POD-ANM series per position (see :class:`ANMConfig`)."""

    enabled: Boolean = Field(True, description="compute the series (needs an analytic energy)")
    order: ANMOrder = Field(6, description="series order")
    tolerance: ANMTolerance = Field(1e-4, description="validity radius tolerance")
    ranks_per_series: PositiveInteger = Field(
        1, description="ranks computing each sample's series together (at most all of them)"
    )

    def config(self) -> ANMConfig:
        """The ANM settings."""
        return ANMConfig(
            enabled=self.enabled,
            order=self.order,
            tolerance=self.tolerance,
            ranks_per_series=self.ranks_per_series,
        )


class CuttingTable(Table):
    """``[cutting]``: the cuttable region the artifact carries for the runtime's scalpel."""

    missing = {"centre": "centre = [x, y, z]", "radius": "radius (mm)"}
    centre: Vector = Field(description="mm: centre of the cuttable region")
    radius: Positive = Field(description="mm: the cells within it can be cut")
    patch_layers: PositiveInteger = Field(2, description="cell rings of the patch around a cut")
    cut_force: Positive = Field(0.02, description="N: blade force above which a face is cut")

    def config(self):
        """The :class:`CuttingConfig` of this table."""
        return CuttingConfig(
            centre=self.centre,
            radius=self.radius,
            patch_layers=self.patch_layers,
            cut_force=self.cut_force,
        )


class CampaignFile(Table):
    """A campaign file (``hapticrom campaign|train CONFIG``): its tables."""

    campaign: CampaignTable = CampaignTable()
    mesh: MeshTable
    material: MaterialTable
    discretisation: DiscretisationTable = DiscretisationTable()
    solver: SolverTable = SolverTable()
    load: CampaignLoadTable
    positions: PositionsTable
    pod: PODTable = PODTable()
    anm: ANMTable = Field(ANMTable(), validate_default=True)
    cutting: CuttingTable | None = None

    @field_validator("anm")
    @classmethod
    def _anm_needs_an_analytic_energy(cls, anm: ANMTable, info: ValidationInfo) -> ANMTable:
        """The series differentiate the energy: no switched-off fibres."""
        material, load = info.data.get("material"), info.data.get("load")
        if anm.enabled and load is not None and load.mode == "sphere":
            raise invalid(
                "the POD-ANM series need an analytic energy and the sphere's penalty contact "
                "switches on and off with the overlap: set [anm] enabled = false (the runtime "
                "then uses the stored full-order curves)"
            )
        if anm.enabled and material is not None:
            if material.params.get("fibre_tension_only") is True:
                raise invalid(
                    "the POD-ANM series need an analytic energy and fibre_tension_only = true "
                    "switches the fibres on and off: set [anm] enabled = false or "
                    "fibre_tension_only = false"
                )
        return anm

    def config(self, raw: dict, base_dir: Path, source: str) -> CampaignConfig:
        """The :class:`CampaignConfig` (``raw``: the data read, kept for the manifest)."""
        problem = ProblemConfig(
            mesh=self.mesh.config(base_dir),
            material=self.material.config(),
            load=LoadConfig(mode="force", force=(0.0, 0.0, 0.0)),  # unused: per position
            discretisation=self.discretisation.config(),
            solver=self.solver.config(),
            output=OutputConfig(xdmf=False),
        )
        return CampaignConfig(
            name=self.campaign.name or Path(source).stem,
            problem=problem,
            load=self.load.config(),
            positions=self.positions.spec,
            pod=self.pod.config(),
            anm=self.anm.config(),
            cutting=self.cutting.config() if self.cutting is not None else None,
            raw=raw,
        )
