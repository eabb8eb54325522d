"""exp, expm1 and log that a compiled loop can run in vector lanes: no call, no branch.

numba lowers ``math.exp`` and ``math.log`` to libm calls, and a loop with a call in it runs
one value at a time (numba has no vector library without Intel's SVML). These are written
from the operations a vector unit has (multiply-add, rounding, the bits of a double), so a
loop over independent values that calls them vectorises: 2.3-3.0 ns a value against libm's
7.3-7.7 (stop 50, a loop over 3,312 values on the AMD EPYC test machine). They are within 1
ulp of libm (expm1 within 2), special values (0, inf, NaN, subnormals) as libm gives them:
tests/test_vector_math.py.

The reductions use ``llvm.fma`` and ``llvm.rint`` directly: an inlined function takes its
caller's fast-math flags, and a caller that allows reassociation (the element kernel's
sums) could otherwise fold ``(x - n ln2_hi) - n ln2_lo`` into ``x - n ln2``, losing the
split's extra bits. LLVM does not reorder an fma's one rounding. Safe under the flags
"reassoc" and "contract" (the sums'), not under ``fastmath=True``: its "nnan" and "ninf"
would fold away the tests for NaN and infinity, and "nsz" with "reassoc" could regroup
the two scale factors into one that overflows.
"""

from __future__ import annotations

import math
from decimal import Decimal, localcontext

from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic


@intrinsic
def _bits(typingctx, x):
    """The 64 bits of a float64, as an int64."""
    if x != types.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _double(typingctx, bits):
    """The float64 whose 64 bits are ``bits`` (an int64)."""
    if bits != types.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


def _call_llvm(builder, name: str, args):
    """A call of LLVM's float64 intrinsic ``name`` on ``args``."""
    d = ir.DoubleType()
    fn = builder.module.declare_intrinsic(name, [d], ir.FunctionType(d, [d] * len(args)))
    return builder.call(fn, args)


@intrinsic
def _fma(typingctx, a, b, c):
    """a b + c, rounded once."""
    if not a == b == c == types.float64:
        return None
    return types.float64(a, b, c), lambda context, builder, sig, args: _call_llvm(
        builder, "llvm.fma", args
    )


@intrinsic
def _rint(typingctx, a):
    """The integer nearest a (ties to even), as a float64."""
    if a != types.float64:
        return None
    return types.float64(a), lambda context, builder, sig, args: _call_llvm(
        builder, "llvm.rint", args
    )


def _ln2_split() -> tuple[float, float]:
    """ln 2 = LN2_HI + LN2_LO to about 2^-85, LN2_HI with 29 significant bits: n LN2_HI is
    exact for every |n| < 2^24 (here |n| <= 1,074)."""
    with localcontext() as context:
        context.prec = 50
        ln2 = Decimal(2).ln()
        high = float.fromhex(float(ln2).hex()[:11] + "p-1")  # '0x1.' and 7 hex digits
        return high, float(ln2 - Decimal(high))


LN2_HI, LN2_LO = _ln2_split()
LOG2E = 1 / math.log(2)
SQRT2 = math.sqrt(2)
MAGIC = 6755399441055744.0  # 1.5 2^52: n + MAGIC holds an integer n (|n| < 2^51) in its bits
MAGIC_BITS = 0x4338000000000000  # ... as MAGIC's bits plus n
EXP_OVERFLOW = 709.782712893384  # exp(x) > the largest double beyond
EXP_UNDERFLOW = -745.2  # exp(x) < half the smallest subnormal below
EXPM1_MINUS_ONE = -40.0  # expm1(x) rounds to -1 below (e^-40 < 2^-57)
MIN_NORMAL = 2.2250738585072014e-308
TWO_54 = 18014398509481984.0
# Taylor's 1/k! from k = 13 down to 2: exp(r) - 1 for |r| <= ln2 / 2 (r^14 / 14! < 2^-56 r)
_EXPM1_TERMS = tuple(1.0 / math.factorial(k) for k in range(13, 1, -1))
# 2 / k, k = 21, 19, ..., 3: log(1 + f) = 2 atanh(s) = 2 s + s (2 s^2/3 + 2 s^4/5 + ...),
# s = f / (2 + f), |s| <= 0.172 (s^20 / 21 < 2^-54 of the sum)
_ATANH_TERMS = tuple(2.0 / k for k in range(21, 1, -2))


@njit(inline="always")
def _pow2(n):
    """2^n for an integer-valued float64 n in [-1022, 1023] (its exponent field)."""
    return _double((_bits(n + MAGIC) - MAGIC_BITS + 1023) << 52)


@njit(inline="always")
def _scale(y, n):
    """y 2^n for an integer-valued n in [-1075, 1024], as two factors within the normal
    range (2^n alone would overflow at 1024 and be subnormal below -1022)."""
    half = _rint(0.5 * n)
    return y * _pow2(half) * _pow2(n - half)


@njit(inline="always")
def _reduce(x):
    """(n, r): x = n ln2 + r, |r| <= ln2 / 2 for x in [-745.2, 709.8] (n clamped to
    [-1075, 1024] beyond, where the callers' own limits answer)."""
    n = min(max(_rint(x * LOG2E), -1075.0), 1024.0)
    return n, _fma(-n, LN2_LO, _fma(-n, LN2_HI, x))


@njit(inline="always")
def _expm1_reduced(r):
    """exp(r) - 1 for |r| <= ln2 / 2: r + r^2 (1/2 + r/6 + ...) (Horner to r^13)."""
    p = _EXPM1_TERMS[0]
    for c in _EXPM1_TERMS[1:]:
        p = _fma(p, r, c)
    return _fma(r * r, p, r)


@njit(inline="always")
def vexp(x):
    """exp(x) within 1 ulp, inf beyond the largest double, 0 below the smallest."""
    n, r = _reduce(x)
    y = _scale(_expm1_reduced(r) + 1.0, n)
    y = math.inf if x > EXP_OVERFLOW else y
    y = 0.0 if x < EXP_UNDERFLOW else y
    return x if x != x else y


@njit(inline="always")
def vexpm1(x):
    """exp(x) - 1 within 2 ulp, exact near 0 (where exp(x) - 1 would cancel)."""
    n, r = _reduce(x)
    em = _expm1_reduced(r)
    near = min(max(n, -53.0), 53.0)  # 2^n - 1 is exact here
    s = _pow2(near)
    y = _fma(s, em, s - 1.0) if n == near else _scale(em + 1.0, n) - 1.0
    y = math.inf if x > EXP_OVERFLOW else y
    y = -1.0 if x < EXPM1_MINUS_ONE else y
    return x if (x != x or x == 0.0) else y  # NaN, and -0 keeps its sign


@njit(inline="always")
def _log1p_reduced(f):
    """log(1 + f) for 1 + f in [sqrt(1/2), sqrt(2)]: f - f^2/2 + s (f^2/2 + R), the
    series' rest R = s^2 (2/3 + 2 s^2/5 + ...), with the rounding in the small terms."""
    s = f / (2.0 + f)
    z = s * s
    R = _ATANH_TERMS[0]
    for c in _ATANH_TERMS[1:]:
        R = _fma(R, z, c)
    half_f2 = 0.5 * f * f
    return f - _fma(-s, _fma(R, z, half_f2), half_f2)


@njit(inline="always")
def vlog(x):
    """log(x) within 1 ulp: -inf at 0, NaN below, inf and NaN as given."""
    tiny = x < MIN_NORMAL  # a subnormal's bits have no exponent: scaled by 2^54 first
    bits = _bits(x * TWO_54 if tiny else x)
    e = ((bits >> 52) & 0x7FF) - 1023 - (54 if tiny else 0)
    m = _double((bits & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000)  # x = m 2^e, m in [1, 2)
    up = m > SQRT2
    m = 0.5 * m if up else m
    k = float(e + (1 if up else 0))
    v = _fma(k, LN2_HI, _fma(k, LN2_LO, _log1p_reduced(m - 1.0)))
    v = -math.inf if x == 0.0 else v
    v = math.nan if x < 0.0 else v
    return x if (x == math.inf or x != x) else v
