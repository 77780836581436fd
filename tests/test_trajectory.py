"""Camera paths between cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest

from macsplat_cli.cameras import Camera, quat_to_rotmat_np, rotmat_to_quat_np
from macsplat_cli.errors import InputError
from macsplat_cli.trajectory import interpolate_cameras, slerp

from support.numerics import ROT_MAT, ROT_QUAT, ROT_ROUND_TRIP

U = np.finfo(np.float64).eps / 2
# float64 budgets (ROT_*: tests/test_rotations.py): a camera at a key frame is its rotation's R → q → R round trip;
# a slerp between them adds ≤ 8u to q (θ = acos of a dot ≤ cos 30°-conditioned, two sines and their quotients);
# a rotation built from cos/sin of a known angle is ROT_MAT off a rotation
KEY = ROT_ROUND_TRIP * U
SLERPED = (2 * math.sqrt(2) * 2 * (ROT_QUAT + 8) + 2 * ROT_MAT) * U  # against a rotation built directly


def _step_tol_deg(step_deg: float) -> float:
    """Bound on _angle's error between two interpolated rotations: tr(R1ᵀR2) is 9 products of entries each ≤ SLERPED
    off (≤ 6·SLERPED) plus γ₉·3, and acos amplifies by 1/sin θ."""
    return math.degrees((6 * SLERPED + 27 * U) / math.sin(math.radians(step_deg)))


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    h = math.radians(deg) / 2
    return quat_to_rotmat_np(np.array([math.cos(h), *(math.sin(h) * axis)]))


def _cam(name: str, R: np.ndarray, c: np.ndarray, f: float = 100.0, w: int = 64, h: int = 48) -> Camera:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c
    return Camera(name, w, h, np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]), T)


def _angle(R1: np.ndarray, R2: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R1.T @ R2) - 1) / 2, -1, 1)))


def test_endpoints_and_constant_speed() -> None:
    axis = np.array([0.2, 1.0, 0.1])
    a = _cam("a", np.eye(3), np.zeros(3))
    b = _cam("b", _rot(axis, 60.0), np.array([1.0, 0.0, 0.5]))
    path = interpolate_cameras([a, b], 7)
    assert [c.name for c in path] == [f"path_{i:04d}" for i in range(7)]
    # the key frames: a rotation round trip; centres (1 − u)·c0 + u·c1 with u ∈ {0, 1} are exact
    np.testing.assert_allclose(path[0].cam_to_world, a.cam_to_world, rtol=0, atol=KEY)
    np.testing.assert_allclose(path[-1].cam_to_world, b.cam_to_world, rtol=0, atol=KEY)
    # slerp: equal angular steps about one axis; lerp: equal steps of the centre
    steps = [_angle(p.cam_to_world[:3, :3], q.cam_to_world[:3, :3]) for p, q in zip(path, path[1:])]
    np.testing.assert_allclose(steps, 10.0, rtol=0, atol=_step_tol_deg(10.0))
    np.testing.assert_array_equal(path[3].center, [0.5, 0.0, 0.25])  # u = 1/2: halves and sums are exact here
    mid = path[3].cam_to_world[:3, :3]
    np.testing.assert_allclose(mid, _rot(axis, 30.0), rtol=0, atol=SLERPED)


def test_takes_the_short_arc_and_passes_through_middle_cameras() -> None:
    a = _cam("a", np.eye(3), np.zeros(3))
    b = _cam("b", _rot(np.array([0, 1.0, 0]), 170.0), np.array([1.0, 0, 0]))
    c = _cam("c", _rot(np.array([0, 1.0, 0]), -170.0), np.array([2.0, 0, 0]))  # 20° further across ±180°
    path = interpolate_cameras([a, b, c], 5)
    np.testing.assert_allclose(path[2].cam_to_world, b.cam_to_world, rtol=0, atol=KEY)
    step = _angle(path[2].cam_to_world[:3, :3], path[3].cam_to_world[:3, :3])
    assert step == pytest.approx(10.0, rel=0, abs=_step_tol_deg(10.0))


def test_mixed_sizes_are_rescaled_and_intrinsics_interpolated() -> None:
    a = _cam("a", np.eye(3), np.zeros(3), f=100.0, w=64, h=48)
    b = _cam("b", np.eye(3), np.ones(3), f=400.0, w=128, h=96)  # f=200 at 64x48
    path = interpolate_cameras([a, b], 3)
    assert all((p.width, p.height) == (64, 48) for p in path)
    # every focal, scale factor and weight here is a binary-exact fraction: the interpolation is exact
    assert path[1].K[0, 0] == 150.0
    path = interpolate_cameras([a, b], 2, width=32, height=24)
    assert path[1].K[0, 0] == 100.0 and path[1].K[0, 2] == 16.0


def test_slerp_matches_rotation_about_a_fixed_axis() -> None:
    q0 = rotmat_to_quat_np(np.eye(3))
    q1 = rotmat_to_quat_np(_rot(np.array([1.0, 0, 0]), 90))
    for u in (0.0, 0.25, 0.5, 1.0):
        R = quat_to_rotmat_np(slerp(q0, q1, u))
        np.testing.assert_allclose(R, _rot(np.array([1.0, 0, 0]), 90 * u), rtol=0, atol=SLERPED)
    # nearly identical quaternions: no 0/0
    q2 = rotmat_to_quat_np(_rot(np.array([1.0, 0, 0]), 1e-6))
    assert np.all(np.isfinite(slerp(q0, q2, 0.5)))


def test_bad_requests() -> None:
    a = _cam("a", np.eye(3), np.zeros(3))
    with pytest.raises(InputError, match="at least two cameras"):
        interpolate_cameras([a], 5)
    with pytest.raises(InputError, match="at least 1"):
        interpolate_cameras([a, a], 0)
