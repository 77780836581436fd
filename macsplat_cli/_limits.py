"""Limits on untrusted inputs, checked before anything is allocated from a declared size.

* :func:`check_regular_file`: inputs must be regular files (not ``/dev/zero``, a FIFO or a folder).
* :func:`read_json_file`: a size cap, a nesting cap and parser recursion reported as a typed error.
* :func:`max_image_pixels`: the decoded-size cap of input photos (``MACSPLAT_MAX_MEGAPIXELS``).
* :func:`check_render_size`: the cap on rendered image sizes.
* :func:`check_photo_count`: 2 to ``MAX_PHOTOS`` photos per reconstruction.
* :func:`check_path_views`: the views rendered along a path (``render --path``, ``reconstruct --num-renders``).

Every check raises the caller's error class (a subclass of :class:`~macsplat_cli.errors.InputError`),
so the CLI exits with status 2 and one line naming the file and the limit.
"""

from __future__ import annotations

import json
import math
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .errors import InputError

__all__ = [
    "MAX_PATH_VIEWS",
    "MAX_GIF_BYTES",
    "MAX_PHOTOS",
    "check_path_views",
    "check_photo_count",
    "DEFAULT_MAX_MEGAPIXELS",
    "MAX_IMAGE_FILE_BYTES",
    "MAX_JSON_BYTES",
    "MAX_JSON_DEPTH",
    "MAX_MEGAPIXELS_ENV",
    "MAX_RENDER_PIXELS",
    "MAX_RENDER_SIDE",
    "MAX_TEXT_BYTES",
    "check_regular_file",
    "check_render_size",
    "json_depth",
    "max_image_pixels",
    "parse_json",
    "read_json_file",
    "read_text_file",
]

ErrorFactory = Callable[[str], Exception]

MAX_JSON_BYTES = 32 * 1024 * 1024
"""Camera, pose, intrinsics and model-config JSON files larger than this are refused (32 MiB)."""
MAX_TEXT_BYTES = 256 * 1024 * 1024
"""Text camera models (COLMAP ``cameras.txt``/``images.txt``) larger than this are refused (256 MiB)."""
MAX_JSON_DEPTH = 64
"""Deepest nesting of arrays/objects accepted in a JSON input (the formats read need at most 5)."""
MAX_IMAGE_FILE_BYTES = 1024 * 1024 * 1024
"""Image files larger than this are refused before they are read (1 GiB)."""
DEFAULT_MAX_MEGAPIXELS = 100.0
"""Default cap on the decoded size of an input photo, in megapixels (width · height / 10⁶)."""
MAX_MEGAPIXELS_ENV = "MACSPLAT_MAX_MEGAPIXELS"
"""Environment variable overriding :data:`DEFAULT_MAX_MEGAPIXELS` (a positive number of megapixels)."""
MAX_RENDER_SIDE = 16384
"""Longest side of a rendered image, in pixels."""
MAX_RENDER_PIXELS = 8192 * 8192
"""Most pixels in a rendered image (67 MP: the framebuffers of one view take a few GB)."""


def check_regular_file(path: Path, error: ErrorFactory, what: str = "a file") -> int:
    """The size in bytes of ``path``, a regular file (symlinks followed).

    ``what`` names the expected kind with its article (``"an image"``), for messages.

    Raises:
        ``error(...)``: the path does not exist, is a folder, or is not a regular file (a device such as
        ``/dev/zero``, a FIFO, a socket), which could be endless or block.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{path}: is a directory, not {what}")
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: not a regular file (a device, FIFO or socket cannot be {what})")
    return int(st.st_size)


def _read_capped(path: Path, limit: int, error: ErrorFactory, what: str) -> bytes:
    size = check_regular_file(path, error, what)
    if size > limit:
        raise error(f"{path}: {size:,} bytes is too large for {what} (at most {limit:,} bytes)")
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)  # the file may have grown since stat
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror or e})") from None
    if len(data) > limit:
        raise error(f"{path}: too large for {what} (at most {limit:,} bytes)")
    return data


def read_text_file(path: Path, error: ErrorFactory, what: str = "a text file", limit: int = MAX_TEXT_BYTES) -> str:
    """UTF-8 text of a regular file of at most ``limit`` bytes.

    Raises:
        ``error(...)``: missing, not a regular file, too large, unreadable or not UTF-8.
    """
    data = _read_capped(path, limit, error, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def json_depth(value: Any) -> int:
    """Nesting depth of a parsed JSON value (0 for a scalar), computed without recursion."""
    deepest = 0
    stack = [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list):
            deepest = max(deepest, d)
            stack.extend((x, d + 1) for x in v if isinstance(x, (dict, list)))
    return deepest


def parse_json(text: str | bytes, where: str, error: ErrorFactory, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """``json.loads(text)`` with parser errors, runaway recursion and deep nesting reported as ``error``.

    Args:
        where: what the text is, for messages (usually the file).
    """
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise error(f"{where}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except UnicodeDecodeError as e:
        raise error(f"{where}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except (RecursionError, MemoryError):
        raise error(f"{where}: JSON nested too deeply (at most {max_depth} levels)") from None
    if json_depth(value) > max_depth:
        raise error(f"{where}: JSON nested too deeply (at most {max_depth} levels)")
    return value


def read_json_file(
    path: Path,
    error: ErrorFactory,
    what: str = "a JSON file",
    *,
    limit: int = MAX_JSON_BYTES,
    max_depth: int = MAX_JSON_DEPTH,
) -> Any:
    """Parse a JSON file safely: a regular file of at most ``limit`` bytes, nested at most ``max_depth`` deep.

    Raises:
        ``error(...)``: the file is missing, a folder or a device, too large, not UTF-8, not JSON, or nested
        too deeply; the one-line message names the file and the problem.
    """
    text = read_text_file(path, error, what, limit)
    return parse_json(text, str(path), error, max_depth)


def max_image_pixels() -> int:
    """The decoded-size cap of input photos in pixels: ``MACSPLAT_MAX_MEGAPIXELS`` (default 100) × 10⁶.

    Raises:
        InputError: the environment variable is not a positive number.
    """
    raw = os.environ.get(MAX_MEGAPIXELS_ENV, "").strip()
    if not raw:
        return int(DEFAULT_MAX_MEGAPIXELS * 1e6)
    try:
        mp = float(raw)
    except ValueError:
        mp = math.nan
    if not (math.isfinite(mp) and mp > 0):
        raise InputError(f"{MAX_MEGAPIXELS_ENV}={raw!r} must be a positive number of megapixels")
    return int(mp * 1e6)


def check_render_size(width: int, height: int, error: ErrorFactory = InputError) -> None:
    """Raise ``error`` unless ``0 < width, height ≤`` :data:`MAX_RENDER_SIDE` and ``width · height ≤``
    :data:`MAX_RENDER_PIXELS`."""
    if width <= 0 or height <= 0:
        raise error(f"image size must be positive, got {width}x{height}")
    if max(width, height) > MAX_RENDER_SIDE or width * height > MAX_RENDER_PIXELS:
        raise error(
            f"render size {width}x{height} is too large: at most {MAX_RENDER_SIDE} px a side and "
            f"{MAX_RENDER_PIXELS / 1e6:.1f} megapixels"
        )


MAX_PHOTOS = 64
"""The most photos one reconstruction takes: twice the tested 32 (time and memory grow about linearly with the
number of photos beyond the all-pairs size: benchmarks/README.md, Multi-view)."""


def check_photo_count(n: int, max_photos: int = MAX_PHOTOS) -> None:
    """Raises :class:`InputError` unless ``2 ≤ n ≤ max_photos``."""
    if n < 2:
        raise InputError(f"{n} photo{'s' if n != 1 else ''} given: a scene needs at least two photos of it")
    if n > max_photos:
        raise InputError(f"{n} photos given: at most {max_photos} are taken in one run")


MAX_PATH_VIEWS = 10_000
"""Most views rendered along a path, ``render --path`` and ``reconstruct --num-renders`` alike (7 minutes of video at
24 fps); they are written as they are rendered, so this bounds the time and the files, not the memory."""
MAX_GIF_BYTES = 4 * 2**30
"""Most memory the frames of a ``.gif`` may hold: Pillow's GIF writer keeps every frame (one byte a pixel once
quantised) until it writes the file; an ``.mp4`` is encoded frame by frame and holds none."""


def check_path_views(option: str, n: int, width: int, height: int, video: str | os.PathLike[str] | None) -> None:
    """The one check of a path's views, before any is rendered: ``1 ≤ n ≤`` :data:`MAX_PATH_VIEWS`, and a ``.gif``
    ``video`` of ``n`` frames of ``width × height`` within :data:`MAX_GIF_BYTES`.

    Args:
        option: the option that asked for ``n`` views, for messages (``--path``, ``--num-renders``).
        width, height: the frames' size (an upper bound when it is not known yet).

    Raises:
        InputError: too many views, or a GIF too large to hold.
    """
    if not 1 <= n <= MAX_PATH_VIEWS:
        raise InputError(f"{option} {n}: give 1 to {MAX_PATH_VIEWS:,} views along the path")
    need = n * width * height
    if video is not None and Path(video).suffix.lower() == ".gif" and need > MAX_GIF_BYTES:
        raise InputError(
            f"--video {video}: {n} GIF frames of {width}x{height} would hold {need / 2**30:.1f} GiB in memory "
            f"(at most {MAX_GIF_BYTES / 2**30:.0f} GiB): use an .mp4, fewer views or smaller frames"
        )
