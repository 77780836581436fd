"""Accuracy of `reconstruct` on the real development scenes (pose error, held-out views).

    python -m benchmarks.accuracy_dev --data ../shared/data            # both intrinsics modes
    python -m benchmarks.accuracy_dev --data ../shared/data --intrinsics given --json out.json
    python -m benchmarks.accuracy_dev --data ../shared/data --intrinsics given --before   # settings before issue 15
    python -m benchmarks.accuracy_dev --data ../shared/data --only co3d --refine 50 --save renders/
    python -m benchmarks.accuracy_dev --data ../shared/data --only co3d --no-slanted --no-colour-check --no-speckle

For every context pair: the relative pose error against ground truth (rotation and
translation direction), the focal error when it was estimated, and for each held-out
target view between the two context views, PSNR and SSIM of the rendered view against the
photo (working resolution). Target cameras: the ground-truth pose expressed in the camera-0
frame, its translation scaled by the estimated-to-GT baseline ratio (the reconstruction
has baseline 1), and the reconstruction's own intrinsics (given or estimated). "copy" is
the baseline of predicting the target with the nearer context photo. "masked" averages
over the pixels the reconstruction covers (rendered alpha > 0.5).

The data sets are third-party and are not part of the repository (see ../shared/data); they are
read through ``macsplat_cli.datasets`` (``benchmarks/_dev.py``). Run from the repository root.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from benchmarks._common import pair_pose, print_header, row, write_json
from benchmarks._dev import between, c2w, dev_frames, load_rgb, photo_size, save_intrinsics, target_intrinsics
from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import Frame
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.errors import MacsplatError
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.metrics import psnr, rotation_error_deg, ssim, translation_direction_error_deg
from macsplat_cli.pipeline.background import BackgroundConfig
from macsplat_cli.pipeline.depth import DepthConfig
from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.pipeline.types import View
from macsplat_cli.pipeline.views import ViewConfig, working_size
from macsplat_cli.presets import Overrides
from macsplat_cli.render import render_camera

# (scene, name, context pair) — indices into the frame list (co3d: the cameras file's order; the
# co3d pairs are the data README's close/medium/wide/very-wide suggestions; ICL and NYU
# frames are 1-based in their names).
CASES = [
    ("co3d", "close 12°", (2, 5)),
    ("co3d", "medium 27°", (0, 5)),
    ("co3d", "wide 55°", (5, 16)),
    ("co3d", "very wide 83°", (5, 13)),
    ("icl_livingroom", "(2,5)", (1, 4)),
    ("icl_livingroom", "(1,5)", (0, 4)),
    ("icl_livingroom", "(2,3)", (1, 2)),
    ("icl_livingroom", "(3,4)", (2, 3)),
    ("nyu_dining", "(1,3)", (0, 2)),
    ("nyu_dining", "(2,5)", (1, 4)),
    ("nyu_dining", "(1,5)", (0, 4)),
]
HEADER = [
    "scene", "pair", "targets", "intrinsics", "rot err °", "t err °", "focal err %", "inliers",
    "PSNR", "SSIM", "masked PSNR", "coverage", "copy PSNR", "copy SSIM", "measured %", "time s",
]  # fmt: skip
METRIC_KEYS = ("psnr", "ssim", "psnr_masked", "coverage", "copy_psnr", "copy_ssim")


def pipeline_config(
    given: tuple[Frame, Frame] | None, *, before: bool = False, slanted: bool = True, colour: bool = True,
    speckle: bool = True,
) -> ReconstructConfig:  # fmt: skip
    """The configuration of one case: the context frames' true intrinsics when ``given``, and
    the depth steps the flags turn off."""
    cfg = ReconstructConfig(views=ViewConfig())
    if before:  # the settings before issue 15
        cfg.depth = DepthConfig(
            fill_lambda=400.0, snap_edges=False, fuse=False, slanted_iters=0, colour_tol=0.0, speckle_size=0.0
        )
        cfg.gaussians = GaussianInitConfig(edge_ratio=math.inf)
    cfg.background = BackgroundConfig(enabled=not before)
    if not slanted:  # the depth without the slanted-plane refinement (issue 15, second step)
        cfg.depth.slanted_iters = 0
    if not colour:  # ... and without the colour check of the measured pixels
        cfg.depth.colour_tol = 0.0
    if not speckle:  # ... and without removing islands of measured depth
        cfg.depth.speckle_size = 0.0
    if given is not None:
        cfg.views.intrinsics = save_intrinsics(Path(tempfile.mkdtemp()) / "k.json", given)
    return cfg


def run_case(
    frames: list[Frame], pair: tuple[int, int], targets: tuple[int, ...], given: bool, size: int,
    refine: int = 0, save: Path | None = None, before: bool = False, slanted: bool = True, colour: bool = True,
    speckle: bool = True,
) -> dict:  # fmt: skip
    f0, f1 = frames[pair[0]], frames[pair[1]]
    cfg = pipeline_config((f0, f1) if given else None, before=before, slanted=slanted, colour=colour,
                          speckle=speckle)  # fmt: skip
    t0 = time.perf_counter()
    try:
        rec = reconstruct(
            [f0.image, f1.image], EngineConfig(overrides=Overrides(size=size, refine=refine), pipeline=cfg)
        )
    except MacsplatError as e:
        return {"failed": str(e), "time_s": time.perf_counter() - t0}
    dt = time.perf_counter() - t0
    T_gt = np.linalg.inv(c2w(f1)) @ c2w(f0)  # camera 0 → camera 1
    R_gt, t_gt = T_gt[:3, :3], T_gt[:3, 3]
    g = pair_pose(rec).geometry
    layer = rec.background
    out: dict[str, Any] = {
        "rotation_error_deg": rotation_error_deg(g.R, R_gt),
        "translation_error_deg": translation_direction_error_deg(g.t, t_gt),
        "intrinsics": rec.report.images[0].intrinsics_source,
        "inliers": len(g.inliers),
        "fallback": rec.report.fallback_used,
        "fill": [getattr(d, "fill_counts", None) for d in rec.depths],
        "measured_pct": 100.0 * float(np.mean([d.measured.mean() for d in rec.depths if d.measured is not None])),
        "background": layer.counts if layer is not None else None,
        "time_s": dt,
        "targets": [],
    }
    v0 = rec.views[0]
    f_gt = f0.camera.K[0, 0] * v0.width / photo_size(f0)[0]
    out["focal_error_pct"] = 100.0 * (g.K0[0, 0] / f_gt - 1.0)
    scale = 1.0 / np.linalg.norm(t_gt)
    scene = rec.gaussians  # with the far layer (rec.background) unless --before
    for ti in targets:
        stem = f"{pair[0]}-{pair[1]}_t{ti}_{'given' if given else 'est'}"
        out["targets"].append(target_metrics(scene, g.K0, v0, frames, pair, ti, scale, size, save, stem))
    return out


def target_metrics(
    scene: Gaussians, K0: np.ndarray, view0: View, frames: list[Frame], pair: tuple[int, int], ti: int,
    scale: float, size: int, save: Path | None, stem: str,
) -> dict:  # fmt: skip
    """Render held-out frame ``ti`` of ``scene`` from its true pose (camera-0 frame, translation times ``scale``;
    view 0's intrinsics ``K0`` rescaled) and score it against its photo, next to the nearer context photo
    ("copy"); with ``save``, write render | target | copy."""
    f0, f1, ft = frames[pair[0]], frames[pair[1]], frames[ti]
    T = np.linalg.inv(c2w(ft)) @ c2w(f0)  # camera 0 → target
    cam_to_world = np.linalg.inv(np.vstack([np.hstack([T[:3, :3], (T[:3, 3] * scale)[:, None]]), [0, 0, 0, 1]]))
    w, h = working_size(*photo_size(ft), size)
    K = target_intrinsics(K0, view0, (w, h))
    with torch.no_grad():
        r = render_camera(scene, Camera(f"t{ti}", w, h, K, cam_to_world))
    pred = np.clip(r.rgb.numpy(), 0, 1)
    target = load_rgb(ft.image, (w, h))
    mask = r.alpha.numpy() > 0.5
    d0 = np.linalg.norm(c2w(ft)[:3, 3] - c2w(f0)[:3, 3])
    d1 = np.linalg.norm(c2w(ft)[:3, 3] - c2w(f1)[:3, 3])
    near = f0 if d0 <= d1 else f1
    copy = load_rgb(near.image, (w, h))
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(save / f"{stem}.png"), np.uint8(np.concatenate([pred, target, copy], 1)[..., ::-1] * 255))
    return {
        "index": ti,
        "psnr": psnr(pred, target),
        "ssim": ssim(pred, target),
        "psnr_masked": psnr(pred, target, mask),
        "coverage": float(mask.mean()),
        "copy_psnr": psnr(copy, target),
        "copy_ssim": ssim(copy, target),
    }


def table_row(r: dict, scene: str, name: str, n_targets: int, mode: str) -> str:
    """The printed row of one case."""
    if "failed" in r:
        cells = [scene, name, str(n_targets), mode, "failed: " + r["failed"][:70]] + [""] * 10
        return "| " + " | ".join(cells) + f" {r['time_s']:.1f} |"
    m = {k: float(np.mean([t[k] for t in r["targets"]])) if r["targets"] else math.nan for k in METRIC_KEYS}
    fe = f"{r['focal_error_pct']:+.1f}" if mode == "estimated" else "–"
    cells = [
        scene, name, str(n_targets), mode + (" +fb" if r["fallback"] else ""),
        f"{r['rotation_error_deg']:.2f}", f"{r['translation_error_deg']:.2f}", fe, str(r["inliers"]),
        f"{m['psnr']:.2f}", f"{m['ssim']:.3f}", f"{m['psnr_masked']:.2f}", f"{m['coverage']:.2f}",
        f"{m['copy_psnr']:.2f}", f"{m['copy_ssim']:.3f}", f"{r['measured_pct']:.0f}", f"{r['time_s']:.1f}",
    ]  # fmt: skip
    return row(cells)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the shared data folder (../shared/data)")
    ap.add_argument("--intrinsics", choices=["given", "estimated", "both"], default="both")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--only", default="", help="run only cases whose scene name contains this")
    ap.add_argument("--json", type=Path, help="also write all results as JSON")
    ap.add_argument("--refine", type=int, default=0, help="refinement steps (0: none; 50 = --refine auto)")
    ap.add_argument("--pair", default="", help="run only cases whose pair name contains this")
    ap.add_argument("--save", type=Path, help="write render | target | copy images here")
    ap.add_argument(
        "--before",
        action="store_true",
        help="the settings before issue 15 (no far layer, fusion, edge snapping; fill λ 400)",
    )
    ap.add_argument("--no-slanted", action="store_true", help="depth without the slanted-plane refinement")
    ap.add_argument("--no-colour-check", action="store_true", help="depth without the colour check of measured pixels")
    ap.add_argument("--no-speckle", action="store_true", help="depth without removing islands of measured depth")
    args = ap.parse_args()
    modes = ["given", "estimated"] if args.intrinsics == "both" else [args.intrinsics]
    results = []
    cache: dict[str, list[Frame]] = {}
    print_header(HEADER, "llll" + "r" * (len(HEADER) - 4))
    for scene, name, pair in CASES:
        if args.only not in scene or args.pair not in name:
            continue
        if scene not in cache:
            cache[scene] = dev_frames(args.data, scene)
        frames = cache[scene]
        targets = tuple(between(frames, pair))
        for mode in modes:
            r = run_case(
                frames, pair, targets, mode == "given", args.size, args.refine, args.save, args.before,
                not args.no_slanted, not args.no_colour_check, not args.no_speckle,
            )  # fmt: skip
            r.update(scene=scene, pair=name, mode=mode)
            results.append(r)
            print(table_row(r, scene, name, len(targets), mode), flush=True)
    if args.json:
        write_json(args.json, results, default=str)


if __name__ == "__main__":
    main()
