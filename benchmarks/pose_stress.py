"""Pose estimation on degenerate synthetic motions: planar scenes and forward motion under noise.

    python benchmarks/pose_stress.py

Planar: 60 random motions (axis random, rotation 0–20°, unit-direction translation of 0.5)
over a tilted plane 6 units away, 200 correspondences with 0.3 px noise, 320×240 px, focal
300 px; the pose is "right" within 2° / 10°, else "wrong", or refused (ReconstructionError) —
with the planar-ambiguity check (``PoseConfig.planar_fraction``) on and off.

Forward motion: 30 draws of 53 points 4–10 units away, translation (0, 0, 0.5), 1 px noise:
verified matches and the translation-direction error (the 1 px inlier threshold against 1 px
noise).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from macsplat_cli.errors import ReconstructionError
from macsplat_cli.metrics import rotation_error_deg, translation_direction_error_deg
from macsplat_cli.pipeline.pose import PoseConfig, estimate_pose
from macsplat_cli.pipeline.types import Matches, View

W, H = 320, 240
K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])


def _view() -> View:
    return View("v", Path("v.png"), np.zeros((H, W, 3), np.float32), np.ones((H, W), bool), K, (W, H), "file")


def _project(X: np.ndarray, R: np.ndarray, t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    X1 = X @ R.T + t
    p0, p1 = X @ K.T, X1 @ K.T
    xy0, xy1 = p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]
    ok = (X1[:, 2] > 0.1) & np.all((xy0 >= 0) & (xy0 < (W, H)) & (xy1 >= 0) & (xy1 < (W, H)), axis=1)
    return xy0[ok][:n], xy1[ok][:n]


def _errors(R_est: np.ndarray, t_est: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    return rotation_error_deg(R_est, R), translation_direction_error_deg(t_est, t)


def _matches(xy0: np.ndarray, xy1: np.ndarray) -> Matches:
    m = len(xy0)
    return Matches(xy0, xy1, np.ones(m, np.float32), np.arange(m), np.arange(m))


def planar(check: bool) -> tuple[int, int, int]:
    cfg = PoseConfig(planar_fraction=0.8 if check else math.inf)
    right = wrong = refused = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        cv2.setRNGSeed(seed)
        a = rng.normal(size=3)
        R = cv2.Rodrigues(a / np.linalg.norm(a) * math.radians(rng.uniform(0, 20)))[0]
        t = rng.normal(size=3)
        t = t / np.linalg.norm(t) * 0.5
        tilt = rng.uniform(-0.5, 0.5, 2)
        P = np.c_[rng.uniform(-3, 3, (1200, 2)), np.zeros(1200)]
        P[:, 2] = 6 - P[:, :2] @ tilt
        xy0, xy1 = _project(P, R, t, 200)
        xy0, xy1 = xy0 + rng.normal(0, 0.3, xy0.shape), xy1 + rng.normal(0, 0.3, xy1.shape)
        try:
            g = estimate_pose(_view(), _view(), _matches(xy0, xy1), cfg)
        except ReconstructionError:
            refused += 1
            continue
        r, te = _errors(g.R, g.t, R, t)
        right, wrong = (right + 1, wrong) if r < 2 and te < 10 else (right, wrong + 1)
    return right, wrong, refused


def forward() -> tuple[float, float, int]:
    inliers, errs, refused = [], [], 0
    R, t = np.eye(3), np.array([0.0, 0.0, 0.5])
    for seed in range(30):
        rng = np.random.default_rng(seed)
        cv2.setRNGSeed(seed)
        X = np.c_[rng.uniform(-3, 3, (318, 2)), rng.uniform(4, 10, 318)]
        xy0, xy1 = _project(X, R, t, 53)
        xy0, xy1 = xy0 + rng.normal(0, 1, xy0.shape), xy1 + rng.normal(0, 1, xy1.shape)
        try:
            g = estimate_pose(_view(), _view(), _matches(xy0, xy1))
        except ReconstructionError:
            refused += 1
            continue
        inliers.append(len(g.inliers) / len(xy0))
        errs.append(_errors(g.R, g.t, R, t)[1])
    return float(np.median(inliers)), float(np.median(errs)), refused


def main() -> None:
    print("| planar check | right | wrong | refused |\n|---|---:|---:|---:|")
    for check in (True, False):
        print("| {} | {} | {} | {} |".format("on" if check else "off", *planar(check)))
    inl, err, refused = forward()
    print("\n| forward motion, 53 points, 1 px noise | value |\n|---|---:|")
    print(f"| verified fraction of the true matches (median) | {inl:.2f} |")
    print(f"| translation-direction error ° (median) | {err:.1f} |")
    print(f"| refused | {refused} / 30 |")


if __name__ == "__main__":
    main()
