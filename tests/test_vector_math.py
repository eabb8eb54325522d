"""The vector-lane exp, expm1 and log (:mod:`hapticrom.online.vector_math`) against the C
library's (Python's ``math``): within 1 ulp (expm1 2) over the whole range of doubles and
densely where the laws use them, special values as the library gives them. Compiled as
the element kernel inlines them (the sums' reassociating flags) and without flags."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from hapticrom.online.hyperreduced import _SUMS
from hapticrom.online.vector_math import vexp, vexpm1, vlog

RNG = np.random.default_rng(20261126)
SPECIAL = [0.0, -0.0, math.inf, -math.inf, math.nan, 5e-324, -5e-324, 1e-310, 1.0, -1.0]


def compiled(function, flags):
    @njit(fastmath=flags, error_model="numpy")
    def loop(x, out):
        for i in range(x.shape[0]):
            out[i] = function(x[i])

    return loop


def library(function, x: float) -> float:
    """math's value, with C's answers where Python raises instead (log of 0 or less,
    overflow)."""
    try:
        return function(x)
    except ValueError:
        return -math.inf if x == 0 else math.nan
    except OverflowError:
        return math.inf


def exp_arguments() -> np.ndarray:
    edges = [709.78, 709.7827, 709.79, -708.39, -708.4, -744.4, -745.1, -745.2, -40.0, -39.9,
             -745.1332191019411, -744.79]  # fmt: skip
    halves = [k * math.log(2) / 2 for k in range(-5, 6)]  # the reduction's boundaries
    return np.concatenate([RNG.uniform(-746, 710, 100_000), RNG.uniform(-3, 3, 100_000),
                           RNG.uniform(-1e-6, 1e-6, 5_000), np.nextafter(halves, math.inf),
                           np.nextafter(halves, -math.inf), edges, SPECIAL])  # fmt: skip


def log_arguments() -> np.ndarray:
    near_one = 1 + RNG.uniform(-1e-3, 1e-3, 20_000)
    edges = [math.sqrt(2), np.nextafter(math.sqrt(2), 3), 0.5, 2.0, 2.2250738585072014e-308,
             np.nextafter(2.2250738585072014e-308, 0), 1.7976931348623157e308]  # fmt: skip
    return np.concatenate([10 ** RNG.uniform(-323, 308, 100_000), RNG.uniform(0.3, 3, 100_000),
                           near_one, -RNG.uniform(0, 10, 100), edges, SPECIAL])  # fmt: skip


@pytest.mark.parametrize("flags", [_SUMS, set()], ids=["sums' flags", "no flags"])
@pytest.mark.parametrize(
    "function, reference, arguments, ulps",
    [
        (vexp, math.exp, exp_arguments, 1),
        (vexpm1, math.expm1, exp_arguments, 2),
        (vlog, math.log, log_arguments, 1),
    ],  # fmt: skip
    ids=["exp", "expm1", "log"],
)
def test_within_an_ulp_or_two_of_the_c_library(function, reference, arguments, ulps, flags):
    x = arguments()
    got = np.empty_like(x)
    compiled(function, flags)(x, got)
    expected = np.array([library(reference, v) for v in x])
    special = ~np.isfinite(expected) | (expected == 0)
    assert np.array_equal(got[special], expected[special], equal_nan=True)
    zero = expected == 0
    assert np.array_equal(np.signbit(got[zero]), np.signbit(expected[zero]))  # -0 as libm
    tiny = np.abs(expected) < 2.2250738585072014e-308  # subnormal results: their own ulp
    spacing = np.array([math.ulp(v) for v in expected[~special]])
    error = np.abs(got[~special] - expected[~special]) / spacing
    assert error.max() <= ulps, x[~special][np.argmax(error)]
    assert not tiny[~special].any() or error[tiny[~special]].max() <= ulps
