"""Test cases: which two frames are the context views, which frames are the targets, and the split.

**By coverage** (scenes with depth; Splatt3R's protocol, reference notes §4.4–4.5): a pair
``(c0, c1)`` (``c0`` the lower frame index, the world frame) has overlap
``coverage[c0, c1]`` (:func:`~macsplat_cli.datasets.coverage.coverage_matrix`: the fraction of ``c1``'s pixels
visible in ``c0``). The splits' thresholds (φ, ψ) are (0.9, 0.9) close, (0.7, 0.7) medium,
(0.5, 0.5) wide and (0.3, 0.3) very wide. A pair meets a split when its overlap is ≥ φ;
its targets are the other frames ``f`` with ``max(coverage[c0, f], coverage[c1, f]) ≥ ψ``
(a per-context maximum, not a union, as in Splatt3R).

**By view angle** (scenes without depth): the angle between the two optical axes, in
bins (upper bound inclusive) close ≤ 15°, medium 15–35°, wide 35–65°, very wide 65–100°
(wider pairs are not used). These bins put the CO3D sample's suggested pairs (12°, 27°,
55°, 83°) one in each split. Targets are the frames *between* the context views
(:func:`between_targets`).

**Assignment**: ``"bin"`` (default) puts a pair in the tightest split it meets, so that
the splits are disjoint and "very wide" means wide pairs only; ``"threshold"`` reads the
thresholds as lower bounds (Splatt3R's sampling rule, under which a close pair is also a
very-wide test case).

Pairs with no target, or (nearly) no baseline, are not used. At most ``max_pairs`` pairs
per split and scene, and ``max_targets`` targets per pair, are drawn with a seeded
generator, so a run is reproducible.

**More than two context views** (``--context-views N``): the cases are drawn as above, then
:func:`~.contexts.extend_cases` adds N − 2 frames to each pair (never a target).
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from .._limits import read_json_file
from ..cameras import Camera
from ..datasets import EvalDataset, EvalScene
from ..datasets.coverage import DEPTH_ATOL, DEPTH_RTOL, coverage_matrix
from ..errors import DatasetError
from ..metrics import angle_between_deg

__all__ = [
    "ANGLE_BINS_DEG",
    "COVERAGE_THRESHOLDS",
    "SPLITS",
    "CaseSelection",
    "EvalCase",
    "SplitConfig",
    "SplitName",
    "angle_splits",
    "between_targets",
    "coverage_splits",
    "load_cases",
    "make_cases",
    "optical_axis_angle_deg",
    "parse_splits",
]

logger = logging.getLogger(__name__)

SplitName = Literal["close", "medium", "wide", "very-wide"]
SPLITS: tuple[str, ...] = get_args(SplitName)
COVERAGE_THRESHOLDS: dict[str, tuple[float, float]] = {
    "close": (0.9, 0.9),
    "medium": (0.7, 0.7),
    "wide": (0.5, 0.5),
    "very-wide": (0.3, 0.3),
}
"""(φ, ψ): context-pair coverage and target coverage thresholds of each split."""
ANGLE_BINS_DEG: dict[str, tuple[float, float]] = {
    "close": (0.0, 15.0),
    "medium": (15.0, 35.0),
    "wide": (35.0, 65.0),
    "very-wide": (65.0, 100.0),
}
"""(low, high]: optical-axis angle bins of each split, for scenes without depth (close includes 0°)."""
SplitMode = Literal["auto", "coverage", "angle"]
Assignment = Literal["bin", "threshold"]


@dataclass(frozen=True)
class EvalCase:
    """One test case: the context frames and the target frames, indices into a scene's frames.

    Attributes:
        scene: scene name.
        split: split name (``"close"`` … ``"very-wide"``, or a name from a cases file).
        context: the context frames, in the order the reconstruction gets them: (c0, c1) for two, c0 defining the
            world frame; more than two (``--context-views``, :mod:`.contexts`) in path order.
        targets: target frame indices.
        criterion: ``"coverage"``, ``"angle"`` or ``"file"``.
        overlap: ``coverage[c0, c1]`` or the optical-axis angle in degrees of the pair (NaN for ``"file"``).
        pair: more than two contexts: the pair the case was drawn for (None: the context is the pair).
    """

    scene: str
    split: str
    context: tuple[int, ...]
    targets: tuple[int, ...]
    criterion: str = "file"
    overlap: float = math.nan
    pair: tuple[int, int] | None = None

    @property
    def key(self) -> str:
        """A unique, readable identifier: ``scene/split/c0-c1`` (``scene/split/c0-c1-c2-…`` for more contexts)."""
        return f"{self.scene}/{self.split}/{'-'.join(str(c) for c in self.context)}"

    @property
    def context_views(self) -> int:
        """The number of context frames."""
        return len(self.context)

    def to_dict(self) -> dict[str, Any]:
        out = {
            "scene": self.scene,
            "split": self.split,
            "context": list(self.context),
            "targets": list(self.targets),
            "criterion": self.criterion,
            "overlap": None if math.isnan(self.overlap) else self.overlap,
            "context_views": self.context_views,
        }
        if self.pair is not None:
            out["pair"] = list(self.pair)
        return out


@dataclass
class SplitConfig:
    """Args:
    splits: which splits to build.
    mode: ``"coverage"`` (needs depth), ``"angle"``, or ``"auto"`` (coverage when every
        frame of the scene has depth).
    assignment: ``"bin"`` (disjoint splits) or ``"threshold"`` (thresholds as lower bounds).
    max_pairs: most context pairs per split and scene (None: all).
    max_targets: most targets per pair (None: all).
    seed: seed of the draws.
    coverage_size: long side, in pixels, at which coverage is computed.
    depth_atol: absolute depth tolerance of the visibility test (scene units).
    depth_rtol: relative depth tolerance of the visibility test.
    angle_slack_deg: a target between the contexts may face up to this much more away
        from them than they differ from each other.
    """

    splits: tuple[str, ...] = SPLITS
    mode: SplitMode = "auto"
    assignment: Assignment = "bin"
    max_pairs: int | None = 5
    max_targets: int | None = 3
    seed: int = 0
    coverage_size: int = 128
    depth_atol: float = DEPTH_ATOL
    depth_rtol: float = DEPTH_RTOL
    angle_slack_deg: float = 15.0


@dataclass
class CaseSelection:
    """The cases of a run, with what they were chosen from.

    Attributes:
        cases: the test cases.
        modes: per scene, ``"coverage"`` or ``"angle"``.
        coverage: per scene with depth, its coverage matrix. [N, N]
        candidates: per (scene, split), the number of eligible pairs before the draw.
    """

    cases: list[EvalCase]
    modes: dict[str, str] = field(default_factory=dict)
    coverage: dict[str, np.ndarray] = field(default_factory=dict)
    candidates: dict[str, dict[str, int]] = field(default_factory=dict)


def parse_splits(text: str) -> tuple[str, ...]:
    """``"all"`` or a comma-separated list of split names → the names, in canonical order.

    Raises:
        DatasetError: an unknown name.
    """
    t = text.strip().lower()
    if t == "all":
        return SPLITS
    names = [s.strip().replace("_", "-") for s in t.split(",") if s.strip()]
    unknown = [s for s in names if s not in SPLITS]
    if unknown or not names:
        raise DatasetError(f"unknown split {', '.join(unknown) or text!r}; use all or a list of {', '.join(SPLITS)}")
    return tuple(s for s in SPLITS if s in names)


def coverage_splits(overlap: float, assignment: Assignment = "bin", splits: Sequence[str] = SPLITS) -> list[str]:
    """Splits whose pair threshold φ the context-pair coverage meets (the tightest one only with ``"bin"``)."""
    met = [s for s in SPLITS if overlap >= COVERAGE_THRESHOLDS[s][0]]
    if assignment == "bin":
        met = met[:1]
    return [s for s in met if s in splits]


def angle_splits(angle_deg: float, assignment: Assignment = "bin", splits: Sequence[str] = SPLITS) -> list[str]:
    """Splits whose angle bin holds ``angle_deg`` (``"bin"``), or whose upper bound it meets (``"threshold"``)."""
    if assignment == "bin":
        met = [s for s in SPLITS if ANGLE_BINS_DEG[s][0] < angle_deg <= ANGLE_BINS_DEG[s][1]]
        if angle_deg == 0.0:
            met = ["close"]
    else:
        met = [s for s in SPLITS if angle_deg <= ANGLE_BINS_DEG[s][1]]
    return [s for s in met if s in splits]


def optical_axis_angle_deg(a: Camera, b: Camera) -> float:
    """Angle between the optical axes (camera +z in the world) of two cameras, in degrees."""
    return float(angle_between_deg(a.cam_to_world[:3, 2], b.cam_to_world[:3, 2]))


def _rotation_angles_deg(R0: np.ndarray, Rs: np.ndarray) -> np.ndarray:
    """Angle of ``R0ᵀ R_k`` for every k, in degrees, by :func:`~macsplat_cli.metrics.rotation_angle_deg`'s formula.

    ``R0`` [3, 3], ``Rs`` [K, 3, 3] → [K].
    """
    D = np.einsum("ba,kbc->kac", np.asarray(R0, np.float64), np.asarray(Rs, np.float64))
    vee = np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], axis=-1)
    sin = 0.5 * np.linalg.norm(vee, axis=-1)
    cos = 0.5 * (np.trace(D, axis1=1, axis2=2) - 1.0)
    return np.degrees(np.arctan2(sin, cos))


def _between(
    centres: np.ndarray, ang_a: np.ndarray, ang_b: np.ndarray, pair: tuple[int, int], slack_deg: float
) -> list[int]:
    """:func:`between_targets` on the centres [N, 3] and the rotation angles (degrees) of every frame to the two
    context views [N] each: O(N), vectorised over the frames."""
    a, b = pair
    ca = centres[a]
    chord = centres[b] - ca
    length = float(np.linalg.norm(chord))
    if length == 0.0:
        return []
    d = centres - ca  # [N, 3]
    u = (d @ chord) / length**2  # [N]
    perp = np.linalg.norm(d - u[:, None] * chord, axis=-1)
    near = np.maximum(ang_a, ang_b) <= ang_a[b] + slack_deg
    ok = (u > 0.05) & (u < 0.95) & (perp < 0.5 * length) & near
    ok[[a, b]] = False
    return [int(i) for i in np.flatnonzero(ok)]


def _centres_and_rotations(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres [N, 3] and rotations [N, 3, 3] (camera to world), float64."""
    centres = np.stack([c.center for c in cameras]).astype(np.float64)
    return centres, np.stack([np.asarray(c.cam_to_world[:3, :3], np.float64) for c in cameras])


def between_targets(cameras: Sequence[Camera], pair: tuple[int, int], slack_deg: float = 15.0) -> list[int]:
    """Frames between two context views.

    A frame qualifies when its centre projects onto the segment between the two context
    centres (at 5–95 % of its length) within half the segment's length of it, and its
    orientation differs from each context view's by at most the contexts' own rotation
    angle plus ``slack_deg``. O(N) for N cameras, vectorised.
    """
    centres, Rs = _centres_and_rotations(cameras)
    a, b = pair
    return _between(centres, _rotation_angles_deg(Rs[a], Rs), _rotation_angles_deg(Rs[b], Rs), pair, slack_deg)


def _draw(rng: np.random.Generator, items: list[Any], limit: int | None) -> list[Any]:
    if limit is None or len(items) <= limit:
        return list(items)
    idx = np.sort(rng.choice(len(items), size=limit, replace=False))
    return [items[int(i)] for i in idx]


def _scene_mode(scene: EvalScene, mode: SplitMode) -> str:
    if mode == "auto":
        return "coverage" if scene.has_depth else "angle"
    if mode == "coverage" and not scene.has_depth:
        missing = next(f for f in scene.frames if f.depth is None)
        raise DatasetError(f"scene {scene.name!r}: splits by coverage need depth, and frame {missing.name!r} has none")
    return mode


def make_cases(
    dataset: EvalDataset,
    config: SplitConfig | None = None,
    *,
    on_coverage: Callable[[str, int, int], None] | None = None,
) -> CaseSelection:
    """Build the test cases of every scene (module docstring).

    Cost, for a scene of N frames: every one of the N(N−1)/2 pairs is considered, and each pair
    that meets a split looks at the N frames for its targets, so O(N³) arithmetic, vectorised over
    the frames (N = 200 by angle: about 2 s on 2 CPU cores, where a loop over the frames took
    2.5 minutes), plus O(N²) memory for the pairwise distances (and rotation angles, by angle);
    by coverage, :func:`~macsplat_cli.datasets.coverage.coverage_matrix` adds N² visibility tests at ``coverage_size``,
    which dominate (about a minute at N = 200). The data set's files were checked when it was
    loaded (:func:`~macsplat_cli.datasets.load_dataset`, from the headers), and the CLI checks the
    frames' sizes before calling this, so bad input fails before this work starts.

    Args:
        dataset: the data set.
        config: settings.
        on_coverage: progress of the coverage computation, ``(scene, done, total)``.

    Returns:
        The cases, ordered by split, scene, then context pair.
    """
    cfg = config or SplitConfig()
    sel = CaseSelection([])
    per_split: dict[str, list[EvalCase]] = {s: [] for s in SPLITS}
    for si, scene in enumerate(dataset.scenes):
        mode = _scene_mode(scene, cfg.mode)
        sel.modes[scene.name] = mode
        cams = [f.camera for f in scene.frames]
        n = len(cams)
        centres, Rs = _centres_and_rotations(cams)
        angles = np.stack([_rotation_angles_deg(R, Rs) for R in Rs]) if mode != "coverage" else None  # [N, N]
        dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)  # [N, N]
        extent = float(dist.max())
        cov = None
        if mode == "coverage":
            cb = (lambda d, t, name=scene.name: on_coverage(name, d, t)) if on_coverage else None
            cov = coverage_matrix(scene, size=cfg.coverage_size, atol=cfg.depth_atol, rtol=cfg.depth_rtol, on_row=cb)
            sel.coverage[scene.name] = cov
        found: dict[str, list[EvalCase]] = {s: [] for s in SPLITS}
        for a in range(n):
            for b in range(a + 1, n):
                if dist[a, b] <= 1e-6 * max(extent, 1e-12):
                    continue  # no baseline: the scale of the scene is undefined
                if cov is not None:
                    overlap = float(cov[a, b])
                    for s in coverage_splits(overlap, cfg.assignment, cfg.splits):
                        psi = COVERAGE_THRESHOLDS[s][1]
                        hit = np.maximum(cov[a], cov[b]) >= psi
                        hit[[a, b]] = False
                        targets = [int(f) for f in np.flatnonzero(hit)]
                        if targets:
                            found[s].append(EvalCase(scene.name, s, (a, b), tuple(targets), "coverage", overlap))
                elif angles is not None:  # the angle mode (angles are measured for every mode but coverage)
                    angle = optical_axis_angle_deg(cams[a], cams[b])
                    splits = angle_splits(angle, cfg.assignment, cfg.splits)
                    targets = _between(centres, angles[a], angles[b], (a, b), cfg.angle_slack_deg) if splits else []
                    for s in splits if targets else []:
                        found[s].append(EvalCase(scene.name, s, (a, b), tuple(targets), "angle", angle))
        sel.candidates[scene.name] = {s: len(found[s]) for s in cfg.splits}
        for k, s in enumerate(SPLITS):
            rng = np.random.default_rng([cfg.seed, si, k])
            for case in _draw(rng, found[s], cfg.max_pairs):
                drawn = tuple(sorted(_draw(rng, list(case.targets), cfg.max_targets)))
                per_split[s].append(EvalCase(case.scene, s, case.context, drawn, case.criterion, case.overlap))
    sel.cases = [c for s in SPLITS for c in per_split[s]]
    logger.info(
        "%d test case(s): %s",
        len(sel.cases),
        ", ".join(f"{s} {len(per_split[s])}" for s in SPLITS if s in cfg.splits),
    )
    return sel


def _check_case(dataset: EvalDataset, case: EvalCase, where: str) -> EvalCase:
    scene = dataset.scene(case.scene)
    n = len(scene.frames)
    idx = (*case.context, *case.targets)
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        raise DatasetError(f"{where}: frame index {bad[0]} out of range for scene {case.scene!r} ({n} frames)")
    if len(case.context) < 2:
        raise DatasetError(f"{where}: case {case.key} has {len(case.context)} context frame; at least two are needed")
    if len(set(case.context)) < len(case.context):
        what = "the two context frames" if len(case.context) == 2 else "the context frames"
        raise DatasetError(f"{where}: {what} of {case.key} repeat a frame")
    if not case.targets:
        raise DatasetError(f"{where}: case {case.key} has no target")
    return case


def load_cases(
    path: str | os.PathLike[str], dataset: EvalDataset, *, every: int = 1, exclude: Sequence[str] = ()
) -> CaseSelection:
    """Read explicit test cases.

    Accepted: ``{"cases": [...]}`` or a list of ``{"scene", "split", "context": [c0, c1],
    "targets": [...]}`` objects (``scene`` may be omitted for a one-scene data set; ``context`` may list more
    than two frames, for ``--context-views``: :mod:`.contexts`), or
    Splatt3R's ``test_set_{φ}_{ψ}.json`` (a list of ``[scene, c0, c1, target]``; the split
    comes from the thresholds in the file name, and rows with the same context pair are
    merged). Indices refer to the scene's frames in loading order (for ScanNet++: the
    filtered train list, as in Splatt3R).

    ``path`` may be a folder: its ``test_set_*.json`` files (else its ``*.json``), in name order, one after the
    other. ``every``: only every ``every``-th row of each file (the MAC-Splat release evaluates every 10th);
    ``exclude``: scenes whose rows are dropped (before they are checked against the data set).

    Raises:
        DatasetError: unreadable file, unknown scene, index out of range.
    """
    p = Path(path)
    if p.is_dir():
        files = sorted(p.glob("test_set_*.json")) or sorted(p.glob("*.json"))
        if not files:
            raise DatasetError(f"{p}: no test_set_*.json or other .json cases file in this folder")
        parts = [load_cases(f, dataset, every=every, exclude=exclude) for f in files]
        return CaseSelection([c for part in parts for c in part.cases], modes=parts[0].modes)
    doc = read_json_file(p, DatasetError, "a JSON cases file")
    rows = doc.get("cases") if isinstance(doc, dict) else doc
    if not isinstance(rows, list) or not rows:
        raise DatasetError(f"{p}: expected a non-empty list of cases")
    rows = rows[:: max(1, every)]
    m = re.search(r"test_set_([0-9.]+)_([0-9.]+)", p.name)
    file_split = "file"
    if m:
        phi = float(m.group(1))
        file_split = next((s for s, (f, _) in COVERAGE_THRESHOLDS.items() if abs(f - phi) < 1e-9), f"phi-{phi:g}")
    default_scene = dataset.scenes[0].name if len(dataset.scenes) == 1 else None
    merged: dict[tuple[str, str, tuple[int, ...]], list[int]] = {}
    for i, row in enumerate(rows):
        where = f"{p}: case {i}"
        key: tuple[str, str, tuple[int, ...]]
        try:
            if isinstance(row, list):
                scene, c0, c1, t = str(row[0]), int(row[1]), int(row[2]), int(row[3])
                key, targets = (scene, file_split, (c0, c1)), [t]
            else:
                scene = str(row.get("scene", default_scene))
                context = tuple(int(x) for x in row["context"])
                key, targets = (scene, str(row.get("split", file_split)), context), [int(t) for t in row["targets"]]
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise DatasetError(
                f"{where}: expected {{scene, split, context: [c0, c1], targets: [...]}} ({e!r})"
            ) from None
        if key[0] == "None":
            raise DatasetError(f"{where}: no scene given, and the data set has {len(dataset.scenes)} scenes")
        if key[0] in exclude:
            continue
        merged.setdefault(key, [])
        merged[key] += [t for t in targets if t not in merged[key]]
    cases = [
        _check_case(dataset, EvalCase(scene, split, context, tuple(t), "file"), str(p))
        for (scene, split, context), t in merged.items()
    ]
    return CaseSelection(cases, modes={s.name: "file" for s in dataset.scenes})
