"""The N-photo chain's settings: one dataclass, its parts named per step."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..._limits import MAX_PHOTOS
from .depth import DepthPlanConfig
from .register import RegisterConfig
from .shortlist import ShortlistConfig

__all__ = ["MAX_PHOTOS", "MultiViewConfig"]


@dataclass
class MultiViewConfig:
    """Args:
    max_photos: more photos than this are refused (a usage error) before any is read.
    shortlist: which pairs are matched (all of them up to a size, else by image similarity and file order).
    register: the incremental registration and its bundle adjustment.
    depth: each photo's depth from its neighbours.
    poses: a cameras file with every photo's pose (``--poses``): no pose is estimated, the scene is in its frame.
    known_pose_max_px: with given poses, a match is kept within this Sampson distance (px) of their epipolar
        geometry (the given poses are trusted to about a pixel: a calibrated rig's, an SfM's).
    covisibility: one set of Gaussians for the scene: where several photos see a surface, only the best-observed
        photo's Gaussians are kept, before the refinement and the compaction (:mod:`.covis`, issue 41). On with
        ``--quality best`` (:func:`~macsplat_cli.presets.configure`); off by default: with ``balanced``'s compaction
        dedup after it, CO3D N = 5 lost 0.09 dB (benchmarks/history/multiview_joint.md).
    """

    max_photos: int = MAX_PHOTOS
    shortlist: ShortlistConfig = field(default_factory=ShortlistConfig)
    register: RegisterConfig = field(default_factory=RegisterConfig)
    depth: DepthPlanConfig = field(default_factory=DepthPlanConfig)
    poses: Path | None = None
    known_pose_max_px: float = 2.0
    covisibility: bool = False
