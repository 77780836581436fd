"""Plain-NumPy twin of ``_patchmatch_kernels.py`` (slow; a test oracle on small images).

Vectorised over the pixels of one colour at a time, with the same operation order as the kernels (window
sums accumulated offset by offset, candidates tried in the same sequence with a strict ``<``), so the two
agree to rounding.
"""

from __future__ import annotations

import numpy as np

from ._patchmatch_kernels import INVALID, NEIGHBOURS, ZNCC_EPS

__all__ = ["initial_costs_reference", "plane_cost_reference", "refine_reference", "uniform_reference"]

_M32 = np.uint64(0xFFFFFFFF)


def _hash32(x: np.ndarray | np.uint64) -> np.ndarray | np.uint64:
    x = x & _M32
    x = x ^ (x >> np.uint64(16))
    x = (x * np.uint64(0x7FEB352D)) & _M32
    x = x ^ (x >> np.uint64(15))
    x = (x * np.uint64(0x846CA68B)) & _M32
    x = x ^ (x >> np.uint64(16))
    return x


def uniform_reference(seed: int, it: int, pixel: np.ndarray, draw: int) -> np.ndarray:
    """Same numbers as ``_patchmatch_kernels.uniform``, for an array of flat pixel indices. [N] float64"""
    with np.errstate(over="ignore"):
        h = _hash32(np.uint64(seed) * np.uint64(0x9E3779B9) + np.uint64(it))
        p = (pixel.astype(np.uint64) * np.uint64(8) + np.uint64(draw)) & _M32
        h = _hash32(h ^ p)
    return (h >> np.uint64(8)).astype(np.float64) * (1.0 / 16777216.0)


def plane_cost_reference(
    ref: np.ndarray,  # [h, w]
    src: np.ndarray,  # [hs, ws]
    A: np.ndarray,  # [3, 3]
    b: np.ndarray,  # [3]
    ys: np.ndarray,  # [N] int
    xs: np.ndarray,  # [N] int
    rho: np.ndarray,  # [N]
    gu: np.ndarray,  # [N]
    gv: np.ndarray,  # [N]
    radius: int,
    step: int,
) -> np.ndarray:
    """Same contract as ``_patchmatch_kernels.plane_cost``, for N pixels with one plane each. [N] float64"""
    h, w = ref.shape
    hs, ws = src.shape
    n = len(ys)
    sums = np.zeros((5, n))
    bad = np.zeros(n, bool)
    count = 0
    u0 = xs + 0.5
    v0 = ys + 0.5
    p0 = A[0, 0] * u0 + A[0, 1] * v0 + A[0, 2] + b[0] * rho
    p1 = A[1, 0] * u0 + A[1, 1] * v0 + A[1, 2] + b[1] * rho
    p2 = A[2, 0] * u0 + A[2, 1] * v0 + A[2, 2] + b[2] * rho
    cu0, cu1, cu2 = A[0, 0] + b[0] * gu, A[1, 0] + b[1] * gu, A[2, 0] + b[2] * gu
    cv0, cv1, cv2 = A[0, 1] + b[0] * gv, A[1, 1] + b[1] * gv, A[2, 1] + b[2] * gv
    for jy in range(-radius, radius + 1):
        dv = jy * step
        yy = np.clip(ys + dv, 0, h - 1)
        for jx in range(-radius, radius + 1):
            du = jx * step
            xx = np.clip(xs + du, 0, w - 1)
            rq = rho + gu * du + gv * dv
            pz = p2 + cu2 * du + cv2 * dv
            bad |= (rq <= 0.0) | (pz <= 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                iz = 1.0 / pz
                px = (p0 + cu0 * du + cv0 * dv) * iz - 0.5
                py = (p1 + cu1 * du + cv1 * dv) * iz - 0.5
            bad |= ~((px >= 0.0) & (px <= ws - 1) & (py >= 0.0) & (py <= hs - 1))
            pxs = np.where(bad, 0.0, px)
            pys = np.where(bad, 0.0, py)
            x0 = np.minimum(pxs.astype(np.int64), ws - 2) if ws > 1 else np.zeros(n, np.int64)
            y0 = np.minimum(pys.astype(np.int64), hs - 2) if hs > 1 else np.zeros(n, np.int64)
            fx = pxs - x0
            fy = pys - y0
            x1 = np.minimum(x0 + 1, ws - 1)
            y1 = np.minimum(y0 + 1, hs - 1)
            top = src[y0, x0] * (1.0 - fx) + src[y0, x1] * fx
            bot = src[y1, x0] * (1.0 - fx) + src[y1, x1] * fx
            s = top * (1.0 - fy) + bot * fy
            r = ref[yy, xx].astype(np.float64)
            count += 1
            sums[0] += r
            sums[1] += r * r
            sums[2] += s
            sums[3] += s * s
            sums[4] += r * s
    inv_n = 1.0 / count
    mr = sums[0] * inv_n
    ms = sums[2] * inv_n
    var_r = np.maximum(sums[1] * inv_n - mr * mr, 0.0)
    var_s = np.maximum(sums[3] * inv_n - ms * ms, 0.0)
    cov = sums[4] * inv_n - mr * ms
    ncc = np.clip(cov / np.sqrt(var_r * var_s + ZNCC_EPS * ZNCC_EPS), -1.0, 1.0)
    return np.where(bad, INVALID, 0.5 * (1.0 - ncc))


def initial_costs_reference(
    ref: np.ndarray, src: np.ndarray, A: np.ndarray, b: np.ndarray, rho: np.ndarray, gu: np.ndarray,
    gv: np.ndarray, radius: int, step: int,
) -> np.ndarray:  # fmt: skip
    """Same contract as ``_patchmatch_kernels.initial_costs``. [h, w] float64"""
    h, w = ref.shape
    ys, xs = np.divmod(np.arange(h * w), w)
    c = plane_cost_reference(ref, src, A, b, ys, xs, rho.ravel(), gu.ravel(), gv.ravel(), radius, step)
    return c.reshape(h, w)


def _same(cr: np.ndarray, cu: np.ndarray, cv: np.ndarray, r: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The same plane (as the kernel tests it): equal slopes, inverse depths within 1e-9 (relative)."""
    return (np.abs(cr - r) <= 1e-9 * cr) & (cu == u) & (cv == v)


def _take(better: np.ndarray, new: tuple, old: tuple) -> tuple:
    return tuple(np.where(better, n, o) for n, o in zip(new, old))


def refine_reference(
    ref: np.ndarray, src: np.ndarray, A: np.ndarray, b: np.ndarray, rho: np.ndarray, gu: np.ndarray,
    gv: np.ndarray, cost: np.ndarray, active: np.ndarray, rho_lo: float, rho_hi: float, f: float,
    slope_max: float, radius: int, step: int, iters: int, seed: int,
) -> None:  # fmt: skip
    """Same contract as ``_patchmatch_kernels.refine`` (in place)."""
    h, w = ref.shape
    yy, xx = np.mgrid[0:h, 0:w]
    for it in range(iters):
        scale = 0.5**it
        for colour in range(2):
            sel = active & ((xx + yy) % 2 == colour)
            ys, xs = yy[sel], xx[sel]
            best, br, bu, bv = cost[sel].copy(), rho[sel].copy(), gu[sel].copy(), gv[sel].copy()
            own = (br.copy(), bu.copy(), bv.copy())
            tried: list[tuple[np.ndarray, ...]] = []
            for dy, dx in NEIGHBOURS:
                ny, nx = ys + dy, xs + dx
                inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
                nyc, nxc = np.clip(ny, 0, h - 1), np.clip(nx, 0, w - 1)
                cu, cv = gu[nyc, nxc], gv[nyc, nxc]
                cr = rho[nyc, nxc] + cu * (xs - nxc) + cv * (ys - nyc)
                ok = inside & (cr >= rho_lo) & (cr <= rho_hi)
                ok &= ~(_same(cr, cu, cv, *own))  # the pixel's own plane
                for t_ok, t_r, t_u, t_v in tried:  # a neighbour's plane already tried
                    ok &= ~(t_ok & _same(cr, cu, cv, t_r, t_u, t_v))
                tried.append((ok, cr, cu, cv))
                c = np.full(len(ys), np.inf)
                c[ok] = plane_cost_reference(ref, src, A, b, ys[ok], xs[ok], cr[ok], cu[ok], cv[ok], radius, step)
                better = c < best
                best, br, bu, bv = _take(better, (c, cr, cu, cv), (best, br, bu, bv))
            pix = ys * w + xs
            for k in range(3):
                a = 1.0 if k == 0 else (0.0 if k == 1 else 0.25)
                m = 0.0 if k == 0 else (1.0 if k == 1 else 0.25)
                r1 = uniform_reference(seed, it * 2 + colour, pix, 3 * k)
                r2 = uniform_reference(seed, it * 2 + colour, pix, 3 * k + 1)
                r3 = uniform_reference(seed, it * 2 + colour, pix, 3 * k + 2)
                cr = np.clip(br * (1.0 + a * 0.2 * scale * (2.0 * r1 - 1.0)), rho_lo, rho_hi)
                su = np.clip(bu * f / br + m * 0.5 * slope_max * scale * (2.0 * r2 - 1.0), -slope_max, slope_max)
                sv = np.clip(bv * f / br + m * 0.5 * slope_max * scale * (2.0 * r3 - 1.0), -slope_max, slope_max)
                cu = su * cr / f
                cv = sv * cr / f
                c = plane_cost_reference(ref, src, A, b, ys, xs, cr, cu, cv, radius, step)
                better = c < best
                best, br, bu, bv = _take(better, (c, cr, cu, cv), (best, br, bu, bv))
            rho[sel], gu[sel], gv[sel], cost[sel] = br, bu, bv, best
