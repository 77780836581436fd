"""Baselines evaluated on the same cases as the reconstruction.

* **points** — the reconstruction's coloured point cloud, rendered as small opaque discs
  with a z-buffer (the "MASt3R (point cloud)" / DUSt3R rows of the Splatt3R paper, which
  render the predicted points without confidence filtering). One point per Gaussian: its
  centre and its colour (the SH DC term); the disc's world radius is ``radius_scale`` times
  the Gaussian's middle standard deviation (for the classical surfels, 0.7 px of the source
  view, so discs of about one pixel that close up the point grid), projected with the
  target's focal length and clamped to ``[min_radius_px, max_radius_px]``. A pixel is
  covered by a disc when its centre is within the radius of the projected point; the
  nearest covering point wins. Pixels no disc covers keep the background.
* **copy** — the context photo whose camera centre is nearest to the target's (ties: the
  smaller rotation), resized to the target's size: what a method that moves no pixel
  would score.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Camera
from ..gaussians import Gaussians
from ..metrics import rotation_error_deg
from ..sh import sh0_to_rgb

__all__ = ["PointCloud", "PointsConfig", "nearest_context", "point_cloud", "render_points"]


@dataclass
class PointsConfig:
    """Args:
    radius_scale: disc radius as a multiple of each Gaussian's middle standard deviation.
    min_radius_px: smallest disc radius on screen.
    max_radius_px: largest disc radius on screen.
    near: points nearer than this (camera z, scene units) are dropped.
    """

    radius_scale: float = 1.5
    min_radius_px: float = 0.5
    max_radius_px: float = 8.0
    near: float = 1e-3


@dataclass
class PointCloud:
    """Coloured points with a world-space radius.

    Attributes:
        xyz: positions. [N, 3] float64
        rgb: colours in [0, 1]. [N, 3] float32
        radius: disc radius in world units. [N] float64
    """

    xyz: np.ndarray
    rgb: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def point_cloud(gaussians: Gaussians, config: PointsConfig | None = None) -> PointCloud:
    """The point cloud of a set of Gaussians: centres, DC colours, radii from the scales."""
    cfg = config or PointsConfig()
    with torch.no_grad():
        xyz = gaussians.means.detach().double().cpu().numpy()
        rgb = sh0_to_rgb(gaussians.sh[:, 0]).clamp(0.0, 1.0).float().cpu().numpy()
        mid = torch.sort(gaussians.log_scales.detach(), dim=1).values[:, 1]
        radius = cfg.radius_scale * torch.exp(mid).double().cpu().numpy()
    ok = np.isfinite(xyz).all(1) & np.isfinite(radius)
    return PointCloud(xyz[ok], rgb[ok], radius[ok])


def render_points(
    points: PointCloud,
    camera: Camera,
    *,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    config: PointsConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render points as opaque discs, nearest first.

    Returns:
        ``(rgb, covered)``: the image [H, W, 3] float32 and the pixels some disc covers [H, W] bool.
    """
    cfg = config or PointsConfig()
    W, H = camera.width, camera.height
    image = np.empty((H * W, 3), np.float32)
    image[:] = np.asarray(background, np.float32)
    covered = np.zeros(H * W, bool)
    if len(points) == 0:
        return image.reshape(H, W, 3), covered.reshape(H, W)
    Xc = points.xyz @ camera.R.T + camera.t
    z = Xc[:, 2]
    front = z > cfg.near
    Xc, z, rgb, rad = Xc[front], z[front], points.rgb[front], points.radius[front]
    K = camera.K
    x = (K[0, 0] * Xc[:, 0] + K[0, 1] * Xc[:, 1]) / z + K[0, 2]
    y = K[1, 1] * Xc[:, 1] / z + K[1, 2]
    r_px = np.clip(rad * 0.5 * (K[0, 0] + K[1, 1]) / z, cfg.min_radius_px, cfg.max_radius_px)
    near = (x > -r_px) & (x < W + r_px) & (y > -r_px) & (y < H + r_px)
    x, y, z, rgb, r_px = x[near], y[near], z[near], rgb[near], r_px[near]
    if len(x) == 0:  # nothing in front of the camera and on screen
        return image.reshape(H, W, 3), covered.reshape(H, W)
    reach = np.ceil(r_px).astype(np.int64)
    pix_all, z_all, src_all = [], [], []
    for R in np.unique(reach):
        sel = np.flatnonzero(reach == R)
        d = np.arange(-R, R + 1)
        dx, dy = (g.reshape(-1) for g in np.meshgrid(d, d, indexing="xy"))
        px = np.floor(x[sel])[:, None].astype(np.int64) + dx[None]
        py = np.floor(y[sel])[:, None].astype(np.int64) + dy[None]
        inside = (px + 0.5 - x[sel, None]) ** 2 + (py + 0.5 - y[sel, None]) ** 2 <= r_px[sel, None] ** 2
        inside &= (px >= 0) & (px < W) & (py >= 0) & (py < H)
        rows, cols = np.nonzero(inside)
        pix_all.append(py[rows, cols] * W + px[rows, cols])
        z_all.append(z[sel][rows])
        src_all.append(sel[rows])
    pix, zz, src = np.concatenate(pix_all), np.concatenate(z_all), np.concatenate(src_all)
    if len(pix):
        order = np.lexsort((zz, pix))  # by pixel, then nearest first
        pix, src = pix[order], src[order]
        first = np.ones(len(pix), bool)
        first[1:] = pix[1:] != pix[:-1]
        image[pix[first]] = rgb[src[first]]
        covered[pix[first]] = True
    return image.reshape(H, W, 3), covered.reshape(H, W)


def nearest_context(target: Camera, contexts: Sequence[Camera]) -> int:
    """Index of the context camera nearest to the target (centre distance, then rotation; then the first)."""
    keys = [
        (
            round(float(np.linalg.norm(target.center - c.center)), 12),
            rotation_error_deg(target.cam_to_world[:3, :3], c.cam_to_world[:3, :3]),
        )
        for c in contexts
    ]
    return min(range(len(keys)), key=keys.__getitem__)
