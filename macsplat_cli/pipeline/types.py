"""Typed data passed between the pipeline stages (one paper stage, one module).

Stages and their interfaces (each backend implements the same callable signature):

====================  =========================================  ======================
stage                 input → output                             module
====================  =========================================  ======================
images/intrinsics     paths → :class:`View` ×2                   ``views.py``
descriptors           :class:`View` → :class:`Features`          ``descriptors.py``
filtered matching     :class:`Features` ×2 → :class:`Matches`    ``matching.py``
pose                  :class:`Matches` → :class:`TwoViewGeometry`  ``pose/``
dense geometry        views + geometry → :class:`DepthMap` ×2    ``depth.py``
Gaussian prediction   views + geometry + depths → GaussianMaps   ``gaussian_init.py``
====================  =========================================  ======================

All pixel coordinates are continuous, at the working resolution, with pixel centres at
+0.5 (the convention of :mod:`macsplat_cli.cameras`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..cameras import Camera
from ..distortion import Distortion

__all__ = [
    "DepthMap", "Features", "FocalEvidence", "IntrinsicsSource", "MatchSet", "Matches", "PoseSource", "TwoViewGeometry",
    "View",
]  # fmt: skip

IntrinsicsSource = Literal["file", "focal", "exif", "prior", "estimated"]
"""Where a view's K came from: ``--intrinsics`` file, ``--focal``, EXIF 35 mm focal,
the 60° field-of-view prior, or the prior refined from the matches."""


@dataclass
class View:
    """One input photo at the working resolution.

    Attributes:
        name: identifier (the file stem).
        path: the file it was read from.
        image: colour in [0, 1]. [H, W, 3] float32
        mask: pixels to reconstruct (False where the file's alpha < 0.5). [H, W] bool
        K: intrinsics at the working resolution. [3, 3] float64
        original_size: (width, height) of the upright original photo.
        intrinsics_source: where ``K`` came from.
        detail: the photo at up to ``DETAIL_SIZE`` px on the long side (never upsampled),
            for stages that benefit from more pixels than the working size (keypoints).
            Same aspect as the original. [h, w, 3] float32
        undistorted: the lens distortion the photo was undistorted from at load (``image``, ``mask`` and
            ``detail`` are then the pinhole photo of ``K``), else None.
    """

    name: str
    path: Path
    image: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    original_size: tuple[int, int]
    intrinsics_source: IntrinsicsSource
    detail: np.ndarray | None = None
    undistorted: Distortion | None = None

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def gray(self) -> np.ndarray:
        """Luma (Rec. 601). [H, W] float32"""
        return (self.image @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.float32)

    def camera(self, cam_to_world: np.ndarray, *, original_size: bool = False) -> Camera:
        """This view as a :class:`Camera` at the working (or original) resolution."""
        cam = Camera(self.name, self.width, self.height, self.K, cam_to_world)
        return cam.rescaled(*self.original_size) if original_size else cam


@dataclass
class Features:
    """Descriptors of one view, each with a confidence.

    Sparse backends give keypoints; dense backends give a map flattened row-major, with
    ``grid`` its (rows, cols) so it can be reshaped.

    Attributes:
        xy: pixel coordinates at the working resolution. [M, 2] float64
        desc: L2-normalised descriptors (cosine similarity = dot product). [M, D] float32
        conf: confidence of each descriptor, ≥ 0 (higher is more reliable). [M] float32
        grid: (rows, cols) of a dense map, or None for keypoints.
        scale: keypoint size in pixels (sparse backends), for diagnostics. [M] or None
    """

    xy: np.ndarray
    desc: np.ndarray
    conf: np.ndarray
    grid: tuple[int, int] | None = None
    scale: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xy.shape[0])


@dataclass
class Matches:
    """Correspondences between view 0 and view 1.

    Attributes:
        xy0: pixels in view 0. [M, 2] float64
        xy1: pixels in view 1. [M, 2] float64
        conf: joint confidence ``w = c0 · c1``. [M] float32
        idx0: index of each match in view 0's features. [M] int64
        idx1: index in view 1's features. [M] int64
        counts: number of matches after each filter, in order (for the report).
        below_gate: the reciprocal matches that failed the confidence gate (set by
            :func:`~.matching.match_features`), or None. Weak evidence, mostly wrong matches, that the pose stage
            may consult (e.g. to tell a plane's two poses apart by the matches off the plane); never counted,
            reported or carried by :meth:`subset`.
    """

    xy0: np.ndarray
    xy1: np.ndarray
    conf: np.ndarray
    idx0: np.ndarray
    idx1: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)
    below_gate: Matches | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.xy0.shape[0])

    def subset(self, keep: np.ndarray, stage: str | None = None) -> Matches:
        """The matches selected by a boolean mask or index array; records ``stage``'s count.
        ``below_gate`` is not carried (a subset is a selection of these matches only)."""
        counts = dict(self.counts)
        out = Matches(self.xy0[keep], self.xy1[keep], self.conf[keep], self.idx0[keep], self.idx1[keep], counts)
        if stage is not None:
            counts[stage] = len(out)
        return out


FocalEvidence = Literal["pointmap"]
"""What, besides the matches, a pose stage measured a prior view's focal length on (the neural backend: Weiszfeld
on the network's point map); the acceptance then does not ask the matches for the focal."""

PoseSource = Literal["matches", "pointmap"]
"""What a pose was estimated from: the matches (the classical pose stage), or a network's point map (PnP); the
acceptance tests either on the matches, and asks the matches for the pose's uncertainty only when it came from them."""


@dataclass
class TwoViewGeometry:
    """The relative pose of two calibrated views. World = camera 0; ``|t| = 1`` (relative scale).

    ``X_cam1 = R · X_cam0 + t``.

    Attributes:
        R: rotation of camera 1 relative to camera 0. [3, 3] float64
        t: translation, unit norm. [3] float64
        K0: intrinsics of view 0 (self-calibrated when ``focal_estimated``). [3, 3]
        K1: intrinsics of view 1. [3, 3]
        inliers: the geometrically verified matches.
        diagnostics: measurements for the report only (residuals, RANSAC and planar counts, focal estimation, ...);
            never read to decide anything.
        doubts: the pose stage's own reasons to doubt the pose, one user-facing line each (the acceptance refuses
            a doubted pose unless told to accept it).
        focal_estimated: ``K0``/``K1`` replace the prior's focal of the views that had only the prior.
        focal_evidence: what besides the matches the focal was measured on; None: the matches only (or none).
        median_parallax_deg: the median parallax of the verified matches (°), when measured.
        source: what the pose was estimated from.
    """

    R: np.ndarray
    t: np.ndarray
    K0: np.ndarray
    K1: np.ndarray
    inliers: Matches
    diagnostics: dict[str, Any] = field(default_factory=dict)
    doubts: list[str] = field(default_factory=list)
    focal_estimated: bool = False
    focal_evidence: FocalEvidence | None = None
    median_parallax_deg: float | None = None
    source: PoseSource = "matches"

    def cam_to_world(self, view: int) -> np.ndarray:
        """Camera-to-world transform of ``view`` (0 or 1) in the camera-0 world. [4, 4]"""
        T = np.eye(4)
        if view == 1:
            T[:3, :3] = self.R.T
            T[:3, 3] = -self.R.T @ self.t
        return T


@dataclass
class DepthMap:
    """Dense depth of one view.

    Attributes:
        depth: camera-space z at each pixel; 0 where unknown. [H, W] float32
        confidence: trust in each depth, in [0, 1]; 0 where unknown. [H, W] float32
        measured: pixels whose depth was measured (matched in the other view), as opposed
            to propagated from neighbours; None means all valid pixels. [H, W] bool
    """

    depth: np.ndarray
    confidence: np.ndarray
    measured: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """Pixels with a depth. [H, W] bool"""
        return (self.depth > 0) & (self.confidence > 0)


@dataclass
class MatchSet:
    """Matches between two of the refined views, for the MAC loss.

    Attributes:
        a, b: the views (indices into the maps).
        xy_a, xy_b: the matched pixels at the working resolution. [M, 2] float64
        weights: each match's weight. [M]
    """

    a: int
    b: int
    xy_a: np.ndarray
    xy_b: np.ndarray
    weights: np.ndarray
