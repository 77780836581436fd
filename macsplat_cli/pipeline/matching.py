"""Filtered matching, as MAC-Splat defines it.

1. Reciprocal nearest neighbours under cosine distance: ``i ↔ j`` is kept when
   ``j = argmin_k D(f0_i, f1_k)`` and ``i = argmin_k D(f1_j, f0_k)``.
2. Joint confidence ``w = c0_i · c1_j``; matches with ``w ≤ τ`` are dropped.
3. Geometric verification (robust essential matrix) happens in :mod:`.pose`.

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

__all__ = ["MatchConfig", "match_features", "reciprocal_nearest_neighbours"]

logger = logging.getLogger(__name__)


@dataclass
class MatchConfig:
    """Args:
    conf_threshold: τ; matches with joint confidence ``c0·c1 ≤ τ`` are dropped.
    max_block_elems: most similarities held in memory at once.
    """

    conf_threshold: float = 0.0
    max_block_elems: int = 1 << 24


def reciprocal_nearest_neighbours(
    desc0: np.ndarray,  # [M0, D]
    desc1: np.ndarray,  # [M1, D]
    *,
    max_block_elems: int = 1 << 24,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by cosine similarity of L2-normalised descriptors.

    Args:
        desc0: descriptors of view 0. [M0, D]
        desc1: descriptors of view 1. [M1, D]
        max_block_elems: block size bound (rows × M1).

    Returns:
        ``(idx0, idx1, sim)``: indices of the mutual pairs, sorted by ``idx0``, and their
        cosine similarity. [K] int64, [K] int64, [K] float32
    """
    m0, m1 = desc0.shape[0], desc1.shape[0]
    if m0 == 0 or m1 == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
    a = torch.from_numpy(np.ascontiguousarray(desc0, dtype=np.float32))
    b = torch.from_numpy(np.ascontiguousarray(desc1, dtype=np.float32))
    rows = max(1, max_block_elems // m1)
    best1 = torch.empty(m0, dtype=torch.int64)  # for each i: argmax_j
    best1_sim = torch.empty(m0)
    col_best = torch.full((m1,), -2.0)  # for each j: max_i and argmax_i
    col_arg = torch.zeros(m1, dtype=torch.int64)
    bt = b.T.contiguous()
    for start in range(0, m0, rows):
        sim = a[start : start + rows] @ bt  # [rows, M1]
        v, j = sim.max(dim=1)
        best1[start : start + rows] = j
        best1_sim[start : start + rows] = v
        cv, ci = sim.max(dim=0)
        better = cv > col_best  # strict: ties keep the first row, like argmax over all rows
        col_best = torch.where(better, cv, col_best)
        col_arg = torch.where(better, ci + start, col_arg)
    i = torch.arange(m0)
    mutual = col_arg[best1] == i
    idx0 = i[mutual].numpy()
    idx1 = best1[mutual].numpy()
    return idx0, idx1, best1_sim[mutual].numpy()


def match_features(f0: Features, f1: Features, config: MatchConfig | None = None) -> Matches:
    """Reciprocal nearest neighbours, then the joint-confidence gate ``c0·c1 > τ``.

    Returns:
        :class:`Matches` with ``counts`` holding ``reciprocal`` and ``confident``.
    """
    cfg = config or MatchConfig()
    idx0, idx1, _ = reciprocal_nearest_neighbours(f0.desc, f1.desc, max_block_elems=cfg.max_block_elems)
    w = (f0.conf[idx0] * f1.conf[idx1]).astype(np.float32)
    m = Matches(f0.xy[idx0], f1.xy[idx1], w, idx0, idx1, counts={"reciprocal": len(idx0)})
    out = m.subset(w > cfg.conf_threshold, "confident")
    logger.debug("matching: %d reciprocal, %d with c0*c1 > %g", len(m), len(out), cfg.conf_threshold)
    return out
