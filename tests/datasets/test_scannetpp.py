"""ScanNet++ loader on synthetic ScanNet++-layout trees (undistorted DSLR, fisheye DSLR, iPhone)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import load_dataset
from macsplat_cli.datasets.scannetpp import CACHE_FOLDER, load_scannetpp, pinhole_K, undistort
from macsplat_cli.datasets.synthetic import make_scene, render, write_scannetpp
from macsplat_cli.datasets.synthetic.scannetpp import fisheye_lens, scannetpp_cameras
from macsplat_cli.errors import DatasetError

from support.numerics import ROT_ROUND_TRIP, gamma

SIZE = (96, 64)


@pytest.fixture(scope="module")
def trees(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("scannetpp")
    return {
        "undistorted": write_scannetpp(
            base / "und", scenes=("room",), layout="undistorted", size=SIZE, bad_frames=(1,)
        ),
        "fisheye": write_scannetpp(
            base / "fish", scenes=("room", "object"), layout="fisheye", size=SIZE, bad_frames=(1,)
        ),
        "iphone": write_scannetpp(base / "iph", scenes=("room",), layout="iphone", size=SIZE, splits=False),
    }


def _copy(tree: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(tree, tmp_path / "copy"))


def _check_poses(scene, layout: str) -> None:  # noqa: ANN001
    """The files hold repr()s (exact); a COLMAP layout stores R as a quaternion: an R → q → R round trip
    (ROT_ROUND_TRIP per entry, +16u for the truth's own orthogonality) and c = −Rᵀt from t = −Rc (that error times |c|
    twice, plus 2γ₃|c|); K is rescaled to the working size (2 roundings a side)."""
    u = np.finfo(np.float64).eps / 2
    truth = {Path(c.name).stem: c for c in scannetpp_cameras(scene.name, size=SIZE, layout=layout)}
    for f in scene.frames:
        true = truth[f.name]
        c = float(np.abs(true.center).sum())
        rot = (ROT_ROUND_TRIP + 16) * u
        pose_tol = rot * (1 + 2 * c) + 2 * gamma(3, np.float64) * c
        assert np.abs(f.camera.cam_to_world - true.cam_to_world).max() <= pose_tol
        assert np.abs(f.camera.K - true.K).max() <= 4 * u * np.abs(true.K).max()
        assert (f.camera.width, f.camera.height) == SIZE


def _interior(a: np.ndarray, b: int = 4) -> np.ndarray:
    return a[b:-b, b:-b]


def test_undistorted_layout_loads_with_exact_poses(trees: dict[str, Path]) -> None:
    ds = load_dataset(trees["undistorted"], scannetpp_split="nvs_sem_val")
    assert ds.layout == "scannetpp" and [s.name for s in ds.scenes] == ["room"]
    scene = ds.scenes[0]
    # train list = frames 0..4 (5 is the test frame), frame 1 is_bad
    assert [f.name for f in scene.frames] == ["DSC00000", "DSC00002", "DSC00003", "DSC00004"]
    assert scene.scale == "metric" and scene.has_depth
    _check_poses(scene, "undistorted")
    assert scene.frames[0].image.parent.name == "resized_undistorted_images"
    view = render(make_scene("room", 0), scene.frames[1].camera)
    assert np.median(np.abs(_interior(scene.depth(1) - view.depth))) < 1e-3  # (d) uint16 mm: ≤ 0.5 mm rounding


def test_fisheye_layout_is_undistorted_once_into_a_cache(trees: dict[str, Path], tmp_path: Path) -> None:
    root = _copy(trees["fisheye"], tmp_path)
    scene = load_scannetpp(root, "nvs_sem_train", None)[0]
    assert scene.name == "room"
    assert [f.name for f in scene.frames] == ["DSC00000", "DSC00002", "DSC00003", "DSC00004"]
    _check_poses(scene, "fisheye")
    cache = root / "data" / "room" / "dslr" / CACHE_FOLDER
    assert all(f.image.parent == cache / "images" for f in scene.frames)
    assert all(f.depth is not None and f.depth.parent == cache / "depth" for f in scene.frames)
    K = pinhole_K(fisheye_lens(SIZE))
    assert K[0, 2] == SIZE[0] / 2 and K[1, 2] == SIZE[1] / 2  # the toolkit's recipe: centred principal point

    # the undistorted image matches a direct pinhole render of the same camera
    world = make_scene("room", 0)
    for i in (0, 2):
        cam = scene.frames[i].camera
        view = render(world, cam)
        img = scene.rgb(i)
        assert np.median(np.abs(_interior(img - view.image))) < 0.05
        blur = lambda a: cv2.GaussianBlur(a, (0, 0), 1.0)  # noqa: E731 - damp JPEG noise
        err = np.median(np.abs(_interior(blur(img) - blur(view.image))))
        Ks = cam.K.copy()
        Ks[0, 2] += 1.0  # one pixel off: clearly worse
        off = render(world, Camera("s", cam.width, cam.height, Ks, cam.cam_to_world))
        assert err < 0.85 * np.median(np.abs(_interior(blur(img) - blur(off.image))))
        assert np.median(np.abs(_interior(scene.depth(i) - view.depth))) < 0.05

    # second load: no file is rewritten
    files = sorted(p for p in cache.rglob("*") if p.is_file())
    stamps = [p.stat().st_mtime_ns for p in files]
    again = load_scannetpp(root, "nvs_sem_train", None)[0]
    assert [f.image for f in again.frames] == [f.image for f in scene.frames]
    assert sorted(p for p in cache.rglob("*") if p.is_file()) == files
    assert [p.stat().st_mtime_ns for p in files] == stamps
    # a newer source image is undistorted again
    src = root / "data" / "room" / "dslr" / "resized_images" / "DSC00000.JPG"
    src.touch()
    load_scannetpp(root, "nvs_sem_train", None)
    assert (cache / "images" / "DSC00000.JPG").stat().st_mtime_ns >= src.stat().st_mtime_ns


def test_fisheye_cache_falls_back_to_the_user_cache(
    trees: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = _copy(trees["fisheye"], tmp_path)
    monkeypatch.setattr(undistort, "_writable", lambda folder: False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    scene = load_scannetpp(root, "nvs_sem_val", None)[0]
    assert scene.name == "object"
    assert all((tmp_path / "xdg" / "macsplat" / "scannetpp") in f.image.parents for f in scene.frames)
    assert not (root / "data" / "object" / "dslr" / CACHE_FOLDER).exists()


def test_colmap_is_the_pose_source_without_nerfstudio(trees: dict[str, Path], tmp_path: Path) -> None:
    root = _copy(trees["fisheye"], tmp_path)
    (root / "data" / "room" / "dslr" / "nerfstudio" / "transforms.json").unlink()
    scene = load_scannetpp(root, "nvs_sem_train", None)[0]
    # COLMAP has no is_bad flag: every train frame
    assert [f.name for f in scene.frames] == [f"DSC{i:05d}" for i in range(5)]
    _check_poses(scene, "fisheye")


def test_iphone_layout(trees: dict[str, Path]) -> None:
    ds = load_dataset(trees["iphone"], "scannetpp")  # no splits/: every scene folder
    scene = ds.scene("room")
    assert [f.name for f in scene.frames] == [f"frame_{i:06d}" for i in range(6)]
    _check_poses(scene, "iphone")
    # the half-size LiDAR-like depth is resized (nearest) to the image into the cache
    d = scene.depth(2)
    assert d.shape == (SIZE[1], SIZE[0])
    view = render(make_scene("room", 0), scene.frames[2].camera)
    assert np.median(np.abs(_interior(d - view.depth))) < 0.05
    assert scene.frames[2].depth is not None and CACHE_FOLDER in scene.frames[2].depth.parts


def test_split_lists_and_scene_names(trees: dict[str, Path], tmp_path: Path) -> None:
    root = trees["fisheye"]
    assert [s.name for s in load_scannetpp(root, "nvs_sem_train", None)] == ["room"]
    assert [s.name for s in load_scannetpp(root, "nvs_sem_val", None)] == ["object"]
    assert [s.name for s in load_scannetpp(root, "nvs_sem_val", ["room", "object"])] == ["room", "object"]
    with pytest.raises(DatasetError, match=r"nvs_test\.txt: split file not found"):
        load_scannetpp(root, "nvs_test", None)
    bare = write_scannetpp(tmp_path / "bare", scenes=("object", "room"), frames=3, layout="iphone", splits=False)
    assert [s.name for s in load_scannetpp(bare, "nvs_sem_train", None)] == ["object", "room"]
    assert [s.name for s in load_scannetpp(bare, "nvs_sem_train", ["room"])] == ["room"]


def test_bad_input_names_the_file(trees: dict[str, Path], tmp_path: Path) -> None:
    root = _copy(trees["fisheye"], tmp_path)
    dslr = root / "data" / "room" / "dslr"
    ts = dslr / "nerfstudio" / "transforms.json"
    ts.write_text("{ not json", encoding="utf-8")
    with pytest.raises(DatasetError, match=r"transforms\.json: invalid JSON at line 1"):
        load_scannetpp(root, "nvs_sem_train", None)
    ts.write_text("[" * 200_000 + "]" * 200_000, encoding="utf-8")  # hostile nesting: a clear error, no RecursionError
    with pytest.raises(DatasetError, match=r"transforms\.json: .*nest"):
        load_scannetpp(root, "nvs_sem_train", None)
    ts.unlink()
    shutil.rmtree(dslr / "colmap")
    with pytest.raises(DatasetError, match=r"transforms\.json: file not found"):
        load_scannetpp(root, "nvs_sem_train", None)

    root = write_scannetpp(tmp_path / "b", scenes=("object",), frames=4, layout="fisheye", size=(48, 32))
    (root / "data" / "object" / "dslr" / "resized_images" / "DSC00002.JPG").unlink()
    with pytest.raises(DatasetError, match=r"resized_images/DSC00002\.JPG: image not found"):
        load_scannetpp(root, "nvs_sem_val", None)

    und = _copy(trees["undistorted"], tmp_path / "u")
    (und / "data" / "room" / "dslr" / "resized_undistorted_images" / "DSC00003.JPG").unlink()
    with pytest.raises(DatasetError, match=r"DSC00003\.JPG: image not found"):
        load_scannetpp(und, "nvs_sem_val", None)
    tu = und / "data" / "room" / "dslr" / "nerfstudio" / "transforms_undistorted.json"
    doc = json.loads(tu.read_text(encoding="utf-8"))
    del doc["fl_x"]
    tu.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(DatasetError, match=r"transforms_undistorted\.json: expected w, h, fl_x"):
        load_scannetpp(und, "nvs_sem_val", None)

    iph = _copy(trees["iphone"], tmp_path / "i")
    (iph / "data" / "room" / "iphone" / "pose_intrinsic_imu.json").write_text("[]", encoding="utf-8")
    with pytest.raises(DatasetError, match=r"pose_intrinsic_imu\.json: expected a JSON object"):
        load_scannetpp(iph, "x", None)
