"""Scene compaction: fewer Gaussians and less render work for (nearly) the same picture.

Stage 8. Every reconstruction starts with one Gaussian per valid pixel of each view. :func:`compact` turns the
per-view maps (:class:`~macsplat_cli.gaussians.GaussianMaps`, ``B = 1`` each, in their view's camera
frame) into a smaller flat :class:`~macsplat_cli.gaussians.Gaussians` set in the world frame, with a
:class:`CompactReport` of what each step removed and why. The steps, in the order they run (each can
be switched off in :class:`CompactConfig`; one module per idea):

1. **prune_opacity** (:mod:`.cleanup`, with 2, 4 and 5): non-finite Gaussians and opacities below the
   renderer's ``ALPHA_MIN`` (the renderer culls them: provably invisible).
2. **prune_floaters**: a pixel Gaussian with fewer than ``floater_min_neighbours`` of its 8 grid
   neighbours on the same surface (relative depth within ``floater_depth_tol``): isolated depth
   outliers ("flying pixels").
3. **dedup** (:mod:`.dedup`): a view-``k`` Gaussian that projects into an earlier view onto a valid pixel of
   consistent depth (relative tolerance ``dedup_depth_tol``) is the same surface seen twice; it is
   merged into that view's Gaussian (positions and colours averaged, opacity the larger one, the
   earlier view's scales and rotation kept, since they tile that view's pixel grid). View-``k``
   Gaussians that sample the surface ``dedup_finer_ratio`` times more finely are kept.
4. **prune_occluded**: Gaussians that no camera sees: behind an opaque Gaussian (z-buffer of the
   centres, relative tolerance ``occlusion_depth_tol``) or outside the image, in every view.
5. **prune_subpixel**: Gaussians whose largest projected standard deviation is below
   ``subpixel_px`` pixels in every view.
6. **adaptive** (:mod:`.blocks`): per view, a quadtree over ``2×2 … max_block`` pixel blocks: a block whose pixels all
   carry a Gaussian, with a colour standard deviation below ``color_tol`` and points on a plane
   (out-of-plane deviation below ``plane_tol`` pixel footprints) becomes one Gaussian (moment-matched
   mean and covariance, in-plane extent widened by ``coverage``, colour averaged, opacity
   ``1 − (1 − ō)^opacity_boost``: it stands for several overlapping Gaussians whose alphas accumulate).
   Blocks on the near side of a depth step (a neighbour ``edge_depth_tol`` farther) are never merged.
   Edges and texture keep one Gaussian per pixel.
7. **sh** (:mod:`.sh_degree`): the SH degree drops to the lowest one whose colours differ from the full degree's by less
   than ``sh_tol`` (95th percentile over the Gaussians, seen from every camera and the midpoints
   between them); with the photos given, a higher degree is kept only if it lowers the colour
   error against them by more than ``sh_tol``.
8. **budget** (:mod:`.budget`): at most ``budget`` Gaussians, the most important ones (opacity × largest
   projected area).

Everything is vectorised over pixels and blocks (no Python loop per Gaussian). Steps 3–5 project a view's Gaussians
into a camera only where the view's pixel tiles can land in its image (:mod:`.cull`). The per-quality settings
(``--quality``, ``--budget``) come from :func:`macsplat_cli.presets.compact_config`. Measured:
benchmarks/history/compact.md.
"""

from __future__ import annotations

from .config import CompactConfig, CompactReport, CompactStep
from .run import compact, compact_reconstruction

__all__ = ["CompactConfig", "CompactReport", "CompactStep", "compact", "compact_reconstruction", "compile_kernels"]


def compile_kernels() -> None:
    """Compile (or load from Numba's cache) the view-against-view kernels of the occlusion and dedup steps now, for
    a background thread (:mod:`._kernels`; importing this package does not load Numba)."""
    from ._kernels import compile_kernels as compact_kernels

    compact_kernels()
