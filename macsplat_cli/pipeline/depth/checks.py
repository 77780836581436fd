"""The checks a measured depth must pass: the SGM winner's own tests, the left-right check, the colour check and
the speckle (island) check.

1. Winner tests (:func:`winner_depth`): the winning plane had a complete window, its cost is at most
   ``max_cost`` and its uniqueness margin at least ``min_uniqueness``.
2. Left-right consistency (:func:`left_right_error`, :func:`checked_depth`): a pixel's depth, carried into the
   other view, must agree with the depth found there within ``consistency`` relative error; the confidence
   falls with that error, the uniqueness and the winning cost.
3. Colour (:func:`colour_outliers`): pixels whose colour disagrees with the other view's at their projection.
4. Speckles (:func:`remove_speckles`): small islands of depth that differs from all around them.

Pixels that fail are left without a measured depth; the fill gives them one.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..types import TwoViewGeometry, View
from .pair import carry_depth, relative_pose
from .sweep import VolumeDepth

__all__ = [
    "COLOUR_WINDOW",
    "checked_depth",
    "colour_outliers",
    "left_right_error",
    "remove_speckles",
    "winner_depth",
]

MIN_UNIQUENESS = 0.02
"""Smallest uniqueness margin of the winning hypothesis."""
MAX_COST = 0.35
"""Largest matching cost (1 − ZNCC)/2 of the winning hypothesis."""
CONSISTENCY = 0.02
"""Largest relative depth disagreement between the two views' estimates (the left-right check)."""
COLOUR_WINDOW = 5
"""Side of the box over which :func:`colour_outliers` averages the colours before comparing them."""

UNIQUENESS_FULL = 0.1
"""Uniqueness margin from which it no longer lowers a measured pixel's confidence (:func:`checked_depth`)."""

CONFIDENCE_FLOOR = 0.2
"""Smallest factor the uniqueness and the winning cost each put on a consistent pixel's confidence."""


def winner_depth(vol: VolumeDepth) -> np.ndarray:
    """Depth where the winner passes the window, cost and uniqueness tests, else 0. [h, w] float32"""
    uniq_ok = vol.uniq >= MIN_UNIQUENESS
    if vol.refined is not None:  # a refined plane has no SGM uniqueness: its own cost must be lower
        uniq_ok = uniq_ok | vol.refined
    ok = vol.has_window & (vol.inv_depth > 0) & (vol.win_cost <= MAX_COST) & uniq_ok
    return np.where(ok, 1.0 / np.maximum(vol.inv_depth, 1e-12), 0.0).astype(np.float32)


def left_right_error(
    depth_ref: np.ndarray, depth_src: np.ndarray, K_ref: np.ndarray, K_src: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Relative disagreement of each reference depth [h, w] with the source view's depth [hs, ws] at the pixel it
    lands on (``R, t``: reference → source camera). [h, w] (inf if none)"""
    h, w = depth_ref.shape
    ys, xs = np.mgrid[0:h, 0:w]
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs, dtype=np.float64)], -1).reshape(-1, 3)
    X = (pix @ np.linalg.inv(K_ref).T) * depth_ref.reshape(-1, 1)
    Xs = X @ R.T + t
    z = Xs[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (Xs @ K_src.T)[:, :2] / z[:, None]
    hs, ws = depth_src.shape
    uv = np.clip(np.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0), -1.0, 1e7)
    ui = np.floor(uv[:, 0]).astype(np.int64)
    vi = np.floor(uv[:, 1]).astype(np.int64)
    inside = (depth_ref.reshape(-1) > 0) & (z > 0) & (ui >= 0) & (ui < ws) & (vi >= 0) & (vi < hs)
    err = np.full(h * w, np.inf)
    d_src = depth_src[vi[inside], ui[inside]]
    rel = np.abs(d_src - z[inside]) / z[inside]
    err[np.flatnonzero(inside)] = np.where(d_src > 0, rel, np.inf)
    return err.reshape(h, w)


def checked_depth(
    vols: list[VolumeDepth], winners: list[np.ndarray], geometry: TwoViewGeometry, ref: int
) -> tuple[np.ndarray, np.ndarray]:
    """View ``ref``'s depth after the left-right check, and its confidence.

    Args:
        vols: both views' sweep results.
        winners: both views' depths that passed the winner tests (:func:`winner_depth`). [h, w] each
        geometry: the two cameras.
        ref: the view (0 or 1).

    Returns:
        ``(depth, confidence)``: 0 where the check fails. [h, w] float32 each
    """
    depth, depth_o = winners[ref], winners[1 - ref]
    uniq, win_cost, Kr, Ko = vols[ref].uniq, vols[ref].win_cost, vols[ref].K, vols[1 - ref].K
    R, t = relative_pose(geometry, ref)
    err = left_right_error(depth, depth_o, Kr, Ko, R, t)
    consistent = err < CONSISTENCY
    conf = consistent * np.clip(1.0 - err / CONSISTENCY, 0.0, 1.0) ** 0.5
    conf = conf * np.clip(uniq / UNIQUENESS_FULL, CONFIDENCE_FLOOR, 1.0)
    conf = conf * np.clip(1.0 - win_cost / MAX_COST, CONFIDENCE_FLOOR, 1.0)
    conf = conf.astype(np.float32)
    depth = np.where(conf > 0, depth, 0.0).astype(np.float32)
    return depth, conf


def _gain_offset(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-channel least squares ``b ≈ (a − ma)·gain + mb`` of colours ``a, b`` [3, N]: ``(ma, mb, gain)`` [3, 1]."""
    ma, mb = a.mean(1, keepdims=True), b.mean(1, keepdims=True)
    gain = ((a - ma) * (b - mb)).mean(1, keepdims=True) / np.maximum(((a - ma) ** 2).mean(1, keepdims=True), 1e-8)
    return ma, mb, gain


def colour_outliers(
    depth: np.ndarray, measured: np.ndarray, v: View, v_o: View, geometry: TwoViewGeometry, ref: int, tol: float
) -> np.ndarray:
    """Measured pixels whose colour disagrees with the other view's where their point projects.

    The left-right check and ZNCC accept matches that are consistent in geometry and in texture *contrast* but
    not in colour: a wrong depth that both views agree on (reflections on a glossy table, repeated wood grain,
    a shadow edge), which then puts the wrong colours at the wrong place in every novel view. Colours are local
    means (a ``COLOUR_WINDOW`` box, so a sub-pixel offset on fine texture is no disagreement), compared after a
    per-channel gain and offset fitted between the views over the measured pixels (least squares, refitted
    without the worst quarter: exposure and white balance may differ).

    Args:
        depth: depth of view ``ref``, 0 where none. [H, W]
        measured: its measured pixels. [H, W] bool
        v, v_o: view ``ref`` and the other view.
        geometry: the two cameras.
        ref: index of ``v`` (0 or 1).
        tol: largest mean absolute colour difference per channel (colours in [0, 1]).

    Returns:
        Measured pixels that disagree by more than ``tol`` (none when fewer than 100 project into the other
        view). [H, W] bool
    """
    K, K_o = (geometry.K0, geometry.K1) if ref == 0 else (geometry.K1, geometry.K0)
    R, t = relative_pose(geometry, ref)
    q, _, inside, sel = carry_depth(np.where(measured, depth, 0.0), K, K_o, R, t, (v_o.height, v_o.width))
    out = np.zeros(depth.shape, bool)
    if inside.sum() < 100:
        return out
    k = (COLOUR_WINDOW, COLOUR_WINDOW)  # local means: a sub-pixel offset on fine texture is no disagreement
    here, there = sel[inside], q[inside]
    # channel-first rows: reductions over contiguous memory
    c = np.stack([cv2.blur(np.ascontiguousarray(v.image[..., i]), k).reshape(-1)[here] for i in range(3)])
    c_o = np.stack([cv2.blur(np.ascontiguousarray(v_o.image[..., i]), k).reshape(-1)[there] for i in range(3)])
    a, b = c[:, ::4], c_o[:, ::4]  # a global fit: a quarter of the pixels is plenty
    ma, mb, gain = _gain_offset(a, b)  # least squares, then again without the worst quarter
    r_fit = np.abs((a - ma) * gain + mb - b).sum(0)
    keep = r_fit <= np.percentile(r_fit, 75)
    ma, mb, gain = _gain_offset(a[:, keep], b[:, keep])
    res = np.abs((c - ma) * gain + mb - c_o).sum(0) / 3.0
    out.reshape(-1)[sel[inside]] = res > tol
    return out


def remove_speckles(depth: np.ndarray, max_size: int, max_step: float, context: int = 31) -> np.ndarray:
    """Islands of measured depth that their surroundings contradict: connected regions of at most ``max_size``
    pixels (:func:`cv2.filterSpeckles` on log depth; neighbours closer than ``max_step`` in relative depth are
    connected; pixels without depth separate regions) whose pixels differ by more than ``max_step`` from the mean
    inverse depth of the other measured pixels within a ``context`` × ``context`` window.

    Wrong matches come in patches (repetitive or glossy texture, foreshortened slants at wider baselines); each
    patch would become a fragment of surface floating in a novel view. Removed, the fill gives those pixels the
    depth of their surroundings. An island with no measured pixels around it, or one that agrees with them across
    a hole, is kept: at wide baselines the measured depth is sparse, and there such islands are mostly right.

    Args:
        depth: depth, 0 where unknown. [H, W] float32
        max_size: largest region that counts as an island, pixels; 0 = off.
        max_step: relative depth difference that still connects two neighbours.
        context: side of the window, pixels, whose other measured pixels judge an island.

    Returns:
        The pixels removed. [H, W] bool
    """
    valid = depth > 0
    if max_size <= 0 or not valid.any():
        return np.zeros(depth.shape, bool)
    step = math.log1p(max_step)
    log_z = np.log(np.where(valid, depth, 1.0).astype(np.float64))
    # 16-bit codes, 1 unit = step / 4 of log depth (so max_step is 4 units); 0 stays "no depth"
    code = np.where(valid, np.clip((log_z - log_z[valid].min()) / (step / 4) + 1, 1, 32767), 0).astype(np.int16)
    cv2.filterSpeckles(code, 0, int(max_size), 4)
    island = valid & (code == 0)
    if not island.any():
        return island
    rest = (valid & ~island).astype(np.float32)
    inv = np.where(valid, 1.0 / np.maximum(depth, 1e-12), 0.0).astype(np.float32)
    num = cv2.boxFilter(inv * rest, -1, (context, context), normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(rest, -1, (context, context), normalize=False, borderType=cv2.BORDER_CONSTANT)
    seen = den > 0.5  # at least one other measured pixel around
    ratio = np.where(seen, inv * den / np.maximum(num, 1e-12), 1.0)
    return island & seen & (np.abs(np.log(np.maximum(ratio, 1e-12))) > step)
