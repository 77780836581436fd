"""Tracks: the keypoints of several photos that the verified pair matches connect, one 3D point each.

Each photo's keypoints are those of the descriptor tier its pairs used (a pair's features are cached per photo and
tier, so two pairs of the same tier share keypoint indices). Matches are edges; a connected component is a track.
A component holding two keypoints of the same photo is inconsistent there: that photo's observations leave it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .pairwise import PairOutcome

__all__ = ["Tracks", "build_tracks"]


@dataclass
class Tracks:
    """Observations of the tracks, one row each.

    Attributes:
        view: the photo of each observation. [O] int64
        track: its track. [O] int64 in ``0..n_tracks-1``
        xy: its pixel (working resolution). [O, 2] float64
        n_tracks: the number of tracks (each seen by ≥ 2 photos).
        conflicts: observations dropped because their track held another keypoint of the same photo.
    """

    view: np.ndarray
    track: np.ndarray
    xy: np.ndarray
    n_tracks: int
    conflicts: int = 0

    def __len__(self) -> int:
        return int(self.view.shape[0])

    def subset(self, keep: np.ndarray) -> Tracks:
        """The observations selected by ``keep`` ([O] bool), tracks not renumbered."""
        return Tracks(self.view[keep], self.track[keep], self.xy[keep], self.n_tracks, self.conflicts)


def build_tracks(outcomes: Sequence[PairOutcome]) -> Tracks:
    """The tracks of the accepted pairs' verified matches (module docstring)."""
    nodes: dict[tuple[int, int], tuple[int, np.ndarray]] = {}  # (photo, id(features)) → (offset, xy)
    total = 0
    edges0, edges1 = [], []

    def offset(view: int, xy: np.ndarray, key: int) -> int:
        nonlocal total
        if (view, key) not in nodes:
            nodes[(view, key)] = (total, xy)
            total += len(xy)
        return nodes[(view, key)][0]

    for o in outcomes:
        if o.result is None:
            continue
        f0, f1 = o.result.features
        m = o.result.geometry.inliers
        a = offset(o.i, f0.xy, id(f0))
        b = offset(o.j, f1.xy, id(f1))
        edges0.append(a + m.idx0)
        edges1.append(b + m.idx1)
    if not edges0:
        return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), 0)
    e0, e1 = np.concatenate(edges0), np.concatenate(edges1)
    from scipy.sparse import coo_matrix  # here, not at the top: two-photo runs never load scipy
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(e0), np.int8), (e0, e1)), shape=(total, total))
    _, label = connected_components(graph, directed=False)
    view = np.empty(total, np.int64)
    xy = np.empty((total, 2))
    for (photo, _key), (start, pts) in nodes.items():
        view[start : start + len(pts)] = photo
        xy[start : start + len(pts)] = pts
    used = np.zeros(total, bool)
    used[e0] = used[e1] = True
    node = np.flatnonzero(used)
    comp, v = label[node], view[node]
    # a photo with two keypoints in one component: drop that photo's observations of it
    key = comp * (int(view.max()) + 1) + v
    uniq, counts = np.unique(key, return_counts=True)
    bad = np.isin(key, uniq[counts > 1])
    node, comp, v = node[~bad], comp[~bad], v[~bad]
    # components still seen by ≥ 2 photos become the tracks, numbered 0..n-1
    ids, inverse, size = np.unique(comp, return_inverse=True, return_counts=True)
    keep = size[inverse] >= 2
    _, track = np.unique(inverse[keep], return_inverse=True)
    return Tracks(v[keep], track.astype(np.int64), xy[node[keep]], int(track.max()) + 1 if keep.any() else 0,
                  int(bad.sum()))  # fmt: skip
