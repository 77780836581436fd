"""The reconstruction pipeline: typed stages chained, each with an interchangeable backend.

``Pipeline(config).run([a, b])`` → :class:`Reconstruction` (Gaussians in the camera-0
frame, the two cameras, depth maps, and a report). Each stage slot takes any callable
with the stage's signature and a ``name``; the defaults are the classical, weight-free
backends. The report names the backend of every stage.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from .. import __version__
from .._limits import check_photo_count
from ..cameras import CameraSet
from ..errors import InputError
from ..gaussians import GaussianMaps, Gaussians
from ..report import ImageReport, RunReport
from .background import BackgroundConfig, BackgroundLayer, background_gaussians
from .depth import DepthConfig
from .descriptors import SiftConfig, SiftDescriptors
from .gaussian_init import GaussianInitConfig
from .learned import learned_tier
from .matching import MatchConfig
from .multiview import MultiViewConfig, MultiViewResult, reconstruct_views
from .pose import FALLBACK_SIFT, WIDE_SIFT, PoseConfig, PoseResult, PoseSearch, PoseSearchConfig
from .slots import DepthStage, DescribeStage, GaussianStage, MatchStage, PairStage, PoseStage
from .stages import DepthGaussians, EssentialPose, FilteredMatcher, PerViewDescriptors, PlaneSweepDepth
from .types import DepthMap, TwoViewGeometry, View
from .views import ViewConfig, load_views

__all__ = ["STAGES", "Pipeline", "ReconstructConfig", "Reconstruction", "count_gaussians"]

logger = logging.getLogger(__name__)

STAGES = ("images", "descriptors", "matching", "pose", "depth", "gaussians")
StageEvent = Callable[[str, Literal["start", "end", "fail"]], None]


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
    """The result of a run: Gaussians in the camera-0 frame (relative scale: baseline 1).

    ``maps`` are the Gaussian stage's, or the refinement's (stage 7, :mod:`.refine`) when it ran; ``report`` gets each
    later stage's section through its ``add_*`` methods (:class:`~macsplat_cli.report.RunReport`).
    """

    views: list[View]
    geometry: TwoViewGeometry | None
    """The two photos' relative pose; None for more than two photos (``poses``)."""
    depths: list[DepthMap]
    maps: list[GaussianMaps]
    report: RunReport
    scale: Literal["relative", "metric"] = "relative"
    compacted: Gaussians | None = None
    """The scene after the compaction (:mod:`.compact`, stage 8), when it ran."""
    background: BackgroundLayer | None = None
    """The far layer around both photos (:mod:`.background`), when it was built; not refined or compacted."""
    pose: PoseResult | None = None
    """The pose search's result (tier, evidence, acceptance), when the pipeline estimated the pose; for more than
    two photos, the first registered pair's."""
    poses: list[np.ndarray] | None = None
    """More than two photos: each view's camera-to-world [4, 4] (the views are the registered photos that have
    Gaussians, in input order); None for two photos (``geometry``)."""
    multiview: MultiViewResult | None = None
    """More than two photos: every photo's registration (and why a photo is not registered), the pairs."""

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
        """The views' cameras (at the photos' original resolution by default); for more than two photos, the
        photos left unregistered are listed with their reasons (``CameraSet.unregistered``)."""
        confidence = self.pose.camera_confidence() if self.pose is not None else None
        if self.poses is not None:
            cams = [v.camera(T, original_size=original_size) for v, T in zip(self.views, self.poses)]
            left = self.multiview.unregistered() if self.multiview is not None else []
            return CameraSet(cams, scale=self.scale, world="camera_0", pose_confidence=confidence, unregistered=left,
                             undistorted=self._undistorted())  # fmt: skip
        assert self.geometry is not None
        K = (self.geometry.K0, self.geometry.K1)
        cams = []
        for k, v in enumerate(self.views):
            cam = View(v.name, v.path, v.image, v.mask, K[k], v.original_size, v.intrinsics_source)
            cams.append(cam.camera(self.geometry.cam_to_world(k), original_size=original_size))
        return CameraSet(cams, scale=self.scale, world="camera_0", pose_confidence=confidence,
                         undistorted=self._undistorted())  # fmt: skip

    def _undistorted(self) -> dict[str, dict[str, Any]]:
        """Camera name → the distortion its photo was undistorted from at load (the cameras file's note)."""
        return {v.name: v.undistorted.to_dict() for v in self.views if v.undistorted is not None}


def count_gaussians(maps: Sequence[GaussianMaps]) -> int:
    """Gaussians the per-view maps carry (their valid pixels)."""
    return int(sum(int(m.valid_mask().sum()) for m in maps))


class Pipeline:
    """Chains the stages; each slot accepts any backend with the stage's signature (:mod:`.stages`).

    Args:
        config: the stages' settings.
        pair: a two-view network's pass, run once before the other stages (its output goes to every later
            stage); None: no such slot (the classical backend).
        descriptors: the ``describe`` slot (``(views, pair) → features``); a per-view backend
            (``View → Features``, e.g. :class:`~.descriptors.SiftDescriptors`) goes in wrapped in
            :class:`~.stages.PerViewDescriptors`.
        matcher, pose, depth, gaussians: the other slots (signatures in :mod:`.stages`).
        fallback_descriptors: the descriptors tried when the first ones verify too few matches (default:
            :data:`~.pose.FALLBACK_SIFT` when ``config.search.fallback`` is on).
        wide_descriptors: the second fallback tier, tried when neither the descriptors nor the fallback give a
            pose (default: :data:`~.pose.WIDE_SIFT` when ``config.search.wide`` is on and both of those are the
            classical ones).
        scale: ``"metric"`` when the backend's geometry is in metres, else ``"relative"`` (baseline 1).

    The descriptor, matcher and pose slots and the descriptor tiers are held by :attr:`search`, the pose search
    (:class:`~.pose.PoseSearch`): ``run`` is the chain images → network pass → pose search → depth → Gaussians.
    """

    def __init__(
        self,
        config: ReconstructConfig | None = None,
        *,
        pair: PairStage | None = None,
        descriptors: DescribeStage | None = None,
        matcher: MatchStage | None = None,
        pose: PoseStage | None = None,
        depth: DepthStage | None = None,
        gaussians: GaussianStage | None = None,
        fallback_descriptors: DescribeStage | None = None,
        wide_descriptors: DescribeStage | None = None,
        scale: Literal["relative", "metric"] = "relative",
    ) -> None:
        self.config = config or ReconstructConfig()
        c = self.config
        self.pair = pair
        # the default wide tier follows the classical chain only (a backend with its own descriptors, or none to
        # fall back to, e.g. the neural one, gets no SIFT tier unless given one)
        classical = descriptors is None and c.search.fallback
        if fallback_descriptors is None and c.search.fallback:
            fallback_descriptors = PerViewDescriptors(SiftDescriptors(FALLBACK_SIFT))
        if wide_descriptors is None and c.search.wide and classical:
            wide_descriptors = PerViewDescriptors(SiftDescriptors(WIDE_SIFT))
        learned = None
        if c.search.learned is not None:  # --matcher auto|aliked (presets.configure)
            learned = learned_tier(c.search.learned, required=c.search.learned_primary)
            if learned is not None and c.search.learned_primary:
                descriptors, matcher, learned = descriptors or learned.describe, matcher or learned.match, None
        self.search = PoseSearch(
            c.search,
            c.pose,
            describe=descriptors or PerViewDescriptors(SiftDescriptors(c.descriptors)),
            match=matcher or FilteredMatcher(c.matching),
            pose=pose or EssentialPose(c.pose),
            fallback=fallback_descriptors,
            wide=wide_descriptors,
            learned=learned,
        )
        self.depth = depth or PlaneSweepDepth(c.depth)
        self.gaussians = gaussians or DepthGaussians(c.gaussians)
        self.scale = scale

    def backends(self) -> dict[str, str | None]:
        def name(stage: Any) -> str | None:
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
        """Reconstruct from two photos.

        Args:
            paths: the two photos; the first defines the world frame.
            on_stage: called with (stage, "start"), then (stage, "end") or (stage, "fail"),
                around each stage (progress display).

        Raises:
            InputError: unreadable photos or intrinsics.
            ReconstructionError: the scene cannot be reconstructed (the message says why).
        """
        check_photo_count(len(paths))
        times: dict[str, float] = {}
        notify = on_stage or (lambda stage, event: None)

        def timed(stage: str, fn: Callable[[], Any]) -> Any:
            notify(stage, "start")
            t0 = time.perf_counter()
            try:
                out = fn()
            except BaseException:
                notify(stage, "fail")
                raise
            times[stage] = time.perf_counter() - t0
            notify(stage, "end")
            logger.debug("%-11s %.2f s", stage, times[stage])
            return out

        loaded: list[View] = timed("images", lambda: load_views(paths, self.config.views))
        if len(loaded) > 2 or self.config.multiview.poses is not None:
            return self._run_views(paths, loaded, times, timed)
        network = self.pair
        pair = timed("network", lambda: network(loaded)) if network is not None else None
        pose: PoseResult = self.search(loaded, pair, timed)
        views, geometry = pose.views, pose.geometry
        depths: list[DepthMap] = timed("depth", lambda: self.depth(views, geometry, pair))
        bg_cfg = self.config.background

        def gaussian_stage() -> tuple[list[GaussianMaps], BackgroundLayer | None]:
            maps = self.gaussians(views, geometry, depths, pair)
            layer = background_gaussians(views, geometry, depths, bg_cfg) if bg_cfg.enabled else None
            return maps, layer

        # the far layer around both photos is timed with the Gaussians (a few thousand, ~0.05 s)
        maps, background = timed("gaussians", gaussian_stage)
        n_layer = len(background.gaussians) if background is not None and background.gaussians is not None else 0
        report = self._report(
            paths, times, views, pose, depths, count_gaussians(maps) + n_layer, self.scale, background
        )
        return Reconstruction(views, geometry, depths, maps, report, scale=self.scale, background=background, pose=pose)

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
            fill={
                "depth": [getattr(d, "fill_counts", None) for d in depths],
                "background": background.counts if background is not None else None,
            },
            multiview=multiview,
        )

    def _run_views(
        self, paths: Sequence[str | Path], loaded: list[View], times: dict[str, float], timed: Callable[..., Any]
    ) -> Reconstruction:
        """More than two photos, or given poses (:mod:`.multiview`): the classical chain only."""
        if self.pair is not None:
            raise InputError(
                f"{len(loaded)} photos: the neural backend reconstructs two photos; use --backend classical for more"
            )

        def two_view_depth(views: list[View], geometry: TwoViewGeometry) -> list[DepthMap]:
            return self.depth(views, geometry, None)

        c = self.config
        mv = reconstruct_views(loaded, self.search, two_view_depth, c.gaussians, c.background, c.multiview, timed)
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
        report = self._report(paths, times, mv.views, pose, depths, count_gaussians(mv.maps) + n_layer, scale,
                              mv.background, multiview=mv.report())  # fmt: skip
        if given:
            report.pose = {"given": str(c.multiview.poses)}
        poses = [reg.cam_to_world(k) for k in ks]
        return Reconstruction(views, None, depths, mv.maps, report, scale=scale, background=mv.background,
                              pose=None if given else pose, poses=poses, multiview=mv)  # fmt: skip
