"""N photos → one scene: pairs chosen (:mod:`.shortlist`), each pair's pose searched and accepted
(:mod:`.pairwise`), tracks (:mod:`.tracks`), incremental registration with bundle adjustment (:mod:`.register`,
:mod:`.triangulate`, :mod:`.bundle`), depth from neighbours (:mod:`.depth`), the chain (:mod:`.run`)."""

from .config import MAX_PHOTOS, MultiViewConfig
from .run import MultiViewResult, reconstruct_views

__all__ = ["MAX_PHOTOS", "MultiViewConfig", "MultiViewResult", "reconstruct_views"]
