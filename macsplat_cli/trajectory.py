"""Camera paths: views interpolated between cameras (slerp rotations, lerp centres)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .cameras import Camera
from .errors import InputError
from .rotations import quat_to_rotmat_np, rotmat_to_quat_np

__all__ = ["interpolate_cameras", "slerp"]


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc. [4], [4] → [4]"""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # q and −q are the same rotation: take the short way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: lerp is exact to ~1e-7 and avoids 0/0
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(dot, 1.0))
    s = math.sin(theta)
    return (math.sin((1.0 - u) * theta) * q0 + math.sin(u * theta) * q1) / s


def interpolate_cameras(
    cameras: Sequence[Camera], n: int, *, width: int | None = None, height: int | None = None
) -> list[Camera]:
    """``n`` cameras evenly spaced along the path through ``cameras`` (both ends included).

    Between consecutive cameras, rotations are slerped, centres and intrinsics linearly
    interpolated. Every camera is first rescaled to ``width × height`` (default: the size
    of the first camera), so cameras of different image sizes can be mixed.

    Args:
        cameras: at least two cameras, in path order.
        n: number of views, ≥ 1.
        width: output image width.
        height: output image height.

    Returns:
        ``n`` cameras named ``path_0000``, ``path_0001``, ...
    """
    if len(cameras) < 2:
        raise InputError(f"a camera path needs at least two cameras, got {len(cameras)}")
    if n < 1:
        raise InputError(f"the number of path views must be at least 1, got {n}")
    w = width or cameras[0].width
    h = height or cameras[0].height
    cams = [c.rescaled(w, h) for c in cameras]
    quats = [rotmat_to_quat_np(c.cam_to_world[:3, :3]) for c in cams]
    out = []
    for k in range(n):
        s = 0.0 if n == 1 else k * (len(cams) - 1) / (n - 1)
        i = min(int(math.floor(s)), len(cams) - 2)
        u = s - i
        a, b = cams[i], cams[i + 1]
        c2w = np.eye(4)
        c2w[:3, :3] = quat_to_rotmat_np(slerp(quats[i], quats[i + 1], u))
        c2w[:3, 3] = (1.0 - u) * a.center + u * b.center
        K = (1.0 - u) * a.K + u * b.K
        out.append(Camera(name=f"path_{k:04d}", width=w, height=h, K=K, cam_to_world=c2w))
    return out
