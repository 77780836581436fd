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
    """

    shortlist: ShortlistConfig = field(default_factory=ShortlistConfig)
    poses: Path | None = None
