"""Why ICL (0, 2) is written with a wrong pose at the given intrinsics: two poses fit the same matches.

    python -m benchmarks.pose_ambiguity_dev --data ../shared/data [--pairs 0,2 1,4]

For ICL-NUIM living-room pairs (frame positions, 0-based; exact ground-truth poses and depth), with the data's
intrinsics and ``--matcher auto``, the accepted pose and what the putative matches of its tier say about it:

* PnP (EPnP + RANSAC, 4 px, then refined) from the view-0 ground-truth depth at the tier's verified matches to their
  view-1 pixels: are the matches true correspondences? (evidence that does not go through the epipolar geometry);
* the median Sampson distance of the putative matches to our pose and to the ground truth;
* the pose re-fitted on the putative matches from the ground truth (``refit_pose``): its support (Sampson < 1 px, in
  front) against ours re-fitted the same way — a second minimum as good as ours is an ambiguity the matches cannot
  settle;
* the best rival from the decomposition of the putative matches' homography (refitted, distinct from ours by
  ``SAME_SOLUTION_DEG``): its support over ours, and the duel of ``resolve_planar`` on all the matches (gated and
  below the gate): (matches ours explains and the rival refutes, the converse).

Measured: benchmarks/history/pose.md (2026-11-29). The data are third-party and not in the repository.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import cv2
import numpy as np

from benchmarks._common import print_header, row
from benchmarks._dev import c2w, dev_frames, save_intrinsics
from macsplat_cli.datasets.base import read_depth
from macsplat_cli.engine import EngineConfig
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.pose import PoseConfig, fundamental_from_pose, sampson_distance
from macsplat_cli.pipeline.pose import search as pose_search
from macsplat_cli.pipeline.pose.geometry import decompose_homography, same_pose, support
from macsplat_cli.pipeline.pose.planar import SAME_SOLUTION_DEG, resolve_planar
from macsplat_cli.pipeline.pose.refit import POSE_LM, refit_pose
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig
from macsplat_cli.pipeline.views import ViewConfig, load_views

HEADER = [
    "pair", "tier", "putative", "ours °", "PnP vs GT °", "PnP vs ours °", "Sampson ours / GT px",
    "GT-start refit ° / support vs ours", "plane rival ° / support vs ours", "duel (ours, rival)",
]  # fmt: skip


def _refit(R: np.ndarray, t: np.ndarray, g, xy0: np.ndarray, xy1: np.ndarray):  # noqa: ANN001, ANN202
    fit = refit_pose(R, t / np.linalg.norm(t), g.K0, g.K1, xy0, xy1, schedule=POSE_LM, unknown=(False, False))
    return fit.R, fit.t, int(support(fit.R, fit.t, g.K0, g.K1, xy0, xy1, PoseConfig().threshold_px).sum())


def _pnp(f0, g, R_gt: np.ndarray, view_width: int) -> tuple[float, float]:  # noqa: ANN001
    """PnP from the view-0 ground-truth depth at the verified matches: rotation vs GT and vs ours (°)."""
    s = f0.camera.width / view_width
    xy0, xy1, Kf = g.inliers.xy0 * s, g.inliers.xy1 * s, f0.camera.K
    depth = read_depth(f0.depth, f0.depth_scale)
    ij = np.clip(np.floor(xy0).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
    z = depth[ij[:, 1], ij[:, 0]]
    ok = z > 0
    X = np.c_[(xy0[:, 0] - Kf[0, 2]) / Kf[0, 0], (xy0[:, 1] - Kf[1, 2]) / Kf[1, 1], np.ones(len(z))] * z[:, None]
    _, rvec, tvec, inl = cv2.solvePnPRansac(X[ok], xy1[ok], Kf, None, reprojectionError=4.0, iterationsCount=5000,
                                            flags=cv2.SOLVEPNP_EPNP)  # fmt: skip
    k = inl[:, 0]
    _, rvec, _ = cv2.solvePnP(X[ok][k], xy1[ok][k], Kf, None, rvec, tvec, useExtrinsicGuess=True)
    R = cv2.Rodrigues(rvec)[0]
    return rotation_error_deg(R, R_gt), rotation_error_deg(R, g.R)


def measure(frames: list, pair: tuple[int, int]) -> list[str]:
    """One table row for the frames ``pair``."""
    f0, f1 = frames[pair[0]], frames[pair[1]]
    cfg = ReconstructConfig(views=ViewConfig(intrinsics=save_intrinsics(Path(tempfile.mkdtemp()) / "k.json", (f0, f1))))
    settings = EngineConfig(pipeline=cfg, matcher="auto").settings()
    settings.pipeline.search = dataclasses.replace(settings.pipeline.search, accept_low_confidence=True)
    attempts: list = []
    chain = pose_search.PoseSearch._chain

    def recorded(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        attempts.append(chain(self, *a, **k))
        return attempts[-1]

    pose_search.PoseSearch._chain = recorded  # type: ignore[method-assign]
    try:
        views = load_views([f0.image, f1.image], settings.pipeline.views)
        res = Pipeline(settings.pipeline).search(views)
    finally:
        pose_search.PoseSearch._chain = chain  # type: ignore[method-assign]
    g = next(a.geometry for a in reversed(attempts) if a.tier == res.tier and a.geometry is not None)
    m = next(a.matches for a in reversed(attempts) if a.tier == res.tier and a.geometry is not None)
    T = np.linalg.inv(c2w(f1)) @ c2w(f0)
    R_gt, t_gt = T[:3, :3], T[:3, 3] / np.linalg.norm(T[:3, 3])
    xy0, xy1 = m.xy0.astype(np.float64), m.xy1.astype(np.float64)
    samp = [float(np.median(np.abs(sampson_distance(fundamental_from_pose(R, t, g.K0, g.K1), xy0, xy1))))
            for R, t in ((g.R, g.t), (R_gt, t_gt))]  # fmt: skip
    Ro, to, own = _refit(g.R, g.t, g, xy0, xy1)
    Rg, _, n_gt = _refit(R_gt, t_gt, g, xy0, xy1)
    H, _ = cv2.findHomography(xy0, xy1, cv2.RANSAC, 1.5)
    rival: tuple[int, tuple[np.ndarray, np.ndarray] | None] = (0, None)
    for R, t in zip(*decompose_homography(np.linalg.inv(g.K1) @ H @ g.K0)):
        for sign in (1.0, -1.0):
            Rc, tc, n = _refit(R, sign * t.ravel(), g, xy0, xy1)
            if n > rival[0] and not same_pose(Rc, tc, Ro, to, SAME_SOLUTION_DEG):
                rival = (n, (Rc, tc))
    duel, rival_cell = "–", "none"
    if rival[1] is not None:
        bg = m.below_gate
        a0 = np.vstack([xy0, bg.xy0]) if bg is not None else xy0
        a1 = np.vstack([xy1, bg.xy1]) if bg is not None else xy1
        v = resolve_planar([(Ro, to), rival[1]], g.K0, g.K1, a0, a1, PoseConfig())
        ex = v.exclusive if v.support[0] >= v.support[1] else v.exclusive[::-1]
        duel = f"{ex[0]}, {ex[1]}"
        rival_cell = f"{rotation_error_deg(rival[1][0], R_gt):.1f} / {rival[0]} vs {own}"
    pnp = _pnp(f0, g, R_gt, views[0].width)
    return [
        f"{pair}", res.tier + (" +guided" if res.guided else ""), str(len(m)), f"{rotation_error_deg(g.R, R_gt):.2f}",
        f"{pnp[0]:.2f}", f"{pnp[1]:.2f}", f"{samp[0]:.2f} / {samp[1]:.2f}",
        f"{rotation_error_deg(Rg, R_gt):.1f} / {n_gt} vs {own}", rival_cell, duel,
    ]  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the shared data folder (../shared/data)")
    ap.add_argument("--pairs", nargs="+", default=["0,2"], help="ICL frame positions, 0-based (e.g. 0,2 1,4)")
    args = ap.parse_args()
    frames = dev_frames(args.data, "icl_livingroom")
    print_header(HEADER, "ll" + "r" * (len(HEADER) - 2))
    for p in args.pairs:
        i, j = map(int, p.split(","))
        print(row(measure(frames, (i, j))), flush=True)


if __name__ == "__main__":
    main()
