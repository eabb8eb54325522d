"""The tool's contact patch on the organ surface, its load, reaction force and displacement.

A tool touches a surface group (``loadable``) at a point ``c`` with a rounded
tip of radius ``r`` (mm). Its patch is defined geometrically, so that it
converges under mesh refinement:

- force control: a dead traction with the smooth profile
  ``w(X) = (1 - |X - c|^2 / r^2)^2`` for ``|X - c| < r`` (0 outside), scaled so
  that it sums to the tool force exactly; the reported displacement is the
  work-conjugate mean ``int w u dA / int w dA``.
- displacement control (the haptic case): the boundary nodes of the group
  within ``r`` of ``c`` move rigidly with the tool (the nearest node alone if
  the mesh is too coarse for ``r``); the force comes from the residual.
- a whole surface group (the beam's end face): ``w = 1``.

Sign convention: ``force`` is the force the tool exerts on the tissue (N);
the tissue pushes back on the tool (and a haptic device renders) ``-force``.
"""

from __future__ import annotations

import dolfinx
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

from hapticrom.offline.fe.organ import OrganMesh
from hapticrom.shared.errors import InputError


def _facet_midpoints_and_radii(mesh: dolfinx.mesh.Mesh, facets: np.ndarray):
    """Midpoints (n,3) of facets and the radius of the sphere around each holding its vertices."""
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, 0)
    if facets.size == 0:
        return np.zeros((0, 3)), np.zeros(0)
    vertices = dolfinx.mesh.entities_to_geometry(mesh, fdim, facets)
    xyz = mesh.geometry.x[vertices]  # (n, nv, 3)
    mid = xyz.mean(axis=1)
    rad = np.linalg.norm(xyz - mid[:, None, :], axis=2).max(axis=1)
    return mid, rad


class ContactPatch:
    """Where a tool (or a surface load) acts: a group, a centre and a radius (mm).

    ``facets`` are the group's facets the load can reach (the whole group for a
    surface load, those meeting the disk of radius ``radius`` for a tool).
    """

    def __init__(self, organ: OrganMesh, group: str, point, radius: float | None, facets):
        self.organ, self.group = organ, group
        self.point = np.asarray(point, dtype=float)
        self.radius = radius
        self.facets = np.asarray(facets, dtype=np.int32)
        self.num_facets = organ.mesh.comm.allreduce(self.facets.size, op=MPI.SUM)

    @classmethod
    def around_point(
        cls, organ: OrganMesh, point, radius: float, group: str = "loadable"
    ) -> ContactPatch:
        """The facets of ``group`` within ``radius`` (mm) of ``point``."""
        comm = organ.mesh.comm
        point = np.asarray(point, dtype=float)
        candidates = organ.facets(group)
        mid, rad = _facet_midpoints_and_radii(organ.mesh, candidates)
        gap = np.linalg.norm(mid - point, axis=1) - rad  # < 0: inside a facet's bounding sphere
        nearest = comm.allreduce(float(gap.min()) if gap.size else np.inf, op=MPI.MIN)
        if nearest > radius:
            raise InputError(
                f"contact point {point.tolist()} mm is off the '{group}' surface of "
                f"{organ.path.name} (about {nearest:.3g} mm away; contact radius {radius} mm)"
            )
        return cls(organ, group, point, radius, candidates[gap <= radius])

    @classmethod
    def whole_group(cls, organ: OrganMesh, group: str) -> ContactPatch:
        """Every facet of ``group`` (a load spread over the whole surface group)."""
        facets = organ.facets(group)
        mid, _ = _facet_midpoints_and_radii(organ.mesh, facets)
        comm = organ.mesh.comm
        n = comm.allreduce(facets.size, op=MPI.SUM)
        centre = comm.allreduce(mid.sum(axis=0), op=MPI.SUM) / max(n, 1)
        return cls(organ, group, centre, None, facets)

    def weight(self):
        """UFL load profile w(X): 1 on a surface group, a C1 bump of radius r for a tool."""
        if getattr(self, "_weight", None) is None:
            self._weight = self._make_weight()
        return self._weight

    def _make_weight(self):
        if self.radius is None:
            return fem.Constant(self.organ.mesh, 1.0)
        X = ufl.SpatialCoordinate(self.organ.mesh)
        c = fem.Constant(self.organ.mesh, self.point)
        r = fem.Constant(self.organ.mesh, float(self.radius))
        s = ufl.dot(X - c, X - c) / r**2
        return ufl.conditional(ufl.lt(s, 1.0), (1 - s) ** 2, 0.0)

    def blocks(self, V: fem.FunctionSpace) -> np.ndarray:
        """Local block (node) indices of V that a rigid tool moves (owned and ghost)."""
        tdim = self.organ.mesh.topology.dim
        self.organ.mesh.topology.create_connectivity(tdim - 1, tdim)
        on_group = fem.locate_dofs_topological(V, tdim - 1, self.facets)
        if self.radius is None:
            return on_group
        x = V.tabulate_dof_coordinates()[on_group]
        dist = np.linalg.norm(x - self.point, axis=1)
        inside = on_group[dist <= self.radius]
        comm = self.organ.mesh.comm
        if comm.allreduce(inside.size, op=MPI.SUM) == 0:
            # The mesh is coarse for this radius: the tool holds the nearest node(s).
            best = comm.allreduce(float(dist.min()) if dist.size else np.inf, op=MPI.MIN)
            inside = on_group[np.abs(dist - best) <= 1e-9]
        return inside


class WeightedMean:
    """Work-conjugate mean displacement int w u dA / int w dA (mm) and int w dA (mm^2)."""

    def __init__(self, u: fem.Function, weight, ds_patch):
        comm = u.function_space.mesh.comm
        self._comm = comm
        self._forms = [fem.form(weight * u[i] * ds_patch) for i in range(3)]
        self.integral = comm.allreduce(fem.assemble_scalar(fem.form(weight * ds_patch)), MPI.SUM)
        if not self.integral > 0:
            raise InputError(
                "the contact patch carries no load on this mesh: increase contact_radius"
            )

    def __call__(self) -> np.ndarray:
        local = np.array([fem.assemble_scalar(f) for f in self._forms])
        return self._comm.allreduce(local, op=MPI.SUM) / self.integral


class NodalMean:
    """Mean displacement (mm) of the nodes a rigid tool moves (each node counted once)."""

    def __init__(self, u: fem.Function, blocks: np.ndarray):
        V = u.function_space
        self._u = u
        self._blocks = blocks[blocks < V.dofmap.index_map.size_local]
        self._comm = V.mesh.comm
        self.count = self._comm.allreduce(self._blocks.size, op=MPI.SUM)

    def __call__(self) -> np.ndarray:
        local = self._u.x.array.reshape(-1, 3)[self._blocks].sum(axis=0)
        return self._comm.allreduce(local, op=MPI.SUM) / max(self.count, 1)


class ReactionForce:
    """Force (N) the tool exerts on the tissue through prescribed patch DOFs.

    It equals the sum over the patch DOFs of the internal force vector
    dPi_int/du, assembled from the same UFL residual as the Newton solve (no
    external load acts on a displacement-controlled patch).
    """

    def __init__(self, residual_u, V: fem.FunctionSpace, patch_blocks: np.ndarray):
        self._form = fem.form(residual_u) if isinstance(residual_u, ufl.Form) else residual_u
        self._vec = fem.Function(V).x  # a la.Vector with V's layout, reused every call
        size_local = V.dofmap.index_map.size_local
        self._blocks = patch_blocks[patch_blocks < size_local]  # owned only: no double count
        self._comm = V.mesh.comm

    def __call__(self) -> np.ndarray:
        vec = self._vec
        vec.array[:] = 0.0
        fem.assemble_vector(vec.array, self._form)
        vec.scatter_reverse(dolfinx.la.InsertMode.add)
        local = vec.array.reshape(-1, 3)[self._blocks].sum(axis=0)
        return self._comm.allreduce(local, op=MPI.SUM)
