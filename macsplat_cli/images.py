"""Image I/O: reading photos (EXIF orientation and focal length, any bit depth) and
writing rendered images, depth maps and videos (atomically)."""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ._atomic import atomic_path, atomic_write_bytes
from ._limits import MAX_IMAGE_FILE_BYTES, MAX_MEGAPIXELS_ENV, check_regular_file, max_image_pixels
from .errors import ImageReadError, InputError, OutputPathError

__all__ = [
    "DEPTH_FORMATS",
    "IMAGE_FORMATS",
    "LoadedImage",
    "MAX_VIDEO_FPS",
    "MIN_VIDEO_FPS",
    "check_fps",
    "load_image",
    "VIDEO_FORMATS",
    "video_writer",
    "save_depth",
    "save_image",
    "to_uint8",
    "write_video",
]

logger = logging.getLogger(__name__)

IMAGE_FORMATS = (".png", ".jpg", ".jpeg", ".webp", ".tif", ".tiff", ".bmp")
DEPTH_FORMATS = (".npy", ".png", ".tif", ".tiff")
VIDEO_FORMATS = (".mp4", ".gif")
MAX_VIDEO_FPS = 240.0
"""Highest video frame rate: what players show, well within the MPEG-4 time base (its denominator is at most
65535; OpenCV's writer refuses more with native log lines, and never returns for an infinite rate)."""
MIN_VIDEO_FPS = 0.01
"""Lowest video frame rate, a frame every 100 s: a GIF frame lasts at most 655 s (Pillow overflows beyond) and
OpenCV's MPEG-4 writer does not open below 0.002."""
_FFMPEG_QUIET = "-8"
"""``OPENCV_FFMPEG_LOGLEVEL`` for the video writer: ffmpeg's ``AV_LOG_QUIET`` (macsplat reports a failure in one
line)."""
DEPTH_PNG_SCALE = 1000.0
"""16-bit depth PNGs store ``round(depth · 1000)``: millimetres for a metric scene."""


_EXIF_ORIENTATION = 0x0112
_EXIF_IFD = 0x8769
_EXIF_FOCAL_35MM = 0xA405
_FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


@dataclass
class LoadedImage:
    """A photo as read from disk, upright.

    Attributes:
        rgb: colour in [0, 1], EXIF orientation applied; grey images are replicated to
            three channels. [H, W, 3] float32
        alpha: opacity in [0, 1] when the file has an alpha channel, else None. [H, W] float32
        focal_35mm: EXIF FocalLengthIn35mmFilm in millimetres, if present and positive.
        bit_depth: bits per channel of the file (8 or 16; 32 for float TIFF).
        path: where it was read from.
    """

    rgb: np.ndarray
    alpha: np.ndarray | None
    focal_35mm: float | None
    bit_depth: int
    path: Path

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    def focal_px_from_exif(self) -> float | None:
        """Focal length in pixels of this image from the 35 mm equivalent, if known.

        The 35 mm equivalent is defined on the diagonal (CIPA DC-008), so
        ``f_px = f35 · diagonal_px / 43.27 mm``, which holds for any aspect ratio.
        """
        if self.focal_35mm is None:
            return None
        return self.focal_35mm * math.hypot(self.width, self.height) / _FULL_FRAME_DIAGONAL_MM


def _exif(data: bytes) -> tuple[int, float | None]:
    """(orientation 1..8, 35 mm focal or None) from a file's EXIF block; (1, None) if absent."""
    try:
        from PIL import Image

        with Image.open(io.BytesIO(data)) as im:
            exif = im.getexif()
            orientation = int(exif.get(_EXIF_ORIENTATION, 1) or 1)
            f35 = exif.get_ifd(_EXIF_IFD).get(_EXIF_FOCAL_35MM)
    except Exception:  # noqa: BLE001 - EXIF is optional metadata; a broken block is ignored
        return 1, None
    focal = float(f35) if isinstance(f35, (int, float)) and f35 > 0 else None
    return (orientation if 1 <= orientation <= 8 else 1), focal


def _apply_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels as displayed for EXIF orientation 1..8 (the transforms of ``ImageOps.exif_transpose``)."""
    swap = (1, 0) + tuple(range(2, img.ndim))
    out = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],  # mirror left-right
        3: lambda a: a[::-1, ::-1],  # rotate 180°
        4: lambda a: a[::-1],  # mirror top-bottom
        5: lambda a: a.transpose(swap),  # transpose
        6: lambda a: np.rot90(a, -1),  # rotate 90° clockwise
        7: lambda a: a[::-1, ::-1].transpose(swap),  # transverse
        8: lambda a: np.rot90(a, 1),  # rotate 90° counter-clockwise
    }[orientation](img)
    return np.ascontiguousarray(out)


def _pillow_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the image header (Pillow's lazy open decodes no pixels); None if Pillow cannot tell."""
    from PIL import Image

    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # macsplat applies its own cap; Pillow's would raise before giving the size
    try:
        with Image.open(io.BytesIO(data)) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception:  # noqa: BLE001 - not something Pillow reads: the headers below, else refused
        return None
    finally:
        Image.MAX_IMAGE_PIXELS = saved


_HEADER_PROBE = 4096
"""Bytes of a Radiance, PFM or PAM file searched for its size (their text headers are a few lines)."""


def _radiance_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) of a Radiance RGBE file: the line after the blank line ending its header, such as
    ``-Y 480 +X 640`` (Y first: rows of X; X first: the image is stored transposed)."""
    if not (head.startswith(b"#?RADIANCE") or head.startswith(b"#?RGBE")):
        return None
    end = head.find(b"\n\n")
    words = head[end + 2 :].split(b"\n", 1)[0].split() if end >= 0 else []
    if len(words) != 4 or not (words[1].isdigit() and words[3].isdigit()):
        return None
    sides = {words[0][-1:].upper(): int(words[1]), words[2][-1:].upper(): int(words[3])}
    return (sides[b"X"], sides[b"Y"]) if set(sides) == {b"X", b"Y"} else None


def _pfm_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) of a portable float map: ``PF`` or ``Pf``, then the width and the height."""
    words = head.split(maxsplit=3)
    if len(words) < 3 or words[0] not in (b"PF", b"Pf") or not (words[1].isdigit() and words[2].isdigit()):
        return None
    return int(words[1]), int(words[2])


def _pam_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) of a portable arbitrary map: ``P7``, then ``WIDTH w`` and ``HEIGHT h`` lines."""
    if not head.startswith(b"P7"):
        return None
    lines = head.split(b"ENDHDR", 1)[0].split(b"\n")
    fields = dict(line.split(None, 1) for line in lines if len(line.split()) == 2)
    w, h = fields.get(b"WIDTH", b"").strip(), fields.get(b"HEIGHT", b"").strip()
    return (int(w), int(h)) if w.isdigit() and h.isdigit() else None


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the image's header, without decoding it: Pillow's formats, and the ones OpenCV
    decodes that Pillow does not read (Radiance HDR, PFM, PAM). None when no header tells it."""
    size = _pillow_size(data)
    if size is None:
        head = data[:_HEADER_PROBE]
        size = _radiance_size(head) or _pfm_size(head) or _pam_size(head)
    return size


_ALPHA_MODES = frozenset({"LA", "La", "PA", "RGBA", "RGBa"})
"""Pillow modes with an alpha band."""


def _pil_alpha(data: bytes) -> np.ndarray | None:
    """The file's transparency as Pillow decodes it, in [0, 1], when it has any: an alpha band (``_ALPHA_MODES``)
    or a transparent colour or palette entry (PNG ``tRNS``, GIF). None otherwise or when Pillow cannot read it.
    [H, W] float32, as stored (before the EXIF orientation)"""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.mode not in _ALPHA_MODES and "transparency" not in im.info:
                return None
            return np.asarray(im.convert("RGBA"))[..., 3].astype(np.float32) / 255.0
    except Exception:  # noqa: BLE001 - OpenCV decoded the pixels; the alpha is only a refinement
        return None


def _check_pixel_count(p: Path, data: bytes) -> None:
    """Refuse an image whose header declares more pixels than ``MACSPLAT_MAX_MEGAPIXELS``, or whose header gives
    no size (:func:`_header_size`): the cap holds for every format OpenCV decodes."""
    size = _header_size(data)
    if size is None:  # OpenCV would decode it to whatever size it declares: refused before decoding
        raise ImageReadError(
            f"{p}: not an image macsplat reads (JPEG, PNG, WebP, TIFF, BMP, ...): its size cannot be read from its "
            "header before decoding"
        )
    w, h = size
    limit = max_image_pixels()
    if w * h > limit:
        raise ImageReadError(
            f"{p}: {w}x{h} is {w * h / 1e6:.1f} megapixels, above the limit of {limit / 1e6:g} megapixels "
            f"(raise it with the environment variable {MAX_MEGAPIXELS_ENV}, or downscale the photo)"
        )


def load_image(path: str | os.PathLike[str]) -> LoadedImage:
    """Read a JPEG/PNG/WebP/TIFF/BMP photo: EXIF orientation applied, any bit depth.

    Grey and grey+alpha images become RGB; 16-bit and float images keep their
    precision (scaled to [0, 1]); CMYK and YCCK JPEGs (Adobe's inverted CMYK) and palette
    images become their RGB colours; an alpha channel (also a grey+alpha TIFF's, or a PNG's
    transparent colour) is returned separately.

    The image's size is read from its header before it is decoded: images above
    ``MACSPLAT_MAX_MEGAPIXELS`` megapixels (default 100) are refused, so a small file that
    decodes to gigabytes (a "decompression bomb") fails fast; so is a file whose header gives
    no size (Pillow's formats, and Radiance HDR, PFM and PAM, which OpenCV decodes, are read).

    Raises:
        ImageReadError: the file is missing, not a regular file, unreadable, not a decodable
            image, larger than the megapixel cap, or of a size its header does not give.
        InputError: ``MACSPLAT_MAX_MEGAPIXELS`` is not a positive number.
    """
    p = Path(path)
    size = check_regular_file(p, ImageReadError, "an image")
    if size > MAX_IMAGE_FILE_BYTES:
        raise ImageReadError(f"{p}: {size:,} bytes is too large for an image (at most {MAX_IMAGE_FILE_BYTES:,} bytes)")
    try:
        with open(p, "rb") as f:
            data = f.read(MAX_IMAGE_FILE_BYTES + 1)
    except OSError as e:
        raise ImageReadError(f"{p}: cannot read ({e.strerror or e})") from None
    if not data:
        raise ImageReadError(f"{p}: the file is empty")
    if len(data) > MAX_IMAGE_FILE_BYTES:
        raise ImageReadError(f"{p}: too large for an image (at most {MAX_IMAGE_FILE_BYTES:,} bytes)")
    _check_pixel_count(p, data)
    try:
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error:  # some truncated files make OpenCV raise instead of returning None
        raw = None
    if raw is None or raw.size == 0:
        raise ImageReadError(f"{p}: not an image OpenCV can decode (JPEG, PNG, WebP, TIFF, BMP)")
    orientation, focal = _exif(data)
    if raw.dtype == np.uint8:
        scale, depth = 255.0, 8
    elif raw.dtype == np.uint16:
        scale, depth = 65535.0, 16
    elif raw.dtype in (np.float32, np.float64):
        scale, depth = 1.0, 32
    else:
        raise ImageReadError(f"{p}: unsupported pixel type {raw.dtype}")
    img = raw.astype(np.float32) / scale
    if img.ndim == 2:
        img = img[..., None]
    channels = img.shape[2]
    alpha = None
    if channels in (2, 4):
        alpha = np.clip(img[..., -1], 0.0, 1.0)
        img = img[..., :-1]
    if alpha is None:
        # OpenCV drops some files' transparency (a grey+alpha or palette+alpha TIFF, a grey PNG's transparent
        # colour); Pillow reads it
        alpha = _pil_alpha(data)
        if alpha is not None and alpha.shape != img.shape[:2]:
            alpha = None
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] == 3:
        img = img[..., ::-1]  # OpenCV decodes BGR
    else:
        raise ImageReadError(f"{p}: unsupported number of channels ({channels})")
    rgb = np.clip(np.nan_to_num(img, nan=0.0), 0.0, 1.0)
    rgb = _apply_orientation(rgb, orientation)
    if alpha is not None:
        alpha = _apply_orientation(alpha, orientation)
    return LoadedImage(rgb=rgb.astype(np.float32), alpha=alpha, focal_35mm=focal, bit_depth=depth, path=p)


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


def check_fps(fps: float) -> None:
    """Raise :class:`InputError` unless :data:`MIN_VIDEO_FPS` ``≤ fps ≤`` :data:`MAX_VIDEO_FPS` (a finite number)."""
    if not (math.isfinite(fps) and MIN_VIDEO_FPS <= fps <= MAX_VIDEO_FPS):
        raise InputError(f"--fps {fps:g}: give a frame rate from {MIN_VIDEO_FPS:g} to {MAX_VIDEO_FPS:g}")


@contextlib.contextmanager
def _native_log_silenced() -> Iterator[None]:
    """OpenCV's and its ffmpeg's own log lines off while the body runs (a failure is reported as one typed error).
    ffmpeg reads its level once, when OpenCV first loads it: the variable is set (unless the user set it) first."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", _FFMPEG_QUIET)
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


class _Mp4Frames:
    """MPEG-4 Part 2 frames sent to OpenCV's encoder as they come; the writer opens at the first frame's size."""

    def __init__(self, tmp: Path, path: str | os.PathLike[str], fps: float) -> None:
        self.tmp, self.path, self.fps = tmp, path, fps
        self.writer: cv2.VideoWriter | None = None
        self.count = 0

    def add(self, frame: np.ndarray) -> None:
        h, w = frame.shape[:2]
        with _native_log_silenced():
            if self.writer is None:
                self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter.fourcc(*"mp4v"), float(self.fps), (w, h))
                if not self.writer.isOpened():
                    raise OutputPathError(f"{self.path}: OpenCV could not open an MPEG-4 video writer for {w}x{h}")
            self.writer.write(np.ascontiguousarray(frame[..., ::-1]))
        self.count += 1

    def release(self) -> None:
        if self.writer is not None:
            with _native_log_silenced():
                self.writer.release()

    def finish(self) -> None:
        _check_video(self.tmp, self.path, self.count)


class _GifFrames:
    """GIF frames kept quantised to an adaptive 256-colour palette (one byte a pixel; what Pillow's GIF writer
    would make of them) and written at the end: Pillow needs them all at once."""

    def __init__(self, tmp: Path, fps: float) -> None:
        self.tmp, self.fps = tmp, fps
        self.frames: list = []

    def add(self, frame: np.ndarray) -> None:
        from PIL import Image

        self.frames.append(Image.fromarray(frame).convert("P", palette=Image.Palette.ADAPTIVE))

    def release(self) -> None:
        pass

    def finish(self) -> None:
        first, *rest = self.frames
        first.save(self.tmp, save_all=True, append_images=rest, duration=round(1000 / self.fps), loop=0)


@contextlib.contextmanager
def video_writer(path: str | os.PathLike[str], fps: float = 24.0) -> Iterator[Callable[[np.ndarray], None]]:
    """A video written frame by frame: yields ``add(frame)`` for ``[H, W, 3] uint8`` RGB frames of one size.

    The frames go into a temporary file beside ``path`` (:func:`~macsplat_cli._atomic.atomic_path`), moved onto
    ``path`` when the block ends without an error; nothing is left otherwise. An ``.mp4`` (MPEG-4 Part 2) is
    encoded as the frames come and holds none of them; a ``.gif`` keeps them, quantised (one byte a pixel),
    until the end (:data:`~macsplat_cli._limits.MAX_GIF_BYTES` bounds them).

    Raises:
        InputError: an unsupported format, a frame rate outside [:data:`MIN_VIDEO_FPS`, :data:`MAX_VIDEO_FPS`], or
            no frame.
        OutputPathError: the video cannot be written, or came out unreadable.
    """
    ext = _suffix(path, VIDEO_FORMATS, "video")
    check_fps(fps)
    with atomic_path(path) as tmp:
        sink = _Mp4Frames(tmp, path, fps) if ext == ".mp4" else _GifFrames(tmp, fps)
        try:
            yield sink.add
        finally:
            sink.release()
        if not (sink.count if isinstance(sink, _Mp4Frames) else sink.frames):
            raise InputError(f"{path}: no frames to write")
        sink.finish()


def write_video(path: str | os.PathLike[str], frames: Sequence[np.ndarray], fps: float = 24.0) -> Path:
    """Write ``[H, W, 3] uint8`` RGB frames as ``.mp4`` (MPEG-4 Part 2) or ``.gif``, atomically
    (:func:`video_writer`, for frames that are all at hand)."""
    _suffix(path, VIDEO_FORMATS, "video")
    if not frames:
        raise InputError(f"{path}: no frames to write")
    with video_writer(path, fps) as add:
        for f in frames:
            add(f)
    return Path(path)


def _check_video(tmp: Path, path: str | os.PathLike[str], n_frames: int) -> None:
    """OpenCV's video writer ignores write errors (a full disk gives a truncated file without its index): read the
    container back and require every frame. Raises OutputPathError otherwise."""
    with _native_log_silenced():
        cap = cv2.VideoCapture(str(tmp))
        try:
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        finally:
            cap.release()
    if n != n_frames:
        raise OutputPathError(
            f"cannot write {path}: the video came out unreadable ({max(n, 0)} of {n_frames} frames; is the disk full?)"
        )
