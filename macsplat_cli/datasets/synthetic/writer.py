"""Write a rendered synthetic scene as a data set folder (the generic layout of :mod:`macsplat_cli.datasets`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from ...cameras import Camera, CameraSet, save_cameras
from ...errors import OutputPathError
from ...images import save_depth, save_image
from .raycast import SyntheticView, render
from .scenes import Scene

__all__ = ["write_dataset"]


def write_dataset(
    folder: str | os.PathLike[str],
    scene: Scene,
    cameras: Sequence[Camera],
    *,
    depth: bool = True,
    supersample: int = 2,
) -> list[SyntheticView]:
    """Render ``cameras`` and write a dataset folder.

    Layout: ``images/<name>.png`` (8-bit RGB), ``depth/<name>.png`` (16-bit, depth in
    millimetres, 0 = no hit; with ``depth``), and ``cameras.json``
    (:func:`~macsplat_cli.cameras.save_cameras`, ``scale="metric"``, ``world="world"``).

    Args:
        folder: output folder (created if missing).
        scene: the scene.
        cameras: the cameras (names unique; used as file stems).
        depth: also write depth maps.
        supersample: anti-aliasing of :func:`render`.

    Returns:
        The rendered views, in the order of ``cameras``.

    Raises:
        OutputPathError: the folder cannot be created or written.
    """
    root = Path(folder)
    camera_set = CameraSet(list(cameras), scale="metric", world="world")
    try:
        (root / "images").mkdir(parents=True, exist_ok=True)
        if depth:
            (root / "depth").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"cannot create {root}: {e.strerror or e}") from e
    views = []
    for cam in camera_set:
        view = render(scene, cam, supersample=supersample)
        save_image(root / "images" / f"{cam.name}.png", view.image)
        if depth:
            save_depth(root / "depth" / f"{cam.name}.png", view.depth)
        views.append(view)
    save_cameras(root / "cameras.json", camera_set)
    return views
