"""Pinhole-camera arithmetic shared by the stages (a low module: numpy and torch only).

Conventions (``cameras.py``): continuous pixel coordinates with pixel centres at +0.5, OpenCV axes
(x right, y down, z forward), ``X_cam = R · X_world + t``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch

__all__ = [
    "NEAR_Z", "intrinsic_rows", "pixel_offsets", "principal_point_window", "project_points", "rescale_intrinsics",
    "scale_focal",
]  # fmt: skip

NEAR_Z = 1e-9
"""A point is in front of a camera when its camera depth exceeds this (:func:`project_points`)."""


def rescale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` [3, 3] for the image resized by ``sx`` horizontally and ``sy`` vertically: row 0 times ``sx``,
    row 1 times ``sy`` (exact with the pixel-corner convention). A new array."""
    out = np.array(K, dtype=np.float64, copy=True)
    out[0] *= sx
    out[1] *= sy
    return out


def principal_point_window(K: np.ndarray, width: int, height: int) -> tuple[int, int, int, int] | None:
    """``(x0, y0, x1, y1)`` (x1, y1 exclusive) of the largest window centred on the principal point of an image
    ``width × height``, in whole pixels: half sides ``min(cx, W − cx)``, ``min(cy, H − cy)`` rounded down, so the
    principal point is within half a pixel of the window's centre (``K`` shifted by ``(x0, y0)`` says where). None
    when the principal point is less than a pixel from the image's border or outside it (no window)."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (math.isfinite(cx) and math.isfinite(cy)):
        return None
    hw = math.floor(min(cx, width - cx))
    hh = math.floor(min(cy, height - cy))
    if hw < 1 or hh < 1:
        return None
    x0, y0 = round(cx - hw), round(cy - hh)
    return x0, y0, x0 + 2 * hw, y0 + 2 * hh


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
        ``inside``), the camera depth, and whether the point is in front (z > :data:`NEAR_Z`), finite and inside.
    """
    X = points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = X[:, 2]
    zs = torch.where(z > NEAR_Z, z, torch.ones_like(z))
    uv = (X @ K.T)[:, :2] / zs[:, None]
    h, w = size
    inside = (z > NEAR_Z) & torch.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0)
    inside &= uv[:, 1] < h
    col = torch.where(inside, uv[:, 0], torch.zeros_like(z)).floor().long().clamp(0, w - 1)
    row = torch.where(inside, uv[:, 1], torch.zeros_like(z)).floor().long().clamp(0, h - 1)
    return col, row, z, inside


def intrinsic_rows(Ks: Iterable[np.ndarray]) -> np.ndarray:
    """Each camera's ``(fx, fy, cx, cy)`` from its ``K`` [3, 3] (no skew), as the CPU kernels take them. [N, 4]
    float64"""
    return np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]] for K in Ks], dtype=np.float64)


def pixel_offsets(sizes: np.ndarray) -> np.ndarray:
    """Where each image's pixels start when the images of ``sizes`` [N, 2] (h, w) lie one after another in one flat
    array (row-major each), as the CPU kernels take per-pixel maps. [N] int64"""
    return np.concatenate([[0], np.cumsum(sizes[:, 0] * sizes[:, 1])[:-1]]).astype(np.int64)
