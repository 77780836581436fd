"""Helpers that let LLVM vectorise the compositing kernels' pixel loops (8 float32 lanes with AVX2).

Numba calls ``expf`` from the C library for ``np.exp``: one scalar call a sample, which keeps the loop that holds it
scalar (Numba's SVML path needs an SVML-patched LLVM, which llvmlite has not shipped since Numba 0.62). So:

* :func:`exp_neg` is ``exp(−s)`` written in float32 arithmetic only (Cody–Waite reduction by ln 2, a degree-6
  polynomial, the power of two built from the float's bits by :func:`_pow2_neg`), which LLVM inlines and vectorises.
  Error ≤ 1 ulp for every float32 ``s`` in ``[0, S_MAX]`` (``glibc``'s ``expf``: ≤ 0.5 ulp); float64 arguments go to
  ``np.exp`` (the float64 path is for the tests, not for speed).
* :func:`radd` is ``s + x`` compiled with the ``reassoc`` flag alone: the sums over a loop's lanes (the backward's
  per-Gaussian gradients) may then be kept as 8 partial sums. Every other operation keeps IEEE order.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import types
from numba.extending import intrinsic, overload

__all__ = ["S_MAX", "exp_neg", "radd"]

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
