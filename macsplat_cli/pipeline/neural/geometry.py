"""Geometry from the network's point maps: the focal length (Weiszfeld) and which pixels of a dense descriptor map
to match. The pose from the point map (PnP) is the pose stage's: :mod:`..pose.pnp`.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from ...errors import InputError, ReconstructionError

__all__ = ["estimate_focal_weiszfeld", "pixel_grid", "sample_descriptors"]


def estimate_focal_weiszfeld(
    pts: np.ndarray,  # [H, W, 3]
    pp: tuple[float, float] | None = None,
    *,
    mask: np.ndarray | None = None,  # [H, W]
    iters: int = 10,
    focal_base: float | None = None,
    focal_range: tuple[float, float] = (0.5, 3.5),
) -> float:
    """Focal length (pixels, square pixels) of the camera that sees the point map ``pts`` in its own frame.

    With ``p = (x/z, y/z)`` and ``d`` the pixel's offset from the principal point, ``f`` minimises
    ``Σ |d − f·p|`` (a robust L1 fit): start from the least-squares ``f = Σ p·d / Σ |p|²``, then
    ``iters`` Weiszfeld reweightings ``w = 1/max(|d − f·p|, 1e-8)``. Pixel centres at +0.5.

    Args:
        pts: point map in the camera's frame. [H, W, 3]
        pp: principal point (default: the image centre).
        mask: pixels to use (default: all with finite points in front of the camera). [H, W]
        iters: reweighting iterations.
        focal_base: with ``focal_range``, the result is clipped to ``[lo, hi] × focal_base``
            (default base: a 60° field of view across the long side).

    Raises:
        ReconstructionError: no usable pixel.
    """
    h, w = pts.shape[:2]
    cx, cy = pp if pp is not None else (w / 2.0, h / 2.0)
    base = focal_base if focal_base is not None else max(w, h) / (2.0 * math.tan(math.radians(30.0)))
    ys, xs = np.mgrid[0:h, 0:w]
    d = np.stack([xs + 0.5 - cx, ys + 0.5 - cy], -1).reshape(-1, 2)
    P = pts.reshape(-1, 3).astype(np.float64)
    ok = np.isfinite(P).all(1) & (P[:, 2] > 1e-12)
    if mask is not None:
        ok &= mask.reshape(-1)
    if not ok.any():
        raise ReconstructionError("focal length: no pixel of the point map is in front of the camera")
    p = P[ok, :2] / P[ok, 2:3]
    d = d[ok]
    den = float((p * p).sum())
    f = float((p * d).sum()) / den if den > 0 else base
    for _ in range(iters):
        wgt = 1.0 / np.maximum(np.linalg.norm(d - f * p, axis=1), 1e-8)
        den = float((wgt[:, None] * p * p).sum())
        if den <= 0:
            break
        f = float((wgt[:, None] * p * d).sum()) / den
    lo, hi = focal_range[0] * base, focal_range[1] * base
    return float(np.clip(f if np.isfinite(f) else base, lo, hi))


def sample_descriptors(
    conf: np.ndarray,  # [H, W]
    *,
    sampling: Literal["grid", "topk"] = "grid",
    stride: int = 4,
    top_k: int = 12288,
    mask: np.ndarray | None = None,  # [H, W]
) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Which pixels of a dense descriptor map to match: flat row-major indices, and the grid shape.

    ``grid``: pixels ``(stride//2 + i·stride, stride//2 + j·stride)``, (rows, cols) returned when no
    pixel was masked out; ``topk``: the ``top_k`` most confident pixels (ties broken by position).

    Returns:
        ``(indices [M] int64, grid or None)``.
    """
    h, w = conf.shape
    if sampling == "grid":
        rows = np.arange(stride // 2, h, stride)
        cols = np.arange(stride // 2, w, stride)
        idx = (rows[:, None] * w + cols[None, :]).reshape(-1)
        grid: tuple[int, int] | None = (len(rows), len(cols))
    elif sampling == "topk":
        flat = conf.reshape(-1)
        k = min(top_k, flat.size)
        idx = np.sort(np.argsort(-flat, kind="stable")[:k])
        grid = None
    else:
        raise InputError(f"descriptor sampling must be 'grid' or 'topk', got {sampling!r}")
    if mask is not None:
        keep = mask.reshape(-1)[idx]
        if not keep.all():
            idx, grid = idx[keep], None
    return idx.astype(np.int64), grid


def pixel_grid(h: int, w: int) -> np.ndarray:
    """Pixel centres (+0.5) of an h×w grid, row-major. [h·w, 2]"""
    ys, xs = np.mgrid[0:h, 0:w]
    return np.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], 1).astype(np.float64)
