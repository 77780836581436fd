"""What every render backend returns, and the depth normalisation they share.

Kept apart from :mod:`.rasterize` (the dispatcher) so that the backends it dispatches to
(:mod:`._gsplat`) depend on this module only: the imports go one way,
``rasterize → _gsplat → _output``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["RenderOutput", "normalise_depth"]


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        rgb: colour, background included (not clamped to [0, 1]). [H, W, 3]
        depth: expected camera-space depth ``Σ w z / Σ w``; 0 where alpha < 1e-6. [H, W]
        alpha: accumulated opacity ``1 − T_final``. [H, W]
        visible: indices of the Gaussians that were projected (front to back). [M] int64
        means2d: their pixel centres (differentiable; for densification statistics). [M, 2]
        n_intersections: number of (tile, Gaussian) pairs composited.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    visible: torch.Tensor
    means2d: torch.Tensor
    n_intersections: int = 0


def normalise_depth(depth_acc: torch.Tensor, alpha: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """``Σ w z / Σ w`` where the weights sum to more than ``eps``, else 0 (double-where safe). [H, W]"""
    ok = alpha > eps
    safe = torch.where(ok, alpha, torch.ones_like(alpha))
    return torch.where(ok, depth_acc / safe, torch.zeros_like(depth_acc))
