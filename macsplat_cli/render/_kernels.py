"""Numba CPU kernels: tile binning and alpha compositing, forward and backward.

Layout (Gaussian-outer, pixel-inner):

* The image is cut into ``tile × tile`` pixel tiles. Each tile owns the list of the
  Gaussians whose support rectangle touches it, in front-to-back order. The Gaussians
  arrive already sorted by depth, so a tile list holds increasing indices and the
  kernels read the per-Gaussian arrays in increasing memory order.
* One thread handles one tile at a time (runs of tiles taken by the threads of ``_threads.parallel_for``). A
  tile's pixel state lives in small arrays in a *block layout*: columns in blocks of 8, each block row-major, so
  that the rows of a Gaussian's support rectangle within one block are one contiguous run of pixels. For each
  Gaussian of the tile list, the kernels walk that run for each block the rectangle touches, every pixel of it a
  lane: no branch in the loop (a skipped sample is a lane whose alpha is masked to 0, which leaves the pixel's
  state bit-for-bit as it was), so LLVM vectorises it (8 float32 lanes with AVX2; ``_lanes.py``: the ``exp``).
* Forward: front-to-back compositing with alpha ≤ 0.99, samples with alpha < 1/255 or a
  negative exponent skipped, and a pixel stopped before the sample that would bring its
  transmittance to ≤ 1e-4 (that sample is not added). The index of the last added sample
  of each pixel is kept for the backward pass.
* Backward: back-to-front over the same samples, transmittance recovered by division by
  (1 − alpha) ≥ 0.01, with a per-pixel running sum of the later contributions. Gradients
  are written to one row per (tile, Gaussian) intersection, so no two threads ever write
  the same memory; the caller reduces the rows per Gaussian. A row's sums over the lanes are reassociated
  (8 partial sums; ``_lanes.radd``).

Every constant and skip rule here is shared with the plain-PyTorch twin in
``reference.py``; the tests compare the two on forward values and gradients.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .._kernel_cache import install as _cache_with_imports
from .._threads import JitOptions, kernel_threads, parallel_for
from . import _workspace
from ._lanes import S_MAX, exp_neg, radd
from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

GRAD_COLS = 6  # per intersection: d mean2d (2), d conic (3), d opacity (1), then d features (FEATURES)
FEATURES = 4
"""Features a Gaussian carries (r, g, b, depth): fixed, so that the lane loops keep them in registers."""

# Float32-typed literals: a float64 literal would promote every float32 expression to
# float64; float64 inputs still promote these to float64.
_HALF = np.float32(0.5)
_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_A_MIN = np.float32(ALPHA_MIN)
_A_MAX = np.float32(ALPHA_MAX)
_T_MIN = np.float32(T_MIN)
_BLOCK = 8  # columns per block of the tile layout: one AVX2 register of float32 lanes

_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_TILE_CHUNKS = 8
"""Chunks of tiles per thread: tiles differ in work, so threads take small runs of them as they come free."""
_BIN_RUNS = 2  # runs of Gaussians per thread in the binning (each run's counters cost a pass over the tiles)
_BIN_MIN_RUN = 16384  # Gaussians: below this a run's own tile counters cost more than its share of the work
LAZY_CAP = 1024
"""Lazy binning (:func:`bin_tiles_lazy`) fills only the first ``LAZY_CAP`` entries of each tile list: at 1 M
Gaussians and 1080p the forward walks ≤ 277 of a tile's 3,213 on average before its pixels are done."""
LAZY_MEAN = 2 * LAZY_CAP  # ... when the lists are this long on average (shorter: the forward walks them whole)


def bin_tiles(pixel_rect: np.ndarray, width: int, height: int, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile lists of the Gaussians touching each tile, in input (depth) order.

    Args:
        pixel_rect: inclusive support rectangles (x0, x1, y0, y1), clipped. [M, 4] int32
        width, height, tile: image size and tile size in pixels.

    Returns:
        ``(offsets, lists)``: tile ``t`` holds ``lists[offsets[t]:offsets[t + 1]]``.
        [n_tiles + 1] int64, [n_isect] int32
    """
    offsets, lists, _ = _bin(pixel_rect, width, height, tile, False)
    return offsets, lists


def bin_tiles_lazy(pixel_rect: np.ndarray, width: int, height: int, tile: int) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`bin_tiles`, but when the lists are long (:data:`LAZY_MEAN` on average) only the first ``cap`` =
    :data:`LAZY_CAP` entries of each are written (the rest of ``lists`` is left unset, its pages untouched).

    Returns:
        ``(offsets, lists, cap)``; ``cap`` 0: every list in full. Walk them with ``composite_forward(…, cap)``."""
    return _bin(pixel_rect, width, height, tile, True)


def _bin(pixel_rect: np.ndarray, width: int, height: int, tile: int, lazy: bool) -> tuple[np.ndarray, np.ndarray, int]:
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
    lists = _workspace.empty(int(offsets[-1]), np.int32)
    cap = LAZY_CAP if lazy and offsets[-1] >= LAZY_MEAN * n_tiles else 0
    parallel_for(_fill_runs, k, pixel_rect, tile, tiles_x, cursor, list_ends(offsets, cap), lists)
    return offsets, lists, cap


def list_ends(offsets: np.ndarray, cap: int) -> np.ndarray:
    """Where each tile's written list ends: ``offsets[t] + min(length, cap)`` (``cap`` 0: the whole). [n_tiles]"""
    return offsets[1:] if cap == 0 else offsets[:-1] + np.minimum(np.diff(offsets), cap)


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
def _fill_runs(start, stop, pixel_rect, tile, tiles_x, cursor, ends, lists):  # noqa: ANN001, ANN202
    k = cursor.shape[0]
    for r in range(start, stop):
        g0, g1 = _run_bounds(r, k, pixel_rect.shape[0])
        for g in range(g0, g1):
            for ty in range(pixel_rect[g, 2] // tile, pixel_rect[g, 3] // tile + 1):
                for tx in range(pixel_rect[g, 0] // tile, pixel_rect[g, 1] // tile + 1):
                    t = ty * tiles_x + tx
                    if cursor[r, t] < ends[t]:
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
def _pix(r, c, tw, th):  # noqa: ANN001, ANN202
    """Index of the tile's pixel at row ``r``, column ``c`` in the block layout (tile ``tw × th``)."""
    blk = c // _BLOCK
    return blk * _BLOCK * th + r * min(_BLOCK, tw - blk * _BLOCK) + c - blk * _BLOCK


@nb.njit(inline="always", **_JIT)
def _pixel_centres(x0, y0, x1, y1, xs, ys):  # noqa: ANN001, ANN202
    """The pixel centres ``(px + ½, py + ½)`` of tile ``[x0, x1) × [y0, y1)`` into ``xs``, ``ys`` (block layout)."""
    tw = x1 - x0
    th = y1 - y0
    for py in range(y0, y1):
        for px in range(x0, x1):
            p = _pix(py - y0, px - x0, tw, th)
            xs[p] = np.float32(px) + _HALF
            ys[p] = np.float32(py) + _HALF


@nb.njit(inline="always", **_JIT)
def _runs(g, pixel_rect, x0, y0, x1, y1):  # noqa: ANN001, ANN202
    """Gaussian ``g``'s rectangle clipped to the tile: ``(gx0, gx1, gy0, gy1)`` (upper bounds exclusive), and the
    blocks it touches ``[b0, b1)``."""
    gx0 = max(pixel_rect[g, 0], x0)
    gx1 = min(pixel_rect[g, 1] + 1, x1)
    gy0 = max(pixel_rect[g, 2], y0)
    gy1 = min(pixel_rect[g, 3] + 1, y1)
    return gx0, gx1, gy0, gy1, (gx0 - x0) // _BLOCK, (gx1 - 1 - x0) // _BLOCK + 1


@nb.njit(inline="always", **_JIT)
def _alpha(x, y, mx, my, ca, cb, cc, op):  # noqa: ANN001, ANN202
    """A Gaussian (centre ``(mx, my)``, conic ``(ca, cb, cc)``, opacity ``op``) at the pixel centre ``(x, y)``:
    ``(dx, dy, σ, exp(−σ), o·exp(−σ), alpha)``; ``exp`` of σ clamped to ``[0, S_MAX]`` (a lane whose σ is outside
    is masked by the callers)."""
    dx = x - mx
    dy = y - my
    sigma = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    gauss = exp_neg(min(max(sigma, _ZERO), S_MAX))
    raw = op * gauss
    return dx, dy, sigma, gauss, raw, min(_A_MAX, raw)


@nb.njit(inline="always", **_JIT)
def _splat_forward(g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, xs, ys, T, acc, lst,
                   live, blive):  # fmt: skip  # noqa: ANN001, ANN202
    """Composite Gaussian ``g`` (position ``k`` in the tile list) onto the tile's live pixels: updates the tile's
    transmittance ``T``, accumulated features ``acc`` [4, P], last-sample index ``lst`` and ``live`` (1, or 0 once
    the pixel is done) in place; skips the blocks with no live pixel left (``blive``: live pixels per block).
    Returns whether it finished a pixel."""
    tw = x1 - x0
    th = y1 - y0
    gx0, gx1, gy0, gy1, b0, b1 = _runs(g, pixel_rect, x0, y0, x1, y1)
    lo = xs.dtype.type(gx0)
    hi = xs.dtype.type(gx1)
    mx, my, ca, cb, cc, op = means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opacities[g]
    f0, f1, f2, f3 = features[g, 0], features[g, 1], features[g, 2], features[g, 3]
    k32 = np.int32(k)
    stopped = False
    for blk in range(b0, b1):
        if blive[blk] == 0:
            continue
        bw = min(_BLOCK, tw - blk * _BLOCK)
        base = blk * _BLOCK * th
        # unsigned indices: Numba then emits no wrap-around of negative indices, which blocks vectorisation
        for p in range(np.uint64(base + (gy0 - y0) * bw), np.uint64(base + (gy1 - y0) * bw)):
            x = xs[p]
            _, _, sigma, _, _, alpha = _alpha(x, ys[p], mx, my, ca, cb, cc, op)
            t_p = T[p]
            lv = live[p]
            ok = (x > lo) & (x < hi) & (sigma >= _ZERO) & (alpha >= _A_MIN) & (lv > _ZERO)
            a_ok = alpha if ok else _ZERO
            stop = t_p * (_ONE - a_ok) <= _T_MIN  # only a live sample can stop: T > T_MIN always
            a_add = _ZERO if stop else a_ok  # 0: the pixel's T, acc and lst stay exactly as they are
            T[p] = t_p * (_ONE - a_add)
            w = a_add * t_p
            acc[0, p] += w * f0
            acc[1, p] += w * f1
            acc[2, p] += w * f2
            acc[3, p] += w * f3
            lst[p] = max(lst[p], k32 if a_add > _ZERO else np.int32(-1))
            live[p] = _ZERO if stop else lv
            stopped |= stop
    return stopped


@nb.njit(inline="always", **_JIT)
def _count_live(b0, b1, tw, th, live, blive):  # noqa: ANN001, ANN202
    """Recount the live pixels of blocks ``[b0, b1)`` into ``blive``; returns the tile's total."""
    for blk in range(b0, b1):
        bw = min(_BLOCK, tw - blk * _BLOCK)
        base = blk * _BLOCK * th
        n = 0
        for p in range(base, base + th * bw):
            n += live[p] > _ZERO
        blive[blk] = n
    return blive[: (tw + _BLOCK - 1) // _BLOCK].sum()


def composite_forward(means2d, conics, opacities, features, pixel_rect, offsets, lists, width, height, tile, cap=0):  # noqa: ANN001, ANN201
    """Front-to-back compositing of depth-sorted Gaussians.

    Args:
        means2d: [M, 2]; conics: [M, 3]; opacities: [M]; features: [M, 4] (:data:`FEATURES`)
        pixel_rect: [M, 4] int32; offsets, lists: from :func:`bin_tiles` (or :func:`bin_tiles_lazy`, with its
        ``cap``: each tile walks at most its first ``cap`` entries).

    Returns:
        ``(feat, trans, last, short)``: accumulated features [H, W, 4] (no background),
        final transmittance [H, W], per pixel the position in its tile list of the
        last sample added (-1 if none) [H, W] int32, and whether a tile reached ``cap`` with pixels not done (the
        result is then not the full compositing: bin in full and composite again).
    """
    if features.shape[1] != FEATURES:
        raise ValueError(f"the compositing kernels take {FEATURES} features per Gaussian, not {features.shape[1]}")
    dtype = means2d.dtype
    feat = _workspace.empty((height, width, FEATURES), dtype)  # every tile writes all its pixels
    trans = _workspace.empty((height, width), dtype)
    last = _workspace.empty((height, width), np.int32)
    short = np.zeros(offsets.shape[0] - 1, np.bool_)
    parallel_for(_forward_tiles, offsets.shape[0] - 1, means2d, conics, opacities, features, pixel_rect, offsets,
                 lists, width, height, tile, cap, feat, trans, last, short, chunks_per_thread=_TILE_CHUNKS)  # fmt: skip
    return feat, trans, last, bool(short.any())


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
    cap,
    feat,
    trans,
    last,
    short,
):  # noqa: ANN001, ANN202
    tiles_x = (width + tile - 1) // tile
    dtype = means2d.dtype
    n = tile * tile
    T, acc, lst, live = np.empty(n, dtype), np.empty((FEATURES, n), dtype), np.empty(n, np.int32), np.empty(n, dtype)
    xs, ys = np.empty(n, dtype), np.empty(n, dtype)
    blive = np.empty((tile + _BLOCK - 1) // _BLOCK, np.int64)
    for t in range(start_tile, stop_tile):
        x0, y0, x1, y1 = _tile_rect(t, tiles_x, tile, width, height)
        tw = x1 - x0
        th = y1 - y0
        live[:] = 1.0
        _count_live(0, (tw + _BLOCK - 1) // _BLOCK, tw, th, live, blive)
        T[:] = 1.0
        acc[:] = 0.0
        lst[:] = -1
        _pixel_centres(x0, y0, x1, y1, xs, ys)
        start = offsets[t]
        length = offsets[t + 1] - start
        walk = length if cap == 0 else min(length, cap)
        done = False
        for k in range(walk):
            g = lists[start + k]
            if _splat_forward(
                g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, xs, ys, T, acc, lst, live, blive
            ):
                _, _, _, _, b0, b1 = _runs(g, pixel_rect, x0, y0, x1, y1)
                if _count_live(b0, b1, tw, th, live, blive) == 0:
                    done = True
                    break
        short[t] = walk < length and not done
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = _pix(py - y0, px - x0, tw, th)
                trans[py, px] = T[p]
                last[py, px] = lst[p]
                for ch in range(FEATURES):
                    feat[py, px, ch] = acc[ch, p]


@nb.njit(inline="always", **_JIT)
def _load_tile(trans, last, v_feat, v_trans, x0, y0, x1, y1, T, Q, V, lst):  # noqa: ANN001, ANN202
    """The forward's final transmittance and last-sample index and the cotangents of one tile into the tile arrays
    ``T``, ``Q``, ``V`` [4, P], ``lst`` (block layout, in place). Returns the largest last-sample index (-1 if
    none)."""
    tw = x1 - x0
    th = y1 - y0
    kmax = -1
    for py in range(y0, y1):
        for px in range(x0, x1):
            p = _pix(py - y0, px - x0, tw, th)
            T[p] = trans[py, px]
            Q[p] = trans[py, px] * v_trans[py, px]
            lst[p] = last[py, px]
            kmax = max(kmax, lst[p])
            for ch in range(FEATURES):
                V[ch, p] = v_feat[py, px, ch]
    return kmax


@nb.njit(inline="always", **_JIT)
def _splat_backward(g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, xs, ys, T, Q, V, lst,
                    out_row):  # fmt: skip  # noqa: ANN001, ANN202
    """Gradient of Gaussian ``g`` (position ``k`` in the tile list) over the tile, back to front: steps the tile's
    ``T`` and ``Q`` back past this sample (a masked lane divides by 1 and adds 0: unchanged) and writes
    ``(d mean x, d mean y, d conic a, b, c, d opacity, d features)`` into ``out_row`` [10]."""
    tw = x1 - x0
    th = y1 - y0
    gx0, gx1, gy0, gy1, b0, b1 = _runs(g, pixel_rect, x0, y0, x1, y1)
    lo = xs.dtype.type(gx0)
    hi = xs.dtype.type(gx1)
    f0, f1, f2, f3 = features[g, 0], features[g, 1], features[g, 2], features[g, 3]
    mx, my, ca, cb, cc, op = means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opacities[g]
    k32 = np.int32(k)
    z = _ZERO * f0  # a zero of the data's dtype
    v_mx, v_my, v_a, v_b, v_c, v_op, v_f0, v_f1, v_f2, v_f3 = z, z, z, z, z, z, z, z, z, z
    for blk in range(b0, b1):
        bw = min(_BLOCK, tw - blk * _BLOCK)
        base = blk * _BLOCK * th
        for p in range(np.uint64(base + (gy0 - y0) * bw), np.uint64(base + (gy1 - y0) * bw)):
            x = xs[p]
            dx, dy, sigma, gauss, raw, alpha = _alpha(x, ys[p], mx, my, ca, cb, cc, op)
            ok = (x > lo) & (x < hi) & (sigma >= _ZERO) & (alpha >= _A_MIN) & (k32 <= lst[p])
            a_ok = alpha if ok else _ZERO
            one_minus = _ONE - a_ok
            t_k = T[p] / one_minus
            w = a_ok * t_k
            v0, v1, v2, v3 = V[0, p], V[1, p], V[2, p], V[3, p]
            fv = f0 * v0 + f1 * v1 + f2 * v2 + f3 * v3
            v_f0 = radd(v_f0, w * v0)
            v_f1 = radd(v_f1, w * v1)
            v_f2 = radd(v_f2, w * v2)
            v_f3 = radd(v_f3, w * v3)
            q = Q[p]
            v_alpha = t_k * fv - q / one_minus
            Q[p] = q + w * fv
            T[p] = t_k
            v_alpha = v_alpha if ok & (raw < _A_MAX) else z  # a clamped alpha depends on neither op nor sigma
            v_op = radd(v_op, v_alpha * gauss)
            v_sigma = -v_alpha * alpha
            v_mx = radd(v_mx, -(v_sigma * (ca * dx + cb * dy)))
            v_my = radd(v_my, -(v_sigma * (cb * dx + cc * dy)))
            v_a = radd(v_a, _HALF * v_sigma * dx * dx)
            v_b = radd(v_b, v_sigma * dx * dy)
            v_c = radd(v_c, _HALF * v_sigma * dy * dy)
    out_row[0], out_row[1], out_row[2], out_row[3], out_row[4] = v_mx, v_my, v_a, v_b, v_c
    out_row[5], out_row[6], out_row[7], out_row[8], out_row[9] = v_op, v_f0, v_f1, v_f2, v_f3


def composite_backward(means2d, conics, opacities, features, pixel_rect, offsets, lists, width, height, tile, trans,  # noqa: ANN001, ANN201
                       last, v_feat, v_trans, walked=None):  # fmt: skip
    """Vector-Jacobian product of :func:`composite_forward`.

    Args:
        (as the forward), plus ``trans`` and ``last`` from the forward, and the cotangents ``v_feat`` [H, W, 4] and
        ``v_trans`` [H, W]. ``walked``: None, or [n_tiles] int64 that receives each tile's count of rows written
        (its first ones); the rows after them are then left unset, not zeroed: read up to ``offsets[t] + walked[t]``.

    Returns:
        One gradient row per intersection, aligned with ``lists``:
        (d mean x, d mean y, d conic a, b, c, d opacity, d feature 0..3). [n_isect, 6 + 4]
    """
    shape, dtype, n_tiles = (lists.shape[0], GRAD_COLS + FEATURES), means2d.dtype, offsets.shape[0] - 1
    out = _workspace.zeros(shape, dtype) if walked is None else _workspace.empty(shape, dtype)
    walked = np.empty(n_tiles, np.int64) if walked is None else walked
    args = (means2d, conics, opacities, features, pixel_rect, offsets, lists, width, height, tile)
    parallel_for(_backward_tiles, n_tiles, *args, trans, last, v_feat, v_trans, out, walked,
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
    walked,
):  # noqa: ANN001, ANN202
    tiles_x = (width + tile - 1) // tile
    dtype = means2d.dtype
    n = tile * tile
    T = np.empty(n, dtype)  # transmittance after the current sample
    Q = np.empty(n, dtype)  # Σ_{later j} α_j T_j (f_j·v) + T_final·v_T
    V = np.empty((FEATURES, n), dtype)
    lst = np.empty(n, np.int32)
    xs, ys = np.empty(n, dtype), np.empty(n, dtype)
    for t in range(start_tile, stop_tile):
        x0, y0, x1, y1 = _tile_rect(t, tiles_x, tile, width, height)
        kmax = _load_tile(trans, last, v_feat, v_trans, x0, y0, x1, y1, T, Q, V, lst)
        _pixel_centres(x0, y0, x1, y1, xs, ys)
        start = offsets[t]
        walked[t] = kmax + 1  # rows [start, start + kmax] written below
        for k in range(kmax, -1, -1):
            g = lists[start + k]
            _splat_backward(
                g, k, means2d, conics, opacities, features, pixel_rect, x0, y0, x1, y1, xs, ys, T, Q, V, lst,
                out[start + k],
            )  # fmt: skip


@nb.njit(**_JIT)
def sum_rows(offsets, ends, lists, rows, out):  # noqa: ANN001, ANN201
    """``out[lists[r]] += rows[r]`` for every intersection ``r`` of tile ``t``'s ``[offsets[t], ends[t])`` (those
    :func:`composite_backward` wrote: ``offsets[:-1] + walked``): its rows summed per Gaussian into ``out`` [M, 6 + 4]
    (in place)."""
    for t in range(ends.shape[0]):
        for r in range(offsets[t], ends[t]):
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
    _fill_runs(0, 0, r, 16, 1, np.zeros((1, 1), np.int64), o, li)
    _forward_tiles(0, 0, f2, f2, f1, f2, r, o, li, 1, 1, 16, 0, f3, f2, last, np.zeros(1, np.bool_))
