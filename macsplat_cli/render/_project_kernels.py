"""Numba CPU kernels: the fused EWA projection (+ SH colour) of :mod:`.projection`, forward and backward.

gsplat's design on a CPU: one pass per Gaussian projects the mean, builds the 2D covariance from the scales and the
quaternion, culls, inverts it to the conic, bounds the support and evaluates the SH colour; the backward recomputes
those quantities from the inputs and walks the same chain back by hand (no saved intermediates, no autograd graph).
The arithmetic, the culls and the guards are those of the plain-PyTorch twin in ``projection.py`` (read its
docstring), term for term; the kernels compute in float64 whatever the input dtype and round each output once, so a
float32 result is the float64 one to half an ulp. The exception is the depth that culls and sorts: it is summed in
the inputs' dtype as the twin sums it, so that coincident Gaussians tie, and keep their order, as in the twin.

Both kernels are serial ``nogil`` loops over a range of Gaussians, split among threads by ``_threads.parallel_for``;
each Gaussian writes only its own rows, so the threads never write the same memory. A range goes in blocks of
:data:`_BLOCK` Gaussians through the vectorised lane loops of ``_project_lanes`` (the per-Gaussian arithmetic); the
SH colour, its finiteness check and its backward stay per Gaussian here.

Camera layout (``cam``, float64 [20]): ``R`` row-major (9), ``t`` (3), ``fx, skew, cx, fy, cy`` (5), the camera
centre ``-Rᵀt`` (3). Scalars (``lim``, float64 [10]): the clamp bounds of the Jacobian's ``u``, ``v`` (4), ``near``,
``far``, ``eps2d``, the smallest kept opacity logit, the log of the screen-std cap's factor ``MAX_SCREEN_STD / f_max``
and the float→int range guard (``big``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._kernel_cache import install as _cache_with_imports
from .._threads import JitOptions, parallel_for
from . import _workspace
from ._project_lanes import P_ROWS, Q_ROWS, backward_lanes, forward_lanes
from ._sh_kernels import sh_basis, sh_basis_vjp

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_CHUNKS = 4
"""Chunks of Gaussians per thread: culled Gaussians cost less, so threads take smaller runs as they come free."""
_BLOCK = 128
"""Gaussians a lane block: ``P`` and ``Q`` (29 rows of float64) take 29 KiB, within a 32 KiB L1 cache."""
REC_COLS = 16
"""Columns of :func:`project_range`'s per-Gaussian record: mean 2D (2), conic (3), opacity (1), colour (3), depth
(1), rectangle (4), padding (2): 64 bytes in float32, one cache line for the gather that reads it in depth order."""
COT_COLS = 10
"""Columns of the backward's cotangent rows: mean 2D (2), conic (3), opacity (1), colour (3), depth (1); the
compositor's gradient rows (``_kernels.GRAD_COLS`` + the features r, g, b, z) as they are."""


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


@nb.njit(inline="always", **_JIT)
def _camera_tuple(cam):  # noqa: ANN001, ANN202
    """The lane loops' camera: ``cam[:17]`` as a tuple (constants in registers, not loads from an array)."""
    return (cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7], cam[8], cam[9], cam[10], cam[11],
            cam[12], cam[13], cam[14], cam[15], cam[16])  # fmt: skip


@nb.njit(inline="always", **_JIT)
def _load(g, i, means, log_scales, quats, opacity_logits, P):  # noqa: ANN001, ANN202
    """Gaussian ``g``'s parameters (but SH) into column ``i`` of the lane block ``P`` (rows 0–10, float64)."""
    for k in range(3):
        P[k, i] = means[g, k]
        P[3 + k, i] = log_scales[g, k]
    for k in range(4):
        P[6 + k, i] = quats[g, k]
    P[10, i] = opacity_logits[g]


@nb.njit(inline="always", **_JIT)
def _color(g, means, sh, cam, d, basis, rec):  # noqa: ANN001, ANN202
    """Gaussian ``g``'s colour ``max(Σ basis·sh + 0.5, 0)`` into ``rec[g, 6:9]`` (SH degree > 0; degree 0: the
    lanes'); returns whether its SH coefficients are finite."""
    ok = True
    for k in range(sh.shape[1]):
        for ch in range(3):
            ok &= np.isfinite(sh[g, k, ch])
    if sh.shape[1] > 1:
        _view_dir(g, means, cam, d)
    sh_basis(d[0], d[1], d[2], basis)
    for ch in range(3):
        acc = 0.0
        for k in range(sh.shape[1]):
            acc += basis[k] * np.float64(sh[g, k, ch])
        rec[g, 6 + ch] = max(acc + 0.5, 0.0)
    return ok


@nb.njit(**_JIT)
def project_range(start, stop, means, log_scales, quats, opacity_logits, sh, cam, zrow, lim, width, height,  # noqa: ANN001, ANN201
                  rec, depths, keep):  # fmt: skip
    """Project Gaussians ``[start, stop)``: each kept one (finite, ``near < z < far``, opacity ≥ 1/255, support on
    the image) gets ``keep[g] = True`` and its record ``rec[g]`` [N, 16] (:data:`REC_COLS`: mean 2D, conic,
    opacity, colour, depth, rectangle); the others only ``keep[g] = False``. Every Gaussian's depth goes to
    ``depths`` [N]: ``R₂·m + t₂`` in the inputs' dtype (``zrow``: ``R₂₀, R₂₁, R₂₂, t₂`` in that dtype), summed
    left to right as the twin's float32 matmul does; every other output comes from the float64 ``z``. In blocks of
    :data:`_BLOCK` through ``_project_lanes.forward_lanes``; the colour per kept Gaussian."""
    c = _camera_tuple(cam)
    P, Q = np.empty((P_ROWS, _BLOCK)), np.empty((Q_ROWS, _BLOCK))
    d, basis = np.zeros(3), np.empty(sh.shape[1])  # d: zero unless SH degree > 0
    for b0 in range(start, stop, _BLOCK):
        n = min(_BLOCK, stop - b0)
        for i in range(n):
            g = b0 + i
            _load(g, i, means, log_scales, quats, opacity_logits, P)
            # the depth that culls and sorts, in the inputs' dtype and the twin's order: coincident Gaussians tie
            # (and keep their index order) exactly when they tie in the twin
            zd = means[g, 0] * zrow[0] + means[g, 1] * zrow[1] + means[g, 2] * zrow[2] + zrow[3]
            depths[g], P[11, i] = zd, zd
            for ch in range(3):
                P[18 + ch, i] = sh[g, 0, ch]
        forward_lanes(n, P, Q, c, lim, width, height)
        for i in range(n):
            g = b0 + i
            keep[g] = Q[10, i] != 0.0 and (sh.shape[1] == 1 or _color(g, means, sh, cam, d, basis, rec))
            if keep[g]:
                for k in range(6):
                    rec[g, k] = Q[k, i]
                for k in range(4):
                    rec[g, 10 + k] = Q[6 + k, i]
                if sh.shape[1] == 1:
                    for ch in range(3):
                        rec[g, 6 + ch] = Q[11 + ch, i]
                rec[g, 9] = depths[g]


@nb.njit(inline="always", **_JIT)
def _color_vjp(g, i, means, sh, cam, cot, d, basis, dbasis, v_sh):  # noqa: ANN001, ANN202
    """The colour's cotangents (row ``i`` of ``cot``, columns 6–8) into ``v_sh[g]`` (all of it); returns their share
    of the mean's cotangent, through the view direction (SH degree > 0; degree 0: the lanes')."""
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
            for k in range(sh.shape[1]):
                v_sh[g, k, ch] = 0.0
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
def _zero_row(g, v_means, v_log_scales, v_quats, v_opacity_logits, v_sh):  # noqa: ANN001, ANN202
    """Gaussian ``g``'s rows of the parameters' cotangents set to zero (a culled Gaussian)."""
    for k in range(3):
        v_means[g, k] = 0.0
        v_log_scales[g, k] = 0.0
    for k in range(4):
        v_quats[g, k] = 0.0
    v_opacity_logits[g] = 0.0
    for k in range(v_sh.shape[1]):
        for ch in range(3):
            v_sh[g, k, ch] = 0.0


@nb.njit(**_JIT)
def project_backward_range(start, stop, rows, means, log_scales, quats, opacity_logits, sh, cam, lim, cot,  # noqa: ANN001, ANN201
                           v_means, v_log_scales, v_quats, v_opacity_logits, v_sh):  # fmt: skip
    """Vector-Jacobian product of :func:`project_range` for Gaussians ``[start, stop)``: a kept Gaussian ``g`` has
    its outputs' cotangents in row ``rows[g]`` of ``cot`` [M, 10] (:data:`COT_COLS`), a culled one ``rows[g] < 0``;
    writes every Gaussian's rows of the parameters' cotangents (a culled one's: zeros). In blocks of
    :data:`_BLOCK` through ``_project_lanes.backward_lanes``; the colour's share per kept Gaussian."""
    c = _camera_tuple(cam)
    P, Q = np.empty((P_ROWS, _BLOCK)), np.empty((Q_ROWS, _BLOCK))
    d = np.zeros(3)  # zero unless SH degree > 0
    basis, dbasis = np.empty(sh.shape[1]), np.empty((sh.shape[1], 3))
    for b0 in range(start, stop, _BLOCK):
        n = min(_BLOCK, stop - b0)
        for i in range(n):
            g = b0 + i
            _load(g, i, means, log_scales, quats, opacity_logits, P)
            r = rows[g]
            for k in range(6):  # mean 2D, conic, opacity; then the depth, the SH's first and the colour
                P[11 + k, i] = cot[r, k] if r >= 0 else 0.0
            P[17, i] = cot[r, 9] if r >= 0 else 0.0
            for ch in range(3):
                P[18 + ch, i] = sh[g, 0, ch]
                P[21 + ch, i] = cot[r, 6 + ch] if r >= 0 else 0.0
        backward_lanes(n, P, Q, c, lim)
        for i in range(n):
            g = b0 + i
            r = rows[g]
            if r < 0:
                _zero_row(g, v_means, v_log_scales, v_quats, v_opacity_logits, v_sh)
                continue
            for k in range(3):
                v_log_scales[g, k] = Q[3 + k, i]
            for k in range(4):
                v_quats[g, k] = Q[6 + k, i]
            v_opacity_logits[g] = Q[10, i]
            vd0 = vd1 = vd2 = 0.0  # degree 0: no view direction
            if sh.shape[1] == 1:
                for ch in range(3):
                    v_sh[g, 0, ch] = Q[11 + ch, i]
            else:
                vd0, vd1, vd2 = _color_vjp(g, r, means, sh, cam, cot, d, basis, dbasis, v_sh)
            v_x, v_y, v_z = Q[0, i], Q[1, i], Q[2, i]
            v_means[g, 0] = cam[0] * v_x + cam[3] * v_y + cam[6] * v_z + vd0  # one rounding per output
            v_means[g, 1] = cam[1] * v_x + cam[4] * v_y + cam[7] * v_z + vd1
            v_means[g, 2] = cam[2] * v_x + cam[5] * v_y + cam[8] * v_z + vd2


@nb.njit(**_JIT)
def depth_order(keep, bits, idx, keys, idx2, keys2):  # noqa: ANN001, ANN201
    """The indices of the kept Gaussians (``keep`` [N] bool) sorted by depth, stable (ties in index order), as
    ``np.argsort(depth[kept], kind="stable")`` would give, into ``idx[:M]``; returns ``M``. An LSD radix sort, one
    byte a pass, of the depths' IEEE bits ``bits`` [N] (uint32 or uint64) mapped to unsigned integers of the same
    order; ``idx``, ``idx2`` [≥ N] int64 and ``keys``, ``keys2`` [≥ N] uint64 are its scratch (any values). Plain
    loops, no array methods: ``start.max()`` and the slice copy ``out[:m] = idx`` (its shape-error message) made
    Numba compile ~5 s of library code on a first run (``benchmarks/first_run.py``)."""
    n, nbits = keep.shape[0], 8 * bits.itemsize
    m = 0
    for g in range(n):
        m += keep[g]
    out, idx, keys, idx2, keys2 = idx, idx[:m], keys[:m], idx2[:m], keys2[:m]
    sign = np.uint64(1) << np.uint64(nbits - 1)
    ones = sign | (sign - np.uint64(1))
    j = 0
    for g in range(n):
        if keep[g]:
            b = np.uint64(bits[g])
            keys[j] = (~b & ones) if (b & sign) else (b | sign)  # negative floats: reversed
            idx[j] = g
            j += 1
    byte = np.uint64(255)
    start = np.empty(257, np.int64)
    swapped = False
    for shift in range(0, nbits, 8):
        sh_ = np.uint64(shift)
        for d in range(257):
            start[d] = 0
        for j in range(m):
            start[np.int64((keys[j] >> sh_) & byte) + 1] += 1
        top = 0
        for d in range(257):
            top = max(top, start[d])
        if top == m:  # one value of this byte: the pass would not move anything
            continue
        for d in range(256):
            start[d + 1] += start[d]
        for j in range(m):
            d = np.int64((keys[j] >> sh_) & byte)
            keys2[start[d]], idx2[start[d]] = keys[j], idx[j]
            start[d] += 1
        keys, keys2, idx, idx2 = keys2, keys, idx2, idx
        swapped = not swapped
    if swapped:  # the last pass wrote the second buffer
        for j in range(m):
            out[j] = idx[j]
    return m


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
    i8, u8 = np.zeros(1, np.int64), np.zeros(1, np.uint64)
    depth_order(keep, f1.view(np.uint32), i8, u8, i8, u8)
    _gather_range(0, 0, np.zeros(1, np.int64), f2, f2, f2, f1, f2, i4)


def project(means, log_scales, quats, opacity_logits, sh, cam, lim, width, height):  # noqa: ANN001, ANN201
    """Project N Gaussians (arrays of one float dtype: ``means`` [N, 3], ``log_scales`` [N, 3], ``quats`` [N, 4],
    ``opacity_logits`` [N], ``sh`` [N, K, 3]) and keep the visible ones, front to back. Every array, scratch and
    result, is on the workspace's buffers (``_workspace``).

    Returns:
        ``(ids, means2d, conics, opacities, features, rect)``: the kept Gaussians' indices [M] int64 sorted by depth
        (stable: ties in index order), and their rows of :func:`project_range`'s outputs, the colours and depths as
        ``features`` [M, 4] (r, g, b, z), the compositor's input.
    """
    n, dtype = means.shape[0], means.dtype
    rec, depths, keep = _workspace.empty((n, REC_COLS), dtype), _workspace.empty(n, dtype), _workspace.empty(n, bool)
    zrow = np.array([cam[6], cam[7], cam[8], cam[11]], dtype)  # exact: cam holds the dtype's values
    parallel_for(project_range, n, means, log_scales, quats, opacity_logits, sh, cam, zrow, lim, width, height, rec,
                 depths, keep, chunks_per_thread=_CHUNKS)  # fmt: skip
    idx, scratch = _workspace.empty(n, np.int64), _workspace.empty(n, np.int64)
    keys, keys2 = _workspace.empty(n, np.uint64), _workspace.empty(n, np.uint64)
    m = depth_order(keep, depths.view(np.uint32 if dtype == np.float32 else np.uint64), idx, keys, scratch, keys2)
    ids = idx[:m]
    out = (_workspace.empty((m, 2), dtype), _workspace.empty((m, 3), dtype), _workspace.empty(m, dtype),
           _workspace.empty((m, 4), dtype), _workspace.empty((m, 4), np.int32))  # fmt: skip
    parallel_for(_gather_range, m, ids, rec, *out)
    return (ids, *out)


@nb.njit(**_JIT)
def _rows_of(ids, rows):  # noqa: ANN001, ANN202
    """``rows[g]``: the position of Gaussian ``g`` in ``ids`` [M], -1 where it is not there (``rows`` [N])."""
    rows[:] = -1
    for i in range(ids.shape[0]):
        rows[ids[i]] = i


def project_vjp(ids, means, log_scales, quats, opacity_logits, sh, cam, lim, cot):  # noqa: ANN001, ANN201
    """The parameters' cotangents ``(v_means, v_log_scales, v_quats, v_opacity_logits, v_sh)`` (shaped as the
    parameters, zero for the Gaussians not in ``ids``; on the workspace's buffers) from those of :func:`project`'s
    outputs, row ``i`` of ``cot`` [M, 10] (:data:`COT_COLS`) for Gaussian ``ids[i]``."""
    dtype = means.dtype
    rows = _workspace.empty(means.shape[0], np.int64)
    _rows_of(ids, rows)
    outs = tuple(_workspace.empty(a.shape, dtype) for a in (means, log_scales, quats, opacity_logits, sh))
    parallel_for(project_backward_range, means.shape[0], rows, means, log_scales, quats, opacity_logits, sh, cam, lim,
                 cot, *outs, chunks_per_thread=_CHUNKS)  # fmt: skip
    return outs
