"""Scene compaction (``macsplat_cli.pipeline.compact``): Gaussians, PLY size, render time and held-out PSNR per preset.

    python -m benchmarks.compact_gaussians --data ../shared/data               # dev scenes + synthetic + example
    python -m benchmarks.compact_gaussians --data ../shared/data --only synthetic --json out.json

Each case is reconstructed once (classical backend, no refinement, 512 px working size; the dev scenes
with their given intrinsics), then compacted with every preset. Per preset: the Gaussians and the
reduction, the PLY size, the compaction time, the time to render every held-out target (the minimum over
``--repeats`` rounds, presets interleaved within each round so that a busy machine slows them alike; also
as process CPU time, less sensitive to other jobs on the machine) and the renderer's tile work
(Gaussian–tile intersections: deterministic, a proxy of render time), the
mean PSNR of the held-out targets against their photos, and the "fidelity": the PSNR of the compacted
render against the full scene's render of the same camera (how much the picture changed; > 100: identical).

Held-out targets: the dev scenes' views between the two context views, placed as in
``accuracy_dev.py`` (``benchmarks/_dev.py``: ground-truth pose in the camera-0 frame, baseline-scaled); the synthetic
pairs' a
ray-traced view half-way between the two cameras; the shipped example has none (its PSNR column is
empty), its fidelity camera is the midpoint between the two cameras.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import cast

import numpy as np
import torch

from benchmarks._common import print_header, row, write_json
from benchmarks._dev import between, c2w, dev_frames, load_rgb, photo_size, save_intrinsics, target_intrinsics
from macsplat_cli._json import to_jsonable
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.images import save_image
from macsplat_cli.metrics import psnr
from macsplat_cli.pipeline.compact import compact_reconstruction
from macsplat_cli.pipeline.run import ReconstructConfig, Reconstruction
from macsplat_cli.pipeline.views import ViewConfig, working_size
from macsplat_cli.ply import write_ply
from macsplat_cli.presets import QUALITIES, Overrides, Quality, compact_config
from macsplat_cli.render import render_camera

ROOT = Path(__file__).resolve().parents[1]
SIZE = 512
DEV_CASES = [
    ("co3d", "close 12°", (2, 5)),
    ("co3d", "medium 27°", (0, 5)),
    ("icl_livingroom", "(2,5)", (1, 4)),
    ("nyu_dining", "(1,3)", (0, 2)),
]
SYNTHETIC_CASES = [("room", 3, 20.0), ("object", 1, 20.0)]


@dataclass
class Case:
    name: str
    rec: Reconstruction
    targets: list[Camera]
    photos: Sequence[np.ndarray | None]  # None: no photo (fidelity only)


def _config(intrinsics: Path | None) -> EngineConfig:
    views = ViewConfig(intrinsics=intrinsics)
    return EngineConfig(overrides=Overrides(size=SIZE), pipeline=ReconstructConfig(views=views))


def dev_case(data: Path, scene: str, name: str, pair: tuple[int, int], tmp: Path) -> Case:
    frames = dev_frames(data, scene)
    f0, f1 = frames[pair[0]], frames[pair[1]]
    k = save_intrinsics(tmp / f"{scene}_{pair[0]}_{pair[1]}.json", (f0, f1))
    rec = reconstruct([f0.image, f1.image], _config(k))
    T_gt = np.linalg.inv(c2w(f1)) @ c2w(f0)
    scale = 1.0 / np.linalg.norm(T_gt[:3, 3])
    targets, photos = [], []
    for ti in between(frames, pair):
        ft = frames[ti]
        T = np.linalg.inv(c2w(ft)) @ c2w(f0)
        T[:3, 3] *= scale
        w, h = working_size(*photo_size(ft), SIZE)
        K = target_intrinsics(rec.views[0].K, rec.views[0], (w, h))
        targets.append(Camera(f"t{ti}", w, h, K, np.linalg.inv(T)))
        photos.append(load_rgb(ft.image, (w, h)))
    return Case(f"{scene} {name}", rec, targets, photos)


def synthetic_case(kind: str, seed: int, angle: float, tmp: Path) -> Case:
    scene = syn.make_scene(kind, seed)  # type: ignore[arg-type]
    a, mid, b = syn.orbit_cameras(kind, [-angle / 2, 0.0, angle / 2], width=SIZE, height=384)  # type: ignore[arg-type]
    a, b = dataclasses.replace(a, name="a.png"), dataclasses.replace(b, name="b.png")
    folder = tmp / f"{kind}{seed}"
    folder.mkdir()
    for c in (a, b):
        save_image(folder / c.name, syn.render(scene, c).image)
    save_cameras(folder / "cams.json", CameraSet([a, b]))
    rec = reconstruct([folder / "a.png", folder / "b.png"], _config(folder / "cams.json"))
    T = np.linalg.inv(mid.cam_to_world) @ a.cam_to_world
    T[:3, 3] /= np.linalg.norm(a.center - b.center)  # the reconstruction's baseline is 1
    return Case(f"synthetic {kind} {angle:g}°", rec, [dataclasses.replace(mid, cam_to_world=np.linalg.inv(T))],
                [syn.render(scene, mid).image])  # fmt: skip


def example_case(root: Path) -> Case:
    ex = root / "examples" / "motorcycle"
    rec = reconstruct([ex / "left.jpg", ex / "right.jpg"], _config(None))
    c0, c1 = rec.cameras(original_size=False)
    c2w = c0.cam_to_world.copy()
    c2w[:3, 3] = 0.5 * (c0.center + c1.center)
    return Case("example motorcycle", rec, [dataclasses.replace(c0, name="mid", cam_to_world=c2w)], [None])


def _render(g: Gaussians, cam: Camera) -> tuple[np.ndarray, float, int, float]:
    """The image, its wall time, the tile intersections and the process CPU time (all threads)."""
    t0, c0 = time.perf_counter(), time.process_time()
    with torch.no_grad():
        out = render_camera(g, cam)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return np.clip(out.rgb.numpy(), 0.0, 1.0), wall, out.n_intersections, cpu


def measure(case: Case, presets: list[Quality], repeats: int, budget: int | None, tmp: Path) -> list[dict]:
    with torch.no_grad():  # every pixel Gaussian (not ``rec.gaussians``, which may be compacted already)
        full = Gaussians.cat([m.to_gaussians() for m in case.rec.maps])
    scenes: dict[str, Gaussians] = {"full": full}
    rows: dict[str, dict] = {"full": {"compact_s": 0.0}}
    for p in presets:
        g, report = compact_reconstruction(case.rec, compact_config(p, budget=budget))
        scenes[p] = g
        rows[p] = {"compact_s": report.seconds, "report": report.to_dict()}
    for name, g in scenes.items():
        rows[name]["gaussians"] = len(g)
        rows[name]["ply_mb"] = _ply_size(g, tmp)
    times = {name: math.inf for name in scenes}
    cpu = {name: math.inf for name in scenes}
    images: dict[str, list[np.ndarray]] = {}
    for name, g in scenes.items():  # warm-up (Numba) and the images
        first = [_render(g, c) for c in case.targets]
        images[name] = [f[0] for f in first]
        rows[name]["intersections"] = sum(f[2] for f in first)
    for _ in range(repeats):
        for name, g in scenes.items():
            runs = [_render(g, c) for c in case.targets]
            times[name] = min(times[name], sum(r[1] for r in runs))
            cpu[name] = min(cpu[name], sum(r[3] for r in runs))
    out = []
    ref = rows["full"]
    for name in scenes:
        r = rows[name]
        have = [(im, ph) for im, ph in zip(images[name], case.photos) if ph is not None]
        r["psnr"] = float(np.mean([psnr(im, ph) for im, ph in have])) if have else math.nan
        fid = [psnr(im, ref) for im, ref in zip(images[name], images["full"])]
        r["fidelity_db"] = float(np.mean(fid))
        r["render_s"] = times[name]
        r.update(case=case.name, preset=name, targets=len(case.targets))
        r["ratio"] = ref["gaussians"] / r["gaussians"] if r["gaussians"] else math.inf
        r["speedup"] = times["full"] / times[name]
        r["render_cpu_s"] = cpu[name]
        r["cpu_speedup"] = cpu["full"] / cpu[name]
        r["work_ratio"] = ref["intersections"] / max(r["intersections"], 1)
        out.append(r)
    for r in out:
        r["d_psnr"] = r["psnr"] - rows["full"]["psnr"]
    return out


def _ply_size(g: Gaussians, tmp: Path) -> float:
    path = tmp / "scene.ply"
    write_ply(path, g)
    size = path.stat().st_size / 1e6
    path.unlink()
    return size


HEADER = ["case", "targets", "preset", "Gaussians", "fewer ×", "PLY MB", "compact s", "render ms", "faster ×",
          "CPU faster ×", "tile work ×", "PSNR", "Δ PSNR", "fidelity dB"]  # fmt: skip


def table_row(r: dict) -> str:
    fid = "> 100" if r["fidelity_db"] > 100 else f"{r['fidelity_db']:.1f}"
    cells = [
        r["case"], str(r["targets"]), r["preset"], f"{r['gaussians']:,}", f"{r['ratio']:.2f}",
        f"{r['ply_mb']:.1f}", f"{r['compact_s']:.2f}", f"{1000 * r['render_s']:.0f}", f"{r['speedup']:.2f}",
        f"{r['cpu_speedup']:.2f}", f"{r['work_ratio']:.2f}",
        "–" if math.isnan(r["psnr"]) else f"{r['psnr']:.2f}",
        "–" if math.isnan(r["d_psnr"]) else f"{r['d_psnr']:+.2f}", fid,
    ]  # fmt: skip
    return row(cells)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="the shared data folder (../shared/data); none: skip")
    ap.add_argument("--only", default="", help="run only cases whose name contains this")
    ap.add_argument("--presets", default=",".join(QUALITIES), help="comma-separated presets")
    ap.add_argument("--budget", type=int, default=None, help="also cap every preset at this many Gaussians")
    ap.add_argument("--repeats", type=int, default=5, help="render rounds (the minimum is reported)")
    ap.add_argument("--json", type=Path, help="also write all results as JSON")
    args = ap.parse_args()
    presets = [p for p in args.presets.split(",") if p]
    if any(p not in QUALITIES for p in presets):
        ap.error(f"--presets: each of {', '.join(QUALITIES)}")
    presets = cast("list[Quality]", presets)
    tmp = Path(tempfile.mkdtemp())
    builders: list[tuple[str, Callable[[], Case]]] = []
    if args.data is not None:
        builders += [(f"{s} {n}", partial(dev_case, args.data, s, n, p, tmp)) for s, n, p in DEV_CASES]
    for k, seed, a in SYNTHETIC_CASES:
        builders.append((f"synthetic {k} {a:g}°", partial(synthetic_case, k, seed, a, tmp)))
    builders += [("example motorcycle", partial(example_case, ROOT))]
    print_header(HEADER, "lrl" + "r" * (len(HEADER) - 3))
    results = []
    for name, build in builders:
        if args.only not in name:
            continue
        case = build()
        for r in measure(case, presets, args.repeats, args.budget, tmp):
            results.append(r)
            print(table_row(r), flush=True)
    if args.json:
        write_json(args.json, to_jsonable(results))


if __name__ == "__main__":
    main()
