"""Tests of macsplat_cli.cameras: the camera schema, its validation, and COLMAP/nerfstudio conversions."""

from __future__ import annotations

import copy
import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from macsplat_cli.camera_formats import (
    cameras_for_photos,
    read_colmap_text,
    read_nerfstudio,
    write_colmap_text,
    write_nerfstudio,
)
from macsplat_cli.cameras import (
    Camera,
    CameraSet,
    load_cameras,
    quat_to_rotmat_np,
    rotmat_to_quat_np,
    save_cameras,
)
from macsplat_cli.distortion import Distortion
from macsplat_cli.errors import CameraFileError, OutputPathError

from support.numerics import ROT_MAT, ROT_ROUND_TRIP, ROT_UNIT_Q, gamma, unit_roundoff

U = unit_roundoff(np.float64)  # every camera quantity is float64
# Rotation budgets (ROT_*) are derived in tests/test_rotations.py; Shepperd on an exactly orthogonal R: ≤ 13u.


# ------------------------------------------------------------------------------------ helpers
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def pose(R: np.ndarray, center: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center
    return T


def intrinsics(fx: float, fy: float, cx: float, cy: float, skew: float = 0.0) -> np.ndarray:
    return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def random_camera_set(seed: int, n: int = 6) -> CameraSet:
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        w, h = int(rng.integers(16, 4000)), int(rng.integers(16, 4000))
        K = intrinsics(rng.uniform(50, 5000), rng.uniform(50, 5000), rng.uniform(0, w), rng.uniform(0, h))
        T = pose(random_rotation(rng), rng.normal(0, 10, 3))
        cams.append(Camera(f"images/view_{i:02d}.png", w, h, K, T))
    # Rotations of 180° exercise every branch of the quaternion conversion.
    for axis in np.eye(3):
        R = 2 * np.outer(axis, axis) - np.eye(3)
        K = intrinsics(60, 60, 32, 24)
        cams.append(Camera(f"flip_{len(cams)}.jpg", 64, 48, K, pose(R, rng.normal(size=3))))
    return CameraSet(cams, scale="metric", world="camera_0")


def assert_sets_match(a: CameraSet, b: CameraSet) -> None:
    """Equal names, sizes and K; poses equal up to a rotation round trip through another convention: R → q → R
    (ROT_ROUND_TRIP·u per entry, plus the QR rotations' own orthogonality defect ≤ 16u) and the centre
    c = −Rᵀt with t = −R'c: the rotation error times |c| twice, plus two 3-term products (γ₃|c| each)."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.name == y.name
        assert (x.width, x.height) == (y.width, y.height)
        np.testing.assert_array_equal(x.K, y.K)
        c = float(np.abs(x.center).sum())
        rot = (ROT_ROUND_TRIP + 16) * U
        atol = np.zeros((4, 4))
        atol[:3, :3] = rot
        atol[:3, 3] = 2 * rot * c + 2 * gamma(3, np.float64) * c
        np.testing.assert_array_less(np.abs(x.cam_to_world - y.cam_to_world), atol + np.finfo(float).tiny)


def simple_camera(name: str = "cam0") -> Camera:
    return Camera(name, 640, 480, intrinsics(500.0, 510.0, 320.0, 240.0), np.eye(4))


def valid_dict() -> dict[str, Any]:
    rng = np.random.default_rng(3)
    return {
        "convention": "opencv",
        "world": "camera_0",
        "scale": "relative",
        "cameras": [
            {"name": "left", "width": 640, "height": 480, "K": intrinsics(500, 500, 320, 240).tolist(),
             "cam_to_world": np.eye(4).tolist()},
            {"name": "right", "width": 640, "height": 480, "K": intrinsics(500, 500, 320, 240).tolist(),
             "cam_to_world": pose(random_rotation(rng), np.array([0.3, 0.0, 0.0])).tolist()},
        ],
    }  # fmt: skip


def write_json(path: Path, d: object) -> Path:
    path.write_text(json.dumps(d))
    return path


# ------------------------------------------------------------------------------------ quaternions
def test_quaternion_of_known_rotations() -> None:
    np.testing.assert_array_equal(rotmat_to_quat_np(np.eye(3)), [1, 0, 0, 0])
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    h = math.sqrt(0.5)
    # Shepperd on exact rotations: ≤ 13u per component (and h itself is one rounding)
    np.testing.assert_allclose(rotmat_to_quat_np(Rz90), [h, 0, 0, h], rtol=0, atol=14 * U)
    np.testing.assert_allclose(rotmat_to_quat_np(np.diag([1.0, -1.0, -1.0])), [0, 1, 0, 0], rtol=0, atol=14 * U)
    # R(q̂): ROT_MAT per entry, from an h that is one rounding off (2√2·u more)
    np.testing.assert_allclose(quat_to_rotmat_np(np.array([h, 0, 0, h])), Rz90, rtol=0, atol=(ROT_MAT + 3) * U)
    # Not normalised: same rotation.
    np.testing.assert_allclose(quat_to_rotmat_np(np.array([2 * h, 0, 0, 2 * h])), Rz90, rtol=0, atol=(ROT_MAT + 3) * U)


def test_quaternion_round_trip_random_and_half_turns() -> None:
    rng = np.random.default_rng(0)
    rotations = [random_rotation(rng) for _ in range(200)]
    axes = [np.eye(3)[i] for i in range(3)]
    axes += [np.array([1.0, 1.0, 0.0]) / math.sqrt(2), np.ones(3) / math.sqrt(3)]
    rotations += [2 * np.outer(a, a) - np.eye(3) for a in axes]  # 180° turns: w = 0
    for R in rotations:
        q = rotmat_to_quat_np(R)
        assert q[0] >= 0
        assert abs(np.linalg.norm(q) - 1) <= (ROT_UNIT_Q + 3) * U  # and the test's own norm: 3u
        # the QR rotations are orthogonal to ≤ 16u per entry, within the ROT_ROUND_TRIP budget's E_R
        np.testing.assert_allclose(quat_to_rotmat_np(q), R, rtol=0, atol=ROT_ROUND_TRIP * U)


# ------------------------------------------------------------------------------------ Camera
def test_camera_pose_helpers() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        cam = Camera("c", 10, 10, intrinsics(5, 5, 5, 5), pose(random_rotation(rng), rng.normal(0, 5, 3)))
        # 4×4 products: γ₄·(|A||B|) entrywise, the inverse's own −Rᵀc (γ₃|c|, times |R| ≤ 1 in the product), and the
        # QR rotation's orthogonality defect (≤ 16u per entry, times |c| in the translation column)
        c = float(np.abs(cam.center).sum())
        for A, B in ((cam.world_to_cam, cam.cam_to_world), (cam.cam_to_world, cam.world_to_cam)):
            bound = gamma(4, np.float64) * (np.abs(A) @ np.abs(B)) + (gamma(3, np.float64) + 16 * 3 * U) * (1 + c)
            np.testing.assert_array_less(np.abs(A @ B - np.eye(4)), bound)
        np.testing.assert_array_equal(cam.center, cam.cam_to_world[:3, 3])
        np.testing.assert_allclose(cam.R @ cam.center + cam.t, 0, rtol=0, atol=2 * gamma(3, np.float64) * c + U * c)
        np.testing.assert_array_equal(cam.world_to_cam[3], [0, 0, 0, 1])


def test_camera_is_immutable_and_float64() -> None:
    K = intrinsics(500, 500, 320, 240).astype(np.float32)
    cam = Camera("c", 640, 480, K, np.eye(4, dtype=np.float32))
    assert cam.K.dtype == np.float64 and cam.cam_to_world.dtype == np.float64
    K[0, 0] = 1.0  # the camera holds a copy
    assert cam.K[0, 0] == 500
    with pytest.raises(ValueError):
        cam.K[0, 0] = 2.0
    with pytest.raises(AttributeError):
        cam.width = 3  # type: ignore[misc]


def test_camera_equality() -> None:
    assert simple_camera() == simple_camera()
    assert simple_camera() != simple_camera("other")
    assert simple_camera() != simple_camera().rescaled(320, 240)


def test_rescaled_scales_rows_of_K() -> None:
    cam = Camera("c", 640, 480, intrinsics(500.0, 510.0, 320.5, 240.25, skew=2.0), np.eye(4))
    wide = cam.rescaled(1280, 480)
    np.testing.assert_array_equal(wide.K, intrinsics(1000.0, 510.0, 641.0, 240.25, skew=4.0))
    assert (wide.width, wide.height) == (1280, 480)
    np.testing.assert_array_equal(wide.cam_to_world, cam.cam_to_world)
    # Pixel-corner convention: the image's corners map to the corners of the new image.
    half = cam.rescaled(320, 120)
    for u, v in [(0.0, 0.0), (640.0, 480.0), (100.0, 7.0)]:
        ray = np.linalg.solve(cam.K, [u, v, 1.0])
        p = half.K @ ray
        # a 3×3 solve (LU: γ₉ backward error, K's condition ≲ 2·640/500) and a product (γ₃), of values ≤ 640
        np.testing.assert_allclose(p[:2] / p[2], [u / 2, v / 4], rtol=0, atol=gamma(16, np.float64) * 640 * 4)
    with pytest.raises(CameraFileError):
        cam.rescaled(0, 10)


def test_with_pose() -> None:
    cam = simple_camera()
    T = pose(np.diag([1.0, -1.0, -1.0]), np.array([1.0, 2.0, 3.0]))
    moved = cam.with_pose(T)
    np.testing.assert_array_equal(moved.cam_to_world, T)
    np.testing.assert_array_equal(moved.K, cam.K)
    with pytest.raises(CameraFileError, match="not rigid"):
        cam.with_pose(np.diag([2.0, 2.0, 2.0, 1.0]))


def _scaled_rotation(T: np.ndarray) -> None:
    T[:3, :3] *= 1.3


def _reflection(T: np.ndarray) -> None:
    T[:3, :3] = np.diag([1.0, 1.0, -1.0])


def _sheared(T: np.ndarray) -> None:
    T[0, 1] = 0.2


def _bad_bottom_row(T: np.ndarray) -> None:
    T[3, 0] = 0.5


def _nan_pose(T: np.ndarray) -> None:
    T[1, 3] = np.nan


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (_scaled_rotation, "not rigid"),
        (_reflection, "reflection"),
        (_sheared, "not rigid"),
        (_bad_bottom_row, "bottom row"),
        (_nan_pose, "NaN"),
    ],
)
def test_invalid_pose_is_rejected(mutate: Callable[[np.ndarray], None], expected: str) -> None:
    T = np.eye(4)
    mutate(T)
    with pytest.raises(CameraFileError, match=expected) as err:
        Camera("bad", 10, 10, intrinsics(5, 5, 5, 5), T)
    assert "'bad'" in str(err.value)


@pytest.mark.parametrize("scale", [1e160, -1e9, 1.0000001e8])
def test_far_position_is_rejected(scale: float) -> None:
    """Issue 37 K2: a finite position beyond MAX_TRANSLATION (1e160 made the pose stages' linear algebra fail)."""
    T = np.eye(4)
    T[:3, 3] = [0.3 * scale, scale, 0.1]
    with pytest.raises(CameraFileError, match=r"'far': cam_to_world translation .* is out of range"):
        Camera("far", 10, 10, intrinsics(5, 5, 5, 5), T)


def test_geo_referenced_position_is_accepted() -> None:
    """UTM and Earth-centred metres (a few 10⁶) are within the bound."""
    T = np.eye(4)
    T[:3, 3] = [4.5e5, 5.4e6, -6.4e6]
    np.testing.assert_array_equal(Camera("utm", 10, 10, intrinsics(5, 5, 5, 5), T).cam_to_world, T)


# ------------------------------------------------------------------------------------ cameras of photos (issue 37 K1)
def _named(*names: str) -> CameraSet:
    return CameraSet([Camera(n, 10, 10, intrinsics(5, 5, 5, 5), np.eye(4)) for n in names])


def test_cameras_go_to_their_photos_by_file_name_or_stem() -> None:
    cams = _named("b.jpg", "c", "a")
    got = cameras_for_photos(cams, [Path("x/a.jpg"), Path("b.jpg"), Path("c.png")], "cams.json")
    assert [c.name for c in got] == ["a", "b.jpg", "c"]


def test_a_camera_named_with_its_folder_goes_to_its_photo() -> None:
    """COLMAP image names hold their folder (``images/a.jpg``): the last part names the photo when it is unique; two
    cameras of one last part in two folders name no photo by it."""
    got = cameras_for_photos(_named("images/a.jpg", "images/b.jpg"), [Path("b.jpg"), Path("a")], "model")
    assert [c.name for c in got] == ["images/b.jpg", "images/a.jpg"]
    with pytest.raises(CameraFileError, match="no camera named after 'a.jpg'"):
        cameras_for_photos(_named("x/a.jpg", "y/a.jpg", "b"), [Path("a.jpg"), Path("b.jpg")], "model")


def test_cameras_in_order_only_when_no_name_matches(caplog: pytest.LogCaptureFixture) -> None:
    """No camera named after any photo: the photos' order, and the log says so; with other counts, an error."""
    with caplog.at_level(logging.INFO, logger="macsplat_cli.camera_formats.photos"):
        got = cameras_for_photos(_named("c0", "c1"), [Path("a.png"), Path("b.png")], "cams.json")
    assert [c.name for c in got] == ["c0", "c1"]
    assert "taken in the photos' order (a.png → c0, b.png → c1)" in caplog.text
    with pytest.raises(CameraFileError, match="no camera is named after a photo, and 3 cameras for 2 photos"):
        cameras_for_photos(_named("c0", "c1", "c2"), [Path("a.png"), Path("b.png")], "cams.json")


@pytest.mark.parametrize(
    ("names", "photos", "expected"),
    [
        (("f0", "f1", "f2"), ("x.png", "f0.png", "f1.png"), r"no camera named after 'x\.png'"),  # the campaign's k2
        (("a", "b"), ("one/a.png", "two/a.png"), r"photos 'one/a\.png' and 'two/a\.png' both claim camera 'a'"),
        (("a", "a.png", "b"), ("a.png", "b.png"), r"photo 'a\.png' has two cameras, 'a\.png' and 'a'"),
    ],
    ids=["mixture", "one-camera-two-photos", "two-cameras-one-photo"],
)
def test_cameras_that_do_not_fit_the_photos_are_named(names: tuple, photos: tuple, expected: str) -> None:
    with pytest.raises(CameraFileError, match=r"^cams\.json: " + expected):
        cameras_for_photos(_named(*names), [Path(p) for p in photos], "cams.json")


def test_the_same_photo_twice_shares_its_camera(tmp_path: Path) -> None:
    """A photo given twice (the pipeline leaves the repeat out) is not two photos claiming one camera."""
    photos = [tmp_path / "a.png", tmp_path / "." / "a.png", tmp_path / "b.png"]
    got = cameras_for_photos(_named("a", "b"), photos, "cams.json")
    assert [c.name for c in got] == ["a", "a", "b"]


def test_scaled_rotation_message_reports_deviation() -> None:
    T = np.eye(4)
    T[:3, :3] *= 1.3
    with pytest.raises(CameraFileError, match=r"deviates from I by 0\.69"):
        Camera("x", 10, 10, intrinsics(5, 5, 5, 5), T)


def test_small_rotation_noise_is_accepted() -> None:
    T = np.eye(4)
    T[:3, :3] += 1e-6
    cam = Camera("x", 10, 10, intrinsics(5, 5, 5, 5), T)
    np.testing.assert_array_equal(cam.cam_to_world, T)  # accepted, and kept as given (validation only)


@pytest.mark.parametrize(
    ("K", "expected"),
    [
        (intrinsics(-5, 5, 5, 5), "positive focal"),
        (intrinsics(5, 0, 5, 5), "positive focal"),
        (np.array([[5.0, 0, 5], [1.0, 5, 5], [0, 0, 1]]), "pinhole"),
        (np.array([[5.0, 0, 5], [0, 5, 5], [0, 0, 2]]), "pinhole"),
        (np.eye(4), "3x3"),
        (intrinsics(np.inf, 5, 5, 5), "NaN or Inf"),
    ],
)
def test_invalid_intrinsics_are_rejected(K: np.ndarray, expected: str) -> None:
    with pytest.raises(CameraFileError, match=expected):
        Camera("bad", 10, 10, K, np.eye(4))


@pytest.mark.parametrize(("width", "height"), [(0, 10), (10, -1), (10.0, 10), (True, 10)])
def test_invalid_size_is_rejected(width: object, height: object) -> None:
    with pytest.raises(CameraFileError, match="positive integer"):
        Camera("bad", width, height, intrinsics(5, 5, 5, 5), np.eye(4))  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ CameraSet
def test_camera_set_basics() -> None:
    cams = CameraSet([simple_camera("a"), simple_camera("b")])
    assert len(cams) == 2 and cams[1].name == "b" and [c.name for c in cams] == ["a", "b"]
    assert cams.convention == "opencv" and cams.scale == "relative" and cams.world == "camera_0"
    with pytest.raises(CameraFileError, match="at least one"):
        CameraSet([])
    with pytest.raises(CameraFileError, match="unique"):
        CameraSet([simple_camera("a"), simple_camera("a")])
    with pytest.raises(CameraFileError, match="scale"):
        CameraSet([simple_camera()], scale="feet")  # type: ignore[arg-type]


def test_save_load_round_trip(tmp_path: Path) -> None:
    cams = random_camera_set(seed=5)
    path = tmp_path / "cams.json"
    save_cameras(path, cams)
    text = path.read_text()
    assert text.startswith('{\n  "convention": "opencv"') and text.endswith("\n")
    loaded = load_cameras(path)
    assert loaded == cams  # dataclass equality: exact K and poses, names, sizes, scale, world
    assert loaded.scale == "metric"
    assert [p.name for p in tmp_path.iterdir()] == ["cams.json"]  # no temporary files left


def test_save_creates_missing_folders_but_not_under_a_file(tmp_path: Path) -> None:
    save_cameras(tmp_path / "new" / "cams.json", random_camera_set(0, 1))
    assert load_cameras(tmp_path / "new" / "cams.json") == random_camera_set(0, 1)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputPathError, match="is a file"):
        save_cameras(tmp_path / "file" / "cams.json", random_camera_set(0, 1))


def test_defaults_for_optional_keys(tmp_path: Path) -> None:
    d = valid_dict()
    del d["scale"], d["world"]
    loaded = load_cameras(write_json(tmp_path / "cams.json", d))
    assert loaded.scale == "relative" and loaded.world == "camera_0"


def _set(path: str, value: object) -> Callable[[dict[str, Any]], None]:
    """Mutation setting ``d[...]`` along a dotted path (integers index lists)."""

    def apply(d: dict[str, Any]) -> None:
        keys: list[Any] = [int(k) if k.isdigit() else k for k in path.split(".")]
        target: Any = d
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value

    return apply


def _delete(path: str) -> Callable[[dict[str, Any]], None]:
    def apply(d: dict[str, Any]) -> None:
        keys: list[Any] = [int(k) if k.isdigit() else k for k in path.split(".")]
        target: Any = d
        for key in keys[:-1]:
            target = target[key]
        del target[keys[-1]]

    return apply


SCALED = (np.eye(4) * 1.3).tolist()
SCALED[3][3] = 1.0
REFLECTED = np.diag([1.0, 1.0, -1.0, 1.0]).tolist()


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (
            _set("cameras.1.cam_to_world", SCALED),
            r"cameras\[1\]: camera 'right': cam_to_world rotation is not rigid",
        ),
        (_set("cameras.0.cam_to_world", REFLECTED), r"cameras\[0\].*reflection"),
        (_set("cameras.1.K", [[500, 0, 320], [0, 500, 240]]), r"cameras\[1\]\.K must be a 3x3 matrix"),
        (_set("cameras.1.K", [[500, 0, 320], [0, 500, 240], [0, 0, "1"]]), r"cameras\[1\]\.K must be a 3x3"),
        (_set("cameras.0.K", [[500, 0, 320], [0, -500, 240], [0, 0, 1]]), r"cameras\[0\].*positive focal"),
        (_set("cameras.0.K", [[500, 0, 320], [3, 500, 240], [0, 0, 1]]), r"cameras\[0\].*pinhole"),
        (_set("cameras.0.cam_to_world", [[1, 0, 0]]), r"cameras\[0\]\.cam_to_world must be a 4x4"),
        (_delete("cameras.1.K"), r"cameras\[1\] is missing key\(s\) 'K'"),
        (_delete("cameras.0.name"), r"cameras\[0\] is missing key\(s\) 'name'"),
        (_set("cameras.0.width", "640"), r"cameras\[0\]\.width must be a positive integer"),
        (_set("cameras.0.height", 480.5), r"cameras\[0\]\.height must be a positive integer"),
        (_set("cameras.0.name", 7), r"cameras\[0\]\.name must be a string"),
        (_set("cameras.1.name", "left"), "unique"),
        (_set("cameras.0", "left.png"), r"cameras\[0\] must be an object"),
        (_set("convention", "opengl"), "convention must be \"opencv\".*'opengl'"),
        (_delete("convention"), "missing key 'convention'"),
        (_set("scale", "feet"), "scale must be"),
        (_set("world", 3), "world must be a string"),
        (_set("cameras", []), "cameras must be a non-empty list"),
        (_delete("cameras"), "missing key 'cameras'"),
    ],
)
def test_malformed_camera_files(tmp_path: Path, mutate: Callable[[dict[str, Any]], None], expected: str) -> None:
    d = copy.deepcopy(valid_dict())
    mutate(d)
    path = write_json(tmp_path / "cams.json", d)
    with pytest.raises(CameraFileError, match=expected) as err:
        load_cameras(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ")
    assert "\n" not in message


def test_nan_in_json_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "cams.json"
    text = json.dumps(valid_dict()).replace("0.3", "NaN", 1)
    assert "NaN" in text
    path.write_text(text)
    with pytest.raises(CameraFileError, match="NaN"):
        load_cameras(path)


def test_invalid_json_reports_position(tmp_path: Path) -> None:
    path = tmp_path / "cams.json"
    path.write_text('{\n  "convention": "opencv",\n  "cameras": [1, 2,]\n}\n')
    with pytest.raises(CameraFileError, match=r"invalid JSON at line 3, column \d+") as err:
        load_cameras(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("content", ["[]", '"cameras"', "null"])
def test_top_level_must_be_an_object(tmp_path: Path, content: str) -> None:
    path = tmp_path / "cams.json"
    path.write_text(content)
    with pytest.raises(CameraFileError, match="top level must be an object"):
        load_cameras(path)


def test_missing_camera_file(tmp_path: Path) -> None:
    with pytest.raises(CameraFileError, match="no such file"):
        load_cameras(tmp_path / "missing.json")


# ------------------------------------------------------------------------------------ COLMAP
def _data_lines(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if not line.startswith("#")]


def test_colmap_hand_checked_case(tmp_path: Path) -> None:
    c2w = pose(np.eye(3), np.array([1.0, 2.0, 3.0]))  # at (1, 2, 3), looking along world +z
    cam = Camera("cam0.png", 640, 480, intrinsics(500.0, 510.0, 320.5, 240.5), c2w)
    write_colmap_text(CameraSet([cam]), tmp_path)
    cameras = _data_lines(tmp_path / "cameras.txt")
    assert cameras == ["1 PINHOLE 640 480 500.0 510.0 320.5 240.5"]
    images = _data_lines(tmp_path / "images.txt")
    assert images[1] == ""  # the (empty) POINTS2D line
    fields = images[0].split()
    assert fields[0] == "1" and fields[8] == "1" and fields[9] == "cam0.png"
    np.testing.assert_array_equal([float(v) for v in fields[1:5]], [1, 0, 0, 0])
    np.testing.assert_array_equal([float(v) for v in fields[5:8]], [-1, -2, -3])
    assert _data_lines(tmp_path / "points3D.txt") == []
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (tmp_path / name).read_text().startswith("# ")


def test_colmap_pose_is_world_to_camera(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    R_c2w, center = random_rotation(rng), rng.normal(size=3)
    write_colmap_text(CameraSet([Camera("a", 8, 8, intrinsics(4, 4, 4, 4), pose(R_c2w, center))]), tmp_path)
    fields = _data_lines(tmp_path / "images.txt")[0].split()
    q = np.array([float(v) for v in fields[1:5]])
    t = np.array([float(v) for v in fields[5:8]])
    assert q[0] >= 0
    # the text holds repr()s (exact); R → q → R within ROT_ROUND_TRIP (+16u: the QR rotation's orthogonality)
    rot = (ROT_ROUND_TRIP + 16) * U
    np.testing.assert_allclose(quat_to_rotmat_np(q), R_c2w.T, rtol=0, atol=rot)
    c = float(np.abs(center).sum())
    np.testing.assert_allclose(t, -R_c2w.T @ center, rtol=0, atol=2 * gamma(3, np.float64) * c)
    # A world point in front of the camera projects with COLMAP's x_cam = R X + t.
    X = center + R_c2w @ np.array([0.1, -0.2, 2.0])
    np.testing.assert_allclose(quat_to_rotmat_np(q) @ X + t, [0.1, -0.2, 2.0], rtol=0,
                               atol=rot * np.abs(X).sum() + gamma(8, np.float64) * (2 * c + 3))  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_json_colmap_json_round_trip(tmp_path: Path, seed: int) -> None:
    cams = random_camera_set(seed)
    save_cameras(tmp_path / "cams.json", cams)
    write_colmap_text(load_cameras(tmp_path / "cams.json"), tmp_path / "sparse" / "0")
    imported = read_colmap_text(tmp_path / "sparse" / "0")
    assert imported.world == "colmap" and imported.scale == "relative"
    save_cameras(tmp_path / "back.json", imported)
    assert_sets_match(cams, load_cameras(tmp_path / "back.json"))


def test_colmap_reader_handles_other_models_and_comments(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "\n"
        "3 SIMPLE_RADIAL 800 600 700 400 300 0.01\n"
        "1 SIMPLE_PINHOLE 640 480 500 320 240\n"
        "2 OPENCV 1024 768 900 910 512 384 0 0 0 0\n"
    )
    (tmp_path / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        "# Number of images: 3, mean observations per image: 1\n"
        "7 1 0 0 0 0 0 0 1 b.jpg\n"
        "10.5 20.5 -1\n"
        "2 0 1 0 0 1 2 3 3 a.jpg\n"
        "\n"
        "9 2 0 0 0 0 0 1 2 c d.jpg\n"
        "1.0 2.0 5 3.0 4.0 -1\n"
    )
    with caplog.at_level(logging.WARNING, logger="macsplat_cli.cameras"):
        cams = read_colmap_text(tmp_path)
    assert [c.name for c in cams] == ["a.jpg", "b.jpg", "c d.jpg"]  # ordered by IMAGE_ID
    a, b, c = cams
    np.testing.assert_array_equal(a.K, intrinsics(700, 700, 400, 300))
    np.testing.assert_array_equal(b.K, intrinsics(500, 500, 320, 240))
    np.testing.assert_array_equal(c.K, intrinsics(900, 910, 512, 384))
    assert (a.width, a.height, c.width, c.height) == (800, 600, 1024, 768)
    # a: q = (0, 1, 0, 0) is 180° about x (its own inverse), t = (1, 2, 3): centre = −Rᵀt = (−1, 2, 3). Quaternions
    # with one non-zero component: every product and sum is exact, so are R and the centres
    np.testing.assert_array_equal(a.cam_to_world[:3, :3], np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_array_equal(a.center, [-1, 2, 3])
    np.testing.assert_array_equal(c.center, [0, 0, -1])  # unnormalised q = (2, 0, 0, 0)
    # the lens models' distortion is kept (it was dropped with a warning): SIMPLE_RADIAL's k is OpenCV's k1, an
    # OPENCV camera with zero coefficients is a pinhole
    assert a.distortion == Distortion("opencv", (0.01, 0.0, 0.0, 0.0, 0.0))
    assert b.distortion is None and c.distortion is None
    assert not caplog.records


@pytest.mark.parametrize(
    ("cameras_txt", "images_txt", "expected"),
    [
        ("1 FOV 10 10 5 5 5 5 0.1\n", "1 1 0 0 0 0 0 0 1 a\n\n", "camera 1 has model FOV, which macsplat does not"),
        ("1 PINHOLE 10 10 5 5 5\n", "1 1 0 0 0 0 0 0 1 a\n\n", "needs 4 params"),
        ("1 PINHOLE 10 10 5 5 5 5\n", "1 1 0 0 0 0 0 0 2 a\n\n", "CAMERA_ID 2"),
        ("1 PINHOLE 10 10 5 5 5 5\n", "1 1 0 0 0 0 0 1 a\n\n", "expected IMAGE_ID"),
        ("1 PINHOLE 10 10 5 5 5 5\n", "1 0 0 0 0 0 0 0 1 a\n\n", "non-zero"),
        ("1 PINHOLE 10 10 5 5 5 5\n", "# nothing\n", "no images"),
        ("1 PINHOLE ten 10 5 5 5 5\n", "1 1 0 0 0 0 0 0 1 a\n\n", "integers"),
    ],
)
def test_colmap_reader_errors(tmp_path: Path, cameras_txt: str, images_txt: str, expected: str) -> None:
    (tmp_path / "cameras.txt").write_text(cameras_txt)
    (tmp_path / "images.txt").write_text(images_txt)
    with pytest.raises(CameraFileError, match=expected):
        read_colmap_text(tmp_path)


def test_colmap_missing_files(tmp_path: Path) -> None:
    with pytest.raises(CameraFileError, match="cameras.txt: no such file"):
        read_colmap_text(tmp_path)


def test_colmap_writer_rejects_skew_and_spaces(tmp_path: Path) -> None:
    skewed = Camera("a", 10, 10, intrinsics(5, 5, 5, 5, skew=0.5), np.eye(4))
    with pytest.raises(CameraFileError, match="skew"):
        write_colmap_text(CameraSet([skewed]), tmp_path / "out")
    with pytest.raises(CameraFileError, match="spaces"):
        write_colmap_text(CameraSet([simple_camera("my image.png")]), tmp_path / "out")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------ nerfstudio
def test_nerfstudio_hand_checked_case(tmp_path: Path) -> None:
    c2w = pose(np.eye(3), np.array([1.0, 2.0, 3.0]))
    cam = Camera("images/cam0.png", 640, 480, intrinsics(500.0, 510.0, 320.5, 240.5), c2w)
    path = write_nerfstudio(CameraSet([cam]), tmp_path / "transforms.json")
    d = json.loads(path.read_text())
    assert d["camera_model"] == "OPENCV"
    (frame,) = d["frames"]
    assert frame["file_path"] == "images/cam0.png"
    assert (frame["fl_x"], frame["fl_y"], frame["cx"], frame["cy"]) == (500.0, 510.0, 320.5, 240.5)
    assert (frame["w"], frame["h"]) == (640, 480)
    expected = [[1, 0, 0, 1], [0, -1, 0, 2], [0, 0, -1, 3], [0, 0, 0, 1]]
    assert frame["transform_matrix"] == expected
    M = np.array(frame["transform_matrix"])
    np.testing.assert_array_equal(M[:, 0], c2w[:, 0])
    np.testing.assert_array_equal(M[:, 1:3], -c2w[:, 1:3])
    np.testing.assert_array_equal(M[:, 3], c2w[:, 3])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_json_nerfstudio_json_round_trip(tmp_path: Path, seed: int) -> None:
    cams = random_camera_set(seed)
    save_cameras(tmp_path / "cams.json", cams)
    write_nerfstudio(load_cameras(tmp_path / "cams.json"), tmp_path / "transforms.json")
    imported = read_nerfstudio(tmp_path / "transforms.json")
    assert imported.world == "nerfstudio"
    save_cameras(tmp_path / "back.json", imported)
    back = load_cameras(tmp_path / "back.json")
    assert_sets_match(cams, back)
    for a, b in zip(cams, back):  # sign flips are exact
        np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)


def test_nerfstudio_shared_intrinsics_and_distortion(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    gl = pose(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 5.0]))  # OpenGL axes; OpenCV rotation = I
    d = {
        "camera_model": "OPENCV",
        "fl_x": 300.0, "fl_y": 310.0, "cx": 160.0, "cy": 120.0, "w": 320, "h": 240, "k1": 0.05,
        "frames": [
            {"file_path": "images/a.png", "transform_matrix": gl.tolist()},
            {"file_path": "images/b.png", "transform_matrix": np.eye(4).tolist(), "fl_x": 333.0, "k1": 0.0},
        ],
    }  # fmt: skip
    path = write_json(tmp_path / "transforms.json", d)
    with caplog.at_level(logging.WARNING, logger="macsplat_cli.cameras"):
        cams = read_nerfstudio(path)
    a, b = cams
    np.testing.assert_array_equal(a.K, intrinsics(300, 310, 160, 120))
    np.testing.assert_array_equal(b.K, intrinsics(333, 310, 160, 120))
    assert (a.width, a.height) == (320, 240)
    np.testing.assert_array_equal(a.cam_to_world, pose(np.eye(3), np.array([0.0, 0.0, 5.0])))
    np.testing.assert_array_equal(b.cam_to_world, np.diag([1.0, -1.0, -1.0, 1.0]))
    assert a.distortion == Distortion("opencv", (0.05, 0.0, 0.0, 0.0, 0.0))  # the top level's k1 (was ignored)
    assert b.distortion is None  # its own k1 = 0 wins
    assert not caplog.records


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (_delete("frames.0.fl_x"), "missing 'fl_x'"),
        (_set("frames.0.w", 10.5), "w must be an integer"),
        (_set("frames.0.transform_matrix", [[1, 0, 0, 0]]), r"frames\[0\]\.transform_matrix must be a 4x4"),
        (_delete("frames.0.file_path"), "file_path must be a string"),
        (_set("camera_model", "EQUIRECTANGULAR"), "camera_model .EQUIRECTANGULAR. is not read"),
        (_set("frames", []), "non-empty"),
        (_set("frames.0.transform_matrix", np.diag([1.0, 1.0, 1.0, 2.0]).tolist()), "bottom row"),
    ],
)
def test_nerfstudio_reader_errors(tmp_path: Path, mutate: Callable[[dict[str, Any]], None], expected: str) -> None:
    d = {
        "camera_model": "OPENCV",
        "frames": [{"file_path": "a.png", "fl_x": 5.0, "fl_y": 5.0, "cx": 5.0, "cy": 5.0, "w": 10, "h": 10,
                    "transform_matrix": np.eye(4).tolist()}],
    }  # fmt: skip
    mutate(d)
    path = write_json(tmp_path / "transforms.json", d)
    with pytest.raises(CameraFileError, match=expected) as err:
        read_nerfstudio(path)
    assert str(err.value).startswith(f"{path}: ")


def test_nerfstudio_writer_rejects_skew(tmp_path: Path) -> None:
    skewed = Camera("a", 10, 10, intrinsics(5, 5, 5, 5, skew=0.5), np.eye(4))
    with pytest.raises(CameraFileError, match="skew"):
        write_nerfstudio(CameraSet([skewed]), tmp_path / "transforms.json")
    assert not (tmp_path / "transforms.json").exists()
