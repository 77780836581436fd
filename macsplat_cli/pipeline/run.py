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

import cv2
import numpy as np
import torch

from .. import __version__
from ..cameras import CameraSet
from ..errors import ReconstructionError
from ..gaussians import GaussianMaps, Gaussians
from ..metrics import rotation_error_deg, translation_direction_error_deg
from ..report import ImageReport, RunReport
from .background import BackgroundConfig, BackgroundLayer, background_gaussians
from .depth import DepthConfig
from .descriptors import SiftConfig, SiftDescriptors
from .gaussian_init import GaussianInitConfig
from .matching import MatchConfig, guided_matches
from .pose import PoseConfig, epipolar_fit, find_homography, fundamental_from_pose
from .pose_confidence import ConfidenceConfig, PoseConfidence, accept_pose
from .stages import (
    DepthGaussians,
    DepthStage,
    DescribeStage,
    EssentialPose,
    FilteredMatcher,
    GaussianStage,
    MatchStage,
    PairStage,
    PerViewDescriptors,
    PlaneSweepDepth,
    PoseStage,
)
from .types import DepthMap, Features, Matches, TwoViewGeometry, View
from .views import ViewConfig, load_views

__all__ = [
    "LOW_CONFIDENCE_HINT",
    "STAGES",
    "Pipeline",
    "PlanePose",
    "ReconstructConfig",
    "Reconstruction",
    "count_gaussians",
    "dominant_plane",
    "plane_poses",
    "pose_confidence",
    "tiebreak_plane_ok",
    "tiebreak_winner_ok",
]

logger = logging.getLogger(__name__)

STAGES = ("images", "descriptors", "matching", "pose", "depth", "gaussians")
StageEvent = Callable[[str, Literal["start", "end", "fail"]], None]


@dataclass
class ReconstructConfig:
    """Every setting of the default pipeline, one dataclass per stage.

    ``fallback_descriptors``: when the primary descriptors verify fewer than
    ``fallback_min_inliers`` matches (or the pose fails), the descriptor → matching → pose
    chain runs again with these (affine-simulated SIFT by default: slower, but it matches
    across wide baselines), and the result with more verified matches is kept. ``None``
    disables the fallback.

    ``guided_band_px``: after the first pose, all keypoints are matched again within this
    distance of their epipolar lines (:func:`~.matching.guided_matches`, ratio
    ``guided_ratio`` among the candidates in the band) and the pose is re-estimated; the
    result is kept if it verifies more matches. On a low-texture 27° pair this took the
    verified matches from 30 to 461. It is skipped when the first pose already has
    ``guided_below`` verified matches (a second dense matching pass for a pose that is
    already at 0.01–0.05° on synthetic pairs), and its pose is rejected if it moved more
    than ``guided_max_change_deg`` (rotation, translation direction) from the first one:
    it refines a pose, it must not jump to another solution (measured: a 2.4° pose
    "refined" into a 50° wrong one on a 90° object pair). ``None`` disables it.

    ``confidence``: the checks of the final pose that are independent of the RANSAC
    (:func:`~.pose_confidence.assess_pose`; ``None`` disables them). Every backend's pose goes through one
    acceptance, :func:`~.pose_confidence.accept_pose`: the pose stage's doubts (``geometry.info["doubts"]``), the
    support minimum of ``pose`` (verified matches) and these checks; a pose with any doubt is refused
    (:class:`~macsplat_cli.errors.ReconstructionError`, naming the first) unless ``accept_low_confidence``,
    which writes the scene and logs a warning. The report's ``pose`` section and the cameras file carry the
    confidence either way.

    ``wide_descriptors``: a second fallback tier for wide baselines, run only when the primary descriptors and
    the first fallback both gave no pose (every other pair keeps its time): affine-simulated SIFT with more tilts
    at a finer detection size (CO3D apple 39–62°, tabletop pairs: 36–223 correct confident matches where the first
    fallback had 10–69). Its pose is kept when it verifies at least ``wide_min_inliers`` matches. When its pose
    fails (on CO3D: "ambiguous, the matches lie on one plane", a tabletop), ``plane_tiebreak_margin`` ranks the
    plane's physical poses (the homography's decompositions with the plane in front) by dense consistency: the
    primary keypoints matched within ``guided_band_px`` of each pose's epipolar lines that it explains in front of
    both cameras, off the plane (every candidate explains the plane's own matches). The best is re-estimated by
    the pose stage from its guided matches when it explains ``plane_tiebreak_margin`` times the next one's and at
    least ``plane_tiebreak_min`` (the pose confidence still checks it); only with known intrinsics, and when at
    least ``plane_tiebreak_plane`` and half of the matches lie on the plane. ``None`` disables either.
    """

    views: ViewConfig = field(default_factory=ViewConfig)
    descriptors: SiftConfig = field(default_factory=SiftConfig)
    fallback_descriptors: SiftConfig | None = field(
        default_factory=lambda: SiftConfig(affine=True, detect_size=512, max_keypoints=4000)
    )
    fallback_min_inliers: int = 100
    wide_descriptors: SiftConfig | None = field(
        default_factory=lambda: SiftConfig(affine=True, detect_size=640, max_keypoints=8000, max_tilt=4.0)
    )
    wide_min_inliers: int = 30
    plane_tiebreak_margin: float | None = 1.5
    plane_tiebreak_min: int = 100
    plane_tiebreak_plane: int = 30
    guided_band_px: float | None = 2.0
    guided_ratio: float = 0.95
    guided_below: int = 1000
    guided_max_change_deg: tuple[float, float] = (3.0, 10.0)
    matching: MatchConfig = field(default_factory=MatchConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    gaussians: GaussianInitConfig = field(default_factory=GaussianInitConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    confidence: ConfidenceConfig | None = field(default_factory=ConfidenceConfig)
    accept_low_confidence: bool = False


LOW_CONFIDENCE_HINT = "use --accept-low-confidence to write the scene anyway"
"""Appended to a refusal for low pose confidence."""


@dataclass
class Reconstruction:
    """The result of a run: Gaussians in the camera-0 frame (relative scale: baseline 1).

    ``maps`` are the Gaussian stage's, or the refinement's (stage 7, :mod:`.refine`) when it ran; ``report`` gets each
    later stage's section through its ``add_*`` methods (:class:`~macsplat_cli.report.RunReport`).
    """

    views: list[View]
    geometry: TwoViewGeometry
    depths: list[DepthMap]
    maps: list[GaussianMaps]
    report: RunReport
    scale: Literal["relative", "metric"] = "relative"
    compacted: Gaussians | None = None
    """The scene after the compaction (:mod:`.compact`, stage 8), when it ran."""
    background: BackgroundLayer | None = None
    """The far layer around both photos (:mod:`.background`), when it was built; not refined or compacted."""

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
        """The two cameras; at the photos' original resolution by default."""
        K = (self.geometry.K0, self.geometry.K1)
        cams = []
        for k, v in enumerate(self.views):
            cam = View(v.name, v.path, v.image, v.mask, K[k], v.original_size, v.intrinsics_source)
            cams.append(cam.camera(self.geometry.cam_to_world(k), original_size=original_size))
        return CameraSet(cams, scale=self.scale, world="camera_0", pose_confidence=pose_confidence(self.geometry))


def pose_confidence(geometry: TwoViewGeometry) -> dict[str, Any] | None:
    """The pose's confidence as the cameras file records it (None when it was not assessed and has no doubts):
    ``score`` (None when not assessed), ``checks``, ``doubts`` and ``accepted_low_confidence``."""
    info = geometry.info
    doubts = list(info.get("doubts", []))  # type: ignore[call-overload]
    if "confidence" not in info and not doubts:
        return None
    return {
        "score": info.get("confidence"),
        "checks": dict(info.get("confidence_checks", {})),  # type: ignore[call-overload]
        "doubts": doubts,
        "accepted_low_confidence": bool(info.get("accepted_low_confidence", False)),
    }


def count_gaussians(maps: Sequence[GaussianMaps]) -> int:
    """Gaussians the per-view maps carry (their valid pixels)."""
    return int(sum(int(m.valid_mask().sum()) for m in maps))


def dominant_plane(matches: Matches, pose: PoseConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The homography of the matches' dominant plane (MAGSAC++, 1.5 pose thresholds) and which matches lie on it:
    ([3, 3], [M] bool), or None when none fits."""
    H, mask = find_homography(matches.xy0, matches.xy1, 1.5 * pose.threshold_px, pose.max_iters)
    if H is None or mask is None:
        return None
    return H, mask


def tiebreak_plane_ok(n_plane: int, n_matches: int, config: ReconstructConfig) -> bool:
    """The plane tie-break's first guard: a dominant plane, ``plane_tiebreak_plane`` matches and half of them (CO3D
    74°, 17 of 39 on a "plane": a pose 11° off passed without it)."""
    return n_plane >= max(config.plane_tiebreak_plane, n_matches / 2)


def tiebreak_winner_ok(scores: Sequence[int], config: ReconstructConfig) -> bool:
    """The plane tie-break's second guard on the candidates' scores (best first): at least ``plane_tiebreak_min``
    and ``plane_tiebreak_margin`` times the next one's."""
    assert config.plane_tiebreak_margin is not None
    if not scores or scores[0] < config.plane_tiebreak_min:
        return False
    return len(scores) == 1 or scores[0] >= config.plane_tiebreak_margin * scores[1]


@dataclass
class PlanePose:
    """One physical pose of a plane (a decomposition of its homography) and its dense-consistency score."""

    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3], unit
    score: int
    """Keypoints matched along its epipolar lines (``guided``) that it explains in front of both cameras and
    that the plane does not."""
    guided: Matches


def plane_poses(
    views: Sequence[View], feats: Sequence[Features], matches: Matches, H: np.ndarray, on_plane: np.ndarray,
    config: ReconstructConfig,
) -> list[PlanePose]:  # fmt: skip
    """The plane's physical poses, best score first (see :meth:`Pipeline._plane_tiebreak`).

    Each decomposition of ``H`` (known intrinsics) that puts the plane's matches (``on_plane``) in front of both
    cameras, once per distinct pose, is scored by the keypoints of ``feats`` matched within
    ``config.guided_band_px`` of its epipolar lines that it explains (Sampson distance below the pose threshold)
    in front of both cameras and that the plane does not (transfer error over 3 pose thresholds).
    """
    c = config
    assert c.guided_band_px is not None
    thr = c.pose.threshold_px
    K0, K1 = views[0].K, views[1].K

    def off_plane(m: Matches) -> np.ndarray:  # [N] bool: farther than 3 thresholds from the plane's transfer
        p = np.c_[m.xy0, np.ones(len(m))] @ H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(p[:, :2] / p[:, 2:] - m.xy1, axis=1)
        return ~(err <= 3.0 * thr)

    _, Rs, ts, _ = cv2.decomposeHomographyMat(np.linalg.inv(K1) @ H @ K0, np.eye(3))
    poses: list[PlanePose] = []
    for R, t in zip(Rs, ts):
        t = t.ravel()
        if np.linalg.norm(t) < 1e-9:
            continue
        t = t / np.linalg.norm(t)
        _, front = epipolar_fit(R, t, K0, K1, matches.xy0[on_plane], matches.xy1[on_plane])
        if front.mean() < 0.5 or any(
            rotation_error_deg(R, p.R) < 1.0 and translation_direction_error_deg(t, p.t) < 5.0 for p in poses
        ):
            continue  # the plane behind a camera, or the same pose again
        F = fundamental_from_pose(R, t, K0, K1)
        g = guided_matches(feats[0], feats[1], F, band_px=c.guided_band_px, ratio=c.guided_ratio)
        d, front_g = epipolar_fit(R, t, K0, K1, g.xy0, g.xy1)
        # every candidate explains the plane by construction: only matches off it are evidence
        poses.append(PlanePose(R, t, int((front_g & (d < thr) & off_plane(g)).sum()), g))
    return sorted(poses, key=lambda p: -p.score)


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
        fallback_descriptors: the descriptors tried when the first ones verify too few matches.
        wide_descriptors: the second fallback tier, tried when neither the descriptors nor the fallback give a
            pose (default: ``config.wide_descriptors`` when both of those are the classical ones).
        scale: ``"metric"`` when the backend's geometry is in metres, else ``"relative"`` (baseline 1).
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
        self.descriptors = descriptors or PerViewDescriptors(SiftDescriptors(c.descriptors))
        self.fallback_descriptors = fallback_descriptors or (
            PerViewDescriptors(SiftDescriptors(c.fallback_descriptors)) if c.fallback_descriptors is not None else None
        )
        # the default tier follows the classical chain only (a backend with its own descriptors, or none to fall
        # back to, e.g. the neural one, gets no SIFT tier unless given one)
        classical = descriptors is None and c.fallback_descriptors is not None
        self.wide_descriptors = wide_descriptors or (
            PerViewDescriptors(SiftDescriptors(c.wide_descriptors))
            if c.wide_descriptors is not None and classical
            else None
        )
        self.matcher = matcher or FilteredMatcher(c.matching)
        self.pose = pose or EssentialPose(c.pose)
        self.depth = depth or PlaneSweepDepth(c.depth)
        self.gaussians = gaussians or DepthGaussians(c.gaussians)
        self.scale = scale

    def backends(self) -> dict[str, str | None]:
        def name(stage: Any) -> str | None:
            return None if stage is None else getattr(stage, "name", type(stage).__name__)

        names = {
            "images": "opencv+pillow",
            "descriptors": name(self.descriptors),
            "descriptors_fallback": name(self.fallback_descriptors),
            "descriptors_wide": name(self.wide_descriptors),
            "matching": name(self.matcher),
            "pose": name(self.pose),
            "depth": name(self.depth),
            "gaussians": name(self.gaussians),
        }
        if self.pair is not None:
            names["pair"] = name(self.pair)
        return names

    def _try_pose(
        self, views: list[View], matches: Matches, pair: Any, timed: Callable[[str, Callable[[], Any]], Any], stage: str
    ) -> tuple[TwoViewGeometry | None, ReconstructionError | None]:
        try:
            return timed(stage, lambda: self.pose(views[0], views[1], matches, pair)), None
        except ReconstructionError as e:
            return None, e

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
        if len(paths) != 2:
            raise ValueError(f"the pipeline takes exactly two photos, got {len(paths)}")
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

        views: list[View] = timed("images", lambda: load_views(paths, self.config.views))
        pair = timed("network", lambda: self.pair(views)) if self.pair is not None else None
        feats: list[Features] = timed("descriptors", lambda: self.descriptors(views, pair))
        feats_primary = feats
        matches: Matches = timed("matching", lambda: self.matcher(feats[0], feats[1]))
        geometry, failure = self._try_pose(views, matches, pair, timed, "pose")
        fallback_used = False
        n_verified = len(geometry.inliers) if geometry is not None else 0
        if self.fallback_descriptors is not None and n_verified < self.config.fallback_min_inliers:
            fb = self.fallback_descriptors
            logger.debug(
                "%d verified matches (< %d): retrying with %s", n_verified, self.config.fallback_min_inliers, fb.name
            )
            feats_fb = timed("descriptors (fallback)", lambda: fb(views, pair))
            matches_fb = timed("matching (fallback)", lambda: self.matcher(feats_fb[0], feats_fb[1]))
            geometry_fb, failure_fb = self._try_pose(views, matches_fb, pair, timed, "pose (fallback)")
            if geometry_fb is not None and len(geometry_fb.inliers) > n_verified:
                geometry, feats, matches, fallback_used = geometry_fb, feats_fb, matches_fb, True
            elif geometry is None:
                failure = failure_fb or failure
        if self.wide_descriptors is not None and geometry is None:
            geometry_w, feats_w, matches_w, failure_w = self._wide(views, feats_primary, pair, timed)
            if geometry_w is not None:  # else the chain's own failure stands (the tier's is logged)
                geometry, feats, matches, fallback_used = geometry_w, feats_w, matches_w, True
            else:
                logger.debug("wide-baseline tier: %s", failure_w)
        if geometry is None:
            assert failure is not None
            raise failure
        if self.config.guided_band_px is not None and len(geometry.inliers) < self.config.guided_below:
            geometry = self._guided(views, feats, geometry, pair, timed)
        self._check_confidence(views, geometry, matches, timed)
        for k, v in enumerate(views):
            if v.intrinsics_source == "prior" and geometry.info.get("focal_estimated"):
                v.intrinsics_source = "estimated"
                v.K = geometry.K0 if k == 0 else geometry.K1
        depths: list[DepthMap] = timed("depth", lambda: self.depth(views, geometry, pair))
        bg_cfg = self.config.background

        def gaussian_stage() -> tuple[list[GaussianMaps], BackgroundLayer | None]:
            maps = self.gaussians(views, geometry, depths, pair)
            layer = background_gaussians(views, geometry, depths, bg_cfg) if bg_cfg.enabled else None
            return maps, layer

        # the far layer around both photos is timed with the Gaussians (a few thousand, ~0.05 s)
        maps, background = timed("gaussians", gaussian_stage)
        n_layer = len(background.gaussians) if background is not None and background.gaussians is not None else 0
        report = RunReport(
            macsplat_version=__version__,
            inputs=[str(p) for p in paths],
            backends=self.backends(),
            times_s={**times, "total": sum(times.values())},
            images=[
                ImageReport(v.name, list(v.original_size), [v.width, v.height], v.intrinsics_source, float(v.K[0, 0]))
                for v in views
            ],
            keypoints=[len(f) for f in feats],
            fallback_used=fallback_used,
            matches={**geometry.inliers.counts},
            inlier_ratio=geometry.info.get("inlier_ratio"),
            pose=dict(geometry.info),
            depth_coverage=[float(d.valid.mean()) for d in depths],
            depth_measured=[float(d.measured.mean()) if d.measured is not None else None for d in depths],
            gaussians=count_gaussians(maps) + n_layer,
            config=asdict(self.config),
            scale=self.scale,
            fill={
                "depth": [getattr(d, "fill_counts", None) for d in depths],
                "background": background.counts if background is not None else None,
            },
        )
        return Reconstruction(views, geometry, depths, maps, report, scale=self.scale, background=background)

    def _check_confidence(
        self, views: list[View], geometry: TwoViewGeometry, evidence: Matches,
        timed: Callable[[str, Callable[[], Any]], Any],
    ) -> None:  # fmt: skip
        """Assess the final pose (before the views are marked as self-calibrated: a view with the prior's focal
        has an unknown focal length) against ``evidence``, the filtered matches its first estimate came from (not
        the guided ones, which the pose itself selected), record it in ``geometry.info`` and refuse a doubtful
        pose unless ``accept_low_confidence``.

        Raises:
            ReconstructionError: the pose stage or the confidence checks doubt the pose.
        """
        c = self.config
        info = geometry.info
        conf: PoseConfidence = timed(
            "pose confidence",
            lambda: accept_pose(views[0], views[1], geometry, c.pose, c.confidence, evidence=evidence),
        )
        if c.confidence is not None:
            info["confidence"] = conf.score
            info["confidence_checks"] = conf.checks  # type: ignore[assignment]
        doubts = conf.reasons
        info["doubts"] = doubts  # type: ignore[assignment]
        if not doubts:
            return
        if not c.accept_low_confidence:
            raise ReconstructionError(f"{doubts[0]} ({LOW_CONFIDENCE_HINT})")
        info["accepted_low_confidence"] = True
        logger.warning("the pose may be wrong, the scene is written anyway (--accept-low-confidence): %s", doubts[0])

    def _wide(
        self, views: list[View], feats_primary: list[Features], pair: Any,
        timed: Callable[[str, Callable[[], Any]], Any],
    ) -> tuple[TwoViewGeometry | None, list[Features], Matches, ReconstructionError | None]:  # fmt: skip
        """The second fallback tier: wide-baseline descriptors, matching and pose; when that pose fails, the
        plane's poses ranked by dense consistency (:meth:`_plane_tiebreak`). Returns (geometry or None, the
        features its matches index, the tier's filtered matches, the failure)."""
        wide = self.wide_descriptors
        assert wide is not None
        logger.debug("still too few verified matches: retrying with %s", wide.name)
        feats_w = timed("descriptors (wide)", lambda: wide(views, pair))
        matches_w: Matches = timed("matching (wide)", lambda: self.matcher(feats_w[0], feats_w[1]))
        geometry_w, failure_w = self._try_pose(views, matches_w, pair, timed, "pose (wide)")
        if geometry_w is not None and len(geometry_w.inliers) < self.config.wide_min_inliers:
            # a handful of matches at a wide baseline is a guess that guided matching would then "confirm"
            # (CO3D 74°: 17 of 34 verified, grown to 437 guided matches 11° off, passed the confidence)
            failure_w = ReconstructionError(
                f"pose could not be estimated: {len(geometry_w.inliers)} verified matches, need at least "
                f"{self.config.wide_min_inliers} at a wide baseline"
            )
            geometry_w = None
        if geometry_w is not None:
            geometry_w.info["descriptors_tier"] = "wide"  # type: ignore[assignment]
            return geometry_w, feats_w, matches_w, None
        if self.config.plane_tiebreak_margin is None:
            return None, feats_w, matches_w, failure_w
        tied = timed("pose (plane tie-break)", lambda: self._plane_tiebreak(views, feats_primary, matches_w, pair))
        if tied is None:
            return None, feats_w, matches_w, failure_w
        tied.info["descriptors_tier"] = "wide+plane-tiebreak"  # type: ignore[assignment]
        return tied, feats_primary, matches_w, None

    def _plane_tiebreak(
        self, views: list[View], feats: list[Features], matches: Matches, pair: Any
    ) -> TwoViewGeometry | None:
        """Rank the physical poses of the matches' dominant plane by dense consistency and re-estimate the best.

        A plane seen from two views has two relative poses that explain its matches equally well; the true one
        also explains the scene off the plane. The plane's poses are scored by :func:`plane_poses` (keypoints of
        ``feats`` matched along each one's epipolar lines that it explains off the plane: matches on the plane are
        explained by every candidate and only dilute the margin; CO3D 39°: 1046 against 845 guided matches,
        1.24×; off the plane 448 against 270, 1.66×, the true pose first). The best must score
        ``plane_tiebreak_margin`` times every distinct rival and at least ``plane_tiebreak_min``; the pose stage
        then re-estimates the pose from its guided matches (all its checks apply), and the result must stay within
        ``guided_max_change_deg`` of the candidate.

        Returns:
            the geometry (``info["plane_tiebreak"]``: the candidates' scores, best first), or None.
        """
        c = self.config
        assert c.plane_tiebreak_margin is not None
        if len(matches) < c.pose.min_inliers or c.guided_band_px is None:
            return None
        if any(v.intrinsics_source == "prior" for v in views):
            return None  # the decomposition needs the intrinsics (CO3D 62°, prior focal: a pose 7° off passed)
        plane = dominant_plane(matches, c.pose)
        if plane is None or not tiebreak_plane_ok(int(plane[1].sum()), len(matches), c):
            return None
        scored = plane_poses(views, feats, matches, *plane, c)
        scores = [s.score for s in scored]
        logger.debug("plane tie-break: candidates explain %s guided matches off the plane", scores)
        if not tiebreak_winner_ok(scores, c):
            return None
        R_best, t_best, guided = scored[0].R, scored[0].t, scored[0].guided
        guided.counts = {**matches.counts, **guided.counts}
        try:
            geometry = self.pose(views[0], views[1], guided, pair)
        except ReconstructionError:
            return None
        if (
            rotation_error_deg(geometry.R, R_best) > c.guided_max_change_deg[0]
            or translation_direction_error_deg(geometry.t, t_best) > c.guided_max_change_deg[1]
        ):
            return None
        geometry.info["plane_tiebreak"] = scores  # type: ignore[assignment]
        return geometry

    def _guided(
        self, views: list[View], feats: list[Features], geometry: TwoViewGeometry, pair: Any,
        timed: Callable[[str, Callable[[], Any]], Any],
    ) -> TwoViewGeometry:  # fmt: skip
        """Epipolar-guided re-matching under the first pose; its pose is kept only if it verifies more
        matches and stays within ``guided_max_change_deg`` of the first."""
        c = self.config
        assert c.guided_band_px is not None
        if geometry.info.get("doubts"):
            # matches picked within the band of a doubtful pose (e.g. one built on the prior's focal) agree with
            # it: they cannot confirm it, and a refit would drop the pose stage's doubt
            return geometry
        F = fundamental_from_pose(geometry.R, geometry.t, geometry.K0, geometry.K1)
        guided = timed(
            "matching (guided)",
            lambda: guided_matches(feats[0], feats[1], F, band_px=c.guided_band_px, ratio=c.guided_ratio),
        )
        guided.counts = {**geometry.inliers.counts, **guided.counts}
        guided.counts.pop("verified", None)
        refined, _ = self._try_pose(views, guided, pair, timed, "pose (guided)")
        if (
            refined is not None
            and len(refined.inliers) > len(geometry.inliers)
            and rotation_error_deg(refined.R, geometry.R) <= c.guided_max_change_deg[0]
            and translation_direction_error_deg(refined.t, geometry.t) <= c.guided_max_change_deg[1]
        ):
            return refined
        return geometry
