"""A new photo's pose from its matches to triangulated points: PnP with RANSAC, or — when PnP finds too few
inliers — anchored on an accepted pair with a registered photo: the pair's rotation and translation direction,
only the baseline's length left to the points (a one-parameter fit, RANSAC over single points).

The anchored pose needs far fewer correct correspondences than PnP's six degrees of freedom: on wide pairs the
matches that chain three photos are few, and epipolar-guided matches that are right in two views can be wrong in the
third (measured on CO3D, benchmarks/history/multiview.md).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["anchored_pose", "pair_anchor", "pnp_pose", "reprojection_px"]


def reprojection_px(obj: np.ndarray, xy: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Reprojection error of each point (inf behind the camera). obj [M, 3], xy [M, 2] → [M]"""
    p = (obj @ R.T + t) @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(p[:, :2] / p[:, 2:3] - xy, axis=1)
    return np.where(p[:, 2] > 0, e, np.inf)


def pnp_pose(
    obj: np.ndarray, xy: np.ndarray, K: np.ndarray, threshold_px: float
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """PnP (EPnP in RANSAC, then Levenberg–Marquardt on the inliers): ``(R, t, inliers)`` or None."""
    if len(obj) < 6:
        return None
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, xy, K, None, iterationsCount=2000, reprojectionError=threshold_px,
                                             confidence=0.9999, flags=cv2.SOLVEPNP_EPNP)  # fmt: skip
    if not ok or inl is None or len(inl) < 6:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl[:, 0]], xy[inl[:, 0]], K, None, rvec, tvec)
    R, t = cv2.Rodrigues(rvec)[0], tvec[:, 0]
    return R, t, int((reprojection_px(obj, xy, K, R, t) <= threshold_px).sum())


def pair_anchor(
    R_pair: np.ndarray, t_pair: np.ndarray, R_r: np.ndarray, t_r: np.ndarray, new_is_second: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The new photo's rotation and its translation as ``a + s·b`` from a pair (``X_2 = R_pair X_1 + s t_pair``)
    with a registered photo at ``(R_r, t_r)``: ``(R, a, b)``."""
    if new_is_second:
        return R_pair @ R_r, R_pair @ t_r, t_pair
    return R_pair.T @ R_r, R_pair.T @ t_r, -R_pair.T @ t_pair


def anchored_pose(
    obj: np.ndarray, xy: np.ndarray, K: np.ndarray, R: np.ndarray, a: np.ndarray, b: np.ndarray,
    threshold_px: float,
) -> tuple[np.ndarray, int] | None:  # fmt: skip
    """The translation ``a + s·b`` (s > 0) that reprojects the most points within ``threshold_px``: every point's
    own ``s`` (least squares of its ray constraint) is a candidate, the best one refined on its inliers.
    ``(t, inliers)`` or None."""
    if len(obj) == 0:
        return None
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ np.linalg.inv(K).T
    c = np.cross(rays, obj @ R.T + a)
    d = np.cross(rays, np.broadcast_to(b, rays.shape))
    s = -np.sum(c * d, 1) / np.maximum(np.sum(d * d, 1), 1e-300)
    cand = np.unique(s[s > 0])
    if cand.size == 0:
        return None
    if cand.size > 400:  # enough to hit the consensus: the inliers' own values cluster
        cand = cand[np.linspace(0, cand.size - 1, 400).astype(int)]
    P = obj @ R.T + a  # [M, 3]; for each candidate: K (P + s b)
    Q = (P[None] + cand[:, None, None] * b) @ K.T  # [C, M, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(Q[..., :2] / Q[..., 2:3] - xy, axis=2)
    inl = (e <= threshold_px) & (Q[..., 2] > 0)
    best = int(np.argmax(inl.sum(1)))
    keep = inl[best]
    s_best = float(np.sum(c[keep] * d[keep] * -1) / max(np.sum(d[keep] * d[keep]), 1e-300)) if keep.any() else 0.0
    s_best = s_best if s_best > 0 else float(cand[best])
    t = a + s_best * b
    return t, int((reprojection_px(obj, xy, K, R, t) <= threshold_px).sum())
