"""Plain-PyTorch twin of ``_sgm_kernels.py`` (slow; a test oracle on small volumes)."""

from __future__ import annotations

import torch

__all__ = ["aggregate_reference", "winner_reference"]


def _scan_lines(cost: torch.Tensor, gray: torch.Tensor, p1: float, p2: float, gamma: float) -> torch.Tensor:
    """Left-to-right path costs for every row at once. cost [H, W, D], gray [H, W] → [H, W, D]"""
    out = torch.empty_like(cost)
    prev = cost[:, 0]
    out[:, 0] = prev
    inf = torch.full_like(prev[:, :1], float("inf"))
    for x in range(1, cost.shape[1]):
        pen2 = torch.clamp(p2 / (1.0 + gamma * (gray[:, x] - gray[:, x - 1]).abs()), min=p1)[:, None]
        m = prev.min(dim=1, keepdim=True).values
        left = torch.cat([inf, prev[:, :-1]], 1) + p1
        right = torch.cat([prev[:, 1:], inf], 1) + p1
        best = torch.minimum(torch.minimum(prev, torch.minimum(left, right)), m + pen2)
        prev = cost[:, x] + best - m
        out[:, x] = prev
    return out


def _oriented(
    cost: torch.Tensor, gray: torch.Tensor, p1: float, p2: float, gamma: float, flip_x: bool, transpose: bool
):  # noqa: ANN202
    c, g = cost, gray
    if transpose:
        c, g = c.transpose(0, 1), g.transpose(0, 1)
    if flip_x:
        c, g = c.flip(1), g.flip(1)
    out = _scan_lines(c, g, p1, p2, gamma)
    if flip_x:
        out = out.flip(1)
    if transpose:
        out = out.transpose(0, 1)
    return out


def _diagonal(
    cost: torch.Tensor, gray: torch.Tensor, p1: float, p2: float, gamma: float, dy: int, dx: int
) -> torch.Tensor:
    """Path costs along direction (dy, dx) with |dy| = |dx| = 1, pixel by pixel (small inputs only)."""
    h, w, _ = cost.shape
    out = torch.empty_like(cost)
    ys = range(h) if dy > 0 else range(h - 1, -1, -1)
    xs = list(range(w)) if dx > 0 else list(range(w - 1, -1, -1))
    for y in ys:
        for x in xs:
            py, px = y - dy, x - dx
            if not (0 <= py < h and 0 <= px < w):
                out[y, x] = cost[y, x]
                continue
            prev = out[py, px]
            m = prev.min()
            pen2 = max(p2 / (1.0 + gamma * abs(float(gray[y, x] - gray[py, px]))), p1)
            inf = torch.tensor([float("inf")], dtype=cost.dtype)
            left = torch.cat([inf, prev[:-1]]) + p1
            right = torch.cat([prev[1:], inf]) + p1
            best = torch.minimum(torch.minimum(prev, torch.minimum(left, right)), m + pen2)
            out[y, x] = cost[y, x] + best - m
    return out


def aggregate_reference(
    cost: torch.Tensor, gray: torch.Tensor, p1: float, p2: float, gamma: float, eight_paths: bool
) -> torch.Tensor:
    """Same contract as ``_sgm_kernels.aggregate``. [H, W, D], [H, W] → [H, W, D]"""
    total = torch.zeros_like(cost)
    for flip_x in (False, True):
        for transpose in (False, True):
            total += _oriented(cost, gray, p1, p2, gamma, flip_x, transpose)
    if eight_paths:
        for dy, dx in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
            total += _diagonal(cost, gray, p1, p2, gamma, dy, dx)
    return total


def winner_reference(agg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Same contract as ``_sgm_kernels.winner``."""
    d_count = agg.shape[2]
    best, idx = agg.min(dim=2)
    d = torch.arange(d_count)
    far = (d[None, None, :] - idx[..., None]).abs() > 1
    second = torch.where(far, agg, torch.full_like(agg, float("inf"))).min(dim=2).values
    uniq = torch.where(torch.isfinite(second) & (second > 0), (second - best) / second, torch.zeros_like(best))
    off = torch.zeros_like(best)
    inner = (idx > 0) & (idx < d_count - 1)
    i0 = (idx - 1).clamp(0, d_count - 1)
    i2 = (idx + 1).clamp(0, d_count - 1)
    a = agg.gather(2, i0[..., None])[..., 0]
    c = agg.gather(2, i2[..., None])[..., 0]
    den = a - 2 * best + c
    ok = inner & (den > 0)
    o = 0.5 * (a - c) / torch.where(ok, den, torch.ones_like(den))
    off = torch.where(ok, o.clamp(-0.5, 0.5), off)
    return idx.to(torch.int32), off, uniq
