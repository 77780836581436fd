"""``reconstruct --up auto``: the world turned so that the cameras' mean up direction is +y.

The reconstruction's world is the first camera's OpenCV frame, whose up is −y; viewers that orbit about +y show it
upside down. One rotation ``R_up`` (about the origin, no translation or scale) is applied to every output alike: the
Gaussians (means, orientations, view-dependent colour), the cameras and the sparse points.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..camera_formats import SparsePoints
from ..cameras import CameraSet
from ..gaussians import Gaussians
from ..rotations import quat_multiply, rotmat_to_quat
from ..sh import eval_sh

__all__ = ["rotate_cameras", "rotate_gaussians", "rotate_points", "up_rotation"]

_SH_FIT_DIRECTIONS = 256
"""Directions on which the SH rotation of each band is fitted (least squares; exact for band ≤ 3 above 16)."""


def up_rotation(cameras: CameraSet) -> np.ndarray:
    """The smallest rotation taking the cameras' mean up (their −y axes in the world, averaged) to +y. [3, 3]"""
    up = -np.mean([c.cam_to_world[:3, 1] for c in cameras], axis=0)
    a = up / max(np.linalg.norm(up), 1e-12)
    b = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # exactly upside down: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def rotate_cameras(cameras: CameraSet, R: np.ndarray) -> CameraSet:
    """Every camera's pose in the world turned by ``R`` [3, 3] (``c2w' = [R 0; 0 1] · c2w``)."""
    T = np.eye(4)
    T[:3, :3] = R
    return dataclasses.replace(cameras, cameras=[c.with_pose(T @ c.cam_to_world) for c in cameras])


def rotate_points(points: SparsePoints, R: np.ndarray) -> SparsePoints:
    """The sparse points turned by ``R`` [3, 3] (their observations unchanged)."""
    return dataclasses.replace(points, xyz=points.xyz @ R.T)


def _sh_band_matrices(R: torch.Tensor, k: int) -> torch.Tensor:
    """M [K, K] with ``Σ_j Y_j(d) sh_j = Σ_j Y_j(R d) (M sh)_j`` for every direction ``d``: block-diagonal per band,
    each block fitted on fixed directions."""
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(_SH_FIT_DIRECTIONS, 3, generator=g, dtype=torch.float64), dim=1)
    eye = torch.eye(k, dtype=torch.float64)

    def basis(dirs: torch.Tensor) -> torch.Tensor:  # [D, K]: each basis function's value (the DC offset removed)
        sh = eye[:, :, None].expand(k, k, 3).repeat_interleave(len(dirs), 0)
        return (eval_sh(sh, dirs.repeat(k, 1))[:, 0] - 0.5).reshape(k, len(dirs)).T

    Y, Yr = basis(d), basis(d @ R.T)
    M = torch.zeros(k, k, dtype=torch.float64)
    start = 0
    for band in range(int(round(k**0.5))):
        s = slice(start, start + 2 * band + 1)
        M[s, s] = torch.linalg.lstsq(Yr[:, s], Y[:, s]).solution
        start += 2 * band + 1
    return M


def rotate_gaussians(g: Gaussians, R: np.ndarray) -> Gaussians:
    """The Gaussians turned by ``R`` [3, 3]: means and orientations rotated, the SH colours rotated band by band so
    that each Gaussian shows the same colour along the turned direction."""
    Rt = torch.as_tensor(R, dtype=torch.float64)
    q = rotmat_to_quat(Rt[None])[0].to(g.quats.dtype)
    means = (g.means.double() @ Rt.T).to(g.means.dtype)
    quats = quat_multiply(q.expand_as(g.quats), g.quats)
    sh = g.sh
    if sh.shape[1] > 1:
        M = _sh_band_matrices(Rt, sh.shape[1]).to(sh.dtype)
        sh = torch.einsum("ij,njc->nic", M, sh)
    return Gaussians(means, g.log_scales, quats, g.opacity_logits, sh)
