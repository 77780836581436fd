"""Multi-view triangulation (:mod:`macsplat_cli.pipeline.multiview.triangulate`) on synthetic tracks made here:
cameras on an arc around a box of points, each point seen by a random subset of 2 to all cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest

from macsplat_cli.errors import ShapeError
from macsplat_cli.pipeline.multiview.triangulate import project, reprojection_errors, triangulate_tracks

FOCAL = 700.0
RADIUS = 5.0


def _look_at(centre: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def _cameras(n: int, offset: np.ndarray | None = None, spread_deg: float = 90.0) -> tuple[np.ndarray, ...]:
    """``(R, t, K)`` of ``n`` cameras on an arc around ``offset`` (default the origin), looking at it."""
    o = np.zeros(3) if offset is None else offset
    angles = np.radians(np.linspace(-spread_deg / 2, spread_deg / 2, n))
    poses = [_look_at(o + RADIUS * np.array([math.sin(a), 0.3 * math.cos(2 * a), -math.cos(a)]), o) for a in angles]
    K = np.tile(np.array([[FOCAL, 0, 320.5], [0, FOCAL * 1.02, 240.5], [0, 0, 1.0]]), (n, 1, 1))
    return np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses]), K


def _tracks(rng: np.random.Generator, n_cams: int, n_points: int, least: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(cam_idx, point_idx)``: each point seen by ``least``..n_cams distinct cameras, the observations shuffled."""
    cams, pts = [], []
    for p in range(n_points):
        k = int(rng.integers(least, n_cams + 1))
        cams.append(rng.choice(n_cams, k, replace=False))
        pts.append(np.full(k, p))
    cam_idx, point_idx = np.concatenate(cams), np.concatenate(pts)
    order = rng.permutation(len(cam_idx))
    return cam_idx[order], point_idx[order]


def _observe(R, t, K, cam_idx, point_idx, X) -> np.ndarray:  # noqa: ANN001
    pix, _ = project(R, t, K, cam_idx, X[point_idx])
    return pix


@pytest.mark.parametrize("offset", [0.0, 1000.0])
def test_noise_free_tracks_are_exact(offset: float) -> None:
    """Exact pixels give the points to rounding, also a world 1000 radii from its origin (the normalisation)."""
    rng = np.random.default_rng(0)
    o = np.full(3, offset)
    R, t, K = _cameras(6, o)
    X = o + rng.uniform(-1.5, 1.5, (300, 3))
    cam_idx, point_idx = _tracks(rng, 6, 300)
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, _observe(R, t, K, cam_idx, point_idx, X), 300)
    np.testing.assert_allclose(tri.points, X, rtol=0, atol=1e-9 * max(RADIUS, offset))
    assert tri.ok.all()
    assert tri.reproj_error_px.max() < 1e-6
    np.testing.assert_array_equal(tri.n_obs, np.bincount(point_idx, minlength=300))


def test_a_point_behind_a_camera_is_flagged() -> None:
    """A point behind camera 0 (in front of camera 1) still projects in both; the DLT fits it exactly, the
    cheirality check refuses it."""
    R, t, K = _cameras(2, spread_deg=60.0)
    centre0 = -R[0].T @ t[0]
    X = np.stack([np.zeros(3), centre0 - 1.0 * R[0][2] + 0.3 * R[0][0]])  # one good point, one 1 unit behind camera 0
    cam_idx, point_idx = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    _, z = project(R, t, K, cam_idx, X[point_idx])
    assert z[2] < 0 < z[3]
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, _observe(R, t, K, cam_idx, point_idx, X), 2)
    np.testing.assert_allclose(tri.points, X, atol=1e-9)
    assert tri.reproj_error_px.max() < 1e-6 and tri.angle_deg[1] > 1.5
    np.testing.assert_array_equal(tri.ok, [True, False])


def test_a_small_angle_is_flagged_and_measured() -> None:
    """Two cameras 0.2 apart looking at points 5 and 20 away: the rays meet at atan(0.2 / 5) ≈ 2.3° and about a
    quarter of it."""
    R = np.tile(np.eye(3), (2, 1, 1))
    t = np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]])  # centres at x = ∓0.1
    K = np.tile(np.array([[FOCAL, 0, 320.5], [0, FOCAL, 240.5], [0, 0, 1.0]]), (2, 1, 1))
    X = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 20.0]])
    cam_idx, point_idx = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, _observe(R, t, K, cam_idx, point_idx, X), 2)
    expected = [2 * math.degrees(math.atan2(0.1, z)) for z in (5.0, 20.0)]
    np.testing.assert_allclose(tri.angle_deg, expected, rtol=1e-9)
    np.testing.assert_array_equal(tri.ok, [True, False])
    assert triangulate_tracks(
        R, t, K, cam_idx, point_idx, _observe(R, t, K, cam_idx, point_idx, X), 2, min_angle_deg=0.5
    ).ok.all()


def test_the_largest_pairwise_angle_is_exact() -> None:
    rng = np.random.default_rng(1)
    R, t, K = _cameras(7)
    X = rng.uniform(-1.5, 1.5, (60, 3))
    cam_idx, point_idx = _tracks(rng, 7, 60)
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, _observe(R, t, K, cam_idx, point_idx, X), 60)
    centres = -np.einsum("cji,cj->ci", R, t)
    for p in range(60):
        rays = X[p] - centres[cam_idx[point_idx == p]]
        pairs = [(a, b) for i, a in enumerate(rays) for b in rays[i + 1 :]]
        best = max(math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), a @ b)) for a, b in pairs)
        assert abs(tri.angle_deg[p] - best) < 1e-9


def test_the_error_threshold_flags_a_bad_observation() -> None:
    rng = np.random.default_rng(2)
    R, t, K = _cameras(5)
    X = rng.uniform(-1.5, 1.5, (40, 3))
    cam_idx, point_idx = _tracks(rng, 5, 40, least=4)  # two views would absorb a shift along the epipolar line
    xy = _observe(R, t, K, cam_idx, point_idx, X)
    moved = [int(np.flatnonzero(point_idx == p)[0]) for p in (3, 7)]
    xy[moved[0]] += [30.0, 0.0]  # a mismatch
    xy[moved[1]] += [0.0, 1.0]  # localisation noise
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, xy, 40)
    errors = reprojection_errors(R, t, K, tri.points, cam_idx, point_idx, xy)
    for p in range(40):
        assert tri.reproj_error_px[p] == pytest.approx(errors[point_idx == p].max(), rel=1e-12)
    assert tri.reproj_error_px[3] > 4.0 and not tri.ok[3]
    assert 0 < tri.reproj_error_px[7] < 4.0 and tri.ok[7]
    assert np.delete(tri.ok, [3]).all()
    assert triangulate_tracks(R, t, K, cam_idx, point_idx, xy, 40, max_error_px=1e9).ok.all()


def test_one_batch_equals_point_by_point() -> None:
    """Noisy tracks of 2..8 observations: the batched call gives what each point alone gives."""
    rng = np.random.default_rng(3)
    R, t, K = _cameras(8)
    X = rng.uniform(-1.5, 1.5, (50, 3))
    cam_idx, point_idx = _tracks(rng, 8, 50)
    xy = _observe(R, t, K, cam_idx, point_idx, X) + rng.normal(0, 1.0, (len(cam_idx), 2))
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, xy, 50)
    # 1 px at 700 px and depth ~5 moves a ray ~0.007 sideways; the depth error grows at small angles: the median
    # point is within a few of those (30 seeds: 0.0074 on average, 0.0093 at most)
    assert np.median(np.linalg.norm(tri.points - X, axis=1)) < 0.02
    for p in range(50):
        m = point_idx == p
        one = triangulate_tracks(R, t, K, cam_idx[m], np.zeros(int(m.sum()), int), xy[m], 1)
        np.testing.assert_allclose(one.points[0], tri.points[p], rtol=0, atol=1e-10)
        np.testing.assert_allclose(one.reproj_error_px[0], tri.reproj_error_px[p], rtol=1e-8)
        np.testing.assert_allclose(one.angle_deg[0], tri.angle_deg[p], rtol=1e-10)
        assert one.ok[0] == tri.ok[p] and one.n_obs[0] == tri.n_obs[p]


def test_undefined_points_and_bad_inputs() -> None:
    R, t, K = _cameras(3)
    X = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, -0.3]])
    cam_idx, point_idx = np.array([0, 1, 2]), np.array([0, 0, 1])  # point 1 seen once, point 2 never
    tri = triangulate_tracks(R, t, K, cam_idx, point_idx, _observe(R, t, K, cam_idx, point_idx, X), 3)
    np.testing.assert_array_equal(tri.n_obs, [2, 1, 0])
    np.testing.assert_array_equal(tri.ok, [True, False, False])
    assert np.isnan(tri.points[1:]).all() and np.isinf(tri.reproj_error_px[1:]).all()
    np.testing.assert_array_equal(tri.angle_deg[1:], 0.0)
    with pytest.raises(ShapeError):
        triangulate_tracks(R, t[:2], K, cam_idx, point_idx, np.zeros((3, 2)), 3)
    with pytest.raises(ValueError, match="point_idx"):
        triangulate_tracks(R, t, K, cam_idx, point_idx, np.zeros((3, 2)), 1)
    with pytest.raises(ValueError, match="cam_idx"):
        triangulate_tracks(R, t, K, cam_idx + 1, point_idx, np.zeros((3, 2)), 3)
