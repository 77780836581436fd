"""The pair shortlist of N-photo reconstruction: every pair for few photos, retrieval + sequence beyond.

Scenes are synthetic: a "scene" is a set of prototype SIFT-like descriptors (non-negative, sparse histograms);
each photo of a scene draws its descriptors from the scene's prototypes with multiplicative noise, plus a share
from a background set common to every scene (so that photos of different scenes are not trivially apart).
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest

from macsplat_cli.pipeline.multiview.shortlist import (
    ShortlistConfig,
    global_descriptors,
    select_pairs,
    similarity,
)
from macsplat_cli.pipeline.types import Features

D = 128
GROUPS, PER_GROUP = 3, 6  # 18 photos > all_pairs_max (8): retrieval decides
U32 = 2.0**-24  # float32 unit roundoff


def _histograms(rng: np.random.Generator, n: int) -> np.ndarray:
    """Sparse non-negative SIFT-like histograms (most mass in a few bins). [n, D] float64"""
    return rng.random((n, D)) ** 4


def _root(h: np.ndarray) -> np.ndarray:
    """RootSIFT: L1-normalise, square root (unit L2). [n, D] float32"""
    return np.sqrt(h / h.sum(axis=1, keepdims=True)).astype(np.float32)


def _features(desc: np.ndarray) -> Features:
    m = len(desc)
    return Features(np.zeros((m, 2)), desc.astype(np.float32), np.ones(m, np.float32))


def _empty() -> Features:
    return _features(np.zeros((0, D), np.float32))


def _scene_histograms(seed: int = 0, per_photo: int = 300, background: float = 0.3) -> list[np.ndarray]:
    """Raw histograms of GROUPS × PER_GROUP photos, photo i in group i // PER_GROUP. Each [per_photo, D]"""
    rng = np.random.default_rng(seed)
    prototypes = [_histograms(rng, 200) for _ in range(GROUPS)]
    shared = _histograms(rng, 200)
    out = []
    for g in range(GROUPS):
        for _ in range(PER_GROUP):
            own = rng.random(per_photo) >= background
            from_scene = prototypes[g][rng.integers(200, size=per_photo)]
            from_background = shared[rng.integers(200, size=per_photo)]
            src = np.where(own[:, None], from_scene, from_background)
            out.append(src * rng.uniform(0.5, 1.5, size=src.shape))
    return out


def _scene(seed: int = 0, **kw: float) -> list[Features]:
    return [_features(_root(h)) for h in _scene_histograms(seed, **kw)]


def _group(i: int) -> int:
    return i // PER_GROUP


@pytest.mark.parametrize("n", [0, 1, 2, 5, 8])
def test_up_to_all_pairs_max_every_pair_is_matched_without_features(n: int) -> None:
    assert select_pairs(n, None, ShortlistConfig()) == list(combinations(range(n), 2))


def test_all_pairs_max_is_the_switch() -> None:
    feats = _scene()
    n = len(feats)
    assert select_pairs(n, feats, ShortlistConfig(all_pairs_max=n)) == list(combinations(range(n), 2))
    assert len(select_pairs(n, feats, ShortlistConfig(all_pairs_max=n - 1))) < n * (n - 1) // 2


def test_the_default_pairs_stay_within_five_per_photo() -> None:
    """At most 5 two-view searches per photo at any N (each ~0.2 s): every pair up to 12 photos was 66 pairs at 12,
    5.5 per photo (benchmarks/history/multiview_scaling.md)."""
    cfg = ShortlistConfig()
    feats = _scene()
    for n in range(2, len(feats) + 1):
        pairs = select_pairs(n, feats[:n] if n > cfg.all_pairs_max else None, cfg)
        assert len(pairs) <= 5 * n, n


def test_the_vlads_a_caller_keeps_are_asked_for_only_when_needed_and_give_the_same_choice() -> None:
    """The pairs stage keeps the VLADs for retrieval and for ordering the failed pairs: retrieval asks for them only
    beyond ``all_pairs_max``, and the kept ones choose what freshly computed ones choose."""
    feats, cfg = _scene(), ShortlistConfig()
    n = len(feats)
    asked: list[int] = []

    def kept() -> np.ndarray:
        asked.append(1)
        return global_descriptors(feats, cfg)

    assert select_pairs(cfg.all_pairs_max, feats[: cfg.all_pairs_max], cfg, kept) == list(
        combinations(range(cfg.all_pairs_max), 2)
    )
    assert asked == []
    small = ShortlistConfig(all_pairs_max=n - 1)
    assert select_pairs(n, feats, small, kept) == select_pairs(n, feats, small) and asked == [1]
    np.testing.assert_array_equal(similarity(feats, cfg, kept), similarity(feats, cfg))


def test_beyond_all_pairs_max_features_are_required() -> None:
    with pytest.raises(ValueError, match="features"):
        select_pairs(13, None, ShortlistConfig())
    with pytest.raises(ValueError, match="features"):
        select_pairs(13, [_empty()] * 12, ShortlistConfig())


def test_pairs_are_bounded_ordered_unique_and_include_sequence_neighbours() -> None:
    rng = np.random.default_rng(3)
    n, cfg = 40, ShortlistConfig(similar=3, sequence_neighbours=2, vocabulary=8)
    feats = [_features(_root(_histograms(rng, 80))) for _ in range(n)]
    pairs = select_pairs(n, feats, cfg)
    assert pairs == sorted(set(pairs))
    assert all(0 <= i < j < n for i, j in pairs)
    assert len(pairs) <= n * (cfg.similar + cfg.sequence_neighbours)
    assert len(pairs) < n * (n - 1) // 2
    assert {(i, i + d) for i in range(n) for d in (1, 2) if i + d < n} <= set(pairs)
    degree = np.bincount(np.array(pairs).ravel(), minlength=n)
    assert degree.min() >= cfg.similar  # every photo keeps its own k retrieved pairs


def test_vlads_are_unit_and_similarity_is_a_cosine_with_a_minus_inf_diagonal() -> None:
    feats = _scene()
    cfg = ShortlistConfig()
    v = global_descriptors(feats, cfg)
    assert v.shape == (len(feats), cfg.vocabulary * D) and v.dtype == np.float32
    # each element is a float64 value rounded to float32 (relative error ≤ u): the norm moves by ≤ u (+ sum error)
    norms = np.linalg.norm(v.astype(np.float64), axis=1)
    assert np.all(np.abs(norms - 1.0) <= 4 * U32)
    sim = similarity(feats, cfg)
    assert sim.shape == (len(feats), len(feats))
    assert np.all(np.isneginf(np.diag(sim)))
    off = ~np.eye(len(feats), dtype=bool)
    np.testing.assert_allclose(sim[off], (v.astype(np.float64) @ v.T.astype(np.float64))[off], rtol=0, atol=1e-12)
    assert np.array_equal(sim, sim.T)
    assert np.all(np.abs(sim[off]) <= 1.0 + 8 * U32)


@pytest.mark.parametrize("sample", [20000, 1500])  # all 5,400 descriptors, or a subsample for the vocabulary
def test_every_photos_most_similar_photos_are_of_its_scene(sample: int) -> None:
    feats = _scene()
    cfg = ShortlistConfig(similar=PER_GROUP - 1, sequence_neighbours=0, sample=sample)
    sim = similarity(feats, cfg)
    n = len(feats)
    for i in range(n):
        top = np.argsort(-sim[i], kind="stable")[: cfg.similar]
        assert {_group(j) for j in top} == {_group(i)}, (i, top, sim[i].round(3))
    # retrieval alone (no sequence neighbours) then picks exactly the pairs within each scene
    within = [(i, j) for i, j in combinations(range(n), 2) if _group(i) == _group(j)]
    assert select_pairs(n, feats, cfg) == within


def test_the_same_input_gives_the_same_pairs_and_descriptors() -> None:
    cfg = ShortlistConfig(sample=1500)
    a, b = _scene(), _scene()
    assert np.array_equal(global_descriptors(a, cfg), global_descriptors(b, cfg))
    assert select_pairs(len(a), a, cfg) == select_pairs(len(b), b, cfg)


def test_a_photo_without_descriptors_is_paired_only_with_its_sequence_neighbours() -> None:
    feats = _scene()
    e = 7
    feats[e] = _empty()
    cfg = ShortlistConfig(similar=3, sequence_neighbours=2)
    v = global_descriptors(feats, cfg)
    assert not v[e].any()
    sim = similarity(feats, cfg)
    others = np.arange(len(feats)) != e
    assert np.all(sim[e, others] == -1.0) and np.all(sim[others, e] == -1.0) and np.isneginf(sim[e, e])
    pairs = select_pairs(len(feats), feats, cfg)
    assert {p for p in pairs if e in p} == {(5, 7), (6, 7), (7, 8), (7, 9)}
    # pairs over 2 apart come from retrieval only: the other photos still find their own scene
    assert all(_group(i) == _group(j) for i, j in pairs if j - i > cfg.sequence_neighbours)


def test_no_descriptors_at_all_leaves_the_sequence() -> None:
    n, cfg = 15, ShortlistConfig(sequence_neighbours=1)
    feats = [_empty() for _ in range(n)]
    assert not global_descriptors(feats, cfg).any()
    assert select_pairs(n, feats, cfg) == [(i, i + 1) for i in range(n - 1)]


def test_fewer_descriptors_than_words() -> None:
    rng = np.random.default_rng(5)
    # 28 descriptors: 3 words of ≥ 8 each, not 28 words of one (whose residuals, the VLAD, would all be zero)
    feats = [_features(_root(_histograms(rng, 2))) for _ in range(14)]
    cfg = ShortlistConfig()
    v = global_descriptors(feats, cfg)
    assert v.shape == (14, cfg.vocabulary * D)
    assert np.all(np.abs(np.linalg.norm(v.astype(np.float64), axis=1) - 1.0) <= 4 * U32)
    pairs = select_pairs(14, feats, cfg)
    assert len(pairs) <= 14 * (cfg.similar + cfg.sequence_neighbours)


def test_hellinger_turns_plain_sift_into_rootsift_and_leaves_signed_descriptors() -> None:
    hist = _scene_histograms(per_photo=120)
    plain = [_features(h / np.linalg.norm(h, axis=1, keepdims=True)) for h in hist]
    root = [_features(_root(h)) for h in hist]
    on, off = ShortlistConfig(hellinger=True, sample=1500), ShortlistConfig(sample=1500)
    # the map equals RootSIFT up to float32 rounding of a few operations per element (a relative few u)
    v_plain, v_root = global_descriptors(plain, on), global_descriptors(root, off)
    np.testing.assert_allclose(v_plain, v_root, rtol=0, atol=1e-4)
    assert not np.allclose(global_descriptors(plain, off), v_root, atol=1e-2)  # the map did something
    rng = np.random.default_rng(2)
    signed = [_features(x / np.linalg.norm(x, axis=1, keepdims=True)) for x in rng.normal(size=(14, 50, 16))]
    assert np.array_equal(global_descriptors(signed, on), global_descriptors(signed, off))


def test_mixed_descriptor_dimensions_and_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="dimensions"):
        global_descriptors([_empty(), _features(np.ones((3, 64), np.float32) / 8)], ShortlistConfig())
    for bad in ({"similar": -1}, {"sequence_neighbours": -1}, {"vocabulary": 0}, {"sample": 0}):
        with pytest.raises(ValueError):
            ShortlistConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        select_pairs(-1, None, ShortlistConfig())
