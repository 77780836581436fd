"""How far to trust a relative pose: checks independent of the RANSAC that produced it, and the acceptance.

The pose stage's own checks ask whether *some* pose explains the matches; the wrong poses that pass them explain
the matches well but are not determined by them — by the focal length (two views whose optical axes nearly meet
hardly constrain it) or by parallax (a rotation without parallax, what a homography's matches give).
:func:`assess_pose` measures, without RANSAC:

* ``refit_rotation_deg``: how far the rotation moves when the pose is re-fitted (:func:`~.refit.refit_pose`) on its
  verified matches at the given intrinsics: a pose that is not the optimum of its own matches moves.
* ``focal_rotation_deg`` (only when a view's focal length comes from the field-of-view prior and nothing but the
  matches can tell it: not when the pose stage measured it on other evidence, ``TwoViewGeometry.focal_evidence``):
  the pose is re-fitted with the focal ``focal_probe`` lower and higher; the rise of the median Sampson distance
  at the better of the two and the rotation's swing between them give the rotation change over the focal change
  the matches cannot reject (a rise of ``focal_tolerance``, growing quadratically, at most ``focal_max_change``);
  a second minimum at ``focal_scan`` counts with its whole swing. The fits use the filtered matches the pose was
  first estimated from (``evidence``), not the guided ones, which agree with the pose they were guided by.
* ``parallax_to_rotation``: the median parallax over the rotation angle, checked above ``parallax_check_above_deg``.
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
from .config import ConfidenceConfig, EvidenceConfig, PoseConfig
from .evidence import PoseEvidence, pose_evidence
from .geometry import fundamental_from_pose, hull_share, sampson_distance
from .refit import refit_pose
from .result import Doubt, PoseConfidence

__all__ = ["acceptance_rule", "accept_pose", "assess_pose", "weigh_evidence"]


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
    g: TwoViewGeometry, evidence: Matches | None, cfg: ConfidenceConfig, xy0: np.ndarray, xy1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The matches of ``evidence`` near the pose (at most ``max_matches``), or ``xy0, xy1`` when too few."""
    if evidence is None or len(evidence) < cfg.min_evidence:
        return xy0, xy1
    e0, e1 = evidence.xy0.astype(np.float64), evidence.xy1.astype(np.float64)
    near = np.abs(sampson_distance(fundamental_from_pose(g.R, g.t, g.K0, g.K1), e0, e1)) < cfg.evidence_band_px
    idx = np.flatnonzero(near)
    if len(idx) < cfg.min_evidence:
        return xy0, xy1
    if len(idx) > cfg.max_matches:
        idx = np.sort(np.random.default_rng(0).choice(idx, cfg.max_matches, replace=False))
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
    geometry: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray, unknown: tuple[bool, bool], cfg: ConfidenceConfig
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

    near = [probe(1.0 - cfg.focal_probe), probe(1.0 + cfg.focal_probe)]
    swing = max(m for _, m in near)
    rise = min(r for r, _ in near)
    scanned = 0.0
    # the swing grows about linearly with the focal change: when even the largest change considered leaves the
    # rotation within the threshold, no second minimum can matter (easy pairs stop here)
    if swing * cfg.focal_max_change / cfg.focal_probe > cfg.max_focal_rotation_deg:
        for k in cfg.focal_scan:
            r_k, m_k = probe(k)
            if r_k <= cfg.focal_tolerance:  # another focal length fits as well: its pose is as plausible
                scanned = max(scanned, m_k)
    # the rise grows ~quadratically with the focal change: the change whose rise is the tolerance
    plausible = min(cfg.focal_probe * math.sqrt(cfg.focal_tolerance / max(rise, cfg.min_rise)), cfg.focal_max_change)
    return max(swing * plausible / cfg.focal_probe, scanned), rise, plausible


def _focal_unknown(v0: View, v1: View, geometry: TwoViewGeometry) -> tuple[bool, bool]:
    """Which views' focal lengths only the matches can determine (the prior's, not measured otherwise)."""
    if geometry.focal_evidence is not None:
        return False, False
    return v0.intrinsics_source == "prior", v1.intrinsics_source == "prior"


def _spread_and_parallax(
    v0: View, v1: View, g: TwoViewGeometry, cfg: ConfidenceConfig, checks: dict, scores: dict, doubts: list[Doubt]
) -> None:
    """The spread and parallax checks (module docstring), into ``checks``, ``scores`` and ``doubts``."""
    inl = g.inliers
    spread = min(hull_share(inl.xy0, v0.width, v0.height), hull_share(inl.xy1, v1.width, v1.height))
    checks["spread"] = spread
    if cfg.min_spread > 0:
        scores["spread"] = _lower(spread, cfg.min_spread)
        if spread < cfg.min_spread:
            doubts.append(Doubt("spread", (
                f"pose confidence low: the {len(inl)} verified matches cover only {100 * spread:.0f} % of a photo "
                f"(need {100 * cfg.min_spread:.0f} %), too small a cluster to pin the pose down"
            )))  # fmt: skip
    rotation = rotation_angle_deg(g.R)
    parallax = g.median_parallax_deg
    if parallax is not None and math.isfinite(parallax) and rotation > 0:
        ratio = float(parallax) / rotation
        checks["parallax_to_rotation"] = ratio
        if rotation > cfg.parallax_check_above_deg:
            scores["parallax"] = _lower(ratio, cfg.min_parallax_to_rotation)
            if ratio < cfg.min_parallax_to_rotation:
                doubts.append(Doubt("parallax", (
                    f"pose confidence low: the pose is mostly rotation ({rotation:.0f}°) with little parallax "
                    f"({float(parallax):.1f}°), what matches on repeated texture or one plane produce"
                )))  # fmt: skip


def assess_pose(
    v0: View, v1: View, geometry: TwoViewGeometry, config: ConfidenceConfig | None = None, *,
    evidence: Matches | None = None,
) -> PoseConfidence:  # fmt: skip
    """How far the relative pose ``geometry`` can be trusted (module docstring).

    Args:
        v0, v1: the two views; a view whose ``intrinsics_source`` is ``"prior"`` has an unknown focal length
            (whether or not the pose stage re-estimated it from the matches: call this with the views as loaded),
            unless the pose stage measured it on other evidence (``geometry.focal_evidence``).
        geometry: the final pose and its verified matches.
        evidence: the filtered matches the pose was first estimated from, before any matching guided by the pose;
            the focal check fits on those within ``evidence_band_px`` of the pose. None: on the verified matches.

    Returns:
        :class:`PoseConfidence`; its doubts are one user-facing line each.
    """
    cfg = config or ConfidenceConfig()
    t0 = time.perf_counter()
    g = geometry
    checks: dict[str, float] = {}
    scores: dict[str, float] = {}
    doubts: list[Doubt] = []
    _spread_and_parallax(v0, v1, g, cfg, checks, scores, doubts)
    inl = g.inliers
    n = len(inl)
    if n >= cfg.min_refit_matches:
        keep = np.arange(n)
        if n > cfg.max_matches:
            keep = np.sort(np.random.default_rng(0).choice(n, cfg.max_matches, replace=False))
        xy0, xy1 = inl.xy0[keep].astype(np.float64), inl.xy1[keep].astype(np.float64)
        moved = rotation_error_deg(refit_pose(g.R, g.t, g.K0, g.K1, xy0, xy1).R, g.R)
        checks["refit_rotation_deg"] = moved
        scores["refit"] = _upper(moved, cfg.max_refit_rotation_deg)
        if moved > cfg.max_refit_rotation_deg:
            doubts.append(Doubt("refit", (
                f"pose confidence low: re-fitted on its own {n} verified matches the rotation moves by {moved:.1f}°"
            )))  # fmt: skip
        unknown = _focal_unknown(v0, v1, g)
        if any(unknown):
            f0, f1 = _fit_set(g, evidence, cfg, xy0, xy1)
            checks["focal_fit_matches"] = len(f0)
            u, rise, plausible = _focal_uncertainty(g, f0, f1, unknown, cfg)
            checks.update(focal_rotation_deg=u, focal_residual_rise=rise, focal_plausible_change=plausible)
            scores["focal"] = _upper(u, cfg.max_focal_rotation_deg)
            if u > cfg.max_focal_rotation_deg:
                doubts.append(Doubt("focal", (
                    f"pose confidence low: the matches do not pin down the focal length (±{100 * plausible:.0f} % "
                    f"fits them about as well), and within that range the rotation changes by up to {u:.0f}°; "
                    "give --focal or --intrinsics"
                )))  # fmt: skip
    score = min(scores.values(), default=1.0)
    checks = {k: float(v) for k, v in checks.items()}
    return PoseConfidence(score=float(score), ok=not doubts, doubts=doubts, checks=checks,
                          seconds=time.perf_counter() - t0)  # fmt: skip


def _evidence_doubts(
    e: PoseEvidence, cfg: EvidenceConfig, scores: dict[str, float], *, from_matches: bool
) -> list[Doubt]:
    """The a contrario test and, for a pose estimated ``from_matches``, the uncertainty (:mod:`.evidence`) as
    doubts, their scores into ``scores``. A pose from a point map (PnP on thousands of points) is not the matches'
    estimate: their uncertainty is reported, not checked."""
    doubts = []
    scores["nfa"] = _lower(max(-e.log10_nfa, 0.0), -cfg.max_log10_nfa) if math.isfinite(e.log10_nfa) else 0.0
    if not e.log10_nfa < cfg.max_log10_nfa:
        doubts.append(Doubt("evidence", (
            f"pose confidence low: the {e.putative} matches found before the pose do not single it out (log10 NFA "
            f"{e.log10_nfa:.1f}, need below {cfg.max_log10_nfa:g}: random matches would agree with some pose as well)"
        )))  # fmt: skip
    three_sigma = 3.0 * e.rotation_sigma_deg
    if not from_matches:
        return doubts
    scores["uncertainty"] = _upper(three_sigma, cfg.max_rotation_3sigma_deg)
    if not three_sigma < cfg.max_rotation_3sigma_deg:
        focal = "; the focal length is free" if e.focal_free else ""
        planar = (
            f"; {100 * e.plane_share:.0f} % of the {e.putative} matches lie on one plane" if e.planar else ""
        )  # fmt: skip
        doubts.append(Doubt("uncertainty", (
            f"pose confidence low: the {e.inliers} matches that support the pose cover {100 * e.coverage:.0f} % of the "
            f"photo and leave its rotation uncertain by ±{three_sigma:.1f}° (3σ{focal}{planar}); a pose needs "
            f"±{cfg.max_rotation_3sigma_deg:g}°"
        )))  # fmt: skip
    return doubts


def _support_doubts(geometry: TwoViewGeometry, pose: PoseConfig) -> list[Doubt]:
    """The pose's support in the matches, as doubts: at least ``pose.min_inliers`` verified matches.

    Not ``pose.min_inlier_ratio``: it was measured on SIFT matches verified within 1 px of their epipolar lines;
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
    v0: View, v1: View, geometry: TwoViewGeometry, pose: PoseConfig, config: ConfidenceConfig | None, *,
    evidence: Matches | None = None,
) -> PoseConfidence:  # fmt: skip
    """The acceptance of a relative pose, for every backend: one place, one set of thresholds.

    Args:
        v0, v1: the two views as loaded (a view with the prior's focal has an unknown focal length).
        geometry: the final pose, its verified matches and its ``doubts`` (the pose stage's own).
        pose: the minimum of support (``min_inliers``).
        config: the checks of :func:`assess_pose`; None skips them (the support is still checked).
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
    if config is not None:
        conf = assess_pose(v0, v1, geometry, config, evidence=evidence)
        score, checks = conf.score, conf.checks
        more: list[Doubt] = []
        if config.evidence is not None:
            found, more, scores = weigh_evidence(v0, v1, geometry, evidence, config.evidence)
            checks.update(found.checks())
            score = min(score, *scores.values())
        # the order a refusal names them in: the a contrario test, the checks (the focal's advice first among its
        # causes), then the uncertainty they may explain
        seen = [d.message for d in doubts]
        doubts += [d for d in more if d.check == "evidence"]
        doubts += [d for d in conf.doubts if d.message not in seen]
        doubts += [d for d in more if d.check != "evidence"]
    else:
        score, checks = 1.0, {}
    if support:
        score = 0.0
    return PoseConfidence(score=float(score), ok=not doubts, doubts=doubts, checks=checks,
                          seconds=time.perf_counter() - t0, evidence=found,
                          rule=acceptance_rule(pose, config))  # fmt: skip


def weigh_evidence(
    v0: View, v1: View, geometry: TwoViewGeometry, putative: Matches | None, config: EvidenceConfig
) -> tuple[PoseEvidence, list[Doubt], dict[str, float]]:
    """The evidence of the ``putative`` matches for ``geometry`` (:func:`~.evidence.pose_evidence`; the verified
    matches when None), its doubts and scores. ``v0, v1``: the views as loaded."""
    found = pose_evidence(
        v0, v1, geometry, putative if putative is not None else geometry.inliers, _focal_unknown(v0, v1, geometry),
        config,
    )  # fmt: skip
    scores: dict[str, float] = {}
    doubts = _evidence_doubts(found, config, scores, from_matches=geometry.source == "matches")
    return found, doubts, scores


def acceptance_rule(pose: PoseConfig, config: ConfidenceConfig | None) -> str:
    """The acceptance rule in words: what a pose must satisfy to be written without a doubt."""
    parts = ["no doubt from the pose stage", f"at least {pose.min_inliers} verified matches"]
    if config is not None:
        e = config.evidence
        if e is not None:
            parts += [
                f"log10 NFA below {e.max_log10_nfa:g} on the tier's putative matches (gathered before the pose)",
                f"rotation 3-sigma below {e.max_rotation_3sigma_deg:g} deg on them (a pose estimated from the matches)",
            ]
        parts += [
            f"a refit on its verified matches moves the rotation less than {config.max_refit_rotation_deg:g} deg",
            f"an unknown focal length leaves less than {config.max_focal_rotation_deg:g} deg of rotation uncertainty",
            f"parallax over rotation at least {config.min_parallax_to_rotation:g} above "
            f"{config.parallax_check_above_deg:g} deg of rotation",
        ]
    return "; ".join(parts)
