"""More than two context views per case (``--context-views N``): each drawn pair extended by N − 2 frames.

A case is drawn as with two context views (:func:`.splits.make_cases`, or read by :func:`.splits.load_cases`): a
pair of context frames and its targets. :func:`extend_cases` then adds N − 2 frames to every pair by one rule, from
the cameras alone, so the same in coverage and in view-angle splits:

1. **Candidates**: the scene's frames that are neither a context nor a target of the case (the targets stay held
   out), with a baseline to every context already chosen (centres further apart than 1e-6 of the scene's extent,
   the rule that keeps a pair with no baseline out of the splits).
2. **Between first**: the candidates between the pair (:func:`.splits.between_targets`' test: the centre over
   5–95 % of the segment joining the pair's centres, within half its length of it, the view facing like the
   pair), by farthest-point sampling on the camera centres: the next frame is the candidate farthest from its
   nearest chosen context (ties: the lower frame index). The contexts spread evenly along the path between the
   pair, the longest gap split first, which is where the targets of a between split lie.
3. **Around next**, when fewer than N − 2 lie between: the remaining candidates nearest to the pair's segment
   (distance of the centre to the segment; ties: the lower index), extending the path beyond either end.

The contexts go to the reconstruction in **path order** (by the position of the centre along the pair's segment,
ties by frame index), the order a sequence's photos have; :attr:`.splits.EvalCase.pair` keeps the drawn pair. A case
with too few candidates is left out and named. Nothing is drawn: with N context views a run evaluates the same
pairs and targets as with two, so runs that differ in N compare the same targets.

Cost: O(F · N) per case for a scene of F frames (the distances of the candidates to the chosen contexts).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from .._limits import MAX_PHOTOS
from ..cameras import Camera
from ..datasets import EvalDataset
from ..errors import DatasetError, InputError
from .splits import EvalCase, _between, _centres_and_rotations, _rotation_angles_deg

__all__ = ["DEFAULT_CONTEXT_VIEWS", "check_context_views", "extend_case", "extend_cases"]

logger = logging.getLogger(__name__)

DEFAULT_CONTEXT_VIEWS = 2
"""Context views per case by default: the pair itself (the two-view protocol)."""
BASELINE_RTOL = 1e-6
"""A candidate closer than this fraction of the scene's extent to a chosen context adds no baseline to it."""


def check_context_views(n: int, *, backends: Sequence[str] = ("classical",)) -> None:
    """Refuse a context-view count the reconstruction cannot take, before any work.

    Raises:
        InputError: ``n`` outside 2 … :data:`~macsplat_cli._limits.MAX_PHOTOS`; more than two with the neural backend
            (the engine reconstructs more than two photos with the classical backend only).
    """
    if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= MAX_PHOTOS:
        raise InputError(f"--context-views {n}: give 2 to {MAX_PHOTOS} (the photos one reconstruction takes)")
    if n == 2:
        return
    if "neural" in backends:
        raise InputError(f"--context-views {n}: the neural backend reconstructs two photos; use --backend classical")


def _segment_position(centres: np.ndarray, pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Every centre's position along the pair's segment (0 at the first, 1 at the second) and its distance to the
    segment. ``centres`` [F, 3] → [F], [F]."""
    a, b = pair
    chord = centres[b] - centres[a]
    length2 = float(chord @ chord)
    d = centres - centres[a]
    u = (d @ chord) / length2 if length2 > 0 else np.zeros(len(centres))
    foot = np.clip(u, 0.0, 1.0)[:, None] * chord
    return u, np.linalg.norm(d - foot, axis=-1)


def _spread(centres: np.ndarray, chosen: list[int], candidates: list[int], k: int, tol: float) -> list[int]:
    """Up to ``k`` of ``candidates`` (ascending indices) by farthest-point sampling from ``chosen``."""
    if not candidates or k <= 0:
        return []
    cand = np.asarray(candidates)
    nearest = np.min(np.linalg.norm(centres[cand][:, None] - centres[chosen][None], axis=-1), axis=1)  # [C]
    picked: list[int] = []
    while len(picked) < k:
        i = int(np.argmax(nearest))  # the first maximum: the lower frame index on ties
        if nearest[i] <= tol:
            break
        picked.append(int(cand[i]))
        nearest = np.minimum(nearest, np.linalg.norm(centres[cand] - centres[cand[i]], axis=-1))
    return picked


def extend_case(cameras: Sequence[Camera], case: EvalCase, n: int, slack_deg: float = 15.0) -> EvalCase | None:
    """The case with ``n`` context frames (module docstring); None when the scene has too few candidates.

    Args:
        cameras: the scene's cameras, in frame order.
        case: a case whose context is its pair (or already ``n`` frames: returned as it is).
        n: the context frames wanted (≥ 2).
        slack_deg: the orientation slack of the between test (:class:`.splits.SplitConfig`'s ``angle_slack_deg``).

    Raises:
        DatasetError: a case with more than two context frames, but not ``n``.
    """
    if len(case.context) == n:
        return case
    if len(case.context) != 2:
        k = len(case.context)
        hint = f"pass --context-views {k}" if n == 2 else f"give cases of two context frames (extended to {n}) or {n}"
        raise DatasetError(f"case {case.key} has {k} context frames and --context-views is {n}: {hint}")
    pair = (case.context[0], case.context[1])
    centres, Rs = _centres_and_rotations(cameras)
    tol = BASELINE_RTOL * max(float(np.linalg.norm(centres.max(0) - centres.min(0))), 1e-12)
    held = set(pair) | set(case.targets)
    ang_a, ang_b = _rotation_angles_deg(Rs[pair[0]], Rs), _rotation_angles_deg(Rs[pair[1]], Rs)
    between = [f for f in _between(centres, ang_a, ang_b, pair, slack_deg) if f not in held]
    chosen = [*pair, *_spread(centres, list(pair), between, n - 2, tol)]
    u, off = _segment_position(centres, pair)
    if len(chosen) < n:
        taken = set(chosen) | held
        around = sorted((float(off[f]), f) for f in range(len(cameras)) if f not in taken)
        for _, f in around:
            if len(chosen) == n:
                break
            if np.min(np.linalg.norm(centres[chosen] - centres[f], axis=-1)) > tol:
                chosen.append(f)
    if len(chosen) < n:
        return None
    order = sorted(chosen, key=lambda f: (float(u[f]), f))
    return dataclasses.replace(case, context=tuple(order), pair=pair)


def extend_cases(
    dataset: EvalDataset, cases: Sequence[EvalCase], n: int, slack_deg: float = 15.0
) -> tuple[list[EvalCase], list[EvalCase]]:
    """Every case with ``n`` context frames (:func:`extend_case`).

    Returns:
        ``(cases, left_out)``: the extended cases in their order, and the cases whose scene has too few frames
        to extend them (logged).

    Raises:
        DatasetError: a case with more than two context frames, but not ``n``.
    """
    cams = {s.name: [f.camera for f in s.frames] for s in dataset.scenes}
    kept: list[EvalCase] = []
    left: list[EvalCase] = []
    for case in cases:
        ext = extend_case(cams[case.scene], case, n, slack_deg)
        (kept if ext is not None else left).append(ext if ext is not None else case)
    for case in left:
        logger.info("%s: left out, too few frames besides its targets for %d context views", case.key, n)
    return kept, left
