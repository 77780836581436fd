"""Which pose do the matches support: ours or the data set's? (NYU dining pairs of accuracy_dev.py)

    python -m benchmarks.pose_agreement_dev --data ../shared/data

For each pair, with the data's intrinsics: our pose's and the data's pose's Sampson errors
over our verified matches (median, and the fraction under 1 px), next to the angle between
the two poses.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks._common import pair_pose
from benchmarks._dev import c2w, dev_frames, save_intrinsics
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.metrics import rotation_error_deg, translation_direction_error_deg
from macsplat_cli.pipeline.pose import fundamental_from_pose, sampson_distance
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.pipeline.views import ViewConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the shared dev data folder")
    ap.add_argument("--scene", default="nyu_dining")
    args = ap.parse_args()
    frames = dev_frames(args.data, args.scene)
    print(
        "| pair | verified | rot ° ours vs data | t ° ours vs data | Sampson px ours (median, <1 px) "
        "| Sampson px data's pose (median, <1 px) |"
    )
    print("|---|---:|---:|---:|---|---|")
    for pair in [(0, 2), (1, 4), (0, 4)]:
        f0, f1 = frames[pair[0]], frames[pair[1]]
        tmp = save_intrinsics(Path(tempfile.mkdtemp()) / "k.json", (f0, f1))
        rec = reconstruct(
            [f0.image, f1.image], EngineConfig(pipeline=ReconstructConfig(views=ViewConfig(intrinsics=tmp)))
        )
        g = pair_pose(rec).geometry
        T = np.linalg.inv(c2w(f1)) @ c2w(f0)
        R_gt, t_gt = T[:3, :3], T[:3, 3] / np.linalg.norm(T[:3, 3])
        m = g.inliers
        ours = np.abs(sampson_distance(fundamental_from_pose(g.R, g.t, g.K0, g.K1), m.xy0, m.xy1))
        data = np.abs(sampson_distance(fundamental_from_pose(R_gt, t_gt, g.K0, g.K1), m.xy0, m.xy1))
        print(
            f"| ({pair[0] + 1},{pair[1] + 1}) | {len(m)} | {rotation_error_deg(g.R, R_gt):.2f} "
            f"| {translation_direction_error_deg(g.t, t_gt):.1f} | {np.median(ours):.2f}, {np.mean(ours < 1):.0%} "
            f"| {np.median(data):.2f}, {np.mean(data < 1):.0%} |"
        )


if __name__ == "__main__":
    main()
