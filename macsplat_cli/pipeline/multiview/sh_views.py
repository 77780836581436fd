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

from ...camera_math import intrinsic_rows, pixel_offsets
from ...gaussians import GaussianMaps

__all__ = ["MIN_SPREAD_DEG", "MIN_VIEWS", "compile_kernels", "view_dependent", "view_dependent_reference"]

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


def _widest_within(dirs: torch.Tensor, seen: torch.Tensor, cos_spread: float) -> torch.Tensor:
    """Whether two of the photos that see a point look at it from directions at least the spread apart.

    A point's farthest direction from its first seeing photo's, ``a``, bounds the widest pair: at least ``a``, at
    most ``2a``. So ``a`` decides most points (wide if ``a`` reaches the spread, narrow if ``2a`` stays below it,
    with a margin for the rounding), and only the rest go through every pair as before.

    Args:
        dirs: each photo's unit direction to each point. [N, n, 3] float64
        seen: which photos see each point. [N, n] bool
    Returns:
        [n] bool
    """
    n = seen.shape[1]
    first = seen.to(torch.uint8).argmax(0)
    ref = dirs[first, torch.arange(n)]  # [n, 3]
    cos_ref = torch.where(seen, (dirs * ref).sum(-1), torch.ones((), dtype=dirs.dtype)).min(0).values
    wide = cos_ref <= cos_spread
    half = math.cos(0.5 * math.acos(cos_spread))
    open_ = (~wide & (cos_ref <= half + 1e-9)).nonzero().squeeze(1)  # 2a may reach the spread: every pair
    if len(open_):
        d, s = dirs[:, open_], seen[:, open_]
        widest = torch.ones(len(open_), dtype=dirs.dtype)
        for i in range(len(d)):
            for j in range(i + 1, len(d)):
                both = s[i] & s[j]
                widest = torch.where(both, torch.minimum(widest, (d[i] * d[j]).sum(1)), widest)
        wide[open_] = widest <= cos_spread
    return wide


def view_dependent(maps: list[GaussianMaps], Ks: list[np.ndarray]) -> list[torch.Tensor]:
    """Per map, the Gaussians whose colour may depend on the direction (module docstring): only a map's valid
    Gaussians are tested (the rest are never rendered), each against every photo in one pass
    (:mod:`._sh_views_kernels`, on the kernel threads; the twin: :func:`view_dependent_reference`).

    Args:
        maps: each photo's Gaussians (``B = 1``, its camera frame, ``cam_to_world`` its pose).
        Ks: each map's intrinsics at the map's resolution. [3, 3]

    Returns:
        Per map, [1, H, W] bool (False at invalid pixels).
    """
    from ..._threads import parallel_for
    from ._sh_views_kernels import view_spread

    poses = np.stack([m.cam_to_world_or_identity(torch.float64)[0].numpy() for m in maps])
    R, t = np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(poses[:, :3, 3])
    intr = intrinsic_rows(Ks)
    sizes = np.array([m.size for m in maps], dtype=np.int64)
    offsets = pixel_offsets(sizes)
    depths = np.concatenate([m.means[0, ..., 2].detach().double().reshape(-1).numpy() for m in maps])
    cos_spread = math.cos(math.radians(MIN_SPREAD_DEG))
    half = math.cos(0.5 * math.acos(cos_spread))
    out = []
    for k, m in enumerate(maps):
        idx = m.valid_mask()[0].reshape(-1).nonzero().squeeze(1)
        T = torch.from_numpy(poses[k])
        X = np.ascontiguousarray((m.means[0].detach().double().reshape(-1, 3)[idx] @ T[:3, :3].T + T[:3, 3]).numpy())
        wide = np.zeros(len(X), dtype=np.bool_)
        parallel_for(view_spread, len(X), X, k, R, t, intr, sizes, offsets, depths, t, MIN_VIEWS, DEPTH_TOL,
                     cos_spread, half, wide, chunks_per_thread=4)  # fmt: skip
        allowed = torch.zeros(m.size[0] * m.size[1], dtype=torch.bool)
        allowed[idx] = torch.from_numpy(wide)
        out.append(allowed.reshape(1, *m.size))
    return out


def view_dependent_reference(maps: list[GaussianMaps], Ks: list[np.ndarray]) -> list[torch.Tensor]:
    """:func:`view_dependent` in PyTorch (its twin): photos × Gaussians masks, and only the Gaussians
    :data:`MIN_VIEWS` photos see tested for the spread (:func:`_widest_within`). Same arguments and result."""
    centres = [m.cam_to_world_or_identity(torch.float64)[0, :3, 3] for m in maps]
    cos_spread = math.cos(math.radians(MIN_SPREAD_DEG))
    out = []
    for k, m in enumerate(maps):
        T = m.cam_to_world_or_identity(torch.float64)[0]
        idx = m.valid_mask()[0].reshape(-1).nonzero().squeeze(1)
        X = m.means[0].detach().double().reshape(-1, 3)[idx] @ T[:3, :3].T + T[:3, 3]
        seen = torch.stack([torch.ones(len(X), dtype=torch.bool) if j == k else _sees(X, mj, Ks[j])
                            for j, mj in enumerate(maps)])  # fmt: skip
        many = (seen.sum(0) >= MIN_VIEWS).nonzero().squeeze(1)
        dirs = torch.stack([torch.nn.functional.normalize(X[many] - c, dim=1) for c in centres])
        allowed = torch.zeros(m.size[0] * m.size[1], dtype=torch.bool)
        allowed[idx[many]] = _widest_within(dirs, seen[:, many], cos_spread)
        out.append(allowed.reshape(1, *m.size))
    return out


def compile_kernels() -> None:
    """Compile (or load from the cache) :func:`view_dependent`'s Numba kernel now: for a background thread."""
    from . import _sh_views_kernels

    _sh_views_kernels.compile_kernels()
