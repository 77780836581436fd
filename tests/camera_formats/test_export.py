"""``reconstruct --export colmap|nerfstudio DIR``: the folders other tools open, read back by pycolmap (when
installed), by our own parsers, and checked for what they promise: the photos under the names the model gives,
every point seen twice or more and reprojecting to its observations, nothing written partially or over what the user
did not ask to replace."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.camera_formats import read_colmap_model, read_nerfstudio
from macsplat_cli.camera_formats.export import write_export
from macsplat_cli.camera_formats.points import SparsePoints
from macsplat_cli.cameras import CameraSet, load_cameras, save_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.distortion import Distortion
from macsplat_cli.errors import OutputPathError
from macsplat_cli.images import save_image

from support.cli import one_error_line, run_cli
from support.scenes import PairFactory, PairSpec, distorted_photo

SPEC = PairSpec(size=(320, 240))


def _points3d(path: Path) -> dict[int, tuple[np.ndarray, list[tuple[int, int]]]]:
    """``points3D.txt`` by hand: id → (xyz, [(image id, point2D index)])."""
    out = {}
    for line in path.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        v = line.split()
        track = [(int(v[i]), int(v[i + 1])) for i in range(8, len(v), 2)]
        out[int(v[0])] = (np.array([float(x) for x in v[1:4]]), track)
    return out


def _points2d(path: Path) -> dict[str, list[tuple[float, float, int]]]:
    """``images.txt``'s POINTS2D lines by hand: image name → [(x, y, point id)]."""
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    out = {}
    for head, obs in zip(lines[0::2], lines[1::2]):
        v = obs.split()
        out[head.split()[9]] = [(float(v[i]), float(v[i + 1]), int(v[i + 2])) for i in range(0, len(v), 3)]
    return out


@pytest.fixture(scope="module")
def colmap_export(pair_files: PairFactory, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A pair reconstructed with ``--export colmap``: (the export folder, the cameras file)."""
    pair = pair_files(SPEC, ("left.png", "right.png"))
    out = tmp_path_factory.mktemp("colmap")
    code, _, err = run_cli(["reconstruct", *pair.photos, "-o", out / "s.ply", "--size", 320, "-q",
                            "--export", "colmap", out / "export"])  # fmt: skip
    assert code == 0, err
    return out / "export", out / "s.cameras.json"


def test_colmap_export_is_a_model_with_its_photos_and_points(colmap_export: tuple[Path, Path]) -> None:
    folder, cameras_json = colmap_export
    model = folder / "sparse" / "0"
    cams = read_colmap_model(model)
    assert [c.name for c in cams] == ["left.png", "right.png"]  # the photos' file names, with their extension
    for cam in cams:
        assert (folder / "images" / cam.name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    written = load_cameras(cameras_json)  # the same cameras as the cameras file
    for a, b in zip(cams, written):
        np.testing.assert_allclose(a.K, b.K, rtol=1e-12)
        np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-12)
    points, obs = _points3d(model / "points3D.txt"), _points2d(model / "images.txt")
    assert len(points) >= 50
    errors = []
    for xyz, track in points.values():
        assert len(track) >= 2
        for image_id, idx in track:
            cam = cams[image_id - 1]
            x, y, pid = obs[cam.name][idx]
            assert points[pid][0] is xyz  # the track and the image's POINTS2D agree
            Xc = cam.R @ xyz + cam.t
            errors.append(np.hypot(*(cam.K[:2] @ Xc / Xc[2] - [x, y])))
    assert np.median(errors) <= 1.0


def test_colmap_export_loads_in_pycolmap(colmap_export: tuple[Path, Path]) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    folder, _ = colmap_export
    rec = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    assert rec.num_cameras() == 2 and rec.num_images() == 2 and rec.num_points3D() >= 50
    errors = []
    for image in rec.images.values():
        assert (folder / "images" / image.name).is_file()
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world  # 4.x: a method
        for p in image.points2D:
            if p.has_point3D():
                xyz = rec.points3D[p.point3D_id].xyz
                errors.append(np.linalg.norm(np.asarray(cam.img_from_cam(pose * xyz))[:2] - p.xy))
    assert all(pt.track.length() >= 2 for pt in rec.points3D.values())
    assert np.median(errors) <= 1.0


def test_nerfstudio_export_round_trips_and_replaces_with_force(pair_files: PairFactory, tmp_path: Path) -> None:
    pair = pair_files(SPEC, ("left.png", "right.png"))
    folder = tmp_path / "ns"
    folder.mkdir()
    (folder / "old.txt").write_text("from before")
    args = ["reconstruct", *pair.photos, "-o", tmp_path / "s.ply", "--size", 320, "-q", "--export", "nerfstudio",
            folder]  # fmt: skip
    code, _, err = run_cli(args)  # a folder that is there and not empty: refused before any work
    assert code == 2 and "not empty" in one_error_line(err) and "--force" in one_error_line(err)
    assert not (tmp_path / "s.ply").exists() and (folder / "old.txt").exists()
    code, _, err = run_cli([*args, "--force"])
    assert code == 0, err
    assert not (folder / "old.txt").exists()
    doc = json.loads((folder / "transforms.json").read_text())
    assert doc["ply_file_path"] == "sparse_pc.ply"
    cams, written = read_nerfstudio(folder / "transforms.json"), load_cameras(tmp_path / "s.cameras.json")
    assert [c.name for c in cams] == ["images/left.png", "images/right.png"]
    for a, b in zip(cams, written):
        assert (folder / a.name).is_file()
        np.testing.assert_allclose(a.K, b.K, rtol=1e-12)
        np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-12)
    header = (folder / "sparse_pc.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert "element vertex" in header and int(header.split("element vertex ")[1].split()[0]) >= 50


def test_export_refuses_a_folder_holding_an_input(pair_files: PairFactory, tmp_path: Path) -> None:
    pair = pair_files(SPEC, ("left.png", "right.png"))
    code, _, err = run_cli(["reconstruct", *pair.photos, "-o", tmp_path / "s.ply", "--export", "colmap",
                            pair.a.parent, "--force"])  # fmt: skip
    assert code == 2 and "photo 1" in one_error_line(err)
    assert pair.a.exists()


def test_export_unknown_format(pair_files: PairFactory, tmp_path: Path) -> None:
    pair = pair_files(SPEC, ("left.png", "right.png"))
    code, _, err = run_cli(["reconstruct", *pair.photos, "-o", tmp_path / "s.ply", "--export", "ply", tmp_path / "x"])
    assert code == 2 and "unknown format 'ply'" in one_error_line(err)


def test_a_failed_export_leaves_nothing(pair_files: PairFactory, tmp_path: Path) -> None:
    pair = pair_files(SPEC, ("left.png", "right.png"), camera_names=True)
    cams = load_cameras(pair.cameras)
    pts = SparsePoints(np.zeros((1, 3)), np.zeros((1, 3), np.uint8), np.zeros(1), np.array([0, 1]),
                       np.array([0, 0]), np.zeros((2, 2)))  # fmt: skip
    with pytest.raises(OutputPathError, match="cannot copy"):
        write_export("colmap", tmp_path / "out", cams, pts, [pair.a, tmp_path / "missing.png"])
    assert list(tmp_path.iterdir()) == []  # neither the folder nor its temporary one


def test_colmap_export_of_distorted_photos_keeps_their_lens(tmp_path: Path) -> None:
    """Photos undistorted at load are exported as they are, with an OPENCV camera: the points' observations are on
    the distorted photos and reproject there through the lens (pycolmap's projection, else the OpenCV model)."""
    lens = Distortion("opencv", (-0.15, 0.02, 0.0, 0.0, 0.0))
    scene = syn.make_scene("room", 0, textured=True)
    cams = syn.orbit_pair("room", 20.0, width=320, height=240, fov_deg=60.0, seed=0)
    photos = [save_image(tmp_path / n, distorted_photo(scene, c, lens, 64)) for n, c in zip(("a.png", "b.png"), cams)]
    save_cameras(tmp_path / "k.json", CameraSet([dataclasses.replace(c, name=p.name, distortion=lens)
                                                 for c, p in zip(cams, photos)]))  # fmt: skip
    code, _, err = run_cli(["reconstruct", *photos, "-o", tmp_path / "s.ply", "-q", "--intrinsics", tmp_path / "k.json",
                            "--export", "colmap", tmp_path / "x"])  # fmt: skip
    assert code == 0, err
    model = tmp_path / "x" / "sparse" / "0"
    got = read_colmap_model(model)
    assert [c.distortion for c in got] == [lens, lens]
    assert (model / "cameras.txt").read_text().count(" OPENCV ") == 2
    points, obs = _points3d(model / "points3D.txt"), _points2d(model / "images.txt")
    errors = []
    for xyz, track in points.values():
        for image_id, idx in track:
            cam = got[image_id - 1]
            x, y, _ = obs[cam.name][idx]
            K_cv = cam.K.copy()
            K_cv[:2, 2] -= 0.5
            rvec = cv2.Rodrigues(cam.R)[0]
            uv = cv2.projectPoints(xyz[None], rvec, cam.t, K_cv, np.array(lens.coeffs))[0].ravel() + 0.5
            errors.append(np.hypot(*(uv - [x, y])))
    assert len(points) >= 50 and np.median(errors) <= 1.0
    # a pinhole reading of the same observations is off: the lens is what makes them fit
    pinhole = []
    for xyz, track in points.values():
        image_id, idx = track[0]
        cam = got[image_id - 1]
        Xc = cam.R @ xyz + cam.t
        pinhole.append(np.hypot(*(cam.K[:2] @ Xc / Xc[2] - obs[cam.name][idx][:2])))
    assert np.median(pinhole) > 2 * np.median(errors) + 0.5


def test_an_export_path_that_is_a_file_or_a_link_is_refused(tmp_path: Path) -> None:
    from macsplat_cli.camera_formats.export import check_export_folder
    from macsplat_cli.errors import InputError

    (tmp_path / "file").write_text("x")
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    for name in ("file", "link"):
        with pytest.raises(InputError, match="exists and is not a folder"):
            check_export_folder(tmp_path / name, True)
    check_export_folder(tmp_path / "real", False)  # empty: fine without --force
    check_export_folder(tmp_path / "new" / "deeper", False)  # absent: fine, nothing created
    assert not (tmp_path / "new").exists()


def test_a_photo_name_with_a_space_is_refused_for_colmap_before_any_work(
    pair_files: PairFactory, tmp_path: Path
) -> None:
    pair = pair_files(SPEC, ("my left.png", "right.png"))
    code, _, err = run_cli(
        ["reconstruct", *pair.photos, "-o", tmp_path / "s.ply", "--export", "colmap", tmp_path / "x"]
    )
    assert code == 2 and "'my left.png'" in one_error_line(err)
    assert not (tmp_path / "s.ply").exists()
