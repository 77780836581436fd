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
        ``O(M²)`` per layer: the lever on LightGlue's time, not kept lower: 1792 saves 0.4 CPU-s a pair (2.4 → 2.0,
        one core) but ICL (2,5), the learned tier's one rescue, keeps 38 verified matches instead of 53; 1536
        loses it (log10 NFA −36) and CO3D 55°'s learned pose moves from 1.1° to 5.6° off.
    detect_size: long side of the image ALIKED runs on (capped at the photo's detail size; never upsampled; the
        keypoints are mapped back to working pixels). ALIKED's time goes with the pixels (CO3D's 1024 × 576 photos,
        one core: 1.7 s a photo at 1024, 1.3 at 896, 0.9 at 768), but the wide pairs' matches with them: CO3D 55°'s
        learned pose is 1.1° off at 1024, 7.1° at 896, and at 768 only 46 % of its matches agree.
    depth_confidence: LightGlue stops after a layer once this share of the points are confident (-1: all 9
        layers). Not lower: 0.9 loses ICL (2,5)'s rescue (its learned pose 2.8° off, refused).
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
