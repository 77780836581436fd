"""Undistortion of ScanNet++ images and depth maps to pinhole cameras, written once to a cache folder.

**New camera.** For ``OPENCV_FISHEYE`` lenses (the DSLR) the recipe of the official toolkit
(``dslr/undistort.py``), so the intrinsics equal those of ``transforms_undistorted.json``: same
size, ``fx, fy`` from ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify`` (identity
rectification, ``balance=0``: no invalid border), principal point forced to the image centre
``(W/2, H/2)``. For ``OPENCV`` lenses (iPhone COLMAP models) the same ``K``.

**Pixel convention.** ``K`` follows :class:`~macsplat_cli.cameras.Camera` (pixel centres at
+0.5); OpenCV's remapping functions put centres on integers, so ``cx, cy`` are shifted by −0.5
for them (the toolkit passes ``K`` unshifted, which moves its images by at most
``0.5·|f/f' − 1|`` px; its intrinsics, not its pixels, are reproduced here).

**Resampling.** Images: bilinear, ``BORDER_REFLECT_101`` (as the toolkit). Depth (uint16 mm):
nearest neighbour, constant 0 border.

**Cache.** ``<scene>/<sensor>/macsplat_undistorted/`` when that folder can be written, else
``$XDG_CACHE_HOME/macsplat/scannetpp/<hash of the sensor folder>/`` (``~/.cache`` without
``XDG_CACHE_HOME``). ``params.json`` records the lenses; a file is written when it is missing,
older than its source or the lens changed, atomically (parallel readers never see half a file).
The cache folder and its ``images/``/``depth/`` are never written through a symbolic link (a data set
could plant one pointing anywhere): the local folder is then not used, a link below it is refused.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import cv2
import numpy as np

from ..._atomic import atomic_write_bytes, atomic_write_text
from ...errors import DatasetError, OutputPathError
from ..base import resize_depth_nearest
from .poses import Lens

__all__ = ["CACHE_FOLDER", "UndistortCache", "cache_root", "pinhole_K", "undistort_maps"]

logger = logging.getLogger(__name__)

CACHE_FOLDER = "macsplat_undistorted"
_CACHE_VERSION = 1


def _cv(K: np.ndarray) -> np.ndarray:
    """``K`` with pixel centres on integers (OpenCV). [3, 3]"""
    Kc = np.array(K, dtype=np.float64)
    Kc[0, 2] -= 0.5
    Kc[1, 2] -= 0.5
    return Kc


def pinhole_K(lens: Lens) -> np.ndarray:
    """The pinhole ``K`` (pixel centres at +0.5) that :func:`undistort_maps` undistorts ``lens`` to. [3, 3]"""
    if not lens.distorted:
        return np.array(lens.K, dtype=np.float64)
    if lens.model == "OPENCV_FISHEYE":
        D = np.array(lens.dist, dtype=np.float64).reshape(4, 1)
        new = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            lens.K, D, (lens.width, lens.height), np.eye(3), balance=0.0
        )
        K = np.array(new, dtype=np.float64)
        K[0, 1], K[1, 0], K[2] = 0.0, 0.0, (0.0, 0.0, 1.0)
        K[0, 2], K[1, 2] = lens.width / 2.0, lens.height / 2.0
        return K
    return np.array(lens.K, dtype=np.float64)


def undistort_maps(lens: Lens) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.remap`` maps from the pinhole image of :func:`pinhole_K` into the distorted image.

    Returns:
        ``map_x``, ``map_y`` ([H, W] float32, distorted-image coordinates, integer centres) and
        the new ``K`` [3, 3].
    """
    K_new = pinhole_K(lens)
    size = (lens.width, lens.height)
    if lens.model == "OPENCV_FISHEYE":
        D = np.array(lens.dist, dtype=np.float64).reshape(4, 1)
        mx, my = cv2.fisheye.initUndistortRectifyMap(_cv(lens.K), D, np.eye(3), _cv(K_new), size, cv2.CV_32FC1)
    else:
        D = np.array(lens.dist, dtype=np.float64)
        mx, my = cv2.initUndistortRectifyMap(_cv(lens.K), D, np.eye(3), _cv(K_new), size, cv2.CV_32FC1)
    return mx, my, K_new


def cache_root(sensor_dir: Path) -> Path:
    """Where the undistorted files of ``sensor_dir`` (a scene's ``dslr/`` or ``iphone/``) go (see module doc)."""
    local = sensor_dir / CACHE_FOLDER
    if not local.is_symlink() and _writable(local):  # a link planted in the data set is not written through
        return local
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    digest = hashlib.sha1(str(sensor_dir.resolve()).encode("utf-8")).hexdigest()[:16]
    return base / "macsplat" / "scannetpp" / f"{sensor_dir.parent.name}_{sensor_dir.name}_{digest}"


def _writable(folder: Path) -> bool:
    """``folder`` exists and can be written, or can be created (checked without creating it)."""
    target = folder if folder.exists() else folder.parent
    return target.is_dir() and os.access(target, os.W_OK | os.X_OK)


def _fresh(out: Path, src: Path) -> bool:
    try:
        return out.stat().st_mtime_ns >= src.stat().st_mtime_ns
    except OSError:
        return False


class UndistortCache:
    """Undistorted copies of one sensor folder's images and depth maps.

    Args:
        sensor_dir: the scene's ``dslr/`` or ``iphone/`` folder.
        root: the cache folder (default :func:`cache_root`).
    """

    def __init__(self, sensor_dir: Path, root: Path | None = None) -> None:
        self.sensor_dir = sensor_dir
        self.root = root if root is not None else cache_root(sensor_dir)
        self._maps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._params_path = self.root / "params.json"
        self._params = self._read_params()
        self._dirty = False
        self.written = 0

    def _read_params(self) -> dict[str, object]:
        try:
            p = json.loads(self._params_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {"version": _CACHE_VERSION, "files": {}}
        if not isinstance(p, dict) or p.get("version") != _CACHE_VERSION or not isinstance(p.get("files"), dict):
            return {"version": _CACHE_VERSION, "files": {}}
        return p

    def _lens_maps(self, lens: Lens) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = json.dumps(lens.key(), sort_keys=True)
        if key not in self._maps:
            self._maps[key] = undistort_maps(lens)
        return self._maps[key]

    def _up_to_date(self, out: Path, src: Path, lens: Lens) -> bool:
        files = self._params["files"]
        assert isinstance(files, dict)
        return files.get(out.name if out.parent.name == "images" else f"depth/{out.name}") == lens.key() and _fresh(
            out, src
        )

    def _record(self, out: Path, lens: Lens) -> None:
        files = self._params["files"]
        assert isinstance(files, dict)
        files[out.name if out.parent.name == "images" else f"depth/{out.name}"] = lens.key()
        self._dirty = True
        self.written += 1

    def _write(self, out: Path, data: bytes) -> None:
        """Write a cache file atomically, never through a link among the cache's own folders."""
        for folder in (self.root, out.parent):
            if folder.is_symlink():
                raise OutputPathError(
                    f"{folder}: the undistortion cache folder is a symbolic link; refusing to write through it "
                    "(remove the link)"
                )
        atomic_write_bytes(out, data)

    def image(self, src: Path, lens: Lens) -> tuple[Path, np.ndarray]:
        """The undistorted image of ``src`` (written if needed) and its pinhole ``K`` [3, 3].

        Raises:
            DatasetError: ``src`` is missing or unreadable, or its size is not the lens's.
            OutputPathError: the cache cannot be written.
        """
        mx, my, K_new = self._lens_maps(lens)
        out = self.root / "images" / src.name
        if self._up_to_date(out, src, lens):
            return out, K_new
        if not src.is_file():
            raise DatasetError(f"{src}: image not found")
        img = cv2.imread(str(src), cv2.IMREAD_COLOR)
        if img is None:
            raise DatasetError(f"{src}: not a readable image")
        if img.shape[:2] != (lens.height, lens.width):
            raise DatasetError(
                f"{src}: the image is {img.shape[1]}x{img.shape[0]}, but its camera is {lens.width}x{lens.height}"
            )
        und = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        ok, buf = cv2.imencode(out.suffix if out.suffix else ".png", und)
        if not ok:  # pragma: no cover - OpenCV encodes every image suffix it decodes
            raise OutputPathError(f"{out}: OpenCV could not encode the image")
        self._write(out, buf.tobytes())
        self._record(out, lens)
        return out, K_new

    def depth(self, src: Path, lens: Lens) -> Path:
        """The undistorted uint16 depth map of ``src`` (written if needed).

        A depth map of another size than the lens (the iPhone's 256×192 LiDAR) is first
        resized to the lens size, nearest neighbour.

        Raises:
            DatasetError: ``src`` is missing or not a single-channel 16-bit image.
        """
        out = self.root / "depth" / f"{src.stem}.png"
        if self._up_to_date(out, src, lens):
            return out
        d = cv2.imread(str(src), cv2.IMREAD_UNCHANGED) if src.is_file() else None
        if d is None or d.ndim != 2:
            raise DatasetError(f"{src}: not a readable single-channel depth map")
        if d.shape != (lens.height, lens.width):
            d = resize_depth_nearest(d, lens.width, lens.height)
        if lens.distorted:
            mx, my, _ = self._lens_maps(lens)
            d = cv2.remap(d, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(d.astype(np.uint16)))
        if not ok:  # pragma: no cover
            raise OutputPathError(f"{out}: OpenCV could not encode the depth map")
        self._write(out, buf.tobytes())
        self._record(out, lens)
        return out

    def close(self) -> None:
        """Write ``params.json`` when files were added."""
        if self._dirty:
            atomic_write_text(self._params_path, json.dumps(self._params, indent=1))
            self._dirty = False
            logger.info("%s: %d undistorted file(s) written to %s", self.sensor_dir, self.written, self.root)
