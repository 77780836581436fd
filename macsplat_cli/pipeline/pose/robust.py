"""OpenCV's robust estimators (MAGSAC++) within their preconditions: no ``cv2.error`` leaves the pose stage.

Fewer distinct correspondences than a model needs, or a non-finite one, and OpenCV is not called; a degenerate
minimal sample (repeated correspondences: one keypoint with several SIFT orientations matched more than once) is
retried on the distinct correspondences.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import cv2
import numpy as np

from ...camera_math import scale_focal
from ...errors import ReconstructionError
from .config import RANSAC_MAX_ITERS, PoseConfig
from .geometry import cheirality, homog

__all__ = [
    "MIN_POINTS_ESSENTIAL",
    "MIN_POINTS_FUNDAMENTAL",
    "MIN_POINTS_HOMOGRAPHY",
    "distinct_matches",
    "essential_pose",
    "find_fundamental",
    "find_homography",
    "robust_fit",
]

logger = logging.getLogger(__name__)

RANSAC_CONFIDENCE = 0.99999
"""RANSAC confidence of the essential and fundamental fits."""

MIN_POINTS_ESSENTIAL = 5
"""Correspondences the five-point essential-matrix solver needs."""
MIN_POINTS_FUNDAMENTAL = 8
"""Correspondences a fundamental matrix needs (OpenCV's USAC samples 7; the 8-point refit needs 8)."""
MIN_POINTS_HOMOGRAPHY = 4
"""Correspondences a homography needs."""


def distinct_matches(xy0: np.ndarray, xy1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct correspondences among ``xy0, xy1`` [M, 2]: (index of the first occurrence of each [K], which
    of them each match repeats [M]). One keypoint can carry several descriptors (SIFT: one per dominant
    orientation), so the same pair of pixels can be matched more than once."""
    if len(xy0) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, first, inverse = np.unique(
        np.concatenate([xy0, xy1], axis=1), axis=0, return_index=True, return_inverse=True
    )  # fmt: skip
    order = np.argsort(first)  # keep the matches' order: the distinct ones as they first appear
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[np.asarray(inverse).reshape(-1)]


def robust_fit(
    fit: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray | None, np.ndarray | None]],
    xy0: np.ndarray,
    xy1: np.ndarray,
    min_points: int,
    what: str,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """An OpenCV robust estimator, ``fit(xy0, xy1) → (model, inlier mask)``, run within its preconditions.

    The points go in as contiguous float64 [M, 2]; fewer than ``min_points`` distinct correspondences, or a
    non-finite one, and OpenCV is not called. OpenCV's USAC asserts (``!model.empty()``) when a minimal sample
    is degenerate, which repeated correspondences make likely: then the distinct correspondences are fitted
    instead, and each repeat takes the inlier flag of its first occurrence. The full set is tried first so that
    every input OpenCV accepts keeps its result.

    Returns:
        ``(model, mask)``: the model and the inlier flags [M] bool, or ``(None, None)`` when no model fits.
        Never raises ``cv2.error``.
    """
    a = np.ascontiguousarray(xy0, np.float64).reshape(-1, 2)
    b = np.ascontiguousarray(xy1, np.float64).reshape(-1, 2)
    if len(a) != len(b) or not (np.isfinite(a).all() and np.isfinite(b).all()):
        return None, None
    first, inverse = distinct_matches(a, b)
    if len(first) < min_points:
        return None, None
    subsets = [None] if len(first) == len(a) else [None, first]
    for sub in subsets:
        try:
            model, mask = fit(a, b) if sub is None else fit(a[sub], b[sub])
        except cv2.error as e:
            logger.debug("%s on %d matches (%d distinct): %s", what, len(a), len(first), str(e).strip()[-120:])
            continue
        if model is None or mask is None or model.size == 0 or not np.isfinite(model).all():
            return None, None
        flags = np.asarray(mask).reshape(-1).astype(bool)
        return model, (flags if sub is None else flags[inverse])
    return None, None


def find_homography(
    xy0: np.ndarray, xy1: np.ndarray, threshold_px: float, max_iters: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """MAGSAC++ homography of the matches ``xy0 → xy1`` [M, 2]: ([3, 3], inliers [M] bool), or (None, None) when
    none fits or the matches cannot determine one (:func:`robust_fit`)."""
    return robust_fit(
        lambda a, b: cv2.findHomography(a, b, cv2.USAC_MAGSAC, threshold_px, maxIters=max_iters),
        xy0, xy1, MIN_POINTS_HOMOGRAPHY, "homography",
    )  # fmt: skip


def find_fundamental(xy0: np.ndarray, xy1: np.ndarray, cfg: PoseConfig) -> tuple[np.ndarray | None, np.ndarray | None]:
    """MAGSAC++ fundamental matrix of the matches [M, 2] (it needs no intrinsics): ([3, 3], inliers [M] bool), or
    (None, None)."""
    return robust_fit(
        lambda a, b: cv2.findFundamentalMat(
            a, b, cv2.USAC_MAGSAC, cfg.threshold_px, RANSAC_CONFIDENCE, RANSAC_MAX_ITERS
        ),
        xy0, xy1, MIN_POINTS_FUNDAMENTAL, "fundamental matrix",
    )  # fmt: skip


def _essential(x0v: np.ndarray, x1v: np.ndarray, f_v: float, cfg: PoseConfig) -> tuple[np.ndarray, np.ndarray]:
    Kv = np.array([[f_v, 0.0, 0.0], [0.0, f_v, 0.0], [0.0, 0.0, 1.0]])
    E, inl = robust_fit(
        lambda a, b: cv2.findEssentialMat(
            a, b, Kv, method=cv2.USAC_MAGSAC, prob=RANSAC_CONFIDENCE, threshold=cfg.threshold_px,
            maxIters=RANSAC_MAX_ITERS,
        ),
        x0v, x1v, MIN_POINTS_ESSENTIAL, "essential matrix",
    )  # fmt: skip
    if E is None or E.shape != (3, 3) or inl is None:
        raise ReconstructionError("pose could not be estimated: no essential matrix fits the matches")
    R, t, front = cheirality(E, x0v[inl] / f_v, x1v[inl] / f_v)
    good = np.zeros_like(inl)
    good[np.flatnonzero(inl)[front]] = True
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T, good


def essential_pose(
    xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool], log_focal: float,
    cfg: PoseConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The verified pose at a focal hypothesis: MAGSAC++ essential matrix and cheirality.

    The views whose focal is ``unknown`` get theirs scaled by ``exp(log_focal)``; the points are mapped through
    ``K⁻¹`` into one virtual camera whose focal length is the mean of the two, so that the inlier threshold stays
    in pixels even when the two images differ.

    Returns:
        ``(R, t, good)``: [3, 3], unit [3], and the matches verified (inliers in front of both cameras) [M] bool.

    Raises:
        ReconstructionError: no essential matrix fits the matches.
    """
    K0s = scale_focal(K0, log_focal) if unknown[0] else K0
    K1s = scale_focal(K1, log_focal) if unknown[1] else K1
    f_v = float(np.mean([K0s[0, 0], K0s[1, 1], K1s[0, 0], K1s[1, 1]]))
    x0n = homog(xy0) @ np.linalg.inv(K0s).T
    x1n = homog(xy1) @ np.linalg.inv(K1s).T
    T, good = _essential(np.ascontiguousarray(x0n[:, :2] * f_v), np.ascontiguousarray(x1n[:, :2] * f_v), f_v, cfg)
    return T[:3, :3], T[:3, 3], good
