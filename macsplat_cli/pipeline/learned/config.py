"""The learned matcher's settings (:class:`LearnedConfig`): ALIKED keypoints and descriptors matched by LightGlue.

Measured: benchmarks/history/learned.md (keypoint budgets, detection sizes, LightGlue's adaptive depth and width).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["LearnedConfig"]


@dataclass(frozen=True)
class LearnedConfig:
    """Args:
    detector: the ALIKED variant (``aliked-n16``: the probe's best on the real pairs; its LightGlue weights).
    max_keypoints: the keypoint budget per photo (the strongest score-map maxima). LightGlue's attention costs
        ``O(M²)`` per layer: the lever on time.
    detect_size: long side of the image ALIKED runs on (capped at the photo's detail size; never upsampled).
    depth_confidence: LightGlue stops after a layer once this share of the points are confident (-1: all 9
        layers).
    width_confidence: LightGlue drops the points it is confident will not match (-1: off). 0.9 (kornia's default
        0.99): LightGlue 30–40 % faster on the dev pairs, their outcomes unchanged.
    filter_threshold: LightGlue's match-score threshold (its default, 0.1).
    """

    detector: str = "aliked-n16"
    max_keypoints: int = 2048
    detect_size: int = 1024
    depth_confidence: float = 0.95
    width_confidence: float = 0.9
    filter_threshold: float = 0.1
