"""Which layout a folder holds, and the one entry point that loads any of them (:func:`load_dataset`)."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path

from ..errors import DatasetError
from .base import LAYOUTS, EvalDataset, Layout
from .co3d import load_co3d_json
from .folder import load_generic
from .icl import load_rgbd_poses
from .scannetpp import load_scannetpp

__all__ = ["detect_layout", "load_dataset"]

logger = logging.getLogger(__name__)


def detect_layout(root: str | os.PathLike[str]) -> str:
    """The layout of a data set folder (see :mod:`macsplat_cli.datasets`).

    Raises:
        DatasetError: the folder is missing or matches no layout.
    """
    r = Path(root)
    if not r.is_dir():
        raise DatasetError(f"{r}: no such folder")
    if (r / "cameras.json").is_file() or any(p.is_dir() and (p / "cameras.json").is_file() for p in r.iterdir()):
        return "generic"
    data = r / "data"
    scannet_scenes = data.is_dir() and any((p / "dslr").is_dir() or (p / "iphone").is_dir() for p in data.iterdir())
    if (
        ((r / "splits").is_dir() and data.is_dir())
        or scannet_scenes
        or ((r / "raw").is_dir() and (r / "processed").is_dir())
    ):
        return "scannetpp"
    if (r / "cameras_opencv.json").is_file():
        return "co3d-json"
    if (r / "pose.txt").is_file() and (r / "color").is_dir():
        depth = r / "depth"
        if depth.is_dir() and any(p.suffix.lower() == ".pgm" for p in depth.iterdir()):
            return "nyu-rgbd"
        return "icl-nuim"
    raise DatasetError(
        f"{r}: not a data set folder: expected cameras.json + images/ (generic), data/<scene>/dslr|iphone or raw/ + "
        "processed/ (ScanNet++), cameras_opencv.json (CO3D sample) or pose.txt + color/ + depth/ (ICL-NUIM / NYU RGB-D)"
    )


def load_dataset(
    root: str | os.PathLike[str],
    layout: Layout | str = "auto",
    *,
    scannetpp_split: str = "nvs_sem_val",
    scenes: Iterable[str] | None = None,
) -> EvalDataset:
    """Read and validate a data set folder.

    Args:
        root: the folder.
        layout: one of :data:`LAYOUTS` (``"auto"`` detects it).
        scannetpp_split: ScanNet++ split file to take the scenes from.
        scenes: only these scenes (ScanNet++ ids, or generic subfolder names).

    Raises:
        DatasetError: a missing or unreadable file, or cameras inconsistent with the images
            (the message names the file).
    """
    r = Path(root)
    if layout not in LAYOUTS:
        raise DatasetError(f"unknown data set layout {layout!r}; use one of {', '.join(LAYOUTS)}")
    kind = detect_layout(r) if layout == "auto" else layout
    if not r.is_dir():
        raise DatasetError(f"{r}: no such folder")
    if kind == "generic":
        found = load_generic(r)
    elif kind == "scannetpp":
        found = load_scannetpp(r, scannetpp_split, scenes)
    elif kind == "co3d-json":
        found = load_co3d_json(r)
    elif kind in ("icl-nuim", "nyu-rgbd"):
        found = load_rgbd_poses(r, kind)  # type: ignore[arg-type]
    else:  # pragma: no cover - LAYOUTS is exhaustive
        raise AssertionError(kind)
    if scenes is not None and kind != "scannetpp":
        wanted = set(scenes)
        found = [s for s in found if s.name in wanted]
        if not found:
            raise DatasetError(f"{r}: none of the scenes {sorted(wanted)} is there")
    logger.info("%s: %s layout, %d scene(s), %d frames", r, kind, len(found), sum(len(s.frames) for s in found))
    return EvalDataset(r, kind, found)
