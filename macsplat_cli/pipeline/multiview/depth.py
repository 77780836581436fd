"""Dense depth of every registered photo from its best neighbours.

Each photo's neighbours are the registered photos it shares the most tracks with. Every neighbour pair runs the
two-view depth stage (plane sweep, SGM, PatchMatch, checks: :mod:`..depth`) in the pair's own frame (baseline 1),
brought to the global scale; a photo's estimates from its pairs are then fused per pixel: the most confident
estimate, averaged with those that agree with it, its confidence lowered where another estimate contradicts it.
Last, each photo's depth loses the pixels another photo sees through and none confirms (:func:`free_space_check`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np

from ..._threads import kernel_threads
from ..types import DepthMap, Matches, TwoViewGeometry, View
from .register import Registration

__all__ = ["depth_pairs", "free_space_check", "fuse_estimates", "multiview_depths", "pair_geometry", "photo_map"]

logger = logging.getLogger(__name__)

SIDE_BY_SIDE_MAX = 4
"""At most this many items of :func:`photo_map` at once, whatever the cores: each depth pair holds its cost volumes
while it runs, and on 2 cores (what the targets are measured on) two already fill them."""

A = TypeVar("A")
B = TypeVar("B")


NEIGHBOURS = 2
"""Each photo's depth comes from this many neighbours (more: fewer holes and outliers, one depth pair's time each)."""
MIN_SHARED = 30
"""A neighbour shares at least this many tracks with the photo (fewer cannot bound the depth range)."""
AGREE = 0.03
"""Two estimates of a pixel agree within this relative depth difference."""
CONTRADICTED = 0.5
"""Confidence factor of a pixel another estimate contradicts."""
CHECK_VIEWS = 4
"""Each photo's fused depth is checked against this many co-visible photos' depths (0: no check)."""
FREE_SPACE = 0.05
"""A point this much (relative) in front of what another photo sees there lies in space that photo sees through: a
floater, dropped when no checked photo confirms it (measured: benchmarks/history/multiview.md)."""


def _shared(reg: Registration) -> np.ndarray:
    """Tracks each two registered photos both observe (kept points only). [N, N] int"""
    n = len(reg.registered)
    tr = reg.tracks
    sel = reg.point_ok[tr.track] & reg.registered[tr.view]
    A = np.zeros((tr.n_tracks, n), bool)
    A[tr.track[sel], tr.view[sel]] = True
    A = A.astype(np.int32)
    S = A.T @ A
    np.fill_diagonal(S, 0)
    return S


def depth_pairs(reg: Registration) -> list[tuple[int, int]]:
    """The pairs whose two-view depth runs: each registered photo with its ``neighbours`` most co-visible
    registered photos (pairs as (a, b), a < b, unique)."""
    S = _shared(reg)
    pairs: set[tuple[int, int]] = set()
    for k in np.flatnonzero(reg.registered).tolist():
        order = np.argsort(-S[k], kind="stable")
        for o in order[:NEIGHBOURS]:
            if S[k, o] >= MIN_SHARED and reg.registered[o]:
                pairs.add((min(k, int(o)), max(k, int(o))))
    return sorted(pairs)


def pair_geometry(reg: Registration, a: int, b: int) -> tuple[TwoViewGeometry, float]:
    """Photos ``a`` and ``b`` as a two-view geometry in ``a``'s frame (``|t| = 1``), and the baseline in the
    global unit; the inliers are their shared tracks' observations (which bound the depth range)."""
    R = reg.R[b] @ reg.R[a].T
    t = reg.t[b] - R @ reg.t[a]
    base = float(np.linalg.norm(t))
    tr = reg.tracks
    ok = reg.point_ok[tr.track]
    xy = np.full((2, tr.n_tracks, 2), np.nan)
    for s, v in enumerate((a, b)):
        sel = ok & (tr.view == v)
        xy[s, tr.track[sel]] = tr.xy[sel]
    both = np.flatnonzero(np.isfinite(xy[0, :, 0]) & np.isfinite(xy[1, :, 0]))
    m = Matches(xy[0, both], xy[1, both], np.ones(len(both), np.float32), both, both, {"shared tracks": len(both)})
    return TwoViewGeometry(R, t / base, reg.K[a], reg.K[b], m), base


def fuse_estimates(estimates: Sequence[DepthMap]) -> DepthMap:
    """One photo's depth estimates from several neighbours → one (module docstring). All [H, W]."""
    if len(estimates) == 1:
        return estimates[0]
    D = np.stack([e.depth for e in estimates]).astype(np.float64)
    C = np.stack([np.where(e.valid, e.confidence, 0.0) for e in estimates]).astype(np.float64)
    M = np.stack([e.measured if e.measured is not None else e.valid for e in estimates])
    best = np.argmax(C, axis=0)
    d0 = np.take_along_axis(D, best[None], 0)[0]
    c0 = np.take_along_axis(C, best[None], 0)[0]
    valid = c0 > 0
    close = (C > 0) & (np.abs(D - d0) <= AGREE * np.maximum(d0, 1e-12))
    against = (C > 0) & ~close
    w = np.where(close, C, 0.0)
    depth = np.where(valid, (w * D).sum(0) / np.maximum(w.sum(0), 1e-12), 0.0)
    conf = np.where(against.any(0), c0 * CONTRADICTED, c0)
    measured = (M & close).any(0) & valid
    return DepthMap(depth.astype(np.float32), np.where(valid, conf, 0.0).astype(np.float32), measured)


DepthFn = Callable[[list[View], TwoViewGeometry], list[DepthMap]]
"""The two-view depth stage: ``(views, geometry) → [DepthMap] ×2`` (baseline-1 units)."""


def photo_map(fn: Callable[[A], B], items: Iterable[A]) -> list[B]:
    """``[fn(x) for x in items]``, the items side by side in :func:`~..._threads.kernel_threads` threads (in order,
    the same results): the per-pair and per-photo steps are independent, and much of each is NumPy, OpenCV or a
    ``nogil`` kernel that release the GIL, so a second core runs what one pair's own threads leave idle."""
    items = list(items)
    workers = min(len(items), kernel_threads(), SIDE_BY_SIDE_MAX)
    if workers < 2:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="multiview") as pool:
        return list(pool.map(fn, items))


def multiview_depths(
    views: Sequence[View], reg: Registration, two_view: DepthFn
) -> tuple[list[DepthMap | None], list[tuple[int, int]]]:
    """Every registered photo's fused depth (None for the others, and for a photo no depth pair reached), and the
    depth pairs that ran."""
    pairs = depth_pairs(reg)

    def pair_depths(ab: tuple[int, int]) -> list[DepthMap]:
        a, b = ab
        g, base = pair_geometry(reg, a, b)
        logger.debug("depth pair %s–%s: baseline %.3f", views[a].name, views[b].name, base)
        estimates = two_view([views[a], views[b]], g)
        return [DepthMap(d.depth * np.float32(base), d.confidence, d.measured) for d in estimates]

    found: dict[int, list[DepthMap]] = {}
    for (a, b), (da, db) in zip(pairs, photo_map(pair_depths, pairs)):
        found.setdefault(a, []).append(da)
        found.setdefault(b, []).append(db)
    fused: list[DepthMap | None] = [fuse_estimates(found[k]) if k in found else None for k in range(len(views))]
    if CHECK_VIEWS <= 0:
        return fused, pairs
    shared = _shared(reg)
    return photo_map(lambda k: _free_space_checked(k, fused, reg, shared[k]), range(len(fused))), pairs


def _free_space_checked(k: int, depths: list[DepthMap | None], reg: Registration, S: np.ndarray) -> DepthMap | None:
    """Photo ``k``'s depth checked (:func:`free_space_check`) against its most co-visible photos with a depth (``S``:
    the tracks it shares with each photo [N])."""
    d = depths[k]
    if d is None:
        return None
    others = [int(j) for j in np.argsort(-S, kind="stable") if j != k and depths[j] is not None and S[j] > 0]
    return free_space_check(k, depths, reg.K, reg.R, reg.t, others[:CHECK_VIEWS])


def free_space_check(
    k: int, depths: Sequence[DepthMap | None], K: np.ndarray, R: np.ndarray, t: np.ndarray, others: Sequence[int]
) -> DepthMap:
    """Photo ``k``'s depth less the pixels that one of the ``others`` sees through (its depth there farther by
    :data:`FREE_SPACE`) and none confirms (within :data:`AGREE`): floaters. ``K``, ``R``, ``t``: every photo's
    intrinsics and world → camera pose ([N, 3, 3], [N, 3, 3], [N, 3])."""
    d = depths[k]
    assert d is not None
    ys, xs = np.nonzero(d.valid)
    if not others or ys.size == 0:
        return d
    z = d.depth[ys, xs].astype(np.float64)
    rays = np.stack([xs + 0.5, ys + 0.5, np.ones_like(z)], 1) @ np.linalg.inv(K[k]).T
    X = (rays * z[:, None] - t[k]) @ R[k]  # world: Rᵀ (X_cam − t)
    support = np.zeros(z.size, bool)
    through = np.zeros(z.size, bool)
    for j in others:
        dj = depths[j]
        assert dj is not None
        Xj = X @ R[j].T + t[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = Xj @ K[j].T
            u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        h, w = dj.depth.shape
        inside = (Xj[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui, vi = (
            np.clip(np.nan_to_num(u), 0, w - 1).astype(np.int64),
            np.clip(np.nan_to_num(v), 0, h - 1).astype(np.int64),
        )
        seen = inside & dj.valid[vi, ui]
        there = dj.depth[vi, ui]
        rel = (Xj[:, 2] - there) / np.maximum(there, 1e-12)
        support |= seen & (np.abs(rel) <= AGREE)
        through |= seen & (rel < -FREE_SPACE)
    drop = through & ~support
    if not drop.any():
        return d
    depth, conf = d.depth.copy(), d.confidence.copy()
    depth[ys[drop], xs[drop]] = 0.0
    conf[ys[drop], xs[drop]] = 0.0
    measured = None if d.measured is None else d.measured & (depth > 0)
    logger.debug("free-space check: %d of %d pixels dropped", int(drop.sum()), z.size)
    return DepthMap(depth, conf, measured)
