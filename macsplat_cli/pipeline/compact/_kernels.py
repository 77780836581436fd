"""Numba kernels of the compaction's view-against-view steps.

The occlusion step (:func:`.cleanup.prune_occluded`): each camera's z-buffer of the opaque centres, then, per Gaussian,
whether any camera sees it, its own camera tried first. The PyTorch twin (:func:`.cleanup.prune_occluded_reference`)
projects every view's Gaussians into every camera twice (the z-buffer, then the test) in float64 tensor passes: 6.8 s
of the 32-photo orbit's compaction, growing as photos × Gaussians. Here the z-buffers still take every opaque centre
into every camera, but the test stops at the first camera that sees a Gaussian: its own, nearly always. Same
arithmetic, point by point; the matrix products are summed in a fixed order (PyTorch's may round differently in the
last bit, so a centre exactly on a pixel edge or on the depth tolerance may fall the other way: the tests bound how
many).

The dedup step's test (:func:`.dedup._mergeable`): where a view's centres land in an earlier view and whether that
view's Gaussian there is the same surface, one pass instead of the twin's (:func:`.dedup._mergeable_reference`) ~20
tensor passes, with the same caveat.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..._kernel_cache import install as _cache_with_imports
from ..._threads import JitOptions

_cache_with_imports()  # before the first @njit: the cache follows the sources this module imports

__all__ = ["compile_kernels", "mergeable", "seen_rows", "zbuffers"]

_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}


@nb.njit(**_JIT, inline="always")
def _project(X, i, w2c, K, c, near_z):  # noqa: ANN001, ANN202
    """Centre ``X[i]`` into camera ``c``: (u, v, z) as :func:`~macsplat_cli.camera_math.project_points` computes them
    (``u``, ``v`` divided by 1 where ``z ≤ near_z``)."""
    x = X[i, 0] * w2c[c, 0, 0] + X[i, 1] * w2c[c, 0, 1] + X[i, 2] * w2c[c, 0, 2] + w2c[c, 0, 3]
    y = X[i, 0] * w2c[c, 1, 0] + X[i, 1] * w2c[c, 1, 1] + X[i, 2] * w2c[c, 1, 2] + w2c[c, 1, 3]
    z = X[i, 0] * w2c[c, 2, 0] + X[i, 1] * w2c[c, 2, 1] + X[i, 2] * w2c[c, 2, 2] + w2c[c, 2, 3]
    zs = z if z > near_z else 1.0
    u = (x * K[c, 0, 0] + y * K[c, 0, 1] + z * K[c, 0, 2]) / zs
    v = (x * K[c, 1, 0] + y * K[c, 1, 1] + z * K[c, 1, 2]) / zs
    return u, v, z


@nb.njit(**_JIT, inline="always")
def _inside(u, v, z, h, w, near_z):  # noqa: ANN001, ANN202
    return z > near_z and math.isfinite(u) and math.isfinite(v) and 0 <= u < w and 0 <= v < h


@nb.njit(**_JIT)
def zbuffers(start, stop, X, opaque, w2c, K, sizes, offsets, near_z, zbuf, pooled):  # noqa: ANN001, ANN201
    """For cameras ``start:stop``: ``zbuf`` the least depth of the opaque centres (``X`` [G, 3] float64 world,
    ``opaque`` [G] bool) landing in each pixel (inf where none), then ``pooled`` its largest over each pixel's 3 × 3
    neighbourhood (within the image). Both flat per camera from ``offsets`` [N] int64; cameras ``w2c`` [N, 4, 4],
    ``K`` [N, 3, 3] float64, ``sizes`` [N, 2] int64 (h, w)."""
    for c in range(start, stop):
        h, w = sizes[c, 0], sizes[c, 1]
        o = offsets[c]
        for p in range(h * w):
            zbuf[o + p] = np.inf
        for i in range(X.shape[0]):
            if not opaque[i]:
                continue
            u, v, z = _project(X, i, w2c, K, c, near_z)
            if _inside(u, v, z, h, w, near_z):
                p = o + min(int(math.floor(v)), h - 1) * w + min(int(math.floor(u)), w - 1)
                if z < zbuf[p]:
                    zbuf[p] = z
        for r in range(h):
            for q in range(w):
                m = -np.inf
                for rr in range(max(r - 1, 0), min(r + 2, h)):
                    for qq in range(max(q - 1, 0), min(q + 2, w)):
                        m = max(m, zbuf[o + rr * w + qq])
                pooled[o + r * w + q] = m


@nb.njit(**_JIT)
def seen_rows(start, stop, X, own, w2c, K, sizes, offsets, near_z, tol, pooled, out):  # noqa: ANN001, ANN201
    """For centres ``start:stop`` of ``X`` [G, 3]: ``out`` [G] bool is True where a camera sees the centre (inside
    its image, in front, and no farther than its pooled z-buffer ``pooled`` (:func:`zbuffers`) times ``1 + tol``),
    the centre's own camera ``own`` [G] int64 tried first."""
    n = w2c.shape[0]
    for i in range(start, stop):
        out[i] = False
        for t in range(n):
            c = own[i] if t == 0 else (t - 1 if t - 1 < own[i] else t)  # own first, then the others in order
            h, w = sizes[c, 0], sizes[c, 1]
            u, v, z = _project(X, i, w2c, K, c, near_z)
            if not _inside(u, v, z, h, w, near_z):
                continue
            p = offsets[c] + min(int(math.floor(v)), h - 1) * w + min(int(math.floor(u)), w - 1)
            if z <= pooled[p] * (1.0 + tol):
                out[i] = True
                break


@nb.njit(**_JIT)
def mergeable(start, stop, X, zk, w2c, K, h, w, zj, alive, near_z, depth_tol, fk, fj, finer, ok, pix, inside):  # noqa: ANN001, ANN201
    """For centres ``start:stop`` of view k's ``X`` [M, 3] float64 (world; their camera depths ``zk`` [M] float32):
    ``inside`` [M] bool whether each lands inside view j's image (camera ``w2c`` [1, 4, 4], ``K`` [1, 3, 3], ``h`` ×
    ``w`` pixels), ``pix`` [M] int64 the pixel (``row * w + col``; 0 outside), and ``ok`` [M] bool whether view j's
    Gaussian there is alive (``alive`` [h·w] bool), the same surface (its depth ``zj`` [h·w] float32 within
    ``depth_tol`` of the centre's) and sampled no more coarsely (``zk / fk · finer ≥ zj / fj``, ``fk``, ``fj`` the
    views' focal lengths)."""
    for i in range(start, stop):
        u, v, z = _project(X, i, w2c, K, 0, near_z)
        inside[i] = _inside(u, v, z, h, w, near_z)
        p = min(int(math.floor(v)), h - 1) * w + min(int(math.floor(u)), w - 1) if inside[i] else 0
        pix[i] = p
        d = np.float64(zj[p])
        ok[i] = (inside[i] and alive[p] and abs(d - z) <= depth_tol * abs(z)
                 and np.float64(zk[i]) / fk * finer >= d / fj)  # fmt: skip


def compile_kernels() -> None:
    """Compile (or load from the cache) the kernels for the types :mod:`.cleanup` and :mod:`.dedup` pass, on no points
    (no work)."""
    X, m4, m3 = np.zeros((0, 3)), np.zeros((1, 4, 4)), np.zeros((1, 3, 3))
    sizes, offsets, f, b = np.ones((1, 2), np.int64), np.zeros(1, np.int64), np.zeros(1), np.zeros(0, np.bool_)
    zbuffers(0, 0, X, np.zeros(0, np.bool_), m4, m3, sizes, offsets, 1e-6, f, f)
    seen_rows(0, 0, X, np.zeros(0, np.int64), m4, m3, sizes, offsets, 1e-6, 0.01, f, b)
    f32 = np.zeros(1, np.float32)
    mergeable(0, 0, X, f32[:0], m4, m3, 1, 1, f32, np.zeros(1, np.bool_), 1e-6, 0.02, 1.0, 1.0, 1.5, b,
              np.zeros(0, np.int64), b)  # fmt: skip
