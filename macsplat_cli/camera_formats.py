"""Camera exchange formats: COLMAP text models and nerfstudio ``transforms.json``.

Both conversions are exact and round-trip with :mod:`macsplat_cli.cameras`; the
conventions (axes, pixel centres, pose direction) are documented on each function.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._limits import read_text_file
from .cameras import (
    _GL_FROM_CV,
    Camera,
    CameraSet,
    Scale,
    _is_int,
    _json_type,
    _matrix,
    _read_json,
    _write_text,
    quat_to_rotmat_np,
    rotmat_to_quat_np,
)
from .errors import CameraFileError, OutputPathError

__all__ = ["read_colmap_text", "read_nerfstudio", "write_colmap_text", "write_nerfstudio"]

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------ COLMAP
_COLMAP_MODELS: dict[str, tuple[int, int]] = {
    # model: (number of params, number of leading pinhole params)
    "SIMPLE_PINHOLE": (3, 3),  # f, cx, cy
    "PINHOLE": (4, 4),  # fx, fy, cx, cy
    "SIMPLE_RADIAL": (4, 3),  # f, cx, cy, k
    "RADIAL": (5, 3),  # f, cx, cy, k1, k2
    "OPENCV": (8, 4),  # fx, fy, cx, cy, k1, k2, p1, p2
    "FULL_OPENCV": (12, 4),  # fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6
}


def _check_no_skew(cam: Camera, fmt: str) -> None:
    if cam.K[0, 1] != 0.0:
        raise CameraFileError(f"camera {cam.name!r}: K has skew {cam.K[0, 1]:g}, which {fmt} cannot store")


def _num(x: float) -> str:
    return repr(float(x))


def write_colmap_text(camera_set: CameraSet, folder: str | os.PathLike[str]) -> Path:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, empty ``points3D.txt``).

    Conversion: each view ``i`` becomes camera ``i + 1`` (model ``PINHOLE``,
    params ``fx fy cx cy`` copied unchanged, since COLMAP uses the same
    pixel-centre convention) and image ``i + 1`` whose pose is world-to-camera:
    ``QW QX QY QZ`` is the Hamilton quaternion of ``R = R_c2wᵀ`` with ``QW ≥ 0``
    and ``TX TY TZ = −R · center``. COLMAP camera axes are OpenCV axes. The world
    name and scale are not stored. ``folder`` is created if needed; each file is
    written atomically.

    Raises:
        CameraFileError: a camera has skew (``PINHOLE`` cannot store it) or a name
            with whitespace (COLMAP names are single tokens).
        OutputPathError: the folder cannot be created or written.

    Returns:
        The folder.
    """
    out = Path(folder)
    cam_lines: list[str] = []
    img_lines: list[str] = []
    for i, cam in enumerate(camera_set.cameras, start=1):
        _check_no_skew(cam, "a COLMAP PINHOLE camera")
        if not cam.name or any(ch.isspace() for ch in cam.name):
            raise CameraFileError(f"camera {cam.name!r}: a COLMAP image name must be non-empty, without spaces")
        params = " ".join(_num(v) for v in (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]))
        cam_lines.append(f"{i} PINHOLE {cam.width} {cam.height} {params}")
        q = rotmat_to_quat_np(cam.R)
        t = cam.t
        img_lines.append(f"{i} {' '.join(_num(v) for v in q)} {' '.join(_num(v) for v in t)} {i} {cam.name}")
        img_lines.append("")  # no 2D points
    n = len(camera_set)
    cameras_txt = (
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: {n}\n" + "".join(line + "\n" for line in cam_lines)
    )
    images_txt = (
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        f"# Number of images: {n}, mean observations per image: 0\n" + "".join(line + "\n" for line in img_lines)
    )
    points_txt = (
        "# 3D point list with one line of data per point:\n"
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        "# Number of points: 0, mean track length: 0\n"
    )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create folder {out}: {e.strerror or e}") from e
    _write_text(out / "cameras.txt", cameras_txt)
    _write_text(out / "images.txt", images_txt)
    _write_text(out / "points3D.txt", points_txt)
    return out


def _read_lines(path: Path) -> list[str]:
    return read_text_file(path, CameraFileError, "a COLMAP text file").splitlines()


def _parse_colmap_cameras(path: Path) -> dict[int, tuple[int, int, np.ndarray]]:
    cams: dict[int, tuple[int, int, np.ndarray]] = {}
    for lineno, raw in enumerate(_read_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}: line {lineno}"
        parts = line.split()
        if len(parts) < 4:
            raise CameraFileError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        model = parts[1]
        if model not in _COLMAP_MODELS:
            raise CameraFileError(
                f"{where}: camera model {model} is not supported (use one of {', '.join(_COLMAP_MODELS)})"
            )
        n_params, n_pinhole = _COLMAP_MODELS[model]
        try:
            cam_id, width, height = int(parts[0]), int(parts[2]), int(parts[3])
            params = [float(v) for v in parts[4:]]
        except ValueError:
            raise CameraFileError(f"{where}: expected integers CAMERA_ID WIDTH HEIGHT and numeric params") from None
        if len(params) != n_params:
            raise CameraFileError(f"{where}: {model} needs {n_params} params, got {len(params)}")
        if n_pinhole == 3:
            fx = fy = params[0]
            cx, cy = params[1:3]
        else:
            fx, fy, cx, cy = params[:4]
        if any(v != 0.0 for v in params[n_pinhole:]):
            logger.warning("%s: camera %d (%s): lens distortion is ignored", path, cam_id, model)
        cams[cam_id] = (width, height, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    return cams


def read_colmap_text(folder: str | os.PathLike[str], *, world: str = "colmap", scale: Scale = "relative") -> CameraSet:
    """Read a COLMAP text model (``cameras.txt`` and ``images.txt``) as a camera set.

    The inverse of :func:`write_colmap_text`: ``cam_to_world`` is
    ``[Rᵀ | −Rᵀt]`` of each image's world-to-camera ``(q, t)``; intrinsics are
    copied. Models ``SIMPLE_PINHOLE``, ``PINHOLE`` and the pinhole part of
    ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV`` are accepted (non-zero
    distortion is ignored with a warning). Cameras are named after the images and
    ordered by ``IMAGE_ID``. ``#`` comment lines and ``POINTS2D`` lines are skipped;
    ``points3D.txt`` is not read.

    Args:
        folder: the folder holding ``cameras.txt`` and ``images.txt``.
        world: name given to COLMAP's world frame.
        scale: ``"relative"`` unless the model is known to be metric.

    Raises:
        CameraFileError: a file is missing or malformed, or an image refers to an
            unknown camera.
    """
    root = Path(folder)
    intrinsics = _parse_colmap_cameras(root / "cameras.txt")
    path = root / "images.txt"
    lines = _read_lines(path)
    images: list[tuple[int, Camera]] = []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        where = f"{path}: line {i}"
        parts = line.split(maxsplit=9)
        if len(parts) != 10:
            raise CameraFileError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        try:
            image_id, cam_id = int(parts[0]), int(parts[8])
            q = np.array([float(v) for v in parts[1:5]])
            t = np.array([float(v) for v in parts[5:8]])
        except ValueError:
            raise CameraFileError(f"{where}: expected integer ids and numeric QW..TZ") from None
        if not (np.isfinite(q).all() and np.isfinite(t).all()) or not np.linalg.norm(q) > 0:
            raise CameraFileError(f"{where}: the quaternion must be finite and non-zero")
        if cam_id not in intrinsics:
            raise CameraFileError(f"{where}: CAMERA_ID {cam_id} is not in {root / 'cameras.txt'}")
        i += 1  # the POINTS2D line that follows every image line
        R = quat_to_rotmat_np(q)
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -(R.T @ t)
        width, height, K = intrinsics[cam_id]
        try:
            cam = Camera(name=parts[9].strip(), width=width, height=height, K=K, cam_to_world=c2w)
        except CameraFileError as e:
            raise CameraFileError(f"{where}: {e}") from None
        images.append((image_id, cam))
    if not images:
        raise CameraFileError(f"{path}: no images")
    images.sort(key=lambda item: item[0])
    try:
        return CameraSet([cam for _, cam in images], scale=scale, world=world)
    except CameraFileError as e:
        raise CameraFileError(f"{path}: {e}") from None


# ------------------------------------------------------------------------------------ nerfstudio
def write_nerfstudio(camera_set: CameraSet, path: str | os.PathLike[str]) -> Path:
    """Write a nerfstudio ``transforms.json`` (atomically).

    Conversion: top-level ``camera_model: "OPENCV"`` (no distortion keys, i.e.
    zero distortion) and one frame per camera with ``file_path`` = the camera
    name (nerfstudio resolves it relative to the JSON file, so name cameras e.g.
    ``"images/left.png"``), ``fl_x fl_y cx cy`` copied from ``K`` (same pixel
    convention), ``w h``, and ``transform_matrix`` = camera-to-world with OpenGL
    camera axes (x right, y up, z back): ``c2w_gl = c2w_cv @ diag(1, −1, −1, 1)``,
    i.e. columns 1 and 2 negated. The world name and scale are not stored.

    Raises:
        CameraFileError: a camera has skew, which nerfstudio cannot store.
        OutputPathError: ``path`` cannot be written.

    Returns:
        The path written.
    """
    frames = []
    for cam in camera_set.cameras:
        _check_no_skew(cam, "nerfstudio")
        frames.append(
            {
                "file_path": cam.name,
                "fl_x": float(cam.K[0, 0]),
                "fl_y": float(cam.K[1, 1]),
                "cx": float(cam.K[0, 2]),
                "cy": float(cam.K[1, 2]),
                "w": cam.width,
                "h": cam.height,
                "transform_matrix": (cam.cam_to_world @ _GL_FROM_CV).tolist(),
            }
        )
    _write_text(path, json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=2) + "\n")
    return Path(path)


_NS_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_NS_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def read_nerfstudio(path: str | os.PathLike[str], *, world: str = "nerfstudio", scale: Scale = "relative") -> CameraSet:
    """Read a nerfstudio ``transforms.json`` as a camera set.

    The inverse of :func:`write_nerfstudio`: ``cam_to_world = transform_matrix @
    diag(1, −1, −1, 1)`` (OpenGL → OpenCV camera axes), ``K`` from ``fl_x fl_y cx
    cy``, size from ``w h``, name from ``file_path``. Intrinsics may be given per
    frame or once at the top level (per-frame values win). ``camera_model`` may be
    ``OPENCV``, ``PINHOLE`` or ``SIMPLE_PINHOLE`` (absent means ``OPENCV``);
    non-zero distortion coefficients are ignored with a warning.

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
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise CameraFileError(f"{p}: camera_model {model!r} is not a pinhole model (use OPENCV or PINHOLE)")
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
        distortion = {k: frame.get(k, d.get(k, 0.0)) for k in _NS_DISTORTION}
        if any(isinstance(v, (int, float)) and v != 0.0 for v in distortion.values()):
            logger.warning("%s: lens distortion is ignored", where)
        name = frame.get("file_path")
        if not isinstance(name, str):
            raise CameraFileError(f"{where}: file_path must be a string, got {_json_type(name)}")
        c2w_gl = _matrix(frame.get("transform_matrix"), 4, 4, f"{where}.transform_matrix")
        K = np.array(
            [[values["fl_x"], 0.0, values["cx"]], [0.0, values["fl_y"], values["cy"]], [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )
        try:
            cameras.append(Camera(name, values["w"], values["h"], K, c2w_gl @ _GL_FROM_CV))
        except CameraFileError as e:
            raise CameraFileError(f"{where}: {e}") from None
    try:
        return CameraSet(cameras, scale=scale, world=world)
    except CameraFileError as e:
        raise CameraFileError(f"{p}: {e}") from None
