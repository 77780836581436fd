"""Two-view geometry: the epipolar constraint of a relative pose, triangulation, cheirality, and the decompositions
of an essential matrix and of a homography into poses.

Conventions: ``X_cam1 = R · X_cam0 + t``, ``|t| = 1``; pixels ``xy`` [M, 2], normalised rays ``x = K⁻¹ (xy, 1)``
[M, 3].
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ...metrics import angle_between_deg, rotation_angle_deg
from ...rotations import nearest_rotation

__all__ = [
    "MIN_TRANSLATION",
    "cheirality",
    "decompose_homography",
    "epipolar_fit",
    "fundamental_from_inverses",
    "fundamental_from_pose",
    "homog",
    "hull_share",
    "line_spread_px",
    "parallax_deg",
    "same_pose",
    "sampson_distance",
    "support",
    "triangulate",
]


MIN_TRANSLATION = 1e-9
"""A decomposition of a homography with a shorter translation has none (a pure rotation): not a pose candidate."""


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[v]×``. [3] → [3, 3]"""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def homog(xy: np.ndarray) -> np.ndarray:
    """``xy`` with a column of ones. [M, 2] → [M, 3]"""
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)


def fundamental_from_pose(R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray) -> np.ndarray:
    """``F = K1⁻ᵀ [t]× R K0⁻¹`` (x1ᵀ F x0 = 0 for pixels). [3, 3]"""
    return fundamental_from_inverses(R, t, np.linalg.inv(K0), np.linalg.inv(K1).T)


def fundamental_from_inverses(R: np.ndarray, t: np.ndarray, K0_inv: np.ndarray, K1_inv_t: np.ndarray) -> np.ndarray:
    """:func:`fundamental_from_pose` from ``K0⁻¹`` and ``K1⁻ᵀ``, for callers reusing them across poses. [3, 3]"""
    return K1_inv_t @ skew(t) @ R @ K0_inv


def sampson_distance(F: np.ndarray, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Signed first-order geometric distance of each match to ``F`` [3, 3] (or to each of a stack of them,
    ``F: [P, 3, 3]`` → ``[P, M]``: one call for all of a finite-difference Jacobian's poses), in pixels. [M]"""
    p0, p1 = homog(xy0), homog(xy1)
    Fp0 = p0 @ np.swapaxes(F, -1, -2)  # [(P,) M, 3]
    Ftp1 = p1 @ F
    e = np.sum(p1 * Fp0, axis=-1)
    denom = Fp0[..., 0] ** 2 + Fp0[..., 1] ** 2 + Ftp1[..., 0] ** 2 + Ftp1[..., 1] ** 2
    return e / np.sqrt(np.maximum(denom, 1e-30))


def triangulate(R: np.ndarray, t: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Midpoint triangulation of normalised rays; points in camera 0. [M, 3] (NaN if parallel)"""
    d0 = x0 / np.linalg.norm(x0, axis=1, keepdims=True)
    d1 = (x1 / np.linalg.norm(x1, axis=1, keepdims=True)) @ R  # ray of camera 1 in camera-0 axes
    c1 = -R.T @ t
    # minimise |a d0 − (c1 + b d1)|²
    b_ = np.sum(d0 * d1, axis=1)
    w0 = c1 @ d0.T
    w1 = d1 @ c1
    den = 1.0 - b_**2
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (w0 - b_ * w1) / den
        b = (b_ * w0 - w1) / den
    p = 0.5 * (a[:, None] * d0 + (c1 + b[:, None] * d1))
    p[den < 1e-12] = np.nan
    return p


def parallax_deg(R: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Angle between the two viewing rays of each match once the rotation is removed. [M]"""
    return np.asarray(angle_between_deg(x0 @ R.T, x1))


def cheirality(E: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The decomposition of E that puts most points in front of both cameras.

    Unlike ``cv2.recoverPose``, no distance cut-off: points near infinity (small baselines, pure rotations) still
    count, so the parallax check can report a missing baseline instead of a misleading "0 verified matches".
    ``x0, x1``: normalised coordinates [M, 2].

    Returns:
        ``(R, t, in_front)`` with ``|t| = 1``. [3, 3], [3], [M] bool
    """
    R1, R2, t_col = cv2.decomposeEssentialMat(E)
    t = np.asarray(t_col).ravel() / max(float(np.linalg.norm(t_col)), 1e-30)
    h0, h1 = homog(x0), homog(x1)
    best = None
    for R in (R1, R2):
        for tt in (t, -t):
            X = triangulate(R, tt, h0, h1)
            z1 = X @ R[2] + tt[2]
            front = np.isfinite(X).all(1) & (X[:, 2] > 0) & (z1 > 0)
            if best is None or front.sum() > best[2].sum():
                best = (R, tt, front)
    assert best is not None
    return best


def decompose_homography(Hn: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The (R, t) candidates of a normalised homography [3, 3], each R the nearest rotation to OpenCV's (its
    rotations are orthonormal only to ~1e-9; Levenberg–Marquardt multiplies small rotations onto R and would keep
    that defect in the returned pose)."""
    _, Rs, ts, _ = cv2.decomposeHomographyMat(Hn, np.eye(3))
    return [nearest_rotation(R) for R in Rs], list(ts)


def epipolar_fit(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sampson distance (px) of each match to a relative pose, and whether it triangulates in front of both
    cameras. [M], [M] bool"""
    if len(xy0) == 0:
        return np.zeros(0), np.zeros(0, bool)
    d = np.abs(sampson_distance(fundamental_from_pose(R, t, K0, K1), xy0, xy1))
    X = triangulate(R, t, homog(xy0) @ np.linalg.inv(K0).T, homog(xy1) @ np.linalg.inv(K1).T)
    with np.errstate(invalid="ignore"):
        front = np.isfinite(X).all(1) & (X[:, 2] > 0) & (X @ R[2] + t[2] > 0)
    return d, front


def support(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, threshold: float
) -> np.ndarray:
    """Matches a relative pose explains: Sampson distance below ``threshold`` px and triangulated in front of
    both cameras. [M] bool"""
    d, front = epipolar_fit(R, t, K0, K1, xy0, xy1)
    return (d < threshold) & front


def same_pose(Ra: np.ndarray, ta: np.ndarray, Rb: np.ndarray, tb: np.ndarray, limits: tuple[float, float]) -> bool:
    """Whether two poses differ by less than ``limits`` (rotation °, translation direction °)."""
    return rotation_angle_deg(Ra @ Rb.T) < limits[0] and float(angle_between_deg(ta, tb)) < limits[1]


def line_spread_px(xy: np.ndarray) -> float:
    """RMS distance (px) of the points ``xy`` [M, 2] from their best-fitting line (0: collinear)."""
    if len(xy) < 3:
        return 0.0
    s = np.linalg.svd(xy - xy.mean(0), compute_uv=False)
    return float(s[-1]) / math.sqrt(len(xy))


def hull_share(xy: np.ndarray, width: int, height: int) -> float:
    """The share of a ``width × height`` photo that the convex hull of the points ``xy`` [M, 2] covers."""
    if len(xy) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(np.ascontiguousarray(xy, np.float32)))) / float(width * height)
