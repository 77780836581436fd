"""The classical (weight-free) backend of each pipeline slot (the slots' interfaces: :mod:`.slots`; the factory
that fills a pipeline with them: :func:`~.run.classical_stages`).

=========  ===============================================================  =======================
slot       signature                                                        classical backend
=========  ===============================================================  =======================
pair       ``(views) → NetworkPair``: a network's one pass (or no slot)     — (none)
describe   ``(views, pair) → [Features, Features]``                         SIFT per view
matcher    ``(features0, features1) → Matches``                             reciprocal NN + τ gate
pose       ``(view0, view1, matches, pair) → TwoViewGeometry``              essential matrix
depth      ``(views, geometry, pair) → [DepthMap, DepthMap]``               plane sweep + SGM
gaussians  ``(views, geometry, depths, pair) → [GaussianMaps, GaussianMaps]``  per-pixel surfels
=========  ===============================================================  =======================

``pair`` is the output of the ``pair`` slot (:data:`~.slots.PairPass`: the network's pass, ``None`` when the
pipeline has none): a backend that needs both views at once (a two-view network) computes it once and every later
stage receives it explicitly. The classical backends take it and leave it unread (in a neural pipeline without a
Gaussian head, :class:`DepthGaussians` receives the network's pass). Each backend has a ``name`` (the report names
the backend of every stage).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

from ..gaussians import GaussianMaps
from .depth import DepthConfig, estimate_depths
from .descriptors import DescriptorBackend
from .gaussian_init import GaussianInitConfig, gaussians_from_depth
from .matching import MatchConfig, match_features
from .pose import PoseConfig, estimate_pose
from .slots import PairPass
from .types import DepthMap, Features, Matches, TwoViewGeometry, View

__all__ = [
    "DepthGaussians",
    "EssentialPose",
    "FilteredMatcher",
    "PerViewDescriptors",
    "PlaneSweepDepth",
]


class PerViewDescriptors:
    """A per-view descriptor backend (``View → Features``, e.g. SIFT) in the ``describe`` slot.

    A backend that declares ``thread_safe = True`` describes the views in parallel threads (OpenCV's SIFT runs
    on one core and releases the GIL: the stage takes about half the time on two cores, same output).
    """

    def __init__(self, backend: DescriptorBackend) -> None:
        self.backend = backend
        self.name = backend.name

    def __call__(self, views: Sequence[View], pair: PairPass = None) -> list[Features]:
        workers = min(len(views), os.cpu_count() or 1)
        if workers < 2 or not getattr(self.backend, "thread_safe", False):
            return [self.backend(v) for v in views]
        with ThreadPoolExecutor(workers, thread_name_prefix="describe") as pool:
            return list(pool.map(self.backend, views))


class FilteredMatcher:
    name = "reciprocal-nn+confidence"

    def __init__(self, config: MatchConfig) -> None:
        self.config = config

    def __call__(self, f0: Features, f1: Features) -> Matches:
        return match_features(f0, f1, self.config)


class EssentialPose:
    name = "classical:essential-magsac+lm"

    def __init__(self, config: PoseConfig) -> None:
        self.config = config

    def __call__(self, v0: View, v1: View, matches: Matches, pair: PairPass = None) -> TwoViewGeometry:
        return estimate_pose(v0, v1, matches, self.config)


class PlaneSweepDepth:
    name = "classical:plane-sweep-sgm"

    def __init__(self, config: DepthConfig) -> None:
        self.config = config

    def __call__(self, views: list[View], geometry: TwoViewGeometry, pair: PairPass = None) -> list[DepthMap]:
        return estimate_depths(views, geometry, self.config)


class DepthGaussians:
    name = "classical:per-pixel-surfels"

    def __init__(self, config: GaussianInitConfig) -> None:
        self.config = config

    def __call__(
        self, views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap], pair: PairPass = None
    ) -> list[GaussianMaps]:
        return gaussians_from_depth(views, geometry, depths, self.config)
