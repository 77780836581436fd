"""The compaction's settings and its report (one step per entry, with why it removed what it did)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from ...errors import InputError
from ...report import CompactReport, CompactStep

__all__ = ["CompactConfig", "CompactReport", "CompactStep"]


@dataclass
class CompactConfig:
    """Settings of :func:`~.run.compact`; the defaults are the ``"balanced"`` preset (the others:
    :func:`macsplat_cli.presets.compact_config`).

    Args:
        name: the preset these settings came from (reported only).
        prune_floaters: remove isolated pixel Gaussians.
        floater_min_neighbours: fewest of the 8 grid neighbours on the same surface to keep a Gaussian.
        floater_depth_tol: a neighbour is on the same surface within this relative depth difference.
        dedup: merge Gaussians that two views share.
        dedup_depth_tol: relative depth tolerance of the reprojection test.
        dedup_finer_ratio: a later view's Gaussian whose pixel footprint is this many times smaller than
            the earlier view's (it sees the surface in more detail) is kept, not merged.
        prune_occluded: remove Gaussians that no view sees.
        occlusion_depth_tol: relative depth margin of the z-buffer test.
        occluder_min_opacity: only Gaussians at least this opaque hide others.
        subpixel_px: remove Gaussians whose largest projected std is below this (pixels) in every view;
            0 disables the step.
        adaptive: merge flat, uniform pixel blocks.
        max_block: largest block side (2, 4, 8 or 16); blocks are 2, 4, … up to it.
        color_tol: largest colour standard deviation (per channel, colours in [0, 1]) of a merged block.
        plane_tol: largest out-of-plane standard deviation of a merged block, in pixel footprints.
        edge_depth_tol: pixels with a neighbour this much farther (relative depth: the near side of a depth step)
            are never merged.
        coverage: the merged Gaussian's in-plane standard deviations relative to the block's moment-matched
            ones (> 1 closes the seams between neighbouring blocks).
        opacity_boost: a merged Gaussian's opacity is ``1 − (1 − ō)^opacity_boost`` (ō: its pixels' mean): one
            Gaussian stands for several overlapping ones, whose alphas accumulate.
        sh: ``"auto"``: drop SH bands that do not matter (see the package docstring); ``"keep"``: keep them;
            ``"zero"``: drop only bands that are exactly zero everywhere (lossless).
        sh_tol: colour tolerance of the SH step (colours in [0, 1]).
        budget: at most this many Gaussians (the most important ones); None: no limit.
    """

    name: str = "balanced"
    prune_floaters: bool = True
    floater_min_neighbours: int = 2
    floater_depth_tol: float = 0.05
    dedup: bool = True
    dedup_depth_tol: float = 0.02
    dedup_finer_ratio: float = 1.5
    prune_occluded: bool = True
    occlusion_depth_tol: float = 0.05
    occluder_min_opacity: float = 0.5
    subpixel_px: float = 0.1
    adaptive: bool = True
    max_block: int = 8
    color_tol: float = 0.06
    plane_tol: float = 0.5
    edge_depth_tol: float = 0.15
    coverage: float = 1.7
    opacity_boost: float = 2.0
    sh: Literal["auto", "keep", "zero"] = "auto"
    sh_tol: float = 2.0 / 255.0
    budget: int | None = None

    def validate(self) -> None:
        """Raise :class:`~macsplat_cli.errors.InputError` on a setting out of range."""
        if self.max_block not in (2, 4, 8, 16):
            raise InputError(f"max_block {self.max_block}: use 2, 4, 8 or 16")
        if self.budget is not None and self.budget < 0:
            raise InputError(f"budget {self.budget}: give a number of Gaussians ≥ 0")
        if self.sh not in ("auto", "keep", "zero"):
            raise InputError(f"sh {self.sh!r}: use auto, keep or zero")
        tolerances = ("floater_depth_tol", "edge_depth_tol", "dedup_depth_tol", "occlusion_depth_tol", "color_tol")
        for name in (*tolerances, "plane_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"{name} {v}: give a finite number ≥ 0")
        if not (math.isfinite(self.coverage) and self.coverage > 0):
            raise InputError(f"coverage {self.coverage}: give a finite number > 0")
