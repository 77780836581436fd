"""Photos with lens distortion (``distortion`` in the cameras file): undistorted once at load to the camera's pinhole
K, so the pose and every later stage see a pinhole photo. A synthetic pair photographed through barrel distortion
(k1 = −0.2) gives its true pose within 0.2° when the distortion is given, and the undistorted photo is the pinhole
render of the same camera."""

from __future__ import annotations

import dataclasses
from pathlib import Path

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
