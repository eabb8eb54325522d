"""An organ mesh in DOLFINx: cells, named surface groups, supports and fibre fields (mm).

A mesh on disk is a gmsh ``.msh`` file with physical groups ``tissue``
(cells) and ``clamped`` / ``loadable`` / ``free`` (boundary faces), plus a
JSON sidecar that says how the organ is held and where its fibres run (see
``meshes/README.md``). :func:`load_organ` reads both on rank 0 and
distributes the mesh over the communicator.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import dolfinx
import numpy as np
from dolfinx import fem
from dolfinx.io import gmsh as gmshio
from mpi4py import MPI

from hapticrom.meshes.fibres import fibre_directions
from hapticrom.meshes.msh import gmsh_model, read_sidecar
from hapticrom.offline.mpi import on_rank_zero
from hapticrom.shared.errors import InputError

COMPONENTS = {"x": 0, "y": 1, "z": 2}
POINT_TOLERANCE = 1e-6  # mm: a point support must coincide with a mesh vertex


@dataclass
class OrganMesh:
    """A distributed organ mesh and what the sidecar says about it."""

    mesh: dolfinx.mesh.Mesh
    facet_tags: dolfinx.mesh.MeshTags
    groups: dict[str, int]  # surface group name -> facet tag
    info: dict  # the JSON sidecar
    path: Path

    @property
    def cell_type(self) -> str:
        """DOLFINx's name of the cell type (hexahedron, tetrahedron)."""
        return self.mesh.topology.cell_type.name

    def facets(self, group: str) -> np.ndarray:
        """Local indices of the boundary facets of a named surface group."""
        if group not in self.groups:
            raise InputError(
                f"mesh {self.path.name} has no surface group '{group}'; "
                f"it has {', '.join(sorted(self.groups))}"
            )
        return self.facet_tags.find(self.groups[group])

    def default_contact_point(self) -> np.ndarray:
        """The mesh's default tool position (mm), from its sidecar."""
        return np.asarray(self.info["default_contact_point"], dtype=float)

    def fibre_fields(self) -> tuple[fem.Function, fem.Function]:
        """The two collagen families m0, n0 as cell-wise constant unit vector fields."""
        spec = self.info.get("fibres")
        if not spec:
            raise InputError(f"mesh {self.path.name} has no fibre field (needed by the HGO law)")
        V = fem.functionspace(self.mesh, ("DG", 0, (3,)))
        m0, n0 = fem.Function(V, name="fibre_m0"), fem.Function(V, name="fibre_n0")
        m0.interpolate(lambda x: fibre_directions(spec, x.T)[0].T)
        n0.interpolate(lambda x: fibre_directions(spec, x.T)[1].T)
        return m0, n0

    def supports(self, V: fem.FunctionSpace) -> list[fem.DirichletBC]:
        """Zero-displacement conditions on the displacement space V from the sidecar."""
        mesh, tdim = self.mesh, self.mesh.topology.dim
        bcs = []
        for spec in self.info.get("supports", []):
            comps = [COMPONENTS[c] for c in spec["components"]]
            if "group" in spec:
                dim, entities = tdim - 1, self.facets(spec["group"])
            else:
                point = np.asarray(spec["point"], dtype=float)
                dim = 0
                entities = dolfinx.mesh.locate_entities(
                    mesh, 0, lambda x, p=point: np.linalg.norm(x.T - p, axis=1) < POINT_TOLERANCE
                )
                found = mesh.comm.allreduce(len(entities), op=MPI.SUM)
                if found == 0:
                    raise InputError(
                        f"mesh {self.path.name}: no vertex at support point {spec['point']}"
                    )
            mesh.topology.create_connectivity(dim, tdim)
            for c in comps:
                dofs = fem.locate_dofs_topological(V.sub(c), dim, entities)
                bcs.append(fem.dirichletbc(0.0, dofs, V.sub(c)))
        return bcs

    def constrained_blocks(self, V: fem.FunctionSpace) -> np.ndarray:
        """Local block (node) indices of V touched by any support, any component."""
        mesh, tdim = self.mesh, self.mesh.topology.dim
        blocks = [np.empty(0, dtype=np.int32)]
        for spec in self.info.get("supports", []):
            if "group" in spec:
                mesh.topology.create_connectivity(tdim - 1, tdim)
                blocks.append(fem.locate_dofs_topological(V, tdim - 1, self.facets(spec["group"])))
        return np.unique(np.concatenate(blocks))


def _read_on_rank_zero(path: Path) -> dict:
    if not path.is_file():
        raise InputError(
            f"mesh file {path} not found; generate it with "
            f"`hapticrom mesh NAME --out {path}` (NAME: cornea, beam, hemisphere, liver)"
        )
    return read_sidecar(path)


def load_organ(path: str | Path, comm: MPI.Comm = MPI.COMM_WORLD) -> OrganMesh:
    """Read ``path`` (.msh) and its sidecar on rank 0, distribute the mesh over ``comm``."""
    path = Path(path)
    info = on_rank_zero(comm, _read_on_rank_zero, path)

    if comm.rank == 0:
        import gmsh

        with gmsh_model(f"hapticrom-read-{path.stem}", {"General.Terminal": 0}):
            error = None
            try:
                gmsh.merge(str(path))
            except Exception as exc:  # noqa: BLE001 - reported on every rank below
                error = InputError(f"mesh file {path} cannot be read by gmsh: {exc}")
            comm.bcast(error, root=0)
            if error is not None:
                raise error
            data = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    else:
        error = comm.bcast(None, root=0)
        if error is not None:
            raise error
        data = gmshio.model_to_mesh(None, comm, 0, gdim=3)

    groups = {name: g.tag for name, g in data.physical_groups.items() if g.dim == 2}
    for required in ("clamped", "loadable"):
        if required not in groups:
            raise InputError(f"mesh {path.name} lacks the surface group '{required}'")
    return OrganMesh(
        mesh=data.mesh, facet_tags=data.facet_tags, groups=groups, info=info, path=path
    )
