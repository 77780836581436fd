"""The stage's entry point: both views' depth maps through sweep, checks, fill, snapping and fusion, in order."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from ..types import DepthMap, TwoViewGeometry, View
from .checks import checked_depth, colour_outliers, remove_speckles, winner_depth
from .config import FILL_RULES, DepthConfig, FilledDepthMap
from .fill import fill_depth_rules, snap_depth_edges
from .fusion import fuse_views
from .slanted import refine_slanted
from .sweep import VolumeDepth, inverse_depth_ranges, sweep_view, upsample_depth

__all__ = ["estimate_depths"]

logger = logging.getLogger(__name__)

FILL_SIGMA_COLOR = 12.0
"""Colour similarity scale of the fill, in 8-bit intensity units."""
FILL_CONFIDENCE = 0.35
"""Confidence of filled pixels with strong support nearby."""
FILL_CLAMP_NEAR = True
"""Keep filled depths no nearer than the median measured depth."""
EDGE_RATIO = 1.1
"""Depth ratio across a 3×3 neighbourhood that counts as a step (``DepthConfig.snap_edges``)."""
FUSE_TOL = 0.05
"""Relative depth margin of the both-view fusion's free-space test (``DepthConfig.fuse``)."""
SPECKLE_STEP = 0.04
"""Relative depth difference that still connects two neighbouring measured pixels (``DepthConfig.speckle_size``)."""


@dataclass
class _ViewDepth:
    """One view's depth at the working resolution after the checks, the fill and the snapping (before the fusion).

    Attributes:
        depth: depth, 0 where none. [H, W] float32
        confidence: [H, W] float32
        measured: pixels whose depth was matched and passed every check. [H, W] bool
        rule: index into :data:`~.config.FILL_RULES` of the rule that gave each pixel its depth. [H, W] uint8
        snapped: pixels moved to one side of a depth step. [H, W] bool
        counts: ``slanted_refined``, ``colour_rejected``, ``speckle_removed`` (see ``FilledDepthMap.fill_counts``).
    """

    depth: np.ndarray
    confidence: np.ndarray
    measured: np.ndarray
    rule: np.ndarray
    snapped: np.ndarray
    counts: dict[str, int]


def estimate_depths(views: list[View], geometry: TwoViewGeometry, config: DepthConfig | None = None) -> list[DepthMap]:
    """Depth maps with confidence for both views, in their own camera frames (working resolution).

    Args:
        views: the two working views.
        geometry: the two cameras (its verified matches bound the depth range).
        config: the stage's configuration (defaults when None).

    Returns:
        One :class:`~.config.FilledDepthMap` per view. [H, W] maps

    Raises:
        ReconstructionError: too few triangulated matches to bound the scene depth.
    """
    cfg = config or DepthConfig()
    ranges = inverse_depth_ranges(geometry)
    vols = [sweep_view(views, geometry, ref, ranges[ref], cfg) for ref in (0, 1)]
    if cfg.slanted_iters > 0:
        refine_slanted(vols, geometry, cfg)
    winners = [winner_depth(vol) for vol in vols]
    per_view = [_view_depth(views, geometry, vols, winners, ref, cfg) for ref in (0, 1)]
    return _fused(per_view, geometry, cfg)


def _view_depth(
    views: list[View],
    geometry: TwoViewGeometry,
    vols: list[VolumeDepth],
    winners: list[np.ndarray],
    ref: int,
    cfg: DepthConfig,
) -> _ViewDepth:
    """View ``ref``: the left-right check, the upsampling to the working resolution, the colour and speckle checks,
    the fill and the snapping of depth steps."""
    depth, conf = checked_depth(vols, winners, geometry, ref)
    v = views[ref]
    refined = vols[ref].refined
    slanted = refined if refined is not None else np.zeros(depth.shape, bool)
    if depth.shape != (v.height, v.width):
        depth, conf = upsample_depth(depth, conf, v.gray)
        up = (v.width, v.height)
        slanted = cv2.resize(slanted.astype(np.uint8), up, interpolation=cv2.INTER_NEAREST) > 0
    measured = (depth > 0) & (conf > 0) & v.mask
    colour_bad = np.zeros(depth.shape, bool)
    if cfg.colour_tol > 0:
        colour_bad = colour_outliers(depth, measured, v, views[1 - ref], geometry, ref, cfg.colour_tol)
        depth, conf, measured = _unmeasure(depth, conf, measured, colour_bad)
    speckles = remove_speckles(np.where(measured, depth, 0.0), round(cfg.speckle_size * depth.size), SPECKLE_STEP)
    depth, conf, measured = _unmeasure(depth, conf, measured, speckles)
    rule = np.where(measured, 0, 3).astype(np.uint8)
    if cfg.fill:
        depth, conf, rule = fill_depth_rules(
            depth, conf, v.image, lam=cfg.fill_lambda, sigma_color=FILL_SIGMA_COLOR,
            fill_confidence=FILL_CONFIDENCE, clamp_near=FILL_CLAMP_NEAR,
        )  # fmt: skip
    conf = np.where(v.mask, conf, 0.0).astype(np.float32)
    depth = np.where(conf > 0, depth, 0.0).astype(np.float32)
    snapped = np.zeros(depth.shape, bool)
    if cfg.snap_edges:
        depth, snapped = snap_depth_edges(depth, EDGE_RATIO)
    counts = {
        "slanted_refined": int((measured & slanted).sum()),
        "colour_rejected": int(colour_bad.sum()),
        "speckle_removed": int(speckles.sum()),
    }
    return _ViewDepth(depth, conf, measured, rule, snapped, counts)


def _unmeasure(
    depth: np.ndarray, conf: np.ndarray, measured: np.ndarray, rejected: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(depth, confidence, measured)`` [H, W] without the ``rejected`` pixels [H, W] bool (left to the fill)."""
    depth = np.where(rejected, 0.0, depth).astype(np.float32)
    conf = np.where(rejected, 0.0, conf).astype(np.float32)
    return depth, conf, measured & ~rejected


def _fused(per_view: list[_ViewDepth], geometry: TwoViewGeometry, cfg: DepthConfig) -> list[DepthMap]:
    """Both views through the fusion (:func:`~.fusion.fuse_views`, when on), with the counts of every rule."""
    depths = [p.depth for p in per_view]
    confs = [p.confidence for p in per_view]
    measured = [p.measured for p in per_view]
    dropped = transferred = [np.zeros(d.shape, bool) for d in depths]
    if cfg.fuse:
        depths, confs, dropped, transferred = fuse_views(depths, confs, measured, geometry, FUSE_TOL)
    out: list[DepthMap] = []
    for ref in (0, 1):
        rule = np.where(depths[ref] > 0, per_view[ref].rule, 3)
        counts = {name: int((rule == i).sum()) for i, name in enumerate(FILL_RULES)}
        counts["snapped_edge"] = int(per_view[ref].snapped.sum())
        counts["dropped_free_space"] = int(dropped[ref].sum())
        counts["from_other_view"] = int(transferred[ref].sum())
        counts.update(per_view[ref].counts)
        logger.debug("depth view %d: %s", ref, counts)
        out.append(FilledDepthMap(depth=depths[ref], confidence=confs[ref], measured=measured[ref], fill_counts=counts))
    return out
