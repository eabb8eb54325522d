"""The runtime's cut topology and patch (numpy) against the offline coupling."""

from __future__ import annotations

import numpy as np
import pytest

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.meshes.cut import interior_faces, limbal_arc
from hapticrom.offline.cutting.patch import couple, patch_around
from hapticrom.offline.studies.cutting import (
    CuttingStudy,
    linear_solve,
    lip_nodes,
    meshes,
    supported_nodes,
    surface_point,
    tangent_and_load,
)
from hapticrom.online.coupled_patch import CoupledPatch, CutRegion

pytestmark = pytest.mark.serial
STUDY = CuttingStudy(refinement="coarse", test_point=(3.4, 0.0))  # load away from the lips


@pytest.fixture(scope="module")
def setting(tmp_path_factory):
    from mpi4py import MPI

    from hapticrom.offline.cutting.element_matrices import element_stiffness
    from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
    from hapticrom.offline.fe.materials import make_law
    from hapticrom.offline.fe.organ import load_organ

    intact, cut, origin, files = meshes(STUDY, tmp_path_factory.mktemp("online-cut"))
    point = surface_point(*STUDY.test_point)
    K_intact, f_intact = tangent_and_load(files["intact"], point, STUDY, MPI.COMM_SELF)
    K_cut, f_cut = tangent_and_load(files["cut"], point, STUDY, MPI.COMM_SELF)
    organ = load_organ(files["intact"], MPI.COMM_SELF)
    model = HyperelasticModel(organ, make_law("svk", E=0.5, nu=0.45),
                              choose_element("hexahedron", "Q1P0"))  # fmt: skip
    Ke = element_stiffness(model, np.arange(len(intact.cells)), intact.cells)
    supported = supported_nodes(intact, np.arange(len(intact.nodes)))
    rng = np.random.default_rng(0)
    modes = [
        linear_solve(K_intact, f, supported) for f in rng.standard_normal((6, K_intact.shape[0]))
    ]
    A, _ = np.linalg.qr(np.column_stack([linear_solve(K_intact, f_intact, supported), *modes]))
    fixed = np.zeros(len(intact.nodes), dtype=bool)
    fixed[sorted(supported)] = True
    region = CutRegion(intact.nodes, intact.cells, Ke, A, fixed, A.T @ (K_intact @ A))
    return intact, cut, origin, K_intact, K_cut, f_intact, f_cut, A, region, supported


def test_online_cut_topology_matches_the_explicit_cut_mesh(setting):
    intact, cut, origin, *_, region, supported = setting
    faces, _ = interior_faces(intact.cells)
    selected = faces[limbal_arc(intact, STUDY.incision)]
    topology = region.intact_topology()
    # Cut in two events (as a scalpel would), which must end as the one-shot cut.
    half = len(selected) // 2
    topology.cut(selected[:half])
    topology.cut(selected[half:])
    assert len(topology.origin) == len(origin)
    # The same connectivity up to the numbering of the copies (made in another order).
    np.testing.assert_array_equal(_first_seen(topology.cells), _first_seen(cut.cells))
    np.testing.assert_array_equal(topology.origin[topology.cells], origin[cut.cells])
    # In one event, the numbering is the explicit cut's too.
    once = region.intact_topology()
    once.cut(selected)
    np.testing.assert_array_equal(once.cells, cut.cells)
    np.testing.assert_array_equal(once.origin, origin)


def _first_seen(cells: np.ndarray) -> np.ndarray:
    """Cells relabelled by the order in which their nodes first appear."""
    _, first, inverse = np.unique(cells.ravel(), return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))
    return rank[inverse].reshape(cells.shape)


@pytest.mark.parametrize("layers", [1, 2])
def test_online_patch_solves_the_offline_coupled_system(setting, layers):
    intact, cut, origin, K_intact, K_cut, f_intact, f_cut, A, region, supported = setting
    faces, _ = interior_faces(intact.cells)
    topology = region.intact_topology()
    topology.cut(faces[limbal_arc(intact, STUDY.incision)])
    patch = CoupledPatch(topology, region, layers)
    cut_supported = supported | {i for i in range(len(origin)) if origin[i] in supported}
    offline = couple(K_intact, K_cut, A, origin, patch_around(cut.cells, lip_nodes(origin),
                                                               layers, cut_supported))  # fmt: skip
    np.testing.assert_array_equal(np.sort(patch.nodes), offline.patch.nodes)
    assert not f_cut[(3 * lip_nodes(origin)[:, None] + np.arange(3)).ravel()].any()
    load_patch = np.where(np.repeat(patch.nodes < len(intact.nodes), 3),
                          f_intact[(3 * topology.origin[patch.nodes][:, None]
                                    + np.arange(3)).ravel()], 0.0)  # fmt: skip
    x = patch.solve(A.T @ f_intact, load_patch)
    u_online = patch.region_displacement(x)
    u_offline = offline.solve(f_cut).reshape(-1, 3)
    scale = np.abs(u_offline).max()
    np.testing.assert_allclose(u_online[topology.cells], u_offline[cut.cells], atol=1e-10 * scale)
    # and the lips open
    lips = lip_nodes(origin)
    assert np.ptp(u_online[lips], axis=0).max() > 1e-4 * scale


def test_artifact_cutting_region_round_trip(mesh_dir, tmp_path):
    """[cutting] in a campaign: the artifact's region assembles to the reduced stiffness."""
    from conftest import campaign_toml
    from mpi4py import MPI

    import hapticrom.online as online
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.reduce.reduction import reduce_campaign

    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=2, per_ring=3)
    text = text.replace('law = "hgo"', 'law = "svk"\nE = 0.5\nnu = 0.45')
    text += "\n[anm]\nenabled = false\n[cutting]\ncentre = [0.0, 0.0, -3.0]\nradius = 20.0\n"
    (tmp_path / "c.toml").write_text(text)
    config = CampaignConfig.from_toml(tmp_path / "c.toml")
    run_campaign(config, tmp_path / "store", MPI.COMM_SELF, verbose=False)
    reduce_campaign(tmp_path / "store", tmp_path / "m.h5", MPI.COMM_SELF, verbose=False)
    region = online.load(tmp_path / "m.h5").cut_region
    assert region is not None and len(region.cells) == 264  # the ball holds the whole mesh
    # Sum_c A_c^T K_c A_c over all cells equals A^T K0 A assembled by DOLFINx (distributed).
    K = np.zeros_like(region.reduced_stiffness)
    for c, cell in enumerate(region.cells):
        A_c = region.basis[(3 * cell[:, None] + np.arange(3)).ravel()]
        K += A_c.T @ region.element_stiffness[c] @ A_c
    scale = np.abs(region.reduced_stiffness).max()
    np.testing.assert_allclose(K, region.reduced_stiffness, atol=1e-10 * scale)
    assert region.fixed.sum() > 0  # the clamped limbus
    # A cut through the region and its factorised patch.
    from hapticrom.meshes import build

    intact = build("cornea", "coarse")  # region node i is mesh node i (the ball holds all)
    faces, _ = interior_faces(intact.cells)
    topology = region.intact_topology()
    new_nodes = topology.cut(faces[limbal_arc(intact, STUDY.incision)])
    assert len(new_nodes) == 9
    patch = CoupledPatch(topology, region, 1)
    assert patch.size > region.reduced_stiffness.shape[0]

    # A format 1.2 file (no pressure coupling) still loads, without it; a damaged
    # optional dataset is named.
    import shutil

    from tamper import mutate

    from hapticrom.shared.artifact import SCHEMA, ArtifactError
    from hapticrom.shared.checksum import array_digest

    old = tmp_path / "old.h5"
    shutil.copyfile(tmp_path / "m.h5", old)
    coupling = [spec.name for group in SCHEMA if group.name == "cutting"
                for spec in group.fields if not spec.required]  # fmt: skip
    assert len(coupling) == 7
    mutate(old, lambda f: f.__delitem__(f"cutting/{coupling[0]}"))
    with pytest.raises(ArtifactError, match=f"incomplete .* {coupling[0]}"):
        online.load(old)

    def drop_the_rest(f):
        for name in coupling[1:]:
            del f[f"cutting/{name}"]

    mutate(old, drop_the_rest)
    assert online.load(old).cut_region.pressure is None

    def narrower(f):
        bad = f["cutting/pressure_basis"][()][:, :-1]
        del f["cutting/pressure_basis"]
        d = f["cutting"].create_dataset("pressure_basis", data=bad)
        d.attrs["units"], d.attrs["sha256"] = "1", array_digest(bad)

    mutate(tmp_path / "m.h5", narrower)
    with pytest.raises(ArtifactError, match=r"cutting/\w+ has shape"):
        online.load(tmp_path / "m.h5")


@pytest.mark.parametrize("n", [1, 127, 128, 129, 700])
def test_blocked_triangular_solve_matches_numpy(n):
    from hapticrom.online.coupled_patch import solve_lower

    rng = np.random.default_rng(n)
    M = rng.standard_normal((n, n))
    L = np.linalg.cholesky(M @ M.T + n * np.eye(n))
    B = rng.standard_normal((n, 3))
    np.testing.assert_allclose(solve_lower(L, B), np.linalg.solve(L, B), rtol=1e-10, atol=1e-12)
    b = B[:, 0]
    np.testing.assert_allclose(solve_lower(L, b, transposed=True), np.linalg.solve(L.T, b),
                               rtol=1e-10, atol=1e-12)  # fmt: skip
