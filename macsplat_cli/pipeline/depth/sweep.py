"""Plane sweep + semi-global matching: one view's depth hypotheses, their ZNCC costs and the SGM winner.

1. Hypotheses: fronto-parallel planes in the reference camera, uniform in inverse depth between bounds taken from
   the triangulated verified matches (with margins). Their number follows the largest pixel shift the range induces
   in the source image, so consecutive planes move the image by about one pixel.
2. Matching cost: each plane's homography ``K_s (R + t·[0 0 ρ]) K_r⁻¹`` warps the source image onto the reference;
   the cost is ``(1 − ZNCC) / 2`` over a small window (robust to exposure differences). Windows that leave the
   source image cost 0.5, "unknown". No rectification is needed, so converging and forward-moving pairs work.
3. Semi-global aggregation (4 or 8 paths, Numba kernels in :mod:`._sgm_kernels`, plain-PyTorch twin in
   :mod:`._sgm_reference`; penalty P2 lowered across image edges), winner-take-all with a parabolic sub-plane
   offset.

The volume is built at a fraction of the working resolution (``DepthConfig.scale``) for speed; the depth is then
upsampled (:func:`upsample_depth`) with an edge-aware (joint bilateral) filter guided by the full-resolution image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ...camera_math import rescale_intrinsics
from ...errors import ReconstructionError
from ..pose import triangulate
from ..types import TwoViewGeometry, View
from .config import DepthConfig
from .pair import relative_pose

__all__ = ["VolumeDepth", "inverse_depth_ranges", "plane_count", "plane_sweep_cost", "sweep_view", "upsample_depth"]

MAX_PLANES = 128
"""Most depth hypotheses; fewer when the depth range moves the image less."""
MIN_PLANES = 32
"""Fewest depth hypotheses."""
WINDOW = 5
"""ZNCC window side, volume pixels (odd)."""
P1 = 0.04
"""SGM penalty for a one-plane jump (cost units; costs lie in [0, 1])."""
P2 = 0.5
"""SGM penalty for larger jumps, before lowering across edges."""
EDGE_GAMMA = 8.0
"""P2 is divided by ``1 + EDGE_GAMMA·|ΔI|`` (intensity in [0, 1])."""
EIGHT_PATHS = False
"""Aggregate along the diagonals too (slower, smoother); four paths by default."""


def inverse_depth_ranges(geometry: TwoViewGeometry) -> list[tuple[float, float]]:
    """Per view, (ρ_min, ρ_max) covering the triangulated matches with margins."""
    m = geometry.inliers
    h0 = np.concatenate([m.xy0, np.ones((len(m), 1))], 1) @ np.linalg.inv(geometry.K0).T
    h1 = np.concatenate([m.xy1, np.ones((len(m), 1))], 1) @ np.linalg.inv(geometry.K1).T
    X = triangulate(geometry.R, geometry.t, h0, h1)
    z0 = X[:, 2]
    z1 = X @ geometry.R[2] + geometry.t[2]
    out = []
    for z in (z0, z1):
        z = z[np.isfinite(z) & (z > 0)]
        if z.size < 8:
            raise ReconstructionError("dense depth: too few triangulated matches to bound the scene depth")
        # Robust percentiles: a few wrong matches triangulate far too near or far, and the
        # plane budget must not be spent on them.
        near, far = np.percentile(z, 5), np.percentile(z, 95)
        out.append((1.0 / (far * 2.5), 1.0 / (near * 0.7)))
    return out


def plane_sweep_cost(
    ref: np.ndarray,  # [h, w] float32
    src: np.ndarray,  # [hs, ws] float32
    K_ref: np.ndarray,
    K_src: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    inv_depths: np.ndarray,  # [D]
    window: int,
) -> tuple[np.ndarray, np.ndarray]:
    """ZNCC cost volume of fronto-parallel planes.

    Returns:
        ``(cost, ncc_valid)``: ``(1 − ZNCC)/2`` per pixel and plane, 0.5 where the window
        leaves the source image [h, w, D] float32; and, per pixel, whether any plane had a
        complete window [h, w] bool.
    """
    h, w = ref.shape
    ksize = (window, window)
    eps = 1e-4
    mu_r = cv2.blur(ref, ksize)
    var_r = np.maximum(cv2.blur(ref * ref, ksize) - mu_r * mu_r, 0.0)
    # cv2 maps pixel centres at integers; our K uses +0.5 centres: shift in and out.
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    unshift = np.linalg.inv(shift)
    K_ref_inv = np.linalg.inv(K_ref)
    cost = np.empty((len(inv_depths), h, w), np.float32)
    any_valid = np.zeros((h, w), bool)
    ones = np.ones(src.shape, np.float32)
    full = 1.0 - 1e-3  # a window is usable only if all its pixels come from inside the source
    for k, rho in enumerate(inv_depths):
        H = unshift @ K_src @ (R + np.outer(t, [0.0, 0.0, rho])) @ K_ref_inv @ shift
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        # No NaN borders: cv2.blur is a running sum, so one NaN would poison the rest of its row.
        warped = cv2.warpPerspective(src, H, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        inside = cv2.warpPerspective(ones, H, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        valid = cv2.blur(inside, ksize) >= full
        mu_w = cv2.blur(warped, ksize)
        var_w = cv2.blur(warped * warped, ksize) - mu_w * mu_w
        cov = cv2.blur(ref * warped, ksize) - mu_r * mu_w
        ncc = cov / np.sqrt(var_r * np.maximum(var_w, 0.0) + eps * eps)
        any_valid |= valid
        cost[k] = np.where(valid, 0.5 * (1.0 - np.clip(ncc, -1.0, 1.0)), 0.5)
    return np.ascontiguousarray(cost.transpose(1, 2, 0)), any_valid


def plane_count(geometry: TwoViewGeometry, ref: int, rho: tuple[float, float], scale: float) -> int:
    """Planes so that consecutive ones shift the source image by about one (volume) pixel."""
    K_src = geometry.K1 if ref == 0 else geometry.K0
    _, t = relative_pose(geometry, ref)
    f = 0.5 * (K_src[0, 0] + K_src[1, 1]) * scale
    shift = f * float(np.linalg.norm(t[:2]) + abs(t[2]) * 0.5) * (rho[1] - rho[0])
    return int(np.clip(math.ceil(shift), MIN_PLANES, MAX_PLANES))


@dataclass
class VolumeDepth:
    """One view's winner-take-all result at the volume resolution ``h × w`` (before the confidence tests).

    Attributes:
        inv_depth: the SGM winner with its sub-plane offset (or the refined plane's). [h, w] float64
        uniq: uniqueness margin of the winner. [h, w] float32
        win_cost: ZNCC cost ``(1 − ZNCC)/2`` of the winner (or of the refined plane). [h, w] float32
        has_window: some plane had a complete window in the source image. [h, w] bool
        K: the view's intrinsics at the volume resolution. [3, 3]
        gray: the view's gray image at the volume resolution. [h, w] float32
        gray_src: the other view's. [hs, ws] float32
        K_src: the other view's intrinsics at its volume resolution. [3, 3]
        rho: the inverse-depth bounds (ρ_min, ρ_max) of the sweep.
        refined: pixels whose plane the slanted refinement changed (None before it ran). [h, w] bool
    """

    inv_depth: np.ndarray
    uniq: np.ndarray
    win_cost: np.ndarray
    has_window: np.ndarray
    K: np.ndarray
    gray: np.ndarray
    gray_src: np.ndarray
    K_src: np.ndarray
    rho: tuple[float, float]
    refined: np.ndarray | None = None


def sweep_view(
    views: list[View], geometry: TwoViewGeometry, ref: int, rho: tuple[float, float], cfg: DepthConfig
) -> VolumeDepth:
    """Plane sweep + SGM winner of view ``ref`` against the other, at the volume resolution.

    Args:
        views: the two working views.
        geometry: the two cameras.
        ref: the reference view (0 or 1).
        rho: its inverse-depth bounds (:func:`inverse_depth_ranges`).
        cfg: the stage's configuration.
    """
    v_ref, v_src = views[ref], views[1 - ref]
    K_ref = geometry.K0 if ref == 0 else geometry.K1
    K_src = geometry.K1 if ref == 0 else geometry.K0
    R, t = relative_pose(geometry, ref)
    h = max(8, int(round(v_ref.height * cfg.scale)))
    w = max(8, int(round(v_ref.width * cfg.scale)))
    hs = max(8, int(round(v_src.height * cfg.scale)))
    ws = max(8, int(round(v_src.width * cfg.scale)))
    g_ref = cv2.resize(v_ref.gray, (w, h), interpolation=cv2.INTER_AREA)
    g_src = cv2.resize(v_src.gray, (ws, hs), interpolation=cv2.INTER_AREA)
    Kr = rescale_intrinsics(K_ref, w / v_ref.width, h / v_ref.height)
    Ks = rescale_intrinsics(K_src, ws / v_src.width, hs / v_src.height)
    n = plane_count(geometry, ref, rho, cfg.scale)
    rhos = np.linspace(rho[0], rho[1], n)
    cost, has_window = plane_sweep_cost(g_ref, g_src, Kr, Ks, R, t, rhos, WINDOW)
    from . import _sgm_kernels  # Numba on first use (engine: the kernels load beside the first stages)

    agg = _sgm_kernels.aggregate(cost, g_ref, P1, P2, EDGE_GAMMA, EIGHT_PATHS)
    idx, off, uniq = _sgm_kernels.winner(agg)
    step = (rho[1] - rho[0]) / max(n - 1, 1)
    inv_depth = rho[0] + (idx + off.astype(np.float64)) * step
    win_cost = np.take_along_axis(cost, idx[..., None], axis=2)[..., 0]
    return VolumeDepth(inv_depth, uniq, win_cost, has_window, Kr, g_ref, g_src, Ks, rho)


def upsample_depth(depth: np.ndarray, conf: np.ndarray, guide: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Volume-resolution depth and confidence [h, w] → working resolution [H, W] (``guide``: the working gray
    image [H, W]): nearest valid, then edge-aware smoothing of 1/z."""
    H, W = guide.shape
    d_up = cv2.resize(depth, (W, H), interpolation=cv2.INTER_NEAREST)
    c_up = cv2.resize(conf, (W, H), interpolation=cv2.INTER_NEAREST)
    valid = d_up > 0
    inv = np.where(valid, 1.0 / np.maximum(d_up, 1e-12), 0.0).astype(np.float32)
    wgt = valid.astype(np.float32)
    g = guide.astype(np.float32)
    sigma_space = max(1.0, 1.0 / max(depth.shape[1] / W, 1e-6))
    # numerator and denominator as two channels of one filter: the same weights, computed once (each channel's sums
    # are those of a one-channel call, bit for bit; the third channel is padding: OpenCV takes 1 or 3)
    both = cv2.ximgproc.jointBilateralFilter(g, np.dstack([inv * wgt, wgt, np.zeros_like(wgt)]), -1, 0.08, sigma_space)
    num, den = both[..., 0], both[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_s = np.where(valid & (den > 1e-3), num / np.maximum(den, 1e-6), 0.0)
    out = np.where(inv_s > 0, 1.0 / np.maximum(inv_s, 1e-12), 0.0).astype(np.float32)
    return out, np.where(out > 0, c_up, 0.0).astype(np.float32)
