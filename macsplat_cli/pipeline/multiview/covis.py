"""Co-visibility initialisation: one set of Gaussians for the scene before any optimisation (issue 41).

Each registered photo's pixel Gaussians come from its own depth, so where several photos see one surface each has
its copy, and copies a little apart in depth or colour blur or ghost the render. Here, before the refinement, a
Gaussian is dropped when another photo sees the same surface point (the photo's own Gaussian at the pixel it
projects to lies within :data:`DEPTH_TOL` of it in depth) and observes it better: a higher score
``opacity / footprint`` (the opacity carries the depth's confidence; the footprint, the world size of a pixel
``z / f``, is smaller where the photo is nearer), ties to the earlier photo. The compaction's dedup
(:mod:`..compact.dedup`) did this after the refinement, keeping the earlier photo's copy whatever its quality.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ...gaussians import GaussianMaps

__all__ = ["CovisReport", "covisibility_init"]

DEPTH_TOL = 0.02
"""Relative depth difference within which two photos' Gaussians are one surface point (the compaction's dedup
tolerance: the fused depths of one surface agree to about 1 % on the development scenes)."""
TIE = 1e-3
"""Scores within this relative difference are a tie (the earlier photo keeps its Gaussian): two photos at one
distance from a surface must not each drop the other's copy."""


@dataclass
class CovisReport:
    """What the initialisation kept: per map, the Gaussians before and after."""

    before: list[int]
    after: list[int]

    def to_dict(self) -> dict[str, object]:
        return {"before": self.before, "after": self.after, "dropped": int(sum(self.before) - sum(self.after))}


def _world(m: GaussianMaps) -> tuple[torch.Tensor, torch.Tensor]:
    """A one-view map's means in the world frame [H·W, 3] float64 and their camera depth [H·W]."""
    T = m.cam_to_world_or_identity(torch.float64)[0]
    x = m.means[0].detach().reshape(-1, 3).double()
    return x @ T[:3, :3].T + T[:3, 3], x[:, 2]


def _scores(m: GaussianMaps, K: np.ndarray) -> torch.Tensor:
    """Each pixel Gaussian's observation score ``opacity · f / z`` (higher: better observed). [H·W] float64"""
    z = m.means[0, ..., 2].detach().double().reshape(-1).clamp_min(1e-12)
    op = torch.sigmoid(m.opacity_logits[0].detach().double()).reshape(-1)
    return op * float(0.5 * (K[0, 0] + K[1, 1])) / z


def _beaten(
    k: int, j: int, maps: list[GaussianMaps], Ks: list[np.ndarray], valid: list[torch.Tensor],
    scores: list[torch.Tensor],
) -> torch.Tensor:  # fmt: skip
    """Map ``k``'s pixels whose surface point map ``j`` sees (a valid Gaussian within :data:`DEPTH_TOL`) with a
    better score. [H·W] bool"""
    Xw, _ = _world(maps[k])
    Tj = maps[j].cam_to_world_or_identity(torch.float64)[0]
    Xc = (Xw - Tj[:3, 3]) @ Tj[:3, :3]  # into camera j
    z = Xc[:, 2]
    Kj = torch.as_tensor(Ks[j], dtype=torch.float64)
    u = Kj[0, 0] * Xc[:, 0] / z + Kj[0, 2]
    v = Kj[1, 1] * Xc[:, 1] / z + Kj[1, 2]
    hj, wj = maps[j].size
    inside = (z > 0) & torch.isfinite(u) & torch.isfinite(v) & (u >= 0) & (u < wj) & (v >= 0) & (v < hj)
    col = torch.where(inside, u, torch.zeros_like(u)).floor().long().clamp(0, wj - 1)
    row = torch.where(inside, v, torch.zeros_like(v)).floor().long().clamp(0, hj - 1)
    pix = row * wj + col
    zj = maps[j].means[0, ..., 2].detach().double().reshape(-1)[pix]
    same = inside & valid[j][pix] & valid[k] & ((zj - z).abs() <= DEPTH_TOL * z.abs())
    sk, sj = scores[k], scores[j][pix]
    better = sj > sk * (1 + TIE)
    if j < k:
        better |= sj >= sk * (1 - TIE)
    return same & better


def covisibility_init(maps: list[GaussianMaps], Ks: list[np.ndarray]) -> tuple[list[GaussianMaps], CovisReport]:
    """Drop every Gaussian another photo observes better (module docstring).

    Args:
        maps: each registered photo's pixel Gaussians (``B = 1``, its camera frame, ``cam_to_world`` set).
        Ks: each map's intrinsics at the map's resolution. [3, 3]

    Returns:
        The maps with ``valid`` cleared where a Gaussian was dropped (the other tensors shared), and the counts.
        Every test is made against the maps as given, so the result does not depend on the photos' order
        except through ties.
    """
    valid = [m.valid_mask()[0].reshape(-1) for m in maps]
    scores = [_scores(m, K) for m, K in zip(maps, Ks)]
    out = []
    for k, m in enumerate(maps):
        drop = torch.zeros_like(valid[k])
        for j in range(len(maps)):
            if j != k:
                drop |= _beaten(k, j, maps, Ks, valid, scores)
        keep = (valid[k] & ~drop).reshape(1, *m.size)
        out.append(GaussianMaps(m.means, m.log_scales, m.quats, m.opacity_logits, m.sh, keep, m.cam_to_world))
    report = CovisReport([int(v.sum()) for v in valid], [int(o.valid_mask().sum()) for o in out])
    return out, report
