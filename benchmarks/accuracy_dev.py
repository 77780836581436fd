"""Accuracy of `reconstruct` on the real development scenes (pose error, held-out views).

    python benchmarks/accuracy_dev.py --data ../shared/data            # both intrinsics modes
    python benchmarks/accuracy_dev.py --data ../shared/data --intrinsics given --json out.json
    python benchmarks/accuracy_dev.py --data ../shared/data --intrinsics given --before   # settings before issue 15
    python benchmarks/accuracy_dev.py --data ../shared/data --only co3d --refine 50 --save renders/
    python benchmarks/accuracy_dev.py --data ../shared/data --only co3d --no-slanted --no-colour-check --no-speckle

For every context pair: the relative pose error against ground truth (rotation and
translation direction), the focal error when it was estimated, and for each held-out
target view between the two context views, PSNR and SSIM of the rendered view against the
photo (working resolution). Target cameras: the ground-truth pose expressed in the camera-0
frame, its translation scaled by the estimated-to-GT baseline ratio (the reconstruction
has baseline 1), and the reconstruction's own intrinsics (given or estimated). "copy" is
the baseline of predicting the target with the nearer context photo. "masked" averages
over the pixels the reconstruction covers (rendered alpha > 0.5).

The data sets are third-party and are not part of the repository (see ../shared/data).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.errors import MacsplatError
from macsplat_cli.metrics import psnr, rotation_error_deg, ssim, translation_direction_error_deg
from macsplat_cli.pipeline.background import BackgroundConfig
from macsplat_cli.pipeline.depth import DepthConfig
from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig
from macsplat_cli.pipeline.refine import RefineConfig
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.pipeline.views import ViewConfig, working_size
from macsplat_cli.render import render_camera


@dataclass
class Frame:
    path: Path
    K: np.ndarray  # pixel-centre +0.5 convention, original resolution
    c2w: np.ndarray  # OpenCV axes
    size: tuple[int, int]


def _quat_xyzw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def co3d(root: Path) -> list[Frame]:
    doc = json.loads((root / "co3d_apple" / "cameras_opencv.json").read_text())
    w, h = doc["width"], doc["height"]
    # K has cx = W/2, cy = H/2: the image centre with +0.5 pixel centres already.
    return [Frame(root / "co3d_apple" / v["image"], np.array(v["K"]), np.array(v["c2w"]), (w, h)) for v in doc["views"]]


def icl_like(root: Path, subset: str) -> list[Frame]:
    d = root / "icl_nuim_and_home_rgbd" / subset
    if subset == "icl_livingroom":
        K = np.array([[481.2, 0, 319.5 + 0.5], [0, 480.0, 239.5 + 0.5], [0, 0, 1]])
        F = np.diag([1.0, -1.0, 1.0, 1.0])  # ICL-NUIM is left-handed: flip y (see the data README)
    else:
        K = np.array([[518.0, 0, 325.5 + 0.5], [0, 519.0, 253.5 + 0.5], [0, 0, 1]])
        F = np.eye(4)
    frames = []
    for i, line in enumerate((d / "pose.txt").read_text().split("\n")):
        if not line.strip():
            continue
        v = np.array([float(x) for x in line.split()])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _quat_xyzw(v[3:7]), v[:3]
        frames.append(Frame(d / "color" / f"{i + 1}.png", K, F @ T @ F, (640, 480)))
    return frames


# (scene, name, context pair) — indices into the frame list (co3d: sorted file order; the
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


def between(frames: list[Frame], pair: tuple[int, int]) -> list[int]:
    """Held-out targets between the context views: the centre projects inside the context
    chord (5–95 %) within half its length, and the orientation differs from each context
    view by at most the context pair's angle + 15°."""
    a, b = frames[pair[0]], frames[pair[1]]
    ca, cb = a.c2w[:3, 3], b.c2w[:3, 3]
    chord = cb - ca
    length = float(np.linalg.norm(chord))
    span = rotation_error_deg(a.c2w[:3, :3], b.c2w[:3, :3])
    out = []
    for i, f in enumerate(frames):
        if i in pair:
            continue
        d = f.c2w[:3, 3] - ca
        u = float(d @ chord) / length**2
        perp = float(np.linalg.norm(d - u * chord))
        ra = rotation_error_deg(a.c2w[:3, :3], f.c2w[:3, :3])
        rb = rotation_error_deg(b.c2w[:3, :3], f.c2w[:3, :3])
        if 0.05 < u < 0.95 and perp < 0.5 * length and max(ra, rb) <= span + 15.0:
            out.append(i)
    return out


def _load_rgb(path: Path, size: tuple[int, int]) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def run_case(
    frames: list[Frame], pair: tuple[int, int], targets: tuple[int, ...], given: bool, size: int,
    refine: int = 0, save: Path | None = None, before: bool = False, slanted: bool = True, colour: bool = True,
    speckle: bool = True,
) -> dict:  # fmt: skip
    f0, f1 = frames[pair[0]], frames[pair[1]]
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
    if given:
        tmp = Path(tempfile.mkdtemp()) / "k.json"
        cams = [Camera(f.path.name, f.size[0], f.size[1], f.K, np.eye(4)) for f in (f0, f1)]
        save_cameras(tmp, CameraSet(cams))
        cfg.views.intrinsics = tmp
    t0 = time.perf_counter()
    try:
        rec = reconstruct([f0.path, f1.path], EngineConfig(size=size, pipeline=cfg, refine=RefineConfig(steps=refine)))
    except MacsplatError as e:
        return {"failed": str(e), "time_s": time.perf_counter() - t0}
    dt = time.perf_counter() - t0
    T_gt = np.linalg.inv(f1.c2w) @ f0.c2w  # camera 0 → camera 1
    R_gt, t_gt = T_gt[:3, :3], T_gt[:3, 3]
    g = rec.geometry
    scene = rec.gaussians  # with the far layer (rec.background) unless --before
    layer = rec.background
    out = {
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
    f_gt = f0.K[0, 0] * v0.width / f0.size[0]
    out["focal_error_pct"] = 100.0 * (g.K0[0, 0] / f_gt - 1.0)
    scale = 1.0 / np.linalg.norm(t_gt)
    for ti in targets:
        ft = frames[ti]
        T = np.linalg.inv(ft.c2w) @ f0.c2w  # camera 0 → target
        c2w = np.linalg.inv(np.vstack([np.hstack([T[:3, :3], (T[:3, 3] * scale)[:, None]]), [0, 0, 0, 1]]))
        w, h = working_size(*ft.size, size)
        K = g.K0.copy()
        K[0] *= w / v0.width
        K[1] *= h / v0.height
        with torch.no_grad():
            r = render_camera(scene, Camera(f"t{ti}", w, h, K, c2w))
        pred = np.clip(r.rgb.numpy(), 0, 1)
        target = _load_rgb(ft.path, (w, h))
        mask = r.alpha.numpy() > 0.5
        d0 = np.linalg.norm(ft.c2w[:3, 3] - f0.c2w[:3, 3])
        d1 = np.linalg.norm(ft.c2w[:3, 3] - f1.c2w[:3, 3])
        near = f0 if d0 <= d1 else f1
        copy = _load_rgb(near.path, (w, h))
        if save is not None:
            save.mkdir(parents=True, exist_ok=True)
            stem = f"{pair[0]}-{pair[1]}_t{ti}_{'given' if given else 'est'}"
            cv2.imwrite(str(save / f"{stem}.png"), np.uint8(np.concatenate([pred, target, copy], 1)[..., ::-1] * 255))
        out["targets"].append(
            {
                "index": ti,
                "psnr": psnr(pred, target),
                "ssim": ssim(pred, target),
                "psnr_masked": psnr(pred, target, mask),
                "coverage": float(mask.mean()),
                "copy_psnr": psnr(copy, target),
                "copy_ssim": ssim(copy, target),
            }
        )
    return out


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
    loaders = {
        "co3d": lambda: co3d(args.data),
        "icl_livingroom": lambda: icl_like(args.data, "icl_livingroom"),
        "nyu_dining": lambda: icl_like(args.data, "nyu_dining"),
    }
    modes = ["given", "estimated"] if args.intrinsics == "both" else [args.intrinsics]
    results = []
    cache: dict[str, list[Frame]] = {}
    header = [
        "scene", "pair", "targets", "intrinsics", "rot err °", "t err °", "focal err %", "inliers",
        "PSNR", "SSIM", "masked PSNR", "coverage", "copy PSNR", "copy SSIM", "measured %", "time s",
    ]  # fmt: skip
    print("| " + " | ".join(header) + " |")
    print("|---|---|---|---|" + "---:|" * (len(header) - 4))
    metric_keys = ("psnr", "ssim", "psnr_masked", "coverage", "copy_psnr", "copy_ssim")
    for scene, name, pair in CASES:
        if args.only not in scene or args.pair not in name:
            continue
        frames = cache.setdefault(scene, loaders[scene]())
        targets = tuple(between(frames, pair))
        for mode in modes:
            r = run_case(
                frames, pair, targets, mode == "given", args.size, args.refine, args.save, args.before,
                not args.no_slanted, not args.no_colour_check, not args.no_speckle,
            )  # fmt: skip
            r.update(scene=scene, pair=name, mode=mode)
            results.append(r)
            if "failed" in r:
                cells = [scene, name, str(len(targets)), mode, "failed: " + r["failed"][:70]] + [""] * 10
                print("| " + " | ".join(cells) + f" {r['time_s']:.1f} |")
                continue
            m = {k: float(np.mean([t[k] for t in r["targets"]])) if r["targets"] else math.nan for k in metric_keys}
            fe = f"{r['focal_error_pct']:+.1f}" if mode == "estimated" else "–"
            cells = [
                scene, name, str(len(targets)), mode + (" +fb" if r["fallback"] else ""),
                f"{r['rotation_error_deg']:.2f}", f"{r['translation_error_deg']:.2f}", fe, str(r["inliers"]),
                f"{m['psnr']:.2f}", f"{m['ssim']:.3f}", f"{m['psnr_masked']:.2f}", f"{m['coverage']:.2f}",
                f"{m['copy_psnr']:.2f}", f"{m['copy_ssim']:.3f}", f"{r['measured_pct']:.0f}", f"{r['time_s']:.1f}",
            ]  # fmt: skip
            print("| " + " | ".join(cells) + " |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    sys.exit(main())
