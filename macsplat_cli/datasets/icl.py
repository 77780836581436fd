"""RGB-D sequences with a ``pose.txt``: ICL-NUIM and NYU Depth v2.

* ICL-NUIM: ``color/<i>.png``, ``depth/<i>.png`` (metres × 5000), ``pose.txt`` (line i:
  ``tx ty tz qx qy qz qw``, camera-to-world) with the ICL-NUIM intrinsics (fx 481.2,
  fy −480, cx 319.5, cy 239.5 at 640×480); the left-handed rig is made right-handed with
  ``F · c2w · F``, ``F = diag(1, −1, 1, 1)``, and ``fy = +480``.
* NYU RGB-D: the same files with ``depth/<i>.pgm`` (16-bit, mm) and the NYU Depth v2 RGB
  calibration (fx 518, fy 519, cx 325.5, cy 253.5; approximate poses).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal

import numpy as np

from ..cameras import Camera, quat_to_rotmat_np
from ..errors import DatasetError
from .base import EvalScene, Frame, check_inside, image_size, validate_scene

__all__ = ["load_rgbd_poses", "load_rgbd_poses_file_order", "pose_file_rotation"]

_ICL_SIZE = (640, 480)
_ICL_K = np.array([[481.2, 0.0, 319.5 + 0.5], [0.0, 480.0, 239.5 + 0.5], [0.0, 0.0, 1.0]])
_NYU_K = np.array([[518.0, 0.0, 325.5 + 0.5], [0.0, 519.0, 253.5 + 0.5], [0.0, 0.0, 1.0]])
_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])


def _quat_xyzw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return quat_to_rotmat_np(np.array([w, x, y, z]))


def load_rgbd_poses(root: Path, kind: Literal["icl-nuim", "nyu-rgbd"]) -> list[EvalScene]:
    """The one (metric) scene of an ICL-NUIM or NYU RGB-D sequence folder."""
    roots = (root,)  # every file read lies inside the data set folder, links resolved
    pose_file = check_inside(root / "pose.txt", roots, "the pose file")
    if not pose_file.is_file():
        raise DatasetError(f"{pose_file}: file not found")
    K, flip, ext, scale = (
        (_ICL_K, True, ".png", 1.0 / 5000.0) if kind == "icl-nuim" else (_NYU_K, False, ".pgm", 1.0 / 1000.0)
    )
    frames = []
    lines = [ln for ln in pose_file.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    for i, line in enumerate(lines, start=1):
        try:
            v = np.array([float(x) for x in line.split()])
        except ValueError:
            raise DatasetError(f"{pose_file}: line {i} is not 7 numbers (tx ty tz qx qy qz qw)") from None
        if v.shape != (7,) or not np.isfinite(v).all() or np.linalg.norm(v[3:]) == 0:
            raise DatasetError(f"{pose_file}: line {i} is not 7 numbers (tx ty tz qx qy qz qw)")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _quat_xyzw(v[3:]), v[:3]
        if flip:
            T = _FLIP_Y @ T @ _FLIP_Y
        img = check_inside(root / "color" / f"{i}.png", roots, f"frame {i}")
        size = image_size(img)
        if size != _ICL_SIZE:
            raise DatasetError(
                f"{img}: {kind} images are {_ICL_SIZE[0]}x{_ICL_SIZE[1]}, this one is {size[0]}x{size[1]}"
            )
        cam = Camera(str(i), size[0], size[1], K, T)
        frames.append(Frame(str(i), img, cam, root / "depth" / f"{i}{ext}", scale))
    return [validate_scene(EvalScene(root.resolve().name, frames, "metric"), root, roots=roots)]


def pose_file_rotation(q: np.ndarray) -> np.ndarray:
    """The rotation of one ``pose.txt`` quaternion, normalised in the file's order. [4] (x, y, z, w) → [3, 3] float64

    The matrix of :func:`load_rgbd_poses` up to the last bit: that one normalises in (w, x, y, z) order, which
    rounds the norm differently for some quaternions (3 of the 10 rotations of the development ICL-NUIM and NYU
    sequences differ by 1–2 × 10⁻¹⁶).
    """
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def load_rgbd_poses_file_order(root: Path, kind: Literal["icl-nuim", "nyu-rgbd"]) -> list[EvalScene]:
    """:func:`load_rgbd_poses` (the same frames, files, intrinsics and checks) with each rotation from
    :func:`pose_file_rotation`: the ground truth the development benchmarks have always placed their targets
    with (``benchmarks/_dev.py``), bit for bit, so that their figures compare across versions.
    """
    scenes = load_rgbd_poses(root, kind)  # validates the pose file and every frame
    lines = [ln for ln in (root / "pose.txt").read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    out = []
    for scene in scenes:
        frames = []
        for frame, line in zip(scene.frames, lines):
            v = np.array([float(x) for x in line.split()])
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = pose_file_rotation(v[3:]), v[:3]
            if kind == "icl-nuim":
                T = _FLIP_Y @ T @ _FLIP_Y
            frames.append(dataclasses.replace(frame, camera=dataclasses.replace(frame.camera, cam_to_world=T)))
        out.append(dataclasses.replace(scene, frames=frames))
    return out
