"""The tool's linear stiffness at any contact point: what the runtime scales each
neighbour's force curve by (artifact ``samples/tool_stiffness``, format 2.1).

Why: between samples the force was the blend sum_i w_i F_i(d) of the three neighbours'
curves. Where the organ's stiffness varies within a sample triangle (eightfold over the
liver's loadable surface, its thin border against its thick body), a blend of curves
cannot follow it: 30 % off at held-out liver positions with 24 samples. The linear
response to the tool's own load, K0 u = f, costs one back-substitution per point once K0
is factorised, so its stiffness k(x) is known everywhere. The runtime blends
``k(x) / k_i F_i(d)`` instead: the variation of the stiffness comes from the linear solve
and only the nonlinear part of each curve is blended (the same liver positions: 0.3 %;
the cornea demo 1.9 % -> 0.4 %; both measured with the campaign's own held-out solves).

k(x) = F / depth in the linear limit, with the campaign's own measures: the tool's weight w
(``ContactPatch.weight``) centred at x, pushing along e, has the load f = F g / W with
g = int w (e . v) dA and W = int w dA, and its depth is the work-conjugate mean
int w (u . e) dA / W = f . u / F (``WeightedMean``), so k = W^2 / (g^T K0^-1 g) (N/mm).

The points are the lattice of :mod:`hapticrom.shared.lattice` on every sample triangle,
moved onto the loadable surface along their blended normal (the runtime's own map from the
surface to a triangle, inverted), and pushed along the surface's normal there, as the
campaign pushes at its positions. A point shared by two
triangles (an edge's, a corner's) is computed once from the same arithmetic, so both
triangles store the same value and the runtime's force stays continuous.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse
from numba import njit

from hapticrom.online.proxy import closest_on_triangle
from hapticrom.shared.errors import InputError
from hapticrom.shared.lattice import lattice_weights

# The liver at 12 held-out positions: worst force error 2.5 % with 8, 0.93 % with 16.
DEFAULT_SUBDIVISIONS = 16
# Where a triangle's samples' normals differ by more than 60 degrees (allowed up to 80 since
# format 2.2: across a rim), the surface lies far from the triangle (13.7 mm on the 4k liver)
# and a step of the lattice is magnified on it: the thin rim's low stiffness fell between the
# points, k(x) 9.4 % high at a held-out position with 16, 1.0 % with 32 (and with 64).
RIM_SUBDIVISIONS = 32
RIM_NORMAL_DOT = 0.5  # cos 60 degrees
LOADABLE = 1  # RenderSurface.groups


def subdivisions_for(normals: np.ndarray, triangles: np.ndarray) -> int:
    """The lattice's subdivisions: RIM_SUBDIVISIONS where a triangle's samples' normals differ
    by more than 60 degrees, DEFAULT_SUBDIVISIONS otherwise (4x fewer points)."""
    n = np.asarray(normals)[np.asarray(triangles)]  # (S, 3, 3)
    rim = len(n) and np.einsum("sij,skj->sik", n, n).min() < RIM_NORMAL_DOT
    return RIM_SUBDIVISIONS if rim else DEFAULT_SUBDIVISIONS


# -- the points: a lattice on each sample triangle -------------------------------------------
def lattice_points(points, normals, triangles, subdivisions: int):
    """(centres (U, 3) mm, push directions (U, 3), index (S, L)): the distinct lattice
    points of the sample triangles, each triangle's row naming its points in lattice order.

    A point is keyed by its samples and their integer weights, sorted by sample, and
    computed in that order, so the triangles sharing it compute it bit for bit alike.
    """
    m, weights = subdivisions, lattice_weights(subdivisions)
    keys: dict[tuple, int] = {}
    centres, pushes = [], []
    index = np.empty((len(triangles), len(weights)), dtype=np.int64)
    for s, corners in enumerate(np.asarray(triangles)):
        for j, a in enumerate(weights):
            key = tuple(sorted((int(c), int(w)) for c, w in zip(corners, a, strict=True) if w))
            if key not in keys:
                keys[key] = len(centres)
                centre, normal = np.zeros(3), np.zeros(3)
                for c, w in key:
                    centre += w / m * points[c]
                    normal += w * normals[c]
                centres.append(centre)
                pushes.append(-normal / np.linalg.norm(normal))
            index[s, j] = keys[key]
    return np.array(centres), np.array(pushes), index


@njit(cache=True)
def _along_normals(queries, directions, vertices, triangles):
    """(triangle (Q,), barycentric weights (Q, 3)): each query q's point q + h n on the
    triangles facing against the push n with the smallest |h| (the line through q along n,
    both ways; Moller-Trumbore), or its nearest point on them if the line meets none. Only
    facing triangles: where the loadable surface wraps around a border (the liver's), the
    line also meets the other face, sometimes nearer (measured: lattice values 2.7 N/mm
    among 1.5-2.0, and 11.7 % force error at a held-out position)."""
    where, weights = np.full(len(queries), -1), np.zeros((len(queries), 3))
    for q in range(len(queries)):
        x, n = queries[q], directions[q]
        best = np.inf
        for t in range(len(triangles)):
            a = vertices[triangles[t, 0]]
            e1, e2 = vertices[triangles[t, 1]] - a, vertices[triangles[t, 2]] - a
            pvec = np.cross(n, e2)
            det = np.dot(e1, pvec)  # = -(e1 x e2) . n: > 0 where the face looks against n
            if det < 1e-14 * np.dot(e1, e1) * np.sqrt(np.dot(e2, e2)):
                continue  # edge-on, or facing away: not the face the push n goes into
            s = x - a
            u = np.dot(s, pvec) / det
            qvec = np.cross(s, e1)
            v = np.dot(n, qvec) / det
            if u < -1e-12 or v < -1e-12 or u + v > 1.0 + 1e-12:
                continue
            h = np.dot(e2, qvec) / det
            if abs(h) < best:
                best, where[q] = abs(h), t
                weights[q, 0], weights[q, 1], weights[q, 2] = 1.0 - u - v, u, v
        if best == np.inf:
            where[q] = _nearest_on(x, vertices, triangles, weights[q])
    return where, weights


@njit(cache=True)
def _nearest_on(x, vertices, triangles, out_weights):
    """The triangle nearest x (its nearest point's weights into ``out_weights``)."""
    p = (x[0], x[1], x[2])
    best, found = np.inf, 0
    for t in range(len(triangles)):
        corners = triangles[t]
        a, b, c = vertices[corners[0]], vertices[corners[1]], vertices[corners[2]]
        u, v, w, d2 = closest_on_triangle(p, (a[0], a[1], a[2]), (b[0], b[1], b[2]),
                                          (c[0], c[1], c[2]))  # fmt: skip
        if d2 < best:
            best, found = d2, t
            out_weights[0], out_weights[1], out_weights[2] = u, v, w
    return found


def onto_loadable_surface(centres, normals, surface) -> tuple[np.ndarray, np.ndarray]:
    """(points (mm), the tool's push there): each centre's point of the loadable triangles
    along its normal (the nearest if none; the runtime's own map from the surface to a
    sample triangle, inverted), and minus the surface's normal there, as a campaign pushes
    (vertex normals: area-weighted, interpolated linearly; a sample triangle's blended
    normal is up to 17 degrees off on the liver, and k along it up to 18 % off)."""
    triangles = np.ascontiguousarray(surface.triangles[surface.groups == LOADABLE], np.int64)
    vertices = np.ascontiguousarray(surface.vertices, np.float64)
    where, weights = _along_normals(np.ascontiguousarray(centres, np.float64),
                                    np.ascontiguousarray(normals, np.float64), vertices,
                                    triangles)  # fmt: skip
    corners = triangles[where]  # (Q, 3)
    points = np.einsum("qc,qcx->qx", weights, vertices[corners])
    face = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                    vertices[triangles[:, 2]] - vertices[triangles[:, 0]])  # fmt: skip
    vertex_normals = np.zeros_like(vertices)
    for c in range(3):
        np.add.at(vertex_normals, triangles[:, c], face)  # area-weighted (|face| = 2 area)
    normal = np.einsum("qc,qcx->qx", weights, vertex_normals[corners])
    return points, -normal / np.linalg.norm(normal, axis=1, keepdims=True)


# -- the tool's load at any point and the linear solve -------------------------------------------
class ToolLoads:
    """The tool's load vector g and its weight W at any centre and push (rank-local, on
    COMM_SELF: one UFL form, its centre and direction constants changed per point)."""

    def __init__(self, config):
        import dolfinx
        import ufl
        from dolfinx import fem
        from mpi4py import MPI

        from hapticrom.offline.fe.dofs import CanonicalOrder
        from hapticrom.offline.fe.formulation import choose_element
        from hapticrom.offline.fe.organ import load_organ

        problem, load = config.problem, config.load
        organ = load_organ(problem.mesh.file, MPI.COMM_SELF)
        element = choose_element(organ.cell_type, problem.discretisation.element)
        mesh = organ.mesh
        V = fem.functionspace(mesh, ("Lagrange", element.displacement_degree, (3,)))
        facets = np.unique(organ.facets(load.surface)).astype(np.int32)
        tags = dolfinx.mesh.meshtags(mesh, mesh.topology.dim - 1, facets,
                                     np.ones(facets.size, dtype=np.int32))  # fmt: skip
        degree = 2 * element.displacement_degree + 4  # as the campaign's load integrals
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags,
                         metadata={"quadrature_degree": degree})(1)  # fmt: skip
        self.centre = fem.Constant(mesh, np.zeros(3))
        self.push = fem.Constant(mesh, np.zeros(3))
        X = ufl.SpatialCoordinate(mesh)
        s = ufl.dot(X - self.centre, X - self.centre) / float(load.contact_radius) ** 2
        w = ufl.conditional(ufl.lt(s, 1.0), (1 - s) ** 2, 0.0)
        v = ufl.TestFunction(V)
        self._g = fem.form(w * ufl.dot(self.push, v) * ds)
        self._W = fem.form(w * ds)
        self._order = CanonicalOrder(V)
        self._assemble = (fem.assemble_vector, fem.assemble_scalar)

    def at(self, centre, push) -> tuple[np.ndarray, float]:
        """(g (canonical DOFs) mm^2, W mm^2) of the tool centred at ``centre`` (mm)."""
        self.centre.value[:] = centre
        self.push.value[:] = push
        vector, scalar = self._assemble
        return self._order.gather(vector(self._g).array), float(scalar(self._W))


BATCH = 128  # right-hand sides per solve: MUMPS's multi-RHS solve is 7x faster a column


def linear_stiffness(K0, supported_nodes, loads: ToolLoads, centres, pushes) -> np.ndarray:
    """k = W^2 / (g^T K0^-1 g) (N/mm) at each centre, the supports' DOFs held (see
    :func:`linear_responses`)."""
    out = np.empty(len(centres))
    for chunk, G, X, W in linear_responses(K0, supported_nodes, loads, centres, pushes):
        out[chunk.start : chunk.stop] = W**2 / np.einsum("ij,ij->j", G, X)
    return out


def linear_responses(K0, supported_nodes, loads: ToolLoads, centres, pushes):
    """Yield (range of the centres, G, X = K0^-1 G, W) for ``BATCH`` centres at a time: the
    tool's loads g (free DOFs, columns) and weights W, and the linear responses (free DOFs;
    :func:`free_dofs` says which): one sparse Cholesky factorisation (MUMPS; options prefix
    ``tool_stiffness_``), then multi-RHS solves."""
    free = free_dofs(K0.shape[0], supported_nodes)
    solver = _factorised(scipy.sparse.csr_matrix(K0)[free][:, free].tocsr())
    try:
        for first in range(0, len(centres), BATCH):
            chunk = range(first, min(first + BATCH, len(centres)))
            G, W = np.empty((len(free), len(chunk)), order="F"), np.empty(len(chunk))
            for j, i in enumerate(chunk):
                g, W[j] = loads.at(centres[i], pushes[i])
                if not W[j] > 0:
                    raise InputError(
                        f"the tool centred at {np.round(centres[i], 4).tolist()} mm touches "
                        "no face of the loadable surface: a sample triangle strays from it"
                    )
                G[:, j] = g[free]
            yield chunk, G, _solve(solver, G), W
    finally:
        solver.destroy()


def free_dofs(num_dofs: int, supported_nodes) -> np.ndarray:
    """The DOFs that are not held by a support (canonical order)."""
    fixed = np.zeros(num_dofs, dtype=bool)
    fixed[(3 * np.asarray(supported_nodes)[:, None] + np.arange(3)).ravel()] = True
    return np.flatnonzero(~fixed)


def _factorised(A: scipy.sparse.csr_matrix):
    """A KSP holding A (symmetric positive definite) factorised by MUMPS's Cholesky."""
    from petsc4py import PETSc

    ints = PETSc.IntType
    M = PETSc.Mat().createAIJ(size=A.shape, csr=(A.indptr.astype(ints), A.indices.astype(ints),
                              A.data), comm=PETSc.COMM_SELF)  # fmt: skip
    M.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    solver = PETSc.KSP().create(PETSc.COMM_SELF)
    solver.setOptionsPrefix("tool_stiffness_")
    solver.setOperators(M)
    solver.setType("preonly")
    solver.getPC().setType("cholesky")
    solver.getPC().setFactorSolverType("mumps")
    solver.setFromOptions()
    solver.setUp()
    M.destroy()
    return solver


def _solve(solver, G: np.ndarray) -> np.ndarray:
    """K^-1 G for the columns of G (Fortran order), by the factor's multi-RHS solve."""
    from petsc4py import PETSc

    B = PETSc.Mat().createDense(G.shape, array=G, comm=PETSc.COMM_SELF)
    X = PETSc.Mat().createDense(G.shape, comm=PETSc.COMM_SELF)
    X.setUp()
    solver.getPC().getFactorMatrix().matSolve(B, X)
    out = X.getDenseArray().copy()
    B.destroy()
    X.destroy()
    return out


def stiffness_lattice(config, store, neighbourhoods, surface, subdivisions=None,
                      say=print) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """((S, L), (P,)) N/mm: the tool's linear stiffness at the lattice points of every
    sample triangle, and at the samples themselves (rank 0; the campaign's K0 from its
    store). ``subdivisions``: None chooses them by :func:`subdivisions_for`."""
    t0 = time.perf_counter()
    where = neighbourhoods
    if subdivisions is None:
        subdivisions = subdivisions_for(where.normals, where.triangles)
    centres, pushes, index = lattice_points(where.points, where.normals, where.triangles,
                                            subdivisions)  # fmt: skip
    k = sample_stiffness(config, store, np.vstack([centres, where.points]),
                         np.vstack([pushes, -where.normals]), surface)  # fmt: skip
    say(f"the tool's linear stiffness at {len(centres)} lattice points ({subdivisions} "
        f"subdivisions; {k.min():.4g} to "
        f"{k.max():.4g} N/mm) in {time.perf_counter() - t0:.1f} s")  # fmt: skip
    return k[index], k[len(centres) :]


def sample_stiffness(config, store, points, pushes, surface) -> np.ndarray:
    """(Q,) N/mm: the tool's linear stiffness at ``points``, each moved onto the loadable
    surface along its push, then pushed as the campaign pushed: along the surface's normal
    there, or along the campaign's fixed direction (along the normal instead, k was up to
    14 % off on a ring of the test cornea: review); the campaign's K0 from its store
    (rank 0)."""
    from hapticrom.offline.campaign.store import csr_from

    on_surface, pushes = onto_loadable_surface(points, pushes, surface)
    if config.load.direction != "normal":  # the campaign pushed along one vector everywhere
        fixed = np.asarray(config.load.direction, dtype=float)
        pushes = np.tile(fixed / np.linalg.norm(fixed), (len(pushes), 1))
    data, _ = store.read_operators()
    return linear_stiffness(csr_from(data, "K0"), data["supported_nodes"], ToolLoads(config),
                            on_surface, pushes)  # fmt: skip
