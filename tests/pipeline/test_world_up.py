"""``reconstruct --up auto``: one world rotation putting the cameras' mean up on +y, applied alike to the Gaussians
(means, orientations, view-dependent colour), the cameras and the points, so that every view renders the same."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.cameras import Camera, CameraSet, load_cameras
from macsplat_cli.pipeline.world_up import rotate_cameras, rotate_gaussians, up_rotation
from macsplat_cli.ply import read_ply
from macsplat_cli.render import render_camera
from macsplat_cli.rotations import quat_to_rotmat_np

from support.cli import run_cli
from support.gaussians import random_gaussians
from support.scenes import PairFactory, PairSpec


def _camera(R_c2w: np.ndarray, centre: np.ndarray, name: str = "c") -> Camera:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_c2w, centre
    return Camera(name, 96, 64, np.array([[80.0, 0, 48], [0, 80, 32], [0, 0, 1]]), T)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_up_rotation_puts_the_mean_up_on_plus_y(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tilt = quat_to_rotmat_np(np.r_[1.0, rng.normal(scale=0.3, size=3)])  # cameras about one tilted up
    cams = CameraSet([_camera(tilt @ quat_to_rotmat_np(np.r_[1.0, 0, rng.normal(scale=0.3), 0]), rng.normal(size=3),
                              f"c{k}") for k in range(4)])  # fmt: skip
    R = up_rotation(cams)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    up = -np.mean([c.cam_to_world[:3, 1] for c in rotate_cameras(cams, R)], axis=0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 1, 0], atol=1e-12)
    # the world of a single OpenCV camera (up = −y) is turned half a turn
    np.testing.assert_allclose(up_rotation(CameraSet([_camera(np.eye(3), np.zeros(3))])) @ [0, -1, 0], [0, 1, 0])


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_turned_scene_and_camera_render_the_same(sh_degree: int) -> None:
    g = random_gaussians(300, seed=sh_degree, sh_degree=sh_degree, dtype=torch.float64)
    cam = _camera(quat_to_rotmat_np(np.array([1.0, 0.1, -0.2, 0.05])), np.array([0.2, -0.1, -0.5]))
    R = quat_to_rotmat_np(np.array([0.3, -0.8, 0.4, 0.2]))
    turned = rotate_cameras(CameraSet([cam]), R)[0]
    a = render_camera(g, cam).rgb
    b = render_camera(rotate_gaussians(g, R), turned).rgb
    assert float(a.abs().max()) > 0.1
    torch.testing.assert_close(b, a, atol=1e-9, rtol=0)


def test_up_auto_in_the_cli_turns_the_scene_and_its_cameras_alike(pair_files: PairFactory, tmp_path: Path) -> None:
    pair = pair_files(PairSpec(size=(320, 240)))
    outs = {}
    for up in ("camera", "auto"):
        out = tmp_path / up
        code, _, err = run_cli(["reconstruct", *pair.photos, "-o", out / "s.ply", "--size", 320, "-q", "--up", up,
                                "--no-far-layer"])  # fmt: skip
        assert code == 0, err
        outs[up] = (read_ply(out / "s.ply"), load_cameras(out / "s.cameras.json"))
    (g0, c0), (g1, c1) = outs["camera"], outs["auto"]
    R = c1[0].cam_to_world[:3, :3] @ c0[0].cam_to_world[:3, :3].T  # the one world rotation
    for a, b in zip(c0, c1):
        np.testing.assert_allclose(b.cam_to_world[:3, :3], R @ a.cam_to_world[:3, :3], atol=1e-9)
        np.testing.assert_allclose(b.center, R @ a.center, atol=1e-9)
    up = -np.mean([c.cam_to_world[:3, 1] for c in c1], axis=0)
    assert up[1] / np.linalg.norm(up) == pytest.approx(1.0)
    torch.testing.assert_close(g1.means.double(), g0.means.double() @ torch.as_tensor(R).T, atol=1e-5, rtol=1e-5)
    assert json.loads((tmp_path / "camera" / "s.cameras.json").read_text())["world"] == "camera_0"
    assert c1.world == "camera_0_up_y"  # the file names the frame it is in
