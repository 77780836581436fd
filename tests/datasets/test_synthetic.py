"""Synthetic two-view scenes: exact depth, photo-consistency, camera pairs, poses, datasets."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from macsplat_cli.cameras import Camera, load_cameras
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.datasets.synthetic import planar
from macsplat_cli.errors import InputError
from macsplat_cli.images import to_uint8

FLAT = S.Texture(albedo=(0.2, 0.4, 0.6), textured=False)
U32, U64 = np.finfo(np.float32).eps / 2, np.finfo(np.float64).eps / 2
# The ray caster works in float64 and stores depth, normals and colours as float32. A float64 ray cast, camera or
# rotation is ≲ 30 operations on its coordinates with no catastrophic cancellation (a ray–plane or ray–sphere
# intersection at ≥ 20° incidence, unit vectors from normalisations, atan2 angles): within F64 = 64u of the largest
# coordinate involved, relative, so a stored float32 value is within u32 + F64 of the exact one.
F64 = 64 * U64


def _f32(x: float) -> float:
    """Bound on a float32-stored value |x| computed in float64: one rounding plus the float64 budget."""
    return (U32 + F64) * abs(x)


def _deg(rad: float) -> float:
    return math.degrees(rad)


@pytest.fixture(scope="module")
def room() -> S.Scene:
    return S.room_scene(0)


@pytest.fixture(scope="module")
def obj() -> S.Scene:
    return S.object_scene(0)


def _camera(width: int = 65, height: int = 49, fov_deg: float = 60.0, cam_to_world: np.ndarray | None = None) -> Camera:
    T = np.eye(4) if cam_to_world is None else cam_to_world
    return Camera("c", width, height, S.intrinsics(width, height, fov_deg), T)


def _pixel_rays(cam: Camera) -> np.ndarray:
    """Camera-space rays (x, y, 1) through every pixel centre. [H, W, 3]"""
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([jj, ii, np.ones_like(jj)], -1)
    return pix @ np.linalg.inv(cam.K).T


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def _rot_angle_deg(R: np.ndarray) -> float:
    return S.pose_errors(R, np.ones(3), np.eye(3), np.ones(3))[0]


def _sift_count(image: np.ndarray) -> int:
    gray = cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2GRAY)
    return len(cv2.SIFT_create().detect(gray, None))


# ------------------------------------------------------------------------------------ exact geometry
def test_fronto_parallel_wall_depth_is_constant_and_colour_is_albedo() -> None:
    wall = S.Quad((-10.0, -10.0, 3.0), (20.0, 0.0, 0.0), (0.0, 20.0, 0.0), FLAT)
    scene = S.Scene([wall], lighting=None)
    view = S.render(scene, _camera())
    assert view.depth.shape == (49, 65) and view.depth.dtype == np.float32
    assert view.depth[24, 32] == pytest.approx(3.0, rel=0, abs=_f32(3.0))  # the centre pixel
    for i, j in [(0, 0), (0, 64), (48, 0), (48, 64)]:  # corners: still z = 3 on a fronto-parallel wall
        assert view.depth[i, j] == pytest.approx(3.0, rel=0, abs=_f32(3.0))
    np.testing.assert_allclose(view.normals.reshape(-1, 3), np.tile([0.0, 0.0, -1.0], (65 * 49, 1)), rtol=0,
                               atol=_f32(1.0))  # fmt: skip
    # unlit, untextured: the albedo, averaged over the supersamples (equal values) and stored: ≤ u32 + F64
    np.testing.assert_allclose(view.image, np.broadcast_to(FLAT.albedo, view.image.shape), rtol=0, atol=_f32(1.0))


def test_tilted_plane_depth_matches_analytic_everywhere() -> None:
    # plane through (0, 0, 4) with normal n: depth at ray r = (x, y, 1) is (n·p0) / (n·r)
    n = np.array([0.3, -0.2, 1.0])
    n /= np.linalg.norm(n)
    p0 = np.array([0.0, 0.0, 4.0])
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    quad = S.Quad(p0 - 20 * e1 - 20 * e2, 40 * e1, 40 * e2, FLAT)
    cam = _camera(fov_deg=70.0)
    view = S.render(S.Scene([quad]), cam)
    rays = _pixel_rays(cam)
    expected = (n @ p0) / (rays @ n)
    # the renderer's and the test's float64 rays (F64 each, amplified by 1/cos of the incidence ≤ 2 here: the plane
    # is tilted ~21°, the rays ≤ 35° off axis) and one float32 rounding
    np.testing.assert_allclose(view.depth, expected, rtol=U32 + 2 * 2 * F64, atol=0)


def test_sphere_and_box_depths_at_the_centre_pixel() -> None:
    cam = _camera()
    sphere = S.Scene([S.Sphere((0.0, 0.0, 5.0), 1.0, texture=FLAT)])
    # b − √(b² − c) with b² = 25, b² − c = 1: the cancellation costs 25u in b² − c (12.5u in the root, of 1)
    assert S.render(sphere, cam).depth[24, 32] == pytest.approx(4.0, rel=0, abs=_f32(5.0))
    # a box turned 45° about y shows an edge at distance 5 − √2
    box = S.Scene([S.Box((0.0, 0.0, 5.0), (1.0, 1.0, 1.0), S.rotation_about((0, 1, 0), 45.0), FLAT)])
    view = S.render(box, cam)
    # the centre pixel's centre lies on the edge exactly (principal point 32.5): depth 5 − √2 up to rounding
    assert view.depth[24, 32] == pytest.approx(5.0 - math.sqrt(2.0), rel=0, abs=_f32(5.0))
    # from inside a box (a room): the far wall
    inside = S.Scene([S.Box((0.0, 0.0, 0.0), (5.0, 5.0, 2.0), None, FLAT)])
    view = S.render(inside, cam)
    assert view.depth[24, 32] == pytest.approx(2.0, rel=0, abs=_f32(2.0))
    assert (view.depth > 0).all()  # closed: every ray hits
    np.testing.assert_array_equal(view.normals[24, 32], [0.0, 0.0, -1.0])  # an axis-aligned face: exact


def test_nearest_surface_wins_and_misses_have_zero_depth() -> None:
    wall = S.Quad((-1.0, -1.0, 6.0), (2.0, 0.0, 0.0), (0.0, 2.0, 0.0), FLAT)  # covers the centre only
    ball = S.Sphere((0.0, 0.0, 4.0), 0.5, texture=S.Texture((1.0, 0.0, 0.0), textured=False))
    view = S.render(S.Scene([wall, ball], lighting=None, background=(0.0, 1.0, 0.0)), _camera())
    assert view.depth[24, 32] == pytest.approx(3.5, rel=0, abs=_f32(4.0))
    np.testing.assert_allclose(view.image[24, 32], [1.0, 0.0, 0.0], rtol=0, atol=_f32(1.0))
    assert view.depth[0, 0] == 0.0 and not view.mask[0, 0]
    np.testing.assert_allclose(view.image[0, 0], [0.0, 1.0, 0.0], rtol=0, atol=_f32(1.0))


def test_shading_depends_on_the_normal_not_on_the_view() -> None:
    light = S.Lighting(direction=(0.0, -1.0, 0.0), ambient=0.3, diffuse=0.7)
    floor = S.Quad((-5.0, 1.0, -5.0), (10.0, 0.0, 0.0), (0.0, 0.0, 10.0), FLAT)  # front normal −y: lit
    wall = S.Quad((-5.0, -5.0, 3.0), (10.0, 0.0, 0.0), (0.0, 10.0, 0.0), FLAT)  # normal −z: ambient only
    scene = S.Scene([floor, wall], lighting=light)
    hits = S.cast_rays(scene, _camera(), np.array([[32.5, 48.0], [32.5, 10.0]]))
    assert hits.primitive.tolist() == [0, 1]
    # float32 albedo times a float64 shade (0.3 + 0.7·cos), stored: the albedo's own float32 rounding (the test's
    # is float64), the product's, and F64 of the shade
    np.testing.assert_allclose(hits.color[0], np.array(FLAT.albedo) * 1.0, rtol=0, atol=2 * _f32(1.0))
    np.testing.assert_allclose(hits.color[1], np.array(FLAT.albedo) * 0.3, rtol=0, atol=2 * _f32(1.0))
    # the same floor point seen from another camera has the same colour
    point = hits.points[0]
    other = S.look_at_camera("o", (2.0, -1.0, -1.0), point, width=65, height=49)
    hit2 = S.cast_rays(scene, other, np.array([[32.5, 24.5]]))
    # the look-at camera and its ray (F64 of the ~4 m geometry), hitting the floor at ≥ 30° (×2)
    np.testing.assert_allclose(hit2.points[0], point, rtol=0, atol=2 * F64 * 4.0)
    np.testing.assert_allclose(hit2.color[0], hits.color[0], rtol=0, atol=2 * _f32(1.0))  # the same shading


def test_room_floor_normals_and_depth_are_consistent(room: S.Scene) -> None:
    cam, _ = S.orbit_pair("room", 0.0, width=128, height=96)
    view = S.render(room, cam, supersample=1)
    assert view.mask.all()  # the room is closed
    world = view.depth[..., None] * _pixel_rays(cam) @ cam.cam_to_world[:3, :3].T + cam.center
    # float32-stored unit normals (u32 per component) and the test's float32 norm (γ₃/2 + u32)
    np.testing.assert_allclose(np.linalg.norm(view.normals, axis=-1), 1.0, rtol=0, atol=4 * U32 + F64)
    floor = np.abs(world[..., 1] - 1.5) < 1e-4  # y = +1.5: the floor
    assert floor.mean() > 0.1
    np.testing.assert_allclose(view.normals[floor], np.tile([0.0, -1.0, 0.0], (int(floor.sum()), 1)), rtol=0,
                               atol=_f32(1.0))  # fmt: skip
    # the room's quads face inwards: the lit floor is brighter than its albedo times the ambient term
    assert room.primitives[0].bounding_sphere()[0][1] == pytest.approx(1.5, rel=0, abs=F64 * 6.0)
    np.testing.assert_allclose(room.primitives[0]._cache["normal"], [0.0, -1.0, 0.0], rtol=0, atol=F64)
    assert 1.0 < view.depth.min() and view.depth.max() < 8.0  # inside a 6 m room, no object on the camera


# ------------------------------------------------------------------------------------ photo-consistency
def _reprojection_colours(v0: S.SyntheticView, v1: S.SyntheticView) -> tuple[np.ndarray, np.ndarray]:
    """Colours of view 0's pixels and of the same surface points in view 1 (where visible in both). [M, 3] each"""
    c0, c1 = v0.camera, v1.camera
    m = v0.mask
    X0 = v0.depth[m][:, None].astype(np.float64) * _pixel_rays(c0)[m]
    Xw = X0 @ c0.cam_to_world[:3, :3].T + c0.center
    X1 = Xw @ c1.R.T + c1.t
    uv = X1 @ c1.K.T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    H, W = v1.depth.shape
    ok = (X1[:, 2] > 0) & (u >= 1) & (u <= W - 1) & (v >= 1) & (v <= H - 1)
    d1 = v1.depth[np.clip(v.astype(int), 0, H - 1), np.clip(u.astype(int), 0, W - 1)]
    ok &= np.abs(d1 - X1[:, 2]) < 0.01 * X1[:, 2]  # depth test: not occluded in view 1
    map_x = np.full((H, W), -10.0, dtype=np.float32)
    map_y = np.full((H, W), -10.0, dtype=np.float32)
    map_x[m], map_y[m] = u - 0.5, v - 0.5  # continuous coordinates → array indices
    warped = cv2.remap(v1.image, map_x, map_y, cv2.INTER_LINEAR)
    return v0.image[m][ok], warped[m][ok]


@pytest.mark.parametrize(
    ("kind", "pair", "min_overlap"),
    [("room", "orbit30", 0.4), ("object", "orbit90", 0.2), ("room", "forward", 0.4)],
)
def test_photo_consistency_between_views(kind: str, pair: str, min_overlap: float, room: S.Scene, obj: S.Scene) -> None:
    scene = room if kind == "room" else obj
    if pair == "forward":
        c0, c1 = S.forward_pair(kind, seed=3, width=320, height=240)
    else:
        c0, c1 = S.orbit_pair(kind, float(pair.removeprefix("orbit")), seed=3, width=320, height=240)
    v0, v1 = S.render(scene, c0), S.render(scene, c1)
    col0, col1 = _reprojection_colours(v0, v1)
    assert len(col0) > min_overlap * v0.mask.sum()
    diff = np.abs(col0 - col1).mean(1)
    assert np.median(diff) < 0.03
    assert np.mean(diff < 0.1) > 0.9
    # and it is a real test: with a wrong pose for view 1 (5 cm to the side) the colours disagree
    T = c1.cam_to_world.copy()
    T[:3, 3] += 0.05 * T[:3, 0]
    wrong = dataclasses.replace(S.render(scene, c1.with_pose(T)), camera=c1)
    col0w, col1w = _reprojection_colours(v0, wrong)
    assert np.median(np.abs(col0w - col1w).mean(1)) > 3 * np.median(diff)


def test_transfer_points_gives_exact_correspondences(room: S.Scene) -> None:
    c0, c1 = S.orbit_pair("room", 20.0, width=160, height=120, seed=5)
    rng = np.random.default_rng(0)
    pix0 = rng.uniform([0, 0], [160, 120], (400, 2))
    pix1, visible = S.transfer_points(room, c0, c1, pix0)
    assert 0.3 < visible.mean() < 1.0  # some points leave the image or are hidden
    # the rays through pix0 and pix1 meet at the same surface point
    h0 = S.cast_rays(room, c0, pix0[visible])
    h1 = S.cast_rays(room, c1, pix1[visible])
    # pix1 is the float64 projection of h0's point, re-cast from c1: float64 all the way (F64 of the ~6 m room),
    # but a grazing surface amplifies a ray's rounding by 1/cos of the incidence, which random pixels do not bound
    # a priori: 1e-9 allows incidences up to 89.99° (measured: 1.3e-14 m, and 5.3e-13 px back)
    np.testing.assert_allclose(h0.points, h1.points, rtol=0, atol=1e-9)
    assert (h0.primitive == h1.primitive).all()
    # transferring back returns the start
    back, vis_back = S.transfer_points(room, c1, c0, pix1[visible])
    assert vis_back.all()
    np.testing.assert_allclose(back, pix0[visible], rtol=0, atol=1e-9 * 400)  # the same, times ≤ 400 px per metre


# ------------------------------------------------------------------------------------ determinism, texture
def test_same_seed_same_images_different_seed_different(room: S.Scene) -> None:
    cam, _ = S.orbit_pair("room", 0.0, width=96, height=72, seed=0)
    a = S.render(room, cam)
    b = S.render(S.room_scene(0), cam)  # a fresh scene: textures rasterised again
    assert np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)
    c = S.render(S.room_scene(1, textured=False), cam)
    assert not np.array_equal(a.depth, c.depth)
    assert S.orbit_pair("object", 30.0, seed=4)[1] == S.orbit_pair("object", 30.0, seed=4)[1]
    assert S.orbit_pair("object", 30.0, seed=4)[1] != S.orbit_pair("object", 30.0, seed=5)[1]


def test_textured_views_have_many_sift_features_textureless_few(room: S.Scene, obj: S.Scene) -> None:
    for kind, scene in (("room", room), ("object", obj)):
        c0, _ = S.orbit_pair(kind, 0.0, seed=0)
        textured = _sift_count(S.render(scene, c0).image)
        flat = _sift_count(S.render(S.make_scene(kind, 0, textured=False), c0).image)
        assert textured >= 500, (kind, textured)
        # flat colours leave only silhouette edges, corners and shading blobs (30–90 keypoints)
        assert flat < 100 and flat < 0.1 * textured, (kind, flat, textured)


def test_render_512x384_gives_a_float_image_in_range(room: S.Scene) -> None:
    """Rendering twice (the textures are rasterised on first use) gives the same float32 image in [0, 1]. Its speed
    is no test's business (a loaded machine fails any bound): ``benchmarks/`` times things."""
    cam, _ = S.orbit_pair("room", 30.0)
    first = S.render(room, cam)
    view = S.render(room, cam)
    assert view.image.shape == (384, 512, 3) and view.image.dtype == np.float32
    assert 0.0 <= view.image.min() and view.image.max() <= 1.0
    assert np.array_equal(first.image, view.image)


def test_supersampling_keeps_centre_depth_and_smooths_colour(obj: S.Scene) -> None:
    cam, _ = S.orbit_pair("object", 0.0, width=96, height=72)
    v1 = S.render(obj, cam, supersample=1)
    v3 = S.render(obj, cam, supersample=3)
    assert np.array_equal(v1.depth, v3.depth)
    assert np.abs(v1.image - v3.image).mean() < 0.1
    assert np.abs(np.diff(v3.image, axis=1)).mean() < np.abs(np.diff(v1.image, axis=1)).mean()
    with pytest.raises(InputError):
        S.render(obj, cam, supersample=0)


# ------------------------------------------------------------------------------------ camera pairs, poses
@pytest.mark.parametrize("kind", ["room", "object"])
@pytest.mark.parametrize("angle", [2.0, 10.0, 30.0, 60.0, 90.0])
def test_orbit_pair_angle_between_optical_axes(kind: str, angle: float) -> None:
    target = S.make_scene(kind, 0).target
    for seed in (0, 1):
        c0, c1 = S.orbit_pair(kind, angle, seed=seed)
        z0, z1 = c0.cam_to_world[:3, 2], c1.cam_to_world[:3, 2]
        # atan2 angles of F64-accurate unit vectors: ≤ 2·F64 rad
        assert _angle_deg(z0, z1) == pytest.approx(angle, rel=0, abs=_deg(2 * F64))
        for cam in (c0, c1):  # both look at the target, from the scene's distance ±5%
            to_target = target - cam.center
            assert _angle_deg(cam.cam_to_world[:3, 2], to_target) <= _deg(2 * F64)
            assert cam.K[0, 2] == 256 and cam.K[1, 2] == 192
            assert cam.K[0, 0] == pytest.approx(256 / math.tan(math.radians(30)), rel=4 * U64, abs=0)
        # the baseline closes the triangle with the target (law of cosines): squares of distances ≤ d² with F64
        # relative error each (twice, squared), and the cancelling sum
        d0, d1 = (float(np.linalg.norm(target - c.center)) for c in (c0, c1))
        baseline = float(np.linalg.norm(c1.center - c0.center))
        law = d0**2 + d1**2 - 2 * d0 * d1 * math.cos(math.radians(angle))
        assert baseline**2 == pytest.approx(law, rel=0, abs=4 * 2 * F64 * (d0 + d1) ** 2)
        assert 0.95 * S.make_scene(kind).view_distance <= d0 <= 1.05 * S.make_scene(kind).view_distance
        # roll jitter: the relative rotation turns more than the optical axis alone
        R, _ = S.relative_pose(c0, c1)
        assert _rot_angle_deg(R) > angle + 1e-3


def test_orbit_pair_without_jitter_is_a_turn_about_the_vertical() -> None:
    c0, c1 = S.orbit_pair("room", 40.0, jitter=False)
    assert c0.center[1] == pytest.approx(c1.center[1], rel=0, abs=2 * F64 * float(np.abs(c0.center).max()))
    R_world = c1.cam_to_world[:3, :3] @ c0.cam_to_world[:3, :3].T
    axis = np.array([R_world[2, 1] - R_world[1, 2], R_world[0, 2] - R_world[2, 0], R_world[1, 0] - R_world[0, 1]])
    # about the vertical (y) axis: the axis's entries are differences of entries ≤ 1 (F64 each) of a ≥ 2 sin 40°
    # long vector
    assert _angle_deg(np.abs(axis), [0.0, 1.0, 0.0]) <= _deg(4 * F64 / (2 * math.sin(math.radians(40))))
    with pytest.raises(InputError):
        S.orbit_pair("room", 175.0)
    with pytest.raises(InputError):
        S.orbit_pair("garage", 10.0)  # type: ignore[arg-type]


def test_forward_pair_moves_along_the_optical_axis() -> None:
    for kind in ("room", "object"):
        c0, c1 = S.forward_pair(kind, forward=0.3, rotation_deg=4.0, seed=2)
        R, t = S.relative_pose(c0, c1)
        centre1_in_cam0 = -R.T @ t
        assert _angle_deg(centre1_in_cam0, [0.0, 0.0, 1.0]) < 8.0  # mostly forward
        target = S.make_scene(kind).target
        dist = np.linalg.norm(target - c0.center)
        assert np.linalg.norm(t) == pytest.approx(0.3 * dist, rel=0.02)  # (d) the pair's ±2 % distance jitter
        assert _rot_angle_deg(R) == pytest.approx(4.0, rel=0, abs=_deg(4 * F64))  # atan2 of F64-accurate entries


def test_pure_rotation_pair_has_zero_baseline() -> None:
    c0, c1 = S.pure_rotation_pair("room", 15.0, seed=1)
    R, t = S.relative_pose(c0, c1)
    # t = R1·(c0 − c1)-like: the same centre twice, so only roundings of the ≤ 6 m coordinates survive
    assert np.linalg.norm(t) <= F64 * 6.0
    assert _rot_angle_deg(R) == pytest.approx(15.0, rel=0, abs=_deg(4 * F64))
    rot_err, trans_err = S.pose_errors(R, t * 0, R, np.array([1.0, 0.0, 0.0]))
    assert rot_err == pytest.approx(0.0, rel=0, abs=_deg(4 * F64)) and math.isnan(trans_err)


def test_relative_pose_maps_points_between_camera_frames() -> None:
    c0, c1 = S.orbit_pair("object", 35.0, seed=7)
    R, t = S.relative_pose(c0, c1)
    np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=2 * F64)
    assert np.linalg.det(R) == pytest.approx(1.0, rel=0, abs=3 * F64)
    X = np.random.default_rng(1).normal(size=(20, 3))
    X0 = X @ c0.R.T + c0.t
    X1 = X @ c1.R.T + c1.t
    scale = float(np.abs(X0).max() + np.abs(t).max())
    np.testing.assert_allclose(X0 @ R.T + t, X1, rtol=0, atol=4 * F64 * scale)  # coordinates ≤ scale
    # epipolar constraint with E = [t]x R on the projections: 9-term sums of products ≤ |x1||t||x0|, each F64
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    x0, x1 = X0 / X0[:, 2:], X1 / X1[:, 2:]
    eps_scale = 9 * float(np.abs(x0).max() * np.abs(x1).max() * np.abs(t).max())
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", x1, tx @ R, x0), 0.0, rtol=0, atol=4 * F64 * eps_scale)
    R_id, t_id = S.relative_pose(c0, c0)
    np.testing.assert_allclose(R_id, np.eye(3), rtol=0, atol=2 * F64)
    np.testing.assert_allclose(t_id, 0.0, rtol=0, atol=2 * F64 * float(np.abs(c0.center).max()))


def test_pose_errors_known_values() -> None:
    R = S.rotation_about((1.0, 2.0, 3.0), 25.0)
    t = np.array([0.3, -0.1, 1.0])
    # atan2 angles (sine and cosine both read off the operands): ≤ 4·F64 rad
    tol = dict(rel=0, abs=_deg(4 * F64))
    assert S.pose_errors(R, t, R, t) == pytest.approx((0.0, 0.0), **tol)
    assert S.pose_errors(R, 5 * t, R, t)[1] == pytest.approx(0.0, **tol)  # scale does not matter
    assert S.pose_errors(R, -t, R, t)[1] == pytest.approx(180.0, **tol)  # the sign does
    assert S.pose_errors(R @ S.rotation_about((0, 1, 0), 10.0), t, R, t)[0] == pytest.approx(10.0, **tol)
    assert S.pose_errors(np.eye(3), [1, 0, 0], S.rotation_about((0, 0, 1), 180.0), [0, 1, 0]) == pytest.approx(
        (180.0, 90.0), **tol
    )


@settings(max_examples=40, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda a: np.linalg.norm(a) > 0.1),
    angle=st.floats(0.0, 179.0),
)
def test_rotation_about_has_the_requested_angle(axis: tuple[float, float, float], angle: float) -> None:
    R = S.rotation_about(axis, angle)
    # Rodrigues in float64 from a normalised axis: entries within F64 of a rotation's
    np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=2 * F64)
    np.testing.assert_allclose(R @ np.asarray(axis), np.asarray(axis), rtol=0, atol=2 * F64 * float(np.abs(axis).sum()))
    assert _rot_angle_deg(R) == pytest.approx(angle, rel=0, abs=_deg(4 * F64))


# ------------------------------------------------------------------------------------ datasets
def test_write_dataset_round_trips(tmp_path, obj: S.Scene) -> None:  # noqa: ANN001
    cams = S.orbit_cameras("object", [-20.0, 0.0, 20.0], width=80, height=60, names=["a", "b", "c"])
    views = S.write_dataset(tmp_path / "ds", obj, cams)
    cam_set = load_cameras(tmp_path / "ds" / "cameras.json")
    assert cam_set.scale == "metric" and cam_set.world == "world"
    assert [c.name for c in cam_set] == ["a", "b", "c"]
    for cam, view in zip(cam_set, views):
        assert cam == view.camera
        img = cv2.imread(str(tmp_path / "ds" / "images" / f"{cam.name}.png"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(img[..., ::-1], to_uint8(view.image))
        depth = cv2.imread(str(tmp_path / "ds" / "depth" / f"{cam.name}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        # depth in whole millimetres: ≤ 0.5 mm rounding, plus the float32 depth's own rounding (≤ u32·8 m)
        np.testing.assert_allclose(depth / 1000.0, view.depth, rtol=0, atol=5e-4 + U32 * 8.0)
    S.write_dataset(tmp_path / "nodepth", obj, cams[:1], depth=False)
    assert not (tmp_path / "nodepth" / "depth").exists()
    assert (tmp_path / "nodepth" / "images" / "a.png").is_file()


def test_invalid_inputs_raise_input_error() -> None:
    with pytest.raises(InputError):
        S.make_scene("garage")  # type: ignore[arg-type]
    with pytest.raises(InputError):
        S.Quad((0, 0, 0), (1, 0, 0), (2, 0, 0))
    with pytest.raises(InputError):
        S.Sphere((0, 0, 0), -1.0)
    with pytest.raises(InputError):
        S.Box((0, 0, 0), (1, 0, 1))
    with pytest.raises(InputError):
        S.intrinsics(64, 48, 180.0)


# ------------------------------------------------------------------------------------------------ planar cases
def test_planar_cases_are_plain_arrays_from_below_the_pipeline() -> None:
    """The planar stress cases come as ``planar.PlanarMatches`` (the data sets build no pipeline type): the original
    family has no sub-gate matches, a table-top with objects has; every match lies on both images (to the noise);
    importing the module loads nothing of the pipeline."""
    plain, R, t = planar.planar_case(0, None)
    assert isinstance(plain, planar.PlanarMatches) and plain.below_gate is None
    assert plain.xy0.shape == plain.xy1.shape == (200, 2) and plain.xy0.dtype == np.float64
    assert R.shape == (3, 3) and t.shape == (3,)
    table, _, _ = planar.planar_case(8, 0.05, "table")
    assert isinstance(table.below_gate, planar.PlanarMatches) and len(table.below_gate.xy0) >= 300
    for xy in (plain.xy0, plain.xy1):
        assert np.all((xy > -2) & (xy < (planar.W + 2, planar.H + 2)))  # projected inside, then 0.3 px of noise
    code = (
        "import sys; import macsplat_cli.datasets.synthetic.planar; "
        "sys.exit(any(m.startswith('macsplat_cli.pipeline') for m in sys.modules))"
    )
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_a_rebuilt_scene_rasterises_its_textures_once_within_the_shared_budget(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from macsplat_cli.datasets.synthetic import textures

    calls: list[int] = []
    real = textures._texture_image
    monkeypatch.setattr(textures, "_texture_image", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(textures, "_SHARED", type(textures._SHARED)())
    tex = S.Texture(albedo=(0.5, 0.4, 0.3), seed=123)

    def wall(z: float) -> np.ndarray:  # the same surface built anew each time: its own per-primitive cache
        return S.render(
            S.Scene([S.Quad((-1.0, -1.0, z), (2.0, 0.0, 0.0), (0.0, 2.0, 0.0), tex)], None), _camera()
        ).image

    first, again = wall(3.0), wall(3.0)
    assert len(calls) == 1 and np.array_equal(first, again)
    ((img, _),) = textures._SHARED.values()
    assert not img.flags.writeable  # shared: no caller can change another scene's texture
    monkeypatch.setattr(textures, "SHARED_CACHE_BYTES", img.nbytes + 1)  # room for one: the older one goes
    wall2 = S.Quad((-1.0, -1.0, 3.0), (2.0, 0.0, 0.0), (0.0, 3.0, 0.0), tex)  # another size: another texture
    S.render(S.Scene([wall2], None), _camera())
    assert len(calls) == 2 and len(textures._SHARED) == 1
    assert next(iter(textures._SHARED))[2] == 3.0
