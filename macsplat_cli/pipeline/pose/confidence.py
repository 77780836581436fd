"""How far to trust a relative pose: checks independent of the RANSAC that produced it, and the acceptance.

The pose stage's own checks ask whether *some* pose explains the matches; the wrong poses that pass them explain
the matches well but are not determined by them — by the focal length (two views whose optical axes nearly meet
hardly constrain it) or by parallax (a rotation without parallax, what a homography's matches give).
:func:`assess_pose` measures, without RANSAC:

* ``refit_rotation_deg``: how far the rotation moves when the pose is re-fitted (:func:`~.refit.refit_pose`) on its
  verified matches at the given intrinsics: a pose that is not the optimum of its own matches moves.
* ``focal_rotation_deg`` (only when a view's focal length comes from the field-of-view prior and nothing but the
  matches can tell it: not when the pose stage measured it on other evidence, ``TwoViewGeometry.focal_evidence``):
  the pose is re-fitted with the focal ``FOCAL_PROBE`` lower and higher; the rise of the median Sampson distance
  at the better of the two and the rotation's swing between them give the rotation change over the focal change
  the matches cannot reject (a rise of ``FOCAL_TOLERANCE``, growing quadratically, at most ``FOCAL_MAX_CHANGE``);
  a second minimum at ``FOCAL_SCAN`` counts with its whole swing. The fits use the filtered matches the pose was
  first estimated from (``evidence``), not the guided ones, which agree with the pose they were guided by.
* ``parallax_to_rotation``: the median parallax over the rotation angle, checked above ``PARALLAX_CHECK_ABOVE_DEG``.
* ``spread``: the share of each photo that the verified matches' convex hull covers (the smaller), reported.

Each check gives a score in [0, 1] that is 0.5 at its threshold (``x² / (x² + thr²)`` for a lower bound, the
converse for an upper one); the confidence is the smallest. :func:`accept_pose` is the acceptance of a pose from any
backend: the pose stage's doubts, the support minimum (``PoseConfig.min_inliers`` verified matches), then
:func:`assess_pose`, then the evidence of the putative matches gathered before the pose (:func:`weigh_evidence`,
:mod:`.evidence`: the a contrario test for every pose, the rotation's uncertainty for a pose estimated from the
matches). Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ...metrics import rotation_angle_deg, rotation_error_deg
from ..types import Matches, TwoViewGeometry, View
from .config import PoseConfig
from .evidence import PoseEvidence, pose_evidence
from .geometry import fundamental_from_pose, hull_share, sampson_distance
from .refit import refit_pose
from .result import Doubt, PoseConfidence

__all__ = ["acceptance_rule", "accept_pose", "assess_pose", "weigh_evidence"]

MAX_REFIT_ROTATION_DEG = 1.0
"""Largest rotation change (°) when the pose is re-fitted on its verified matches."""
FOCAL_PROBE = 0.10
"""Relative focal-length change at which the pose is re-fitted (both directions)."""
FOCAL_SCAN = (0.8, 1.25)
"""Further focal factors at which the pose is re-fitted: a second minimum of the fit there (a rise within
:data:`FOCAL_TOLERANCE`) counts with its rotation swing."""
FOCAL_TOLERANCE = 0.10
"""Relative rise of the median Sampson distance that the matches are taken to reject."""
FOCAL_MAX_CHANGE = 0.5
"""The largest focal change considered (ordinary cameras, 40–90° across the long side, lie within ±50 % of the 60°
prior)."""
MAX_FOCAL_ROTATION_DEG = 4.0
"""Largest rotation uncertainty (°) left by an unknown focal length."""
MIN_PARALLAX_TO_ROTATION = 0.15
"""Smallest median parallax / rotation angle of a pose rotating more than :data:`PARALLAX_CHECK_ABOVE_DEG` (a pan
of more than 30° with as little parallax is what a homography's matches give)."""
PARALLAX_CHECK_ABOVE_DEG = 30.0
"""The parallax check applies above this rotation (°): a handheld pan at small angles has as little parallax and
is right."""
MAX_MATCHES = 1000
"""The fits use at most this many verified matches (a fixed-seed random sample)."""
EVIDENCE_BAND_PX = 2.0
"""The matches of ``evidence`` within this Sampson distance (px) of the pose are the focal check's fit set."""
MIN_EVIDENCE = 200
"""Fewer such matches than this and the verified matches are the fit set instead (the median of fewer residuals
is too noisy to see a 10 % rise)."""
MIN_REFIT_MATCHES = 8
"""The re-fit checks need at least this many verified matches (a fundamental matrix's eight)."""
MIN_RISE = 1e-3
"""The residual rise is floored at this before the plausible focal change is extrapolated from it (no rise at all
would claim any focal length fits)."""
MAX_LOG10_NFA = -3.0
"""A pose is meaningful when its log10 NFA is below this: at most one false alarm in 1000 pairs of random matches
(a stated rate, not a tuned threshold)."""
MAX_ROTATION_3SIGMA_DEG = 2.0
"""The largest three-sigma rotation uncertainty (°) of an accepted pose estimated from the matches: 5° let three
poses 13–26° off through on the pose protocol's tuning split where 2° let the search go on to a tier that found
the right one."""


def _upper(x: float, thr: float) -> float:
    """Score of a measurement that must stay below ``thr``: 1 at 0, 0.5 at ``thr``, → 0 above."""
    if not math.isfinite(x):
        return 0.0
    return thr * thr / (thr * thr + x * x) if thr > 0 else float(x <= 0)


def _lower(x: float, thr: float) -> float:
    """Score of a measurement that must stay above ``thr``: 0 at 0, 0.5 at ``thr``, → 1 above."""
    if not math.isfinite(x):
        return 0.0
    return x * x / (x * x + thr * thr) if thr > 0 else 1.0


def _fit_set(
    g: TwoViewGeometry, evidence: Matches | None, xy0: np.ndarray, xy1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The matches of ``evidence`` near the pose (at most :data:`MAX_MATCHES`), or ``xy0, xy1`` when too few."""
    if evidence is None or len(evidence) < MIN_EVIDENCE:
        return xy0, xy1
    e0, e1 = evidence.xy0.astype(np.float64), evidence.xy1.astype(np.float64)
    near = np.abs(sampson_distance(fundamental_from_pose(g.R, g.t, g.K0, g.K1), e0, e1)) < EVIDENCE_BAND_PX
    idx = np.flatnonzero(near)
    if len(idx) < MIN_EVIDENCE:
        return xy0, xy1
    if len(idx) > MAX_MATCHES:
        idx = np.sort(np.random.default_rng(0).choice(idx, MAX_MATCHES, replace=False))
    return e0[idx], e1[idx]


def _focal_times(K: np.ndarray, k: float, unknown: bool) -> np.ndarray:
    """``K`` with its focal lengths (and skew) times ``k`` when the focal is ``unknown`` (a probe of the focal,
    multiplicative: not ``camera_math.scale_focal``'s log scale, which would round ``k`` through ``exp(log k)``)."""
    if not unknown:
        return K
    out = K.copy()
    out[0, :2] *= k
    out[1, 1] *= k
    return out


def _focal_uncertainty(
    geometry: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray, unknown: tuple[bool, bool]
) -> tuple[float, float, float]:
    """``(rotation uncertainty °, residual rise at the probe, focal change the matches cannot reject)`` of the
    pose re-fitted on the matches ``xy0, xy1`` [M, 2]."""
    g = geometry
    base = refit_pose(g.R, g.t, g.K0, g.K1, xy0, xy1)
    r0 = max(float(np.median(np.abs(base.residuals))), 1e-9)

    def probe(k: float) -> tuple[float, float]:  # (rise, rotation swing) of the pose re-fitted at focal × k
        K0k, K1k = _focal_times(g.K0, k, unknown[0]), _focal_times(g.K1, k, unknown[1])
        fit = refit_pose(base.R, base.t, K0k, K1k, xy0, xy1)
        return float(np.median(np.abs(fit.residuals))) / r0 - 1.0, rotation_error_deg(fit.R, base.R)

    near = [probe(1.0 - FOCAL_PROBE), probe(1.0 + FOCAL_PROBE)]
    swing = max(m for _, m in near)
    rise = min(r for r, _ in near)
    scanned = 0.0
    # the swing grows about linearly with the focal change: when even the largest change considered leaves the
    # rotation within the threshold, no second minimum can matter (easy pairs stop here)
    if swing * FOCAL_MAX_CHANGE / FOCAL_PROBE > MAX_FOCAL_ROTATION_DEG:
        for k in FOCAL_SCAN:
            r_k, m_k = probe(k)
            if r_k <= FOCAL_TOLERANCE:  # another focal length fits as well: its pose is as plausible
                scanned = max(scanned, m_k)
    # the rise grows ~quadratically with the focal change: the change whose rise is the tolerance
    plausible = min(FOCAL_PROBE * math.sqrt(FOCAL_TOLERANCE / max(rise, MIN_RISE)), FOCAL_MAX_CHANGE)
    return max(swing * plausible / FOCAL_PROBE, scanned), rise, plausible


def _focal_unknown(v0: View, v1: View, geometry: TwoViewGeometry) -> tuple[bool, bool]:
    """Which views' focal lengths only the matches can determine (the prior's, not measured otherwise)."""
    if geometry.focal_evidence is not None:
        return False, False
    return v0.intrinsics_source == "prior", v1.intrinsics_source == "prior"


def _spread_and_parallax(
    v0: View, v1: View, g: TwoViewGeometry, checks: dict, scores: dict, doubts: list[Doubt]
) -> None:
    """The spread (reported) and the parallax check (module docstring), into ``checks``, ``scores`` and ``doubts``."""
    inl = g.inliers
    spread = min(hull_share(inl.xy0, v0.width, v0.height), hull_share(inl.xy1, v1.width, v1.height))
    checks["spread"] = spread  # reported, not checked
    rotation = rotation_angle_deg(g.R)
    parallax = g.median_parallax_deg
    if parallax is not None and math.isfinite(parallax) and rotation > 0:
        ratio = float(parallax) / rotation
        checks["parallax_to_rotation"] = ratio
        if rotation > PARALLAX_CHECK_ABOVE_DEG:
            scores["parallax"] = _lower(ratio, MIN_PARALLAX_TO_ROTATION)
            if ratio < MIN_PARALLAX_TO_ROTATION:
                doubts.append(Doubt("parallax", (
                    f"pose confidence low: the pose is mostly rotation ({rotation:.0f}°) with little parallax "
                    f"({float(parallax):.1f}°), what matches on repeated texture or one plane produce"
                )))  # fmt: skip


def assess_pose(v0: View, v1: View, geometry: TwoViewGeometry, *, evidence: Matches | None = None) -> PoseConfidence:
    """How far the relative pose ``geometry`` can be trusted (module docstring).

    Args:
        v0, v1: the two views; a view whose ``intrinsics_source`` is ``"prior"`` has an unknown focal length
            (whether or not the pose stage re-estimated it from the matches: call this with the views as loaded),
            unless the pose stage measured it on other evidence (``geometry.focal_evidence``).
        geometry: the final pose and its verified matches.
        evidence: the filtered matches the pose was first estimated from, before any matching guided by the pose;
            the focal check fits on those within :data:`EVIDENCE_BAND_PX` of the pose. None: on the verified matches.

    Returns:
        :class:`PoseConfidence`; its doubts are one user-facing line each.
    """
    t0 = time.perf_counter()
    g = geometry
    checks: dict[str, float] = {}
    scores: dict[str, float] = {}
    doubts: list[Doubt] = []
    _spread_and_parallax(v0, v1, g, checks, scores, doubts)
    inl = g.inliers
    n = len(inl)
    if n >= MIN_REFIT_MATCHES:
        keep = np.arange(n)
        if n > MAX_MATCHES:
            keep = np.sort(np.random.default_rng(0).choice(n, MAX_MATCHES, replace=False))
        xy0, xy1 = inl.xy0[keep].astype(np.float64), inl.xy1[keep].astype(np.float64)
        moved = rotation_error_deg(refit_pose(g.R, g.t, g.K0, g.K1, xy0, xy1).R, g.R)
        checks["refit_rotation_deg"] = moved
        scores["refit"] = _upper(moved, MAX_REFIT_ROTATION_DEG)
        if moved > MAX_REFIT_ROTATION_DEG:
            doubts.append(Doubt("refit", (
                f"pose confidence low: re-fitted on its own {n} verified matches the rotation moves by {moved:.1f}°"
            )))  # fmt: skip
        unknown = _focal_unknown(v0, v1, g)
        if any(unknown):
            f0, f1 = _fit_set(g, evidence, xy0, xy1)
            checks["focal_fit_matches"] = len(f0)
            u, rise, plausible = _focal_uncertainty(g, f0, f1, unknown)
            checks.update(focal_rotation_deg=u, focal_residual_rise=rise, focal_plausible_change=plausible)
            scores["focal"] = _upper(u, MAX_FOCAL_ROTATION_DEG)
            if u > MAX_FOCAL_ROTATION_DEG:
                doubts.append(Doubt("focal", (
                    f"pose confidence low: the matches do not pin down the focal length (±{100 * plausible:.0f} % "
                    f"fits them about as well), and within that range the rotation changes by up to {u:.0f}°; "
                    "give --focal or --intrinsics"
                )))  # fmt: skip
    score = min(scores.values(), default=1.0)
    checks = {k: float(v) for k, v in checks.items()}
    return PoseConfidence(score=float(score), ok=not doubts, doubts=doubts, checks=checks,
                          seconds=time.perf_counter() - t0)  # fmt: skip


def _evidence_doubts(e: PoseEvidence, scores: dict[str, float], *, from_matches: bool) -> list[Doubt]:
    """The a contrario test and, for a pose estimated ``from_matches``, the uncertainty (:mod:`.evidence`) as
    doubts, their scores into ``scores``. A pose from a point map (PnP on thousands of points) is not the matches'
    estimate: their uncertainty is reported, not checked."""
    doubts = []
    scores["nfa"] = _lower(max(-e.log10_nfa, 0.0), -MAX_LOG10_NFA) if math.isfinite(e.log10_nfa) else 0.0
    if not e.log10_nfa < MAX_LOG10_NFA:
        doubts.append(Doubt("evidence", (
            f"pose confidence low: the {e.putative} matches found before the pose do not single it out (log10 NFA "
            f"{e.log10_nfa:.1f}, need below {MAX_LOG10_NFA:g}: random matches would agree with some pose as well)"
        )))  # fmt: skip
    three_sigma = 3.0 * e.rotation_sigma_deg
    if not from_matches:
        return doubts
    scores["uncertainty"] = _upper(three_sigma, MAX_ROTATION_3SIGMA_DEG)
    if not three_sigma < MAX_ROTATION_3SIGMA_DEG:
        focal = "; the focal length is free" if e.focal_free else ""
        planar = (
            f"; {100 * e.plane_share:.0f} % of the {e.putative} matches lie on one plane" if e.planar else ""
        )  # fmt: skip
        doubts.append(Doubt("uncertainty", (
            f"pose confidence low: the {e.inliers} matches that support the pose cover {100 * e.coverage:.0f} % of the "
            f"photo and leave its rotation uncertain by ±{three_sigma:.1f}° (3σ{focal}{planar}); a pose needs "
            f"±{MAX_ROTATION_3SIGMA_DEG:g}°"
        )))  # fmt: skip
    return doubts


def _support_doubts(geometry: TwoViewGeometry, pose: PoseConfig) -> list[Doubt]:
    """The pose's support in the matches, as doubts: at least ``pose.min_inliers`` verified matches.

    Not :data:`~.checks.MIN_INLIER_RATIO`: it was measured on SIFT matches verified within 1 px of their epipolar lines;
    the neural backend's grid-sampled matches verified against the point maps agree at lower ratios.
    """
    n = len(geometry.inliers)
    if n >= pose.min_inliers:
        return []
    return [Doubt("support", (
        f"pose confidence low: only {n} verified match{'es' if n != 1 else ''} agree{'s' if n == 1 else ''} with the "
        f"pose, need at least {pose.min_inliers}"
    ))]  # fmt: skip


def accept_pose(
    v0: View, v1: View, geometry: TwoViewGeometry, pose: PoseConfig, checks: bool, *,
    evidence: Matches | None = None,
) -> PoseConfidence:  # fmt: skip
    """The acceptance of a relative pose, for every backend: one place, one set of thresholds.

    Args:
        v0, v1: the two views as loaded (a view with the prior's focal has an unknown focal length).
        geometry: the final pose, its verified matches and its ``doubts`` (the pose stage's own).
        pose: the minimum of support (``min_inliers``).
        checks: run :func:`assess_pose` and :func:`weigh_evidence`; False skips them (the support is still
            checked).
        evidence: as for :func:`assess_pose`.

    Returns:
        :class:`PoseConfidence`: ``doubts`` are the pose stage's, then the failed support minimum, the a contrario
        test's, :func:`assess_pose`'s (not repeating a message), and the uncertainty's; ``score`` is the smallest
        check score (1 without checks), 0 when the support minimum fails; ``checks`` are :func:`assess_pose`'s and
        :func:`weigh_evidence`'s measurements; ``evidence`` and ``rule`` what was weighed and how.
    """
    t0 = time.perf_counter()
    found = None
    doubts = [Doubt("pose", str(d)) for d in geometry.doubts]
    support = _support_doubts(geometry, pose)
    doubts += support
    measured: dict[str, float] = {}
    if checks:
        conf = assess_pose(v0, v1, geometry, evidence=evidence)
        score, measured = conf.score, conf.checks
        found, more, scores = weigh_evidence(v0, v1, geometry, evidence)
        measured.update(found.checks())
        score = min(score, *scores.values())
        # the order a refusal names them in: the a contrario test, the checks (the focal's advice first among its
        # causes), then the uncertainty they may explain
        seen = [d.message for d in doubts]
        doubts += [d for d in more if d.check == "evidence"]
        doubts += [d for d in conf.doubts if d.message not in seen]
        doubts += [d for d in more if d.check != "evidence"]
    else:
        score = 1.0
    if support:
        score = 0.0
    return PoseConfidence(score=float(score), ok=not doubts, doubts=doubts, checks=measured,
                          seconds=time.perf_counter() - t0, evidence=found,
                          rule=acceptance_rule(pose, checks))  # fmt: skip


def weigh_evidence(
    v0: View, v1: View, geometry: TwoViewGeometry, putative: Matches | None
) -> tuple[PoseEvidence, list[Doubt], dict[str, float]]:
    """The evidence of the ``putative`` matches for ``geometry`` (:func:`~.evidence.pose_evidence`; the verified
    matches when None), its doubts and scores. ``v0, v1``: the views as loaded."""
    found = pose_evidence(
        v0, v1, geometry, putative if putative is not None else geometry.inliers, _focal_unknown(v0, v1, geometry)
    )
    scores: dict[str, float] = {}
    doubts = _evidence_doubts(found, scores, from_matches=geometry.source == "matches")
    return found, doubts, scores


def acceptance_rule(pose: PoseConfig, checks: bool) -> str:
    """The acceptance rule in words: what a pose must satisfy to be written without a doubt."""
    parts = ["no doubt from the pose stage", f"at least {pose.min_inliers} verified matches"]
    if checks:
        parts += [
            f"log10 NFA below {MAX_LOG10_NFA:g} on the tier's putative matches (gathered before the pose)",
            f"rotation 3-sigma below {MAX_ROTATION_3SIGMA_DEG:g} deg on them (a pose estimated from the matches)",
            f"a refit on its verified matches moves the rotation less than {MAX_REFIT_ROTATION_DEG:g} deg",
            f"an unknown focal length leaves less than {MAX_FOCAL_ROTATION_DEG:g} deg of rotation uncertainty",
            f"parallax over rotation at least {MIN_PARALLAX_TO_ROTATION:g} above "
            f"{PARALLAX_CHECK_ABOVE_DEG:g} deg of rotation",
        ]
    return "; ".join(parts)
