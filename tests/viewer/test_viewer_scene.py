"""What the viewer sends the page (viewer/scene.py) and how it picks its address (viewer/server.py, no server)."""

from __future__ import annotations

import logging
import os
import socket
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.cameras import Camera
from macsplat_cli.errors import InputError
from macsplat_cli.rotations import quat_to_rotmat_np
from macsplat_cli.sh import sh0_to_rgb
from macsplat_cli.viewer import (
    PortInUseError,
    camera_pose,
    find_image,
    is_loopback,
    load_thumbnails,
    resolve_port,
    splat_arrays,
    thin_out,
)

from support.gaussians import random_gaussians
from support.viewer_scene import plane_cameras


def test_splat_arrays_carry_the_scene_as_macsplat_means_it() -> None:
    g = random_gaussians(200, seed=3, sh_degree=2)
    g.means[7, 1] = float("nan")  # a non-finite Gaussian is left out, not sent
    s = splat_arrays(g)
    keep = torch.ones(200, dtype=torch.bool)
    keep[7] = False
    assert len(s) == 199 and s.centers.dtype == np.float32
    np.testing.assert_allclose(s.centers, g.means[keep].numpy(), rtol=0, atol=0)
    cov = g[keep.nonzero().squeeze(1)].covariances().double().numpy()
    np.testing.assert_allclose(s.covariances, cov, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(s.rgbs, sh0_to_rgb(g.sh[keep, 0]).clamp(0, 1).numpy(), atol=1e-7)
    np.testing.assert_allclose(s.opacities[:, 0], torch.sigmoid(g.opacity_logits[keep]).numpy(), atol=1e-7)
    assert s.opacities.shape == (199, 1)


def test_thin_out_keeps_the_opaque_large_gaussians() -> None:
    g = random_gaussians(100, seed=1)
    assert thin_out(g, 100) is g
    big = torch.arange(100) % 10 == 0
    g.log_scales[big] += 2.0
    g.opacity_logits[big] = 5.0
    kept = thin_out(g, 10)
    assert len(kept) == 10
    np.testing.assert_array_equal(kept.means.numpy(), g.means[big].numpy())  # the ten, in their order


def test_camera_pose_is_the_cameras_own_frame() -> None:
    cam = plane_cameras()[1]
    pose = camera_pose(cam)
    R = cam.cam_to_world[:3, :3]
    np.testing.assert_allclose(quat_to_rotmat_np(pose.wxyz), R, atol=1e-12)
    np.testing.assert_allclose(pose.position, cam.cam_to_world[:3, 3])
    np.testing.assert_allclose(pose.look_at - pose.position, R[:, 2], atol=1e-12)  # ahead: the camera's +z
    np.testing.assert_allclose(pose.up, -R[:, 1], atol=1e-12)  # up: the camera's −y
    assert pose.fov_y == pytest.approx(2 * np.arctan(cam.height / 2 / cam.K[1, 1]))
    assert pose.aspect == pytest.approx(cam.width / cam.height)


def test_find_image_by_name_or_stem(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "left.JPG").write_bytes(b"x")
    (tmp_path / "a" / "right.png").write_bytes(b"x")
    folders = [tmp_path / "a", tmp_path / "b"]
    assert find_image("left", folders) == tmp_path / "b" / "left.JPG"  # reconstruct names cameras by the stem
    assert find_image("right.png", folders) == tmp_path / "a" / "right.png"
    assert find_image("sub/right.png", folders) == tmp_path / "a" / "right.png"
    assert find_image("middle", folders) is None


def _photo(path: Path) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((12, 16, 3), 200, np.uint8)).save(path)
    return path


def test_find_image_stays_inside_its_folders(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A camera's name cannot make the viewer read a photo outside the folders it looks in (issue 37, V1)."""
    photos = tmp_path / "photos"
    secret = _photo(tmp_path / "private" / "secret.png")
    _photo(photos / "inside.png")
    (photos / "sub").mkdir()
    os.symlink(secret, photos / "link.png")  # a link in the folder that leads out of it
    os.symlink(tmp_path / "private", photos / "sub" / "out")  # a linked folder that leads out
    for name in (str(secret), "../private/secret.png", "sub/../../private/secret.png", "link", "link.png",
                 "sub/out/secret.png", "..\\private\\secret.png"):  # fmt: skip
        assert find_image(name, [photos]) is None, name
    assert find_image("inside", [photos]) == photos / "inside.png"
    assert find_image("sub/inside.png", [photos]) == photos / "inside.png"  # the base name, inside
    # the photo is not shown, and the log says why, once per camera
    cams = [Camera(n, 16, 12, np.eye(3), np.eye(4)) for n in (str(secret), "link", "inside")]
    with caplog.at_level(logging.INFO, logger="macsplat_cli"):
        thumbs = load_thumbnails(cams, [photos], 8)
    assert list(thumbs) == ["inside"]
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and all("is drawn without a photo" in m for m in said), said
    assert "absolute" in said[0] and "link out of" in said[1]


def test_find_image_takes_any_name_length(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A name longer than a file name can be has no photo (was OSError 'File name too long'), and the log line that
    says so is short (issue 37, V4)."""
    _photo(tmp_path / ("y" * 250 + ".png"))
    assert find_image("y" * 250, [tmp_path]) == tmp_path / ("y" * 250 + ".png")  # 254 bytes: a file name
    for name in ("x" * 300, "é" * 200, "x" * 2_000_000, "a/" * 5000 + "b", "y" * 250 + "/" + "z" * 256):
        assert find_image(name, [tmp_path]) is None, name[:20]
    cam = Camera("x" * 2_000_000, 16, 12, np.eye(3), np.eye(4))
    with caplog.at_level(logging.DEBUG, logger="macsplat_cli"):
        assert load_thumbnails([cam], [tmp_path], 8) == {}
    assert len(caplog.records) == 1 and len(caplog.records[0].getMessage()) < 300


def test_loopback_hosts() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1") and is_loopback("127.0.0.2")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5") and not is_loopback("example.org")


def test_port_zero_picks_a_free_port_and_a_taken_one_is_refused() -> None:
    port = resolve_port("127.0.0.1", 0)
    assert 0 < port < 65536
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        with pytest.raises(PortInUseError, match=rf"port {taken} on 127.0.0.1 is in use.*--port 0"):
            resolve_port("127.0.0.1", taken)
    assert issubclass(PortInUseError, InputError)
