"""Numba kernel of :func:`.sh_views.view_dependent`: per Gaussian of one photo's map, which photos see it and whether
two of them look at it from directions the spread apart, in one pass over the photos.

The PyTorch twin (:func:`.sh_views.view_dependent_reference`) builds photos × Gaussians masks and directions in
float64 and compares every pair of photos for the points the first direction leaves open: 7.5 s of the joint
refinement's set-up at 32 photos (full resolution), growing as photos × Gaussians. Same arithmetic here, point by
point; the matrix products are summed in a fixed order (PyTorch's may round differently in the last bit, so a point
exactly on a pixel edge or on the depth tolerance may fall the other way: the tests bound how many).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..._kernel_cache import install as _cache_with_imports
from ..._threads import JitOptions

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

__all__ = ["view_spread"]

_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}


@nb.njit(**_JIT)
def view_spread(start, stop, X, k, R, t, intr, sizes, offsets, depths, centres, min_views, depth_tol, cos_spread,
                half, out):  # noqa: ANN001, ANN201  # fmt: skip
    """For points ``start:stop`` of ``X`` [n, 3] float64 (map ``k``'s Gaussians in the world): ``out`` [n] bool is
    True where at least ``min_views`` photos see the point (photo ``k`` always; another when it projects inside it,
    in front, and its own depth at that pixel is within ``depth_tol`` of the point's) and two of them look at it from
    directions with a cosine at most ``cos_spread`` (``half``: the cosine of half that angle).

    Photos: ``R`` [N, 3, 3] and ``t`` [N, 3] camera-to-world, ``intr`` [N, 4] (fx, fy, cx, cy), ``sizes`` [N, 2]
    int64 (h, w), ``depths`` the maps' camera-frame depths flattened one after another from ``offsets`` [N] int64,
    ``centres`` [N, 3] (the cameras' centres).
    """
    N = R.shape[0]
    seen = np.zeros(N, np.bool_)
    dirs = np.zeros((N, 3))
    for i in range(start, stop):
        count = 0
        for j in range(N):
            if j == k:
                seen[j] = True
                count += 1
                continue
            seen[j] = False
            d0 = X[i, 0] - t[j, 0]
            d1 = X[i, 1] - t[j, 1]
            d2 = X[i, 2] - t[j, 2]
            z = d0 * R[j, 0, 2] + d1 * R[j, 1, 2] + d2 * R[j, 2, 2]
            if not z > 0:
                continue
            x = d0 * R[j, 0, 0] + d1 * R[j, 1, 0] + d2 * R[j, 2, 0]
            y = d0 * R[j, 0, 1] + d1 * R[j, 1, 1] + d2 * R[j, 2, 1]
            u = intr[j, 0] * x / z + intr[j, 2]
            v = intr[j, 1] * y / z + intr[j, 3]
            h, w = sizes[j, 0], sizes[j, 1]
            if not (math.isfinite(u) and math.isfinite(v) and 0 <= u < w and 0 <= v < h):
                continue
            col = min(int(math.floor(u)), w - 1)
            row = min(int(math.floor(v)), h - 1)
            zm = depths[offsets[j] + row * w + col]
            if abs(zm - z) <= depth_tol * abs(z):
                seen[j] = True
                count += 1
        if count < min_views:
            out[i] = False
            continue
        first = -1
        for j in range(N):
            a = X[i, 0] - centres[j, 0]
            b = X[i, 1] - centres[j, 1]
            c = X[i, 2] - centres[j, 2]
            norm = max(math.sqrt(a * a + b * b + c * c), 1e-12)
            dirs[j, 0] = a / norm
            dirs[j, 1] = b / norm
            dirs[j, 2] = c / norm
            if seen[j] and first < 0:
                first = j
        cos_ref = 1.0
        for j in range(N):
            if seen[j]:
                cos_ref = min(cos_ref, dirs[j, 0] * dirs[first, 0] + dirs[j, 1] * dirs[first, 1]
                              + dirs[j, 2] * dirs[first, 2])  # fmt: skip
        wide = cos_ref <= cos_spread
        if not wide and cos_ref <= half + 1e-9:  # the widest pair may still reach the spread: every pair
            widest = 1.0
            for a in range(N):
                if not seen[a]:
                    continue
                for b in range(a + 1, N):
                    if seen[b]:
                        widest = min(widest, dirs[a, 0] * dirs[b, 0] + dirs[a, 1] * dirs[b, 1]
                                     + dirs[a, 2] * dirs[b, 2])  # fmt: skip
            wide = widest <= cos_spread
        out[i] = wide


def compile_kernels() -> None:
    """Compile (or load from the cache) the kernel for the types :mod:`.sh_views` passes, on no points (no work)."""
    f3 = np.zeros((1, 3))
    view_spread(0, 0, np.zeros((0, 3)), 0, np.zeros((1, 3, 3)), f3, np.zeros((1, 4)), np.zeros((1, 2), np.int64),
                np.zeros(1, np.int64), np.zeros(1), f3, 3, 0.03, 0.9, 0.97, np.zeros(0, np.bool_))  # fmt: skip
