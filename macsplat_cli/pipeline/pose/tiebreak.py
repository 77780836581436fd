"""The plane tie-break (issue 14, wide-baseline recall): a plane's two physical poses ranked by dense consistency.

A plane seen from two views has two relative poses that explain its matches equally well; the true one also
explains the scene off the plane. Each pose is scored by the keypoints matched along its epipolar lines
(:func:`~..matching.guided_matches`) that it explains in front of both cameras, off the plane (the plane's own
matches are explained by every candidate and would only dilute the margin). Only with known intrinsics (the
decomposition needs them). Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ...errors import ReconstructionError
from ...metrics import rotation_error_deg, translation_direction_error_deg
from ..matching import guided_matches
from ..slots import PairPass, PoseStage
from ..types import Features, Matches, TwoViewGeometry, View
from .config import (
    GUIDED_MAX_CHANGE_DEG,
    GUIDED_RATIO,
    HOMOGRAPHY_FACTOR,
    RANSAC_MAX_ITERS,
    SAME_POSE_DEG,
    PoseConfig,
    PoseSearchConfig,
)
from .geometry import MIN_TRANSLATION, epipolar_fit, fundamental_from_pose
from .robust import find_homography

__all__ = ["PlanePose", "dominant_plane", "plane_poses", "plane_tiebreak", "tiebreak_plane_ok", "tiebreak_winner_ok"]

logger = logging.getLogger(__name__)

PLANE_TIEBREAK_MIN = 100
"""The tie-break's winner must score at least this (guided matches it explains off the plane)."""
PLANE_TIEBREAK_PLANE = 30
"""The tie-break needs at least this many matches on the dominant plane..."""
PLANE_TIEBREAK_PLANE_SHARE = 0.5
"""...and this share of the matches (a "plane" of fewer gave a pose 11° off)."""
PLANE_TIEBREAK_FRONT = 0.5
"""A decomposition that puts less than this share of the plane's matches in front of both cameras is not a
physical pose."""
PLANE_TIEBREAK_OFF_PLANE = 3.0
"""A guided match is off the plane when its transfer error exceeds this many pose thresholds (every candidate
explains the plane's own matches: only the others are evidence)."""


def dominant_plane(matches: Matches, pose: PoseConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The homography of the matches' dominant plane (MAGSAC++ at ``HOMOGRAPHY_FACTOR`` pose thresholds) and which
    matches lie on it: ([3, 3], [M] bool), or None when none fits."""
    H, mask = find_homography(matches.xy0, matches.xy1, HOMOGRAPHY_FACTOR * pose.threshold_px, RANSAC_MAX_ITERS)
    if H is None or mask is None:
        return None
    return H, mask


def tiebreak_plane_ok(n_plane: int, n_matches: int) -> bool:
    """The plane tie-break's first guard: a dominant plane of ``PLANE_TIEBREAK_PLANE`` matches and
    ``PLANE_TIEBREAK_PLANE_SHARE`` of them."""
    return n_plane >= max(PLANE_TIEBREAK_PLANE, n_matches * PLANE_TIEBREAK_PLANE_SHARE)


def tiebreak_winner_ok(scores: Sequence[int], config: PoseSearchConfig) -> bool:
    """The plane tie-break's second guard on the candidates' scores (best first): at least ``PLANE_TIEBREAK_MIN``
    and ``plane_tiebreak_margin`` times the next one's."""
    assert config.plane_tiebreak_margin is not None
    if not scores or scores[0] < PLANE_TIEBREAK_MIN:
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
    config: PoseSearchConfig, pose: PoseConfig,
) -> list[PlanePose]:  # fmt: skip
    """The plane's physical poses, best score first (module docstring).

    Each decomposition of ``H`` (known intrinsics) that puts ``PLANE_TIEBREAK_FRONT`` of the plane's matches
    (``on_plane``) in front of both cameras, once per distinct pose (``SAME_POSE_DEG``), is scored by the keypoints
    of ``feats`` matched within ``guided_band_px`` of its epipolar lines that it explains (Sampson distance below
    the pose threshold) in front of both cameras and that the plane does not (transfer error over
    ``PLANE_TIEBREAK_OFF_PLANE`` pose thresholds).
    """
    c = config
    assert c.guided_band_px is not None
    thr = pose.threshold_px
    K0, K1 = views[0].K, views[1].K

    def off_plane(m: Matches) -> np.ndarray:  # [N] bool: farther than the band from the plane's transfer
        p = np.c_[m.xy0, np.ones(len(m))] @ H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(p[:, :2] / p[:, 2:] - m.xy1, axis=1)
        return ~(err <= PLANE_TIEBREAK_OFF_PLANE * thr)

    _, Rs, ts, _ = cv2.decomposeHomographyMat(np.linalg.inv(K1) @ H @ K0, np.eye(3))
    poses: list[PlanePose] = []
    rot_deg, dir_deg = SAME_POSE_DEG
    for R, t in zip(Rs, ts):
        t = t.ravel()
        if np.linalg.norm(t) < MIN_TRANSLATION:
            continue
        t = t / np.linalg.norm(t)
        _, front = epipolar_fit(R, t, K0, K1, matches.xy0[on_plane], matches.xy1[on_plane])
        if front.mean() < PLANE_TIEBREAK_FRONT or any(
            rotation_error_deg(R, p.R) < rot_deg and translation_direction_error_deg(t, p.t) < dir_deg for p in poses
        ):
            continue  # the plane behind a camera, or the same pose again
        F = fundamental_from_pose(R, t, K0, K1)
        g = guided_matches(feats[0], feats[1], F, band_px=c.guided_band_px, ratio=GUIDED_RATIO)
        d, front_g = epipolar_fit(R, t, K0, K1, g.xy0, g.xy1)
        # every candidate explains the plane by construction: only matches off it are evidence
        poses.append(PlanePose(R, t, int((front_g & (d < thr) & off_plane(g)).sum()), g))
    return sorted(poses, key=lambda p: -p.score)


def plane_tiebreak(
    views: Sequence[View], feats: Sequence[Features], matches: Matches, pair: PairPass, pose_stage: PoseStage,
    config: PoseSearchConfig, pose: PoseConfig,
) -> tuple[TwoViewGeometry, list[int]] | None:  # fmt: skip
    """Rank the physical poses of the matches' dominant plane and re-estimate the best (module docstring).

    The best must pass :func:`tiebreak_plane_ok` and :func:`tiebreak_winner_ok`; the pose stage ``pose_stage`` then
    re-estimates the pose from its guided matches (all its checks apply), and the result must stay within
    ``GUIDED_MAX_CHANGE_DEG`` of the candidate.

    Returns:
        ``(geometry, scores)`` (the candidates' scores, best first), or None.
    """
    c = config
    assert c.plane_tiebreak_margin is not None
    if len(matches) < pose.min_inliers or c.guided_band_px is None:
        return None
    if any(v.intrinsics_source == "prior" for v in views):
        return None  # the decomposition needs the intrinsics (with the prior's focal a pose 7° off passed)
    plane = dominant_plane(matches, pose)
    if plane is None or not tiebreak_plane_ok(int(plane[1].sum()), len(matches)):
        return None
    scored = plane_poses(views, feats, matches, *plane, c, pose)
    scores = [s.score for s in scored]
    logger.debug("plane tie-break: candidates explain %s guided matches off the plane", scores)
    if not tiebreak_winner_ok(scores, c):
        return None
    R_best, t_best, guided = scored[0].R, scored[0].t, scored[0].guided
    guided.counts = {**matches.counts, **guided.counts}
    try:
        geometry = pose_stage(views[0], views[1], guided, pair)
    except ReconstructionError:
        return None
    if (
        rotation_error_deg(geometry.R, R_best) > GUIDED_MAX_CHANGE_DEG[0]
        or translation_direction_error_deg(geometry.t, t_best) > GUIDED_MAX_CHANGE_DEG[1]
    ):
        return None
    return geometry, scores
