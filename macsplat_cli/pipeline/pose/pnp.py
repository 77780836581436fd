"""The pose of a camera from 2-D ↔ 3-D correspondences (PnP + RANSAC): the neural backend's pose, from the
network's point map of view 1 in camera 0's frame.

PnP, not Procrustes: the network gives view 1's points in camera 0's frame only, and PnP needs one forward pass
where Procrustes needs two; depth errors along view 1's own rays do not move a point's projection, and a scale
disagreement between two passes would not matter. ``cv2.solvePnPRansac`` (SQPnP, EPnP when it asserts), then
Levenberg–Marquardt on the inliers. Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from ...errors import ReconstructionError

__all__ = ["PnPResult", "pose_from_pointmap"]

logger = logging.getLogger(__name__)


@dataclass
class PnPResult:
    """Pose of a camera from 2-D ↔ 3-D correspondences: ``x_cam = R·X + t``.

    Attributes:
        R: rotation. [3, 3]
        t: translation, in the points' units. [3]
        inliers: the RANSAC inliers. [N] bool
        median_error_px: median reprojection error of the inliers after refinement.
    """

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    median_error_px: float


def pose_from_pointmap(
    xy: np.ndarray,  # [N, 2]
    X: np.ndarray,  # [N, 3]
    K: np.ndarray,  # [3, 3]
    *,
    threshold_px: float = 5.0,
    iterations: int = 100,
    confidence: float = 0.999,
    min_points: int = 6,
) -> PnPResult:
    """The pose of the camera that sees the 3-D points ``X`` at pixels ``xy`` (PnP + RANSAC).

    For MASt3R: ``X`` = view 1's point map (expressed in camera 0's frame), ``xy`` = those pixels of
    view 1, ``K`` = view 1's intrinsics; the result is the relative pose ``X_cam1 = R·X_cam0 + t``.
    SQPnP inside RANSAC, then Levenberg–Marquardt on the inliers. Pixel centres at +0.5 (OpenCV's
    projection has none: a constant shift of both the pixels and the principal point, so no effect).

    Raises:
        ReconstructionError: fewer than ``min_points`` distinct finite correspondences, 3-D points along one line
            (a rotation about it is undetermined), or no pose found.
    """
    ok = np.isfinite(X).all(1) & np.isfinite(xy).all(1)
    X, xy = np.ascontiguousarray(X[ok], np.float64), np.ascontiguousarray(xy[ok], np.float64)
    n = len(X)
    distinct = len(np.unique(np.concatenate([X, xy], axis=1), axis=0)) if n else 0
    if distinct < max(min_points, 4):
        repeats = f" ({n} with repeats)" if distinct < n else ""
        raise ReconstructionError(
            f"pose could not be estimated: the network is confident about only {distinct} pixels of the second "
            f"view{repeats}"
        )
    spread = np.linalg.svd(X - X.mean(0), compute_uv=False)  # [3], descending
    if not spread[1] > 1e-6 * spread[0]:
        raise ReconstructionError(
            f"pose could not be estimated: the network's {n} confident points of the second view lie on one line"
        )
    K = np.asarray(K, np.float64)
    found, rvec, tvec, idx = False, None, None, None
    # SQPnP is the most accurate minimal solver, but OpenCV asserts on degenerate samples (e.g. nearly
    # coincident points); EPnP is the fallback.
    for method in (cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP):
        try:
            found, rvec, tvec, idx = cv2.solvePnPRansac(
                X, xy, K, None, iterationsCount=iterations, reprojectionError=threshold_px, confidence=confidence,
                flags=method,
            )  # fmt: skip
        except cv2.error as e:
            logger.debug("PnP (method %d) failed: %s", method, str(e).strip().splitlines()[-1])
            continue
        if found:
            break
    if (
        not found
        or idx is None
        or len(idx) < 4
        or rvec is None
        or tvec is None
        or not (np.isfinite(rvec).all() and np.isfinite(tvec).all())
    ):
        raise ReconstructionError(
            f"pose could not be estimated: no camera pose explains the network's point map of the second view "
            f"({n} confident pixels)"
        )
    inliers = np.zeros(n, bool)
    inliers[idx.reshape(-1)] = True
    try:
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], xy[inliers], K, None, rvec, tvec)
    except cv2.error as e:  # keep the RANSAC pose
        logger.debug("PnP refinement failed: %s", str(e).strip().splitlines()[-1])
    proj = cv2.projectPoints(X, rvec, tvec, K, None)[0].reshape(-1, 2)
    err = np.linalg.norm(proj - xy, axis=1)
    inliers = err < threshold_px  # re-classified after the refinement
    full = np.zeros(len(ok), bool)
    full[np.flatnonzero(ok)[inliers]] = True
    R = cv2.Rodrigues(rvec)[0]
    median = float(np.median(err[inliers])) if inliers.any() else float("nan")
    return PnPResult(R=R, t=tvec.reshape(3).astype(np.float64), inliers=full, median_error_px=median)
