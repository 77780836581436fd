"""More photos, a better scene? The gain of N photos over the two middle ones at the same held-out views (issue 41).

    python -m benchmarks.multiview_gain                                   # object and room, 4 and 8 photos, balanced
    python -m benchmarks.multiview_gain --qualities balanced,best --scenes object --views 4

The issue's measure, on ray-traced scenes with exact cameras (a stand-in for the real 4-photo sets kept outside the
repository): photos on an orbit spanning ``--span`` degrees (45°: 4 photos 15° apart), 512 x 384, 60° field of
view, the intrinsics given; poses estimated. Held-out targets are rendered from the true scene at

* **mid**: between the two middle photos (where the middle pair alone already sees well: the views where the issue
  found a set 1.8 dB below its pair), and
* **side**: between each outer photo and its middle neighbour (where more photos should help most).

Per scene, N and quality: our N-photo scene and the two middle photos' scene (``reconstruct`` on those two alone, same
quality), each rendered at every target through the true camera mapped into our frame (a similarity from the
registered cameras' centres, Umeyama; two cameras: first camera and baseline ratio), PSNR against the target; "gain"
is N-photo minus pair, per group of targets; "copy" predicts a target with the nearest photo. Also: photos
registered, the worst relative-rotation error over the registered photos (degrees) and the wall seconds of each run.
The photos are rendered into ``--cache`` once.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from benchmarks._colmap_peer import align_rotation_errors
from benchmarks._common import print_header, row, write_json
from benchmarks._dev import load_rgb
from benchmarks.multiview_dev import refine_note, similarity
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets.synthetic import make_scene, orbit_cameras, render
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.images import save_image
from macsplat_cli.metrics import psnr
from macsplat_cli.pipeline.run import ReconstructConfig, Reconstruction
from macsplat_cli.render import render_camera

DEFAULT_CACHE = Path(tempfile.gettempdir()) / "macsplat_multiview_gain"
SIZE = (512, 384)
FOV = 60.0


@dataclass
class Orbit:
    """Photos (paths), their true camera-to-world [4, 4], the targets' cameras by group, the intrinsics file."""

    photos: list[Path]
    poses: list[np.ndarray]
    targets: dict[str, list[tuple[Path, Camera]]]
    intrinsics: Path


@dataclass
class Run:
    """One reconstruction, scored: PSNR per target group, registered photos, worst rotation error, seconds."""

    psnr: dict[str, float] = field(default_factory=dict)
    registered: int = 0
    rot_max_deg: float = float("nan")
    seconds: float = 0.0
    error: str = ""
    refine: str = ""
    """The refinement's resolution and, where the photos chose it, their sharp-minus-pooled gain (dB)."""


def orbit(kind: str, n: int, span: float, cache: Path) -> Orbit:
    """``n`` photos evenly over ``span`` degrees of azimuth, centred on the scene's front; targets between them."""
    scene = make_scene(kind, 0)  # type: ignore[arg-type]
    az = np.linspace(-span / 2, span / 2, n)
    mid = n // 2
    groups = {"mid": [az[mid - 1] + f * (az[mid] - az[mid - 1]) for f in (1 / 3, 2 / 3)],
              "side": [(az[0] + az[1]) / 2, (az[-2] + az[-1]) / 2]}  # fmt: skip
    folder = cache / f"{kind}_n{n}_span{span:g}"
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"view{k:02d}" for k in range(n)]
    cams = orbit_cameras(scene, az.tolist(), width=SIZE[0], height=SIZE[1], fov_deg=FOV, names=names)
    photos = [folder / f"{m}.png" for m in names]
    for cam, p in zip(cams, photos):
        if not p.exists():
            save_image(p, render(scene, cam, supersample=1).image)
    targets: dict[str, list[tuple[Path, Camera]]] = {}
    for g, azs in groups.items():
        tc = orbit_cameras(scene, azs, width=SIZE[0], height=SIZE[1], fov_deg=FOV,
                           names=[f"{g}{k}" for k in range(len(azs))])  # fmt: skip
        targets[g] = []
        for cam in tc:
            p = folder / f"target_{cam.name}.png"
            if not p.exists():
                save_image(p, render(scene, cam, supersample=1).image)
            targets[g].append((p, cam))
    intr = folder / "intrinsics.json"
    save_cameras(intr, CameraSet([cams[0]]))
    return Orbit(photos, [np.asarray(c.cam_to_world) for c in cams], targets, intr)


def run(o: Orbit, idx: Sequence[int], quality: str) -> Run:
    """Ours on the photos ``idx`` of ``o`` at ``quality``, scored at every target."""
    cfg = ReconstructConfig()
    cfg.views.intrinsics = o.intrinsics
    out = Run()
    t0 = time.perf_counter()
    try:
        rec = reconstruct([o.photos[i] for i in idx], EngineConfig(quality=quality, pipeline=cfg))  # type: ignore[arg-type]
    except ReconstructionError as e:
        out.error, out.seconds = str(e).splitlines()[0][:80], time.perf_counter() - t0
        return out
    out.seconds = time.perf_counter() - t0
    out.refine = refine_note(rec)
    score(rec, o, idx, out)
    return out


def score(rec: Reconstruction, o: Orbit, idx: Sequence[int], out: Run) -> None:
    """Fill ``out`` from ``rec``: registration, rotation error, the targets' PSNR."""
    stem = {o.photos[i].stem: k for k, i in enumerate(idx)}
    cams = {stem[c.name]: c for c in rec.cameras(original_size=False)}
    reg = sorted(cams)
    out.registered = len(reg)
    gt = [o.poses[i] for i in idx]
    errs = align_rotation_errors([cams[k].cam_to_world if k in cams else None for k in range(len(idx))], gt)
    out.rot_max_deg = float(errs.max()) if len(errs) else float("nan")
    s, R, t = similarity([cams[k].cam_to_world for k in reg], [gt[k] for k in reg])
    scene = rec.gaussians
    K = cams[reg[0]].K
    w, h = cams[reg[0]].width, cams[reg[0]].height
    for g, tg in o.targets.items():
        values = []
        for path, cam in tg:
            T = np.eye(4)
            T[:3, :3] = R @ cam.cam_to_world[:3, :3]
            T[:3, 3] = s * (R @ cam.cam_to_world[:3, 3]) + t
            with torch.no_grad():
                pred = render_camera(scene, Camera(cam.name, w, h, K, T)).rgb.clamp(0, 1).numpy()
            values.append(psnr(pred, load_rgb(path, (w, h))))
        out.psnr[g] = float(np.mean(values))


def copy_psnr(o: Orbit, idx: Sequence[int], g: str) -> float:
    """The nearest photo (by azimuth along the orbit: camera-centre distance) as the prediction of group ``g``."""
    values = []
    for path, cam in o.targets[g]:
        near = min(idx, key=lambda i: float(np.linalg.norm(o.poses[i][:3, 3] - cam.cam_to_world[:3, 3])))
        values.append(psnr(load_rgb(o.photos[near], SIZE), load_rgb(path, SIZE)))
    return float(np.mean(values))


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="object,room")
    p.add_argument("--views", default="4,8", help="photos over the span (each even, >= 4)")
    p.add_argument("--qualities", default="balanced")
    p.add_argument("--span", type=float, default=45.0, help="degrees of azimuth the photos span")
    p.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    print_header(["scene", "N", "quality", "registered", "rot max °", "mid PSNR (pair)", "mid gain",
                  "side PSNR (pair)", "side gain", "copy mid / side", "s (pair s)", "refine (sharp dB)"],
                 "lllrrrrrrrrl")  # fmt: skip
    records = []
    for kind in args.scenes.split(","):
        for n in (int(v) for v in args.views.split(",")):
            o = orbit(kind, n, args.span, args.cache)
            mid = n // 2
            for q in args.qualities.split(","):
                full, pair = run(o, range(n), q), run(o, [mid - 1, mid], q)
                gain = {g: full.psnr.get(g, math.nan) - pair.psnr.get(g, math.nan) for g in o.targets}
                copy = {g: copy_psnr(o, range(n), g) for g in o.targets}
                cells = [kind, str(n), q, f"{full.registered}/{n}" + (f" {full.error}" if full.error else ""),
                         f"{full.rot_max_deg:.2f}"]  # fmt: skip
                for g in ("mid", "side"):
                    cells += [f"{full.psnr.get(g, math.nan):.2f} ({pair.psnr.get(g, math.nan):.2f})", f"{gain[g]:+.2f}"]
                cells += [f"{copy['mid']:.2f} / {copy['side']:.2f}", f"{full.seconds:.1f} ({pair.seconds:.1f})",
                          full.refine]  # fmt: skip
                print(row(cells), flush=True)
                records.append({"scene": kind, "n": n, "quality": q, "full": full.__dict__, "pair": pair.__dict__,
                                "gain": gain, "copy": copy})  # fmt: skip
    if args.json:
        write_json(args.json, records)
    sys.exit(0)


if __name__ == "__main__":
    main()
