"""An export folder: the cameras, the sparse points and the photos, laid out as another tool opens them.

``colmap``: ``DIR/sparse/0/{cameras,images,points3D}.txt`` and ``DIR/images/<photo>`` (the layout COLMAP, gsplat's
and nerfstudio's COLMAP parsers and the Inria 3DGS trainer read). ``nerfstudio``: ``DIR/transforms.json``,
``DIR/sparse_pc.ply`` (the same points) and ``DIR/images/<photo>``. The folder is built beside its place under a
temporary name and renamed into place at the end: it is there whole or not at all.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Literal, get_args

from .._atomic import check_writable
from ..cameras import CameraSet
from ..errors import InputError, OutputPathError
from .colmap import write_colmap_text
from .nerfstudio import write_nerfstudio
from .points import SparsePoints, write_point_ply

__all__ = ["EXPORT_FORMATS", "ExportFormat", "check_export_folder", "write_export"]

ExportFormat = Literal["colmap", "nerfstudio"]
EXPORT_FORMATS: tuple[str, ...] = get_args(ExportFormat)
_EXIF_ORIENTATION = 0x0112


def check_export_folder(folder: Path, force: bool, keep: Sequence[tuple[str, Path | None]] = ()) -> None:
    """Before any work: ``folder`` may be written (absent, empty, or replaced with ``force``), and replacing it
    removes none of ``keep`` (``(label, path)`` of the inputs and other outputs).

    Raises:
        InputError: it exists and is not an empty folder (without ``force``), is a link or a file, or holds one of
            ``keep``.
        OutputPathError: its parent cannot be written.
    """
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise InputError(f"--export {folder}: exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not force:
        raise InputError(f"--export {folder}: the folder exists and is not empty; add --force to replace it")
    root = os.path.realpath(folder)
    for label, p in keep:
        if p is not None and os.path.commonpath([root, os.path.realpath(p)]) == root:
            raise InputError(f"--export {folder}: it holds {label} {p}, which the export would replace")
    check_writable(folder / "transforms.json")


def _copy_photo(src: Path, dst: Path) -> None:
    """The photo's file, or its upright pixels when its EXIF orientation turns it (the cameras are of the upright
    photo; other tools read the stored pixels)."""
    from PIL import Image, ImageOps

    try:
        with Image.open(src) as im:
            turned = im.getexif().get(_EXIF_ORIENTATION, 1) not in (None, 1)
            if turned:
                ImageOps.exif_transpose(im).save(dst)
                return
        shutil.copyfile(src, dst)
    except OSError as e:
        raise OutputPathError(f"cannot copy {src} to {dst}: {e.strerror or e}") from e


def _write_into(kind: ExportFormat, tmp: Path, cameras: CameraSet, points: SparsePoints, photos: Sequence[Path]):
    (tmp / "images").mkdir()
    for cam, photo in zip(cameras, photos):
        _copy_photo(photo, tmp / "images" / cam.name)
    if kind == "colmap":
        write_colmap_text(cameras, tmp / "sparse" / "0", points)
    else:
        write_point_ply(tmp / "sparse_pc.ply", points)
        write_nerfstudio(cameras, tmp / "transforms.json", image_folder="images/", ply_file_path="sparse_pc.ply")


def write_export(
    kind: ExportFormat, folder: Path, cameras: CameraSet, points: SparsePoints, photos: Sequence[Path]
) -> Path:
    """Write the export folder ``folder`` (module docstring): ``photos[i]`` is camera ``i``'s photo, copied as
    ``images/<camera name>``. An existing ``folder`` (checked by :func:`check_export_folder`) is replaced.

    Raises:
        OutputPathError: something cannot be written (nothing is left behind).
    """
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    old: Path | None = None
    try:
        _write_into(kind, tmp, cameras, points, photos)
        if folder.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".old", dir=folder.parent))
            os.replace(folder, old)
        os.replace(tmp, folder)
    except OSError as e:
        if old is not None and not folder.exists():
            os.replace(old, folder)
            old = None
        raise OutputPathError(f"cannot write {folder}: {e.strerror or e}") from e
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    return folder
