"""The compaction's dedup step: a surface two views both saw becomes one set of Gaussians."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .config import CompactConfig
from .state import ViewState

__all__ = ["dedup"]

_SAMPLE = 64
"""Every 64th Gaussian tells whether an earlier view sees any of a view's surface (an overlap is thousands)."""


def dedup(views: list[ViewState], cfg: CompactConfig) -> str:
    """Step 3: a later view's Gaussian on a surface an earlier view saw is merged into that view's (in place)."""
    for k in range(1, len(views)):
        vk = views[k]
        for j in range(k):
            vj = views[j]
            idx = vk.alive.reshape(-1).nonzero().squeeze(1)
            if idx.numel() == 0:
                break
            Xw = vk.world_means().reshape(-1, 3)[idx]
            if not vj.project(Xw[::_SAMPLE])[3].any():  # many photos: most pairs see nothing of each other
                continue
            col, row, z, inside = vj.project(Xw)
            hj, wj = vj.size
            zj = vj.means[..., 2].double()[row, col]
            ok = inside & vj.alive[row, col] & ((zj - z).abs() <= cfg.dedup_depth_tol * z.abs())
            # pixel footprints on the surface (world units per pixel): keep what samples the surface finer
            zk = vk.means[..., 2].double().reshape(-1)[idx]
            ok &= zk / vk.focal * cfg.dedup_finer_ratio >= zj / vj.focal
            src, tgt = idx[ok], (row * wj + col)[ok]
            if src.numel() == 0:
                continue
            n = hj * wj
            count = torch.zeros(n, dtype=torch.float64).index_add_(0, tgt, torch.ones_like(tgt, dtype=torch.float64))
            w2c = torch.linalg.inv(vj.c2w)
            Xj = Xw[ok] @ w2c[:3, :3].T + w2c[:3, 3]  # in view j's frame
            sum_means = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, tgt, Xj)
            kk = vk.sh.shape[-2]
            sh_src = vk.sh.reshape(-1, kk, 3)[src].double()
            kj = vj.sh.shape[-2]
            if kk != kj:
                kmax = max(kk, kj)
                sh_src = F.pad(sh_src, (0, 0, 0, kmax - kk))
                if kj < kmax:
                    vj.sh = F.pad(vj.sh, (0, 0, 0, kmax - kj))
                    kj = kmax
            sum_sh = torch.zeros(n, kj, 3, dtype=torch.float64).index_add_(0, tgt, sh_src)
            max_logit = torch.full((n,), -math.inf, dtype=vk.logits.dtype)
            max_logit.scatter_reduce_(0, tgt, vk.logits.reshape(-1)[src], "amax")
            hit = count > 0
            c = count[hit][:, None]
            flat_means = vj.means.reshape(-1, 3)
            flat_means[hit] = (0.5 * flat_means[hit].double() + 0.5 * sum_means[hit] / c).to(flat_means.dtype)
            flat_sh = vj.sh.reshape(-1, kj, 3)
            flat_sh[hit] = (0.5 * flat_sh[hit].double() + 0.5 * sum_sh[hit] / c[..., None]).to(flat_sh.dtype)
            flat_logits = vj.logits.reshape(-1)
            flat_logits[hit] = torch.maximum(flat_logits[hit], max_logit[hit])
            alive = vk.alive.reshape(-1)
            alive[src] = False
    return (
        f"surface seen by an earlier view: reprojects onto a valid pixel within {cfg.dedup_depth_tol:.0%} depth "
        "(merged into it: positions and colours averaged, opacity the larger)"
    )
