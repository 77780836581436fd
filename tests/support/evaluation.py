"""The evaluation tests' synthetic data: a smoothly textured plane seen by cameras translated along x (coverage and
the visibility mask have closed forms), blank data sets of given cameras, and the ground-truth reconstructor.

Shared by ``test_evaluation.py`` and ``test_cli_eval.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.evaluation import OracleReconstructor
from macsplat_cli.images import save_image
from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig

__all__ = [
    "H",
    "K",
    "ORACLE",
    "PLANE_X",
    "W",
    "Z",
    "SmoothQuad",
    "translated_camera",
    "write_blank_dataset",
    "write_plane_dataset",
]

W, H, Z = 96, 64, 3.0
K = S.intrinsics(W, H, 60.0)
PLANE_X = (0.0, 0.06, 0.09, 0.17, 0.81, 2.26)
"""Camera x positions: every pair's coverage is ≥ 0.03 away from a split threshold."""


class SmoothQuad(S.Quad):
    """A quad with a slowly varying colour (periods of 2.5–3.9 m, i.e. ~70–110 px at 3 m).

    Low frequencies keep the Gaussians' own blur far below 40 dB of error, while a one
    pixel camera error still costs ~10 dB.
    """

    def surface(self, points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        du, dv = self._cache["dual"]
        rel = points - self.origin[:, None]
        u = (du[:, None] * rel).sum(0) * float(np.linalg.norm(self.edge_u))
        v = (dv[:, None] * rel).sum(0) * float(np.linalg.norm(self.edge_v))
        rgb = np.stack(
            [
                0.5 + 0.25 * np.sin(2 * np.pi * u / 3.0),
                0.5 + 0.25 * np.sin(2 * np.pi * v / 2.55 + 1.0),
                0.5 + 0.2 * np.sin(2 * np.pi * (u + v) / 3.9 + 2.0),
            ],
            1,
        )
        return np.repeat(self._cache["normal"][:, None], points.shape[1], axis=1), rgb.astype(np.float32)


def translated_camera(name: str, x: float, yaw_deg: float = 0.0) -> Camera:
    """A W×H camera at (x, 0, 0), turned by ``yaw_deg`` about the y axis."""
    T = np.eye(4)
    T[:3, :3] = S.rotation_about((0, 1, 0), yaw_deg)
    T[0, 3] = x
    return Camera(name, W, H, K, T)


def write_plane_dataset(root: Path, xs: tuple[float, ...] = PLANE_X) -> Path:
    """A generic data set (synthetic.write_dataset) of the smooth plane: 96x64 images + depth."""
    scene = S.Scene([SmoothQuad((-6.0, -4.0, Z), (12.0, 0.0, 0.0), (0.0, 8.0, 0.0))], lighting=None)
    S.write_dataset(root, scene, [translated_camera(f"f{i}", x) for i, x in enumerate(xs)])
    return root


def write_blank_dataset(root: Path, cams: list[Camera]) -> None:
    """A generic data set of black images, one per camera, with its cameras.json."""
    (root / "images").mkdir(parents=True)
    for c in cams:
        save_image(root / "images" / f"{c.name}.png", np.zeros((c.height, c.width, 3), np.uint8))
    save_cameras(root / "cameras.json", CameraSet(cams))


ORACLE = OracleReconstructor(gaussians=GaussianInitConfig(footprint=0.4))
"""The ground-truth reconstructor (Gaussian footprint 0.4), registered as a backend by the tests."""
