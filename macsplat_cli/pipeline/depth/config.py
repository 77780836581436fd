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
    """Dense depth: the sweep, the checks, the fill and the fusion (measured: benchmarks/history/depth.md).

    Args:
        scale: resolution of the cost volume relative to the working images.
        max_planes: most depth hypotheses; fewer when the depth range moves the image less.
        min_planes: fewest depth hypotheses.
        window: ZNCC window side, pixels (odd).
        p1: SGM penalty for a one-plane jump (cost units; costs lie in [0, 1]).
        p2: SGM penalty for larger jumps, before lowering across edges.
        edge_gamma: P2 is divided by ``1 + edge_gamma·|ΔI|`` (intensity in [0, 1]).
        eight_paths: aggregate along diagonals too (slower, smoother).
        consistency: largest relative depth disagreement between the two views' estimates.
        min_uniqueness: smallest uniqueness margin of the winning hypothesis.
        max_cost: largest matching cost (1 − ZNCC)/2 of the winning hypothesis.
        fill: give every pixel without a trustworthy depth one propagated from its
            confident neighbours (edge-aware), at confidence ``fill_confidence`` or less.
        fill_lambda: smoothness of the fill (OpenCV fast global smoother λ): high enough that the fill does not follow
            fine texture edges (wood grain) inside one surface.
        fill_sigma_color: colour similarity scale of the fill, in 8-bit intensity units.
        fill_confidence: confidence of filled pixels with strong support nearby.
        fill_clamp_near: keep filled depths no nearer than the median measured depth.
        snap_edges: move every pixel on a depth step (its 3×3 neighbourhood spans more than ``edge_ratio`` in depth)
            to the nearer or the farther side, whichever its depth is closer to: the upsampling and the fill blend
            the two sides into depths between them, Gaussians that float between an object and its background
            ("flying pixels") in a novel view.
        edge_ratio: depth ratio across a 3×3 neighbourhood that counts as a step.
        fuse: both-view fusion (:func:`~.fusion.fuse_views`): a pixel whose point lies in the other view's free space
            (nearer than that view's surface by more than ``fuse_tol``, relative) is a second, wrong layer of the
            surface; a filled one is dropped, and a filled pixel of the other view that a measured point contradicts
            takes that point's depth instead.
        fuse_tol: relative depth margin of the free-space test.
        slanted_iters: PatchMatch iterations of the slanted-plane refinement (:mod:`.slanted`), 0 = off.
            The pixels whose SGM winner is not confirmed (it fails the cost or uniqueness test or the left-right check)
            get a plane (inverse depth and its slope) refined from their confirmed neighbours' planes and random
            perturbations, with a ZNCC window warped through the plane's own homography, so surfaces foreshortened
            differently in the two views (slanted to the cameras, wider baselines) match; then the left-right check
            runs on the refined depths.
        slanted_radius: the refinement's ZNCC window has ``(2·radius + 1)²`` samples ...
        slanted_step: ... spaced ``step`` volume pixels (radius 2, step 2: 25 samples over a 9 × 9 window).
        slanted_slope_max: largest normalised slope ``|∂ρ/∂u|·f/ρ`` (≈ tan of the tilt from fronto-parallel).
        slanted_seed: seed of the refinement's random perturbations (the result does not depend on the threads).
        colour_tol: measured pixels whose colour differs from the other view's at their projection by more than this
            (mean absolute difference per channel of 5 × 5 local means, after a per-channel gain and offset fitted
            between the views; :func:`~.checks.colour_outliers`) are not measured but filled; 0 = off. Catches depths
            both views agree on wrongly (reflections, repeated texture).
        speckle_size: after those checks, islands of measured depth up to this share of the image's pixels whose depth
            differs from the measured depth around them by more than ``speckle_step`` (relative) are filled instead
            (:func:`~.checks.remove_speckles`); 0 = off. Wrong matches come in patches, and each patch floats as a
            fragment of surface in a novel view.
        speckle_step: relative depth difference that still connects two neighbouring measured pixels.
    """

    scale: float = 0.5
    max_planes: int = 128
    min_planes: int = 32
    window: int = 5
    p1: float = 0.04
    p2: float = 0.5
    edge_gamma: float = 8.0
    eight_paths: bool = False
    consistency: float = 0.02
    min_uniqueness: float = 0.02
    max_cost: float = 0.35
    fill: bool = True
    fill_lambda: float = 5000.0
    fill_sigma_color: float = 12.0
    fill_confidence: float = 0.35
    fill_clamp_near: bool = True
    snap_edges: bool = True
    edge_ratio: float = 1.1
    fuse: bool = True
    fuse_tol: float = 0.05
    slanted_iters: int = 3
    slanted_radius: int = 2
    slanted_step: int = 2
    slanted_slope_max: float = 3.0
    slanted_seed: int = 0
    colour_tol: float = 0.1
    speckle_size: float = 0.001
    speckle_step: float = 0.04
