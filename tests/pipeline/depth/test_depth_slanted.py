"""Slanted-plane (PatchMatch) refinement of the dense depth: the Numba kernels against their NumPy twins, the
plane-induced cost against the plane sweep, recovery of a slanted plane, and ``estimate_depths`` with the
refinement on a wide synthetic orbit."""

from __future__ import annotations

import numpy as np
import pytest

from macsplat_cli.datasets import synthetic as S
from macsplat_cli.pipeline.depth import DepthConfig, colour_outliers, estimate_depths, plane_sweep_cost
from macsplat_cli.pipeline.depth import _patchmatch_kernels as PK
from macsplat_cli.pipeline.depth import _patchmatch_reference as PR
from macsplat_cli.pipeline.types import TwoViewGeometry, View

from support.numerics import unit_roundoff
from support.scenes import apply_homography, orbit_views, pixel_centres, smooth_texture

U32 = unit_roundoff(np.float32)

K = np.array([[100.0, 0.0, 64.0], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]])
W, H = 128, 96


def _slanted_pair(seed: int = 0) -> dict:
    """A textured plane whose inverse depth is ``m · (u, v, 1)`` in the reference (tilted ~60° about the vertical
    axis), seen by a source camera 1 unit away, turned 25°: the plane is foreshortened very differently in the two
    views (the source image of a reference pixel step is 0.52 px wide at the centre)."""
    R = S.rotation_about((0.0, 1.0, 0.0), 25.0)
    t = np.array([-1.0, 0.0, 0.1])
    m = np.array([0.004, 0.0005, 0.0])
    m[2] = 0.45 - m[0] * 64.0 - m[1] * 48.0  # ρ = 0.45 at the image centre; slope s_u = g_u·f/ρ ≈ 0.9
    A = K @ R @ np.linalg.inv(K)
    b = K @ t
    H_plane = A + np.outer(b, m)  # reference pixel → source pixel through the plane
    tex = smooth_texture(np.random.default_rng(seed))
    pix = pixel_centres(W, H)
    ref = tex(pix).reshape(H, W).astype(np.float64)
    src = tex(apply_homography(np.linalg.inv(H_plane), pix)).reshape(H, W).astype(np.float64)
    ys, xs = np.mgrid[0:H, 0:W]
    rho = m[0] * (xs + 0.5) + m[1] * (ys + 0.5) + m[2]
    return dict(ref=ref, src=src, A=A, b=b, R=R, t=t, m=m, rho=rho)


# ------------------------------------------------------------------------------------ kernels vs twins
# (a) The NumPy twins run the kernels' IEEE operations (+, −, ×, ÷, √, truncation, comparisons) in the same
# order — window sums accumulated offset by offset, per pixel, no reductions that could be reordered — and
# Numba compiles without fastmath (no reassociation, no FMA contraction), so each result is correctly rounded
# the same way on every CPU: the outputs are bitwise equal, and the tests say so.
def test_uniform_matches_reference_and_is_uniform() -> None:
    pix = np.arange(20000)
    for seed, it, draw in ((0, 0, 0), (7, 3, 5), (123456, 11, 8)):
        ref = PR.uniform_reference(seed, it, pix, draw)
        got = np.array([PK.uniform(seed, it, int(p), draw) for p in pix[:300]])
        np.testing.assert_array_equal(got, ref[:300])
        assert ref.min() >= 0.0 and ref.max() < 1.0
        assert abs(ref.mean() - 0.5) < 0.01 and abs(np.mean(ref < 0.25) - 0.25) < 0.01
    # different draws / iterations give different streams
    assert np.mean(PR.uniform_reference(0, 0, pix, 0) == PR.uniform_reference(0, 0, pix, 1)) < 0.01
    assert np.mean(PR.uniform_reference(0, 0, pix, 0) == PR.uniform_reference(0, 1, pix, 0)) < 0.01


@pytest.mark.parametrize(("radius", "step"), [(1, 1), (2, 2), (3, 1)])
@pytest.mark.parametrize("shape", [(24, 30), (31, 27)])
def test_plane_cost_matches_reference(radius: int, step: int, shape: tuple[int, int]) -> None:
    """Random images and planes (some leaving the source, some behind a camera): equal to the NumPy twin."""
    rng = np.random.default_rng(radius * 10 + step + shape[0])
    h, w = shape
    ref = rng.random((h, w))
    src = rng.random((h + 3, w - 2))
    A = np.eye(3) + rng.normal(0, 0.02, (3, 3)) * np.array([[1.0], [1.0], [0.01]])
    b = np.array([-2.0, 0.3, 0.05])
    n = 400
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    rho = rng.uniform(-0.1, 1.5, n)
    gu, gv = rng.normal(0, 0.02, n), rng.normal(0, 0.02, n)
    want = PR.plane_cost_reference(ref, src, A, b, ys, xs, rho, gu, gv, radius, step)
    got = np.array([PK.plane_cost(ref, src, A, b, y, x, r, u, v, radius, step)
                    for y, x, r, u, v in zip(ys, xs, rho, gu, gv)])  # fmt: skip
    np.testing.assert_array_equal(got, want)
    valid = want < PK.INVALID
    assert 0.2 < valid.mean() < 0.95  # both kinds are exercised
    assert ((want[valid] >= 0) & (want[valid] <= 1)).all()
    full = PR.initial_costs_reference(ref, src, A, b, np.full((h, w), 0.5), np.zeros((h, w)), np.zeros((h, w)),
                                      radius, step)  # fmt: skip
    got_full = PK.initial_costs(ref, src, A, b, np.full((h, w), 0.5), np.zeros((h, w)), np.zeros((h, w)), radius, step)
    np.testing.assert_array_equal(got_full, full)


@pytest.mark.parametrize("iters", [1, 3])
@pytest.mark.parametrize("shape", [(11, 14), (16, 9)])
def test_refine_matches_reference(iters: int, shape: tuple[int, int]) -> None:
    """The red-black PatchMatch equals its NumPy twin (planes, costs; inactive pixels untouched)."""
    pair = _slanted_pair(1)
    h, w = shape
    ref = np.ascontiguousarray(pair["ref"][30 : 30 + h, 40 : 40 + w])
    src = pair["src"]
    rng = np.random.default_rng(iters + h)
    # the crop's pixel (y, x) is the full image's (y + 30, x + 40): move the principal point
    Kc = K.copy()
    Kc[0, 2] -= 40
    Kc[1, 2] -= 30
    A = K @ pair["R"] @ np.linalg.inv(Kc)
    b = K @ pair["t"]
    rho = rng.uniform(0.3, 0.6, (h, w))
    gu = rng.normal(0, 0.002, (h, w))
    gv = rng.normal(0, 0.002, (h, w))
    active = rng.random((h, w)) < 0.7
    cost = PK.initial_costs(ref, src, A, b, rho, gu, gv, 2, 1)
    state_nb = [a.copy() for a in (rho, gu, gv, cost)]
    state_np = [a.copy() for a in (rho, gu, gv, cost)]
    args = (0.1, 1.2, 100.0, 3.0, 2, 1, iters, 5)
    PK.refine(ref, src, A, b, *state_nb, active, *args)
    PR.refine_reference(ref, src, A, b, *state_np, active, *args)
    for a_nb, a_np in zip(state_nb, state_np):
        np.testing.assert_array_equal(a_nb, a_np)
    for a_nb, a0 in zip(state_nb, (rho, gu, gv, cost)):
        np.testing.assert_array_equal(a_nb[~active], a0[~active])
    assert (state_nb[3][active] <= cost[active]).all()  # a pixel's cost never rises
    assert (state_nb[3][active] < cost[active]).mean() > 0.5


def test_refine_skips_planes_it_already_evaluated() -> None:
    """A pixel does not evaluate again a neighbour's plane it evaluated in its previous phase when that neighbour has
    not changed since (a fixed seed): one active pixel among seeds evaluates its distinct neighbour planes in the
    first iteration, then only its three random perturbations per iteration; the planes equal the NumPy twin's."""
    pair = _slanted_pair(2)
    h, w = 24, 24
    ref = np.ascontiguousarray(pair["ref"][30 : 30 + h, 40 : 40 + w])
    Kc = K.copy()
    Kc[0, 2] -= 40
    Kc[1, 2] -= 30
    A, b = K @ pair["R"] @ np.linalg.inv(Kc), K @ pair["t"]
    rng = np.random.default_rng(3)
    rho = rng.uniform(0.3, 0.6, (h, w))
    gu, gv = rng.normal(0, 0.002, (h, w)), rng.normal(0, 0.002, (h, w))
    active = np.zeros((h, w), bool)
    active[12, 12] = True  # its 8 neighbours are seeds: their planes never change
    cost = PK.initial_costs(ref, pair["src"], A, b, rho, gu, gv, 2, 1)
    runs = {}
    for iters in (1, 3):
        state = [a.copy() for a in (rho, gu, gv, cost)]
        runs[iters] = PK.refine(ref, pair["src"], A, b, *state, active, 0.1, 1.2, 100.0, 3.0, 2, 1, iters, 5)
        want = [a.copy() for a in (rho, gu, gv, cost)]
        PR.refine_reference(ref, pair["src"], A, b, *want, active, 0.1, 1.2, 100.0, 3.0, 2, 1, iters, 5)
        for got, ref_state in zip(state, want):
            np.testing.assert_array_equal(got, ref_state)
    assert runs[1] == 8 + 3  # the seeds' 8 planes (random: all distinct, in range) and 3 perturbations
    assert runs[3] == runs[1] + 2 * 3


# ------------------------------------------------------------------------------------ behaviour
def test_plane_cost_fronto_matches_plane_sweep() -> None:
    """A zero slope is a fronto-parallel plane: the cost equals the plane sweep's (OpenCV warp, box filters) up
    to the sweep's float32 rounding."""
    pair = _slanted_pair(2)
    ref, src = pair["ref"].astype(np.float32), pair["src"].astype(np.float32)
    rhos = np.array([0.3, 0.45, 0.6])
    sweep, _ = plane_sweep_cost(ref, src, K, K, pair["R"], pair["t"], rhos, 5)
    ys, xs = np.mgrid[4 : H - 4 : 3, 4 : W - 4 : 3]
    ys, xs = ys.ravel(), xs.ravel()
    # (c) float32 sweep against the float64 twin: the sweep's 5×5 means (float64 box sums, one float32 store) and
    # var = E[x²] − μ², cov = E[xy] − μμ' carry ≤ 6u·E[x²] each; ncc = cov/√(var·var') then moves by
    # ≤ 6u·E[x²]·(1/√(var·var') + (1/var + 1/var')/2) ≤ 12u·E[x²]/var_min, the cost ½(1 − ncc) by half of it.
    # E[x²] and var_min from the images' 5×5 windows (the warped windows are the same texture); measured 4e-6.
    wins = [np.stack([img[ys + dy, xs + dx] for dy in range(-2, 3) for dx in range(-2, 3)], 1) for img in (ref, src)]
    e2_max = max(float((w.astype(np.float64) ** 2).mean(1).max()) for w in wins)
    var_min = min(float(w.astype(np.float64).var(1).min()) for w in wins)
    tol = 6 * U32 * e2_max / var_min
    for k, r in enumerate(rhos):
        c = PR.plane_cost_reference(pair["ref"], pair["src"], pair["A"], pair["b"], ys, xs,
                                    np.full(len(ys), r), np.zeros(len(ys)), np.zeros(len(ys)), 2, 1)  # fmt: skip
        ok = c < PK.INVALID
        assert ok.mean() > 0.3
        np.testing.assert_allclose(c[ok], sweep[ys[ok], xs[ok], k], rtol=0, atol=tol)


def test_slanted_window_beats_fronto_parallel_on_a_tilted_plane() -> None:
    """On a strongly foreshortened plane the true slanted plane costs ~0, and less than the true depth with a
    fronto-parallel window."""
    pair = _slanted_pair(3)
    m, rho = pair["m"], pair["rho"]
    ys, xs = np.mgrid[6 : H - 6 : 2, 6 : W - 6 : 2]
    ys, xs = ys.ravel(), xs.ravel()
    n = len(ys)
    args = (pair["ref"], pair["src"], pair["A"], pair["b"], ys, xs, rho[ys, xs])
    slanted = PR.plane_cost_reference(*args, np.full(n, m[0]), np.full(n, m[1]), 3, 1)
    fronto = PR.plane_cost_reference(*args, np.zeros(n), np.zeros(n), 3, 1)
    ok = (slanted < PK.INVALID) & (fronto < PK.INVALID)
    # (d) measured: 93 % valid, median slanted cost 1.1e-3, fronto 0.085, slanted lower at every pixel
    assert ok.mean() > 0.3
    assert np.median(slanted[ok]) < 0.01
    assert np.median(fronto[ok]) > 3 * np.median(slanted[ok]) + 0.02
    assert np.mean(slanted[ok] < fronto[ok]) > 0.95


def test_refine_recovers_a_slanted_plane_from_sparse_seeds() -> None:
    """A fronto-parallel start 20 % off, with 2 % of the pixels fixed to the true plane: the refinement carries
    the plane to the rest (inverse depth within 1 %, slope within 0.1 of the truth for most pixels)."""
    pair = _slanted_pair(4)
    ref, src, rho_true, m = pair["ref"], pair["src"], pair["rho"], pair["m"]
    rng = np.random.default_rng(0)
    seeds = rng.random((H, W)) < 0.02
    rho = np.where(seeds, rho_true, 0.8 * rho_true.mean())
    gu = np.where(seeds, m[0], 0.0)
    gv = np.where(seeds, m[1], 0.0)
    cost = PK.initial_costs(ref, src, pair["A"], pair["b"], rho, gu, gv, 2, 2)
    valid = cost < PK.INVALID
    PK.refine(ref, src, pair["A"], pair["b"], rho, gu, gv, cost, ~seeds, 0.05, 2.0, 100.0, 3.0, 2, 2, 4, 0)
    # (d) measured: 92 % of the inner pixels judged, all within 1 % of the true inverse depth, median slope error
    # 2.7e-5, 84 % valid at the start
    judged = ~seeds & (cost < 0.1)
    inner = np.zeros((H, W), bool)
    inner[8:-8, 8:-8] = True
    assert (judged & inner).mean() > 0.4 * inner.mean()
    rel = np.abs(rho - rho_true) / rho_true
    assert np.mean(rel[judged & inner] < 0.01) > 0.9
    s_err = np.abs(gu - m[0]) * 100.0 / rho_true
    assert np.median(s_err[judged & inner]) < 0.1
    assert valid[inner].mean() > 0.5


def test_estimate_depths_slanted_refinement_measures_more_at_45_degrees() -> None:
    """A 45° orbit of the synthetic object with its true geometry: the refinement measures more pixels than the
    plane sweep alone (+30 %), at least as accurately (median < 2 %; 18–21 % of them are > 10 % off either
    way at this baseline), and ``slanted_iters = 0`` turns it off."""
    views, geometry, gts = orbit_views("object", 45.0)
    off = estimate_depths(views, geometry, DepthConfig(slanted_iters=0))
    on = estimate_depths(views, geometry, DepthConfig(slanted_iters=3))
    # (d) measured (view 0, view 1): measured ×1.37/×1.38, median 0.58 %/0.56 % (off: 0.78 %/0.72 %), within 10 %
    # 0.95/0.96 (off: 0.94/0.95), refined share 0.27
    for d_off, d_on, gt in zip(off, on, gts):
        assert d_on.measured.sum() > 1.15 * d_off.measured.sum()
        rel = []
        for d in (d_off, d_on):
            meas = d.measured & (gt > 0)
            rel.append(np.abs(d.depth[meas] - gt[meas]) / gt[meas])
        assert np.median(rel[1]) < 0.02 and np.median(rel[1]) <= np.median(rel[0]) + 1e-3
        assert np.mean(rel[1] < 0.1) > 0.75 and np.mean(rel[1] < 0.1) >= np.mean(rel[0] < 0.1) - 0.01
        assert d_on.fill_counts["slanted_refined"] > 0.1 * d_on.measured.sum()
        assert d_off.fill_counts["slanted_refined"] == 0


# ------------------------------------------------------------------------------------ colour check
def _covisible(views: list[View], geometry: TwoViewGeometry, gt: list) -> np.ndarray:
    """View-0 pixels whose true point is the surface view 1 sees there (not occluded, inside). [H, W] bool"""
    h, w = gt[0].shape
    pix = np.c_[pixel_centres(w, h), np.ones(h * w)]
    X = pix @ np.linalg.inv(views[0].K).T * gt[0].reshape(-1, 1)
    X1 = X @ geometry.R.T + geometry.t
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (X1 @ views[1].K.T)[:, :2] / X1[:, 2:]
    uv = np.nan_to_num(uv, nan=-1.0)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h) & (X1[:, 2] > 0)
    ui, vi = np.clip(uv[:, 0].astype(int), 0, w - 1), np.clip(uv[:, 1].astype(int), 0, h - 1)
    z1 = gt[1][vi, ui]
    return (inside & (np.abs(z1 - X1[:, 2]) < 0.02 * X1[:, 2]) & (gt[0].reshape(-1) > 0)).reshape(h, w)


def test_colour_outliers_flags_wrong_depths_not_exposure() -> None:
    """With the true depth few co-visible pixels disagree in colour, also after an exposure and white-balance
    change of the other photo; a block given a 30 % wrong depth lands on other colours and is flagged."""
    views, geometry, gt = orbit_views("room", 20.0)
    depth = gt[0].astype(np.float32)
    measured = _covisible(views, geometry, gt)
    # (d) measured: co-visible 0.69; flagged 0.4 % (0.1 % after the exposure change); in the wrong block 49 %,
    # outside it 0.4 %
    assert measured.mean() > 0.5
    flagged = colour_outliers(depth, measured, views[0], views[1], geometry, 0, 0.1)
    assert flagged.shape == depth.shape and flagged.dtype == bool
    assert not (flagged & ~measured).any()
    assert flagged.mean() < 0.05
    v1 = views[1]
    darker = View(v1.name, v1.path, np.clip(v1.image * np.array([0.7, 0.8, 0.9], np.float32) + 0.05, 0, 1), v1.mask,
                  v1.K, v1.original_size, v1.intrinsics_source)  # fmt: skip
    assert colour_outliers(depth, measured, views[0], darker, geometry, 0, 0.1).mean() < 0.05
    wrong = depth.copy()
    block = np.zeros(depth.shape, bool)
    block[60:140, 100:220] = True
    wrong[block] *= 1.3
    flagged = colour_outliers(wrong, measured, views[0], views[1], geometry, 0, 0.1)
    assert flagged[block & measured].mean() > 0.4
    assert flagged[~block & measured].mean() < 0.05


def test_estimate_depths_colour_check_counts() -> None:
    """``colour_tol`` turns the colour check on and off; rejected pixels are not measured and are counted, and
    the measured pixels more than 10 % off drop from ~10 % to ~5 % (30° object orbit, true geometry)."""
    views, geometry, gt = orbit_views("object", 30.0)
    on = estimate_depths(views, geometry, DepthConfig(colour_tol=0.1, slanted_iters=0, speckle_size=0.0))
    off = estimate_depths(views, geometry, DepthConfig(colour_tol=0.0, slanted_iters=0, speckle_size=0.0))
    # (d) measured: 7 % rejected; > 10 % off: 5.2 %/4.4 % with the check, 10.5 %/9.3 % without (ratio 0.49/0.47)
    for d_on, d_off, g in zip(on, off, gt):
        assert d_off.fill_counts["colour_rejected"] == 0
        n = d_on.fill_counts["colour_rejected"]
        assert 0 < n < 0.2 * d_off.measured.sum()
        assert d_on.measured.sum() <= d_off.measured.sum() - n + 0.01 * d_off.measured.sum()
        for d in (d_on, d_off):
            meas = d.measured & (g > 0)
            rel = np.abs(d.depth[meas] - g[meas]) / g[meas]
            d.bad = np.mean(rel > 0.1)  # type: ignore[attr-defined]
        assert d_on.bad < 0.7 * d_off.bad  # type: ignore[attr-defined]
