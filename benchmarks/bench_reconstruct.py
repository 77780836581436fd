"""Wall time of `macsplat reconstruct` on two ~1 MP photos, per stage.

    python -m benchmarks.bench_reconstruct                         # synthetic 1152x864 pair
    python -m benchmarks.bench_reconstruct --images a.jpg b.jpg    # your photos
    python -m benchmarks.bench_reconstruct --quality fast          # a --quality preset (default: balanced)

Three measurements:

* **first run**: the command in a fresh process with an empty Numba cache (kernels are
  compiled, as on a fresh install);
* **CLI, cached**: the command in a fresh process once the kernels are cached — what a
  user waits for (Python start, imports, reading photos, writing PLY + cameras);
* **per stage**: the pipeline in-process, median of ``--repeat`` runs after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _synthetic_pair(folder: Path) -> list[Path]:
    from macsplat_cli.datasets import synthetic
    from macsplat_cli.images import save_image

    scene = synthetic.make_scene("room", seed=3)
    cams = synthetic.orbit_pair(scene, 15.0, width=1152, height=864, seed=3)
    paths = []
    for cam in cams:
        p = folder / f"{cam.name}.jpg"
        save_image(p, synthetic.render(scene, cam).image)
        paths.append(p)
    return paths


def _cli(images: list[Path], out: Path, env: dict[str, str], extra: list[str]) -> float:
    cmd = [sys.executable, "-m", "macsplat_cli", "reconstruct", *map(str, images), "-o", str(out / "scene.ply"), "-q"]
    cmd += extra
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", nargs=2, type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quality", choices=("fast", "balanced", "best"), default=None)
    args = ap.parse_args()
    extra = ["--quality", args.quality] if args.quality else []
    tmp = Path(tempfile.mkdtemp())
    images = args.images or _synthetic_pair(tmp)
    from PIL import Image

    sizes = [Image.open(p).size for p in images]
    print(f"photos: {', '.join(f'{p.name} {w}x{h} ({w * h / 1e6:.2f} MP)' for p, (w, h) in zip(images, sizes))}")

    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(tmp / "numba-cache")  # empty: the first run compiles
    first = _cli(images, tmp, env, extra)
    cached = sorted(_cli(images, tmp, env, extra) for _ in range(args.repeat))[args.repeat // 2]

    from macsplat_cli.cameras import save_cameras
    from macsplat_cli.engine import reconstruct
    from macsplat_cli.ply import write_ply

    config = None
    if args.quality:  # as the CLI builds it (the engine applies the preset's working size)
        from macsplat_cli.engine import EngineConfig

        config = EngineConfig(quality=args.quality)
    reconstruct(images, config)  # warm-up (kernels from the default cache location)
    runs = []
    for _ in range(args.repeat):
        rec = reconstruct(images, config)
        t0 = time.perf_counter()
        write_ply(tmp / "s.ply", rec.gaussians)
        save_cameras(tmp / "c.json", rec.cameras())
        times = dict(rec.report.times_s)
        times["write"] = time.perf_counter() - t0
        times["total"] = times["total"] + times["write"]
        runs.append(times)
    stages = list(runs[0])
    med = {k: sorted(r.get(k, 0.0) for r in runs)[len(runs) // 2] for k in stages}
    print(f"\nfirst run (empty Numba cache, CLI): {first:.2f} s")
    print(f"CLI with cached kernels (median of {args.repeat}): {cached:.2f} s\n")
    print("| stage | seconds |")
    print("|---|---:|")
    for k in stages:
        print(f"| {k} | {med[k]:.3f} |")
    print(f"\nGaussians: {rec.report.gaussians:,}; matches: {json.dumps(rec.report.matches)}")


if __name__ == "__main__":
    main()
