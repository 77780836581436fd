"""Numba kernel of :func:`.covis.covisibility_init`: per Gaussian of one photo, whether another photo observes the
same surface point better, the other photos tried nearest first and the first that does ending the search.

The PyTorch twin (:func:`.covis.covisibility_init_reference`) runs one photo against another as ~25 float64 tensor
passes over the Gaussians still kept (~100 ns a test): a kept Gaussian meets every other photo, so the init grew as
kept Gaussians × photos (6.2 CPU s at 32 photos of the orbit). Same arithmetic here, point by point; the matrix
product is summed in a fixed order (PyTorch's may round differently in the last bit, so a point exactly on a pixel
edge or on the depth or score tolerance may fall the other way: the tests bound how many).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..._kernel_cache import install as _cache_with_imports
from ..._threads import JitOptions

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

__all__ = ["compile_kernels", "kept"]

_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}


@nb.njit(**_JIT)
def kept(start, stop, idx, k, order, world, valid, score, depth, offsets, R, c, intr, sizes, depth_tol, tie,
         out):  # noqa: ANN001, ANN201  # fmt: skip
    """For photo ``k``'s pixels ``idx[start:stop]`` ([n] int64, its valid ones): ``out`` [n] bool is False where a
    photo of ``order`` ([N − 1] int64, nearest first) sees the pixel's Gaussian on the same surface point (it
    projects inside the photo, in front, onto a valid pixel whose depth is within ``depth_tol`` of its own) with a
    better score (more than ``1 + tie`` times; an earlier photo from ``1 − tie`` times on), else True.

    Photos, one after another from ``offsets`` [N] int64 in the flat per-pixel arrays: ``world`` [P, 3] float64 the
    world points, ``valid`` [P] bool, ``score`` [P] float64, ``depth`` [P] float64 camera depths; ``R`` [N, 3, 3]
    and ``c`` [N, 3] each camera's rotation and centre (camera-to-world), ``intr`` [N, 4] (fx, fy, cx, cy),
    ``sizes`` [N, 2] int64 (h, w).
    """
    left = np.arange(start, stop)  # the chunk's Gaussians still kept, photo by photo (each photo's lookups local)
    n = len(left)
    for j in order:
        if n == 0:
            break
        h, w = sizes[j, 0], sizes[j, 1]
        m = 0
        for t in range(n):
            i = left[t]
            p = offsets[k] + idx[i]
            d0 = world[p, 0] - c[j, 0]
            d1 = world[p, 1] - c[j, 1]
            d2 = world[p, 2] - c[j, 2]
            z = d0 * R[j, 0, 2] + d1 * R[j, 1, 2] + d2 * R[j, 2, 2]
            x = d0 * R[j, 0, 0] + d1 * R[j, 1, 0] + d2 * R[j, 2, 0]
            y = d0 * R[j, 0, 1] + d1 * R[j, 1, 1] + d2 * R[j, 2, 1]
            u = intr[j, 0] * x / z + intr[j, 2]
            v = intr[j, 1] * y / z + intr[j, 3]
            beaten = False
            if z > 0 and u >= 0 and u < w and v >= 0 and v < h:  # NaN and ±inf fail a comparison
                q = offsets[j] + min(int(v), h - 1) * w + min(int(u), w - 1)  # non-negative: truncation is the floor
                if valid[q] and abs(depth[q] - z) <= depth_tol * abs(z):
                    sj, sk = score[q], score[p]
                    beaten = sj > sk * (1 + tie) or (j < k and sj >= sk * (1 - tie))
            if not beaten:
                left[m] = i
                m += 1
        n = m
    for i in range(start, stop):
        out[i] = False
    for t in range(n):
        out[left[t]] = True


def compile_kernels() -> None:
    """Compile (or load from the cache) the kernel for the types :mod:`.covis` passes, on no points (no work)."""
    f = np.zeros(1)
    kept(0, 0, np.zeros(0, np.int64), 0, np.zeros(0, np.int64), np.zeros((1, 3)), np.zeros(1, np.bool_), f, f,
         np.zeros(1, np.int64), np.zeros((1, 3, 3)), np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 2), np.int64),
         0.02, 1e-3, np.zeros(0, np.bool_))  # fmt: skip
