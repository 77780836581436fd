"""ScanNet++ cameras: nerfstudio ``transforms.json`` and COLMAP text models, as OpenCV poses and lens models.

Conventions (reference notes §4.2): the nerfstudio ``transform_matrix`` is camera-to-world
in OpenGL camera axes *and* a permuted world frame; :func:`nerfstudio_to_opencv` gives OpenCV
camera-to-world in the mesh-aligned frame, the frame of COLMAP's ``images.txt``
(world-to-camera, OpenCV axes). Intrinsics are in the COLMAP/nerfstudio pixel convention
(pixel centres at +0.5), the convention of :class:`~macsplat_cli.cameras.Camera`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...cameras import quat_to_rotmat_np
from ...errors import DatasetError

__all__ = [
    "Lens",
    "PoseTable",
    "lens_from_transforms",
    "nerfstudio_to_opencv",
    "opencv_to_nerfstudio",
    "poses_from_transforms",
    "read_colmap_scene",
]

LENS_MODELS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")
_DIST_KEYS = {"PINHOLE": (), "OPENCV": ("k1", "k2", "p1", "p2"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}


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


@dataclass(frozen=True)
class Lens:
    """A camera's intrinsics and lens distortion.

    Attributes:
        width: image width in pixels.
        height: image height in pixels.
        K: ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, pixel centres at +0.5. [3, 3]
        model: ``"PINHOLE"``, ``"OPENCV"`` (``k1 k2 p1 p2``) or ``"OPENCV_FISHEYE"``
            (Kannala–Brandt ``k1 k2 k3 k4``, the model of ``cv2.fisheye``).
        dist: the distortion coefficients of ``model`` (empty for ``PINHOLE``).
    """

    width: int
    height: int
    K: np.ndarray
    model: str = "PINHOLE"
    dist: tuple[float, ...] = ()

    @property
    def distorted(self) -> bool:
        """The lens has non-zero distortion."""
        return any(d != 0.0 for d in self.dist)

    def key(self) -> dict[str, Any]:
        """JSON-able description (the undistortion cache compares it)."""
        return {"w": self.width, "h": self.height, "K": self.K.tolist(), "model": self.model, "dist": list(self.dist)}


PoseTable = dict[str, tuple[np.ndarray, Lens, bool]]
"""Image file name → (OpenCV camera-to-world [4, 4], lens, ``is_bad``)."""


def lens_from_transforms(doc: dict[str, Any], path: Path, frame: dict[str, Any] | None = None) -> Lens:
    """The lens of a nerfstudio ``transforms.json`` (per-frame keys override the top-level ones).

    Raises:
        DatasetError: a missing key or an unsupported ``camera_model`` (the message names ``path``).
    """
    src = dict(doc)
    if frame is not None:
        src.update(
            {
                k: v
                for k, v in frame.items()
                if k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")
            }
        )
    model = str(src.get("camera_model", "PINHOLE")).upper()
    if model not in LENS_MODELS:
        raise DatasetError(f"{path}: camera_model {model!r} is not supported (use one of {', '.join(LENS_MODELS)})")
    try:
        w, h = int(src["w"]), int(src["h"])
        K = np.array(
            [[float(src["fl_x"]), 0.0, float(src["cx"])], [0.0, float(src["fl_y"]), float(src["cy"])], [0.0, 0.0, 1.0]]
        )
        dist = tuple(float(src.get(k, 0.0)) for k in _DIST_KEYS[model])
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: expected w, h, fl_x, fl_y, cx, cy ({e!r})") from None
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and w > 0 and h > 0):
        raise DatasetError(f"{path}: invalid intrinsics w={w}, h={h}, K={K.tolist()}")
    return Lens(w, h, K, model, dist)


def poses_from_transforms(doc: Any, path: Path) -> tuple[PoseTable, list[str]]:
    """Poses of every frame (``frames`` and ``test_frames``) of a nerfstudio ``transforms.json``.

    Returns:
        The pose table (keys: file names without folders) and the names of ``frames`` (the
        train frames), in file order.

    Raises:
        DatasetError: malformed document (the message names ``path``).
    """
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        raise DatasetError(f"{path}: expected a JSON object with a 'frames' list")
    table: PoseTable = {}
    train: list[str] = []
    lens = lens_from_transforms(doc, path)
    for key in ("frames", "test_frames"):
        frames = doc.get(key, [])
        if not isinstance(frames, list):
            raise DatasetError(f"{path}: '{key}' must be a list")
        for f in frames:
            try:
                name = Path(str(f["file_path"])).name
                T = np.array(f["transform_matrix"], dtype=np.float64)
            except (KeyError, TypeError, ValueError) as e:
                raise DatasetError(f"{path}: a frame needs file_path and transform_matrix ({e!r})") from None
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise DatasetError(f"{path}: frame {name}: transform_matrix must be a finite 4x4 matrix")
            has_own = any(k in f for k in ("fl_x", "fl_y", "cx", "cy", "w", "h"))
            table[name] = (
                nerfstudio_to_opencv(T),
                lens_from_transforms(doc, path, f) if has_own else lens,
                bool(f.get("is_bad", False)),
            )
            if key == "frames":
                train.append(name)
    return table, train


def _colmap_lines(path: Path) -> list[str]:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read ({e})") from None


def _colmap_cameras(path: Path) -> dict[int, Lens]:
    n_params = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "OPENCV": 8, "OPENCV_FISHEYE": 8}
    cams: dict[int, Lens] = {}
    for lineno, raw in enumerate(_colmap_lines(path), start=1):
        parts = raw.split()
        if not parts or parts[0].startswith("#"):
            continue
        model = parts[1] if len(parts) > 1 else ""
        if model not in n_params:
            raise DatasetError(
                f"{path}: line {lineno}: camera model {model!r} is not supported (use one of {', '.join(n_params)})"
            )
        try:
            cam_id, w, h = int(parts[0]), int(parts[2]), int(parts[3])
            p = [float(v) for v in parts[4:]]
        except (ValueError, IndexError):
            raise DatasetError(f"{path}: line {lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]") from None
        if len(p) != n_params[model]:
            raise DatasetError(f"{path}: line {lineno}: {model} needs {n_params[model]} params, got {len(p)}")
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if model == "SIMPLE_PINHOLE" else p[:4]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cams[cam_id] = Lens(w, h, K, "PINHOLE" if model == "SIMPLE_PINHOLE" else model, tuple(p[4:]))
    return cams


def read_colmap_scene(folder: Path) -> PoseTable:
    """Poses and lenses of a COLMAP text model (``cameras.txt`` + ``images.txt``), keyed by image file name.

    ``images.txt`` holds world-to-camera ``QW QX QY QZ TX TY TZ`` (OpenCV axes) followed by a
    POINTS2D line (possibly empty); camera models ``SIMPLE_PINHOLE``, ``PINHOLE``, ``OPENCV``
    and ``OPENCV_FISHEYE`` (the ScanNet++ DSLR) are read with their distortion. COLMAP has no
    ``is_bad`` flag (always False).

    Raises:
        DatasetError: a missing or malformed file (the message names it).
    """
    cams = _colmap_cameras(folder / "cameras.txt")
    path = folder / "images.txt"
    lines = _colmap_lines(path)
    table: PoseTable = {}
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        parts = line.split(maxsplit=9)
        try:
            cam_id = int(parts[8])
            q = np.array([float(v) for v in parts[1:5]])
            t = np.array([float(v) for v in parts[5:8]])
            name = Path(parts[9].strip()).name
        except (ValueError, IndexError):
            raise DatasetError(f"{path}: line {i}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME") from None
        if cam_id not in cams:
            raise DatasetError(f"{path}: line {i}: CAMERA_ID {cam_id} is not in {folder / 'cameras.txt'}")
        if not (np.isfinite(q).all() and np.isfinite(t).all() and np.linalg.norm(q) > 0):
            raise DatasetError(f"{path}: line {i}: the pose must be finite with a non-zero quaternion")
        i += 1  # the POINTS2D line
        R = quat_to_rotmat_np(q / np.linalg.norm(q))
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -(R.T @ t)
        table[name] = (c2w, cams[cam_id], False)
    if not table:
        raise DatasetError(f"{path}: no images")
    return table
