"""Relative pose: accuracy on exact synthetic correspondences with noise and outliers, focal self-calibration,
degenerate inputs, and the geometric helpers (Sampson distance, triangulation)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.cameras import Camera
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.errors import ReconstructionError
from macsplat_cli.pipeline.pose import PoseConfig, estimate_pose, fundamental_from_pose, sampson_distance, triangulate
from macsplat_cli.pipeline.types import IntrinsicsSource, Matches, View
from macsplat_cli.pipeline.views import prior_focal

from support import REPO
from support.cli import one_error_line, run_cli

W, H = 512, 384


@pytest.fixture(scope="module")
def scenes() -> dict[str, S.Scene]:
    return {"object": S.object_scene(0), "room": S.room_scene(0)}


def _view(name: str, K: np.ndarray, source: IntrinsicsSource, width: int = W, height: int = H) -> View:
    """A view with the given intrinsics; the pose stage only reads K, the source and the image size."""
    image = np.zeros((height, width, 3), np.float32)
    return View(name, Path(f"{name}.png"), image, np.ones((height, width), bool), K.copy(), (width, height), source)


def _matches(xy0: np.ndarray, xy1: np.ndarray) -> Matches:
    n = len(xy0)
    return Matches(xy0, xy1, np.ones(n, np.float32), np.arange(n), np.arange(n))


def _corrupt(
    xy0: np.ndarray, xy1: np.ndarray, rng: np.random.Generator, *, noise: float, outliers: float, size=(W, H)
) -> tuple[Matches, np.ndarray]:
    """Gaussian pixel noise on both sides and a fraction of matches replaced by random points; (matches, is_outlier)."""
    n = len(xy0)
    xy0 = xy0 + rng.normal(0.0, noise, xy0.shape)
    xy1 = xy1 + rng.normal(0.0, noise, xy1.shape)
    bad = np.zeros(n, bool)
    bad[rng.choice(n, int(round(outliers * n)), replace=False)] = True
    xy1[bad] = rng.uniform([0, 0], size, (int(bad.sum()), 2))
    return _matches(xy0, xy1), bad


def _scene_correspondences(
    scene: S.Scene, cam0: Camera, cam1: Camera, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` exact correspondences of random pixels of view 0 that are visible in view 1."""
    px = rng.uniform([0, 0], [cam0.width, cam0.height], (3 * n, 2))
    px1, visible = S.transfer_points(scene, cam0, cam1, px)
    assert visible.sum() >= n
    return px[visible][:n], px1[visible][:n]


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of points ``X`` (camera-0 frame) in camera 0 and in camera 1 (``X1 = R X + t``), same K."""
    p0 = X @ K.T
    p1 = (X @ R.T + t) @ K.T
    return p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]


def _points_in_both(
    K: np.ndarray, R: np.ndarray, t: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points 4–10 units in front of camera 0, kept where both cameras see them."""
    X = np.c_[rng.uniform(-3, 3, (6 * n, 2)), rng.uniform(4, 10, 6 * n)]
    xy0, xy1 = _project(K, R, t, X)
    z1 = (X @ R.T + t)[:, 2]
    ok = (z1 > 0) & np.all((xy0 >= 0) & (xy0 < (W, H)) & (xy1 >= 0) & (xy1 < (W, H)), axis=1)
    assert ok.sum() >= n
    return xy0[ok][:n], xy1[ok][:n]


def _prior_K() -> np.ndarray:
    f = prior_focal(W, H)
    return np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------ accuracy
@pytest.mark.parametrize("kind", ["object", "room"])
@pytest.mark.parametrize("angle", [10.0, 45.0])
def test_pose_with_known_intrinsics(scenes: dict[str, S.Scene], kind: str, angle: float) -> None:
    """Orbit pairs, 0.3 px noise, 30 % outliers, exact K: rotation < 0.2°, translation direction < 1°, and the
    verified matches are the true ones."""
    scene = scenes[kind]
    cam0, cam1 = S.orbit_pair(scene, angle, width=W, height=H, seed=int(angle))
    rng = np.random.default_rng(int(angle) + len(kind))
    xy0, xy1 = _scene_correspondences(scene, cam0, cam1, 1500, rng)
    matches, bad = _corrupt(xy0, xy1, rng, noise=0.3, outliers=0.3)
    geo = estimate_pose(_view("a", cam0.K, "file"), _view("b", cam1.K, "file"), matches)

    R_gt, t_gt = S.relative_pose(cam0, cam1)
    rot_err, t_err = S.pose_errors(geo.R, geo.t, R_gt, t_gt)
    assert rot_err < 0.2 and t_err < 1.0
    assert np.linalg.norm(geo.t) == pytest.approx(1.0, abs=1e-9)
    assert np.linalg.det(geo.R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_array_equal(geo.K0, cam0.K)  # given intrinsics are kept
    assert geo.focal_estimated is False
    inl = geo.inliers.idx0
    assert geo.inliers.counts["verified"] == len(inl) == geo.diagnostics["inliers"]
    assert np.mean(~bad[inl]) > 0.98  # precision: a few outliers may fall on their epipolar line by chance
    assert np.isin(np.flatnonzero(~bad), inl).mean() > 0.95  # recall
    assert geo.median_parallax_deg > 1.0


@pytest.mark.parametrize("fov_deg", [45.0, 75.0])
def test_focal_is_estimated_from_general_motion(fov_deg: float) -> None:
    """Intrinsics from the 60° prior, true FOV 45°/75°, generic rotation and translation: the focal is recovered
    within 3 % and reported as estimated; the pose is still accurate."""
    rng = np.random.default_rng(int(fov_deg))
    K_true = S.intrinsics(W, H, fov_deg)
    R = S.rotation_about((0.3, 1.0, 0.2), 15.0)
    t = np.array([1.0, 0.3, 0.2])
    xy0, xy1 = _points_in_both(K_true, R, t, 1500, rng)
    matches, _ = _corrupt(xy0, xy1, rng, noise=0.3, outliers=0.3)
    K_prior = _prior_K()
    geo = estimate_pose(_view("a", K_prior, "prior"), _view("b", K_prior, "prior"), matches)
    assert geo.focal_estimated is True
    for K in (geo.K0, geo.K1):
        assert K[0, 0] == pytest.approx(K_true[0, 0], rel=0.03)
        assert K[1, 1] == pytest.approx(K_true[1, 1], rel=0.03)
        np.testing.assert_allclose(K[:2, 2], K_prior[:2, 2])  # only the focal length is estimated
    rot_err, t_err = S.pose_errors(geo.R, geo.t, R, t)
    assert rot_err < 0.2 and t_err < 1.0


def test_unobservable_focal_keeps_the_prior() -> None:
    """Pure sideways translation (no rotation) does not determine the focal: the prior K is kept, no crash."""
    rng = np.random.default_rng(2)
    K_true = S.intrinsics(W, H, 45.0)
    t = np.array([1.0, 0.0, 0.0])
    xy0, xy1 = _points_in_both(K_true, np.eye(3), t, 1000, rng)
    matches, _ = _corrupt(xy0, xy1, rng, noise=0.3, outliers=0.3)
    K_prior = _prior_K()
    geo = estimate_pose(_view("a", K_prior, "prior"), _view("b", K_prior, "prior"), matches)
    assert geo.focal_estimated is False
    np.testing.assert_array_equal(geo.K0, K_prior)
    np.testing.assert_array_equal(geo.K1, K_prior)
    rot_err, t_err = S.pose_errors(geo.R, geo.t, np.eye(3), t)
    assert rot_err < 0.2 and t_err < 1.0  # a sideways motion is recovered whatever the focal


def test_estimate_focal_disabled_keeps_the_prior() -> None:
    """``estimate_focal=False``: even an observable focal is left at the prior."""
    rng = np.random.default_rng(3)
    K_true = S.intrinsics(W, H, 45.0)
    R = S.rotation_about((0.3, 1.0, 0.2), 15.0)
    xy0, xy1 = _points_in_both(K_true, R, np.array([1.0, 0.3, 0.2]), 500, rng)
    K_prior = _prior_K()
    geo = estimate_pose(
        _view("a", K_prior, "prior"), _view("b", K_prior, "prior"), _matches(xy0, xy1), PoseConfig(estimate_focal=False)
    )
    assert geo.focal_estimated is False
    np.testing.assert_array_equal(geo.K0, K_prior)


# ------------------------------------------------------------------------------------ failures
@pytest.mark.parametrize(("n", "min_inliers", "need"), [(14, 15, 15), (7, 5, 8), (0, 15, 15)])
def test_too_few_matches(n: int, min_inliers: int, need: int) -> None:
    """Fewer matches than ``max(min_inliers, 8)`` fails before RANSAC, naming both numbers."""
    rng = np.random.default_rng(n)
    K = S.intrinsics(W, H, 60.0)
    xy0, xy1 = _points_in_both(K, np.eye(3), np.array([1.0, 0.0, 0.0]), max(n, 1), rng)
    with pytest.raises(ReconstructionError, match=rf"\b{n} matches .*need at least {need}\b"):
        estimate_pose(
            _view("a", K, "file"),
            _view("b", K, "file"),
            _matches(xy0[:n], xy1[:n]),
            PoseConfig(min_inliers=min_inliers),
        )


def test_random_matches_fail_verification() -> None:
    """Unrelated matches: too few survive geometric verification; the message gives the verified count."""
    rng = np.random.default_rng(0)
    K = S.intrinsics(W, H, 60.0)
    m = _matches(rng.uniform(0, (W, H), (200, 2)), rng.uniform(0, (W, H), (200, 2)))
    with pytest.raises(ReconstructionError, match=r"\b\d+ verified matches.*need at least 15"):
        estimate_pose(_view("a", K, "file"), _view("b", K, "file"), m)


def test_identical_images() -> None:
    """xy1 == xy0: "the same view", whatever the intrinsics source."""
    rng = np.random.default_rng(1)
    K = S.intrinsics(W, H, 60.0)
    xy = rng.uniform(0, (W, H), (300, 2))
    for source in ("file", "prior"):
        with pytest.raises(ReconstructionError, match="same view"):
            estimate_pose(_view("a", K, source), _view("b", K, source), _matches(xy, xy.copy()))


@pytest.mark.parametrize("angle", [5.0, 20.0])
def test_pure_rotation_reports_no_baseline(angle: float) -> None:
    """Matches related by a rotation homography (no translation) fail with "no baseline"."""
    rng = np.random.default_rng(int(angle))
    K = S.intrinsics(W, H, 60.0)
    Hm = K @ S.rotation_about((0.1, 1.0, 0.05), angle) @ np.linalg.inv(K)
    xy0 = rng.uniform(0, (W, H), (300, 2))
    p = np.c_[xy0, np.ones(300)] @ Hm.T
    xy1 = p[:, :2] / p[:, 2:] + rng.normal(0.0, 0.3, (300, 2))
    with pytest.raises(ReconstructionError, match="no baseline"):
        estimate_pose(_view("a", K, "file"), _view("b", K, "file"), _matches(xy0, xy1))


@pytest.mark.parametrize("angle", [5.0, 20.0])
def test_pure_rotation_fails(scenes: dict[str, S.Scene], angle: float) -> None:
    """A pure rotation (``pure_rotation_pair``, exact correspondences) raises a ReconstructionError, no pose."""
    scene = scenes["room"]
    cam0, cam1 = S.pure_rotation_pair(scene, angle, width=W, height=H)
    rng = np.random.default_rng(int(angle))
    xy0, xy1 = _scene_correspondences(scene, cam0, cam1, 400, rng)
    with pytest.raises(ReconstructionError, match=r"\b\d+ verified matches|no baseline"):
        estimate_pose(_view("a", cam0.K, "file"), _view("b", cam1.K, "file"), _matches(xy0, xy1))


def test_low_parallax_reports_no_baseline_with_the_count(scenes: dict[str, S.Scene]) -> None:
    """Median parallax below ``min_parallax_deg``: "no baseline", naming the number of verified matches."""
    scene = scenes["object"]
    cam0, cam1 = S.orbit_pair(scene, 10.0, width=W, height=H)
    xy0, xy1 = _scene_correspondences(scene, cam0, cam1, 300, np.random.default_rng(0))
    v0, v1 = _view("a", cam0.K, "file"), _view("b", cam1.K, "file")
    parallax = estimate_pose(v0, v1, _matches(xy0, xy1)).median_parallax_deg
    with pytest.raises(ReconstructionError, match=r"no baseline: the median parallax of the 300 verified matches"):
        estimate_pose(v0, v1, _matches(xy0, xy1), PoseConfig(min_parallax_deg=parallax + 1.0))


# ------------------------------------------------------------------------------------ Sampson distance
def test_sampson_distance_rectified_pair_is_half_split_offset() -> None:
    """Rectified pair (R = I, t = x): epipolar lines are rows. A vertical offset δ in view 1 gives |Sampson| = δ/√2,
    the exact geometric distance (the optimal correction moves each point by δ/2); exact matches give 0."""
    K = S.intrinsics(W, H, 60.0)
    rng = np.random.default_rng(0)
    xy0, xy1 = _points_in_both(K, np.eye(3), np.array([1.0, 0.0, 0.0]), 50, rng)
    F = fundamental_from_pose(np.eye(3), np.array([1.0, 0.0, 0.0]), K, K)
    np.testing.assert_allclose(sampson_distance(F, xy0, xy1), 0.0, atol=1e-9)
    for delta in (0.1, 1.0, 3.0):
        d = sampson_distance(F, xy0, xy1 + [0.0, delta])
        np.testing.assert_allclose(np.abs(d), delta / math.sqrt(2.0), rtol=1e-9)
        np.testing.assert_allclose(sampson_distance(F, xy0, xy1 - [0.0, delta]), -d, rtol=1e-9)  # signed
        np.testing.assert_allclose(sampson_distance(F, xy0 - [0.0, delta / 2], xy1 + [0.0, delta / 2]), d, rtol=1e-9)
    np.testing.assert_allclose(sampson_distance(F, xy0, xy1 + [5.0, 0.0]), 0.0, atol=1e-9)  # along the line: 0


def test_sampson_distance_general_pose_is_linear_in_the_offset() -> None:
    """Generic pose: ~0 for exact matches; for an offset δ of xy1 across its epipolar line the distance grows
    linearly (≈ δ/√2 when both images see the line alike, never more than δ); invariant to the scale of F."""
    K = S.intrinsics(W, H, 60.0)
    R = S.rotation_about((0.2, 1.0, 0.1), 10.0)
    t = np.array([0.8, 0.1, 0.3])
    rng = np.random.default_rng(1)
    xy0, xy1 = _points_in_both(K, R, t, 100, rng)
    F = fundamental_from_pose(R, t, K, K)
    assert np.abs(sampson_distance(F, xy0, xy1)).max() < 1e-8
    lines = np.c_[xy0, np.ones(len(xy0))] @ F.T
    normal = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    one = sampson_distance(F, xy0, xy1 + normal)
    assert (np.abs(one) <= 1.0 + 1e-9).all()
    np.testing.assert_allclose(np.abs(one), 1.0 / math.sqrt(2.0), rtol=0.15)
    for delta in (0.25, 2.0):
        np.testing.assert_allclose(sampson_distance(F, xy0, xy1 + delta * normal), delta * one, rtol=0.01)
    np.testing.assert_allclose(sampson_distance(-7.0 * F, xy0, xy1 + normal), -one, rtol=1e-9)


# ------------------------------------------------------------------------------------ triangulation
def test_triangulate_recovers_points() -> None:
    """Noise-free rays of known points triangulate back to them (rays of any length); parallel rays give NaN."""
    rng = np.random.default_rng(4)
    R = S.rotation_about((0.3, 1.0, -0.2), 12.0)
    t = np.array([0.7, -0.1, 0.2])
    X = np.c_[rng.uniform(-2, 2, (200, 2)), rng.uniform(1, 20, 200)]
    x0 = X / X[:, 2:]
    X1 = X @ R.T + t
    x1 = X1 / X1[:, 2:]
    np.testing.assert_allclose(triangulate(R, t, x0, x1), X, rtol=1e-9, atol=1e-9)
    scale = rng.uniform(0.1, 10.0, (200, 1))
    np.testing.assert_allclose(triangulate(R, t, x0 * scale, x1 * scale[::-1]), X, rtol=1e-9, atol=1e-9)
    parallel = triangulate(R, t, x0[:5], x0[:5] @ R.T)  # same direction in both frames: a point at infinity
    assert np.isnan(parallel).all()


@pytest.mark.parametrize("size", [64, 100, 512])
def test_small_working_sizes_scale_the_pixel_thresholds(size: int) -> None:
    """The shipped stereo pair (rectified: no rotation) at the smallest allowed working size. With the 1 px
    thresholds of a 512-px image, every match at 64 px fit one plane both ways and the pair was refused as
    "ambiguous … photograph more of the scene's depth" (a setting blamed on the scene)."""
    from macsplat_cli.engine import EngineConfig, reconstruct
    from macsplat_cli.presets import Overrides

    root = REPO / "examples" / "motorcycle"
    config = EngineConfig(quality="best", overrides=Overrides(size=size, refine=0))  # the poses: no refinement
    rec = reconstruct([root / "left.jpg", root / "right.jpg"], config)
    assert abs(max(rec.report.images[0].working_size) - size) <= 8  # the working size asked for (multiple of 16)
    assert rec.pose.geometry.diagnostics["rotation_deg"] < 0.5 and rec.report.matches["verified"] > 1000


def test_flipped_fraction_tells_a_mirror_from_a_view_change() -> None:
    from macsplat_cli.pipeline.pose import flipped_fraction

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 500, (400, 2))
    noise = rng.normal(0, 0.5, xy.shape)
    roll = np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])  # camera roll keeps orientation
    assert flipped_fraction(xy, xy @ roll.T + 40 + noise) < 0.02
    mirrored = np.c_[512 - xy[:, 0], xy[:, 1]] + noise
    assert flipped_fraction(xy, mirrored) > 0.95
    # an orbit: the object (left half, near) and the background (right half, far) move in opposite directions,
    # so triangles spanning both flip; the depth test keeps only patches of one surface
    near = xy[:, 0] < 250
    moved = xy + np.where(near[:, None], [30.0, 0.0], [-30.0, 0.0]) + noise
    depth = np.where(near, 1.0, 3.0)
    assert (
        flipped_fraction(xy, moved, depth) < flipped_fraction(xy, moved) and flipped_fraction(xy, moved, depth) < 0.02
    )


def test_a_photo_and_its_mirror_image_are_refused(tmp_path: Path) -> None:
    """Isotropic dots match their mirror images (SIFT of a round blob is nearly mirror-symmetric): 58 verified
    matches and a 177° "pose" used to be accepted (exit 0). The command runs the library's ``engine.reconstruct``:
    its error line is the ReconstructionError's message, its exit code that class's (one reconstruction, not one
    through the command and another through the library)."""
    from macsplat_cli.images import save_image

    rng = np.random.default_rng(0)
    h, w = 384, 512
    img = np.full((h, w, 3), 0.5, np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    for _ in range(400):
        cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(2, 9)
        blob = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))[..., None]
        img = img * (1 - blob) + rng.uniform(0, 1, 3) * blob
    save_image(tmp_path / "a.png", img.astype(np.float32))
    save_image(tmp_path / "mirror.png", np.ascontiguousarray(img[:, ::-1]).astype(np.float32))
    code, _, err = run_cli(["reconstruct", tmp_path / "a.png", tmp_path / "mirror.png", "-o", tmp_path / "s.ply", "-q"])
    assert code == ReconstructionError.exit_code == 3 and not (tmp_path / "s.ply").exists()
    assert "mirror images of each other" in one_error_line(err)


def test_planar_pose_is_a_rotation_to_roundoff() -> None:
    """A plane facing the camera, pure sideways motion, exact matches: the pose comes from the homography's
    decomposition, whose rotations OpenCV returns orthonormal only to ~1e-9; the returned R must be a rotation to
    roundoff: Levenberg–Marquardt multiplies ≤ 30 small rotations onto it (each product a dot of 3 terms: γ₃), after
    the nearest-rotation projection (18u + 2γ₃, see test_rotations)."""
    import cv2

    w, h = 320, 240
    rng = np.random.default_rng(0)
    cv2.setRNGSeed(0)
    K = np.array([[300.0, 0, w / 2], [0, 300.0, h / 2], [0, 0, 1]])
    t = np.array([0.0, 0.5, 0.0])
    X = np.c_[rng.uniform(-3, 3, (156, 2)), np.full(156, 6.0)]
    p0, p1 = X @ K.T, (X + t) @ K.T
    xy0, xy1 = p0[:, :2] / p0[:, 2:], p1[:, :2] / p1[:, 2:]
    ok = np.all((xy0 >= 0) & (xy0 < (w, h)) & (xy1 >= 0) & (xy1 < (w, h)), axis=1)
    xy0, xy1 = xy0[ok][:26], xy1[ok][:26]
    view = View("v", Path("v.png"), np.zeros((h, w, 3), np.float32), np.ones((h, w), bool), K, (w, h), "file")
    m = len(xy0)
    geo = estimate_pose(view, view, Matches(xy0, xy1, np.ones(m, np.float32), np.arange(m), np.arange(m)))
    u = np.finfo(np.float64).eps / 2
    bound = 32 * 3 * u / (1 - 3 * u) + 18 * u
    assert np.abs(geo.R @ geo.R.T - np.eye(3)).max() <= bound
    assert abs(np.linalg.det(geo.R) - 1.0) <= bound
