"""COLMAP models in: ``--poses DIR`` / ``--intrinsics DIR`` read a COLMAP model (text or binary) for the photos,
its frame and scale kept; a camera the model's lens cannot be taken from is refused naming it (exit 2)."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.camera_formats import read_colmap_model, write_colmap_text
from macsplat_cli.cameras import CameraSet, load_cameras
from macsplat_cli.distortion import Distortion
from macsplat_cli.errors import CameraFileError
from macsplat_cli.rotations import rotmat_to_quat_np

from support.cli import one_error_line, run_cli
from support.scenes import PairFactory, PairSpec

SPEC = PairSpec(size=(320, 240))
_MODEL_IDS = {"PINHOLE": 1, "OPENCV": 4, "OPENCV_FISHEYE": 5}


def _write_binary(cams: CameraSet, folder: Path, models: list[tuple[str, list[float]]]) -> None:
    """COLMAP's binary layout, written by hand (``cameras.bin``, ``images.bin``): camera i + 1 with ``models[i]``."""
    folder.mkdir(parents=True)
    data = struct.pack("<Q", len(cams))
    for i, (cam, (model, params)) in enumerate(zip(cams, models), start=1):
        data += struct.pack("<iiQQ", i, _MODEL_IDS[model], cam.width, cam.height)
        data += struct.pack(f"<{len(params)}d", *params)
    (folder / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(cams))
    for i, cam in enumerate(cams, start=1):
        data += struct.pack("<I7di", i, *rotmat_to_quat_np(cam.R), *cam.t, i) + cam.name.encode() + b"\0"
        data += struct.pack("<Q", 1) + struct.pack("<ddq", 1.5, 2.5, -1)  # one 2D point, no 3D point
    (folder / "images.bin").write_bytes(data)


def test_binary_model_reads_as_the_text_model(pair_files: PairFactory, tmp_path: Path) -> None:
    cams = load_cameras(pair_files(SPEC, camera_names=True).cameras)
    fisheye = [0.01, -0.002, 0.0005, 0.0]
    models = [("OPENCV", [*cams[0].K[[0, 1, 0, 1], [0, 1, 2, 2]], 0.1, -0.05, 0.001, 0.002]),
              ("OPENCV_FISHEYE", [*cams[1].K[[0, 1, 0, 1], [0, 1, 2, 2]], *fisheye])]  # fmt: skip
    _write_binary(cams, tmp_path / "bin", models)
    got = read_colmap_model(tmp_path / "bin")
    assert [c.name for c in got] == ["a.png", "b.png"]
    for a, b in zip(got, cams):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-12)
    assert got[0].distortion == Distortion("opencv", (0.1, -0.05, 0.001, 0.002, 0.0))
    assert got[1].distortion == Distortion("fisheye", tuple(fisheye))
    write_colmap_text(got, tmp_path / "txt")  # and back through the text model, distortion kept
    for a, b in zip(read_colmap_model(tmp_path / "txt"), got):
        assert a.distortion == b.distortion and np.array_equal(a.K, b.K)
        np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-12)


def test_poses_from_a_colmap_model_keep_its_frame_and_scale(pair_files: PairFactory, tmp_path: Path) -> None:
    pair = pair_files(SPEC, camera_names=True)
    cams = load_cameras(pair.cameras)
    T = np.eye(4)  # the model in another frame and scale than any camera's: a turn, a shift, x 3.7
    T[:3, :3] = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0] * np.array([1, 1, 1])
    T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))
    T[:3, 3] = [5.0, -2.0, 1.0]
    moved = [c.with_pose(T @ c.cam_to_world) for c in cams]
    moved = [m.with_pose(np.r_[np.c_[m.cam_to_world[:3, :3], m.cam_to_world[:3, 3] * 3.7], [[0, 0, 0, 1]]])
             for m in moved]  # fmt: skip
    _write_binary(
        CameraSet(moved), tmp_path / "model", [("PINHOLE", list(c.K[[0, 1, 0, 1], [0, 1, 2, 2]])) for c in moved]
    )
    code, _, err = run_cli(["reconstruct", *pair.photos, "-o", tmp_path / "s.ply", "--size", 320, "-q",
                            "--poses", tmp_path / "model"])  # fmt: skip
    assert code == 0, err
    for a, b in zip(load_cameras(tmp_path / "s.cameras.json"), moved):
        np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-9)
        np.testing.assert_allclose(a.K, b.K, rtol=1e-12)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("1 FOV 320 240 300 300 160 120 0.5", "camera 1 has model FOV, which macsplat does not read"),
        ("1 OPENCV 320 240 300 300 160 120 nan 0 0 0", "camera 1 (OPENCV) has a NaN"),
        ("1 RADIAL 320 240 300 160 120 -0.9 0.1", "camera 1: camera 'a.png': its opencv distortion folds the image"),
    ],
)
def test_bad_colmap_cameras_exit_2_naming_the_camera(
    pair_files: PairFactory, tmp_path: Path, line: str, expected: str
) -> None:
    pair = pair_files(SPEC)
    model = tmp_path / "model"
    model.mkdir()
    (model / "cameras.txt").write_text(line + "\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 1 0 0 1 b.png\n\n")
    with pytest.raises(CameraFileError, match=re.escape(expected)):
        read_colmap_model(model)
    for option in ("--intrinsics", "--poses"):
        code, _, err = run_cli(["reconstruct", *pair.photos, "-o", tmp_path / "s.ply", option, model])
        assert code == 2 and expected in one_error_line(err)
    assert not (tmp_path / "s.ply").exists()
