"""Hostile and odd inputs to the command line (issue 16).

* outputs that are inputs (same path, symbolic or hard link, a file inside --renders or a
  frame folder) are refused before any work, and the input is left as it was;
* Rich markup in file names and option values (``[/]``, ``[copy]``) is printed verbatim, in
  error lines and in summaries, for every command;
* SIGTERM during a write removes the partial file (exit 143, SIGINT 130), and temporary files
  left by killed writes are removed by the next write of the same file once their process is gone;
* an unwritable existing --renders folder is found before the first stage: nothing is written.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from macsplat_cli._atomic import atomic_write_bytes, remove_stale_temporaries
from macsplat_cli.cameras import CameraSet, save_cameras
from macsplat_cli.cli import main
from macsplat_cli.cli._common import err_console
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.pipeline.run import Pipeline
from macsplat_cli.ply import write_ply

from support import REPO
from support.gaussians import random_gaussians
from support.scenes import PairFactory, PairSpec

SIZE = (128, 96)  # the pair; reconstructed at --size 128 in about a second


@pytest.fixture(scope="module")
def pair(pair_files: PairFactory) -> tuple[Path, Path]:
    """A textured room pair 12° apart at 128×96, with Rich markup in its file names."""
    return pair_files(
        PairSpec("room", 12.0, SIZE, 60.0, scene_seed=5), ("IMG_001 [copy].png", "[bold]IMG_002.png")
    ).photos


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A small valid scene (PLY) and a two-camera file at 64×48 for ``render``."""
    folder = tmp_path_factory.mktemp("hostile_scene")
    g = random_gaussians(200, seed=3)
    write_ply(folder / "scene.ply", g)
    cams = syn.orbit_pair("room", 12.0, width=64, height=48, fov_deg=60.0)
    save_cameras(folder / "cams.json", CameraSet(list(cams)))
    return folder / "scene.ply", folder / "cams.json"


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and "MarkupError" not in err, err
    assert sum("error:" in ln for ln in lines) == 1 and lines[-1].startswith("error: "), err
    return lines[-1]


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in sorted(folder.rglob("*"))}


# ------------------------------------------------------------------------------ outputs vs inputs
def _link(kind: str, src: Path, dst: Path) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if kind == "hard":
        os.link(src, dst)
    else:
        dst.symlink_to(src)
    return dst


@pytest.mark.parametrize(
    ("case", "label"),
    [
        ("cameras-is-photo-b", "--cameras"),
        ("report-is-photo-a", "--report"),
        ("report-hard-link-to-a", "--report"),
        ("cameras-symlink-to-b", "--cameras"),
        ("report-is-intrinsics", "--report"),
        ("renders-holds-photo-a", "--renders"),
        ("scene-is-lpips-weights", "-o"),
    ],
)
def test_reconstruct_refuses_to_overwrite_an_input(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, case: str, label: str
) -> None:
    """An output that is an input (path, link or a view file inside --renders): exit 2, before any work."""
    calls: list[object] = []
    monkeypatch.setattr(Pipeline, "run", lambda self, *a, **k: calls.append(a))
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    a.write_bytes(b"photo a")
    b.write_bytes(b"photo b")
    cams = tmp_path / "cams.json"
    cams.write_text("{}")
    args: list[str | Path] = ["reconstruct", a, b, "-o", tmp_path / "s.ply", "-q"]
    args += {
        "cameras-is-photo-b": ["--cameras", b],
        "report-is-photo-a": ["--report", a],
        "report-hard-link-to-a": ["--report", _link("hard", a, tmp_path / "x" / "report.json")],
        "cameras-symlink-to-b": ["--cameras", _link("sym", b, tmp_path / "y" / "c.json")],
        "report-is-intrinsics": ["--intrinsics", cams, "--report", cams],
        "renders-holds-photo-a": ["--renders", _link("hard", a, tmp_path / "views" / "view_001.png").parent],
        "scene-is-lpips-weights": ["--refine", "2", "--lpips-weights", tmp_path / "s.ply"],
    }[case]
    if case == "scene-is-lpips-weights":
        (tmp_path / "s.ply").write_bytes(b"weights")
    before = _snapshot(tmp_path)
    got = main([str(x) for x in args])
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2, line
    assert line.startswith(f"error: {label} ") and "refusing to overwrite an input" in line, line
    assert calls == []
    assert _snapshot(tmp_path) == before  # the inputs as they were, nothing new


def test_reconstruct_two_outputs_hard_linked_are_one_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Two outputs that are hard links of one existing file collide like two equal paths."""
    (tmp_path / "r.json").write_text("old")
    os.link(tmp_path / "r.json", tmp_path / "c.json")
    got = main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(tmp_path / "s.ply"),
                "--cameras", str(tmp_path / "c.json"), "--report", str(tmp_path / "r.json")])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and "same file" in line, line
    assert (tmp_path / "r.json").read_text() == "old"


@pytest.mark.parametrize("case", ["output-hard-link-to-scene", "depth-symlink-to-cameras", "frame-is-the-scene"])
def test_render_refuses_to_overwrite_an_input(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path], case: str
) -> None:
    """``render``: the image, depth or a frame of -o DIR that is the scene or the camera file → exit 2."""
    scene = tmp_path / "scene.ply"
    scene.write_bytes(scene_files[0].read_bytes())
    cams = tmp_path / "cams.json"
    cams.write_bytes(scene_files[1].read_bytes())
    args: list[str | Path] = ["render", scene, "--pose", cams, "-q"]
    args += {
        "output-hard-link-to-scene": ["-o", _link("hard", scene, tmp_path / "view.png")],
        "depth-symlink-to-cameras": ["-o", tmp_path / "v.png", "--depth", _link("sym", cams, tmp_path / "d.png")],
        "frame-is-the-scene": ["--path", "3", "-o", _link("hard", scene, tmp_path / "f" / "frame_0002.png").parent],
    }[case]
    before = _snapshot(tmp_path)
    got = main([str(x) for x in args])
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and "refusing to overwrite an input" in line, line
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--path", "10001", "-o", "frames"], "less than or equal to 10000"),  # more views than any path needs
        (["--path", "2000", "--width", "8000", "--height", "6000", "--video", "v.gif"], "GiB in memory"),
    ],
)
def test_render_path_is_bounded_before_any_work(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path], extra: list[str], needle: str
) -> None:
    """``render --path N``: N is capped, and a GIF whose frames would not fit in memory (Pillow holds them all) is
    refused before the first frame (exit 2, nothing written)."""
    args = ["render", str(scene_files[0]), "--pose", str(scene_files[1]), "-q"]
    args += [str(tmp_path / a) if a in ("frames", "v.gif") else a for a in extra]
    before = _snapshot(tmp_path)
    got = main(args)
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and needle in line, line
    assert _snapshot(tmp_path) == before


def test_export_onnx_refuses_to_overwrite_a_checkpoint(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``export-onnx -o`` that is (a link to) a checkpoint: exit 2 before the checkpoints load."""
    import macsplat_cli.neural.loading as loading

    loads: list[object] = []

    def load(**files: object) -> None:
        loads.append(files)
        raise RuntimeError("loaded")

    monkeypatch.setattr(loading, "load_pair_predictor", load)
    weights = tmp_path / "mast3r.pth"
    weights.write_bytes(b"checkpoint")
    out = _link("sym", weights, tmp_path / "predictor.onnx")
    got = main(["export-onnx", "-o", str(out), "--weights", str(weights), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and line.startswith("error: -o ") and "--weights" in line, line
    assert loads == [] and weights.read_bytes() == b"checkpoint"


# ------------------------------------------------------------------------------ Rich markup
@pytest.mark.parametrize(
    ("args", "verbatim"),
    [
        pytest.param(["reconstruct", "{a}", "{b}", "-o", "{tmp}/s.ply", "--refine", "[/]"], "'[/]'",
                     id="reconstruct-refine"),
        pytest.param(["reconstruct", "{tmp}/IMG_001 [copy].jpg", "{b}", "-o", "{tmp}/s.ply"], "IMG_001 [copy].jpg",
                     id="reconstruct-missing-bracketed-photo"),
        pytest.param(["reconstruct", "{a}", "{b}", "-o", "{tmp}/[bold]s[/].txt"], "[bold]s[/].txt",
                     id="reconstruct-output-name"),
        pytest.param(["reconstruct", "{a}", "{b}", "-o", "{tmp}/s.ply", "--quality", "[red]x"], "'[red]x'",
                     id="reconstruct-quality"),
        pytest.param(["render", "{scene}", "--pose", "{cams}", "-o", "{tmp}/v.png", "--background", "[/]"], "'[/]'",
                     id="render-background"),
        pytest.param(["render", "{scene}", "--pose", "{cams}", "-o", "{tmp}/v.png", "--backend", "[/]"], "'[/]'",
                     id="render-backend-usage-error"),
        pytest.param(["render", "{scene}", "--pose", "{badk}", "-o", "{tmp}/v.png"], "[[fx",
                     id="render-builtin-message-with-brackets"),
        pytest.param(["eval", "--data", "{tmp}/d", "--backend", "[/]"], "'[/]'", id="eval-backend"),
        pytest.param(["bench", "--data", "{tmp}/d", "--size", "[/]"], "'[/]'", id="bench-size"),
        pytest.param(["train", "--data", "{tmp}/d", "--out", "{tmp}/o", "--size", "[/]"], "'[/]'", id="train-size"),
        pytest.param(["export-onnx", "-o", "{tmp}/[/]x.txt", "--weights", "{tmp}/w.pth"], "[/]x.txt",
                     id="export-onnx-output"),
        pytest.param(["export-onnx", "-o", "{tmp}/x.onnx", "--weights", "{tmp}/w.pth", "--size", "[/]"], "'[/]'",
                     id="export-onnx-size"),
    ],
)  # fmt: skip
def test_markup_in_names_and_values_is_printed_verbatim(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    pair: tuple[Path, Path],
    scene_files: tuple[Path, Path],
    args: list[str],
    verbatim: str,
) -> None:
    """Bracketed text in a path or option value: exit 2 and one ``error:`` line holding it verbatim."""
    badk = json.loads(scene_files[1].read_text())
    badk["cameras"][0]["K"][2] = [0.0, 1.0, 1.0]
    (tmp_path / "badk.json").write_text(json.dumps(badk))
    names = {"{a}": pair[0], "{b}": pair[1], "{scene}": scene_files[0], "{cams}": scene_files[1],
             "{badk}": tmp_path / "badk.json", "{tmp}": tmp_path}  # fmt: skip
    argv = []
    for x in args:
        for k, v in names.items():
            x = x.replace(k, str(v))
        argv.append(x)
    got = main(argv)
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2, line
    assert verbatim in line, line


def test_a_usage_error_line_is_cut(capsys: pytest.CaptureFixture[str]) -> None:
    """A usage error quoting a huge option name is one short line, cut like every error line (issue 37, V4: the
    option parser's errors were printed whole)."""
    got = main(["reconstruct", "--bogus-" + "q" * 5000])
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and "--bogus-qqq" in line and line.endswith("…") and len(line) <= 2010, len(line)


def test_reconstruct_with_markup_in_every_name_succeeds_and_prints_them(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, pair: tuple[Path, Path]
) -> None:
    """Photos ``IMG_001 [copy].png``, ``[bold]IMG_002.png`` and outputs under ``[/]``: exit 0, names intact."""
    monkeypatch.setattr(err_console, "_width", 1000)  # one table row per line: the paths unwrapped
    out = tmp_path / "[/]" / "scene [copy].ply"
    report = tmp_path / "[red]r[/].json"
    got = main(["reconstruct", str(pair[0]), str(pair[1]), "-o", str(out), "--report", str(report),
                "--size", str(SIZE[0]), "--focal", "111"])  # fmt: skip
    err = capsys.readouterr().err
    assert got == 0, err
    assert out.is_file() and out.with_name("scene [copy].cameras.json").is_file() and report.is_file()
    assert "Traceback" not in err and "error:" not in err
    for text in ("IMG_001 [copy].png", "[bold]IMG_002.png", str(out), str(out.with_name("scene [copy].cameras.json"))):
        assert text in err, (text, err)


# ------------------------------------------------------------------------------ output locations
@pytest.mark.parametrize("case", ["existing-renders-not-writable", "renders-holds-a-folder-named-like-a-view"])
def test_unwritable_renders_folder_fails_before_any_work(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    pair: tuple[Path, Path],
    case: str,
) -> None:
    """An existing --renders folder that cannot take the views: exit 2, and no scene, cameras or view written."""
    renders = tmp_path / "views"
    renders.mkdir()
    if case == "existing-renders-not-writable":  # tests run as root, who may write anywhere: ask os.access
        real_access = os.access

        def access(p: str | os.PathLike[str], mode: int, **kw: object) -> bool:
            return not (mode & os.W_OK and Path(p) == renders) and real_access(p, mode, **kw)  # type: ignore[arg-type]

        monkeypatch.setattr(os, "access", access)
    else:
        (renders / "view_001.png").mkdir()
    before = _snapshot(tmp_path)
    got = main(["reconstruct", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "s.ply"), "--renders", str(renders),
                "--num-renders", "3", "--report", str(tmp_path / "r.json"), "--size", str(SIZE[0])])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and "views" in line, line
    assert _snapshot(tmp_path) == before  # nothing at all written


# ------------------------------------------------------------------------------ signals, stale temporaries
_HANG_IN_A_WRITE = """
import sys, time
import macsplat_cli.cli.reconstruct as command
from macsplat_cli._atomic import atomic_path
from macsplat_cli.cli import main

def hang(images, config, *, output, **kw):
    with atomic_path(output) as tmp:
        tmp.write_bytes(b"half a scene")
        print("writing", flush=True)
        time.sleep(60)

command._reconstruct = hang
sys.exit(main(sys.argv[1:]))
"""


def _default_signals() -> None:
    """In the child before exec: SIGINT and SIGTERM at their defaults, as in a terminal."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "SIGINT"])
def test_signal_during_a_write_leaves_no_temporary_file(tmp_path: Path, sig: signal.Signals, code: int) -> None:
    """``kill``/``timeout`` (SIGTERM) mid-write: the partial file is removed, exit 143 (Ctrl-C: 130)."""
    out = tmp_path / "out"
    out.mkdir()
    script = tmp_path / "hang.py"
    script.write_text(_HANG_IN_A_WRITE)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, str(script), "reconstruct", "a.png", "b.png", "-o", str(out / "x.ply")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        preexec_fn=_default_signals,  # a background pytest (``cmd &``) starts children with SIGINT ignored
    )  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "writing", proc.stderr
        assert [p.name for p in out.iterdir() if p.name.startswith(".x.ply.")], "the write should be in progress"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code, err
    assert "interrupted" in err and "Traceback" not in err, err
    assert list(out.iterdir()) == []


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _plant(folder: Path, name: str, age_s: float) -> Path:
    p = folder / name
    p.write_bytes(b"partial")
    t = time.time() - age_s
    os.utime(p, (t, t))
    return p


def test_stale_temporaries_of_dead_processes_are_removed_by_the_next_write(tmp_path: Path) -> None:
    """Only old temporaries of the same file whose process is gone are removed; live or fresh ones stay."""
    dead, live = _dead_pid(), os.getpid()
    stale = _plant(tmp_path, f".scene.ply.{dead}.k3j_9x2a.tmp.ply", 120)
    kept = [
        _plant(tmp_path, f".scene.ply.{live}.a1b2c3d4.tmp.ply", 120),  # its process still runs
        _plant(tmp_path, f".scene.ply.{dead}.zzzzzzzz.tmp.ply", 5),  # too recent to judge
        _plant(tmp_path, f".other.ply.{dead}.q1w2e3r4.tmp.ply", 120),  # another file's
        _plant(tmp_path, f".scene.ply.7.ply.{dead}.q1w2e3r4.tmp.ply", 120),  # scene.ply.7.ply's
        _plant(tmp_path, ".scene.ply.notapid.tmp.ply", 120),  # not named by atomic_path
    ]
    atomic_write_bytes(tmp_path / "scene.ply", b"new scene")
    assert not stale.exists()
    assert all(p.exists() for p in kept)
    assert (tmp_path / "scene.ply").read_bytes() == b"new scene"
    assert sorted(tmp_path.iterdir()) == sorted([*kept, tmp_path / "scene.ply"])


def test_a_killed_write_is_cleaned_by_the_next_one(tmp_path: Path) -> None:
    """SIGKILL cannot be handled: its temporary file stays, named with the pid, until the next write."""
    script = textwrap.dedent(
        f"""
        import time
        from macsplat_cli._atomic import atomic_path
        with atomic_path({str(tmp_path / "[copy] x.ply")!r}) as tmp:
            tmp.write_bytes(b"half")
            print("writing", flush=True)
            time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})  # fmt: skip
    assert proc.stdout is not None and proc.stdout.readline().strip() == "writing"
    proc.kill()
    proc.wait(timeout=30)
    left = list(tmp_path.iterdir())
    assert len(left) == 1 and left[0].name.startswith(f".[copy] x.ply.{proc.pid}."), left
    assert remove_stale_temporaries(tmp_path / "[copy] x.ply") == []  # too recent: its owner might be alive
    t = time.time() - 120
    os.utime(left[0], (t, t))
    atomic_write_bytes(tmp_path / "[copy] x.ply", b"whole")
    assert [p.name for p in tmp_path.iterdir()] == ["[copy] x.ply"]


# ------------------------------------------------------------------------------ issue 37: render, videos, --poses
class _FakeVideoWriter:
    """Stands in for ``cv2.VideoWriter``: records each frame written into ``events``; writes nothing."""

    events: list[str] = []
    fps: list[float] = []

    def __init__(self, path: str, fourcc: int, fps: float, size: tuple[int, int]) -> None:
        self.fps.append(fps)

    @staticmethod
    def fourcc(*code: str) -> int:
        return 0

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return True

    def write(self, frame: object) -> None:
        self.events.append("write")

    def release(self) -> None:
        pass


@pytest.fixture
def fake_video(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """``cv2.VideoWriter`` faked (its read-back check off) and ``render_camera`` counted: the events in order."""
    import cv2

    import macsplat_cli.images as images
    import macsplat_cli.render as render

    events: list[str] = []
    monkeypatch.setattr(_FakeVideoWriter, "events", events)
    monkeypatch.setattr(_FakeVideoWriter, "fps", [])
    monkeypatch.setattr(cv2, "VideoWriter", _FakeVideoWriter)
    monkeypatch.setattr(images, "_check_video", lambda *a: None)
    real = render.render_camera

    def counted(*a: object, **k: object) -> object:
        events.append("render")
        return real(*a, **k)

    monkeypatch.setattr(render, "render_camera", counted)
    return events


@pytest.mark.parametrize("fps", ["inf", "nan", "0", "-1", "1e-6", "0.009", "241", "1000000", "1e308"])
def test_render_fps_outside_its_range_is_refused_before_any_work(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path], fake_video: list[str],
    fps: str,
) -> None:  # fmt: skip
    """Issue 37 R1: ``--fps inf`` made OpenCV's writer hang for good (SIGTERM ignored); every rate outside
    [0.01, 240] (1e-6 overflowed Pillow's GIF frame duration) is refused with exit 2 before a view is rendered or a
    writer opened, and nothing is written."""
    before = _snapshot(tmp_path)
    args = ["render", str(scene_files[0]), "--cameras", str(scene_files[1]), "--path", "3", "--fps", fps]
    got = main([*args, "--video", str(tmp_path / "v.mp4"), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and "--fps" in line, line
    assert fake_video == [] and _FakeVideoWriter.fps == []
    assert _snapshot(tmp_path) == before


def test_render_video_frames_are_encoded_as_they_are_rendered(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path], fake_video: list[str]
) -> None:
    """Issue 37 N1: ``render --path N --video`` hands each view to the encoder before rendering the next (no list of
    every frame); a fractional rate within [0.01, 240] is taken."""
    args = ["render", str(scene_files[0]), "--cameras", str(scene_files[1]), "--path", "4", "--fps", "0.5"]
    assert main([*args, "--video", str(tmp_path / "v.mp4"), "-q"]) == 0, capsys.readouterr().err
    assert fake_video == ["render", "write"] * 4 and _FakeVideoWriter.fps == [0.5]


def test_reconstruct_num_renders_is_capped_before_any_work(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, pair: tuple[Path, Path]
) -> None:
    """Issue 37 N1: ``--num-renders`` has the cap of ``render --path`` (MAX_PATH_VIEWS), checked before the first
    stage (it had none: 10⁸ views, every one kept in memory)."""
    import macsplat_cli.engine as engine

    def no_run(*a: object, **k: object) -> None:
        raise AssertionError("the reconstruction ran")

    monkeypatch.setattr(engine, "reconstruct", no_run)
    args = ["reconstruct", *map(str, pair), "-o", str(tmp_path / "s.ply"), "--video", str(tmp_path / "v.mp4")]
    got = main([*args, "--num-renders", "100000000", "-q"])
    err = capsys.readouterr().err
    assert got == 2 and "--num-renders" in err and "10000" in err, err
    assert list(tmp_path.iterdir()) == []


def test_reconstruct_writes_each_novel_view_as_it_is_rendered(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, pair: tuple[Path, Path],
    fake_video: list[str],
) -> None:  # fmt: skip
    """Issue 37 N1: ``reconstruct --renders --video`` writes each novel view (its file, its video frame) before
    rendering the next, as ``render --path`` does (it rendered them all into memory first)."""
    import macsplat_cli.images as images

    real = images.save_image

    def saved(*a: object, **k: object) -> object:
        fake_video.append("save")
        return real(*a, **k)

    monkeypatch.setattr(images, "save_image", saved)
    out = tmp_path / "out"
    args = ["reconstruct", *map(str, pair), "-o", str(out / "s.ply"), "--size", "128", "--accept-low-confidence"]
    got = main([*args, "--renders", str(out / "views"), "--video", str(out / "v.mp4"), "--num-renders", "3", "-q"])
    assert got == 0, capsys.readouterr().err
    assert fake_video[-9:] == ["render", "save", "write"] * 3
    assert sorted(p.name for p in (out / "views").iterdir()) == [f"view_{i:03d}.png" for i in range(3)]


_ENCODER_FAILS = """
import numpy as np
from macsplat_cli.errors import OutputPathError
from macsplat_cli.images import write_video
try:
    write_video({path!r}, [np.zeros((16, 9000, 3), np.uint8)])
except OutputPathError as e:
    print(e)
"""


def test_video_encoder_failure_prints_no_native_log(tmp_path: Path) -> None:
    """Issue 37 C1: a frame size MPEG-4 cannot encode is one typed error; OpenCV's and ffmpeg's own log lines
    (``[mpeg4 @ 0x...]``, ``[ERROR:0@...] global cap_ffmpeg_impl.hpp``) stay off stderr (a fresh process: ffmpeg
    reads its log level when first loaded)."""
    code = _ENCODER_FAILS.format(path=str(tmp_path / "v.mp4"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**env, "PYTHONPATH": str(REPO)})  # fmt: skip
    assert "could not open an MPEG-4 video writer" in proc.stdout, (proc.stdout, proc.stderr)
    assert proc.stderr.strip() == "", proc.stderr
    assert list(tmp_path.iterdir()) == []


def _poses_file(path: Path, names: list[str], translation_scale: float = 1.0) -> Path:
    """Two cameras named ``names`` (a 12° orbit at 128×96), positions times ``translation_scale``, written as JSON
    (``Camera`` itself refuses positions out of range)."""
    cams = syn.orbit_pair("room", 12.0, width=SIZE[0], height=SIZE[1], fov_deg=60.0)
    doc = CameraSet(list(cams)).to_dict()
    for d, n in zip(doc["cameras"], names):
        d["name"] = n
        for row in d["cam_to_world"][:3]:
            row[3] *= translation_scale
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize(
    ("names", "scale", "needle"),
    [
        (["IMG_001 [copy]", "other"], 1.0, "no camera named after '[bold]IMG_002.png'"),  # K1: a mixture
        (["IMG_001 [copy]", "[bold]IMG_002"], 1e160, "translation"),  # K2: finite, far out of range
    ],
    ids=["K1-mixture", "K2-1e160"],
)
def test_reconstruct_poses_that_do_not_fit_the_photos(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, pair: tuple[Path, Path], names: list[str], scale: float,
    needle: str,
) -> None:  # fmt: skip
    """Issue 37 K1: a camera file naming one photo's camera but not the other's is refused (it went by order: the
    unnamed photo took whatever camera came second). K2: positions of 1e160 are refused (LinAlgError, exit 1)."""
    poses = _poses_file(tmp_path / "poses.json", names, scale)
    out = tmp_path / "out"
    got = main(["reconstruct", *map(str, pair), "--poses", str(poses), "-o", str(out / "s.ply"), "--size", "128"])
    line = _one_error_line(capsys.readouterr().err)
    assert got == 2 and str(poses) in line and needle in line, line
    assert not out.exists()
