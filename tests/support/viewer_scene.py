"""A small scene for the viewer's tests: a coloured plane of Gaussians before camera 0, and a second camera."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.ply import write_ply

WIDTH, HEIGHT, FOCAL = 320, 240, 300.0


@dataclass(frozen=True)
class PlaneScene:
    ply: Path
    cameras: Path
    gaussians: Gaussians
    camera_list: list[Camera]


def plane_gaussians(nx: int = 96, ny: int = 72, depth: float = 3.0) -> Gaussians:
    """A flat, opaque plane at z = ``depth`` covering the middle of camera 0's view; its colour changes in large
    blocks (blue, green, purple, grey: nothing orange, the frusta's colour) and gets lighter to the right."""
    xs = torch.linspace(-1.2, 1.2, nx, dtype=torch.float64)
    ys = torch.linspace(-0.9, 0.9, ny, dtype=torch.float64)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    means = torch.stack([gx, gy, torch.full_like(gx, depth)], -1).reshape(-1, 3)
    block = ((gx > 0).long() + 2 * (gy > 0).long()).reshape(-1)
    palette = torch.tensor([[0.1, 0.2, 0.8], [0.1, 0.6, 0.2], [0.5, 0.1, 0.6], [0.35, 0.35, 0.35]], dtype=torch.float64)
    rgb = (palette[block] + 0.25 * ((gx.reshape(-1) + 1.2) / 2.4)[:, None]).clamp(0, 1)
    step = 2.4 / (nx - 1)
    scales = torch.tensor([step * 0.8, step * 0.8, step * 0.05], dtype=torch.float64).expand(len(means), 3)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(len(means), 4)
    opacities = torch.full((len(means),), 0.98, dtype=torch.float64)
    return Gaussians.from_activated(means, scales.clone(), quats.clone(), opacities, rgb).to(torch.float32)


def plane_cameras() -> list[Camera]:
    K = np.array([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]])
    c2w_1 = np.eye(4)
    a = np.deg2rad(-10.0)
    c2w_1[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    c2w_1[:3, 3] = [0.6, 0.0, 0.1]
    return [Camera("left", WIDTH, HEIGHT, K, np.eye(4)), Camera("right", WIDTH, HEIGHT, K, c2w_1)]


def write_plane_scene(folder: Path) -> PlaneScene:
    """The plane and its two cameras written as ``plane.ply`` and ``plane.cameras.json`` in ``folder``."""
    g = plane_gaussians()
    cams = plane_cameras()
    ply, cameras = folder / "plane.ply", folder / "plane.cameras.json"
    write_ply(ply, g)
    save_cameras(cameras, CameraSet(cams))
    return PlaneScene(ply, cameras, g, cams)
