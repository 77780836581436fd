"""nerfstudio's ``transforms.json``: cameras as nerfstudio (and gsplat's nerfstudio-style loaders) read them.

The conversion is exact and round-trips with :mod:`macsplat_cli.cameras`; the conventions (axes, pixel centres,
pose direction) are documented on each function.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..cameras import _GL_FROM_CV, Camera, CameraSet, Scale, _is_int, _json_type, _matrix, _read_json, _write_text
from ..distortion import DISTORTION_MODELS, Distortion
from ..errors import CameraFileError

__all__ = ["read_nerfstudio", "write_nerfstudio"]

_NS_MODELS = {"OPENCV": "opencv", "PINHOLE": None, "SIMPLE_PINHOLE": None, "OPENCV_FISHEYE": "fisheye"}
"""nerfstudio's ``camera_model`` values read → our distortion model (None: pinhole)."""


def write_nerfstudio(
    camera_set: CameraSet, path: str | os.PathLike[str], *, image_folder: str = "", ply_file_path: str | None = None
) -> Path:
    """Write a nerfstudio ``transforms.json`` (atomically).

    Conversion: top-level ``camera_model`` ``"OPENCV"`` (``"OPENCV_FISHEYE"`` when the cameras have fisheye
    distortion) and one frame per camera with ``file_path`` = ``image_folder`` + the camera name (nerfstudio resolves
    it relative to the JSON file), ``fl_x fl_y cx cy`` copied from ``K`` (same pixel convention), ``w h``, the
    camera's distortion coefficients when it has any (``k1 k2 k3 p1 p2``, or fisheye ``k1..k4``; none means zero
    distortion), and ``transform_matrix`` = camera-to-world with OpenGL camera axes (x right, y up, z back):
    ``c2w_gl = c2w_cv @ diag(1, −1, −1, 1)``, i.e. columns 1 and 2 negated. ``ply_file_path`` (e.g.
    ``"sparse_pc.ply"``) names a point cloud beside it, in the same world. The world name and scale are not stored.

    Raises:
        CameraFileError: a camera has skew, which nerfstudio cannot store, or fisheye and other cameras are mixed.
        OutputPathError: ``path`` cannot be written.

    Returns:
        The path written.
    """
    fisheye = {cam.distortion is not None and cam.distortion.model == "fisheye" for cam in camera_set.cameras}
    if len(fisheye) > 1:
        raise CameraFileError("nerfstudio has one camera_model per file: fisheye and other cameras cannot be mixed")
    frames = []
    for cam in camera_set.cameras:
        if cam.K[0, 1] != 0.0:
            raise CameraFileError(f"camera {cam.name!r}: K has skew {cam.K[0, 1]:g}, which nerfstudio cannot store")
        frame: dict[str, Any] = {
            "file_path": image_folder + cam.name,
            "fl_x": float(cam.K[0, 0]),
            "fl_y": float(cam.K[1, 1]),
            "cx": float(cam.K[0, 2]),
            "cy": float(cam.K[1, 2]),
            "w": cam.width,
            "h": cam.height,
        }
        if cam.distortion is not None:
            frame.update(zip(DISTORTION_MODELS[cam.distortion.model], cam.distortion.coeffs))
        frame["transform_matrix"] = (cam.cam_to_world @ _GL_FROM_CV).tolist()
        frames.append(frame)
    doc: dict[str, Any] = {"camera_model": "OPENCV_FISHEYE" if True in fisheye else "OPENCV", "frames": frames}
    if ply_file_path is not None:
        doc["ply_file_path"] = ply_file_path
    _write_text(path, json.dumps(doc, indent=2) + "\n")
    return Path(path)


_NS_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def _distortion(model: str | None, frame: Mapping, top: Mapping, where: str) -> Distortion | None:
    """A frame's distortion under ``model`` (per-frame coefficients win over the top level's); None when zero."""
    if model is None:
        return None
    values = {k: frame.get(k, top.get(k, 0.0)) for k in DISTORTION_MODELS[model]}
    for k, v in values.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise CameraFileError(f"{where}: {k} must be a finite number, got {v!r}")
    out = Distortion(model, tuple(float(values[k]) for k in DISTORTION_MODELS[model]))
    return None if out.is_zero else out


def read_nerfstudio(path: str | os.PathLike[str], *, world: str = "nerfstudio", scale: Scale = "relative") -> CameraSet:
    """Read a nerfstudio ``transforms.json`` as a camera set.

    The inverse of :func:`write_nerfstudio`: ``cam_to_world = transform_matrix @
    diag(1, −1, −1, 1)`` (OpenGL → OpenCV camera axes), ``K`` from ``fl_x fl_y cx
    cy``, size from ``w h``, name from ``file_path``. Intrinsics and distortion may be
    given per frame or once at the top level (per-frame values win). ``camera_model`` may be
    ``OPENCV`` (``k1 k2 k3 p1 p2``), ``OPENCV_FISHEYE`` (``k1..k4``), ``PINHOLE`` or ``SIMPLE_PINHOLE``
    (absent means ``OPENCV``); the coefficients become the camera's distortion.

    Args:
        path: the ``transforms.json`` file.
        world: name given to the file's world frame.
        scale: ``"relative"`` unless the poses are known to be metric.

    Raises:
        CameraFileError: the file is missing, not JSON, or malformed.
    """
    p = Path(path)
    d = _read_json(p)
    if not isinstance(d, Mapping):
        raise CameraFileError(f"{p}: the top level must be an object, got {_json_type(d)}")
    model = d.get("camera_model", "OPENCV")
    if model not in _NS_MODELS:
        raise CameraFileError(f"{p}: camera_model {model!r} is not read (use one of {', '.join(_NS_MODELS)})")
    frames = d.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CameraFileError(f"{p}: frames must be a non-empty list")
    cameras = []
    for i, frame in enumerate(frames):
        where = f"{p}: frames[{i}]"
        if not isinstance(frame, Mapping):
            raise CameraFileError(f"{where} must be an object, got {_json_type(frame)}")
        values: dict[str, Any] = {}
        for key in _NS_INTRINSICS:
            value = frame.get(key, d.get(key))
            if value is None:
                raise CameraFileError(f"{where}: missing {key!r} (neither in the frame nor at the top level)")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise CameraFileError(f"{where}: {key} must be a number, got {_json_type(value)}")
            values[key] = value
        for key in ("w", "h"):
            if not _is_int(values[key]):
                if isinstance(values[key], float) and values[key].is_integer():
                    values[key] = int(values[key])
                else:
                    raise CameraFileError(f"{where}: {key} must be an integer, got {values[key]!r}")
        distortion = _distortion(_NS_MODELS[model], frame, d, where)
        name = frame.get("file_path")
        if not isinstance(name, str):
            raise CameraFileError(f"{where}: file_path must be a string, got {_json_type(name)}")
        c2w_gl = _matrix(frame.get("transform_matrix"), 4, 4, f"{where}.transform_matrix")
        K = np.array(
            [[values["fl_x"], 0.0, values["cx"]], [0.0, values["fl_y"], values["cy"]], [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )
        try:
            cameras.append(Camera(name, values["w"], values["h"], K, c2w_gl @ _GL_FROM_CV, distortion))
        except CameraFileError as e:
            raise CameraFileError(f"{where}: {e}") from None
    try:
        return CameraSet(cameras, scale=scale, world=world)
    except CameraFileError as e:
        raise CameraFileError(f"{p}: {e}") from None
