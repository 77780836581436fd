"""Reconstruct time and peak memory against the photos' size and the working size.

The shipped example pair, resized (cubic) to each photo size and saved as JPEG (quality 92, like a phone's), then
``macsplat reconstruct A B -o … -q --size S`` in a fresh process per cell (warm Numba cache): wall seconds and the
process's peak resident memory (``wait4``'s ``ru_maxrss``). The render side of the question (time against the
number of Gaussians) is ``bench_render.py``'s table.

    python -m benchmarks.scaling                                   # 0.3, 1, 4, 12, 24 MP × --size 256, 512, 1024
    python -m benchmarks.scaling --megapixels 1,24 --sizes 512
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._common import print_header, row

ROOT = Path(__file__).resolve().parents[1]
PAIR = (ROOT / "examples/motorcycle/left.jpg", ROOT / "examples/motorcycle/right.jpg")


def _photos(work: Path, megapixels: float) -> tuple[Path, Path]:
    import cv2

    out = []
    for p in PAIR:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise SystemExit(f"cannot read {p}")
        h, w = img.shape[:2]
        f = (megapixels * 1e6 / (w * h)) ** 0.5
        big = cv2.resize(img, (round(w * f), round(h * f)), interpolation=cv2.INTER_CUBIC)
        path = work / f"{p.stem}_{megapixels:g}mp.jpg"
        cv2.imwrite(str(path), big, [cv2.IMWRITE_JPEG_QUALITY, 92])
        out.append(path)
    return out[0], out[1]


def _run(photos: tuple[Path, Path], size: int, work: Path) -> tuple[float, float, int]:
    """(wall seconds, peak RSS MiB, exit code) of one reconstruct in a fresh process."""
    out = Path(tempfile.mkdtemp(dir=work))
    cmd = [sys.executable, "-m", "macsplat_cli", "reconstruct", *map(str, photos), "-o", str(out / "s.ply"),
           "--size", str(size), "-q"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    return seconds, usage.ru_maxrss / 1024, proc.returncode


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--megapixels", default="0.3,1,4,12,24", help="photo sizes, MP, comma-separated")
    p.add_argument("--sizes", default="256,512,1024", help="--size values, comma-separated")
    args = p.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        _run(_photos(work, 0.3), sizes[0], work)  # warm the Numba cache
        print(f"macsplat reconstruct on the example pair resized, {os.cpu_count()} CPUs; seconds / peak MiB\n")
        print_header(["photos", *(f"--size {s}" for s in sizes)], "l" + "r" * len(sizes))
        for mp in (float(v) for v in args.megapixels.split(",")):
            photos = _photos(work, mp)
            cells = []
            for s in sizes:
                seconds, peak, code = _run(photos, s, work)
                cells.append(f"{seconds:.1f} s / {peak:,.0f}" + ("" if code == 0 else f" (exit {code})"))
            print(row([f"{mp:g} MP", *cells]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
