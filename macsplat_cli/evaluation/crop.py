"""The MAC-Splat release's image preparation for ``--protocol mac-splat``: a square crop centred on the principal
point, rescaled (Lanczos) to ``size × size``; the camera's ``K`` follows exactly, the depth map is cut the same way
(nearest). Written as new files, so that every later step (reconstruction, masks, metrics) sees the cropped frames.

Steps for an image ``W × H`` with principal point ``(cx, cy)`` (continuous pixel coordinates, centres at +0.5):
1. the largest window centred on the principal point: half sides ``min(cx, W − cx)``, ``min(cy, H − cy)``, rounded
   down to whole pixels (so ``cx`` moves by under a pixel from the window's centre and ``K`` says where it is);
2. rescaled so that its shorter side is ``size`` (the longer one rounded);
3. the centre ``size × size`` of that.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..camera_math import principal_point_window
from ..cameras import Camera
from ..datasets import EvalDataset, EvalScene, Frame
from ..errors import DatasetError
from ..images import load_image
from .splits import EvalCase

__all__ = ["crop_camera", "crop_frames", "crop_window"]


def crop_window(camera: Camera) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (x1, y1 exclusive) of step 1, in whole pixels."""
    window = principal_point_window(camera.K, camera.width, camera.height)
    if window is None:
        cx, cy = float(camera.K[0, 2]), float(camera.K[1, 2])
        raise DatasetError(f"camera {camera.name!r}: the principal point ({cx:.1f}, {cy:.1f}) is outside the image")
    return window


def crop_camera(
    camera: Camera, size: int
) -> tuple[Camera, tuple[int, int, int, int], tuple[int, int], tuple[int, int]]:
    """The camera of the cropped image, with the window (step 1), the rescaled size (step 2) and the offset of the
    centre square in it (step 3)."""
    x0, y0, x1, y1 = crop_window(camera)
    w, h = x1 - x0, y1 - y0
    s = size / min(w, h)
    rw, rh = max(size, round(w * s)), max(size, round(h * s))
    ox, oy = (rw - size) // 2, (rh - size) // 2
    K = camera.K.astype(np.float64).copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    K[0] *= rw / w
    K[1] *= rh / h
    K[0, 2] -= ox
    K[1, 2] -= oy
    return dataclasses.replace(camera, width=size, height=size, K=K), (x0, y0, x1, y1), (rw, rh), (ox, oy)


def _crop_frame(frame: Frame, size: int, folder: Path, depth: np.ndarray | None, number: int) -> Frame:
    cam, (x0, y0, x1, y1), (rw, rh), (ox, oy) = crop_camera(frame.camera, size)
    rgb = load_image(frame.image).rgb
    if rgb.shape[:2] != (frame.camera.height, frame.camera.width):
        raise DatasetError(f"{frame.image}: {rgb.shape[1]}x{rgb.shape[0]}, its camera says "
                           f"{frame.camera.width}x{frame.camera.height}")  # fmt: skip
    img = cv2.resize(rgb[y0:y1, x0:x1], (rw, rh), interpolation=cv2.INTER_LANCZOS4)[oy : oy + size, ox : ox + size]
    stem = f"{number:06d}_{frame.image.stem}"
    image_path = folder / f"{stem}.png"
    cv2.imwrite(
        str(image_path), cv2.cvtColor(np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16), cv2.COLOR_RGB2BGR)
    )
    depth_path = None
    if depth is not None:
        d = cv2.resize(depth[y0:y1, x0:x1], (rw, rh), interpolation=cv2.INTER_NEAREST)[oy : oy + size, ox : ox + size]
        depth_path = folder / f"{stem}.depth.npy"
        np.save(depth_path, d.astype(np.float32))
    return Frame(frame.name, image_path, cam, depth_path, 1.0)


def crop_frames(dataset: EvalDataset, cases: Sequence[EvalCase], size: int, folder: Path) -> EvalDataset:
    """``dataset`` with every frame the ``cases`` use (contexts and targets) cropped into ``folder`` (16-bit PNG, depth
    as float32 ``.npy``); the other frames as they were (no case reads them)."""
    folder.mkdir(parents=True, exist_ok=True)
    used: dict[str, set[int]] = {}
    for c in cases:
        used.setdefault(c.scene, set()).update((*c.context, *c.targets))
    scenes, number = [], 0
    for scene in dataset.scenes:
        frames = list(scene.frames)
        for i in sorted(used.get(scene.name, ())):
            frames[i] = _crop_frame(scene.frames[i], size, folder, scene.depth(i), number)
            number += 1
        scenes.append(EvalScene(scene.name, frames, scene.scale))
    return dataclasses.replace(dataset, scenes=scenes)
