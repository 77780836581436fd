"""Evaluation data sets: posed images (+ depth) from a folder, in one of several layouts.

Every loader gives an :class:`EvalDataset`: scenes of :class:`Frame` s, each with its image
file, its ground-truth :class:`~macsplat_cli.cameras.Camera` (OpenCV axes, pixel centres at
+0.5, at the image's own resolution) and optionally a depth map (camera-space z).

Layouts (``layout="auto"`` picks the first that fits):

* ``generic`` — ``cameras.json`` (the macsplat cameras schema, see
  :mod:`macsplat_cli.cameras`), ``images/<name>.<ext>`` and optionally
  ``depth/<stem>.{png,npy,tif,tiff}``: 16-bit PNG holds ``round(depth · 1000)``
  (:func:`~macsplat_cli.images.save_depth`), ``.npy``/``.tif`` hold float depth in scene
  units; 0 = no depth. This is what :func:`macsplat_cli.synthetic.write_dataset` writes.
  The folder is one scene, or holds one scene per subfolder. ``scale`` of the cameras
  file says whether the scene is metric.
* ``scannetpp`` — ScanNet++ DSLR data (undistorted), either the official release tree
  (``<root>/splits/<split>.txt``, ``<root>/data/<scene>/dslr/``) or Splatt3R's
  ``<root>/raw`` + ``<root>/processed`` tree. Per scene: ``nerfstudio/transforms_undistorted.json``
  (intrinsics and poses), ``undistorted_images/`` or ``resized_undistorted_images/``,
  optionally ``undistorted_depths/<stem>.png`` (uint16 mm, 0 = invalid). Frames: the
  ``train`` list of ``train_test_lists.json`` (else every frame of the transforms file),
  without the frames marked ``is_bad``. Poses: nerfstudio ``transform_matrix`` converted
  to OpenCV camera-to-world in the mesh frame (:func:`nerfstudio_to_opencv`).
* ``co3d-json`` — ``cameras_opencv.json`` ``{"width", "height", "views": [{"image", "K",
  "c2w"}]}`` (OpenCV axes, principal point in the +0.5 convention), as in the CO3D
  development sample; no depth, arbitrary scale.
* ``icl-nuim`` — ``color/<i>.png``, ``depth/<i>.png`` (metres × 5000), ``pose.txt`` (line i:
  ``tx ty tz qx qy qz qw``, camera-to-world) with the ICL-NUIM intrinsics (fx 481.2,
  fy −480, cx 319.5, cy 239.5 at 640×480); the left-handed rig is made right-handed with
  ``F · c2w · F``, ``F = diag(1, −1, 1, 1)``, and ``fy = +480``.
* ``nyu-rgbd`` — the same files with ``depth/<i>.pgm`` (16-bit, mm) and the NYU Depth v2
  RGB calibration (fx 518, fy 519, cx 325.5, cy 253.5; approximate poses).

Loading validates cheaply, before any evaluation work: every file exists, every image's
header is readable and its size matches its camera, depth maps match their image size.
Problems raise :class:`~macsplat_cli.errors.DatasetError` naming the file.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np

from ..cameras import Camera, CameraSet, Scale, load_cameras, quat_to_rotmat_np
from ..errors import CameraFileError, DatasetError, ImageReadError
from ..images import DEPTH_PNG_SCALE, IMAGE_FORMATS, load_image

__all__ = [
    "LAYOUTS",
    "EvalDataset",
    "EvalScene",
    "Frame",
    "Layout",
    "detect_layout",
    "load_dataset",
    "nerfstudio_to_opencv",
    "opencv_to_nerfstudio",
    "read_depth",
    "resize_depth_nearest",
]

logger = logging.getLogger(__name__)

Layout = Literal["auto", "generic", "scannetpp", "co3d-json", "icl-nuim", "nyu-rgbd"]
LAYOUTS: tuple[str, ...] = get_args(Layout)
_DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
_ICL_SIZE = (640, 480)
_ICL_K = np.array([[481.2, 0.0, 319.5 + 0.5], [0.0, 480.0, 239.5 + 0.5], [0.0, 0.0, 1.0]])
_NYU_K = np.array([[518.0, 0.0, 325.5 + 0.5], [0.0, 519.0, 253.5 + 0.5], [0.0, 0.0, 1.0]])
_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])


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


def nerfstudio_to_opencv(transform_matrix: np.ndarray) -> np.ndarray:
    """ScanNet++ nerfstudio ``transform_matrix`` → OpenCV camera-to-world in the mesh frame. [4, 4]

    The inverse of the toolkit's conversion (camera y, z flipped; world rows permuted and
    z negated): ``c2w[2] *= −1; c2w = c2w[[1, 0, 2, 3]]; c2w[:3, 1:3] *= −1``.
    """
    c2w = np.array(transform_matrix, dtype=np.float64)
    c2w[2, :] *= -1
    c2w = c2w[[1, 0, 2, 3], :]
    c2w[0:3, 1:3] *= -1
    return c2w


def opencv_to_nerfstudio(cam_to_world: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (mesh frame) → ScanNet++ nerfstudio ``transform_matrix``. [4, 4]"""
    T = np.array(cam_to_world, dtype=np.float64)
    T[0:3, 1:3] *= -1
    T = T[[1, 0, 2, 3], :]
    T[2, :] *= -1
    return T


def _image_size(path: Path) -> tuple[int, int]:
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
    return _image_size(path)


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: not a readable JSON file ({e})") from None


def _validate(scene: EvalScene, where: Path) -> EvalScene:
    """Files exist, image and depth sizes match the cameras, at least three frames."""
    if len(scene.frames) < 3:
        raise DatasetError(f"{where}: scene {scene.name!r} has {len(scene.frames)} frame(s); at least 3 are needed")
    names = [f.name for f in scene.frames]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise DatasetError(f"{where}: frame names repeated in scene {scene.name!r}: {', '.join(dup)}")
    for f in scene.frames:
        size = _image_size(f.image)
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


# ------------------------------------------------------------------------------------ layouts
def _find_image(folder: Path, name: str) -> Path:
    direct = folder / name
    if direct.is_file():
        return direct
    stem = Path(name).stem if Path(name).suffix.lower() in IMAGE_FORMATS else name
    for ext in IMAGE_FORMATS:
        for cand in (folder / f"{stem}{ext}", folder / f"{stem}{ext.upper()}"):
            if cand.is_file():
                return cand
    raise DatasetError(f"{folder / name}: image not found (looked for {stem}.* with an image extension)")


def _generic_scene(folder: Path, name: str) -> EvalScene:
    try:
        cams: CameraSet = load_cameras(folder / "cameras.json")
    except CameraFileError as e:
        raise DatasetError(str(e)) from None
    images, depth_dir = folder / "images", folder / "depth"
    if not images.is_dir():
        raise DatasetError(f"{images}: folder not found (the generic layout keeps its images there)")
    frames = []
    for cam in cams:
        img = _find_image(images, cam.name)
        depth = None
        if depth_dir.is_dir():
            cands = [depth_dir / f"{Path(cam.name).stem}{s}" for s in _DEPTH_SUFFIXES]
            depth = next((c for c in cands if c.is_file()), None)
        scale = 1.0 / DEPTH_PNG_SCALE if depth is not None and depth.suffix.lower() == ".png" else 1.0
        frames.append(Frame(cam.name, img, cam, depth, scale))
    return _validate(EvalScene(name, frames, cams.scale), folder)


def _load_generic(root: Path) -> list[EvalScene]:
    if (root / "cameras.json").is_file():
        return [_generic_scene(root, root.resolve().name)]
    subs = sorted(p for p in root.iterdir() if p.is_dir() and (p / "cameras.json").is_file())
    if not subs:
        raise DatasetError(f"{root}: no cameras.json, neither in the folder nor in a subfolder")
    return [_generic_scene(p, p.name) for p in subs]


def _load_co3d_json(root: Path) -> list[EvalScene]:
    path = root / "cameras_opencv.json"
    doc = _read_json(path)
    try:
        w, h = int(doc["width"]), int(doc["height"])
        views = list(doc["views"])
        frames = []
        for i, v in enumerate(views):
            img = root / v["image"]
            try:
                cam = Camera(Path(v["image"]).stem, w, h, np.array(v["K"], float), np.array(v["c2w"], float))
            except CameraFileError as e:
                raise DatasetError(f"{path}: views[{i}]: {e}") from None
            frames.append(Frame(cam.name, img, cam))
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: expected {{width, height, views: [{{image, K, c2w}}]}} ({e!r})") from None
    return [_validate(EvalScene(root.resolve().name, frames, "relative"), root)]


def _quat_xyzw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return quat_to_rotmat_np(np.array([w, x, y, z]))


def _load_rgbd_poses(root: Path, kind: Literal["icl-nuim", "nyu-rgbd"]) -> list[EvalScene]:
    pose_file = root / "pose.txt"
    if not pose_file.is_file():
        raise DatasetError(f"{pose_file}: file not found")
    K, flip, ext, scale = (
        (_ICL_K, True, ".png", 1.0 / 5000.0) if kind == "icl-nuim" else (_NYU_K, False, ".pgm", 1.0 / 1000.0)
    )
    frames = []
    lines = [ln for ln in pose_file.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    for i, line in enumerate(lines, start=1):
        try:
            v = np.array([float(x) for x in line.split()])
        except ValueError:
            raise DatasetError(f"{pose_file}: line {i} is not 7 numbers (tx ty tz qx qy qz qw)") from None
        if v.shape != (7,) or not np.isfinite(v).all() or np.linalg.norm(v[3:]) == 0:
            raise DatasetError(f"{pose_file}: line {i} is not 7 numbers (tx ty tz qx qy qz qw)")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _quat_xyzw(v[3:]), v[:3]
        if flip:
            T = _FLIP_Y @ T @ _FLIP_Y
        img = root / "color" / f"{i}.png"
        size = _image_size(img)
        if size != _ICL_SIZE:
            raise DatasetError(
                f"{img}: {kind} images are {_ICL_SIZE[0]}x{_ICL_SIZE[1]}, this one is {size[0]}x{size[1]}"
            )
        cam = Camera(str(i), size[0], size[1], K, T)
        frames.append(Frame(str(i), img, cam, root / "depth" / f"{i}{ext}", scale))
    return [_validate(EvalScene(root.resolve().name, frames, "metric"), root)]


def _scannetpp_scene(data_root: Path, raw_root: Path, scene_id: str) -> EvalScene:
    dslr = data_root / scene_id / "dslr"
    raw_dslr = raw_root / "data" / scene_id / "dslr"
    if not raw_dslr.is_dir():
        raw_dslr = dslr
    tu_path = dslr / "nerfstudio" / "transforms_undistorted.json"
    tu = _read_json(tu_path)
    img_dir = next(
        (dslr / d for d in ("undistorted_images", "resized_undistorted_images") if (dslr / d).is_dir()), None
    )
    if img_dir is None:
        raise DatasetError(f"{dslr}: no undistorted_images/ or resized_undistorted_images/ folder")
    depth_dir = dslr / "undistorted_depths"
    try:
        w, h = int(tu["w"]), int(tu["h"])
        K = np.array([[float(tu["fl_x"]), 0.0, float(tu["cx"])], [0.0, float(tu["fl_y"]), float(tu["cy"])], [0, 0, 1]])
        poses = {Path(f["file_path"]).name: f for f in list(tu["frames"]) + list(tu.get("test_frames", []))}
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{tu_path}: expected w, h, fl_x, fl_y, cx, cy and frames ({e!r})") from None
    bad = {name for name, f in poses.items() if f.get("is_bad")}
    ts_path = raw_dslr / "nerfstudio" / "transforms.json"
    if ts_path.is_file() and ts_path != tu_path:
        for f in _read_json(ts_path).get("frames", []):
            if f.get("is_bad"):
                bad.add(Path(f["file_path"]).name)
    lists_path = raw_dslr / "train_test_lists.json"
    if lists_path.is_file():
        names = [Path(n).name for n in _read_json(lists_path).get("train", [])]
    else:
        names = [Path(f["file_path"]).name for f in tu["frames"]]
    frames = []
    for name in names:
        if name in bad:
            continue
        if name not in poses:
            raise DatasetError(f"{tu_path}: no pose for frame {name} of the train list")
        try:
            cam = Camera(name, w, h, K, nerfstudio_to_opencv(np.array(poses[name]["transform_matrix"], float)))
        except (CameraFileError, KeyError, ValueError) as e:
            raise DatasetError(f"{tu_path}: frame {name}: {e}") from None
        depth = depth_dir / f"{Path(name).stem}.png" if depth_dir.is_dir() else None
        frames.append(Frame(Path(name).stem, img_dir / name, cam, depth, 1.0 / 1000.0))
    logger.debug("scannetpp %s: %d frames (%d marked is_bad)", scene_id, len(frames), len(bad))
    return _validate(EvalScene(scene_id, frames, "metric"), dslr)


def _load_scannetpp(root: Path, split: str, scenes: Iterable[str] | None) -> list[EvalScene]:
    if (root / "processed").is_dir():
        data_root, raw_root = root / "processed", root / "raw"
    else:
        data_root, raw_root = root / "data", root
    if scenes is None:
        split_file = raw_root / "splits" / f"{split}.txt"
        if not split_file.is_file():
            raise DatasetError(f"{split_file}: split file not found")
        ids = [ln.strip() for ln in split_file.read_text(encoding="utf-8").splitlines() if ln.strip()]
    else:
        ids = list(scenes)
    present = [s for s in ids if (data_root / s / "dslr").is_dir()]
    missing = [s for s in ids if s not in present]
    if missing:
        logger.warning("%d scene(s) of the split are not in %s (skipped): %s", len(missing), data_root, missing[:5])
    if not present:
        raise DatasetError(f"{data_root}: none of the {len(ids)} scenes of split {split!r} is there")
    return [_scannetpp_scene(data_root, raw_root, s) for s in present]


def detect_layout(root: str | os.PathLike[str]) -> str:
    """The layout of a data set folder (see the module docstring).

    Raises:
        DatasetError: the folder is missing or matches no layout.
    """
    r = Path(root)
    if not r.is_dir():
        raise DatasetError(f"{r}: no such folder")
    if (r / "cameras.json").is_file() or any(p.is_dir() and (p / "cameras.json").is_file() for p in r.iterdir()):
        return "generic"
    if ((r / "splits").is_dir() and (r / "data").is_dir()) or ((r / "raw").is_dir() and (r / "processed").is_dir()):
        return "scannetpp"
    if (r / "cameras_opencv.json").is_file():
        return "co3d-json"
    if (r / "pose.txt").is_file() and (r / "color").is_dir():
        depth = r / "depth"
        if depth.is_dir() and any(p.suffix.lower() == ".pgm" for p in depth.iterdir()):
            return "nyu-rgbd"
        return "icl-nuim"
    raise DatasetError(
        f"{r}: not a data set folder: expected cameras.json + images/ (generic), splits/ + data/ or raw/ + processed/ "
        "(ScanNet++), cameras_opencv.json (CO3D sample) or pose.txt + color/ + depth/ (ICL-NUIM / NYU RGB-D)"
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
        found = _load_generic(r)
    elif kind == "scannetpp":
        found = _load_scannetpp(r, scannetpp_split, scenes)
    elif kind == "co3d-json":
        found = _load_co3d_json(r)
    elif kind in ("icl-nuim", "nyu-rgbd"):
        found = _load_rgbd_poses(r, kind)  # type: ignore[arg-type]
    else:  # pragma: no cover - LAYOUTS is exhaustive
        raise AssertionError(kind)
    if scenes is not None and kind != "scannetpp":
        wanted = set(scenes)
        found = [s for s in found if s.name in wanted]
        if not found:
            raise DatasetError(f"{r}: none of the scenes {sorted(wanted)} is there")
    logger.info("%s: %s layout, %d scene(s), %d frames", r, kind, len(found), sum(len(s.frames) for s in found))
    return EvalDataset(r, kind, found)
