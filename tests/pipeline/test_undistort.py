"""Photos with lens distortion (``distortion`` in the cameras file): undistorted once at load to the camera's pinhole
K, so the pose and every later stage see a pinhole photo. A synthetic pair photographed through barrel distortion
(k1 = −0.2) gives its true pose within 0.2° when the distortion is given, and the undistorted photo is the pinhole
render of the same camera."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from macsplat_cli.cameras import Camera, CameraSet, load_cameras, save_cameras
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.distortion import Distortion
from macsplat_cli.errors import CameraFileError
from macsplat_cli.images import save_image
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig
from macsplat_cli.pipeline.views import ViewConfig, load_views

from support.scenes import distorted_photo

BARREL = Distortion("opencv", (-0.2, 0.0, 0.0, 0.0, 0.0))
W, H = 512, 384


@pytest.fixture(scope="module")
def barrel_pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path], tuple[Camera, Camera], object]:
    """The room pair photographed through ``BARREL``: (its cameras file with the distortion, the photos, the true
    cameras, the scene)."""
    folder = tmp_path_factory.mktemp("barrel")
    scene = syn.make_scene("room", 0, textured=True)
    cams = syn.orbit_pair("room", 20.0, width=W, height=H, fov_deg=60.0, seed=0)
    names = ("a.png", "b.png")
    photos = [save_image(folder / n, distorted_photo(scene, c, BARREL)) for n, c in zip(names, cams)]
    given = CameraSet([dataclasses.replace(c, name=n, distortion=BARREL) for n, c in zip(names, cams)])
    save_cameras(folder / "cameras.json", given)
    return folder / "cameras.json", photos, cams, scene


def _pose_error(intrinsics: Path, photos: list[Path], cams: tuple[Camera, Camera]) -> float:
    cfg = ReconstructConfig(views=ViewConfig(intrinsics=intrinsics))
    g = Pipeline(cfg).search(load_views(photos, cfg.views)).geometry
    truth = np.linalg.inv(cams[1].cam_to_world) @ cams[0].cam_to_world
    return rotation_error_deg(g.R, truth[:3, :3])


def test_barrel_distortion_given_gives_the_pose(barrel_pair, tmp_path: Path) -> None:  # noqa: ANN001
    intrinsics, photos, cams, _ = barrel_pair
    assert _pose_error(intrinsics, photos, cams) <= 0.2  # 0.02° when measured
    # the same photos with the distortion left out: the pose is measurably worse (what the distortion costs)
    pinhole = CameraSet([dataclasses.replace(c, distortion=None) for c in load_cameras(intrinsics)])
    save_cameras(tmp_path / "pinhole.json", pinhole)
    assert _pose_error(tmp_path / "pinhole.json", photos, cams) > 1.0  # 4.2° when measured


def test_the_undistorted_photo_is_the_pinhole_render(barrel_pair) -> None:  # noqa: ANN001
    intrinsics, photos, cams, scene = barrel_pair
    views = load_views(photos, ViewConfig(intrinsics=intrinsics, size=W))
    assert [v.undistorted for v in views] == [BARREL, BARREL]
    truth = syn.render(scene, cams[0], supersample=3).image
    v = views[0]
    np.testing.assert_array_equal(v.K, cams[0].K)  # the camera's own pinhole K
    inner = v.mask.copy()
    inner[:4], inner[-4:], inner[:, :4], inner[:, -4:] = False, False, False, False
    mse = float(np.mean((v.image[inner] - truth[inner]) ** 2))
    assert 10 * np.log10(1 / mse) > 30.0  # dB: the resampling twice (distort, undistort) blurs a little, no more
    assert v.mask.mean() > 0.99  # barrel: the pinhole frame lies inside the photo


@pytest.mark.parametrize(
    ("distortion", "expected"),
    [
        ({"model": "opencv", "k1": -0.6}, "folds the image"),  # the radius peaks inside the frame
        ({"model": "opencv", "k1": float("nan")}, "must be a finite number"),
        ({"model": "fisheye", "k1": -0.5}, "folds the image"),
        ({"model": "opencv", "k4": 0.1}, "k4 not a coefficient of the opencv model"),
        ({"model": "kannala"}, "model must be one of opencv, fisheye"),
    ],
)
def test_bad_distortion_is_refused_naming_the_camera(distortion: dict, expected: str) -> None:
    d = {"convention": "opencv", "cameras": [{"name": "left", "width": 640, "height": 480,
         "K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "cam_to_world": np.eye(4).tolist(),
         "distortion": distortion}]}  # fmt: skip
    with pytest.raises(CameraFileError, match=expected) as err:
        CameraSet.from_dict(d, "k.json")
    assert "left" in str(err.value) or "cameras[0]" in str(err.value)


def test_a_camera_without_distortion_loads_as_before(tmp_path: Path) -> None:
    cam = Camera("left", 640, 480, np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.0]]), np.eye(4))
    save_cameras(tmp_path / "k.json", CameraSet([cam]))
    assert "distortion" not in (tmp_path / "k.json").read_text()


@pytest.mark.parametrize(
    "d",
    [
        Distortion("opencv", (-0.2, 0.05, 0.001, -0.002, 0.01)),
        Distortion("opencv", (0.2079, -0.5844, -0.0007, 0.0004, 0.4974)),  # NYU Depth v2's RGB camera
        Distortion("fisheye", (0.05, -0.01, 0.002, -0.0005)),
    ],
)
def test_the_lens_model_is_opencvs(d: Distortion) -> None:
    """The forward model (the fold check, the export's observations) is OpenCV's projection, and the undistortion
    maps sample the photo where that model puts each pinhole pixel (pixel centres at +0.5 on our side)."""
    from macsplat_cli.distortion import distort_normalised
    from macsplat_cli.pipeline.undistort import undistort_maps

    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-0.6, 0.6, (50, 2)), np.ones(50)]
    xd, yd = distort_normalised(d, X[:, 0], X[:, 1])
    project = cv2.fisheye.projectPoints if d.model == "fisheye" else cv2.projectPoints
    cv = project(X[:, None], np.zeros(3), np.zeros(3), np.eye(3), np.array(d.coeffs))[0].reshape(-1, 2)
    np.testing.assert_allclose(np.c_[xd, yd], cv, atol=1e-12)
    K = np.array([[300.0, 0, 161.0], [0, 302.0, 119.0], [0, 0, 1]])
    mx, my = undistort_maps(K, d, 320, 240)
    i, j = rng.integers(0, 240, 40), rng.integers(0, 320, 40)
    xn, yn = (j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1]
    xd, yd = distort_normalised(d, xn, yn)
    np.testing.assert_allclose(mx[i, j] + 0.5, K[0, 0] * xd + K[0, 2], atol=2e-3)  # float32 maps
    np.testing.assert_allclose(my[i, j] + 0.5, K[1, 1] * yd + K[1, 2], atol=2e-3)
