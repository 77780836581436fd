"""Pinhole cameras: one schema for every camera macsplat reads, writes or renders.

**Axes.** OpenCV camera axes: x right, y down, z forward (the camera looks along
+z). ``cam_to_world`` maps camera coordinates to world coordinates; its inverse
``world_to_cam = [Rᵀ | −Rᵀt]`` is the "viewmat" of gsplat and the pose of COLMAP.

**Pixels.** ``K`` maps camera coordinates to continuous image coordinates whose
origin is the top-left *corner* of the image: the top-left pixel covers [0, 1]²,
so pixel (row i, column j) has its centre at ``(j + 0.5, i + 0.5)``. This is the
convention of COLMAP, gsplat and nerfstudio. A ``K`` from OpenCV calibration
puts pixel centres on integers and needs ``+0.5`` on ``cx`` and ``cy``. With this
convention, resizing an image from ``W×H`` to ``W'×H'`` multiplies row 0 of ``K``
by ``W'/W`` and row 1 by ``H'/H``, exactly (:meth:`Camera.rescaled`).

**File format** (``cameras.json``, written by :func:`save_cameras`)::

    {
      "convention": "opencv",          # required; the only accepted value
      "world": "camera_0",             # name of the world frame (default "camera_0")
      "scale": "relative",             # "relative" (up to scale) or "metric" (default "relative")
      "cameras": [                     # at least one
        {"name": "left", "width": 640, "height": 480,
         "K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]],      # pixels of width × height
         "cam_to_world": [[...], [...], [...], [0, 0, 0, 1]],
         "distortion": {"model": "opencv", "k1": 0.1, "k2": 0, "p1": 0, "p2": 0, "k3": 0}}  # optional
      ]
    }

``distortion`` (optional, absent = a pinhole camera) is OpenCV's lens model in the camera's normalised
coordinates: ``"opencv"`` with ``k1 k2 p1 p2 k3`` (``cv2.undistort``'s order), or ``"fisheye"`` with ``k1 k2 k3 k4``
(``cv2.fisheye``); absent coefficients are 0. ``reconstruct`` undistorts such photos once, at load, to the pinhole
``K`` of the same camera, and the cameras it writes are pinhole (the file's ``"undistorted"`` entry names them).

Conversions to and from COLMAP text models and nerfstudio ``transforms.json``
live in :mod:`macsplat_cli.camera_formats`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal, get_args

import numpy as np

from ._atomic import atomic_write_text
from ._json import to_jsonable
from ._limits import read_json_file
from .distortion import DISTORTION_MODELS, Distortion, fold_problem
from .errors import CameraFileError, OutputPathError
from .rotations import quat_to_rotmat_np, rotmat_to_quat_np  # re-exported: the camera formats' converters

__all__ = [
    "Camera",
    "CameraSet",
    "Distortion",
    "Scale",
    "load_cameras",
    "quat_to_rotmat_np",
    "rotmat_to_quat_np",
    "save_cameras",
]

logger = logging.getLogger(__name__)

Scale = Literal["relative", "metric"]
_SCALES: tuple[str, ...] = get_args(Scale)
RIGID_TOL = 1e-4
"""Largest accepted deviation of ``RᵀR`` from ``I`` (max abs entry) and of ``det R`` from 1."""
MAX_TRANSLATION = 1e8
"""Largest accepted camera position (each coordinate of ``cam_to_world[:3, 3]``): geo-referenced frames (UTM, Earth-
centred metres, a few 10⁶) fit, and the pipeline's products of positions (10¹⁶) stay far from overflow; 1e160
made the pose stages' linear algebra fail."""
_STRUCTURAL_TOL = 1e-9
"""Tolerance on the entries of ``K`` and ``cam_to_world`` that must be exactly 0 or 1."""
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Flips camera y and z: OpenCV (x right, y down, z forward) ↔ OpenGL (x right, y up, z back)."""


# ------------------------------------------------------------------------------------ Camera
def _intrinsics_problem(K: np.ndarray) -> str | None:
    if K.shape != (3, 3):
        return f"K must be 3x3, got shape {list(K.shape)}"
    if not np.isfinite(K).all():
        return "K holds NaN or Inf"
    if abs(K[1, 0]) > _STRUCTURAL_TOL or np.abs(K[2] - [0.0, 0.0, 1.0]).max() > _STRUCTURAL_TOL:
        return f"K must be a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return f"K must have positive focal lengths, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
    return None


def _pose_problem(T: np.ndarray) -> str | None:
    if T.shape != (4, 4):
        return f"cam_to_world must be 4x4, got shape {list(T.shape)}"
    if not np.isfinite(T).all():
        return "cam_to_world holds NaN or Inf"
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > _STRUCTURAL_TOL:
        return f"cam_to_world bottom row must be [0, 0, 0, 1], got {T[3].tolist()}"
    if np.abs(T[:3, 3]).max() > MAX_TRANSLATION:
        return (
            f"cam_to_world translation {T[:3, 3].tolist()} is out of range: each coordinate at most "
            f"{MAX_TRANSLATION:g} in magnitude"
        )
    R = T[:3, :3]
    det = float(np.linalg.det(R))
    if det < 0:
        return f"cam_to_world rotation is a reflection (det = {det:.3g}), not a proper rotation"
    deviation = float(np.abs(R.T @ R - np.eye(3)).max())
    if deviation > RIGID_TOL or abs(det - 1.0) > RIGID_TOL:
        return f"cam_to_world rotation is not rigid (RᵀR deviates from I by {deviation:.3g}, det = {det:.3g})"
    return None


def _is_int(v: object) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera with OpenCV axes (see the module docstring for conventions).

    Attributes:
        name: identifier, usually the image file name (unique within a :class:`CameraSet`).
        width: image width in pixels.
        height: image height in pixels.
        K: intrinsics in pixels of ``width × height``, pixel centres at ``+0.5``;
            skew ``K[0, 1]`` is allowed. [3, 3] float64
        cam_to_world: rigid camera-to-world transform (OpenCV camera axes). [4, 4] float64
        distortion: the lens's distortion (:class:`Distortion`), or None for a pinhole camera; kept by
            :meth:`rescaled` (it acts on normalised coordinates).

    Construction copies ``K`` and ``cam_to_world`` to read-only float64 arrays and
    raises :class:`~macsplat_cli.errors.CameraFileError` if the camera is invalid:
    non-positive size, a ``K`` that is not an upper-triangular pinhole matrix with
    positive focal lengths, or a ``cam_to_world`` that is not rigid (rotation
    orthonormal with det +1 within :data:`RIGID_TOL`) or whose position exceeds
    :data:`MAX_TRANSLATION`. Entries that must be exactly
    0 or 1 are snapped when within 1e-9. Equality compares all fields exactly.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    cam_to_world: np.ndarray
    distortion: Distortion | None = None

    def __post_init__(self) -> None:
        def fail(problem: str) -> CameraFileError:
            return CameraFileError(f"camera {self.name!r}: {problem}")

        if not isinstance(self.name, str):
            raise CameraFileError(f"camera name must be a string, got {type(self.name).__name__}")
        for field in ("width", "height"):
            value = getattr(self, field)
            if not _is_int(value) or value <= 0:
                raise fail(f"{field} must be a positive integer, got {value!r}")
            object.__setattr__(self, field, int(value))
        try:
            K = np.array(self.K, dtype=np.float64)
            T = np.array(self.cam_to_world, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise fail(f"K and cam_to_world must be numeric matrices ({e})") from None
        problem = _intrinsics_problem(K) or _pose_problem(T)
        if problem:
            raise fail(problem)
        if self.distortion is not None:
            if not isinstance(self.distortion, Distortion) or self.distortion.model not in DISTORTION_MODELS:
                raise fail(f"distortion must be a Distortion of a model in {tuple(DISTORTION_MODELS)}")
            d = self.distortion
            if len(d.coeffs) != len(DISTORTION_MODELS[d.model]) or not np.isfinite(d.coeffs).all():
                raise fail(f"its {d.model} distortion needs {len(DISTORTION_MODELS[d.model])} finite coefficients, "
                           f"got {list(d.coeffs)}")  # fmt: skip
            problem = fold_problem(d, K, self.width, self.height)
            if problem:
                raise fail(problem)
        K[1, 0], K[2] = 0.0, (0.0, 0.0, 1.0)
        T[3] = (0.0, 0.0, 0.0, 1.0)
        K.setflags(write=False)
        T.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_to_world", T)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.name == other.name
            and self.width == other.width
            and self.height == other.height
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.cam_to_world, other.cam_to_world)
            and self.distortion == other.distortion
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-looking array fields: not hashable

    # ---------------------------------------------------------------- pose
    @property
    def R(self) -> np.ndarray:
        """World-to-camera rotation ``R_c2wᵀ`` (COLMAP's and gsplat's R). [3, 3]"""
        return self.cam_to_world[:3, :3].T.copy()

    @property
    def t(self) -> np.ndarray:
        """World-to-camera translation ``−R t_c2w`` (COLMAP's and gsplat's t). [3]"""
        return -(self.R @ self.cam_to_world[:3, 3])

    @property
    def world_to_cam(self) -> np.ndarray:
        """World-to-camera transform ``[Rᵀ | −Rᵀt]`` of the rigid ``cam_to_world``. [4, 4]"""
        out = np.eye(4)
        out[:3, :3] = self.R
        out[:3, 3] = self.t
        return out

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates. [3]"""
        return self.cam_to_world[:3, 3].copy()

    # ---------------------------------------------------------------- derived cameras
    def rescaled(self, width: int, height: int) -> Camera:
        """The same camera for the image resized to ``width × height``.

        Row 0 of ``K`` is multiplied by ``width / self.width`` and row 1 by
        ``height / self.height``, which is exact with the pixel-corner convention.
        """
        if not (_is_int(width) and _is_int(height) and width > 0 and height > 0):
            raise CameraFileError(f"camera {self.name!r}: cannot rescale to {width!r}x{height!r}")
        K = self.K.copy()
        K[0] *= width / self.width
        K[1] *= height / self.height
        return dataclasses.replace(self, width=int(width), height=int(height), K=K)

    def with_pose(self, cam_to_world: np.ndarray) -> Camera:
        """The same camera at another pose.

        Args:
            cam_to_world: rigid camera-to-world transform. [4, 4]
        """
        return dataclasses.replace(self, cam_to_world=cam_to_world)

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (the ``cameras[i]`` entry of the file format; ``distortion`` only when set)."""
        out: dict[str, Any] = {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "cam_to_world": self.cam_to_world.tolist(),
        }
        if self.distortion is not None:
            out["distortion"] = self.distortion.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: object, where: str = "camera") -> Camera:
        """Parse a ``cameras[i]`` entry; ``where`` prefixes error messages (e.g. ``"cams.json: cameras[1]"``).

        Raises:
            CameraFileError: a key is missing, a value has the wrong type, or the
                camera is invalid.
        """
        if not isinstance(d, Mapping):
            raise CameraFileError(f"{where} must be an object, got {_json_type(d)}")
        missing = [key for key in ("name", "width", "height", "K", "cam_to_world") if key not in d]
        if missing:
            raise CameraFileError(f"{where} is missing key(s) {', '.join(repr(k) for k in missing)}")
        if not isinstance(d["name"], str):
            raise CameraFileError(f"{where}.name must be a string, got {_json_type(d['name'])}")
        for key in ("width", "height"):
            if not _is_int(d[key]) or d[key] <= 0:
                raise CameraFileError(f"{where}.{key} must be a positive integer, got {d[key]!r}")
        K = _matrix(d["K"], 3, 3, f"{where}.K")
        T = _matrix(d["cam_to_world"], 4, 4, f"{where}.cam_to_world")
        dist = Distortion.from_dict(d["distortion"], f"{where}.distortion") if d.get("distortion") is not None else None
        try:
            return cls(name=d["name"], width=d["width"], height=d["height"], K=K, cam_to_world=T, distortion=dist)
        except CameraFileError as e:
            raise CameraFileError(f"{where}: {e}") from None


def _json_type(v: object) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "a list"
    if isinstance(v, Mapping):
        return "an object"
    return type(v).__name__


def _matrix(value: object, rows: int, cols: int, what: str) -> np.ndarray:
    """A ``rows × cols`` JSON list of lists of numbers as a float64 array, or a CameraFileError."""
    ok = (
        isinstance(value, list)
        and len(value) == rows
        and all(
            isinstance(row, list)
            and len(row) == cols
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in row)
            for row in value
        )
    )
    if not ok:
        raise CameraFileError(f"{what} must be a {rows}x{cols} matrix of numbers")
    return np.array(value, dtype=np.float64)


# ------------------------------------------------------------------------------------ CameraSet
@dataclass
class CameraSet:
    """Cameras sharing one world frame.

    Attributes:
        cameras: at least one camera, names unique.
        scale: ``"relative"`` if the world is known up to scale, ``"metric"`` if in metres.
        world: name of the world frame (``"camera_0"``: the first camera's frame;
            ``"colmap"``/``"nerfstudio"`` for worlds imported from those tools).
        convention: always ``"opencv"`` (class constant).
        pose_confidence: how far the estimated relative pose can be trusted, for the cameras a reconstruction
            wrote (``score`` in [0, 1] or None, ``checks``, ``doubts``, ``accepted_low_confidence``;
            :meth:`macsplat_cli.pipeline.pose.PoseResult.camera_confidence`); None otherwise. Written as the file's
            ``"pose_confidence"`` entry when set, read back as it is (a JSON object).
        unregistered: photos of the reconstruction that could not be registered (``name``, ``width``,
            ``height``, ``reason``): written after the cameras in ``"cameras"`` with ``"registered": false`` and
            no pose; read back into this list, never as cameras.
        undistorted: camera name → the distortion its photo had (:meth:`Distortion.to_dict`), for the cameras
            whose photos were undistorted to their pinhole ``K`` before use; the file's ``"undistorted"`` entry
            (written when not empty).
    """

    cameras: list[Camera]
    scale: Scale = "relative"
    world: str = "camera_0"
    pose_confidence: dict[str, Any] | None = None
    unregistered: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    undistorted: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    convention: ClassVar[str] = "opencv"

    def __post_init__(self) -> None:
        self.cameras = list(self.cameras)
        if not self.cameras:
            raise CameraFileError("a camera set needs at least one camera")
        for i, cam in enumerate(self.cameras):
            if not isinstance(cam, Camera):
                raise CameraFileError(f"cameras[{i}] is a {type(cam).__name__}, not a Camera")
        names = [cam.name for cam in self.cameras]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            repeated = ", ".join(map(repr, duplicates))
            raise CameraFileError(f"camera names must be unique; repeated: {repeated}")
        if self.scale not in _SCALES:
            raise CameraFileError(f"scale must be 'relative' or 'metric', got {self.scale!r}")
        if not isinstance(self.world, str):
            raise CameraFileError(f"world must be a string, got {type(self.world).__name__}")
        if self.pose_confidence is not None and not isinstance(self.pose_confidence, Mapping):
            raise CameraFileError(f"pose_confidence must be an object, got {_json_type(self.pose_confidence)}")

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, index: int) -> Camera:
        return self.cameras[index]

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict in the file format of the module docstring."""
        out: dict[str, Any] = {
            "convention": self.convention,
            "world": self.world,
            "scale": self.scale,
            "cameras": [cam.to_dict() for cam in self.cameras] + [to_jsonable(dict(u)) for u in self.unregistered],
        }
        if self.pose_confidence is not None:
            out["pose_confidence"] = to_jsonable(dict(self.pose_confidence))
        if self.undistorted:
            out["undistorted"] = {
                "note": "these cameras' photos were undistorted to the pinhole K given here before use",
                "cameras": to_jsonable(dict(self.undistorted)),
            }
        return out

    @classmethod
    def from_dict(cls, d: object, where: str = "cameras") -> CameraSet:
        """Parse the file format; ``where`` (usually the file name) prefixes error messages.

        ``convention`` and ``cameras`` are required; ``world`` defaults to
        ``"camera_0"`` and ``scale`` to ``"relative"``. Unknown keys are ignored.

        Raises:
            CameraFileError: the content does not follow the format.
        """
        if not isinstance(d, Mapping):
            raise CameraFileError(f"{where}: the top level must be an object, got {_json_type(d)}")
        if "convention" not in d:
            raise CameraFileError(f"{where}: missing key 'convention' (must be \"opencv\")")
        if d["convention"] != cls.convention:
            raise CameraFileError(
                f'{where}: convention must be "opencv" (x right, y down, z forward), got {d["convention"]!r}'
            )
        scale = d.get("scale", "relative")
        if scale not in _SCALES:
            raise CameraFileError(f'{where}: scale must be "relative" or "metric", got {scale!r}')
        world = d.get("world", "camera_0")
        if not isinstance(world, str):
            raise CameraFileError(f"{where}: world must be a string, got {_json_type(world)}")
        if "cameras" not in d:
            raise CameraFileError(f"{where}: missing key 'cameras'")
        cams = d["cameras"]
        if not isinstance(cams, list) or not cams:
            raise CameraFileError(f"{where}: cameras must be a non-empty list of camera objects")
        left = [dict(c) for c in cams if isinstance(c, Mapping) and c.get("registered") is False]
        cameras = [Camera.from_dict(c, f"{where}: cameras[{i}]") for i, c in enumerate(cams)
                   if not (isinstance(c, Mapping) and c.get("registered") is False)]  # fmt: skip
        if not cameras:
            raise CameraFileError(f"{where}: no registered camera")
        confidence = d.get("pose_confidence")
        if confidence is not None and not isinstance(confidence, Mapping):
            raise CameraFileError(f"{where}: pose_confidence must be an object, got {_json_type(confidence)}")
        note = d.get("undistorted")
        undistorted = note.get("cameras") if isinstance(note, Mapping) else None
        try:
            return cls(cameras=cameras, scale=scale, world=world,
                       pose_confidence=dict(confidence) if confidence is not None else None, unregistered=left,
                       undistorted=dict(undistorted) if isinstance(undistorted, Mapping) else {})  # fmt: skip
        except CameraFileError as e:
            raise CameraFileError(f"{where}: {e}") from None


# ------------------------------------------------------------------------------------ JSON files
def _read_json(path: Path) -> Any:
    """Parse a camera file: a regular file of at most 32 MiB, nested at most 64 levels (:mod:`._limits`)."""
    return read_json_file(path, CameraFileError, "a camera file")


def _write_text(path: str | os.PathLike[str], text: str) -> None:
    try:
        atomic_write_text(path, text)
    except OSError as e:
        raise OutputPathError(f"cannot write {path}: {e.strerror or e}") from e


def load_cameras(path: str | os.PathLike[str]) -> CameraSet:
    """Load a ``cameras.json`` file (format in the module docstring).

    Raises:
        CameraFileError: the file is missing, not JSON, or does not follow the
            format; the one-line message names the file and the problem.
    """
    p = Path(path)
    return CameraSet.from_dict(_read_json(p), str(p))


def save_cameras(path: str | os.PathLike[str], camera_set: CameraSet) -> None:
    """Write ``camera_set`` to ``path`` as indented JSON, atomically.

    Floats are written with ``repr`` precision, so :func:`load_cameras` gives back
    exactly the same values.

    Raises:
        OutputPathError: ``path`` cannot be written.
    """
    _write_text(path, json.dumps(camera_set.to_dict(), indent=2) + "\n")


# ------------------------------------------------------------------------------------ cameras of photos
