"""Training samples: context pairs and target views drawn from posed data sets, and their loader.

**Candidate pairs** (:func:`candidate_pairs`, Splatt3R's sampling, reference notes §4.4). In a scene
whose frames all have depth (or whose coverage matrix is given), ``coverage[a, b]`` is the fraction of
frame ``b``'s pixels visible in frame ``a`` (:func:`~macsplat_cli.evaluation.coverage.coverage_matrix`,
Splatt3R's visibility test). An *ordered* pair ``(a, b)`` is a candidate when
``lo ≤ coverage[a, b] ≤ hi`` (``PairSamplingConfig.coverage``; Splatt3R enumerates ``c1`` and draws
``c2`` with ``coverage[c1][c2] > φ``, so both orders of a pair are candidates when both directions meet
the range, and ``a`` — the first context — defines the frame the network predicts in). The default
``(0.3, 1.0)`` is Splatt3R's training threshold φ = 0.3 with no upper bound; an upper bound below 1
drops near-duplicate views. The pair's candidate targets are the other frames ``f`` with
``max(coverage[a, f], coverage[b, f]) ≥ lo`` (ψ = φ, a per-context maximum as in Splatt3R: at least
``lo`` of the target is seen by one of the contexts).

In a scene without depth the optical-axis angle
(:func:`~macsplat_cli.evaluation.splits.optical_axis_angle_deg`) stands in for coverage: a pair is a
candidate when ``min_angle_deg ≤ angle(a, b) ≤ max_angle_deg``, and its targets are the frames within
``max_angle_deg`` of both contexts. This proxy ignores translation; it fits object-centric and
forward-facing captures.

Pairs whose two camera centres coincide (no baseline) and pairs without any target are not candidates.
The list is deterministic (scenes, then ``a``, then ``b`` in order; no randomness).

**Cost.** The candidates are not listed with their targets (``O(N³)`` for a scene of ``N`` frames: at 2,000
frames, ~1.2 M ordered pairs of ~600 targets each). :class:`CandidatePairs` keeps each pair's scene and
contexts (``[M]`` and ``[M, 2]`` int32) and one ``[N, N]`` Boolean "seen" matrix per scene, and a pair's
targets are derived when it is sampled (``O(N)``): building is ``O(N²)`` time and memory per scene (by
angle, plus one Boolean matrix product in BLAS that tells which pairs have a target, ~0.2 s at 2,000 frames),
not counting the coverage matrix of a scene with depth. The pairs, their order, their targets and every draw
are those of the full listing.

**Samples** (:class:`PairDataset`). Sample ``i`` of an epoch uses pair ``i`` (every candidate once per
epoch), or — with ``samples_per_epoch`` — pair ``perm[i mod P]`` of a per-epoch permutation. Its
``targets`` target views are drawn from the pair's candidates without replacement (with repetition
when the pair has fewer). Every draw comes from a generator seeded with ``(seed, epoch, i)`` only, so a
sample does not depend on the worker that makes it, nor on the order of the requests.

**Images** (:func:`resize_and_crop`): scaled, keeping the aspect ratio, to the smallest size covering
``size`` = (W, H), then centre-cropped to ``size``; ``K`` is scaled by the per-axis resize factors and
shifted by the crop offset (exact with macsplat's pixel-centre-at-+0.5 convention).

**Unreadable images.** A sample with an image that cannot be decoded is replaced by another one drawn
with ``(seed, epoch, i, attempt)``; each file is named once in a warning, and ``PairDataset.skipped``
counts the samples each file made skip (with :func:`make_loader`, counted in the main process whatever
the number of workers). When every image is unreadable, or no readable sample turns up after
:data:`MAX_ATTEMPTS` draws, :class:`~macsplat_cli.errors.DatasetError`.

**Loader** (:func:`make_loader`): a :class:`torch.utils.data.distributed.DistributedSampler` (seeded;
with ``world_size = 1`` it is a plain seeded shuffle), so the ranks of a world split one permutation
without overlap; :meth:`PairLoader.set_epoch` moves the sampler and the draws to another epoch.
"""

from __future__ import annotations

import itertools
import logging
import random
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate
from torch.utils.data.distributed import DistributedSampler

from ..datasets import EvalDataset, EvalScene, resize_depth_nearest
from ..errors import DatasetError, ImageReadError, InputError
from ..images import load_image

__all__ = [
    "MAX_ATTEMPTS",
    "CandidatePairs",
    "PairDataset",
    "PairLoader",
    "PairSamplingConfig",
    "TrainPair",
    "candidate_pairs",
    "make_loader",
    "resize_and_crop",
]

logger = logging.getLogger(__name__)

MAX_ATTEMPTS = 100
"""Most draws for one sample before giving up on unreadable images."""
_SAMPLE_TAG = 0x5A17
_PERM_TAG = 0x9E12


# ------------------------------------------------------------------------------------ config and pairs
@dataclass
class PairSamplingConfig:
    """How training samples are drawn (module docstring).

    Args:
        coverage: ``(lo, hi)`` range of ``coverage[a, b]`` for a context pair; ``lo`` is also the target
            threshold ψ. Default: Splatt3R's φ = ψ = 0.3, no upper bound.
        max_angle_deg: scenes without depth: largest optical-axis angle of a context pair, and between a
            target and each context.
        min_angle_deg: scenes without depth: smallest optical-axis angle of a context pair.
        targets: target views per sample (fixed, for batching).
        size: ``(W, H)`` of every image of a sample, multiples of 16.
        samples_per_epoch: samples in an epoch; None: every candidate pair once.

    Raises:
        InputError: a value out of range.
    """

    coverage: tuple[float, float] = (0.3, 1.0)
    max_angle_deg: float = 60.0
    min_angle_deg: float = 5.0
    targets: int = 2
    size: tuple[int, int] = (256, 192)
    samples_per_epoch: int | None = None

    def __post_init__(self) -> None:
        lo, hi = (float(x) for x in self.coverage)
        if not 0.0 <= lo <= hi <= 1.0:
            raise InputError(f"coverage range must satisfy 0 ≤ lo ≤ hi ≤ 1, got {self.coverage!r}")
        self.coverage = (lo, hi)
        if not 0.0 <= self.min_angle_deg <= self.max_angle_deg <= 180.0:
            raise InputError(
                f"angle range must satisfy 0 ≤ min ≤ max ≤ 180 degrees, got {self.min_angle_deg}–{self.max_angle_deg}"
            )
        if int(self.targets) != self.targets or self.targets < 1:
            raise InputError(f"targets must be a positive integer, got {self.targets!r}")
        w, h = (int(x) for x in self.size)
        if (w, h) != tuple(self.size) or w <= 0 or h <= 0 or w % 16 or h % 16:
            raise InputError(f"size must be (W, H), positive multiples of 16, got {self.size!r}")
        self.size = (w, h)
        if self.samples_per_epoch is not None and (
            int(self.samples_per_epoch) != self.samples_per_epoch or self.samples_per_epoch < 1
        ):
            raise InputError(f"samples_per_epoch must be a positive integer or None, got {self.samples_per_epoch!r}")


@dataclass(frozen=True)
class TrainPair:
    """One candidate: a scene, two context frames and the frames that may serve as targets (indices).

    Attributes:
        scene: index into ``dataset.scenes``.
        context: ``(a, b)`` frame indices; ``a`` is the first context view (the prediction frame).
        targets: candidate target frame indices (neither context), at least one.
    """

    scene: int
    context: tuple[int, int]
    targets: tuple[int, ...]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise angles between unit vectors, in degrees. [N, 3], [M, 3] → [N, M]"""
    return np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))


@dataclass(frozen=True)
class _TargetRule:
    """The candidate targets of the pairs of one scene, without listing them.

    Attributes:
        seen: ``[N, N]`` bool; coverage: ``coverage[a, f] ≥ lo``; angle: ``angle(a, f) ≤ max_angle_deg``.
        both: a target must be seen by both contexts (angle), else by either (coverage).
    """

    seen: np.ndarray
    both: bool

    def targets(self, a: int, b: int) -> np.ndarray:
        """The candidate targets of the pair ``(a, b)``, ascending. [K] int64"""
        ok = (self.seen[a] & self.seen[b]) if self.both else (self.seen[a] | self.seen[b])
        ok[[a, b]] = False
        return np.flatnonzero(ok)

    def has_targets(self, pair_ok: np.ndarray) -> np.ndarray:
        """Which pairs ``(a, b)`` of ``pair_ok`` (``[N, N]`` bool, no diagonal) have at least one target. [N, N] bool

        Coverage (either context): ``O(N²)``, from the row counts of ``seen``. Angle (both contexts): the count of
        frames seen by both is ``(seen @ seenᵀ)[a, b]``, one Boolean matrix product (``O(N³)`` multiply-adds in
        BLAS, exact in float32 below 2²⁴ frames; ~0.2 s at 2,000 frames), in row blocks of ``_ROWS``.
        """
        s = self.seen
        diag = s.diagonal().astype(np.int32)
        if not self.both:  # |seen[a] \ {a, b}| > 0 or |seen[b] \ {a, b}| > 0
            outside = s.sum(1, dtype=np.int32)[:, None] - diag[:, None] - s  # [a, b]: |seen[a] \ {a, b}|
            return pair_ok & ((outside > 0) | (outside.T > 0))
        out = np.zeros_like(pair_ok)
        f32 = s.astype(np.float32)
        rows = np.flatnonzero(pair_ok.any(1))
        for i in range(0, len(rows), _ROWS):
            r = rows[i : i + _ROWS]
            both = f32[r] @ f32.T  # [a, b]: frames seen by a and b, a and b themselves included
            both -= diag[r, None] * s[:, r].T  # f = a: seen[a, a] & seen[b, a]
            both -= s[r] * diag[None, :]  # f = b: seen[a, b] & seen[b, b]
            out[r] = pair_ok[r] & (both > 0.5)
        return out

    def used_frames(self, pairs: np.ndarray) -> np.ndarray:
        """The frames that ``pairs`` (``[P, 2]``, this scene's) name as a context or a candidate target. [F] int64"""
        n = len(self.seen)
        P = np.zeros((n, n), dtype=bool)
        P[pairs[:, 0], pairs[:, 1]] = True
        used = np.zeros(n, dtype=bool)
        used[pairs.ravel()] = True
        s = self.seen & ~np.eye(n, dtype=bool)
        if not self.both:  # f a target through context a: seen[a, f] and a pair (a, b) with b ≠ f; likewise for b
            row, col = P.sum(1), P.sum(0)
            used |= (s & ((row[:, None] - P) > 0)).any(0) | (s & ((col[:, None] - P.T) > 0)).any(0)
        else:  # f a target: a pair (a, b) among the frames ≠ f that see it (usually every frame is a context)
            for f in np.flatnonzero(~used):
                near = np.flatnonzero(s[:, f])
                used[f] = bool(P[np.ix_(near, near)].any())
        return np.flatnonzero(used)


_ROWS = 512
"""Row block of the Boolean matrix products (memory ``_ROWS × N`` floats)."""


class CandidatePairs(Sequence[TrainPair]):
    """The candidate pairs (:func:`candidate_pairs`) as compact arrays: a sequence of :class:`TrainPair`.

    The ``M`` pairs are stored as their scene and context indices (``[M]``, ``[M, 2]`` int32); the targets of a pair
    are derived when asked (``O(N)`` for a scene of ``N`` frames) from one ``[N, N]`` Boolean matrix per scene, so
    memory is ``O(M + Σ N²)`` — never the ``O(N³)`` of listing every pair's targets. A list of explicit
    :class:`TrainPair` (:meth:`from_pairs`) is stored with its targets as given.

    ``pairs[k]`` builds pair ``k``; ``pairs.targets(k)`` gives its targets as an array; :meth:`subset` selects pairs
    by index without copying the per-scene matrices. Two sequences of the same pairs compare equal.
    """

    def __init__(
        self,
        scene: np.ndarray,
        context: np.ndarray,
        rules: Mapping[int, _TargetRule] | None = None,
        explicit: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        self._scene = np.ascontiguousarray(scene, dtype=np.int32).reshape(-1)
        self._context = np.ascontiguousarray(context, dtype=np.int32).reshape(-1, 2)
        self._rules = dict(rules) if rules is not None else None
        self._explicit = explicit  # (offsets [M + 1] int64, targets [Σ] int32)

    @classmethod
    def from_pairs(cls, pairs: Sequence[TrainPair]) -> CandidatePairs:
        """Explicit pairs, targets as given (``O(Σ targets)``)."""
        if isinstance(pairs, CandidatePairs):
            return pairs
        offsets = np.cumsum([0] + [len(p.targets) for p in pairs]).astype(np.int64)
        targets = np.fromiter((t for p in pairs for t in p.targets), np.int32, int(offsets[-1]))
        return cls(
            np.array([p.scene for p in pairs], np.int32),
            np.array([p.context for p in pairs], np.int32).reshape(-1, 2),
            explicit=(offsets, targets),
        )

    @classmethod
    def concatenate(cls, parts: Sequence[CandidatePairs]) -> CandidatePairs:
        """The pairs of several rule-based sets of distinct scenes, in order."""
        rules: dict[int, _TargetRule] = {}
        for p in parts:
            rules.update(p._rules or {})
        scene = np.concatenate([p._scene for p in parts]) if parts else np.zeros(0, np.int32)
        context = np.concatenate([p._context for p in parts]) if parts else np.zeros((0, 2), np.int32)
        return cls(scene, context, rules)

    def __len__(self) -> int:
        return len(self._scene)

    def scene(self, k: int) -> int:
        return int(self._scene[k])

    def context(self, k: int) -> tuple[int, int]:
        c = self._context[k]
        return int(c[0]), int(c[1])

    def targets(self, k: int) -> np.ndarray:
        """The candidate targets of pair ``k``, ascending. [K] int"""
        if self._explicit is not None:
            offsets, targets = self._explicit
            return targets[offsets[k] : offsets[k + 1]]
        assert self._rules is not None
        a, b = self._context[k]
        return self._rules[int(self._scene[k])].targets(int(a), int(b))

    def __getitem__(self, k: Any) -> Any:
        if isinstance(k, slice):
            return self.subset(np.arange(len(self))[k])
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(f"pair {k} out of range ({len(self)})")
        return TrainPair(self.scene(k), self.context(k), tuple(int(t) for t in self.targets(k)))

    def __iter__(self) -> Iterator[TrainPair]:
        return (self[k] for k in range(len(self)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, (str, bytes)):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"CandidatePairs({len(self)} pairs over {len(np.unique(self._scene))} scene(s))"

    def subset(self, indices: Sequence[int] | np.ndarray) -> CandidatePairs:
        """The pairs ``indices`` (in that order)."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= len(self)):
            raise IndexError(f"pair indices out of range ({len(self)})")
        explicit = None
        if self._explicit is not None:
            offsets, targets = self._explicit
            sizes = offsets[idx + 1] - offsets[idx]
            new_offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
            parts = [targets[offsets[k] : offsets[k + 1]] for k in idx]
            explicit = (new_offsets, np.concatenate(parts).astype(np.int32) if parts else np.zeros(0, np.int32))
        return CandidatePairs(self._scene[idx], self._context[idx], self._rules, explicit)

    def used_frames(self) -> dict[int, np.ndarray]:
        """Per scene, the frames these pairs name (as a context or a candidate target)."""
        out: dict[int, np.ndarray] = {}
        for s in np.unique(self._scene):
            sel = self._scene == s
            if self._explicit is not None:
                frames = [self._context[sel].ravel()] + [self.targets(int(k)) for k in np.flatnonzero(sel)]
                out[int(s)] = np.unique(np.concatenate(frames))
            else:
                assert self._rules is not None
                out[int(s)] = self._rules[int(s)].used_frames(self._context[sel])
        return out

    def validate(self, dataset: EvalDataset) -> None:
        """Every pair inside ``dataset``, with two distinct contexts and at least one target.

        Raises:
            DatasetError: the first pair that is not.
        """
        bad = np.zeros(len(self), dtype=bool)
        n = np.zeros(len(self), dtype=np.int64)  # frames in each pair's scene (0: no such scene)
        for s in np.unique(self._scene):
            if 0 <= s < len(dataset.scenes):
                n[self._scene == s] = len(dataset.scenes[s].frames)
        bad |= (self._context < 0).any(1) | (self._context >= n[:, None]).any(1)
        bad |= self._context[:, 0] == self._context[:, 1]
        if self._explicit is not None:
            offsets, targets = self._explicit
            counts = offsets[1:] - offsets[:-1]
            bad |= counts == 0
            owner = np.repeat(np.arange(len(self)), counts)
            bad[owner[(targets < 0) | (targets >= n[owner])]] = True
        else:
            assert self._rules is not None
            for s in np.unique(self._scene):
                rule = self._rules.get(int(s))
                sel = self._scene == s
                if rule is None or rule.seen.shape != (n[sel][0],) * 2:
                    bad |= sel
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise DatasetError(f"{dataset.root}: invalid training pair {self.scene(k), self.context(k)}")


def _scene_pairs(
    si: int, scene: EvalScene, config: PairSamplingConfig, coverage: np.ndarray | None
) -> tuple[CandidatePairs, str]:
    """The candidate pairs of one scene: ``O(N²)`` time and memory (plus one ``N × N`` Boolean matrix product
    by angle, :meth:`_TargetRule.has_targets`)."""
    n = len(scene.frames)
    centres = np.stack([f.camera.center for f in scene.frames])
    extent = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) if n else 0.0
    apart = np.zeros((n, n), dtype=bool)
    for i in range(0, n, _ROWS):  # [rows, N, 3] at a time, not [N, N, 3]
        apart[i : i + _ROWS] = np.linalg.norm(centres[i : i + _ROWS, None] - centres[None], axis=-1) > 1e-6 * max(
            extent, 1e-12
        )
    if coverage is not None:
        lo, hi = config.coverage
        pair_ok = (coverage >= lo) & (coverage <= hi)
        rule = _TargetRule(coverage >= lo, both=False)  # max(cov[a, f], cov[b, f]) ≥ lo
        mode = "coverage"
    else:
        axes = np.stack([f.camera.cam_to_world[:3, 2] for f in scene.frames])
        axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
        ang = _angle_deg(axes, axes)
        pair_ok = (ang >= config.min_angle_deg) & (ang <= config.max_angle_deg)
        rule = _TargetRule(ang <= config.max_angle_deg, both=True)
        mode = "angle"
    pair_ok &= apart & ~np.eye(n, dtype=bool)
    a, b = np.nonzero(rule.has_targets(pair_ok))  # row-major: a, then b
    pairs = CandidatePairs(np.full(len(a), si, np.int32), np.stack([a, b], 1), {si: rule})
    return pairs, mode


def candidate_pairs(
    dataset: EvalDataset,
    config: PairSamplingConfig,
    *,
    coverage: Mapping[str, np.ndarray] | None = None,
    on_scene: Callable[[int, int], None] | None = None,
) -> CandidatePairs:
    """Every candidate context pair of every scene, with its candidate targets (module docstring).

    Cost per scene of ``N`` frames: ``O(N²)`` time and memory (by angle, plus one ``N × N`` Boolean matrix product
    in BLAS, ~0.2 s at 2,000 frames), not counting the coverage matrix of a scene with depth; the targets of a pair
    are derived when the pair is used (:class:`CandidatePairs`).

    Args:
        dataset: the data set.
        config: the sampling settings.
        coverage: precomputed coverage matrices by scene name (``[N, N]``, ``[a, b]`` = fraction of
            ``b`` seen by ``a``, e.g. Splatt3R's ``coverage/<scene>.json``); other scenes with depth get
            :func:`~macsplat_cli.evaluation.coverage.coverage_matrix` (at 128 px).
        on_scene: progress callback ``(done, total)`` after each scene.

    Returns:
        The pairs, in a deterministic order (a sequence of :class:`TrainPair`).

    Raises:
        DatasetError: no valid pair in the whole data set (naming it), or a given matrix of the wrong shape or
            with non-finite values.
    """
    from ..evaluation.coverage import coverage_matrix  # the evaluation package is heavier; import on use

    coverage = coverage or {}
    parts: list[CandidatePairs] = []
    for si, scene in enumerate(dataset.scenes):
        n = len(scene.frames)
        cov = coverage.get(scene.name)
        if cov is not None:
            cov = np.asarray(cov, dtype=np.float64)
            if cov.shape != (n, n):
                raise DatasetError(
                    f"{dataset.root}: coverage of scene {scene.name!r} is {list(cov.shape)}, expected [{n}, {n}]"
                )
            if not np.isfinite(cov).all():
                raise DatasetError(f"{dataset.root}: coverage of scene {scene.name!r} holds non-finite values")
        elif scene.has_depth:
            cov = coverage_matrix(scene)
        pairs, mode = _scene_pairs(si, scene, config, cov)
        if not len(pairs):
            logger.warning("scene %s: no valid training pair (by %s)", scene.name, mode)
        else:
            logger.info("scene %s: %d training pair(s) by %s", scene.name, len(pairs), mode)
        parts.append(pairs)
        if on_scene is not None:
            on_scene(si + 1, len(dataset.scenes))
    out = CandidatePairs.concatenate(parts)
    if not len(out):
        lo, hi = config.coverage
        raise DatasetError(
            f"{dataset.root}: no valid pair in the data set (coverage {lo:g}–{hi:g} with depth, "
            f"optical-axis angle {config.min_angle_deg:g}–{config.max_angle_deg:g}° without, and at least one "
            "target)"
        )
    return out


# ------------------------------------------------------------------------------------ images
def _fit(width: int, height: int, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(resized W, resized H, crop x0, crop y0) of the aspect-preserving cover-and-centre-crop."""
    W, H = size
    s = max(W / width, H / height)
    rw, rh = max(W, round(width * s)), max(H, round(height * s))
    return rw, rh, (rw - W) // 2, (rh - H) // 2


def resize_and_crop(image: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Scale an image to cover ``size`` = (W, H) keeping its aspect ratio, centre-crop, and adjust ``K``.

    Args:
        image: ``[h, w, C]`` or ``[h, w]``.
        K: intrinsics of ``image`` (pixel centres at +0.5). [3, 3]
        size: output (W, H).

    Returns:
        ``(image [H, W, C], K [3, 3] float64)``: ``K`` row 0 is scaled by ``W'/w`` and row 1 by
        ``H'/h`` (``W' × H'`` the resized size), then ``cx -= x0``, ``cy -= y0`` (the crop's corner).
        The image is resampled bilinearly at pixel centres, antialiased when shrinking; float32.
    """
    h, w = image.shape[:2]
    rw, rh, x0, y0 = _fit(w, h, size)
    if (rw, rh) != (w, h):
        # torch, not OpenCV: OpenCV's thread pool can deadlock in forked loader workers
        t = torch.from_numpy(np.ascontiguousarray(image, np.float32))
        t = t[None, None] if t.ndim == 2 else t.permute(2, 0, 1)[None]
        t = F.interpolate(t, size=(rh, rw), mode="bilinear", antialias=rw < w or rh < h, align_corners=False)
        image = (t[0, 0] if image.ndim == 2 else t[0].permute(1, 2, 0)).numpy()
    W, H = size
    out = np.ascontiguousarray(image[y0 : y0 + H, x0 : x0 + W])
    K2 = np.array(K, dtype=np.float64)
    K2[0] *= rw / w
    K2[1] *= rh / h
    K2[0, 2] -= x0
    K2[1, 2] -= y0
    return out, K2


def _crop_depth(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    h, w = depth.shape
    rw, rh, x0, y0 = _fit(w, h, size)
    d = resize_depth_nearest(depth, rw, rh)
    return np.ascontiguousarray(d[y0 : y0 + size[1], x0 : x0 + size[0]])


class _Unreadable(Exception):
    def __init__(self, path: str, reason: str) -> None:
        super().__init__(path)
        self.path, self.reason = path, reason


# ------------------------------------------------------------------------------------ dataset
class PairDataset(Dataset):
    """Training samples of two context views and ``config.targets`` target views (module docstring).

    ``dataset[i]`` is a dict of tensors (``T = config.targets``, ``(W, H) = config.size``):

    * ``"context"``: ``[2, 3, H, W]`` float32 in [0, 1]; ``"context_K"``: ``[2, 3, 3]`` float64 (of the
      resized, cropped image, pixel centres at +0.5); ``"context_c2w"``: ``[2, 4, 4]`` float64 (world);
    * ``"target"``: ``[T, 3, H, W]``; ``"target_K"``: ``[T, 3, 3]``; ``"target_c2w"``: ``[T, 4, 4]``;
    * ``"index"``: the sample index ``i``, int64 scalar;
    * with ``depth=True``: ``"context_depth"`` ``[2, H, W]`` and ``"target_depth"`` ``[T, H, W]`` float32
      (ground truth, nearest-resized and cropped like the image; 0 = none or a frame without depth).

    Attributes:
        skipped: per unreadable image file, the number of samples it made skip (in this process).

    Raises:
        DatasetError: no pair, or a pair pointing outside the data set.
    """

    def __init__(
        self,
        dataset: EvalDataset,
        pairs: Sequence[TrainPair],
        config: PairSamplingConfig,
        *,
        seed: int = 0,
        epoch: int = 0,
        depth: bool = False,
    ) -> None:
        if not len(pairs):
            raise DatasetError(f"{dataset.root}: no training pair")
        # compact arrays, not a list of Python objects: cheap to fork or pickle into workers
        self._pairs = CandidatePairs.from_pairs(pairs)
        self._pairs.validate(dataset)
        self.dataset = dataset
        self.config = config
        self.seed = int(seed) % 2**63
        self.epoch = int(epoch)
        self.depth = bool(depth)
        self._images: set[str] | None = None  # every image the pairs name, listed on the first unreadable one
        self.skipped: dict[str, int] = {}
        self._bad: dict[str, str] = {}
        self._perms: dict[tuple[int, int], np.ndarray] = {}

    @property
    def num_pairs(self) -> int:
        return len(self._pairs)

    @property
    def pairs(self) -> CandidatePairs:
        """The candidate pairs (a sequence of :class:`TrainPair`)."""
        return self._pairs

    def pair(self, k: int) -> TrainPair:
        """Candidate pair ``k``."""
        return self._pairs[k]

    def set_epoch(self, epoch: int) -> None:
        """Draw the pairs (with ``samples_per_epoch``), targets and replacements of another epoch."""
        self.epoch = int(epoch)
        self._perms.clear()

    def __len__(self) -> int:
        n = self.config.samples_per_epoch
        return self.num_pairs if n is None else int(n)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        sample, skipped = self.sample(i)
        for path, reason in skipped:
            self.record_skip(path, reason)
        return sample

    # -------------------------------------------------------------- internals
    def record_skip(self, path: str, reason: str) -> None:
        """Count one sample skipped because of ``path``; the first time, name it in a warning."""
        if path not in self.skipped:
            logger.warning("%s: unreadable image, skipped (%s)", path, reason)
        self.skipped[path] = self.skipped.get(path, 0) + 1

    def _all_images(self) -> set[str]:
        if self._images is None:
            self._images = {
                str(self.dataset.scenes[s].frames[int(j)].image)
                for s, frames in self._pairs.used_frames().items()
                for j in frames
            }
        return self._images

    def _pair_index(self, i: int) -> int:
        if self.config.samples_per_epoch is None:
            return i
        block, k = divmod(i, self.num_pairs)
        perm = self._perms.get((self.epoch, block))
        if perm is None:
            rng = np.random.default_rng([_PERM_TAG, self.seed, self.epoch % 2**63, block])
            perm = self._perms[(self.epoch, block)] = rng.permutation(self.num_pairs)
        return int(perm[k])

    def _draw_targets(self, rng: np.random.Generator, k: int) -> np.ndarray:
        cands = self._pairs.targets(k)
        T = self.config.targets
        if len(cands) >= T:
            return cands[rng.choice(len(cands), T, replace=False)]
        extra = cands[rng.choice(len(cands), T - len(cands), replace=True)]
        return np.concatenate([rng.permutation(cands), extra])

    def _view(self, scene: EvalScene, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        f = scene.frames[j]
        key = str(f.image)
        if key in self._bad:
            raise _Unreadable(key, self._bad[key])
        try:
            rgb = load_image(f.image).rgb
            if rgb.shape[:2] != (f.camera.height, f.camera.width):
                raise ImageReadError(
                    f"the image is {rgb.shape[1]}x{rgb.shape[0]}, its camera {f.camera.width}x{f.camera.height}"
                )
        except ImageReadError as e:
            self._bad[key] = str(e)
            raise _Unreadable(key, str(e)) from None
        img, K = resize_and_crop(rgb, f.camera.K, self.config.size)
        d = None
        if self.depth:
            raw = scene.depth(j)
            W, H = self.config.size
            d = _crop_depth(raw, self.config.size) if raw is not None else np.zeros((H, W), np.float32)
        return img, K, d

    def sample(self, i: int) -> tuple[dict[str, torch.Tensor], list[tuple[str, str]]]:
        """Sample ``i`` and the ``(file, reason)`` of each unreadable image that made a draw skip."""
        if not 0 <= i < len(self):
            raise IndexError(f"sample {i} out of range ({len(self)})")
        skipped: list[tuple[str, str]] = []
        for attempt in range(MAX_ATTEMPTS):
            rng = np.random.default_rng([_SAMPLE_TAG, self.seed, self.epoch % 2**63, i, attempt])
            k = self._pair_index(i) if attempt == 0 else int(rng.integers(self.num_pairs))
            targets = self._draw_targets(rng, k)
            scene = self.dataset.scenes[self._pairs.scene(k)]
            frames = [int(j) for j in (*self._pairs.context(k), *targets)]
            try:
                views = [self._view(scene, j) for j in frames]
            except _Unreadable as e:
                skipped.append((e.path, e.reason))
                if self._all_images().issubset(self._bad):
                    raise DatasetError(
                        f"{self.dataset.root}: every image of the training pairs is unreadable "
                        f"(e.g. {e.path}: {e.reason})"
                    ) from None
                continue
            imgs = torch.from_numpy(np.stack([v[0] for v in views])).permute(0, 3, 1, 2).contiguous()
            Ks = torch.from_numpy(np.stack([v[1] for v in views]))
            c2w = torch.from_numpy(np.stack([np.array(scene.frames[j].camera.cam_to_world) for j in frames]))
            out = {
                "context": imgs[:2],
                "context_K": Ks[:2],
                "context_c2w": c2w[:2],
                "target": imgs[2:],
                "target_K": Ks[2:],
                "target_c2w": c2w[2:],
                "index": torch.tensor(i, dtype=torch.int64),
            }
            if self.depth:
                ds = torch.from_numpy(np.stack([v[2] for v in views]))
                out["context_depth"], out["target_depth"] = ds[:2], ds[2:]
            return out, skipped
        raise DatasetError(
            f"{self.dataset.root}: no readable sample after {MAX_ATTEMPTS} draws for sample {i} "
            f"({len(self._bad)} unreadable image(s), e.g. {skipped[-1][0]})"
        )


# ------------------------------------------------------------------------------------ loader
class _Reporting(Dataset):
    """``PairDataset`` whose items carry the unreadable files, so the main process can count them."""

    def __init__(self, ds: PairDataset) -> None:
        self.ds = ds

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, i: int) -> tuple[dict[str, torch.Tensor], list[tuple[str, str]]]:
        return self.ds.sample(i)


def _collate(
    items: list[tuple[dict[str, torch.Tensor], list[tuple[str, str]]]],
) -> tuple[dict[str, torch.Tensor], list[tuple[str, str]]]:
    return default_collate([s for s, _ in items]), [x for _, sk in items for x in sk]


def _seed_worker(worker_id: int) -> None:
    """Seed the global generators of a worker from its (deterministic) torch seed.

    (Not ``cv2.setNumThreads``: in a forked worker it can deadlock on the parent's thread pool.)
    """
    s = torch.initial_seed() % 2**32
    np.random.seed(s)
    random.seed(s)


class PairLoader(DataLoader):
    """A :class:`~torch.utils.data.DataLoader` of :class:`PairDataset` batches (:func:`make_loader`).

    Iterating yields the batches (dicts of tensors with a leading batch axis); unreadable files met by
    the workers are counted in ``pair_dataset.skipped`` and named once in a warning, in this process.

    Attributes:
        pair_dataset: the :class:`PairDataset` (``dataset`` is an internal wrapper of it).
    """

    pair_dataset: PairDataset

    def set_epoch(self, epoch: int) -> None:
        """Shuffle and draw for ``epoch`` (call before iterating; workers are started per epoch)."""
        self.pair_dataset.set_epoch(epoch)
        sampler = self.sampler.sampler if isinstance(self.sampler, _Skip) else self.sampler
        if isinstance(sampler, DistributedSampler):
            sampler.set_epoch(epoch)

    def __iter__(self) -> Any:  # type: ignore[override]
        for batch, skipped in super().__iter__():
            for path, reason in skipped:
                self.pair_dataset.record_skip(path, reason)
            yield batch


class _Skip(Sampler):
    """A sampler without its first ``start`` indices (a resumed epoch: what was done is not loaded again)."""

    def __init__(self, sampler: DistributedSampler, start: int) -> None:
        self.sampler, self.start = sampler, int(start)

    def __iter__(self) -> Iterator[int]:
        return itertools.islice(iter(self.sampler), self.start, None)

    def __len__(self) -> int:
        return max(0, len(self.sampler) - self.start)


def make_loader(
    ds: PairDataset,
    *,
    batch_size: int,
    workers: int = 0,
    shuffle: bool = True,
    seed: int = 0,
    rank: int = 0,
    world_size: int = 1,
    drop_last: bool = True,
    pin_memory: bool = False,
    start_batch: int = 0,
) -> PairLoader:
    """A deterministic loader of ``ds``: the same seed and epoch give the same batches, whatever ``workers``.

    The sampler is a :class:`~torch.utils.data.distributed.DistributedSampler` seeded with ``seed``
    (the same on every rank): rank ``r`` of ``world_size`` takes every ``world_size``-th index of one
    permutation of the epoch, so the ranks never overlap (with ``drop_last`` the tail that does not
    divide evenly is dropped; without, it is padded by repeating indices, as torch does). With
    ``world_size = 1`` it is a seeded shuffle. Call :meth:`PairLoader.set_epoch` before each epoch.

    Args:
        ds: the samples.
        batch_size: samples per batch (per rank).
        workers: worker processes (0: load in this process).
        shuffle: shuffle the samples of each epoch.
        seed: seed of the shuffle and of the workers' global generators.
        rank: this process's rank.
        world_size: number of processes.
        drop_last: drop the last incomplete batch (and the sampler's uneven tail).
        pin_memory: pin batches in page-locked memory (faster copies to a GPU).
        start_batch: begin the epoch at this batch (the samples before it are skipped, not loaded); the batches
            that follow are those of a loader that started at 0 (every sample's draw depends on its index only).

    Raises:
        InputError: a bad batch size, worker count, rank or start batch.
    """
    if batch_size < 1:
        raise InputError(f"batch size must be at least 1, got {batch_size}")
    if workers < 0:
        raise InputError(f"workers must be ≥ 0, got {workers}")
    if world_size < 1 or not 0 <= rank < world_size:
        raise InputError(f"rank {rank} is not in a world of {world_size}")
    if start_batch < 0:
        raise InputError(f"start batch must be ≥ 0, got {start_batch}")
    wrapped = _Reporting(ds)
    sampler = DistributedSampler(
        wrapped, num_replicas=world_size, rank=rank, shuffle=shuffle, seed=int(seed), drop_last=drop_last
    )
    sampler.set_epoch(ds.epoch)
    order: Sampler = _Skip(sampler, start_batch * batch_size) if start_batch else sampler
    generator = torch.Generator()
    generator.manual_seed(int(seed) % 2**63)
    loader = PairLoader(
        wrapped,
        batch_size=batch_size,
        sampler=order,
        num_workers=workers,
        collate_fn=_collate,
        pin_memory=pin_memory,
        drop_last=drop_last,
        worker_init_fn=_seed_worker if workers > 0 else None,
        generator=generator,
        persistent_workers=False,
    )
    loader.pair_dataset = ds
    return loader
