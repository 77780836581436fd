"""Which photo pairs of an N-photo reconstruction get matched (the pair shortlist).

Matching every pair costs N(N-1)/2 two-view matches. Up to ``all_pairs_max`` photos that is affordable and the
most robust choice, so every pair is matched. Beyond it, each photo is paired with

* its ``similar`` most similar photos by a global descriptor (retrieval), and
* its ``sequence_neighbours`` predecessors and successors in file order (photos are usually taken in order, and
  a sequence neighbour is found even when retrieval misses it),

so the number of pairs grows as O(N·k) instead of O(N²): at most ``N · (similar + sequence_neighbours)``.

The global descriptor is VLAD (Jégou et al. 2010, with the normalisations of Arandjelović & Zisserman 2013,
"All about VLAD"):

1. a vocabulary of ``vocabulary`` visual words, k-means fitted on a seeded sample of all photos' descriptors
   together (so the words fit this scene; a small deterministic numpy k-means, k-means++ seeding);
2. per photo, the residuals ``x − c(x)`` of its descriptors summed per nearest word: [vocabulary, D];
3. intra-normalisation (each word's sum to unit L2: a repeated structure cannot dominate through one word),
   signed square root (damps bursts), global L2: [vocabulary · D], unit L2.

The similarity of two photos is the cosine (dot product) of their VLADs.

Descriptors. The classical backend (:mod:`..descriptors`) already gives RootSIFT (``SiftConfig.root=True``), so
by default descriptors are used as they come. For plain L2-normalised SIFT (``root=False``) set
``ShortlistConfig.hellinger``: the Hellinger map (L1-normalise, square root; unit L2 again) turns it into
RootSIFT. Which of the two a photo holds cannot be told from the values: both are non-negative unit vectors, and
their flatness (L1/L2 norm) overlaps across image types (measured: the median over one image's SIFT ranged
0.32–0.77 · √D for plain SIFT and 0.42–0.92 · √D for RootSIFT on a photo and four synthetic patterns), so it is
a setting, not a guess. The map is applied only to a photo whose descriptors are all non-negative (it is
undefined for signed ones): signed, generic descriptors (learned backends) are always used as they come.

A photo without descriptors gets the zero VLAD and similarity −1 to every photo; it is never chosen by retrieval,
so its pairs come from its sequence neighbours only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..types import Features

__all__ = ["ShortlistConfig", "global_descriptors", "select_pairs", "similarity"]

_KMEANS_ITERATIONS = 20
"""Most Lloyd iterations: the vocabulary only needs to partition descriptor space the same way for all photos
(each photo is encoded with the same words), not to converge; 20 bounds the time (~0.15 s on 20,000 × 128)."""

_MIN_PER_WORD = 8
"""Fewest sampled descriptors per word: with fewer descriptors than that (tiny photos) the words shrink onto
single descriptors and their residuals, the VLAD itself, vanish (one descriptor per word gives a zero VLAD)."""


@dataclass
class ShortlistConfig:
    """Which pairs of photos are matched (why each default: benchmarks/history/settings.md).

    Args:
        all_pairs_max: up to this many photos (≥ 0) every pair is matched.
        similar: beyond it, each photo's k most similar photos by the global descriptor (≥ 0).
        sequence_neighbours: plus photos i±1..i±n in file order (≥ 0; a safety net for retrieval misses).
        vocabulary: VLAD visual words (≥ 1), fitted on this scene's own descriptors.
        sample: descriptors sampled (all photos together, ≥ 1) to fit the vocabulary.
        seed: seed of the sample and of the k-means seeding (same input → same pairs).
        hellinger: apply the Hellinger map (L1-normalise, square root) to non-negative descriptors first, for plain
            SIFT (off for RootSIFT, which would get a 4th root).
    """

    all_pairs_max: int = 8
    similar: int = 3
    sequence_neighbours: int = 2
    vocabulary: int = 32
    sample: int = 20000
    seed: int = 0
    hellinger: bool = False

    def __post_init__(self) -> None:
        for name in ("all_pairs_max", "similar", "sequence_neighbours"):
            if getattr(self, name) < 0:
                raise ValueError(f"ShortlistConfig.{name} must be ≥ 0, got {getattr(self, name)}")
        for name in ("vocabulary", "sample"):
            if getattr(self, name) < 1:
                raise ValueError(f"ShortlistConfig.{name} must be ≥ 1, got {getattr(self, name)}")


def _descriptor_dim(features: Sequence[Features]) -> int:
    """The common descriptor dimension D of all photos (0 for no photos)."""
    dims = {int(f.desc.shape[1]) for f in features}
    if len(dims) > 1:
        raise ValueError(f"photos have descriptors of different dimensions: {sorted(dims)}")
    return dims.pop() if dims else 0


def _prepare(desc: np.ndarray, hellinger: bool) -> np.ndarray:
    """Descriptors as VLAD encodes them: float32, Hellinger-mapped when asked and non-negative. [M, D] float32"""
    x = np.asarray(desc, dtype=np.float32)
    if not hellinger or x.size == 0 or x.min() < 0:
        return x
    x = x / np.maximum(x.sum(axis=1, keepdims=True), np.float32(1e-12))
    return np.sqrt(x)


def _sample(descs: Sequence[np.ndarray], size: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``size`` descriptors drawn uniformly without replacement from all photos together. [S, D] float32"""
    counts = np.array([len(d) for d in descs], dtype=np.int64)
    total = int(counts.sum())
    if total <= size:
        return np.concatenate(descs, axis=0)
    pick = np.sort(rng.choice(total, size=size, replace=False))
    starts = np.concatenate([[0], np.cumsum(counts)])
    photo = np.searchsorted(starts, pick, side="right") - 1
    return np.concatenate([descs[i][pick[photo == i] - starts[i]] for i in np.unique(photo)], axis=0)


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of each row's nearest centre (squared Euclidean; ``‖x‖²`` is common to a row). [M] int64"""
    d = (centres * centres).sum(axis=1)[None, :] - 2.0 * (x @ centres.T)
    return np.argmin(d, axis=1)


def _kmeans_pp(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: each next centre drawn with probability ∝ squared distance to the nearest so far. [k, D]"""
    sq = (x.astype(np.float64) ** 2).sum(axis=1)

    def dist2(c: np.ndarray) -> np.ndarray:  # ‖x − c‖², clamped at 0 against rounding
        return np.maximum(sq - 2.0 * (x @ c).astype(np.float64) + float(c @ c), 0.0)

    centres = np.empty((k, x.shape[1]), dtype=np.float32)
    centres[0] = x[rng.integers(len(x))]
    d2 = dist2(centres[0])
    for j in range(1, k):
        total = d2.sum()
        centres[j] = x[rng.choice(len(x), p=d2 / total) if total > 0 else rng.integers(len(x))]
        d2 = np.minimum(d2, dist2(centres[j]))
    return centres


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Lloyd's k-means from a k-means++ seeding; an empty cluster keeps its centre. x: [S, D] → centres [k, D]"""
    centres = _kmeans_pp(x, k, rng)
    assign = _nearest(x, centres)
    for _ in range(_KMEANS_ITERATIONS):
        counts = np.bincount(assign, minlength=k)
        sums = _sum_by_label(x, assign, k)
        filled = counts > 0
        centres[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        new = _nearest(x, centres)
        if np.array_equal(new, assign):
            break
        assign = new
    return centres


def _sum_by_label(x: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Per-label sums of the rows of ``x`` (a one-hot product). x: [M, D], labels: [M] → [k, D] float64"""
    onehot = (labels[:, None] == np.arange(k)[None, :]).astype(x.dtype)
    return (x.T @ onehot).T.astype(np.float64)  # [D, M] @ [M, k]: the fast layout (~4× the [k, M] @ [M, D] one)


def _vlad(x: np.ndarray, centres: np.ndarray, vocabulary: int) -> np.ndarray:
    """One photo's VLAD: residual sums per word, intra-normalised, signed sqrt, unit L2 (zero for no descriptors).

    x: [M, D]; centres: [K, D] with K ≤ vocabulary (words beyond K stay zero) → [vocabulary · D] float32
    """
    k, dim = centres.shape
    v = np.zeros((vocabulary, dim), dtype=np.float64)
    if len(x) == 0 or k == 0:
        return v.reshape(-1).astype(np.float32)
    labels = _nearest(x, centres)
    v[:k] = _sum_by_label(x - centres[labels], labels, k)
    norms = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.divide(v, norms, out=np.zeros_like(v), where=norms > 0)
    v = np.sign(v) * np.sqrt(np.abs(v))
    total = np.linalg.norm(v)
    return (v.reshape(-1) / total if total > 0 else v.reshape(-1)).astype(np.float32)


def global_descriptors(features: Sequence[Features], config: ShortlistConfig) -> np.ndarray:
    """L2-normalised VLAD of each photo, on a vocabulary fitted to all photos' descriptors together.

    features: N photos' descriptors, each [M_i, D] (M_i may be 0) → [N, vocabulary · D] float32, each row unit L2
    or zero (a photo with no descriptors). With fewer than ``vocabulary · 8`` descriptors in the sample, fewer
    words are fitted and the rest stay zero. Deterministic for a given input and ``config.seed``.
    """
    dim = _descriptor_dim(features)
    descs = [_prepare(f.desc, config.hellinger) for f in features]
    out = np.zeros((len(descs), config.vocabulary * dim), dtype=np.float32)
    rng = np.random.default_rng(config.seed)
    sample = _sample(descs, config.sample, rng) if descs else np.zeros((0, dim), np.float32)
    if len(sample) == 0:
        return out
    centres = _kmeans(sample, max(1, min(config.vocabulary, len(sample) // _MIN_PER_WORD)), rng)
    for i, x in enumerate(descs):
        out[i] = _vlad(x, centres, config.vocabulary)
    return out


def _cosine(vlads: np.ndarray) -> np.ndarray:
    """Cosine similarity of unit-or-zero rows; −1 wherever a row is zero, −inf on the diagonal. [N, N] float64"""
    v = vlads.astype(np.float64)
    sim = v @ v.T
    empty = ~(np.abs(v).sum(axis=1) > 0)
    sim[empty, :] = -1.0
    sim[:, empty] = -1.0
    np.fill_diagonal(sim, -np.inf)
    return sim


def similarity(
    features: Sequence[Features], config: ShortlistConfig, vlads: Callable[[], np.ndarray] | None = None
) -> np.ndarray:
    """Cosine similarity of the photos' VLADs (:func:`global_descriptors`, or ``vlads()`` where the caller keeps
    them). [N, N] float64

    Symmetric, in [−1, 1] off the diagonal; the diagonal is −inf (a photo is never its own match, and an argsort
    puts it last); a photo with no descriptors has −1 to every other photo.
    """
    return _cosine(vlads() if vlads is not None else global_descriptors(features, config))


def _retrieved(sim: np.ndarray, empty: np.ndarray, k: int) -> list[tuple[int, int]]:
    """Each non-empty photo's ``k`` most similar non-empty photos (ties: lower index first), as (min, max) pairs."""
    s = sim.copy()
    s[:, empty] = -np.inf
    order = np.argsort(-s, axis=1, kind="stable")[:, :k]
    pairs = []
    for i in np.flatnonzero(~empty).tolist():
        for j in order[i].tolist():
            if np.isfinite(s[i, j]):
                pairs.append((min(i, j), max(i, j)))
    return pairs


def select_pairs(
    n: int, features: Sequence[Features] | None, config: ShortlistConfig,
    vlads: Callable[[], np.ndarray] | None = None,
) -> list[tuple[int, int]]:  # fmt: skip
    """The photo pairs to match, as ``(i, j)`` with ``i < j``, unique, sorted.

    ``n ≤ config.all_pairs_max``: every pair (``features`` may be None). Otherwise the union of each photo's
    ``config.similar`` most similar photos (:func:`similarity`; photos with no descriptors take part in no
    retrieved pair) and its ``config.sequence_neighbours`` neighbours on each side in file order: at most
    ``n · (similar + sequence_neighbours)`` pairs. Deterministic. ``vlads``: the features' VLADs where the caller
    keeps them (called only beyond ``all_pairs_max``).
    """
    if n < 0:
        raise ValueError(f"n must be ≥ 0, got {n}")
    if n <= config.all_pairs_max:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    if features is None or len(features) != n:
        got = "None" if features is None else f"{len(features)} photos"
        raise ValueError(f"select_pairs needs the {n} photos' features beyond all_pairs_max, got {got}")
    pairs = {(i, i + d) for i in range(n) for d in range(1, config.sequence_neighbours + 1) if i + d < n}
    if config.similar > 0:
        v = vlads() if vlads is not None else global_descriptors(features, config)
        empty = ~(np.abs(v).sum(axis=1) > 0)
        pairs.update(_retrieved(_cosine(v), empty, config.similar))
    return sorted(pairs)
