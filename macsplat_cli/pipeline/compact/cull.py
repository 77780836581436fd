"""The compaction's spatial index: each view's alive Gaussians grouped by pixel tile, with each tile's world bounding
box, so that a step that projects Gaussians into a camera projects only the tiles whose box meets that camera's
frustum (the others' Gaussians would all land outside the image).

With many photos most views see little of each other: the view-against-view steps (dedup, prune_occluded,
prune_subpixel) then cost O(Gaussians a camera can see) per camera instead of O(all Gaussians), the same outputs
(the test is conservative: a tile it rejects holds no Gaussian that :meth:`~.state.ViewState.project` finds
inside).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ...camera_math import NEAR_Z
from .state import ViewState

__all__ = ["TILE", "Tiles", "view_tiles"]

TILE = 16
"""Side (px) of a tile: 768 tiles in a 512 × 384 map, small enough to follow a frustum's edge, large enough that the
box test (five half-spaces) costs little beside projecting the tile's 256 Gaussians."""
_MARGIN_PX = 1.0
"""The frustum is widened by this many pixels on each side: the box test and the projection round differently."""
_ALL_SHARE = 0.6
"""When the tiles a camera sees hold this share of the Gaussians, all are projected (the others land outside): picking
them out would cost more than projecting the rest."""


@dataclass
class Tiles:
    """One view's alive Gaussians grouped by pixel tile (only tiles holding one).

    Attributes:
        order: positions in the view's alive list (the ``index`` given), grouped by tile. [M] int64
        start: each tile's first entry in ``order``; the last entry is M. [T + 1] int64
        lo, hi: each tile's world bounding box, its least and largest corner. [T, 3] float64 each
    """

    order: torch.Tensor
    start: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor

    def seen_by(self, cam: ViewState) -> torch.Tensor | slice:
        """Positions in the alive list of the Gaussians in tiles whose box meets ``cam``'s frustum (grouped by
        tile, ascending within a tile) [M'] int64, or ``slice(None)`` (all of them) when that is most of them
        (:data:`_ALL_SHARE`)."""
        sel = _box_in_frustum(self.lo, self.hi, cam.w2c, cam.K, cam.size).nonzero().squeeze(1)
        if sel.numel() == 0:
            return self.order[:0]
        first, count = self.start[sel], self.start[sel + 1] - self.start[sel]
        ends = count.cumsum(0)
        if int(ends[-1]) >= _ALL_SHARE * len(self.order):
            return slice(None)
        pos = torch.arange(int(ends[-1]), dtype=torch.int64)
        pos += torch.repeat_interleave(first - (ends - count), count)
        return self.order[pos]


def view_tiles(index: torch.Tensor, world: torch.Tensor, width: int) -> Tiles:
    """The tiles of a view's alive Gaussians: ``index`` their pixel (``row * width + col``) [M], ``world`` their
    world centres [M, 3] float64."""
    ntx = -(-width // TILE)
    tile = (index // width // TILE) * ntx + (index % width) // TILE
    tile_sorted, order = torch.sort(tile, stable=True)
    ids, count = torch.unique_consecutive(tile_sorted, return_counts=True)
    start = torch.zeros(len(ids) + 1, dtype=torch.int64)
    start[1:] = count.cumsum(0)
    dense = torch.searchsorted(ids, tile)  # each Gaussian's tile among the non-empty ones
    lo = torch.full((len(ids), 3), torch.inf, dtype=world.dtype)
    hi = torch.full((len(ids), 3), -torch.inf, dtype=world.dtype)
    d3 = dense[:, None].expand(-1, 3)
    lo.scatter_reduce_(0, d3, world, "amin")
    hi.scatter_reduce_(0, d3, world, "amax")
    return Tiles(order, start, lo, hi)


def _box_in_frustum(
    lo: torch.Tensor, hi: torch.Tensor, w2c: torch.Tensor, K: torch.Tensor, size: tuple[int, int]
) -> torch.Tensor:
    """Whether each world box (least and largest corner ``lo``, ``hi`` [T, 3]) may hold a point that projects inside
    the image ``size`` (height, width) of the camera ``w2c`` [4, 4], ``K`` [3, 3] (conservative: False only when the
    whole box lies outside one of the frustum's five half-spaces). [T] bool

    Each half-space is ``a · X + b > 0`` in world coordinates (``z > NEAR_Z``, ``u ≥ −margin``, ``u < w + margin``,
    the same for ``v``; ``u · z`` and ``z`` are affine in ``X``); an affine function's largest value over a box is
    ``a · centre + |a| · half-extent + b`` (what its largest corner gives, in one product instead of eight)."""
    P = K @ w2c[:3]  # [3, 4]: (u·z, v·z, z) = P · (X, 1)
    h, w = size
    m = _MARGIN_PX
    z = P[2] - torch.tensor([0.0, 0.0, 0.0, NEAR_Z], dtype=P.dtype)
    planes = torch.stack([z, P[0] + m * P[2], (w + m) * P[2] - P[0], P[1] + m * P[2], (h + m) * P[2] - P[1]])
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    top = centre @ planes[:, :3].T + half @ planes[:, :3].abs().T + planes[:, 3]  # [T, 5] each half-space's largest
    return (top > 0).all(1)
