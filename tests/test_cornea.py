"""HGO cornea (thesis §2.4-2.5) on the coarse mesh: indentation, locking, step cutting."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.contact import ReactionForce
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.shared.errors import SolverError

pytestmark = pytest.mark.serial


def cornea_config(mesh_dir, **sections) -> ProblemConfig:
    data = {
        "mesh": {"file": str(mesh_dir / "cornea-coarse.msh")},
        "material": {"law": "hgo"},
        # The coarse mesh's node spacing is about 0.9 mm: the tool holds the apex node.
        "load": {
            "mode": "displacement",
            "displacement": [0.0, 0.0, -0.5],
            "contact_radius": 0.8,
            "steps": 5,
        },
    }
    for name, table in sections.items():  # merge; a None value removes the key
        merged = {**data.get(name, {}), **table}
        data[name] = {k: v for k, v in merged.items() if v is not None}
    return ProblemConfig.from_dict(data)


@pytest.fixture(scope="module")
def indentation(mesh_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("cornea")
    model = FullOrderModel(cornea_config(mesh_dir), verbose=False)
    return model, model.solve(out_dir=out), out


def test_indentation_force_is_a_stiffening_push_back(indentation):
    model, result, out = indentation
    assert model.patch_displacement.count == 1
    np.testing.assert_allclose(result.displacement[:, 2], -0.1 * np.arange(1, 6), atol=1e-12)
    fz = result.force[:, 2]
    # The tool pushes the tissue down (force on the tissue along -z), harder and harder.
    assert np.all(fz < 0) and np.all(np.diff(fz) < 0)
    # Thesis Table 2.2: 0.0227 N at 0.45 mm on its own mesh: order 1e-2 N.
    assert 5e-3 < -fz[-1] < 1e-1
    # The patch and the fibre field are symmetric under x -> -x, y -> -y: no lateral force.
    assert np.abs(result.force[:, :2]).max() < 1e-9 * np.abs(fz).max()
    assert all(r.step_cuts == 0 for r in result.records)


def test_curve_csv_and_fields(indentation):
    _, result, out = indentation
    with open(out / "curve.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 5
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5]
    np.testing.assert_allclose([float(r["force_z"]) for r in rows], result.force[:, 2], rtol=1e-9)
    np.testing.assert_allclose([float(r["load_factor"]) for r in rows], result.load_factor)
    xdmf = (out / "fields.xdmf").read_text()
    for name in ("displacement", "pressure", "fibre_m0", "fibre_n0"):
        assert f'Name="{name}"' in xdmf
    assert xdmf.count('<Attribute Name="displacement"') == 6  # reference state + 5 increments
    for name in ("displacement", "pressure", "fibres"):  # VTX: each field at its own degree
        assert (out / f"fields-{name}.bp" / "md.0").is_file()


def test_modified_newton_reaches_the_same_equilibria(mesh_dir, indentation):
    _, full, _ = indentation
    model = FullOrderModel(cornea_config(mesh_dir, solver={"newton": "modified"}), verbose=False)
    modified = model.solve()
    np.testing.assert_allclose(modified.force, full.force, rtol=1e-7, atol=1e-12)


def test_reaction_force_balances_the_clamped_rim(indentation):
    """Global equilibrium: the limbus holds the cornea with exactly the tool's force.

    The internal forces of a translation-invariant energy sum to zero over all
    nodes, so the support reaction (summed the same way over the clamped
    nodes) must be minus the tool force computed on the contact patch.
    """
    model, result, _ = indentation
    V = model.model.V
    rim = ReactionForce(model.newton.problem.F[0], V, model.organ.constrained_blocks(V))
    np.testing.assert_allclose(rim(), -result.force[-1], atol=1e-9 * np.abs(result.force).max())


def test_mixed_element_removes_volumetric_locking(mesh_dir):
    """Q1 hexahedra lock on nearly incompressible tissue; the Q1/P0 element does not."""

    def apex_deflection(element, D):
        config = cornea_config(
            mesh_dir,
            material={"D": D},
            discretisation={"element": element},
            load={"mode": "force", "force": [0.0, 0.0, -0.002], "displacement": None, "steps": 1},
        )
        return FullOrderModel(config, verbose=False).solve().displacement[-1, 2]

    mixed = apex_deflection("Q1P0", 1e-5)
    locked = apex_deflection("Q1", 1e-5)
    assert mixed < 0 and locked < 0
    assert abs(mixed) > 5 * abs(locked), "Q1P0 should be far softer than locking Q1"
    # Nearly incompressible either way: a 100x larger D barely moves the apex.
    assert apex_deflection("Q1P0", 1e-3) == pytest.approx(mixed, rel=5e-3)


def test_step_cutting_recovers_and_reports(mesh_dir, indentation):
    """Too few Newton iterations for one big step: the load step is halved until it passes."""
    _, reference, _ = indentation
    config = cornea_config(
        mesh_dir,
        load={"steps": 1},
        solver={"petsc_options": {"snes_max_it": 3}},
    )
    result = FullOrderModel(config, verbose=False).solve()
    assert result.records[0].step_cuts >= 1
    assert result.load_factor[-1] == 1.0
    # Hyperelastic: the equilibrium at full load does not depend on the path.
    assert result.force[-1, 2] == pytest.approx(reference.force[-1, 2], rel=1e-7)


def test_divergence_is_never_an_answer(mesh_dir):
    config = cornea_config(
        mesh_dir,
        load={"steps": 1, "max_step_cuts": 1},
        solver={"petsc_options": {"snes_max_it": 1}},
    )
    with pytest.raises(SolverError, match="Newton diverged at load factor"):
        FullOrderModel(config, verbose=False).solve()


def test_iterative_linear_solver_reaches_the_same_equilibria(mesh_dir, indentation):
    """The memory-lean option (GMRES + block ILU) for meshes too big for LU."""
    _, direct, _ = indentation
    config = cornea_config(mesh_dir, solver={"linear_solver": "iterative"})
    iterative = FullOrderModel(config, verbose=False).solve()
    scale = np.abs(direct.force).max()
    np.testing.assert_allclose(iterative.force, direct.force, rtol=0, atol=1e-6 * scale)


def test_close_frees_the_solver_that_a_reference_cycle_would_keep(mesh_dir):
    """The SNES holds the solver's tangent callback (a cycle Python's collector leaves):
    ``close`` destroys the SNES and its matrices now, so a campaign solving one position
    after another does not keep every factorisation (measured: +70 MB per coarse-liver
    solve without it, flat with it)."""
    model = FullOrderModel(cornea_config(mesh_dir, load={"steps": 1}), verbose=False)
    model.solve()
    problem = model.newton.problem
    handles = [problem.solver, problem.A, problem.b, problem.x]
    assert all(obj.handle != 0 for obj in handles)
    model.close()
    assert all(obj.handle == 0 for obj in handles)
