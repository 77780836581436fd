"""Numba CPU kernels: tile binning and alpha compositing, forward and backward.

Layout (Gaussian-outer, pixel-inner, as measured fastest on CPUs):

* The image is cut into ``tile × tile`` pixel tiles. Each tile owns the list of the
  Gaussians whose support rectangle touches it, in front-to-back order. The Gaussians
  arrive already sorted by depth, so a tile list holds increasing indices and the
  kernels read the per-Gaussian arrays in increasing memory order.
* One thread handles one tile at a time (runs of tiles taken by the threads of ``_threads.parallel_for``). For
  each Gaussian of the tile list, only the pixels of its support rectangle inside the tile are visited.
* Forward: front-to-back compositing with alpha ≤ 0.99, samples with alpha < 1/255 or a
  negative exponent skipped, and a pixel stopped before the sample that would bring its
  transmittance to ≤ 1e-4 (that sample is not added). The index of the last added sample
  of each pixel is kept for the backward pass.
* Backward: back-to-front over the same samples, transmittance recovered by division by
  (1 − alpha) ≥ 0.01, with a per-pixel running sum of the later contributions. Gradients
  are written to one row per (tile, Gaussian) intersection, so no two threads ever write
  the same memory; the caller reduces the rows per Gaussian.

Every constant and skip rule here is shared with the plain-PyTorch twin in
``reference.py``; the tests compare the two on forward values and gradients.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .._threads import JitOptions, kernel_threads, parallel_for
from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN

GRAD_COLS = 6  # per intersection: d mean2d (2), d conic (3), d opacity (1), then d features (C)

# Float32-typed literals: a float64 literal would promote every float32 expression to
# float64; float64 inputs still promote these to float64.
_HALF = np.float32(0.5)
_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_A_MIN = np.float32(ALPHA_MIN)
_A_MAX = np.float32(ALPHA_MAX)
_T_MIN = np.float32(T_MIN)
_LOG_255 = np.float32(np.log(255.0))
_LEVEL_SLACK = np.float32(1e-3)  # the exp-free rejection must never reject alpha ≥ 1/255

_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_TILE_CHUNKS = 8
"""Chunks of tiles per thread: tiles differ in work, so threads take small runs of them as they come free."""
_BIN_RUNS = 2  # runs of Gaussians per thread in the binning (each run's counters cost a pass over the tiles)
_BIN_MIN_RUN = 16384  # Gaussians: below this a run's own tile counters cost more than its share of the work


@nb.njit(inline="always", **_JIT)
def _level(op):  # noqa: ANN001, ANN202
    """σ above which ``op·exp(−σ) < 1/255`` for sure: lets the kernels skip ``exp``."""
    return np.log(op) + _LOG_255 + _LEVEL_SLACK


def bin_tiles(pixel_rect: np.ndarray, width: int, height: int, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile lists of the Gaussians touching each tile, in input (depth) order.

    Args:
        pixel_rect: inclusive support rectangles (x0, x1, y0, y1), clipped. [M, 4] int32
        width, height, tile: image size and tile size in pixels.

    Returns:
        ``(offsets, lists)``: tile ``t`` holds ``lists[offsets[t]:offsets[t + 1]]``.
        [n_tiles + 1] int64, [n_isect] int32
    """
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    # The Gaussians in k contiguous runs, one thread a run at a time: each run counts its own tiles' hits, then
    # writes its Gaussians after the earlier runs' in each tile list (so the lists stay in depth order). Each
    # Gaussian visits only its own tiles (~1 ns an intersection; scanning every Gaussian per tile row cost ~10x).
    n_tiles = tiles_x * tiles_y
    k = max(1, min(kernel_threads() * _BIN_RUNS, pixel_rect.shape[0] // _BIN_MIN_RUN))
    counts = np.zeros((k, n_tiles), np.int64)
    parallel_for(_count_runs, k, pixel_rect, tile, tiles_x, counts)
    offsets = np.zeros(n_tiles + 1, np.int64)
    offsets[1:] = np.cumsum(counts.sum(0))
    cursor = offsets[None, :-1] + np.cumsum(counts, 0) - counts  # [k, n_tiles]: each run's first slot per tile
    lists = np.empty(offsets[-1], np.int32)
    parallel_for(_fill_runs, k, pixel_rect, tile, tiles_x, cursor, lists)
    return offsets, lists


@nb.njit(inline="always", **_JIT)
def _run_bounds(r, k, m):  # noqa: ANN001, ANN202
    """Gaussians ``[g0, g1)`` of run ``r`` of ``k`` over ``m``."""
    return m * r // k, m * (r + 1) // k


@nb.njit(**_JIT)
def _count_runs(start, stop, pixel_rect, tile, tiles_x, counts):  # noqa: ANN001, ANN202
    k = counts.shape[0]
    for r in range(start, stop):
        g0, g1 = _run_bounds(r, k, pixel_rect.shape[0])
        for g in range(g0, g1):
            for ty in range(pixel_rect[g, 2] // tile, pixel_rect[g, 3] // tile + 1):
                for tx in range(pixel_rect[g, 0] // tile, pixel_rect[g, 1] // tile + 1):
                    counts[r, ty * tiles_x + tx] += 1


@nb.njit(**_JIT)
def _fill_runs(start, stop, pixel_rect, tile, tiles_x, cursor, lists):  # noqa: ANN001, ANN202
    k = cursor.shape[0]
    for r in range(start, stop):
        g0, g1 = _run_bounds(r, k, pixel_rect.shape[0])
        for g in range(g0, g1):
            for ty in range(pixel_rect[g, 2] // tile, pixel_rect[g, 3] // tile + 1):
                for tx in range(pixel_rect[g, 0] // tile, pixel_rect[g, 1] // tile + 1):
                    t = ty * tiles_x + tx
                    lists[cursor[r, t]] = g
                    cursor[r, t] += 1


@nb.njit(inline="always", **_JIT)
def _tile_rect(t, tiles_x, tile, width, height):  # noqa: ANN001, ANN202
    """Pixel bounds ``(x0, y0, x1, y1)`` (x1, y1 exclusive) of tile ``t``, clipped to the image."""
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * tile
    y0 = ty * tile
    x1 = min(x0 + tile, width)
    y1 = min(y0 + tile, height)
    return x0, y0, x1, y1


@nb.njit(inline="always", **_JIT)
def _gaussian_in_tile(g, means2d, conics, opacities, pixel_rect, x0, y0, x1, y1):  # noqa: ANN001, ANN202
    """Gaussian ``g`` as both splat passes read it: its pixel rectangle clipped to the tile ``(gx0, gx1, gy0,
    gy1)`` (upper bounds exclusive), centre ``(mx, my)``, conic ``(a, b, c)``, opacity and its alpha level."""
    gx0 = max(pixel_rect[g, 0], x0)
    gx1 = min(pixel_rect[g, 1] + 1, x1)
    gy0 = max(pixel_rect[g, 2], y0)
    gy1 = min(pixel_rect[g, 3] + 1, y1)
    op = opacities[g]
    return gx0, gx1, gy0, gy1, means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], op, _level(op)


@nb.njit(inline="always", **_JIT)
def _splat_forward(g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, T, acc, lst, done):  # noqa: ANN001, ANN202
    """Composite Gaussian ``g`` (position ``k`` in the tile list) onto the tile's pixels not yet done: updates the
    tile's transmittance ``T``, accumulated features ``acc``, last-sample index ``lst`` and ``done`` in place.
    Returns how many pixels it finished."""
    tw = x1 - x0
    n_ch = features.shape[1]
    n_done = 0
    gx0, gx1, gy0, gy1, mx, my, ca, cb, cc, op, level = _gaussian_in_tile(
        g, means2d, conics, opacities, pixel_rect, x0, y0, x1, y1
    )
    for py in range(gy0, gy1):
        dy = np.float32(py) + _HALF - my
        row = (py - y0) * tw - x0
        for px in range(gx0, gx1):
            p = row + px
            if done[p]:
                continue
            dx = np.float32(px) + _HALF - mx
            sigma = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            if sigma < _ZERO or sigma > level:
                continue
            alpha = min(_A_MAX, op * np.exp(-sigma))
            if alpha < _A_MIN:
                continue
            next_t = T[p] * (_ONE - alpha)
            if next_t <= _T_MIN:
                done[p] = True
                n_done += 1
                continue
            w = alpha * T[p]
            for ch in range(n_ch):
                acc[p, ch] += w * features[g, ch]
            T[p] = next_t
            lst[p] = k
    return n_done


def composite_forward(means2d, conics, opacities, features, pixel_rect, offsets, lists, width, height, tile):  # noqa: ANN001, ANN201
    """Front-to-back compositing of depth-sorted Gaussians.

    Args:
        means2d: [M, 2]; conics: [M, 3]; opacities: [M]; features: [M, C]
        pixel_rect: [M, 4] int32; offsets, lists: from :func:`bin_tiles`.

    Returns:
        ``(feat, trans, last)``: accumulated features [H, W, C] (no background),
        final transmittance [H, W], and per pixel the position in its tile list of the
        last sample added (-1 if none) [H, W] int32.
    """
    n_ch = features.shape[1]
    dtype = means2d.dtype
    feat = np.zeros((height, width, n_ch), dtype)
    trans = np.ones((height, width), dtype)
    last = np.full((height, width), -1, np.int32)
    parallel_for(_forward_tiles, offsets.shape[0] - 1, means2d, conics, opacities, features, pixel_rect, offsets,
                 lists, width, height, tile, feat, trans, last, chunks_per_thread=_TILE_CHUNKS)  # fmt: skip
    return feat, trans, last


@nb.njit(**_JIT)
def _forward_tiles(
    start_tile,
    stop_tile,
    means2d,
    conics,
    opacities,
    features,
    pixel_rect,
    offsets,
    lists,
    width,
    height,
    tile,
    feat,
    trans,
    last,
):  # noqa: ANN001, ANN202
    tiles_x = (width + tile - 1) // tile
    n_ch = features.shape[1]
    dtype = means2d.dtype
    for t in range(start_tile, stop_tile):
        x0, y0, x1, y1 = _tile_rect(t, tiles_x, tile, width, height)
        tw = x1 - x0
        npix = tw * (y1 - y0)
        T = np.ones(npix, dtype)
        acc = np.zeros((npix, n_ch), dtype)
        lst = np.full(npix, -1, np.int32)
        done = np.zeros(npix, np.bool_)
        n_done = 0
        start = offsets[t]
        for k in range(offsets[t + 1] - start):
            g = lists[start + k]
            n_done += _splat_forward(
                g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, T, acc, lst, done
            )
            if n_done == npix:
                break
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tw + px - x0
                trans[py, px] = T[p]
                last[py, px] = lst[p]
                for ch in range(n_ch):
                    feat[py, px, ch] = acc[p, ch]


@nb.njit(inline="always", **_JIT)
def _load_tile(trans, last, v_feat, v_trans, x0, y0, x1, y1, T, Q, V, lst):  # noqa: ANN001, ANN202
    """The forward's final transmittance and last-sample index and the cotangents of one tile into the tile arrays
    ``T``, ``Q``, ``V``, ``lst`` (in place). Returns the largest last-sample index (-1 if none)."""
    tw = x1 - x0
    n_ch = V.shape[1]
    kmax = -1
    for py in range(y0, y1):
        for px in range(x0, x1):
            p = (py - y0) * tw + px - x0
            T[p] = trans[py, px]
            Q[p] = trans[py, px] * v_trans[py, px]
            lst[p] = last[py, px]
            kmax = max(kmax, lst[p])
            for ch in range(n_ch):
                V[p, ch] = v_feat[py, px, ch]
    return kmax


@nb.njit(inline="always", **_JIT)
def _splat_backward(g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, T, Q, V, lst, v_f):  # noqa: ANN001, ANN202
    """Gradient of Gaussian ``g`` (position ``k`` in the tile list) over the tile, back to front: steps the tile's
    ``T`` and ``Q`` back past this sample and sums its feature gradient into ``v_f`` (in place).
    Returns ``(d mean x, d mean y, d conic a, b, c, d opacity)``."""
    tw = x1 - x0
    n_ch = features.shape[1]
    gx0, gx1, gy0, gy1, mx, my, ca, cb, cc, op, level = _gaussian_in_tile(
        g, means2d, conics, opacities, pixel_rect, x0, y0, x1, y1
    )
    v_mx = 0.0
    v_my = 0.0
    v_a = 0.0
    v_b = 0.0
    v_c = 0.0
    v_op = 0.0
    v_f[:] = 0.0
    for py in range(gy0, gy1):
        dy = np.float32(py) + _HALF - my
        row = (py - y0) * tw - x0
        for px in range(gx0, gx1):
            p = row + px
            if k > lst[p]:
                continue
            dx = np.float32(px) + _HALF - mx
            sigma = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            if sigma < _ZERO or sigma > level:
                continue
            gauss = np.exp(-sigma)
            raw = op * gauss
            alpha = min(_A_MAX, raw)
            if alpha < _A_MIN:
                continue
            one_minus = _ONE - alpha
            t_k = T[p] / one_minus
            w = alpha * t_k
            fv = 0.0
            for ch in range(n_ch):
                fv += features[g, ch] * V[p, ch]
                v_f[ch] += w * V[p, ch]
            v_alpha = t_k * fv - Q[p] / one_minus
            Q[p] += w * fv
            T[p] = t_k
            if raw < _A_MAX:  # alpha not clamped: it depends on op and sigma
                v_op += v_alpha * gauss
                v_sigma = -v_alpha * alpha
                v_mx -= v_sigma * (ca * dx + cb * dy)
                v_my -= v_sigma * (cb * dx + cc * dy)
                v_a += _HALF * v_sigma * dx * dx
                v_b += v_sigma * dx * dy
                v_c += _HALF * v_sigma * dy * dy
    return v_mx, v_my, v_a, v_b, v_c, v_op


def composite_backward(
    means2d, conics, opacities, features, pixel_rect, offsets, lists, width, height, tile, trans, last, v_feat, v_trans
):  # noqa: ANN001, ANN201
    """Vector-Jacobian product of :func:`composite_forward`.

    Args:
        (as the forward), plus ``trans`` and ``last`` from the forward, and the
        cotangents ``v_feat`` [H, W, C] and ``v_trans`` [H, W].

    Returns:
        One gradient row per intersection, aligned with ``lists``:
        (d mean x, d mean y, d conic a, b, c, d opacity, d feature 0..C-1). [n_isect, 6 + C]
    """
    out = np.zeros((lists.shape[0], GRAD_COLS + features.shape[1]), means2d.dtype)
    args = (means2d, conics, opacities, features, pixel_rect, offsets, lists, width, height, tile)
    parallel_for(_backward_tiles, offsets.shape[0] - 1, *args, trans, last, v_feat, v_trans, out,
                 chunks_per_thread=_TILE_CHUNKS)  # fmt: skip
    return out


@nb.njit(**_JIT)
def _backward_tiles(
    start_tile,
    stop_tile,
    means2d,
    conics,
    opacities,
    features,
    pixel_rect,
    offsets,
    lists,
    width,
    height,
    tile,
    trans,
    last,
    v_feat,
    v_trans,
    out,
):  # noqa: ANN001, ANN202
    tiles_x = (width + tile - 1) // tile
    n_ch = features.shape[1]
    dtype = means2d.dtype
    for t in range(start_tile, stop_tile):
        x0, y0, x1, y1 = _tile_rect(t, tiles_x, tile, width, height)
        npix = (x1 - x0) * (y1 - y0)
        T = np.empty(npix, dtype)  # transmittance after the current sample
        Q = np.empty(npix, dtype)  # Σ_{later j} α_j T_j (f_j·v) + T_final·v_T
        V = np.empty((npix, n_ch), dtype)
        lst = np.empty(npix, np.int32)
        kmax = _load_tile(trans, last, v_feat, v_trans, x0, y0, x1, y1, T, Q, V, lst)
        v_f = np.empty(n_ch, dtype)
        start = offsets[t]
        for k in range(kmax, -1, -1):
            g = lists[start + k]
            v_mx, v_my, v_a, v_b, v_c, v_op = _splat_backward(
                g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, T, Q, V, lst, v_f
            )
            r = start + k
            out[r, 0] = v_mx
            out[r, 1] = v_my
            out[r, 2] = v_a
            out[r, 3] = v_b
            out[r, 4] = v_c
            out[r, 5] = v_op
            for ch in range(n_ch):
                out[r, GRAD_COLS + ch] = v_f[ch]


@nb.njit(**_JIT)
def sum_rows(lists, rows, out):  # noqa: ANN001, ANN201
    """``out[lists[r]] += rows[r]`` for every intersection ``r``: :func:`composite_backward`'s rows summed per
    Gaussian into ``out`` [M, 6 + C] (in place)."""
    for r in range(lists.shape[0]):
        g = lists[r]
        for k in range(rows.shape[1]):
            out[g, k] += rows[r, k]


def compile_kernels() -> None:
    """Compile (or load from the cache) the binning and the forward compositing for float32 Gaussians, on empty
    ranges: no work, only the compilation, for a background thread (the backward compiles when first needed)."""
    f1, f2, f3 = np.zeros(1, np.float32), np.zeros((1, 1), np.float32), np.zeros((1, 1, 1), np.float32)
    r, o, li, last = (
        np.zeros((1, 4), np.int32),
        np.zeros(2, np.int64),
        np.zeros(1, np.int32),
        np.zeros((1, 1), np.int32),
    )
    _count_runs(0, 0, r, 16, 1, np.zeros((1, 1), np.int64))
    _fill_runs(0, 0, r, 16, 1, np.zeros((1, 1), np.int64), li)
    _forward_tiles(0, 0, f2, f2, f1, f2, r, o, li, 1, 1, 16, f3, f2, last)
