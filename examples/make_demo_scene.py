"""Build ``examples/demo/``: a small procedural Gaussian scene and two cameras.

A sphere with a coloured band pattern standing on a checkerboard floor, about 6,600 flat
Gaussians (SH degree 0), in OpenCV world axes (y down). Regenerate with::

    python examples/make_demo_scene.py examples/demo
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

from macsplat_cli.cameras import Camera, CameraSet, rotmat_to_quat_np, save_cameras
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.ply import write_ply


def _quat_from_normal(n: np.ndarray) -> np.ndarray:
    """(w, x, y, z) rotating local z onto each normal. [N, 3] → [N, 4]"""
    out = np.empty((len(n), 4))
    for i, v in enumerate(n):
        a = np.cross([0.0, 0.0, 1.0], v)
        s, c = np.linalg.norm(a), float(v[2])
        if s < 1e-9:
            out[i] = (1.0, 0.0, 0.0, 0.0) if c > 0 else (0.0, 1.0, 0.0, 0.0)
            continue
        ang = math.atan2(s, c)
        out[i] = (math.cos(ang / 2), *(math.sin(ang / 2) * a / s))
    return out


def build() -> tuple[Gaussians, CameraSet]:
    # sphere: Fibonacci lattice, flat Gaussians tangent to the surface
    n_s, r, centre = 3000, 0.5, np.array([0.0, 0.0, 3.0])
    k = np.arange(n_s) + 0.5
    phi = np.arccos(1 - 2 * k / n_s)
    theta = math.pi * (1 + 5**0.5) * k
    normal = np.stack([np.cos(theta) * np.sin(phi), np.cos(phi), np.sin(theta) * np.sin(phi)], -1)
    s_means = centre + r * normal
    band = (np.floor((phi / math.pi) * 8) % 2)[:, None]
    hue = (theta % (2 * math.pi)) / (2 * math.pi)
    s_rgb = band * np.stack([0.9 * hue, 0.4 + 0.4 * hue, 1 - 0.8 * hue], -1) + (1 - band) * 0.92
    s_scale = np.tile([0.022, 0.022, 0.002], (n_s, 1))
    # floor: y = +0.5 (OpenCV y points down), checkerboard
    g = np.linspace(-1.5, 1.5, 60)
    fx, fz = np.meshgrid(g, g + 3.0)
    f_means = np.stack([fx.ravel(), np.full(fx.size, 0.5), fz.ravel()], -1)
    checker = ((np.floor(fx.ravel() * 2) + np.floor(fz.ravel() * 2)) % 2)[:, None]
    f_rgb = 0.25 + 0.5 * checker * np.array([[1.0, 0.85, 0.6]])
    f_normal = np.tile([0.0, -1.0, 0.0], (fx.size, 1))
    f_scale = np.tile([0.03, 0.03, 0.002], (fx.size, 1))
    means = np.concatenate([s_means, f_means])
    rgb = np.concatenate([s_rgb, f_rgb]).clip(0, 1)
    quats = _quat_from_normal(np.concatenate([normal, f_normal]))
    scales = np.concatenate([s_scale, f_scale])
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    gaussians = Gaussians.from_activated(t(means), t(scales), t(quats), torch.full((len(means),), 0.95), t(rgb))

    def cam(name: str, eye: np.ndarray) -> Camera:
        target = centre + np.array([0.0, 0.15, 0.0])
        z = (target - eye) / np.linalg.norm(target - eye)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
        c2w[:3, 3] = eye
        rotmat_to_quat_np(c2w[:3, :3])  # validates a proper rotation
        K = np.array([[420.0, 0.0, 256.0], [0.0, 420.0, 192.0], [0.0, 0.0, 1.0]])
        return Camera(name, 512, 384, K, c2w)

    cams = CameraSet([cam("left", np.array([-0.9, -0.35, 0.9])), cam("right", np.array([0.9, -0.35, 0.9]))])
    return gaussians, cams


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "examples/demo")
    out.mkdir(parents=True, exist_ok=True)
    gaussians, cams = build()
    write_ply(out / "scene.ply", gaussians)
    save_cameras(out / "cameras.json", cams)
    print(f"wrote {len(gaussians)} Gaussians and {len(cams)} cameras to {out}")


if __name__ == "__main__":
    main()
