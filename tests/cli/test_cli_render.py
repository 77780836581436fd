"""``macsplat render`` end to end, through the same entry point as the console script."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.cli import main
from macsplat_cli.images import load_image
from macsplat_cli.ply import read_ply, write_ply
from macsplat_cli.render import render_camera

from support.gaussians import random_gaussians

K = np.array([[120.0, 0.0, 40.0], [0.0, 120.0, 30.0], [0.0, 0.0, 1.0]])


def _pose(x: float, yaw_deg: float) -> np.ndarray:
    th = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]]
    T[0, 3] = x
    return T


@pytest.fixture
def scene(tmp_path: Path) -> tuple[Path, Path]:
    write_ply(tmp_path / "scene.ply", random_gaussians(800, seed=11, sh_degree=1))
    cams = CameraSet([Camera("a", 80, 60, K, _pose(0, 0)), Camera("b", 80, 60, K, _pose(0.4, -8))])
    save_cameras(tmp_path / "cams.json", cams)
    return tmp_path / "scene.ply", tmp_path / "cams.json"


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _read_rgb(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img[..., ::-1] if img.ndim == 3 else img


def test_render_matches_library_and_writes_depth(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    code, _, err = run(
        capsys,
        "render",
        ply,
        "--pose",
        cams,
        "--view",
        "1",
        "-o",
        tmp_path / "v.png",
        "--depth",
        tmp_path / "d.npy",
        "--background",
        "white",
    )
    assert code == 0, err
    img = _read_rgb(tmp_path / "v.png")
    assert img.shape == (60, 80, 3)
    from macsplat_cli.cameras import load_cameras

    expected = render_camera(read_ply(ply), load_cameras(cams)[1], background=(1.0, 1.0, 1.0))
    ref = np.clip(np.rint(expected.rgb.numpy() * 255), 0, 255).astype(np.uint8)
    assert np.abs(img.astype(int) - ref.astype(int)).max() <= 1
    depth = np.load(tmp_path / "d.npy")
    assert depth.dtype == np.float32 and depth.shape == (60, 80)
    np.testing.assert_allclose(depth, expected.depth.numpy(), rtol=1e-6)
    assert "macsplat render" in err  # summary table on stderr


def test_render_png_depth_is_16bit_millimetres(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    code, _, err = run(
        capsys, "render", ply, "--pose", cams, "-o", tmp_path / "v.jpg", "--depth", tmp_path / "d.png", "-q"
    )
    assert code == 0, err
    d = _read_rgb(tmp_path / "d.png")
    assert d.dtype == np.uint16
    valid = d > 0
    assert valid.mean() > 0.3 and 1500 < np.median(d[valid]) < 4500  # the scene is 2–4 units away
    assert err == ""  # --quiet


def test_render_creates_missing_output_folders(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    code, _, err = run(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "new" / "dir" / "v.png", "-q")
    assert code == 0, err
    assert (tmp_path / "new" / "dir" / "v.png").is_file()


def test_render_rescales_intrinsics(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    assert run(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "big.png", "--width", "160")[0] == 0
    assert run(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "small.png")[0] == 0
    big, small = _read_rgb(tmp_path / "big.png"), _read_rgb(tmp_path / "small.png")
    assert big.shape == (120, 160, 3)  # height follows the aspect ratio
    import cv2

    down = cv2.resize(big, (80, 60), interpolation=cv2.INTER_AREA)
    assert np.abs(down.astype(float) - small.astype(float)).mean() < 6  # same view, twice the resolution


def test_render_path_frames_and_videos(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    code, _, err = run(
        capsys,
        "render",
        ply,
        "--cameras",
        cams,
        "--path",
        "5",
        "-o",
        tmp_path / "frames",
        "--video",
        tmp_path / "path.gif",
    )
    assert code == 0, err
    frames = sorted((tmp_path / "frames").glob("*.png"))
    assert [f.name for f in frames] == [f"frame_{i:04d}.png" for i in range(5)]
    first = _read_rgb(frames[0])
    assert run(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "a.png")[0] == 0
    assert np.abs(first.astype(int) - _read_rgb(tmp_path / "a.png").astype(int)).max() <= 1  # path starts at camera a
    last = _read_rgb(frames[-1])
    assert run(capsys, "render", ply, "--pose", cams, "--view", "1", "-o", tmp_path / "b.png")[0] == 0
    assert np.abs(last.astype(int) - _read_rgb(tmp_path / "b.png").astype(int)).max() <= 1
    from PIL import Image

    with Image.open(tmp_path / "path.gif") as gif:
        assert gif.n_frames == 5 and gif.size == (80, 60)
    code, _, err = run(capsys, "render", ply, "--cameras", cams, "--path", "4", "--video", tmp_path / "p.mp4")
    assert code == 0, err
    import cv2

    cap = cv2.VideoCapture(str(tmp_path / "p.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 4
    cap.release()


def test_render_standard_ply_written_from_scratch(capsys, tmp_path: Path) -> None:  # noqa: ANN001
    """A PLY another tool could have written (plyfile, no normals, degree 0, extra property)."""
    from plyfile import PlyData, PlyElement

    n = 300
    rng = np.random.default_rng(5)
    names = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
        "confidence",
    ]
    arr = np.zeros(n, dtype=[(k, "f4") for k in names])
    arr["x"], arr["y"] = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    arr["z"] = rng.uniform(2, 4, n)
    for k in ("f_dc_0", "f_dc_1", "f_dc_2"):
        arr[k] = rng.normal(0, 1, n)
    arr["opacity"] = 2.0
    for k in ("scale_0", "scale_1", "scale_2"):
        arr[k] = np.log(0.08)
    arr["rot_0"] = 1.0
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "other.ply"))
    save_cameras(tmp_path / "c.json", CameraSet([Camera("c", 80, 60, K, np.eye(4))]))
    code, _, err = run(
        capsys, "render", tmp_path / "other.ply", "--pose", tmp_path / "c.json", "-o", tmp_path / "o.png"
    )
    assert code == 0, err
    img = _read_rgb(tmp_path / "o.png")
    assert img.mean() > 40  # the splats are visible and coloured, not background


# ------------------------------------------------------------------------------ bad input


def _bad(capsys, *args) -> str:  # noqa: ANN001
    code, _, err = run(capsys, *args)
    assert code == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    assert "Traceback" not in err
    return lines[0]


def test_bad_inputs_give_one_line_and_exit_2(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    out = tmp_path / "x.png"
    assert "missing.ply" in _bad(capsys, "render", tmp_path / "missing.ply", "--pose", cams, "-o", out)
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    assert "junk.ply" in _bad(capsys, "render", tmp_path / "junk.ply", "--pose", cams, "-o", out)
    (tmp_path / "pts.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n0 0 1\n"
    )
    assert "opacity" in _bad(capsys, "render", tmp_path / "pts.ply", "--pose", cams, "-o", out)
    (tmp_path / "bad.json").write_text("{ not json")
    assert "bad.json" in _bad(capsys, "render", ply, "--pose", tmp_path / "bad.json", "-o", out)
    doc = json.loads(cams.read_text())
    doc["cameras"][0]["cam_to_world"][0][0] = 2.0  # a scaled, non-rigid rotation
    (tmp_path / "nonrigid.json").write_text(json.dumps(doc))
    assert "rigid" in _bad(capsys, "render", ply, "--pose", tmp_path / "nonrigid.json", "-o", out)
    assert "is a file" in _bad(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "bad.json" / "x.png")
    assert "format" in _bad(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "x.xyz")
    assert "--view 5" in _bad(capsys, "render", ply, "--pose", cams, "--view", "5", "-o", out)
    assert "camera file" in _bad(capsys, "render", ply, "-o", out)
    assert "--path" in _bad(capsys, "render", ply, "--pose", cams, "-o", out, "--video", tmp_path / "v.mp4")
    assert "background" in _bad(capsys, "render", ply, "--pose", cams, "-o", out, "--background", "purple")
    assert "No such option" in _bad(capsys, "render", ply, "--bogus")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["scene.ply", "cams.json", "junk.ply", "pts.ply", "bad.json", "nonrigid.json"]
    )  # no partial or temporary files


def test_verbose_shows_traceback(capsys, scene, tmp_path: Path) -> None:  # noqa: ANN001
    ply, cams = scene
    code, _, err = run(capsys, "render", tmp_path / "missing.ply", "--pose", cams, "-o", tmp_path / "x.png", "-v")
    assert code == 2 and "Traceback" in err and "error:" in err


def test_failed_render_leaves_no_output(capsys, scene, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    ply, cams = scene

    def boom(*a, **k):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("kaboom")

    monkeypatch.setattr("macsplat_cli.images.cv2.imencode", boom)
    code, _, err = run(capsys, "render", ply, "--pose", cams, "-o", tmp_path / "x.png")
    assert code == 1 and "internal error: RuntimeError: kaboom" in err
    assert not (tmp_path / "x.png").exists()


def test_version_and_help_of_every_command(capsys) -> None:  # noqa: ANN001
    from macsplat_cli import __version__
    from macsplat_cli.cli import app

    code, out, _ = run(capsys, "--version")
    assert code == 0 and out.strip() == f"macsplat {__version__}"
    code, out, _ = run(capsys, "--help")
    assert code == 0
    commands = [c.name for c in app.registered_commands if not c.hidden]
    assert commands and all(name in out for name in commands)
    for name in commands:
        code, out, _ = run(capsys, name, "--help")
        assert code == 0 and "Usage" in out, name
    code, out, _ = run(capsys, "eval", "merge", "--help")  # eval's sub-command (registered as eval-merge, hidden)
    assert code == 0 and "Usage" in out and "SHARD..." in out


def test_console_script_exits_without_teardown_and_loses_nothing(tmp_path: Path, scene) -> None:  # noqa: ANN001
    """The installed entry point, in subprocesses: exit codes and stderr as a user sees them. ``run()`` ends the
    process with ``os._exit`` after a command: piped output complete, files whole, exit codes kept — and with
    ``MACSPLAT_CLEAN_EXIT=1`` (the normal teardown) the same."""
    ply, cams = scene
    exe = [sys.executable, "-m", "macsplat_cli"]
    outs = {}
    for clean in ("0", "1"):
        env = {**os.environ, "MACSPLAT_CLEAN_EXIT": clean, "COLUMNS": "100"}
        helped = subprocess.run([*exe, "--help"], capture_output=True, text=True, env=env)
        assert helped.returncode == 0 and helped.stdout.rstrip().endswith("╯"), helped.stdout[-200:]
        png = tmp_path / f"s{clean}.png"
        ok = subprocess.run([*exe, "render", str(ply), "--pose", str(cams), "-o", str(png)], capture_output=True,
                            text=True, env=env)  # fmt: skip
        # the summary table (stderr) is whole: its last line is the table's bottom border
        assert ok.returncode == 0 and png.name in ok.stderr and ok.stderr.rstrip().endswith("┘"), ok.stderr
        bad = subprocess.run([*exe, "render", str(ply), "--pose", str(tmp_path / "no.json"), "-o", str(png)],
                             capture_output=True, text=True, env=env)  # fmt: skip
        assert bad.returncode == 2 and bad.stderr.startswith("error:") and "\n" not in bad.stderr.strip(), bad.stderr
        outs[clean] = (helped.stdout, load_image(png).rgb)
    assert outs["0"][0] == outs["1"][0]
    np.testing.assert_array_equal(outs["0"][1], outs["1"][1])


def test_teardown_is_kept_when_something_may_need_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """A thread still running, the environment switch or a tracer keep the normal exit."""
    import threading

    from macsplat_cli.cli import _needs_teardown

    monkeypatch.delenv("MACSPLAT_CLEAN_EXIT", raising=False)
    monkeypatch.setattr(sys, "gettrace", lambda: None)
    monkeypatch.setattr(sys, "getprofile", lambda: None)
    monkeypatch.delitem(sys.modules, "coverage", raising=False)
    assert not _needs_teardown()
    monkeypatch.setenv("MACSPLAT_CLEAN_EXIT", "1")
    assert _needs_teardown()
    monkeypatch.setenv("MACSPLAT_CLEAN_EXIT", "0")
    stop = threading.Event()
    worker = threading.Thread(target=stop.wait)
    worker.start()
    try:
        assert _needs_teardown()
    finally:
        stop.set()
        worker.join()
    assert not _needs_teardown()
    monkeypatch.setattr(sys, "gettrace", lambda: print)
    assert _needs_teardown()
