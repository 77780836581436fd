"""The CO3D development-sample layout: ``cameras_opencv.json`` with OpenCV ``K`` and ``c2w`` per view.

``{"width", "height", "views": [{"image", "K", "c2w"}]}`` (OpenCV axes, principal point in
the +0.5 convention); no depth, arbitrary scale.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import CameraFileError, DatasetError
from .base import EvalScene, Frame, read_json, validate_scene

__all__ = ["load_co3d_json"]


def load_co3d_json(root: Path) -> list[EvalScene]:
    """The one scene of a ``cameras_opencv.json`` folder."""
    path = root / "cameras_opencv.json"
    doc = read_json(path)
    try:
        w, h = int(doc["width"]), int(doc["height"])
        views = list(doc["views"])
        frames = []
        for i, v in enumerate(views):
            img = root / v["image"]
            try:
                cam = Camera(Path(v["image"]).stem, w, h, np.array(v["K"], float), np.array(v["c2w"], float))
            except CameraFileError as e:
                raise DatasetError(f"{path}: views[{i}]: {e}") from None
            frames.append(Frame(cam.name, img, cam))
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: expected {{width, height, views: [{{image, K, c2w}}]}} ({e!r})") from None
    return [validate_scene(EvalScene(root.resolve().name, frames, "relative"), root)]
