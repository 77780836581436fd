"""A sparse point cloud with its observations: what a COLMAP model's ``points3D`` and nerfstudio's ``sparse_pc.ply``
hold, in the cameras' world frame."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._atomic import atomic_write_bytes
from ..errors import OutputPathError

__all__ = ["SparsePoints", "write_point_ply"]


@dataclass
class SparsePoints:
    """Triangulated points and the camera pixels that see them.

    Attributes:
        xyz: the points, world frame. [P, 3] float64
        rgb: their colours. [P, 3] uint8
        error: each point's mean reprojection error over its observations, in pixels of the cameras. [P] float64
        obs_image: each observation's camera (index into the camera set). [O] int64
        obs_point: its point (index into ``xyz``). [O] int64
        obs_xy: its pixel in that camera's image (pixel centres at +0.5; on the photo as the camera sees it, i.e.
            distorted when the camera has distortion). [O, 2] float64
    """

    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def write_point_ply(path: str | os.PathLike[str], points: SparsePoints) -> Path:
    """The points as a binary little-endian PLY of ``x y z`` (float32) and ``red green blue`` (uchar), the
    layout of nerfstudio's ``sparse_pc.ply``; written atomically.

    Raises:
        OutputPathError: ``path`` cannot be written.
    """
    n = len(points)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    rows = np.zeros(n, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rows["xyz"] = points.xyz
    rows["rgb"] = points.rgb
    try:
        atomic_write_bytes(path, header.encode("ascii") + rows.tobytes())
    except OSError as e:
        raise OutputPathError(f"cannot write {path}: {e.strerror or e}") from e
    return Path(path)
