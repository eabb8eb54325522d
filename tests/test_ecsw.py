"""ECSW's element selection (offline/reduce/ecsw.py) against quadrature and scipy's NNLS."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls

from hapticrom.offline.reduce.ecsw import ecsw
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial


def _legendre_rows(points: np.ndarray, degree: int) -> np.ndarray:
    """G for the integrals of the Legendre polynomials P_0 .. P_degree over [-1, 1] from
    E equal cells: G[k, e] = P_k(x_e) h (midpoint rule), so G @ 1 is the midpoint sum."""
    h = 2.0 / len(points)
    return np.polynomial.legendre.legvander(points, degree).T * h


def test_a_fine_quadrature_is_compressed_to_a_few_points_that_keep_its_integrals():
    """2,000 midpoint cells over [-1, 1], the integrals of the Legendre polynomials up to
    degree 9: at most 10 points (Caratheodory), positive weights, the same integrals to the
    tolerance; and they integrate the polynomials of the span they were trained on, not
    others (a degree-12 one, say, less well)."""
    x = np.linspace(-1, 1, 2001)[:-1] + 1.0 / 2000
    G = _legendre_rows(x, 9)
    s = ecsw(G, tolerance=1e-10)
    assert len(s.elements) <= 10 and np.all(s.weights > 0)
    assert s.residual <= 1e-10
    np.testing.assert_allclose(G[:, s.elements] @ s.weights, G.sum(axis=1), atol=1e-10 * 2)
    h = 2.0 / len(x)  # a weight multiplies a cell's contribution: 1 is the fine rule's
    assert h * s.weights.sum() == pytest.approx(2.0, rel=1e-10)  # the interval's length
    cubic = x**3 - 0.5 * x  # in the span: integrated as the fine rule does
    assert h * cubic[s.elements] @ s.weights == pytest.approx(h * cubic.sum(), abs=1e-9)
    outside = x**12  # not in the span: the few points miss its integral
    assert abs(h * outside[s.elements] @ s.weights - h * outside.sum()) > 1e-6


def test_a_looser_tolerance_keeps_fewer_elements_and_meets_it():
    rng = np.random.default_rng(7)
    G = rng.random((60, 400)) * np.linspace(0.1, 1.0, 400)  # positive contributions
    counts = []
    for tolerance in (1e-1, 1e-2, 1e-3, 1e-4):
        s = ecsw(G, tolerance=tolerance)
        assert s.residual <= tolerance
        assert np.all(s.weights > 0) and np.all(np.diff(s.elements) > 0)
        counts.append(len(s.elements))
    assert counts == sorted(counts) and counts[0] < counts[-1]


def test_run_to_the_end_it_is_the_non_negative_least_squares_optimum():
    """Tolerance 0 on a problem whose b is not reachable: scipy's NNLS (the same problem,
    another implementation) finds the same residual."""
    rng = np.random.default_rng(3)
    G = rng.standard_normal((40, 25))
    b = rng.standard_normal(40)
    s = ecsw(G, b, tolerance=0.0)
    w_ref, r_ref = nnls(G, b)
    assert s.residual * np.linalg.norm(b) == pytest.approx(r_ref, rel=1e-9)
    w = np.zeros(25)
    w[s.elements] = s.weights
    np.testing.assert_allclose(w, w_ref, atol=1e-9 * np.abs(w_ref).max())


def test_max_elements_stops_the_selection():
    rng = np.random.default_rng(5)
    G = rng.random((50, 300))
    s = ecsw(G, tolerance=1e-8, max_elements=5)
    assert len(s.elements) == 5 and s.residual > 1e-8


def test_nothing_to_reproduce_selects_nothing():
    s = ecsw(np.ones((4, 6)), np.zeros(4))
    assert len(s.elements) == 0 and s.residual == 0.0


@pytest.mark.parametrize(
    "G, b, tolerance, match",
    [
        (np.ones((3, 4)), np.ones(2), 0.1, "b must have 3"),
        (np.ones(4), None, 0.1, "2-D"),
        (np.array([[1.0, np.nan]]), None, 0.1, "finite"),
        (np.ones((3, 4)), None, -0.1, "tolerance"),
        (np.ones((3, 4)), None, 1.0, "tolerance"),
    ],
)
def test_bad_input_is_refused(G, b, tolerance, match):
    with pytest.raises(InputError, match=match):
        ecsw(G, b, tolerance)
