"""Fill and depth steps: a depth for every pixel inside the view's mask, and no depth left between two sides.

1. Fill (:func:`fill_depth_rules`): every pixel without a measured depth gets one from its confident neighbours
   (edge-aware, OpenCV's fast global smoother), or, far from any, from a push-pull pyramid (:func:`push_pull`).
2. Depth steps (:func:`snap_depth_edges`): pixels between the two sides of a step (:func:`depth_edges`) are moved
   to one side.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["depth_edges", "fill_depth", "fill_depth_rules", "push_pull", "snap_depth_edges"]


def push_pull(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Fill every pixel from the weighted samples by a push-pull pyramid (Gortler et al. 1996).

    Push: sum weights and weighted values 2×2 → 1 until one pixel is left. Pull: from the
    coarsest level down, each pixel keeps its own average where its weight is ≥ 1 and
    blends in the upsampled coarser estimate where it is lighter.

    Args:
        values: samples. [H, W] float32
        weights: sample weights ≥ 0; 0 = no sample. [H, W] float32

    Returns:
        A value for every pixel. [H, W] float32
    """
    levels = [(values * weights, weights)]
    while max(levels[-1][1].shape) > 1:
        vw, w = levels[-1]
        h2, w2 = (vw.shape[0] + 1) // 2, (vw.shape[1] + 1) // 2
        pad = ((0, 2 * h2 - vw.shape[0]), (0, 2 * w2 - vw.shape[1]))
        vw_p, w_p = np.pad(vw, pad), np.pad(w, pad)
        vw_c = vw_p.reshape(h2, 2, w2, 2).sum((1, 3))
        w_c = w_p.reshape(h2, 2, w2, 2).sum((1, 3))
        levels.append((vw_c, w_c))
    vw, w = levels[-1]
    est = np.where(w > 0, vw / np.maximum(w, 1e-12), 0.0)
    for vw, w in reversed(levels[:-1]):
        up = np.repeat(np.repeat(est, 2, 0), 2, 1)[: vw.shape[0], : vw.shape[1]]
        own = np.where(w > 0, vw / np.maximum(w, 1e-12), 0.0)
        a = np.clip(w, 0.0, 1.0)
        est = a * own + (1.0 - a) * up
    return est.astype(np.float32)


def fill_depth(
    depth: np.ndarray,  # [H, W]
    confidence: np.ndarray,  # [H, W]
    image: np.ndarray,  # [H, W, 3]
    *,
    lam: float,
    sigma_color: float,
    fill_confidence: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Give every pixel a depth (:func:`fill_depth_rules` without the rule map)."""
    d, c, _ = fill_depth_rules(depth, confidence, image, lam=lam, sigma_color=sigma_color,
                               fill_confidence=fill_confidence)  # fmt: skip
    return d, c


def fill_depth_rules(
    depth: np.ndarray,  # [H, W]
    confidence: np.ndarray,  # [H, W]
    image: np.ndarray,  # [H, W, 3]
    *,
    lam: float,
    sigma_color: float,
    fill_confidence: float,
    clamp_near: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Give every pixel a depth: confident ones keep theirs, the others are propagated.

    Near the confident pixels: normalised convolution with OpenCV's fast global smoother
    (an edge-aware weighted least-squares filter), ``fill = FGS(ρ·c) / FGS(c)`` on inverse
    depth ρ, which stops at image edges. Where that support vanishes (regions the other
    view never saw), a push-pull pyramid extends the nearest depths. Filled pixels get at
    most ``fill_confidence``, scaled by the support.

    Filled depths are kept no nearer than the median measured depth: a wrongly near fill
    becomes a floater that hides everything behind it in a novel view, while a wrongly far
    one only reads as background (measured: benchmarks/history/depth.md).

    Returns:
        ``(depth, confidence, rule)`` with the confident pixels unchanged [H, W], [H, W], and the rule that gave
        each pixel its depth, an index into :data:`~.config.FILL_RULES` [H, W] uint8.
    """
    valid = (depth > 0) & (confidence > 0)
    rule = np.where(valid, 0, 3).astype(np.uint8)
    if not valid.any():
        return depth, confidence, rule
    guide = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
    fgs = cv2.ximgproc.createFastGlobalSmootherFilter(guide, lam, sigma_color)
    wgt = np.where(valid, confidence, 0.0).astype(np.float32)
    inv = np.where(valid, 1.0 / np.maximum(depth, 1e-12), 0.0).astype(np.float32)
    num = fgs.filter(inv * wgt)
    den = fgs.filter(wgt)
    ok = (den > 1e-4) & (num > 0)
    inv_fill = np.where(ok, num / np.maximum(den, 1e-12), 0.0)
    rule[~valid & ok] = 1
    support = np.clip(den / max(float(np.percentile(wgt[valid], 50)), 1e-6), 0.0, 1.0)
    if not ok.all():  # far from any confident pixel: push-pull from what the smoother reached
        inv_far = push_pull(inv_fill.astype(np.float32), ok.astype(np.float32) * np.maximum(support, 1e-3))
        inv_fill = np.where(ok, inv_fill, inv_far)
        rule[~valid & ~ok & (inv_far > 0)] = 2
    if clamp_near:
        inv_fill = np.minimum(inv_fill, float(np.median(inv[valid])))
    hole = ~valid & (inv_fill > 0)
    out_d = np.where(valid, depth, np.where(hole, 1.0 / np.maximum(inv_fill, 1e-12), 0.0)).astype(np.float32)
    fill_c = fill_confidence * np.maximum(support, 0.1)
    out_c = np.where(valid, confidence, np.where(hole, fill_c, 0.0)).astype(np.float32)
    rule[~valid & ~hole] = 3
    return out_d, out_c, rule


def depth_edges(depth: np.ndarray, ratio: float) -> np.ndarray:
    """Pixels on a depth step: the depths with a depth in their 3×3 neighbourhood span more than ``ratio``.

    Args:
        depth: depth, 0 where unknown. [H, W]
        ratio: the farthest / nearest depth ratio that counts as a step (> 1).

    Returns:
        [H, W] bool
    """
    valid = depth > 0
    inv = np.where(valid, 1.0 / np.maximum(depth, 1e-12), 0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(inv, kernel)  # nearest
    lo = cv2.erode(np.where(valid, inv, np.float32(np.inf)).astype(np.float32), kernel)  # farthest
    with np.errstate(invalid="ignore", over="ignore"):
        return valid & np.isfinite(lo) & (hi > lo * ratio)


def snap_depth_edges(depth: np.ndarray, ratio: float, radius: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Move each pixel on a depth step (:func:`depth_edges`) to the nearest or the farthest depth within
    ``radius`` pixels, whichever is closer in inverse depth, so no depth is left between an object and what is
    behind it (a step smeared over up to ``2·radius`` pixels by an upsampling or a fill included).

    Args:
        depth: depth, 0 where unknown. [H, W]
        ratio: the depth ratio across a 3×3 neighbourhood that counts as a step.
        radius: half-width of the window the two sides are taken from.

    Returns:
        ``(depth, moved)``: the snapped depth [H, W] float32 and the pixels moved by more than 1 % [H, W] bool.
    """
    valid = depth > 0
    inv0 = np.where(valid, 1.0 / np.maximum(depth, 1e-12), 0.0).astype(np.float32)
    inv = inv0
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    for _ in range(2):  # a second pass catches the corners of a smeared step, flat in the first one's 3×3 test
        edges = depth_edges(np.where(valid, 1.0 / np.maximum(inv, 1e-12), 0.0), ratio)
        if not edges.any():
            break
        hi = cv2.dilate(inv, kernel)
        lo = cv2.erode(np.where(valid, inv, np.float32(np.inf)).astype(np.float32), kernel)
        inv = np.where(edges, np.where(inv - lo < hi - inv, lo, hi), inv).astype(np.float32)
    moved = valid & (np.abs(inv - inv0) > 0.01 * inv0)
    out = np.where(valid, 1.0 / np.maximum(inv, 1e-12), 0.0).astype(np.float32)
    return out, moved
