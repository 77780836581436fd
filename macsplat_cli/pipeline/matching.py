"""Filtered matching, as MAC-Splat defines it.

1. Reciprocal nearest neighbours under cosine distance: ``i ↔ j`` is kept when
   ``j = argmin_k D(f0_i, f1_k)`` and ``i = argmin_k D(f1_j, f0_k)``.
2. Joint confidence ``w = c0_i · c1_j``; matches with ``w ≤ τ`` are dropped.
3. Geometric verification (robust essential matrix) happens in :mod:`.pose`.

Descriptor confidence. Learned backends (MASt3R) predict ``c`` per pixel. Classical
descriptors have none, so with ``ratio_confidence`` each descriptor's confidence is its
distinctiveness *against the other view*: ``c = 1 − d1 / d2``, with ``d1``, ``d2`` the
distances to its nearest and second-nearest descriptor there (Lowe's ratio). Measured on
real pairs, this correlates with a match being correct (Spearman 0.69) where keypoint
response (0.12) and in-image distinctiveness (−0.01) do not; the gate ``c0·c1 > τ`` then
acts as a symmetric ratio test (τ = 0.04 ≈ ratio 0.8 on both sides).

The similarity matrix is never materialised: rows are processed in blocks sized so that
one block holds at most ``max_block_elems`` similarities, keeping memory bounded for
dense descriptor maps as well as keypoints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from .types import Features, Matches

__all__ = [
    "compile_kernels",
    "MatchConfig",
    "NearestNeighbours",
    "guided_matches",
    "match_features",
    "ratio_distinctiveness",
    "reciprocal_nearest_neighbours",
    "seeded_reciprocal_neighbours",
]

logger = logging.getLogger(__name__)


@dataclass
class MatchConfig:
    """Args:
    conf_threshold: τ; matches with joint confidence ``c0·c1 ≤ τ`` are dropped.
    ratio_confidence: multiply each descriptor's confidence by ``1 − d1/d2`` against the
        other view (for backends without a learned confidence).
    max_block_elems: most similarities held in memory at once.
    """

    conf_threshold: float = 0.04
    ratio_confidence: bool = True
    max_block_elems: int = 1 << 24


@dataclass
class NearestNeighbours:
    """Mutual nearest neighbours and, per descriptor, its top-2 similarities in the other view.

    Attributes:
        idx0: view-0 index of each mutual pair. [K] int64
        idx1: view-1 index of each mutual pair. [K] int64
        sim: cosine similarity of each pair. [K] float32
        top2_0: best and second-best similarity of every view-0 descriptor. [M0, 2]
        top2_1: the same for every view-1 descriptor. [M1, 2]
    """

    idx0: np.ndarray
    idx1: np.ndarray
    sim: np.ndarray
    top2_0: np.ndarray
    top2_1: np.ndarray


def reciprocal_nearest_neighbours(
    desc0: np.ndarray,  # [M0, D]
    desc1: np.ndarray,  # [M1, D]
    *,
    max_block_elems: int = 1 << 24,
) -> NearestNeighbours:
    """Mutual nearest neighbours by cosine similarity of L2-normalised descriptors.

    Rows of the similarity matrix are computed in blocks; column maxima are carried
    across blocks, so memory is ``O(max_block_elems + M0 + M1)``.
    """
    m0, m1 = desc0.shape[0], desc1.shape[0]
    empty = np.zeros(0, np.int64)
    if m0 == 0 or m1 == 0:
        return NearestNeighbours(empty, empty, np.zeros(0, np.float32), np.zeros((m0, 2)), np.zeros((m1, 2)))
    from . import _match_kernels  # Numba on first use (engine: the kernels load beside the first stages)

    a = torch.from_numpy(np.ascontiguousarray(desc0, dtype=np.float32))
    bt = torch.from_numpy(np.ascontiguousarray(desc1, dtype=np.float32)).T.contiguous()
    rows = max(1, max_block_elems // m1)
    k = min(2, m1)
    row_top = torch.full((m0, 2), -1.0)  # a missing second best counts as the farthest, −1
    row_arg = torch.zeros(m0, dtype=torch.int64)
    col_top = torch.full((2, m1), -1.0)  # best and second-best similarity per column
    col_arg = torch.zeros(m1, dtype=torch.int64)
    for start in range(0, m0, rows):
        sim = a[start : start + rows] @ bt  # [rows, M1]
        v, j = sim.topk(k, dim=1)
        row_top[start : start + rows, :k] = v
        row_arg[start : start + rows] = j[:, 0]
        # strict: earlier rows win ties, like a global argmax
        _match_kernels.column_top2_update(sim.numpy(), start, col_top.numpy(), col_arg.numpy())
    i = torch.arange(m0)
    mutual = col_arg[row_arg] == i
    return NearestNeighbours(
        idx0=i[mutual].numpy(),
        idx1=row_arg[mutual].numpy(),
        sim=row_top[mutual, 0].numpy(),
        top2_0=row_top.numpy(),
        top2_1=col_top.T.numpy(),
    )


def _nearest(queries: torch.Tensor, database: torch.Tensor, max_block_elems: int) -> torch.Tensor:
    """Index of each query's most similar database row (the first of equals), in blocks of queries. [Q] int64"""
    out = torch.empty(queries.shape[0], dtype=torch.int64, device=queries.device)
    rows = max(1, max_block_elems // max(1, database.shape[0]))
    for start in range(0, queries.shape[0], rows):
        out[start : start + rows] = (queries[start : start + rows] @ database.T).argmax(dim=1)
    return out


@torch.no_grad()
def seeded_reciprocal_neighbours(
    desc0: torch.Tensor,  # [N0, D]
    desc1: torch.Tensor,  # [N1, D]
    seeds: torch.Tensor,  # [S]
    *,
    max_iters: int = 10,
    max_block_elems: int = 1 << 24,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reciprocal nearest neighbours over *every* descriptor of both views, found from seeds in view 0 (the
    MAC-Splat release's matcher, after MASt3R's): each seed ``x`` goes to its nearest neighbour ``y`` in view 1 and
    back to ``x'``, the nearest of ``y`` in view 0; ``x' = x`` is a reciprocal pair, else the walk goes on from ``x'``
    (at most ``max_iters`` rounds; the similarity never falls along a walk, and walks that meet merge). Unlike
    :func:`reciprocal_nearest_neighbours` on a subsampled grid, a match can land on any pixel of either view.

    Args:
        desc0: view 0's descriptors (unit length: cosine similarity = dot product). [N0, D]
        desc1: view 1's. [N1, D]
        seeds: view-0 indices to start from. [S] int64

    Returns:
        ``(idx0 [K], idx1 [K])`` int64, the distinct reciprocal pairs reached, sorted by ``idx0``.
    """
    x = torch.unique(seeds.to(desc0.device))
    found = torch.zeros(0, dtype=torch.int64, device=desc0.device)
    n1 = desc1.shape[0]
    for _ in range(max_iters):
        if not len(x):
            break
        y = _nearest(desc0[x], desc1, max_block_elems)
        back = _nearest(desc1[y], desc0, max_block_elems)
        done = back == x
        found = torch.cat([found, x[done] * n1 + y[done]])
        x = torch.unique(back[~done])
    pairs = torch.unique(found)
    return pairs // n1, pairs % n1


def ratio_distinctiveness(top2: np.ndarray) -> np.ndarray:
    """``1 − d1/d2`` from the best two cosine similarities (L2 distance of unit vectors). [M]"""
    d = np.sqrt(np.maximum(2.0 - 2.0 * top2.astype(np.float64), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(d[:, 1] > 1e-12, d[:, 0] / d[:, 1], 1.0)
    return np.clip(1.0 - r, 0.0, 1.0).astype(np.float32)


def match_features(f0: Features, f1: Features, config: MatchConfig | None = None) -> Matches:
    """Reciprocal nearest neighbours, then the joint-confidence gate ``c0·c1 > τ``.

    Returns:
        :class:`Matches` with ``counts`` holding ``reciprocal`` and ``confident``; its ``below_gate`` holds the
        reciprocal matches that failed the gate (for the pose stage's planar disambiguation, not counted).
    """
    cfg = config or MatchConfig()
    nn = reciprocal_nearest_neighbours(f0.desc, f1.desc, max_block_elems=cfg.max_block_elems)
    c0, c1 = f0.conf, f1.conf
    if cfg.ratio_confidence:
        c0 = c0 * ratio_distinctiveness(nn.top2_0)
        c1 = c1 * ratio_distinctiveness(nn.top2_1)
    w = (c0[nn.idx0] * c1[nn.idx1]).astype(np.float32)
    m = Matches(f0.xy[nn.idx0], f1.xy[nn.idx1], w, nn.idx0, nn.idx1, counts={"reciprocal": len(nn.idx0)})
    keep = w > cfg.conf_threshold
    out = m.subset(keep, "confident")
    out.below_gate = m.subset(~keep)
    logger.debug("matching: %d reciprocal, %d with c0*c1 > %g", len(m), len(out), cfg.conf_threshold)
    return out


def guided_matches(
    f0: Features,
    f1: Features,
    F: np.ndarray,  # [3, 3]
    *,
    band_px: float = 2.0,
    ratio: float = 0.95,
    max_block_elems: int = 1 << 24,
) -> Matches:
    """Epipolar-guided matching: mutual best descriptor among candidates near the epipolar line.

    With a first estimate of the geometry, a keypoint's match can only lie within
    ``band_px`` of its epipolar line, which removes most of the competitors that make
    descriptors ambiguous on repetitive or low-texture surfaces. A pair is kept when it is
    mutually best within the band and its L2 descriptor distance is below ``ratio`` times
    that of the second-best candidate in the band (in both directions).

    Returns:
        :class:`Matches` (confidence ``1 − ratio`` product), ``counts["guided"]``.
    """
    n0, n1 = len(f0), len(f1)
    if n0 == 0 or n1 == 0:
        e = np.zeros(0, np.int64)
        return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.float32), e, e, {"guided": 0})
    from . import _match_kernels  # Numba on first use (engine: the kernels load beside the first stages)

    a = torch.from_numpy(np.ascontiguousarray(f0.desc, np.float32))
    bt = torch.from_numpy(np.ascontiguousarray(f1.desc, np.float32)).T.contiguous()
    p0 = np.concatenate([f0.xy, np.ones((n0, 1))], 1)
    lines = p0 @ np.asarray(F, np.float64).T  # epipolar lines in view 1 of view-0 points. [N0, 3]
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-12)
    # float32 is exact enough here: unit normals and coordinates ≤ a few thousand px
    lines1 = torch.from_numpy(np.ascontiguousarray(lines, np.float32))
    p1 = torch.from_numpy(np.ascontiguousarray(np.concatenate([f1.xy, np.ones((n1, 1))], 1), np.float32))
    p1t = p1.T.contiguous()
    neg = -4.0
    rows = max(1, max_block_elems // n1)
    row_top = torch.full((n0, 2), neg, dtype=torch.float32)
    row_arg = torch.zeros(n0, dtype=torch.int64)
    col_top = torch.full((2, n1), neg, dtype=torch.float32)
    col_arg = torch.zeros(n1, dtype=torch.int64)
    for start in range(0, n0, rows):
        sim = a[start : start + rows] @ bt
        dist = lines1[start : start + rows] @ p1t  # signed point-to-line distance in view 1
        # in place, no second block: outside the band (or NaN) gets ``neg``
        sim.masked_fill_(~((dist <= band_px) & (dist >= -band_px)), neg)
        k = min(2, n1)
        v, j = sim.topk(k, dim=1)
        row_top[start : start + rows, :k] = v
        row_arg[start : start + rows] = j[:, 0]
        _match_kernels.column_top2_update(sim.numpy(), start, col_top.numpy(), col_arg.numpy())
    i = torch.arange(n0)
    ok = (col_arg[row_arg] == i) & (row_top[:, 0] > neg)
    idx0 = i[ok].numpy()
    idx1 = row_arg[ok].numpy()
    c0 = ratio_distinctiveness(row_top.numpy().clip(-1.0, 1.0))[idx0]
    c1 = ratio_distinctiveness(col_top.T.numpy().clip(-1.0, 1.0))[idx1]
    keep = (c0 > 1.0 - ratio) & (c1 > 1.0 - ratio)
    idx0, idx1 = idx0[keep], idx1[keep]
    w = (c0[keep] * c1[keep]).astype(np.float32)
    return Matches(f0.xy[idx0], f1.xy[idx1], w, idx0, idx1, counts={"guided": len(idx0)})


def compile_kernels() -> None:
    """Compile the stage's Numba kernel now (or load it from the cache): for a background thread."""
    from . import _match_kernels

    _match_kernels.compile_kernels()
