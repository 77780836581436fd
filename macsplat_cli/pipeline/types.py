"""Typed data passed between the pipeline stages (one paper stage, one module).

Stages and their interfaces (each backend implements the same callable signature):

====================  =========================================  ======================
stage                 input → output                             module
====================  =========================================  ======================
images/intrinsics     paths → :class:`View` ×2                   ``views.py``
descriptors           :class:`View` → :class:`Features`          ``descriptors.py``
filtered matching     :class:`Features` ×2 → :class:`Matches`    ``matching.py``
pose                  :class:`Matches` → :class:`TwoViewGeometry`  ``pose.py``
dense geometry        views + geometry → :class:`DepthMap` ×2    ``depth.py``
Gaussian prediction   views + geometry + depths → Gaussians      ``gaussian_init.py``
====================  =========================================  ======================

All pixel coordinates are continuous, at the working resolution, with pixel centres at
+0.5 (the convention of :mod:`macsplat_cli.cameras`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

from ..cameras import Camera, rotmat_to_quat_np
from ..gaussians import Gaussians, quat_multiply

__all__ = ["DepthMap", "Features", "IntrinsicsSource", "Matches", "PixelGaussians", "TwoViewGeometry", "View"]

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
    """

    name: str
    path: Path
    image: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    original_size: tuple[int, int]
    intrinsics_source: IntrinsicsSource
    detail: np.ndarray | None = None

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
    """

    xy0: np.ndarray
    xy1: np.ndarray
    conf: np.ndarray
    idx0: np.ndarray
    idx1: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.xy0.shape[0])

    def subset(self, keep: np.ndarray, stage: str | None = None) -> Matches:
        """The matches selected by a boolean mask or index array; records ``stage``'s count."""
        counts = dict(self.counts)
        out = Matches(self.xy0[keep], self.xy1[keep], self.conf[keep], self.idx0[keep], self.idx1[keep], counts)
        if stage is not None:
            counts[stage] = len(out)
        return out


@dataclass
class TwoViewGeometry:
    """The relative pose of two calibrated views. World = camera 0; ``|t| = 1`` (relative scale).

    ``X_cam1 = R · X_cam0 + t``.

    Attributes:
        R: rotation of camera 1 relative to camera 0. [3, 3] float64
        t: translation, unit norm. [3] float64
        K0: intrinsics of view 0 (refined when they were estimated). [3, 3]
        K1: intrinsics of view 1. [3, 3]
        inliers: the geometrically verified matches.
        info: diagnostics for the report (residuals, parallax, focal estimation, ...).
    """

    R: np.ndarray
    t: np.ndarray
    K0: np.ndarray
    K1: np.ndarray
    inliers: Matches
    info: dict[str, float | int | str | bool] = field(default_factory=dict)

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
class PixelGaussians:
    """One Gaussian per pixel of a view, in that view's camera frame (pre-activation values).

    The Gaussian-prediction stage's output: what a Splatt3R-style head predicts, and what
    the MAC loss samples at match pixels. :meth:`to_world` gives the renderable set.

    Attributes:
        means: centres in the camera frame. [H, W, 3]
        log_scales: log standard deviations. [H, W, 3]
        quats: (w, x, y, z) rotations in the camera frame. [H, W, 4]
        opacity_logits: opacities before the sigmoid. [H, W]
        sh: SH coefficients. [H, W, K, 3]
        valid: pixels that carry a Gaussian. [H, W] bool
        cam_to_world: the view's camera-to-world transform. [4, 4] float64
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    valid: torch.Tensor
    cam_to_world: torch.Tensor

    @property
    def size(self) -> tuple[int, int]:
        """(H, W)"""
        return int(self.means.shape[0]), int(self.means.shape[1])

    def tensors(self) -> list[torch.Tensor]:
        """The five parameter maps (to optimise)."""
        return [self.means, self.log_scales, self.quats, self.opacity_logits, self.sh]

    def to_world(self) -> Gaussians:
        """The valid pixels' Gaussians in the world frame (differentiable w.r.t. the maps)."""
        dtype = self.means.dtype
        T = self.cam_to_world.to(dtype)
        sel = self.valid.reshape(-1).nonzero().squeeze(1)
        means = self.means.reshape(-1, 3)[sel] @ T[:3, :3].T + T[:3, 3]
        q_c2w = torch.as_tensor(rotmat_to_quat_np(T[:3, :3].detach().double().numpy()), dtype=dtype)
        quats = quat_multiply(q_c2w.expand(len(sel), 4), self.quats.reshape(-1, 4)[sel])
        k = self.sh.shape[2]
        return Gaussians(
            means=means,
            log_scales=self.log_scales.reshape(-1, 3)[sel],
            quats=quats,
            opacity_logits=self.opacity_logits.reshape(-1)[sel],
            sh=self.sh.reshape(-1, k, 3)[sel],
        )

    def pooled(self, factor: int) -> PixelGaussians:
        """Merge ``factor × factor`` pixel blocks into one Gaussian each (H, W divisible by it).

        Parameters are averaged over the block's valid pixels; the standard deviations grow
        by ``factor``, since each Gaussian now covers ``factor²`` pixels.
        """
        if factor == 1:
            return self
        h, w = self.size
        if h % factor or w % factor:
            raise ValueError(f"a {w}x{h} map cannot be pooled by {factor}")
        v = self.valid.to(self.means.dtype)[None, None]
        count = F.avg_pool2d(v, factor)[0, 0]

        def pool(x: torch.Tensor) -> torch.Tensor:  # [H, W, C] → [H/f, W/f, C]
            c = x.reshape(h, w, -1).permute(2, 0, 1)[None]
            s = F.avg_pool2d(c * v, factor)[0]
            return (s / count.clamp_min(1e-12)).permute(1, 2, 0)

        k = self.sh.shape[2]
        quats = pool(self.quats)
        return PixelGaussians(
            means=pool(self.means),
            log_scales=pool(self.log_scales) + float(np.log(factor)),
            quats=quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True).clamp_min(1e-12),
            opacity_logits=pool(self.opacity_logits)[..., 0],
            sh=pool(self.sh).reshape(h // factor, w // factor, k, 3),
            valid=count > 0,
            cam_to_world=self.cam_to_world,
        )

    def detach(self) -> PixelGaussians:
        return PixelGaussians(*(t.detach().clone() for t in self.tensors()), self.valid, self.cam_to_world)
