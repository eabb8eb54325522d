"""Beam in traction (thesis §3.4.1) against the analytic homogeneous uniaxial solution.

A 400 x 40 x 40 mm beam (E = 1 MPa, nu = 0.25), held axially at x = 0 with
just enough pins to remove rigid motion, carries a dead traction of 0.25 MPa
(400 N) on its end face at load factor 1. The exact solution is homogeneous:
F = diag(l1, l2, l2) with P11 = traction and P22 = P33 = 0, which trilinear
elements represent exactly, so the FE stretch must match to solver tolerance.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest

from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.fullorder import FullOrderModel

pytestmark = pytest.mark.serial

E, NU, TRACTION, LENGTH = 1.0, 0.25, 0.25, 400.0
MU, LAMBDA = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))


def uniaxial_stress(law: str, l1: float, l2: float) -> tuple[float, float]:
    """First Piola-Kirchhoff P11, P22 (MPa) of F = diag(l1, l2, l2), written out by hand."""
    if law == "svk":
        E1, E2 = (l1**2 - 1) / 2, (l2**2 - 1) / 2
        trE = E1 + 2 * E2
        return l1 * (LAMBDA * trE + 2 * MU * E1), l2 * (LAMBDA * trE + 2 * MU * E2)
    lnJ = np.log(l1 * l2**2)
    return (MU * (l1 - 1 / l1) + LAMBDA * lnJ / l1, MU * (l2 - 1 / l2) + LAMBDA * lnJ / l2)


def analytic_stretches(law: str, traction: float) -> tuple[float, float]:
    """Solve P11 = traction, P22 = 0 for (l1, l2) by Newton with a difference Jacobian."""
    x = np.array([1.0, 1.0])
    for _ in range(50):
        r = np.array(uniaxial_stress(law, *x)) - [traction, 0.0]
        if np.abs(r).max() < 1e-15:
            break
        h = 1e-7
        Jac = np.column_stack(
            [(np.array(uniaxial_stress(law, *(x + h * e))) - r - [traction, 0.0]) / h
             for e in np.eye(2)]
        )  # fmt: skip
        x = x - np.linalg.solve(Jac, r)
    assert np.abs(np.array(uniaxial_stress(law, *x)) - [traction, 0.0]).max() < 1e-12
    return float(x[0]), float(x[1])


def beam_config(mesh_dir, law: str, element: str = "auto") -> ProblemConfig:
    return ProblemConfig.from_dict(
        {
            "mesh": {"file": str(mesh_dir / "beam-coarse.msh")},
            "material": {"law": law, "E": E, "nu": NU},
            "discretisation": {"element": element},
            "load": {"mode": "traction", "traction": [TRACTION, 0.0, 0.0], "steps": 10},
        }
    )


@pytest.mark.parametrize("law", ["svk", "neo-hookean"])
@pytest.mark.parametrize("element", ["Q1P0", "Q1"])
def test_beam_traction_matches_analytic_stretch(mesh_dir, tmp_path, law, element):
    model = FullOrderModel(beam_config(mesh_dir, law, element), verbose=False)
    result = model.solve(out_dir=tmp_path)
    assert len(result.records) == 10
    np.testing.assert_allclose(result.load_factor, np.arange(1, 11) / 10)

    stretch_fe = 1 + result.displacement[:, 0] / LENGTH
    stretch_exact = np.array(
        [analytic_stretches(law, lf * TRACTION)[0] for lf in result.load_factor]
    )
    rel_error = np.abs(stretch_fe - stretch_exact) / stretch_exact
    assert rel_error.max() <= 1e-3  # the bound; homogeneous -> in fact ~1e-10
    assert rel_error.max() <= 1e-8, f"axial stretch error {rel_error.max():.2e}"

    # Lateral contraction at the free end's corner node (400, 20, 20).
    u = model.model.u
    x = u.function_space.tabulate_dof_coordinates()
    corner = np.flatnonzero(np.linalg.norm(x - [LENGTH, 20.0, 20.0], axis=1) < 1e-9)
    assert corner.size == 1
    l2_fe = 1 + u.x.array.reshape(-1, 3)[corner[0], 1] / 20.0
    l2_exact = analytic_stretches(law, TRACTION)[1]
    assert abs(l2_fe - l2_exact) <= 1e-8 * l2_exact

    # The force column is the applied load, 400 N at factor 1.
    np.testing.assert_allclose(result.force[:, 0], result.load_factor * TRACTION * 1600.0)

    with open(tmp_path / "curve.csv") as f:
        rows = list(csv.DictReader(f))
    required = "step,load_factor,force_x,force_y,force_z,disp_x,disp_y,disp_z".split(",")
    assert set(required) <= set(rows[0])
    np.testing.assert_allclose([float(r["disp_x"]) for r in rows], result.displacement[:, 0])
    assert (tmp_path / "fields.xdmf").is_file() and (tmp_path / "fields.h5").is_file()
    assert (tmp_path / "fields-displacement.bp").is_dir()
    assert (tmp_path / "fields-pressure.bp").is_dir() == (element == "Q1P0")


def test_neo_hookean_tip_displacement_is_large(mesh_dir):
    """Thesis Fig. 3.4: about 120 mm of tip displacement at load factor 1."""
    l1, _ = analytic_stretches("neo-hookean", TRACTION)
    assert 100.0 < (l1 - 1) * LENGTH < 140.0


def _vtx_schema(bp) -> list[str]:
    """Names of the arrays in a VTX folder's VTK schema (the ``vtk.xml`` attribute, stored
    as plain text in the ADIOS2 metadata ``md.0``)."""
    import xml.etree.ElementTree as ET

    md = (bp / "md.0").read_bytes()
    start = md.index(b"<VTKFile")
    schema = ET.fromstring(md[start : md.index(b"</VTKFile>", start) + len(b"</VTKFile>")])
    return [a.get("Name") for a in schema.iter("DataArray")]


@pytest.fixture(scope="module")
def quadratic_solve(mesh_dir, tmp_path_factory):
    """Two increments of the coarse beam with Q2P0 elements, fields written: (model, dir)."""
    out = tmp_path_factory.mktemp("beam-q2")
    config = ProblemConfig.from_dict(
        {
            "mesh": {"file": str(mesh_dir / "beam-coarse.msh")},
            "material": {"law": "svk", "E": E, "nu": NU},
            "discretisation": {"element": "Q2P0"},
            "load": {"mode": "traction", "traction": [0.1 * TRACTION, 0.0, 0.0], "steps": 2},
        }
    )
    model = FullOrderModel(config, verbose=False)
    model.solve(out_dir=out)
    return model, out


def test_vtx_keeps_a_quadratic_displacement_at_degree_2(quadratic_solve):
    """XDMF interpolates a Q2 displacement down to the vertices; the VTX files keep every
    node: the last step's displacement is the degree-2 field's own values."""
    model, out = quadratic_solve
    u, p = model.model.u, model.model.p
    assert u.function_space.element.basix_element.degree == 2
    assert (out / "fields.xdmf").is_file()  # still there: tests and older tools read it
    bp = out / "fields-displacement.bp"
    assert "displacement" in _vtx_schema(bp)
    assert "pressure" in _vtx_schema(out / "fields-pressure.bp")
    # Serial: VTX stores the displacement as (nodes, 3) in the dof order, which is
    # u.x.array; 525 nodes of the Q2 beam against 99 vertices.
    nodes = u.function_space.dofmap.index_map.size_global
    assert nodes > u.function_space.mesh.geometry.index_map().size_global
    assert u.x.array.tobytes() in (bp / "data.0").read_bytes()
    assert p.x.array.tobytes() in (out / "fields-pressure.bp" / "data.0").read_bytes()


def test_vtx_reads_back_with_adios2(quadratic_solve):
    adios2 = pytest.importorskip("adios2", reason="no adios2 Python bindings to read it back")
    model, out = quadratic_solve
    u = model.model.u
    with adios2.FileReader(str(out / "fields-displacement.bp")) as f:
        steps = f.num_steps()
        nodes = f.read("NumberOfNodes", step_selection=[0, 1])
        last = f.read("displacement", step_selection=[steps - 1, 1])
    assert steps == 3  # the reference state and two increments
    assert int(np.asarray(nodes).reshape(-1)[0]) == u.function_space.dofmap.index_map.size_global
    np.testing.assert_array_equal(np.asarray(last).reshape(-1), u.x.array)
