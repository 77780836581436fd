"""One ScanNet++ scene as an :class:`~macsplat_cli.datasets.base.EvalScene`: DSLR (preferred) or iPhone frames."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...cameras import Camera
from ...errors import CameraFileError, DatasetError
from ..base import EvalScene, Frame, check_inside, image_size, member_path, read_json, validate_scene
from .poses import Lens, PoseTable, poses_from_transforms, read_colmap_scene
from .undistort import UndistortCache, pinhole_K

__all__ = ["IPHONE_VIDEO_SIZE", "load_dslr_scene", "load_iphone_scene"]

logger = logging.getLogger(__name__)

IPHONE_VIDEO_SIZE = (1920, 1440)
"""(W, H) of the iPhone video, the resolution of the ``intrinsic`` matrices of ``pose_intrinsic_imu.json``."""
_UNDISTORTED_IMAGES = ("undistorted_images", "resized_undistorted_images")
_UNDISTORTED_DEPTHS = ("undistorted_depths", "resized_undistorted_depths")


def _first_dir(parent: Path, names: tuple[str, ...]) -> Path | None:
    return next((parent / n for n in names if (parent / n).is_dir()), None)


def _camera(name: str, K: np.ndarray, lens: Lens, c2w: np.ndarray, where: Path) -> Camera:
    try:
        return Camera(name, lens.width, lens.height, K, c2w)
    except CameraFileError as e:
        raise DatasetError(f"{where}: frame {name}: {e}") from None


def _pose_source(ns_path: Path, colmap: Path, also: Path | None = None) -> tuple[PoseTable, list[str], Path]:
    """Poses from nerfstudio ``transforms.json``, else COLMAP; (table, train names, the file read)."""
    if ns_path.is_file():
        table, train = poses_from_transforms(read_json(ns_path), ns_path)
        return table, train, ns_path
    if (colmap / "images.txt").is_file():
        table = read_colmap_scene(colmap)
        return table, sorted(table), colmap / "images.txt"
    nor = f"{also}, " if also is not None else ""
    raise DatasetError(f"{ns_path}: file not found (nor {nor}{colmap / 'images.txt'}): the scene has no poses")


def load_dslr_scene(
    scene_id: str, dslr: Path, raw_dslr: Path | None = None, *, within: Sequence[Path] | None = None
) -> EvalScene:
    """The DSLR frames of a scene.

    Images, in order of preference:

    1. ``undistorted_images/`` or ``resized_undistorted_images/`` with the pinhole intrinsics
       and poses of ``nerfstudio/transforms_undistorted.json`` (depth:
       ``undistorted_depths/<stem>.png``);
    2. the same images with ``nerfstudio/transforms.json`` (or ``colmap/``): the intrinsics are
       those of the toolkit's undistortion of its fisheye lens (:func:`.undistort.pinhole_K`);
    3. ``resized_images/`` (fisheye) with ``nerfstudio/transforms.json``, else ``colmap/``:
       undistorted once into a cache (:class:`.undistort.UndistortCache`); depth:
       ``render_depth/<stem>.png`` undistorted likewise.

    Frames: the ``train`` list of ``train_test_lists.json``, else the ``frames`` of the
    transforms file (every image of ``images.txt`` for COLMAP), minus those marked ``is_bad``
    in any transforms file. Depth maps are uint16 millimetres.

    Args:
        scene_id: the scene's name.
        dslr: ``<scene>/dslr``.
        raw_dslr: where ``train_test_lists.json`` and the raw ``transforms.json`` are, when
            elsewhere (Splatt3R's ``raw``/``processed`` split).
        within: the folders every file read must lie in, links resolved (default: ``dslr`` and
            ``raw_dslr``); the undistortion cache is added.
    """
    raw = raw_dslr if raw_dslr is not None and raw_dslr.is_dir() else dslr
    ns = raw / "nerfstudio" / "transforms.json"
    if not ns.is_file():
        ns = dslr / "nerfstudio" / "transforms.json"
    src = _dslr_source(dslr, raw, ns)
    bad = _bad_frames(src, ns, raw)
    names = _train_names(dslr, raw, src.train)
    roots = [*(within if within is not None else (dslr, raw)), *([src.cache.root] if src.cache is not None else [])]
    check_inside(src.source, roots, "the pose file")
    frames = _dslr_frames(src, names, bad, roots)
    logger.debug("scannetpp %s: %d DSLR frames from %s (%d marked is_bad)", scene_id, len(frames), src.source, len(bad))
    return validate_scene(EvalScene(scene_id, frames, "metric"), dslr, roots=roots)


@dataclass
class _DslrSource:
    """Where a scene's DSLR frames come from (:func:`load_dslr_scene`, items 1–3).

    Attributes:
        table: the poses by image name.
        train: the frames the pose file lists.
        source: the pose file read.
        pinhole: whether the table's intrinsics are those of the images (else the toolkit's undistortion of the lens).
        img_dir: the images' folder.
        depth_dir: the depth maps' folder, or None.
        cache: the undistortion cache of fisheye images, or None.
    """

    table: PoseTable
    train: list[str]
    source: Path
    pinhole: bool
    img_dir: Path
    depth_dir: Path | None
    cache: UndistortCache | None


def _dslr_source(dslr: Path, raw: Path, ns: Path) -> _DslrSource:
    """The images, depth maps and poses to read, in the order of preference of :func:`load_dslr_scene`."""
    ns_u = dslr / "nerfstudio" / "transforms_undistorted.json"
    colmap = dslr / "colmap" if (dslr / "colmap").is_dir() else raw / "colmap"
    und_dir = _first_dir(dslr, _UNDISTORTED_IMAGES)
    dist_dir = dslr / "resized_images" if (dslr / "resized_images").is_dir() else None
    cache: UndistortCache | None = None
    if und_dir is not None and (ns_u.is_file() or dist_dir is None):
        if ns_u.is_file():
            table, train = poses_from_transforms(read_json(ns_u), ns_u)
            source, pinhole = ns_u, True
        else:
            table, train, source = _pose_source(ns, colmap, also=ns_u)
            pinhole = False
        img_dir, depth_dir = und_dir, _first_dir(dslr, _UNDISTORTED_DEPTHS)
    elif dist_dir is not None:
        table, train, source = _pose_source(ns, colmap)
        pinhole, img_dir = True, dist_dir
        depth_dir = dslr / "render_depth" if (dslr / "render_depth").is_dir() else None
        if any(lens.distorted for _, lens, _ in table.values()):
            cache = UndistortCache(dslr)
    else:
        raise DatasetError(
            f"{dslr}: no DSLR images: expected resized_undistorted_images/ (or undistorted_images/) or resized_images/"
        )
    return _DslrSource(table, train, source, pinhole, img_dir, depth_dir, cache)


def _bad_frames(src: _DslrSource, ns: Path, raw: Path) -> set[str]:
    """The frames marked ``is_bad`` in the pose file read or in any other transforms file."""
    bad = {name for name, (_, _, b) in src.table.items() if b}
    for other in (ns, raw / "nerfstudio" / "transforms.json"):
        if other.is_file() and other != src.source:
            other_table, _ = poses_from_transforms(read_json(other), other)
            bad |= {name for name, (_, _, b) in other_table.items() if b}
    return bad


def _train_names(dslr: Path, raw: Path, train: list[str]) -> list[str]:
    """The ``train`` list of ``train_test_lists.json`` (in ``raw``, else ``dslr``), else the pose file's frames."""
    lists = raw / "train_test_lists.json"
    if not lists.is_file():
        lists = dslr / "train_test_lists.json"
    if not lists.is_file():
        return train
    doc = read_json(lists)
    if not isinstance(doc, dict) or not isinstance(doc.get("train"), list):
        raise DatasetError(f"{lists}: expected a JSON object with a 'train' list")
    return [Path(str(n)).name for n in doc["train"]]


def _dslr_frames(src: _DslrSource, names: list[str], bad: set[str], roots: list[Path]) -> list[Frame]:
    """The frames of ``names`` not in ``bad``, fisheye images undistorted through the cache (closed after)."""
    source, table, img_dir, depth_dir, cache = src.source, src.table, src.img_dir, src.depth_dir, src.cache
    frames = []
    try:
        for name in names:
            if name in bad:
                continue
            if name not in table:
                raise DatasetError(f"{source}: no pose for frame {name} of the train list")
            c2w, lens, _ = table[name]
            member_path(img_dir, name, f"{source}: frame")
            stem = Path(name).stem
            depth = depth_dir / f"{stem}.png" if depth_dir is not None else None
            if cache is not None and lens.distorted:
                image, K = cache.image(check_inside(img_dir / name, roots, f"frame {stem!r}"), lens)
                depth = cache.depth(check_inside(depth, roots, f"frame {stem!r}"), lens) if depth is not None else None
            else:
                image, K = img_dir / name, (lens.K if src.pinhole else pinhole_K(lens))
            frames.append(Frame(stem, image, _camera(stem, K, lens, c2w, source), depth, 1.0 / 1000.0))
    finally:
        if cache is not None:
            cache.close()
    return frames


def _pose_intrinsic_imu(path: Path, rgb: Path) -> PoseTable:
    """``pose_intrinsic_imu.json``: ``aligned_pose`` (else ``pose``) as OpenCV camera-to-world in the mesh frame.

    The ``intrinsic`` matrices are for the 1920×1440 video and are rescaled to the size of the
    extracted frames (read from the first one).
    """
    doc = read_json(path)
    if not isinstance(doc, dict) or not doc:
        raise DatasetError(f"{path}: expected a JSON object of frames")
    present = sorted(p for p in rgb.iterdir() if p.is_file() and p.stem in doc)
    if not present:
        raise DatasetError(f"{rgb}: none of the frames of {path.name} is there")
    w, h = image_size(check_inside(present[0], (path.parent,), f"frame {present[0].stem!r}"))
    sx, sy = w / IPHONE_VIDEO_SIZE[0], h / IPHONE_VIDEO_SIZE[1]
    table: PoseTable = {}
    for p in present:
        entry = doc[p.stem]
        try:
            K = np.array(entry["intrinsic"], dtype=np.float64).reshape(3, 3)
            c2w = np.array(entry["aligned_pose"] if "aligned_pose" in entry else entry["pose"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as e:
            raise DatasetError(
                f"{path}: {p.stem}: expected 'intrinsic' (3x3) and 'aligned_pose' (4x4) ({e!r})"
            ) from None
        if c2w.shape != (4, 4) or not (np.isfinite(c2w).all() and np.isfinite(K).all()):
            raise DatasetError(f"{path}: {p.stem}: the pose must be a finite 4x4 matrix")
        K[0] *= sx
        K[1] *= sy
        table[p.name] = (c2w, Lens(w, h, K), False)
    return table


def load_iphone_scene(scene_id: str, iphone: Path, *, within: Sequence[Path] | None = None) -> EvalScene:
    """The iPhone frames of a scene: ``rgb/<frame>.jpg`` (extracted from ``rgb.mkv``), depth ``depth/<frame>.png``.

    Poses, in order of preference: ``nerfstudio/transforms.json`` (converted like the DSLR's),
    ``pose_intrinsic_imu.json`` (``aligned_pose``, camera-to-world with OpenCV axes in the mesh
    frame, as third-party ScanNet++ code uses it; not checked against the toolkit), ``colmap/``.
    Frames: every extracted frame that has a pose, in name order. Depth maps (uint16 mm, the
    LiDAR's 256×192) are resized (nearest) to the image size into the cache
    (:class:`.undistort.UndistortCache`), as are images of distorted (``OPENCV``) lenses. Every file
    read lies inside ``within`` (default: ``iphone``) or the cache, links resolved.
    """
    rgb = iphone / "rgb"
    if not rgb.is_dir():
        raise DatasetError(f"{rgb}: folder not found (extract the frames of rgb.mkv there)")
    ns, pii, colmap = iphone / "nerfstudio" / "transforms.json", iphone / "pose_intrinsic_imu.json", iphone / "colmap"
    if ns.is_file():
        table, _ = poses_from_transforms(read_json(ns), ns)
        source = ns
    elif pii.is_file():
        table, source = _pose_intrinsic_imu(pii, rgb), pii
    elif (colmap / "images.txt").is_file():
        table, source = read_colmap_scene(colmap), colmap / "images.txt"
    else:
        raise DatasetError(f"{pii}: file not found (nor {ns} or {colmap / 'images.txt'}): the scene has no poses")
    names = sorted(n for n in table if (rgb / n).is_file() and not table[n][2])
    if not names:
        raise DatasetError(f"{rgb}: none of the frames of {source} is there")
    depth_dir = iphone / "depth" if (iphone / "depth").is_dir() else None
    cache = UndistortCache(iphone)
    roots = [*(within if within is not None else (iphone,)), cache.root]
    check_inside(source, roots, "the pose file")
    frames = []
    try:
        for name in names:
            c2w, lens, _ = table[name]
            member_path(rgb, name, f"{source}: frame")
            stem = Path(name).stem
            if lens.distorted:
                image, K = cache.image(check_inside(rgb / name, roots, f"frame {stem!r}"), lens)
            else:
                image, K = rgb / name, lens.K
            depth = depth_dir / f"{stem}.png" if depth_dir is not None else None
            if depth is not None:
                check_inside(depth, roots, f"frame {stem!r}")
            if depth is not None and (lens.distorted or image_size(depth) != (lens.width, lens.height)):
                depth = cache.depth(depth, lens)
            frames.append(Frame(stem, image, _camera(stem, K, lens, c2w, source), depth, 1.0 / 1000.0))
    finally:
        cache.close()
    logger.debug("scannetpp %s: %d iPhone frames from %s", scene_id, len(frames), source)
    return validate_scene(EvalScene(scene_id, frames, "metric"), iphone, roots=roots)
