"""ScanNet++ DSLR data (undistorted), in the official release tree or Splatt3R's ``raw``/``processed`` tree.

Trees: ``<root>/splits/<split>.txt`` + ``<root>/data/<scene>/dslr/``, or ``<root>/raw`` +
``<root>/processed``. Per scene: ``nerfstudio/transforms_undistorted.json`` (intrinsics and
poses), ``undistorted_images/`` or ``resized_undistorted_images/``, optionally
``undistorted_depths/<stem>.png`` (uint16 mm, 0 = invalid). Frames: the ``train`` list of
``train_test_lists.json`` (else every frame of the transforms file), without the frames
marked ``is_bad``. Poses: nerfstudio ``transform_matrix`` converted to OpenCV
camera-to-world in the mesh frame (:func:`nerfstudio_to_opencv`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import CameraFileError, DatasetError
from .base import EvalScene, Frame, read_json, validate_scene

__all__ = ["load_scannetpp", "nerfstudio_to_opencv", "opencv_to_nerfstudio"]

logger = logging.getLogger(__name__)


def nerfstudio_to_opencv(transform_matrix: np.ndarray) -> np.ndarray:
    """ScanNet++ nerfstudio ``transform_matrix`` → OpenCV camera-to-world in the mesh frame. [4, 4]

    The inverse of the toolkit's conversion (camera y, z flipped; world rows permuted and
    z negated): ``c2w[2] *= −1; c2w = c2w[[1, 0, 2, 3]]; c2w[:3, 1:3] *= −1``.
    """
    c2w = np.array(transform_matrix, dtype=np.float64)
    c2w[2, :] *= -1
    c2w = c2w[[1, 0, 2, 3], :]
    c2w[0:3, 1:3] *= -1
    return c2w


def opencv_to_nerfstudio(cam_to_world: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (mesh frame) → ScanNet++ nerfstudio ``transform_matrix``. [4, 4]"""
    T = np.array(cam_to_world, dtype=np.float64)
    T[0:3, 1:3] *= -1
    T = T[[1, 0, 2, 3], :]
    T[2, :] *= -1
    return T


def _scannetpp_scene(data_root: Path, raw_root: Path, scene_id: str) -> EvalScene:
    dslr = data_root / scene_id / "dslr"
    raw_dslr = raw_root / "data" / scene_id / "dslr"
    if not raw_dslr.is_dir():
        raw_dslr = dslr
    tu_path = dslr / "nerfstudio" / "transforms_undistorted.json"
    tu = read_json(tu_path)
    img_dir = next(
        (dslr / d for d in ("undistorted_images", "resized_undistorted_images") if (dslr / d).is_dir()), None
    )
    if img_dir is None:
        raise DatasetError(f"{dslr}: no undistorted_images/ or resized_undistorted_images/ folder")
    depth_dir = dslr / "undistorted_depths"
    try:
        w, h = int(tu["w"]), int(tu["h"])
        K = np.array([[float(tu["fl_x"]), 0.0, float(tu["cx"])], [0.0, float(tu["fl_y"]), float(tu["cy"])], [0, 0, 1]])
        poses = {Path(f["file_path"]).name: f for f in list(tu["frames"]) + list(tu.get("test_frames", []))}
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{tu_path}: expected w, h, fl_x, fl_y, cx, cy and frames ({e!r})") from None
    bad = {name for name, f in poses.items() if f.get("is_bad")}
    ts_path = raw_dslr / "nerfstudio" / "transforms.json"
    if ts_path.is_file() and ts_path != tu_path:
        for f in read_json(ts_path).get("frames", []):
            if f.get("is_bad"):
                bad.add(Path(f["file_path"]).name)
    lists_path = raw_dslr / "train_test_lists.json"
    if lists_path.is_file():
        names = [Path(n).name for n in read_json(lists_path).get("train", [])]
    else:
        names = [Path(f["file_path"]).name for f in tu["frames"]]
    frames = []
    for name in names:
        if name in bad:
            continue
        if name not in poses:
            raise DatasetError(f"{tu_path}: no pose for frame {name} of the train list")
        try:
            cam = Camera(name, w, h, K, nerfstudio_to_opencv(np.array(poses[name]["transform_matrix"], float)))
        except (CameraFileError, KeyError, ValueError) as e:
            raise DatasetError(f"{tu_path}: frame {name}: {e}") from None
        depth = depth_dir / f"{Path(name).stem}.png" if depth_dir.is_dir() else None
        frames.append(Frame(Path(name).stem, img_dir / name, cam, depth, 1.0 / 1000.0))
    logger.debug("scannetpp %s: %d frames (%d marked is_bad)", scene_id, len(frames), len(bad))
    return validate_scene(EvalScene(scene_id, frames, "metric"), dslr)


def load_scannetpp(root: Path, split: str, scenes: Iterable[str] | None) -> list[EvalScene]:
    """The scenes of ``split`` (or ``scenes``) present under ``root``; missing ones are skipped with a warning."""
    if (root / "processed").is_dir():
        data_root, raw_root = root / "processed", root / "raw"
    else:
        data_root, raw_root = root / "data", root
    if scenes is None:
        split_file = raw_root / "splits" / f"{split}.txt"
        if not split_file.is_file():
            raise DatasetError(f"{split_file}: split file not found")
        ids = [ln.strip() for ln in split_file.read_text(encoding="utf-8").splitlines() if ln.strip()]
    else:
        ids = list(scenes)
    present = [s for s in ids if (data_root / s / "dslr").is_dir()]
    missing = [s for s in ids if s not in present]
    if missing:
        logger.warning("%d scene(s) of the split are not in %s (skipped): %s", len(missing), data_root, missing[:5])
    if not present:
        raise DatasetError(f"{data_root}: none of the {len(ids)} scenes of split {split!r} is there")
    return [_scannetpp_scene(data_root, raw_root, s) for s in present]
