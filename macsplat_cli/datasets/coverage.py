"""Splatt3R's visibility mask and the pairwise coverage it defines.

:func:`visibility_mask` follows Splatt3R's ``utils/loss_mask.py`` (reference notes §4.6):
for every pixel of the target view,

1. back-project the pixel centre with the target's ground-truth depth into the world;
2. project the point into each context view: camera-space depth ``z_c`` and pixel
   ``(u_c, v_c)``;
3. ``in_frustum_c = 0 < u_c < W and 0 < v_c < H`` (strict, and — as in Splatt3R — no
   test of ``z_c > 0``);
4. ``depth_match_c = |z_c − D_c(u_c, v_c)| ≤ atol + rtol·|D_c(u_c, v_c)|`` with ``D_c``
   sampled bilinearly (``grid_sample``, ``align_corners=False``, zero padding; atol 0.1 m,
   rtol 1e-5: ``torch.isclose``);
5. ``mask = (OR_c in_frustum_c) AND (D_t > 1e-6) AND (OR_c depth_match_c)`` — the two ORs
   are taken independently, as in Splatt3R.

Pixel coordinates follow macsplat's convention (pixel centres at +0.5, origin at the
image corner), in which ``g = 2·u/W − 1`` is exactly the ``grid_sample`` coordinate of
``u``; Splatt3R back-projects integer pixel coordinates with an OpenCV ``K`` and samples
with the same ``g``, a half-pixel offset this implementation does not reproduce.

:func:`coverage_matrix`: ``coverage[a, b]`` = fraction of frame ``b``'s pixels (all
pixels, depth or not) visible in frame ``a`` alone — the direction Splatt3R's sampling
code uses (``coverage[c1][c2] ≥ φ`` for the context pair). Splatt3R's coverage files were
made by unpublished code; resolution (here ``size`` pixels on the long side, depth resized
by nearest neighbour) and denominator are this implementation's choices.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..cameras import Camera
from .base import EvalScene, resize_depth_nearest

__all__ = ["DEPTH_ATOL", "DEPTH_RTOL", "coverage_matrix", "visibility_mask", "visibility_masks"]

logger = logging.getLogger(__name__)

DEPTH_ATOL = 0.1
"""Splatt3R's depth-agreement tolerance, in scene units (metres on ScanNet++)."""
DEPTH_RTOL = 1e-5
"""``torch.isclose``'s default relative tolerance, which Splatt3R keeps."""


def _backproject(depth: torch.Tensor, K: np.ndarray, c2w: np.ndarray) -> torch.Tensor:
    """World points of every pixel centre at its depth. [H, W] → [H·W, 3] float64"""
    h, w = depth.shape
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5, indexing="ij"
    )
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)
    rays = pix @ torch.tensor(np.linalg.inv(K)).T
    pts = rays * depth.reshape(-1, 1).to(torch.float64)
    T = torch.tensor(np.asarray(c2w, np.float64))
    return pts @ T[:3, :3].T + T[:3, 3]


def visibility_masks(
    target_depth: np.ndarray,  # [H, W]
    target_camera: Camera,
    context_depths: Sequence[np.ndarray],  # C × [Hc, Wc]
    context_cameras: Sequence[Camera],
    *,
    atol: float = DEPTH_ATOL,
    rtol: float = DEPTH_RTOL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-context terms of the visibility test of one target view.

    Cameras must be at the resolution of their depth maps.

    Returns:
        ``(in_frustum, depth_match, valid)``: ``[C, H, W]`` bool, ``[C, H, W]`` bool, and
        the target's valid-depth pixels ``D_t > 1e-6`` ``[H, W]`` bool.
    """
    d_t = torch.from_numpy(np.ascontiguousarray(target_depth, np.float64))
    h, w = d_t.shape
    X = _backproject(d_t, target_camera.K, target_camera.cam_to_world)  # [P, 3]
    frustum, match = [], []
    for depth, cam in zip(context_depths, context_cameras):
        W2C = torch.tensor(cam.world_to_cam)
        Xc = X @ W2C[:3, :3].T + W2C[:3, 3]
        z = Xc[:, 2]
        proj = Xc @ torch.tensor(cam.K).T
        u, v = proj[:, 0] / z, proj[:, 1] / z  # z = 0 gives inf/nan: neither in frustum nor matched
        hc, wc = depth.shape
        frustum.append((u > 0) & (u < wc) & (v > 0) & (v < hc))
        grid = torch.stack([2.0 * u / wc - 1.0, 2.0 * v / hc - 1.0], -1).reshape(1, 1, -1, 2)
        grid = torch.nan_to_num(grid, nan=-2.0, posinf=-2.0, neginf=-2.0)  # off-image: samples the zero padding
        dc = torch.from_numpy(np.ascontiguousarray(depth, np.float64))[None, None]
        sampled = F.grid_sample(dc, grid, mode="bilinear", padding_mode="zeros", align_corners=False).reshape(-1)
        match.append(torch.isclose(z, sampled, rtol=rtol, atol=atol))
    shape = (len(frustum), h, w)
    return (
        torch.stack(frustum).reshape(shape).numpy(),
        torch.stack(match).reshape(shape).numpy(),
        (d_t > 1e-6).numpy(),
    )


def visibility_mask(
    target_depth: np.ndarray,  # [H, W]
    target_camera: Camera,
    context_depths: Sequence[np.ndarray],
    context_cameras: Sequence[Camera],
    *,
    atol: float = DEPTH_ATOL,
    rtol: float = DEPTH_RTOL,
) -> np.ndarray:
    """Splatt3R's visibility ("loss") mask of a target view against the context views (module docstring).

    Args:
        target_depth: ground-truth depth of the target (camera-space z, 0 = none). [H, W]
        target_camera: its camera, at the depth map's resolution.
        context_depths: ground-truth depth of each context view. C × [Hc, Wc]
        context_cameras: their cameras, at their depth maps' resolutions.
        atol: absolute depth tolerance (scene units).
        rtol: relative depth tolerance.

    Returns:
        Pixels of the target seen by the context views. [H, W] bool
    """
    frustum, match, valid = visibility_masks(
        target_depth, target_camera, context_depths, context_cameras, atol=atol, rtol=rtol
    )
    return frustum.any(0) & valid & match.any(0)


def _small(camera: Camera, size: int) -> Camera:
    s = min(1.0, size / max(camera.width, camera.height))
    if s >= 1.0:
        return camera
    return camera.rescaled(max(1, round(camera.width * s)), max(1, round(camera.height * s)))


def coverage_matrix(
    scene: EvalScene,
    *,
    size: int = 128,
    atol: float = DEPTH_ATOL,
    rtol: float = DEPTH_RTOL,
    on_row: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Pairwise coverage of a scene with depth: ``cov[a, b]`` = fraction of ``b``'s pixels visible in ``a``.

    Computed at ``size`` pixels on the long side (never up); the diagonal is the fraction
    of pixels with depth.

    Args:
        scene: a scene whose frames all have depth.
        size: working long side.
        atol: absolute depth tolerance (scene units).
        rtol: relative depth tolerance.
        on_row: progress callback ``(done, total)``.

    Returns:
        ``[N, N]`` float64.
    """
    n = len(scene.frames)
    cams = [_small(f.camera, size) for f in scene.frames]
    depths = []
    for i, cam in enumerate(cams):
        d = scene.depth(i)
        assert d is not None, "coverage needs depth for every frame"
        depths.append(resize_depth_nearest(d, cam.width, cam.height))
    cov = np.zeros((n, n))
    for b in range(n):
        frustum, match, valid = visibility_masks(depths[b], cams[b], depths, cams, atol=atol, rtol=rtol)
        cov[:, b] = (frustum & match & valid[None]).reshape(n, -1).mean(1)
        if on_row is not None:
            on_row(b + 1, n)
    logger.debug("coverage of %s: %d frames at %d px", scene.name, n, size)
    return cov
