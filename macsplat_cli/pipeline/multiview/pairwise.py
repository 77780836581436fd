"""The two-view geometry of every selected pair, each through the same search and acceptance as two photos.

Descriptors are computed once per photo and tier (:class:`CachedDescriptors`); a pair whose pose the acceptance
refuses is dropped with its reason, never fatal.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ...errors import ReconstructionError
from ..learned import LearnedTier
from ..pose import PoseResult, PoseSearch
from ..pose.focal import FOCAL_DOUBT_START
from ..slots import DescribeStage, PairPass
from ..types import Features, TwoViewGeometry, View

__all__ = [
    "CachedDescriptors", "PairOutcome", "cached_search", "focal_doubts_only", "match_all", "match_pairs",
    "primary_only",
]  # fmt: skip

logger = logging.getLogger(__name__)


class CachedDescriptors:
    """A ``describe`` slot that computes each view's features once (keyed by the view object), whatever the pair.

    Only for per-view backends (``PerViewDescriptors``): a pairwise backend's features depend on the pair.
    """

    def __init__(self, stage: DescribeStage) -> None:
        self.stage = stage
        self.name = getattr(stage, "name", type(stage).__name__)
        self._cache: dict[int, tuple[View, Features]] = {}
        self._lock = threading.Lock()

    def __call__(self, views: Sequence[View], pair: PairPass = None) -> list[Features]:
        missing = [v for v in views if id(v) not in self._cache]
        if missing:
            for v, f in zip(missing, self.stage(missing, pair)):
                with self._lock:
                    self._cache[id(v)] = (v, f)  # the view is kept: its id stays unique while cached
        return [self._cache[id(v)][1] for v in views]


def cached_search(search: PoseSearch, *, accept_low_confidence: bool = False) -> PoseSearch:
    """A copy of ``search`` whose descriptor tiers are cached per view (``accept_low_confidence``: keep a doubted
    pose, its doubts listed, for the caller to judge)."""
    cfg = search.config
    if accept_low_confidence:
        cfg = dataclasses.replace(cfg, accept_low_confidence=True)
    return PoseSearch(
        cfg,
        search.pose_config,
        describe=CachedDescriptors(search.describe),
        match=search.match,
        pose=search.pose,
        fallback=CachedDescriptors(search.fallback) if search.fallback is not None else None,
        wide=CachedDescriptors(search.wide) if search.wide is not None else None,
        learned=_cached_tier(search.learned),
        warn_doubts=not accept_low_confidence,
    )


def _cached_tier(tier: LearnedTier | None) -> LearnedTier | None:
    """The learned tier with its descriptors cached per view (its matcher is pairwise)."""
    return None if tier is None else dataclasses.replace(tier, describe=CachedDescriptors(tier.describe))


def primary_only(search: PoseSearch) -> PoseSearch:
    """``search`` with its primary descriptors only (the same cached ones): the fallback and wide-baseline tiers
    are for the pairs that connect what the primary matches leave apart (:func:`match_all`)."""
    return PoseSearch(search.config, search.pose_config, describe=search.describe, match=search.match,
                      pose=search.pose, warn_doubts=search.warn_doubts)  # fmt: skip


def _components(n: int, outcomes: Sequence[PairOutcome]) -> np.ndarray:
    """The connected components of the accepted pairs' graph: a label per photo. [n] int"""
    label = np.arange(n)

    def root(a: int) -> int:
        while label[a] != a:
            label[a] = label[label[a]]
            a = int(label[a])
        return a

    for o in outcomes:
        if o.result is not None:
            label[root(o.i)] = root(o.j)
    return np.array([root(a) for a in range(n)])


LEARNED_TRIES_PER_JOIN = 2
"""How many failed pairs between the same two groups of photos the learned tier runs on (the most similar first):
it costs 3–7 s a pair on a 2-core CPU, and with no cap CO3D's 8 photos ran it on every pair joining the isolated
photos (584 s against 32 s; benchmarks/history/learned.md)."""
SLOW_TRIES_PER_JOIN = 3
"""How many failed pairs between the same two groups of photos the SIFT fallback and wide tiers run on (the most
similar first, the learned tier's among them): on real photos a failing pair costs 4–13 s in those tiers (their
descriptor products are 4–16× the primary's), and CO3D's two photos that no pair reaches ran them on all 13 of
their pairs, 91 of the pair stage's ~110 s (benchmarks/history/multiview_scaling.md)."""


def match_all(
    views: Sequence[View], pairs: Sequence[tuple[int, int]], search: PoseSearch,
    similarity: Callable[[], np.ndarray] | None = None,
) -> list[PairOutcome]:  # fmt: skip
    """Every pair with the primary tier; then, with every tier, the pairs that failed and would join two groups
    of photos the accepted pairs leave apart (an isolated photo is a group): the slow tiers run where they can
    change what registers, on at most :data:`SLOW_TRIES_PER_JOIN` pairs per two groups (the learned one on
    :data:`LEARNED_TRIES_PER_JOIN`), the most similar pairs first.

    Args:
        similarity: the photos' similarity, [N, N] (:func:`.shortlist.similarity`), called only when a failed pair
            could join two groups; None: the pairs' own order.
    """
    outs = match_pairs(views, pairs, primary_only(search))
    if search.fallback is None and search.wide is None and search.learned is None:
        return outs
    label = _components(len(views), outs)
    failed = [n for n, o in enumerate(outs) if o.result is None and label[o.i] != label[o.j]]
    if failed and similarity is not None:
        sim = similarity()
        failed.sort(key=lambda n: -sim[outs[n].i, outs[n].j])  # stable: equal similarities keep the pairs' order
    sift_only = without_learned(search)
    tries: dict[tuple[int, int], int] = {}
    for n in failed:
        o = outs[n]
        join = (min(label[o.i], label[o.j]), max(label[o.i], label[o.j]))
        if join[0] == join[1] or tries.get(join, 0) >= SLOW_TRIES_PER_JOIN:
            continue  # joined by an earlier pair, or tried enough
        learned = search.learned is not None and tries.get(join, 0) < LEARNED_TRIES_PER_JOIN
        tries[join] = tries.get(join, 0) + 1
        again = match_pairs(views, [(o.i, o.j)], search if learned else sift_only)[0]
        outs[n] = dataclasses.replace(again, seconds=o.seconds + again.seconds)
        if again.result is not None:
            label = _components(len(views), outs)
    return outs


def without_learned(search: PoseSearch) -> PoseSearch:
    """``search`` with every tier but the learned one."""
    return PoseSearch(search.config, search.pose_config, describe=search.describe, match=search.match,
                      pose=search.pose, fallback=search.fallback, wide=search.wide,
                      warn_doubts=search.warn_doubts)  # fmt: skip


@dataclass
class PairOutcome:
    """One pair's two-view result: the accepted pose, or why there is none.

    Attributes:
        i, j: the photos (indices into the views, ``i < j``).
        result: the pose search's result (its ``views`` are ``(views[i], views[j])``), or None.
        reason: why the pair gave no pose (the search's refusal), or None.
        seconds: the search's wall time.
    """

    i: int
    j: int
    result: PoseResult | None
    reason: str | None
    seconds: float
    provisional: bool = False
    """Accepted with its focal-length doubts only: a photo's focal is left to the bundle adjustment of all photos;
    its rotation is not trusted to check the others."""

    @property
    def inliers(self) -> int:
        return len(self.result.geometry.inliers) if self.result is not None else 0

    @property
    def geometry(self) -> TwoViewGeometry:
        """The accepted pose's two-view geometry; only for a pair with a result (``ValueError`` otherwise)."""
        if self.result is None:
            raise ValueError(f"pair ({self.i}, {self.j}) has no pose: {self.reason}")
        return self.result.geometry


FOCAL_CHECKS = ("focal", "uncertainty")
"""The acceptance's checks a pose of a photo with an unknown focal may fail and still be kept provisionally: what
the focal leaves open (the focal check, and the rotation's uncertainty, which includes the focal's)."""


def focal_doubts_only(result: PoseResult, views: Sequence[View]) -> bool:
    """Every doubt about the pose is one the unknown focal of one of ``views`` explains (:data:`FOCAL_CHECKS`, or
    the pose stage's own focal doubt)."""
    if not any(v.intrinsics_source == "prior" for v in views):
        return False
    return all(d.check in FOCAL_CHECKS or (d.check == "pose" and d.message.startswith(FOCAL_DOUBT_START))
               for d in result.doubts)  # fmt: skip


def match_pairs(views: Sequence[View], pairs: Sequence[tuple[int, int]], search: PoseSearch) -> list[PairOutcome]:
    """The pose search on each pair (``search`` should cache its descriptors and keep doubted poses:
    :func:`cached_search`).

    A pair the search refuses (a :class:`ReconstructionError`), or whose pose is doubted for anything but an unknown
    focal (:func:`focal_doubts_only`), is kept with its reason; any other error propagates.
    """
    out = []
    for i, j in pairs:
        t0 = time.perf_counter()
        provisional = False
        try:
            res: PoseResult | None = search([views[i], views[j]])
            reason = None
            if res is not None and res.doubts:
                provisional = focal_doubts_only(res, (views[i], views[j]))
                if not provisional:
                    reason = str(res.doubts[0])
                    res = None
        except ReconstructionError as e:
            res, reason = None, str(e)
        out.append(PairOutcome(i, j, res, reason, time.perf_counter() - t0, provisional))
        logger.debug("pair %s–%s: %s", views[i].name, views[j].name,
                     f"{out[-1].inliers} inliers" if res is not None else reason)  # fmt: skip
    return out
