"""Finite-element spaces and the (mixed) hyperelastic energy of an organ (mm, N, MPa).

The total potential energy of the tissue under a dead surface traction t is

    Pi(u, p) = int_Omega Psi_mix(F, p) dX - int_Gamma_t t . u dA,
    Psi_mix  = Psi_rest(F) + p theta(F) - p^2 / (2 kappa)

(see :class:`~hapticrom.offline.fe.materials.EnergySplit`). With a pressure
space (``Q1P0``, ``P2P0``, ``Q2Q1``, ...) ``p`` is an unknown and the
volumetric constraint is enforced weakly, which removes volumetric locking of
nearly incompressible tissue; eliminating ``p`` gives back Psi exactly. With a
displacement-only element (``Q1``, ``P1``, ...) Psi itself is used.

Residuals and Jacobians are the UFL derivatives of Pi; nothing is hand-coded.
Material parameters and loads are ``fem.Constant`` objects, so changing them
never recompiles a kernel. Quadrature degrees are always explicit (UFL would
otherwise estimate absurd degrees for the exponential fibre terms).
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx
import numpy as np
import ufl
from dolfinx import fem
from petsc4py import PETSc

from hapticrom.offline.fe.materials import MaterialLaw
from hapticrom.offline.fe.organ import OrganMesh
from hapticrom.shared.errors import InputError


@dataclass(frozen=True)
class Element:
    """A displacement-pressure element pair."""

    name: str
    displacement_degree: int
    pressure: str | None  # None (displacement only), "DG0" or "CG1"

    @property
    def mixed(self) -> bool:
        """Whether the element carries a pressure field."""
        return self.pressure is not None

    def default_quadrature_degree(self) -> int:
        """Quadrature degree that integrates the element's energy well."""
        # 2x2x2 Gauss for trilinear hexahedra, 3x3x3 for triquadratic; degree 4 for P2 tets.
        return 2 * self.displacement_degree


ELEMENTS: dict[str, dict[str, Element]] = {
    "hexahedron": {
        e.name: e
        for e in (
            Element("Q1", 1, None),
            Element("Q1P0", 1, "DG0"),
            Element("Q2", 2, None),
            Element("Q2P0", 2, "DG0"),
            Element("Q2Q1", 2, "CG1"),
        )
    },
    "tetrahedron": {
        e.name: e
        for e in (
            Element("P1", 1, None),
            Element("P2", 2, None),
            Element("P2P0", 2, "DG0"),
            Element("P2P1", 2, "CG1"),
        )
    },
}
DEFAULT_ELEMENT = {"hexahedron": "Q1P0", "tetrahedron": "P2P0"}


def choose_element(cell_type: str, name: str) -> Element:
    """The element named ``name`` for ``cell_type`` (InputError if unknown or mismatched)."""
    if cell_type not in ELEMENTS:
        raise InputError(f"unsupported cell type {cell_type}; use hexahedra or tetrahedra")
    if name == "auto":
        name = DEFAULT_ELEMENT[cell_type]
    if name not in ELEMENTS[cell_type]:
        raise InputError(
            f"element {name!r} is not available on {cell_type} meshes; "
            f"choose auto or one of {', '.join(ELEMENTS[cell_type])}"
        )
    return ELEMENTS[cell_type][name]


def mixed_energy_density(law: MaterialLaw, F, p, constants, fibres):
    """Psi_mix(F, p) = rest + p theta - p^2/(2 kappa) (MPa); Psi(F) itself when p is None.

    Shared by the real forms of :class:`HyperelasticModel` and the complex forms
    of the ANM (:mod:`hapticrom.offline.reduce.anm`), so both differentiate one energy.
    """
    split = law.energy_split(F, constants, fibres)
    if p is None:
        return split.rest + split.kappa / 2 * split.theta**2
    return split.rest + p * split.theta - p**2 / (2 * split.kappa)


class HyperelasticModel:
    """Unknowns, constants and UFL forms of one organ + one material law + one element.

    Attributes:
        u: displacement (mm), vector Lagrange of the element's degree.
        p: pressure-like multiplier (MPa) or None for displacement-only elements.
        unknowns: [u] or [u, p], the SNES unknowns in block order.
        constants: material parameters by name (fem.Constant, MPa).
        traction: dead surface traction on the loaded facets (fem.Constant, MPa).
        load_tag: facet marker used by ``ds(load_tag)`` for the loaded facets.
    """

    LOAD_TAG = 1

    def __init__(
        self,
        organ: OrganMesh,
        law: MaterialLaw,
        element: Element,
        quadrature_degree: int | None = None,
    ):
        mesh = organ.mesh
        self.organ, self.law, self.element = organ, law, element
        self.quadrature_degree = quadrature_degree or element.default_quadrature_degree()

        self.V = fem.functionspace(mesh, ("Lagrange", element.displacement_degree, (3,)))
        self.u = fem.Function(self.V, name="displacement")
        self.unknowns = [self.u]
        self.Q = self.p = None
        if element.mixed:
            family, degree = {"DG0": ("DG", 0), "CG1": ("Lagrange", 1)}[element.pressure]
            self.Q = fem.functionspace(mesh, (family, degree))
            self.p = fem.Function(self.Q, name="pressure")
            self.unknowns.append(self.p)

        self.constants = {
            k: fem.Constant(mesh, PETSc.ScalarType(v)) for k, v in law.parameters().items()
        }
        self.fibres = organ.fibre_fields() if law.requires_fibres else None
        self.traction = fem.Constant(mesh, np.zeros(3, dtype=PETSc.ScalarType))
        self.load_weight = fem.Constant(mesh, 0.0)
        self.dx = ufl.Measure(
            "dx", domain=mesh, metadata={"quadrature_degree": self.quadrature_degree}
        )
        self.set_load_region(np.empty(0, dtype=np.int32), self.load_weight)
        self.contact_energies = []  # e.g. a rigid sphere's penalty (:mod:`.sphere`)
        self.further_loads = []  # (traction, weight) of further tools on the load region

    # -- loads -----------------------------------------------------------------
    def set_load_region(self, facets: np.ndarray, weight) -> None:
        """The dead load is ``traction * weight(X)`` on ``facets``; call before building forms.

        The load integrals use a higher quadrature degree than the volume: the
        weight of a tool is a quartic bump with a cut-off at its radius.
        """
        fdim = self.organ.mesh.topology.dim - 1
        facets = np.unique(np.asarray(facets, dtype=np.int32))
        tags = dolfinx.mesh.meshtags(
            self.organ.mesh, fdim, facets, np.full(facets.size, self.LOAD_TAG, dtype=np.int32)
        )
        self.load_weight = weight
        self.ds = ufl.Measure(
            "ds",
            domain=self.organ.mesh,
            subdomain_data=tags,
            metadata={"quadrature_degree": self.quadrature_degree + 4},
        )

    # -- energy and its derivatives --------------------------------------------
    def deformation_gradient(self):
        """F = I + grad u."""
        return ufl.Identity(3) + ufl.grad(self.u)

    def strain_energy_density(self):
        """Psi_mix(F, p) of the element (Psi itself for displacement-only elements), MPa."""
        return mixed_energy_density(
            self.law, self.deformation_gradient(), self.p, self.constants, self.fibres
        )

    def internal_energy(self):
        """Strain energy of the body (mJ = N mm)."""
        return self.strain_energy_density() * self.dx

    def external_work(self):
        """Work of the tool's dead load on the loaded surface (mJ)."""
        work = ufl.dot(self.traction, self.u) * self.load_weight * self.ds(self.LOAD_TAG)
        for traction, weight in self.further_loads:  # each weight vanishes off its own disk
            work = work + ufl.dot(traction, self.u) * weight * self.ds(self.LOAD_TAG)
        return work

    def potential_energy(self):
        """Total potential energy Pi = internal energy - external work (+ contact) (mJ)."""
        energy = self.internal_energy() - self.external_work()
        for contact in self.contact_energies:
            energy = energy + contact
        return energy

    def residual_forms(self, include_load: bool = True) -> list:
        """[dPi/du . v, dPi/dp . q] (or the first alone): N, and mm^3 for the pressure rows."""
        Pi = self.potential_energy() if include_load else self.internal_energy()
        return [ufl.derivative(Pi, w, ufl.TestFunction(w.function_space)) for w in self.unknowns]

    def jacobian_forms(self, residuals: list) -> list[list]:
        """The block Jacobian of ``residuals`` by UFL differentiation."""
        return [
            [ufl.derivative(R, w, ufl.TrialFunction(w.function_space)) for w in self.unknowns]
            for R in residuals
        ]

    # -- sizes -----------------------------------------------------------------
    def num_dofs(self) -> dict[str, int]:
        """Global numbers of unknowns: displacement DOFs (3 per node) and pressure DOFs."""
        im = self.V.dofmap.index_map
        counts = {"displacement": im.size_global * self.V.dofmap.index_map_bs, "pressure": 0}
        if self.Q is not None:
            counts["pressure"] = self.Q.dofmap.index_map.size_global
        return counts
