"""ScanNet++ (v1/v2) scenes: DSLR (undistorted, or fisheye undistorted here) or iPhone frames with metric poses.

**Trees.** The official release, ``<root>/splits/<split>.txt`` + ``<root>/data/<scene>/``, or
Splatt3R's ``<root>/raw/{splits,data}`` + ``<root>/processed/<scene>/``.

**Scenes.** ``scenes`` when given; else the ids of ``splits/<split>.txt`` (e.g. ``nvs_sem_train``,
``nvs_sem_val``) when the tree has a ``splits/`` folder; else every scene folder. Scenes of a
split that are not downloaded are skipped with a warning.

**Sensor.** The DSLR when the scene has a ``dslr/`` folder (:func:`.scene.load_dslr_scene`:
undistorted images with ``transforms_undistorted.json``, else fisheye ``resized_images/``
undistorted with ``cv2.fisheye`` into a cache, :mod:`.undistort`), else the iPhone
(:func:`.scene.load_iphone_scene`). ``sensor`` forces one.

**Poses.** OpenCV camera-to-world in the mesh-aligned frame: nerfstudio ``transform_matrix``
through :func:`nerfstudio_to_opencv`, or COLMAP ``images.txt`` when there is no nerfstudio file
(:mod:`.poses`). Depth: uint16 millimetres, 0 = invalid.

Errors (missing or malformed files, images of the wrong size) raise
:class:`~macsplat_cli.errors.DatasetError` naming the file. Synthetic trees of both layouts
(fisheye included) for tests: :func:`macsplat_cli.datasets.synthetic.write_scannetpp`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

from ...errors import DatasetError
from ..base import EvalScene, member_path
from .poses import Lens, nerfstudio_to_opencv, opencv_to_nerfstudio, poses_from_transforms, read_colmap_scene
from .scene import IPHONE_VIDEO_SIZE, load_dslr_scene, load_iphone_scene
from .undistort import CACHE_FOLDER, UndistortCache, cache_root, pinhole_K, undistort_maps

__all__ = [
    "CACHE_FOLDER",
    "IPHONE_VIDEO_SIZE",
    "Lens",
    "Sensor",
    "UndistortCache",
    "cache_root",
    "load_dslr_scene",
    "load_iphone_scene",
    "load_scannetpp",
    "nerfstudio_to_opencv",
    "opencv_to_nerfstudio",
    "pinhole_K",
    "poses_from_transforms",
    "read_colmap_scene",
    "scannetpp_scene_ids",
    "undistort_maps",
]

logger = logging.getLogger(__name__)

Sensor = Literal["auto", "dslr", "iphone"]


def _roots(root: Path) -> tuple[Path, Path]:
    """(folder of the scene folders, folder of ``splits/`` and the raw ``data/``)."""
    if (root / "processed").is_dir():
        return root / "processed", root / "raw"
    return root / "data", root


def _has_sensor(scene_dir: Path) -> bool:
    return (scene_dir / "dslr").is_dir() or (scene_dir / "iphone").is_dir()


def _scene_id(data_root: Path, scene: str, what: str) -> str:
    """A scene id is a plain folder name under ``data_root`` (no separator, no ``..``): :func:`..base.member_path`."""
    member_path(data_root, scene, what)
    return scene


def scannetpp_scene_ids(root: str | Path, split: str, scenes: Iterable[str] | None = None) -> list[str]:
    """The scene ids to load (see the module doc); not checked for presence.

    Raises:
        DatasetError: ``splits/`` exists without ``<split>.txt``, or there is no scene folder.
    """
    r = Path(root)
    data_root, raw_root = _roots(r)
    if scenes is not None:
        return [_scene_id(data_root, s, "--scenes: scene") for s in scenes]
    splits = raw_root / "splits"
    if splits.is_dir():
        split_file = splits / f"{split}.txt"
        if not split_file.is_file():
            have = sorted(p.stem for p in splits.glob("*.txt"))
            raise DatasetError(f"{split_file}: split file not found (there: {', '.join(have) or 'none'})")
        try:
            text = split_file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise DatasetError(f"{split_file}: cannot read ({e})") from None
        ids = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
        return [_scene_id(data_root, s, f"{split_file}: scene") for s in ids]
    if not data_root.is_dir():
        raise DatasetError(f"{data_root}: folder not found (a ScanNet++ tree has data/<scene>/dslr or iphone)")
    ids = sorted(p.name for p in data_root.iterdir() if p.is_dir() and _has_sensor(p))
    if not ids:
        raise DatasetError(f"{data_root}: no scene folder with dslr/ or iphone/")
    logger.info("%s: no splits/ folder; taking all %d scene folder(s)", r, len(ids))
    return ids


def load_scannetpp(root: Path, split: str, scenes: Iterable[str] | None, *, sensor: Sensor = "auto") -> list[EvalScene]:
    """The scenes of ``split`` (or ``scenes``, or every scene folder) present under ``root``.

    Args:
        root: the ScanNet++ root (official or Splatt3R tree).
        split: name of the split file (``splits/<split>.txt``), used when ``scenes`` is None
            and the tree has ``splits/``.
        scenes: scene ids to load instead of a split.
        sensor: ``"auto"`` (DSLR when present, else iPhone), ``"dslr"`` or ``"iphone"``.

    Raises:
        DatasetError: no scene is there, or a scene's files are missing or malformed (the
            message names the file).
    """
    if sensor not in ("auto", "dslr", "iphone"):
        raise DatasetError(f"unknown ScanNet++ sensor {sensor!r}; use auto, dslr or iphone")
    data_root, raw_root = _roots(Path(root))
    ids = scannetpp_scene_ids(root, split, scenes)
    wanted = {"auto": ("dslr", "iphone"), "dslr": ("dslr",), "iphone": ("iphone",)}[sensor]
    present = [s for s in ids if any((data_root / s / w).is_dir() for w in wanted)]
    missing = [s for s in ids if s not in present]
    if missing:
        logger.warning("%d scene(s) of the split are not in %s (skipped): %s", len(missing), data_root, missing[:5])
    if not present:
        raise DatasetError(f"{data_root}: none of the {len(ids)} scenes of split {split!r} is there")
    out = []
    within = (Path(root),)  # every file read lies in the tree, links resolved (or in the undistortion cache)
    for s in present:
        if "dslr" in wanted and (data_root / s / "dslr").is_dir():
            out.append(load_dslr_scene(s, data_root / s / "dslr", raw_root / "data" / s / "dslr", within=within))
        else:
            out.append(load_iphone_scene(s, data_root / s / "iphone", within=within))
    return out
