"""Stage 1: the two photos at the working resolution, with intrinsics.

Working size: the long side is scaled to ``size`` (never up), then each side is rounded
to a multiple of 16, the backbone's patch size, so the classical and neural backends see
the same pixels; the aspect ratio may change by < 3 %, and K is scaled per axis, which is
exact with pixel centres at +0.5.

Intrinsics, in order of precedence:

1. ``--intrinsics cams.json`` (the cameras schema): one camera for every photo, or one
   per photo (matched by name; in order only when no camera is named after a photo:
   :func:`~macsplat_cli.camera_formats.cameras_for_photos`), rescaled to the working size. A camera
   whose aspect ratio differs from its photo's by more than 1 % does not fit. A camera with lens distortion has
   its photo undistorted to its pinhole K first (:mod:`.undistort`).
2. ``--focal PX``: the focal length in pixels of the original photos.
3. The EXIF 35 mm-equivalent focal length.
4. A 60° field of view across the long side (``prior``), which the pose stage refines
   from the matches where the geometry allows (then reported as ``estimated``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..camera_formats import cameras_for_photos, load_camera_input
from ..cameras import Camera
from ..errors import CameraFileError, ImageReadError, InputError
from ..images import LoadedImage, load_image
from .types import IntrinsicsSource, View
from .undistort import undistort_photo

__all__ = ["MIN_IMAGE_SIDE", "ViewConfig", "load_views", "prior_focal", "working_size"]

logger = logging.getLogger(__name__)

MIN_IMAGE_SIDE = 64
PATCH = 16
DETAIL_SIZE = 1024


@dataclass
class ViewConfig:
    """Args:
    size: long side of the working images, in pixels (rounded to a multiple of 16).
    intrinsics: a cameras-schema file with the photos' intrinsics.
    focal: focal length in pixels of the original photos.
    prior_fov_deg: field of view across the long side when nothing else is known.
    use_exif: use the EXIF 35 mm-equivalent focal length when present.
    """

    size: int = 512
    intrinsics: Path | None = None
    focal: float | None = None
    prior_fov_deg: float = 60.0
    use_exif: bool = True


def working_size(width: int, height: int, size: int) -> tuple[int, int]:
    """(W', H'): long side scaled to ``size`` (never up), sides rounded to multiples of 16.

    Each side is rounded to the nearest multiple of 16, or down when rounding up would
    exceed the photo's own size.
    """
    s = min(1.0, size / max(width, height))

    def side(n: int) -> int:
        r = int(round(n * s / PATCH)) * PATCH
        if r > n:
            r = (n // PATCH) * PATCH
        return max(PATCH, r)

    return side(width), side(height)


def prior_focal(width: int, height: int, fov_deg: float = 60.0) -> float:
    """Focal length (pixels) giving ``fov_deg`` across the long side."""
    return max(width, height) / (2.0 * math.tan(math.radians(fov_deg) / 2.0))


def _K(f: float, width: int, height: int) -> np.ndarray:
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _file_cameras(path: Path, images: Sequence[LoadedImage]) -> list[Camera]:
    """One camera for every photo, or each photo's own (:func:`~macsplat_cli.camera_formats.cameras_for_photos`)."""
    cams = load_camera_input(path)  # a cameras file or a COLMAP model folder
    if len(cams) == 1:
        return [cams[0]] * len(images)
    return cameras_for_photos(cams, [img.path for img in images], path)


def _fit(cam: Camera, img: LoadedImage, path: Path) -> None:
    a_cam, a_img = cam.width / cam.height, img.width / img.height
    if abs(a_cam - a_img) / a_img > 0.01:
        hint = " (rotated? EXIF orientation is applied to the photo)" if abs(1 / a_cam - a_img) / a_img < 0.01 else ""
        raise CameraFileError(
            f"{path}: camera {cam.name!r} is for a {cam.width}x{cam.height} image, but {img.path.name} is "
            f"{img.width}x{img.height}{hint}: the intrinsics do not fit"
        )
    cx, cy = cam.K[0, 2] / cam.width, cam.K[1, 2] / cam.height
    if not (0.0 < cx < 1.0 and 0.0 < cy < 1.0):
        raise CameraFileError(f"{path}: camera {cam.name!r} has its principal point outside the image")


def load_views(paths: Sequence[str | Path], config: ViewConfig | None = None) -> list[View]:
    """Read the photos and build :class:`View` s at the working resolution.

    Raises:
        ImageReadError: a photo is missing or not an image.
        InputError: a photo is smaller than 64 px on a side, or a bad ``--focal``.
        CameraFileError: the intrinsics file is malformed or does not fit the photos.
    """
    cfg = config or ViewConfig()
    images = [load_image(p) for p in paths]
    for img in images:
        if min(img.width, img.height) < MIN_IMAGE_SIDE:
            raise ImageReadError(
                f"{img.path}: {img.width}x{img.height} px is too small; at least {MIN_IMAGE_SIDE} px on each side "
                "are needed"
            )
    file_cams = _file_cameras(cfg.intrinsics, images) if cfg.intrinsics is not None else None
    if cfg.focal is not None and not (math.isfinite(cfg.focal) and cfg.focal > 0):
        raise InputError(f"--focal must be a positive number of pixels, got {cfg.focal}")
    views = []
    for i, img in enumerate(images):
        w, h = working_size(img.width, img.height, cfg.size)
        source: IntrinsicsSource
        if file_cams is not None and cfg.intrinsics is not None:  # both or neither
            _fit(file_cams[i], img, cfg.intrinsics)
            img = undistort_photo(img, file_cams[i])  # a pinhole photo from here on (same K)
            K = file_cams[i].rescaled(w, h).K.copy()
            source = "file"
        else:
            exif_f = img.focal_px_from_exif() if cfg.use_exif else None
            if cfg.focal is not None:
                f, source = cfg.focal, "focal"
            elif exif_f is not None:
                f, source = exif_f, "exif"
            else:
                f, source = prior_focal(img.width, img.height, cfg.prior_fov_deg), "prior"
            K = _K(f, img.width, img.height)
            K[0] *= w / img.width
            K[1] *= h / img.height
        rgb = (
            cv2.resize(img.rgb, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (img.width, img.height) else img.rgb
        )
        if img.alpha is not None:
            alpha = cv2.resize(img.alpha, (w, h), interpolation=cv2.INTER_AREA)
            mask = alpha >= 0.5
        else:
            mask = np.ones((h, w), bool)
        name = img.path.stem
        s_detail = min(1.0, DETAIL_SIZE / max(img.width, img.height))
        detail = img.rgb
        if s_detail < 1.0:
            size_d = (round(img.width * s_detail), round(img.height * s_detail))
            detail = cv2.resize(img.rgb, size_d, interpolation=cv2.INTER_AREA)
        views.append(
            View(
                name,
                img.path,
                np.ascontiguousarray(rgb, np.float32),
                mask,
                K,
                (img.width, img.height),
                source,
                detail=detail,
                undistorted=file_cams[i].distortion if file_cams is not None and img is not images[i] else None,
            )  # fmt: skip
        )
        logger.debug("%s: %dx%d → %dx%d, intrinsics from %s", img.path.name, img.width, img.height, w, h, source)
    if len(views) == 2 and views[0].name == views[1].name:
        views[1].name = views[1].name + "_1"
    return views
