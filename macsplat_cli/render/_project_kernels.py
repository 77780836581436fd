"""Numba CPU kernels: the fused EWA projection (+ SH colour) of :mod:`.projection`, forward and backward.

gsplat's design on a CPU: one pass per Gaussian projects the mean, builds the 2D covariance from the scales and the
quaternion, culls, inverts it to the conic, bounds the support and evaluates the SH colour; the backward recomputes
those quantities from the inputs and walks the same chain back by hand (no saved intermediates, no autograd graph).
The arithmetic, the culls and the guards are those of the plain-PyTorch twin in ``projection.py`` (read its
docstring), term for term; the kernels compute in float64 whatever the input dtype and round each output once, so a
float32 result is the float64 one to half an ulp. The exception is the depth that culls and sorts: it is summed in
the inputs' dtype as the twin sums it, so that coincident Gaussians tie, and keep their order, as in the twin.

Both kernels are serial ``nogil`` loops over a range of Gaussians, split among threads by ``_threads.parallel_for``;
each Gaussian writes only its own rows, so the threads never write the same memory.

Camera layout (``cam``, float64 [20]): ``R`` row-major (9), ``t`` (3), ``fx, skew, cx, fy, cy`` (5), the camera
centre ``-Rᵀt`` (3). Scalars (``lim``, float64 [10]): the clamp bounds of the Jacobian's ``u``, ``v`` (4), ``near``,
``far``, ``eps2d``, the smallest kept opacity logit, the log of the screen-std cap's factor ``MAX_SCREEN_STD / f_max``
and the float→int range guard (``big``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._threads import JitOptions, parallel_for
from ._sh_kernels import sh_basis, sh_basis_vjp

_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_BBOX_MARGIN = 1e-2  # as projection._BBOX_MARGIN
_LOG_255 = math.log(255.0)
_CHUNKS = 4
REC_COLS = 16
"""Columns of :func:`project_range`'s per-Gaussian record: mean 2D (2), conic (3), opacity (1), colour (3), depth
(1), rectangle (4), padding (2): 64 bytes in float32, one cache line for the gather that reads it in depth order."""
COT_COLS = 10
"""Columns of the backward's cotangent rows: mean 2D (2), conic (3), opacity (1), colour (3), depth (1); the
compositor's gradient rows (``_kernels.GRAD_COLS`` + the features r, g, b, z) as they are."""
"""Chunks of Gaussians per thread: culled Gaussians cost less, so threads take smaller runs as they come free."""


@nb.njit(**_JIT)
def _rotmat(qw, qx, qy, qz, Rq):  # noqa: ANN001, ANN202
    """``rotations.quat_to_rotmat`` into ``Rq`` [3, 3] (in place); returns ``s = 2 / |q|²`` (0: the identity)."""
    n2 = qw * qw + qx * qx + qy * qy + qz * qz
    s = 2.0 / n2 if n2 > 1e-12 else 0.0
    Rq[0, 0] = 1.0 - s * (qy * qy + qz * qz)
    Rq[0, 1] = s * (qx * qy - qw * qz)
    Rq[0, 2] = s * (qx * qz + qw * qy)
    Rq[1, 0] = s * (qx * qy + qw * qz)
    Rq[1, 1] = 1.0 - s * (qx * qx + qz * qz)
    Rq[1, 2] = s * (qy * qz - qw * qx)
    Rq[2, 0] = s * (qx * qz - qw * qy)
    Rq[2, 1] = s * (qy * qz + qw * qx)
    Rq[2, 2] = 1.0 - s * (qx * qx + qy * qy)
    return s


@nb.njit(**_JIT)
def _finite(g, means, log_scales, quats, opacity_logits, sh):  # noqa: ANN001, ANN202
    """Whether every parameter of Gaussian ``g`` is finite."""
    ok = np.isfinite(opacity_logits[g])
    for i in range(3):
        ok &= np.isfinite(means[g, i]) & np.isfinite(log_scales[g, i])
    for i in range(4):
        ok &= np.isfinite(quats[g, i])
    for k in range(sh.shape[1]):
        for ch in range(3):
            ok &= np.isfinite(sh[g, k, ch])
    return ok


@nb.njit(**_JIT)
def _camera_point(g, means, cam, pc):  # noqa: ANN001, ANN202
    """Gaussian ``g``'s centre in the camera frame, ``R m + t``, into ``pc`` [3] (in place)."""
    for i in range(3):
        pc[i] = cam[9 + i]
        for j in range(3):
            pc[i] += cam[3 * i + j] * np.float64(means[g, j])


@nb.njit(**_JIT)
def _jacobian(x, y, inv_z, cam, lim):  # noqa: ANN001, ANN202
    """The EWA Jacobian's non-zero entries ``(J00, J01, J02, J11, J12)`` at the clamped ``u, v``, and ``(u, v)``
    with flags telling whether each was inside its clamp (the gradient passes)."""
    fx, skew, fy = cam[12], cam[13], cam[15]
    ur = x * inv_z
    vr = y * inv_z
    u = min(max(ur, lim[0]), lim[1])
    v = min(max(vr, lim[2]), lim[3])
    u_in = lim[0] <= ur <= lim[1]
    v_in = lim[2] <= vr <= lim[3]
    return fx * inv_z, skew * inv_z, -(fx * u + skew * v) * inv_z, fy * inv_z, -fy * v * inv_z, u, v, u_in, v_in


@nb.njit(inline="always", **_JIT)
def _cov_factor(g, log_scales, quats, cam, log_cap, J, Rq, W, s, M2):  # noqa: ANN001, ANN202
    """``M2 = J R Rq diag(s)`` [2, 3] (``cov2d = M2 M2ᵀ``) into ``M2``, with ``Rq``, ``W = R Rq`` and the capped
    scales ``s`` [3] on the way (all in place); returns the quaternion's ``2 / |q|²``."""
    sq = _rotmat(np.float64(quats[g, 0]), np.float64(quats[g, 1]), np.float64(quats[g, 2]),
                 np.float64(quats[g, 3]), Rq)  # fmt: skip
    for j in range(3):
        s[j] = math.exp(min(np.float64(log_scales[g, j]), log_cap))
    for i in range(3):
        for j in range(3):
            W[i, j] = cam[3 * i] * Rq[0, j] + cam[3 * i + 1] * Rq[1, j] + cam[3 * i + 2] * Rq[2, j]
    for j in range(3):
        M2[0, j] = (J[0] * W[0, j] + J[1] * W[1, j] + J[2] * W[2, j]) * s[j]
        M2[1, j] = (J[3] * W[1, j] + J[4] * W[2, j]) * s[j]
    return sq


@nb.njit(**_JIT)
def _conic(M2, eps2d):  # noqa: ANN001, ANN202
    """``(a, b, c, det)``: the undilated 2D covariance ``[[a, b], [b, c]] = M2 M2ᵀ`` and the dilated determinant
    ``Σ minors² + ε(a + c) + ε²`` (never below ε²)."""
    a = M2[0, 0] * M2[0, 0] + M2[0, 1] * M2[0, 1] + M2[0, 2] * M2[0, 2]
    b = M2[0, 0] * M2[1, 0] + M2[0, 1] * M2[1, 1] + M2[0, 2] * M2[1, 2]
    c = M2[1, 0] * M2[1, 0] + M2[1, 1] * M2[1, 1] + M2[1, 2] * M2[1, 2]
    m01 = M2[0, 0] * M2[1, 1] - M2[0, 1] * M2[1, 0]
    m02 = M2[0, 0] * M2[1, 2] - M2[0, 2] * M2[1, 0]
    m12 = M2[0, 1] * M2[1, 2] - M2[0, 2] * M2[1, 1]
    det = m01 * m01 + m02 * m02 + m12 * m12 + eps2d * (a + c) + eps2d * eps2d
    return a, b, c, det


@nb.njit(**_JIT)
def _rect(mx, my, op, a_blur, c_blur, lim, width, height, rec, i):  # noqa: ANN001, ANN202
    """The support rectangle (alpha ≥ 1/255) of a Gaussian into ``rec[i, 10:14]`` (integers below ``big`` in
    magnitude: exact in float32); returns whether it reaches the image."""
    level = max(2.0 * (math.log(op) + _LOG_255), 0.0)
    rx = math.sqrt(level * a_blur) + _BBOX_MARGIN
    ry = math.sqrt(level * c_blur) + _BBOX_MARGIN
    big = lim[9]
    x0 = max(math.ceil(min(max(mx - rx - 0.5, -big), big)), 0.0)
    x1 = min(math.floor(min(max(mx + rx - 0.5, -big), big)), width - 1.0)
    y0 = max(math.ceil(min(max(my - ry - 0.5, -big), big)), 0.0)
    y1 = min(math.floor(min(max(my + ry - 0.5, -big), big)), height - 1.0)
    rec[i, 10], rec[i, 11], rec[i, 12], rec[i, 13] = x0, x1, y0, y1
    return x0 <= x1 and y0 <= y1 and level > 0.0


@nb.njit(**_JIT)
def _view_dir(g, means, cam, d):  # noqa: ANN001, ANN202
    """The unit direction from the camera centre to Gaussian ``g`` into ``d`` [3] (in place); returns the length."""
    n2 = 0.0
    for i in range(3):
        d[i] = np.float64(means[g, i]) - cam[17 + i]
        n2 += d[i] * d[i]
    n = math.sqrt(n2)
    for i in range(3):
        d[i] /= n
    return n


@nb.njit(**_JIT)
def project_range(start, stop, means, log_scales, quats, opacity_logits, sh, cam, zrow, lim, width, height,  # noqa: ANN001, ANN201
                  rec, depths, keep):  # fmt: skip
    """Project Gaussians ``[start, stop)``: each kept one (finite, ``near < z < far``, opacity ≥ 1/255, support on
    the image) gets ``keep[g] = True``, its depth in ``depths`` [N] and its record ``rec[g]`` [N, 16]
    (:data:`REC_COLS`: mean 2D, conic, opacity, colour, depth, rectangle); the others only ``keep[g] = False``.
    The depth is ``R₂·m + t₂`` in the inputs' dtype (``zrow``: ``R₂₀, R₂₁, R₂₂, t₂`` in that dtype), summed left
    to right as the twin's float32 matmul does; every other output comes from the float64 ``z``."""
    pc, J, s, d = np.empty(3), np.empty(5), np.empty(3), np.zeros(3)  # d: zero unless SH degree > 0
    Rq, W, M2 = np.empty((3, 3)), np.empty((3, 3)), np.empty((2, 3))
    basis = np.empty(sh.shape[1])
    eps2d = lim[6]
    for g in range(start, stop):
        keep[g] = False
        if not _finite(g, means, log_scales, quats, opacity_logits, sh):
            continue
        _camera_point(g, means, cam, pc)
        x, y, z = pc[0], pc[1], pc[2]
        # the depth that culls and sorts, in the inputs' dtype and the twin's order: coincident Gaussians tie
        # (and keep their index order) exactly when they tie in the twin
        zd = means[g, 0] * zrow[0] + means[g, 1] * zrow[1] + means[g, 2] * zrow[2] + zrow[3]
        logit = np.float64(opacity_logits[g])
        if not (zd > lim[4] and z > lim[4] and zd < lim[5] and logit >= lim[7]):
            continue
        inv_z = 1.0 / z
        mx = (cam[12] * x + cam[13] * y) * inv_z + cam[14]
        my = cam[15] * y * inv_z + cam[16]
        J[0], J[1], J[2], J[3], J[4], _, _, _, _ = _jacobian(x, y, inv_z, cam, lim)
        _cov_factor(g, log_scales, quats, cam, math.log(z) + lim[8], J, Rq, W, s, M2)
        a, b, c, det = _conic(M2, eps2d)
        op = 1.0 / (1.0 + math.exp(-logit))
        if not _rect(mx, my, op, a + eps2d, c + eps2d, lim, width, height, rec, g):
            continue
        keep[g] = True
        rec[g, 0], rec[g, 1] = mx, my
        rec[g, 2], rec[g, 3], rec[g, 4] = (c + eps2d) / det, -b / det, (a + eps2d) / det
        depths[g], rec[g, 5], rec[g, 9] = zd, op, zd
        if sh.shape[1] > 1:
            _view_dir(g, means, cam, d)
        sh_basis(d[0], d[1], d[2], basis)
        for ch in range(3):
            acc = 0.0
            for k in range(sh.shape[1]):
                acc += basis[k] * np.float64(sh[g, k, ch])
            rec[g, 6 + ch] = max(acc + 0.5, 0.0)


@nb.njit(inline="always", **_JIT)
def _conic_vjp(M2, eps2d, vA, vB, vC, vM2):  # noqa: ANN001, ANN202
    """Cotangent of ``M2`` [2, 3] into ``vM2`` from the conic's ``(vA, vB, vC)`` (in place)."""
    a, b, c, det = _conic(M2, eps2d)
    id2 = 1.0 / (det * det)
    v_det = -(vA * (c + eps2d) - vB * b + vC * (a + eps2d)) * id2
    v_a = vC / det + eps2d * v_det
    v_b = -vB / det
    v_c = vA / det + eps2d * v_det
    r00, r01, r02, r10, r11, r12 = M2[0, 0], M2[0, 1], M2[0, 2], M2[1, 0], M2[1, 1], M2[1, 2]
    vm01 = 2.0 * (r00 * r11 - r01 * r10) * v_det
    vm02 = 2.0 * (r00 * r12 - r02 * r10) * v_det
    vm12 = 2.0 * (r01 * r12 - r02 * r11) * v_det
    for j in range(3):
        vM2[0, j] = 2.0 * M2[0, j] * v_a + M2[1, j] * v_b
        vM2[1, j] = 2.0 * M2[1, j] * v_c + M2[0, j] * v_b
    vM2[0, 0] += vm01 * r11 + vm02 * r12
    vM2[0, 1] += -vm01 * r10 + vm12 * r12
    vM2[0, 2] += -vm02 * r10 - vm12 * r11
    vM2[1, 0] += -vm01 * r01 - vm02 * r02
    vM2[1, 1] += vm01 * r00 - vm12 * r02
    vM2[1, 2] += vm02 * r00 + vm12 * r01


@nb.njit(inline="always", **_JIT)
def _quat_vjp(qw, qx, qy, qz, sq, G):  # noqa: ANN001, ANN202
    """Cotangent ``(v_w, v_x, v_y, v_z)`` of a quaternion from that of its rotation ``G`` [3, 3] (zero for the
    identity fallback ``s = 0``)."""
    if sq == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    v_s = (-G[0, 0] * (qy * qy + qz * qz) + G[0, 1] * (qx * qy - qw * qz) + G[0, 2] * (qx * qz + qw * qy)
           + G[1, 0] * (qx * qy + qw * qz) - G[1, 1] * (qx * qx + qz * qz) + G[1, 2] * (qy * qz - qw * qx)
           + G[2, 0] * (qx * qz - qw * qy) + G[2, 1] * (qy * qz + qw * qx) - G[2, 2] * (qx * qx + qy * qy))  # fmt: skip
    v_n2 = -v_s * sq * sq * 0.5  # s = 2 / n2: ds/dn2 = -s²/2
    vw = sq * (-G[0, 1] * qz + G[0, 2] * qy + G[1, 0] * qz - G[1, 2] * qx - G[2, 0] * qy + G[2, 1] * qx)
    vx = sq * (-2.0 * qx * (G[1, 1] + G[2, 2]) + G[0, 1] * qy + G[0, 2] * qz + G[1, 0] * qy - G[1, 2] * qw
               + G[2, 0] * qz + G[2, 1] * qw)  # fmt: skip
    vy = sq * (-2.0 * qy * (G[0, 0] + G[2, 2]) + G[0, 1] * qx + G[0, 2] * qw + G[1, 0] * qx + G[1, 2] * qz
               - G[2, 0] * qw + G[2, 1] * qz)  # fmt: skip
    vz = sq * (-2.0 * qz * (G[0, 0] + G[1, 1]) - G[0, 1] * qw + G[0, 2] * qx + G[1, 0] * qw + G[1, 2] * qy
               + G[2, 0] * qx + G[2, 1] * qy)  # fmt: skip
    return vw + 2.0 * qw * v_n2, vx + 2.0 * qx * v_n2, vy + 2.0 * qy * v_n2, vz + 2.0 * qz * v_n2


@nb.njit(inline="always", **_JIT)
def _color_vjp(g, i, means, sh, cam, cot, d, basis, dbasis, v_sh):  # noqa: ANN001, ANN202
    """The colour's cotangents (row ``i`` of ``cot``, columns 6–8) into ``v_sh[g]`` (in place); returns their share
    of the mean's cotangent, through the view direction (zero for degree 0, where ``d`` stays zero)."""
    n = _view_dir(g, means, cam, d) if sh.shape[1] > 1 else 1.0
    sh_basis(d[0], d[1], d[2], basis)
    v_dir0 = v_dir1 = v_dir2 = 0.0
    if sh.shape[1] > 1:
        sh_basis_vjp(d[0], d[1], d[2], dbasis)
    for ch in range(3):
        acc = 0.0
        for k in range(sh.shape[1]):
            acc += basis[k] * np.float64(sh[g, k, ch])
        if acc + 0.5 < 0.0:  # clamped at 0: no gradient
            continue
        vc = np.float64(cot[i, 6 + ch])
        for k in range(sh.shape[1]):
            v_sh[g, k, ch] = basis[k] * vc
            if k > 0:
                w = np.float64(sh[g, k, ch]) * vc
                v_dir0 += dbasis[k, 0] * w
                v_dir1 += dbasis[k, 1] * w
                v_dir2 += dbasis[k, 2] * w
    dot = d[0] * v_dir0 + d[1] * v_dir1 + d[2] * v_dir2
    return (v_dir0 - d[0] * dot) / n, (v_dir1 - d[1] * dot) / n, (v_dir2 - d[2] * dot) / n


@nb.njit(inline="always", **_JIT)
def _cov_vjp(g, log_scales, quats, cam, log_cap, sq, J, W, s, vM2, G, v_log_scales, v_quats):  # noqa: ANN001, ANN202
    """Through ``M2 = J W diag(s)``: the cotangents of the scales (into ``v_log_scales[g]``, none past the cap)
    and of the quaternion (into ``v_quats[g]``); returns the Jacobian's ``(vJ00, vJ01, vJ02, vJ11, vJ12)``."""
    vJ00 = vJ01 = vJ02 = vJ11 = vJ12 = 0.0
    for j in range(3):
        w0, w1, w2 = W[0, j] * s[j], W[1, j] * s[j], W[2, j] * s[j]
        vJ00 += vM2[0, j] * w0
        vJ01 += vM2[0, j] * w1
        vJ02 += vM2[0, j] * w2
        vJ11 += vM2[1, j] * w1
        vJ12 += vM2[1, j] * w2
        vMc0 = J[0] * vM2[0, j]
        vMc1 = J[1] * vM2[0, j] + J[3] * vM2[1, j]
        vMc2 = J[2] * vM2[0, j] + J[4] * vM2[1, j]
        v_s = vMc0 * W[0, j] + vMc1 * W[1, j] + vMc2 * W[2, j]
        ls = np.float64(log_scales[g, j])
        if ls <= log_cap:  # torch.minimum splits a tie's gradient in half
            v_log_scales[g, j] = v_s * s[j] * (1.0 if ls < log_cap else 0.5)
        for k in range(3):  # G = Rᵀ v_W with v_W[:, j] = s_j v_Mc[:, j]
            G[k, j] = (cam[k] * vMc0 + cam[3 + k] * vMc1 + cam[6 + k] * vMc2) * s[j]
    q = (np.float64(quats[g, 0]), np.float64(quats[g, 1]), np.float64(quats[g, 2]), np.float64(quats[g, 3]))
    v_quats[g, 0], v_quats[g, 1], v_quats[g, 2], v_quats[g, 3] = _quat_vjp(q[0], q[1], q[2], q[3], sq, G)
    return vJ00, vJ01, vJ02, vJ11, vJ12


@nb.njit(**_JIT)
def project_backward_range(start, stop, rows, means, log_scales, quats, opacity_logits, sh, cam, lim, cot,  # noqa: ANN001, ANN201
                           v_means, v_log_scales, v_quats, v_opacity_logits, v_sh):  # fmt: skip
    """Vector-Jacobian product of :func:`project_range` for Gaussians ``[start, stop)``: a kept Gaussian ``g`` has
    its outputs' cotangents in row ``rows[g]`` of ``cot`` [M, 10] (:data:`COT_COLS`), a culled one ``rows[g] < 0``;
    writes the kept ones' rows of the parameters' cotangents (the others stay as they are, zero). In index order, so
    the parameters are read and written in memory order."""
    pc, J, s, d = np.empty(3), np.empty(5), np.empty(3), np.zeros(3)  # d: zero unless SH degree > 0
    Rq, W, M2, vM2, G = np.empty((3, 3)), np.empty((3, 3)), np.empty((2, 3)), np.empty((2, 3)), np.empty((3, 3))
    basis, dbasis = np.empty(sh.shape[1]), np.empty((sh.shape[1], 3))
    fx, skew, fy = cam[12], cam[13], cam[15]
    for g in range(start, stop):
        i = rows[g]
        if i < 0:
            continue
        _camera_point(g, means, cam, pc)
        x, y, z = pc[0], pc[1], pc[2]
        inv_z = 1.0 / z
        J[0], J[1], J[2], J[3], J[4], u, v, u_in, v_in = _jacobian(x, y, inv_z, cam, lim)
        log_cap = math.log(z) + lim[8]
        sq = _cov_factor(g, log_scales, quats, cam, log_cap, J, Rq, W, s, M2)
        vA, vB, vC = np.float64(cot[i, 2]), np.float64(cot[i, 3]), np.float64(cot[i, 4])
        _conic_vjp(M2, lim[6], vA, vB, vC, vM2)
        vJ00, vJ01, vJ02, vJ11, vJ12 = _cov_vjp(
            g, log_scales, quats, cam, log_cap, sq, J, W, s, vM2, G, v_log_scales, v_quats
        )
        v_inv_z = fx * vJ00 + skew * vJ01 - (fx * u + skew * v) * vJ02 + fy * vJ11 - fy * v * vJ12
        v_x = v_y = 0.0
        if u_in:
            v_x += -fx * inv_z * vJ02 * inv_z
            v_inv_z += -fx * inv_z * vJ02 * x
        if v_in:
            v_v = -(skew * vJ02 + fy * vJ12) * inv_z
            v_y += v_v * inv_z
            v_inv_z += v_v * y
        vmx, vmy = np.float64(cot[i, 0]), np.float64(cot[i, 1])
        v_x += fx * inv_z * vmx
        v_y += (skew * vmx + fy * vmy) * inv_z
        v_inv_z += (fx * x + skew * y) * vmx + fy * y * vmy
        v_z = np.float64(cot[i, 9]) - v_inv_z * inv_z * inv_z
        op = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[g])))
        v_opacity_logits[g] = np.float64(cot[i, 5]) * op * (1.0 - op)
        vd0, vd1, vd2 = _color_vjp(g, i, means, sh, cam, cot, d, basis, dbasis, v_sh)
        v_means[g, 0] = cam[0] * v_x + cam[3] * v_y + cam[6] * v_z + vd0  # one rounding per output
        v_means[g, 1] = cam[1] * v_x + cam[4] * v_y + cam[7] * v_z + vd1
        v_means[g, 2] = cam[2] * v_x + cam[5] * v_y + cam[8] * v_z + vd2


@nb.njit(**_JIT)
def depth_order(keep, bits):  # noqa: ANN001, ANN201
    """The indices [M] int64 of the kept Gaussians (``keep`` [N] bool) sorted by depth, stable (ties in index
    order), as ``np.argsort(depth[kept], kind="stable")`` would give: an LSD radix sort, one byte a pass, of the
    depths' IEEE bits ``bits`` [N] (uint32 or uint64) mapped to unsigned integers of the same order."""
    n, nbits = keep.shape[0], 8 * bits.itemsize
    m = 0
    for g in range(n):
        m += keep[g]
    idx, keys = np.empty(m, np.int64), np.empty(m, np.uint64)
    sign = np.uint64(1) << np.uint64(nbits - 1)
    ones = sign | (sign - np.uint64(1))
    j = 0
    for g in range(n):
        if keep[g]:
            b = np.uint64(bits[g])
            keys[j] = (~b & ones) if (b & sign) else (b | sign)  # negative floats: reversed
            idx[j] = g
            j += 1
    idx2, keys2 = np.empty(m, np.int64), np.empty(m, np.uint64)
    byte = np.uint64(255)
    for shift in range(0, nbits, 8):
        sh_ = np.uint64(shift)
        start = np.zeros(257, np.int64)
        for j in range(m):
            start[np.int64((keys[j] >> sh_) & byte) + 1] += 1
        if start.max() == m:  # one value of this byte: the pass would not move anything
            continue
        for d in range(256):
            start[d + 1] += start[d]
        for j in range(m):
            d = np.int64((keys[j] >> sh_) & byte)
            keys2[start[d]], idx2[start[d]] = keys[j], idx[j]
            start[d] += 1
        keys, keys2, idx, idx2 = keys2, keys, idx2, idx
    return idx


@nb.njit(**_JIT)
def _gather_range(start, stop, ids, rec, o_means2d, o_conics, o_opacities, o_features, o_rect):  # noqa: ANN001, ANN202
    """Records ``ids[start:stop]`` of :func:`project_range`'s ``rec`` into rows ``[start, stop)`` of the sorted
    outputs (the colours and depths as ``o_features`` [M, 4]): one record a Gaussian, read in one cache line."""
    for i in range(start, stop):
        g = ids[i]
        o_means2d[i, 0], o_means2d[i, 1] = rec[g, 0], rec[g, 1]
        o_conics[i, 0], o_conics[i, 1], o_conics[i, 2] = rec[g, 2], rec[g, 3], rec[g, 4]
        o_opacities[i] = rec[g, 5]
        for k in range(4):
            o_features[i, k] = rec[g, 6 + k]
            o_rect[i, k] = np.int32(rec[g, 10 + k])


def compile_kernels() -> None:
    """Compile (or load from the cache) the float32 forward (projection, depth order, gather) on empty ranges: no
    work, only the compilation, for a background thread (the backward compiles when first needed)."""
    f1, f2, f3 = np.zeros(1, np.float32), np.zeros((1, 1), np.float32), np.zeros((1, 1, 3), np.float32)
    c, i4, keep = np.zeros(20), np.zeros((1, 4), np.int32), np.zeros(1, np.bool_)
    project_range(0, 0, f2, f2, f2, f1, f3, c, f1, c, 1, 1, f2, f1, keep)
    depth_order(keep, f1.view(np.uint32))
    _gather_range(0, 0, np.zeros(1, np.int64), f2, f2, f2, f1, f2, i4)


def project(means, log_scales, quats, opacity_logits, sh, cam, lim, width, height):  # noqa: ANN001, ANN201
    """Project N Gaussians (arrays of one float dtype: ``means`` [N, 3], ``log_scales`` [N, 3], ``quats`` [N, 4],
    ``opacity_logits`` [N], ``sh`` [N, K, 3]) and keep the visible ones, front to back.

    Returns:
        ``(ids, means2d, conics, opacities, features, rect)``: the kept Gaussians' indices [M] int64 sorted by depth
        (stable: ties in index order), and their rows of :func:`project_range`'s outputs, the colours and depths as
        ``features`` [M, 4] (r, g, b, z), the compositor's input.
    """
    n, dtype = means.shape[0], means.dtype
    rec, depths, keep = np.empty((n, REC_COLS), dtype), np.empty(n, dtype), np.empty(n, np.bool_)
    zrow = np.array([cam[6], cam[7], cam[8], cam[11]], dtype)  # exact: cam holds the dtype's values
    parallel_for(project_range, n, means, log_scales, quats, opacity_logits, sh, cam, zrow, lim, width, height, rec,
                 depths, keep, chunks_per_thread=_CHUNKS)  # fmt: skip
    ids = depth_order(keep, depths.view(np.uint32 if dtype == np.float32 else np.uint64))
    m = ids.shape[0]
    out = (np.empty((m, 2), dtype), np.empty((m, 3), dtype), np.empty(m, dtype), np.empty((m, 4), dtype),
           np.empty((m, 4), np.int32))  # fmt: skip
    parallel_for(_gather_range, m, ids, rec, *out)
    return (ids, *out)


def project_vjp(ids, means, log_scales, quats, opacity_logits, sh, cam, lim, cot):  # noqa: ANN001, ANN201
    """The parameters' cotangents ``(v_means, v_log_scales, v_quats, v_opacity_logits, v_sh)`` (shaped as the
    parameters, zero for the Gaussians not in ``ids``) from those of :func:`project`'s outputs, row ``i`` of ``cot``
    [M, 10] (:data:`COT_COLS`) for Gaussian ``ids[i]``."""
    dtype = means.dtype
    rows = np.full(means.shape[0], -1, np.int64)
    rows[ids] = np.arange(ids.shape[0])
    outs = tuple(np.zeros(a.shape, dtype) for a in (means, log_scales, quats, opacity_logits, sh))
    parallel_for(project_backward_range, means.shape[0], rows, means, log_scales, quats, opacity_logits, sh, cam, lim,
                 cot, *outs, chunks_per_thread=_CHUNKS)  # fmt: skip
    return outs
