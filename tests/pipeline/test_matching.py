"""Filtered matching: reciprocal nearest neighbours, the ratio confidence, the gate, epipolar guidance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from macsplat_cli.datasets.synthetic import rotation_about
from macsplat_cli.pipeline.matching import (
    MatchConfig,
    guided_matches,
    match_features,
    ratio_distinctiveness,
    reciprocal_nearest_neighbours,
    seeded_reciprocal_neighbours,
)
from macsplat_cli.pipeline.pose import fundamental_from_pose
from macsplat_cli.pipeline.types import Features

from support.numerics import assert_within, gamma, unit_roundoff
from support.scenes import PairFactory, PairSpec

U32 = unit_roundoff(np.float32)


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _random_desc(n: int, dim: int, rng: np.random.Generator) -> np.ndarray:
    return _unit(rng.normal(size=(n, dim)))


def _features(xy: np.ndarray, desc: np.ndarray, conf: np.ndarray | None = None) -> Features:
    n = len(desc)
    return Features(np.asarray(xy, np.float64), desc, np.ones(n, np.float32) if conf is None else conf)


def _sim_err(d0: np.ndarray, d1: np.ndarray) -> float:
    """Bound on the rounding error of any float32 similarity d0ᵢ·d1ⱼ (D-term dot product, in any order):
    γ_D·Σ|d0ᵢₖ d1ⱼₖ| ≤ γ_D·‖d0ᵢ‖‖d1ⱼ‖ (Cauchy–Schwarz)."""
    if d0.size == 0 or d1.size == 0:
        return 0.0
    norms = [float(np.linalg.norm(d.astype(np.float64), axis=1).max()) for d in (d0, d1)]
    return gamma(d0.shape[1], np.float32) * norms[0] * norms[1]


def _conf_tol(d_best: np.ndarray, ds: float, roundings: int) -> np.ndarray:
    """Bound on |Δw| of the joint confidence w = c0·c1, c = conf·(1 − d_best/d_second) with d = √(2 − 2s), when every
    similarity is off by at most ``ds``: |∂c/∂s_best| = 1/(d_best·d_second) and |∂c/∂s_second| = d_best/d_second³
    are both ≤ 1/d_best² (d_second ≥ d_best; sorting top-2 lists is 1-Lipschitz), so |Δc| ≤ 2·ds/d_best²; w adds
    both views' (conf, c ≤ 1); plus ``roundings`` float32 roundings of values ≤ 1 on the two sides together."""
    return 2 * (2 * ds / d_best**2) + roundings * U32


def _pair_distance(d0: np.ndarray, d1: np.ndarray, idx0: np.ndarray, idx1: np.ndarray) -> np.ndarray:
    """L2 distance of each matched pair of unit descriptors, in float64. [K]"""
    return np.linalg.norm(d0[idx0].astype(np.float64) - d1[idx1], axis=1)


def _assert_separated(top: np.ndarray, err: float) -> None:
    """Precondition of comparing a float32 argmax with the float64 one: every best similarity beats the second by
    more than twice the float32 rounding bound, so no rounding can swap them (a data property, checked)."""
    if top.shape[1] == 2 and len(top):
        second = np.where(top[:, 1] > -1.0, top[:, 1], -np.inf)
        assert (top[:, 0] - second > 2 * err).all(), "a near-tie in the test data: the argmax is not determined"


def _brute_force(d0: np.ndarray, d1: np.ndarray) -> tuple[set[tuple[int, int]], np.ndarray, np.ndarray]:
    """Mutual argmax pairs of the full similarity matrix, and the sorted top-2 of every row and column."""
    sim = d0.astype(np.float64) @ d1.astype(np.float64).T
    row_arg, col_arg = sim.argmax(1), sim.argmax(0)
    pairs = {(i, int(row_arg[i])) for i in range(sim.shape[0]) if col_arg[row_arg[i]] == i}
    top_rows = -np.sort(-sim, axis=1)[:, :2]
    top_cols = -np.sort(-sim.T, axis=1)[:, :2]
    return pairs, top_rows, top_cols


def _check_top2(actual: np.ndarray, expected: np.ndarray, m: int, err: float) -> None:
    """The best two similarities; where only one exists, the second is a sentinel no similarity beats. ``err``
    bounds each float32 similarity's rounding; sorting is 1-Lipschitz, so the sorted top-2 are within it too."""
    assert actual.shape == (m, 2)
    k = expected.shape[1]
    assert_within(actual[:, :k], expected, err, "top-2 similarities")
    if k == 1:
        assert (actual[:, 1] <= -1.0).all()


# ------------------------------------------------------------------------------------ reciprocal NN
@pytest.mark.parametrize(
    ("m0", "m1", "dim"),
    [(37, 53, 16), (53, 37, 8), (1, 20, 16), (20, 1, 16), (1, 1, 4), (64, 64, 32), (5, 200, 24)],
)
@pytest.mark.parametrize("max_block_elems", [1, 7, 64, 1 << 24])
def test_reciprocal_nn_equals_brute_force(m0: int, m1: int, dim: int, max_block_elems: int) -> None:
    """Blocked mutual NN and top-2 similarities equal those of the full similarity matrix, for any block size."""
    rng = np.random.default_rng(m0 * 1000 + m1)
    d0, d1 = _random_desc(m0, dim, rng), _random_desc(m1, dim, rng)
    nn = reciprocal_nearest_neighbours(d0, d1, max_block_elems=max_block_elems)
    pairs, top_rows, top_cols = _brute_force(d0, d1)
    err = _sim_err(d0, d1)
    _assert_separated(top_rows, err)
    _assert_separated(top_cols, err)
    got = set(zip(nn.idx0.tolist(), nn.idx1.tolist()))
    assert got == pairs
    assert len(got) == len(nn.idx0)  # no duplicates
    assert nn.idx0.dtype == np.int64 and nn.idx1.dtype == np.int64
    # float32 dot of D terms against float64 (of the same float32 inputs): ≤ γ_D·Σ|terms| each
    terms = d0[nn.idx0].astype(np.float64) * d1[nn.idx1]
    assert_within(nn.sim, terms.sum(1), gamma(dim, np.float32) * np.abs(terms).sum(1), "similarities")
    _check_top2(nn.top2_0, top_rows, m0, err)
    _check_top2(nn.top2_1, top_cols, m1, err)


def test_reciprocal_nn_recovers_a_permutation() -> None:
    """Noisy permuted copies are each other's mutual nearest neighbours, whatever the block size."""
    rng = np.random.default_rng(3)
    d0 = _random_desc(100, 32, rng)
    perm = rng.permutation(100)
    d1 = _unit(d0[perm] + 0.05 * rng.normal(size=(100, 32)))
    for block in (1, 100, 1 << 24):
        nn = reciprocal_nearest_neighbours(d0, d1, max_block_elems=block)
        assert len(nn.idx0) == 100
        np.testing.assert_array_equal(perm[nn.idx1], nn.idx0)


@pytest.mark.parametrize(("m0", "m1", "dim"), [(37, 53, 4), (120, 90, 3), (64, 64, 8)])
def test_seeded_reciprocal_neighbours_reach_only_mutual_pairs(m0: int, m1: int, dim: int) -> None:
    """Seeded walks end at mutual nearest neighbours of the full sets (brute force); seeded everywhere, they find
    them all; from sparse seeds, a subset containing the pairs of the seeds that are mutual; any block size."""
    rng = np.random.default_rng(m0 + m1 + dim)
    d0, d1 = _random_desc(m0, dim, rng), _random_desc(m1, dim, rng)
    pairs, top_rows, top_cols = _brute_force(d0, d1)
    err = _sim_err(d0, d1)
    _assert_separated(top_rows, err)  # no near-ties: float32 argmax agrees with float64's
    _assert_separated(top_cols, err)
    t0, t1 = torch.from_numpy(d0), torch.from_numpy(d1)
    for block in (1, 50, 1 << 24):
        i0, i1 = seeded_reciprocal_neighbours(t0, t1, torch.arange(m0), max_block_elems=block)
        assert set(zip(i0.tolist(), i1.tolist())) == pairs
    seeds = torch.arange(0, m0, 7)
    i0, i1 = seeded_reciprocal_neighbours(t0, t1, seeds)
    got = set(zip(i0.tolist(), i1.tolist()))
    assert len(got) == len(i0) and torch.all(i0[1:] >= i0[:-1])  # distinct, sorted by idx0
    sim = d0.astype(np.float64) @ d1.astype(np.float64).T

    def walk(x: int, rounds: int) -> tuple[int, int] | None:  # the definition, in float64
        for _ in range(rounds):
            y = int(sim[x].argmax())
            back = int(sim[:, y].argmax())
            if back == x:
                return x, y
            x = back
        return None

    for rounds in (1, 10):
        want = {e for e in (walk(int(x), rounds) for x in seeds) if e is not None}
        i0, i1 = seeded_reciprocal_neighbours(t0, t1, seeds, max_iters=rounds)
        assert set(zip(i0.tolist(), i1.tolist())) == want and want <= pairs


@pytest.mark.parametrize(("m0", "m1"), [(0, 5), (5, 0), (0, 0)])
def test_reciprocal_nn_empty(m0: int, m1: int) -> None:
    """An empty side gives no pairs and top-2 arrays of the right (empty) shapes."""
    rng = np.random.default_rng(0)
    nn = reciprocal_nearest_neighbours(_random_desc(m0, 8, rng), _random_desc(m1, 8, rng))
    assert len(nn.idx0) == len(nn.idx1) == len(nn.sim) == 0
    assert nn.top2_0.shape == (m0, 2) and nn.top2_1.shape == (m1, 2)


# ------------------------------------------------------------------------------------ ratio confidence
def _sims_at_angles(a_deg: float, b_deg: float) -> np.ndarray:
    """Cosine similarities of (1, 0) to the unit vectors at angles a and b."""
    q = np.array([1.0, 0.0])
    va = np.array([math.cos(math.radians(a_deg)), math.sin(math.radians(a_deg))])
    vb = np.array([math.cos(math.radians(b_deg)), math.sin(math.radians(b_deg))])
    return np.array([q @ va, q @ vb])


def _ratio_tol(a_deg: float | np.ndarray) -> float | np.ndarray:
    """Bound on |ratio_distinctiveness − exact| for similarities from cos/sin in float64: the float32 output is one
    rounding of a value in [0, 1] (≤ u32); before it, float64 s is off by ≤ 4u (cos, sin, the dot), so
    d = √(2 − 2s) by ≤ 4u/d² + 2u relative and r = d1/d2 (d2 ≥ d1) by ≤ 8u/d1² + 5u relative — with the test's
    own float64 evaluation, ≤ (8/d1² + 16)·u64, d1 = 2 sin(a/2) the best chord (d1 = 0 is exact: r = 0)."""
    d1 = 2 * np.sin(np.radians(np.asarray(a_deg, np.float64)) / 2)
    d1 = np.where(d1 > 0, d1, 1.0)  # a = 0: d1 = 0 gives r = 0 exactly
    return U32 + (8 / d1**2 + 16) * unit_roundoff(np.float64)


@pytest.mark.parametrize(
    ("a_deg", "b_deg", "expected"),
    [
        (60.0, 90.0, 1.0 - 1.0 / math.sqrt(2.0)),  # chord lengths 1 and √2
        (0.0, 90.0, 1.0),  # an exact match
        (45.0, 45.0, 0.0),  # two equally good candidates
        (30.0, 120.0, 1.0 - math.sin(math.radians(15.0)) / math.sin(math.radians(60.0))),
        (90.0, 180.0, 1.0 - math.sqrt(2.0) / 2.0),  # the second is antipodal: distance 2
        (0.0, 0.0, 0.0),  # both identical to the query: no distinctiveness (no division by zero)
        (90.0, 60.0, 0.0),  # "second" closer than "best" clips to 0
    ],
)
def test_ratio_distinctiveness_hand_computed(a_deg: float, b_deg: float, expected: float) -> None:
    """``1 − d1/d2`` with ``d = 2 sin(θ/2)`` the chord between unit vectors θ apart."""
    out = ratio_distinctiveness(_sims_at_angles(a_deg, b_deg)[None])
    assert out.shape == (1,) and out.dtype == np.float32
    assert_within(out, expected, _ratio_tol(a_deg), "1 − d1/d2")


def test_ratio_distinctiveness_is_vectorised() -> None:
    """Rows are independent: a batch gives the per-row values, all in [0, 1]."""
    angles = [(10.0, 80.0), (20.0, 25.0), (5.0, 170.0)]
    batch = np.stack([_sims_at_angles(a, b) for a, b in angles])
    out = ratio_distinctiveness(batch)
    expected = [1.0 - math.sin(math.radians(a / 2)) / math.sin(math.radians(b / 2)) for a, b in angles]
    assert_within(out, expected, _ratio_tol(np.array([a for a, _ in angles])), "1 − d1/d2")


# ------------------------------------------------------------------------------------ the confidence gate
def _ambiguous_pair(seed: int = 0) -> tuple[Features, Features, np.ndarray]:
    """View 1 holds noisy copies of 60 of view 0's 80 descriptors (permuted), 20 of them with a near-twin
    decoy, plus 30 distractors. Returns the features and the true view-1 index of each view-0 descriptor (−1)."""
    rng = np.random.default_rng(seed)
    d0 = _random_desc(80, 32, rng)
    copies = _unit(d0[:60] + rng.normal(scale=0.15, size=(60, 32)) / math.sqrt(32))
    twins = _unit(d0[:20] + rng.normal(scale=0.2, size=(20, 32)) / math.sqrt(32))
    d1 = np.concatenate([copies, twins, _random_desc(30, 32, rng)])
    perm = rng.permutation(len(d1))
    d1 = d1[perm]
    truth = np.full(80, -1)
    truth[:60] = np.argsort(perm)[:60]
    xy0 = rng.uniform(0, 100, (80, 2))
    xy1 = rng.uniform(0, 100, (len(d1), 2))
    conf0 = rng.uniform(0.2, 1.0, 80).astype(np.float32)
    conf1 = rng.uniform(0.2, 1.0, len(d1)).astype(np.float32)
    return _features(xy0, d0, conf0), _features(xy1, d1, conf1), truth


def test_match_features_counts_and_ratio_weights() -> None:
    """Counts: reciprocal ≥ confident = len; weights are c·(1 − d1/d2) on both sides from the brute-force top-2."""
    f0, f1, _ = _ambiguous_pair()
    m = match_features(f0, f1, MatchConfig(conf_threshold=0.04, max_block_elems=50))
    pairs, top_rows, top_cols = _brute_force(f0.desc, f1.desc)
    assert m.counts["reciprocal"] == len(pairs)
    assert m.counts["confident"] == len(m) < m.counts["reciprocal"]  # the decoys make some matches ambiguous
    assert set(zip(m.idx0.tolist(), m.idx1.tolist())) <= pairs
    c0 = f0.conf * ratio_distinctiveness(top_rows)
    c1 = f1.conf * ratio_distinctiveness(top_cols)
    # float32 similarities (≤ γ₃₂ each) against float64 ones; c = conf·ratio and w = c0·c1: 3 float32 roundings a side
    ds = _sim_err(f0.desc, f1.desc)
    tol = _conf_tol(_pair_distance(f0.desc, f1.desc, m.idx0, m.idx1), ds, roundings=6)
    assert_within(m.conf, c0[m.idx0] * c1[m.idx1], tol, "joint confidence")
    assert (m.conf > 0.04).all()
    np.testing.assert_array_equal(m.xy0, f0.xy[m.idx0])
    np.testing.assert_array_equal(m.xy1, f1.xy[m.idx1])
    dropped = np.array([(i, j) for i, j in pairs if (i, j) not in set(zip(m.idx0.tolist(), m.idx1.tolist()))])
    tol_dropped = _conf_tol(_pair_distance(f0.desc, f1.desc, dropped[:, 0], dropped[:, 1]), ds, roundings=6)
    assert (c0[dropped[:, 0]] * c1[dropped[:, 1]] <= 0.04 + tol_dropped).all()  # only the gate removed them


def test_match_features_keeps_the_matches_below_the_gate_apart() -> None:
    """``below_gate`` holds exactly the reciprocal pairs the gate dropped (for the pose stage's planar check); it
    is not counted and a subset does not carry it."""
    f0, f1, _ = _ambiguous_pair()
    m = match_features(f0, f1, MatchConfig(conf_threshold=0.04))
    pairs, _, _ = _brute_force(f0.desc, f1.desc)
    below = m.below_gate
    assert below is not None and len(below) > 0
    kept = set(zip(m.idx0.tolist(), m.idx1.tolist()))
    dropped = set(zip(below.idx0.tolist(), below.idx1.tolist()))
    assert kept | dropped == pairs and not kept & dropped
    assert (below.conf <= 0.04).all()
    np.testing.assert_array_equal(below.xy0, f0.xy[below.idx0])
    assert m.counts == {"reciprocal": len(pairs), "confident": len(m)}
    assert m.subset(np.ones(len(m), bool), "verified").below_gate is None


def test_match_features_keeps_true_matches() -> None:
    """The confident matches are (almost all) the true correspondences."""
    f0, f1, truth = _ambiguous_pair(1)
    m = match_features(f0, f1)
    assert len(m) >= 30
    assert np.mean(truth[m.idx0] == m.idx1) >= 0.95


def test_raising_the_threshold_never_adds_matches() -> None:
    """The accepted pairs for a higher τ are a subset of those for a lower τ, and the gate is exact."""
    f0, f1, _ = _ambiguous_pair(2)
    previous: set[tuple[int, int]] | None = None
    sizes = []
    for tau in (0.0, 0.02, 0.04, 0.1, 0.2, 0.4, 0.7):
        m = match_features(f0, f1, MatchConfig(conf_threshold=tau))
        got = set(zip(m.idx0.tolist(), m.idx1.tolist()))
        assert (m.conf > tau).all()
        if previous is not None:
            assert got <= previous
        previous = got
        sizes.append(len(got))
    assert sizes[0] > sizes[-1]  # the thresholds did bite


def test_match_features_without_ratio_uses_feature_confidence() -> None:
    """``ratio_confidence=False``: w = c0·c1 of the features' own confidences, gated at τ."""
    f0, f1, _ = _ambiguous_pair(4)
    tau = 0.3
    m = match_features(f0, f1, MatchConfig(conf_threshold=tau, ratio_confidence=False))
    pairs, _, _ = _brute_force(f0.desc, f1.desc)
    expected = {(i, j) for i, j in pairs if f0.conf[i] * f1.conf[j] > tau}
    assert set(zip(m.idx0.tolist(), m.idx1.tolist())) == expected
    # (a) the same single float32 multiplication of the same two float32 numbers: IEEE rounds it identically
    np.testing.assert_array_equal(m.conf, f0.conf[m.idx0] * f1.conf[m.idx1])
    assert m.counts["reciprocal"] == len(pairs) > len(m)
    # the gate is strict: a zero confidence is dropped even at τ = 0
    f0.conf[:40] = 0.0
    m0 = match_features(f0, f1, MatchConfig(conf_threshold=0.0, ratio_confidence=False))
    assert len(m0) > 0 and (m0.idx0 >= 40).all()


@pytest.mark.parametrize(
    ("m0", "m1"),
    [
        (40, 50),
        (2, 30),
        (1, 30),
    ],
)
def test_match_features_is_symmetric(m0: int, m1: int) -> None:
    """Swapping the two views swaps the matches and keeps their confidences."""
    rng = np.random.default_rng(m0 + m1)
    d0 = _random_desc(m0, 16, rng)
    d1 = np.concatenate([_unit(d0 + 0.3 * rng.normal(size=d0.shape) / 4), _random_desc(m1 - m0, 16, rng)])
    f0 = _features(rng.uniform(0, 50, (m0, 2)), d0)
    f1 = _features(rng.uniform(0, 50, (m1, 2)), d1)
    cfg = MatchConfig(conf_threshold=0.0)
    a, b = match_features(f0, f1, cfg), match_features(f1, f0, cfg)
    fwd = dict(zip(zip(a.idx0.tolist(), a.idx1.tolist()), a.conf.tolist()))
    bwd = dict(zip(zip(b.idx1.tolist(), b.idx0.tolist()), b.conf.tolist()))
    assert fwd.keys() == bwd.keys() and len(fwd) > 0
    # d0·d1ᵀ and d1·d0ᵀ are two float32 orders of the same sums: similarities differ by ≤ 2γ₁₆ (a 3-rounding side)
    keys = np.array(list(fwd))
    tol = _conf_tol(_pair_distance(d0, d1, keys[:, 0], keys[:, 1]), 2 * _sim_err(d0, d1), roundings=6)
    assert_within([bwd[k] for k in fwd], list(fwd.values()), tol, "swapped-view confidences")


# ------------------------------------------------------------------------------------ guided matching
K_GUIDED = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _stereo_setup(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact correspondences of random points for a generic pose, and its fundamental matrix."""
    rng = np.random.default_rng(seed)
    R = rotation_about((0.2, 1.0, 0.1), 8.0)
    t = np.array([0.9, 0.2, 0.1])
    X = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(4, 8, n)]
    x0 = X @ K_GUIDED.T
    Xc = X @ R.T + t
    x1 = Xc @ K_GUIDED.T
    return x0[:, :2] / x0[:, 2:], x1[:, :2] / x1[:, 2:], fundamental_from_pose(R, t, K_GUIDED, K_GUIDED)


def _line_distance(F: np.ndarray, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Distance of each xy1 to the epipolar line of its xy0 in view 1 (pixels)."""
    lines = np.c_[xy0, np.ones(len(xy0))] @ F.T
    return np.abs(np.sum(lines * np.c_[xy1, np.ones(len(xy1))], axis=1)) / np.linalg.norm(lines[:, :2], axis=1)


def _line_distance_err(F: np.ndarray, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Bound on the rounding of ``guided_matches``' float32 point-to-line distance a·x + b·y + c (unit normal):
    the coefficients and the point are rounded to float32 (u each) and the 3-term dot adds γ₃, all relative to
    Σ = |a·x| + |b·y| + |c|; the float64 lines before the rounding and this test's float64 distance add γ₁₀(f64)."""
    lines = np.c_[xy0, np.ones(len(xy0))] @ F.T
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    terms = np.abs(lines * np.c_[xy1, np.ones(len(xy1))]).sum(1)
    return (gamma(3, np.float32) + 2 * U32 + gamma(10, np.float64)) * terms


def test_guided_matches_separate_duplicates_by_the_epipolar_band() -> None:
    """Each descriptor appears twice in view 1: a slightly noisy copy at the true place and an exact copy far from
    the epipolar line. Plain mutual NN picks the decoys; guided matching recovers the true correspondences."""
    n = 120
    rng = np.random.default_rng(5)
    xy0, xy1_true, F = _stereo_setup(n, 5)
    d0 = _random_desc(n, 32, rng)
    true_desc = _unit(d0 + 0.1 * rng.normal(size=d0.shape) / math.sqrt(32))
    decoy_xy = rng.uniform([0, 0], [640, 480], (4 * n, 2))
    far = _line_distance(F, np.repeat(xy0, 4, 0), decoy_xy).reshape(n, 4) > 20.0
    decoy_xy = decoy_xy.reshape(n, 4, 2)[np.arange(n), far.argmax(1)]  # one decoy per point, > 20 px off its line
    assert far.any(1).all()
    xy1 = np.concatenate([xy1_true, decoy_xy])
    d1 = np.concatenate([true_desc, d0])  # the decoys are exact copies: more similar than the true matches
    f0, f1 = _features(xy0, d0), _features(xy1, d1)

    plain = match_features(f0, f1, MatchConfig(conf_threshold=0.0, ratio_confidence=False))
    assert len(plain) == n and (plain.idx1 >= n).all()  # every plain match is a decoy

    guided = guided_matches(f0, f1, F, band_px=2.0)
    assert guided.counts == {"guided": len(guided)}
    assert len(guided) >= 0.95 * n
    np.testing.assert_array_equal(guided.idx1, guided.idx0)  # true match of i is view-1 feature i
    np.testing.assert_array_equal(guided.xy1, xy1_true[guided.idx0])  # (a) copies of the input positions
    assert ((guided.conf > 0) & (guided.conf <= 1)).all()


@pytest.mark.parametrize("band_px", [0.5, 2.0, 8.0])
def test_guided_matches_lie_in_the_band(band_px: float) -> None:
    """Random descriptors and positions: every returned pair is within ``band_px`` of its epipolar line."""
    rng = np.random.default_rng(int(band_px * 10))
    xy0, xy1, F = _stereo_setup(300, 7)
    xy1 = rng.uniform([0, 0], [640, 480], xy1.shape)  # unrelated positions: many pairs fall outside any band
    d0 = _random_desc(300, 8, rng)
    d1 = _unit(d0[rng.permutation(300)] + 0.5 * rng.normal(size=(300, 8)) / math.sqrt(8))
    m = guided_matches(_features(xy0, d0), _features(xy1, d1), F, band_px=band_px, ratio=1.0)
    assert len(m) > 0
    assert (_line_distance(F, m.xy0, m.xy1) <= band_px + _line_distance_err(F, m.xy0, m.xy1)).all()
    assert len(set(m.idx0.tolist())) == len(m) and len(set(m.idx1.tolist())) == len(m)  # one-to-one


def _assert_guided_decisions_robust(f0: Features, f1: Features, F: np.ndarray, band_px: float, ratio: float) -> None:
    """Precondition of comparing two float32 runs of ``guided_matches`` (other block shapes, so other summation
    orders) by their indices: no decision of the data is within rounding of its threshold — band membership
    (distance off by ≤ :func:`_line_distance_err`), the in-band argmax (similarities off by ≤ γ_D) and the ratio
    test (c off by ≤ :func:`_conf_tol`). Checked in float64; a failure means the test data must change."""
    n1 = len(f1)
    lines = np.c_[f0.xy, np.ones(len(f0))] @ F.T
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    p1 = np.c_[f1.xy, np.ones(n1)]
    dist = np.abs(lines @ p1.T)
    dist_err = (gamma(3, np.float32) + 2 * U32 + gamma(10, np.float64)) * (np.abs(lines) @ np.abs(p1).T)
    assert (np.abs(dist - band_px) > 2 * dist_err).all(), "a distance at the band's edge"
    sim = np.where(dist <= band_px, f0.desc.astype(np.float64) @ f1.desc.astype(np.float64).T, -4.0)
    err = _sim_err(f0.desc, f1.desc)
    for s in (sim, sim.T):
        top = -np.sort(-s, axis=1)[:, :2]
        _assert_separated(top, err)
        d = np.sqrt(np.maximum(2.0 - 2.0 * top.clip(-1.0, 1.0), 0.0))
        both = top[:, 1] > -4.0  # a second in-band candidate: the ratio test decides
        c = 1.0 - d[both, 0] / d[both, 1]
        assert (np.abs(c - (1.0 - ratio)) > _conf_tol(d[both, 0], err, roundings=2)).all(), "c at the ratio gate"


def test_guided_matches_band_and_block_size() -> None:
    """A wider band never loses a pair whose true match is inside the narrow one; block size does not matter."""
    rng = np.random.default_rng(11)
    xy0, xy1, F = _stereo_setup(150, 11)
    d0 = _random_desc(150, 16, rng)
    d1 = _unit(d0 + 0.2 * rng.normal(size=d0.shape) / 4)
    f0, f1 = _features(xy0, d0), _features(xy1 + rng.normal(scale=0.3, size=xy1.shape), d1)
    _assert_guided_decisions_robust(f0, f1, F, band_px=2.0, ratio=0.95)
    a = guided_matches(f0, f1, F, band_px=2.0)
    b = guided_matches(f0, f1, F, band_px=2.0, max_block_elems=7)
    np.testing.assert_array_equal(a.idx0, b.idx0)
    np.testing.assert_array_equal(a.idx1, b.idx1)
    # The similarities are float32 dot products of 16-d unit vectors, |δs| ≤ γ₁₆ each way, so two block sizes
    # differ by ≤ 2γ₁₆. c = 1 − d_best/d_second with d = √(2 − 2s): |∂c/∂s| ≤ 2/d_best² (d_second ≥ d_best),
    # the joint w = c0·c1 (c ≤ 1) adds both views' errors, plus a float32 rounding of each step.
    d_best = np.linalg.norm(d0[a.idx0].astype(np.float64) - d1[a.idx1], axis=1)
    tol = 2 * (2 / d_best**2) * (2 * gamma(16, np.float32)) + 4 * unit_roundoff(np.float32)
    assert (np.abs(a.conf.astype(np.float64) - b.conf) <= tol).all()
    assert len(a) >= 140 and (a.idx0 == a.idx1).all()


def test_guided_matches_ratio_test_inside_the_band() -> None:
    """A near-twin of the true match, further along the same epipolar line, makes the pair ambiguous: the ratio
    test drops it; with ``ratio=1`` (only a positive margin needed) most come back."""
    n, n_amb = 120, 20
    rng = np.random.default_rng(13)
    xy0, xy1, F = _stereo_setup(n, 13)
    lines = np.c_[xy0, np.ones(n)] @ F.T
    along = np.c_[-lines[:, 1], lines[:, 0]] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    d0 = _random_desc(n, 32, rng)
    d1 = _unit(d0 + 0.1 * rng.normal(size=d0.shape) / math.sqrt(32))
    twin_xy = xy1[:n_amb] + 40.0 * along[:n_amb]  # on the epipolar line, 40 px away
    twin_desc = _unit(d1[:n_amb] + 0.01 * rng.normal(size=(n_amb, 32)) / math.sqrt(32))
    f0 = _features(xy0, d0)
    f1 = _features(np.concatenate([xy1, twin_xy]), np.concatenate([d1, twin_desc]))
    strict = guided_matches(f0, f1, F, band_px=2.0, ratio=0.95)
    assert not np.isin(strict.idx0, np.arange(n_amb)).any()
    assert len(strict) >= 0.95 * (n - n_amb) and (strict.idx0 == strict.idx1).all()
    loose = guided_matches(f0, f1, F, band_px=2.0, ratio=1.0)
    assert np.isin(loose.idx0, np.arange(n_amb)).sum() >= n_amb // 2


@pytest.mark.parametrize(("n0", "n1"), [(0, 10), (10, 0), (0, 0)])
def test_guided_matches_empty(n0: int, n1: int) -> None:
    """No features on a side: no matches, well-shaped arrays, ``counts["guided"] == 0``."""
    rng = np.random.default_rng(0)
    _, _, F = _stereo_setup(1, 0)
    f0 = _features(rng.uniform(0, 100, (n0, 2)), _random_desc(n0, 8, rng))
    f1 = _features(rng.uniform(0, 100, (n1, 2)), _random_desc(n1, 8, rng))
    m = guided_matches(f0, f1, F)
    assert len(m) == 0 and m.counts == {"guided": 0}
    assert m.xy0.shape == (0, 2) and m.xy1.shape == (0, 2) and m.idx0.shape == (0,)


@pytest.mark.parametrize("shape", [(1, 5), (7, 300), (64, 1031), (513, 257)])
@pytest.mark.parametrize("levels", [0, 3])
def test_column_top2_kernel_matches_reference(shape: tuple[int, int], levels: int) -> None:
    """The Numba column top-2 fold equals its PyTorch twin over several blocks, ties included (``levels``:
    values rounded to so few levels that most columns tie)."""
    from macsplat_cli.pipeline import _match_kernels

    rng = np.random.default_rng(shape[0] * 7 + levels)
    rows, cols = shape
    full = rng.uniform(-1, 1, (3 * rows, cols)).astype(np.float32)
    if levels:
        full = np.round(full * levels) / levels
    top_k, arg_k = np.full((2, cols), -1.0, np.float32), np.zeros(cols, np.int64)
    top_r, arg_r = torch.full((2, cols), -1.0), torch.zeros(cols, dtype=torch.int64)
    for start in range(0, 3 * rows, rows):
        block = full[start : start + rows]
        _match_kernels.column_top2_update(np.ascontiguousarray(block), start, top_k, arg_k)
        _match_kernels.column_top2_update_reference(torch.from_numpy(block), start, top_r, arg_r)
    np.testing.assert_array_equal(top_k, top_r.numpy())
    np.testing.assert_array_equal(arg_k, arg_r.numpy())
    # and both are the global answer: the first row of the column maximum, the second-largest entry
    np.testing.assert_array_equal(arg_k, full.argmax(0))
    np.testing.assert_array_equal(top_k, -np.sort(-full, axis=0)[:2])


def test_sift_describes_both_views_in_threads_with_the_same_output(pair_files: PairFactory) -> None:
    """SIFT is thread-safe: the describe slot runs the two views in parallel threads, and gets exactly what one
    view at a time gets; a backend that does not declare itself thread-safe stays on the calling thread."""
    import os
    import threading

    from macsplat_cli.pipeline.descriptors import SiftDescriptors
    from macsplat_cli.pipeline.stages import PerViewDescriptors
    from macsplat_cli.pipeline.views import load_views

    files = pair_files(PairSpec("room", 15.0, (320, 240), scene_seed=2, orbit_seed=2), ("view0.png", "view1.png"))
    views = load_views(list(files.photos))
    sift = SiftDescriptors()
    threads: list[str] = []

    class Spy:
        name, thread_safe = "spy", True

        def __call__(self, view):  # noqa: ANN001, ANN204
            threads.append(threading.current_thread().name)
            return sift(view)

    both = PerViewDescriptors(Spy())(views)
    one_by_one = [sift(v) for v in views]
    for a, b in zip(both, one_by_one):
        assert len(a) > 100
        np.testing.assert_array_equal(a.xy, b.xy)
        np.testing.assert_array_equal(a.desc, b.desc)
    if (os.cpu_count() or 1) > 1:
        assert all(t.startswith("describe") for t in threads), threads
    threads.clear()
    Spy.thread_safe = False
    PerViewDescriptors(Spy())(views)
    assert threads == [threading.current_thread().name] * 2
