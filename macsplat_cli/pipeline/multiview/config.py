"""The N-photo chain's settings: one dataclass, its parts named per step."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..._limits import MAX_PHOTOS
from .shortlist import ShortlistConfig

__all__ = ["MAX_PHOTOS", "MultiViewConfig"]


@dataclass
class MultiViewConfig:
    """The settings of more than two photos (at most :data:`MAX_PHOTOS`); the registration's and the depth plan's
    thresholds are constants of :mod:`.register` and :mod:`.depth` (benchmarks/history/settings.md).

    Args:
        shortlist: which pairs are matched (all of them up to a size, else by image similarity and file order).
        poses: a cameras file with every photo's pose (``--poses``): no pose is estimated, the scene is in its frame.
        covisibility: one set of Gaussians for the scene: where several photos see a surface, only the best-observed
            photo's Gaussians are kept, before the refinement and the compaction (:mod:`.covis`). On with
            ``--quality best`` and with ``balanced``'s joint refinement (:func:`~macsplat_cli.presets.configure`);
            off by default: without a refinement, ``balanced``'s compaction dedup after it, CO3D N = 5 lost 0.09 dB
            (benchmarks/history/multiview_joint.md).
    """

    shortlist: ShortlistConfig = field(default_factory=ShortlistConfig)
    poses: Path | None = None
    covisibility: bool = False
