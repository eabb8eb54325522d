"""Results of a full-order solve on disk: ``curve.csv``, and fields for ParaView (XDMF, VTX).

``curve.csv`` (written by rank 0, one row per converged increment, flushed at
once so a crash loses nothing already computed):

    step, load_factor, force_x, force_y, force_z, disp_x, disp_y, disp_z,
    newton_iterations, step_cuts, seconds

``force_*``: force the tool exerts on the tissue (N); ``disp_*``: area-mean
displacement of the contact patch (mm).

The fields, at every increment with the load factor as time, in two forms:

- ``fields.xdmf`` (+ ``.h5``): the displacement (mm), for mixed elements the pressure
  (MPa), and the fibre directions. XDMF holds fields at the mesh's geometric degree
  only, so a quadratic (P2, Q2) displacement is interpolated down to its vertices.
- ``fields-displacement.bp``, ``fields-pressure.bp``, ``fields-fibres.bp``: ADIOS2 VTX
  (``dolfinx.io.VTXWriter``), each field at its own degree: a quadratic displacement
  keeps its edge (and face, cell) nodes, a DG0 pressure stays cell-wise. VTX puts one
  element per file, hence one file per field. ParaView opens a ``.bp`` folder with its
  ADIOS2VTXReader (ParaView 5.10 or newer).
"""

from __future__ import annotations

import csv
from pathlib import Path

from dolfinx import fem, io
from mpi4py import MPI

from hapticrom.offline.fe.solver import StepRecord

CURVE_COLUMNS = [
    "step",
    "load_factor",
    "force_x",
    "force_y",
    "force_z",
    "disp_x",
    "disp_y",
    "disp_z",
    "newton_iterations",
    "step_cuts",
    "seconds",
]
CURVE_UNITS = "# units: force N (tool on tissue), disp mm (contact patch mean), seconds s"


class CurveWriter:
    """Appends one row per converged increment to ``curve.csv`` on rank 0."""

    def __init__(self, path: Path, comm: MPI.Comm):
        self.path, self.comm = Path(path), comm
        self._file = None
        if comm.rank == 0:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "w", newline="")  # noqa: SIM115 - closed in close()
            self._writer = csv.writer(self._file)
            self._writer.writerow(CURVE_COLUMNS)
            self._file.flush()

    def write(self, record: StepRecord, force, disp) -> None:
        """Append the row of a converged increment (force N, disp mm) and flush it."""
        if self._file is None:
            return
        row = [record.step, f"{record.load_factor:.10g}"]
        row += [f"{v:.10e}" for v in (*force, *disp)]
        row += [record.newton_iterations, record.step_cuts, f"{record.seconds:.4f}"]
        self._writer.writerow(row)
        self._file.flush()

    def close(self) -> None:
        """Close the file (rank 0; a no-op elsewhere)."""
        if self._file is not None:
            self._file.close()
            self._file = None


class FieldWriter:
    """Time series of the solution fields: XDMF (at the mesh's degree) and VTX (each
    field at its own degree) next to each other, named after ``path`` (``fields.xdmf``
    gives ``fields-displacement.bp`` ...); ``vtx=False`` writes the XDMF only."""

    def __init__(
        self, path: Path, u: fem.Function, p: fem.Function | None, fibres=None, vtx: bool = True
    ):
        path = Path(path)
        mesh = u.function_space.mesh
        self._xdmf = io.XDMFFile(mesh.comm, str(path), "w")
        self._xdmf.write_mesh(mesh)
        self._u, self._p = u, p
        degree = mesh.geometry.cmaps[0].degree
        self._u_out = u
        if u.function_space.element.basix_element.degree != degree:
            V1 = fem.functionspace(mesh, ("Lagrange", degree, (3,)))
            self._u_out = fem.Function(V1, name=u.name)
        self._p_out = p
        if p is not None and p.function_space.element.basix_element.degree not in (0, degree):
            self._p_out = fem.Function(fem.functionspace(mesh, ("Lagrange", degree)), name=p.name)
        if fibres is not None:
            for f in fibres:
                self._xdmf.write_function(f, 0.0)
        self._vtx = []
        if vtx:
            self._vtx = self._open_vtx(path, [u] if p is None else [u, p], fibres)

    @staticmethod
    def _open_vtx(path: Path, fields: list, fibres) -> list:
        """One VTX writer per field (``<stem>-<name>.bp``); the fibres written at once."""
        comm = fields[0].function_space.mesh.comm

        def writer(name: str, functions: list):
            # The mesh never moves (displacement is a field): write it once, not per step.
            return io.VTXWriter(
                comm, path.with_name(f"{path.stem}-{name}.bp"), functions,
                mesh_policy=io.VTXMeshPolicy.reuse,
            )  # fmt: skip

        if fibres is not None:
            with writer("fibres", list(fibres)) as w:
                w.write(0.0)
        return [writer(f.name, [f]) for f in fields]

    def write(self, t: float) -> None:
        """Write every field at time ``t`` (the load factor)."""
        if self._u_out is not self._u:
            self._u_out.interpolate(self._u)
        self._xdmf.write_function(self._u_out, t)
        if self._p is not None:
            if self._p_out is not self._p:
                self._p_out.interpolate(self._p)
            self._xdmf.write_function(self._p_out, t)
        for w in self._vtx:
            w.write(t)

    def close(self) -> None:
        """Close every file (collective: every rank calls it)."""
        self._xdmf.close()
        for w in self._vtx:
            w.close()
        self._vtx = []
