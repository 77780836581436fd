"""The compaction's pruning steps: what no view can show (non-finite, transparent, isolated, hidden, sub-pixel).

Each step marks pixels of the views' :class:`~.state.ViewState` dead and returns why, for the report.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .config import CompactConfig
from .cull import view_tiles
from .state import NEIGHBOURS, ViewState

__all__ = ["prune_floaters", "prune_occluded", "prune_occluded_reference", "prune_opacity", "prune_subpixel"]


def prune_opacity(views: list[ViewState]) -> str:
    """Step 1: non-finite Gaussians and opacities below the renderer's ``ALPHA_MIN`` (it culls them)."""
    from ...render.constants import ALPHA_MIN  # here: importing render loads Numba (the settings import this module)

    logit_min = math.log(ALPHA_MIN / (1.0 - ALPHA_MIN))
    for v in views:
        finite = torch.isfinite(v.means).all(-1) & torch.isfinite(v.log_scales).all(-1)
        finite &= torch.isfinite(v.quats).all(-1) & torch.isfinite(v.logits) & torch.isfinite(v.sh).flatten(2).all(-1)
        v.alive &= finite & (v.logits >= logit_min)
    return f"non-finite, or opacity < {ALPHA_MIN:.4f} (culled by the renderer)"


def prune_floaters(views: list[ViewState], cfg: CompactConfig) -> str:
    """Step 2: pixels with fewer than ``floater_min_neighbours`` of 8 neighbours on their surface."""
    for v in views:
        z = torch.where(v.alive, v.means[..., 2], torch.zeros_like(v.logits))
        zp = F.pad(z[None, None], (1, 1, 1, 1))[0, 0]
        h, w = v.size
        count = torch.zeros_like(z)
        for dy, dx in NEIGHBOURS:
            zn = zp[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            count += ((zn > 0) & ((zn - z).abs() <= cfg.floater_depth_tol * z.abs())).to(z.dtype)
        v.alive &= count >= cfg.floater_min_neighbours
    return f"fewer than {cfg.floater_min_neighbours} of 8 neighbours within {cfg.floater_depth_tol:.0%} depth"


def prune_occluded(views: list[ViewState], cfg: CompactConfig) -> str:
    """Step 4: Gaussians behind an opaque one (z-buffer of the centres) or off-image, in every view. Each camera's
    z-buffer takes every opaque centre, then a Gaussian is tested camera by camera, its own first, until one sees
    it (:mod:`._kernels`, on the kernel threads; the twin: :func:`prune_occluded_reference`)."""
    from ..._threads import parallel_for
    from ...camera_math import NEAR_Z, pixel_offsets
    from ._kernels import seen_rows, zbuffers

    alive = [v.alive.reshape(-1).nonzero().squeeze(1) for v in views]  # only these can occlude or be kept
    X = np.ascontiguousarray(torch.cat([v.world_means().reshape(-1, 3)[a] for v, a in zip(views, alive)]).numpy())
    opaque = torch.cat([torch.sigmoid(v.logits.reshape(-1)[a]) >= cfg.occluder_min_opacity
                        for v, a in zip(views, alive)]).numpy()  # fmt: skip
    own = np.repeat(np.arange(len(views), dtype=np.int64), [len(a) for a in alive])
    w2c = np.ascontiguousarray(torch.stack([v.w2c for v in views]).numpy())
    K = np.ascontiguousarray(torch.stack([v.K.double() for v in views]).numpy())
    sizes = np.array([v.size for v in views], dtype=np.int64)
    offsets, pixels = pixel_offsets(sizes), int((sizes[:, 0] * sizes[:, 1]).sum())
    zbuf, pooled = np.empty(pixels), np.empty(pixels)
    parallel_for(zbuffers, len(views), X, opaque, w2c, K, sizes, offsets, NEAR_Z, zbuf, pooled, chunks_per_thread=4)
    seen = np.zeros(len(X), dtype=np.bool_)
    parallel_for(seen_rows, len(X), X, own, w2c, K, sizes, offsets, NEAR_Z, cfg.occlusion_depth_tol, pooled, seen,
                 chunks_per_thread=4)  # fmt: skip
    for v, a, s in zip(views, alive, torch.from_numpy(seen).split([len(a) for a in alive])):
        v.alive.view(-1)[a[~s]] = False
    return _OCCLUDED.format(cfg.occluder_min_opacity)


_OCCLUDED = "hidden in every view (behind a Gaussian of opacity ≥ {:g}, or off-image)"


def prune_occluded_reference(views: list[ViewState], cfg: CompactConfig) -> str:
    """:func:`prune_occluded` in PyTorch (its twin): every view's Gaussians into every camera, twice (the z-buffer,
    then the test); each camera projects only the tiles it can see (:mod:`.cull`). Same arguments and effect."""
    alive = [v.alive.reshape(-1).nonzero().squeeze(1) for v in views]  # only these can occlude or be kept
    worlds = [v.world_means().reshape(-1, 3)[a] for v, a in zip(views, alive)]
    tiles = [view_tiles(a, X, v.size[1]) for v, a, X in zip(views, alive, worlds)]
    opaque = [torch.sigmoid(v.logits.reshape(-1)[a]) >= cfg.occluder_min_opacity for v, a in zip(views, alive)]
    seen = [torch.zeros(len(a), dtype=torch.bool) for a in alive]
    for c in views:
        h, w = c.size
        zbuf = torch.full((h * w,), math.inf, dtype=torch.float64)
        projected = []
        for X, occluder, tl in zip(worlds, opaque, tiles):
            sel = tl.seen_by(c)
            col, row, z, inside = c.project(X[sel])
            projected.append((sel, row * w + col, z, inside))
            occ = inside & occluder[sel]
            zbuf.scatter_reduce_(0, (row * w + col)[occ], z[occ], "amin")
        # a pixel hides what lies behind only if its 3×3 neighbourhood is covered too (the farthest of the
        # nearest depths): a lone occluder centre covers part of its pixel, and leaves no hole behind
        zbuf = F.max_pool2d(zbuf.reshape(1, 1, h, w), 3, stride=1, padding=1).reshape(-1)
        for s, (sel, pix, z, inside) in zip(seen, projected):
            s[sel] |= inside & (z <= zbuf[pix] * (1.0 + cfg.occlusion_depth_tol))
    for v, a, s in zip(views, alive, seen):
        v.alive.view(-1)[a[~s]] = False
    return _OCCLUDED.format(cfg.occluder_min_opacity)


def prune_subpixel(views: list[ViewState], cfg: CompactConfig) -> str:
    """Step 5: Gaussians whose largest projected std is below ``subpixel_px`` in every view. A Gaussian's own view
    is tried first: the other views are tried only on the Gaussians it alone would prune (none, mostly), each on
    the tiles it can see (:mod:`.cull`)."""
    for k, v in enumerate(views):
        a = v.alive.reshape(-1).nonzero().squeeze(1)
        X = v.world_means().reshape(-1, 3)[a]
        sigma = torch.exp(v.log_scales.double().amax(-1)).reshape(-1)[a]
        best = _largest_px(X, sigma, v, torch.zeros_like(sigma))
        low = (best < cfg.subpixel_px).nonzero().squeeze(1)
        if low.numel():
            X, sigma = X[low], sigma[low]
            tl = view_tiles(a[low], X, v.size[1])
            best_low = best[low]
            for c in (c for i, c in enumerate(views) if i != k):
                sel = tl.seen_by(c)
                best_low[sel] = _largest_px(X[sel], sigma[sel], c, best_low[sel])
            best[low] = best_low
        v.alive.view(-1)[a[best < cfg.subpixel_px]] = False
    return f"largest projected std below {cfg.subpixel_px:g} px in every view"


def _largest_px(X: torch.Tensor, sigma: torch.Tensor, c: ViewState, best: torch.Tensor) -> torch.Tensor:
    """``best`` [M] raised to the projected std (px) in ``c`` of the Gaussians at ``X`` [M, 3] with std ``sigma`` [M]
    where ``c`` sees them."""
    _, _, z, inside = c.project(X)
    return torch.maximum(best, torch.where(inside, sigma * c.focal / z.clamp_min(1e-12), torch.zeros_like(z)))
