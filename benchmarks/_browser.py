"""Headless Chromium driven over the DevTools protocol: load a page, screenshot it, list what it fetched.

For the viewer's browser test and its time-to-first-frame benchmark. WebGL runs on the CPU through SwiftShader
(``--use-angle=swiftshader --enable-unsafe-swiftshader``). Every host name resolves to nothing
(``--host-resolver-rules``), so the page can reach loopback addresses only; :attr:`Browser.requests` lists every
URL it asked for, to prove it. Needs ``websockets`` (a dependency of the ``view`` extra).
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from typing import Any

import numpy as np

PROFILE_REMOVE_TRIES = 10  # × 0.2 s: long enough for exiting helpers to finish writing
CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")


def find_chromium() -> str | None:
    """The path of a Chromium or Chrome executable on PATH, or None."""
    for name in CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """One headless Chromium with one page of ``width`` × ``height`` CSS pixels (device scale 1)."""

    def __init__(self, executable: str, width: int = 1024, height: int = 768, timeout: float = 30.0) -> None:
        from websockets.sync.client import connect

        self._profile = tempfile.TemporaryDirectory(prefix="macsplat-chromium-")
        args = [
            executable, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
            "--enable-webgl", "--ignore-gpu-blocklist", "--no-first-run", "--no-default-browser-check",
            "--disable-background-networking", "--disable-component-update", "--disable-sync", "--disable-extensions",
            "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1", f"--user-data-dir={self._profile.name}",
            f"--window-size={width},{height}", "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
            "about:blank",
        ]  # fmt: skip
        # Its own process group: Chromium's helper processes (renderer, GPU, crash handler) outlive a terminated
        # main process and keep writing the profile, so close() ends the whole group before removing it.
        self._proc = subprocess.Popen(
            args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True
        )
        port = self._devtools_port(timeout)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=timeout) as r:
            pages = [t for t in json.load(r) if t.get("type") == "page"]
        self._ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=2**28, open_timeout=timeout)
        self._ids = itertools.count(1)
        self.requests: list[str] = []
        self._loaded = False
        self.console_errors: list[str] = []
        self.call("Page.enable")
        self.call("Network.enable")
        self.call("Runtime.enable")
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def _devtools_port(self, timeout: float) -> int:
        assert self._proc.stderr is not None
        deadline = time.monotonic() + timeout
        lines = []
        while time.monotonic() < deadline:
            line = self._proc.stderr.readline()
            if not line and self._proc.poll() is not None:
                break
            lines.append(line)
            m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
            if m:
                return int(m.group(1))
        raise RuntimeError("Chromium did not start: " + "".join(lines[-5:]).strip())

    def _event(self, msg: dict[str, Any]) -> None:
        method, params = msg.get("method"), msg.get("params", {})
        if method == "Network.requestWillBeSent":
            self.requests.append(params["request"]["url"])
        elif method == "Page.loadEventFired":
            self._loaded = True
        elif method == "Runtime.exceptionThrown":
            self.console_errors.append(str(params.get("exceptionDetails", {}).get("text")))

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command; its result (events received meanwhile are recorded)."""
        i = next(self._ids)
        self._ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=120))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def goto(self, url: str, timeout: float = 60.0) -> None:
        """Navigate and wait for the page's load event."""
        self._loaded = False
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + timeout
        while not self._loaded:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"{url} did not load in {timeout:.0f} s")
            self._event(json.loads(self._ws.recv(timeout=remaining)))

    def screenshot(self) -> np.ndarray:
        """The page as it is now. [H, W, 3] uint8 RGB"""
        import cv2

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise RuntimeError("the browser's screenshot is not a PNG OpenCV can decode")
        return np.ascontiguousarray(bgr[..., ::-1])

    def evaluate(self, expression: str) -> Any:
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True).get("result", {}).get("value")

    def close(self) -> None:
        try:
            self._ws.close()
        finally:
            self._signal_group(signal.SIGTERM)
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
            self._signal_group(signal.SIGKILL)
            self._proc.wait()
            self._remove_profile()

    def _signal_group(self, sig: signal.Signals) -> None:
        try:
            os.killpg(self._proc.pid, sig)
        except ProcessLookupError:  # the group is gone already
            pass

    def _remove_profile(self, tries: int = PROFILE_REMOVE_TRIES) -> None:
        """Removes the profile folder; a helper that was still exiting may add a file between listing and removal."""
        for _ in range(tries - 1):
            try:
                shutil.rmtree(self._profile.name)
                break
            except FileNotFoundError:
                break
            except OSError:
                time.sleep(0.2)
        self._profile.cleanup()

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_for_frame(browser: Browser, drawn: Any, timeout: float = 60.0, poll: float = 0.25) -> tuple[np.ndarray, float]:
    """Screenshots until ``drawn(screenshot)`` is true: (that screenshot, seconds waited); TimeoutError if never."""
    t0 = time.monotonic()
    while True:
        shot = browser.screenshot()
        if drawn(shot):
            return shot, time.monotonic() - t0
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(f"the page drew nothing that passes in {timeout:.0f} s")
        time.sleep(poll)


def region_mask(height: int, width: int) -> np.ndarray:
    """Pixels of a viser page that show the scene: without the control panel (top right), the notification (top
    left) and the axes gizmo (bottom left). [H, W] bool"""
    mask = np.ones((height, width), bool)
    mask[:260, :] = False
    mask[height - 90 :, :90] = False
    return mask
