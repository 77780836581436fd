"""``macsplat view`` and ``reconstruct --view`` from the command line: bad input, the port, Ctrl-C, the wiring."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest

import macsplat_cli.viewer as viewer
from macsplat_cli.cli import view as view_cli
from macsplat_cli.viewer import ViewerServer

from support.cli import one_error_line, run_cli
from support.scenes import PairSpec
from support.viewer_scene import PlaneScene, write_plane_scene

ROOT = Path(__file__).resolve().parents[2]


def _sigint_default() -> None:
    """In the child: Ctrl-C's default handling, even when this test runs where SIGINT is ignored (a background job
    of a non-interactive shell ignores it, and an ignored signal stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def plane_scene(tmp_path: Path) -> PlaneScene:
    return write_plane_scene(tmp_path)


def test_missing_extra_is_one_line_and_exit_2(plane_scene: PlaneScene, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser fails
    code, _, err = run_cli(["view", plane_scene.ply, "--no-open"])
    assert code == 2
    assert err.strip().splitlines() == ["error: the viewer needs viser: pip install 'macsplat[view]'"]


def test_port_in_use_is_refused_before_anything_is_served(plane_scene: PlaneScene) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        code, out, err = run_cli(["view", plane_scene.ply, "--port", port, "--no-open"])
    assert code == 2 and out == ""
    assert err.strip().splitlines() == [
        f"error: port {port} on 127.0.0.1 is in use: pick another with --port, or --port 0"
    ]


def test_bad_scene_file_is_exit_2(tmp_path: Path) -> None:
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    code, _, err = run_cli(["view", tmp_path / "bad.ply", "--port", "0", "--no-open"])
    assert code == 2 and err.startswith("error:") and len(err.strip().splitlines()) == 1


def test_images_must_be_a_folder(plane_scene: PlaneScene) -> None:
    code, _, err = run_cli(["view", plane_scene.ply, "--images", plane_scene.ply, "--no-open"])
    assert code == 2 and err.strip() == f"error: --images {plane_scene.ply}: not a folder"


def test_another_host_is_warned_about(plane_scene: PlaneScene, monkeypatch: pytest.MonkeyPatch) -> None:
    """A host that is not loopback prints who can then see the scene (checked on loopback: is_loopback is told no,
    so that the test serves nothing beyond this machine)."""
    monkeypatch.setattr(viewer, "is_loopback", lambda host: False)

    def interrupt(self: ViewerServer, *args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(ViewerServer, "wait", interrupt)
    code, out, err = run_cli(["view", plane_scene.ply, "--port", "0", "--no-open"])
    assert code == 130
    assert "warning: serving on 127.0.0.1: anyone who can reach this machine on port" in " ".join(err.split())
    assert out.startswith("http://127.0.0.1:")


def _served_once(monkeypatch: pytest.MonkeyPatch, args: list) -> tuple[int, str, str]:  # noqa: ANN001
    """``macsplat view ARGS --port 0 --no-open``, its page built and served, then Ctrl-C (exit 130)."""

    def interrupt(self: ViewerServer, *a: object, **kw: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(ViewerServer, "wait", interrupt)
    return run_cli(["view", *args, "--port", "0", "--no-open"])


def _cameras_named(plane_scene: PlaneScene, folder: Path, *names: str) -> Path:
    data = json.loads(plane_scene.cameras.read_text())
    data["cameras"] = [{**data["cameras"][0], "name": n} for n in names]
    folder.mkdir(exist_ok=True)
    (folder / "c.cameras.json").write_text(json.dumps(data))
    return folder / "c.cameras.json"


def test_a_camera_name_shows_no_photo_outside_the_folders(
    plane_scene: PlaneScene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Cameras named by a path out of ``--images``, the cameras' and the scene's folders have no photo (issue 37,
    V1); the photo inside ``--images`` is shown."""
    from PIL import Image

    for where in ("private/secret.png", "photos/left.png"):
        (tmp_path / where).parent.mkdir(exist_ok=True)
        Image.fromarray(np.full((24, 32, 3), 90, np.uint8)).save(tmp_path / where)
    secret = tmp_path / "private" / "secret.png"
    cams = _cameras_named(plane_scene, tmp_path / "c", str(secret), "../private/secret.png", "left")
    code, out, err = _served_once(monkeypatch, [plane_scene.ply, "--cameras", cams, "--images", tmp_path / "photos"])
    assert code == 130 and out.startswith("http://127.0.0.1:")
    assert "viewer: 6,912 Gaussians, 3 cameras, 1 photos" in err
    assert " ".join(err.split()).count("is drawn without a photo: its name is no file name inside the photo") == 2


def test_a_long_camera_name_is_drawn_without_a_photo(
    plane_scene: PlaneScene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A name longer than a file name can be (was: 'internal error: OSError: File name too long', a 2 MB line for a
    2 MB name) is a camera without a photo, said in a short line (issue 37, V4)."""
    cams = _cameras_named(plane_scene, tmp_path / "c", "x" * 300, "y" * 2_000_000)
    code, out, err = _served_once(monkeypatch, [plane_scene.ply, "--cameras", cams])
    assert code == 130 and out.startswith("http://127.0.0.1:"), err[:500]
    assert "viewer: 6,912 Gaussians, 2 cameras, 0 photos" in err and len(err) < 2000


def test_an_error_line_is_cut(plane_scene: PlaneScene) -> None:
    """A value quoted in an error is cut, so the line stays short (issue 37, V4): a 5,000-character --images name
    (was: 'internal error: OSError: File name too long' and the whole name)."""
    code, _, err = run_cli(["view", plane_scene.ply, "--images", "d" * 5000, "--no-open"])
    line = one_error_line(err)
    assert code == 2 and line.startswith("error: --images ddd") and line.endswith("…") and len(line) <= 2007


def test_view_serves_until_ctrl_c(plane_scene: PlaneScene) -> None:
    """The real command in its own process: the URL alone on stdout, the page served, Ctrl-C → exit 130."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "macsplat_cli", "view", str(plane_scene.ply), "--port", "0", "--no-open"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=_sigint_default,
    )  # fmt: skip
    try:
        url = proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    assert "viewer: 6,912 Gaussians, 2 cameras, 0 photos" in err and "interrupted" in err
    assert "Traceback" not in err


def test_reconstruct_view_serves_what_it_wrote(
    pair_files,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,  # noqa: ANN001 - session fixture
) -> None:
    seen: dict = {}

    def fake_serve(gaussians, cameras, **kwargs) -> None:  # noqa: ANN001
        seen.update(gaussians=gaussians, cameras=cameras, **kwargs)

    monkeypatch.setattr(view_cli, "serve_scene", fake_serve)
    pair = pair_files(PairSpec(size=(256, 192)))
    out = tmp_path / "scene.ply"
    code, _, err = run_cli(["reconstruct", pair.a, pair.b, "-o", out, "--view", "--view-port", "0", "-q"])
    assert code == 0, err
    from macsplat_cli.cameras import load_cameras
    from macsplat_cli.ply import read_ply

    assert len(seen["gaussians"]) == len(read_ply(out)) > 0
    assert [c.name for c in seen["cameras"]] == [c.name for c in load_cameras(tmp_path / "scene.cameras.json").cameras]
    assert seen["image_folders"] == [pair.a.parent] and seen["port"] == 0 and seen["host"] == "127.0.0.1"


def test_reconstruct_view_checks_the_port_before_the_work(pair_files, tmp_path: Path) -> None:  # noqa: ANN001
    pair = pair_files(PairSpec(size=(256, 192)))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        code, _, err = run_cli(["reconstruct", pair.a, pair.b, "-o", tmp_path / "s.ply", "--view", "--view-port", port])
    assert code == 2 and "is in use" in err
    assert not (tmp_path / "s.ply").exists()
