"""The compaction's budget step: at most ``budget`` Gaussians, the most important ones."""

from __future__ import annotations

import math

import torch

from ...gaussians import Gaussians
from .state import ViewState

__all__ = ["importance", "keep_most_important"]


def importance(g: Gaussians, cams: list[ViewState]) -> torch.Tensor:
    """Opacity × the largest projected area over the views (px²). [N]"""
    s = torch.sort(g.log_scales.double(), dim=-1, descending=True).values
    area = math.pi * torch.exp(s[:, 0] + s[:, 1])
    best = torch.zeros(len(g), dtype=torch.float64)
    for c in cams:
        _, _, z, inside = c.project(g.means.double())
        px = torch.where(inside, area * (c.focal / z.clamp_min(1e-12)) ** 2, torch.zeros_like(area))
        best = torch.maximum(best, px)
    return torch.sigmoid(g.opacity_logits.double()) * best


def keep_most_important(g: Gaussians, cams: list[ViewState], budget: int) -> Gaussians:
    """The ``budget`` most important Gaussians of ``g`` (:func:`importance`), in their order in ``g``."""
    keep = torch.topk(importance(g, cams), budget).indices.sort().values
    return g[keep]
