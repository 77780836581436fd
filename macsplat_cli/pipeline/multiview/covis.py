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

from ...camera_math import intrinsic_rows, pixel_offsets
from ...gaussians import GaussianMaps

__all__ = ["CovisReport", "compile_kernels", "covisibility_init", "covisibility_init_reference"]

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


def _world(m: GaussianMaps) -> torch.Tensor:
    """A one-view map's means in the world frame. [H·W, 3] float64"""
    T = m.cam_to_world_or_identity(torch.float64)[0]
    x = m.means[0].detach().reshape(-1, 3).double()
    return x @ T[:3, :3].T + T[:3, 3]


def _scores(m: GaussianMaps, K: np.ndarray) -> torch.Tensor:
    """Each pixel Gaussian's observation score ``opacity · f / z`` (higher: better observed). [H·W] float64"""
    z = m.means[0, ..., 2].detach().double().reshape(-1).clamp_min(1e-12)
    op = torch.sigmoid(m.opacity_logits[0].detach().double()).reshape(-1)
    return op * float(0.5 * (K[0, 0] + K[1, 1])) / z


@dataclass
class _Seen:
    """What every test needs of one photo, computed once: its world points [H·W, 3], valid pixels [H·W], scores
    [H·W], camera depths [H·W] (float64), world-to-camera rotation [3, 3] and centre [3], K [3, 3] and size."""

    world: torch.Tensor
    valid: torch.Tensor
    score: torch.Tensor
    z: torch.Tensor
    R: torch.Tensor
    c: torch.Tensor
    K: torch.Tensor
    size: tuple[int, int]


def _seen(m: GaussianMaps, K: np.ndarray) -> _Seen:
    T = m.cam_to_world_or_identity(torch.float64)[0]
    z = m.means[0, ..., 2].detach().double().reshape(-1)
    return _Seen(_world(m), m.valid_mask()[0].reshape(-1), _scores(m, K), z, T[:3, :3], T[:3, 3],
                 torch.as_tensor(K, dtype=torch.float64), m.size)  # fmt: skip


def _pixel(u: torch.Tensor, w: int) -> torch.Tensor:
    """The pixel index ``floor(u)`` along an axis of ``w`` pixels where ``0 ≤ u < w``, some index within
    ``[0, w)`` elsewhere (NaN included): a lookup the caller masks. [n] int64"""
    return u.nan_to_num(0.0).clamp(0, w - 1).long()  # non-negative: truncation is the floor


def _beaten(k: int, j: int, seen: list[_Seen], idx: torch.Tensor) -> torch.Tensor:
    """Which of photo ``k``'s pixels ``idx`` [n] photo ``j`` sees on the same surface point (a valid Gaussian within
    :data:`DEPTH_TOL` in depth at the pixel it projects to) with a better score. [n] bool"""
    a, b = seen[k], seen[j]
    Xc = (a.world[idx] - b.c) @ b.R  # into camera j
    z = Xc[:, 2]
    u = b.K[0, 0] * Xc[:, 0] / z + b.K[0, 2]
    v = b.K[1, 1] * Xc[:, 1] / z + b.K[1, 2]
    hj, wj = b.size
    inside = (z > 0) & (u >= 0) & (u < wj) & (v >= 0) & (v < hj)  # NaN and ±inf fail a comparison
    pix = _pixel(v, hj) * wj + _pixel(u, wj)
    same = inside & b.valid[pix] & ((b.z[pix] - z).abs() <= DEPTH_TOL * z.abs())
    sk, sj = a.score[idx], b.score[pix]
    better = sj > sk * (1 + TIE)
    if j < k:
        better |= sj >= sk * (1 - TIE)
    return same & better


def _nearest_first(k: int, seen: list[_Seen]) -> list[int]:
    """The other photos, the nearest camera centre first (the likeliest to see ``k``'s surfaces)."""
    d = [float((s.c - seen[k].c).norm()) for s in seen]
    return sorted((j for j in range(len(seen)) if j != k), key=lambda j: (d[j], j))


def covisibility_init(maps: list[GaussianMaps], Ks: list[np.ndarray]) -> tuple[list[GaussianMaps], CovisReport]:
    """Drop every Gaussian another photo observes better (module docstring).

    A photo's Gaussians are tested against the other photos nearest camera first, and a Gaussian beaten once is not
    tested again: every test is made against the maps as given, so the result does not depend on the photos' order
    except through ties. One pass per Gaussian over the photos (:mod:`._covis_kernels`, on the kernel threads); the
    twin: :func:`covisibility_init_reference`.

    Args:
        maps: each registered photo's pixel Gaussians (``B = 1``, its camera frame, ``cam_to_world`` set).
        Ks: each map's intrinsics at the map's resolution. [3, 3]

    Returns:
        The maps with ``valid`` cleared where a Gaussian was dropped (the other tensors shared), and the counts.
    """
    from ..._threads import parallel_for
    from ._covis_kernels import kept

    seen = [_seen(m, K) for m, K in zip(maps, Ks)]
    flat = [np.ascontiguousarray(torch.cat([getattr(s, name) for s in seen]).numpy())
            for name in ("world", "valid", "score", "z")]  # fmt: skip
    sizes = np.array([s.size for s in seen], dtype=np.int64)
    offsets = pixel_offsets(sizes)
    R = np.ascontiguousarray(torch.stack([s.R for s in seen]).numpy())
    c = np.ascontiguousarray(torch.stack([s.c for s in seen]).numpy())
    intr = intrinsic_rows(s.K.numpy() for s in seen)
    keeps = []
    for k in range(len(maps)):
        idx = seen[k].valid.nonzero().squeeze(1)
        out = np.zeros(len(idx), dtype=np.bool_)
        order = np.array(_nearest_first(k, seen), dtype=np.int64)
        parallel_for(kept, len(idx), idx.numpy(), k, order, *flat, offsets, R, c, intr, sizes, DEPTH_TOL, TIE, out,
                     chunks_per_thread=4)  # fmt: skip
        keeps.append(idx[torch.from_numpy(out)])
    return _with_kept(maps, seen, keeps)


def covisibility_init_reference(
    maps: list[GaussianMaps], Ks: list[np.ndarray]
) -> tuple[list[GaussianMaps], CovisReport]:
    """:func:`covisibility_init` in PyTorch (its twin): photo ``k``'s Gaussians still kept against one photo at a
    time (:func:`_beaten`). Same arguments and result."""
    seen = [_seen(m, K) for m, K in zip(maps, Ks)]
    keeps = []
    for k in range(len(maps)):
        idx = seen[k].valid.nonzero().squeeze(1)  # the pixels still kept
        for j in _nearest_first(k, seen):
            if not len(idx):
                break
            idx = idx[~_beaten(k, j, seen, idx)]
        keeps.append(idx)
    return _with_kept(maps, seen, keeps)


def _with_kept(
    maps: list[GaussianMaps], seen: list[_Seen], keeps: list[torch.Tensor]
) -> tuple[list[GaussianMaps], CovisReport]:
    """The maps valid only at their kept pixels (``keeps``: per map, flat pixel indices [n] int64), and the counts."""
    out = []
    for m, s, idx in zip(maps, seen, keeps):
        keep = torch.zeros_like(s.valid)
        keep[idx] = True
        out.append(GaussianMaps(m.means, m.log_scales, m.quats, m.opacity_logits, m.sh, keep.reshape(1, *m.size),
                                m.cam_to_world))  # fmt: skip
    report = CovisReport([int(s.valid.sum()) for s in seen], [int(o.valid_mask().sum()) for o in out])
    return out, report


def compile_kernels() -> None:
    """Compile (or load from Numba's cache) :func:`covisibility_init`'s kernel now: for a background thread."""
    from ._covis_kernels import compile_kernels as covis_kernels

    covis_kernels()
