"""The neural stages' test scene: a ray-traced 96×64 room pair whose photos reach the network pixel for pixel, and
:class:`OracleBackbone`, a stand-in for MASt3R that returns the pair's exact point maps."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.neural import BackboneConfig, BackboneView

from .scenes import PairFiles, PairSpec

__all__ = ["PAIR", "SIZE", "OracleBackbone", "Scene", "backproject"]

SIZE = (96, 64)  # multiples of 16: the working images are the rendered ones, pixel for pixel
PAIR = PairSpec("room", 20.0, SIZE, fov_deg=50.0)
"""A room pair 20° apart, 50° field of view (not the pipeline's 60° prior)."""


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points of a depth map (pixel centres at +0.5). [H, W] → [H, W, 3]"""
    h, w = depth.shape
    ys, xs = np.mgrid[0:h, 0:w]
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones((h, w))], -1)
    return pix @ np.linalg.inv(K).T * depth[..., None]


class Scene:
    """The :data:`PAIR` photos (``a``, ``b``), their true cameras and depths, and the true relative pose (R, t)."""

    def __init__(self, files: PairFiles) -> None:
        assert files.rendered.spec == PAIR, files.rendered.spec
        self.cam0, self.cam1 = files.rendered.cams
        self.depth0, self.depth1 = files.rendered.depths
        self.a, self.b = files.a, files.b
        self.R, self.t = syn.relative_pose(self.cam0, self.cam1)


class OracleBackbone(torch.nn.Module):
    """Stands in for MASt3R: the true point maps of a scene (both in camera 0's frame), descriptors that
    are a fixed random function of the 3-D point (so that matching works), and constant confidences."""

    def __init__(self, scene: Scene) -> None:
        super().__init__()
        self.config = BackboneConfig.tiny()
        P0 = backproject(scene.depth0, scene.cam0.K)
        P1 = (backproject(scene.depth1, scene.cam1.K) - scene.t) @ scene.R  # camera 1 → camera 0
        rng = np.random.default_rng(0)
        omega = rng.standard_normal((256, 3)) * 2 * np.pi / 0.3  # descriptors vary over ~30 cm (a few pixels)
        mix = rng.standard_normal((256, 24))

        def describe(P: np.ndarray) -> torch.Tensor:
            Xw = P @ scene.cam0.cam_to_world[:3, :3].T + scene.cam0.cam_to_world[:3, 3]
            return F.normalize(torch.from_numpy(np.cos(Xw @ omega.T) @ mix).float(), dim=-1)[None]

        self.pts = [torch.from_numpy(p).float()[None] for p in (P0, P1)]
        self.desc = [describe(P0), describe(P1)]
        self.calls = 0

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[BackboneView, BackboneView]:
        self.calls += 1
        h, w = img1.shape[2:]
        assert self.pts[0].shape[1:3] == (h, w), "the images must reach the network at their working size"
        views = []
        for pts, desc in zip(self.pts, self.desc):
            conf = torch.full((1, h, w), 5.0)
            views.append(BackboneView(pts, conf, desc, torch.full((1, h, w), 3.0), (), (h // 16, w // 16)))
        return views[0], views[1]
