"""The POD-ANM steps' tabulated series against the series themselves.

A step interpolates each section's force and path parameter a in depth (cubic Hermite on
uniform knots, as many as `kernels.tabulate_series` finds it needs) instead of solving
depth(a) = depth by Newton. The reference here is the series evaluated at the roots numpy
finds (eigenvalues of the companion matrix), on series of degree 6 with every coefficient
non-zero, so that the interpolant is not exact (the test model's series are nearly cubic
in a).
"""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.online import kernels as k

pytestmark = pytest.mark.serial
P = np.polynomial.polynomial
RNG = np.random.default_rng(23)


def _series(sections: int):
    """A sample's sections: depth(a) increasing on [0, a_max], force(a) stiffening, each
    section starting where the last ended (as ANM continuation does), degree 6."""
    depth, force, a_max = [], [], []
    d0 = f0 = 0.0
    for _ in range(sections):
        c = np.r_[d0, 0.4, RNG.uniform(-0.05, 0.05, 5) * 0.4 ** -np.arange(1, 6) * 0.1]
        f = np.r_[f0, 0.02, RNG.uniform(0.0, 0.02, 5) * 0.4 ** -np.arange(1, 6) * 0.1]
        depth.append(c), force.append(f), a_max.append(0.4)
        d0, f0 = P.polyval(0.4, c), P.polyval(0.4, f)
    return np.array(depth), np.array(force), np.array(a_max)


@pytest.fixture(scope="module")
def samples():
    """Three samples of 3, 2 and 4 sections: series, records and offsets."""
    parts = [_series(n) for n in (3, 2, 4)]
    depth, force, a_max = (np.concatenate([p[i] for p in parts]) for i in range(3))
    assert (P.polyval(np.linspace(0, 0.4, 200)[:, None], P.polyder(depth.T)) > 0).all()
    records, _, _ = k.tabulate_series(depth, force, a_max)
    offsets = np.r_[0, np.cumsum([3, 2, 4])].astype(np.int64)
    return depth, force, a_max, records, offsets


def _knots(records) -> int:
    return (records.shape[1] - k.REC_FORCE) // 4


def _buffer(samples, weights=(0.5, 0.3, 0.2), order=(0, 1, 2)):
    _, _, _, records, offsets = samples
    smax, q = int(np.diff(offsets).max()), _knots(records)
    buf = np.zeros(k.buffer_size(2, 7, smax, q))
    buf[k.ANM_BASE], buf[k.ANM_N1], buf[k.ANM_SMAX] = k.CURVE + 4, 7, smax
    buf[k.SECTION_KNOTS] = q
    for j in range(3):
        buf[k.CURVE + 4 + j * k.anm_block_size(q, smax) + k.BLOCK_SAMPLE] = -1.0
    _load(buf, samples, weights, order)
    return buf


def _load(buf, samples, weights, order):
    _, _, _, records, offsets = samples
    k.load_sections(np.array(weights, float), np.array(order, float), offsets, records.ravel(),
                    buf)  # fmt: skip


def _exact(samples, i: int, depth: float):
    """(force, dF/ddepth, section, a) of sample i's series at ``depth`` (numpy roots)."""
    dc, fc, a_max, _, offsets = samples
    rows = range(offsets[i], offsets[i + 1])
    for s in range(len(rows)):
        z = rows[s]
        end = P.polyval(a_max[z], dc[z])
        if depth <= end or z == rows[-1]:
            break
    if depth > end:  # beyond the last section: linear along the end slope
        slope = P.polyval(a_max[z], P.polyder(fc[z])) / P.polyval(a_max[z], P.polyder(dc[z]))
        return P.polyval(a_max[z], fc[z]) + slope * (depth - end), slope, s, a_max[z]
    c = dc[z].copy()
    c[0] -= depth
    roots = P.polyroots(c)
    real = roots[np.abs(roots.imag) <= 1e-9].real
    a = real[(real >= -1e-9) & (real <= a_max[z] * (1 + 1e-9))].min()
    slope = P.polyval(a, P.polyder(fc[z])) / P.polyval(a, P.polyder(dc[z]))
    return P.polyval(a, fc[z]), slope, s, a


def test_the_knots_are_chosen_for_the_tolerance(samples):
    """More knots for rougher series: these (degree 6, every term as large as the linear
    one at a_max) need more than 65, a cubic 17, and the midpoint errors tabulate_series
    reports are within the tolerance."""
    dc, fc, a_max, records, _ = samples
    q = _knots(records)
    assert q > 65
    force_error, a_error = k.tabulation_error(dc, fc, a_max, records)
    assert force_error <= k.TABULATION_TOLERANCE * np.abs(records[:, k.REC_FORCE]).max() + 1e-300
    assert a_error <= k.TABULATION_TOLERANCE * a_max.max()
    linear = np.r_[0.0, 1.0, 0, 0, 0, 0, 0]  # depth = a
    cubic = np.r_[0.0, 0.02, 0.01, 0.003, 0, 0, 0]  # force: a cubic in depth, interpolated exactly
    records, q_cubic, errors = k.tabulate_series([linear], [cubic], [0.4])
    assert q_cubic == 17
    assert errors[0] <= 1e-16 and errors[1] <= 1e-16


def test_the_step_force_and_slope_follow_the_series(samples):
    """Between knots the force is within 1e-11 of the largest force (the interpolant's
    h^4 error, bounded by TABULATION_TOLERANCE at the midpoints), its slope within 1e-7
    of the largest slope (the interpolant's derivative, h^3)."""
    buf = _buffer(samples)
    weights = (0.5, 0.3, 0.2)
    end = min(P.polyval(samples[2][o - 1], samples[0][o - 1]) for o in samples[4][1:])
    depths = RNG.uniform(0.0, 1.3 * end, 400)
    exact = np.array([[_exact(samples, i, d)[:2] for i in range(3)] for d in depths])
    force = exact[:, :, 0] @ weights
    slope = exact[:, :, 1] @ weights
    got = np.array([(k.anm_force(buf, d), buf[k.ANM_SLOPE]) for d in depths])
    assert np.abs(got[:, 0] - force).max() <= 2 * k.TABULATION_TOLERANCE * np.abs(force).max()
    assert np.abs(got[:, 1] - slope).max() <= 1e-7 * np.abs(slope).max()
    assert np.abs(got[:, 0] - force).max() > 0  # an interpolant, not the series: not exact


def test_the_table_is_the_series_at_its_knots(samples):
    """At the knots: a solves depth(a) = knot to the root finder's 1e-14 (1 + depth), and
    the force is the series' at that a."""
    dc, fc, a_max, records, _ = samples
    q = _knots(records)
    for z in range(len(a_max)):
        r = records[z]
        knots = r[k.REC_DEPTH0] + r[k.REC_SPACING] * np.arange(q)
        a = r[k.REC_FORCE + 2 * q : k.REC_FORCE + 3 * q]
        np.testing.assert_allclose(P.polyval(a, dc[z]), knots, rtol=0, atol=2e-14)
        np.testing.assert_allclose(r[k.REC_FORCE : k.REC_FORCE + q], P.polyval(a, fc[z]),
                                   rtol=1e-14, atol=0)  # fmt: skip
        assert r[k.REC_DEPTH_END] == pytest.approx(P.polyval(a_max[z], dc[z]), rel=1e-15)


def test_the_surface_reads_each_neighbours_section_and_a(samples):
    """`anm_section` (what the surface field evaluates the series at) against the roots;
    beyond the last section, how far a goes on along the exact end slope 1 / depth'(a_max)."""
    dc, _, a_max, _, offsets = samples
    buf = _buffer(samples)
    base, _, _, block = k.anm_layout(buf)
    for d in RNG.uniform(0.0, 1.2 * samples[3][-1, k.REC_DEPTH_END], 200):
        for j in range(3):
            s, a, beyond = k.anm_section(buf, base + j * block, d)
            _, _, s_exact, a_exact = _exact(samples, j, d)
            assert s == s_exact
            assert a == pytest.approx(a_exact, abs=1e-11)
            z = offsets[j + 1] - 1  # the last section
            end = P.polyval(a_max[z], dc[z])
            rate = 1.0 / P.polyval(a_max[z], P.polyder(dc[z]))
            assert beyond == pytest.approx(max(d - end, 0.0) * rate, rel=1e-9, abs=1e-15)


def test_a_moved_contact_copies_only_the_records_it_lacks(samples):
    """Blocks that keep their sample keep their records; the result is bit for bit that
    of a fresh buffer loaded with the new neighbours."""
    buf = _buffer(samples)
    for weights, order in (((0.2, 0.2, 0.6), (0, 1, 2)), ((0.1, 0.6, 0.3), (2, 1, 0)),
                           ((1.0, 0.0, 0.0), (1, 1, 2))):  # fmt: skip
        _load(buf, samples, weights, order)
        fresh = _buffer(samples, weights, order)
        for d in RNG.uniform(0.0, 1.0, 20):
            assert k.anm_force(buf, d) == k.anm_force(fresh, d)
            assert buf[k.ANM_SLOPE] == fresh[k.ANM_SLOPE]


def test_rough_series_cannot_make_the_tables_huge(samples):
    """A crafted artifact's series may never meet the tolerance: the knots stop at the
    budget, and the error reached is reported."""
    dc, fc, a_max, _, _ = samples
    budget = len(a_max) * k.record_stride(65)
    records, q, errors = k.tabulate_series(dc, fc, a_max, budget=budget)
    assert q == 65 and records.size <= budget
    assert errors[0] > k.TABULATION_TOLERANCE * np.abs(records[:, k.REC_FORCE]).max()
    records, q, _ = k.tabulate_series(dc, fc, a_max, budget=1)
    assert q == 17  # the fewest, whatever the budget


def test_a_depth_before_a_crafted_short_section_reads_its_start():
    """A section 1e-12 mm long after a 1e-6 mm gap (a crafted file): its knot spacing's
    inverse is 6e13, and a depth in the gap must not extrapolate its cubic 6e7 intervals."""
    first = np.r_[0.0, 1.0, 0, 0]  # depth = a on [0, 0.2]
    second = np.r_[0.2 + 1e-6, 1e-12 / 0.2, 0, 0]
    force = np.array([[0.0, 0.05, 0.01, 0], [0.0104, 0.05, 0, 0]])
    records, q, _ = k.tabulate_series(np.array([first, second]), force, [0.2, 0.2])
    samples = (None, None, None, records, np.array([0, 2, 2, 2], dtype=np.int64))
    buf = _buffer(samples, weights=(1.0, 0.0, 0.0), order=(0, 0, 0))
    got = k.anm_force(buf, 0.2 + 5e-7)  # past the first section's end, before the second's
    assert got == records[1, k.REC_FORCE]  # the second section's start
    assert np.isfinite(buf[k.ANM_SLOPE])


def test_a_section_with_no_depth_range_is_refused():
    """1e-200 mm on 0.2 mm rounds to no range at all: refused, naming the section."""
    flat = np.r_[0.2, 1e-200, 0, 0]
    with pytest.raises(ValueError, match="section 1 .*no depth range"):
        k.tabulate_series([np.r_[0.0, 1.0, 0, 0], flat], [[0, 0.05, 0, 0]] * 2, [0.2, 0.2])
