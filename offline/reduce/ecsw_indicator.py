"""An online error indicator of the hyper-reduced model (issue 18): the full-order
residual at the reduced state, read on a second element sample.

The reduced state u = Phi q, p = Psi pi leaves a residual r(u, p) in the full order. Its
part in an enriched space W = [Phi, Phi_e] (Phi_e: directions the basis lacks, here the
next POD modes of the snapshots) is what the model does not see: the basis' truncation
(the Phi_e rows) and the sampling's error (the Phi rows: the first sample zeroes its own
estimate of them, not the true sum). One Newton step in W turns it into a displacement
correction,

    delta = -T^-1 [W^T r_u; Psi^T r_p],     eta = ||delta_u|| / ||q||,

the indicator: the correction relative to the state (W and Phi orthonormal, so both norms
are the nodal L2 norms of the fields). T is the tangent at the state (``at_state``; the
tangent at rest overestimated a stiffening law's error 2-20x on the coarse HGO cornea of
the tests, when written) or at rest (factorised once: cheaper, for the linear range). The
W rows are a reduced residual like the model's, so ECSW integrates them too, on a second
sample trained on W, optionally without the model's own elements (independent; where few
elements carry the nonlinearity the rest may not reach the tolerance: 0.6 % on the coarse
cornea of the tests, when written). In the linear range with every element and W holding
the full order's solution, eta is the true error (tested to 1e-5). What eta cannot see:
error outside W (the basis' truncation, if the enrichment misses it). Online cost: a
residual and tangent on the second sample and a dense solve of the enriched size. The
effectivity (eta over the true error) is measured (``bench/ecsw_tradeoff.py
--indicator-modes``), not assumed. Units: mm, N, MPa.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from hapticrom.offline.reduce.ecsw import ecsw
from hapticrom.offline.reduce.ecsw_model import HyperReducedModel, MeshElements, training_matrix
from hapticrom.shared.errors import InputError


class ErrorIndicator:
    """eta(q, pi, load) of the model whose basis is the first ``n`` columns of ``basis``
    (W (N, n_W)); ``enriched``: a :class:`HyperReducedModel` on W and the model's Psi."""

    def __init__(self, enriched: HyperReducedModel, basis, n: int, at_state: bool = True,
                 fit: float = 0.0):  # fmt: skip
        if basis.shape[1] != enriched.n or not 0 < n <= enriched.n:
            raise InputError(f"the model's {n} modes must be the first of the enriched basis' "
                             f"{enriched.n} ({basis.shape[1]} given)")  # fmt: skip
        self.enriched, self.basis, self.n, self.at_state = enriched, basis, n, at_state
        self.q = np.zeros(enriched.n)  # the state in W's coordinates (the Phi_e part zero)
        self.factor = None  # the rest tangent's, factorised (at_state False)
        self.fit = fit  # the second sample's relative ECSW residual (0: every element)
        if not at_state:
            zero = np.zeros(enriched.n_p)
            rest = enriched.residual_tangent(np.zeros(enriched.n), zero, np.zeros(enriched.n))[1]
            self.factor = scipy.linalg.lu_factor(rest)

    def estimate(self, q, pi, load) -> float:
        """eta at the model's state (q, pi) under ``load``: the reduced load on W (n_W,),
        ``basis.T @ f``, N."""
        self.q[: self.n] = q
        if self.at_state:
            r, T = self.enriched.residual_tangent(self.q, pi, load)
            delta = np.linalg.solve(T, -r)
        else:
            r = self.enriched.residual(self.q, pi, load)
            delta = scipy.linalg.lu_solve(self.factor, -r)
        return float(np.linalg.norm(delta[: self.enriched.n]) / max(np.linalg.norm(q), 1e-300))


def enriched_basis(Phi, enrichment) -> np.ndarray:
    """W = [Phi, Phi_e]: ``Phi`` (orthonormal) unchanged, then an orthonormal basis of the
    part of ``enrichment``'s span orthogonal to it (by SVD: dependent or repeated columns,
    wherever they stand, lose nothing of the others); directions already in Phi's span are
    dropped."""
    E = enrichment - Phi @ (Phi.T @ enrichment)
    E -= Phi @ (Phi.T @ E)  # twice: orthogonal to Phi to round-off
    size = max(float(np.linalg.norm(enrichment, axis=0).max(initial=0.0)), 1e-300)
    U, s, _ = np.linalg.svd(E, full_matrices=False)
    return np.hstack([Phi, U[:, s > 1e-8 * size]])  # below: a column in Phi's span, round-off


def error_indicator(mesh: MeshElements, Phi, Psi, enrichment, states=None,
                    tolerance: float | None = None, exclude=(), split: bool = True, rest=None,
                    at_state: bool = True) -> ErrorIndicator:  # fmt: skip
    """The indicator of the model on ``Phi``, ``Psi``: its second sample ECSW at
    ``tolerance`` (1e-3 if None) on the enriched basis' training matrix at ``states`` (the
    model's (q, pi) pairs), none of the elements ``exclude`` (the model's own sample: an
    independent one);
    ``states`` None: every element (the indicator of the Galerkin model, or the reference
    of a sampled one). ``fit``: the second sample's relative ECSW residual (an excluded
    sample may not reach the tolerance where few elements carry the nonlinearity)."""
    if states is None and (len(exclude) or tolerance is not None):
        raise InputError("error_indicator: every element (states None) takes no exclude or "
                         "tolerance")  # fmt: skip
    if states is not None and any(len(q) != Phi.shape[1] for q, _ in states):
        raise InputError(f"error_indicator: the states must be on Phi's {Phi.shape[1]} modes")
    W = enriched_basis(Phi, enrichment)
    if states is None:
        model = HyperReducedModel(mesh, W, Psi, split=split, rest=rest)
        return ErrorIndicator(model, W, Phi.shape[1], at_state)
    padded = [(np.concatenate([q, np.zeros(W.shape[1] - len(q))]), pi) for q, pi in states]
    G = training_matrix(mesh, W, Psi, padded, split=split, rest=rest)[0]
    b = G.sum(axis=1)  # the sum over every element, the excluded ones' included
    G[:, np.asarray(exclude, dtype=np.int64)] = 0.0  # never chosen
    sampling = ecsw(G, b, tolerance=1e-3 if tolerance is None else tolerance)
    model = HyperReducedModel(mesh, W, Psi, sampling.elements, sampling.weights, split=split,
                              rest=rest)  # fmt: skip
    return ErrorIndicator(model, W, Phi.shape[1], at_state, sampling.residual)
