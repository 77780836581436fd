"""The CO3D development-sample layout: ``cameras_opencv.json`` with OpenCV ``K`` and ``c2w`` per view.

``{"width", "height", "views": [{"image", "K", "c2w"}]}`` (OpenCV axes, principal point in
the +0.5 convention); no depth, arbitrary scale. ``image`` is a relative path inside the folder
(``images/frame000007.jpg``; no ``..``, not absolute: :func:`.base.member_path`), and no file read
may lead out of the folder through a link (:func:`.base.check_inside`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import CameraFileError, DatasetError
from .base import EvalScene, Frame, check_inside, member_path, read_json, validate_scene

__all__ = ["load_co3d_json"]


def load_co3d_json(root: Path) -> list[EvalScene]:
    """The one scene of a ``cameras_opencv.json`` folder."""
    path = check_inside(root / "cameras_opencv.json", (root,), "the cameras file")
    doc = read_json(path)
    try:
        w, h = int(doc["width"]), int(doc["height"])
        views = list(doc["views"])
        frames = []
        for i, v in enumerate(views):
            img = member_path(root, v["image"], f"{path}: views[{i}].image", subfolders=True)
            try:
                cam = Camera(Path(v["image"]).stem, w, h, np.array(v["K"], float), np.array(v["c2w"], float))
            except CameraFileError as e:
                raise DatasetError(f"{path}: views[{i}]: {e}") from None
            frames.append(Frame(cam.name, img, cam))
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: expected {{width, height, views: [{{image, K, c2w}}]}} ({e!r})") from None
    return [validate_scene(EvalScene(root.resolve().name, frames, "relative"), root, roots=(root,))]
