"""COLMAP models: cameras, images and points as COLMAP's text files, read from text or binary.

Conventions: COLMAP's camera axes are OpenCV's and its pixel centres are at +0.5, as in
:mod:`macsplat_cli.cameras`; an image's pose is world-to-camera ``(q, t)``. The lens models map to
:class:`~macsplat_cli.distortion.Distortion` (:data:`COLMAP_MODELS`).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._limits import MAX_TEXT_BYTES, check_regular_file, read_text_file
from ..cameras import Camera, CameraSet, Scale, _write_text, quat_to_rotmat_np, rotmat_to_quat_np
from ..distortion import Distortion
from ..errors import CameraFileError, OutputPathError
from .points import SparsePoints

__all__ = ["COLMAP_MODELS", "read_colmap_model", "read_colmap_text", "write_colmap_text"]


@dataclass(frozen=True)
class _Model:
    """A COLMAP camera model: its id in the binary files, its parameter count, and how they map to ours."""

    id: int
    n_params: int
    single_focal: bool  # f, cx, cy, ... instead of fx, fy, cx, cy, ...
    distortion: str | None  # our model, or None for a pinhole
    coeffs: tuple[int, ...] = ()  # for each of our coefficients: the index in params, or -1 for 0


COLMAP_MODELS: dict[str, _Model] = {
    "SIMPLE_PINHOLE": _Model(0, 3, True, None),
    "PINHOLE": _Model(1, 4, False, None),
    "SIMPLE_RADIAL": _Model(2, 4, True, "opencv", (3, -1, -1, -1, -1)),  # f cx cy k
    "RADIAL": _Model(3, 5, True, "opencv", (3, 4, -1, -1, -1)),  # f cx cy k1 k2
    "OPENCV": _Model(4, 8, False, "opencv", (4, 5, 6, 7, -1)),  # fx fy cx cy k1 k2 p1 p2
    "OPENCV_FISHEYE": _Model(5, 8, False, "fisheye", (4, 5, 6, 7)),  # fx fy cx cy k1 k2 k3 k4
    "FULL_OPENCV": _Model(6, 12, False, "opencv", (4, 5, 6, 7, 8)),  # + k3 k4 k5 k6 (the last three must be 0)
}
"""The COLMAP camera models read (and, PINHOLE / OPENCV / OPENCV_FISHEYE, written)."""
_BY_ID = {m.id: name for name, m in COLMAP_MODELS.items()}


# ------------------------------------------------------------------------------------ writing
def _num(x: float) -> str:
    return repr(float(x))


def _camera_line(i: int, cam: Camera) -> str:
    """``cameras.txt``'s line of camera ``i``: PINHOLE, or OPENCV / OPENCV_FISHEYE with its distortion."""
    if cam.K[0, 1] != 0.0:
        raise CameraFileError(f"camera {cam.name!r}: K has skew {cam.K[0, 1]:g}, which a COLMAP camera cannot store")
    pinhole = [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]]
    d = cam.distortion
    if d is None:
        model, params = "PINHOLE", pinhole
    elif d.model == "fisheye":
        model, params = "OPENCV_FISHEYE", pinhole + list(d.coeffs)
    else:
        k1, k2, p1, p2, k3 = d.coeffs
        model, params = ("OPENCV", pinhole + [k1, k2, p1, p2]) if k3 == 0.0 else (
            "FULL_OPENCV", pinhole + [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0])  # fmt: skip
    return f"{i} {model} {cam.width} {cam.height} {' '.join(_num(v) for v in params)}"


def write_colmap_text(
    camera_set: CameraSet, folder: str | os.PathLike[str], points: SparsePoints | None = None
) -> Path:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    Conversion: each camera ``i`` becomes COLMAP camera ``i + 1`` (``PINHOLE`` with ``fx fy cx cy`` copied, since
    COLMAP uses the same pixel-centre convention; ``OPENCV`` / ``FULL_OPENCV`` / ``OPENCV_FISHEYE`` when it has
    distortion) and image ``i + 1`` named after the camera, whose pose is world-to-camera: ``QW QX QY QZ`` is the
    Hamilton quaternion of ``R = R_c2wᵀ`` with ``QW ≥ 0`` and ``TX TY TZ = −R · center``. With ``points``, each
    point ``p`` becomes point ``p + 1`` with its colour, error and track, and each image lists the points it
    observes (``POINTS2D``); without, ``points3D.txt`` is empty. The world name and scale are not stored.
    ``folder`` is created if needed; each file is written atomically.

    Raises:
        CameraFileError: a camera has skew or a name with whitespace (COLMAP names are single tokens).
        OutputPathError: the folder cannot be created or written.

    Returns:
        The folder.
    """
    out = Path(folder)
    n = len(camera_set)
    per_image: list[list[tuple[float, float, int]]] = [[] for _ in range(n)]
    track_lines: list[str] = []
    if points is not None:
        slot = np.zeros(len(points.obs_point), np.int64)  # each observation's POINT2D_IDX in its image
        for o, (img, pt) in enumerate(zip(points.obs_image, points.obs_point)):
            slot[o] = len(per_image[img])
            per_image[img].append((float(points.obs_xy[o, 0]), float(points.obs_xy[o, 1]), int(pt) + 1))
        tracks: list[list[str]] = [[] for _ in range(len(points))]
        for o, (img, pt) in enumerate(zip(points.obs_image, points.obs_point)):
            tracks[pt].append(f"{int(img) + 1} {int(slot[o])}")
        for p in range(len(points)):
            xyz = " ".join(_num(v) for v in points.xyz[p])
            rgb = " ".join(str(int(v)) for v in points.rgb[p])
            track_lines.append(f"{p + 1} {xyz} {rgb} {_num(points.error[p])} {' '.join(tracks[p])}")
    cam_lines, img_lines = [], []
    for i, cam in enumerate(camera_set.cameras, start=1):
        if not cam.name or any(ch.isspace() for ch in cam.name):
            raise CameraFileError(f"camera {cam.name!r}: a COLMAP image name must be non-empty, without spaces")
        cam_lines.append(_camera_line(i, cam))
        q, t = rotmat_to_quat_np(cam.R), cam.t
        img_lines.append(f"{i} {' '.join(_num(v) for v in q)} {' '.join(_num(v) for v in t)} {i} {cam.name}")
        img_lines.append(" ".join(f"{_num(x)} {_num(y)} {p}" for x, y, p in per_image[i - 1]))
    n_obs = sum(len(o) for o in per_image)
    files = {
        "cameras.txt": "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: {n}\n" + "".join(line + "\n" for line in cam_lines),
        "images.txt": "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        f"# Number of images: {n}, mean observations per image: {_num(n_obs / n) if n_obs else 0}\n"
        + "".join(line + "\n" for line in img_lines),
        "points3D.txt": "# 3D point list with one line of data per point:\n"
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        f"# Number of points: {len(track_lines)}, mean track length: "
        f"{_num(n_obs / len(track_lines)) if track_lines else 0}\n" + "".join(line + "\n" for line in track_lines),
    }
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create folder {out}: {e.strerror or e}") from e
    for name, text in files.items():
        _write_text(out / name, text)
    return out


# ------------------------------------------------------------------------------------ reading
def _intrinsics(model: str, cam_id: int, width: int, height: int, params: list[float], where: str) -> tuple:
    """(width, height, K, distortion) of a COLMAP camera, or a CameraFileError naming it."""
    spec = COLMAP_MODELS.get(model)
    if spec is None:
        raise CameraFileError(
            f"{where}: camera {cam_id} has model {model}, which macsplat does not read "
            f"(use one of {', '.join(COLMAP_MODELS)})"
        )
    if len(params) != spec.n_params:
        raise CameraFileError(f"{where}: camera {cam_id} ({model}) needs {spec.n_params} params, got {len(params)}")
    if not np.isfinite(params).all():
        raise CameraFileError(f"{where}: camera {cam_id} ({model}) has a NaN or infinite parameter")
    if spec.single_focal:
        fx = fy = params[0]
        cx, cy = params[1:3]
    else:
        fx, fy, cx, cy = params[:4]
    if model == "FULL_OPENCV" and any(v != 0.0 for v in params[9:]):
        raise CameraFileError(f"{where}: camera {cam_id} (FULL_OPENCV) has k4..k6 (a rational model) not all 0")
    distortion = None
    if spec.distortion is not None:
        distortion = Distortion(spec.distortion, tuple(params[k] if k >= 0 else 0.0 for k in spec.coeffs))
        distortion = None if distortion.is_zero else distortion
    return width, height, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), distortion


def _text_lines(path: Path) -> list[str]:
    return read_text_file(path, CameraFileError, "a COLMAP text file").splitlines()


def _text_cameras(path: Path) -> dict[int, tuple]:
    cams: dict[int, tuple] = {}
    for lineno, raw in enumerate(_text_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}: line {lineno}"
        parts = line.split()
        if len(parts) < 4:
            raise CameraFileError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        try:
            cam_id, width, height = int(parts[0]), int(parts[2]), int(parts[3])
            params = [float(v) for v in parts[4:]]
        except ValueError:
            raise CameraFileError(f"{where}: expected integers CAMERA_ID WIDTH HEIGHT and numeric params") from None
        cams[cam_id] = _intrinsics(parts[1], cam_id, width, height, params, where)
    return cams


def _text_images(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str, str]]:
    """(IMAGE_ID, q, t, CAMERA_ID, NAME, where) of each image line of ``images.txt``."""
    lines = _text_lines(path)
    out = []
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
        out.append((image_id, q, t, cam_id, parts[9].strip(), where))
        i += 1  # the POINTS2D line that follows every image line
    return out


def _read_binary(path: Path) -> bytes:
    size = check_regular_file(path, CameraFileError, "a COLMAP binary file")
    if size > MAX_TEXT_BYTES:
        raise CameraFileError(f"{path}: {size} bytes, more than the {MAX_TEXT_BYTES} accepted")
    try:
        return path.read_bytes()
    except OSError as e:
        raise CameraFileError(f"{path}: cannot read: {e.strerror or e}") from None


class _Reader:
    """Little-endian fields of a COLMAP binary file, a truncated file reported as such."""

    def __init__(self, path: Path) -> None:
        self.path, self.data, self.at = path, _read_binary(path), 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise CameraFileError(f"{self.path}: truncated at byte {self.at}")
        out = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return out

    def name(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise CameraFileError(f"{self.path}: truncated in an image name")
        raw, self.at = self.data[self.at : end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CameraFileError(f"{self.path}: an image name is not UTF-8") from None


def _binary_cameras(path: Path) -> dict[int, tuple]:
    r = _Reader(path)
    cams: dict[int, tuple] = {}
    for _ in range(r.take("Q")[0]):
        cam_id, model_id, width, height = r.take("iiQQ")
        model = _BY_ID.get(model_id, f"#{model_id}")
        spec = COLMAP_MODELS.get(model)
        if spec is None:  # its parameter count is unknown here: nothing after it can be read
            _intrinsics(model, cam_id, width, height, [], str(path))
        params = list(r.take(f"{spec.n_params}d"))  # type: ignore[union-attr]
        cams[cam_id] = _intrinsics(model, cam_id, width, height, params, str(path))
    return cams


def _binary_images(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str, str]]:
    r = _Reader(path)
    out = []
    for _ in range(r.take("Q")[0]):
        image_id, *qt, cam_id = r.take("I7di")
        name = r.name()
        (n2d,) = r.take("Q")
        r.at += n2d * 24  # POINTS2D: x, y (double), POINT3D_ID (int64)
        if r.at > len(r.data):
            raise CameraFileError(f"{path}: truncated in image {image_id}'s points")
        out.append((image_id, np.array(qt[:4]), np.array(qt[4:]), cam_id, name, f"{path}: image {image_id}"))
    return out


def read_colmap_model(folder: str | os.PathLike[str], *, world: str = "colmap", scale: Scale = "relative") -> CameraSet:
    """Read a COLMAP model folder's cameras and images, text (``cameras.txt``, ``images.txt``) or binary
    (``cameras.bin``, ``images.bin``; used when no text model is there), as a camera set.

    ``cam_to_world`` is ``[Rᵀ | −Rᵀt]`` of each image's world-to-camera ``(q, t)`` (the model's frame and scale
    kept); intrinsics are copied; the lens models of :data:`COLMAP_MODELS` become the cameras' ``distortion``.
    Cameras are named after the images and ordered by ``IMAGE_ID``; ``points3D`` is not read.

    Args:
        folder: the model folder (e.g. ``sparse/0``).
        world: name given to COLMAP's world frame.
        scale: ``"relative"`` unless the model is known to be metric.

    Raises:
        CameraFileError: a file is missing or malformed, a camera's model is not one of :data:`COLMAP_MODELS`,
            its parameters are NaN or fold the image, or an image refers to an unknown camera.
    """
    root = Path(folder)
    text = (root / "cameras.txt").exists() or not (root / "cameras.bin").exists()
    if text:
        intrinsics, images = _text_cameras(root / "cameras.txt"), _text_images(root / "images.txt")
    else:
        intrinsics, images = _binary_cameras(root / "cameras.bin"), _binary_images(root / "images.bin")
    source = root / ("images.txt" if text else "images.bin")
    cams: list[tuple[int, Camera]] = []
    for image_id, q, t, cam_id, name, where in images:
        if not (np.isfinite(q).all() and np.isfinite(t).all()) or not np.linalg.norm(q) > 0:
            raise CameraFileError(f"{where}: the quaternion must be finite and non-zero")
        if cam_id not in intrinsics:
            raise CameraFileError(f"{where}: CAMERA_ID {cam_id} is not in the model's cameras")
        R = quat_to_rotmat_np(q)
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -(R.T @ t)
        width, height, K, distortion = intrinsics[cam_id]
        try:
            cams.append((image_id, Camera(name, width, height, K, c2w, distortion)))
        except CameraFileError as e:
            raise CameraFileError(f"{where}: camera {cam_id}: {e}") from None
    if not cams:
        raise CameraFileError(f"{source}: no images")
    cams.sort(key=lambda item: item[0])
    try:
        return CameraSet([cam for _, cam in cams], scale=scale, world=world)
    except CameraFileError as e:
        raise CameraFileError(f"{source}: {e}") from None


def read_colmap_text(folder: str | os.PathLike[str], *, world: str = "colmap", scale: Scale = "relative") -> CameraSet:
    """Read a COLMAP text model (``cameras.txt`` and ``images.txt``): :func:`read_colmap_model` on its text files."""
    root = Path(folder)
    if not (root / "cameras.txt").exists():
        raise CameraFileError(f"{root / 'cameras.txt'}: no such file")
    return read_colmap_model(root, world=world, scale=scale)
