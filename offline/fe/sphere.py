"""A rigid, frictionless sphere pressed into the organ, by a penalty (mm, N, MPa).

The sphere of radius R centred at c (a :class:`dolfinx.fem.Constant` the load
factor moves) overlaps the deformed surface point x = X + u by <R - |x - c|>. The
contact energy over the surface group

    Pi_c = int (kappa / 3) <R - |x - c|>^3 dA

adds to the body's potential energy: its first variation is a contact pressure
kappa <R - |x - c|>^2 along (x - c) / |x - c| (normal to the sphere: no friction),
its second variation the contact tangent, both by UFL differentiation. The
overlap it leaves is sqrt(p / kappa) for a pressure p: with kappa = 1e4 N/mm^4 and
p = 0.05 MPa, 2 um. As kappa grows the force converges to the rigid sphere's, with
an error of order kappa^(-1/2) (the overlap against the depth); ``bench/
position_accuracy.py`` shows it. The integrand has a kink at the contact's edge: the
surface quadrature is raised (degree + 6).

The force the sphere exerts on the tissue is the pressure's integral (N); the tool
feels its opposite.
"""

from __future__ import annotations

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI


class SphereIndenter:
    """The sphere's contact with surface group ``group`` of ``model`` (a
    :class:`~hapticrom.offline.fe.formulation.HyperelasticModel`): radius (mm), start
    centre (mm), penalty kappa (N/mm^4). ``energy`` is the UFL form to add to the
    potential energy; :meth:`move` sets the centre, :meth:`force` integrates the
    pressure."""

    def __init__(self, model, radius: float, centre, penalty: float, group: str = "loadable"):
        organ = model.organ
        mesh = organ.mesh
        self.radius, self.penalty = float(radius), float(penalty)
        self.start = np.asarray(centre, dtype=float)
        self.centre = fem.Constant(mesh, self.start.copy())
        # A form takes one facet tagging: the model's load region is the group (with no
        # dead load on it), and the sphere integrates over it.
        model.set_load_region(organ.facets(group), fem.Constant(mesh, 0.0))
        ds = model.ds(model.LOAD_TAG, metadata={"quadrature_degree": model.quadrature_degree + 6})
        x = ufl.SpatialCoordinate(mesh) + model.u
        d = x - self.centre
        distance = ufl.sqrt(ufl.dot(d, d))
        overlap = ufl.conditional(ufl.lt(distance, self.radius), self.radius - distance, 0.0)
        kappa = fem.Constant(mesh, self.penalty)
        self.energy = kappa / 3.0 * overlap**3 * ds
        pressure = kappa * overlap**2
        self._force = [fem.form(pressure * d[i] / distance * ds) for i in range(3)]
        self._overlap = fem.form(ufl.conditional(ufl.gt(overlap, 0.0), 1.0, 0.0) * ds)
        self._comm = mesh.comm

    def move(self, centre) -> None:
        """Put the sphere's centre at ``centre`` (mm)."""
        self.centre.value[:] = np.asarray(centre, dtype=float)

    def force(self) -> np.ndarray:
        """The force the sphere exerts on the tissue (N): the contact pressure's integral."""
        local = np.array([fem.assemble_scalar(f) for f in self._force])
        return self._comm.allreduce(local, op=MPI.SUM)

    def contact_area(self) -> float:
        """The reference area (mm^2) where the sphere overlaps the surface."""
        return self._comm.allreduce(fem.assemble_scalar(self._overlap), op=MPI.SUM)
