"""``reconstruct``'s outputs for other tools: ``--export FORMAT DIR`` (COLMAP, nerfstudio) and ``--up``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, get_args

if TYPE_CHECKING:
    import numpy as np

    from ..camera_formats.export import ExportFormat
    from ..cameras import CameraSet
    from ..gaussians import Gaussians
    from ..pipeline.run import Reconstruction

__all__ = ["OutputExtras", "check_exports", "export_requests", "up_choice", "world_outputs", "write_exports"]

Up = Literal["camera", "auto"]
UP_CHOICES: tuple[Up, ...] = ("camera", "auto")
UP_WORLD = "camera_0_up_y"
"""The cameras file's world name with ``--up auto``: camera 0's frame turned so that the cameras' mean up is +y."""


@dataclass
class OutputExtras:
    """The options beyond the scene and its cameras: each ``--export`` as ``(format, folder)``, ``--force`` (an
    export folder may be replaced), ``--up`` (``camera``: the first camera's frame; ``auto``: mean up on +y)."""

    exports: list[tuple[ExportFormat, Path]] = field(default_factory=list)
    force: bool = False
    up: Up = "camera"


def export_requests(pairs: Sequence[tuple[str, Path]]) -> list[tuple[ExportFormat, Path]]:
    """``--export`` values checked: a known format each, no folder named twice.

    Raises:
        InputError: an unknown format, or one folder for two exports.
    """
    from ..camera_formats.export import EXPORT_FORMATS, ExportFormat
    from ..errors import InputError

    kinds: tuple[ExportFormat, ...] = get_args(ExportFormat)
    out: list[tuple[ExportFormat, Path]] = []
    for fmt, folder in pairs:
        f = next((k for k in kinds if k == fmt.strip().lower()), None)
        if f is None:
            raise InputError(
                f"--export {fmt} {folder}: unknown format {fmt!r} (use one of {', '.join(EXPORT_FORMATS)})"
            )
        if any(Path(folder).resolve() == Path(other).resolve() for _, other in out):
            raise InputError(f"--export {folder}: one folder for two exports")
        out.append((f, Path(folder)))
    return out


def up_choice(text: str) -> Up:
    """``--up`` checked.

    Raises:
        InputError: neither ``camera`` nor ``auto``.
    """
    from ..errors import InputError

    t = text.strip().lower()
    for up in UP_CHOICES:
        if up == t:
            return up
    raise InputError(f"--up {text!r}: use camera (the first camera's frame, the default) or auto (mean up on +y)")


def check_exports(extras: OutputExtras, keep: Sequence[tuple[str, Path | None]], photos: Sequence[Path] = ()) -> None:
    """Every export folder writable before the first stage (:func:`~macsplat_cli.camera_formats.export.
    check_export_folder`); none holds an input or another output; a COLMAP model's photo names are single tokens.

    Raises:
        InputError: one of those is not so.
    """
    from ..camera_formats.export import check_export_folder
    from ..errors import InputError

    for fmt, folder in extras.exports:
        check_export_folder(folder, extras.force, keep)
        spaced = [p.name for p in photos if any(ch.isspace() for ch in p.name)]
        if fmt == "colmap" and spaced:
            raise InputError(f"--export colmap: a COLMAP image name has no spaces; rename the photo {spaced[0]!r}")


def world_outputs(result: Reconstruction, up: str) -> tuple[Gaussians, CameraSet, np.ndarray | None]:
    """The scene, its cameras and the world rotation (None, or ``[3, 3]`` with ``--up auto``) to write them in."""
    import dataclasses

    import numpy as np

    from ..pipeline.world_up import rotate_cameras, rotate_gaussians, up_rotation

    cameras = result.cameras()
    if up != "auto":
        return result.gaussians, cameras, None
    R = up_rotation(cameras)
    turned = dataclasses.replace(rotate_cameras(cameras, R), world=UP_WORLD)
    return rotate_gaussians(result.gaussians, R), turned, np.asarray(R)


def write_exports(result: Reconstruction, extras: OutputExtras, rotation: np.ndarray | None) -> dict[str, Path]:
    """Each ``--export`` folder written (whole or not at all); role → folder."""
    from ..camera_formats.export import write_export
    from ..pipeline.sparse import export_cameras, sparse_points
    from ..pipeline.world_up import rotate_cameras, rotate_points

    if not extras.exports:
        return {}
    cameras, photos = export_cameras(result)
    points = sparse_points(result, cameras)
    if rotation is not None:
        cameras, points = rotate_cameras(cameras, rotation), rotate_points(points, rotation)
    written = {}
    for fmt, folder in extras.exports:
        written[f"export {fmt}"] = write_export(fmt, folder, cameras, points, photos)
    return written
