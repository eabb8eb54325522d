"""Register tiles (:mod:`hapticrom.online.vector_tiles`) and the tangent's q-q projection
(hyperreduced's ``_add_projected_stiffness``), against numpy in both precisions: in tiles
and, where the modes are not a whole number of a tile's lanes, in the loops; for element
rows that fill whole tiles (the hexahedron's 24) and that do not (the quadratic
tetrahedron's 30)."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from test_hyperreduced import (
    MODES,
    PRESSURE_MODES,
    RELATIVE,
    element_tangents,
    make_problem,
    readonly,
    sample,
)

from hapticrom.online.haptic_newton import projection_rows
from hapticrom.online.hyperreduced import (
    _SUMS,
    Scratch,
    _add_projected_stiffness,
    _tiled_projection,
    sampled_residual_tangent,
)
from hapticrom.online.vector_tiles import (
    TILE_ROWS,
    tile,
    tile_add,
    tile_fma,
    tile_lanes,
    tile_store,
    tile_zero,
)
from hapticrom.shared.errors import InputError

RNG = np.random.default_rng(20261207)
TOLERANCE = {np.float64: 1e-13, np.float32: 1e-5}  # of the largest entry: a sum of m terms


@njit
def tile_product(A, B, C, add):
    """C[i:i+4, j:j+lanes] (+)= A[:, i:i+4]^T B[:, j:j+lanes] for every tile of C."""
    lanes = tile_lanes(B)
    acc = tile(B)
    for i in range(0, C.shape[0], TILE_ROWS):
        for j in range(0, C.shape[1], lanes):
            tile_zero(acc)
            for c in range(A.shape[0]):
                tile_fma(acc, B, c, j, A[c, i], A[c, i + 1], A[c, i + 2], A[c, i + 3])
            if add:
                tile_add(acc, C, i, j)
            else:
                tile_store(acc, C, i, j)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tiles_multiply_add_store_and_add_as_numpy(dtype):
    lanes = 64 // np.dtype(dtype).itemsize
    A = RNG.standard_normal((7, 8)).astype(dtype)
    B = RNG.standard_normal((7, 2 * lanes)).astype(dtype)
    C = np.full((8, 2 * lanes), np.nan, dtype)
    tile_product(A, B, C, False)  # stored: the NaNs gone
    expected = A.astype(np.float64).T @ B.astype(np.float64)
    assert np.abs(C - expected).max() <= TOLERANCE[dtype] * np.abs(expected).max()
    before = RNG.standard_normal(C.shape).astype(dtype)
    C[:] = before
    tile_product(A, B, C, True)
    assert np.abs(C - (before + expected)).max() <= TOLERANCE[dtype] * np.abs(expected).max()
    assert tile_lanes(B) == lanes


@njit(fastmath=_SUMS)
def project(PhiQ, weights, K_uu, Kw, TQ, Kqq):
    Kqq[:, :] = 0.0
    for s in range(PhiQ.shape[0]):
        _add_projected_stiffness(PhiQ, s, weights[s], K_uu[s], Kw, TQ, Kqq)


@njit(fastmath=_SUMS)
def tiled(P, Kw, TQ, Kqq):
    _tiled_projection(P, Kw, TQ, Kqq)


def element_problem(S, m, n):
    Phi = 0.1 * RNG.standard_normal((S, m, n))
    K = RNG.standard_normal((S, m, m))
    return Phi, K + K.transpose(0, 2, 1), RNG.uniform(0.5, 2.0, S)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("m", [24, 30])  # whole tiles of rows; two rows past them
@pytest.mark.parametrize("n", [16, 21, 72])
def test_the_projection_is_phi_t_k_phi_in_tiles_or_loops(dtype, m, n):
    """Kqq's upper triangle (n x n) = sum_s w_s Phi_s^T K_s Phi_s, the rows rounded to
    dtype: in tiles where the columns are a whole number of lanes (padded ones as
    projection_rows pads them, or n itself), in the loops otherwise."""
    Phi, K, w = element_problem(3, m, n)
    rounded = Phi.astype(dtype).astype(np.float64)
    expected = np.einsum("sai,sab,sbj->ij", rounded, K * w[:, None, None], rounded)
    lanes = 64 // np.dtype(dtype).itemsize
    padded = projection_rows(Phi, np.float32) if dtype == np.float32 else Phi
    for PhiQ in (Phi.astype(dtype), padded):
        N = PhiQ.shape[2]
        Kqq = np.full((N, N), np.nan, dtype)
        TQ = np.empty((m, N), dtype)
        project(PhiQ, w, K, np.empty((m, m), dtype), TQ, Kqq)
        upper = np.triu_indices(n)
        error = np.abs(Kqq[:n, :n][upper] - expected[upper]).max()
        assert error <= TOLERANCE[dtype] * np.abs(expected).max(), (N, N % lanes)
        last = w[-1] * K[-1] @ rounded[-1]  # TQ holds the last element's K Phi
        assert np.abs(TQ[:, :n] - last).max() <= TOLERANCE[dtype] * np.abs(last).max()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("m", [24, 30])
def test_tiled_projection_entry_by_entry(dtype, m):
    """One element, columns a whole number of lanes: _tiled_projection's TQ and every entry
    of Kqq's upper block triangle (the diagonal blocks whole) against numpy; the entries
    below the diagonal blocks untouched (NaN before, NaN after)."""
    lanes = 64 // np.dtype(dtype).itemsize
    n = 3 * lanes
    Phi, K, w = element_problem(1, m, n)
    P = np.ascontiguousarray(Phi[0], dtype)
    Kw = (w[0] * K[0]).astype(dtype)
    TQ, Kqq = np.full((m, n), np.nan, dtype), np.full((n, n), np.nan, dtype)
    for i in range(n):
        Kqq[i, (i // lanes) * lanes :] = 0.0
    tiled(P, Kw, TQ, Kqq)
    TQ64, P64 = Kw.astype(np.float64) @ P.astype(np.float64), P.astype(np.float64)
    assert np.abs(TQ - TQ64).max() <= TOLERANCE[dtype] * np.abs(TQ64).max()
    expected = P64.T @ TQ64
    bound = TOLERANCE[dtype] * np.abs(expected).max()
    for i in range(n):
        j = (i // lanes) * lanes
        assert np.abs(Kqq[i, j:] - expected[i, j:]).max() <= bound
        assert np.isnan(Kqq[i, :j]).all()


@pytest.mark.parametrize("modes", [8, 16])
def test_the_whole_tangent_in_double_takes_the_tiles(modes):
    """sampled_residual_tangent (float64, its own buffers as the projection's): with the
    modes a multiple of 8 its q-q block is summed in tiles; it is the numpy assembly's
    sum_e w_e Phi_e^T K_uu,e Phi_e (the element kernel called from Python)."""
    problem = make_problem("hex-hgo")  # this module's RNG is reseeded after it (conftest)
    Phi = np.hstack([problem.Phi, 0.03 * RNG.standard_normal((len(problem.Phi), modes - MODES))])
    elements = RNG.permutation(problem.elements)[: problem.elements - 1]
    weights = RNG.uniform(0.5, 2.0, len(elements))
    base = sample(problem, elements, weights)
    inputs = (*base[:2], readonly(Phi[problem.rows[elements]]), *base[3:])
    q, pi = readonly(RNG.standard_normal(modes)), readonly(0.05 * RNG.standard_normal(3))
    size = modes + PRESSURE_MODES
    r, K = np.full(size, np.nan), np.full((size, size), np.nan)
    sampled_residual_tangent(*inputs, q, pi, r, K, *Scratch(problem.nodes, modes).buffers())
    expected = np.zeros((modes, modes))
    for e, w in zip(elements, weights, strict=True):
        Phi_e = Phi[problem.rows[e]]
        u, p = Phi_e @ q, problem.Psi[e] @ pi
        K_uu = element_tangents(problem.X[e], u.reshape(-1, 3), p, problem.params[e],
                                problem.reference)[1]  # fmt: skip
        expected += w * Phi_e.T @ K_uu @ Phi_e
    assert np.abs(K[:modes, :modes] - expected).max() <= RELATIVE * np.abs(expected).max()


def test_projection_rows():
    """float64: Phi itself; float32: rounded, padded with zeros to 16 columns' multiples,
    read only; an overflow refused."""
    Phi = RNG.standard_normal((2, 24, 21))
    assert projection_rows(Phi, np.float64) is Phi
    rows = projection_rows(Phi, np.float32)
    assert rows.dtype == np.float32 and rows.shape == (2, 24, 32) and not rows.flags.writeable
    assert np.array_equal(rows[:, :, :21], Phi.astype(np.float32)) and (rows[:, :, 21:] == 0).all()
    assert projection_rows(Phi[:, :, :16], np.float32).shape == (2, 24, 16)
    with pytest.raises(InputError, match="overflows"):
        projection_rows(np.full((1, 3, 2), 1e39), np.float32)
