"""The reduced model coupled with a cut patch (thesis eq. 4.8) against the cut meshed explicitly."""

from __future__ import annotations

import numpy as np
import pytest

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.offline.cutting.patch import continuation_map, couple, patch_around, relative_l2
from hapticrom.offline.studies.cutting import (
    CuttingStudy,
    linear_solve,
    lip_nodes,
    meshes,
    run_study,
    supported_nodes,
    surface_point,
    tangent_and_load,
)
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
STUDY = CuttingStudy(refinement="coarse", test_point=(4.8, 0.0))


@pytest.fixture(scope="module")
def coarse(tmp_path_factory):
    from mpi4py import MPI

    work = tmp_path_factory.mktemp("cut")
    intact, cut, origin, files = meshes(STUDY, work)
    point = surface_point(*STUDY.test_point)
    K_cut, f_cut = tangent_and_load(files["cut"], point, STUDY, MPI.COMM_SELF)
    K_intact, _ = tangent_and_load(files["intact"], point, STUDY, MPI.COMM_SELF)
    supported = supported_nodes(intact, origin)
    return intact, cut, origin, K_intact, K_cut, f_cut, supported


def test_coupling_is_exact_when_the_basis_holds_the_solution_outside_the_patch(coarse):
    """Galerkin in a space that contains the exact (linear) cut solution returns it.

    The cut solution averaged over each pair of lips is continuous, so it can be
    a reduced mode; what is left is supported on the lips' nodes, which the patch
    carries. Add unrelated modes (intact solutions) to make it a real reduced space.
    """
    intact, cut, origin, K_intact, K_cut, f_cut, supported = coarse
    u_exact = linear_solve(K_cut, f_cut, supported)
    N = len(intact.nodes)
    v = np.zeros(3 * N)
    counts = np.zeros(N)
    np.add.at(v.reshape(-1, 3), origin, u_exact.reshape(-1, 3))
    np.add.at(counts, origin, 1.0)
    v = (v.reshape(-1, 3) / counts[:, None]).ravel()
    rng = np.random.default_rng(3)
    others = [linear_solve(K_intact, f, supported_nodes(intact, np.arange(N)))
              for f in rng.standard_normal((3, 3 * N)) * 1e-4]  # fmt: skip
    A, _ = np.linalg.qr(np.column_stack([v, *others]))
    patch = patch_around(cut.cells, lip_nodes(origin), 1, supported)
    coupled = couple(K_intact, K_cut, A, origin, patch)
    u = coupled.solve(f_cut)
    assert relative_l2(u, u_exact) <= 1e-9
    # Without the patch's lip DOFs the cut cannot open: the same basis is then wrong.
    u_blind = coupled.TA @ np.linalg.solve(A.T @ K_intact @ A, coupled.TA.T @ f_cut)
    assert relative_l2(u_blind, u_exact) >= 1e-3


def test_patch_nodes_are_interior_and_unsupported(coarse):
    intact, cut, origin, *_, supported = coarse
    patch = patch_around(cut.cells, lip_nodes(origin), 2, supported)
    outside = np.setdiff1d(np.arange(len(cut.cells)), patch.cells)
    assert not np.isin(patch.nodes, cut.cells[outside]).any()  # u^L = 0 on the outer boundary
    assert not set(patch.nodes.tolist()) & supported
    assert set(lip_nodes(origin).tolist()) - supported <= set(patch.nodes.tolist())
    T = continuation_map(origin)
    np.testing.assert_array_equal(T @ np.arange(3.0 * len(intact.nodes)),
                                  (3 * origin[:, None] + np.arange(3)).ravel())  # fmt: skip
    with pytest.raises(InputError, match="layer"):
        patch_around(cut.cells, lip_nodes(origin), 0, supported)


def test_limbal_incision_study_on_the_coarse_cornea(tmp_path):
    """Reduced + patch beats the cut-blind reduced model against the nonlinear cut solve."""
    result = run_study(STUDY, tmp_path / "work", out=tmp_path / "figures")
    assert result["error_coupled"] < 0.7 * result["error_blind"]
    assert result["error_coupled"] <= 0.05
    assert result["max_opening_coupled_mm"] > 0.5 * result["max_opening_reference_mm"]
    for figure in result["figures"]:
        assert (tmp_path / "figures").joinpath(figure.split("/")[-1]).stat().st_size > 10_000


def test_a_patch_under_the_tool_holds_a_dent_the_basis_lacks(tmp_path):
    """At a tool position the training did not cover (rho 4.4 mm, 10 degrees), the
    basis lacks the dent; local DOFs under the tool hold it (coarse cornea, 1 ring)."""
    from dataclasses import replace

    held_out = replace(STUDY, test_point=(4.4, 10.0), patch_layers=1)
    assert not any(10.0 in angles for _, angles in held_out.training)
    cut_only = run_study(held_out, tmp_path / "work")
    with_tool = run_study(replace(held_out, patch_at_tool=True), tmp_path / "work")
    assert with_tool["patch_dofs"] > cut_only["patch_dofs"]
    assert cut_only["error_coupled"] > 0.05  # measured 7.7 %
    assert with_tool["error_coupled"] <= 0.05  # measured 3.0 %
    assert with_tool["error_coupled"] < 0.5 * cut_only["error_coupled"]
