"""The learned tier's own doubts (:func:`learned_doubts`): a learned pose is refused when the matches that verify it
lie mostly on a texture that repeats within the photo, or when its a contrario test passes SIFT's bar but not the
learned tier's stricter one.

LightGlue matches a texture repeated exactly (tiles, wallpaper, a facade's windows) consistently, and can match it
at the wrong repetition: every match then agrees with one wrong pose, and the acceptance's evidence (the a contrario
test, the coverage, the uncertainty) cannot tell it from a right one (the tuning split's object at 75°: 90.8° off, 369
inliers, log10 NFA −846, accepted; the held-out tabletop at 105° of the last round: 179.5° off). What sets those
matches apart is the photo itself: a keypoint on a repeated texture has a **twin**, another keypoint of the same
photo, away from it, with nearly the same ALIKED descriptor (the descriptor describes the patch alone, before
LightGlue's context). The guard counts the verified matches whose keypoint has a twin, in each photo, and refuses the
pose when that share exceeds :data:`MAX_TWIN_SHARE` in either photo, for the tier's verified matches and for the
final pose's (guided re-matching under a wrong pose gathers repeated tiles: 11 % before, 63 % after, on the tuning
object at 90°). It costs a matrix product per photo (2048 × 2048).

Smaller supports fail differently: LightGlue matches a region as a whole, so its wrong matches agree with one
another more often than the a contrario test's background (independent, uniform matches) assumes, and a wrong
learned pose passed SIFT's bar at log10 NFA −24 and −33 on the tuning split. A learned pose needs
:data:`MAX_LOG10_NFA`.

Chosen on the pose protocol's tuning split and the development pairs (benchmarks/history/learned.md).
"""

from __future__ import annotations

import numpy as np

from ..types import Features, Matches

__all__ = ["MAX_LOG10_NFA", "MAX_TWIN_SHARE", "TWIN_DISTANCE", "TWIN_MIN_PX", "learned_doubts", "twin_share"]

TWIN_DISTANCE = 0.5
"""Two unit ALIKED descriptors this close (Euclidean) describe the same texture: of a right learned pose's verified
keypoints on the development photos 0–2 % have such a twin (ICL's ray-traced room 10–22 %); of the wrong poses' on the
tuning split's repeated tiles 47–92 %."""
TWIN_MIN_PX = 12.0
"""A twin is at least this far from the keypoint (working pixels): nearer keypoints see the same structure."""
MAX_TWIN_SHARE = 0.35
"""The share of a photo's verified keypoints with a twin above which the learned pose is refused (tuning split: the
wrong learned poses on repeated tiles 0.47–0.92; the right learned poses of the development pairs ≤ 0.22)."""
MAX_LOG10_NFA = -50.0
"""The a contrario test's bar for a learned pose (SIFT's: ``EvidenceConfig.max_log10_nfa``): LightGlue's wrong matches
are not independent (its attention matches a region as a whole), so chance agreement is likelier than the
background model says (tuning split: wrong learned poses accepted at −33 and −24; the right learned poses of the
development pairs at −68 and below)."""
_ROWS = 256
"""Keypoints compared at once (bounds the distance matrices' memory: 256 × 2048)."""


def twin_share(features: Features, idx: np.ndarray) -> float:
    """The share of the keypoints ``idx`` of one photo that have a twin (module docstring).

    Args:
        features: the photo's keypoints (``xy`` [N, 2], working pixels) and unit descriptors (``desc`` [N, D]).
        idx: the keypoints to count. [M] int
    Returns:
        The share in [0, 1] (0 for no keypoints).
    """
    if len(idx) == 0:
        return 0.0
    desc = np.asarray(features.desc, np.float32)
    xy = np.asarray(features.xy, np.float64)
    min_cos = 1.0 - TWIN_DISTANCE**2 / 2  # |a − b|² = 2 − 2 a·b for unit vectors
    twins = 0
    for start in range(0, len(idx), _ROWS):
        rows = np.asarray(idx[start : start + _ROWS])
        cos = desc[rows] @ desc.T  # [m, N]
        near = ((xy[rows, None, :] - xy[None, :, :]) ** 2).sum(-1) < TWIN_MIN_PX**2
        cos[near] = -np.inf
        twins += int((cos.max(axis=1) >= min_cos).sum())
    return twins / len(idx)


def learned_doubts(features: list[Features], verified: Matches, final: Matches, log10_nfa: float | None) -> list[str]:
    """Why a learned pose is refused, in order (none: it stands as far as the learned tier goes; the acceptance's own
    checks still judge it).

    Args:
        features: the two photos' learned features, which ``verified`` and ``final`` index.
        verified: the matches that verified the tier's pose (before guided re-matching).
        final: the final pose's verified matches (the guided ones when they replaced the pose; else ``verified``).
        log10_nfa: the a contrario test's log10 NFA on the tier's putative matches; None when not measured.
    """
    out = []
    if log10_nfa is not None and log10_nfa > MAX_LOG10_NFA:
        out.append(f"pose is unreliable: its learned matches give log10 NFA {log10_nfa:.0f}, a learned pose needs "
                   f"{MAX_LOG10_NFA:.0f} or less (LightGlue's wrong matches agree with one another)")  # fmt: skip
    share = max(twin_share(features[k], m.idx0 if k == 0 else m.idx1) for m in (verified, final) for k in (0, 1))
    if share > MAX_TWIN_SHARE:
        out.append(f"pose is unreliable: {share:.0%} of the learned matches that verify it lie on a texture repeated "
                   f"elsewhere in the photo (at most {MAX_TWIN_SHARE:.0%}): they may pair one repetition with "
                   "another")  # fmt: skip
    return out
