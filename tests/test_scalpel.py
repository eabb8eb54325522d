"""The runtime's scalpel: cut events, softening, lips, bad input (coarse cornea, SVK)."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.serial
R = 7.8  # mm, anterior radius of the cornea


def on_surface(rho, degrees=0.0):
    a = np.radians(degrees)
    return np.array([rho * np.cos(a), rho * np.sin(a), -R + np.sqrt(R * R - rho * rho)])


def _train(root, text: str):
    """Run the campaign ``text`` (serial) under ``root`` and reduce it: (model, config)."""
    from mpi4py import MPI

    import hapticrom.online as online
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
    from hapticrom.offline.reduce.reduction import reduce_campaign

    (root / "c.toml").write_text(text)
    config = CampaignConfig.from_toml(root / "c.toml")
    run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
    reduce_campaign(root / "store", root / "m.h5", MPI.COMM_SELF, verbose=False)
    return online.load(root / "m.h5"), config


@pytest.fixture(scope="module")
def model(mesh_dir, tmp_path_factory):
    from conftest import campaign_toml

    root = tmp_path_factory.mktemp("scalpel")
    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=2, per_ring=3)
    text = text.replace('law = "hgo"', 'law = "svk"\nE = 0.5\nnu = 0.45')
    centre = on_surface(4.6).tolist()
    text += f"\n[anm]\nenabled = false\n[cutting]\ncentre = {centre}\nradius = 2.5\n"
    text += "cut_force = 1e-4\npatch_layers = 1\n"
    return _train(root, text)[0]


def test_pressing_the_blade_cuts_and_softens(model):
    sim = model.simulator()
    intact = model.simulator()
    point = on_surface(4.6)
    sim.scalpel(point, [0.0, 1.0, 0.0])  # blade along the limbus
    intact.set_contact(point)
    n = sim.contact_normal.copy()
    assert sim.last_cut is None
    forces = []
    for depth in (0.005, 0.01, 0.02, 0.04):
        forces.append(sim.step_displacement(-depth * n).copy())
        f_intact = intact.step_displacement(-depth * n)
        if sim.last_cut is not None:
            # Cut: the tissue is softer there than the intact one (never stiffer).
            assert np.linalg.norm(forces[-1]) < np.linalg.norm(f_intact)
    assert sim.last_cut is not None and sim.last_cut.faces > 0
    events = sim.cut_events
    assert sum(e.new_nodes for e in events) > 0 and events[-1].patch_unknowns > 0
    # Sliding along the blade extends the cut; steps without a new cut change nothing.
    sim.scalpel(on_surface(4.6, 8.0), [0.0, 1.0, 0.0])
    sim.step_displacement(-0.04 * n)
    assert len(sim.cut_events) >= len(events)
    count = len(sim.cut_events)
    sim.step_displacement(-0.04 * n)
    assert len(sim.cut_events) == count  # the same faces are not cut twice
    # The rendered surface shows the two lips, apart.
    out = np.zeros_like(model.vertices)
    sim.surface_displacement(out)
    vertices, positions, displacement = sim.lip_vertices
    assert len(vertices) > 0
    np.testing.assert_array_equal(positions, model.vertices[vertices])
    assert np.abs(displacement - out[vertices]).max() > 0
    # A renderer's view: the lips split the triangles, each side uses its own vertices.
    all_vertices, triangles = sim.cut_surface()
    V = len(model.vertices)
    assert len(all_vertices) == V + len(vertices) and len(triangles) == len(model.triangles)
    used = np.unique(triangles)
    assert np.all(np.isin(np.arange(V, V + len(vertices)), used))  # every lip copy is drawn
    assert np.all(np.isin(vertices, used))  # and so is the other lip
    changed = np.any(triangles != model.triangles, axis=1)
    np.testing.assert_array_equal(all_vertices[triangles[changed]],
                                  model.vertices[model.triangles[changed]])  # fmt: skip


def test_a_background_cut_ends_as_the_waited_one(model):
    """Cut events on a worker thread: the steps go on with the state before the cut, and
    once installed (in order) everything equals cutting synchronously."""
    waited, background, intact = model.simulator(), model.simulator(), model.simulator()
    n = None
    for angle in (0.0, 8.0):
        point = on_surface(4.6, angle)
        waited.scalpel(point, [0.0, 1.0, 0.0])
        background.scalpel(point, [0.0, 1.0, 0.0], background=True)
        intact.set_contact(point)
        n = waited.contact_normal.copy() if n is None else n
        for depth in (0.005, 0.01, 0.02, 0.04):
            ratio_before = background.cut_stiffness_ratio
            installed = len(background.cut_events)
            waited.step_displacement(-depth * n)
            f = background.step_displacement(-depth * n).copy()
            if background.cut_pending and len(background.cut_events) == installed:
                # Not installed yet: the force of the state before.
                f_intact = intact.step_displacement(-depth * n)
                np.testing.assert_allclose(f, ratio_before * f_intact, rtol=1e-12)
    background.finish_cuts()
    assert not background.cut_pending
    summary = [(e.faces, e.new_nodes, e.patch_unknowns) for e in waited.cut_events]
    assert len(summary) >= 2
    assert [(e.faces, e.new_nodes, e.patch_unknowns) for e in background.cut_events] == summary
    np.testing.assert_array_equal(background.cutting.cuts.topology.cells,
                                  waited.cutting.cuts.topology.cells)  # fmt: skip
    np.testing.assert_allclose(background.cutting.cuts.ratio, waited.cutting.cuts.ratio,
                               rtol=1e-12)  # fmt: skip
    np.testing.assert_allclose(background.step_displacement(-0.03 * n),
                               waited.step_displacement(-0.03 * n), rtol=1e-12)  # fmt: skip
    u_waited = waited.surface_displacement(np.zeros_like(model.vertices)).copy()
    u_background = background.surface_displacement(np.zeros_like(model.vertices))
    np.testing.assert_allclose(u_background, u_waited, rtol=1e-12, atol=1e-15)


def test_a_failed_background_cut_changes_nothing(model, monkeypatch):
    """A cut whose patch cannot be factorised: the servo loop goes on, the error is kept,
    the topology is as before, a later cut works; the GIL switch interval is restored."""
    import sys

    from hapticrom.online.cutting import Cuts

    switch = sys.getswitchinterval()
    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0], background=True)
    n = sim.contact_normal.copy()
    original = Cuts._compliances

    def failing(self, patch):
        raise np.linalg.LinAlgError("not positive definite (test)")

    monkeypatch.setattr(Cuts, "_compliances", failing)
    with pytest.warns(RuntimeWarning, match="cut failed"):
        for depth in (0.005, 0.01, 0.02, 0.04):
            sim.step_displacement(-depth * n)
        assert sim.cut_pending or sim.cut_error is not None
        sim.step_displacement(-0.04 * n)
        while sim.cut_pending:
            sim.step_displacement(-0.04 * n)
    assert isinstance(sim.cut_error, np.linalg.LinAlgError)
    assert sim.cut_events == [] and sim.cutting.cuts.topology.cut_faces == set()
    assert sim.cutting.cuts.next.cut_faces == set()  # the worker's topology too
    assert sys.getswitchinterval() == switch
    monkeypatch.setattr(Cuts, "_compliances", original)
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0], background=True)
    sim.step_displacement(-0.04 * n)
    sim.finish_cuts()
    reference = model.simulator()
    reference.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    reference.step_displacement(-0.04 * n)
    assert [e.faces for e in sim.cut_events] == [e.faces for e in reference.cut_events]
    assert sim.cutting.cuts.topology.cut_faces == reference.cutting.cuts.topology.cut_faces
    assert sys.getswitchinterval() == switch


def test_the_scalpel_cuts_under_force_control(model):
    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    n = sim.contact_normal.copy()
    for force in (1e-5, 5e-5, 2e-4, 5e-4):  # N on the tissue, into it; cut force 1e-4 N
        d = sim.step_force(-force * n).copy()
    assert sim.cut_events and sim.cut_stiffness_ratio < 1.0
    intact = model.simulator()
    intact.set_contact(on_surface(4.6))
    assert np.linalg.norm(d) > np.linalg.norm(intact.step_force(-5e-4 * n))  # yields more


def test_bad_scalpel_input_leaves_the_state_alone(model):
    from hapticrom.online import ScalpelInputError

    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    sim.step_displacement(-0.03 * sim.contact_normal)
    before = (len(sim.cut_events), sim.contact_normal.copy(), sim.depth)
    for position, blade, message in (
        ([0.0, 0.0, 5.0], [0.0, 1.0, 0.0], "off the organ"),
        (on_surface(4.6), [0.0, 0.0, 0.0], "zero or along"),
        (on_surface(4.6), on_surface(4.6) - [0.0, 0.0, -R], "zero or along"),  # the normal
        ([np.nan, 0.0, 0.0], [0.0, 1.0, 0.0], "finite"),
    ):
        with pytest.raises(ScalpelInputError, match=message):
            sim.scalpel(position, blade)
        assert len(sim.cut_events) == before[0]
        np.testing.assert_array_equal(sim.contact_normal, before[1])
        assert sim.depth == before[2]


def test_artifact_without_a_region_refuses_the_scalpel(small_artifact):
    import hapticrom.online as online

    sim = online.load(small_artifact).simulator()
    with pytest.raises(ValueError, match="cuttable region"):
        sim.scalpel([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])


def test_reduce_again_with_other_reduction_tables_only(small_campaign, tmp_path, mesh_dir):
    """`hapticrom reduce --campaign`: [anm]/[cutting] may change, the solves may not."""
    from conftest import campaign_toml
    from mpi4py import MPI

    from hapticrom.offline.campaign.run import CampaignConfig
    from hapticrom.offline.reduce.reduction import reduce_campaign
    from hapticrom.shared.errors import InputError

    _, store, _ = small_campaign
    other = tmp_path / "other.toml"
    other.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh").replace("0.3", "0.25"))
    with pytest.raises(InputError, match="another campaign"):
        reduce_campaign(store.root, tmp_path / "x.h5", MPI.COMM_SELF, verbose=False,
                        reduction=CampaignConfig.from_toml(other))  # fmt: skip
    same = tmp_path / "same.toml"
    same.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh") + "\n[anm]\nenabled = false\n")
    reduce_campaign(store.root, tmp_path / "y.h5", MPI.COMM_SELF, verbose=False,
                    reduction=CampaignConfig.from_toml(same))  # fmt: skip
    import hapticrom.online as online

    assert online.load(tmp_path / "y.h5").anm is None


def test_force_control_yields_more_where_cut(model):
    sim, intact = model.simulator(), model.simulator()
    point = on_surface(4.6)
    sim.scalpel(point, [0.0, 1.0, 0.0])
    for depth in (0.01, 0.02, 0.04):
        sim.step_displacement(-depth * sim.contact_normal)
    assert sim.cut_events
    intact.set_contact(point)
    push = -0.5 * model.trained_force * sim.contact_normal
    d_cut = sim.step_force(push).copy()
    d_intact = intact.step_force(push).copy()
    ratio = sim.cutting.cuts.ratio[sim.cutting.vertex]  # cut / intact stiffness at the contact
    assert ratio < 1
    np.testing.assert_allclose(np.linalg.norm(d_cut), np.linalg.norm(d_intact) / ratio)


@pytest.fixture(scope="module")
def hgo_model(mesh_dir, tmp_path_factory):
    """The nearly incompressible HGO cornea (D = 1e-5) with a cuttable region (format 1.3)."""
    from conftest import campaign_toml

    root = tmp_path_factory.mktemp("scalpel-hgo")
    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=2, per_ring=3)
    text = text.replace(
        'mode = "displacement"\nmagnitude = 0.3',
        'mode = "force"\nmagnitude = 0.03\ndirection = "normal"',
    )  # soft tip
    # Trained where the scalpel works: the reduced model must hold the tool's response there.
    points = [
        on_surface(rho, a).tolist()
        for rho, a in ((4.6, 0), (4.6, 12), (4.6, -12), (4.0, 6), (4.0, -6), (5.2, 6), (5.2, -6))
    ]
    text = text.replace("points = [[0.0, 0.0, 0.0]]", f"points = {points}")
    text += f"\n[anm]\nenabled = false\n[cutting]\ncentre = {on_surface(4.6).tolist()}\n"
    text += "radius = 3.0\ncut_force = 1e-4\npatch_layers = 2\n"
    model, config = _train(root, text)
    return model, mesh_dir / "cornea-coarse.msh", config


def _linear_full_order(mesh_file, config, point, direction, tmp_path):
    """Work-conjugate compliance (mm/N) of the full order under a small soft-tip load."""
    from mpi4py import MPI

    from hapticrom.offline.config import ProblemConfig
    from hapticrom.offline.fe.dofs import CanonicalOrder
    from hapticrom.offline.fe.fullorder import FullOrderModel

    force = 1e-6  # N: the linear range
    problem = ProblemConfig.from_dict({
        "mesh": {"file": str(mesh_file)},
        "material": {"law": "hgo"},
        "load": {"mode": "force", "contact_point": list(point),
                 "force": list(force * direction), "contact_radius": config.load.contact_radius,
                 "steps": 1},
        "output": {"xdmf": False},
    })  # fmt: skip
    fom = FullOrderModel(problem, MPI.COMM_SELF, verbose=False)
    result = fom.solve()
    u = CanonicalOrder(fom.model.V).gather(fom.model.u.x.array).reshape(-1, 3) / force
    return float(result.displacement[-1] @ direction) / force, u


def test_cut_softening_matches_the_full_order_with_the_cut_meshed(hgo_model, tmp_path):
    """The runtime's cut stiffness ratio at the tool against DOLFINx on the explicitly cut mesh.

    Nearly incompressible tissue is where an element-condensed reduced part locks
    (the coupled model 7x too stiff); with the reduced pressure kept outside the
    patch, the uncut coupled model has the full order's compliance and the cut
    softens the contact as the full order with the cut meshed does.
    """
    from hapticrom.meshes import build
    from hapticrom.meshes.cut import cut_mesh, interior_faces
    from hapticrom.meshes.msh import write_msh
    from hapticrom.online.coupled_patch import CoupledPatch, compliance

    model, mesh_file, config = hgo_model
    assert model.cut_region.pressure is not None  # a Q1P0 model exports its pressure coupling
    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    n = sim.contact_normal.copy()
    for depth in (0.01, 0.02, 0.03):
        sim.step_displacement(-depth * n)
    assert sim.cut_events, "the scalpel did not cut"
    scalpel = sim.cutting
    vertex = scalpel.vertex
    point, direction = model.vertices[vertex], -scalpel.normals[vertex]
    # The same faces cut in the mesh.
    nodes = np.asarray(model.artifact["cutting"]["nodes"])
    keys = {tuple(sorted(nodes[list(f)])) for f in scalpel.cuts.topology.cut_faces}
    intact = build("cornea", "coarse")
    faces, _ = interior_faces(intact.cells)
    chosen = np.array([i for i, f in enumerate(faces) if tuple(sorted(f)) in keys])
    assert len(chosen) == len(keys)
    cut, _ = cut_mesh(intact, chosen)
    cut_file = write_msh(tmp_path / "cut.msh", cut.nodes, cut.cells, cut.facet_groups,
                         cut.sidecar())  # fmt: skip
    c_intact, _ = _linear_full_order(mesh_file, config, point, direction, tmp_path)
    c_cut, u_cut = _linear_full_order(cut_file, config, point, direction, tmp_path)
    full_order_ratio = c_intact / c_cut
    assert full_order_ratio < 0.97  # the cut matters here
    # The reduced part: with its pressure condensed per element it is locked (D = 1e-5,
    # snapshots at large strain: measured 2.7x too stiff);
    # with the reduced pressure basis (what the coupling keeps outside the patch) it is not.
    loads = scalpel.cuts.loads
    on_region, B_uncut, uncut = loads.vertices, loads.B_uncut, loads.uncut
    k = int(np.flatnonzero(on_region == vertex)[0])
    b = B_uncut[: uncut.G, k]
    locked = b @ np.linalg.solve(model.cut_region.reduced_stiffness, b)
    reduced_pressure = b @ np.linalg.solve(model.artifact["global"]["reduced_stiffness"], b)
    assert locked < 0.5 * c_intact
    assert reduced_pressure == pytest.approx(c_intact, rel=0.1)
    # The uncut coupled model has the full order's compliance, however small its patch
    # (with the element-condensed reduced part, a 1-ring patch was 32 % too stiff here).
    for layers in (1, 2):
        cells = CoupledPatch(scalpel.cuts.topology, model.cut_region, layers).cells
        region = model.cut_region
        patch = CoupledPatch(region.intact_topology(), region, 1, cells)
        loads = scalpel.cuts.tool.loads(patch, np.array([vertex]))
        assert compliance(patch, loads)[0] == pytest.approx(c_intact, rel=0.1)
    # The cut's softening of the contact: within 10 % of the full order's.
    softening = 1.0 - sim.cut_stiffness_ratio
    assert softening == pytest.approx(1.0 - full_order_ratio, rel=0.1)
    # The rendered surface with the cut, against the full order's at the same depth.
    surface = np.asarray(model.artifact["surface"]["nodes"])
    reference = u_cut[surface] * sim.depth / c_cut
    blind = model.simulator()
    blind.set_contact(on_surface(4.6))
    blind.step_displacement(-sim.depth * n)

    def error(s):
        u = s.surface_displacement(np.zeros_like(model.vertices))
        return np.linalg.norm(u - reference) / np.linalg.norm(reference)

    # Coarse mesh, a cut that softens by a third: measured 15 % with it, 39 % blind.
    assert error(sim) < 0.2 and error(sim) < 0.5 * error(blind)


def test_placing_the_scalpel_again_allocates_nothing(model):
    """scalpel() every servo tick: after the first call no allocation at all (tracemalloc
    sees every Python and numpy allocation: none per call, none kept)."""
    import sys
    import tracemalloc

    sim = model.simulator()
    blade = np.array([0.0, 1.0, 0.0])
    start = on_surface(4.6)
    near = [np.ascontiguousarray(start + 0.3 * np.array([np.cos(a), np.sin(a), 0.0]))
            for a in np.linspace(0.0, 2.0 * np.pi, 50)]  # fmt: skip
    sim.scalpel(start, blade)
    for p in near:
        sim.scalpel(p, blade)
    tracemalloc.start()
    try:
        base, _ = tracemalloc.get_traced_memory()
        blocks = sys.getallocatedblocks()
        for _ in range(20):
            sim.scalpel(start, blade)  # the same position
            for p in near:  # and nearby ones
                sim.scalpel(p, blade)
        kept = sys.getallocatedblocks() - blocks
        current, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert kept < 50
    # A few hundred bytes of the interpreter's own (the call's argument tuples); one
    # array over the surface vertices alone would be len(vertices) x 24 bytes.
    assert current - base < 1024 and peak - base < 2048 < 24 * len(model.vertices)
    assert sim.cut_events == []  # placing never cuts: only a step pressing the blade does


def test_the_scalpel_finds_the_nearest_vertex_exactly(model):
    """The placement's grid search against a brute-force search over every vertex."""
    from hapticrom.online import ScalpelInputError

    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    scalpel = sim.cutting
    V = model.vertices
    rng = np.random.default_rng(3)
    reach = 2.0 * scalpel.cell_size
    points = V[rng.integers(len(V), size=300)] + rng.normal(0.0, 0.5 * reach, (300, 3))
    placed = refused = 0
    for p in np.vstack([points, V[:20]]):
        gap2 = np.sum((V - p) ** 2, axis=1)
        in_region = np.where(scalpel.surface_region >= 0, gap2, np.inf)
        region = int(np.argmin(in_region))
        region = region if in_region[region] <= scalpel.cell_size**2 else -1
        assert scalpel.region_vertex(p) == region
        if gap2.min() > reach**2:
            with pytest.raises(ScalpelInputError, match="off the organ"):
                sim.scalpel(p, [0.0, 1.0, 0.0])
            refused += 1
            continue
        vertex = int(np.argmin(gap2))
        normal = scalpel.normals[vertex]
        blade = np.cross(normal, np.eye(3)[np.argmin(np.abs(normal))])  # in the tangent plane
        sim.scalpel(p, blade)
        placed += 1
        assert scalpel.scalpel_vertex == vertex and scalpel.vertex == region
        np.testing.assert_allclose(scalpel.blade, blade / np.linalg.norm(blade), atol=1e-12)
        across = np.cross(scalpel.blade, scalpel.normals[vertex])
        np.testing.assert_allclose(scalpel.across, across / np.linalg.norm(across), atol=1e-12)
    assert placed > 100 and refused > 10


def test_scalpel_inputs_of_other_types_and_shapes(model):
    from hapticrom.online import ScalpelInputError

    sim = model.simulator()
    point = on_surface(4.6)
    sim.scalpel(point, np.array([0.0, 1.0, 0.0]))
    frame = (sim.cutting.scalpel_vertex, sim.cutting.blade.copy(), sim.cutting.across.copy())
    for p, b in ((point.tolist(), (0, 1, 0)), (point.astype(np.float32), np.array([0, 1, 0]))):
        sim.scalpel(p, b)
        assert sim.cutting.scalpel_vertex == frame[0]
        np.testing.assert_allclose(sim.cutting.blade, frame[1], atol=1e-6)
    sim.scalpel(point, np.array([0.0, 1.0, 0.0]))
    before = (sim.contact_normal.copy(), sim.cutting.blade.copy(), sim.cutting.vertex)
    for p, b, message in (
        (point[:2], [0.0, 1.0, 0.0], r"shape \(2,\)"),
        (np.r_[point, 0.0], [0.0, 1.0, 0.0], r"shape \(4,\)"),
        (point, [0.0, 1.0], r"shape \(2,\)"),
        (point.reshape(3, 1), [0.0, 1.0, 0.0], r"shape \(3, 1\)"),
        ("abc", [0.0, 1.0, 0.0], "3 numbers"),
        (point, [0.0, np.inf, 0.0], "finite"),
    ):
        with pytest.raises(ScalpelInputError, match=message):
            sim.scalpel(p, b)
        np.testing.assert_array_equal(sim.contact_normal, before[0])
        np.testing.assert_array_equal(sim.cutting.blade, before[1])
        assert sim.cutting.vertex == before[2]


def test_a_force_step_with_a_cut_stays_within_the_displacement_limit(model):
    """The cut tissue yields 1 / ratio times more: a force whose displacement with the cut
    would pass max_displacement is refused, though without the cut it would not."""
    from hapticrom.online.simulator import StepInputError

    point = on_surface(4.6)
    sim = model.simulator(max_displacement=0.5 * model.trained_depth)
    sim.scalpel(point, [0.0, 1.0, 0.0])
    n = sim.contact_normal.copy()
    for depth in (0.01, 0.02, 0.04):
        sim.step_displacement(-depth * n)
    ratio = sim.cut_stiffness_ratio
    assert sim.cut_events and ratio < 0.99
    intact = model.simulator()
    intact.set_contact(point)
    # A push whose intact depth is a little under the limit: with the cut, past it.
    push = -intact.step_displacement(-0.5 * (1 + ratio) / 2 * model.trained_depth * n).copy()
    assert np.linalg.norm(intact.step_force(push)) < sim.max_displacement
    depth = sim.depth
    with pytest.raises(StepInputError, match="beyond the displacement limit"):
        sim.step_force(push)
    assert sim.depth == depth
    d = sim.step_force(0.5 * ratio * push)  # within it, cut and all
    assert np.linalg.norm(d) <= sim.max_displacement


def test_the_rendered_cut_cannot_be_written(model):
    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    for depth in (0.01, 0.02, 0.04):
        sim.step_displacement(-depth * sim.contact_normal)
    assert sim.cut_events
    sim.surface_displacement(np.zeros_like(model.vertices))
    vertices, positions, displacement = sim.lip_vertices
    all_vertices, triangles = sim.cut_surface()
    for internal in (vertices, displacement, triangles, all_vertices):
        with pytest.raises(ValueError, match="read-only"):
            internal[...] = 0


def test_placing_the_scalpel_again_at_the_same_place_is_the_same_state(model):
    """The same-place shortcut: after a plain contact elsewhere, or at a new place, the
    placement is made in full; at the same place it only re-arms the blade."""
    blade = np.array([0.0, 1.0, 0.0])
    here, there = on_surface(4.6), on_surface(3.0)
    shortcut, full = model.simulator(), model.simulator()
    shortcut.scalpel(here, blade)
    shortcut.set_contact(there)  # moves the contact away: the next placement is a full one
    shortcut.scalpel(here, blade)
    shortcut.scalpel(here, blade)  # the shortcut
    full.scalpel(here, blade)
    for sim in (shortcut, full):
        sim.step_displacement(-0.05 * sim.contact_normal)
    np.testing.assert_array_equal(shortcut.contact_normal, full.contact_normal)
    np.testing.assert_array_equal(shortcut.step_displacement(-0.05 * full.contact_normal),
                                  full.step_displacement(-0.05 * full.contact_normal))  # fmt: skip
    assert shortcut.weights[0].tolist() == full.weights[0].tolist()


def test_the_tool_radius_is_the_model_attribute(model, monkeypatch):
    """The tool load's radius is /model's contact_radius (checked and covered by the
    artifact's digest), not a value from the campaign's raw JSON."""
    attrs = model.artifact.group_attrs["model"]
    monkeypatch.setitem(attrs, "contact_radius", 0.25 * float(attrs["contact_radius"]))
    monkeypatch.setitem(model.artifact.attrs["campaign"]["load"], "contact_radius", 99.0)
    sim = model.simulator()
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    assert sim.cutting.tool_radius == attrs["contact_radius"]
    assert sim.cutting.cuts.tool.radius == attrs["contact_radius"]


def test_cutting_state_is_declared_in_init(model):
    """The simulator holds one cutting component; neither it nor the cuts grow attributes
    while placing, cutting (waited and in the background) and rendering."""
    sim = model.simulator()
    declared = set(vars(sim))
    assert sim.cutting is None and "cutting" in declared
    sim.scalpel(on_surface(4.6), [0.0, 1.0, 0.0])
    parts = {"controller": sim.cutting, "cuts": sim.cutting.cuts, "worker": sim.cutting.cuts.worker,
             "lips": sim.cutting.lips}  # fmt: skip
    before = {name: set(vars(part)) for name, part in parts.items()}
    n = sim.contact_normal.copy()
    out = np.zeros_like(model.vertices)
    for depth in (0.01, 0.02, 0.04):
        sim.step_displacement(-depth * n)
    sim.scalpel(on_surface(4.6, 8.0), [0.0, 1.0, 0.0], background=True)
    sim.step_displacement(-0.04 * n)
    sim.finish_cuts()
    sim.step_force(-1e-4 * n)
    sim.set_contact(on_surface(4.4))
    sim.surface_displacement(out)
    sim.cut_surface()
    assert sim.cut_events
    assert set(vars(sim)) == declared
    assert {name: set(vars(part)) for name, part in parts.items()} == before
