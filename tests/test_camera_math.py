"""camera_math: the shared pinhole arithmetic."""

import math

import numpy as np
import torch

from macsplat_cli.camera_math import project_points, rescale_intrinsics, scale_focal
from macsplat_cli.cameras import Camera


def test_rescale_intrinsics_matches_camera_rescaled():
    K = np.array([[500.0, 0.5, 320.0], [0.0, 490.0, 240.0], [0, 0, 1]])
    cam = Camera("a", 640, 480, K, np.eye(4))
    assert np.array_equal(rescale_intrinsics(K, 0.5, 0.25), cam.rescaled(320, 120).K)
    assert rescale_intrinsics(K, 1.0, 1.0) is not K


def test_scale_focal_keeps_principal_point():
    K = np.array([[500.0, 0.5, 320.0], [0.0, 490.0, 240.0], [0, 0, 1]])
    assert scale_focal(K, 0.0) is K
    Ks = scale_focal(K, math.log(2.0))
    assert np.allclose(Ks[[0, 0, 1], [0, 1, 1]], 2.0 * K[[0, 0, 1], [0, 1, 1]], rtol=4 * np.finfo(float).eps)
    assert np.array_equal(Ks[:, 2], K[:, 2]) and np.array_equal(K[0, 0], 500.0)


def test_project_points_pixels_and_inside():
    K = torch.tensor([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = torch.tensor([0.0, 0.0, 1.0])  # the camera one unit behind the origin
    pts = torch.tensor([[0.0, 0, 1], [0.2, -0.1, 1], [0, 0, -2], [5, 0, 1], [float("nan"), 0, 1]], dtype=torch.float64)
    col, row, z, inside = project_points(pts, w2c, K, (80, 100))
    assert inside.tolist() == [True, True, False, False, False]
    # (0, 0, 2) → (50, 40); (0.2, -0.1, 2) → (60, 35)
    assert col[:2].tolist() == [50, 60] and row[:2].tolist() == [40, 35]
    assert z[:3].tolist() == [2.0, 2.0, -1.0]
    assert col[2:].tolist() == [0, 0, 0] and row[2:].tolist() == [0, 0, 0]
