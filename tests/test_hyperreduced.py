"""The hyper-reduced internal forces (:mod:`hapticrom.online.hyperreduced`) on small
synthetic meshes, without DOLFINx.

Distorted grids of Q1 hexahedra and face-sharing P2 tetrahedra with one global node
numbering (elements share DOFs), random global bases Phi, Psi and the three laws (HGO
also near-incompressible, kappa = 2e5 MPa). The kernel is held to an independent numpy
assembly of its module's formulas over the element kernel called per element from
Python (which maps each point itself: the kernels read element_geometry's gradients);
each element's nonlinear term (ECSW's columns) plus the exact linear matrices to the whole
sum; its tangent to central differences of its residual. Then: every output written, a
reused scratch, wrong shapes refused before writing, no allocation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import cycle

import numpy as np
import pytest
from allocation_probe import run_probe
from conftest import reseed

from hapticrom.online import element_kernels as ek
from hapticrom.online import material_kernels as mk
from hapticrom.online.hyperreduced import (
    Scratch,
    element_contributions,
    sampled_residual,
    sampled_residual_tangent,
)

pytestmark = pytest.mark.serial
RNG = np.random.default_rng(20260518)
MODES, PRESSURE_MODES = 5, 3
SPACING = 2.0  # mm: the hexahedra's edge, about the tetrahedra's
# mm a unit of q: |grad u| up to 0.05-0.15 at q of about 1 (the P2 nodes are twice as
# close and their gradients steeper)
MODE_SCALE = {"hexahedron": 0.03, "tetrahedron": 0.01}
PRESSURE = 0.05  # MPa a unit of pi: p of about 0.1 MPa, the laws' stresses here
RELATIVE = 1e-12  # kernel vs the numpy assembly (the same sums in another order)

# A case: the cell, and the laws of its elements (cycled over them); the law's keyword
# arguments take random unit fibres when the law is hgo. kappa: svk 0.58, neo-Hookean
# 9.3, the compressible hgo 200, the default hgo (the cornea's) 2e5 MPa.
SVK = ("svk", dict(E=1.0, nu=0.3))
NEO_HOOKEAN = ("neo-hookean", dict(E=3.0, nu=0.45))
HGO = ("hgo", dict(C1=0.05, D=1e-2, C2=0.02, k1=0.5, k2=10.0, k3=0.1, k4=5.0))
HGO_TENSION_ONLY = ("hgo", dict(D=1e-2, fibre_tension_only=True))
HGO_DEFAULT = ("hgo", {})
CASES = {
    "hex-svk": ("hexahedron", [SVK]),
    "hex-neo-hookean": ("hexahedron", [NEO_HOOKEAN]),
    "hex-hgo": ("hexahedron", [HGO]),
    "hex-mixed-laws": ("hexahedron", [SVK, HGO, NEO_HOOKEAN, HGO_TENSION_ONLY]),
    "tet-neo-hookean": ("tetrahedron", [NEO_HOOKEAN]),
    "tet-hgo-incompressible": ("tetrahedron", [HGO_DEFAULT]),
}


def readonly(a) -> np.ndarray:
    """A C-contiguous float64 read-only copy: the kernel's input flags."""
    a = np.array(a, dtype=np.float64, order="C")
    a.flags.writeable = False
    return a


def random_unit() -> np.ndarray:
    v = RNG.standard_normal(3)
    return v / np.linalg.norm(v)


# -- the synthetic meshes ---------------------------------------------------------------------
def hexahedra(cells=(3, 2, 1)) -> np.ndarray:
    """(E, 8, 3): a grid of SPACING-mm cells, each grid node moved up to 0.1 SPACING a
    direction (no cell affine); node a of a cell at its corner (a & 1, a >> 1 & 1, a >> 2)."""
    shape = tuple(c + 1 for c in cells)
    grid = np.stack(np.meshgrid(*(np.arange(s) for s in shape), indexing="ij"), axis=-1)
    grid = SPACING * grid + 0.1 * SPACING * RNG.uniform(-1.0, 1.0, grid.shape)
    corners = np.stack([np.arange(8) & 1, np.arange(8) >> 1 & 1, np.arange(8) >> 2], axis=1)
    X = [
        [grid[i + a, j + b, k + c] for a, b, c in corners]
        for i in range(cells[0])
        for j in range(cells[1])
        for k in range(cells[2])
    ]
    return np.array(X)


def affine_tetrahedron(vertices: np.ndarray) -> np.ndarray:
    """The 10 P2 nodes (Basix order) of the tetrahedron of these vertices, reordered so that
    its map from the reference cell has a positive determinant."""
    J = (vertices[1:] - vertices[0]).T  # columns: the reference axes' images
    if np.linalg.det(J) < 0:
        vertices = vertices[[0, 2, 1, 3]]
        J = (vertices[1:] - vertices[0]).T
    return vertices[0] + ek.reference_element("tetrahedron").nodes @ J.T


def tetrahedra() -> np.ndarray:
    """(3, 10, 3): a tetrahedron of a random affine map and the two built on its faces
    opposite vertices 0 and 1 (their apexes that vertex mirrored through the face's
    centroid): two faces shared, six nodes each, and an edge shared by all three."""
    J = SPACING * (np.eye(3) + 0.2 * RNG.standard_normal((3, 3)))
    while np.linalg.det(J) < 0.5 * SPACING**3:  # well shaped, positively oriented
        J = SPACING * (np.eye(3) + 0.2 * RNG.standard_normal((3, 3)))
    V = np.vstack([np.zeros(3), J.T]) + RNG.uniform(-5.0, 5.0, 3)
    elements = [affine_tetrahedron(V)]
    for apex in (0, 1):
        face = V[[v for v in range(4) if v != apex]]
        mirrored = 2 * face.mean(axis=0) - V[apex]
        elements.append(affine_tetrahedron(np.vstack([face, mirrored])))
    return np.array(elements)


def global_nodes(X: np.ndarray) -> np.ndarray:
    """(E, nodes): one global number a distinct point (coincident within 1e-9 mm)."""
    points: list[np.ndarray] = []
    numbers = np.empty(X.shape[:2], dtype=np.int64)
    for e, a in np.ndindex(*X.shape[:2]):
        match = [i for i, x in enumerate(points) if np.linalg.norm(x - X[e, a]) < 1e-9]
        numbers[e, a] = match[0] if match else len(points)
        if not match:
            points.append(X[e, a])
    return numbers


@dataclass
class Problem:
    """Every element of a mesh with its global bases' rows and rest tangents."""

    X: np.ndarray  # (E, nodes, 3)
    rows: np.ndarray  # (E, m): the element's rows of Phi
    params: np.ndarray  # (E, PARAMETER_SIZE)
    Phi: np.ndarray  # (3 global nodes, MODES)
    Psi: np.ndarray  # (E, PRESSURE_MODES): one row a cell
    reference: ek.ReferenceElement
    K0: np.ndarray  # (E, m, m): K_uu at rest
    k0: np.ndarray  # (E, m): K_up at rest

    @property
    def elements(self) -> int:
        return len(self.X)

    @property
    def nodes(self) -> int:
        return self.X.shape[1]


def element_tangents(X, u, p, params, reference):
    """The element kernel called from Python: (r_u, K_uu, K_up, scalars)."""
    m = X.size
    r_u, K_uu, K_up, scalars = np.empty(m), np.empty((m, m)), np.empty(m), np.empty(4)
    ek.element_residual_tangent(readonly(X), readonly(u), p, readonly(params),
                                reference.gradients, reference.weights, r_u, K_uu, K_up,
                                scalars)  # fmt: skip
    return r_u, K_uu, K_up, scalars


def make_problem(name: str) -> Problem:
    """The synthetic problem ``name``, the same whatever drew from RNG before (another
    module's fixture builds these too, in an order pytest-xdist chooses)."""
    reseed(RNG, f"problem-{name}")
    cell, laws = CASES[name]
    X = hexahedra() if cell == "hexahedron" else tetrahedra()
    numbers = global_nodes(X)
    rows = (3 * numbers[:, :, None] + np.arange(3)).reshape(len(X), -1)
    params = []
    for _, (law, kwargs) in zip(X, cycle(laws)):
        fibres = dict(m0=random_unit(), n0=random_unit()) if law == "hgo" else {}
        params.append(mk.law_parameters(law, **kwargs, **fibres))
    reference = ek.reference_element(cell)
    zero = np.zeros(X.shape[1:])
    rest = [element_tangents(x, zero, 0.0, pa, reference) for x, pa in zip(X, params, strict=True)]
    return Problem(
        X=X,
        rows=rows,
        params=np.array(params),
        Phi=MODE_SCALE[cell] * RNG.standard_normal((3 * (numbers.max() + 1), MODES)),
        Psi=RNG.standard_normal((len(X), PRESSURE_MODES)),
        reference=reference,
        K0=np.array([t[1] for t in rest]),
        k0=np.array([t[2] for t in rest]),
    )


@pytest.fixture(scope="module", params=list(CASES))
def problem(request) -> Problem:
    return make_problem(request.param)


def random_state() -> tuple[np.ndarray, np.ndarray]:
    return readonly(RNG.standard_normal(MODES)), readonly(PRESSURE * RNG.standard_normal(3))


def geometry(X: np.ndarray, reference: ek.ReferenceElement) -> tuple[np.ndarray, np.ndarray]:
    """element_geometry's (dN, dV) of the elements X, NaN-filled outputs first."""
    points = len(reference.weights)
    dN, dV = np.full((len(X), points) + X.shape[1:], np.nan), np.full((len(X), points), np.nan)
    ek.element_geometry(readonly(X), reference.gradients, reference.weights, dN, dV)
    return dN, dV


def sample(problem: Problem, elements, weights) -> tuple:
    """The kernels' per-sample inputs (dN, dV, Phi, Psi, params, weights), read-only."""
    s = np.asarray(elements)
    dN, dV = geometry(problem.X[s], problem.reference)
    arrays = (dN, dV, problem.Phi[problem.rows[s]], problem.Psi[s], problem.params[s], weights)
    return tuple(readonly(a) for a in arrays)


def evaluate(problem: Problem, inputs: tuple, q, pi, scratch: Scratch | None = None):
    """The kernel's (r, K) into NaN-filled outputs."""
    scratch = Scratch(problem.nodes, MODES) if scratch is None else scratch
    size = MODES + PRESSURE_MODES
    r, K = np.full(size, np.nan), np.full((size, size), np.nan)
    sampled_residual_tangent(*inputs, q, pi, r, K, *scratch.buffers())
    return r, K


def numpy_sums(problem: Problem, elements, weights, q, pi):
    """The module's sampled sums, element by element in numpy over the element kernel."""
    n, size = MODES, MODES + PRESSURE_MODES
    r, K = np.zeros(size), np.zeros((size, size))
    for e, w in zip(elements, weights, strict=True):
        Phi_e, Psi_e = problem.Phi[problem.rows[e]], problem.Psi[e]
        u, p = Phi_e @ q, Psi_e @ pi
        r_u, K_uu, K_up, scalars = element_tangents(
            problem.X[e], u.reshape(-1, 3), p, problem.params[e], problem.reference
        )
        Theta = scalars[ek.PRESSURE_RESIDUAL] + p * scalars[ek.VOLUME] / problem.params[e, mk.KAPPA]
        r[:n] += w * Phi_e.T @ r_u
        r[n:] += w * Psi_e * Theta
        K[:n, :n] += w * Phi_e.T @ K_uu @ Phi_e
        K[:n, n:] += w * np.outer(Phi_e.T @ K_up, Psi_e)
    K[n:, :n] = K[:n, n:].T
    return r, K


def relative(a, reference) -> float:
    return float(np.abs(a - reference).max() / np.abs(reference).max())


def tangent_errors(K, K_ref) -> dict[str, float]:
    """Each block's largest difference relative to the reference block's largest entry:
    the q rows (N) and pi rows (mm^3) differ in scale by orders of magnitude."""
    n = MODES
    return {
        "K_qq": relative(K[:n, :n], K_ref[:n, :n]),
        "K_qpi": relative(K[:n, n:], K_ref[:n, n:]),
        "K_piq": relative(K[n:, :n], K_ref[n:, :n]),
    }


def block_errors(r, K, r_ref, K_ref) -> dict[str, float]:
    """tangent_errors and those of the residual's q and pi rows."""
    n = MODES
    errors = {"r_q": relative(r[:n], r_ref[:n]), "r_pi": relative(r[n:], r_ref[n:])}
    return errors | tangent_errors(K, K_ref)


def random_subset(problem: Problem):
    """All elements but one, shuffled, with weights in [0.5, 2]: an ECSW sample."""
    elements = RNG.permutation(problem.elements)[: problem.elements - 1]
    return elements, RNG.uniform(0.5, 2.0, len(elements))


# -- the sums -------------------------------------------------------------------------------
def test_sums_equal_a_numpy_assembly(problem):
    elements, weights = random_subset(problem)
    q, pi = random_state()
    r, K = evaluate(problem, sample(problem, elements, weights), q, pi)
    r_ref, K_ref = numpy_sums(problem, elements, weights, q, pi)
    errors = block_errors(r, K, r_ref, K_ref)
    assert max(errors.values()) <= RELATIVE, errors
    n = MODES
    assert np.all(K[n:, n:] == 0.0)  # Theta does not depend on p: no pi-pi block


def test_nonlinear_terms_and_linear_matrices_are_the_whole_sum(problem):
    """element_contributions' columns (each element's term less its rest tangent's part,
    unweighted) summed over every element, plus the exact linear matrices, are the whole
    sum at weight 1: the split the model makes in the reduced space (module doc)."""
    everything, ones = np.arange(problem.elements), np.ones(problem.elements)
    q, pi = random_state()
    inputs = sample(problem, everything, ones)
    r_whole, _ = evaluate(problem, inputs, q, pi)
    size, n = MODES + PRESSURE_MODES, MODES
    columns = np.full((problem.elements, size), np.nan)
    scratch = Scratch(problem.nodes, MODES)
    element_contributions(*inputs, readonly(problem.K0), readonly(problem.k0), q, pi, columns,
                          scratch.u, scratch.r_u, scratch.scalars)  # fmt: skip
    Phi_e, Psi_e = problem.Phi[problem.rows], problem.Psi
    L_uu = np.einsum("emi,emk,ekj->ij", Phi_e, problem.K0, Phi_e)
    L_up = np.einsum("emi,em,ek->ik", Phi_e, problem.k0, Psi_e)
    r_split = columns.sum(axis=0)
    without_linear = {"r_q": relative(r_split[:n], r_whole[:n]),
                      "r_pi": relative(r_split[n:], r_whole[n:])}  # fmt: skip
    r_split[:n] += L_uu @ q + L_up @ pi
    r_split[n:] += L_up.T @ q
    for rows in (slice(0, n), slice(n, None)):  # q rows N, pi rows mm^3: apart
        assert relative(r_split[rows], r_whole[rows]) <= RELATIVE
    # not trivially: without the linear matrices the pressure rows are far off (the q rows
    # can be too, but at a state where a fibre's exponential dominates they need not be:
    # 7 of 2000 random states on tet-hgo-incompressible within 1e-10)
    assert without_linear["r_pi"] > 1e-3, without_linear


def test_tangent_is_the_residuals_derivative(problem):
    """Central differences of r in q extrapolated (Richardson: (4 D(h/2) - D(h)) / 3) at
    h = 1e-3 against q of about 1. The h^2 error term cancels (alone it reaches 5.5e-6
    here: strains of 0.05-0.16 a unit of q, hgo's exponents 10-30); the h^4 / 480 |r^(5)|
    term stays below the rounding, about 3e-13 |r'| / h (the sum cancels between elements
    and against K0 u) times the combination's 3: the error grows as h shrinks, the worst
    of 240 random draws 1.6e-9 at 1e-3 (6e-9 at 1e-4). Held to 1e-8 of each block's
    largest entry. r is linear in pi, so its differences in pi are exact but for rounding
    (step 1: p moves by about 1 MPa).

    Tension-only fibres are left out: their energy has a kink where a family starts to
    carry (I4 = 1), and a difference that straddles it is no derivative (seen: 2.6e-3 at
    h = 1e-3, 3.5e-9 at h = 1e-5 for the same state); their tangent is checked against UFL
    away from the kink (tests/test_material_kernels.py)."""
    elements, weights = random_subset(problem)
    smooth = problem.params[elements, mk.TENSION_ONLY] == 0.0
    elements, weights = elements[smooth], weights[smooth]
    inputs = sample(problem, elements, weights)
    q, pi = random_state()
    r, K = evaluate(problem, inputs, q, pi)
    assert np.array_equal(K, K.T)
    n, size = MODES, MODES + PRESSURE_MODES

    def difference(step):  # r(x + step) - r(x - step)
        plus = evaluate(problem, inputs, readonly(q + step[:n]), readonly(pi + step[n:]))[0]
        return plus - evaluate(problem, inputs, readonly(q - step[:n]), readonly(pi - step[n:]))[0]

    K_fd = np.empty((size, size))
    for column in range(size):
        step = np.zeros(size)
        if column < n:
            step[column] = h = 1e-3
            K_fd[:, column] = (8 * difference(step / 2) - difference(step)) / (6 * h)
        else:
            step[column] = 1.0
            K_fd[:, column] = difference(step) / 2
    errors = tangent_errors(K, K_fd)
    assert max(errors["K_qq"], errors["K_piq"]) <= 1e-8, errors
    assert errors["K_qpi"] <= 1e-10, errors
    # the pi-pi block: Theta's differences in pi, rounding of p V / kappa only
    assert np.abs(K_fd[n:, n:]).max() <= 1e-10 * np.abs(K_fd[n:, :n]).max()


def test_residual_alone_is_the_tangent_kernels_residual(problem):
    """``sampled_residual`` (a modified Newton's iterations) writes every entry of r, the
    same sums as ``sampled_residual_tangent``'s r and the numpy assembly's; a wrong r is
    refused before anything is written."""
    elements, weights = random_subset(problem)
    inputs = sample(problem, elements, weights)
    q, pi = random_state()
    r_full, _ = evaluate(problem, inputs, q, pi)
    r_ref, _ = numpy_sums(problem, elements, weights, q, pi)
    scratch = Scratch(problem.nodes, MODES)
    r = np.full(MODES + PRESSURE_MODES, np.nan)
    sampled_residual(*inputs, q, pi, r, scratch.u, scratch.r_u, scratch.scalars)
    assert np.isfinite(r).all()
    n = MODES
    for rows in (slice(0, n), slice(n, None)):  # q rows N, pi rows mm^3: apart
        assert relative(r[rows], r_full[rows]) <= RELATIVE
        assert relative(r[rows], r_ref[rows]) <= RELATIVE
    wrong = np.full(MODES + PRESSURE_MODES + 1, 7.0)
    with pytest.raises(ValueError, match="r must be"):
        sampled_residual(*inputs, q, pi, wrong, scratch.u, scratch.r_u, scratch.scalars)
    assert np.all(wrong == 7.0)


def test_more_points_than_the_lanes_hold_take_the_point_by_point_path():
    """hgo hexahedra with 27 quadrature points (degree 4): more than the points path's
    stack buffer holds (MAX_POINTS), so ``sampled_residual`` takes the point-by-point
    kernel; its sums are the numpy assembly's over that kernel (past the buffer's end, the
    points path would read and write beyond its stack)."""
    problem = replace(make_problem("hex-hgo"), reference=ek.reference_element("hexahedron", 4))
    assert len(problem.reference.weights) == 27 > mk.MAX_POINTS
    elements, weights = random_subset(problem)
    q, pi = random_state()
    r_ref, _ = numpy_sums(problem, elements, weights, q, pi)
    scratch = Scratch(problem.nodes, MODES)
    r = np.full(MODES + PRESSURE_MODES, np.nan)
    sampled_residual(*sample(problem, elements, weights), q, pi, r, scratch.u, scratch.r_u,
                     scratch.scalars)  # fmt: skip
    for rows in (slice(0, MODES), slice(MODES, None)):
        assert relative(r[rows], r_ref[rows]) <= RELATIVE


def _rule(name: str) -> ek.ReferenceElement:
    """A reference element whose points leave lanes of the points path's shapes empty."""
    if name == "hex-gauss-1":  # 1 point: the hexahedron's 8 lanes, 7 padded
        return ek.reference_element("hexahedron", 1)
    gauss = ek.reference_element("hexahedron")
    if name == "hex-12":  # 8 nodes and 12 points: MAX_POINTS lanes, the nodes a variable
        extra = np.array([[0.3, 0.4, 0.5], [0.7, 0.2, 0.6], [0.5, 0.5, 0.5], [0.1, 0.8, 0.3]])
        rule = (np.vstack([gauss.points, extra]), np.r_[0.75 * gauss.weights, np.full(4, 1 / 16)])
        return ek.reference_element("hexahedron", rule=rule)
    points = np.array([[0.1, 0.2, 0.3], [0.5, 0.1, 0.2], [0.2, 0.5, 0.1], [0.25, 0.25, 0.25]])
    return ek.reference_element("tetrahedron", rule=(points, np.full(4, 1 / 24)))  # 16 lanes


@pytest.mark.parametrize("name, rule", [("hex-hgo", "hex-gauss-1"), ("hex-hgo", "hex-12"),
                                        ("tet-hgo-incompressible", "tet-4")])  # fmt: skip
def test_points_the_lanes_leave_empty_add_nothing(name, rule):
    """The points path runs over literal lane counts (POINT_SHAPES), the points padded with
    lanes of no gradient and no volume: with 1 of a hexahedron's 8 lanes, 4 of a
    tetrahedron's 16, and 12 points of a hexahedron (MAX_POINTS lanes, its 8 nodes not a
    literal), ``sampled_residual`` is the numpy assembly over the point-by-point kernel."""
    problem = replace(make_problem(name), reference=_rule(rule))
    points, nodes = len(problem.reference.weights), problem.nodes
    assert points not in [lanes for lanes, _ in ek.POINT_SHAPES]  # some lanes padded
    elements, weights = random_subset(problem)
    q, pi = random_state()
    r_ref, _ = numpy_sums(problem, elements, weights, q, pi)
    scratch = Scratch(nodes, MODES)
    r = np.full(MODES + PRESSURE_MODES, np.nan)
    sampled_residual(*sample(problem, elements, weights), q, pi, r, scratch.u, scratch.r_u,
                     scratch.scalars)  # fmt: skip
    for rows in (slice(0, MODES), slice(MODES, None)):
        assert relative(r[rows], r_ref[rows]) <= RELATIVE


# -- outputs and scratch ----------------------------------------------------------------------
def test_every_output_written_and_scratch_reusable(problem):
    """NaN-filled r, K and scratch come back finite, equal to a fresh scratch's; a scratch
    reused across calls at other states and samples gives the same bits again."""
    elements, weights = random_subset(problem)
    inputs = sample(problem, elements, weights)
    q, pi = random_state()
    fresh = evaluate(problem, inputs, q, pi)
    assert np.isfinite(fresh[0]).all() and np.isfinite(fresh[1]).all()
    scratch = Scratch(problem.nodes, MODES)
    for buffer in scratch.buffers():
        buffer.fill(np.nan)
    first = evaluate(problem, inputs, q, pi, scratch)
    assert all(np.array_equal(a, b) for a, b in zip(first, fresh, strict=True))
    other_inputs = sample(problem, *random_subset(problem))
    between = evaluate(problem, other_inputs, *random_state(), scratch)
    assert not np.array_equal(between[0], first[0])
    again = evaluate(problem, inputs, q, pi, scratch)
    assert all(np.array_equal(a, b) for a, b in zip(again, first, strict=True))


def test_wrong_shapes_refused_before_writing():
    """Each of the kernel's shape checks, by the start of its message, with r and K left
    as they were."""
    problem = make_problem("hex-neo-hookean")
    elements, weights = random_subset(problem)
    dN, dV, Phi, Psi, params, w = sample(problem, elements, weights)
    q, pi = random_state()
    size = MODES + PRESSURE_MODES
    r, K = np.empty(size), np.empty((size, size))
    buffers = Scratch(problem.nodes, MODES).buffers()
    rows, nodes, points, q_pi = "dN, dV, Phi", "Phi must have 3 rows", "dN and dV", r"q \(n,\)"
    r_K, wrong_scratch = "r must be", "the scratch does not fit"

    def call(**changed):
        arguments = dict(dN=dN, dV=dV, Phi=Phi, Psi=Psi, params=params, weights=w, q=q, pi=pi,
                         r=r, K=K)  # fmt: skip
        arguments.update(changed)
        scratch = arguments.pop("scratch", buffers)
        return tuple(arguments.values()) + tuple(scratch)

    def scratch_with(index, array):
        return tuple(array if i == index else b for i, b in enumerate(buffers))

    m = Phi.shape[1]
    calls = [
        (rows, call(dN=dN[:-1])),
        (rows, call(dV=dV[:-1])),
        (rows, call(Psi=Psi[:-1])),
        (rows, call(params=params[:-1])),
        (rows, call(weights=w[:-1])),
        (nodes, call(Phi=readonly(Phi[:, :-3]))),
        (nodes, call(dN=readonly(np.pad(dN, ((0, 0), (0, 0), (0, 0), (0, 1)))))),
        (nodes, call(dN=readonly(dN[:, :, :-1]))),
        (nodes, call(params=readonly(params[:, :-1]))),
        (points, call(dV=readonly(dV[:, :-1]))),
        (points, call(dN=readonly(dN[:, :-1]))),
        (q_pi, call(q=readonly(np.append(q, 0.0)))),
        (q_pi, call(q=q[:-1])),
        (q_pi, call(pi=pi[:-1])),
        (r_K, call(r=np.empty(size + 1))),
        (r_K, call(K=np.empty((size + 1, size)))),
        (r_K, call(K=np.empty((size, size - 1)))),
        (wrong_scratch, call(scratch=Scratch(problem.nodes + 2, MODES).buffers())),
        (wrong_scratch, call(scratch=Scratch(10, MODES).buffers())),  # a P2 tetrahedron's
        (wrong_scratch, call(scratch=Scratch(problem.nodes, MODES + 1).buffers())),
        (wrong_scratch, call(scratch=scratch_with(1, np.empty(m - 1)))),  # r_u
        (wrong_scratch, call(scratch=scratch_with(2, np.empty((m + 3, m))))),  # K_uu
        # oversized (in bounds if unchecked): u, K_uu, K_up, scalars, T
        (wrong_scratch, call(scratch=scratch_with(0, np.empty((problem.nodes, 4))))),
        (wrong_scratch, call(scratch=scratch_with(2, np.empty((m, m + 3))))),
        (wrong_scratch, call(scratch=scratch_with(3, np.empty(m + 1)))),
        (wrong_scratch, call(scratch=scratch_with(4, np.empty(ek.SCALAR_SIZE + 1)))),
        (wrong_scratch, call(scratch=scratch_with(5, np.empty((m + 3, MODES))))),
    ]
    for message, arguments in calls:
        r_, K_ = arguments[8], arguments[9]
        r_.fill(7.0)
        K_.fill(7.0)
        with pytest.raises(ValueError, match=message):
            sampled_residual_tangent(*arguments)
        assert np.all(r_ == 7.0) and np.all(K_ == 7.0), message  # nothing written


def test_contributions_refuse_wrong_rest_tangents():
    """element_contributions' own checks (K0, k0, out) before anything is written."""
    problem = make_problem("hex-svk")
    everything, ones = np.arange(problem.elements), np.ones(problem.elements)
    inputs = sample(problem, everything, ones)
    q, pi = random_state()
    K0, k0 = readonly(problem.K0), readonly(problem.k0)
    scratch = Scratch(problem.nodes, MODES)
    size = MODES + PRESSURE_MODES
    for message, rest, shape in [
        ("K0 must be", (readonly(K0[:-1]), k0), (problem.elements, size)),
        ("K0 must be", (readonly(K0[:, :, :-1]), k0), (problem.elements, size)),
        ("K0 must be", (K0, readonly(k0[:, :-1])), (problem.elements, size)),
        ("out must be", (K0, k0), (problem.elements, size + 1)),
    ]:
        out = np.full(shape, 7.0)
        with pytest.raises(ValueError, match=message):
            element_contributions(*inputs, *rest, q, pi, out, scratch.u, scratch.r_u,
                                  scratch.scalars)  # fmt: skip
        assert np.all(out == 7.0)


def test_geometry_is_the_element_kernels_map():
    """element_geometry's point volumes sum to each element's volume (the element kernel's
    scalar, which maps its points itself), its gradients integrate a linear field's
    gradient exactly, and a reference tabulation of another cell, of other directions or a
    rule of other points is refused before writing."""
    for name in ("hex-svk", "tet-neo-hookean"):
        problem = make_problem(name)
        dN, dV = geometry(problem.X, problem.reference)
        zero = np.zeros(problem.X.shape[1:])
        for e in range(problem.elements):
            scalars = element_tangents(problem.X[e], zero, 0.0, problem.params[e],
                                       problem.reference)[3]  # fmt: skip
            assert abs(dV[e].sum() - scalars[ek.VOLUME]) <= 1e-13 * scalars[ek.VOLUME]
        G = RNG.standard_normal((3, 3))  # u = G X: grad u = G at every point
        grad = np.einsum("epaj,eai->epij", dN, problem.X @ G.T)
        assert np.abs(grad - G).max() <= 1e-12 * np.abs(G).max()
    hexahedra_ = make_problem("hex-svk")
    tetrahedron = ek.reference_element("tetrahedron")
    G, rule = hexahedra_.reference.gradients, hexahedra_.reference.weights
    for message, gradients, weights in [
        ("gradients must be", tetrahedron.gradients, tetrahedron.weights),
        ("gradients must be", readonly(np.pad(G, ((0, 0), (0, 0), (0, 1)))), rule),
        ("gradients must be", G, readonly(rule[:-1])),
    ]:
        dN = np.full((hexahedra_.elements, len(weights), hexahedra_.nodes, 3), 7.0)
        dV = np.full((hexahedra_.elements, len(weights)), 7.0)
        with pytest.raises(ValueError, match=message):
            ek.element_geometry(readonly(hexahedra_.X), gradients, weights, dN, dV)
        assert np.all(dN == 7.0) and np.all(dV == 7.0)
    points = len(rule)
    for dN, dV in [
        (np.empty((hexahedra_.elements, points, hexahedra_.nodes + 1, 3)), np.empty((6, points))),
        (np.empty((hexahedra_.elements, points, hexahedra_.nodes, 3)), np.empty((5, points))),
        (np.empty((hexahedra_.elements, points - 1, hexahedra_.nodes, 3)), np.empty((6, points))),
        (np.empty((hexahedra_.elements, points, hexahedra_.nodes, 2)), np.empty((6, points))),
    ]:
        dN.fill(7.0)
        dV.fill(7.0)
        with pytest.raises(ValueError, match="dN must be"):
            ek.element_geometry(readonly(hexahedra_.X), G, rule, dN, dV)
        assert np.all(dN == 7.0) and np.all(dV == 7.0)
    with pytest.raises(ValueError, match="X must be"):
        X = readonly(np.pad(hexahedra_.X, ((0, 0), (0, 0), (0, 1))))
        ek.element_geometry(X, G, rule, np.empty((6, points, hexahedra_.nodes, 3)),
                            np.empty((6, points)))  # fmt: skip


# -- no allocation ------------------------------------------------------------------------------
def test_allocates_nothing():
    """numba's allocation counters (which see an allocating canary) move as much over 1000
    calls of the kernels (with and without the tangent) from a compiled driver as over one:
    the boxing of the driver's arguments only."""
    body = """
        from hapticrom.online import element_kernels as ek, material_kernels as mk
        from hapticrom.online.hyperreduced import (
            Scratch, sampled_residual, sampled_residual_tangent)

        @njit
        def run(dN, dV, Phi, Psi, params, w, q, pi, r, K, u, r_u, K_uu, K_up, scalars, T, n):
            total = 0.0
            for _ in range(n):
                sampled_residual_tangent(dN, dV, Phi, Psi, params, w, q, pi, r, K,
                                         u, r_u, K_uu, K_up, scalars, T)
                total += r[0]
                sampled_residual(dN, dV, Phi, Psi, params, w, q, pi, r, u, r_u, scalars)
                total += r[0]
            return total

        def readonly(a):
            a = np.array(a, dtype=np.float64, order="C")
            a.flags.writeable = False
            return a

        rng = np.random.default_rng(1)
        fibres = dict(m0=np.array([1.0, 0.0, 0.0]), n0=np.array([0.0, 1.0, 0.0]))
        laws = [mk.law_parameters("neo-hookean", E=1.0, nu=0.3), mk.law_parameters("hgo", **fibres)]
        n, n_p, S = 5, 3, 2
        for cell in ("hexahedron", "tetrahedron"):
            ref = ek.reference_element(cell)
            m = ref.nodes.size
            X = readonly([ref.nodes, ref.nodes + 0.02 * rng.standard_normal(ref.nodes.shape)])
            dN = np.empty((S, len(ref.weights), len(ref.nodes), 3))
            dV = np.empty((S, len(ref.weights)))
            ek.element_geometry(X, ref.gradients, ref.weights, dN, dV)
            inputs = (readonly(dN), readonly(dV), readonly(0.01 * rng.standard_normal((S, m, n))),
                      readonly(rng.standard_normal((S, n_p))), readonly(laws),
                      readonly([1.0, 2.0]),
                      readonly(rng.standard_normal(n)), readonly(0.1 * rng.standard_normal(n_p)),
                      np.empty(n + n_p), np.empty((n + n_p, n + n_p)),
                      *Scratch(len(ref.nodes), n).buffers())
            same_allocations(run, *inputs)
            assert np.isfinite(inputs[8]).all()
        print("ok")
    """
    run_probe(body)
