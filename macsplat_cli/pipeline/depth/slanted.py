"""Slanted PatchMatch: planes with a slope for the pixels whose SGM winner is not confirmed.

The fronto-parallel sweep matches windows that, on a surface slanted to the cameras, are foreshortened differently
in the two views. For the pixels whose winner fails the winner tests or the left-right check
(:mod:`.checks`), a plane (inverse depth and its slope) is refined by red-black PatchMatch from the confirmed
neighbours' planes and random perturbations, with a ZNCC window warped through the plane's own homography (Numba
kernels in :mod:`._patchmatch_kernels`, plain-NumPy twin in :mod:`._patchmatch_reference`). The left-right check
then runs again on the refined depths (``DepthConfig.slanted_iters``; measured: benchmarks/history/depth.md).
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from ..types import TwoViewGeometry
from .checks import CONSISTENCY, left_right_error, winner_depth
from .config import DepthConfig
from .pair import relative_pose
from .sweep import VolumeDepth

__all__ = ["inverse_depth_slopes", "refine_slanted"]

logger = logging.getLogger(__name__)

SLANTED_RADIUS = 2
"""The refinement's ZNCC window has ``(2·SLANTED_RADIUS + 1)²`` samples ..."""
SLANTED_STEP = 2
"""... spaced this many volume pixels (radius 2, step 2: 25 samples over a 9 × 9 window)."""
SLANTED_SLOPE_MAX = 3.0
"""Largest normalised slope ``|∂ρ/∂u|·f/ρ`` (≈ tan of the tilt from fronto-parallel)."""
SLANTED_SEED = 0
"""Seed of the refinement's random perturbations (the result does not depend on the threads)."""


def inverse_depth_slopes(inv_depth: np.ndarray, valid: np.ndarray, radius: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel gradient of the inverse depth (per pixel), central differences averaged over a
    ``(2·radius + 1)²`` box of valid pixels; 0 where none. ``([h, w], [h, w])`` float64"""
    inv = np.where(valid, inv_depth, 0.0).astype(np.float32)
    wgt = valid.astype(np.float32)
    gx = np.zeros_like(inv)
    gy = np.zeros_like(inv)
    okx = np.zeros_like(wgt)
    oky = np.zeros_like(wgt)
    okx[:, 1:-1] = wgt[:, 2:] * wgt[:, :-2]
    oky[1:-1] = wgt[2:] * wgt[:-2]
    gx[:, 1:-1] = 0.5 * (inv[:, 2:] - inv[:, :-2]) * okx[:, 1:-1]
    gy[1:-1] = 0.5 * (inv[2:] - inv[:-2]) * oky[1:-1]
    k = (2 * radius + 1, 2 * radius + 1)
    sx, nx = cv2.blur(gx, k), cv2.blur(okx, k)
    sy, ny = cv2.blur(gy, k), cv2.blur(oky, k)
    gu = np.where(nx > 0.2, sx / np.maximum(nx, 1e-6), 0.0)
    gv = np.where(ny > 0.2, sy / np.maximum(ny, 1e-6), 0.0)
    return gu.astype(np.float64), gv.astype(np.float64)


def refine_slanted(raw: list[VolumeDepth], geometry: TwoViewGeometry, cfg: DepthConfig) -> None:
    """PatchMatch refinement of slanted planes (:mod:`._patchmatch_kernels`) for the pixels the SGM winner
    leaves unconfirmed (fails the tests or the left-right check), seeded by the confirmed ones; in place: sets
    ``inv_depth``, ``win_cost`` and ``refined`` of both views' :class:`~.sweep.VolumeDepth`."""
    from . import _patchmatch_kernels  # Numba on first use (engine: the kernels load beside the first stages)

    confident = [winner_depth(r) for r in raw]
    for ref in (0, 1):
        r = raw[ref]
        R, t = relative_pose(geometry, ref)
        err = left_right_error(confident[ref], confident[1 - ref], r.K, raw[1 - ref].K, R, t)
        seed = err < CONSISTENCY
        active = r.has_window & ~seed
        rho = np.clip(r.inv_depth, r.rho[0], r.rho[1]).astype(np.float64)
        gu, gv = inverse_depth_slopes(rho, seed | active)
        A = r.K_src @ R @ np.linalg.inv(r.K)
        b = r.K_src @ t
        ref_g = r.gray.astype(np.float64)
        src_g = r.gray_src.astype(np.float64)
        rad, step = SLANTED_RADIUS, SLANTED_STEP
        cost = _patchmatch_kernels.initial_costs(ref_g, src_g, A, b, rho, gu, gv, rad, step)
        f = 0.5 * (r.K[0, 0] + r.K[1, 1])
        rho0 = rho.copy()
        evaluated = _patchmatch_kernels.refine(
            ref_g, src_g, A, b, rho, gu, gv, cost, active, r.rho[0], r.rho[1], f, SLANTED_SLOPE_MAX,
            rad, step, cfg.slanted_iters, SLANTED_SEED,
        )  # fmt: skip
        changed = active & (rho != rho0)
        r.inv_depth = np.where(changed, rho, r.inv_depth)
        r.win_cost = np.where(changed, np.minimum(cost, 0.5), r.win_cost).astype(np.float32)
        r.refined = changed
        logger.debug("slanted refinement view %d: %d active, %d changed, %d window costs", ref, int(active.sum()),
                     int(changed.sum()), evaluated)  # fmt: skip
