"""The development scenes (``--data``, the shared data folder; not in the repository) as the benchmarks use them.

Frames come from the library's loaders (:mod:`macsplat_cli.datasets`): CO3D apple through
:func:`~macsplat_cli.datasets.co3d.load_co3d_json` (frame order: the cameras file's), ICL-NUIM living room and
NYU dining through :func:`~macsplat_cli.datasets.icl.load_rgbd_poses_file_order` (frame ``i`` is
``color/{i + 1}.png``). Each :class:`~macsplat_cli.datasets.Frame` holds the image file and its ground-truth
camera (OpenCV axes, +0.5 pixel centres, at the photo's own size).

Held-out targets and their placement are the same in every benchmark: the frames between the two context views
(:func:`between`), the ground-truth pose in the camera-0 frame with its translation scaled by the estimated-to-true
baseline ratio (the reconstruction has baseline 1), rendered at the working size with the reconstruction's own
intrinsics (:func:`target_intrinsics`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from macsplat_cli.camera_math import rescale_intrinsics
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import Frame
from macsplat_cli.datasets.co3d import load_co3d_json
from macsplat_cli.datasets.icl import load_rgbd_poses_file_order
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.types import View

SCENES = ("co3d", "icl_livingroom", "nyu_dining")
"""The development scenes by the names the benchmarks' tables use."""


def dev_frames(data: Path, scene: str) -> list[Frame]:
    """The frames of one development scene (``SCENES``) under the shared data folder ``data``."""
    if scene == "co3d":
        return load_co3d_json(data / "co3d_apple")[0].frames
    kind = {"icl_livingroom": "icl-nuim", "nyu_dining": "nyu-rgbd"}[scene]
    return load_rgbd_poses_file_order(data / "icl_nuim_and_home_rgbd" / scene, kind)[0].frames  # type: ignore[arg-type]


def photo_size(frame: Frame) -> tuple[int, int]:
    """(width, height) of the frame's photo."""
    return frame.camera.width, frame.camera.height


def c2w(frame: Frame) -> np.ndarray:
    """The frame's ground-truth camera-to-world transform. [4, 4] float64"""
    return frame.camera.cam_to_world


def between(frames: list[Frame], pair: tuple[int, int]) -> list[int]:
    """Held-out targets between the context views: the centre projects inside the context
    chord (5–95 %) within half its length, and the orientation differs from each context
    view by at most the context pair's angle + 15°."""
    a, b = c2w(frames[pair[0]]), c2w(frames[pair[1]])
    ca, cb = a[:3, 3], b[:3, 3]
    chord = cb - ca
    length = float(np.linalg.norm(chord))
    span = rotation_error_deg(a[:3, :3], b[:3, :3])
    out = []
    for i, f in enumerate(frames):
        if i in pair:
            continue
        d = c2w(f)[:3, 3] - ca
        u = float(d @ chord) / length**2
        perp = float(np.linalg.norm(d - u * chord))
        ra = rotation_error_deg(a[:3, :3], c2w(f)[:3, :3])
        rb = rotation_error_deg(b[:3, :3], c2w(f)[:3, :3])
        if 0.05 < u < 0.95 and perp < 0.5 * length and max(ra, rb) <= span + 15.0:
            out.append(i)
    return out


def load_rgb(path: Path, size: tuple[int, int]) -> np.ndarray:
    """A photo as RGB float32 in [0, 1], resized (area) to ``size`` = (W, H). [H, W, 3]"""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"{path}: not a readable image")
    img = bgr[..., ::-1].astype(np.float32) / 255.0
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def save_intrinsics(path: Path, frames: tuple[Frame, Frame]) -> Path:
    """Write the two context frames' true intrinsics as a cameras file (``--intrinsics``); ``path``."""
    save_cameras(path, CameraSet([Camera(f.image.name, *photo_size(f), f.camera.K, np.eye(4)) for f in frames]))
    return path


def target_intrinsics(K0: np.ndarray, view0: View, size: tuple[int, int]) -> np.ndarray:
    """The reconstruction's view-0 intrinsics ``K0`` [3, 3] (at ``view0``'s working size) for an image of
    ``size`` = (W, H)."""
    return rescale_intrinsics(K0, size[0] / view0.width, size[1] / view0.height)
