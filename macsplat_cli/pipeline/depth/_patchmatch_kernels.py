"""Numba kernels for PatchMatch-stereo refinement of slanted planes (two views, no rectification).

Each reference pixel ``p`` carries a plane, stored as its inverse depth ``ρ`` at the pixel centre and the
gradient ``(g_u, g_v)`` of the inverse depth per pixel: a 3-D plane has an inverse depth that is affine in the
pixel coordinates, so a window pixel ``q = p + (du, dv)`` lies at ``ρ_q = ρ + g_u·du + g_v·dv`` and lands in the
source image at ``x_s ~ A·q̃ + b·ρ_q`` with ``A = K_s R K_r⁻¹``, ``b = K_s t`` (the plane's own homography).
The cost is ``(1 − ZNCC)/2`` over that window, so windows on slanted surfaces (foreshortened differently in
the two views) follow the surface instead of a fronto-parallel plane.

``refine`` runs red-black PatchMatch (Bleyer et al. 2011; the checkerboard schedule of Galliani et al. 2015):
each pixel of one colour tries its neighbours' planes (offsets of odd Manhattan length, so every neighbour has
the other colour) and random perturbations of its own, and keeps the cheapest. A phase only reads pixels of the
other colour, so the result does not depend on the order or the number of threads. Random numbers come from a
hash of (seed, iteration, pixel, draw), shared with the NumPy twin ``_patchmatch_reference.py``; tests compare
the two.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..._kernel_cache import install as _cache_with_imports
from ..._threads import JitOptions, parallel_for

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}

INVALID = 2.0
"""Cost of a hypothesis whose window leaves the source image or goes behind a camera (above any real cost)."""

NEIGHBOURS = np.array([[0, -1], [0, 1], [-1, 0], [1, 0], [0, -5], [0, 5], [-5, 0], [5, 0]], np.int64)
"""(dy, dx) of the neighbours whose planes a pixel tries: all of odd Manhattan length (the other colour)."""

ZNCC_EPS = 1e-4
"""Regularises the ZNCC of flat windows, as in the plane sweep."""

_M32 = np.uint64(0xFFFFFFFF)


@nb.njit(inline="always", **_JIT)
def _hash32(x):  # noqa: ANN001, ANN202
    """A 32-bit integer hash (the "lowbias32" mixer), on uint64 holding 32-bit values."""
    x = x & _M32
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & _M32
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & _M32
    x ^= x >> np.uint64(16)
    return x


@nb.njit(inline="always", **_JIT)
def uniform(seed, it, pixel, draw):  # noqa: ANN001, ANN201
    """A number in [0, 1) from (seed, iteration, flat pixel index, draw index)."""
    h = _hash32(np.uint64(seed) * np.uint64(0x9E3779B9) + np.uint64(it))
    h = _hash32(h ^ ((np.uint64(pixel) * np.uint64(8) + np.uint64(draw)) & _M32))
    return float(h >> np.uint64(8)) * (1.0 / 16777216.0)


@nb.njit(inline="always", **_JIT)
def _ref_window(ref, y, x, radius, step, rwin):  # noqa: ANN001, ANN202
    """Pixel (y, x)'s reference window samples (row by row; outside the image clamped to its border) into ``rwin``
    [(2·radius + 1)²], and returns their mean and variance ``(mr, var_r)``."""
    h, w = ref.shape
    n = 0
    sr = 0.0
    srr = 0.0
    for jy in range(-radius, radius + 1):
        yy = min(max(y + jy * step, 0), h - 1)
        for jx in range(-radius, radius + 1):
            xx = min(max(x + jx * step, 0), w - 1)
            r = float(ref[yy, xx])
            rwin[n] = r
            n += 1
            sr += r
            srr += r * r
    inv_n = 1.0 / n
    mr = sr * inv_n
    return mr, max(srr * inv_n - mr * mr, 0.0)


@nb.njit(**_JIT)
def _window_cost(src, A, b, y, x, rho, gu, gv, radius, step, rwin, mr, var_r):  # noqa: ANN001, ANN202
    """:func:`plane_cost` with the reference window's samples, mean and variance given (:func:`_ref_window`): a
    pixel's planes share them (computed once per pixel, not once per plane)."""
    hs, ws = src.shape
    n = 0
    ss = 0.0
    sss = 0.0
    srs = 0.0
    u0 = x + 0.5
    v0 = y + 0.5
    p0 = A[0, 0] * u0 + A[0, 1] * v0 + A[0, 2] + b[0] * rho
    p1 = A[1, 0] * u0 + A[1, 1] * v0 + A[1, 2] + b[1] * rho
    p2 = A[2, 0] * u0 + A[2, 1] * v0 + A[2, 2] + b[2] * rho
    cu0 = A[0, 0] + b[0] * gu
    cu1 = A[1, 0] + b[1] * gu
    cu2 = A[2, 0] + b[2] * gu
    cv0 = A[0, 1] + b[0] * gv
    cv1 = A[1, 1] + b[1] * gv
    cv2 = A[2, 1] + b[2] * gv
    for jy in range(-radius, radius + 1):
        dv = jy * step
        for jx in range(-radius, radius + 1):
            du = jx * step
            rq = rho + gu * du + gv * dv
            if rq <= 0.0:
                return INVALID
            pz = p2 + cu2 * du + cv2 * dv
            if pz <= 0.0:
                return INVALID
            iz = 1.0 / pz
            px = (p0 + cu0 * du + cv0 * dv) * iz - 0.5
            py = (p1 + cu1 * du + cv1 * dv) * iz - 0.5
            if not (px >= 0.0 and px <= ws - 1 and py >= 0.0 and py <= hs - 1):
                return INVALID
            x0 = min(int(px), ws - 2) if ws > 1 else 0
            y0 = min(int(py), hs - 2) if hs > 1 else 0
            fx = px - x0
            fy = py - y0
            x1 = min(x0 + 1, ws - 1)
            y1 = min(y0 + 1, hs - 1)
            top = src[y0, x0] * (1.0 - fx) + src[y0, x1] * fx
            bot = src[y1, x0] * (1.0 - fx) + src[y1, x1] * fx
            s = top * (1.0 - fy) + bot * fy
            r = rwin[n]
            n += 1
            ss += s
            sss += s * s
            srs += r * s
    inv_n = 1.0 / n
    ms = ss * inv_n
    var_s = max(sss * inv_n - ms * ms, 0.0)
    cov = srs * inv_n - mr * ms
    ncc = cov / np.sqrt(var_r * var_s + ZNCC_EPS * ZNCC_EPS)
    ncc = min(1.0, max(-1.0, ncc))
    return 0.5 * (1.0 - ncc)


@nb.njit(**_JIT)
def plane_cost(ref, src, A, b, y, x, rho, gu, gv, radius, step):  # noqa: ANN001, ANN201
    """``(1 − ZNCC)/2`` of the window of pixel (y, x) warped through its plane; :data:`INVALID` if any window
    sample leaves the source image (bilinear support included) or lies behind either camera.

    The window has ``(2·radius + 1)²`` samples spaced ``step`` pixels; reference samples outside the reference
    image are clamped to its border.
    """
    rwin = np.empty((2 * radius + 1) ** 2, np.float64)
    mr, var_r = _ref_window(ref, y, x, radius, step, rwin)
    return _window_cost(src, A, b, y, x, rho, gu, gv, radius, step, rwin, mr, var_r)


@nb.njit(**_JIT)
def _initial_rows(start, stop, ref, src, A, b, rho, gu, gv, radius, step, out):  # noqa: ANN001, ANN202
    rwin = np.empty((2 * radius + 1) ** 2, np.float64)
    for y in range(start, stop):
        for x in range(ref.shape[1]):
            mr, var_r = _ref_window(ref, y, x, radius, step, rwin)
            out[y, x] = _window_cost(src, A, b, y, x, rho[y, x], gu[y, x], gv[y, x], radius, step, rwin, mr, var_r)


def initial_costs(ref, src, A, b, rho, gu, gv, radius, step):  # noqa: ANN001, ANN201
    """:func:`plane_cost` of every pixel's own plane. [h, w] float64"""
    out = np.empty(ref.shape, np.float64)
    parallel_for(_initial_rows, ref.shape[0], ref, src, A, b, rho, gu, gv, radius, step, out)
    return out


def refine(ref, src, A, b, rho, gu, gv, cost, active, rho_lo, rho_hi, f, slope_max, radius, step, iters, seed):  # noqa: ANN001, ANN201
    """Red-black PatchMatch, in place on ``rho``, ``gu``, ``gv``, ``cost`` (all [h, w] float64); returns the number of
    window costs it evaluated.

    Only ``active`` pixels ([h, w] bool) change; the others are fixed seeds whose planes propagate. Per
    iteration ``i`` and pixel: the planes of the :data:`NEIGHBOURS` (carried to this pixel), then three random
    perturbations of the best so far: inverse depth by up to ``±0.2·2⁻ⁱ`` (relative), the slope by up to
    ``±0.5·slope_max·2⁻ⁱ``, both by a quarter of those. Slopes are normalised, ``s = g·f/ρ`` (``f``: the focal
    length in pixels; ``|s| = tan`` of the plane's tilt from fronto-parallel about that axis, roughly), and
    kept within ``±slope_max``; inverse depths within ``[rho_lo, rho_hi]``.

    A neighbour's plane that the pixel already evaluated in its previous phase, unchanged since (a seed, or a pixel
    its own last phase left as it was), is not evaluated again: the same plane has the same cost, and the pixel's
    cost is already at most that (it only falls), so the strict ``<`` could not take it. The planes are those of
    the plain schedule (the NumPy twin's), bit for bit, at fewer evaluations.
    """
    h = ref.shape[0]
    changed = np.zeros(ref.shape, np.uint8)  # 1: the pixel's last phase took a new plane
    known = np.zeros(ref.shape, np.uint8)  # bit k: neighbour k's plane was evaluated at the pixel's last phase
    evals = np.zeros(h, np.int64)
    for it in range(iters):
        for colour in range(2):  # a phase reads only the other colour: its rows can go to any thread
            parallel_for(_refine_rows, h, ref, src, A, b, rho, gu, gv, cost, active, rho_lo, rho_hi, f,
                         slope_max, radius, step, it, colour, seed, changed, known, evals)  # fmt: skip
    return int(evals.sum())


@nb.njit(**_JIT)
def _refine_rows(
    start, stop, ref, src, A, b, rho, gu, gv, cost, active, rho_lo, rho_hi, f, slope_max, radius, step, it, colour,
    seed, changed, known, evals,
):  # noqa: ANN001, ANN202  # fmt: skip
    """One phase (iteration ``it``, pixels of ``colour``) of :func:`refine` on rows ``start … stop − 1``; ``changed``,
    ``known`` [h, w] uint8 and ``evals`` [h] int64 as :func:`refine` keeps them."""
    h, w = ref.shape
    n_nb = NEIGHBOURS.shape[0]
    scale = 0.5**it
    for y in range(start, stop):
        tried = np.empty((n_nb, 3), np.float64)
        rwin = np.empty((2 * radius + 1) ** 2, np.float64)
        n_evals = 0
        for x in range(w):
            if (x + y) % 2 != colour or not active[y, x]:
                continue
            mr, var_r = _ref_window(ref, y, x, radius, step, rwin)
            best = cost[y, x]
            br = rho[y, x]
            bu = gu[y, x]
            bv = gv[y, x]
            n_tried = 0
            was_known = known[y, x]
            now_known = 0
            took = False
            for k in range(n_nb):
                ny = y + NEIGHBOURS[k, 0]
                nx = x + NEIGHBOURS[k, 1]
                if ny < 0 or ny >= h or nx < 0 or nx >= w:
                    continue
                cu = gu[ny, nx]
                cv = gv[ny, nx]
                cr = rho[ny, nx] + cu * (x - nx) + cv * (y - ny)
                if cr < rho_lo or cr > rho_hi:
                    continue
                if abs(cr - rho[y, x]) <= 1e-9 * cr and cu == gu[y, x] and cv == gv[y, x]:
                    continue  # the pixel's own plane (a converged neighbourhood): same cost
                seen = False
                for j in range(n_tried):
                    if cu == tried[j, 1] and cv == tried[j, 2] and abs(cr - tried[j, 0]) <= 1e-9 * cr:
                        seen = True
                        break
                if seen:
                    continue  # the plane of a neighbour already tried
                tried[n_tried, 0] = cr
                tried[n_tried, 1] = cu
                tried[n_tried, 2] = cv
                n_tried += 1
                bit = 1 << k
                now_known |= bit
                if (was_known & bit) != 0 and changed[ny, nx] == 0:
                    continue  # evaluated at this pixel's last phase, the same plane since: cost ≥ best
                n_evals += 1
                c = _window_cost(src, A, b, y, x, cr, cu, cv, radius, step, rwin, mr, var_r)
                if c < best:
                    best, br, bu, bv = c, cr, cu, cv
                    took = True
            pix = y * w + x
            for k in range(3):
                a = 1.0 if k == 0 else (0.0 if k == 1 else 0.25)
                m = 0.0 if k == 0 else (1.0 if k == 1 else 0.25)
                r1 = uniform(seed, it * 2 + colour, pix, 3 * k)
                r2 = uniform(seed, it * 2 + colour, pix, 3 * k + 1)
                r3 = uniform(seed, it * 2 + colour, pix, 3 * k + 2)
                cr = br * (1.0 + a * 0.2 * scale * (2.0 * r1 - 1.0))
                cr = min(max(cr, rho_lo), rho_hi)
                su = bu * f / br + m * 0.5 * slope_max * scale * (2.0 * r2 - 1.0)
                sv = bv * f / br + m * 0.5 * slope_max * scale * (2.0 * r3 - 1.0)
                su = min(max(su, -slope_max), slope_max)
                sv = min(max(sv, -slope_max), slope_max)
                cu = su * cr / f
                cv = sv * cr / f
                n_evals += 1
                c = _window_cost(src, A, b, y, x, cr, cu, cv, radius, step, rwin, mr, var_r)
                if c < best:
                    best, br, bu, bv = c, cr, cu, cv
                    took = True
            rho[y, x] = br
            gu[y, x] = bu
            gv[y, x] = bv
            cost[y, x] = best
            changed[y, x] = 1 if took else 0
            known[y, x] = now_known
        evals[y] += n_evals


def compile_kernels() -> None:
    """Compile (or load from the cache) the kernels for the types :mod:`.slanted` passes (float64 C arrays), on
    empty ranges: no work, only the compilation, for a background thread."""
    a, v, m = np.zeros((1, 1)), np.zeros(3), np.zeros((1, 1), np.bool_)
    u8, n = np.zeros((1, 1), np.uint8), np.zeros(1, np.int64)
    _initial_rows(0, 0, a, a, a, v, a, a, a, 0, 0, a)
    _refine_rows(0, 0, a, a, a, v, a, a, a, a, m, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, u8, u8, n)
