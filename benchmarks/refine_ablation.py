"""The "w/o MAC" ablation of the default backend: no refinement vs refinement without and with MAC.

    python -m benchmarks.refine_ablation                        # synthetic scenes only
    python -m benchmarks.refine_ablation --data ../shared/data  # + the real dev scenes
    python -m benchmarks.refine_ablation --steps 50 --scale 2   # the defaults of --refine auto

Synthetic: room and object scenes at 20° and 45° orbits with the true intrinsics; the
held-out target is the camera half way round the orbit; depth error is the median relative
error of the rendered depth at camera 0 against the ground truth (over pixels with
alpha > 0.5). Real: the dev scenes of accuracy_dev.py (``benchmarks/_dev.py``: targets between the context views,
GT target poses expressed in camera 0 and scaled by the baseline ratio). Pose errors are
the same in every mode (refinement does not move the cameras).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks._common import print_header, row
from benchmarks._dev import between, c2w, dev_frames, load_rgb, photo_size, save_intrinsics, target_intrinsics
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.images import save_image
from macsplat_cli.metrics import psnr, ssim
from macsplat_cli.pipeline.refine import AUTO_STEPS, RefineConfig, refine
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.pipeline.views import ViewConfig, working_size
from macsplat_cli.render import render_camera

MODES: dict[str, dict[str, Any]] = {
    "refine w/o MAC": dict(use_mac=False),
    "refine + MAC": dict(use_mac=True),
    "refine + dense MAC": dict(use_mac=True, mac_matches="dense"),  # only with --dense-mac
}
DENSE = False


def _scenes(rec, steps: int, scale: int) -> dict[str, tuple[Gaussians, float]]:  # noqa: ANN001
    out = {"none": (rec.gaussians, 0.0)}
    for name, opts in MODES.items():
        if name == "refine + dense MAC" and not DENSE:
            continue
        t0 = time.perf_counter()
        cfg = RefineConfig(steps=steps, scale=scale, **opts)
        r = refine(rec.views, rec.pose.geometry, rec.maps, cfg, depths=rec.depths)
        with torch.no_grad():
            out[name] = (Gaussians.cat([m.to_gaussians() for m in r.maps]), time.perf_counter() - t0)
    return out


def _image_metrics(g: Gaussians, cam: Camera, target: np.ndarray) -> tuple[float, float, float]:
    with torch.no_grad():
        o = render_camera(g, cam)
    pred = np.clip(o.rgb.numpy(), 0, 1)
    return psnr(pred, target), ssim(pred, target), psnr(pred, target, o.alpha.numpy() > 0.5)


def synthetic_rows(steps: int, scale: int) -> list[list[str]]:
    tmp = Path(tempfile.mkdtemp())
    rows = []
    for kind in ("room", "object"):
        scene = S.make_scene(kind, seed=0)
        for angle in (20.0, 45.0):
            c0, cm, c1 = S.orbit_cameras(scene, [0.0, angle / 2, angle])
            paths, gt = [], {}
            for c in (c0, cm, c1):
                v = S.render(scene, c)
                gt[c.name] = v
                p = tmp / f"{kind}{angle}_{c.name}.png"
                save_image(p, v.image)
                paths.append(p)
            save_cameras(tmp / "k.json", CameraSet([c0, c1]))
            rec = reconstruct(
                [paths[0], paths[2]],
                EngineConfig(pipeline=ReconstructConfig(views=ViewConfig(intrinsics=tmp / "k.json"))),
            )
            R, t = S.relative_pose(c0, c1)
            base = float(np.linalg.norm(t))
            Tm = np.linalg.inv(cm.cam_to_world) @ c0.cam_to_world
            Tm[:3, 3] /= base
            target_cam = Camera("mid", cm.width, cm.height, cm.K, np.linalg.inv(Tm))
            depth_gt = gt[c0.name].depth / base
            cam0 = Camera("c0", c0.width, c0.height, c0.K, np.eye(4))
            for mode, (g, secs) in _scenes(rec, steps, scale).items():
                ps, s_, pm = _image_metrics(g, target_cam, gt[cm.name].image)
                with torch.no_grad():
                    o = render_camera(g, cam0)
                d, a = o.depth.numpy(), o.alpha.numpy()
                m = (a > 0.5) & (depth_gt > 0)
                derr = float(np.median(np.abs(d[m] - depth_gt[m]) / depth_gt[m])) * 100
                rows.append([f"synthetic {kind}", f"{angle:g}°", mode, f"{ps:.2f}", f"{s_:.3f}", f"{pm:.2f}",
                             f"{derr:.1f}", f"{secs:.1f}"])  # fmt: skip
                print(row(rows[-1]), flush=True)
    return rows


def real_rows(data: Path, steps: int, scale: int) -> list[list[str]]:
    rows = []
    cases = [("co3d", "close 12°", (2, 5)), ("co3d", "medium 27°", (0, 5)), ("icl_livingroom", "(1,5)", (0, 4)),
             ("nyu_dining", "(1,3)", (0, 2))]  # fmt: skip
    for scene, name, pair in cases:
        frames = dev_frames(data, scene)
        targets = between(frames, pair)
        f0, f1 = frames[pair[0]], frames[pair[1]]
        tmp = save_intrinsics(Path(tempfile.mkdtemp()) / "k.json", (f0, f1))
        rec = reconstruct(
            [f0.image, f1.image], EngineConfig(pipeline=ReconstructConfig(views=ViewConfig(intrinsics=tmp)))
        )
        T_gt = np.linalg.inv(c2w(f1)) @ c2w(f0)
        s = 1.0 / np.linalg.norm(T_gt[:3, 3])
        for mode, (g, secs) in _scenes(rec, steps, scale).items():
            ms = []
            for ti in targets:
                ft = frames[ti]
                T = np.linalg.inv(c2w(ft)) @ c2w(f0)
                T[:3, 3] *= s
                w, h = working_size(*photo_size(ft), 512)
                K = target_intrinsics(rec.views[0].K, rec.views[0], (w, h))
                ms.append(_image_metrics(g, Camera("t", w, h, K, np.linalg.inv(T)), load_rgb(ft.image, (w, h))))
            p, s_, pm = np.mean(ms, axis=0)
            rows.append([f"{scene} {name}", f"{len(targets)} targets", mode, f"{p:.2f}", f"{s_:.3f}", f"{pm:.2f}", "–",
                         f"{secs:.1f}"])  # fmt: skip
            print(row(rows[-1]), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="the shared dev data folder; omit for synthetic scenes only")
    ap.add_argument("--steps", type=int, default=AUTO_STEPS)
    ap.add_argument("--scale", type=int, default=RefineConfig().scale)
    ap.add_argument("--dense-mac", action="store_true", help="also MAC over dense depth-consistent pixel pairs")
    ap.add_argument("--real-only", action="store_true", help="skip the synthetic scenes")
    args = ap.parse_args()
    global DENSE
    DENSE = args.dense_mac
    print(f"refinement: up to {args.steps} steps at 1/{args.scale} resolution, early stop on plateau\n")
    print_header(["scene", "pair", "mode", "PSNR", "SSIM", "masked PSNR", "depth err % (cam 0)", "refine s"],
                 "lllrrrrr")  # fmt: skip
    if not args.real_only:
        synthetic_rows(args.steps, args.scale)
    if args.data:
        real_rows(args.data, args.steps, args.scale)


if __name__ == "__main__":
    main()
