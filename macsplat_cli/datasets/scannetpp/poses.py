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

from ...camera_formats import read_colmap_model
from ...cameras import Camera
from ...errors import CameraFileError, DatasetError

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
        model: ``"PINHOLE"``, ``"OPENCV"`` (``k1 k2 p1 p2``, ``k3`` where it is not 0) or ``"OPENCV_FISHEYE"``
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


def _lens(cam: Camera) -> Lens:
    """A camera's intrinsics as the data set's :class:`Lens` (OpenCV's ``k3`` kept only where it is not 0)."""
    d = cam.distortion
    if d is None:
        return Lens(cam.width, cam.height, cam.K)
    if d.model == "fisheye":
        return Lens(cam.width, cam.height, cam.K, "OPENCV_FISHEYE", d.coeffs)
    return Lens(cam.width, cam.height, cam.K, "OPENCV", d.coeffs if d.coeffs[4] != 0.0 else d.coeffs[:4])


def read_colmap_scene(folder: Path) -> PoseTable:
    """Poses and lenses of a COLMAP model in ``folder``, keyed by image file name.

    Read by :func:`~macsplat_cli.camera_formats.read_colmap_model` (text ``cameras.txt`` + ``images.txt``, or the
    binary files): world-to-camera ``q, t`` (OpenCV axes) become camera-to-world; the pinhole, radial, OpenCV and
    fisheye (the ScanNet++ DSLR) models are read with their distortion. COLMAP has no ``is_bad`` flag (always
    False).

    Raises:
        DatasetError: a missing or malformed file, or an invalid camera (the message names it).
    """
    try:
        cams = read_colmap_model(folder)
    except CameraFileError as e:
        raise DatasetError(str(e)) from None
    return {Path(c.name).name: (c.cam_to_world, _lens(c), False) for c in cams}
