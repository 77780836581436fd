"""The compaction's pruning steps: what no view can show (non-finite, transparent, isolated, hidden, sub-pixel).

Each step marks pixels of the views' :class:`~.state.ViewState` dead and returns why, for the report.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .config import CompactConfig
from .state import NEIGHBOURS, ViewState

__all__ = ["prune_floaters", "prune_occluded", "prune_opacity", "prune_subpixel"]


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
    """Step 4: Gaussians behind an opaque one (z-buffer of the centres) or off-image, in every view."""
    alive = [v.alive.reshape(-1).nonzero().squeeze(1) for v in views]  # only these can occlude or be kept
    worlds = [v.world_means().reshape(-1, 3)[a] for v, a in zip(views, alive)]
    opaque = [torch.sigmoid(v.logits.reshape(-1)[a]) >= cfg.occluder_min_opacity for v, a in zip(views, alive)]
    seen = [torch.zeros(len(a), dtype=torch.bool) for a in alive]
    for c in views:
        h, w = c.size
        zbuf = torch.full((h * w,), math.inf, dtype=torch.float64)
        projected = []
        for X, occluder in zip(worlds, opaque):
            col, row, z, inside = c.project(X)
            projected.append((row * w + col, z, inside))
            occ = inside & occluder
            zbuf.scatter_reduce_(0, (row * w + col)[occ], z[occ], "amin")
        # a pixel hides what lies behind only if its 3×3 neighbourhood is covered too (the farthest of the
        # nearest depths): a lone occluder centre covers part of its pixel, and leaves no hole behind
        zbuf = F.max_pool2d(zbuf.reshape(1, 1, h, w), 3, stride=1, padding=1).reshape(-1)
        for s, (pix, z, inside) in zip(seen, projected):
            s |= inside & (z <= zbuf[pix] * (1.0 + cfg.occlusion_depth_tol))
    for v, a, s in zip(views, alive, seen):
        v.alive.view(-1)[a[~s]] = False
    return f"hidden in every view (behind a Gaussian of opacity ≥ {cfg.occluder_min_opacity:g}, or off-image)"


def prune_subpixel(views: list[ViewState], cfg: CompactConfig) -> str:
    """Step 5: Gaussians whose largest projected std is below ``subpixel_px`` in every view."""
    for v in views:
        a = v.alive.reshape(-1).nonzero().squeeze(1)
        X = v.world_means().reshape(-1, 3)[a]
        sigma = torch.exp(v.log_scales.double().amax(-1)).reshape(-1)[a]
        best = torch.zeros_like(sigma)
        for c in views:
            _, _, z, inside = c.project(X)
            px = torch.where(inside, sigma * c.focal / z.clamp_min(1e-12), torch.zeros_like(sigma))
            best = torch.maximum(best, px)
        v.alive.view(-1)[a[best < cfg.subpixel_px]] = False
    return f"largest projected std below {cfg.subpixel_px:g} px in every view"
