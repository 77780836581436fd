"""Stage 5: dense depth with confidence for both views (plane sweep + semi-global matching).

For each view (the *reference*) against the other (the *source*), one module per idea:

1. :mod:`.sweep`: fronto-parallel planes uniform in inverse depth, a ZNCC cost volume through each plane's
   homography (no rectification), semi-global aggregation and the winner with a sub-plane offset, at a fraction
   of the working resolution; Numba kernels :mod:`._sgm_kernels`, plain-PyTorch twin :mod:`._sgm_reference`.
2. :mod:`.slanted` (``DepthConfig.slanted_iters``): PatchMatch refinement of slanted planes for the pixels whose
   winner is not confirmed, seeded by the confirmed ones; Numba kernels :mod:`._patchmatch_kernels`, plain-NumPy
   twin :mod:`._patchmatch_reference`.
3. :mod:`.checks`: the winner's cost and uniqueness tests, the left-right check (the confidence), the colour
   check and the removal of speckles. Pixels that fail are left without a measured depth.
4. :mod:`.fill`: every other pixel inside the view's mask gets a depth from its confident neighbours
   (edge-aware) or, far from any, from a push-pull pyramid; pixels between the two sides of a depth step are
   moved to one side.
5. :mod:`.fusion`: a filled point in the other view's free space is dropped; a filled point that a measured
   point of the other view shows to be too far takes that point's depth.

:mod:`.estimate` chains them (:func:`estimate_depths`); :mod:`.pair` holds the two cameras' relative pose and the
carrying of a depth map into the other view; :mod:`.config` the configuration and the output type, whose
:attr:`FilledDepthMap.fill_counts` give the counts of every rule (the run report's ``fill`` section).
Measured: benchmarks/history/depth.md.
"""

from __future__ import annotations

from .checks import colour_outliers, remove_speckles
from .config import FILL_RULES, DepthConfig, FilledDepthMap
from .estimate import estimate_depths
from .fill import depth_edges, fill_depth, fill_depth_rules, push_pull, snap_depth_edges
from .fusion import fuse_views
from .sweep import plane_sweep_cost

__all__ = [
    "FILL_RULES",
    "DepthConfig",
    "FilledDepthMap",
    "colour_outliers",
    "compile_kernels",
    "depth_edges",
    "estimate_depths",
    "fill_depth",
    "fill_depth_rules",
    "fuse_views",
    "plane_sweep_cost",
    "push_pull",
    "remove_speckles",
    "snap_depth_edges",
]


def compile_kernels() -> None:
    """Compile the stage's Numba kernels now (or load them from the cache): for a background thread."""
    from . import _patchmatch_kernels, _sgm_kernels

    _sgm_kernels.compile_kernels()
    _patchmatch_kernels.compile_kernels()
