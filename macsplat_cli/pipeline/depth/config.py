"""The dense-depth stage's configuration and its output type (the fill rules a pixel's depth came from)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..types import DepthMap

__all__ = ["FILL_RULES", "DepthConfig", "FilledDepthMap"]

FILL_RULES = ("measured", "filled_edge_aware", "filled_push_pull", "none")
"""How a pixel got its depth: matched in the other view; propagated by the edge-aware smoother from confident
neighbours; extended by the push-pull pyramid (far from any); no depth (outside the view's mask, or dropped by
the both-view fusion)."""


@dataclass
class FilledDepthMap(DepthMap):
    """A :class:`~..types.DepthMap` with how many pixels each rule gave their depth (for the report).

    Attributes:
        fill_counts: rule → pixels. The :data:`FILL_RULES` partition the image (they add up to H·W); within
            them, ``snapped_edge``: pixels moved to one side of a depth step; ``dropped_free_space``: filled pixels
            the fusion proved a wrong second layer (now without depth, in ``none``); ``from_other_view``:
            filled pixels that took a measured depth of the other view; ``slanted_refined``: measured pixels whose
            depth came from the slanted-plane refinement (``DepthConfig.slanted_iters``) rather than the SGM winner;
            ``colour_rejected``: pixels that passed the depth checks but failed the colour check
            (:func:`~.checks.colour_outliers`) and were filled instead; ``speckle_removed``: measured pixels of
            islands their surroundings contradict (:func:`~.checks.remove_speckles`), filled instead.
    """

    fill_counts: dict[str, int] = field(default_factory=dict)


@dataclass
class DepthConfig:
    """Dense depth: the sweep, the checks, the fill and the fusion. The thresholds nobody turns are constants beside
    the code (:mod:`.sweep`, :mod:`.checks`, :mod:`.slanted`, :mod:`.estimate`); measured:
    benchmarks/history/depth.md, benchmarks/history/settings.md.

    Args:
        scale: resolution of the cost volume relative to the working images, in (0, 1].
        fill: give every pixel without a trustworthy depth one propagated from its confident neighbours
            (edge-aware), at confidence :data:`~.estimate.FILL_CONFIDENCE` or less.
        fill_lambda: smoothness of the fill (OpenCV fast global smoother λ, > 0): high enough that the fill does not
            follow fine texture edges (wood grain) inside one surface.
        snap_edges: move every pixel on a depth step (its 3×3 neighbourhood spans more than
            :data:`~.estimate.EDGE_RATIO` in depth) to the nearer or the farther side, whichever its depth is closer
            to: no Gaussians floating between an object and its background ("flying pixels").
        fuse: both-view fusion (:func:`~.fusion.fuse_views`): a pixel whose point lies in the other view's free space
            is a second, wrong layer of the surface; a filled one is dropped, and a filled pixel of the other view
            that a measured point contradicts takes that point's depth instead.
        slanted_iters: PatchMatch iterations of the slanted-plane refinement (:mod:`.slanted`), ≥ 0; 0 = off. The
            pixels whose SGM winner is not confirmed get a plane (inverse depth and slope) refined from their
            confirmed neighbours' with a ZNCC window warped through the plane's homography; then the left-right
            check runs on the refined depths.
        colour_tol: measured pixels whose colour differs from the other view's at their projection by more than
            this (mean absolute difference per channel of 5 × 5 local means, in [0, 1], after a per-channel gain
            and offset; :func:`~.checks.colour_outliers`) are filled instead; 0 = off.
        speckle_size: islands of measured depth up to this share of the image's pixels, in [0, 1], whose depth
            differs from the measured depth around them are filled instead (:func:`~.checks.remove_speckles`);
            0 = off.
    """

    scale: float = 0.5
    fill: bool = True
    fill_lambda: float = 5000.0
    snap_edges: bool = True
    fuse: bool = True
    slanted_iters: int = 3
    colour_tol: float = 0.1
    speckle_size: float = 0.001
