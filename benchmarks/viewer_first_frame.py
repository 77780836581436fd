"""``macsplat view`` in headless Chromium: time to the first drawn frame, and whether the page stays responsive.

For each scene: ``macsplat view SCENE --port 0 --no-open`` in its own process (seconds until it prints its URL:
reading the PLY and building the page), then a fresh headless Chromium (software WebGL through SwiftShader, the
CPU only) loads the page; "first frame" is the first screenshot in which the scene covers the part of the view
it covers in macsplat's own render (polled every 0.25 s). Then, for 10 s, the page is asked to evaluate ``1+1``
and to take a screenshot in turn: the slowest answer says whether the page froze (a frozen main thread answers
neither).

    python -m benchmarks.viewer_first_frame                          # the example scene (reconstructed first), 1 M
    python -m benchmarks.viewer_first_frame --scenes out/scene.ply --size 1024x768

Scenes: ``example`` (``reconstruct`` of the shipped pair, ≈100 k Gaussians), ``random:N`` (N random Gaussians
in front of camera 0, with the example's cameras), or a PLY path (its ``.cameras.json`` beside it).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._browser import Browser, find_chromium, region_mask
from benchmarks._common import print_header, row

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = (ROOT / "examples/motorcycle/left.jpg", ROOT / "examples/motorcycle/right.jpg")


def _cli(*args: object, **kw: object) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "macsplat_cli", *map(str, args)], env=env, **kw)  # type: ignore[call-overload]


def _example(work: Path) -> Path:
    ply = work / "example.ply"
    if not ply.exists():
        subprocess.run([sys.executable, "-m", "macsplat_cli", "reconstruct", *EXAMPLE, "-o", ply, "-q"],
                       check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
    return ply


def _random(work: Path, n: int) -> Path:
    import shutil

    import torch

    from macsplat_cli.gaussians import Gaussians
    from macsplat_cli.ply import write_ply

    ply = work / f"random{n}.ply"
    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.4, 1.0]) - torch.tensor([1.0, 0.7, -2.5])
    params = (means, torch.log(torch.rand(n, 3, generator=g) * 0.01 + 0.003), torch.randn(n, 4, generator=g),
              torch.rand(n, generator=g) * 4 - 2, torch.randn(n, 1, 3, generator=g) * 0.5)  # fmt: skip
    write_ply(ply, Gaussians(*params))
    shutil.copy(_example(work).with_suffix(".cameras.json"), ply.with_suffix(".cameras.json"))
    return ply


def _covered(ply: Path, w: int, h: int) -> np.ndarray:
    """Where macsplat's render of camera 0 (as the page frames it) is covered. [h, w] bool"""
    import torch

    from macsplat_cli.cameras import load_cameras
    from macsplat_cli.ply import read_ply
    from macsplat_cli.render import render
    from macsplat_cli.viewer import camera_pose

    cam = load_cameras(ply.with_suffix(".cameras.json")).cameras[0]
    fy = h / (2 * np.tan(camera_pose(cam).fov_y / 2))
    K = torch.tensor([[fy, 0.0, w / 2], [0.0, fy, h / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.from_numpy(np.linalg.inv(cam.cam_to_world)).float()
    with torch.no_grad():
        alpha = render(read_ply(ply), viewmat, K, w, h).alpha.numpy()
    return (alpha > 0.9) & region_mask(h, w)


def _measure(chromium: str, ply: Path, w: int, h: int, timeout: float) -> list[str]:
    covered = _covered(ply, w, h)
    t0 = time.monotonic()
    proc = _cli("view", ply, "--port", 0, "--no-open", "-q", stdout=subprocess.PIPE, text=True)
    t_ready = float("nan")
    try:
        url = proc.stdout.readline().strip()  # type: ignore[union-attr]
        t_ready = time.monotonic() - t0
        with Browser(chromium, w, h, timeout=timeout) as browser:
            t1 = time.monotonic()
            browser.goto(url, timeout=timeout)
            first = None
            while time.monotonic() - t1 < timeout:
                shot = browser.screenshot()
                if ((255 - shot.astype(int)).sum(-1) > 40)[covered].mean() > 0.9:
                    first = time.monotonic() - t1
                    break
                time.sleep(0.25)
            slowest, t2 = 0.0, time.monotonic()
            while first is not None and time.monotonic() - t2 < 10:
                for ask in (lambda: browser.evaluate("1+1"), browser.screenshot):
                    t = time.monotonic()
                    ask()
                    slowest = max(slowest, time.monotonic() - t)
    except TimeoutError:  # the page did not answer the browser's own protocol within its limit: frozen
        return [f"{t_ready:.1f}", "frozen", f"> {timeout:.0f}"]
    finally:
        proc.terminate()
        proc.wait()
    return [f"{t_ready:.1f}", f"{first:.1f}" if first is not None else f"> {timeout:.0f}", f"{slowest:.2f}"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="example,random:1000000", help="comma-separated: example, random:N, PATH")
    p.add_argument("--size", default="1024x768", help="browser window, WxH")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for the first frame")
    args = p.parse_args(argv)
    chromium = find_chromium()
    if chromium is None:
        print("no Chromium on PATH: nothing to measure")
        return 0
    w, h = (int(v) for v in args.size.split("x"))
    print(f"headless {Path(chromium).name}, SwiftShader (software WebGL), {os.cpu_count()} CPU cores, {w}x{h}\n")
    print_header(["scene", "Gaussians", "server ready s", "first frame s", "slowest answer after s"], "lrrrr")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for spec in args.scenes.split(","):
            if spec == "example":
                ply = _example(work)
            elif spec.startswith("random:"):
                ply = _random(work, int(spec.split(":")[1]))
            else:
                ply = Path(spec)
            from macsplat_cli.ply import read_ply

            n = len(read_ply(ply))
            print(row([spec, f"{n:,}", *_measure(chromium, ply, w, h, args.timeout)]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
