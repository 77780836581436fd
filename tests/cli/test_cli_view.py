"""``macsplat view`` and ``reconstruct --view`` from the command line: bad input, the port, Ctrl-C, the wiring."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

import macsplat_cli.viewer as viewer
from macsplat_cli.cli import view as view_cli
from macsplat_cli.viewer import ViewerServer

from support.cli import run_cli
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
