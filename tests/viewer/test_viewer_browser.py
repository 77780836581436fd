"""``macsplat view`` in a real browser: headless Chromium, WebGL through SwiftShader, traffic on loopback only.

The page is loaded from the real command (its own process), screenshotted once the scene is drawn, and compared with
macsplat's own render from the same camera; the cameras' frusta are looked for from a viewpoint behind them; the
"render" button is pressed. Slow (``--runslow``, as ``.ci/run`` runs it); skipped, saying why, when no Chromium is
installed (``.ci/run`` installs Debian's).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks._browser import Browser, find_chromium, region_mask, wait_for_frame
from macsplat_cli.images import to_uint8
from macsplat_cli.render import render
from macsplat_cli.viewer import camera_pose

from support.viewer_scene import PlaneScene

pytest.importorskip("viser")
pytest.importorskip("websockets")
CHROMIUM = find_chromium()
pytestmark = [
    pytest.mark.slow,  # a browser's start and a software-WebGL draw: pytest -q skips it, .ci/run runs it (--runslow)
    pytest.mark.skipif(
        CHROMIUM is None, reason="no Chromium on PATH (.ci/run installs Debian's chromium with apt-get where it can)"
    ),
]
ROOT = Path(__file__).resolve().parents[2]


def _sigint_default() -> None:
    """In the child: Ctrl-C's default handling, even when this test runs where SIGINT is ignored (a background job
    of a non-interactive shell ignores it, and an ignored signal stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


W, H = 800, 600


def _not_white(img: np.ndarray) -> np.ndarray:
    return (255 - img.astype(int)).sum(-1) > 40


def _orange(img: np.ndarray) -> np.ndarray:
    """Pixels of the frusta's colour (FRUSTUM_RGB, anti-aliased)."""
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return (r > 180) & (g > 70) & (g < 170) & (b < 90)


def _our_render(scene: PlaneScene) -> tuple[np.ndarray, np.ndarray]:
    """macsplat's render of camera 0 as the page shows it: W×H, its vertical field of view, white background."""
    pose = camera_pose(scene.camera_list[0])
    fy = H / (2 * np.tan(pose.fov_y / 2))
    K = torch.tensor([[fy, 0.0, W / 2], [0.0, fy, H / 2], [0.0, 0.0, 1.0]])
    out = render(scene.gaussians, torch.eye(4), K, W, H, background=(1.0, 1.0, 1.0))
    return to_uint8(out.rgb), out.alpha.numpy()


def _luminance_blocks(img: np.ndarray, mask: np.ndarray, k: int = 8) -> np.ndarray:
    lum = img.astype(float) @ np.array([0.299, 0.587, 0.114])
    h, w = (s // k * k for s in lum.shape)
    blocks = lum[:h, :w].reshape(h // k, k, w // k, k).mean((1, 3))
    keep = mask[:h, :w].reshape(h // k, k, w // k, k).all((1, 3))
    return blocks[keep]


@pytest.fixture
def served(plane_scene: PlaneScene):  # noqa: ANN201 - generator fixture
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "macsplat_cli", "view", str(plane_scene.ply), "--port", "0", "--no-open"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=_sigint_default,
    )  # fmt: skip
    url = proc.stdout.readline().strip()  # type: ignore[union-attr]
    try:
        assert url.startswith("http://127.0.0.1:"), proc.stderr.read() if proc.poll() is not None else url  # type: ignore[union-attr]
        yield url, proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_page_draws_the_scene_as_macsplat_renders_it(served, plane_scene: PlaneScene) -> None:  # noqa: ANN001
    url, proc = served
    ours, alpha = _our_render(plane_scene)
    mask = region_mask(H, W)
    covered, empty = mask & (alpha > 0.9), mask & (alpha < 0.02)
    assert covered.sum() > 50_000 and empty.sum() > 20_000  # the test scene leaves both in view
    with Browser(CHROMIUM, W, H) as browser:
        browser.goto(url)
        shot, _ = wait_for_frame(browser, lambda s: _not_white(s)[covered].mean() > 0.95, timeout=90)
        time.sleep(1.0)  # let the splat sort settle, then the frame compared
        shot = browser.screenshot()
        assert _not_white(shot)[covered].mean() > 0.95  # Gaussians where they project
        assert (_not_white(shot) & ~_orange(shot))[empty].mean() < 0.1  # background (or a frustum) where none does
        a, b = _luminance_blocks(shot, mask), _luminance_blocks(ours, mask)
        assert np.corrcoef(a, b)[0, 1] >= 0.5

        # the frusta (orange), seen from behind and above both cameras
        browser.goto(url + "?initialCameraPosition=0.3,-2.5,-4&initialCameraLookAt=0.3,0,1&initialCameraUp=0,-1,0")

        shot, _ = wait_for_frame(browser, lambda s: _orange(s)[mask].sum() > 300, timeout=90)

        # the "render" button: macsplat's rasterizer renders the page's viewpoint into the panel
        clicked = browser.evaluate(
            "(() => { const b = [...document.querySelectorAll('button')]"
            ".find(e => e.textContent.includes('Render with macsplat')); if (b) b.click(); return !!b; })()"
        )
        assert clicked
        deadline = time.monotonic() + 60
        while "macsplat render," not in (browser.evaluate("document.body.innerText") or ""):
            assert time.monotonic() < deadline, "the render button showed no image"
            time.sleep(0.5)
        port = url.rsplit(":", 1)[1]
        local = (f"http://127.0.0.1:{port}/", f"blob:http://127.0.0.1:{port}/", "data:")
        assert browser.requests and all(u.startswith(local) for u in browser.requests), browser.requests
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=30) == 130
