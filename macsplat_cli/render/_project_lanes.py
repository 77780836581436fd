"""The fused projection's per-Gaussian arithmetic as lane loops: LLVM vectorises them (4 float64 lanes with AVX2).

``_project_kernels`` copies a block of Gaussians' parameters into the rows of a small float64 array ``P`` (a row a
parameter, a column a Gaussian), runs :func:`forward_lanes` or :func:`backward_lanes` over its columns, and copies the
rows of ``Q`` back out. Rows of one array, indexed by the loop counter alone (unsigned, so that Numba emits no
wrap-around of negative indices), are what LLVM can vectorise: the Gaussians' own arrays, read with a stride of 3
or 4, are not (their bounds need more run-time assumptions than LLVM makes). In the loops: no branch (a cull is a
mask, a guard a select), no call left after inlining (``exp``, ``log``: ``_lanes.exp64``, ``log64``), every
temporary a scalar, no load from an array argument (the camera and ``lim`` come in as tuples), and the numpy error
model in every caller (Python's adds a zero-division exit to each division, which stops the vectoriser). The two
loops are inlined by Numba into ``_project_kernels``' drivers, the small helpers by LLVM (Numba's own inlining
copies a helper's IR per call: seconds of compilation). Numba's cache does not notice an edit here (the drivers'
cache entries are keyed on their own file): clear ``render/__pycache__`` after one.

The arithmetic is that of the plain-PyTorch twin in ``projection.py``, term for term and in the order of the scalar
kernels these replaced (the results were bit-identical to theirs but for ``exp64``/``log64``'s ≤ 1 ulp, float64).

``P`` rows (both): mean (0–2), log-scales (3–5), quaternion (6–9), opacity logit (10), then the forward's depth in
the inputs' dtype (11), or the backward's cotangents of the mean 2D, conic, opacity and depth (11–17); the first SH
coefficient (18–20); the backward's cotangent of the colour (21–23). ``Q`` rows, forward: mean 2D (0, 1), conic
(2–4), opacity (5), rectangle (6–9), kept (10: 1 or 0), the degree-0 colour ``max(C0·sh₀ + 0.5, 0)`` (11–13).
Backward: the cotangents of the camera-frame centre (0–2), log-scales (3–5), quaternion (6–9), opacity logit (10),
degree 0's ``sh₀`` (11–13). For a higher SH degree the caller computes the colour and its backward itself.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._kernel_cache import install as _cache_with_imports
from .._threads import JitOptions
from ..sh import C0
from ._lanes import exp64, log64

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_BBOX_MARGIN = 1e-2  # as projection._BBOX_MARGIN
_LOG_255 = math.log(255.0)
P_ROWS = 24
Q_ROWS = 14


@nb.njit(**_JIT)
def _finite(v):  # noqa: ANN001, ANN202
    """Whether ``v`` is finite (a compare, no call)."""
    return (v - v) == 0.0


@nb.njit(**_JIT)
def _rot(qw, qx, qy, qz):  # noqa: ANN001, ANN202
    """``(s, Rq row-major (9))``: ``rotations.quat_to_rotmat`` and ``s = 2 / |q|²`` (0: the identity)."""
    n2 = qw * qw + qx * qx + qy * qy + qz * qz
    s = 2.0 / n2 if n2 > 1e-12 else 0.0
    return (s, 1.0 - s * (qy * qy + qz * qz), s * (qx * qy - qw * qz), s * (qx * qz + qw * qy),
            s * (qx * qy + qw * qz), 1.0 - s * (qx * qx + qz * qz), s * (qy * qz - qw * qx),
            s * (qx * qz - qw * qy), s * (qy * qz + qw * qx), 1.0 - s * (qx * qx + qy * qy))  # fmt: skip


@nb.njit(**_JIT)
def _wcol(c, q0, q1, q2):  # noqa: ANN001, ANN202
    """Column ``(q0, q1, q2)`` of ``Rq`` turned by the camera: that column of ``W = R Rq``."""
    return (c[0] * q0 + c[1] * q1 + c[2] * q2, c[3] * q0 + c[4] * q1 + c[5] * q2,
            c[6] * q0 + c[7] * q1 + c[8] * q2)  # fmt: skip


@nb.njit(**_JIT)
def _setup(P, i, c, lim):  # noqa: ANN001, ANN202
    """Column ``i``'s camera-frame centre, Jacobian (and its clamps) and ``log`` cap: what the forward and the
    backward share (flat scalars: a nested tuple stays in memory and keeps the loop scalar)."""
    m0, m1, m2 = P[0, i], P[1, i], P[2, i]
    x = ((c[9] + c[0] * m0) + c[1] * m1) + c[2] * m2
    y = ((c[10] + c[3] * m0) + c[4] * m1) + c[5] * m2
    z = ((c[11] + c[6] * m0) + c[7] * m1) + c[8] * m2
    inv_z = 1.0 / z
    ur, vr = x * inv_z, y * inv_z
    u, v = min(max(ur, lim[0]), lim[1]), min(max(vr, lim[2]), lim[3])
    u_in, v_in = (lim[0] <= ur) & (ur <= lim[1]), (lim[2] <= vr) & (vr <= lim[3])
    fx, skew, fy = c[12], c[13], c[15]
    J0, J1, J2, J3, J4 = fx * inv_z, skew * inv_z, -(fx * u + skew * v) * inv_z, fy * inv_z, -fy * v * inv_z
    return x, y, z, inv_z, u, v, u_in, v_in, J0, J1, J2, J3, J4, log64(z) + lim[8]


@nb.njit(**_JIT)
def _conic(p00, p01, p02, p10, p11, p12, eps2d):  # noqa: ANN001, ANN202
    """``(a, b, c, det)``: the undilated 2D covariance ``[[a, b], [b, c]] = M2 M2ᵀ`` and the dilated determinant
    ``Σ minors² + ε(a + c) + ε²`` (never below ε²)."""
    a = p00 * p00 + p01 * p01 + p02 * p02
    b = p00 * p10 + p01 * p11 + p02 * p12
    c = p10 * p10 + p11 * p11 + p12 * p12
    m01 = p00 * p11 - p01 * p10
    m02 = p00 * p12 - p02 * p10
    m12 = p01 * p12 - p02 * p11
    return a, b, c, m01 * m01 + m02 * m02 + m12 * m12 + eps2d * (a + c) + eps2d * eps2d


@nb.njit(inline="always", **_JIT)
def forward_lanes(n, P, Q, c, lim, width, height):  # noqa: ANN001, ANN201
    """The projection of columns ``[0, n)`` of ``P`` into ``Q`` (rows: the module docstring); ``c`` the camera
    (``_project_kernels``' ``cam``) as a tuple, ``lim`` its scalars."""
    lim = (lim[0], lim[1], lim[2], lim[3], lim[4], lim[5], lim[6], lim[7], lim[8], lim[9])  # no loads in the loop
    eps2d, big, wm1, hm1 = lim[6], lim[9], width - 1.0, height - 1.0
    for i in range(np.uint64(n)):
        x, y, z, inv_z, u, v, _, _, J0, J1, J2, J3, J4, log_cap = _setup(P, i, c, lim)
        _, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rot(P[6, i], P[7, i], P[8, i], P[9, i])
        ok = _finite(P[0, i]) & _finite(P[1, i]) & _finite(P[2, i]) & _finite(P[3, i]) & _finite(P[4, i])
        ok &= _finite(P[5, i]) & _finite(P[6, i]) & _finite(P[7, i]) & _finite(P[8, i]) & _finite(P[9, i])
        ok &= _finite(P[10, i]) & _finite(P[18, i]) & _finite(P[19, i]) & _finite(P[20, i])
        zd, logit = P[11, i], P[10, i]
        ok &= (zd > lim[4]) & (z > lim[4]) & (zd < lim[5]) & (logit >= lim[7])
        w0, w1, w2 = _wcol(c, r00, r10, r20)
        s = exp64(min(P[3, i], log_cap))
        p00, p10 = (J0 * w0 + J1 * w1 + J2 * w2) * s, (J3 * w1 + J4 * w2) * s
        w0, w1, w2 = _wcol(c, r01, r11, r21)
        s = exp64(min(P[4, i], log_cap))
        p01, p11 = (J0 * w0 + J1 * w1 + J2 * w2) * s, (J3 * w1 + J4 * w2) * s
        w0, w1, w2 = _wcol(c, r02, r12, r22)
        s = exp64(min(P[5, i], log_cap))
        p02, p12 = (J0 * w0 + J1 * w1 + J2 * w2) * s, (J3 * w1 + J4 * w2) * s
        a, b, cc, det = _conic(p00, p01, p02, p10, p11, p12, eps2d)
        mx = (c[12] * x + c[13] * y) * inv_z + c[14]
        my = c[15] * y * inv_z + c[16]
        op = 1.0 / (1.0 + exp64(-logit))
        level = max(2.0 * (log64(op) + _LOG_255), 0.0)  # the support: alpha ≥ 1/255
        rx = math.sqrt(level * (a + eps2d)) + _BBOX_MARGIN
        ry = math.sqrt(level * (cc + eps2d)) + _BBOX_MARGIN
        x0 = max(np.ceil(min(max(mx - rx - 0.5, -big), big)), 0.0)
        x1 = min(np.floor(min(max(mx + rx - 0.5, -big), big)), wm1)
        y0 = max(np.ceil(min(max(my - ry - 0.5, -big), big)), 0.0)
        y1 = min(np.floor(min(max(my + ry - 0.5, -big), big)), hm1)
        ok &= (x0 <= x1) & (y0 <= y1) & (level > 0.0)
        Q[0, i], Q[1, i], Q[2, i], Q[3, i], Q[4, i] = mx, my, (cc + eps2d) / det, -b / det, (a + eps2d) / det
        Q[5, i], Q[6, i], Q[7, i], Q[8, i], Q[9, i], Q[10, i] = op, x0, x1, y0, y1, 1.0 if ok else 0.0
        Q[11, i] = max((0.0 + C0 * P[18, i]) + 0.5, 0.0)  # sh_basis's C0 · sh₀, summed from 0 as there
        Q[12, i] = max((0.0 + C0 * P[19, i]) + 0.5, 0.0)
        Q[13, i] = max((0.0 + C0 * P[20, i]) + 0.5, 0.0)


@nb.njit(inline="always", **_JIT)
def _conic_vjp(p00, p01, p02, p10, p11, p12, eps2d, vA, vB, vC):  # noqa: ANN001, ANN202
    """The cotangent of ``M2`` (row-major, 6) from the conic's ``(vA, vB, vC)``."""
    a, b, c, det = _conic(p00, p01, p02, p10, p11, p12, eps2d)
    id2 = 1.0 / (det * det)
    v_det = -(vA * (c + eps2d) - vB * b + vC * (a + eps2d)) * id2
    v_a = vC / det + eps2d * v_det
    v_b = -vB / det
    v_c = vA / det + eps2d * v_det
    vm01 = 2.0 * (p00 * p11 - p01 * p10) * v_det
    vm02 = 2.0 * (p00 * p12 - p02 * p10) * v_det
    vm12 = 2.0 * (p01 * p12 - p02 * p11) * v_det
    return ((2.0 * p00 * v_a + p10 * v_b) + (vm01 * p11 + vm02 * p12),
            (2.0 * p01 * v_a + p11 * v_b) + (-vm01 * p10 + vm12 * p12),
            (2.0 * p02 * v_a + p12 * v_b) + (-vm02 * p10 - vm12 * p11),
            (2.0 * p10 * v_c + p00 * v_b) + (-vm01 * p01 - vm02 * p02),
            (2.0 * p11 * v_c + p01 * v_b) + (vm01 * p00 - vm12 * p02),
            (2.0 * p12 * v_c + p02 * v_b) + (vm02 * p00 + vm12 * p01))  # fmt: skip


@nb.njit(**_JIT)
def _col_vjp(c, J0, J1, J2, J3, J4, w0, w1, w2, s, v0, v1):  # noqa: ANN001, ANN202
    """Column ``j`` of ``M2 = J W diag(s)`` back, from its cotangent ``(v0, v1)``: ``(W s)`` of the column (3, for
    the Jacobian's cotangent), the cotangent of ``s_j`` and the column of ``G = Rᵀ v_W`` (3)."""
    vm0 = J0 * v0
    vm1 = J1 * v0 + J3 * v1
    vm2 = J2 * v0 + J4 * v1
    return (w0 * s, w1 * s, w2 * s, vm0 * w0 + vm1 * w1 + vm2 * w2, (c[0] * vm0 + c[3] * vm1 + c[6] * vm2) * s,
            (c[1] * vm0 + c[4] * vm1 + c[7] * vm2) * s, (c[2] * vm0 + c[5] * vm1 + c[8] * vm2) * s)  # fmt: skip


@nb.njit(inline="always", **_JIT)
def _quat_vjp(qw, qx, qy, qz, sq, g00, g01, g02, g10, g11, g12, g20, g21, g22):  # noqa: ANN001, ANN202, PLR0913
    """The cotangent ``(v_w, v_x, v_y, v_z)`` of a quaternion from that of its rotation ``G`` (row-major, 9; zero
    for the identity fallback ``sq = 0``)."""
    v_s = (-g00 * (qy * qy + qz * qz) + g01 * (qx * qy - qw * qz) + g02 * (qx * qz + qw * qy)
           + g10 * (qx * qy + qw * qz) - g11 * (qx * qx + qz * qz) + g12 * (qy * qz - qw * qx)
           + g20 * (qx * qz - qw * qy) + g21 * (qy * qz + qw * qx) - g22 * (qx * qx + qy * qy))  # fmt: skip
    v_n2 = -v_s * sq * sq * 0.5  # s = 2 / n2: ds/dn2 = -s²/2
    vw = sq * (-g01 * qz + g02 * qy + g10 * qz - g12 * qx - g20 * qy + g21 * qx)
    vx = sq * (-2.0 * qx * (g11 + g22) + g01 * qy + g02 * qz + g10 * qy - g12 * qw
               + g20 * qz + g21 * qw)  # fmt: skip
    vy = sq * (-2.0 * qy * (g00 + g22) + g01 * qx + g02 * qw + g10 * qx + g12 * qz
               - g20 * qw + g21 * qz)  # fmt: skip
    vz = sq * (-2.0 * qz * (g00 + g11) - g01 * qw + g02 * qx + g10 * qw + g12 * qy
               + g20 * qx + g21 * qy)  # fmt: skip
    live = sq != 0.0
    return ((vw + 2.0 * qw * v_n2) if live else 0.0, (vx + 2.0 * qx * v_n2) if live else 0.0,
            (vy + 2.0 * qy * v_n2) if live else 0.0, (vz + 2.0 * qz * v_n2) if live else 0.0)  # fmt: skip


@nb.njit(inline="always", **_JIT)
def backward_lanes(n, P, Q, c, lim):  # noqa: ANN001, ANN201
    """The vector-Jacobian product of :func:`forward_lanes` for columns ``[0, n)`` of ``P`` into ``Q`` (rows: the
    module docstring; the colour's share of the mean's cotangent is the caller's)."""
    fx, skew, fy = c[12], c[13], c[15]
    lim = (lim[0], lim[1], lim[2], lim[3], lim[4], lim[5], lim[6], lim[7], lim[8], lim[9])  # no loads in the loop
    for i in range(np.uint64(n)):
        x, y, z, inv_z, u, v, u_in, v_in, J0, J1, J2, J3, J4, log_cap = _setup(P, i, c, lim)
        sq, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rot(P[6, i], P[7, i], P[8, i], P[9, i])
        ls0, ls1, ls2 = P[3, i], P[4, i], P[5, i]
        w00, w10, w20 = _wcol(c, r00, r10, r20)
        w01, w11, w21 = _wcol(c, r01, r11, r21)
        w02, w12, w22 = _wcol(c, r02, r12, r22)
        s0, s1, s2 = exp64(min(ls0, log_cap)), exp64(min(ls1, log_cap)), exp64(min(ls2, log_cap))
        p00, p10 = (J0 * w00 + J1 * w10 + J2 * w20) * s0, (J3 * w10 + J4 * w20) * s0
        p01, p11 = (J0 * w01 + J1 * w11 + J2 * w21) * s1, (J3 * w11 + J4 * w21) * s1
        p02, p12 = (J0 * w02 + J1 * w12 + J2 * w22) * s2, (J3 * w12 + J4 * w22) * s2
        v00, v01, v02, v10, v11, v12 = _conic_vjp(p00, p01, p02, p10, p11, p12, lim[6], P[13, i], P[14, i], P[15, i])
        a0, a1, a2, vs0, g00, g10, g20 = _col_vjp(c, J0, J1, J2, J3, J4, w00, w10, w20, s0, v00, v10)
        b0, b1, b2, vs1, g01, g11, g21 = _col_vjp(c, J0, J1, J2, J3, J4, w01, w11, w21, s1, v01, v11)
        e0, e1, e2, vs2, g02, g12, g22 = _col_vjp(c, J0, J1, J2, J3, J4, w02, w12, w22, s2, v02, v12)
        vJ00 = ((0.0 + v00 * a0) + v01 * b0) + v02 * e0
        vJ01 = ((0.0 + v00 * a1) + v01 * b1) + v02 * e1
        vJ02 = ((0.0 + v00 * a2) + v01 * b2) + v02 * e2
        vJ11 = ((0.0 + v10 * a1) + v11 * b1) + v12 * e1
        vJ12 = ((0.0 + v10 * a2) + v11 * b2) + v12 * e2
        # the scales: none past the cap; torch.minimum splits a tie's gradient in half
        Q[3, i] = vs0 * s0 * (1.0 if ls0 < log_cap else 0.5) if ls0 <= log_cap else 0.0
        Q[4, i] = vs1 * s1 * (1.0 if ls1 < log_cap else 0.5) if ls1 <= log_cap else 0.0
        Q[5, i] = vs2 * s2 * (1.0 if ls2 < log_cap else 0.5) if ls2 <= log_cap else 0.0
        Q[6, i], Q[7, i], Q[8, i], Q[9, i] = _quat_vjp(
            P[6, i], P[7, i], P[8, i], P[9, i], sq, g00, g01, g02, g10, g11, g12, g20, g21, g22
        )
        v_inv_z = fx * vJ00 + skew * vJ01 - (fx * u + skew * v) * vJ02 + fy * vJ11 - fy * v * vJ12
        v_x = 0.0 + -fx * inv_z * vJ02 * inv_z if u_in else 0.0
        v_inv_z = v_inv_z + -fx * inv_z * vJ02 * x if u_in else v_inv_z
        v_v = -(skew * vJ02 + fy * vJ12) * inv_z
        v_y = 0.0 + v_v * inv_z if v_in else 0.0
        v_inv_z = v_inv_z + v_v * y if v_in else v_inv_z
        vmx, vmy = P[11, i], P[12, i]
        Q[0, i] = v_x + fx * inv_z * vmx
        Q[1, i] = v_y + (skew * vmx + fy * vmy) * inv_z
        v_inv_z += (fx * x + skew * y) * vmx + fy * y * vmy
        Q[2, i] = P[17, i] - v_inv_z * inv_z * inv_z
        op = 1.0 / (1.0 + exp64(-P[10, i]))
        Q[10, i] = P[16, i] * op * (1.0 - op)
        for ch in range(3):  # degree 0's colour: no gradient where clamped at 0
            Q[11 + ch, i] = C0 * P[21 + ch, i] if (0.0 + C0 * P[18 + ch, i]) + 0.5 >= 0.0 else 0.0
