"""The settings of stage 4: the two-view pose (:class:`PoseConfig`) and the search around it with its acceptance
(:class:`PoseSearchConfig`), the knobs a user or a preset turns. Every other value of the stage is a named module
constant beside the code that uses it (those several modules share are here); which measurement chose each is in
benchmarks/history/settings.md and benchmarks/history/pose.md.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..descriptors import SiftConfig
from ..learned.config import LearnedConfig

__all__ = [
    "FALLBACK_SIFT",
    "GUIDED_MAX_CHANGE_DEG",
    "GUIDED_RATIO",
    "HOMOGRAPHY_FACTOR",
    "PoseConfig",
    "PoseSearchConfig",
    "RANSAC_MAX_ITERS",
    "SAME_POSE_DEG",
    "WIDE_SIFT",
]

RANSAC_MAX_ITERS = 10000
"""RANSAC iterations of every robust fit of the stage (essential, fundamental, homography)."""
HOMOGRAPHY_FACTOR = 1.5
"""A homography's inlier threshold, in ``threshold_px``: a plane's transfer error adds both views' localisation
errors, the Sampson distance only their component across the line."""
SAME_POSE_DEG = (1.0, 5.0)
"""Two poses within this rotation and translation-direction difference (°) are the same."""
GUIDED_RATIO = 0.95
"""The ratio test among the candidates in the guided re-matching's band."""
GUIDED_MAX_CHANGE_DEG = (3.0, 10.0)
"""A guided (or tie-break) pose that moved more than this (rotation, translation direction, °) from the pose that
guided it is rejected: it refines a pose, it must not jump to another."""
FALLBACK_SIFT = SiftConfig(affine=True, detect_size=512, max_keypoints=4000)
"""The fallback tier's descriptors: affine-simulated SIFT, slower, but it matches across wide baselines."""
WIDE_SIFT = SiftConfig(affine=True, detect_size=640, max_keypoints=8000, max_tilt=4.0)
"""The wide tier's descriptors: affine SIFT with more tilts at a finer detection size."""


@dataclass
class PoseConfig:
    """The classical two-view pose (:func:`~.essential.estimate_pose`).

    Pixel thresholds apply at a working long side of :data:`~.essential.REFERENCE_SIDE`; below it they shrink with
    the image.

    Args:
        threshold_px: inlier threshold on the epipolar (Sampson) distance, working-resolution px (> 0).
        min_inliers: fewer verified matches than this is a failure, and the support every backend's pose needs (≥ 8).
        refine: run the non-linear refinement.
        estimate_focal: self-calibrate views whose intrinsics come from the field-of-view prior.
        min_parallax_deg: a smaller median parallax of the verified matches (°) is no baseline (a pure rotation).
    """

    threshold_px: float = 1.0
    min_inliers: int = 15
    refine: bool = True
    estimate_focal: bool = True
    min_parallax_deg: float = 0.5


@dataclass
class PoseSearchConfig:
    """The search for the pose (:class:`~.search.PoseSearch`): descriptor tiers, plane tie-break, guided re-matching
    and the acceptance.

    Args:
        fallback: when the primary descriptors verify fewer than ``fallback_min_inliers`` matches (or the pose
            fails), the descriptor → matching → pose chain runs again with :data:`FALLBACK_SIFT`; the result with
            more verified matches is kept.
        fallback_min_inliers: fewer verified matches than this and the fallback tier runs (≥ 0).
        wide: the second fallback tier for wide baselines (:data:`WIDE_SIFT`), run only when the primary and
            fallback tiers both gave no pose.
        plane_tiebreak_margin: when the wide tier's pose fails, the plane's physical poses are ranked by dense
            consistency (:func:`~.tiebreak.plane_tiebreak`); the best must score this many times the next one's
            (≥ 1). None: off.
        guided_band_px: after the first pose, all keypoints are matched again within this distance (px) of their
            epipolar lines (:func:`~..matching.guided_matches`) and the pose re-estimated; the result is kept if it
            verifies more matches. None: off.
        confidence: the checks of the final pose independent of the RANSAC (:func:`~.confidence.accept_pose`);
            off: only the pose stage's doubts and the support minimum apply.
        accept_low_confidence: a pose with doubts is written anyway (a warning) instead of refused.
        learned: the learned tier (ALIKED + LightGlue, :mod:`..learned`), run after the SIFT tiers when their pose
            fails or its matches do not support it; None: off (``--matcher sift``; ``presets.configure`` sets it).
        learned_primary: the learned matcher is the primary (and only) tier (``--matcher aliked``): its weight
            files are then required.
    """

    fallback: bool = True
    fallback_min_inliers: int = 100
    wide: bool = True
    plane_tiebreak_margin: float | None = 1.5
    guided_band_px: float | None = 2.0
    confidence: bool = True
    accept_low_confidence: bool = False
    learned: LearnedConfig | None = None
    learned_primary: bool = False
