"""Bundle adjustment (:mod:`macsplat_cli.pipeline.multiview.bundle`) on synthetic scenes made here: random points in
a box seen by cameras on an arc around it, exact projections, then noise, outliers and perturbed starts.

Camera 0 stays at its true pose (the default fixed pose), so rotations compare with the truth directly and the
centres after one scale, the ratio of a true to an estimated baseline from camera 0.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from macsplat_cli.errors import ShapeError
from macsplat_cli.metrics import rotation_error_deg
from macsplat_cli.pipeline.multiview.bundle import (
    BundleConfig,
    _Problem,
    _restore_scale,
    _rodrigues,
    _scale_reference,
    bundle_adjust,
)
from macsplat_cli.pipeline.multiview.triangulate import reprojection_errors

FOCAL = 600.0
PP = (320.5, 240.5)
RADIUS = 6.0
BOX = 2.5  # half-size of the points' box: the points fill most of the view and vary in depth


def _look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World → camera ``(R, t)`` of a camera at ``centre`` looking at the origin, y down."""
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def _scene(rng: np.random.Generator, n_cams: int = 5, n_points: int = 150, spread_deg: float = 80.0) -> dict:
    """Cameras on an arc of ``spread_deg`` (slightly up and down), points in a box of half-size ``BOX`` at the
    origin, every point seen by every camera, exact pixels."""
    angles = np.radians(np.linspace(-spread_deg / 2, spread_deg / 2, n_cams))
    poses = [_look_at(RADIUS * np.array([math.sin(a), 0.4 * math.cos(3 * a), -math.cos(a)])) for a in angles]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    K = np.tile(np.array([[FOCAL, 0, PP[0]], [0, FOCAL, PP[1]], [0, 0, 1.0]]), (n_cams, 1, 1))
    X = rng.uniform(-BOX, BOX, (n_points, 3))
    cam_idx = np.tile(np.arange(n_cams), n_points)
    point_idx = np.repeat(np.arange(n_points), n_cams)
    Xc = np.einsum("oij,oj->oi", R[cam_idx], X[point_idx]) + t[cam_idx]
    xy = np.einsum("oij,oj->oi", K[cam_idx][:, :2], Xc) / Xc[:, 2:3]
    return dict(R=R, t=t, K=K, X=X, cam_idx=cam_idx, point_idx=point_idx, xy=xy)


def _perturbed(rng: np.random.Generator, s: dict, rot_deg: float = 1.5, trans: float = 0.03, point: float = 0.03):
    """``(R, t, X)``: every camera but 0 turned by ``rot_deg`` about a random axis and its centre moved by
    ``trans`` of the radius; points moved by ``point`` (world units, ~1 % of the box)."""
    axes = rng.normal(size=(len(s["R"]), 3))
    axes *= math.radians(rot_deg) / np.linalg.norm(axes, axis=1, keepdims=True)
    axes[0] = 0
    R = _rodrigues(axes)[0] @ s["R"]
    centres = -np.einsum("cji,cj->ci", s["R"], s["t"]) + trans * RADIUS * rng.normal(size=(len(R), 3)) / math.sqrt(3)
    centres[0] = -s["R"][0].T @ s["t"][0]
    t = -np.einsum("cij,cj->ci", R, centres)
    t[0] = s["t"][0]
    return R, t, s["X"] + point * rng.normal(size=s["X"].shape)


def _focal_off_start(seed: int, n_cams: int, n_points: int, focal: float):  # noqa: ANN202
    """A scene, a perturbed start ``(R, t, X)``, the intrinsics with every focal ``focal`` × the truth, and the
    observations with 0.5 px noise, and the generator for what follows: ``(s, R, t, X, K, xy, rng)``."""
    rng = np.random.default_rng(seed)
    s = _scene(rng, n_cams=n_cams, n_points=n_points)
    R, t, X = _perturbed(rng, s)
    K = s["K"].copy()
    K[:, :2, :2] *= focal
    return s, R, t, X, K, s["xy"] + 0.5 * rng.normal(size=s["xy"].shape), rng


def _centres(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -np.einsum("cji,cj->ci", R, t)


def _pose_errors(res, s: dict) -> tuple[float, float]:  # noqa: ANN001
    """Largest rotation error (°) and largest centre error (relative to the radius) after the scale gauge: the
    estimate's centres scaled about camera 0 so that camera 1's baseline is the true one."""
    rot = max(rotation_error_deg(a, b) for a, b in zip(res.R, s["R"]))
    c_est, c_true = _centres(res.R, res.t), _centres(s["R"], s["t"])
    lam = np.linalg.norm(c_true[1] - c_true[0]) / np.linalg.norm(c_est[1] - c_est[0])
    aligned = c_true[0] + lam * (c_est - c_true[0])
    return rot, float(np.abs(aligned - c_true).max() / RADIUS)


def _run(s: dict, R: np.ndarray, t: np.ndarray, X: np.ndarray, xy: np.ndarray | None = None, **kw):  # noqa: ANN202
    return bundle_adjust(R, t, s["K"], X, s["cam_idx"], s["point_idx"], s["xy"] if xy is None else xy, **kw)


def test_noise_free_start_perturbed_recovers_the_observations_and_poses() -> None:
    rng = np.random.default_rng(0)
    s = _scene(rng)
    R, t, X = _perturbed(rng, s)
    res = _run(s, R, t, X)
    assert res.rms_before_px > 10
    assert res.rms_after_px < 1e-6 and res.residual_px.max() < 1e-5
    rot, centre = _pose_errors(res, s)
    # 1e-6 px on a 600 px focal is 1e-7°; the poses follow the pixels up to the conditioning of the scene
    assert rot < 1e-5 and centre < 1e-7
    assert res.success and res.evaluations <= BundleConfig().max_evaluations
    np.testing.assert_array_equal(res.R[0], s["R"][0])
    np.testing.assert_array_equal(res.t[0], s["t"][0])
    np.testing.assert_array_equal(res.K, s["K"])


def test_pixel_noise_leaves_the_rms_of_the_degrees_of_freedom() -> None:
    """σ per coordinate: after a least-squares fit the residual sum of squares is σ² (2O − n) with n free
    parameters (6 per free camera, 3 per point, less the free scale), so the RMS of the error norms is
    σ √((2O − n) / O); its relative spread is ~√(1 / (2 (2O − n))) ≈ 1.4 % here, and Huber at 2σ changes little."""
    rng = np.random.default_rng(1)
    sigma = 0.5
    s = _scene(rng, n_cams=6, n_points=300)
    R, t, X = _perturbed(rng, s)
    xy = s["xy"] + sigma * rng.normal(size=s["xy"].shape)
    res = _run(s, R, t, X, xy)
    n_obs = len(xy)
    n = 6 * (len(R) - 1) + 3 * len(X) - 1
    expected = sigma * math.sqrt((2 * n_obs - n) / n_obs)
    assert abs(res.rms_after_px / expected - 1) < 0.1, (res.rms_after_px, expected)
    rot, centre = _pose_errors(res, s)
    assert rot < 0.1 and centre < 0.01


def test_outliers_do_not_pull_the_poses() -> None:
    """10 % of the observations moved 30 px: Huber bounds each one's pull; plain least squares (a huge loss scale)
    is pulled further. Over 20 seeds of this scene the largest rotation error was 0.069° (0.043° without the
    outliers: most of it is the 0.5 px noise), least squares' at least 4.9 times it."""
    rng = np.random.default_rng(2)
    s = _scene(rng, n_cams=6, n_points=600)
    R, t, X = _perturbed(rng, s)
    xy = s["xy"] + 0.5 * rng.normal(size=s["xy"].shape)
    bad = rng.random(len(xy)) < 0.1
    direction = rng.normal(size=(int(bad.sum()), 2))
    xy[bad] += 30 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    res = _run(s, R, t, X, xy)
    rot, centre = _pose_errors(res, s)
    assert rot < 0.1 and centre < 0.01
    assert np.median(res.residual_px[bad]) > 25 and np.median(res.residual_px[~bad]) < 1.5
    plain = _run(s, R, t, X, xy, config=BundleConfig(loss_scale_px=1e6))
    rot_ls, _ = _pose_errors(plain, s)
    assert rot_ls > 2 * rot, (rot_ls, rot)


def test_a_shared_focal_converges_to_the_truth() -> None:
    s, R, t, X, K, xy, _ = _focal_off_start(3, n_cams=5, n_points=150, focal=1.1)
    res = bundle_adjust(R, t, K, X, s["cam_idx"], s["point_idx"], xy, focal_group=np.zeros(5, int))
    f = res.K[:, 0, 0]
    assert np.all(f == f[0]) and abs(f[0] / FOCAL - 1) < 0.005, f[0]
    np.testing.assert_allclose(res.K[:, 1, 1], f)
    np.testing.assert_array_equal(res.K[:, :2, 2], K[:, :2, 2])
    # without the focal parameter the 10 % error stays in the pixels
    stuck = bundle_adjust(R, t, K, X, s["cam_idx"], s["point_idx"], xy)
    assert stuck.rms_after_px > 1.5 * res.rms_after_px


def test_focal_groups_are_separate_and_minus_one_is_fixed() -> None:
    rng = np.random.default_rng(4)
    s = _scene(rng, n_cams=6, n_points=150)
    R, t, X = _perturbed(rng, s, rot_deg=0.5, trans=0.01)
    K = s["K"].copy()
    K[3:, :2, :2] *= 0.95  # group 1 starts 5 % short; group 0 at the truth; camera 0 fixed
    group = np.array([-1, 0, 0, 1, 1, 1])
    res = bundle_adjust(R, t, K, X, s["cam_idx"], s["point_idx"], s["xy"], focal_group=group)
    assert res.rms_after_px < 1e-6
    np.testing.assert_allclose(res.K[:, 0, 0], FOCAL, rtol=1e-8)
    np.testing.assert_array_equal(res.K[0], K[0])


def test_fixed_poses_are_honoured_and_two_fix_the_scale() -> None:
    """Cameras 0 and 1 fixed at the truth: they stay bit for bit, their baseline fixes the scale, so the others
    come back to the truth itself, with no gauge to align."""
    rng = np.random.default_rng(5)
    s = _scene(rng)
    R, t, X = _perturbed(rng, s)
    R[1], t[1] = s["R"][1], s["t"][1]
    fixed = np.array([True, True, False, False, False])
    res = _run(s, R, t, X, fixed_pose=fixed)
    np.testing.assert_array_equal(res.R[:2], s["R"][:2])
    np.testing.assert_array_equal(res.t[:2], s["t"][:2])
    np.testing.assert_allclose(_centres(res.R, res.t), _centres(s["R"], s["t"]), atol=1e-7 * RADIUS)
    np.testing.assert_allclose(res.points, s["X"], atol=1e-7 * RADIUS)
    # a fixed camera that is not camera 0
    fixed = np.array([False, False, True, False, False])
    R, t, X = _perturbed(rng, s)
    res = _run(s, R, t, X, fixed_pose=fixed)
    np.testing.assert_array_equal(res.R[2], R[2])
    np.testing.assert_array_equal(res.t[2], t[2])
    assert res.rms_after_px < 1e-6


def test_the_scale_gauge_keeps_the_first_baseline() -> None:
    """The start's scale is 20 % off the truth: the solve keeps the baseline from camera 0 to camera 1 as it was."""
    rng = np.random.default_rng(6)
    s = _scene(rng)
    R, t, X = _perturbed(rng, s)
    c = _centres(R, t)
    c_scaled = c[0] + 1.2 * (c - c[0])
    t = -np.einsum("cij,cj->ci", R, c_scaled)
    res = _run(s, R, t, X + 0.2 * (X - c[0]))
    before = np.linalg.norm(c_scaled[1] - c_scaled[0])
    after = _centres(res.R, res.t)
    assert abs(np.linalg.norm(after[1] - after[0]) / before - 1) < 1e-12
    assert res.rms_after_px < 1e-6


def test_the_renormalisation_keeps_every_reprojection_error() -> None:
    rng = np.random.default_rng(7)
    s = _scene(rng, n_points=40)
    xy = s["xy"] + rng.normal(size=s["xy"].shape)
    R, t, X = _perturbed(rng, s)
    free = np.array([False, True, True, True, True])
    t2, X2 = _restore_scale(R, t, X, free, 0, 1, 3.7)
    c2 = _centres(R, t2)
    assert abs(np.linalg.norm(c2[1] - c2[0]) - 3.7) < 1e-12 * 3.7
    np.testing.assert_array_equal(t2[0], t[0])
    e1 = reprojection_errors(R, t, s["K"], X, s["cam_idx"], s["point_idx"], xy)
    e2 = reprojection_errors(R, t2, s["K"], X2, s["cam_idx"], s["point_idx"], xy)
    np.testing.assert_allclose(e2, e1, rtol=1e-9, atol=1e-9)


def test_the_scale_reference_skips_a_camera_without_baseline() -> None:
    rng = np.random.default_rng(8)
    s = _scene(rng, n_points=10)
    R, t = s["R"].copy(), s["t"].copy()
    R[1] = _rodrigues(np.array([[0.0, 0.2, 0.0]]))[0][0] @ R[0]
    t[1] = -R[1] @ _centres(R, t)[0]  # camera 1 turns in place about camera 0's centre
    fixed = np.array([True, False, False, False, False])
    assert _scale_reference(R, t, fixed) == (0, 2)
    assert _scale_reference(R, t, np.array([True, False, True, False, False])) is None  # two centres fix it
    assert _scale_reference(R, t, np.array([True, True, False, False, False])) == (0, 2)  # one centre


def test_the_analytic_jacobian_equals_central_differences() -> None:
    rng = np.random.default_rng(9)
    s = _scene(rng, n_cams=4, n_points=12)
    R, t, X = _perturbed(rng, s)
    K = s["K"].copy()
    K[:, 0, 1] = 3.0  # a skew, scaled with the focal
    prob = _Problem(
        R,
        t,
        K,
        X,
        s["cam_idx"],
        s["point_idx"],
        s["xy"],
        np.array([False, True, True, True]),
        np.array([-1, 0, 0, 1]),
        np.ones(len(X), bool),
    )
    x = prob.x0() + 0.05 * rng.normal(size=prob.n_params)  # away from δ = 0: the left Jacobian of SO(3) counts
    J = prob.jacobian(x).toarray()
    h = 1e-6
    eye = np.eye(prob.n_params) * h
    numeric = np.stack([(prob.residuals(x + e) - prob.residuals(x - e)) / (2 * h) for e in eye], axis=1)
    # central differences: O(h²) truncation and ~eps·|r|/h rounding, relative to the Jacobian's scale (~1e3)
    np.testing.assert_allclose(J, numeric, atol=1e-6 * np.abs(numeric).max())
    assert np.all(prob.sparsity().toarray()[J != 0] == 1)  # the structure holds every non-zero


def test_finite_differences_reach_the_same_solution() -> None:
    rng = np.random.default_rng(10)
    s = _scene(rng, n_points=60)
    R, t, X = _perturbed(rng, s)
    xy = s["xy"] + 0.5 * rng.normal(size=s["xy"].shape)
    a = _run(s, R, t, X, xy)
    b = _run(s, R, t, X, xy, config=BundleConfig(jacobian="2-point"))
    assert abs(a.rms_after_px - b.rms_after_px) < 1e-4 * a.rms_after_px
    np.testing.assert_allclose(b.points, a.points, atol=1e-4)


def test_points_under_the_observation_minimum_stay_and_inputs_are_checked() -> None:
    rng = np.random.default_rng(11)
    s = _scene(rng, n_points=30)
    R, t, X = _perturbed(rng, s)
    R[1], t[1] = s["R"][1], s["t"][1]
    keep = ~((s["point_idx"] == 0) & (s["cam_idx"] > 0))  # point 0 seen once
    fixed = np.array([True, True, False, False, False])  # two centres fix the scale: no rescaling of point 0
    res = bundle_adjust(R, t, s["K"], X, s["cam_idx"][keep], s["point_idx"][keep], s["xy"][keep], fixed_pose=fixed)
    np.testing.assert_allclose(res.points[0], X[0], rtol=1e-12)
    assert res.residual_px.shape == (int(keep.sum()),)
    assert np.median(res.residual_px) < 1e-6
    with pytest.raises(ValueError, match="fixed pose"):
        _run(s, R, t, X, fixed_pose=np.zeros(5, bool))
    with pytest.raises(ShapeError):
        _run(s, R, t, X[:, :2])
    with pytest.raises(ValueError, match="point_idx"):
        bundle_adjust(R, t, s["K"], X[:5], s["cam_idx"], s["point_idx"], s["xy"])


def test_the_schur_step_is_the_damped_gauss_newton_step() -> None:
    """The points eliminated, the cameras solved, the points back: the step solves the full damped normal equations
    (a shared focal group included), as a dense solve does."""
    from macsplat_cli.pipeline.multiview.schur import _huber, _Layout, _Normal

    rng = np.random.default_rng(7)
    s = _scene(rng, n_cams=4, n_points=40)
    R, t, X = _perturbed(rng, s)
    group = np.array([-1, 0, 0, 0])
    prob = _Problem(R, t, s["K"], X, s["cam_idx"], s["point_idx"], s["xy"], np.array([False, True, True, True]),
                    group, np.ones(len(X), bool))  # fmt: skip
    x = prob.x0()
    r = prob.residuals(x) + rng.normal(scale=2.0, size=2 * len(s["xy"]))  # some beyond the Huber scale
    _, w = _huber(r, 1.0)
    J = prob.jacobian(x)
    normal = _Normal(_Layout(prob), prob.blocks(x), r, w)
    H = J.T @ (w[:, None] * J.toarray())
    lam = 1e-3
    dense = np.linalg.solve(H + lam * np.diag(np.diag(H)), -(J.T @ (w * r)))
    np.testing.assert_allclose(normal.step(lam), dense, rtol=1e-6, atol=1e-9 * np.abs(dense).max())


def test_the_schur_solver_reaches_the_lsmr_solution() -> None:
    """The two solvers minimise the same robust cost: from the same start (noise, outliers, a shared focal 5 % off)
    they stop at the same poses, focal and errors, up to their tolerance (1e-6 of the cost)."""
    s, R, t, X, K, xy, rng = _focal_off_start(8, n_cams=6, n_points=200, focal=1.05)
    bad = rng.random(len(xy)) < 0.05
    xy[bad] += 20.0
    ours, scipy_ = (bundle_adjust(R, t, K, X, s["cam_idx"], s["point_idx"], xy, focal_group=np.zeros(6, int),
                                  config=BundleConfig(solver=solver))
                    for solver in ("schur", "lsmr"))  # fmt: skip
    assert ours.success and scipy_.success
    assert abs(ours.K[1, 0, 0] / FOCAL - 1) < 0.002  # the focal found, not left at its 5 % start
    assert max(rotation_error_deg(a, b) for a, b in zip(ours.R, scipy_.R)) < 2e-3
    np.testing.assert_allclose(ours.K, scipy_.K, rtol=1e-4)
    np.testing.assert_allclose(ours.residual_px, scipy_.residual_px, atol=0.1)
    assert abs(ours.rms_after_px / scipy_.rms_after_px - 1) < 1e-4
    with pytest.raises(ValueError, match="solver"):
        bundle_adjust(R, t, K, X, s["cam_idx"], s["point_idx"], xy, config=BundleConfig(solver="cg"))


def test_the_schur_kernel_equals_its_numpy_twin() -> None:
    """The Numba sum of the points' terms and the NumPy one (every pair gathered at once) agree, on tracks of 1 to 6
    observations, a fixed camera (its columns the dummy one) and a focal group."""
    from macsplat_cli.pipeline.multiview.schur import _Layout, schur_term_reference

    rng = np.random.default_rng(9)
    s = _scene(rng, n_cams=6, n_points=60)
    keep = rng.random(len(s["cam_idx"])) < 0.6
    ci, pi, xy = s["cam_idx"][keep], s["point_idx"][keep], s["xy"][keep]
    free_point = np.bincount(pi, minlength=60) >= 1
    prob = _Problem(s["R"], s["t"], s["K"], s["X"], ci, pi, xy, np.arange(6) > 0, np.array([-1, 0, 0, 0, 1, 1]),
                    free_point)  # fmt: skip
    lay = _Layout(prob)
    Y, W = rng.normal(size=(2, len(lay.pt), 7, 3))
    ours = lay.schur_term(Y, W)
    np.testing.assert_allclose(ours, schur_term_reference(lay, Y, W), rtol=1e-12, atol=1e-12)
    assert ours.shape == (prob.off_point, prob.off_point) and np.abs(ours).max() > 0
