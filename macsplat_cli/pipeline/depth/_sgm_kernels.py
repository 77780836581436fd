"""Numba kernels for semi-global matching over a plane-sweep cost volume.

``aggregate`` sums, over 4 or 8 scan directions, the path costs
``L_r(p, d) = C(p, d) + min(L_r(p−r, d), L_r(p−r, d±1) + P1, min_k L_r(p−r, k) + P2(p)) − min_k L_r(p−r, k)``
(Hirschmüller 2008), with ``P2`` lowered across intensity edges. ``winner`` picks the
best hypothesis per pixel with a parabolic sub-sample offset and a uniqueness margin.
The plain-PyTorch twin is ``_sgm_reference.py``; tests compare the two.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..._kernel_cache import install as _cache_with_imports
from ..._threads import JitOptions, parallel_for

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}
_I = np.int64
"""Integer arguments of ``_scan`` are cast to this, so that it compiles once for every caller."""


@nb.njit(inline="always", **_JIT)
def _p2(p2, gamma, g_now, g_prev, p1):  # noqa: ANN001, ANN202
    v = p2 / (1.0 + gamma * abs(g_now - g_prev))
    return v if v > p1 else p1


@nb.njit(**_JIT)
def _scan(cost, gray, out, y, x, dy, dx, n, p1, p2, gamma, prev, cur):  # noqa: ANN001, ANN202
    """Aggregate one scan line starting at (y, x), stepping (dy, dx), for n pixels. Every integer argument is an
    int64 (the callers cast them: ``_I``), so that this compiles once, not once per mix of integer types. ``prev``:
    [D] float32, ``cur``: [D] float64 (a step's path costs before their float32 store, whose minimum is taken
    unrounded)."""
    d_count = cost.shape[2]
    last = d_count - 1
    for d in range(d_count):
        prev[d] = cost[y, x, d]
        out[y, x, d] += prev[d]
    prev_min = prev[0]
    for d in range(1, d_count):
        if prev[d] < prev_min:
            prev_min = prev[d]
    for _ in range(1, n):
        g_prev = gray[y, x]
        y += dy
        x += dx
        pen2 = _p2(p2, gamma, gray[y, x], g_prev, p1)
        jump = prev_min + pen2
        c = cost[y, x]
        # the first and last hypotheses have one neighbour; the others' loop has no branch on d (4-5x faster),
        # each candidate compared in the same order with the same strict < as the plain loop (the same bits)
        best = np.float64(prev[0])
        if last > 0 and prev[1] + p1 < best:
            best = prev[1] + p1
        if jump < best:
            best = jump
        cur[0] = c[0] + best - prev_min
        for d in range(1, last):
            best = np.float64(prev[d])
            lo = prev[d - 1] + p1
            best = lo if lo < best else best
            hi = prev[d + 1] + p1
            best = hi if hi < best else best
            best = jump if jump < best else best
            cur[d] = c[d] + best - prev_min
        if last > 0:
            best = np.float64(prev[last])
            if prev[last - 1] + p1 < best:
                best = prev[last - 1] + p1
            if jump < best:
                best = jump
            cur[last] = c[last] + best - prev_min
        cur_min = np.inf
        o = out[y, x]
        for d in range(d_count):
            v = cur[d]
            if v < cur_min:
                cur_min = v
            prev[d] = v
            o[d] += prev[d]
        prev_min = cur_min


@nb.njit(**_JIT)
def _straight(start, stop, cost, gray, out, p1, p2, gamma, vertical):  # noqa: ANN001, ANN202
    """Both paths of lines ``start … stop − 1``: rows (left-to-right and back) or, when ``vertical``, columns
    (top-to-bottom and back)."""
    h, w, d_count = cost.shape
    h, w, one, zero = _I(h), _I(w), _I(1), _I(0)
    prev = np.empty(d_count, cost.dtype)
    cur = np.empty(d_count, np.float64)
    for k in range(start, stop):
        if vertical:
            _scan(cost, gray, out, zero, _I(k), one, zero, h, p1, p2, gamma, prev, cur)
            _scan(cost, gray, out, h - one, _I(k), -one, zero, h, p1, p2, gamma, prev, cur)
        else:
            _scan(cost, gray, out, _I(k), zero, zero, one, w, p1, p2, gamma, prev, cur)
            _scan(cost, gray, out, _I(k), w - one, zero, -one, w, p1, p2, gamma, prev, cur)


@nb.njit(**_JIT)
def _diagonals(start, stop, cost, gray, out, p1, p2, gamma, right):  # noqa: ANN001, ANN202
    """The diagonal paths of lines ``start … stop − 1``, both ways: direction (+1, +1) when ``right`` (one line
    per start pixel on the top row, x = k, or the left column, y = k − w + 1), else (+1, −1) (the top row or the
    right column)."""
    h, w, d_count = cost.shape
    h, w, one, zero = _I(h), _I(w), _I(1), _I(0)
    prev = np.empty(d_count, cost.dtype)
    cur = np.empty(d_count, np.float64)
    for k in range(start, stop):
        kk = _I(k)
        if right:
            y0, x0 = (zero, kk) if kk < w else (kk - w + one, zero)
            n = min(h - y0, w - x0)
            _scan(cost, gray, out, y0, x0, one, one, n, p1, p2, gamma, prev, cur)
            _scan(cost, gray, out, y0 + n - one, x0 + n - one, -one, -one, n, p1, p2, gamma, prev, cur)
        else:
            y0, x0 = (zero, kk) if kk < w else (kk - w + one, w - one)
            n = min(h - y0, x0 + one)
            _scan(cost, gray, out, y0, x0, one, -one, n, p1, p2, gamma, prev, cur)
            _scan(cost, gray, out, y0 + n - one, x0 - n + one, -one, one, n, p1, p2, gamma, prev, cur)


def aggregate(cost: np.ndarray, gray: np.ndarray, p1: float, p2: float, gamma: float, eight_paths: bool) -> np.ndarray:
    """Sum of the SGM path costs. ``cost: [H, W, D]`` float32, ``gray: [H, W]`` → ``[H, W, D]``.

    One direction pair at a time, its lines split among threads: the lines of one pass are disjoint, so no two
    threads write one pixel at once, and every pixel sums its paths in the same order whatever the threads."""
    h, w, _ = cost.shape
    out = np.zeros_like(cost)
    args = (cost, gray, out, float(p1), float(p2), float(gamma))
    parallel_for(_straight, h, *args, False)
    parallel_for(_straight, w, *args, True)
    if eight_paths:
        parallel_for(_diagonals, w + h - 1, *args, True)
        parallel_for(_diagonals, w + h - 1, *args, False)
    return out


@nb.njit(**_JIT)
def _winner_rows(start, stop, agg, idx, off, uniq):  # noqa: ANN001, ANN202
    d_count = agg.shape[2]
    for y in range(start, stop):
        for x in range(agg.shape[1]):
            best = agg[y, x, 0]
            k = 0
            for d in range(1, d_count):
                if agg[y, x, d] < best:
                    best = agg[y, x, d]
                    k = d
            second = np.inf
            for d in range(d_count):
                if abs(d - k) > 1 and agg[y, x, d] < second:
                    second = agg[y, x, d]
            idx[y, x] = k
            if 0 < k < d_count - 1:
                a, b, c = agg[y, x, k - 1], agg[y, x, k], agg[y, x, k + 1]
                den = a - 2.0 * b + c
                if den > 0:
                    o = 0.5 * (a - c) / den
                    off[y, x] = min(0.5, max(-0.5, o))
            if second < np.inf and second > 0:
                uniq[y, x] = (second - best) / second


def winner(agg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best hypothesis per pixel, its parabolic sub-sample offset and uniqueness.

    Returns:
        ``(index, offset, uniqueness)``: the argmin [H, W] int32; the sub-sample offset in
        [-0.5, 0.5] [H, W] float32; ``(second − best) / second`` where ``second`` is the
        lowest cost more than one hypothesis away from the best, in [0, 1] [H, W] float32.
    """
    h, w, _ = agg.shape
    idx = np.zeros((h, w), np.int32)
    off = np.zeros((h, w), np.float32)
    uniq = np.zeros((h, w), np.float32)
    parallel_for(_winner_rows, h, agg, idx, off, uniq)
    return idx, off, uniq


def compile_kernels() -> None:
    """Compile (or load from the cache) every kernel here for the argument types the sweep passes (float32 C arrays,
    float64 penalties), on empty ranges: no work, only the compilation, for a background thread."""
    c, g, i = np.zeros((1, 1, 1), np.float32), np.zeros((1, 1), np.float32), np.zeros((1, 1), np.int32)
    _straight(0, 0, c, g, c, 0.0, 0.0, 0.0, False)
    _winner_rows(0, 0, c, i, g, g)
