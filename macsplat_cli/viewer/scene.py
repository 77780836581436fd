"""What the browser viewer is sent: the Gaussians as the WebGL splat renderer takes them, and the cameras.

No viser import here: these are plain arrays, tested on their own. Conventions (``cameras.py``): OpenCV axes, the
world frame of the scene's cameras; the viewer's camera and frusta use the same axes (x right, y down, z forward),
so a camera's ``cam_to_world`` is its frustum's pose unchanged.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..cameras import Camera
from ..gaussians import Gaussians
from ..rotations import rotmat_to_quat_np
from ..sh import sh0_to_rgb

__all__ = [
    "SplatArrays",
    "ViewPose",
    "camera_pose",
    "find_image",
    "load_thumbnails",
    "splat_arrays",
    "thin_out",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SplatArrays:
    """The scene as viser's ``add_gaussian_splats`` takes it (view-independent colour: SH band 0)."""

    centers: np.ndarray  # [N, 3] float32
    covariances: np.ndarray  # [N, 3, 3] float32, world frame
    rgbs: np.ndarray  # [N, 3] float32 in [0, 1]
    opacities: np.ndarray  # [N, 1] float32 in (0, 1)

    def __len__(self) -> int:
        return int(self.centers.shape[0])


def splat_arrays(g: Gaussians) -> SplatArrays:
    """``g`` (finite Gaussians only; the others are left out) → :class:`SplatArrays`."""
    with torch.no_grad():
        g = g.detach().to(dtype=torch.float32)
        g = g[g.finite_mask().nonzero().squeeze(1)]
        rgb = sh0_to_rgb(g.sh[:, 0, :]).clamp(0.0, 1.0)
        return SplatArrays(
            centers=g.means.numpy().astype(np.float32, copy=True),
            covariances=g.covariances().numpy().astype(np.float32, copy=True),
            rgbs=rgb.numpy().astype(np.float32, copy=True),
            opacities=g.opacities[:, None].numpy().astype(np.float32, copy=True),
        )


def thin_out(g: Gaussians, budget: int) -> Gaussians:
    """The ``budget`` Gaussians that cover the most: opacity × the area of the two largest axes (a view-free
    stand-in for the compaction's screen-space importance, which needs the cameras). ``g`` itself when it fits."""
    if len(g) <= budget:
        return g
    with torch.no_grad():
        s = torch.sort(g.log_scales.detach(), dim=1).values
        score = torch.log(g.opacities.detach().clamp_min(1e-12)) + s[:, 1] + s[:, 2]
        keep = torch.topk(torch.nan_to_num(score, nan=-torch.inf), budget).indices.sort().values
    return g[keep]


@dataclass(frozen=True)
class ViewPose:
    """A viewpoint as the viewer takes it: position, orientation (wxyz, camera-to-world, OpenCV axes), the point
    looked at (one unit ahead), the up direction (the camera's −y) and the vertical field of view (radians)."""

    position: np.ndarray  # [3]
    wxyz: np.ndarray  # [4]
    look_at: np.ndarray  # [3]
    up: np.ndarray  # [3]
    fov_y: float
    aspect: float


def camera_pose(camera: Camera) -> ViewPose:
    """The viewer's form of ``camera`` (its vertical field of view from fy and the height; the principal point is
    taken at the centre, as the viewer's camera has it)."""
    c2w = np.asarray(camera.cam_to_world, dtype=np.float64)
    R, t = c2w[:3, :3], c2w[:3, 3]
    fy = float(camera.K[1, 1])
    return ViewPose(
        position=t.copy(),
        wxyz=rotmat_to_quat_np(R),
        look_at=t + R[:, 2],
        up=-R[:, 1],
        fov_y=float(2.0 * np.arctan(camera.height / (2.0 * fy))),
        aspect=camera.width / camera.height,
    )


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff", ".bmp")
MAX_NAME_BYTES = 255
"""Longest file name (UTF-8 bytes) a camera's photo can have: the limit of every common file system (NAME_MAX);
a longer camera name has no photo (the system would refuse the look-up)."""
SHOWN_NAME_CHARS = 80
"""A camera name in a log line or the page is cut to this many characters: a cameras file may hold megabytes."""


def short_name(name: str) -> str:
    """``name`` as logs and the page show it: at most :data:`SHOWN_NAME_CHARS` characters, "…" where cut."""
    return name if len(name) <= SHOWN_NAME_CHARS else name[: SHOWN_NAME_CHARS - 1] + "…"


def find_image(name: str, folders: list[Path]) -> Path | None:
    """The photo of the camera ``name`` in the first folder that has it: ``folder / name``, its base name, or the
    name with an image suffix (``reconstruct`` names cameras by the photo's stem). None when none is found.

    A photo is only looked for inside ``folders``, as the data-set loaders read their files
    (:func:`~macsplat_cli.datasets.base.member_path`, :func:`~macsplat_cli.datasets.base.check_inside`): a name
    that is absolute, has a ``..`` component or a part over :data:`MAX_NAME_BYTES` has no photo, and neither has a
    candidate that is a link leading out of its folder."""
    return _locate(name, folders)[0]


def _locate(name: str, folders: list[Path]) -> tuple[Path | None, str | None]:
    """:func:`find_image`'s answer, and why a photo that was named is not taken (None: not refused, maybe absent)."""
    from ..datasets.base import check_inside, member_path
    from ..errors import DatasetError

    parts = [p for p in re.split(r"[\\/]", name) if p]
    try:
        member_path(Path("."), name, "camera", subfolders=True)
    except DatasetError:
        return None, "its name is no file name inside the photo folders (absolute, with a '..' part, or empty)"
    if any(len(p.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES for p in parts):
        return None, f"its name is longer than a file name can be ({MAX_NAME_BYTES} bytes)"
    why = None
    for folder in folders:
        candidates = [folder / name, folder / parts[-1]] + [folder / (parts[-1] + s) for s in IMAGE_SUFFIXES]
        candidates += [folder / (parts[-1] + s.upper()) for s in IMAGE_SUFFIXES]
        for candidate in candidates:
            try:
                if candidate.is_file():
                    return check_inside(candidate, [folder], "photo"), None
            except DatasetError:
                why = f"its photo {short_name(str(candidate))} is a link out of {folder}"
            except (OSError, ValueError):  # a path the system refuses (too long as a whole)
                continue
    return None, why


def load_thumbnails(cameras: list[Camera], folders: list[Path], long_side: int) -> dict[str, np.ndarray]:
    """Camera name → its photo, at most ``long_side`` px, [h, w, 3] uint8, for the cameras whose photo is found
    inside ``folders`` (:func:`find_image`) and readable (the others are drawn without one; logged)."""
    import cv2

    from ..errors import MacsplatError
    from ..images import load_image, to_uint8

    out: dict[str, np.ndarray] = {}
    for camera in cameras:
        path, why = _locate(camera.name, folders)
        if path is None:
            if why is None:
                logger.debug("no photo found for camera %s", short_name(camera.name))
            else:
                logger.warning("camera %s is drawn without a photo: %s", short_name(camera.name), why)
            continue
        try:
            rgb = load_image(path).rgb
        except MacsplatError as e:
            logger.warning("photo of camera %s not shown: %s", short_name(camera.name), e)
            continue
        h, w = rgb.shape[:2]
        f = min(1.0, long_side / max(h, w))
        if f < 1.0:
            rgb = cv2.resize(rgb, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
        out[camera.name] = to_uint8(rgb)
    return out
