"""The reconstruction pipeline: typed stages chained, each with an interchangeable backend.

``Pipeline(config, stages).run(paths)`` → :class:`Reconstruction` (Gaussians in the camera-0 frame, every view's
camera pose, depth maps, and a report), for two photos or more. The slots come from a factory:
:func:`classical_stages` (the weight-free backends, the default) or :func:`~.neural.neural_stages` (the network's),
each a :class:`Stages`. The report names the backend of every stage; :class:`StageClock` times them.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import torch

from .. import __version__
from ..cameras import CameraSet
from ..gaussians import GaussianMaps, Gaussians
from ..report import FillReport, ImageReport, RunReport
from .background import BackgroundConfig, BackgroundLayer, background_gaussians
from .depth import DepthConfig
from .descriptors import SiftConfig, SiftDescriptors
from .gaussian_init import GaussianInitConfig
from .learned import LearnedTier, learned_tier
from .matching import MatchConfig
from .multiview import MultiViewConfig, MultiViewResult, reconstruct_views
from .pose import FALLBACK_SIFT, WIDE_SIFT, PoseConfig, PoseResult, PoseSearch, PoseSearchConfig
from .slots import DepthStage, DescribeStage, GaussianStage, MatchStage, PairPass, PairStage, PoseStage, StageEvent
from .stages import DepthGaussians, EssentialPose, FilteredMatcher, PerViewDescriptors, PlaneSweepDepth
from .types import DepthMap, TwoViewGeometry, View
from .views import ViewConfig, load_views

__all__ = [
    "STAGES", "Pipeline", "ReconstructConfig", "Reconstruction", "StageClock", "StageEvent", "Stages",
    "classical_stages", "count_gaussians",
]  # fmt: skip

logger = logging.getLogger(__name__)

STAGES = ("images", "descriptors", "matching", "pose", "depth", "gaussians")
T = TypeVar("T")


@dataclass
class ReconstructConfig:
    """Every setting of the default pipeline, one dataclass per stage.

    Args:
        views: loading, working size and intrinsics (stage 1).
        descriptors: the primary descriptors (stage 2).
        matching: the filtered matching (stage 3).
        pose: the two-view pose's thresholds (stage 4).
        search: the search for the pose around it: fallback and wide-baseline descriptor tiers, plane tie-break,
            guided re-matching, acceptance (stage 4, :class:`~.pose.PoseSearchConfig`).
        depth: dense depth (stage 5).
        gaussians: Gaussians from the depth (stage 6).
        background: the far layer around both photos (stage 6).
        multiview: more than two photos: pairs, registration, depth from neighbours (:mod:`.multiview`).
    """

    views: ViewConfig = field(default_factory=ViewConfig)
    descriptors: SiftConfig = field(default_factory=SiftConfig)
    matching: MatchConfig = field(default_factory=MatchConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    search: PoseSearchConfig = field(default_factory=PoseSearchConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    gaussians: GaussianInitConfig = field(default_factory=GaussianInitConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    multiview: MultiViewConfig = field(default_factory=MultiViewConfig)


@dataclass
class Reconstruction:
    """The result of a run, for two photos or more: Gaussians in the camera-0 frame (relative scale: the first
    pair's baseline 1) and every view's camera pose.

    ``maps`` are the Gaussian stage's, or the refinement's (stage 7, :mod:`.refine`) when it ran; ``report`` gets each
    later stage's section through its ``add_*`` methods (:class:`~macsplat_cli.report.RunReport`). The two-view
    geometry (relative pose, verified matches, self-calibrated ``K``) is a detail of the pair: ``pose.geometry``.
    """

    views: list[View]
    """The views that have Gaussians, in input order (two photos: both), each with its final ``K``."""
    poses: list[np.ndarray]
    """Each view's camera-to-world [4, 4] in the camera-0 world."""
    depths: list[DepthMap]
    maps: list[GaussianMaps]
    report: RunReport
    scale: Literal["relative", "metric"] = "relative"
    compacted: Gaussians | None = None
    """The scene after the compaction (:mod:`.compact`, stage 8), when it ran."""
    background: BackgroundLayer | None = None
    """The far layer around the photos (:mod:`.background`), when it was built; not refined or compacted."""
    pose: PoseResult | None = None
    """The pose search's result for the pair (its geometry, tier, evidence, acceptance), when the pipeline estimated
    a pose; for more than two photos, the first registered pair's."""
    multiview: MultiViewResult | None = None
    """Views registered together (more than two photos, or given poses): every photo's registration (and why a
    photo is not registered), the pairs; None for a pair."""

    @functools.cached_property
    def gaussians(self) -> Gaussians:
        """The scene in the world (camera-0) frame: the compacted set when the compaction ran, else every
        view's pixel Gaussians (computed once; a refined or compacted reconstruction is a new object)."""
        layer = self.background.gaussians if self.background is not None else None
        if self.compacted is not None:
            scene = self.compacted
        else:
            with torch.no_grad():
                scene = Gaussians.cat([m.to_gaussians() for m in self.maps])
        return scene if layer is None else Gaussians.cat([scene, layer])

    def cameras(self, *, original_size: bool = True) -> CameraSet:
        """The views' cameras (at the photos' original resolution by default); the photos left unregistered are
        listed with their reasons (``CameraSet.unregistered``)."""
        confidence = self.pose.camera_confidence() if self.pose is not None else None
        cams = [v.camera(T, original_size=original_size) for v, T in zip(self.views, self.poses)]
        left = self.multiview.unregistered() if self.multiview is not None else []
        undistorted = {v.name: v.undistorted.to_dict() for v in self.views if v.undistorted is not None}
        return CameraSet(cams, scale=self.scale, world="camera_0", pose_confidence=confidence, unregistered=left,
                         undistorted=undistorted)  # fmt: skip


def count_gaussians(maps: Sequence[GaussianMaps]) -> int:
    """Gaussians the per-view maps carry (their valid pixels)."""
    return int(sum(int(m.valid_mask().sum()) for m in maps))


class StageClock:
    """Runs the stages of one reconstruction: ``clock(stage, fn)`` calls ``fn()`` between the stage's ``start`` and
    ``end`` events (``fail`` when it raises) and records its wall seconds in :attr:`times` (the one stage timer of
    the pipeline and the engine, a :class:`~.slots.StageTimer`).

    Args:
        on_stage: called with ``(stage, "start" | "end" | "fail")``; None: no one listens.
    """

    def __init__(self, on_stage: StageEvent | None = None) -> None:
        self.on_stage = on_stage
        self.times: dict[str, float] = {}

    def __call__(self, stage: str, fn: Callable[[], T]) -> T:
        notify = self.on_stage or _unheard
        notify(stage, "start")
        t0 = time.perf_counter()
        try:
            out = fn()
        except BaseException:
            notify(stage, "fail")
            raise
        self.times[stage] = time.perf_counter() - t0
        notify(stage, "end")
        logger.debug("%-11s %.2f s", stage, self.times[stage])
        return out


def _unheard(stage: str, event: Literal["start", "end", "fail"]) -> None:
    return None


@dataclass
class Stages:
    """Every slot of a pipeline (signatures in :mod:`.slots`), as a backend's factory fills them:
    :func:`classical_stages` or :func:`~.neural.neural_stages`.

    Attributes:
        describe, match, pose, depth, gaussians: the slots.
        pair: a two-view network's pass, run once before the other stages (its output goes to every later
            stage); None: no such slot (the classical backend).
        fallback: the descriptors tried when the first ones verify too few matches, or None.
        wide: the second fallback tier, tried when neither the descriptors nor the fallback give a pose, or None.
        learned: the learned tier (ALIKED + LightGlue), run last, or None.
        scale: ``"metric"`` when the backend's geometry is in metres, else ``"relative"`` (baseline 1).
    """

    describe: DescribeStage
    match: MatchStage
    pose: PoseStage
    depth: DepthStage
    gaussians: GaussianStage
    pair: PairStage | None = None
    fallback: DescribeStage | None = None
    wide: DescribeStage | None = None
    learned: LearnedTier | None = None
    scale: Literal["relative", "metric"] = "relative"


def classical_stages(
    config: ReconstructConfig, *, descriptors: DescribeStage | None = None, matcher: MatchStage | None = None,
    pose: PoseStage | None = None, depth: DepthStage | None = None, gaussians: GaussianStage | None = None,
    fallback: DescribeStage | None = None,
) -> Stages:  # fmt: skip
    """The weight-free backends of every slot from ``config``, with any slot given replaced (a backend's own,
    :func:`~.neural.neural_stages`, or a test's).

    The descriptor tiers come from ``config.search``: the fallback (``fallback``: :data:`~.pose.FALLBACK_SIFT`),
    the wide-baseline tier (``wide``: :data:`~.pose.WIDE_SIFT`, with the classical descriptors and fallback only: a
    backend with its own descriptors, or none to fall back to, gets no SIFT tier) and the learned tier
    (``learned``, ``--matcher auto|aliked``; ``learned_primary``: it is the primary descriptors and matcher
    instead).
    """
    search = config.search
    classical = descriptors is None and search.fallback
    if fallback is None and search.fallback:
        fallback = PerViewDescriptors(SiftDescriptors(FALLBACK_SIFT))
    wide = PerViewDescriptors(SiftDescriptors(WIDE_SIFT)) if search.wide and classical else None
    learned = None
    if search.learned is not None:  # --matcher auto|aliked (presets.configure)
        learned = learned_tier(search.learned, required=search.learned_primary)
        if learned is not None and search.learned_primary:
            descriptors, matcher, learned = descriptors or learned.describe, matcher or learned.match, None
    return Stages(
        describe=descriptors or PerViewDescriptors(SiftDescriptors(config.descriptors)),
        match=matcher or FilteredMatcher(config.matching),
        pose=pose or EssentialPose(config.pose),
        depth=depth or PlaneSweepDepth(config.depth),
        gaussians=gaussians or DepthGaussians(config.gaussians),
        fallback=fallback,
        wide=wide,
        learned=learned,
    )


class Pipeline:
    """Chains the stages; each slot accepts any backend with the stage's signature (:mod:`.slots`).

    Args:
        config: the stages' settings.
        stages: the backends of every slot (default: :func:`classical_stages` of ``config``).

    The descriptor, matcher and pose slots and the descriptor tiers are held by :attr:`search`, the pose search
    (:class:`~.pose.PoseSearch`): ``run`` is the chain images → network pass → pose search → depth → Gaussians.
    """

    def __init__(self, config: ReconstructConfig | None = None, stages: Stages | None = None) -> None:
        self.config = config or ReconstructConfig()
        c = self.config
        s = stages or classical_stages(c)
        self.pair = s.pair
        self.search = PoseSearch(c.search, c.pose, describe=s.describe, match=s.match, pose=s.pose,
                                 fallback=s.fallback, wide=s.wide, learned=s.learned)  # fmt: skip
        self.depth = s.depth
        self.gaussians = s.gaussians
        self.scale = s.scale

    def backends(self) -> dict[str, str | None]:
        def name(stage: object) -> str | None:
            return None if stage is None else getattr(stage, "name", type(stage).__name__)

        s = self.search
        names = {
            "images": "opencv+pillow",
            "descriptors": name(s.describe),
            "descriptors_fallback": name(s.fallback),
            "descriptors_wide": name(s.wide),
            "matching": name(s.match),
            "pose": name(s.pose),
            "depth": name(self.depth),
            "gaussians": name(self.gaussians),
        }
        if s.learned is not None:
            names["descriptors_learned"] = s.learned.name
        if self.pair is not None:
            names["pair"] = name(self.pair)
        return names

    def run(self, paths: Sequence[str | Path], *, on_stage: StageEvent | None = None) -> Reconstruction:
        """Reconstruct from two photos or more (more than two, or given poses: :mod:`.multiview`).

        Args:
            paths: the photos (2 to :data:`~macsplat_cli._limits.MAX_PHOTOS`: the caller checks the count, as
                :func:`~macsplat_cli.engine.reconstruct` does); the first defines the world frame.
            on_stage: called with (stage, "start"), then (stage, "end") or (stage, "fail"),
                around each stage (progress display).

        Raises:
            InputError: unreadable photos or intrinsics.
            ReconstructionError: the scene cannot be reconstructed (the message says why).
        """
        clock = StageClock(on_stage)
        loaded: list[View] = clock("images", lambda: load_views(paths, self.config.views))
        if len(loaded) > 2 or self.config.multiview.poses is not None:
            return self._run_views(paths, loaded, clock)
        network = self.pair
        pair: PairPass = clock("network", lambda: network(loaded)) if network is not None else None
        pose: PoseResult = self.search(loaded, pair, clock)
        views, geometry = pose.views, pose.geometry
        depths: list[DepthMap] = clock("depth", lambda: self.depth(views, geometry, pair))
        bg_cfg = self.config.background

        def gaussian_stage() -> tuple[list[GaussianMaps], BackgroundLayer | None]:
            maps = self.gaussians(views, geometry, depths, pair)
            layer = background_gaussians(views, geometry, depths, bg_cfg) if bg_cfg.enabled else None
            return maps, layer

        # the far layer around both photos is timed with the Gaussians (a few thousand, ~0.05 s)
        maps, background = clock("gaussians", gaussian_stage)
        n_layer = len(background.gaussians) if background is not None and background.gaussians is not None else 0
        report = self._report(
            paths, clock.times, views, pose, depths, count_gaussians(maps) + n_layer, self.scale, background
        )
        poses = [geometry.cam_to_world(0), geometry.cam_to_world(1)]
        return Reconstruction(views, poses, depths, maps, report, scale=self.scale, background=background, pose=pose)

    def _report(
        self, paths: Sequence[str | Path], times: dict[str, float], views: Sequence[View], pose: PoseResult,
        depths: Sequence[DepthMap], gaussians: int, scale: Literal["relative", "metric"],
        background: BackgroundLayer | None, multiview: dict[str, Any] | None = None,
    ) -> RunReport:  # fmt: skip
        """The report of stages 1–6: the photos, the (first) pair's matches and pose, the depths, the Gaussians."""
        return RunReport(
            macsplat_version=__version__,
            inputs=[str(p) for p in paths],
            backends=self.backends(),
            times_s={**times, "total": sum(times.values())},
            images=[
                ImageReport(v.name, list(v.original_size), [v.width, v.height], v.intrinsics_source, float(v.K[0, 0]))
                for v in views
            ],
            keypoints=[len(f) for f in pose.features],
            fallback_used=pose.fallback_used,
            matches={**pose.geometry.inliers.counts},
            inlier_ratio=pose.inlier_ratio,
            pose=pose.report(),
            depth_coverage=[float(d.valid.mean()) for d in depths],
            depth_measured=[float(d.measured.mean()) if d.measured is not None else None for d in depths],
            gaussians=gaussians,
            config=asdict(self.config),
            scale=scale,
            fill=FillReport(
                depth=[getattr(d, "fill_counts", None) for d in depths],
                background=background.counts if background is not None else None,
            ),
            multiview=multiview,
        )

    def _run_views(self, paths: Sequence[str | Path], loaded: list[View], clock: StageClock) -> Reconstruction:
        """More than two photos, or given poses (:mod:`.multiview`): the classical chain only (the engine refuses the
        neural backend here, before its weights load)."""

        def two_view_depth(views: list[View], geometry: TwoViewGeometry) -> list[DepthMap]:
            return self.depth(views, geometry, None)

        c = self.config
        mv = reconstruct_views(loaded, self.search, two_view_depth, c.gaussians, c.background, c.multiview, clock)
        reg, ks = mv.registration, mv.map_views
        views = [mv.views[k] for k in ks]
        depths = [d for d in (mv.depths[k] for k in ks) if d is not None]
        given = c.multiview.poses is not None
        # the report's pair: the first registered pair, or with given poses the pair with the most matches
        first = max(mv.pairs, key=lambda o: o.inliers if given else (o.i, o.j) == reg.init_pair)
        pose = first.result
        assert pose is not None
        scale = mv.scale or self.scale
        layer = mv.background.gaussians if mv.background is not None else None
        n_layer = len(layer) if layer is not None else 0
        report = self._report(paths, clock.times, mv.views, pose, depths, count_gaussians(mv.maps) + n_layer, scale,
                              mv.background, multiview=mv.report())  # fmt: skip
        if given:
            report.pose = {"given": str(c.multiview.poses)}
        poses = [reg.cam_to_world(k) for k in ks]
        return Reconstruction(views, poses, depths, mv.maps, report, scale=scale, background=mv.background,
                              pose=None if given else pose, multiview=mv)  # fmt: skip
