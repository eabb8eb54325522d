"""The Asymptotic Numerical Method in a reduced space, for any UFL strain energy (thesis ch. 3).

Reduced unknowns ``y = (alpha, beta, lam)``: the displacement
``u = lam g + A alpha`` (A: POD modes, zero on the supports and on a
displacement-controlled patch; g: the lifting, the displacement per unit load
factor), the pressure ``p = B beta`` (reduced pressure modes: see
:mod:`.reduction` for why the pressure must be reduced, not condensed
element-wise) and the load factor ``lam``. The reduced residual is

    r(y) = [ A^T (R_u(u, p) - lam f) ;  B^T R_p(u, p) ]      (n + n_p equations)

with the full-order residuals R_u (N), R_p (mm^3) and the external load f at
load factor 1 (N). ANM (thesis eqs. 3.19-3.29) writes the branch through an
equilibrium ``y0`` as a power series ``y(a) = y0 + sum_k a^k y_k`` in the
pseudo-arclength ``a = <alpha - alpha0, alpha1>_s + (lam - lam0) lam1`` and
solves one linear system with the same reduced tangent per order:

    K_t x_k + r_lam lam_k = -F_k^nl,     <x_k, x_1>_s + lam_k lam_1 = delta_k1.

``F_k^nl`` is the k-th Taylor coefficient of ``r`` along the truncated path
``sum_{i<k} a^i y_i``. It is computed from the UFL energy itself, for any law:
the residual is compiled for complex arguments, evaluated at ``M`` points of a
circle ``a = rho exp(2 pi i j / M)`` and the Cauchy integral is done by an FFT
(aliasing from orders k + M onward is ``(rho / R)^M`` for a series of radius
``R``; ``rho = R / 2`` and ``M = 32`` make it ~1e-10). The tangent ``K_t`` is
built by complex-step derivatives (exact to rounding). Nothing is derived by
hand per material (thesis Appendix A shows why that does not scale).

Pressure: the pressure equations are part of ``r`` and solved with the
displacement at every order (the reduced tangent's pressure block is small and
dense), which is the reduced-space condensation of the element-wise pressure:
the series of the displacement is that of the condensed problem.

Validity of a section (the classical criterion, Cochelin 1994): the series is
used up to ``a_max = (tol ||y_1|| / ||y_N||)^(1/(N-1))``; a new section starts
there (after a reduced Newton correction of the small residual left by the
truncation) until the requested load range is covered.

Outputs, as series in ``a`` of the same order: the load ``lam`` and the
response conjugate to it. Displacement control: the tool force along the tool
direction, ``g^T R_u / |d|`` (N; at equilibrium this is the sum of the
residual over the patch, the full-order reaction). Force control: the
displacement along the load, ``f^T u / |sum f|`` (mm).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import dolfinx
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from scipy.optimize import brentq

from hapticrom.offline.fe.formulation import HyperelasticModel, mixed_energy_density
from hapticrom.shared.errors import InputError, SolverError

COMPLEX = np.complex128
# Complex kernels: without -fcx-limited-range every complex product and quotient is a call
# to libgcc's __muldc3/__divdc3 (C99 Annex G inf/nan recovery, which finite residuals
# never need).
JIT_OPTIONS = {"cffi_extra_compile_args": ["-O2", "-g0", "-fcx-limited-range"]}
# Radius of the Cauchy integrals as a fraction of the estimated radius of convergence R.
# Along the truncated path r(a) = a^k (r_k + r_(k+1) a + ...), so with M points the
# coefficient r_k is polluted only by r_(k+M) rho^M ~ 4^-M relative (1e-6 for M = 10),
# while rounding grows like eps 4^k (1e-12 at k = 6, 2e-10 at k = 10). The FFT of a
# real path's values is real, and M > k points resolve the coefficient k.
RHO_FRACTION = 1.0 / 4.0
# Imaginary step of the tangent, relative to the state's size. No subtraction, so the
# step can be small; but not 1e-30: the compiled HGO residual carries imaginary noise of
# ~1e-25 N even at real arguments (measured on the cornea; from the complex power
# J^(-2/3), it seems), and 1e-10 keeps that below 1e-14 relative while the O(h^2) error
# of the complex step stays at ~1e-20.
COMPLEX_STEP = 1e-10


# -- the residual at complex arguments -----------------------------------------------
class ComplexResidual:
    """The model's internal residual [R_u, R_p], compiled for complex displacements.

    Built from the same energy as the real forms
    (:func:`~hapticrom.offline.fe.formulation.mixed_energy_density`) with complex
    copies of the constants and fibres. The load is not included: it is a dead
    load, linear in the load factor, and enters the reduced residual as
    ``-lam A^T f``. UFL's complex mode conjugates test functions, so the forms
    are written ``inner(dPsi/dF, grad v)``; the basis functions are real, which
    makes that the analytic continuation of the real residual.
    """

    def __init__(self, model: HyperelasticModel):
        law = model.law
        if getattr(law, "fibre_tension_only", False):
            raise InputError(
                "ANM needs an analytic energy; 'fibre_tension_only = true' switches the "
                "fibres on and off (not differentiable at I4 = 1): set it to false"
            )
        mesh = model.organ.mesh
        self.model = model
        self.u = fem.Function(model.V, dtype=COMPLEX)
        self.p = fem.Function(model.Q, dtype=COMPLEX) if model.Q is not None else None
        constants = {k: fem.Constant(mesh, COMPLEX(c.value)) for k, c in model.constants.items()}
        fibres = None
        if model.fibres is not None:
            fibres = tuple(self._complex_copy(f) for f in model.fibres)
        F = ufl.variable(ufl.Identity(3) + ufl.grad(self.u))
        p = ufl.variable(self.p) if self.p is not None else None
        psi = mixed_energy_density(law, F, p, constants, fibres)
        forms = [ufl.inner(ufl.diff(psi, F), ufl.grad(ufl.TestFunction(model.V))) * model.dx]
        if p is not None:
            forms.append(ufl.inner(ufl.diff(psi, p), ufl.TestFunction(model.Q)) * model.dx)
        self.forms = [fem.form(f, dtype=COMPLEX, jit_options=JIT_OPTIONS) for f in forms]
        spaces = [model.V] + ([model.Q] if model.Q is not None else [])
        self._vectors = [
            dolfinx.la.vector(V.dofmap.index_map, V.dofmap.index_map_bs, dtype=COMPLEX)
            for V in spaces
        ]
        self.owned = [V.dofmap.index_map.size_local * V.dofmap.index_map_bs for V in spaces]
        self._keep = (constants, fibres)

    @staticmethod
    def _complex_copy(f: fem.Function) -> fem.Function:
        g = fem.Function(f.function_space, dtype=COMPLEX)
        g.x.array[:] = f.x.array
        return g

    def __call__(self, u_owned: np.ndarray, p_owned: np.ndarray | None = None):
        """Owned rows of R_u (N) and R_p (mm^3, or None) at the given owned DOF values."""
        self.u.x.array[: self.owned[0]] = u_owned
        self.u.x.scatter_forward()
        if self.p is not None:
            self.p.x.array[: self.owned[1]] = p_owned
            self.p.x.scatter_forward()
        out = []
        for form, vec, n in zip(self.forms, self._vectors, self.owned, strict=True):
            vec.array[:] = 0.0
            fem.assemble_vector(vec.array, form)
            vec.scatter_reverse(dolfinx.la.InsertMode.add)
            out.append(vec.array[:n].copy())
        return out[0], (out[1] if len(out) > 1 else None)


# -- the reduced space ----------------------------------------------------------------
@dataclass
class ReducedSpace:
    """This rank's owned rows of the reduced space's vectors.

    ``A`` (rows, n): displacement modes (mm); ``g`` (rows,): lifting (mm per unit
    load factor, zero under force control); ``f`` (rows,): external load at load
    factor 1 (N, zero under displacement control); ``B`` (cells, n_p) or None:
    pressure modes (MPa); ``load_size``: |d| (mm) or |sum f| (N), what load
    factor 1 means; ``mode``: "displacement" or "force".
    """

    A: np.ndarray
    g: np.ndarray
    f: np.ndarray
    B: np.ndarray | None
    load_size: float
    mode: str

    @property
    def n(self) -> int:
        """Number of displacement modes."""
        return self.A.shape[1]

    @property
    def n_p(self) -> int:
        """Number of pressure modes (0 without a pressure)."""
        return 0 if self.B is None else self.B.shape[1]


def snapshot_space(
    comm: MPI.Comm,
    load_factor: np.ndarray,
    U: np.ndarray,
    P: np.ndarray | None,
    mode: str,
    f: np.ndarray,
    load_size: float | None = None,
    truncation=None,
) -> tuple[ReducedSpace, np.ndarray]:
    """The reduced space of one load path's snapshots, and the arclength scale.

    ``U`` (owned rows x K) and ``P`` (owned cells x K): converged states at load
    factors ``load_factor`` (K,), in DOLFINx owned order. Displacement control:
    the lifting g is the first state per unit load factor (exactly the tool's
    displacement on the patch), and the modes are the POD of ``u_k - lam_k g``
    (zero on the patch). Force control: g = 0, the modes are the POD of the
    states. Pressure modes: at most ceil(n_u / 2) (see :mod:`.reduction`).
    Scale: alpha by the size of the last state's coordinates, lam by 1.
    """
    from hapticrom.offline.reduce.pod import Truncation, pod, pressure_basis

    truncation = truncation or Truncation()
    lam = np.asarray(load_factor, dtype=float)
    if mode == "displacement":
        g = U[:, 0] / lam[0]
        Q = U[:, 1:] - np.outer(g, lam[1:])
        if load_size is None:
            raise ValueError("displacement control needs the tool displacement's size")
    else:
        g = np.zeros(U.shape[0])
        Q = U
        total = comm.allreduce(f.reshape(-1, 3).sum(axis=0), op=MPI.SUM)
        load_size = float(np.linalg.norm(total))  # N
    if Q.shape[1] == 0:
        raise InputError("POD-ANM needs at least two load increments")
    A = pod(Q, comm, None, truncation).basis_local
    if A.shape[1] == 0:
        raise InputError("the snapshots have no displacement mode beyond the lifting")
    B = None
    if P is not None:
        B = pressure_basis(P, comm, A.shape[1] + (1 if mode == "displacement" else 0))
    space = ReducedSpace(A=A, g=g, f=f, B=B, load_size=float(load_size), mode=mode)
    alpha_last = comm.allreduce(A.T @ Q[:, -1], op=MPI.SUM)
    s_alpha = max(float(np.linalg.norm(alpha_last)), 1e-30)
    scale = np.r_[np.full(A.shape[1], 1.0 / s_alpha**2), np.zeros(space.n_p), 1.0]
    return space, scale


class ReducedResidual:
    """r(y) of the module docstring, plus the conjugate response, at complex y."""

    def __init__(self, residual: ComplexResidual, space: ReducedSpace, comm: MPI.Comm):
        self.residual, self.space, self.comm = residual, space, comm
        self.n, self.n_p = space.n, space.n_p
        self.size = self.n + self.n_p + 1  # unknowns (alpha, beta, lam)
        self.evaluations = 0

    def fields(self, y: np.ndarray):
        """(u, p) owned rows at reduced unknowns y: u = lam g + A alpha, p = B beta."""
        s = self.space
        alpha, beta, lam = y[: self.n], y[self.n : self.n + self.n_p], y[-1]
        u = lam * s.g + s.A @ alpha
        p = s.B @ beta if s.B is not None else None
        return u, p

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """[r (n + n_p), response (1)] at y (complex or real), identical on every rank."""
        s = self.space
        y = np.asarray(y, dtype=COMPLEX)
        u, p = self.fields(y)
        Ru, Rp = self.residual(u, p)
        local = np.empty(self.n + self.n_p + 1, dtype=COMPLEX)
        local[: self.n] = s.A.T @ Ru - y[-1] * (s.f @ s.A)
        if self.n_p:
            local[self.n : self.n + self.n_p] = s.B.T @ Rp
        if s.mode == "displacement":
            local[-1] = (s.g @ Ru) / s.load_size  # tool force along the tool direction, N
        else:
            local[-1] = (s.f @ u) / s.load_size  # displacement along the load, mm
        self.evaluations += 1
        return self.comm.allreduce(local, op=MPI.SUM)

    def jacobian(self, y0: np.ndarray) -> np.ndarray:
        """d[r, response]/dy at real y0 by complex steps: (n + n_p + 1) x (n + n_p + 1)."""
        J = np.empty((self.size, self.size))
        h = COMPLEX_STEP * max(1.0, float(np.abs(y0).max()))
        for j in range(self.size):
            y = np.asarray(y0, dtype=COMPLEX).copy()
            y[j] += 1j * h
            J[:, j] = self(y).imag / h
        return J

    def taylor(self, Y: np.ndarray, orders: int, rho: float, points: int = 16) -> np.ndarray:
        """Taylor coefficients 0..orders of [r, response] along ``sum_i a^i Y[i]`` (real Y).

        Cauchy integral on the circle |a| = rho by an FFT of ``points`` values; the
        path is real, so r(conj a) = conj r(a) and half the circle suffices.
        """
        if orders >= points or points % 2:
            raise ValueError(f"an even number of points above {orders} is needed, got {points}")
        half = points // 2
        a = rho * np.exp(2j * np.pi * np.arange(half + 1) / points)
        powers = a[:, None] ** np.arange(len(Y))[None, :]  # (half+1, m)
        values = np.array([self(powers[j] @ Y) for j in range(half + 1)])
        full = np.concatenate([values, np.conj(values[half - 1 : 0 : -1])])
        c = np.fft.fft(full, axis=0)[: orders + 1] / points
        return c.real / rho ** np.arange(orders + 1)[:, None]


# -- series and sections ---------------------------------------------------------------
@dataclass
class Section:
    """One ANM section: y(a) = sum_k a^k Y[k], response(a) = sum_k a^k response[k]."""

    Y: np.ndarray  # (N + 1, n + n_p + 1): coefficients of (alpha, beta, lam); Y[0] = start
    response: np.ndarray  # (N + 1,): N (displacement control) or mm (force control)
    a_max: float  # validity radius

    @property
    def order(self) -> int:
        """Order N of the series."""
        return self.Y.shape[0] - 1

    def truncated(self, order: int, a_max: float) -> Section:
        """The same section cut to order ``order``, valid to ``a_max``."""
        return Section(self.Y[: order + 1].copy(), self.response[: order + 1].copy(), a_max)

    def load(self, a):
        """Load factor at a (Horner)."""
        return np.polynomial.polynomial.polyval(a, self.Y[:, -1])

    def state(self, a) -> np.ndarray:
        """Reduced unknowns y(a) (Horner)."""
        return np.polynomial.polynomial.polyval(a, self.Y)

    def value(self, a):
        """Response at a (Horner)."""
        return np.polynomial.polynomial.polyval(a, self.response)

    def end(self) -> tuple[float, float]:
        """(load factor, response) at the end of the section."""
        return float(self.load(self.a_max)), float(self.value(self.a_max))


@dataclass
class ANMOptions:
    """Order, validity tolerance and continuation limits of the series."""

    order: int = 6
    tolerance: float = 1e-4  # validity: ||y_N|| a^N <= tol ||y_1|| a (module docstring)
    load_max: float = 1.0  # continue until this load factor is covered
    max_sections: int = 60
    points: int | None = None  # FFT points of the Cauchy integrals (None: max(10, N + 4))
    correction_tolerance: float = 1e-10  # reduced Newton at a section start, relative

    def __post_init__(self):
        if not (isinstance(self.order, int) and 1 <= self.order <= 15):
            raise InputError(f"ANM order must be an integer in 1..15, got {self.order!r}")
        if not (0 < self.tolerance < 1):
            raise InputError(f"ANM tolerance must be in (0, 1), got {self.tolerance!r}")
        if self.points is None:
            self.points = max(10, self.order + 4)
            self.points += self.points % 2
        if self.points < self.order + 2 or self.points % 2:
            raise InputError(f"ANM needs an even number of FFT points, at least {self.order + 2}")


@dataclass
class Branch:
    """A continuation: sections in order of increasing pseudo-arclength."""

    sections: list[Section]
    scale: np.ndarray  # weights of the arclength inner product on y
    evaluations: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def locate(self, load: float) -> tuple[Section, float]:
        """The section and the a at which the load factor equals ``load`` (root-find)."""
        for s in self.sections:
            lo, hi = float(s.load(0.0)), s.end()[0]
            if min(lo, hi) - 1e-14 <= load <= max(lo, hi) + 1e-14:
                return s, root(s, load)
        raise ValueError(f"load factor {load} is outside the branch")

    def response_at(self, load: float) -> float:
        """The response where the load factor equals ``load``."""
        s, a = self.locate(load)
        return float(s.value(a))

    def state_at(self, load: float) -> np.ndarray:
        """The reduced unknowns where the load factor equals ``load``."""
        s, a = self.locate(load)
        return s.state(a)

    @property
    def load_range(self) -> tuple[float, float]:
        """(first, last) load factor the branch covers."""
        return float(self.sections[0].load(0.0)), self.sections[-1].end()[0]


def root(section: Section, load: float) -> float:
    """a in [0, a_max] with lam(a) = load: Brent's method on the polynomial (scipy's brentq).

    A load outside [lam(0), lam(a_max)] by rounding (``Branch.locate`` accepts 1e-14)
    gives the nearer end.
    """
    lo, hi = 0.0, float(section.a_max)

    def residual(a: float) -> float:
        return float(section.load(a)) - load

    f_lo, f_hi = residual(lo), residual(hi)
    if f_lo == 0.0 or f_hi == 0.0 or (f_lo > 0) == (f_hi > 0):
        return lo if abs(f_lo) <= abs(f_hi) else hi
    return brentq(residual, lo, hi, xtol=1e-15 * hi)


def _inner(x, y, scale):
    return float(np.sum(scale * x * y))


def validity_radius(Y: np.ndarray, scale: np.ndarray, tol: float) -> float:
    """(tol ||y_1|| / ||y_N||)^(1/(N-1)) in the arclength norm."""
    N = Y.shape[0] - 1
    n1 = math.sqrt(_inner(Y[1], Y[1], scale))
    nN = math.sqrt(_inner(Y[N], Y[N], scale))
    if N < 2 or nN == 0.0:
        return math.inf
    return (tol * n1 / nN) ** (1.0 / (N - 1))


def series(
    r: ReducedResidual,
    y0: np.ndarray,
    J: np.ndarray,
    scale: np.ndarray,
    order: int,
    previous_direction: np.ndarray | None,
    rho_cap: float,
    remaining_load: float,
    response0: float,
    points: int = 16,
) -> tuple[np.ndarray, np.ndarray]:
    """The ANM coefficients y_1..y_N at the equilibrium y0 with its tangent J.

    Returns Y (Y[0] = y0) and the response's coefficients (response0 at y0).
    """
    m = r.size - 1  # equations (n + n_p), unknowns m + 1
    Kt, r_lam = J[:m, :m], J[:m, m]
    sx = scale[:m]
    x_hat = -np.linalg.solve(Kt, r_lam)  # d(alpha, beta)/d(lam) along the branch
    lam1 = 1.0 / math.sqrt(_inner(x_hat, x_hat, sx) + scale[m])
    y1 = np.r_[lam1 * x_hat, lam1]
    if previous_direction is not None and _inner(y1, previous_direction, scale) < 0:
        y1 = -y1  # keep going the same way along the branch
    elif previous_direction is None and y1[m] < 0:
        y1 = -y1  # start by loading
    Y = [np.asarray(y0, dtype=float), y1]
    response = [response0, J[m] @ y1]
    denominator = _inner(x_hat, y1[:m], sx) + scale[m] * y1[m]
    # Before the coefficients say anything: half of the a that covers the remaining load
    # linearly (lam_1 <= 1 in the arclength norm), at most the previous section's radius.
    rho = RHO_FRACTION * min(rho_cap, remaining_load / max(abs(y1[m]), 1e-12))
    n1 = math.sqrt(_inner(y1, y1, scale))
    for k in range(2, order + 1):
        if k >= 3:
            # Half the radius of convergence estimated from the growth of the coefficients
            # (the smallest root estimate so far): far enough from any singularity of the
            # energy (ln J, J^(-2/3) at J = 0) and from the aliasing orders k + M.
            nj = math.sqrt(max(_inner(Y[-1], Y[-1], scale), 1e-300))
            rho = min(rho, RHO_FRACTION * (n1 / nj) ** (1.0 / (k - 2)))
        Fk = r.taylor(np.array(Y), k, rho, points)[k]
        x_tilde = -np.linalg.solve(Kt, Fk[:m])
        lam_k = -_inner(x_tilde, y1[:m], sx) / denominator
        Y.append(np.r_[x_tilde + lam_k * x_hat, lam_k])
        # The response's coefficient k: the same integral's last row (the path without
        # y_k) plus its linear part in y_k, from the tangent's last row.
        response.append(Fk[m] + J[m] @ Y[k])
    return np.array(Y), np.array(response)


def _correct(r: ReducedResidual, y: np.ndarray, reference: float, tol: float):
    """Reduced Newton at fixed load factor; returns (y, J at y, value of r at y, iterations)."""
    m = r.size - 1
    y = y.copy()
    for it in range(8):
        J = r.jacobian(y)
        value = r(y).real
        if np.linalg.norm(value[:m]) <= tol * reference:
            return y, J, value, it
        y[:m] -= np.linalg.solve(J[:m, :m], value[:m])
    raise SolverError(
        f"ANM: the reduced Newton correction did not converge at load factor {y[-1]:.6g} "
        f"(residual {np.linalg.norm(value[:m]):.3e}, reference {reference:.3e})"
    )


def continuation(r: ReducedResidual, scale: np.ndarray, options: ANMOptions) -> Branch:
    """ANM sections from the reference state (y = 0) until ``options.load_max`` is covered."""
    t0 = time.perf_counter()
    y0 = np.zeros(r.size)
    J = r.jacobian(y0)
    reference = float(np.linalg.norm(J[: r.size - 1, -1]))  # |dr/dlam|: load factor 1's force
    sections: list[Section] = []
    direction = None
    rho = math.inf  # radius cap for the first Cauchy integrals: twice the previous a_max
    notes = []
    while True:
        if len(sections) >= options.max_sections:
            raise SolverError(
                f"ANM: {options.max_sections} sections did not reach load factor "
                f"{options.load_max} (reached {y0[-1]:.4g}); raise the order or the tolerance"
            )
        y0, J, value, its = _correct(r, y0, reference, options.correction_tolerance)
        if its:
            notes.append(f"section {len(sections) + 1}: {its} correction iteration(s)")
        remaining = max(options.load_max - y0[-1], 0.05 * options.load_max)
        Y, response = series(
            r, y0, J, scale, options.order, direction, rho, remaining, value[-1], options.points
        )
        a_max = validity_radius(Y, scale, options.tolerance) if options.order >= 2 else math.inf
        if not math.isfinite(a_max):
            # Order 1 (or an exactly linear problem): one section reaches any load.
            dlam = Y[1][-1]
            a_max = (options.load_max - y0[-1]) / dlam if dlam > 0 else 1.0
        section = Section(Y, response, a_max)
        sections.append(section)
        direction = Y[1]
        rho = 2.0 * a_max
        y0 = section.state(a_max)
        if y0[-1] >= options.load_max or options.order == 1 or not math.isfinite(a_max):
            break
    seconds = time.perf_counter() - t0
    return Branch(sections, scale, r.evaluations, seconds, notes)
