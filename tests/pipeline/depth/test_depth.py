"""Dense depth: the SGM kernels against their PyTorch twins, push-pull filling, the plane-sweep cost, and
``estimate_depths`` with ground-truth geometry on synthetic orbits and the Middlebury motorcycle pair."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.datasets import synthetic as S
from macsplat_cli.images import save_image
from macsplat_cli.pipeline.depth import _sgm_kernels, _sgm_reference, estimate_depths, plane_sweep_cost, push_pull
from macsplat_cli.pipeline.depth.pair import carry_depth, relative_pose
from macsplat_cli.pipeline.depth.sweep import upsample_depth
from macsplat_cli.pipeline.types import DepthMap, Matches, TwoViewGeometry, View
from macsplat_cli.pipeline.views import ViewConfig, load_views

from support.numerics import assert_within, gamma, unit_roundoff
from support.scenes import apply_homography, orbit_views, pixel_centres, smooth_texture

U32 = unit_roundoff(np.float32)

# ------------------------------------------------------------------------------------ SGM kernels
SGM_SHAPES = [(1, 5, 3), (5, 1, 4), (1, 1, 3), (2, 7, 16), (7, 2, 5), (6, 9, 8), (13, 4, 3), (9, 11, 16)]
SGM_FEW_PLANES = [(4, 6, 1), (5, 3, 2)]  # the aggregation's first and last hypotheses are the same one, or neighbours
SGM_PENALTIES = [(0.04, 0.5, 8.0), (0.1, 0.3, 0.0), (0.3, 0.2, 2.0)]  # the last: P2 < P1, clamped up to P1


@pytest.mark.parametrize("shape", SGM_SHAPES + SGM_FEW_PLANES, ids=lambda s: "x".join(map(str, s)))
@pytest.mark.parametrize("eight_paths", [False, True], ids=["4paths", "8paths"])
@pytest.mark.parametrize(("p1", "p2", "edge_gamma"), SGM_PENALTIES)
def test_aggregate_matches_reference(
    shape: tuple[int, int, int], eight_paths: bool, p1: float, p2: float, edge_gamma: float
) -> None:
    """Numba ``aggregate`` equals the PyTorch reference on random volumes (non-square, thin, D = 3 … 16)."""
    rng = np.random.default_rng(sum(shape) * 7 + int(eight_paths))
    cost = rng.random(shape, dtype=np.float32)
    gray = rng.random(shape[:2], dtype=np.float32)
    gray[:, : shape[1] // 2] += 0.5  # an intensity edge: P2 varies along the paths
    out = _sgm_kernels.aggregate(cost, gray, p1, p2, edge_gamma, eight_paths)
    ref = _sgm_reference.aggregate_reference(
        torch.from_numpy(cost), torch.from_numpy(gray), p1, p2, edge_gamma, eight_paths
    )
    assert out.shape == shape and out.dtype == np.float32
    n_paths = 8 if eight_paths else 4
    # One path step: the twin rounds ≤ 6 float32 operations (P2/(1 + γ|ΔI|): 3; the + P1 or + P2; C + best; − min),
    # the kernel 1 (its arithmetic is float64 up to the float32 store), each of a value ≤ M = max C + P1 + max(P1, P2)
    # (L − min L ≤ C + P2). min and + are 1-Lipschitz, so a path of n pixels drifts by ≤ (n − 1)·7u·M; the n_paths
    # path costs are then summed in two orders (2γ_{n_paths} of the total).
    M = float(cost.max()) + p1 + max(p1, p2)
    tol = n_paths * (max(shape[:2]) - 1) * 7 * U32 * M + 2 * gamma(n_paths, np.float32) * np.abs(ref.numpy())
    assert_within(out, ref.numpy(), tol, "SGM aggregate, Numba vs twin")
    # each path adds at least C(p, ·)'s min (exactly: L ≥ C in the kernel), then n_paths float32 additions
    least = n_paths * cost.min(axis=2, keepdims=True)
    assert (out >= least - gamma(n_paths + 1, np.float32) * least).all()


@pytest.mark.parametrize("shape", SGM_SHAPES, ids=lambda s: "x".join(map(str, s)))
def test_winner_matches_reference(shape: tuple[int, int, int]) -> None:
    """Numba ``winner`` (argmin, parabolic offset, uniqueness) equals the PyTorch reference."""
    rng = np.random.default_rng(sum(shape))
    agg = rng.random(shape, dtype=np.float32) * 4.0
    idx, off, uniq = _sgm_kernels.winner(agg)
    r_idx, r_off, r_uniq = _sgm_reference.winner_reference(torch.from_numpy(agg))
    assert idx.dtype == np.int32 and off.dtype == np.float32 and uniq.dtype == np.float32
    np.testing.assert_array_equal(idx, r_idx.numpy())  # (a) comparisons of the same float32 values are exact
    np.testing.assert_array_equal(idx, agg.argmin(axis=2))
    # offset o = ½(a − c)/(a − 2b + c): the twin rounds in float32 (den: a − 2b then + c, ≤ u(|a − 2b| + |den|);
    # a − c and the quotient: 2u), the kernel in float64 with one float32 store (u); clamping is 1-Lipschitz.
    k = np.clip(idx, 1, shape[2] - 2)[..., None].astype(np.int64)
    a, b, c = (np.take_along_axis(agg.astype(np.float64), k + j, 2)[..., 0] for j in (-1, 0, 1))
    den = a - 2 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        o = np.abs(0.5 * (a - c) / den)
        off_tol = np.where(den > 0, o * (U32 * (np.abs(a - 2 * b) + den) / den + 3 * U32) + U32 * np.minimum(o, 0.5), 0)
    assert_within(off, r_off.numpy(), off_tol, "parabolic offset")
    # uniqueness (second − best)/second ∈ [0, 1]: the twin's subtraction and division (2u), the kernel's store (u)
    assert_within(uniq, r_uniq.numpy(), 3 * U32 * np.abs(r_uniq.numpy()), "uniqueness")
    assert (np.abs(off) <= 0.5).all() and ((uniq >= 0) & (uniq <= 1)).all()


def test_winner_hand_computed() -> None:
    """Costs [4, 1, 2, 3, 6]: best 1, second (two or more steps away) 3 → uniqueness 2/3; parabola offset
    0.5·(4 − 2)/(4 − 2 + 2) = 0.25. A minimum at the end has no offset."""
    agg = np.array([[[4.0, 1.0, 2.0, 3.0, 6.0], [6.0, 5.0, 4.0, 3.0, 1.0]]], np.float32)
    for idx, off, uniq in (_sgm_kernels.winner(agg), _sgm_reference.winner_reference(torch.from_numpy(agg))):
        assert np.asarray(idx).tolist() == [[1, 4]]
        np.testing.assert_array_equal(np.asarray(off), [[0.25, 0.0]])  # 0.5·2/4: every step exact in binary
        # 2/3 is one rounding of a value < 1 (≤ u); 3/4 is exact
        assert_within(np.asarray(uniq), [[2.0 / 3.0, (4.0 - 1.0) / 4.0]], U32, "uniqueness")


# ------------------------------------------------------------------------------------ push-pull
def _levels(shape: tuple[int, int]) -> int:
    """The number of push-pull levels above the image (halving, rounding up, to one pixel)."""
    return max(math.ceil(math.log2(max(shape))), 0)


def test_relative_pose_of_view_1_inverts_view_0() -> None:
    """``relative_pose(g, 1)`` takes camera-1 points back to camera 0: composed with view 0's, the identity."""
    rng = np.random.default_rng(0)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R *= np.sign(np.linalg.det(R))
    t = rng.normal(size=3)
    idx = np.zeros(0, np.int64)
    none = Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.float32), idx, idx)
    g = TwoViewGeometry(R, t, np.eye(3), np.eye(3), none)
    (R0, t0), (R1, t1) = relative_pose(g, 0), relative_pose(g, 1)
    X = rng.normal(size=(10, 3))
    np.testing.assert_allclose((X @ R0.T + t0) @ R1.T + t1, X, atol=1e-12)


def test_carry_depth_lands_where_the_point_projects() -> None:
    """Each pixel with a depth lands, in the other view, on the pixel its 3D point projects into; pixels without
    a depth, behind the other camera or outside its image are not carried."""
    rng = np.random.default_rng(1)
    h, w, ho, wo = 12, 16, 10, 14
    K = np.array([[20.0, 0.5, 8.0], [0.0, 21.0, 6.0], [0.0, 0.0, 1.0]])
    K_o = np.array([[18.0, 0.0, 7.0], [0.0, 18.0, 5.0], [0.0, 0.0, 1.0]])
    a = 0.1
    R = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    t = np.array([-0.3, 0.05, 0.1])
    depth = rng.uniform(1.0, 3.0, (h, w)).astype(np.float32)
    depth[0, :4] = 0.0  # no depth
    q, z, inside, sel = carry_depth(depth, K, K_o, R, t, (ho, wo))
    ys, xs = np.nonzero(depth > 0)
    np.testing.assert_array_equal(sel, ys * w + xs)
    X = np.c_[xs + 0.5, ys + 0.5, np.ones(len(xs))] @ np.linalg.inv(K).T * depth[ys, xs, None]
    Xo = X @ R.T + t
    uv = Xo @ K_o.T
    uv = uv[:, :2] / uv[:, 2:]
    expect_in = (Xo[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < wo) & (uv[:, 1] >= 0) & (uv[:, 1] < ho)
    assert 0 < expect_in.sum() < len(xs)  # the case covers both
    np.testing.assert_array_equal(inside, expect_in)
    np.testing.assert_allclose(z, Xo[:, 2], rtol=1e-12)
    flat = np.floor(uv[:, 1]).astype(np.int64) * wo + np.floor(uv[:, 0]).astype(np.int64)
    np.testing.assert_array_equal(q[inside], flat[expect_in])


@pytest.mark.parametrize("shape", [(37, 53), (1, 9), (9, 1), (64, 64), (5, 3)])
def test_push_pull_fills_and_keeps_full_weight_samples(shape: tuple[int, int]) -> None:
    """Every pixel gets a finite value within the samples' range; samples of weight ≥ 1 are kept exactly."""
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    values = rng.uniform(1.0, 5.0, shape).astype(np.float32)
    weights = np.where(rng.random(shape) < 0.1, rng.choice([1.0, 2.5], shape), 0.0).astype(np.float32)
    weights.flat[rng.integers(values.size)] = 1.0  # at least one sample
    weights[(weights == 0) & (rng.random(shape) < 0.05)] = 0.4  # a few light samples
    out = push_pull(values, weights)
    assert out.shape == shape and out.dtype == np.float32 and np.isfinite(out).all()
    np.testing.assert_array_equal(out[weights == 1.0], values[weights == 1.0])
    # v·w/w: two float32 roundings (the blend with a = 1 keeps ``own`` exactly)
    np.testing.assert_allclose(out[weights > 1.0], values[weights > 1.0], rtol=gamma(2, np.float32), atol=0)
    # Weighted means of samples in [lo, hi]: level k of the push sums 4ᵏ products in k 4-term steps (vw: γ_{3k+1},
    # w: γ_{3k}), its mean vw/w adds u, and each of the K pull levels blends a·own + (1 − a)·up (γ₃ of the larger):
    # the result stays within [lo, hi] up to γ_{9K+3}·hi, K = ⌈log₂ max(H, W)⌉ levels.
    sampled = values[weights > 0]
    slack = gamma(9 * _levels(shape) + 3, np.float32) * float(sampled.max())
    assert out.min() >= sampled.min() - slack and out.max() <= sampled.max() + slack


@pytest.mark.parametrize("weight", [1.0, 0.3])
@pytest.mark.parametrize("where", [(0, 0), (20, 33), (40, 10)])
def test_push_pull_single_sample_is_constant(weight: float, where: tuple[int, int]) -> None:
    """One sample anywhere, of any weight: the whole image takes its value."""
    values = np.zeros((41, 34), np.float32)
    weights = np.zeros_like(values)
    values[where] = 2.75
    weights[where] = weight
    values[0, 1] = 100.0  # a value without weight is ignored
    # The sample's own mean fl(fl(v·w)/w) is 2 roundings; each of the K pull levels blends it with the coarser
    # estimate of the same value (γ₃); sums with zero weights are exact.
    np.testing.assert_allclose(push_pull(values, weights), 2.75, rtol=gamma(2 + 3 * _levels(values.shape), np.float32))


# ------------------------------------------------------------------------------------ plane sweep
def _local_variance(img: np.ndarray, k: int) -> np.ndarray:
    """Variance over the k × k window centred on each pixel (edge pixels: their clipped window)."""
    pad = np.pad(img.astype(np.float64), k // 2, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(pad, (k, k))
    return win.var(axis=(-1, -2))


def test_plane_sweep_minimum_at_the_true_plane() -> None:
    """A fronto-parallel textured plane at depth 2, rendered exactly in both views: the ZNCC cost is ~0 and
    minimal at the true plane; windows that leave the source cost 0.5; affine intensity changes do not matter."""
    w, h = 128, 96
    K = np.array([[100.0, 0.0, 64.0], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]])
    R = S.rotation_about((0.1, 1.0, 0.0), 3.0)
    t = np.array([0.3, 0.05, 0.02])
    inv_depths = np.linspace(0.2, 1.0, 17)
    true_k = 6
    rho = inv_depths[true_k]  # depth 2 (with t ≈ 0.3, one plane step moves the image by ~1.5 px)
    H_true = K @ (R + np.outer(t, [0.0, 0.0, rho])) @ np.linalg.inv(K)  # reference pixel → source pixel
    tex = smooth_texture(np.random.default_rng(0))
    pix = pixel_centres(w, h)
    ref = tex(pix).reshape(h, w)
    src = tex(apply_homography(np.linalg.inv(H_true), pix)).reshape(h, w)  # texture fixed on the plane
    cost, has_window = plane_sweep_cost(ref, src, K, K, R, t, inv_depths, 5)
    assert cost.shape == (h, w, len(inv_depths)) and cost.dtype == np.float32
    assert has_window.shape == (h, w) and has_window.dtype == bool

    p_src = apply_homography(H_true, pix).reshape(h, w, 2)
    inside = np.all((p_src > 5.0) & (p_src < np.array([w, h]) - 5.0), axis=-1)
    outside = np.any((p_src < -5.0) | (p_src > np.array([w, h]) + 5.0), axis=-1)
    inner = np.zeros((h, w), bool)
    inner[3:-3, 3:-3] = True  # the reference window itself must be inside the reference image
    good = inside & inner
    assert good.mean() > 0.5 and outside.any()
    # (d) measured: every good pixel's minimum at the true plane, median cost 8.4e-5 there
    assert np.mean(cost[good].argmin(axis=1) == true_k) > 0.97
    assert np.median(cost[good, true_k]) < 0.01
    np.testing.assert_array_equal(cost[outside, true_k], 0.5)
    assert has_window[good].all()

    # ZNCC: an exposure change (gain and offset) leaves the cost of textured windows unchanged
    brighter, _ = plane_sweep_cost(ref, 0.6 * src + 0.3, K, K, R, t, inv_depths, 5)
    textured = good & (_local_variance(ref, 5) > 2.5e-3)  # flat windows are regularised by an ε
    assert textured.mean() > 0.4
    # (d) not rounding: ZNCC's ε = 1e-4 (ncc = cov/√(var_r·var_w + ε²)) makes the cost depend on the gain where
    # var_r·var_w is not ≫ ε²: measured 1.69e-3 on these windows, 1.73e-3 with float64 images (so rounding, of any
    # kernel set, moves it by < 1e-4): bound 2e-3
    np.testing.assert_allclose(brighter[textured], cost[textured], atol=2e-3)
    assert np.mean(brighter[good].argmin(axis=1) == true_k) > 0.97


# ------------------------------------------------------------------------------------ estimate_depths
def _check_coverage(depths: list[DepthMap], views: list[View]) -> None:
    for dm, v in zip(depths, views):
        assert dm.depth.shape == (v.height, v.width) and dm.depth.dtype == np.float32
        # every pixel inside the mask has a depth, unless both-view fusion proved it a wrong second layer
        holes = v.mask & (dm.depth == 0)
        assert int(holes.sum()) == dm.fill_counts["dropped_free_space"] < 0.1 * v.mask.sum()
        assert (dm.confidence[v.mask & ~holes] > 0).all() and (dm.confidence[holes] == 0).all()
        assert (dm.depth[~v.mask] == 0).all() and (dm.confidence[~v.mask] == 0).all()
        assert dm.measured is not None and not (dm.measured & ~v.mask).any()
        assert (dm.depth[dm.measured] > 0).all()
        assert ((dm.confidence >= 0) & (dm.confidence <= 1)).all()


@pytest.mark.parametrize(("kind", "angle"), [("object", 10.0), ("room", 15.0)])
def test_estimate_depths_with_ground_truth_geometry(kind: str, angle: float) -> None:
    """Synthetic orbit with its true pose (unit baseline) and true correspondences as inliers: the measured
    pixels have median relative depth error < 3 %, and every pixel inside the masks gets a depth."""
    views, geometry, gts = orbit_views(kind, angle)
    views[0].mask[:, : views[0].mask.shape[1] // 5] = False  # the user masked out a strip of view 0
    depths = estimate_depths(views, geometry)
    assert len(depths) == 2
    _check_coverage(depths, views)
    # (d) accuracy against the ground truth, not rounding: measured coverage ≥ 0.60, median ≤ 0.61 %, share
    # within 10 % ≥ 0.975 (object and room, both views); the bounds leave ≥ 1.5× / 5× / 2.5× margins
    for dm, gt in zip(depths, gts):
        meas = dm.measured & (gt > 0)
        assert meas.mean() > 0.4
        rel = np.abs(dm.depth[meas] - gt[meas]) / gt[meas]
        assert np.median(rel) < 0.03
        assert np.mean(rel < 0.1) > 0.9


# Middlebury 2014 "Motorcycle" (quarter size, as shipped by scikit-image): calibration of the original pair
# scaled by 1/4; OpenCV pixel-centre convention (integers), so ours is +0.5.
MOTO_F, MOTO_CX0, MOTO_CY, MOTO_DOFFS = 994.978, 311.193, 254.877, 31.086  # baseline 193.001 mm


def _motorcycle_views(tmp_path: Path, size: int) -> tuple[list[View], np.ndarray, tuple[int, int]]:
    """The pair written as PNGs with a two-camera intrinsics file, read back by ``load_views``."""
    skimage_data = pytest.importorskip("skimage.data")
    left, right, disp = skimage_data.stereo_motorcycle()
    h0, w0 = left.shape[:2]
    save_image(tmp_path / "im0.png", left)
    save_image(tmp_path / "im1.png", right)

    def cam(name: str, cx: float) -> Camera:
        K = np.array([[MOTO_F, 0.0, cx + 0.5], [0.0, MOTO_F, MOTO_CY + 0.5], [0.0, 0.0, 1.0]])
        return Camera(name, w0, h0, K, np.eye(4))

    # listed in the opposite order of the photos: the cameras must be matched by name
    save_cameras(tmp_path / "cams.json", CameraSet([cam("im1", MOTO_CX0 + MOTO_DOFFS), cam("im0", MOTO_CX0)]))
    config = ViewConfig(size=size, intrinsics=tmp_path / "cams.json")
    views = load_views([tmp_path / "im0.png", tmp_path / "im1.png"], config)
    return views, disp, (w0, h0)


def test_estimate_depths_middlebury_motorcycle(tmp_path: Path) -> None:
    """Real stereo photos with the true rectified geometry (R = I, t = −x): median relative depth error < 2 % and
    δ<1.25 > 0.9 over all pixels with a ground-truth disparity."""
    views, disp, (w0, h0) = _motorcycle_views(tmp_path, 512)
    v0, v1 = views
    w, h = v0.width, v0.height
    assert (w, h) == (512, 352) and v0.intrinsics_source == v1.intrinsics_source == "file"
    sx, sy = w / w0, h / h0
    # each photo got its own camera: float64, cx scaled by sx (one rounding each), then their difference
    cx_err = gamma(3, np.float64) * (abs(v1.K[0, 2]) + abs(v0.K[0, 2]))
    assert v1.K[0, 2] - v0.K[0, 2] == pytest.approx(MOTO_DOFFS * sx, rel=0, abs=cx_err)

    finite = np.isfinite(disp)
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(finite)
    pick = rng.choice(len(xs), 2000, replace=False)
    xl, yl = xs[pick] + 0.5, ys[pick] + 0.5
    xr = xl - disp[ys[pick], xs[pick]]  # Middlebury: x_right = x_left − d
    n = len(pick)
    inliers = Matches(
        np.c_[xl * sx, yl * sy], np.c_[xr * sx, yl * sy], np.ones(n, np.float32), np.arange(n), np.arange(n)
    )
    geometry = TwoViewGeometry(np.eye(3), np.array([-1.0, 0.0, 0.0]), v0.K, v1.K, inliers)
    depths = estimate_depths(views, geometry)
    _check_coverage(depths, views)

    # ground truth at the working pixels: the original pixel under each working pixel centre
    gt_depth = np.where(finite, MOTO_F / (np.where(finite, disp, 0.0) + MOTO_DOFFS), 0.0)  # in baselines
    col = ((np.arange(w) + 0.5) / sx).astype(int)
    row = ((np.arange(h) + 0.5) / sy).astype(int)
    gt = gt_depth[np.ix_(row, col)]
    has_gt = finite[np.ix_(row, col)]
    est = depths[0].depth[has_gt]
    ref = gt[has_gt]
    rel = np.abs(est - ref) / ref
    with np.errstate(divide="ignore"):  # pixels dropped by the fusion (est = 0) count as failures
        ratio = np.maximum(est / ref, ref / est)
    # (d) measured: median 0.78 %, δ<1.25 0.917, measured share 0.81 with median 0.59 %
    assert np.median(rel) < 0.02
    assert np.mean(ratio < 1.25) > 0.9
    meas = depths[0].measured[has_gt]
    assert meas.mean() > 0.5 and np.median(rel[meas]) < 0.01  # measured pixels are the more accurate ones


def test_plane_sweep_window_validity_uses_source_size() -> None:
    """A source image smaller than the reference: pixels whose windows map outside it have no valid window."""
    w, h = 64, 48
    K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    ref = smooth_texture(np.random.default_rng(1))(pixel_centres(w, h)).reshape(h, w)
    src = np.ascontiguousarray(ref[:, : w // 2])  # the source only covers the left half (same K, no motion)
    cost, has_window = plane_sweep_cost(ref, src, K, K, np.eye(3), np.zeros(3), np.array([0.5]), 5)
    assert has_window[:, 3 : w // 2 - 3].all()
    assert not has_window[:, w // 2 + 3 :].any()
    np.testing.assert_array_equal(cost[:, w // 2 + 3 :, 0], 0.5)
    # (d) identical pixels: ZNCC = var/√(var² + ε²) ≈ 1 − ε²/(2var²), a model effect of the ε; measured median
    # 1.3e-5 and max 2.2e-3 (the flattest windows), bounds 1e-3 and 0.01
    same = cost[3:-3, 3 : w // 2 - 3, 0]
    assert np.median(same) < 1e-3 and same.max() < 0.01


def test_upsample_depth_is_two_joint_bilateral_filters() -> None:
    """The upsampling filters the weighted inverse depth and the weights as two channels of one joint bilateral
    filter: each channel equals its own one-channel filter bit for bit (the same guide, the same weights)."""
    import cv2

    rng = np.random.default_rng(4)
    H, W = 60, 80
    guide = smooth_texture(rng)(pixel_centres(W, H)).reshape(H, W).astype(np.float32)
    depth = (1.0 + rng.random((H // 2, W // 2))).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0.0
    conf = rng.random(depth.shape).astype(np.float32)
    got, got_c = upsample_depth(depth, conf, guide)
    d_up = cv2.resize(depth, (W, H), interpolation=cv2.INTER_NEAREST)
    valid = d_up > 0
    inv = np.where(valid, 1.0 / np.maximum(d_up, 1e-12), 0.0).astype(np.float32)
    wgt = valid.astype(np.float32)
    num = cv2.ximgproc.jointBilateralFilter(guide, inv * wgt, -1, 0.08, 2.0)
    den = cv2.ximgproc.jointBilateralFilter(guide, wgt, -1, 0.08, 2.0)
    inv_s = np.where(valid & (den > 1e-3), num / np.maximum(den, 1e-6), 0.0)
    want = np.where(inv_s > 0, 1.0 / np.maximum(inv_s, 1e-12), 0.0).astype(np.float32)
    np.testing.assert_array_equal(got, want)
    assert (got > 0).mean() > 0.5 and ((got_c > 0) == (got > 0)).all()
