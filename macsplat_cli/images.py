"""Writing rendered images, depth maps and videos (atomically)."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from ._atomic import atomic_path, atomic_write_bytes
from .errors import InputError, OutputPathError

__all__ = [
    "DEPTH_FORMATS",
    "IMAGE_FORMATS",
    "VIDEO_FORMATS",
    "save_depth",
    "save_image",
    "to_uint8",
    "write_video",
]

logger = logging.getLogger(__name__)

IMAGE_FORMATS = (".png", ".jpg", ".jpeg", ".webp", ".tif", ".tiff", ".bmp")
DEPTH_FORMATS = (".npy", ".png", ".tif", ".tiff")
VIDEO_FORMATS = (".mp4", ".gif")
DEPTH_PNG_SCALE = 1000.0
"""16-bit depth PNGs store ``round(depth · 1000)``: millimetres for a metric scene."""


def _suffix(path: str | os.PathLike[str], allowed: Sequence[str], what: str) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise InputError(f"{path}: unsupported {what} format {suffix or '(none)'!r}; use one of {', '.join(allowed)}")
    return suffix


def check_image_path(path: str | os.PathLike[str]) -> None:
    """Raise :class:`InputError` if ``path`` does not name a supported image format."""
    _suffix(path, IMAGE_FORMATS, "image")


def to_uint8(rgb: torch.Tensor | np.ndarray) -> np.ndarray:
    """Float colour in [0, 1] → 8-bit, clamped and rounded. ``[H, W, 3]`` → ``[H, W, 3] uint8``"""
    if isinstance(rgb, torch.Tensor):
        rgb = rgb.detach().cpu().float().numpy()
    arr = np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0)
    return np.clip(np.rint(arr * 255.0), 0, 255).astype(np.uint8)


def _encode(ext: str, bgr: np.ndarray, path: str | os.PathLike[str]) -> bytes:
    ok, buf = cv2.imencode(ext, bgr)
    if not ok:  # pragma: no cover - OpenCV supports every format listed
        raise OutputPathError(f"{path}: OpenCV could not encode a {ext} image")
    return buf.tobytes()


def save_image(path: str | os.PathLike[str], rgb: torch.Tensor | np.ndarray) -> Path:
    """Write an RGB image (float in [0, 1] or uint8) atomically; format from the suffix. ``[H, W, 3]``"""
    ext = _suffix(path, IMAGE_FORMATS, "image")
    arr = rgb if isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 else to_uint8(rgb)
    return atomic_write_bytes(path, _encode(ext, np.ascontiguousarray(arr[..., ::-1]), path))


def save_depth(path: str | os.PathLike[str], depth: torch.Tensor | np.ndarray) -> Path:
    """Write a depth map atomically; 0 marks pixels without depth. ``[H, W]``

    * ``.npy``: float32 depth in scene units.
    * ``.tif``/``.tiff``: float32 depth in scene units.
    * ``.png``: 16-bit, ``round(depth · 1000)`` (millimetres when the scene is metric);
      values above 65.535 scene units are clipped, with a warning.
    """
    ext = _suffix(path, DEPTH_FORMATS, "depth")
    if isinstance(depth, torch.Tensor):
        depth = depth.detach().cpu().float().numpy()
    d = np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if ext == ".npy":
        with atomic_path(path) as tmp:
            np.save(tmp, d)
        return Path(path)
    if ext == ".png":
        scaled = np.rint(d * DEPTH_PNG_SCALE)
        n_clip = int((scaled > 65535).sum())
        if n_clip:
            logger.warning(
                "%s: %d pixel(s) deeper than %.3f scene units were clipped (16-bit PNG stores depth x %g)",
                path,
                n_clip,
                65535 / DEPTH_PNG_SCALE,
                DEPTH_PNG_SCALE,
            )
        return atomic_write_bytes(path, _encode(ext, np.clip(scaled, 0, 65535).astype(np.uint16), path))
    return atomic_write_bytes(path, _encode(ext, d, path))


def write_video(path: str | os.PathLike[str], frames: Sequence[np.ndarray], fps: float = 24.0) -> Path:
    """Write ``[H, W, 3] uint8`` RGB frames as ``.mp4`` (MPEG-4 Part 2) or ``.gif``, atomically."""
    ext = _suffix(path, VIDEO_FORMATS, "video")
    if not frames:
        raise InputError(f"{path}: no frames to write")
    with atomic_path(path) as tmp:
        if ext == ".gif":
            from PIL import Image

            images = [Image.fromarray(f) for f in frames]
            images[0].save(tmp, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
        else:
            h, w = frames[0].shape[:2]
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
            if not writer.isOpened():
                raise OutputPathError(f"{path}: OpenCV could not open an MPEG-4 video writer")
            try:
                for f in frames:
                    writer.write(np.ascontiguousarray(f[..., ::-1]))
            finally:
                writer.release()
    return Path(path)
