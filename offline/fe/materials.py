"""Hyperelastic material laws as UFL strain energies (units: MPa, i.e. mJ/mm^3).

Each law is a small frozen dataclass holding its parameters (validated on
construction) and returning a UFL strain-energy density ``Psi(F)``. Stresses
and tangents are never written by hand: the solver differentiates ``Psi`` with
``ufl.derivative`` and tests with ``ufl.diff``. Energies are analytic
expressions (no ``ufl.inner``, ``abs`` or conjugates): the ANM evaluates them
at complex deformations (:mod:`hapticrom.offline.reduce.anm`).

Parameters enter the UFL expressions through a mapping ``c`` (name -> UFL
value). The solver passes ``dolfinx.fem.Constant`` objects so that a new
parameter value does not recompile the kernels; tests may pass floats.

Every law splits its energy as ``Psi = Psi_rest(F) + kappa/2 * theta(F)**2``
(:class:`EnergySplit`) with a scalar volumetric strain ``theta`` and a bulk
modulus ``kappa``. The mixed displacement-pressure formulation
(:mod:`hapticrom.offline.fe.formulation`) replaces the volumetric term by
``p*theta - p**2/(2*kappa)``, which gives back ``kappa/2*theta**2`` when the
pressure ``p`` is eliminated; that is how nearly incompressible tissue avoids
volumetric locking on linear elements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar, NamedTuple

import ufl

from hapticrom.shared.errors import InputError


class EnergySplit(NamedTuple):
    """``Psi = rest + kappa/2 * theta**2`` (all UFL expressions, MPa)."""

    rest: Any
    theta: Any
    kappa: Any


def _kinematics(F):
    """Right Cauchy-Green tensor C = F^T F and volume ratio J = det F."""
    C = F.T * F
    J = ufl.det(F)
    return C, J


def _lame(E: Any, nu: Any) -> tuple[Any, Any]:
    """Lame constants (lambda, mu) in MPa from Young's modulus E (MPa) and Poisson's ratio."""
    mu = E / (2 * (1 + nu))
    lmbda = E * nu / ((1 + nu) * (1 - 2 * nu))
    return lmbda, mu


@dataclass(frozen=True)
class MaterialLaw:
    """Base class: parameter bookkeeping and validation shared by all laws."""

    name: ClassVar[str] = ""
    requires_fibres: ClassVar[bool] = False

    def parameters(self) -> dict[str, float]:
        """Numeric parameters (MPa or dimensionless) by name, for ``fem.Constant``s."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self) if f.type == "float"}

    def energy_split(self, F, c, fibres=None) -> EnergySplit:  # pragma: no cover - abstract
        """The energy's volumetric and isochoric/fibre parts at F (UFL)."""
        raise NotImplementedError

    def strain_energy(self, F, c=None, fibres=None):
        """Strain-energy density Psi(F) in MPa (mJ/mm^3)."""
        split = self.energy_split(F, self._constants(c), fibres)
        return split.rest + split.kappa / 2 * split.theta**2

    def _constants(self, c):
        return self.parameters() if c is None else c

    def _require(self, condition: bool, message: str) -> None:
        if not condition:
            raise InputError(f"material '{self.name}': {message}")


@dataclass(frozen=True)
class IsotropicLaw(MaterialLaw):
    """An isotropic law given by Young's modulus E (MPa) and Poisson's ratio nu."""

    E: float
    nu: float

    def __post_init__(self):
        self._require(self.E > 0, f"E must be positive (got {self.E} MPa)")
        self._require(-1 < self.nu < 0.5, f"nu must lie in (-1, 0.5) (got {self.nu})")


@dataclass(frozen=True)
class SaintVenantKirchhoff(IsotropicLaw):
    """Saint Venant-Kirchhoff: Psi = lambda/2 (tr E)^2 + mu E:E (thesis eq. 3.9).

    Volumetric strain theta = tr E, bulk-like modulus kappa = lambda.
    """

    name: ClassVar[str] = "svk"

    def energy_split(self, F, c, fibres=None) -> EnergySplit:
        """The energy's volumetric and isochoric/fibre parts at F (UFL)."""
        c = self._constants(c)
        lmbda, mu = _lame(c["E"], c["nu"])
        C, _ = _kinematics(F)
        Egl = (C - ufl.Identity(3)) / 2
        # E:E as tr(E E) (E is symmetric): ufl.inner conjugates its second argument in complex
        # mode, which would break the analytic continuation the ANM relies on.
        return EnergySplit(rest=mu * ufl.tr(Egl * Egl), theta=ufl.tr(Egl), kappa=lmbda)


@dataclass(frozen=True)
class NeoHookean(IsotropicLaw):
    """Compressible neo-Hookean (thesis eq. 3.30).

    Psi = mu/2 (tr C - 3) - mu ln J + lambda/2 (ln J)^2, with the Lame constants
    from E (MPa) and nu. Volumetric strain theta = ln J, kappa = lambda.
    """

    name: ClassVar[str] = "neo-hookean"

    def energy_split(self, F, c, fibres=None) -> EnergySplit:
        """The energy's volumetric and isochoric/fibre parts at F (UFL)."""
        c = self._constants(c)
        lmbda, mu = _lame(c["E"], c["nu"])
        C, J = _kinematics(F)
        lnJ = ufl.ln(J)
        rest = mu / 2 * (ufl.tr(C) - 3) - mu * lnJ
        return EnergySplit(rest=rest, theta=lnJ, kappa=lmbda)


@dataclass(frozen=True)
class HolzapfelGasser(MaterialLaw):
    """Holzapfel-Gasser two-fibre law for the cornea (thesis eqs. 2.14-2.20, Table 2.1).

    Psi = (1/D) (ln J)^2 + C1/2 (I1b - 3) + C2/2 (I2b - 3)
          + k1/(2 k2) {exp[k2 (I4b - 1)^2] - 1} + k3/(2 k4) {exp[k4 (I6b - 1)^2] - 1}

    with the invariants of the isochoric Cb = J^(-2/3) C, I4b = m0.Cb m0 and
    I6b = n0.Cb n0 for the two collagen families m0, n0 (unit vectors, reference
    configuration). C1, C2, k1, k3 and 1/D in MPa; k2, k4 dimensionless.

    ``fibre_tension_only=False`` (the default) keeps the law as the thesis wrote
    and computed it: fibres resist compression too, and the energy is smooth
    (what the asymptotic expansions of the ANM need). ``True`` switches a family
    off while it is not stretched (I4b <= 1), the usual choice for collagen.
    Volumetric strain theta = ln J, kappa = 2/D.
    """

    C1: float = 0.1
    D: float = 1e-5
    C2: float = 0.0
    k1: float = 0.234
    k2: float = 29.917
    k3: float = 0.234
    k4: float = 29.917
    fibre_tension_only: bool = False

    name: ClassVar[str] = "hgo"
    requires_fibres: ClassVar[bool] = True

    def __post_init__(self):
        self._require(self.C1 > 0, f"C1 must be positive (got {self.C1} MPa)")
        self._require(self.D > 0, f"D must be positive (got {self.D} 1/MPa)")
        self._require(self.C2 >= 0, f"C2 must not be negative (got {self.C2} MPa)")
        for k in ("k1", "k3"):
            self._require(getattr(self, k) >= 0, f"{k} must not be negative")
        for k in ("k2", "k4"):
            self._require(getattr(self, k) > 0, f"{k} must be positive")

    def energy_split(self, F, c, fibres=None) -> EnergySplit:
        """The energy's volumetric and isochoric/fibre parts at F (UFL)."""
        if fibres is None:
            raise InputError("material 'hgo' needs the fibre fields m0, n0 of the mesh")
        c = self._constants(c)
        m0, n0 = fibres
        C, J = _kinematics(F)
        Cb = J ** (-2.0 / 3.0) * C
        I1b = ufl.tr(Cb)
        I2b = (I1b**2 - ufl.tr(Cb * Cb)) / 2
        I4b = ufl.dot(m0, Cb * m0)
        I6b = ufl.dot(n0, Cb * n0)
        rest = c["C1"] / 2 * (I1b - 3) + c["C2"] / 2 * (I2b - 3)
        rest += self._fibre(I4b, c["k1"], c["k2"]) + self._fibre(I6b, c["k3"], c["k4"])
        return EnergySplit(rest=rest, theta=ufl.ln(J), kappa=2 / c["D"])

    def _fibre(self, I, k_stiff, k_exp):
        energy = k_stiff / (2 * k_exp) * (ufl.exp(k_exp * (I - 1) ** 2) - 1)
        if self.fibre_tension_only:
            # C1-continuous at I = 1 since the energy and its slope both vanish there.
            return ufl.conditional(ufl.gt(I, 1), energy, 0)
        return energy


LAWS: dict[str, type[MaterialLaw]] = {
    law.name: law for law in (SaintVenantKirchhoff, NeoHookean, HolzapfelGasser)
}
ALIASES = {
    "neohookean": "neo-hookean",
    "neo_hookean": "neo-hookean",
    "saint-venant-kirchhoff": "svk",
}


def _finite(v: int | float) -> bool:
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer beyond float range (TOML integers are unbounded)
        return False


def make_law(name: str, **params) -> MaterialLaw:
    """Build a law from its name and parameters; a clear InputError on anything unknown."""
    key = ALIASES.get(name.lower(), name.lower())
    if key not in LAWS:
        raise InputError(f"unknown material '{name}'; choose one of {', '.join(sorted(LAWS))}")
    cls = LAWS[key]
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise InputError(
            f"material '{key}' has no parameter {', '.join(unknown)}; "
            f"its parameters are {', '.join(sorted(known))}"
        )
    for k, v in params.items():
        if k == "fibre_tension_only":
            if not isinstance(v, bool):
                raise InputError(f"material '{key}': fibre_tension_only must be true or false")
            continue
        if isinstance(v, bool) or not (isinstance(v, int | float) and _finite(v)):
            raise InputError(f"material '{key}': parameter {k} must be a finite number, got {v!r}")
    try:
        return cls(**params)
    except TypeError as exc:  # a required parameter is missing
        raise InputError(f"material '{key}': {exc}") from None
