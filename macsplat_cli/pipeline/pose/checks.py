"""The classical pose's own checks: degenerate matches before the estimate; too few inliers, no baseline, a low
inlier ratio and mirror images after it. Each failure is a :class:`~macsplat_cli.errors.ReconstructionError` whose
message says why, for the user.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ...errors import NonFiniteError, ReconstructionError, SameViewError
from ...metrics import rotation_angle_deg
from ..types import Matches, View
from .config import PoseConfig
from .diagnostics import PoseDiagnostics
from .geometry import fundamental_from_pose, homog, line_spread_px, parallax_deg, sampson_distance, triangulate
from .robust import MIN_POINTS_FUNDAMENTAL, distinct_matches

__all__ = ["check_finite", "check_matches", "final_inliers", "flipped_fraction", "summarise"]

MIN_INLIER_RATIO = 0.5
"""Smallest fraction of the matches that must agree with the pose (wrong poses had 28–37 %)."""
SAME_VIEW_SHIFT_PX = 0.5
"""The median displacement of the matches (px) below which two same-size photos may be one view."""
SAME_VIEW_STILL_PX = 1.0
"""A match that moves less than this (px) has not moved."""
SAME_VIEW_SHARE = 0.8
"""More than this share of matches that have not moved makes the two photos one view."""


def check_finite(v0: View, v1: View, matches: Matches) -> None:
    """Raises:
    NonFiniteError: a match coordinate or an intrinsic matrix holds NaN/Inf."""
    for name, a in (
        ("matches.xy0", matches.xy0),
        ("matches.xy1", matches.xy1),
        ("K of view 0", v0.K),
        ("K of view 1", v1.K),
    ):
        if not np.isfinite(a).all():
            raise NonFiniteError(f"{name} holds {int((~np.isfinite(a)).sum())} non-finite value(s) (NaN or Inf)")


def check_matches(v0: View, v1: View, xy0: np.ndarray, xy1: np.ndarray, cfg: PoseConfig) -> None:
    """Refuse matches ``xy0, xy1`` [M, 2] that cannot determine a pose: too few distinct ones, all along one line in
    a photo, or two photos of the same view (same size, the matches have not moved).

    Raises:
        ReconstructionError: with the reason; :class:`~macsplat_cli.errors.SameViewError` for the same view.
    """
    n = len(xy0)
    distinct, _ = distinct_matches(xy0, xy1)
    need = max(cfg.min_inliers, MIN_POINTS_FUNDAMENTAL)
    if len(distinct) < need:
        repeats = f" ({n} with repeats)" if len(distinct) < n else ""
        raise ReconstructionError(
            f"pose could not be estimated: only {len(distinct)} match{'es' if len(distinct) != 1 else ''} survived "
            f"filtering{repeats}, need at least {need}"
        )
    for k, xy in enumerate((xy0[distinct], xy1[distinct])):
        if line_spread_px(xy) < cfg.threshold_px:
            raise ReconstructionError(
                f"pose could not be estimated: the {len(distinct)} matches lie along one line in photo {k + 1} "
                "(within the inlier threshold), which leaves the relative pose undetermined"
            )
    if v0.image.shape == v1.image.shape:
        shift = np.median(np.linalg.norm(xy1 - xy0, axis=1))
        still = np.linalg.norm(xy1 - xy0, axis=1) < SAME_VIEW_STILL_PX
        if shift < SAME_VIEW_SHIFT_PX and np.mean(still) > SAME_VIEW_SHARE:
            raise SameViewError(
                f"the two images show the same view (median match displacement {shift:.2f} px): "
                "move the camera between the photos"
            )


def final_inliers(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, cfg: PoseConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Final inliers (small epipolar distance, in front of both cameras), Sampson distances, triangulated points
    and normalised coordinates. [M] bool, [M], [M, 3], [M, 3], [M, 3]"""
    F = fundamental_from_pose(R, t, K0, K1)
    d = np.abs(sampson_distance(F, xy0, xy1))
    x0n = homog(xy0) @ np.linalg.inv(K0).T
    x1n = homog(xy1) @ np.linalg.inv(K1).T
    X = triangulate(R, t, x0n, x1n)
    z1 = X @ R[2] + t[2]
    final = (d < cfg.threshold_px) & np.isfinite(X).all(1) & (X[:, 2] > 0) & (z1 > 0)
    return final, d, X, x0n, x1n


def summarise(
    R: np.ndarray, final: np.ndarray, d: np.ndarray, x0n: np.ndarray, x1n: np.ndarray, n: int, diag: PoseDiagnostics,
    cfg: PoseConfig,
) -> tuple[int, float]:  # fmt: skip
    """Record the inlier diagnostics of a pose in ``diag`` and raise on too few inliers, no baseline or a low
    inlier ratio. Returns the number of final inliers and their median parallax (°)."""
    n_final = int(final.sum())
    if n_final < cfg.min_inliers:
        raise ReconstructionError(
            f"pose could not be estimated: {n_final} verified matches after refinement, need at least {cfg.min_inliers}"
        )
    parallax = float(np.median(parallax_deg(R, x0n[final], x1n[final])))
    diag.inliers, diag.inlier_ratio = n_final, n_final / n
    diag.median_sampson_px, diag.rotation_deg = float(np.median(d[final])), rotation_angle_deg(R)
    if parallax < cfg.min_parallax_deg:
        raise ReconstructionError(
            f"no baseline: the median parallax of the {n_final} verified matches is {parallax:.2f}°, below "
            f"{cfg.min_parallax_deg}° (a pure rotation, or a scene too far away): move the camera sideways"
        )
    if n_final < MIN_INLIER_RATIO * n:
        raise ReconstructionError(
            f"pose is unreliable: only {n_final} of {n} matches ({100 * n_final / n:.0f} %) agree with the best "
            f"relative pose, need {100 * MIN_INLIER_RATIO:.0f} % (too little overlap or texture?)"
        )
    return n_final, parallax


def flipped_fraction(
    xy0: np.ndarray, xy1: np.ndarray, depth: np.ndarray | None = None, *, neighbours: int = 2,
    max_points: int = 2000, min_px: float = 4.0, max_depth_ratio: float = 1.2, min_sine: float = 0.05,
    min_surface: int = 10, min_surface_share: float = 0.25,
) -> float:  # fmt: skip
    """Share of the triangles (a match and its two nearest neighbours in photo 0) whose orientation flips in
    photo 1. Two views of a scene keep the orientation of nearby points (only depth discontinuities flip a
    few); a mirror image flips nearly all. 0 for fewer than 3 matches.

    Args:
        xy0, xy1: matched pixels. [N, 2]
        depth: triangulated depths (any scale): only triangles whose corners lie within ``max_depth_ratio`` of
            each other count — a patch of one surface; a triangle spanning an object and the background behind it
            flips legitimately when the camera orbits the object. [N]
        neighbours: corners of a triangle besides the match.
        max_points: at most this many matches (evenly subsampled).
        min_px: closer neighbours are skipped (near-duplicate keypoints: their triangles are noise).
        max_depth_ratio: see ``depth``.
        min_sine: a triangle whose sine of the corner angle is below this (nearly collinear) is skipped: its sign is
            noise.
        min_surface, min_surface_share: with fewer one-surface triangles than this many and this share of all,
            the depths are not trusted (a wrong pose) and every triangle counts.
    """
    n = len(xy0)
    if n < neighbours + 1:
        return 0.0
    if n > max_points:
        sel = np.linspace(0, n - 1, max_points).astype(np.int64)
        xy0, xy1, n = xy0[sel], xy1[sel], max_points
        depth = depth[sel] if depth is not None else None
    p = torch.from_numpy(np.ascontiguousarray(xy0, np.float64))
    d = torch.cdist(p, p)  # [N, N]; far faster than a broadcast norm and a full argsort
    d[d < min_px] = math.inf  # itself, and near-duplicate keypoints (affine-simulated SIFT): their triangles are noise
    dist, nn_t = d.topk(neighbours, dim=1, largest=False)  # the nearest first
    nn = nn_t.numpy()  # [N, 2]
    i = np.flatnonzero(np.isfinite(dist.numpy()).all(1))
    j, k = nn[i, 0], nn[i, 1]
    a0, b0 = xy0[j] - xy0[i], xy0[k] - xy0[i]
    a1, b1 = xy1[j] - xy1[i], xy1[k] - xy1[i]
    s0 = a0[:, 0] * b0[:, 1] - a0[:, 1] * b0[:, 0]
    s1 = a1[:, 0] * b1[:, 1] - a1[:, 1] * b1[:, 0]
    ok = (np.abs(s0) > min_sine * (np.linalg.norm(a0, axis=1) * np.linalg.norm(b0, axis=1) + 1e-12)) & (
        np.abs(s1) > min_sine * (np.linalg.norm(a1, axis=1) * np.linalg.norm(b1, axis=1) + 1e-12)
    )
    if depth is not None:
        z = np.stack([depth[i], depth[j], depth[k]], 1)
        surface = ok & (z.min(1) > 0) & (z.max(1) <= max_depth_ratio * z.min(1))
        if surface.sum() >= max(min_surface, min_surface_share * ok.sum()):
            ok = surface
    if not ok.any():
        return 0.0
    return float(np.mean(np.sign(s0[ok]) != np.sign(s1[ok])))
