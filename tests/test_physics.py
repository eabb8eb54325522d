"""The artifact's hyper-reduced physics (format 2.5, group ``hyperreduced``) written by the
trainer and stepped by the runtime, against the full order and the trainer's own model.

A force-controlled HGO campaign on the coarse cornea (conftest's ``force_campaign``): a
region about its centre position on bases that span every position's full-order states,
so those states are the reduced equations' root: pressed as the campaign pressed, the
runtime's steps must settle on them.
"""

from __future__ import annotations

import numpy as np
import pytest

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.offline.reduce.ecsw import ecsw
from hapticrom.offline.reduce.ecsw_model import (
    HyperReducedModel,
    group_nodes,
    mesh_elements,
    rest_tangents,
    training_matrix,
)
from hapticrom.offline.reduce.ecsw_physics import (
    GripNodes,
    add_physics,
    physics_group,
    region_arrays,
)
from hapticrom.offline.reduce.tool_stiffness import ToolLoads
from hapticrom.online.dense_solve import lu_solve
from hapticrom.online.haptic_newton import HapticNewton
from hapticrom.online.model import load
from hapticrom.shared.artifact import read_artifact, with_group, write_artifact
from hapticrom.shared.artifact_rules import CHECK_DATASETS
from hapticrom.shared.errors import ArtifactError, InputError

pytestmark = pytest.mark.serial
RADIUS = 2.5  # mm: the region's tools may be this far from its centre
# tampered()'s change to a group 1.0 file: the grip datasets and the cupping left out
WITHOUT_GRIP = {name: lambda a: None for name in ("grip_offsets", "grip_nodes", "grip_rows")}
AS_1_0 = {"holder_cupping": None}
WITHOUT_CHECK = {name: lambda a: None for name in ("check_element_offsets", *CHECK_DATASETS)}
COARSE = 0.001  # ECSW's tolerance of the region whose sampling errs visibly (its estimate's)


@pytest.fixture(scope="module")
def trained(force_campaign, force_artifact, tmp_path_factory):
    """(config, the centre position's path, Phi, the Galerkin and a sampled model, their
    artifacts' paths)."""
    config, store, _ = force_campaign
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    rest = rest_tangents(mesh)
    data, attrs = store.read_position(0)
    solved = [store.read_position(i)[0] for i in store.completed()]
    U = np.vstack([d["displacement"] for d in solved])
    P = np.vstack([d["pressure"] for d in solved])
    Phi, Psi = np.linalg.qr(U.T)[0], np.linalg.qr(P.T)[0]  # every position's states exact
    states = [(Phi.T @ u, Psi.T @ p) for u, p in zip(U, P, strict=True)]
    G = training_matrix(mesh, Phi, Psi, states, rest=rest)[0]
    models = {"galerkin": HyperReducedModel(mesh, Phi, Psi, rest=rest)}
    for name, tolerance in (("sampled", 1e-4), ("coarse", COARSE)):
        sampling = ecsw(G, tolerance=tolerance)
        models[name] = HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights,
                                         rest=rest)  # fmt: skip
    # the coarse sample's check sample is every element: its estimate is of the sampling's
    # whole error (the trainer's is a second sample at a tighter tolerance)
    checks = {"coarse": models["galerkin"]}
    surface = read_artifact(force_artifact)["surface"]
    loads = ToolLoads(config)
    grip = GripNodes(*group_nodes(config.problem.mesh.file, config.load.surface))
    root = tmp_path_factory.mktemp("physics")
    paths, regions = {}, {}
    for name, model in models.items():
        regions[name] = region_arrays(mesh, model, Phi, surface, attrs["point"], RADIUS, loads,
                                      grip, config.load.contact_radius,
                                      checks.get(name))  # fmt: skip
        paths[name] = add_physics(force_artifact, root / f"{name}.h5", [regions[name]],
                                  mesh.reference.cell, 1e-4)  # fmt: skip
    path = (data, np.asarray(attrs["point"], float))
    return config, path, Phi, models, paths, regions, mesh.reference.cell


def pressed(physics, point, force, factors, ramp=40, hold=60):
    """The physics ramped to ``factors[-1]`` of ``force`` at ``point``, then held."""
    for factor in np.linspace(0.0, factors[-1], ramp + 1)[1:]:
        physics.press(0, point, factor * force)
        assert physics.step()
    for _ in range(hold):
        assert physics.step()
    return physics


def test_a_press_at_a_vertex_is_the_full_orders_load_projected(trained):
    config, (data, point), Phi, _, paths, _, _ = trained
    model = load(paths["galerkin"], isolate=False)
    physics = model.physics()
    assert np.linalg.norm(physics.vertices - point, axis=1).min() < 1e-9  # a vertex
    f = data["load_vector"]
    force = f.reshape(-1, 3).sum(axis=0)
    got = physics.tool_load(point, force)
    assert np.allclose(got, Phi.T @ f, rtol=0, atol=1e-12 * np.abs(Phi.T @ f).max())


@pytest.mark.parametrize("name", ["galerkin", "sampled"])
def test_steps_settle_on_the_trainers_model_and_the_full_order(trained, name):
    """The runtime's region, loaded from the file, pressed as the campaign: its surface
    settles on the trainer's model's equilibrium (1e-8) and, for the Galerkin model on
    its spanning basis, on the full order's (1e-6); the sampled one within 1 %."""
    config, (data, point), Phi, models, paths, _, _ = trained
    model = load(paths[name], isolate=False)
    f = data["load_vector"]
    factors = data["load_factor"]
    # slices=1: a tangent at every step's state (at 3, the 201-element sample's lagging
    # tangent diverged on this 20 + 20 mode basis; test_ecsw_model holds the lagging schedule)
    physics = pressed(model.physics(slices=1), point, f.reshape(-1, 3).sum(axis=0), factors)
    assert physics.refreshes == 0  # a converging schedule never wakes the guard
    out = np.zeros_like(physics.vertices)
    physics.surface_displacement(out)
    nodes = model.artifact["surface"]["nodes"]
    expected = models[name].solve(Phi.T @ f, factors, tolerance=1e-12)[0][-1]
    trainers = (Phi @ expected).reshape(-1, 3)[nodes]
    assert np.linalg.norm(out - trainers) <= 1e-8 * np.linalg.norm(trainers)
    full = data["displacement"][-1].reshape(-1, 3)[nodes]
    tolerance = 1e-6 if name == "galerkin" else 1e-2
    assert np.linalg.norm(out - full) <= tolerance * np.linalg.norm(full)


def test_a_holder_is_the_trainers_penalty_and_pulls_back(trained):
    """A holder 1.5 mm from the press: its rows are the patch's mean and rotation built
    again here from the trainer's basis at the mesh's nodes, the runtime settles on the
    trainer's model with that penalty (1e-8), the dent is shallower than without it and the
    holder pulls the tissue back against the press. (On this basis, states of presses
    only, the hold nearly locks the model: the runtime needs a region basis with the
    holder's responses, as bench/ecsw_tradeoff.py's --held-tool builds.)"""
    config, (data, point), Phi, models, paths, _, _ = trained
    model = load(paths["galerkin"], isolate=False)
    force = data["load_vector"].reshape(-1, 3).sum(axis=0)
    surface = model.artifact["surface"]
    vertices = surface["vertices"]
    grip = vertices[np.argmin(np.abs(np.linalg.norm(vertices - point, axis=1) - 1.5))]
    factors = data["load_factor"]
    free = pressed(model.physics(slices=1), point, force, factors)
    held = pressed(model.physics(holders=[grip], slices=1), point, force, factors)
    dent = [np.dot(p.tool_load(point, force), p.q) / np.linalg.norm(force) for p in (free, held)]
    assert 0 < dent[1] < dent[0]
    assert np.dot(held.holder_force(0), force) < 0
    loadable = np.unique(surface["triangles"][surface["groups"] == 1])
    near = loadable[np.linalg.norm(vertices[loadable] - grip, axis=1) <= config.load.contact_radius]
    n = Phi.shape[1]
    rows = Phi.reshape(-1, 3, n)[surface["nodes"][near]]
    if len(near) < 3:  # a coarse mesh: each vertex held, as the full order's holder
        A = rows.reshape(-1, n)
    else:
        r = vertices[near] - vertices[near].mean(axis=0)
        moment = sum(np.cross(r[k][:, None], rows[k], axis=0) for k in range(len(near)))
        J = sum(r[k] @ r[k] * np.eye(3) - np.outer(r[k], r[k]) for k in range(len(near)))
        A = np.vstack([rows.mean(axis=0), np.sqrt(np.mean(np.sum(r**2, axis=1)))
                       * np.linalg.solve(J, moment)])  # fmt: skip
    assert np.allclose(held.holders[0], A, rtol=0, atol=1e-12)
    trainers = models["galerkin"]
    constant = trainers.linear.copy()
    try:
        trainers.linear[:n, :n] += held.hold_stiffness * (A.T @ A)
        expected = trainers.solve(Phi.T @ data["load_vector"], factors, tolerance=1e-10)[0][-1]
    finally:
        trainers.linear[:] = constant
    assert np.linalg.norm(held.q - expected) <= 1e-8 * np.linalg.norm(expected)


def test_a_holders_rows_are_its_patchs_translation_rotation_and_cupping():
    """On a patch of three nodes or more a holder keeps the mean displacement and the
    least-squares rotation (times the RMS radius) and, ``flat``, the cupping: a basis of a
    translation along x, a rigid rotation about z (u_i = e_z x r_i) and a cupping along z
    (u_i = (|r_i|^2 - their mean) e_z) reads back as exactly those (the translation none
    of the cupping, the cupping none of the mean, |s - mean s| in its own row); on two
    nodes, each node's rows."""
    from hapticrom.online.physics import holder_rows

    rng = np.random.default_rng(4)
    points = rng.normal(size=(5, 3))
    r = points - points.mean(axis=0)
    s = (r**2).sum(axis=1) - (r**2).sum(axis=1).mean()
    basis = np.zeros((5, 3, 3))
    basis[:, 0, 0] = 1.0
    basis[:, :, 1] = np.cross([0.0, 0.0, 1.0], r)
    basis[:, 2, 2] = s
    rigid = holder_rows(basis.reshape(-1, 3), points, np.arange(5))
    flat = holder_rows(basis.reshape(-1, 3), points, np.arange(5), flat=True)
    assert rigid.shape == (6, 3) and np.array_equal(flat[:6], rigid)
    rms = np.sqrt(np.mean(np.sum(r**2, axis=1)))
    assert np.allclose(flat @ [1.0, 0, 0], [1, 0, 0, 0, 0, 0, 0, 0, 0], atol=1e-12)
    assert np.allclose(rigid @ [0, 1.0, 0], [0, 0, 0, 0, 0, rms], atol=1e-12)
    cupping = flat @ [0, 0, 1.0]
    assert np.allclose(cupping[:3], 0, atol=1e-12)
    assert np.allclose(cupping[6:], [0, 0, np.linalg.norm(s)], atol=1e-12)
    two = holder_rows(basis.reshape(-1, 3), points, np.array([1, 3]), flat=True)
    assert np.array_equal(two, basis[[1, 3]].reshape(-1, 3))


def test_a_holder_on_two_vertices_holds_each_and_sums_their_reactions(trained):
    """A grip between two loadable vertices (both within the tool's radius, as the full
    order's holder would hold both): each vertex held, its force the penalty's on their
    displacements summed, read from the drawn surface."""
    config, (data, point), _, _, paths, _, _ = trained
    model = load(paths["galerkin"], isolate=False)
    surface = model.artifact["surface"]
    vertices, radius = surface["vertices"], config.load.contact_radius
    loadable = np.unique(surface["triangles"][surface["groups"] == 1])
    edges = [(a, b) for t in surface["triangles"][surface["groups"] == 1]
             for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))]  # fmt: skip
    grip = None
    for a, b in edges:
        middle = 0.5 * (vertices[a] + vertices[b])
        near = np.linalg.norm(vertices[loadable] - middle, axis=1) <= radius
        if near.sum() == 2 and 1.0 < np.linalg.norm(middle - point) < 2.0:
            grip = middle
            break
    assert grip is not None
    force = data["load_vector"].reshape(-1, 3).sum(axis=0)
    held = pressed(model.physics(holders=[grip], slices=1), point, force, data["load_factor"])
    assert held.holder_nodes == [2] and held.holders[0].shape[0] == 6
    u = np.zeros_like(held.vertices)
    held.surface_displacement(u)
    patch = loadable[np.linalg.norm(vertices[loadable] - grip, axis=1) <= radius]
    expected = -held.hold_stiffness * u[patch].sum(axis=0)
    assert np.allclose(held.holder_force(0), expected, rtol=1e-10, atol=0)
    assert np.dot(held.holder_force(0), force) < 0  # it pulls back against the press


def test_a_holder_grips_the_nodes_the_full_orders_holder_holds(trained):
    """At grips 1-2 mm from the region's centre, the runtime's patch is the full order's
    displacement-controlled tool's (``ContactPatch.blocks``: the nodes of the loadable
    facets within the tool's radius, the mid-side nodes of P2 too): the same positions,
    and the grip rows are the basis at those nodes."""
    from dolfinx import fem
    from mpi4py import MPI

    from hapticrom.offline.fe.contact import ContactPatch
    from hapticrom.offline.fe.dofs import CanonicalOrder
    from hapticrom.offline.fe.organ import load_organ
    from hapticrom.online.element_kernels import CELLS

    config, (_, point), Phi, _, paths, _, _ = trained
    model = load(paths["galerkin"], isolate=False)
    organ = load_organ(config.problem.mesh.file, MPI.COMM_SELF)
    V = fem.functionspace(organ.mesh, ("Lagrange", CELLS[organ.cell_type], (3,)))
    canonical, coordinates = CanonicalOrder(V).canonical_of_global, V.tabulate_dof_coordinates()
    vertices, radius, n = (
        model.artifact["surface"]["vertices"],
        config.load.contact_radius,
        Phi.shape[1],
    )
    grips = vertices[(np.linalg.norm(vertices - point, axis=1) > 1.0)
                     & (np.linalg.norm(vertices - point, axis=1) < 2.0)][:4]  # fmt: skip
    assert len(grips) == 4
    mid_side = 0
    for grip in grips:
        physics = model.physics(holders=[grip], slices=1)
        patch = physics._holder_patch(grip)
        blocks = ContactPatch.around_point(organ, grip, radius, config.load.surface).blocks(V)
        order = np.lexsort(coordinates[blocks].T)
        mine = np.lexsort(physics.grip_points[patch].T)
        assert np.allclose(physics.grip_points[patch][mine], coordinates[blocks][order], atol=1e-12)
        rows = physics.grip_basis.reshape(-1, 3, n)[patch][mine]
        assert np.array_equal(rows, Phi.reshape(-1, 3, n)[canonical[blocks][order]])
        on_surface = np.linalg.norm(physics.grip_points[patch][:, None] - vertices, axis=2)
        mid_side += int((on_surface.min(axis=1) > 1e-9).sum())
    if organ.cell_type == "tetrahedron":  # P2: the mid-side nodes, which the surface lacks
        assert mid_side > 0


def test_a_file_without_grip_nodes_grips_the_loadable_vertices(trained, tmp_path):
    """A group 1.0 file (no grip datasets): a holder grips the loadable surface vertices
    within the tool's radius, their surface rows."""
    config, (_, point), _, _, _, _, _ = trained
    path = tampered(trained, tmp_path, WITHOUT_GRIP, AS_1_0)
    model = load(path, isolate=False)
    surface = model.artifact["surface"]
    vertices = surface["vertices"]
    grip = vertices[np.argmin(np.abs(np.linalg.norm(vertices - point, axis=1) - 1.5))]
    physics = model.physics(holders=[grip], slices=1)
    assert physics.grip_points is physics.vertices
    loadable = np.unique(surface["triangles"][surface["groups"] == 1])
    near = loadable[np.linalg.norm(vertices[loadable] - grip, axis=1) <= config.load.contact_radius]
    assert np.array_equal(physics._holder_patch(grip), near)


def lifted(physics, lift, ramp=40, hold=60):
    """``physics``' holder 0 moved to ``lift`` (3,) mm in ``ramp`` steps, then held."""
    for factor in np.linspace(0.0, 1.0, ramp + 1)[1:]:
        physics.move_holder(0, factor * lift)
        assert physics.step()
    for _ in range(hold):
        assert physics.step()
    return physics


def trainers_hold(model, physics) -> np.ndarray:
    """``model`` (a trainer's) with ``physics``' holder penalty k A^T A and its load k A^T
    t solved (Newton, 1e-10): the state the runtime must settle on."""
    A, t = physics.holders[0], physics.holder_targets[0]
    n = A.shape[1]
    constant = model.linear.copy()
    try:
        model.linear[:n, :n] += physics.hold_stiffness * (A.T @ A)
        pull = physics.hold_stiffness * (A.T @ t)
        return model.solve(pull, np.linspace(0.1, 1.0, 10), tolerance=1e-10)[0][-1]
    finally:
        model.linear[:] = constant


def outward(vertices, grip, length) -> np.ndarray:
    """(3,) mm: ``length`` along the grip's direction from the surface's mean (out of it)."""
    away = grip - vertices.mean(axis=0)
    return length * away / np.linalg.norm(away)


def test_a_moved_holder_lifts_its_patch_as_the_trainers_model(trained):
    """Grasp-and-lift: a holder moved 0.05 mm out of the surface, nothing pressing. The
    runtime settles on the trainer's model with the penalty about the moved grip (its load
    k A^T t, 1e-8), the patch follows the grip (to 1e-3 of the lift), and the holder pulls
    the tissue along the lift; a refused move changes nothing."""
    config, (data, point), Phi, models, paths, _, _ = trained
    model = load(paths["galerkin"], isolate=False)
    vertices = model.artifact["surface"]["vertices"]
    grip = vertices[np.argmin(np.abs(np.linalg.norm(vertices - point, axis=1) - 1.5))]
    lift = outward(vertices, grip, 0.05)
    physics = lifted(model.physics(holders=[grip], slices=1), lift)
    before = [physics.load.copy(), physics.holder_targets[0].copy(), physics.holder_loads.copy()]
    for bad in ([np.nan, 0, 0], np.array([np.nan, 0, 0]), np.array([0, 0, 2e4]), [0, 0], "up"):
        with pytest.raises(InputError, match="displacement"):
            physics.move_holder(0, bad)
    with pytest.raises(InputError, match="holder must be"):
        physics.move_holder(1, lift)
    after = [physics.load, physics.holder_targets[0], physics.holder_loads]
    assert all(np.array_equal(a, b) for a, b in zip(before, after, strict=True))
    expected = trainers_hold(models["galerkin"], physics)
    assert np.linalg.norm(physics.q - expected) <= 1e-8 * np.linalg.norm(expected)
    u = np.zeros_like(vertices)
    physics.surface_displacement(u)
    assert physics.holder_nodes[0] < 3  # the coarse mesh: each node held
    surface = model.artifact["surface"]
    loadable = np.unique(surface["triangles"][surface["groups"] == 1])
    patch = loadable[
        np.linalg.norm(vertices[loadable] - grip, axis=1) <= config.load.contact_radius
    ]
    assert np.abs(u[patch] - lift).max() <= 1e-3 * np.linalg.norm(lift)
    assert np.dot(physics.holder_force(0), lift) > 0
    # a press beside the lifted holder: the guard judges the pressing load alone (beside
    # the holder's k A^T t any press had passed as steady: a fresh tangent for each)
    force = data["load_vector"].reshape(-1, 3).sum(axis=0)
    for factor in np.linspace(0.0, 0.5, 11)[1:]:
        physics.press(0, point, factor * force)
        assert physics.step()
    assert physics.refreshes == 0


def test_a_wide_holder_lifts_its_patch_as_the_trainers_model(trained, tmp_path):
    """A grip of three nodes or more (the tool's radius widened 2.5 times in the loaded
    model: on the coarse mesh a tool grips one node), moved 0.05 mm out of the surface: a
    1.0 file's holder keeps the patch's mean and rotation (6 rows), a 1.1 file's its
    cupping too (9). Each settles on the trainer's model with its penalty and load (1e-8),
    its force is the penalty on the mean's gap (read from the drawn surface), along the
    lift; the rigid hold's mean follows the grip to 1e-3 of the lift, and the flat hold
    cups the patch less than the rigid one."""
    from hapticrom.online.physics import flatness_weights

    config, (_, point), Phi, models, paths, _, _ = trained
    grip_less = tampered(trained, tmp_path, WITHOUT_GRIP, AS_1_0)
    as_1_1 = tampered(trained, tmp_path, {}, {"holder_cupping": 1}, name="cupping.h5")
    radius = 2.5 * config.load.contact_radius
    cupping = {}
    for rows, path in ((6, grip_less), (9, as_1_1)):
        model = load(path, isolate=False)
        model.artifact.group_attrs["model"]["contact_radius"] = radius  # in memory only
        vertices = model.artifact["surface"]["vertices"]
        grip = vertices[np.argmin(np.abs(np.linalg.norm(vertices - point, axis=1) - 1.5))]
        lift = outward(vertices, grip, 0.05)
        physics = lifted(model.physics(holders=[grip], slices=1), lift)
        assert physics.holder_nodes[0] >= 3 and physics.holders[0].shape[0] == rows
        expected = trainers_hold(models["galerkin"], physics)
        assert np.linalg.norm(physics.q - expected) <= 1e-8 * np.linalg.norm(expected)
        u = np.zeros_like(vertices)
        physics.surface_displacement(u)
        surface = model.artifact["surface"]
        loadable = np.unique(surface["triangles"][surface["groups"] == 1])
        patch = loadable[np.linalg.norm(vertices[loadable] - grip, axis=1) <= radius]
        assert len(patch) == physics.holder_nodes[0]
        mean = u[patch].mean(axis=0)
        pull = physics.holder_force(0)
        assert np.allclose(pull, -physics.hold_stiffness * (mean - lift), rtol=1e-9, atol=0)
        assert np.dot(pull, lift) > 0
        if rows == 6:
            assert np.linalg.norm(mean - lift) <= 1e-3 * np.linalg.norm(lift)
        cupping[rows] = np.linalg.norm(flatness_weights(vertices[patch]) @ u[patch])
    assert cupping[9] < cupping[6]


@pytest.fixture(scope="module")
def held(trained, tmp_path_factory):
    """A held region (group 1.3) on the coarse cornea: a holder 1.5 mm from the centre
    gripping the grip nodes within 2.5 tools' radii (on this mesh a tool grips one node),
    the trainer's basis with the responses with that patch held (its rigid motions, and
    the centre position's press with the patch at rest), its Galerkin model, the hold
    patterns of the responses' reactions; and the same region without them (a holder
    that keeps its patch's mean and rotation). A dict of what the tests read."""
    from hapticrom.offline.reduce.ecsw_model import rest_operators
    from hapticrom.offline.reduce.ecsw_regions import held_patch_responses, hold_patterns

    config, (data, point), Phi, _, paths, _, cell = trained
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    rest = rest_tangents(mesh)
    operators = rest_operators(mesh, rest)
    grip = GripNodes(*group_nodes(config.problem.mesh.file, config.load.surface))
    wide = 2.5 * config.load.contact_radius
    site = grip.points[np.argmin(np.abs(np.linalg.norm(grip.points - point, axis=1) - 1.5))]
    free = np.flatnonzero(np.abs(Phi).max(axis=1) > 0)
    loads = data["load_vector"][:, None]
    columns, reactions = held_patch_responses(operators, grip, site, wide, free, loads)
    basis = np.linalg.qr(np.hstack([Phi, columns]))[0]
    condensed = (operators.Bt.T @ columns / operators.compliance[:, None]).T  # their pressures
    Psi = np.linalg.qr(np.vstack([data["pressure"], condensed]).T)[0]
    model = HyperReducedModel(mesh, basis, Psi, rest=rest)
    patch = grip.patch(site, wide)
    patterns = hold_patterns(reactions)
    surface = read_artifact(paths["galerkin"])["surface"]
    root = tmp_path_factory.mktemp("held")
    out = {}
    for name, hold in (("held", (patch, patterns)), ("moments", None)):
        region = region_arrays(mesh, model, basis, surface, point, RADIUS, ToolLoads(config),
                               grip, config.load.contact_radius, None, hold)  # fmt: skip
        out[name] = add_physics(paths["galerkin"], root / f"{name}.h5", [region], cell, 1e-4)
        out[name + "_region"] = region
    return {**out, "model": model, "basis": basis, "site": site, "wide": wide, "grip": grip,
            "patch": patch, "patterns": patterns, "columns": columns, "reactions": reactions,
            "operators": operators, "free": free, "loads": loads}  # fmt: skip


def test_held_patch_responses_are_the_linear_full_orders_hold(held):
    """``held_patch_responses``: on the patch, each column is its motion (unit translations
    and rotations) or zero (the press); off it, the free rows are in equilibrium (K x = g)
    and the rest zero; the reactions are K x - g there. Betti's reciprocity: the motions'
    work matrix m_j^T R_k is symmetric positive definite, and the press's reactions do on
    a motion the work the motion's response does against the press, m_j^T R_g =
    -x_j^T g. The hold patterns are orthonormal and span the reactions to their
    tolerance."""
    from hapticrom.offline.reduce.ecsw_regions import (
        HOLD_PATTERNS,
        held_patch_responses,
        patch_motions,
    )

    grip, patch, X, R = held["grip"], held["patch"], held["columns"], held["reactions"]
    K, g, free = held["operators"].condensed(), held["loads"][:, 0], held["free"]
    assert len(patch) >= 3 and X.shape[1] == 7
    rows = (3 * grip.nodes[patch][:, None] + np.arange(3)).ravel()
    motions = patch_motions(grip.points[patch]).reshape(len(rows), 6)
    assert np.array_equal(X[rows, :6], motions) and not X[rows, 6].any()
    inner = np.setdiff1d(free, rows)
    assert not X[np.setdiff1d(np.arange(len(X)), free)].any()
    loads = np.zeros_like(X)
    loads[:, 6] = g
    residual = (K @ X - loads)[inner]
    # to rounding of the near-incompressible K's largest terms times the columns'
    rounding = 1e-12 * np.abs(K).max() * np.abs(X).max()
    assert np.abs(residual).max() <= rounding
    assert np.allclose(R, (K @ X - loads)[rows], rtol=0, atol=rounding)
    work = motions.T @ R[:, :6]
    assert np.allclose(work, work.T, rtol=0, atol=1e-9 * np.abs(work).max())
    assert np.linalg.eigvalsh(0.5 * (work + work.T)).min() > 0
    betti = -X[:, :6].T @ g
    assert np.allclose(motions.T @ R[:, 6], betti, rtol=0, atol=1e-8 * np.abs(betti).max())
    L = held["patterns"]
    assert np.allclose(L.T @ L, np.eye(L.shape[1]), rtol=0, atol=1e-12)
    supported = np.flatnonzero(~np.isin(3 * grip.nodes, free))  # grip nodes the supports hold
    assert len(supported)
    with pytest.raises(InputError, match="grips a supported node"):
        held_patch_responses(held["operators"], grip, grip.points[supported[0]], held["wide"],
                             free, held["loads"])  # fmt: skip
    unit = R / np.linalg.norm(R, axis=0)
    assert np.linalg.norm(unit - L @ (L.T @ unit)) <= HOLD_PATTERNS * np.linalg.norm(unit, 2) * 3


def test_a_held_regions_holder_holds_its_patch_in_its_patterns(held):
    """The holder the region was built for holds s L^T A (s = P^-1/2; built again here
    from the trainer's basis at the patch's nodes), settles on the trainer's model with
    that penalty and load (1e-8), pulls with the patterns' nodal forces summed, and lifted
    by 1 um moves the surface as the full order's linear hold (the patch translated, the
    rest free: 2e-3) and pulls with its reactions summed (2e-3), where the same region
    holding the patch's mean and rotation (a file without the hold patterns), or its
    cupping too (as a 1.1 file's holder), is off by over ten times as much; a holder
    elsewhere keeps its patch's mean and rotation (a 1.3 file's bases carry no cupping
    responses)."""
    fields, errors = {}, {}
    for name in ("held", "moments", "cupping"):
        model = load(held["moments" if name == "cupping" else name], isolate=False)
        model.artifact.group_attrs["model"]["contact_radius"] = held["wide"]  # in memory only
        if name == "cupping":  # as a 1.1 file's holder, on the same basis
            model.artifact.group_attrs["hyperreduced"]["holder_cupping"] = 1
        nodes = model.artifact["surface"]["nodes"]
        vertices = model.artifact["surface"]["vertices"]
        lift = outward(vertices, held["site"], 1e-3)
        physics = lifted(model.physics(holders=[held["site"]], slices=1), lift)
        u = np.zeros_like(vertices)
        physics.surface_displacement(u)
        linear = (held["columns"][:, :3] @ lift).reshape(-1, 3)[nodes]
        errors[name] = np.linalg.norm(u - linear) / np.linalg.norm(linear)
        fields[name] = physics
    physics = fields["held"]
    patch, L, basis = held["patch"], held["patterns"], held["basis"]
    n = basis.shape[1]
    rows = basis.reshape(-1, 3, n)[held["grip"].nodes[patch]].reshape(-1, n)
    s = 1.0 / np.sqrt(len(patch))
    assert np.allclose(physics.holders[0], s * L.T @ rows, rtol=0, atol=1e-12)
    expected = trainers_hold(held["model"], physics)
    assert np.linalg.norm(physics.q - expected) <= 1e-8 * np.linalg.norm(expected)
    lift = outward(vertices, held["site"], 1e-3)
    target = s * L.T @ np.tile(lift, len(patch))
    assert np.allclose(physics.holder_targets[0], target, rtol=0, atol=1e-15)
    load_ = physics.hold_stiffness * physics.holders[0].T @ target
    assert np.allclose(physics.holder_loads[0], load_, rtol=0, atol=1e-12 * np.abs(load_).max())
    # the full order's linear hold pulls with its patch's reactions summed (K x on the patch)
    reaction = (held["reactions"][:, :3] @ lift).reshape(-1, 3).sum(axis=0)
    pull = physics.holder_force(0)
    assert np.linalg.norm(pull - reaction) <= 2e-3 * np.linalg.norm(reaction)
    assert [fields[k].holders[0].shape[0] for k in ("moments", "cupping")] == [6, 9]
    assert errors["held"] <= 2e-3
    assert min(errors["moments"], errors["cupping"]) >= 10 * errors["held"]
    elsewhere = held["site"] + np.array([0.3, 0.0, 0.0])
    other = load(held["held"], isolate=False)
    other.artifact.group_attrs["model"]["contact_radius"] = held["wide"]
    assert other.physics(holders=[elsewhere], slices=1).holders[0].shape[0] == 6


def test_refused_input_changes_nothing(trained, force_artifact):
    config, (data, point), _, _, paths, _, _ = trained
    model = load(paths["galerkin"], isolate=False)
    physics = model.physics()
    force = data["load_vector"].reshape(-1, 3).sum(axis=0)
    physics.press(0, point, force)
    before = physics.load.copy()
    far = physics.centre + np.array([RADIUS + 1.0, 0.0, 0.0])
    below = point + [0, 0, -1.0]  # inside the region, 1 mm under its loadable surface
    for args, message in (((point, [np.nan, 0, 0]), "force"), (([0, 0], force), "point"),
                          ((far, force), "outside the region"),
                          ((below, force), "off the region's loadable")):  # fmt: skip
        with pytest.raises(InputError, match=message):
            physics.press(0, *args)
    assert np.array_equal(physics.load, before)
    for tool in (True, 1.0, "a", None):
        with pytest.raises(InputError, match="tool id"):
            physics.press(tool, point, force)
    with pytest.raises(InputError, match="force"):
        physics.press(0, point, [0.0, 0.0, 1e6])  # beyond any tissue's
    assert np.array_equal(physics.load, before)
    for kwargs, message in (({"region": 1}, "region must be"), ({"region": 0.5}, "region"),
                            ({"region": True}, "region"), ({"iterations": 0}, "iterations"),
                            ({"iterations": 1000}, "iterations"), ({"slices": 2.0}, "slices"),
                            ({"holders": None}, "holders must be"),
                            ({"holders": [far]}, "outside the region"),
                            ({"holders": [point + [0, 0, 1.0]]}, "no loadable surface node"),
                            ({"holders": [[np.inf, 0, 0]]}, "holder")):  # fmt: skip
        with pytest.raises(InputError, match=message):
            model.physics(**kwargs)
    out = np.zeros_like(physics.vertices)
    out.flags.writeable = False
    for bad in (np.zeros((3, 3)), out, np.zeros_like(physics.vertices, order="F"),
                physics.vertices.tolist()):  # fmt: skip
        with pytest.raises(InputError, match="writeable C-contiguous float64"):
            physics.surface_displacement(bad)
    with pytest.raises(InputError, match="holder must be"):
        physics.holder_force(0)  # none holds
    physics.release(0)
    assert not physics.load.any()
    with pytest.raises(InputError, match="no hyper-reduced physics"):
        load(force_artifact, isolate=False).physics()


def test_release_leaves_the_other_tools_load_exactly(trained):
    """A huge force released leaves no rounding behind: the load is summed again."""
    model = load(trained[4]["galerkin"], isolate=False)
    physics = model.physics()
    point = trained[1][1]
    physics.press(0, point, [0.0, 0.0, -0.01])
    alone = physics.load.copy()
    physics.press(1, point, [0.0, 0.0, -9e4])
    physics.release(1)
    assert np.array_equal(physics.load, alone)


def test_a_singular_tangent_is_the_files_error(trained, tmp_path):
    """A constant tangent that cancels the sampled sums' at rest: the file's error."""
    galerkin = trained[3]["galerkin"]
    n, n_p = galerkin.n, galerkin.n_p
    sampled = galerkin.residual_tangent(np.zeros(n), np.zeros(n_p), np.zeros(n))[1]
    sampled = sampled - galerkin.linear
    cancelling = -0.5 * (sampled + sampled.T)
    model = load(tampered(trained, tmp_path, {"constant_tangent": lambda a: cancelling[None]}),
                 isolate=False)  # fmt: skip
    with pytest.raises(ArtifactError, match="constant_tangent: region 0"):
        model.physics()


def test_a_small_region_steps_with_fewer_slices(trained, tmp_path):
    """A region of 5 sampled elements: the default 30 tangent parts become 5, of one
    element each."""

    def first(k):
        return lambda a: a[:k]

    change = {name: first(5) for name in ("element_nodes", "weights", "basis_rows",
                                          "pressure_rows", "parameters")}  # fmt: skip
    change["element_offsets"] = lambda a: np.array([0, 5])
    physics = load(tampered(trained, tmp_path, change), isolate=False).physics()
    assert np.array_equal(physics.newton.bounds, np.arange(6))


def tampered(trained, tmp_path, change, attrs=None, region="galerkin", name="tampered.h5"):
    """The ``region``'s group with ``change`` (name -> function of the array, or of
    None: the dataset left out) and ``attrs`` (None: left out) written
    and read back: the writer's read-back refuses what the reader refuses."""
    _, _, _, _, paths, regions, cell = trained
    group = physics_group([regions[region]], cell, 1e-4)
    for name, edit in change.items():
        group[name] = edit(np.array(group[name]))
        if group[name] is None:  # the dataset left out
            del group[name]
    group["attrs"].update(attrs or {})
    group["attrs"] = {k: v for k, v in group["attrs"].items() if v is not None}
    content, root = with_group(read_artifact(paths["galerkin"]), "hyperreduced", group)
    write_artifact(tmp_path / name, content, root)
    return tmp_path / name


def _set(index, value):
    def edit(a):
        a[index] = value
        return a

    return edit


@pytest.mark.parametrize(
    "change, attrs, message",
    [
        ({"element_offsets": _set(-1, 1)}, None, "element_offsets must rise"),
        ({"load_offsets": _set(0, 1)}, None, "load_offsets must rise"),
        ({"pressure_rows": lambda a: np.hstack([a, a[:, :1]])}, None, "shape|n \\+ n_p"),
        ({"parameters": _set((0, 0), 7.0)}, None, "unknown law id"),
        ({"parameters": _set((0, 1), -1.0)}, None, "kappa"),
        ({"parameters": _set((0, 8), 2.0)}, None, "m0 is not a unit vector"),
        ({"parameters": _set((0, 5), 1e6)}, None, "k2"),
        ({"weights": _set(0, 0.0)}, None, "weights has values that are not positive"),
        ({"weights": _set(0, 1e7)}, None, "weights has values beyond"),
        ({"basis_rows": _set((0, 0, 0), 1.5)}, None, "basis_rows has values beyond"),
        ({"tool_loads": _set((0, 0, 0), 11.0)}, None, "tool_loads has values beyond"),
        ({"constant_tangent": _set((0, 0, 1), 1e9)}, None, "not symmetric"),
        ({"load_vertices": _set(0, -1)}, None, "load_vertices"),
        (
            {
                "centres": lambda a: a[:0],
                "radii": lambda a: a[:0],
                "constant_tangent": lambda a: a[:0],
                "surface_basis": lambda a: a[:0],
                "element_offsets": lambda a: a[:1],
                "load_offsets": lambda a: a[:1],
                "grip_offsets": lambda a: a[:1],
            },
            None,
            "no region",
        ),
        ({"element_nodes": _set((0, 0, 0), np.nan)}, None, "NaN"),
        ({"grip_offsets": _set(-1, 1)}, None, "grip_offsets must rise"),
        ({"grip_rows": _set((0, 0, 0), 1.5)}, None, "grip_rows has values beyond"),
        ({"grip_nodes": _set((0, 0), 2e4)}, None, "grip_nodes: region 0 has a node .* from its"),
        ({"grip_nodes": _set((0, 0), 9e3)}, None, "grip_nodes: region 0 has a node .* from its"),
        ({"grip_nodes": lambda a: np.vstack([a[:1], a[:-1]])}, None, "repeats a node"),
        ({}, {"holder_cupping": 2}, "holder_cupping"),
        ({"grip_nodes": _set((0, 0), np.nan)}, None, "NaN"),
        ({"grip_rows": lambda a: None}, None, "go together"),
        ({}, {"cell": "tetrahedron"}, "nodes an element"),
        ({}, {"hold_stiffness": -1.0}, "hold_stiffness"),
    ],
)
def test_the_reader_refuses_a_tampered_group(trained, tmp_path, change, attrs, message):
    with pytest.raises(ArtifactError, match=message):
        tampered(trained, tmp_path, change, attrs)
    assert not (tmp_path / "tampered.h5").exists()


def test_held_and_unheld_regions_share_a_file(trained, held, tmp_path):
    """A file of a held region and one without a holder (hold datasets of an empty slice):
    written, read back, the first's holder holds its patterns, the second's its mean and
    rotation."""
    group = physics_group([held["held_region"], held["moments_region"]], trained[6], 1e-4)
    assert list(group["hold_offsets"]) == [0, len(held["patch"]), len(held["patch"])]
    content, root = with_group(read_artifact(held["held"]), "hyperreduced", group)
    write_artifact(tmp_path / "two.h5", content, root)
    model = load(tmp_path / "two.h5", isolate=False)
    model.artifact.group_attrs["model"]["contact_radius"] = held["wide"]
    rows = [model.physics(region=r, holders=[held["site"]]).holders[0].shape[0] for r in (0, 1)]
    assert rows == [held["patterns"].shape[1], 6]


def _scaled(a):
    a[..., 0] *= 1.01
    return a


@pytest.mark.parametrize(
    "change, message",
    [
        ({"hold_offsets": _set(-1, 1)}, "hold_offsets must rise"),
        ({"hold_nodes": lambda a: np.r_[a[:1], a[:-1]]}, "not distinct rows"),
        ({"hold_nodes": _set(0, 10**6)}, "not distinct rows"),
        ({"hold_nodes": _set(0, -1)}, "hold_nodes"),
        ({"hold_ranks": _set(0, 0)}, "hold_ranks: region 0's 0 does not fit"),
        ({"hold_ranks": _set(0, 10**6)}, "hold_ranks"),
        ({"hold_ranks": lambda a: a - 1}, "beyond its rank"),
        ({"hold_reactions": _scaled}, "not orthonormal"),
        ({"hold_reactions": _set((0, 0, 0), np.nan)}, "NaN"),
        ({"hold_ranks": lambda a: None}, "go together"),
        (
            {name: lambda a: None for name in ("grip_offsets", "grip_nodes", "grip_rows")},
            "the file has none",
        ),
    ],
)
def test_the_reader_refuses_tampered_hold_patterns(trained, held, tmp_path, change, message):
    group = physics_group([held["held_region"]], trained[6], 1e-4)
    for name, edit in change.items():
        group[name] = edit(np.array(group[name]))
        if group[name] is None:
            del group[name]
    content, root = with_group(read_artifact(held["held"]), "hyperreduced", group)
    with pytest.raises(ArtifactError, match=message):
        write_artifact(tmp_path / "tampered.h5", content, root)
    assert not (tmp_path / "tampered.h5").exists()


def test_unsigned_offsets_that_fall_are_refused(trained, tmp_path):
    """Two regions whose uint32 element offsets fall (np.diff would wrap them round)."""
    _, _, _, _, paths, regions, cell = trained
    group = physics_group([regions["galerkin"]] * 2, cell, 1e-4)
    total = group["element_offsets"][-1]
    group["element_offsets"] = np.array([0, total + 1, total], np.uint32)
    content, root = with_group(read_artifact(paths["galerkin"]), "hyperreduced", group)
    with pytest.raises(ArtifactError, match="element_offsets must rise"):
        write_artifact(tmp_path / "two.h5", content, root)


def test_a_load_vertex_off_the_loadable_surface_is_refused(trained, tmp_path):
    model = load(trained[4]["galerkin"], isolate=False)
    s = model.artifact["surface"]
    loadable = np.zeros(len(s["vertices"]), bool)
    loadable[s["triangles"][s["groups"] == 1].ravel()] = True
    other = int(np.flatnonzero(~loadable)[0])
    with pytest.raises(ArtifactError, match="no loadable triangle"):
        tampered(trained, tmp_path, {"load_vertices": _set(0, other)})


def test_a_tangled_element_is_refused_when_stepped(trained, tmp_path):
    """The reader cannot tell a tangled element (no rule of its own: the cell's Jacobian
    is the runtime's); the physics refuses it before any step."""

    def swap(a):
        a[0, [0, 1]] = a[0, [1, 0]]
        return a

    model = load(tampered(trained, tmp_path, {"element_nodes": swap}), isolate=False)
    with pytest.raises(ArtifactError, match="element 0 is tangled"):
        model.physics()


def test_a_tangent_diverging_under_a_steady_ramp_is_taken_again_fresh(trained, monkeypatch):
    """The coarse region (ECSW 1e-3) pressed to three times the campaign's force in 100
    equal steps, the tangent in 10 parts, then held: the lagging tangent diverges during
    the ramp (the schedule alone refuses steps; without the ramp's guard, RAMP_JUMP
    infinite, the physics refuses its 43rd step for good). With it every step is taken, a
    few on a fresh tangent, and the state settles on the trainer's model's equilibrium."""
    import hapticrom.online.physics as physics_module

    config, (data, point), Phi, models, paths, _, _ = trained
    f, factors = 3.0 * data["load_vector"], data["load_factor"]
    force = f.reshape(-1, 3).sum(axis=0)
    ramp = list(np.linspace(0.0, factors[-1], 101)[1:]) + [factors[-1]] * 50
    taken = {}
    for jump in (np.inf, physics_module.RAMP_JUMP):
        monkeypatch.setattr(physics_module, "RAMP_JUMP", jump)
        physics = load(paths["coarse"], isolate=False).physics(slices=10)
        bare = HapticNewton(physics.newton.sample, physics.newton.linear, 1, 10)
        q, pi, refused = np.zeros_like(physics.q), np.zeros_like(physics.pi), 0
        steps = []
        for factor in ramp:
            physics.press(0, point, factor * force)
            steps.append(physics.step())
            refused += not bare.step(q, pi, physics.load)
        assert refused > 0  # the schedule alone diverges
        taken[jump] = all(steps)
    assert taken == {np.inf: False, physics_module.RAMP_JUMP: True}
    assert 0 < physics.refreshes <= 10
    expected = models["coarse"].solve(Phi.T @ f, factors, tolerance=1e-12)[0][-1]
    assert np.linalg.norm(physics.q - expected) <= 1e-8 * np.linalg.norm(expected)


def test_the_guard_takes_a_diverging_step_again_on_a_fresh_tangent(trained):
    """The haptic schedule (a tangent part a step, 3 parts) on the sampled region, pressed
    as the campaign in 40 steps, then held for 60. Without the guard (HapticNewton alone)
    the lagging tangent diverges at the hold: in the 8th held step the update jumps from
    0.016 to 0.146 of the state, by the 13th it reaches 0.51, and every step after is
    refused. With it, every step is taken, a few on a fresh tangent, and the state settles
    on the trainer's model's equilibrium."""
    config, (data, point), Phi, models, paths, _, _ = trained
    f, factors = data["load_vector"], data["load_factor"]
    force = f.reshape(-1, 3).sum(axis=0)
    physics = load(paths["sampled"], isolate=False).physics(slices=3)
    bare = HapticNewton(physics.newton.sample, physics.newton.linear, 1, 3)
    q, pi, refused = np.zeros_like(physics.q), np.zeros_like(physics.pi), 0
    for factor in list(np.linspace(0.0, factors[-1], 41)[1:]) + [factors[-1]] * 60:
        physics.press(0, point, factor * force)
        assert physics.step()
        refused += not bare.step(q, pi, physics.load)
    assert refused > 0  # the schedule alone diverges
    assert 0 < physics.refreshes <= 10
    expected = models["sampled"].solve(Phi.T @ f, factors, tolerance=1e-12)[0][-1]
    assert np.linalg.norm(physics.q - expected) <= 1e-8 * np.linalg.norm(expected)


def test_a_refresh_is_the_tangent_at_the_state(trained):
    """HapticNewton.refresh factorises the tangent at the given state (the trainer's
    model's), drops the tangent being built and starts the parts again."""
    _, _, _, models, _, _, _ = trained
    model = models["sampled"]
    newton = HapticNewton(model.sample, model.linear, 1, 3)
    rng = np.random.default_rng(3)
    q, pi = 1e-2 * rng.standard_normal(model.n), 1e-3 * rng.standard_normal(model.n_p)
    assert newton.refresh(q, pi)
    K = model.residual_tangent(q, pi, np.zeros(model.n))[1]
    x = rng.standard_normal(K.shape[0])
    b = K @ x
    lu_solve(newton.lu, newton.pivots[0], b)
    assert np.allclose(b, x, rtol=0, atol=1e-8 * np.abs(x).max())
    assert newton.part == 0 and np.array_equal(newton.building, model.linear)


def test_pressing_again_allocates_nothing(trained):
    """A haptic loop presses every step: after a tool's first press, pressing again with
    float64 arrays allocates nothing of its own. tracemalloc sees every Python and numpy
    allocation; the peak over 1000 presses is held to that of 1000 bare calls of the
    compiled blend (numba boxing its ten arguments, about 0.5 KB), with less to spare than
    one reduced load's data (8 n bytes; the einsum blend that press had before peaked at
    5.4 KB)."""
    import tracemalloc

    from hapticrom.online.physics import _tool_load

    model = load(trained[4]["galerkin"], isolate=False)
    physics = model.physics()
    point = np.array(trained[1][1], dtype=np.float64)
    forces = [np.array([0.0, 0.0, -0.01]), np.array([0.001, 0.0, -0.02])]
    physics.press(0, point, forces[0])
    physics.press(1, point, forces[1])
    expected = physics.tool_load(point, forces[0]) + physics.tool_load(point, forces[1])
    p, out = physics, np.empty(len(physics.load))
    arguments = (point, forces[0], p.centre, p.radius, p.contact_radius, p.load_points,
                 p.triangles, p.tool_loads, p._weights, out)  # fmt: skip

    def peak(call) -> tuple[int, int]:
        tracemalloc.start()
        try:
            base, _ = tracemalloc.get_traced_memory()
            for k in range(1000):
                call(k)
            current, top = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        return current - base, top - base

    bare = peak(lambda k: _tool_load(*arguments))
    kept, pressing = peak(lambda k: physics.press(k % 2, point, forces[k % 2]))
    assert np.allclose(physics.load, expected, rtol=1e-14, atol=0)
    assert kept < 256 and pressing < bare[1] + 8 * len(out), (kept, pressing, bare)


def settled(trained, path, estimate_steps, hold=60, precision="single"):
    """The physics of ``path`` (a tangent every step) pressed as the campaign, then held."""
    _, (data, point), _, _, _, _, _ = trained
    f = data["load_vector"]
    physics = load(path, isolate=False).physics(slices=1, estimate_steps=estimate_steps,
                                                precision=precision)  # fmt: skip
    return pressed(physics, point, f.reshape(-1, 3).sum(axis=0), data["load_factor"], hold=hold)


def test_the_error_estimate_is_a_newton_step_on_the_samples_difference(trained):
    """Settled under the campaign's press, the coarse region's estimate is one Newton step,
    on the model's tangent, of the check model (here every element) from the model's
    state: the trainer's models (numpy, LAPACK) at that state give the same to 1e-8; and
    it reads the gap between the two models' equilibria (solved apart) within a factor of
    two (0.89 % against 0.78 % when written: the model's tangent is not the check's)."""
    _, (data, _), Phi, models, paths, _, _ = trained
    physics = load(paths["coarse"], isolate=False).physics(estimate_steps=5)
    assert np.isnan(physics.error_estimate())  # no estimate finished yet
    physics = settled(trained, paths["coarse"], 5, precision="double")  # T as LAPACK's
    eta, q, pi = physics.error_estimate(), physics.q, physics.pi
    load_ = Phi.T @ data["load_vector"]
    r, T = models["coarse"].residual_tangent(q, pi, data["load_factor"][-1] * load_)
    r_check = models["galerkin"].residual(q, pi, data["load_factor"][-1] * load_)
    step = np.linalg.solve(T, r_check - r)[: len(q)]
    assert abs(eta - np.linalg.norm(step) / np.linalg.norm(q)) <= 1e-8 * eta
    sampled, galerkin = (models[name].solve(load_, data["load_factor"], tolerance=1e-12)[0][-1]
                         for name in ("coarse", "galerkin"))  # fmt: skip
    gap = np.linalg.norm(galerkin - sampled) / np.linalg.norm(sampled)
    assert gap > 1e-3  # the sampling errs visibly: else the test reads nothing
    assert 0.5 * gap <= eta <= 2 * gap, (eta, gap)


def test_the_estimate_is_nan_without_a_check_sample_or_with_none_asked(trained):
    physics = settled(trained, trained[4]["sampled"], 5, hold=5)
    assert np.isnan(physics.error_estimate())
    physics = settled(trained, trained[4]["coarse"], 0, hold=5)
    assert physics.check is None and np.isnan(physics.error_estimate())


def own_check(group):
    """``group`` with the check sample replaced by the model's own sample."""
    for name in ("check_element_offsets", *CHECK_DATASETS):
        group[name] = group[name.removeprefix("check_")]
    return group


def test_the_estimate_changes_nothing_and_reads_zero_on_the_models_own_sample(trained, tmp_path):
    """A check sample that is the model's own: the two sums cancel exactly, eta = 0; and
    the states are those of the same physics without a check sample, bit for bit."""
    _, _, _, _, paths, regions, cell = trained
    group = own_check(physics_group([regions["coarse"]], cell, 1e-4))
    content, root = with_group(read_artifact(paths["coarse"]), "hyperreduced", group)
    write_artifact(tmp_path / "own.h5", content, root)
    own = settled(trained, tmp_path / "own.h5", 7)
    bare = settled(trained, tampered(trained, tmp_path, WITHOUT_CHECK, region="coarse"), 7)
    assert own.error_estimate() == 0.0 and np.isnan(bare.error_estimate())
    assert np.array_equal(own.q, bare.q) and np.array_equal(own.pi, bare.pi)


def test_the_estimate_does_not_depend_on_its_parts(trained):
    """At a settled state, an estimate in one step and one spread over seven agree."""
    paths = trained[4]
    one, seven = (settled(trained, paths["coarse"], k).error_estimate() for k in (1, 7))
    assert abs(one - seven) <= 1e-6 * one, (one, seven)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"check_constant_tangent": lambda a: None}, "go together"),
        ({"check_element_offsets": _set(-1, 1)}, "check_element_offsets must rise"),
        ({"check_parameters": _set((0, 0), 7.0)}, "check_parameters row 0: unknown law id"),
        ({"check_weights": _set(0, 0.0)}, "check_weights has values that are not positive"),
        ({"check_weights": _set(0, 1e7)}, "check_weights has values beyond"),
        ({"check_basis_rows": _set((0, 0, 0), 1.5)}, "check_basis_rows has values beyond"),
        ({"check_pressure_rows": lambda a: a[:, :1]}, "shape"),
        ({"check_constant_tangent": _set((0, 0, 1), 1e9)}, "not symmetric"),
        ({"check_element_nodes": _set((0, 0, 0), np.inf)}, "check_element_nodes"),
    ],
)
def test_the_reader_refuses_a_tampered_check_sample(trained, tmp_path, change, message):
    with pytest.raises(ArtifactError, match=message):
        tampered(trained, tmp_path, change, region="coarse")
    assert not (tmp_path / "tampered.h5").exists()


def test_a_tangled_check_element_is_refused(trained, tmp_path):
    def swap(a):
        a[0, [0, 1]] = a[0, [1, 0]]
        return a

    model = load(tampered(trained, tmp_path, {"check_element_nodes": swap}, region="coarse"),
                 isolate=False)  # fmt: skip
    with pytest.raises(ArtifactError, match="check_element_nodes: element 0 is tangled"):
        model.physics()


@pytest.mark.parametrize("steps", [-1, 1.5, True, False, "5", 10**6, np.uint64(2**64 - 1)])
def test_estimate_steps_must_be_a_positive_integer(trained, steps):
    model = load(trained[4]["coarse"], isolate=False)
    with pytest.raises(InputError, match="estimate_steps"):
        model.physics(estimate_steps=steps)


def test_the_check_kernel_refuses_bounds_without_a_part(trained):
    """Bounds of no part (a caller's SamplingCheck with its parts wrapped round) raise
    ValueError before anything is read or written."""
    from hapticrom.online.sampling_check import check_part

    physics = load(trained[4]["coarse"], isolate=False).physics()
    c, s, n = physics.check, physics.check.scratch, len(physics.q)
    empty = np.zeros(1, np.int64)
    empty.flags.writeable = False
    before = c.sums.copy()
    with pytest.raises(ValueError, match="at least one part"):
        check_part(*c.sample, *c.check, c.difference, empty, empty, 0, physics.q, physics.pi,
                   physics.newton.lu, physics.newton.pivots, c.xq, c.xp, c.sums, c.r, s.u,
                   s.r_u, s.scalars)  # fmt: skip
    assert np.array_equal(c.sums, before) and n == len(c.xq)


@pytest.mark.parametrize("name", ["sampled", "coarse"])
def test_a_release_at_once_returns_to_rest(trained, name):
    """Pressed, settled, then released in one step: the physics takes every step back to
    rest (a leap under the change is taken shorter, ``shortened``) and, pressed again,
    settles where it did (the demo's two-tool region released at once had diverged:
    README, stop 46)."""
    physics = settled(trained, trained[4][name], 0)
    loaded = physics.q.copy()
    physics.release(0)
    assert all(physics.step() for _ in range(200))
    assert np.linalg.norm(physics.q) <= 1e-6 * np.linalg.norm(loaded), physics.shortened
    _, (data, point), _, _, _, _, _ = trained
    pressed(physics, point, data["load_vector"].reshape(-1, 3).sum(axis=0), data["load_factor"])
    assert np.linalg.norm(physics.q - loaded) <= 1e-8 * np.linalg.norm(loaded)
