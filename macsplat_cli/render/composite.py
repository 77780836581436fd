"""Differentiable alpha compositing of projected Gaussians on the CPU (Numba kernels)."""

from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from . import _kernels

__all__ = ["TILE_SIZE", "Tiles", "bin_tiles", "composite"]

TILE_SIZE = 16


class Tiles:
    """Tile lists of a set of depth-sorted Gaussians (see :func:`bin_tiles`)."""

    def __init__(self, offsets: np.ndarray, lists: np.ndarray, width: int, height: int, tile: int) -> None:
        self.offsets = offsets  # [n_tiles + 1] int64
        self.lists = lists  # [n_isect] int32
        self.width = width
        self.height = height
        self.tile = tile

    @property
    def n_intersections(self) -> int:
        return int(self.lists.shape[0])


def bin_tiles(pixel_rect: torch.Tensor, width: int, height: int, tile: int = TILE_SIZE) -> Tiles:
    """Bin depth-sorted Gaussians into tiles. ``pixel_rect: [M, 4] int32`` (x0, x1, y0, y1)."""
    rect = np.ascontiguousarray(pixel_rect.detach().cpu().numpy().astype(np.int32, copy=False))
    offsets, lists = _kernels.bin_tiles(rect, width, height, tile)
    return Tiles(offsets, lists, width, height, tile)


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(  # noqa: ANN205 - autograd signature
        ctx,  # noqa: ANN001
        means2d: torch.Tensor,
        conics: torch.Tensor,
        opacities: torch.Tensor,
        features: torch.Tensor,
        pixel_rect: torch.Tensor,
        tiles: Tiles,
    ):
        arrays = (_np(means2d), _np(conics), _np(opacities), _np(features), _np(pixel_rect))
        feat, trans, last, _ = _kernels.composite_forward(
            *arrays, tiles.offsets, tiles.lists, tiles.width, tiles.height, tiles.tile
        )
        ctx.arrays = arrays
        ctx.tiles = tiles
        ctx.trans = trans
        ctx.last = last
        ctx.device = means2d.device
        return torch.from_numpy(feat).to(means2d.device), torch.from_numpy(trans).to(means2d.device)

    @staticmethod
    @once_differentiable
    def backward(ctx, v_feat: torch.Tensor, v_trans: torch.Tensor):  # noqa: ANN001, ANN205
        tiles: Tiles = ctx.tiles
        means2d = ctx.arrays[0]
        n, n_ch = ctx.arrays[3].shape
        dtype = means2d.dtype
        h, w = tiles.height, tiles.width
        v_feat_np = _np(v_feat).astype(dtype, copy=False) if v_feat is not None else np.zeros((h, w, n_ch), dtype)
        v_trans_np = _np(v_trans).astype(dtype, copy=False) if v_trans is not None else np.zeros((h, w), dtype)
        rows = _kernels.composite_backward(
            *ctx.arrays
            + (tiles.offsets, tiles.lists, w, h, tiles.tile, ctx.trans, ctx.last)
            + (np.ascontiguousarray(v_feat_np), np.ascontiguousarray(v_trans_np))
        )
        grads = torch.zeros((n, rows.shape[1]), dtype=torch.from_numpy(rows[:0]).dtype)
        grads.index_add_(0, torch.from_numpy(tiles.lists).long(), torch.from_numpy(rows))
        grads = grads.to(ctx.device)
        c = _kernels.GRAD_COLS
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, c:], None, None


def composite(
    means2d: torch.Tensor,  # [M, 2]
    conics: torch.Tensor,  # [M, 3]
    opacities: torch.Tensor,  # [M]
    features: torch.Tensor,  # [M, 4]
    pixel_rect: torch.Tensor,  # [M, 4] int32
    width: int,
    height: int,
    *,
    tiles: Tiles | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite depth-sorted Gaussians front to back; differentiable.

    Args:
        means2d: pixel centres. [M, 2]
        conics: inverse 2D covariances (a, b, c). [M, 3]
        opacities: opacities in (0, 1). [M]
        features: per-Gaussian values to composite (colour and depth; ``_kernels.FEATURES``). [M, 4]
        pixel_rect: inclusive support rectangles, clipped to the image. [M, 4] int32
        width: image width.
        height: image height.
        tiles: precomputed :func:`bin_tiles` result for ``pixel_rect``.

    Returns:
        ``(feat, trans)``: ``Σ_k f_k α_k T_k`` per pixel [H, W, 4] (no background) and the
        final transmittance [H, W].
    """
    if tiles is None:
        tiles = bin_tiles(pixel_rect, width, height)
    if means2d.shape[0] == 0:
        feat = means2d.new_zeros((height, width, features.shape[1])) + 0 * features.sum()
        return feat, means2d.new_ones((height, width)) + 0 * opacities.sum()
    return _Composite.apply(means2d, conics, opacities, features, pixel_rect, tiles)
