"""A hyper-reduced mixed model (issue 18): global displacement and pressure bases, the
elements ECSW sampled with their weights, and a reduced Newton on them.

The residual and tangent are :mod:`hapticrom.online.hyperreduced`'s (the module's formulas:
the part linear in (u, p) exact through small matrices over every element, the rest summed
over the sampled elements); the Newton around them is numpy, the prototype of the online
solve. Units: mm, N, MPa; displacement rows in the campaign's canonical order.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from mpi4py import MPI

from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.organ import load_organ
from hapticrom.online import element_kernels as ek
from hapticrom.online.hyperreduced import (
    Scratch,
    element_contributions,
    sampled_residual,
    sampled_residual_tangent,
)
from hapticrom.online.material_kernels import KAPPA, law_parameters
from hapticrom.shared.errors import InputError, SolverError


@dataclass(frozen=True)
class MeshElements:
    """An organ's elements as the element kernels read them (E elements of ``nodes`` nodes,
    m = 3 nodes rows)."""

    X: np.ndarray  # (E, nodes, 3) reference nodes, mm, Basix order
    rows: np.ndarray  # (E, m) the nodes' canonical displacement rows
    cell: np.ndarray  # (E,) the element's canonical cell (pressure) index
    params: np.ndarray  # (E, PARAMETER_SIZE) packed law, each cell's fibres
    reference: ek.ReferenceElement

    @cached_property
    def geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """Every element's physical gradients (E, points, nodes, 3) and point volumes
        (E, points), mm: ``element_kernels.element_geometry``'s, computed once."""
        ref = self.reference
        dN = np.empty((len(self.X), len(ref.weights), self.X.shape[1], 3))
        dV = np.empty((len(self.X), len(ref.weights)))
        ek.element_geometry(_readonly(self.X), ref.gradients, ref.weights, dN, dV)
        return dN, dV


def mesh_elements(mesh_file, material) -> MeshElements:
    """The elements of the organ in ``mesh_file`` with ``material`` (a MaterialConfig)."""
    from dolfinx import fem

    organ = load_organ(mesh_file, MPI.COMM_SELF)
    cell = organ.cell_type
    V = fem.functionspace(organ.mesh, ("Lagrange", ek.CELLS[cell], (3,)))
    Q = fem.functionspace(organ.mesh, ("DG", 0))
    nodes, cells = CanonicalOrder(V), CanonicalOrder(Q)
    blocks = V.dofmap.list  # (E, nodes), Basix order within a cell
    X = V.tabulate_dof_coordinates()[blocks]
    canonical = nodes.canonical_of_global[blocks]
    rows = (3 * canonical[:, :, None] + np.arange(3)).reshape(len(blocks), -1)
    cell_index = cells.canonical_of_global[Q.dofmap.list[:, 0]]
    params = dict(material.params)
    if material.law == "hgo":
        m0, n0 = organ.fibre_fields()
        m = m0.x.array.reshape(-1, 3)[m0.function_space.dofmap.list[:, 0]]
        n = n0.x.array.reshape(-1, 3)[n0.function_space.dofmap.list[:, 0]]
        pairs = zip(m, n, strict=True)
        packed = np.array([law_parameters("hgo", **params, m0=a, n0=b) for a, b in pairs])
    else:
        packed = np.tile(law_parameters(material.law, **params), (len(blocks), 1))
    return MeshElements(np.ascontiguousarray(X), rows, cell_index, packed,
                        ek.reference_element(cell))  # fmt: skip


def group_nodes(mesh_file, group: str) -> tuple[np.ndarray, np.ndarray]:
    """(canonical node indices, their coordinates (mm)) of a surface group's facets: the
    nodes of :func:`mesh_elements`' displacement space (vertices, and edge nodes of P2)."""
    from dolfinx import fem

    organ = load_organ(mesh_file, MPI.COMM_SELF)
    V = fem.functionspace(organ.mesh, ("Lagrange", ek.CELLS[organ.cell_type], (3,)))
    blocks = fem.locate_dofs_topological(V, organ.mesh.topology.dim - 1, organ.facets(group))
    nodes = CanonicalOrder(V).canonical_of_global[blocks]
    return nodes, V.tabulate_dof_coordinates()[blocks]


def rest_tangents(elements: MeshElements) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each element's tangent at rest and volume: (K0 (E, m, m), k0 (E, m), V_e (E,))."""
    X, ref = elements.X, elements.reference
    E, m = elements.rows.shape
    K0, k0, volumes = np.empty((E, m, m)), np.empty((E, m)), np.empty(E)
    r_u, scalars = np.empty(m), np.empty(ek.SCALAR_SIZE)
    rest = np.zeros((m // 3, 3))
    for e in range(E):
        ek.element_residual_tangent(X[e], rest, 0.0, elements.params[e], ref.gradients,
                                    ref.weights, r_u, K0[e], k0[e], scalars)  # fmt: skip
        volumes[e] = scalars[ek.VOLUME]
    return K0, k0, volumes


@dataclass(frozen=True)
class RestOperators:
    """The mixed model's linear operators at rest, assembled over every element (N
    displacement rows, C cells): A = sum K0_e (N/mm, the volumetric part excluded), Bt =
    sum k0_e (N x C, mm^2: the divergence, transposed), and compliance = V_e / kappa_e
    (C,) (mm^3/MPa). With one pressure a cell it condenses exactly:
    K = A + Bt diag(1 / compliance) Bt^T is the full order's stiffness at rest."""

    A: scipy.sparse.csr_matrix
    Bt: scipy.sparse.csr_matrix
    compliance: np.ndarray

    def condensed(self) -> scipy.sparse.csr_matrix:
        return (self.A + self.Bt @ scipy.sparse.diags(1.0 / self.compliance) @ self.Bt.T).tocsr()


def rest_operators(mesh: MeshElements, rest) -> RestOperators:
    """:class:`RestOperators` from :func:`rest_tangents`' output."""
    K0, k0, volumes = rest
    E, m = mesh.rows.shape
    N = int(mesh.rows.max()) + 1
    rows = np.repeat(mesh.rows, m, axis=1).ravel()
    columns = np.tile(mesh.rows, (1, m)).ravel()
    A = scipy.sparse.csr_matrix((K0.ravel(), (rows, columns)), shape=(N, N))
    cells = np.repeat(mesh.cell, m)
    Bt = scipy.sparse.csr_matrix((k0.ravel(), (mesh.rows.ravel(), cells)), shape=(N, E))
    compliance = np.empty(E)
    compliance[mesh.cell] = volumes / mesh.params[:, KAPPA]
    return RestOperators(A, Bt, compliance)


def rest_solver(operators, free):
    """F -> K^-1 F on the ``free`` rows (zero elsewhere), K the condensed stiffness at rest:
    one factorisation."""
    K = operators.condensed()
    factor = scipy.sparse.linalg.splu(K[free][:, free].tocsc())

    def solve(F):
        out = np.zeros(F.shape)
        out[free] = factor.solve(F[free])
        return out

    return solve


def supremizers(operators: RestOperators, Psi, free) -> np.ndarray:
    """A^-1 Bt Psi (N, n_p), zero outside the ``free`` rows: for each pressure mode the
    displacement it pushes hardest, whose addition makes a mixed reduced basis inf-sup
    stable (Rozza and Veroy 2007)."""
    A = operators.A[free][:, free].tocsc()
    out = np.zeros((operators.A.shape[0], Psi.shape[1]))
    out[free] = scipy.sparse.linalg.splu(A).solve(np.asarray(operators.Bt @ Psi)[free])
    return out


def condensed_internal_force(mesh: MeshElements, u: np.ndarray) -> np.ndarray:
    """The full order's internal force (N, canonical rows) at the displacement u (mm), each
    element's pressure condensed out: p_e = kappa Theta_e / V_e makes its r_p zero, as at
    any equilibrium of the mixed model with one pressure a cell."""
    X, ref = mesh.X, mesh.reference
    f = np.zeros(u.size)
    r_u, scalars = np.empty(mesh.rows.shape[1]), np.empty(ek.SCALAR_SIZE)
    for e in range(len(X)):
        u_e = np.ascontiguousarray(u[mesh.rows[e]].reshape(-1, 3))
        params = mesh.params[e]
        ek.element_residual(X[e], u_e, 0.0, params, ref.gradients, ref.weights, r_u, scalars)
        p = params[KAPPA] * scalars[ek.PRESSURE_RESIDUAL] / scalars[ek.VOLUME]  # r_p(0) = Theta
        ek.element_residual(X[e], u_e, p, params, ref.gradients, ref.weights, r_u, scalars)
        f[mesh.rows[e]] += r_u
    return f


def modal_derivatives(mesh: MeshElements, Phi, solve, size: float = 5e-3) -> np.ndarray:
    """The second-order corrections of the modes Phi (N, n): -K^-1 D^2 f[phi_i, phi_j] for
    i <= j, (N, n (n + 1) / 2), D^2 f by central differences of
    :func:`condensed_internal_force` (four a pair, the modes scaled to ``size`` mm at most;
    the fourth-order term is exact to rounding for a quadratic f). ``solve``: K^-1 on the
    free rows (K, the stiffness at rest). A linear mode of a nearly incompressible tissue
    keeps its volume to first order only; its square changes it by |grad u|^2 and meets
    kappa (bench/ecsw_tradeoff.py measures the locking): these corrections restore the
    volume, and follow rotations, to second order (Idelsohn and Cardona 1985)."""
    scale = size / max(float(np.abs(Phi).max()), 1e-300)
    columns = []
    for i in range(Phi.shape[1]):
        for j in range(i, Phi.shape[1]):
            a, b = scale * Phi[:, i], scale * Phi[:, j]
            second = (condensed_internal_force(mesh, a + b) - condensed_internal_force(mesh, a - b)
                      - condensed_internal_force(mesh, b - a)
                      + condensed_internal_force(mesh, -a - b)) / (4.0 * scale**2)  # fmt: skip
            columns.append(-solve(second))
    return np.array(columns).T


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float64)
    a.flags.writeable = False
    return a


class HyperReducedModel:
    """R(q, pi) = 0 on the bases ``Phi`` (N, n) and ``Psi`` (cells, n_p) with the internal
    forces of the sampled ``elements`` (indices) and ``weights``; every element with weight
    1 if ``elements`` is None (the Galerkin model itself). ``split``: the linear part exact
    (else sampled with the rest). ``rest``: :func:`rest_tangents`' output, if computed.
    ``L_uu``, ``L_up``: the exact linear matrices over every element; ``linear``: the
    tangent's constant part, with the hyperreduced module's L_q, L_qp (the exact matrices
    less the sample's weighted share of them, which its kernels sum whole)."""

    def __init__(self, mesh: MeshElements, Phi, Psi, elements=None, weights=None,
                 split: bool = True, rest=None):  # fmt: skip
        E = len(mesh.X)
        if elements is None:
            elements, weights = np.arange(E), np.ones(E)
        elements, weights = np.asarray(elements, dtype=np.int64), np.asarray(weights, float)
        if elements.shape != weights.shape or not (weights > 0).all():
            raise InputError("elements and weights: one positive weight a sampled element")
        if elements.ndim != 1 or not ((elements >= 0) & (elements < E)).all():
            raise InputError(f"sampled elements must be indices of the mesh's {E} elements")
        if len(np.unique(elements)) != len(elements):
            raise InputError("a sampled element is listed twice: give it one weight")
        K0, k0, volumes = rest if rest is not None else rest_tangents(mesh)
        Phi_e = Phi[mesh.rows]  # (E, m, n)
        Psi_e = Psi[mesh.cell]  # (E, n_p)
        self.n, self.n_p = Phi.shape[1], Psi.shape[1]
        self.M = np.einsum("e,ek,el->kl", volumes / mesh.params[:, KAPPA], Psi_e, Psi_e)
        # the exact linear matrices, and the part of them the sampled sum holds
        self.L_uu = np.einsum("emi,emj->ij", Phi_e, np.einsum("emk,ekj->emj", K0, Phi_e))
        self.L_up = np.einsum("emi,em,ek->ik", Phi_e, k0, Psi_e)
        s = self.elements = elements.copy()  # the sampled elements' indices in the mesh
        s.flags.writeable = False
        n, size = self.n, self.n + self.n_p
        self.linear = np.zeros((size, size))  # the tangent's constant part (module doc)
        if split:
            K0_Phi = np.einsum("emk,ekj->emj", K0[s], Phi_e[s])
            self.linear[:n, :n] = self.L_uu - np.einsum("e,emi,emj->ij", weights, Phi_e[s], K0_Phi)
            self.linear[:n, n:] = self.L_up - np.einsum("e,emi,em,ek->ik", weights, Phi_e[s],
                                                        k0[s], Psi_e[s])  # fmt: skip
        self.linear[n:, :n], self.linear[n:, n:] = self.linear[:n, n:].T, -self.M
        dN, dV = mesh.geometry
        arrays = (dN[s], dV[s], Phi_e[s], Psi_e[s], mesh.params[s], weights)
        self.sample = tuple(_readonly(a) for a in arrays)
        self.rest = (_readonly(K0[s]), _readonly(k0[s])) if split else None
        self.scratch = Scratch(mesh.X.shape[1], self.n)
        self.r, self.K = np.empty(size), np.empty((size, size))

    @property
    def sampled_elements(self) -> int:
        return len(self.sample[0])

    def residual_tangent(self, q, pi, load) -> tuple[np.ndarray, np.ndarray]:
        """(R, dR/d(q, pi)) at (q, pi) under the reduced load ``load`` (n,), N."""
        sampled_residual_tangent(*self.sample, np.ascontiguousarray(q, float),
                                 np.ascontiguousarray(pi, float), self.r, self.K,
                                 *self.scratch.buffers())  # fmt: skip
        return self._with_linear_part(self.r, q, pi, load), self.K + self.linear

    def residual(self, q, pi, load) -> np.ndarray:
        """R at (q, pi) under ``load`` without the tangent (a modified Newton's iterations)."""
        scratch = self.scratch
        sampled_residual(*self.sample, np.ascontiguousarray(q, float),
                         np.ascontiguousarray(pi, float), self.r, scratch.u, scratch.r_u,
                         scratch.scalars)  # fmt: skip
        return self._with_linear_part(self.r, q, pi, load)

    def _with_linear_part(self, sampled, q, pi, load) -> np.ndarray:
        """The sampled residual plus the constant tangent's part and the load (a new array)."""
        n, r = self.n, sampled.copy()
        r += self.linear[:, :n] @ q + self.linear[:, n:] @ pi
        r[:n] -= load
        return r

    def linear_tangent(self) -> np.ndarray:
        """The constant part of dR/d(q, pi): [[L_q, L_qp], [L_qp^T, -M]] (a new array; the
        module's L_q, L_qp: the exact linear matrices less the sample's share of them)."""
        return self.linear.copy()

    def sampled_tangent(self, q, pi, part: slice) -> np.ndarray:
        """The sampled sum's dR/d(q, pi) over the sampled elements ``part`` alone (no linear
        part): a slice of the tangent, for a tangent built over several steps."""
        sample = tuple(a[part] for a in self.sample)
        sampled_residual_tangent(*sample, np.ascontiguousarray(q, float),
                                 np.ascontiguousarray(pi, float), self.r, self.K,
                                 *self.scratch.buffers())  # fmt: skip
        return self.K.copy()

    def solve(self, load, factors, tolerance: float = 1e-9, max_iterations: int = 30,
              partial: bool = False):  # fmt: skip
        """Newton along the load path ``factors`` * ``load`` (reduced, N), each step from
        the last; returns (q (steps, n), pi (steps, n_p), Newton iterations a step).
        Converged when the update is below ``tolerance`` relative to the state. A step that
        does not converge raises SolverError, or with ``partial`` ends the path there (the
        arrays hold the steps that converged)."""
        q, pi = np.zeros(self.n), np.zeros(self.n_p)
        Q, Pi, iterations = [], [], []
        for factor in factors:
            converged = self._newton(q, pi, factor * load, tolerance, max_iterations)
            if converged is None:
                if partial:
                    break
                raise SolverError(f"reduced Newton: no convergence in {max_iterations} "
                                  f"iterations at load factor {factor:g}")  # fmt: skip
            Q.append(q.copy())
            Pi.append(pi.copy())
            iterations.append(converged)
        return np.array(Q).reshape(-1, self.n), np.array(Pi).reshape(-1, self.n_p), iterations

    def _newton(self, q, pi, load, tolerance, max_iterations) -> int | None:
        """Newton from (q, pi), updated in place; its iterations, or None if it did not
        converge (or left the finite numbers)."""
        for iteration in range(1, max_iterations + 1):
            r, K = self.residual_tangent(q, pi, load)
            if not (np.isfinite(r).all() and np.isfinite(K).all()):
                return None
            delta = np.linalg.solve(K, -r)
            q += delta[: self.n]
            pi += delta[self.n :]
            if np.linalg.norm(delta[: self.n]) <= tolerance * max(np.linalg.norm(q), 1e-300):
                return iteration
        return None


class ModifiedNewton:
    """The frames of a haptic loop on a :class:`HyperReducedModel`: each frame from the last
    frame's state, iterations on the residual alone with the last factorised tangent (the
    load moves little in a frame, so the tangent of a few frames ago still contracts); a
    frame whose modified iterations reach ``refresh_after`` continues with full Newton
    iterations, each refreshing the tangent kept for the next frames. Converged when the
    update is below ``tolerance`` relative to the state, as :meth:`HyperReducedModel.solve`.
    ``residuals`` and ``tangents`` count the evaluations of each kind."""

    def __init__(self, model: HyperReducedModel, tolerance: float = 1e-8,
                 max_iterations: int = 30, refresh_after: int = 3):  # fmt: skip
        if refresh_after < 1 or max_iterations < 1:
            raise InputError("refresh_after and max_iterations must be at least 1")
        self.model = model
        self.tolerance, self.max_iterations = tolerance, max_iterations
        self.refresh_after = refresh_after
        self.factors = None  # the last tangent's LU factorisation
        self.residuals = self.tangents = 0

    def frame(self, q, pi, load) -> int | None:
        """Equilibrium under ``load`` from (q, pi), updated in place; the iterations, or
        None if it did not converge (or left the finite numbers): then q, pi and the kept
        tangent are as they were."""
        n, factors = self.model.n, self.factors
        x, y = q.copy(), pi.copy()
        for iteration in range(1, self.max_iterations + 1):
            if factors is None or iteration > self.refresh_after:
                r, K = self.model.residual_tangent(x, y, load)
                if not (np.isfinite(r).all() and np.isfinite(K).all()):
                    return None
                factors = scipy.linalg.lu_factor(K)
                self.tangents += 1
            else:
                r = self.model.residual(x, y, load)
                if not np.isfinite(r).all():
                    return None
                self.residuals += 1
            delta = scipy.linalg.lu_solve(factors, -r)
            x += delta[:n]
            y += delta[n:]
            if np.linalg.norm(delta[:n]) <= self.tolerance * max(np.linalg.norm(x), 1e-300):
                q[:], pi[:], self.factors = x, y, factors
                return iteration
        return None


def training_matrix(mesh: MeshElements, Phi, Psi, states, split: bool = True, rest=None):
    """ECSW's G for the model on ``Phi``, ``Psi``: column e stacks element e's sampled
    contribution (unweighted) at each of ``states``, reduced coordinates (q, pi); rows
    state-major, n + n_p a state. The displacement and pressure rows are scaled apart, by
    the norm of their full sums over the states, so that both weigh alike (the pressure
    rows are mm^3, the others N). Returns (G, the scale of a state's n + n_p rows)."""
    everything = HyperReducedModel(mesh, Phi, Psi, split=split, rest=rest)
    n, n_p, scratch = everything.n, everything.n_p, everything.scratch
    rows = everything.sample[2]
    rest_terms = everything.rest or (_readonly(np.zeros(rows.shape[:2] + rows.shape[1:2])),
                                     _readonly(np.zeros(rows.shape[:2])))  # fmt: skip
    out = np.empty((len(mesh.X), n + n_p))
    blocks = []
    for q, pi in states:
        element_contributions(*everything.sample, *rest_terms, np.ascontiguousarray(q, float),
                              np.ascontiguousarray(pi, float), out, scratch.u, scratch.r_u,
                              scratch.scalars)  # fmt: skip
        blocks.append(out.T.copy())
    G = np.vstack(blocks)
    sums = G.sum(axis=1).reshape(-1, n + n_p)
    scale = np.empty(n + n_p)
    for rows in (slice(0, n), slice(n, n + n_p)):
        scale[rows] = 1.0 / max(float(np.linalg.norm(sums[:, rows])), 1e-300)
    return G * np.tile(scale, len(blocks))[:, None], scale
