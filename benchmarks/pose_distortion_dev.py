"""Why two NYU dining pairs are written with a wrong pose (issue 25): the Kinect's lens distortion.

    python -m benchmarks.pose_distortion_dev --data ../shared/data

For the NYU pairs of ``accuracy_dev.py`` (given intrinsics), the pose search's accepted pose and what the putative
matches of its tier say about it and about the ground truth:

* the rotation error of our pose, and of the pose re-estimated from the same putative matches undistorted with the
  NYU Depth v2 RGB calibration (``NYU_DISTORTION``: the photos are not undistorted, the intrinsics file carries none);
* PnP (EPnP + RANSAC, 4 px) from the view-0 sensor depth at those matches to their view-1 pixels: evidence that does
  not go through the epipolar geometry — its rotation against the ground truth and against ours;
* the median Sampson distance of the matches to our pose and to the ground truth (original pixels);
* the rotation error when the intrinsics file carries that distortion (``distortion`` in the cameras schema, issue
  42): the pipeline undistorts the photos at load and runs the whole pose search on them (``given dist. °``).

No test on the matches alone can refuse such a pose: the distorted matches fit it better than the true one. The data
are third-party and not in the repository (``../shared/data``).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import cv2
import numpy as np

from benchmarks._common import print_header, row
from benchmarks._dev import c2w, dev_frames
from benchmarks._pose_cases import _allow_low_confidence
from benchmarks.accuracy_dev import CASES, pipeline_config
from macsplat_cli.cameras import load_cameras, save_cameras
from macsplat_cli.datasets.base import read_depth
from macsplat_cli.distortion import Distortion
from macsplat_cli.errors import MacsplatError
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.pose import PoseConfig, estimate_pose, fundamental_from_pose, sampson_distance
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig
from macsplat_cli.pipeline.views import load_views

NYU_DISTORTION = np.array([0.2079, -0.5844, -0.0007, 0.0004, 0.4974])
"""The NYU Depth v2 toolbox's RGB distortion (k1, k2, p1, p2, k3)."""
HEADER = [
    "pair", "putative", "ours °", "undistorted °", "PnP vs GT °", "PnP vs ours °", "Sampson ours px", "Sampson GT px",
    "given dist. °",
]  # fmt: skip


def given_distortion_error(cfg: ReconstructConfig, paths: list[Path], R_gt: np.ndarray, size: int) -> str:
    """The pose search's rotation error (°) with ``NYU_DISTORTION`` in the intrinsics file: the photos undistorted
    at load, as ``reconstruct --intrinsics`` does."""
    if cfg.views.intrinsics is None:
        raise ValueError("given_distortion_error needs the intrinsics file of the run")
    cams = load_cameras(cfg.views.intrinsics)
    cams.cameras = [dataclasses.replace(c, distortion=Distortion("opencv", tuple(NYU_DISTORTION))) for c in cams]
    path = Path(tempfile.mkdtemp()) / "k_distortion.json"
    save_cameras(path, cams)
    cfg = dataclasses.replace(cfg, views=dataclasses.replace(cfg.views, intrinsics=path, size=size))
    try:
        g = Pipeline(cfg).search(load_views(paths, cfg.views)).geometry
    except MacsplatError as e:
        return f"failed: {e}"[:40]
    return f"{rotation_error_deg(g.R, R_gt):.2f}"


def measure(frames: list, pair: tuple[int, int], size: int) -> list[str]:
    """One table row for the frames ``pair``."""
    f0, f1 = frames[pair[0]], frames[pair[1]]
    cfg = pipeline_config((f0, f1))
    cfg.views.size = size
    _allow_low_confidence(cfg)
    views = load_views([f0.image, f1.image], cfg.views)
    result = Pipeline(cfg).search(views)
    g, m = result.geometry, result.evidence
    T = np.linalg.inv(c2w(f1)) @ c2w(f0)
    R_gt, t_gt = T[:3, :3], T[:3, 3]
    K = views[0].K
    u0, u1 = (cv2.undistortPoints(xy.reshape(-1, 1, 2), K, NYU_DISTORTION, P=K).reshape(-1, 2) for xy in (m.xy0, m.xy1))
    try:
        und = estimate_pose(views[0], views[1], dataclasses.replace(m, xy0=u0, xy1=u1), PoseConfig())
        und_err = f"{rotation_error_deg(und.R, R_gt):.2f}"
    except MacsplatError as e:
        und_err = f"failed: {e}"[:40]
    # original pixels: the sensor depth and the ground-truth K are at the photo's own resolution
    s = f0.camera.width / views[0].width
    xy0, xy1, Kf = m.xy0 * s, m.xy1 * s, f0.camera.K
    depth = read_depth(f0.depth, f0.depth_scale)
    ij = np.clip(np.floor(xy0).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
    z = depth[ij[:, 1], ij[:, 0]]
    ok = z > 0
    X = np.c_[(xy0[:, 0] - Kf[0, 2]) / Kf[0, 0], (xy0[:, 1] - Kf[1, 2]) / Kf[1, 1], np.ones(len(z))] * z[:, None]
    _, rvec, _, _ = cv2.solvePnPRansac(X[ok], xy1[ok], Kf, None, reprojectionError=4.0, iterationsCount=5000,
                                       flags=cv2.SOLVEPNP_EPNP)  # fmt: skip
    R_pnp = cv2.Rodrigues(rvec)[0]
    samp = [
        float(np.median(np.abs(sampson_distance(fundamental_from_pose(R, t / np.linalg.norm(t), Kf, Kf), xy0, xy1))))
        for R, t in ((g.R, g.t), (R_gt, t_gt))
    ]
    return [
        f"{pair}", str(len(m)), f"{rotation_error_deg(g.R, R_gt):.2f}", und_err,
        f"{rotation_error_deg(R_pnp, R_gt):.2f}", f"{rotation_error_deg(R_pnp, g.R):.2f}", f"{samp[0]:.2f}",
        f"{samp[1]:.2f}", given_distortion_error(cfg, [f0.image, f1.image], R_gt, size),
    ]  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the shared data folder (../shared/data)")
    ap.add_argument("--size", type=int, default=512, help="working long side, as reconstruct's default")
    args = ap.parse_args()
    frames = dev_frames(args.data, "nyu_dining")
    print_header(HEADER, "l" + "r" * (len(HEADER) - 1))
    for scene, _, pair in CASES:
        if scene == "nyu_dining":
            print(row(measure(frames, pair, args.size)), flush=True)


if __name__ == "__main__":
    main()
