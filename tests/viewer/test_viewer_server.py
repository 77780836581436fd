"""The viewer's server (viser on loopback): what it serves, and its "render" button's image."""

from __future__ import annotations

import logging
import time
import urllib.error
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from macsplat_cli.errors import InputError
from macsplat_cli.images import to_uint8
from macsplat_cli.render import render
from macsplat_cli.viewer import ViewerConfig, ViewerServer, camera_pose, resolve_port

from support.viewer_scene import PlaneScene

viser = pytest.importorskip("viser")


@pytest.fixture
def server(plane_scene: PlaneScene):  # noqa: ANN201 - generator fixture
    config = ViewerConfig(port=resolve_port("127.0.0.1", 0), render_long_side=160)
    s = ViewerServer(plane_scene.gaussians, plane_scene.camera_list, title="plane.ply", config=config)
    yield s
    s.stop()


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def test_serves_the_page_on_loopback_and_no_files(server: ViewerServer, plane_scene: PlaneScene) -> None:
    assert server.url == f"http://127.0.0.1:{server.port}"
    status, body = _get(server.url + "/")
    assert status == 200 and b"<html" in body.lower()
    secret = plane_scene.ply.read_bytes()[:200]
    for path in ("/plane.ply", "/../plane.ply", "/%2e%2e/%2e%2e/etc/passwd", f"/{plane_scene.ply}"):
        status, body = _get(server.url + path)
        assert secret not in body and b"root:" not in body, path
    assert server.server.request_share_url() is None  # never a tunnel through a public relay


def test_render_button_image_is_macsplats_render_of_that_view(server: ViewerServer, plane_scene: PlaneScene) -> None:
    cam = plane_scene.camera_list[1]
    pose = camera_pose(cam)
    image = server.render_view(pose.wxyz, pose.position, pose.fov_y, pose.aspect)
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8  # long side 160, the camera's aspect
    K = torch.tensor(cam.K, dtype=torch.float32)
    K[:2] *= 0.5  # 320x240 -> 160x120; the principal point is the centre, as the viewer has it
    viewmat = torch.from_numpy(np.linalg.inv(cam.cam_to_world)).float()
    expected = to_uint8(render(plane_scene.gaussians, viewmat, K, 160, 120).rgb)
    assert np.abs(image.astype(int) - expected.astype(int)).max() <= 1
    assert image.std() > 10  # the plane's blocks, not an empty frame


def test_too_many_gaussians_are_refused_with_a_budget_hint(plane_scene: PlaneScene) -> None:
    config = ViewerConfig(port=resolve_port("127.0.0.1", 0), max_gaussians=1000)
    with pytest.raises(InputError, match=r"6,912 Gaussians is more than the viewer takes \(1,000\).*--budget 500"):
        ViewerServer(plane_scene.gaussians, plane_scene.camera_list, config=config)


def test_a_scene_without_cameras_is_served(plane_scene: PlaneScene) -> None:
    s = ViewerServer(plane_scene.gaussians, [], config=ViewerConfig(port=resolve_port("127.0.0.1", 0)))
    try:
        assert _get(s.url + "/")[0] == 200
    finally:
        s.stop()


def _connect(server: ViewerServer, origin: str | None, **headers: str):  # noqa: ANN202 - a websockets connection
    from websockets.sync.client import connect

    return connect(
        server.url.replace("http://", "ws://"), subprotocols=[f"viser-v{viser.__version__}"], max_size=None,
        open_timeout=10, origin=origin, additional_headers=headers or None,
    )  # fmt: skip


def test_websocket_takes_only_the_viewers_own_page(server: ViewerServer, caplog: pytest.LogCaptureFixture) -> None:
    """Another web site's page cannot open the WebSocket and read the scene (issue 37, V2): refused with 403 before
    any message; the viewer's own page (any loopback spelling) and clients without an Origin are served."""
    from websockets.exceptions import InvalidStatus

    port = server.port
    with caplog.at_level(logging.WARNING, logger="macsplat_cli"):
        for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{port + 1}",
                       f"https://127.0.0.1:{port}", "null", f"http://127.0.0.1.evil.example:{port}"):  # fmt: skip
            with pytest.raises(InvalidStatus) as refused:
                _connect(server, origin)
            assert refused.value.response.status_code == 403, origin
        with pytest.raises(InvalidStatus):  # the first of two Origin headers is not enough
            _connect(server, f"http://127.0.0.1:{port}", Origin="http://evil.example")
    assert len(caplog.records) == 7 and "refused a connection from the web page at 'http://evil.example'" in (
        caplog.records[0].getMessage()
    )
    for origin in (f"http://127.0.0.1:{port}", f"http://localhost:{port}", f"http://LOCALHOST:{port}/",
                   f"http://[::1]:{port}", None):  # fmt: skip
        with _connect(server, origin) as ws:
            assert len(ws.recv(timeout=20)) > 1000, origin  # the scene's messages


def test_origin_rules_for_another_host() -> None:
    """With ``--host`` other than loopback, the page's origin is the address the browser reached (or --host)."""
    from macsplat_cli.viewer.origin import origin_allowed

    lan = ("192.168.1.5", 8080)
    assert origin_allowed("http://192.168.1.5:8080", "0.0.0.0", lan)
    assert origin_allowed("http://192.168.1.5:8080", "0.0.0.0", ("::ffff:192.168.1.5", 8080, 0, 0))
    assert origin_allowed("http://viewer.lan:8080", "viewer.lan", lan)
    assert not origin_allowed("http://192.168.1.6:8080", "0.0.0.0", lan)  # another machine's page
    assert not origin_allowed("http://rebound.example:8080", "0.0.0.0", lan)  # a DNS-rebinding page
    assert origin_allowed("http://127.0.0.1", "127.0.0.1", ("127.0.0.1", 80))  # port 80 is left out
    assert not origin_allowed("http://127.0.0.1:99999", "127.0.0.1", ("127.0.0.1", 8080))


def test_a_viser_that_starts_otherwise_is_refused(plane_scene: PlaneScene, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where viser would start its server without the origin check (another viser version), nothing is served."""
    from macsplat_cli.viewer.origin import OriginGuard

    monkeypatch.setattr(OriginGuard, "wrap", lambda self, serve: serve)  # viser's serve, unchecked
    port = resolve_port("127.0.0.1", 0)
    with pytest.raises(InputError, match=r"cannot check its clients' web origin with viser 1\."):
        ViewerServer(plane_scene.gaussians, [], config=ViewerConfig(port=port))
    assert resolve_port("127.0.0.1", port) == port  # stopped: the port is free again


class _Camera:
    """What a client's page last sent as its camera (viser's CameraHandle's fields)."""

    def __init__(  # noqa: ANN001
        self, wxyz=(1.0, 0, 0, 0), position=(0.0, 0, 0), fov=1.0, image_width=640, image_height=480
    ) -> None:
        self.wxyz, self.position, self.fov = np.asarray(wxyz, float), np.asarray(position, float), fov
        self.image_width, self.image_height = image_width, image_height

    @property
    def aspect(self) -> float:
        return float(self.image_width) / self.image_height


def test_a_degenerate_client_camera_is_one_log_line(server: ViewerServer, caplog: pytest.LogCaptureFixture) -> None:
    """Any client can send a camera that cannot be rendered; "Render with macsplat" then logs one line and notes
    it in the panel instead of raising (issue 37, V3)."""
    nan = float("nan")
    bad = [
        _Camera(image_height=0), _Camera(wxyz=(0.0, 0, 0, 0)), _Camera(position=(nan, 0, 0)), _Camera(fov=nan),
        _Camera(fov=0.0), _Camera(fov=4.0), _Camera(image_width=10**9, image_height=1), _Camera(position=(1e300, 0, 0)),
        _Camera(wxyz=(1e300, 1e300, 0, 0)),
    ]  # fmt: skip
    for cam in bad:
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="macsplat_cli"):
            server._render_for(SimpleNamespace(camera=cam))
        assert len(caplog.records) == 1 and "a client's view was not rendered" in caplog.records[0].getMessage()
        assert server._render_note.content.startswith("cannot render this view: ")
    server._render_for(SimpleNamespace(camera=_Camera(wxyz=(2.0, 0, 0, 0))))  # any length: the rotation is taken
    assert server._render_note.content.startswith("macsplat render, 160×120 px")


def test_a_client_sending_a_degenerate_camera_gets_no_traceback(
    server: ViewerServer, capfd: pytest.CaptureFixture, caplog: pytest.LogCaptureFixture
) -> None:
    """The campaign's client (issue 37, V3): a camera of height 0, then a click on the render button, over the
    WebSocket; the viewer writes no traceback and still renders the next, sound view."""
    import msgspec
    import zstandard
    from viser import _messages as M

    def send(ws, message) -> None:  # noqa: ANN001
        ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    def camera(height: int) -> M.ViewerCameraMessage:
        return M.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0), fov=1.0, near=0.01, far=100.0, image_height=height,
            image_width=640, look_at=(0.0, 0.0, 1.0), up_direction=(0.0, -1.0, 0.0),
        )  # fmt: skip

    def wait_for(text: str) -> None:
        deadline = time.monotonic() + 20
        while text not in server._render_note.content:
            assert time.monotonic() < deadline, server._render_note.content
            time.sleep(0.05)

    with _connect(server, None) as ws:
        raw = ws.recv(timeout=20)
        n_in, n_c = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
        doc = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(raw[16 : 16 + n_c], max_output_size=n_in))
        button = next(
            m["uuid"] for m in doc["messages"]
            if m.get("type") == "GuiButtonMessage" and "Render with macsplat" in str(m.get("props"))
        )  # fmt: skip
        with caplog.at_level(logging.WARNING, logger="macsplat_cli"):
            send(ws, camera(0))
            time.sleep(0.3)
            send(ws, M.GuiUpdateMessage(uuid=button, updates={"value": True}))
            wait_for("cannot render this view")
            send(ws, camera(480))
            time.sleep(0.3)
            send(ws, M.GuiUpdateMessage(uuid=button, updates={"value": True}))
            wait_for("macsplat render, 160×120 px")
    assert [r.getMessage() for r in caplog.records] == [
        "viewer: a client's view was not rendered: image size 640×0 px is empty or too narrow"
    ]
    assert "Traceback" not in capfd.readouterr().err


def test_camera_names_are_shown_cut_and_unique() -> None:
    """The page shows a camera's name cut to 80 characters (a 2 MB name is not sent as a label), one entry each."""
    from macsplat_cli.viewer.server import shown_names

    shown = shown_names(["left", "x" * 2_000_000, "x" * 300, "left", "left #4"])
    assert shown[0] == "left" and shown[1] == "x" * 79 + "…" and len(set(shown)) == 5
    assert shown[2] == "x" * 79 + "… #3" and shown[3] == "left #4" and shown[4] == "left #4 #5"
    assert shown_names(["a", "a #3", "a"]) == ["a", "a #3", "a #3'"]
