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

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@nb.njit(inline="always", **_JIT)
def _p2(p2, gamma, g_now, g_prev, p1):  # noqa: ANN001, ANN202
    v = p2 / (1.0 + gamma * abs(g_now - g_prev))
    return v if v > p1 else p1


@nb.njit(**_JIT)
def _scan(cost, gray, out, y, x, dy, dx, n, p1, p2, gamma, prev, cur):  # noqa: ANN001, ANN202
    """Aggregate one scan line starting at (y, x), stepping (dy, dx), for n pixels."""
    # prange indices are unsigned; uint64 + int64 would type as float64 in Numba
    y = np.int64(y)
    x = np.int64(x)
    d_count = cost.shape[2]
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
        cur_min = np.inf
        for d in range(d_count):
            best = prev[d]
            if d > 0 and prev[d - 1] + p1 < best:
                best = prev[d - 1] + p1
            if d < d_count - 1 and prev[d + 1] + p1 < best:
                best = prev[d + 1] + p1
            if jump < best:
                best = jump
            v = cost[y, x, d] + best - prev_min
            cur[d] = v
            if v < cur_min:
                cur_min = v
        for d in range(d_count):
            prev[d] = cur[d]
            out[y, x, d] += cur[d]
        prev_min = cur_min


@nb.njit(parallel=True, **_JIT)
def aggregate(cost, gray, p1, p2, gamma, eight_paths):  # noqa: ANN001, ANN201
    """Sum of the SGM path costs. ``cost: [H, W, D]`` float32, ``gray: [H, W]`` → ``[H, W, D]``."""
    h, w, d_count = cost.shape
    out = np.zeros_like(cost)
    # Each prange loop visits disjoint lines, so no two threads write one pixel at once.
    for y in nb.prange(h):
        prev = np.empty(d_count, cost.dtype)
        cur = np.empty(d_count, cost.dtype)
        _scan(cost, gray, out, y, 0, 0, 1, w, p1, p2, gamma, prev, cur)
        _scan(cost, gray, out, y, w - 1, 0, -1, w, p1, p2, gamma, prev, cur)
    for x in nb.prange(w):
        prev = np.empty(d_count, cost.dtype)
        cur = np.empty(d_count, cost.dtype)
        _scan(cost, gray, out, 0, x, 1, 0, h, p1, p2, gamma, prev, cur)
        _scan(cost, gray, out, h - 1, x, -1, 0, h, p1, p2, gamma, prev, cur)
    if eight_paths:
        # diagonals: one line per start pixel on the top row and left column (and mirrored)
        n_diag = w + h - 1
        for k in nb.prange(n_diag):
            prev = np.empty(d_count, cost.dtype)
            cur = np.empty(d_count, cost.dtype)
            # direction (+1, +1): starts on the top row (x = k) or the left column (y = k − w + 1)
            y0, x0 = (0, k) if k < w else (k - w + 1, 0)
            n = min(h - y0, w - x0)
            _scan(cost, gray, out, y0, x0, 1, 1, n, p1, p2, gamma, prev, cur)
            _scan(cost, gray, out, y0 + n - 1, x0 + n - 1, -1, -1, n, p1, p2, gamma, prev, cur)
        for k in nb.prange(n_diag):
            prev = np.empty(d_count, cost.dtype)
            cur = np.empty(d_count, cost.dtype)
            # direction (+1, −1): starts on the top row (x = k) or the right column (y = k − w + 1)
            y0, x0 = (0, k) if k < w else (k - w + 1, w - 1)
            n = min(h - y0, x0 + 1)
            _scan(cost, gray, out, y0, x0, 1, -1, n, p1, p2, gamma, prev, cur)
            _scan(cost, gray, out, y0 + n - 1, x0 - n + 1, -1, 1, n, p1, p2, gamma, prev, cur)
    return out


@nb.njit(parallel=True, **_JIT)
def winner(agg):  # noqa: ANN001, ANN201
    """Best hypothesis per pixel, its parabolic sub-sample offset and uniqueness.

    Returns:
        ``(index, offset, uniqueness)``: the argmin [H, W] int32; the sub-sample offset in
        [-0.5, 0.5] [H, W] float32; ``(second − best) / second`` where ``second`` is the
        lowest cost more than one hypothesis away from the best, in [0, 1] [H, W] float32.
    """
    h, w, d_count = agg.shape
    idx = np.zeros((h, w), np.int32)
    off = np.zeros((h, w), np.float32)
    uniq = np.zeros((h, w), np.float32)
    for y in nb.prange(h):
        for x in range(w):
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
    return idx, off, uniq
