"""The two cameras seen from one of them: the relative pose, and a depth map's pixels carried into the other view.

:func:`carry_depth` is not :func:`~macsplat_cli.camera_math.project_points`: it starts from a depth map (pixel
centres back-projected at their depths, NumPy float64, component by component) rather than from world points, and
it returns flat pixel indices of the other view with the points' depths there, for the checks and the fusion.
"""

from __future__ import annotations

import numpy as np

from ..types import TwoViewGeometry

__all__ = ["carry_depth", "relative_pose"]


def relative_pose(geometry: TwoViewGeometry, ref: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) taking view ``ref``'s camera points to the other view's camera points. ([3, 3], [3])"""
    if ref == 0:
        return geometry.R, geometry.t
    return geometry.R.T, -geometry.R.T @ geometry.t


def carry_depth(
    depth: np.ndarray, K: np.ndarray, K_o: np.ndarray, R: np.ndarray, t: np.ndarray, shape_o: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel with a depth carried into the other view.

    Args:
        depth: this view's depth, 0 where none. [H, W]
        K, K_o: this view's and the other view's intrinsics. [3, 3] each
        R, t: this camera → the other camera (:func:`relative_pose`). [3, 3], [3]
        shape_o: the other view's (height, width).

    Returns:
        ``(q, z, inside, sel)`` [N] each, for the N pixels with a depth: the flat index of the pixel each lands on in
        the other view (0 where not ``inside``), its depth there, whether it lands inside the other image in front
        of it, and its own flat pixel index here.
    """
    h, w = depth.shape
    sel = np.flatnonzero(depth.reshape(-1) > 0)
    ys, xs = np.divmod(sel, w)
    z = depth.reshape(-1)[sel].astype(np.float64)
    # ray directions (z = 1) component by component: (N, 3) @ (3, 3) products are slow in NumPy
    Ki = np.linalg.inv(K)
    u, v = xs + 0.5, ys + 0.5
    rx = Ki[0, 0] * u + Ki[0, 1] * v + Ki[0, 2]
    ry = Ki[1, 0] * u + Ki[1, 1] * v + Ki[1, 2]
    rz = Ki[2, 0] * u + Ki[2, 1] * v + Ki[2, 2]
    M = K_o @ R  # camera k → homogeneous pixels of the other view
    m = K_o @ t
    pu = (M[0, 0] * rx + M[0, 1] * ry + M[0, 2] * rz) * z + m[0]
    pv = (M[1, 0] * rx + M[1, 1] * ry + M[1, 2] * rz) * z + m[1]
    zo = (R[2, 0] * rx + R[2, 1] * ry + R[2, 2] * rz) * z + t[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uo = pu / zo
        vo = pv / zo
    ho, wo = shape_o
    inside = (zo > 0) & (uo >= 0) & (uo < wo) & (vo >= 0) & (vo < ho)
    ui = np.where(inside, uo, 0).astype(np.int64)
    vi = np.where(inside, vo, 0).astype(np.int64)
    return vi * wo + ui, zo, inside, sel
