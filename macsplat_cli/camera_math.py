"""Pinhole-camera arithmetic shared by the stages (a low module: numpy and torch only).

Conventions (``cameras.py``): continuous pixel coordinates with pixel centres at +0.5, OpenCV axes
(x right, y down, z forward), ``X_cam = R · X_world + t``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["project_points", "rescale_intrinsics", "scale_focal"]


def rescale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` [3, 3] for the image resized by ``sx`` horizontally and ``sy`` vertically: row 0 times ``sx``,
    row 1 times ``sy`` (exact with the pixel-corner convention). A new array."""
    out = np.array(K, dtype=np.float64, copy=True)
    out[0] *= sx
    out[1] *= sy
    return out


def scale_focal(K: np.ndarray, log_scale: float) -> np.ndarray:
    """``K`` [3, 3] with its focal lengths (and skew) times ``exp(log_scale)``, the principal point kept: the
    focal-length hypothesis of a self-calibrating pose search. ``K`` itself when ``log_scale`` is 0."""
    if log_scale == 0.0:
        return K
    out = K.copy()
    f = math.exp(log_scale)
    out[0, 0] *= f
    out[0, 1] *= f
    out[1, 1] *= f
    return out


def project_points(
    points: torch.Tensor, world_to_cam: torch.Tensor, K: torch.Tensor, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points into a camera's pixel grid.

    Args:
        points: world points. [N, 3]
        world_to_cam: rigid transform. [4, 4]
        K: intrinsics. [3, 3]
        size: the image (height, width).

    Returns:
        ``(col, row, z, inside)`` [N] each: the integer pixel (clamped into the image; 0 where not
        ``inside``), the camera depth, and whether the point is in front (z > 1e-9), finite and inside.
    """
    X = points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = X[:, 2]
    zs = torch.where(z > 1e-9, z, torch.ones_like(z))
    uv = (X @ K.T)[:, :2] / zs[:, None]
    h, w = size
    inside = (z > 1e-9) & torch.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0)
    inside &= uv[:, 1] < h
    col = torch.where(inside, uv[:, 0], torch.zeros_like(z)).floor().long().clamp(0, w - 1)
    row = torch.where(inside, uv[:, 1], torch.zeros_like(z)).floor().long().clamp(0, h - 1)
    return col, row, z, inside
