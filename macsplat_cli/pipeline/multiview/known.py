"""Known poses as input (``--poses cams.json``): the photos' cameras are given, so no pose is estimated.

Each selected pair's putative matches (the primary descriptors, the filtered matcher) are verified against the
epipolar geometry of the given poses instead of a pose search; the tracks are triangulated from the given cameras
and the scene comes out in their frame and scale (metric when the file says so).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...camera_formats import cameras_for_photos, load_camera_input
from ..pose import PoseResult
from ..pose.geometry import fundamental_from_pose, sampson_distance
from ..slots import DescribeStage, MatchStage
from ..types import TwoViewGeometry, View
from .pairwise import PairOutcome

__all__ = ["KnownPoses", "known_pose_pairs", "load_known_poses"]

KNOWN_POSE_MAX_PX = 2.0
"""With given poses (``--poses``), a match is kept within this Sampson distance (px) of their epipolar geometry: the
given poses are trusted to about a pixel (a calibrated rig's, an SfM's)."""


@dataclass
class KnownPoses:
    """The given cameras, per photo: world → camera ``R`` [N, 3, 3], ``t`` [N, 3]; the file's ``scale``."""

    R: np.ndarray
    t: np.ndarray
    scale: str


def load_known_poses(path: Path, views: Sequence[View]) -> KnownPoses:
    """The cameras of ``path`` for ``views``, matched to the photos by
    :func:`~macsplat_cli.camera_formats.cameras_for_photos` (by name; in order only when no camera is named after
    a photo).

    Raises:
        CameraFileError: the file is malformed, or does not give every photo a camera of its own.
    """
    cams = load_camera_input(path)  # a cameras file or a COLMAP model folder
    chosen = cameras_for_photos(cams, [v.path for v in views], path)
    W2C = np.stack([np.linalg.inv(c.cam_to_world) for c in chosen])
    return KnownPoses(W2C[:, :3, :3], W2C[:, :3, 3], cams.scale)


def known_pose_pairs(
    views: Sequence[View], pairs: Sequence[tuple[int, int]], describe: DescribeStage, match: MatchStage,
    poses: KnownPoses, max_sampson_px: float,
) -> list[PairOutcome]:  # fmt: skip
    """Each pair's matches that the given poses' epipolar geometry verifies (Sampson distance ≤ ``max_sampson_px``),
    as a :class:`PairOutcome` whose ``result`` holds the given relative pose (``|t| = 1``) and those matches."""
    out = []
    for i, j in pairs:
        t0 = time.perf_counter()
        vi, vj = views[i], views[j]
        fi, fj = describe([vi, vj], None)  # per-view features: no pair
        m = match(fi, fj)
        R = poses.R[j] @ poses.R[i].T
        t = poses.t[j] - R @ poses.t[i]
        base = float(np.linalg.norm(t))
        if base <= 0 or len(m) == 0:
            why = "the given cameras have the same centre" if base <= 0 else "no matches"
            out.append(PairOutcome(i, j, None, why, time.perf_counter() - t0))
            continue
        F = fundamental_from_pose(R, t / base, vi.K, vj.K)
        keep = np.abs(sampson_distance(F, m.xy0, m.xy1)) <= max_sampson_px
        inliers = m.subset(keep, "verified (given poses)")
        g = TwoViewGeometry(R, t / base, vi.K, vj.K, inliers)
        res = PoseResult(geometry=g, views=[vi, vj], tier="primary", features=[fi, fj], evidence=m)
        out.append(PairOutcome(i, j, res, None, time.perf_counter() - t0))
    return out
