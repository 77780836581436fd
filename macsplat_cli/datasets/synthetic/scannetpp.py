"""Small ScanNet++-layout trees rendered from the synthetic scenes (no real ScanNet++ may be redistributed).

:func:`write_scannetpp` writes ``<root>/splits/`` and ``<root>/data/<scene>/`` in one of three
layouts (reference notes §4.1–4.3):

* ``"undistorted"`` — ``dslr/resized_undistorted_images/DSC%05d.JPG`` (pinhole renders),
  ``dslr/undistorted_depths/DSC%05d.png``, ``nerfstudio/transforms_undistorted.json`` (PINHOLE)
  and the fisheye ``nerfstudio/transforms.json``, ``colmap/``, ``train_test_lists.json``;
* ``"fisheye"`` — ``dslr/resized_images/DSC%05d.JPG`` rendered through an ``OPENCV_FISHEYE``
  lens (each sample's ray from the inverse Kannala–Brandt model, solved by Newton's method,
  independently of OpenCV), ``dslr/render_depth/DSC%05d.png``, ``nerfstudio/transforms.json``,
  ``colmap/`` (``OPENCV_FISHEYE``), ``train_test_lists.json``; no undistorted files;
* ``"iphone"`` — ``iphone/rgb/frame_%06d.jpg``, ``iphone/depth/frame_%06d.png`` at half the
  image size (as the LiDAR's lower resolution), ``iphone/pose_intrinsic_imu.json``
  (``intrinsic`` for the 1920×1440 video, ``aligned_pose`` = OpenCV camera-to-world).

The ground truth (:func:`scannetpp_cameras`) is the pinhole camera of each frame: the one the
toolkit's undistortion gives for the fisheye lens (:func:`~macsplat_cli.datasets.scannetpp.pinhole_K`),
at OpenCV camera-to-world poses on an orbit. Depth maps are uint16 millimetres.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..._atomic import atomic_write_text
from ...cameras import Camera, rotmat_to_quat_np
from ...errors import InputError
from ...images import save_depth, save_image
from ..scannetpp import IPHONE_VIDEO_SIZE, Lens, opencv_to_nerfstudio, pinhole_K
from .orbits import orbit_cameras
from .raycast import cast_rays, render
from .scenes import Scene, make_scene

__all__ = ["SCANNETPP_LAYOUTS", "fisheye_lens", "render_fisheye", "scannetpp_cameras", "write_scannetpp"]

SCANNETPP_LAYOUTS = ("undistorted", "fisheye", "iphone")
_DIST = (-0.03, 0.012, -0.004, 0.0008)


def fisheye_lens(size: tuple[int, int]) -> Lens:
    """The synthetic DSLR lens: ``OPENCV_FISHEYE``, ``f = 0.6·W``, centred, mild ``k1..k4``."""
    w, h = size
    f = 0.6 * w
    return Lens(w, h, np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]]), "OPENCV_FISHEYE", _DIST)


def _frame_names(layout: str, n: int) -> list[str]:
    return [f"frame_{i:06d}.jpg" if layout == "iphone" else f"DSC{i:05d}.JPG" for i in range(n)]


def scannetpp_cameras(
    kind: str, *, frames: int = 6, size: tuple[int, int] = (96, 64), layout: str = "undistorted"
) -> list[Camera]:
    """The ground-truth pinhole cameras of a scene of :func:`write_scannetpp` (named like its image files).

    ``K`` is :func:`~macsplat_cli.datasets.scannetpp.pinhole_K` of :func:`fisheye_lens`; poses
    (OpenCV camera-to-world) lie on an orbit of ±25° azimuth around the scene's target.
    """
    w, h = size
    K = pinhole_K(fisheye_lens(size))
    az = np.linspace(-25.0, 25.0, frames) if frames > 1 else [0.0]
    orbit = orbit_cameras(kind, [float(a) for a in az], width=w, height=h, fov_deg=60.0)  # type: ignore[arg-type]
    return [Camera(n, w, h, K, c.cam_to_world) for n, c in zip(_frame_names(layout, frames), orbit)]


def _fisheye_rays(lens: Lens, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates (x/z, y/z) of fisheye image points (pixel centres at +0.5). [N] each"""
    xd = (px - lens.K[0, 2]) / lens.K[0, 0]
    yd = (py - lens.K[1, 2]) / lens.K[1, 1]
    rd = np.hypot(xd, yd)
    k1, k2, k3, k4 = lens.dist
    theta = rd.copy()
    for _ in range(30):  # θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸) = r_d
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - rd
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        theta = theta - f / df
    scale = np.where(rd > 1e-12, np.tan(theta) / np.maximum(rd, 1e-12), 1.0)
    return xd * scale, yd * scale


def render_fisheye(scene: Scene, camera: Camera, lens: Lens, *, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Render ``scene`` through a fisheye ``lens`` at ``camera``'s pose.

    Colour: the mean of ``supersample²`` rays per pixel; depth: camera-space z of the ray
    through the pixel centre (0 = no hit).

    Returns:
        image [H, W, 3] float32 in [0, 1], depth [H, W] float32.
    """
    W, H, ss = lens.width, lens.height, int(supersample)
    Kp = camera.K  # rays are cast as pinhole pixel coordinates of ``camera``

    def cast(s: int) -> tuple[np.ndarray, np.ndarray]:
        xs = (np.arange(W * s) + 0.5) / s
        ys = (np.arange(H * s) + 0.5) / s
        px, py = np.tile(xs, H * s), np.repeat(ys, W * s)
        x, y = _fisheye_rays(lens, px, py)
        pix = np.stack([Kp[0, 0] * x + Kp[0, 2], Kp[1, 1] * y + Kp[1, 2]], 1)
        hits = cast_rays(scene, camera, pix)
        return hits.color, hits.depth

    color, _ = cast(ss)
    _, depth = cast(1)
    image = color.reshape(H, ss, W, ss, 3).mean(axis=(1, 3))
    return np.ascontiguousarray(image, np.float32), depth.reshape(H, W).astype(np.float32)


def _transforms(lens: Lens, K: np.ndarray, model: str, cams: Sequence[Camera], n_train: int, bad: set[int]) -> str:
    dist = dict(zip(("k1", "k2", "k3", "k4"), lens.dist if model == "OPENCV_FISHEYE" else (0.0,) * 4))
    frames = [
        {
            "file_path": c.name,
            "mask_path": f"{Path(c.name).stem}.png",
            "transform_matrix": opencv_to_nerfstudio(c.cam_to_world).tolist(),
            "is_bad": i in bad,
        }
        for i, c in enumerate(cams)
    ]
    doc = {
        "fl_x": K[0, 0],
        "fl_y": K[1, 1],
        "cx": K[0, 2],
        "cy": K[1, 2],
        "w": lens.width,
        "h": lens.height,
        "camera_model": model,
        **dist,
        "has_mask": False,
        "frames": frames[:n_train],
        "test_frames": frames[n_train:],
    }
    return json.dumps(doc, indent=1)


def _colmap(folder: Path, lens: Lens, cams: Sequence[Camera]) -> None:
    K = lens.K
    params = " ".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *lens.dist))
    atomic_write_text(folder / "cameras.txt", f"# Camera list\n1 OPENCV_FISHEYE {lens.width} {lens.height} {params}\n")
    lines = ["# Image list with two lines of data per image:"]
    for i, c in enumerate(cams, start=1):
        q, t = rotmat_to_quat_np(c.R), c.t
        lines += [f"{i} {' '.join(repr(float(v)) for v in (*q, *t))} 1 {c.name}", ""]
    atomic_write_text(folder / "images.txt", "\n".join(lines) + "\n")
    atomic_write_text(folder / "points3D.txt", "# 3D point list\n")


def _write_scene(sdir: Path, scene: Scene, cams: list[Camera], layout: str, bad: set[int]) -> None:
    lens = fisheye_lens((cams[0].width, cams[0].height))
    n_train = max(len(cams) - 1, 3)
    if layout == "iphone":
        poses = {}
        sx, sy = IPHONE_VIDEO_SIZE[0] / lens.width, IPHONE_VIDEO_SIZE[1] / lens.height
        for i, c in enumerate(cams):
            view = render(scene, c)
            save_image(sdir / "iphone" / "rgb" / c.name, view.image)
            small = render(scene, c.rescaled(lens.width // 2, lens.height // 2), supersample=1)
            save_depth(sdir / "iphone" / "depth" / f"{Path(c.name).stem}.png", small.depth)
            K = c.K.copy()
            K[0] *= sx
            K[1] *= sy
            pose = c.cam_to_world.tolist()
            poses[Path(c.name).stem] = {
                "timestamp": i / 60.0,
                "intrinsic": K.tolist(),
                "pose": pose,
                "aligned_pose": pose,
                "imu": {},
            }
        atomic_write_text(sdir / "iphone" / "pose_intrinsic_imu.json", json.dumps(poses, indent=1))
        return
    dslr = sdir / "dslr"
    for c in cams:
        stem = Path(c.name).stem
        if layout == "fisheye":
            image, depth = render_fisheye(scene, c, lens)
            save_image(dslr / "resized_images" / c.name, image)
            save_depth(dslr / "render_depth" / f"{stem}.png", depth)
        else:
            view = render(scene, c)
            save_image(dslr / "resized_undistorted_images" / c.name, view.image)
            save_depth(dslr / "undistorted_depths" / f"{stem}.png", view.depth)
    ns = dslr / "nerfstudio"
    atomic_write_text(ns / "transforms.json", _transforms(lens, lens.K, "OPENCV_FISHEYE", cams, n_train, bad))
    if layout == "undistorted":
        doc = _transforms(lens, cams[0].K, "PINHOLE", cams, n_train, bad)
        atomic_write_text(ns / "transforms_undistorted.json", doc)
    _colmap(dslr / "colmap", lens, cams)
    names = [c.name for c in cams]
    atomic_write_text(dslr / "train_test_lists.json", json.dumps({"train": names[:n_train], "test": names[n_train:]}))


def write_scannetpp(
    root: str | os.PathLike[str],
    *,
    scenes: Sequence[str] = ("room", "object"),
    frames: int = 6,
    layout: str = "undistorted",
    size: tuple[int, int] = (96, 64),
    seed: int = 0,
    splits: bool = True,
    bad_frames: Sequence[int] = (),
) -> Path:
    """Write a ScanNet++-layout tree (module doc) and return ``root``.

    Args:
        root: the tree's root (created if missing).
        scenes: scene kinds (``"room"``, ``"object"``), also the scene ids; scene ``i`` is
            made with seed ``seed + i``.
        frames: frames per scene (the last one is the test frame of the DSLR layouts when
            there are more than 3).
        layout: ``"undistorted"``, ``"fisheye"`` or ``"iphone"``.
        size: image size (W, H).
        seed: base seed of the scenes.
        splits: write ``splits/nvs_sem_train.txt`` (all scenes but the last) and
            ``splits/nvs_sem_val.txt`` (the last).
        bad_frames: frame indices marked ``is_bad`` in the transforms files.

    Raises:
        InputError: an unknown layout or scene kind, fewer than 3 frames, or duplicate scenes.
    """
    if layout not in SCANNETPP_LAYOUTS:
        raise InputError(f"unknown ScanNet++ layout {layout!r}; use one of {', '.join(SCANNETPP_LAYOUTS)}")
    if frames < 3:
        raise InputError(f"a scene needs at least 3 frames, got {frames}")
    if len(set(scenes)) != len(scenes) or not scenes:
        raise InputError(f"scene names must be unique and non-empty, got {list(scenes)}")
    r = Path(root)
    for i, kind in enumerate(scenes):
        scene = make_scene(kind, seed + i)  # type: ignore[arg-type]
        cams = scannetpp_cameras(kind, frames=frames, size=size, layout=layout)
        _write_scene(r / "data" / kind, scene, cams, layout, set(bad_frames))
    if splits:
        names = list(scenes)
        atomic_write_text(r / "splits" / "nvs_sem_train.txt", "".join(f"{s}\n" for s in (names[:-1] or names)))
        atomic_write_text(r / "splits" / "nvs_sem_val.txt", f"{names[-1]}\n")
    return r
