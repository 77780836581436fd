"""Data-set types (:class:`EvalDataset` of :class:`EvalScene` s of :class:`Frame` s) and what every loader shares.

Loaders validate cheaply, before any evaluation work, with :func:`validate_scene`: every
file exists, every image's header is readable and its size matches its camera, depth maps
match their image size. Problems raise :class:`~macsplat_cli.errors.DatasetError` naming
the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np

from .._limits import read_json_file
from ..cameras import Camera, Scale
from ..errors import DatasetError, ImageReadError
from ..images import load_image

__all__ = [
    "LAYOUTS",
    "EvalDataset",
    "EvalScene",
    "Frame",
    "Layout",
    "image_size",
    "read_depth",
    "read_json",
    "resize_depth_nearest",
    "validate_scene",
]

Layout = Literal["auto", "generic", "scannetpp", "co3d-json", "icl-nuim", "nyu-rgbd"]
LAYOUTS: tuple[str, ...] = get_args(Layout)


@dataclass(frozen=True)
class Frame:
    """One posed image of a scene.

    Attributes:
        name: identifier, unique within the scene.
        image: the image file.
        camera: ground-truth camera at the image's own resolution (OpenCV axes, +0.5 pixel centres).
        depth: the depth map file (camera-space z), or None.
        depth_scale: factor from the stored integer values to scene units (ignored for float files).
    """

    name: str
    image: Path
    camera: Camera
    depth: Path | None = None
    depth_scale: float = 1.0


@dataclass
class EvalScene:
    """Frames sharing one world frame.

    Attributes:
        name: scene identifier.
        frames: at least three frames (two context views and a target).
        scale: ``"metric"`` when cameras and depth are in metres, else ``"relative"``.
    """

    name: str
    frames: list[Frame]
    scale: Scale = "relative"

    @property
    def has_depth(self) -> bool:
        """Every frame has a depth map."""
        return all(f.depth is not None for f in self.frames)

    def depth(self, index: int, size: tuple[int, int] | None = None) -> np.ndarray | None:
        """Depth of frame ``index`` in scene units (0 = none), optionally resized (nearest) to ``size`` = (W, H).

        Returns:
            ``[H, W]`` float32, or None when the frame has no depth.
        """
        f = self.frames[index]
        if f.depth is None:
            return None
        d = read_depth(f.depth, f.depth_scale)
        if d.shape != (f.camera.height, f.camera.width):
            raise DatasetError(
                f"{f.depth}: depth is {d.shape[1]}x{d.shape[0]}, but its image is {f.camera.width}x{f.camera.height}"
            )
        return resize_depth_nearest(d, *size) if size is not None else d

    def rgb(self, index: int, size: tuple[int, int] | None = None) -> np.ndarray:
        """Colour of frame ``index`` in [0, 1], optionally resized (area) to ``size`` = (W, H). [H, W, 3]"""
        f = self.frames[index]
        try:
            img = load_image(f.image).rgb
        except ImageReadError as e:
            raise DatasetError(str(e)) from None
        if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
            img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img, np.float32)


@dataclass
class EvalDataset:
    """Scenes read from one folder."""

    root: Path
    layout: str
    scenes: list[EvalScene] = field(default_factory=list)

    def scene(self, name: str) -> EvalScene:
        for s in self.scenes:
            if s.name == name:
                return s
        raise DatasetError(f"{self.root}: no scene named {name!r}")


# ------------------------------------------------------------------------------------ helpers
def read_depth(path: str | os.PathLike[str], scale: float = 1.0) -> np.ndarray:
    """A depth map: ``.npy`` (float), or an image file (16-bit integers × ``scale``, float as is). [H, W] float32

    Non-finite and negative values become 0 (no depth).

    Raises:
        DatasetError: the file is missing or not a depth map.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: depth map not found")
    try:
        if p.suffix.lower() == ".npy":
            raw = np.load(p, allow_pickle=False)
        else:
            raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    except (OSError, ValueError, cv2.error) as e:
        raise DatasetError(f"{p}: cannot read the depth map ({e})") from None
    if raw is None or raw.ndim != 2:
        raise DatasetError(f"{p}: not a single-channel depth map")
    d = raw.astype(np.float32) * np.float32(scale) if np.issubdtype(raw.dtype, np.integer) else raw.astype(np.float32)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def resize_depth_nearest(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize that samples at pixel centres (no averaging across depth edges). [H, W] → [h, w]

    Output pixel ``(i, j)`` takes the input pixel containing the point ``((j + 0.5)·W/w, (i + 0.5)·H/h)``.
    """
    H, W = depth.shape
    if (W, H) == (width, height):
        return depth
    xs = np.minimum(((np.arange(width) + 0.5) * W / width).astype(np.intp), W - 1)
    ys = np.minimum(((np.arange(height) + 0.5) * H / height).astype(np.intp), H - 1)
    return np.ascontiguousarray(depth[ys[:, None], xs[None, :]])


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image as displayed (EXIF orientation applied), from its header."""
    if not path.is_file():
        raise DatasetError(f"{path}: image not found")
    try:
        from PIL import Image

        with Image.open(path) as im:
            w, h = im.size
            orientation = int(im.getexif().get(0x0112, 1) or 1)
    except Exception as e:  # noqa: BLE001 - Pillow raises many types for a broken header
        raise DatasetError(f"{path}: not a readable image ({type(e).__name__}: {e})") from None
    return (h, w) if orientation in (5, 6, 7, 8) else (w, h)


def _depth_size(path: Path) -> tuple[int, int]:
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as e:
            raise DatasetError(f"{path}: not a readable .npy depth map ({e})") from None
        if arr.ndim != 2:
            raise DatasetError(f"{path}: depth must be a 2D array, got shape {list(arr.shape)}")
        return int(arr.shape[1]), int(arr.shape[0])
    return image_size(path)


def read_json(path: Path) -> Any:
    """A JSON document. Raises DatasetError naming the file when it is missing, malformed, too large (32 MiB) or
    nested too deeply (:func:`~macsplat_cli._limits.read_json_file`)."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    return read_json_file(path, DatasetError)


def validate_scene(scene: EvalScene, where: Path) -> EvalScene:
    """Files exist, image and depth sizes match the cameras, at least three frames."""
    if len(scene.frames) < 3:
        raise DatasetError(f"{where}: scene {scene.name!r} has {len(scene.frames)} frame(s); at least 3 are needed")
    names = [f.name for f in scene.frames]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise DatasetError(f"{where}: frame names repeated in scene {scene.name!r}: {', '.join(dup)}")
    for f in scene.frames:
        size = image_size(f.image)
        cam = (f.camera.width, f.camera.height)
        if size != cam:
            raise DatasetError(
                f"{f.image}: the image is {size[0]}x{size[1]}, but its camera {f.camera.name!r} is {cam[0]}x{cam[1]}"
            )
        if f.depth is not None:
            if not f.depth.is_file():
                raise DatasetError(f"{f.depth}: depth map not found")
            dsize = _depth_size(f.depth)
            if dsize != size:
                raise DatasetError(
                    f"{f.depth}: depth is {dsize[0]}x{dsize[1]}, but {f.image.name} is {size[0]}x{size[1]}"
                )
    return scene
