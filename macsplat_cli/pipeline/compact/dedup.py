"""The compaction's dedup step: a surface two views both saw becomes one set of Gaussians."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .config import CompactConfig
from .cull import view_tiles
from .state import ViewState

__all__ = ["dedup"]

_SAMPLE = 64
"""Every 64th Gaussian tells whether an earlier view sees any of a view's surface (an overlap is thousands)."""


def dedup(views: list[ViewState], cfg: CompactConfig) -> str:
    """Step 3: a later view's Gaussian on a surface an earlier view saw is merged into that view's (in place).

    A view's centres are moved to the world frame once, the earlier views are tried the most overlapping first
    (:func:`_most_overlapping_first`), and each tests only the tiles of them its frustum meets (:mod:`.cull`); the
    merge sums only over the pixels it hits.
    """
    for k in range(1, len(views)):
        vk = views[k]
        world = vk.world_means().reshape(-1, 3)  # vk is only merged into (changed) after its own turn
        start = vk.alive.reshape(-1).nonzero().squeeze(1)
        tiles = view_tiles(start, world[start], vk.size[1])
        for j in _most_overlapping_first(vk, views[:k], start[::_SAMPLE], world[start[::_SAMPLE]], cfg):
            vj = views[j]
            alive = vk.alive.reshape(-1)
            idx = alive.nonzero().squeeze(1)
            if idx.numel() == 0:
                break
            if not vj.project(world[idx[::_SAMPLE]])[3].any():  # many photos: most pairs see nothing of each other
                continue
            sel = tiles.seen_by(vj)
            if not isinstance(sel, slice):
                near = start[sel]
                idx = near[alive[near]].sort().values  # the alive pixels vj may see, in pixel order (the sums')
            _merge(vk, vj, idx, world[idx], cfg)
    return (
        f"surface seen by an earlier view: reprojects onto a valid pixel within {cfg.dedup_depth_tol:.0%} depth "
        "(merged into it: positions and colours averaged, opacity the larger)"
    )


def _most_overlapping_first(
    vk: ViewState, earlier: list[ViewState], idx: torch.Tensor, Xw: torch.Tensor, cfg: CompactConfig
) -> list[int]:
    """The earlier views that see any of view k's sampled Gaussians ``idx`` [S] (world centres ``Xw`` [S, 3]), those
    that would take most of them (:func:`_mergeable`) first (ties: the earlier view first).

    A Gaussian merges into the first view tried that takes it: with the likeliest first, most of a view's Gaussians
    die on its first merges and the other views project only the rest (in photo order, at 32 photos of an orbit
    where every view sees every other, the first views tried were the farthest)."""
    tests = [_mergeable(vk, vj, idx, Xw, cfg) for vj in earlier]
    seen = [j for j, t in enumerate(tests) if t[3].any()]  # many photos: most pairs see nothing of each other
    return sorted(seen, key=lambda j: -int(tests[j][0].sum()))


def _mergeable(
    vk: ViewState, vj: ViewState, idx: torch.Tensor, Xw: torch.Tensor, cfg: CompactConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which of view k's pixels ``idx`` [M] (world centres ``Xw`` [M, 3]) land on an alive pixel of view j within
    the depth tolerance, where j samples the surface no coarser [M] bool; the pixel of j each lands on (column, row)
    [M] each; and which land inside j's image [M] bool. One pass per centre (:mod:`._kernels`, on the kernel
    threads); the twin: :func:`_mergeable_reference`."""
    from ..._threads import parallel_for
    from ...camera_math import NEAR_Z
    from ._kernels import mergeable

    m = len(idx)
    ok, pix, inside = np.empty(m, np.bool_), np.empty(m, np.int64), np.empty(m, np.bool_)
    h, w = vj.size
    cam = np.ascontiguousarray(vj.w2c[None].numpy()), vj.K[None].numpy()  # inv() gives a column-major w2c
    zk, zj = vk.means[..., 2].reshape(-1)[idx].numpy(), vj.means[..., 2].reshape(-1).contiguous().numpy()
    parallel_for(mergeable, m, np.ascontiguousarray(Xw.numpy()), zk, *cam, h, w, zj, vj.alive.reshape(-1).numpy(),
                 NEAR_Z, cfg.dedup_depth_tol, vk.focal, vj.focal, cfg.dedup_finer_ratio, ok, pix, inside,
                 chunks_per_thread=2)  # fmt: skip
    p = torch.from_numpy(pix)
    return torch.from_numpy(ok), p % w, p // w, torch.from_numpy(inside)


def _mergeable_reference(
    vk: ViewState, vj: ViewState, idx: torch.Tensor, Xw: torch.Tensor, cfg: CompactConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_mergeable` in PyTorch (its twin). Same arguments and results."""
    col, row, z, inside = vj.project(Xw)
    zj = vj.means[..., 2].double()[row, col]
    ok = inside & vj.alive[row, col] & ((zj - z).abs() <= cfg.dedup_depth_tol * z.abs())
    # pixel footprints on the surface (world units per pixel): keep what samples the surface finer
    zk = vk.means[..., 2].double().reshape(-1)[idx]
    ok &= zk / vk.focal * cfg.dedup_finer_ratio >= zj / vj.focal
    return ok, col, row, inside


def _merge(vk: ViewState, vj: ViewState, idx: torch.Tensor, Xw: torch.Tensor, cfg: CompactConfig) -> None:
    """View ``k``'s alive pixels ``idx`` [M] (world centres ``Xw`` [M, 3]) that land on a consistent pixel of the
    earlier view ``j`` are merged into it and die."""
    ok, col, row, _ = _mergeable(vk, vj, idx, Xw, cfg)
    wj = vj.size[1]
    src, tgt = idx[ok], (row * wj + col)[ok]
    if src.numel() == 0:
        return
    hit, slot = torch.unique(tgt, sorted=True, return_inverse=True)  # the pixels of j hit, each source's among them
    n = len(hit)
    count = torch.zeros(n, dtype=torch.float64).index_add_(0, slot, torch.ones_like(slot, dtype=torch.float64))
    w2c = torch.linalg.inv(vj.c2w)
    Xj = Xw[ok] @ w2c[:3, :3].T + w2c[:3, 3]  # in view j's frame
    sum_means = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, slot, Xj)
    kk = vk.sh.shape[-2]
    sh_src = vk.sh.reshape(-1, kk, 3)[src].double()
    kj = vj.sh.shape[-2]
    if kk != kj:
        kmax = max(kk, kj)
        sh_src = F.pad(sh_src, (0, 0, 0, kmax - kk))
        if kj < kmax:
            vj.sh = F.pad(vj.sh, (0, 0, 0, kmax - kj))
            kj = kmax
    sum_sh = torch.zeros(n, kj, 3, dtype=torch.float64).index_add_(0, slot, sh_src)
    max_logit = torch.full((n,), -math.inf, dtype=vk.logits.dtype)
    max_logit.scatter_reduce_(0, slot, vk.logits.reshape(-1)[src], "amax")
    c = count[:, None]
    flat_means = vj.means.reshape(-1, 3)
    flat_means[hit] = (0.5 * flat_means[hit].double() + 0.5 * sum_means / c).to(flat_means.dtype)
    flat_sh = vj.sh.reshape(-1, kj, 3)
    flat_sh[hit] = (0.5 * flat_sh[hit].double() + 0.5 * sum_sh / c[..., None]).to(flat_sh.dtype)
    flat_logits = vj.logits.reshape(-1)
    flat_logits[hit] = torch.maximum(flat_logits[hit], max_logit)
    vk.alive.reshape(-1)[src] = False
