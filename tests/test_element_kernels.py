"""The online element kernels against the trainer's mixed forms assembled by DOLFINx.

The reference is :class:`~hapticrom.offline.fe.formulation.HyperelasticModel` itself: its
residual and Jacobian forms (UFL derivatives of the mixed energy) assembled on small,
distorted, rotated meshes of Q1P0 hexahedra and P2P0 tetrahedra at a smooth random
displacement and a random DG0 pressure, against the element kernels summed through the
cell-to-DOF maps. Independent second checks: Basix's shape functions and quadrature, a
rigid rotation, the element's force and moment balance, central differences of the
kernels themselves, bad shapes, and no allocation in a runtime free of the FE stack.
"""

from __future__ import annotations

from types import SimpleNamespace

import basix
import numpy as np
import pytest
import scipy.sparse
import ufl
from allocation_probe import BLOCK_FE_STACK, run_probe
from conftest import reseed
from dolfinx import fem, mesh
from dolfinx.fem.petsc import assemble_matrix
from dolfinx.io.gmsh import cell_perm_array
from mpi4py import MPI

import hapticrom.offline  # noqa: F401 - h5py and MPI first
from hapticrom.offline.fe.formulation import HyperelasticModel, choose_element
from hapticrom.offline.fe.materials import make_law
from hapticrom.online import element_kernels as ek
from hapticrom.online import material_kernels as mk
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(20261124)  # restarted before each test (conftest.py)


RELATIVE = 1e-10  # kernels vs DOLFINx, relative to the reference block's largest entry

# (law, its parameters): the second hgo is the cornea's (kappa = 2/D = 2e5 MPa).
LAWS = {
    "svk": ("svk", dict(E=1.0, nu=0.3)),
    "neo-hookean": ("neo-hookean", dict(E=3.0, nu=0.45)),
    "hgo": ("hgo", dict(C1=0.05, D=1e-2, C2=0.02, k1=0.5, k2=10.0, k3=0.1, k4=5.0)),
    "hgo-tension-only": ("hgo", dict(fibre_tension_only=True)),
}
CELL_TYPES = {"hexahedron": mesh.CellType.hexahedron, "tetrahedron": mesh.CellType.tetrahedron}
BASIX_CELLS = {"hexahedron": basix.CellType.hexahedron, "tetrahedron": basix.CellType.tetrahedron}
PRESSURE = 0.05  # MPa: the random pressure's scale, that of the laws' stresses here


def random_rotation():
    Q, R = np.linalg.qr(RNG.standard_normal((3, 3)))
    Q = Q @ np.diag(np.sign(np.diag(R)))
    return Q if np.linalg.det(Q) > 0 else -Q


def random_unit():
    v = RNG.standard_normal(3)
    return v / np.linalg.norm(v)


def distorted_box(cell: str):
    """A 2 x 1.5 x 1 mm box of 4 hexahedra or 12 tetrahedra, each vertex moved up to
    0.12 mm a direction, then rotated and moved off the origin: no cell is affine (the
    hexahedra) or axis-aligned."""
    cells = (2, 2, 1) if cell == "hexahedron" else (2, 1, 1)
    domain = mesh.create_box(
        MPI.COMM_SELF, [[0.0, 0.0, 0.0], [2.0, 1.5, 1.0]], cells, CELL_TYPES[cell]
    )
    x = domain.geometry.x
    x[:] = (x + 0.12 * RNG.uniform(-1.0, 1.0, x.shape)) @ random_rotation().T + [3.0, -1.0, 2.0]
    return domain


@pytest.fixture(scope="module", params=list(CELL_TYPES))
def box(request):
    """(cell name, mesh, reference element, the cells' volumes by DOLFINx)."""
    cell = request.param
    reseed(RNG, f"box-{cell}")
    domain = distorted_box(cell)
    DG0 = fem.functionspace(domain, ("DG", 0))
    volumes = fem.assemble_vector(fem.form(ufl.TestFunction(DG0) * ufl.dx)).array.copy()
    return cell, domain, ek.reference_element(cell), volumes


def packed_law(name: str, m0, n0):
    law, params = LAWS[name]
    fibres = dict(m0=m0, n0=n0) if law == "hgo" else {}
    return mk.law_parameters(law, **params, **fibres)


def trainer_model(domain, name: str, m0, n0) -> HyperelasticModel:
    """The trainer's model (the cell's default element) with constant unit fibres."""
    law, params = LAWS[name]
    fibres = (fem.Constant(domain, m0), fem.Constant(domain, n0))
    organ = SimpleNamespace(mesh=domain, fibre_fields=lambda: fibres)
    cell = domain.topology.cell_type.name
    return HyperelasticModel(organ, make_law(law, **params), choose_element(cell, "auto"))


def smooth_displacement(x):
    """Three random sine modes (mm): strains of about 0.15, every det F well positive."""
    u = np.zeros_like(x)
    for _ in range(3):
        wave = RNG.standard_normal(3)
        u += 0.05 * np.outer(random_unit(), np.sin(wave @ x + RNG.uniform(0.0, 2 * np.pi)))
    return u


def dense(form) -> np.ndarray:
    A = assemble_matrix(fem.form(form))
    A.assemble()
    indptr, indices, data = A.getValuesCSR()
    out = scipy.sparse.csr_matrix((data, indices, indptr), shape=A.getSize()).toarray()
    A.destroy()
    return out


def element_fields(model):
    """Per cell: (displacement rows, pressure DOF, X, u, p) through the cell-to-DOF maps."""
    coordinates = model.V.tabulate_dof_coordinates()
    u = model.u.x.array.reshape(-1, 3)
    for c in range(model.organ.mesh.topology.index_map(3).size_local):
        nodes = model.V.dofmap.cell_dofs(c)
        rows = (3 * nodes[:, None] + np.arange(3)).ravel()
        q = model.Q.dofmap.cell_dofs(c)[0]
        X, u_e = (np.ascontiguousarray(a[nodes]) for a in (coordinates, u))
        yield rows, q, X, u_e, float(model.p.x.array[q])


def kernels_assembled(model, packed, reference):
    """The full order's residual, Jacobian blocks and energy from the element kernels."""
    n_u, n_p = model.u.x.array.size, model.p.x.array.size
    R_u, R_p, K_pp = np.zeros(n_u), np.zeros(n_p), np.zeros((n_p, n_p))
    K_uu, K_up = np.zeros((n_u, n_u)), np.zeros((n_u, n_p))
    energy = 0.0
    for rows, q, X, u, p in element_fields(model):
        r, K, k, s = outputs(len(X))
        ek.element_residual_tangent(X, u, p, packed, reference.gradients, reference.weights,
                                    r, K, k, s)  # fmt: skip
        R_u[rows] += r
        R_p[q] += s[ek.PRESSURE_RESIDUAL]
        K_uu[np.ix_(rows, rows)] += K
        K_up[rows, q] += k
        K_pp[q, q] += s[ek.PRESSURE_STIFFNESS]
        energy += s[ek.ENERGY]
    return dict(R_u=R_u, R_p=R_p, K_uu=K_uu, K_up=K_up, K_pp=K_pp, energy=energy)


def outputs(nodes: int):
    """(r_u, K_uu, K_up, scalars) for an element of ``nodes`` nodes, NaN-filled: every
    entry must be written."""
    m = 3 * nodes
    return np.full(m, np.nan), np.full((m, m), np.nan), np.full(m, np.nan), np.full(4, np.nan)


def relative_error(value, reference):
    return np.abs(np.asarray(value) - reference).max() / np.abs(reference).max()


# -- against the trainer's forms ------------------------------------------------------------
@pytest.mark.parametrize("name", list(LAWS))
def test_kernels_assemble_to_the_full_order(box, name):
    cell, domain, reference, _ = box
    m0, n0 = random_unit(), random_unit()
    model = trainer_model(domain, name, m0, n0)
    assert model.quadrature_degree == 2 * ek.CELLS[cell]
    model.u.interpolate(smooth_displacement)
    model.p.x.array[:] = PRESSURE * RNG.uniform(-1.0, 1.0, model.p.x.array.size)
    residuals = model.residual_forms(include_load=False)
    (Kuu, Kup), (Kpu, Kpp) = (
        [dense(form) for form in row] for row in model.jacobian_forms(residuals)
    )
    expected = dict(
        R_u=fem.assemble_vector(fem.form(residuals[0])).array,
        R_p=fem.assemble_vector(fem.form(residuals[1])).array,
        K_uu=Kuu, K_up=Kup, K_pp=Kpp,
        energy=fem.assemble_scalar(fem.form(model.internal_energy())),
    )  # fmt: skip
    got = kernels_assembled(model, packed_law(name, m0, n0), reference)
    errors = {key: relative_error(got[key], expected[key]) for key in expected}
    assert all(error <= RELATIVE for error in errors.values()), errors
    assert relative_error(Kpu, Kup.T) <= 1e-14  # the reference is symmetric too
    assert np.array_equal(got["K_uu"], got["K_uu"].T)


# -- reference elements -----------------------------------------------------------------------
@pytest.mark.parametrize("cell, degree", [("hexahedron", 2), ("hexahedron", 4), ("tetrahedron", 4)])
def test_reference_element_is_basix(cell, degree):
    """Nodes, quadrature and shape-function gradients as Basix's (DOLFINx's) element."""
    reference = ek.reference_element(cell, degree)
    points, weights = basix.make_quadrature(BASIX_CELLS[cell], degree)
    np.testing.assert_allclose(reference.points, points, rtol=0, atol=1e-15)
    np.testing.assert_allclose(reference.weights, weights, rtol=1e-14, atol=0)
    element = basix.create_element(basix.ElementFamily.P, BASIX_CELLS[cell], ek.CELLS[cell],
                                   basix.LagrangeVariant.gll_warped)  # fmt: skip
    np.testing.assert_allclose(reference.nodes, element.points, rtol=0, atol=1e-15)
    tabulated = element.tabulate(1, points)[:, :, :, 0]  # (1 + 3 derivatives, points, nodes)
    values = ek.shape_functions(cell, points)[0]
    np.testing.assert_allclose(values, tabulated[0], rtol=0, atol=1e-14)
    gradients = np.moveaxis(tabulated[1:], 0, 2)  # (points, nodes, 3)
    np.testing.assert_allclose(reference.gradients, gradients, rtol=0, atol=1e-13)
    assert not reference.gradients.flags.writeable


def test_gmsh_permutation_is_dolfinx():
    assert list(ek.BASIX_FROM_GMSH["hexahedron"]) == cell_perm_array(mesh.CellType.hexahedron, 8)
    tetrahedron = cell_perm_array(mesh.CellType.tetrahedron, 10)
    assert list(ek.BASIX_FROM_GMSH["tetrahedron"]) == tetrahedron


@pytest.mark.parametrize(
    "cell, kwargs, message",
    [
        ("wedge", {}, "no reference element"),
        ("tetrahedron", {"quadrature_degree": 2}, "degree-4 rule only"),
        ("hexahedron", {"quadrature_degree": -1}, "non-negative integer"),
        ("hexahedron", {"quadrature_degree": 2.0}, "non-negative integer"),
        ("hexahedron", {"rule": (np.zeros((2, 3)), np.ones(3))}, "quadrature rule"),
        ("hexahedron", {"rule": (np.zeros((1, 2)), np.ones(1))}, "quadrature rule"),
    ],
)
def test_bad_reference_elements_refused(cell, kwargs, message):
    with pytest.raises(InputError, match=message):
        ek.reference_element(cell, **kwargs)


def test_explicit_rule_is_used():
    """A one-point rule at the centroid gives a constant-strain element: its volume is the
    weight times det J."""
    centroid = (np.full((1, 3), 0.25), np.array([1.0 / 6.0]))
    reference = ek.reference_element("tetrahedron", rule=centroid)
    X = np.ascontiguousarray(ek.reference_element("tetrahedron").nodes * [1.0, 2.0, 3.0])
    r, K, k, s = outputs(10)
    packed = mk.law_parameters("svk", E=1.0, nu=0.3)
    ek.element_residual_tangent(X, np.zeros_like(X), 0.0, packed, reference.gradients,
                                reference.weights, r, K, k, s)  # fmt: skip
    assert s[ek.VOLUME] == pytest.approx(1.0, rel=1e-15)


# -- independent checks on the kernels alone ------------------------------------------------
def element(box, name):
    """(X, packed law, reference) of the box's first cell, random fibres."""
    cell, domain, reference, _ = box
    model_X = domain.geometry.x[domain.geometry.dofmaps[0][0]]
    if cell == "tetrahedron":  # the P2 nodes of a straight-sided cell: vertices and midpoints
        edges = [model_X[[i, j]].mean(axis=0) for i, j in ek._TETRAHEDRON_EDGES]
        model_X = np.vstack([model_X, edges])
    return np.ascontiguousarray(model_X), packed_law(name, random_unit(), random_unit()), reference


def run(X, u, p, packed, reference):
    r, K, k, s = outputs(len(X))
    ek.element_residual_tangent(X, u, p, packed, reference.gradients, reference.weights,
                                r, K, k, s)  # fmt: skip
    return r, K, k, s


@pytest.mark.parametrize("name", list(LAWS))
def test_rigid_rotation(box, name):
    """x = Q X + c on every cell: no force at p = 0 (to rounding of the stiffness times
    the element's size), and r_p = -p V_e / kappa at any p (theta = 0) with DOLFINx's V_e."""
    cell, domain, reference, volumes = box
    Q, c = random_rotation(), RNG.standard_normal(3)
    packed = packed_law(name, random_unit(), random_unit())
    model = SimpleNamespace(V=fem.functionspace(domain, ("Lagrange", ek.CELLS[cell], (3,))))
    model.Q = fem.functionspace(domain, ("DG", 0))
    model.organ = SimpleNamespace(mesh=domain)
    model.u, model.p = fem.Function(model.V), fem.Function(model.Q)
    model.u.interpolate(lambda x: (Q - np.eye(3)) @ x + c[:, None])
    for _, q, X, u, _ in element_fields(model):
        size = np.ptp(X, axis=0).max()
        r, K, _, s = run(X, u, 0.0, packed, reference)
        assert np.abs(r).max() <= 1e-12 * np.abs(K).max() * size
        assert abs(s[ek.ENERGY]) <= 1e-12 * np.abs(K).max() * size**2
        assert s[ek.VOLUME] == pytest.approx(volumes[q], rel=1e-13)
        p = PRESSURE * RNG.uniform(-1.0, 1.0)
        s_p = run(X, u, p, packed, reference)[3]
        expected = -p * volumes[q] / packed[mk.KAPPA]
        assert s_p[ek.PRESSURE_RESIDUAL] == pytest.approx(expected, rel=1e-9)


def random_state(X):
    """A random nodal displacement (strains of about 0.1) and pressure."""
    size = np.ptp(X, axis=0).max()
    return 0.03 * size * RNG.standard_normal(X.shape), PRESSURE * RNG.uniform(-1.0, 1.0)


@pytest.mark.parametrize("name", list(LAWS))
def test_force_and_moment_balance(box, name):
    """sum_a r_a = 0 (sum_a dN_a = 0) and sum_a x_a x r_a = 0 (P F^T is symmetric) at any
    (u, p): an element's internal forces are in equilibrium."""
    X, packed, reference = element(box, name)
    u, p = random_state(X)
    r = run(X, u, p, packed, reference)[0].reshape(-1, 3)
    scale = np.abs(r).max()
    assert np.abs(r.sum(axis=0)).max() <= 1e-13 * scale * len(X)
    moment = np.cross(X + u, r).sum(axis=0)
    assert np.abs(moment).max() <= 1e-13 * scale * len(X) * np.abs(X + u).max()


@pytest.mark.parametrize("name", list(LAWS))
def test_tangent_is_the_residuals_derivative(box, name):
    """K_uu, K_up against central differences of r_u and r_p in u (step 1e-6 mm: truncation
    and rounding below 1e-7 of the largest entry); r_u and r_p against those of the energy;
    K_up and K_pp against differences in p, exact at any step (r is linear in p)."""
    X, packed, reference = element(box, name)
    u, p = random_state(X)
    r, K, k, s = run(X, u, p, packed, reference)
    h, m = 1e-6, u.size
    K_fd, k_fd, r_fd = np.empty((m, m)), np.empty(m), np.empty(m)
    for column in range(m):
        step = np.zeros(m)
        step[column] = h
        plus = run(X, u + step.reshape(u.shape), p, packed, reference)
        minus = run(X, u - step.reshape(u.shape), p, packed, reference)
        K_fd[:, column] = (plus[0] - minus[0]) / (2 * h)
        k_fd[column] = (plus[3][ek.PRESSURE_RESIDUAL] - minus[3][ek.PRESSURE_RESIDUAL]) / (2 * h)
        r_fd[column] = (plus[3][ek.ENERGY] - minus[3][ek.ENERGY]) / (2 * h)
    assert relative_error(K, K_fd) <= 1e-7
    assert relative_error(k, k_fd) <= 1e-7
    assert relative_error(r, r_fd) <= 1e-7
    # Differences in p are exact but for the rounding of what they difference: r and the
    # energy at p +- 1 can be 1e10 times k (a stiff fibre's exponential at a random state,
    # seen on a P2 tetrahedron with the tension-only law), whence the second bound.
    plus, minus = run(X, u, p + 1.0, packed, reference), run(X, u, p - 1.0, packed, reference)
    rounding = 1e-14 * max(np.abs(plus[0]).max(), np.abs(minus[0]).max())
    assert np.abs(k - (plus[0] - minus[0]) / 2).max() <= 1e-9 * np.abs(k).max() + rounding
    pressure_rows = (plus[3] - minus[3]) / 2
    assert pressure_rows[ek.PRESSURE_RESIDUAL] == pytest.approx(s[ek.PRESSURE_STIFFNESS], rel=1e-9)
    rounding = 1e-14 * max(abs(plus[3][ek.ENERGY]), abs(minus[3][ek.ENERGY]))
    expected = s[ek.PRESSURE_RESIDUAL]
    assert abs(pressure_rows[ek.ENERGY] - expected) <= 1e-9 * abs(expected) + rounding


@pytest.mark.parametrize("name", ["svk", "hgo"])
def test_residual_kernel_is_the_tangent_kernels(box, name):
    X, packed, reference = element(box, name)
    u, p = random_state(X)
    r, _, _, s = run(X, u, p, packed, reference)
    r2, s2 = np.full(r.shape, np.nan), np.full(4, np.nan)
    ek.element_residual(X, u, p, packed, reference.gradients, reference.weights, r2, s2)
    assert np.array_equal(r, r2) and np.array_equal(s, s2)


def test_refuses_wrong_shapes_and_flags_unknown_laws():
    reference = ek.reference_element("hexahedron")
    X = np.ascontiguousarray(reference.nodes)
    u = np.zeros_like(X)
    G, w = reference.gradients, reference.weights
    packed = mk.law_parameters("svk", E=1.0, nu=0.3)
    r, K, k, s = outputs(8)
    many = np.zeros((ek.MAX_NODES + 1, 3))
    calls = [
        ("X must be", (X[:, :2].copy(), u, packed, G, w, r, K, k, s)),
        ("u must have", (X, u[:7].copy(), packed, G, w, r, K, k, s)),
        ("PARAMETER_SIZE", (X, u, packed[:-1].copy(), G, w, r, K, k, s)),
        ("gradients must be", (X, u, packed, G[:, :7].copy(), w, r, K, k, s)),
        ("weights must have", (X, u, packed, G, w[:7].copy(), r, K, k, s)),
        ("wrong shape \\(r_u", (X, u, packed, G, w, r[:23].copy(), K, k, s)),
        ("wrong shape \\(K_uu", (X, u, packed, G, w, r, K[:, :23].copy(), k, s)),
        ("wrong shape \\(K_uu", (X, u, packed, G, w, r, K, k[:23].copy(), s)),
        ("SCALAR_SIZE", (X, u, packed, G, w, r, K, k, s[:3].copy())),
        ("MAX_NODES", (many, many, packed, np.zeros((8, ek.MAX_NODES + 1, 3)), w, r, K, k, s)),
    ]
    for message, (X_, u_, params, G_, w_, r_, K_, k_, s_) in calls:
        r_[:], s_[:] = 7.0, 7.0
        with pytest.raises(ValueError, match=message):
            ek.element_residual_tangent(X_, u_, 0.0, params, G_, w_, r_, K_, k_, s_)
        assert np.all(r_ == 7.0) and np.all(s_ == 7.0)  # nothing written
    unknown = packed.copy()
    unknown[mk.LAW] = 7.0
    ek.element_residual_tangent(X, u, 0.0, unknown, G, w, r, K, k, s)
    assert np.isnan(r).all() and np.isnan(K).all() and np.isnan(s[ek.ENERGY])


# -- the runtime stays small, and allocates nothing ----------------------------------------
def test_runtime_module_imports_no_fe_stack_and_allocates_nothing(tmp_path):
    """Compiled afresh (an empty numba cache) with the finite-element stack and scipy
    blocked; then numba's allocation counters (which see an allocating canary) do not
    move over 1000 calls of each kernel."""
    body = """
        from hapticrom.online import element_kernels as ek, material_kernels as mk

        @njit
        def run(X, u, params, G, w, r, K, k, s, n):
            total = 0.0
            for _ in range(n):
                ek.element_residual_tangent(X, u, 0.01, params, G, w, r, K, k, s)
                total += s[0]
                ek.element_residual(X, u, 0.01, params, G, w, r, s)
                total += s[0]
            return total

        fibres = dict(m0=np.array([1.0, 0.0, 0.0]), n0=np.array([0.0, 1.0, 0.0]))
        laws = [mk.law_parameters("svk", E=1.0, nu=0.3),
                mk.law_parameters("neo-hookean", E=1.0, nu=0.3),
                mk.law_parameters("hgo", **fibres, C2=0.1, fibre_tension_only=True)]
        for cell in ("hexahedron", "tetrahedron"):
            ref = ek.reference_element(cell)
            X = np.ascontiguousarray(ref.nodes)
            u = 0.01 * np.sin(np.arange(X.size, dtype=float)).reshape(X.shape)
            m = X.size
            buffers = (np.empty(m), np.empty((m, m)), np.empty(m), np.empty(ek.SCALAR_SIZE))
            for params in laws:
                same_allocations(run, X, u, params, ref.gradients, ref.weights, *buffers)
        loaded = [m for m in ("ufl", "dolfinx", "scipy", "petsc4py") if m in sys.modules]
        assert not loaded, loaded
        print("ok")
    """
    run_probe(body, BLOCK_FE_STACK, {"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
