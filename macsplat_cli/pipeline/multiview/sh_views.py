"""Where the photos constrain view-dependent colour: SH degree 1 for the Gaussians that at least
:data:`MIN_VIEWS` photos see from directions at least :data:`MIN_SPREAD_DEG` apart, degree 0 elsewhere (issue 41).

A Gaussian is seen by a photo when it projects inside it and the photo's own Gaussian at that pixel lies within
:data:`DEPTH_TOL` of it in depth (not hidden behind another surface). With fewer photos, or photos from nearly one
direction, a degree-1 colour fits the photos and only adds noise at new views.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ...gaussians import GaussianMaps

__all__ = ["MIN_SPREAD_DEG", "MIN_VIEWS", "view_dependent"]

MIN_VIEWS = 3
"""Photos that must see a Gaussian before its colour may depend on the direction (two fix only a difference)."""
MIN_SPREAD_DEG = 10.0
"""The widest angle between two of its photos' viewing directions, at least (below, one direction's colour)."""
DEPTH_TOL = 0.03
"""Relative depth agreement for "the photo sees it" (the fused depths of a surface agree to ~1 %; pooled maps less)."""


def _sees(X: torch.Tensor, m: GaussianMaps, K: np.ndarray) -> torch.Tensor:
    """Which world points ``X`` [N, 3] map ``m``'s camera sees (inside, in front, not hidden). [N] bool"""
    T = m.cam_to_world_or_identity(torch.float64)[0]
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    z = Xc[:, 2]
    u = K[0, 0] * Xc[:, 0] / z + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / z + K[1, 2]
    h, w = m.size
    inside = (z > 0) & torch.isfinite(u) & torch.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    col = torch.where(inside, u, torch.zeros_like(u)).floor().long().clamp(0, w - 1)
    row = torch.where(inside, v, torch.zeros_like(v)).floor().long().clamp(0, h - 1)
    zm = m.means[0, ..., 2].detach().double()[row, col]
    return inside & ((zm - z).abs() <= DEPTH_TOL * z.abs())


def view_dependent(maps: list[GaussianMaps], Ks: list[np.ndarray]) -> list[torch.Tensor]:
    """Per map, the Gaussians whose colour may depend on the direction (module docstring).

    Args:
        maps: each photo's Gaussians (``B = 1``, its camera frame, ``cam_to_world`` its pose).
        Ks: each map's intrinsics at the map's resolution. [3, 3]

    Returns:
        Per map, [1, H, W] bool.
    """
    centres = [m.cam_to_world_or_identity(torch.float64)[0, :3, 3] for m in maps]
    cos_spread = math.cos(math.radians(MIN_SPREAD_DEG))
    out = []
    for k, m in enumerate(maps):
        T = m.cam_to_world_or_identity(torch.float64)[0]
        X = m.means[0].detach().double().reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        seen = [torch.ones(len(X), dtype=torch.bool) if j == k else _sees(X, mj, Ks[j]) for j, mj in enumerate(maps)]
        dirs = [torch.nn.functional.normalize(X - c, dim=1) for c in centres]
        count = torch.stack(seen).sum(0)
        widest = torch.ones(len(X), dtype=torch.float64)  # the smallest cosine between two photos that see it
        for i in range(len(maps)):
            for j in range(i + 1, len(maps)):
                both = seen[i] & seen[j]
                widest = torch.where(both, torch.minimum(widest, (dirs[i] * dirs[j]).sum(1)), widest)
        out.append(((count >= MIN_VIEWS) & (widest <= cos_spread)).reshape(1, *m.size))
    return out
