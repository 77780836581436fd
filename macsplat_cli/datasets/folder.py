"""The generic layout: ``cameras.json`` + ``images/`` (+ ``depth/``), one scene per folder or per subfolder.

``cameras.json`` follows the macsplat cameras schema (:mod:`macsplat_cli.cameras`);
``images/<name>.<ext>``; optionally ``depth/<stem>.{png,npy,tif,tiff}``: 16-bit PNG holds
``round(depth · 1000)`` (:func:`~macsplat_cli.images.save_depth`), ``.npy``/``.tif`` hold
float depth in scene units; 0 = no depth. This is what
:func:`macsplat_cli.datasets.synthetic.write_dataset` writes. ``scale`` of the cameras file
says whether the scene is metric.

A camera's name is a plain file name (no folder, no ``..``, not absolute: :func:`.base.member_path`),
every file read lies inside the data set folder once links are resolved (:func:`.base.check_inside`),
and two cameras may not use one image (``f0`` and ``f0.png`` both find ``images/f0.png``).
"""

from __future__ import annotations

from pathlib import Path

from ..cameras import CameraSet, load_cameras
from ..errors import CameraFileError, DatasetError
from ..images import DEPTH_PNG_SCALE, IMAGE_FORMATS
from .base import EvalScene, Frame, check_inside, member_path, validate_scene

__all__ = ["load_generic"]

_DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")


def _find_image(folder: Path, name: str, what: str) -> Path:
    """The image of camera ``name`` in ``folder``: ``<name>`` itself, else ``<stem>.<image extension>``."""
    direct = member_path(folder, name, what)
    if direct.is_file():
        return direct
    stem = Path(name).stem if Path(name).suffix.lower() in IMAGE_FORMATS else name
    for ext in IMAGE_FORMATS:
        for cand in (folder / f"{stem}{ext}", folder / f"{stem}{ext.upper()}"):
            if cand.is_file():
                return cand
    raise DatasetError(f"{folder / name}: image not found (looked for {stem}.* with an image extension)")


def _generic_scene(folder: Path, name: str, within: Path) -> EvalScene:
    """The scene in ``folder``, whose files must lie inside ``within`` (the data set folder)."""
    cams_path = check_inside(folder / "cameras.json", (within,), f"scene {name!r}")
    try:
        cams: CameraSet = load_cameras(cams_path)
    except CameraFileError as e:
        raise DatasetError(str(e)) from None
    images, depth_dir = folder / "images", folder / "depth"
    if not images.is_dir():
        raise DatasetError(f"{images}: folder not found (the generic layout keeps its images there)")
    frames = []
    for cam in cams:
        img = _find_image(images, cam.name, f"{cams_path}: camera")
        depth = None
        if depth_dir.is_dir():
            cands = [depth_dir / f"{Path(cam.name).stem}{s}" for s in _DEPTH_SUFFIXES]
            depth = next((c for c in cands if c.is_file()), None)
        scale = 1.0 / DEPTH_PNG_SCALE if depth is not None and depth.suffix.lower() == ".png" else 1.0
        frames.append(Frame(cam.name, img, cam, depth, scale))
    return validate_scene(EvalScene(name, frames, cams.scale), folder, roots=(within,))


def load_generic(root: Path) -> list[EvalScene]:
    """The scene in ``root``, or one per subfolder holding a ``cameras.json`` (sorted by name)."""
    if (root / "cameras.json").is_file():
        return [_generic_scene(root, root.resolve().name, root)]
    subs = sorted(p for p in root.iterdir() if p.is_dir() and (p / "cameras.json").is_file())
    if not subs:
        raise DatasetError(f"{root}: no cameras.json, neither in the folder nor in a subfolder")
    return [_generic_scene(p, p.name, root) for p in subs]
