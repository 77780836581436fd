"""Hostile file-system input, second round (issue 23): where macsplat reads and writes.

* outputs: a symbolic link (even to a regular file), a device node or a FIFO at an output's name
  is refused before any work, never replaced or written through (``_atomic.check_writable``);
  ``eval``/``bench`` never write through a link planted in their output folder, not even at
  ``cases.jsonl``, which is rewritten after every case;
* write errors (``/sys``, ``/proc``, a full disk, a failed rename) are one line and exit 2, with
  no temporary file left, and an output ``os.access`` wrongly calls writable is found before work;
* data sets: a camera name (or a CO3D ``image``, an ICL frame, a ScanNet++ scene id) cannot name
  a file outside the data set, by an absolute path, ``..`` or a link; two cameras cannot share an
  image;
* many frames: a photo too small for the pipeline is found from the headers before the cases are
  made, and ``evaluate`` checks the context views before its first reconstruction.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli import _atomic
from macsplat_cli._atomic import atomic_path, atomic_write_bytes, check_writable
from macsplat_cli.cameras import CameraSet, save_cameras
from macsplat_cli.cli import main
from macsplat_cli.datasets import load_dataset
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import DatasetError, OutputPathError, ReconstructionError
from macsplat_cli.evaluation import evaluate, make_cases
from macsplat_cli.evaluation.bench import BenchSetting
from macsplat_cli.evaluation.reconstructors import BACKENDS
from macsplat_cli.evaluation.result_files import ResultWriter
from macsplat_cli.evaluation.results import CaseResult, EvalConfig, EvalRun
from macsplat_cli.evaluation.splits import EvalCase, SplitConfig, between_targets
from macsplat_cli.images import save_image, write_video
from macsplat_cli.pipeline.run import Pipeline
from macsplat_cli.ply import write_ply

from support.cli import file_size_limit
from support.gaussians import random_gaussians

IS_ROOT = os.geteuid() == 0


# ------------------------------------------------------------------------------ helpers
def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and "internal error" not in err, err
    assert sum("error:" in ln for ln in lines) == 1 and lines[-1].startswith("error: "), err
    return lines[-1]


def _snapshot(folder: Path) -> dict[str, object]:
    """Every entry under ``folder``: a file's bytes, a link's target, else its file type."""
    out: dict[str, object] = {}
    for p in sorted(folder.rglob("*")):
        st = p.lstat()
        if stat.S_ISLNK(st.st_mode):
            out[str(p.relative_to(folder))] = ("link", os.readlink(p))
        elif stat.S_ISREG(st.st_mode):
            out[str(p.relative_to(folder))] = p.read_bytes()
        else:
            out[str(p.relative_to(folder))] = stat.S_IFMT(st.st_mode)
    return out


def _special(kind: str, path: Path, target: Path | None = None) -> Path:
    """A link, FIFO or character device (``/dev/null``'s numbers; root only) at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == "link":
        assert target is not None
        path.symlink_to(target)
    elif kind == "dangling-link":
        path.symlink_to(path.parent / "nowhere" / "x")
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        if not IS_ROOT:
            pytest.skip("mknod needs root")
        os.mknod(path, 0o644 | stat.S_IFCHR, os.makedev(1, 3))
    else:  # pragma: no cover
        raise AssertionError(kind)
    return path


class StubReconstructor:
    """Counts its calls and fails every case (eval goes on; the files are what the tests look at)."""

    name = "stub"

    def __init__(self) -> None:
        self.calls: list[str] = []

    def __call__(self, scene, case, settings):  # noqa: ANN001, ANN204
        self.calls.append(case.key)
        raise ReconstructionError("stub: not reconstructed")


@pytest.fixture
def stub(monkeypatch: pytest.MonkeyPatch) -> StubReconstructor:
    rec = StubReconstructor()
    monkeypatch.setitem(BACKENDS, "stub", lambda config, models=None: rec)
    return rec


def write_frames(root: Path, sizes: list[tuple[int, int]], names: list[str] | None = None) -> Path:
    """A generic data set of cameras on an arc (5° apart) with flat grey photos of the given sizes, fast (no ray
    tracing); the camera of each frame has its photo's size."""
    names = names or [f"f{i}" for i in range(len(sizes))]
    cams = []
    for i, (name, (w, h)) in enumerate(zip(names, sizes)):
        cam = syn.orbit_cameras("room", [5.0 * i], width=w, height=h, names=[name])[0]
        cams.append(cam)
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(cams):
        save_image(root / "images" / f"{cam.name}.png", np.full((cam.height, cam.width, 3), 40 + i % 200, np.uint8))
    save_cameras(root / "cameras.json", CameraSet(cams, world="world"))
    return root


@pytest.fixture(scope="module")
def small_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_frames(tmp_path_factory.mktemp("hostile_paths") / "D", [(96, 72)] * 4)


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("hostile_paths_scene")
    write_ply(folder / "scene.ply", random_gaussians(200, seed=3))
    cams = syn.orbit_pair("room", 12.0, width=64, height=48, fov_deg=60.0)
    save_cameras(folder / "cams.json", CameraSet(list(cams)))
    return folder / "scene.ply", folder / "cams.json"


# ------------------------------------------------------------------------------ 1: eval/bench output folders
def test_eval_does_not_write_through_a_link_at_cases_jsonl(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, small_set: Path, stub: StubReconstructor
) -> None:
    """``ln -s victim res/cases.jsonl; macsplat eval --out res``: exit 2 before any case, the victim as it was."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    res = tmp_path / "res"
    _special("link", res / "cases.jsonl", victim)
    before = _snapshot(tmp_path)
    code = main(["eval", "--data", str(small_set), "--backend", "stub", "--out", str(res), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "cases.jsonl" in line and "symbolic link" in line, line
    assert victim.read_text() == "precious\n" and stub.calls == []
    assert _snapshot(tmp_path) == before


def test_result_writer_refuses_a_link_planted_between_cases(tmp_path: Path) -> None:
    """The file appended after every case: a link put at its name during the run is not written through."""
    case = EvalCase("s", "close", (0, 1), (2,))
    run = EvalRun("d", "generic", "stub", EvalConfig(), [case, case])
    writer = ResultWriter(tmp_path / "res")
    writer.start(run)
    run.results.append(CaseResult(case, "stub", status="failed", error="x"))
    writer.add(run, run.results[-1])
    assert len(writer.jsonl.read_text().splitlines()) == 1
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    writer.jsonl.unlink()
    writer.jsonl.symlink_to(victim)
    run.results.append(CaseResult(case, "stub", status="failed", error="y"))
    with pytest.raises(OutputPathError, match="cases.jsonl: it is a symbolic link"):
        writer.add(run, run.results[-1])
    assert victim.read_text() == "precious\n" and writer.jsonl.is_symlink()


def test_cases_jsonl_is_whole_after_every_case(tmp_path: Path) -> None:
    """Rewritten atomically: one line per finished case, each a complete JSON document."""
    case = EvalCase("s", "close", (0, 1), (2,))
    run = EvalRun("d", "generic", "stub", EvalConfig(), [case] * 3)
    writer = ResultWriter(tmp_path / "res")
    writer.start(run)
    assert writer.jsonl.read_text() == ""
    for k in range(3):
        run.results.append(CaseResult(case, "stub", status="failed", error=f"e{k}"))
        writer.add(run, run.results[-1])
        lines = writer.jsonl.read_text().splitlines()
        assert [json.loads(ln)["error"] for ln in lines] == [f"e{i}" for i in range(k + 1)]
    assert [p.name for p in (tmp_path / "res").iterdir() if p.name.startswith(".")] == []


def test_eval_does_not_write_coverage_through_a_linked_folder(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, stub: StubReconstructor
) -> None:
    """``res/coverage -> elsewhere/``: the coverage files would land outside --out; refused before any work."""
    data = tmp_path / "P"
    syn.write_dataset(data, syn.make_scene("room", 1), syn.orbit_cameras("room", [0, 4, 8], width=64, height=64))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    _special("link", tmp_path / "res" / "coverage", elsewhere)
    code = main(["eval", "--data", str(data), "--backend", "stub", "--out", str(tmp_path / "res"), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "coverage" in line and "symbolic link" in line, line
    assert list(elsewhere.iterdir()) == [] and stub.calls == []


def test_bench_does_not_write_through_a_link_in_a_setting_folder(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, small_set: Path, stub: StubReconstructor
) -> None:
    """``bench --out B`` with ``B/runs/<setting>/cases.jsonl -> victim``: exit 2 before any work."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    slug = BenchSetting("stub", 96).slug
    _special("link", tmp_path / "B" / "runs" / slug / "cases.jsonl", victim)
    before = _snapshot(tmp_path)
    code = main(["bench", "--data", str(small_set), "--backend", "stub", "--size", "96", "--out", str(tmp_path / "B"),
                 "-q"])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "cases.jsonl" in line and "symbolic link" in line, line
    assert victim.read_text() == "precious\n" and stub.calls == []
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------------------ 2: outputs that are not regular files
@pytest.mark.parametrize("kind", ["link", "dangling-link", "fifo", "device"])
def test_an_existing_output_that_is_not_a_regular_file_is_refused(tmp_path: Path, kind: str) -> None:
    """A link (even to a regular file), a FIFO or a device at the output's name: refused, left as it was."""
    target = tmp_path / "target.json"
    target.write_text("target\n")
    out = _special(kind, tmp_path / "out" / "report.json", target)
    before = _snapshot(tmp_path)
    with pytest.raises(OutputPathError, match=r"report\.json: (it is a symbolic link|it exists and is not a regular)"):
        check_writable(out)
    with pytest.raises(OutputPathError):
        atomic_write_bytes(out, b"{}")
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_reconstruct_refuses_a_special_report_before_any_work(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, kind: str
) -> None:
    """``mknod fake c 1 3; macsplat reconstruct L R -o s.ply --report fake``: exit 2, the node untouched."""
    calls: list[object] = []
    monkeypatch.setattr(Pipeline, "run", lambda self, *a, **k: calls.append(a))
    for name in ("a.png", "b.png"):
        save_image(tmp_path / name, np.zeros((64, 64, 3), np.uint8))
    fake = _special(kind, tmp_path / "fake")
    before = _snapshot(tmp_path)
    code = main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(tmp_path / "s.ply"),
                 "--report", str(fake), "-q"])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "not a regular file" in line, line
    assert calls == [] and _snapshot(tmp_path) == before


def test_reconstruct_refuses_a_report_linked_to_dev_stdout(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``--report`` naming a link such as ``/dev/stdout``: the link is not replaced by a file."""
    calls: list[object] = []
    monkeypatch.setattr(Pipeline, "run", lambda self, *a, **k: calls.append(a))
    for name in ("a.png", "b.png"):
        save_image(tmp_path / name, np.zeros((64, 64, 3), np.uint8))
    link = _special("link", tmp_path / "stdout", Path("/dev/stdout"))
    code = main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(tmp_path / "s.ply"),
                 "--report", str(link), "-q"])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "symbolic link" in line, line
    assert calls == [] and link.is_symlink() and os.readlink(link) == "/dev/stdout"
    assert not (tmp_path / "s.ply").exists()


@pytest.mark.parametrize("which", ["image", "depth", "video", "frame"])
def test_render_refuses_special_outputs_before_rendering(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path], which: str
) -> None:
    """``render``: a FIFO (or a link) at -o, --depth, --video or a frame of -o DIR: exit 2, nothing written."""
    scene, cams = scene_files
    args = ["render", str(scene), "--pose", str(cams), "-q"]
    if which == "image":
        args += ["-o", str(_special("fifo", tmp_path / "v.png"))]
    elif which == "depth":
        args += ["-o", str(tmp_path / "v.png"), "--depth", str(_special("fifo", tmp_path / "d.npy"))]
    elif which == "video":
        args += ["--path", "3", "-o", str(tmp_path / "frames"), "--video", str(_special("fifo", tmp_path / "v.gif"))]
    else:
        args += ["--path", "3", "-o", str(tmp_path / "frames")]
        _special("link", tmp_path / "frames" / "frame_0001.png", tmp_path / "elsewhere.png")
    before = _snapshot(tmp_path)
    code = main(args)
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and ("not a regular file" in line or "symbolic link" in line), line
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("which", ["graph", "parity", "data"])
def test_export_onnx_refuses_a_special_output_before_loading(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, which: str
) -> None:
    """``export-onnx -o`` a FIFO, or a FIFO where its parity report or weights file goes: exit 2 before the
    checkpoints load."""
    import macsplat_cli.neural.loading as loading

    loads: list[object] = []

    def load(**files: object) -> None:
        loads.append(files)
        raise RuntimeError("loaded")

    monkeypatch.setattr(loading, "load_pair_predictor", load)
    (tmp_path / "mast3r.pth").write_bytes(b"checkpoint")
    graph = tmp_path / "predictor.onnx"
    name = {"graph": graph.name, "parity": "predictor.parity.json", "data": "predictor.onnx.data"}[which]
    special = _special("fifo", tmp_path / name)
    code = main(["export-onnx", "-o", str(graph), "--weights", str(tmp_path / "mast3r.pth"), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "not a regular file" in line and name in line, line
    assert loads == [] and stat.S_ISFIFO(special.lstat().st_mode)


# ------------------------------------------------------------------------------ 3: write errors
def test_an_output_under_sys_is_one_line_before_any_work(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path]
) -> None:
    """``render --path 3 -o frames/ --video /sys/x.gif``: exit 2 naming the video, no frame written (root: os.access
    says /sys is writable; the probe finds it is not)."""
    scene, cams = scene_files
    code = main(["render", str(scene), "--cameras", str(cams), "--path", "3", "-o", str(tmp_path / "frames"),
                 "--video", "/sys/x.gif", "-q"])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "cannot write /sys/x.gif" in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("target", ["/proc/x.png", "/sys/x.png", "/sys/frames/v.png"])
def test_check_writable_probes_what_os_access_cannot_judge(target: str) -> None:
    with pytest.raises(OutputPathError, match=f"cannot write {target}"):
        check_writable(target)


def test_render_depth_under_proc_writes_no_image(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, scene_files: tuple[Path, Path]
) -> None:
    """``-o v.png --depth /proc/x.npy``: refused before the view is rendered, so no v.png is left."""
    scene, cams = scene_files
    code = main(["render", str(scene), "--cameras", str(cams), "-o", str(tmp_path / "v.png"), "--depth", "/proc/x.npy",
                 "-q"])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "cannot write /proc/x.npy" in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("where", ["body", "replace", "mkstemp"])
def test_oserrors_of_a_write_become_one_output_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, where: str
) -> None:
    """ENOSPC in the body, EROFS from the rename, EACCES from mkstemp: OutputPathError, no temporary file left."""
    out = tmp_path / "scene.ply"
    out.write_bytes(b"old")

    def fail(*args: object, **kwargs: object) -> None:
        raise {"replace": OSError(errno.EROFS, "Read-only"), "mkstemp": PermissionError(errno.EACCES, "denied")}[where]

    if where != "body":
        monkeypatch.setattr(_atomic.os if where == "replace" else _atomic.tempfile, where, fail)
    with pytest.raises(OutputPathError, match=r"cannot write .*scene\.ply: (No space|Read-only|denied)"):
        with atomic_path(out) as tmp:
            tmp.write_bytes(b"half")
            if where == "body":
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"] and out.read_bytes() == b"old"


@pytest.fixture
def full_disk(tmp_path: Path):  # noqa: ANN201
    """A 64 KiB tmpfs, filled up but for a few blocks (skipped where mounting is not permitted)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if not IS_ROOT or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                                     capture_output=True).returncode != 0:  # fmt: skip
        pytest.skip("cannot mount a tmpfs here")
    try:
        with open(mnt / "filler", "wb") as f:
            try:
                f.write(b"\0" * (56 * 1024))
            except OSError:
                pass
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def test_render_on_a_full_disk_is_one_line_and_leaves_nothing(
    capsys: pytest.CaptureFixture[str], full_disk: Path, scene_files: tuple[Path, Path]
) -> None:
    scene, cams = scene_files
    before = sorted(p.name for p in full_disk.iterdir())
    code = main(["render", str(scene), "--cameras", str(cams), "--width", "320", "--height", "240", "-o",
                 str(full_disk / "v.tif"), "-q"])  # fmt: skip
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "cannot write" in line and "No space left on device" in line, line
    assert sorted(p.name for p in full_disk.iterdir()) == before


def test_an_mp4_cut_short_by_a_full_disk_is_an_output_error(full_disk: Path) -> None:
    """OpenCV's video writer ignores write errors: the truncated file (no index) must not be renamed into place."""
    rng = np.random.default_rng(0)
    frames = [(rng.random((128, 160, 3)) * 255).astype(np.uint8) for _ in range(20)]  # noise: ~100 KB of MPEG-4
    before = sorted(p.name for p in full_disk.iterdir())
    with pytest.raises(OutputPathError, match=r"cannot write .*v\.mp4: the video came out unreadable"):
        write_video(full_disk / "v.mp4", frames)
    assert sorted(p.name for p in full_disk.iterdir()) == before


@pytest.mark.parametrize("writer", ["save_fusion", "atomic_torch_save"])
def test_a_torch_save_cut_short_is_an_output_error(tmp_path: Path, writer: str) -> None:
    """torch reports a failed write as RuntimeError ("unexpected pos"): the library's checkpoint writers turn it
    into OutputPathError and leave the previous file as it was (a file-size limit stands in for a full disk)."""
    import torch

    from macsplat_cli.neural.fusion import FusionConfig, ResidualSemanticFusion, save_fusion

    out = tmp_path / "w.pth"
    out.write_bytes(b"previous")
    module = ResidualSemanticFusion(FusionConfig())
    if writer == "save_fusion":
        write = lambda: save_fusion(module, out)  # noqa: E731
    else:
        from macsplat_cli._atomic import atomic_torch_save

        write = lambda: atomic_torch_save(out, {"state_dict": module.state_dict(), "x": torch.zeros(10_000)})  # noqa: E731
    with file_size_limit(4096), pytest.raises(OutputPathError, match=r"cannot write .*w\.pth"):
        write()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.pth"] and out.read_bytes() == b"previous"


# ------------------------------------------------------------------------------ 4: reads outside the data set
@pytest.mark.parametrize("how", ["absolute", "dotdot", "separator", "link-out"])
def test_a_camera_name_cannot_reach_outside_the_data_set(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, stub: StubReconstructor, how: str
) -> None:
    """``"name": "/etc/passwd"`` (or ``../x``, ``sub/x``, a link out of images/): exit 2 naming the camera."""
    root = write_frames(tmp_path / "D", [(96, 72)] * 3)
    outside = tmp_path / "outside.png"
    save_image(outside, np.full((72, 96, 3), 200, np.uint8))  # a valid photo of the right size
    doc = json.loads((root / "cameras.json").read_text())
    (root / "images" / "f0.png").unlink()
    name = {"absolute": str(outside), "dotdot": "../../outside.png", "separator": "sub/f0.png", "link-out": "f0"}[how]
    if how == "separator":
        save_image(root / "images" / "sub" / "f0.png", np.zeros((72, 96, 3), np.uint8))
    if how == "link-out":
        (root / "images" / "f0.png").symlink_to(outside)
    doc["cameras"][0]["name"] = name
    (root / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match="outside the data set" if how == "link-out" else "camera"):
        load_dataset(root)
    code = main(["eval", "--data", str(root), "--backend", "stub", "--out", str(tmp_path / "res"), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and name.split("/")[-1] in line, line
    assert stub.calls == [] and not (tmp_path / "res").exists()


def test_two_cameras_cannot_share_an_image(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, stub: StubReconstructor
) -> None:
    """``f0`` and ``f0.png`` both find ``images/f0.png``: exit 2 naming both."""
    root = write_frames(tmp_path / "D", [(96, 72)] * 3, names=["f0", "f1", "f0.png"])
    (root / "images" / "f0.png.png").unlink()
    code = main(["eval", "--data", str(root), "--backend", "stub", "--out", str(tmp_path / "res"), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "'f0'" in line and "'f0.png'" in line and "same image" in line, line
    assert stub.calls == []


@pytest.mark.parametrize("image", ["/abs", "../outside.png", "images/../../outside.png"])
def test_co3d_images_stay_inside_the_folder(tmp_path: Path, image: str) -> None:
    root = tmp_path / "co3d"
    (root / "images").mkdir(parents=True)
    outside = tmp_path / "outside.png"
    save_image(outside, np.zeros((72, 96, 3), np.uint8))
    views = []
    for i in range(3):
        save_image(root / "images" / f"{i}.png", np.zeros((72, 96, 3), np.uint8))
        cam = syn.orbit_cameras("room", [5.0 * i], width=96, height=72)[0]
        views.append({"image": f"images/{i}.png", "K": cam.K.tolist(), "c2w": cam.cam_to_world.tolist()})
    views[0]["image"] = str(outside) if image == "/abs" else image
    (root / "cameras_opencv.json").write_text(json.dumps({"width": 96, "height": 72, "views": views}))
    with pytest.raises(DatasetError, match=r"views\[0\]\.image"):
        load_dataset(root)


def test_icl_frames_do_not_link_out(tmp_path: Path) -> None:
    root = tmp_path / "icl"
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    outside = tmp_path / "outside.png"
    save_image(outside, np.zeros((480, 640, 3), np.uint8))
    for i in range(1, 4):
        if i == 2:
            (root / "color" / "2.png").symlink_to(outside)
        else:
            save_image(root / "color" / f"{i}.png", np.zeros((480, 640, 3), np.uint8))
        save_image(root / "depth" / f"{i}.png", np.zeros((480, 640, 3), np.uint8))
    (root / "pose.txt").write_text("\n".join(f"{0.1 * i} 0 0 0 0 0 1" for i in range(1, 4)) + "\n")
    with pytest.raises(DatasetError, match=r"color/2\.png: frame 2 leads to .*outside the data set"):
        load_dataset(root, "icl-nuim")


def test_scannetpp_scene_ids_are_plain_names(tmp_path: Path) -> None:
    """A split file line ``../../elsewhere`` would load a scene from outside the tree."""
    from macsplat_cli.datasets.scannetpp import scannetpp_scene_ids

    (tmp_path / "splits").mkdir()
    (tmp_path / "data").mkdir()
    (tmp_path / "splits" / "nvs_sem_val.txt").write_text("abc\n../../elsewhere\n")
    with pytest.raises(DatasetError, match=r"nvs_sem_val\.txt: scene '\.\./\.\./elsewhere' has a '\.\.' component"):
        scannetpp_scene_ids(tmp_path, "nvs_sem_val")
    with pytest.raises(DatasetError, match=r"--scenes: scene '/etc' is an absolute path"):
        scannetpp_scene_ids(tmp_path, "nvs_sem_val", ["/etc"])


# ------------------------------------------------------------------------------ 5: many frames
def test_many_frames_with_a_last_photo_too_small_fail_before_any_case(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, stub: StubReconstructor
) -> None:
    """200 frames, the last 48x40 (its camera too): exit 2 naming it, before the cases are made or reconstructed."""
    import macsplat_cli.evaluation as evaluation

    root = write_frames(tmp_path / "many", [(96, 72)] * 199 + [(48, 40)])
    made: list[object] = []
    real_make_cases = evaluation.make_cases
    monkeypatch.setattr(evaluation, "make_cases", lambda *a, **k: made.append(a) or real_make_cases(*a, **k))
    code = main(["eval", "--data", str(root), "--backend", "stub", "--out", str(tmp_path / "res"), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "f199.png: 48x40 px is too small" in line, line
    assert made == [] and stub.calls == []
    assert not (tmp_path / "res").exists()


def test_evaluate_checks_every_context_view_before_the_first_case(tmp_path: Path, stub: StubReconstructor) -> None:
    """The library entry point too: a small context view in the last case stops the run before the first."""
    root = write_frames(tmp_path / "D", [(96, 72)] * 5 + [(48, 40)])
    ds = load_dataset(root)
    name = ds.scenes[0].name
    cases = [EvalCase(name, "close", (0, 1), (2,)), EvalCase(name, "close", (4, 5), (3,))]
    with pytest.raises(DatasetError, match=r"f5\.png: 48x40 px is too small for a context view \(case .*4-5\)"):
        evaluate(ds, cases, stub)
    assert stub.calls == []


def test_photo_above_the_megapixel_cap_is_found_at_load(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The header says the photo is above MACSPLAT_MAX_MEGAPIXELS: refused when the data set loads."""
    root = write_frames(tmp_path / "D", [(96, 72)] * 2 + [(400, 300)])
    monkeypatch.setenv("MACSPLAT_MAX_MEGAPIXELS", "0.1")
    with pytest.raises(DatasetError, match=r"f2\.png: 400x300 is 0\.1 megapixels, above the limit of 0\.1"):
        load_dataset(root)


def _between_reference(cams, pair, slack):  # noqa: ANN001, ANN202
    """The per-frame loop :func:`between_targets` replaced (rotation angles via metrics.rotation_error_deg)."""
    from macsplat_cli.metrics import rotation_error_deg

    a, b = cams[pair[0]], cams[pair[1]]
    chord = b.center - a.center
    length = float(np.linalg.norm(chord))
    span = rotation_error_deg(a.cam_to_world[:3, :3], b.cam_to_world[:3, :3])
    out = []
    for i, f in enumerate(cams):
        if i in pair:
            continue
        d = f.center - a.center
        u = float(d @ chord) / length**2
        perp = float(np.linalg.norm(d - u * chord))
        ra = rotation_error_deg(a.cam_to_world[:3, :3], f.cam_to_world[:3, :3])
        rb = rotation_error_deg(b.cam_to_world[:3, :3], f.cam_to_world[:3, :3])
        if 0.05 < u < 0.95 and perp < 0.5 * length and max(ra, rb) <= span + slack:
            out.append(i)
    return out


def test_vectorised_pair_enumeration_matches_the_per_frame_loop() -> None:
    rng = np.random.default_rng(4)
    cams = syn.orbit_cameras("room", list(np.sort(rng.uniform(0, 120, 30))), width=64, height=48)
    for a in range(0, 30, 3):
        for b in range(a + 1, 30, 4):
            assert between_targets(cams, (a, b), 15.0) == _between_reference(cams, (a, b), 15.0)


def test_many_frames_make_cases_by_angle_quickly(tmp_path: Path) -> None:
    """200 frames by angle: the cases come from O(N²) vectorised pair checks (it took minutes before)."""
    ds = load_dataset(write_frames(tmp_path / "many", [(64, 64)] * 200))
    sel = make_cases(ds, SplitConfig(mode="angle", max_pairs=2, max_targets=2))
    assert sel.cases and all(len(c.targets) <= 2 for c in sel.cases)


def test_eval_refuses_a_cases_file_among_its_outputs(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, small_set: Path, stub: StubReconstructor
) -> None:
    """``--cases res/results.json --out res``: the cases file would be overwritten by the first case's results."""
    res = tmp_path / "res"
    res.mkdir()
    cases = res / "results.json"
    cases.write_text(json.dumps({"cases": [{"split": "close", "context": [0, 1], "targets": [2]}]}))
    code = main(["eval", "--data", str(small_set), "--backend", "stub", "--cases", str(cases), "--out", str(res), "-q"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2 and "refusing to overwrite an input" in line and "--cases" in line, line
    assert stub.calls == [] and json.loads(cases.read_text())["cases"][0]["targets"] == [2]


def test_a_linked_images_folder_out_of_the_data_set_is_refused(tmp_path: Path) -> None:
    """``images -> /elsewhere``: the photos are not in the folder the user named."""
    root = write_frames(tmp_path / "D", [(96, 72)] * 3)
    (root / "images").rename(tmp_path / "elsewhere")
    (root / "images").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(DatasetError, match=r"images/f0\.png: frame 'f0' leads to .*elsewhere.*outside the data set"):
        load_dataset(root)


def test_links_inside_the_data_set_are_followed(tmp_path: Path) -> None:
    """Not every link is hostile: ``images/f0.png -> ../store/f0.png`` inside the folder, or ``--data`` itself a
    link, load as before."""
    root = write_frames(tmp_path / "D", [(96, 72)] * 3)
    (root / "store").mkdir()
    (root / "images" / "f0.png").rename(root / "store" / "f0.png")
    (root / "images" / "f0.png").symlink_to(Path("..") / "store" / "f0.png")
    (tmp_path / "link").symlink_to(root)
    for where in (root, tmp_path / "link"):
        ds = load_dataset(where)
        assert [f.name for f in ds.scenes[0].frames] == ["f0", "f1", "f2"]
