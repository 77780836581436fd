"""Both-view fusion: one surface where the two filled depth maps disagree (:func:`fuse_views`)."""

from __future__ import annotations

import cv2
import numpy as np

from ..types import TwoViewGeometry
from .pair import carry_depth, relative_pose

__all__ = ["fuse_views"]


def fuse_views(
    depths: list[np.ndarray],
    confidences: list[np.ndarray],
    measured: list[np.ndarray],
    geometry: TwoViewGeometry,
    tol: float,
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Both-view fusion: one surface where the two depth maps disagree.

    A point of view k that lies nearer to view o than o's surface there (by more than ``tol`` of the depth,
    against the nearest depth of o's 3×3 neighbourhood, so edges do not count) contradicts what o sees: one of
    the two is a wrong, second layer, which a novel view shows as a ghosted copy of the surface. The measured
    one wins: a filled point of k is dropped when o's pixel is measured or filled too; when k's point is
    measured and o's pixel filled, o's pixel takes k's depth (the nearest such) instead.

    Args:
        depths, confidences, measured: per view, depth (0: none), confidence, measured mask. [H, W] each
        geometry: the two cameras.
        tol: relative depth margin.

    Returns:
        ``(depths, confidences, dropped, transferred)``: updated copies, and per view the pixels dropped and the
        pixels whose depth came from the other view. [H, W] each
    """
    depths = [d.astype(np.float32).copy() for d in depths]
    confidences = [c.astype(np.float32).copy() for c in confidences]
    Ks = (geometry.K0, geometry.K1)
    kernel = np.ones((3, 3), np.uint8)
    dropped = [np.zeros(d.shape, bool) for d in depths]
    transferred = [np.zeros(d.shape, bool) for d in depths]
    originals = [d.copy() for d in depths]
    for k in (0, 1):
        o = 1 - k
        R, t = relative_pose(geometry, k)
        d_o = originals[o]
        near_o = cv2.erode(np.where(d_o > 0, d_o, np.float32(np.inf)).astype(np.float32), kernel).reshape(-1)
        q, z, inside, sel = carry_depth(originals[k], Ks[k], Ks[o], R, t, d_o.shape)
        viol = inside & np.isfinite(near_o[q]) & (z < near_o[q] * (1.0 - tol))
        meas_k = measured[k].reshape(-1)[sel]
        meas_o = measured[o].reshape(-1)[q]
        drop = viol & ~meas_k
        fix = viol & meas_k & ~meas_o
        flat_d, flat_c = depths[k].reshape(-1), confidences[k].reshape(-1)
        flat_d[sel[drop]] = 0.0
        flat_c[sel[drop]] = 0.0
        dropped[k].reshape(-1)[sel[drop]] = True
        if fix.any():
            zbuf = np.full(d_o.size, np.inf)
            np.minimum.at(zbuf, q[fix], z[fix])
            got = np.isfinite(zbuf) & (depths[o].reshape(-1) > 0) & ~measured[o].reshape(-1)
            depths[o].reshape(-1)[got] = zbuf[got].astype(np.float32)
            transferred[o].reshape(-1)[got] = True
    return depths, confidences, dropped, transferred
