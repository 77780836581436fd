"""Helpers that let LLVM vectorise the compositing kernels' pixel loops (8 float32 lanes with AVX2).

Numba calls ``expf`` from the C library for ``np.exp``: one scalar call a sample, which keeps the loop that holds it
scalar (Numba's SVML path needs an SVML-patched LLVM, which llvmlite has not shipped since Numba 0.62). So:

* :func:`exp_neg` is ``exp(−s)`` written in float32 arithmetic only (Cody–Waite reduction by ln 2, a degree-6
  polynomial, the power of two built from the float's bits by :func:`_pow2_neg`), which LLVM inlines and vectorises.
  Error ≤ 1 ulp for every float32 ``s`` in ``[0, S_MAX]`` (``glibc``'s ``expf``: ≤ 0.5 ulp); float64 arguments go to
  ``np.exp`` (the float64 path is for the tests, not for speed).
* :func:`radd` is ``s + x`` compiled with the ``reassoc`` flag alone: the sums over a loop's lanes (the backward's
  per-Gaussian gradients) may then be kept as 8 partial sums. Every other operation keeps IEEE order.
* :func:`exp64` and :func:`log64` are ``exp`` and ``log`` in float64 arithmetic only, for the projection's lane
  loops (4 float64 lanes with AVX2): within 1 ulp of the C library's (which is within ~0.5 ulp of the exact value).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import types
from numba.extending import intrinsic, overload

from .._kernel_cache import install as _cache_with_imports

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

__all__ = ["S_MAX", "exp64", "exp_neg", "log64", "radd"]

S_MAX = np.float32(64.0)
"""Arguments are clamped to ``[0, S_MAX]`` by the callers (masked lanes may hold anything): exp(−64) ≈ 1.6e-28."""

_F = np.float32
_INV_LN2 = _F(1.4426950408889634)
_SHIFT = _F(12582912.0)  # 1.5·2²³: adding it rounds to an integer kept in the low mantissa bits
_LN2_HI = _F(0.693359375)  # ln 2 = HI + LO, HI with 9 significant bits so that n·HI is exact for n < 2¹⁵
_LN2_LO = _F(-2.12194440e-4)
# exp(r) ≈ 1 + r + r²·(C2 + C3 r + … + C6 r⁴) on |r| ≤ ln2/2 (least squares at Chebyshev nodes; 3.6e-9 relative)
_C2, _C3, _C4, _C5, _C6 = (_F(c) for c in (0.49999988, 0.16666518, 0.041669533, 0.008368918, 0.0013751403))
_BIAS = 0x4B400000 + 127  # the bits of _SHIFT, plus the float32 exponent bias


@intrinsic
def _pow2_neg(typingctx, z):  # noqa: ANN001, ANN202, ARG001
    """``2⁻ⁿ`` (float32) for ``z = n + 1.5·2²³`` (float32; ``0 ≤ n ≤ 126``): an integer subtraction and a shift of
    ``z``'s bits, which LLVM vectorises (Numba has no float↔int bit cast of its own)."""

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202, ARG001
        i32 = ir.IntType(32)
        e = builder.sub(ir.Constant(i32, _BIAS), builder.bitcast(args[0], i32))
        return builder.bitcast(builder.shl(e, ir.Constant(i32, 23)), ir.FloatType())

    return types.float32(types.float32), codegen


def exp_neg(s):  # noqa: ANN001, ANN201
    """``exp(−s)`` for ``0 ≤ s ≤ S_MAX``, in the argument's dtype (Numba only)."""
    raise NotImplementedError("exp_neg runs inside Numba kernels only")


@overload(exp_neg, inline="always")
def _exp_neg_impl(s):  # noqa: ANN001, ANN202
    if s == types.float32:

        def impl(s):  # noqa: ANN001, ANN202
            z = s * _INV_LN2 + _SHIFT
            n = z - _SHIFT  # round(s / ln 2)
            r = (n * _LN2_HI - s) + n * _LN2_LO  # −s + n ln 2, |r| ≤ ln2/2 (+ rounding)
            q = _C6 * r + _C5
            q = q * r + _C4
            q = q * r + _C3
            q = q * r + _C2
            p = (r * r) * q + r
            return (p + _F(1.0)) * _pow2_neg(z)  # type: ignore[call-arg]  # (typingctx: Numba passes it)

        return impl

    def impl64(s):  # noqa: ANN001, ANN202
        return np.exp(-s)

    return impl64


@nb.njit(cache=True, nogil=True, fastmath={"reassoc"}, error_model="numpy")
def radd(s, x):  # noqa: ANN001, ANN201
    """``s + x``, reassociable (see the module docstring)."""
    return s + x


@intrinsic
def _bits(typingctx, x):  # noqa: ANN001, ANN202, ARG001
    """The IEEE bits of a float64, as an int64."""

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202, ARG001
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _from_bits(typingctx, i):  # noqa: ANN001, ANN202, ARG001
    """The float64 whose IEEE bits are the int64 ``i``."""

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202, ARG001
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


_SHIFT64 = 6755399441055744.0  # 1.5·2⁵²: adding it rounds to an integer kept in the low mantissa bits
_SHIFT64_BITS = 0x4338000000000000
_LN2_HI64 = 6.93147180369123816490e-01  # fdlibm's split of ln 2: n·HI exact for |n| < 2¹¹
_LN2_LO64 = 1.90821492927058770002e-10
_EXP_MIN, _EXP_MAX = -708.0, 709.0  # the normal range of exp's results (exp64 clamps its argument to it)
_T = tuple(1.0 / math.factorial(k) for k in range(14))  # Taylor to degree 13 on |r| ≤ ln2/2: 4e-18 relative
_LG = (6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01, 2.222219843214978396e-01,
       1.818357216161805012e-01, 1.531383769920937332e-01, 1.479819860511658591e-01)  # fdlibm's log  # fmt: skip


@nb.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def exp64(x):  # noqa: ANN001, ANN201
    """``exp(x)`` (float64), the argument clamped to [−708, 709] (no subnormal or infinite results; NaN stays
    NaN): Cody–Waite reduction by ln 2, Taylor to degree 13, 2ⁿ from the bits in two halves (n may be −1022)."""
    x = min(max(x, _EXP_MIN), _EXP_MAX)
    z = x * 1.4426950408889634 + _SHIFT64
    n = z - _SHIFT64  # round(x / ln 2)
    r = (x - n * _LN2_HI64) - n * _LN2_LO64
    p = _T[13] * r + _T[12]
    p = p * r + _T[11]
    p = p * r + _T[10]
    p = p * r + _T[9]
    p = p * r + _T[8]
    p = p * r + _T[7]
    p = p * r + _T[6]
    p = p * r + _T[5]
    p = p * r + _T[4]
    p = p * r + _T[3]
    p = p * r + _T[2]
    p = (p * r) * r + r
    k = _bits(z) - _SHIFT64_BITS  # type: ignore[call-arg]  # n as an integer
    h = k >> 1
    return ((p + 1.0) * _from_bits((h + 1023) << 52)) * _from_bits((k - h + 1023) << 52)


@nb.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def log64(x):  # noqa: ANN001, ANN201
    """``log(x)`` (float64) for ``x > 0`` (subnormals included; other arguments: unspecified): fdlibm's
    ``__ieee754_log`` without its branches — ``x = 2ᵏ(1 + f)``, ``1 + f`` in [√2/2, √2), a degree-14 polynomial in
    ``s = f / (2 + f)``."""
    tiny = x < 2.2250738585072014e-308
    x = x * 18014398509481984.0 if tiny else x  # 2⁵⁴: normal
    bits: int = _bits(x)  # type: ignore[call-arg]
    hx = bits >> 32
    i = ((hx & 0x000FFFFF) + 0x95F64) & 0x100000  # 1 + f ≥ √2: halve it
    k = (hx >> 20) - (1077 if tiny else 1023) + (i >> 20)
    f = _from_bits((((hx & 0x000FFFFF) | (i ^ 0x3FF00000)) << 32) | (bits & 0xFFFFFFFF)) - 1.0
    dk = _from_bits(k + _SHIFT64_BITS) - _SHIFT64  # k as a float, no conversion
    hfsq = 0.5 * f * f
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    r = z * (_LG[0] + w * (_LG[2] + w * (_LG[4] + w * _LG[6]))) + w * (_LG[1] + w * (_LG[3] + w * _LG[5]))
    return dk * _LN2_HI64 - ((hfsq - (s * (hfsq + r) + dk * _LN2_LO64)) - f)
