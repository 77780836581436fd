"""The plane tie-break's candidates (issue 14): does dense consistency pick the right pose of a plane, and how
accurate is that pose?

    python -m benchmarks.plane_tiebreak --data ../shared/data            # CO3D apple + synthetic orbits
    python -m benchmarks.plane_tiebreak --only co3d --rows              # every case's candidates

For each case (intrinsics given: the tie-break needs them) and each descriptor tier (the primary SIFT and the
wide-baseline tier's affine-simulated SIFT), the tier's filtered matches give the dominant plane
(``dominant_plane``), and ``plane_poses`` scores the plane's physical poses with the primary keypoints, as
``macsplat_cli.pipeline.pose.tiebreak.plane_tiebreak`` does. Per case: the plane's share of the matches, each
candidate's rotation error against the ground truth and its score (guided matches explained off the plane), whether
the tie-break's guards (``PLANE_TIEBREAK_PLANE`` and half of the matches on the plane, ``PLANE_TIEBREAK_MIN``,
``plane_tiebreak_margin``) let the leader through, whether the leader is the candidate nearer the truth (the right
side of the twofold ambiguity) and whether it is within 5°. The pose the pipeline would then re-estimate from the
leader's guided matches stays near the leader (within ``GUIDED_MAX_CHANGE_DEG``), so a leader several degrees off is
a pose several degrees off.

Cases: the 24 CO3D apple pairs of ``pose_confidence.py`` (8–105°) and synthetic orbits (room, object; 20–90°;
field of view 50°/75°; seeds 0, 1).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

from benchmarks import pose_confidence as PC  # the cases and their preparation
from benchmarks._common import progress
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.descriptors import SiftDescriptors
from macsplat_cli.pipeline.matching import match_features
from macsplat_cli.pipeline.pose import WIDE_SIFT, dominant_plane, plane_poses, tiebreak_plane_ok, tiebreak_winner_ok
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.pipeline.views import load_views

RIGHT_DEG = 5.0


def cases(data: Path, only: str | None) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    if only in (None, "co3d"):
        out += [{**c, "given": True} for c in PC.co3d_cases(data) if c["given"]]
    if only in (None, "synthetic"):
        out += [
            {"set": "synthetic", "kind": kind, "angle": angle, "fov": fov, "seed": seed, "given": True}
            for kind in ("room", "object") for angle in (20, 45, 60, 75, 90) for fov in (50, 75) for seed in (0, 1)
        ]  # fmt: skip
    return out


def run(case: dict[str, Any], data: Path, tmp: Path) -> list[dict[str, Any]]:
    """One row per descriptor tier with a plane: the plane's share and the scored candidates."""
    paths, cfg, R_gt, _ = PC.prepare(case, data, tmp)
    views = load_views(paths, cfg.views)
    primary = [SiftDescriptors(cfg.descriptors)(v) for v in views]
    rows = []
    for tier, sift_cfg in (("primary", None), ("wide", WIDE_SIFT)):
        feats = primary if sift_cfg is None else [SiftDescriptors(sift_cfg)(v) for v in views]
        m = match_features(feats[0], feats[1], cfg.matching)
        if len(m) < cfg.pose.min_inliers:
            continue
        plane = dominant_plane(m, cfg.pose)
        if plane is None:
            continue
        poses = plane_poses(views, primary, m, *plane, cfg.search, cfg.pose)
        rows.append(
            {
                "tier": tier,
                "matches": len(m),
                "plane": int(plane[1].sum()),
                "candidates": [(rotation_error_deg(p.R, R_gt), p.score) for p in poses],
            }
        )
    return rows


def verdict(row: dict[str, Any], cfg: ReconstructConfig) -> tuple[bool, bool, bool]:
    """(the guards let the leader through, the leader is the nearer candidate, the leader is within 5°)."""
    cands = row["candidates"]
    if not cands:
        return False, False, False
    scores = [s for _, s in cands]
    through = tiebreak_plane_ok(row["plane"], row["matches"]) and tiebreak_winner_ok(scores, cfg.search)
    nearer = all(cands[0][0] <= e for e, _ in cands[1:])
    return through, nearer, cands[0][0] < RIGHT_DEG


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("../shared/data"), help="the shared data folder (CO3D)")
    ap.add_argument("--only", choices=["synthetic", "co3d"], help="run one set only")
    ap.add_argument("--rows", action="store_true", help="print every case's candidates")
    args = ap.parse_args()
    cfg = ReconstructConfig()
    tmp = Path(tempfile.mkdtemp())
    summary: dict[str, list[int]] = {}
    wrong: list[str] = []
    if args.rows:
        print("| case | tier | plane / matches | candidates: rotation error °, score | through | nearer | < 5° |")
        print("|---|---|---|---|---|---|---|")
    for case in cases(args.data, args.only):
        name = " ".join(f"{k}={v}" for k, v in case.items() if k not in ("set", "given"))
        for row in run(case, args.data, tmp):
            through, nearer, right = verdict(row, cfg)
            s = summary.setdefault(case["set"], [0, 0, 0, 0])
            s[0] += 1
            if through:
                s[1] += 1
                s[2] += nearer
                s[3] += right
                if not right:
                    wrong.append(f"{case['set']} {name} ({row['tier']}): leader {row['candidates'][0][0]:.1f}° off")
            if args.rows:
                cands = ", ".join(f"{e:.1f}°: {sc}" for e, sc in row["candidates"])
                marks = " | ".join("yes" if b else "no" for b in (through, nearer, right))
                share = f"{row['plane']} / {row['matches']}"
                print(f"| {case['set']} {name} | {row['tier']} | {share} | {cands} | {marks} |")
        progress(f"done: {case['set']} {name}")
    print()
    print("| set | tiers with a plane | through the guards | leader the nearer candidate | leader within 5° |")
    print("|---|---:|---:|---:|---:|")
    for k, (n, n_through, n_near, n_right) in summary.items():
        print(f"| {k} | {n} | {n_through} | {n_near} | {n_right} |")
    for w in wrong:
        print(f"- through the guards but {w}")


if __name__ == "__main__":
    main()
