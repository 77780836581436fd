"""N photos → one scene: pairs chosen (:mod:`.shortlist`), each pair's pose searched and accepted
(:mod:`.pairwise`), tracks (:mod:`.tracks`), incremental registration with bundle adjustment (:mod:`.register`,
:mod:`.triangulate`, :mod:`.bundle`), depth from neighbours (:mod:`.depth`), the chain (:mod:`.run`)."""

from .config import MAX_PHOTOS, MultiViewConfig
from .run import MultiViewResult, reconstruct_views

__all__ = ["MAX_PHOTOS", "MultiViewConfig", "MultiViewResult", "compile_kernels", "reconstruct_views"]


def compile_kernels() -> None:
    """Compile (or load from Numba's cache) the N-photo stages' kernels now, for a background thread: the bundle
    adjustment's Schur complement, the co-visibility init's test, then where view-dependent colour is allowed (the
    joint refinement's set-up)."""
    from .bundle import compile_kernels as bundle_kernels
    from .covis import compile_kernels as covis_kernels
    from .sh_views import compile_kernels as sh_kernels

    bundle_kernels()
    covis_kernels()
    sh_kernels()
