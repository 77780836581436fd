"""Data-set types (:class:`EvalDataset` of :class:`EvalScene` s of :class:`Frame` s) and what every loader shares.

Loaders validate cheaply, before any evaluation work, with :func:`validate_scene`: every
file exists, every image's header is readable (no pixel is decoded), its size matches its camera
and is within the photo limits, no two frames share an image, depth maps match their image size,
and no file leads out of the data set. Problems raise :class:`~macsplat_cli.errors.DatasetError`
naming the file.

**What a data set may name.** A file name read from a data set's own files (a camera name of
``cameras.json``, an ``image`` of ``cameras_opencv.json``, a ScanNet++ frame or scene id) goes
through :func:`member_path`: it must be relative, without a ``..`` component, and (except where
a layout names files in subfolders) a plain file name without a path separator. And every file
read, links resolved, must lie inside the data set folder the user named (``--data``, itself
resolved: it may be a link) or macsplat's own undistortion cache (:func:`check_inside`): a link
inside the data set that leads out of it, to a file or to a folder (``images -> /elsewhere``), is
refused, so that a data set cannot make macsplat read ``/etc/passwd`` or photos it does not hold.
A data set whose files live elsewhere is read by pointing ``--data`` at a folder that holds them.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Literal, get_args

import cv2
import numpy as np

from .._limits import MAX_IMAGE_FILE_BYTES, MAX_MEGAPIXELS_ENV, max_image_pixels, read_json_file
from ..cameras import Camera, Scale
from ..errors import DatasetError, ImageReadError
from ..images import load_image

__all__ = [
    "LAYOUTS",
    "EvalDataset",
    "EvalScene",
    "Frame",
    "Layout",
    "check_inside",
    "image_size",
    "member_path",
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
    _check_depth_dtype(raw, p)
    d = raw.astype(np.float32) * np.float32(scale) if np.issubdtype(raw.dtype, np.integer) else raw.astype(np.float32)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


DEPTH_KINDS = "iuf"
"""The NumPy dtype kinds a depth map may hold: signed and unsigned integers, floats (not strings, objects, booleans,
complex numbers, dates or records)."""


def _check_depth_dtype(depth: np.ndarray, path: Path) -> None:
    """Raise DatasetError naming ``path`` unless ``depth`` holds numbers (:data:`DEPTH_KINDS`)."""
    if depth.dtype.kind not in DEPTH_KINDS or depth.dtype.fields is not None:
        raise DatasetError(f"{path}: not a numeric depth map (dtype {depth.dtype.str}); give integers or floats")


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


def member_path(folder: Path, name: object, what: str, *, subfolders: bool = False) -> Path:
    """``folder / name`` for a file name read from a data set's own files, refused where it could lead elsewhere.

    Args:
        folder: the folder the name is relative to.
        name: the name as read (any JSON value; it must be a string).
        what: where the name comes from, for the message (``"D/cameras.json: camera"``; the name follows).
        subfolders: the layout names files in subfolders of ``folder`` (``images/frame1.jpg``);
            otherwise the name must be a plain file name.

    Raises:
        DatasetError: the name is not a string, is empty or ``.``/``..``, holds a NUL character, is
            absolute (POSIX or Windows), has a ``..`` component, or (without ``subfolders``) a path
            separator (``/`` or ``\\``).
    """
    if not isinstance(name, str):
        raise DatasetError(f"{what} {name!r}: the file name must be a string")
    parts = re.split(r"[\\/]", name)
    bad = None
    if not name.strip() or name in (".", "..") or "\x00" in name:
        bad = "is not a file name"
    elif PurePosixPath(name).is_absolute() or PureWindowsPath(name).is_absolute() or PureWindowsPath(name).drive:
        bad = "is an absolute path"
    elif ".." in parts:
        bad = "has a '..' component"
    elif len(parts) > 1 and not subfolders:
        bad = "holds a path separator"
    if bad is not None:
        raise DatasetError(f"{what} {name!r} {bad}; a data set names its files by plain names inside {folder}")
    return folder / name


def check_inside(path: Path, roots: Sequence[Path], what: str) -> Path:
    """``path``, which must lie inside one of the folders ``roots`` once links are resolved (when it exists).

    Raises:
        DatasetError: a link (of the file or of a folder below a root) leads out of every root.
    """
    if not os.path.lexists(path):
        return path
    real = Path(os.path.realpath(path))
    if any(real == r or r in real.parents for r in (Path(os.path.realpath(r)) for r in roots)):
        return path
    shown = ", ".join(str(r) for r in roots)
    raise DatasetError(
        f"{path}: {what} leads to {real}, outside the data set ({shown}); a link out of the data set is not followed"
    )


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image as displayed (EXIF orientation applied), from its header (no pixel decoded)."""
    if not path.is_file():
        raise DatasetError(f"{path}: image not found")
    try:
        from PIL import Image

        saved = Image.MAX_IMAGE_PIXELS
        Image.MAX_IMAGE_PIXELS = None  # macsplat applies its own cap (validate_scene); Pillow's would hide the size
        try:
            with Image.open(path) as im:
                w, h = im.size
                orientation = int(im.getexif().get(0x0112, 1) or 1)
        finally:
            Image.MAX_IMAGE_PIXELS = saved
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
        _check_depth_dtype(arr, path)
        return int(arr.shape[1]), int(arr.shape[0])
    return image_size(path)


def read_json(path: Path) -> Any:
    """A JSON document. Raises DatasetError naming the file when it is missing, malformed, too large (32 MiB) or
    nested too deeply (:func:`~macsplat_cli._limits.read_json_file`)."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    return read_json_file(path, DatasetError)


def validate_scene(scene: EvalScene, where: Path, roots: Sequence[Path] | None = None) -> EvalScene:
    """Check a scene from its files' headers, before any evaluation work (nothing is decoded).

    At least three frames with distinct names; every image exists, its header is readable, its
    size (EXIF orientation applied) is its camera's, it is within the photo limits
    (``MACSPLAT_MAX_MEGAPIXELS``, 1 GiB per file), and no two frames use one image file (also
    through a link); depth maps exist and match their image's size; with ``roots``, every image
    and depth map lies, links resolved, inside one of these folders. O(N) in the number of
    frames, one header read per file.

    Raises:
        DatasetError: the first problem, naming the file (and the frames, for a shared image).
    """
    if len(scene.frames) < 3:
        raise DatasetError(f"{where}: scene {scene.name!r} has {len(scene.frames)} frame(s); at least 3 are needed")
    names = [f.name for f in scene.frames]
    dup = sorted({n for n in names if names.count(n) > 1}) if len(set(names)) != len(names) else []
    if dup:
        raise DatasetError(f"{where}: frame names repeated in scene {scene.name!r}: {', '.join(dup)}")
    limit = max_image_pixels()
    used: dict[object, str] = {}
    for f in scene.frames:
        for p in (f.image, f.depth):
            if p is not None and roots is not None:
                check_inside(p, roots, f"frame {f.name!r}")
        size = image_size(f.image)
        cam = (f.camera.width, f.camera.height)
        if size != cam:
            raise DatasetError(
                f"{f.image}: the image is {size[0]}x{size[1]}, but its camera {f.camera.name!r} is {cam[0]}x{cam[1]}"
            )
        st = f.image.stat()
        if st.st_size > MAX_IMAGE_FILE_BYTES:
            raise DatasetError(f"{f.image}: {st.st_size:,} bytes is too large for an image")
        if size[0] * size[1] > limit:
            raise DatasetError(
                f"{f.image}: {size[0]}x{size[1]} is {size[0] * size[1] / 1e6:.1f} megapixels, above the limit of "
                f"{limit / 1e6:g} megapixels (raise it with the environment variable {MAX_MEGAPIXELS_ENV})"
            )
        key = (st.st_dev, st.st_ino)
        if key in used:
            raise DatasetError(
                f"{where}: frames {used[key]!r} and {f.name!r} of scene {scene.name!r} use the same image file "
                f"{f.image}: each camera needs its own image"
            )
        used[key] = f.name
        if f.depth is not None:
            if not f.depth.is_file():
                raise DatasetError(f"{f.depth}: depth map not found")
            dsize = _depth_size(f.depth)
            if dsize != size:
                raise DatasetError(
                    f"{f.depth}: depth is {dsize[0]}x{dsize[1]}, but {f.image.name} is {size[0]}x{size[1]}"
                )
    return scene
