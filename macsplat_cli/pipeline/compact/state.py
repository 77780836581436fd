"""The compaction's per-view state: one view's pixel Gaussians in its camera frame and the pixels still alive,
and the helpers the steps share (projection, covariances, the move to the world frame)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from ...camera_math import project_points
from ...cameras import Camera
from ...errors import InputError
from ...gaussians import GaussianMaps, Gaussians
from ...rotations import quat_multiply, quat_to_rotmat, rotmat_to_quat_np

__all__ = ["NEIGHBOURS", "ViewState", "covariances", "logit", "to_world", "view_states"]

NEIGHBOURS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
"""The 8 grid neighbours of a pixel, as (dy, dx)."""


@dataclass
class ViewState:
    """One view's pixel Gaussians in its camera frame, with the pixels still alive."""

    means: torch.Tensor  # [H, W, 3] camera frame
    log_scales: torch.Tensor  # [H, W, 3]
    quats: torch.Tensor  # [H, W, 4]
    logits: torch.Tensor  # [H, W]
    sh: torch.Tensor  # [H, W, K, 3]
    alive: torch.Tensor  # [H, W] bool
    valid: torch.Tensor  # [H, W] bool, the map's own mask (before any step)
    c2w: torch.Tensor  # [4, 4] float64
    K: torch.Tensor  # [3, 3] float64, intrinsics of the map's pixel grid
    image: torch.Tensor | None  # [H, W, 3] the photo at the map's size

    @property
    def size(self) -> tuple[int, int]:
        return int(self.means.shape[0]), int(self.means.shape[1])

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def world_means(self) -> torch.Tensor:
        """Centres in the world frame. [H, W, 3] float64"""
        return self.means.double() @ self.c2w[:3, :3].T + self.c2w[:3, 3]

    @cached_property
    def w2c(self) -> torch.Tensor:
        """The world-to-camera transform, the inverse of ``c2w`` (computed once: the steps project into a view once
        per other view). [4, 4] float64"""
        return torch.linalg.inv(self.c2w)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """World points [N, 3] (float64) into this view: (pixel column, pixel row, camera z, inside) [N] each."""
        return project_points(points, self.w2c, self.K, self.size)


def covariances(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """``R S² Rᵀ``. [..., 3, 3]"""
    m = quat_to_rotmat(quats) * torch.exp(log_scales)[..., None, :]
    return m @ m.transpose(-1, -2)


def logit(p: torch.Tensor) -> torch.Tensor:
    """The inverse sigmoid, ``p`` clamped to [1e-6, 1 − 1e-6]."""
    p = p.clamp(1e-6, 1.0 - 1e-6)
    return torch.log(p) - torch.log1p(-p)


def to_world(g: Gaussians, c2w: torch.Tensor) -> Gaussians:
    """Camera-frame Gaussians → world, as :meth:`GaussianMaps.to_gaussians` does it."""
    T = c2w.to(g.dtype)
    q = torch.as_tensor(rotmat_to_quat_np(c2w[:3, :3].numpy()), dtype=g.dtype)
    return Gaussians(
        g.means @ T[:3, :3].T + T[:3, 3], g.log_scales, quat_multiply(q.expand(len(g), 4), g.quats),
        g.opacity_logits, g.sh,
    )  # fmt: skip


def view_states(
    maps: Sequence[GaussianMaps], cameras: Sequence[Camera], images: Sequence[np.ndarray] | None
) -> list[ViewState]:
    """Each view's state: a copy of its map's tensors, its pose and intrinsics at the map's size, its photo resized."""
    if len(maps) != len(cameras):
        raise InputError(f"compact() got {len(maps)} maps and {len(cameras)} cameras")
    if images is not None and len(images) != len(maps):
        raise InputError(f"compact() got {len(maps)} maps and {len(images)} images")
    out = []
    for k, (m, cam) in enumerate(zip(maps, cameras)):
        if m.batch != 1:
            raise InputError(f"compact() takes one map per view (B = 1), got B = {m.batch} for view {k}")
        h, w = m.size
        c2w = torch.tensor(np.array(cam.cam_to_world), dtype=torch.float64)
        if m.cam_to_world is not None:
            mc = m.cam_to_world[0].double().cpu()
            if float((mc - c2w).abs().max()) > 1e-5:
                raise InputError(f"view {k}: the map's cam_to_world differs from the camera's pose")
            c2w = mc
        K = torch.tensor(np.array(cam.rescaled(w, h).K), dtype=torch.float64)
        img = None
        if images is not None:
            a = np.asarray(images[k], dtype=np.float32)
            if a.shape[:2] != (h, w):
                import cv2

                a = np.asarray(cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA))
            img = torch.from_numpy(np.ascontiguousarray(a)).to(m.dtype)
        # a copy (the steps write into it through views)
        means, log_scales, quats, logits, sh = (t[0].contiguous().clone() for t in m.tensors())
        valid = m.valid_mask()[0].clone()
        out.append(ViewState(means, log_scales, quats, logits, sh, valid.clone(), valid, c2w, K, img))
    return out
