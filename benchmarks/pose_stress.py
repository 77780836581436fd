"""Pose estimation on degenerate synthetic motions: planar scenes and forward motion under noise.

    python -m benchmarks.pose_stress              # this checkout's pose stage
    python -m benchmarks.pose_stress --rev HEAD   # ... and a git revision's pose.py side by side

Planar (issue 14), 320×240 px, focal 300 px (known); the pose is "right" within 2° / 10°, else "wrong", or
refused (ReconstructionError). Two motions, 60 seeds each:

* ``random``: axis random, rotation 0–20°, translation 0.5 in a random direction, over a plane tilted by up
  to ±0.5 and 6 units away (about 5° between the views: the original benchmark).
* ``table``: a table (6 × 4 units) photographed from 6 units away, 30–60° above it, the second photo 10–30°
  further round the table (the users' table-top pairs, issue 14).

Families:

* ``pure plane``: 200 exact correspondences on the plane, 0.3 px noise, nothing else (the only evidence
  that separates the plane's two poses is cheirality: the wrong one may put part of the plane behind a
  camera).
* ``plane + p % off``: a table-top: 300 true correspondences, ``p`` % of them on objects standing on the
  table (0.1–1 units tall, ±3 units of table); the off-plane ones pass the confidence gate with probability
  0.5, the rest are in ``Matches.below_gate``; 200 go to the gated matches (plus 5 % random outliers, 0.3 px
  noise), the others below the gate (0.6 px noise) with 300 random outliers.

Focal observability (issue 16, ``--focal``, ~5 min): ray-traced 640×480 orbit pairs (room and object, 10–75°,
fields of view 40/50/75°, seeds 0–1), SIFT + the confidence gate as ``reconstruct`` runs them, no intrinsics
(the 60° prior): per pair the focal error of the self-calibration, the rotation error, and whether the pose stage
flagged the focal as not observable (``info["focal_observable"]``, a doubt in ``info["doubts"]``).

Forward motion: 30 draws of 53 points 4–10 units away, translation (0, 0, 0.5), 1 px noise:
verified matches and the translation-direction error (the 1 px inlier threshold against 1 px
noise).
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np

from macsplat_cli.datasets.synthetic.planar import H, K, PlanarMatches, W, planar_case, project
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.metrics import rotation_error_deg, translation_direction_error_deg
from macsplat_cli.pipeline import pose as pose_module
from macsplat_cli.pipeline.types import Matches, View

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = {"pure plane": None, "plane + 0 % off": 0.0, "plane + 3 % off": 0.03, "plane + 5 % off": 0.05,
            "plane + 10 % off": 0.10, "plane + 20 % off": 0.20}  # fmt: skip


def _view() -> View:
    return View("v", Path("v.png"), np.zeros((H, W, 3), np.float32), np.ones((H, W), bool), K, (W, H), "file")


def plane_matches(xy0: np.ndarray, xy1: np.ndarray) -> Matches:
    m = len(xy0)
    return Matches(xy0, xy1, np.ones(m, np.float32), np.arange(m), np.arange(m))


def _matches(p: PlanarMatches) -> Matches:
    """The pipeline's matches of a planar case (the data sets build none: they sit below the pipeline)."""
    m = plane_matches(p.xy0, p.xy1)
    m.below_gate = plane_matches(p.below_gate.xy0, p.below_gate.xy1) if p.below_gate is not None else None
    return m


def _errors(R_est: np.ndarray, t_est: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    return rotation_error_deg(R_est, R), translation_direction_error_deg(t_est, t)


def planar(
    module: ModuleType, off: float | None, motion: str = "random", seeds: int = 60, *, planar_off: bool = False
) -> tuple[int, int, int]:
    """(right, wrong, refused) poses of the planar cases; ``planar_off``: no pair counts as planar (the plane's
    resolution never runs: ``essential.PLANAR_FRACTION``, a ``PoseConfig`` field in a checkout before issue 38)."""
    essential = getattr(module, "essential", None)
    before = getattr(essential, "PLANAR_FRACTION", None)
    cfg = module.PoseConfig(planar_fraction=math.inf) if planar_off and before is None else module.PoseConfig()
    if planar_off and essential is not None and before is not None:
        essential.PLANAR_FRACTION = math.inf
    right = wrong = refused = 0
    try:
        for seed in range(seeds):
            p, R, t = planar_case(seed, off, motion)
            m = _matches(p)
            cv2.setRNGSeed(seed)
            try:
                g = module.estimate_pose(_view(), _view(), m, cfg)
            except ReconstructionError:
                refused += 1
                continue
            r, te = _errors(g.R, g.t, R, t)
            right, wrong = (right + 1, wrong) if r < 2 and te < 10 else (right, wrong + 1)
    finally:
        if essential is not None and before is not None:
            essential.PLANAR_FRACTION = before
    return right, wrong, refused


def forward(module: ModuleType) -> tuple[float, float, int]:
    inliers, errs, refused = [], [], 0
    R, t = np.eye(3), np.array([0.0, 0.0, 0.5])
    for seed in range(30):
        rng = np.random.default_rng(seed)
        cv2.setRNGSeed(seed)
        X = np.c_[rng.uniform(-3, 3, (318, 2)), rng.uniform(4, 10, 318)]
        xy0, xy1, ok = project(X, R, t)
        xy0, xy1 = xy0[ok][:53], xy1[ok][:53]
        xy0, xy1 = xy0 + rng.normal(0, 1, xy0.shape), xy1 + rng.normal(0, 1, xy1.shape)
        try:
            g = module.estimate_pose(_view(), _view(), plane_matches(xy0, xy1))
        except ReconstructionError:
            refused += 1
            continue
        inliers.append(len(g.inliers) / len(xy0))
        errs.append(_errors(g.R, g.t, R, t)[1])
    return float(np.median(inliers)), float(np.median(errs)), refused


def focal_table(out: Path) -> None:
    """Render the orbit pairs, estimate the pose without intrinsics, print one row per pair and a summary."""
    from macsplat_cli.datasets import synthetic as syn
    from macsplat_cli.images import save_image
    from macsplat_cli.pipeline.descriptors import SiftDescriptors
    from macsplat_cli.pipeline.matching import match_features
    from macsplat_cli.pipeline.run import ReconstructConfig
    from macsplat_cli.pipeline.views import load_views

    cfg = ReconstructConfig()
    sift = SiftDescriptors(cfg.descriptors)
    print("| pair | fitted focal error | focal used | rotation error ° | rotation uncertainty ° | flagged |")
    print("|---|---:|---:|---:|---:|---|")
    summary: dict[tuple[str, bool], list[int]] = {}
    for kind in ("object", "room"):
        for angle in (10, 15, 20, 30, 45, 60, 75):
            for fov in (40, 50, 75):
                for seed in (0, 1):
                    scene = syn.make_scene(kind, seed)
                    c0, c1 = syn.orbit_pair(kind, angle, width=640, height=480, fov_deg=fov, seed=seed)
                    paths = [out / f"{kind}_{angle}_{fov}_{seed}_{k}.png" for k in (0, 1)]
                    for p, c in zip(paths, (c0, c1)):
                        save_image(p, syn.render(scene, c).image)
                    views = load_views(paths, cfg.views)
                    m = match_features(sift(views[0]), sift(views[1]), cfg.matching)
                    truth = syn.relative_pose(c0, c1)
                    f_true = c0.K[0, 0] * views[0].width / c0.width
                    name = f"{kind} {angle}° fov {fov} s{seed}"
                    cv2.setRNGSeed(0)
                    try:
                        g = pose_module.estimate_pose(views[0], views[1], m)
                    except ReconstructionError as e:
                        print(f"| {name} | refused: {str(e)[:50]} | | | | |")
                        continue
                    i = g.diagnostics
                    fit = i["focal_scale_fitted"] * views[0].K[0, 0] / f_true - 1
                    used = g.K0[0, 0] / f_true - 1
                    rot = syn.pose_errors(g.R, g.t, *truth)[0]
                    flagged = bool(g.doubts)
                    unc = i["focal_rotation_uncertainty_deg"]
                    cells = f"{100 * fit:+.1f} % | {100 * used:+.1f} % | {rot:.2f} | {unc:.3f}"
                    print(f"| {name} | {cells} | {'yes' if flagged else ''} |", flush=True)
                    bad = abs(fit) > 0.05
                    summary.setdefault(("bad" if bad else "good", flagged), []).append(angle)
    print("\n| fitted focal | flagged | not flagged |\n|---|---:|---:|")
    for q in ("bad", "good"):
        label = "off by > 5 %" if q == "bad" else "within 5 %"
        print(f"| {label} | {len(summary.get((q, True), []))} | {len(summary.get((q, False), []))} |")


def _module_at(rev: str) -> ModuleType:
    """``macsplat_cli/pipeline/pose.py`` as of git revision ``rev``, imported beside this checkout's."""
    src = subprocess.run(
        ["git", "show", f"{rev}:macsplat_cli/pipeline/pose.py"], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout
    path = Path(tempfile.mkdtemp()) / "pose_rev.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("macsplat_cli.pipeline._pose_rev", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rev", help="also run the pose stage of this git revision (e.g. HEAD), for before/after")
    ap.add_argument("--seeds", type=int, default=60)
    ap.add_argument("--focal", action="store_true", help="only the focal-observability table (renders, ~5 min)")
    args = ap.parse_args()
    if args.focal:
        focal_table(Path(tempfile.mkdtemp()))
        return
    modules = [("this checkout", pose_module)] + ([(args.rev, _module_at(args.rev))] if args.rev else [])
    print("| motion | family | pose stage | right | wrong | refused |\n|---|---|---|---:|---:|---:|")
    for motion in ("random", "table"):
        for family, off in FAMILIES.items():
            for name, module in modules:
                counts = planar(module, off, motion, args.seeds)
                print(f"| {motion} | {family} | {name} | " + " | ".join(map(str, counts)) + " |", flush=True)
    for name, module in modules:
        counts = planar(module, None, "random", args.seeds, planar_off=True)
        print(f"| random | pure plane, planar check off | {name} | " + " | ".join(map(str, counts)) + " |")
    inl, err, refused = forward(pose_module)
    print("\n| forward motion, 53 points, 1 px noise | value |\n|---|---:|")
    print(f"| verified fraction of the true matches (median) | {inl:.2f} |")
    print(f"| translation-direction error ° (median) | {err:.1f} |")
    print(f"| refused | {refused} / 30 |")


if __name__ == "__main__":
    main()
