"""Candidate training pairs: which ordered pairs of a scene's frames are contexts, and their target views.

**Candidate pairs** (:func:`candidate_pairs`, Splatt3R's sampling, reference notes §4.4). In a scene
whose frames all have depth (or whose coverage matrix is given), ``coverage[a, b]`` is the fraction of
frame ``b``'s pixels visible in frame ``a`` (:func:`~macsplat_cli.datasets.coverage.coverage_matrix`,
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
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..datasets import EvalDataset, EvalScene
from ..errors import DatasetError, InputError

__all__ = ["CandidatePairs", "PairSamplingConfig", "TrainPair", "candidate_pairs"]

logger = logging.getLogger(__name__)


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
        crop: ``"centre"`` (cover ``size`` keeping the aspect, centre crop) or ``"principal-point"`` (first the
            largest window centred on the principal point, then the same: the MAC-Splat release's 512×512 frames).
        per_scene: samples per scene in an epoch, each drawn scene first (:meth:`CandidatePairs.draw_by_scene`,
            the MAC-Splat release's sampling, 20 there); None: every candidate pair once (or ``samples_per_epoch``).

    Raises:
        InputError: a value out of range.
    """

    coverage: tuple[float, float] = (0.3, 1.0)
    max_angle_deg: float = 60.0
    min_angle_deg: float = 5.0
    targets: int = 2
    size: tuple[int, int] = (256, 192)
    samples_per_epoch: int | None = None
    crop: str = "centre"
    per_scene: int | None = None

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
        if self.per_scene is not None and (int(self.per_scene) != self.per_scene or self.per_scene < 1):
            raise InputError(f"per_scene must be a positive integer or None, got {self.per_scene!r}")
        if self.per_scene is not None and self.samples_per_epoch is not None:
            raise InputError("per_scene and samples_per_epoch both set an epoch's length: give one")
        if self.crop not in ("centre", "principal-point"):
            raise InputError(f"crop {self.crop!r}: use centre or principal-point")


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
        self._groups: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # _scene_groups, built on first use

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

    def _scene_groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(order, first, scenes)``: the pairs sorted by scene then first context (stable), the bounds in
        ``order`` of each (scene, first context) block, and the bounds in ``first`` of each scene's blocks."""
        if self._groups is None:
            order = np.lexsort((self._context[:, 0], self._scene))
            keys = np.stack([self._scene[order], self._context[order, 0]], 1)
            first = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)]) if len(order) else order
            scene_of_first = keys[first, 0]
            scenes = np.flatnonzero(np.r_[True, scene_of_first[1:] != scene_of_first[:-1]]) if len(first) else first
            self._groups = (order, np.r_[first, len(order)], np.r_[scenes, len(first)])
        return self._groups

    @property
    def num_scenes(self) -> int:
        """Scenes with at least one pair."""
        return len(self._scene_groups()[2]) - 1

    def draw_by_scene(self, rng: np.random.Generator) -> int:
        """A pair index drawn as the MAC-Splat release draws a sample: a scene uniformly, then a first context
        uniformly among that scene's frames that are the first context of a pair, then a second uniformly among
        its partners (the release draws the first context among all frames, with fallbacks for one without a
        partner in range). Three draws from ``rng``. Raises IndexError without pairs."""
        order, first, scenes = self._scene_groups()
        if not len(order):
            raise IndexError("no pair to draw")
        s = int(rng.integers(len(scenes) - 1))
        f = int(rng.integers(scenes[s], scenes[s + 1]))
        return int(order[rng.integers(first[f], first[f + 1])])

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

    __hash__ = None  # type: ignore[assignment]  # equal to any equal sequence, so not hashable (as list)

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
            :func:`~macsplat_cli.datasets.coverage.coverage_matrix` (at 128 px).
        on_scene: progress callback ``(done, total)`` after each scene.

    Returns:
        The pairs, in a deterministic order (a sequence of :class:`TrainPair`).

    Raises:
        DatasetError: no valid pair in the whole data set (naming it), or a given matrix of the wrong shape or
            with non-finite values.
    """
    from ..datasets.coverage import coverage_matrix  # torch: imported on use

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
