"""How far to trust a relative pose: checks independent of the RANSAC that produced it (issue 14).

The pose stage's own checks (inlier ratio, homography excess, planar ambiguity, mirror images) ask whether
*some* pose explains the matches. The wrong poses that pass them explain the matches well but are not determined
by them. Measured on ray-traced wide pairs and CO3D (``benchmarks/pose_confidence.py``), they come in two kinds:

* **The focal length's.** With no intrinsics given, two views whose optical axes (nearly) meet — every
  object-centric pair — hardly constrain the focal length (Bougnoux's degeneracy), and at 45–90° a focal length
  10 % off turns the rotation by 4–6°. The estimate lands 10–30 % off and the rotation 5–50° off, while the
  estimate's data-only standard deviation claims 1 %.
* **A rotation without parallax.** Few matches on repetitive texture (CO3D at 40°, after the affine-simulated
  fallback and the guided re-matching) that a homography nearly explains yield a pose that is mostly rotation
  (53–65°) with a median parallax of 5–7°, 39–52° off; correct poses had a parallax of 0.19–1.0 times their
  rotation (0.4 in the synthetic room, 0.8–1.0 on CO3D), the wrong ones 0.08–0.10. A handheld pan can look the
  same at small angles (NYU dining (1, 3): 20° of rotation, 1.6° of parallax, ratio 0.08, right within 0.5°), so
  the check applies above 30° of rotation only.

:func:`assess_pose` measures, without RANSAC:

* ``refit_rotation_deg``: how far the rotation moves when the pose is re-fitted (Gauss–Newton on the Sampson
  distances, Cauchy weights) at the given intrinsics: a pose that is not the optimum of its own matches (a
  perturbed or foreign estimate) moves.
* ``focal_rotation_deg`` (only when a view's intrinsics come from the field-of-view prior and nothing but the
  matches can tell its focal length: not when the pose stage measured it on other evidence, as the neural backend
  does on the network's point map, ``info["focal_evidence"] = "pointmap"``): the pose is re-fitted
  with the focal length fixed ``focal_probe`` (10 %) lower and higher; ``focal_residual_rise`` is how much the
  median Sampson distance grows at the better of the two, and the rotation's swing between them is extrapolated
  to the focal change the matches cannot reject (a rise of ``focal_tolerance``, 10 %, assuming the rise grows
  quadratically, at most ``focal_max_change``). The pose is also re-fitted at ``focal_scan`` (×0.8, ×1.25): a
  second minimum there (a rise within the tolerance) counts with its whole swing. That is the rotation
  uncertainty an unknown focal length leaves. The fits use the filtered matches the pose was first estimated
  from (``evidence``, when at least ``min_evidence`` lie near the pose), not the guided ones: guided matching
  keeps what agrees with the pose it is guided by, and on a 45° room pair a pose 7.8° off with its focal 19 %
  off explained its 738 guided matches far better than the true pose (median error ×4), while the 414 filtered
  matches fit both equally (0.075 / 0.063 px). The
  median distance, not a χ² test: at wide baselines the residuals are systematic (SIFT localisation under
  perspective distortion), so a statistically "significant" 5 % rise over 600 matches rejects nothing.
* ``parallax_to_rotation``: the median parallax of the verified matches over the rotation angle, checked when
  the rotation exceeds ``parallax_check_above_deg``.
* ``spread``: the share of each photo that the verified matches' convex hull covers (the smaller), reported.

:func:`accept_pose` is the acceptance of a relative pose, whichever backend estimated it (the classical essential
matrix, the neural backend's PnP on the network's point maps): the pose stage's own doubts, the support the pose has
in the matches (``PoseConfig.min_inliers`` verified matches: the classical pose stage returns no pose without them, a
pose from elsewhere is held to the same figure here), then :func:`assess_pose`. The pipeline calls it once for every
backend; a replacement of the acceptance (issue 23: an a-contrario test) replaces this function.

Each check gives a score in [0, 1] that is 0.5 at its threshold (``x² / (x² + thr²)`` for a lower bound, the
converse for an upper one); the confidence is the smallest, and the pose is ``ok`` when every check passes.
Cheap: one 5-parameter Gauss–Newton fit on at most ``max_matches`` matches with known intrinsics (≈10 ms at
512 px), four with an unknown focal length (six when the focal length matters, at wide baselines).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..metrics import rotation_angle_deg, rotation_error_deg
from .pose import PoseConfig, fundamental_from_pose, sampson_distance
from .types import Matches, TwoViewGeometry, View

__all__ = ["ConfidenceConfig", "PoseConfidence", "accept_pose", "assess_pose", "refit_pose"]


@dataclass
class ConfidenceConfig:
    """Thresholds of :func:`assess_pose`.

    Args:
        max_refit_rotation_deg: largest rotation change when the pose is re-fitted on its verified matches.
        focal_probe: relative focal-length change at which the pose is re-fitted (both directions).
        focal_scan: further focal factors at which the pose is re-fitted: a second minimum of the fit there (a
            rise within ``focal_tolerance``) counts with its rotation swing.
        evidence_band_px: the matches of ``evidence`` within this Sampson distance of the pose are the fit set.
        min_evidence: fewer such matches than this and the verified matches are the fit set instead (the median of
            fewer residuals is too noisy to see a 10 % rise: CO3D pairs at 29–32° with 69–136 were refused).
        focal_tolerance: relative rise of the median Sampson distance that the matches are taken to reject.
        focal_max_change: the largest focal change considered (ordinary cameras, 40–90° across the long side,
            lie within ±50 % of the 60° prior).
        max_focal_rotation_deg: largest rotation uncertainty left by an unknown focal length.
        min_parallax_to_rotation: smallest median parallax / rotation angle of a pose rotating more than
            ``parallax_check_above_deg`` (a pan of more than 30° with as little parallax is what a homography's
            matches give, not a camera that still sees the same scene).
        min_spread: smallest share of each photo covered by the verified matches' convex hull (0: not checked,
            only reported).
        max_matches: the fits use at most this many verified matches (a fixed-seed random sample).
    """

    max_refit_rotation_deg: float = 1.0
    focal_probe: float = 0.10
    focal_scan: tuple[float, ...] = (0.8, 1.25)
    focal_tolerance: float = 0.10
    focal_max_change: float = 0.5
    max_focal_rotation_deg: float = 4.0
    min_parallax_to_rotation: float = 0.15
    parallax_check_above_deg: float = 30.0
    min_spread: float = 0.0
    max_matches: int = 1000
    evidence_band_px: float = 2.0
    min_evidence: int = 200


@dataclass
class PoseConfidence:
    """The outcome of :func:`assess_pose`.

    Attributes:
        score: the smallest check score, in [0, 1]; 0.5 at a threshold.
        ok: every check passed.
        reasons: a one-line, user-facing reason per failed check.
        checks: the measurements, by name.
        seconds: time spent.
    """

    score: float
    ok: bool
    reasons: list[str] = field(default_factory=list)
    checks: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: score, ok, reasons, checks."""
        return {"score": self.score, "ok": self.ok, "reasons": list(self.reasons), "checks": dict(self.checks)}


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


def refit_pose(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, *,
    scale_px: float = 1.0, iters: int = 15,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The pose re-fitted at fixed intrinsics: Gauss–Newton with Cauchy weights on the Sampson distances of the
    matches ``xy0, xy1`` [M, 2], over the rotation (3) and the translation direction (2), from ``(R, t)``.

    Returns:
        ``(R, t, residuals)``: [3, 3], unit [3], signed Sampson distances [M] (px).
    """

    def apply(theta: np.ndarray, R_: np.ndarray, t_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dR, _ = cv2.Rodrigues(theta[:3].reshape(3, 1))
        basis = np.linalg.svd(t_.reshape(1, 3))[2][1:]  # two unit vectors ⟂ t
        t_new = t_ + theta[3:5] @ basis
        return dR @ R_, t_new / np.linalg.norm(t_new)

    def residuals(R_: np.ndarray, t_: np.ndarray) -> np.ndarray:
        return sampson_distance(fundamental_from_pose(R_, t_, K0, K1), xy0, xy1)

    def cost(r_: np.ndarray) -> float:
        return float(np.sum(np.log1p((r_ / scale_px) ** 2)))

    r = residuals(R, t)
    h = 1e-6
    eye = np.eye(5) * h
    for _ in range(iters):
        Fs = [fundamental_from_pose(*apply(e, R, t), K0, K1) for e in np.concatenate([eye, -eye])]
        rs = sampson_distance(np.stack(Fs), xy0, xy1)  # [10, M], central differences
        J = ((rs[:5] - rs[5:]) / (2 * h)).T
        w = 1.0 / (1.0 + (r / scale_px) ** 2)
        H = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r
        try:
            step = -np.linalg.solve(H + 1e-6 * np.diag(np.diag(H) + 1e-12), g)
        except np.linalg.LinAlgError:
            break
        R_new, t_new = apply(step, R, t)
        r_new = residuals(R_new, t_new)
        if cost(r_new) >= cost(r):
            break
        R, t, r = R_new, t_new, r_new
        if np.linalg.norm(step) < 1e-9:
            break
    return R, t, r


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


def _hull_share(xy: np.ndarray, width: int, height: int) -> float:
    if len(xy) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(np.ascontiguousarray(xy, np.float32)))) / float(width * height)


def _scaled(K: np.ndarray, k: float, unknown: bool) -> np.ndarray:
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
    R_fit, t_fit, r_fit = refit_pose(g.R, g.t, g.K0, g.K1, xy0, xy1)
    r0 = max(float(np.median(np.abs(r_fit))), 1e-9)

    def probe(k: float) -> tuple[float, float]:  # (rise, rotation swing) of the pose re-fitted at focal × k
        R, _, r = refit_pose(R_fit, t_fit, _scaled(g.K0, k, unknown[0]), _scaled(g.K1, k, unknown[1]), xy0, xy1)
        return float(np.median(np.abs(r))) / r0 - 1.0, rotation_error_deg(R, R_fit)

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
    plausible = min(cfg.focal_probe * math.sqrt(cfg.focal_tolerance / max(rise, 1e-3)), cfg.focal_max_change)
    return max(swing * plausible / cfg.focal_probe, scanned), rise, plausible


FOCAL_EVIDENCE_OTHER_THAN_MATCHES = ("pointmap",)
"""Values of ``info["focal_evidence"]`` by which a pose stage says it measured a prior view's focal length on
something else than the matches (the neural backend: Weiszfeld on the network's point map)."""


def _focal_unknown(v0: View, v1: View, geometry: TwoViewGeometry) -> tuple[bool, bool]:
    """Which views' focal lengths only the matches can determine (the prior's, not measured otherwise)."""
    if geometry.info.get("focal_evidence") in FOCAL_EVIDENCE_OTHER_THAN_MATCHES:
        return False, False
    return v0.intrinsics_source == "prior", v1.intrinsics_source == "prior"


def assess_pose(
    v0: View, v1: View, geometry: TwoViewGeometry, config: ConfidenceConfig | None = None, *,
    evidence: Matches | None = None,
) -> PoseConfidence:  # fmt: skip
    """How far the relative pose ``geometry`` can be trusted (module docstring).

    Args:
        v0, v1: the two views; a view whose ``intrinsics_source`` is ``"prior"`` has an unknown focal length
            (whether or not the pose stage re-estimated it from the matches: call this before the pipeline marks it
            estimated), unless the pose stage measured it on other evidence (``info["focal_evidence"]``).
        geometry: the final pose and its verified matches.
        evidence: the filtered matches the pose was first estimated from, before any matching guided by the pose
            (which selects matches that agree with it, right or wrong); the focal check fits on those within
            ``evidence_band_px`` of the pose. None: on the verified matches.

    Returns:
        :class:`PoseConfidence`; its ``reasons`` are one line each, for the user.
    """
    cfg = config or ConfidenceConfig()
    t0 = time.perf_counter()
    g = geometry
    checks: dict[str, float] = {}
    scores: dict[str, float] = {}
    reasons: list[str] = []
    inl = g.inliers
    n = len(inl)
    spread = min(_hull_share(inl.xy0, v0.width, v0.height), _hull_share(inl.xy1, v1.width, v1.height))
    checks["spread"] = spread
    if cfg.min_spread > 0:
        scores["spread"] = _lower(spread, cfg.min_spread)
        if spread < cfg.min_spread:
            reasons.append(
                f"pose confidence low: the {n} verified matches cover only {100 * spread:.0f} % of a photo "
                f"(need {100 * cfg.min_spread:.0f} %), too small a cluster to pin the pose down"
            )
    rotation = rotation_angle_deg(g.R)
    parallax = g.info.get("median_parallax_deg")
    if isinstance(parallax, (int, float)) and math.isfinite(parallax) and rotation > 0:
        ratio = float(parallax) / rotation
        checks["parallax_to_rotation"] = ratio
        if rotation > cfg.parallax_check_above_deg:
            scores["parallax"] = _lower(ratio, cfg.min_parallax_to_rotation)
            if ratio < cfg.min_parallax_to_rotation:
                reasons.append(
                    f"pose confidence low: the pose is mostly rotation ({rotation:.0f}°) with little parallax "
                    f"({float(parallax):.1f}°), what matches on repeated texture or one plane produce"
                )
    if n >= 8:
        keep = np.arange(n)
        if n > cfg.max_matches:
            keep = np.sort(np.random.default_rng(0).choice(n, cfg.max_matches, replace=False))
        xy0, xy1 = inl.xy0[keep].astype(np.float64), inl.xy1[keep].astype(np.float64)
        R_fit, _, _ = refit_pose(g.R, g.t, g.K0, g.K1, xy0, xy1)
        moved = rotation_error_deg(R_fit, g.R)
        checks["refit_rotation_deg"] = moved
        scores["refit"] = _upper(moved, cfg.max_refit_rotation_deg)
        if moved > cfg.max_refit_rotation_deg:
            reasons.append(
                f"pose confidence low: re-fitted on its own {n} verified matches the rotation moves by {moved:.1f}°"
            )
        unknown = _focal_unknown(v0, v1, g)
        if any(unknown):
            f0, f1 = _fit_set(g, evidence, cfg, xy0, xy1)
            checks["focal_fit_matches"] = len(f0)
            u, rise, plausible = _focal_uncertainty(g, f0, f1, unknown, cfg)
            checks.update(focal_rotation_deg=u, focal_residual_rise=rise, focal_plausible_change=plausible)
            scores["focal"] = _upper(u, cfg.max_focal_rotation_deg)
            if u > cfg.max_focal_rotation_deg:
                reasons.append(
                    f"pose confidence low: the matches do not pin down the focal length (±{100 * plausible:.0f} % "
                    f"fits them about as well), and within that range the rotation changes by up to {u:.0f}°; "
                    "give --focal or --intrinsics"
                )
    score = min(scores.values(), default=1.0)
    checks = {k: float(v) for k, v in checks.items()}
    return PoseConfidence(score=float(score), ok=not reasons, reasons=reasons, checks=checks,
                          seconds=time.perf_counter() - t0)  # fmt: skip


def _support_reasons(geometry: TwoViewGeometry, pose: PoseConfig) -> list[str]:
    """The pose's support in the matches, as reasons: at least ``pose.min_inliers`` verified matches.

    Not ``pose.min_inlier_ratio``: it was measured on SIFT matches verified within 1 px of their epipolar lines;
    the neural backend's grid-sampled matches verified against the point maps (exact ones, 96×64) agree at 54 %.
    """
    n = len(geometry.inliers)
    if n >= pose.min_inliers:
        return []
    return [
        f"pose confidence low: only {n} verified match{'es' if n != 1 else ''} agree{'s' if n == 1 else ''} with the "
        f"pose, need at least {pose.min_inliers}"
    ]


def accept_pose(
    v0: View, v1: View, geometry: TwoViewGeometry, pose: PoseConfig, config: ConfidenceConfig | None, *,
    evidence: Matches | None = None,
) -> PoseConfidence:  # fmt: skip
    """The acceptance of a relative pose, for every backend (module docstring): one place, one set of thresholds.

    Args:
        v0, v1: the two views (``intrinsics_source`` as loaded: call before the pipeline marks a focal estimated).
        geometry: the final pose, its verified matches and its ``info`` (``doubts``: the pose stage's own).
        pose: the minimum of support (``min_inliers``).
        config: the checks of :func:`assess_pose`; None skips them (the support is still checked).
        evidence: as for :func:`assess_pose`.

    Returns:
        :class:`PoseConfidence`: ``reasons`` are the pose stage's doubts, then the failed support minimum, then
        :func:`assess_pose`'s reasons (one user-facing line each, the first is the one a refusal names);
        ``score`` is :func:`assess_pose`'s, 0 when the support minimum fails; ``checks`` are :func:`assess_pose`'s.
    """
    t0 = time.perf_counter()
    raw = geometry.info.get("doubts", [])
    reasons = [str(d) for d in raw] if isinstance(raw, (list, tuple)) else [str(raw)]
    support = _support_reasons(geometry, pose)
    reasons += support
    if config is not None:
        conf = assess_pose(v0, v1, geometry, config, evidence=evidence)
        score, checks = conf.score, conf.checks
        reasons += [r for r in conf.reasons if r not in reasons]
    else:
        score, checks = 1.0, {}
    if support:
        score = 0.0
    return PoseConfidence(score=float(score), ok=not reasons, reasons=reasons, checks=checks,
                          seconds=time.perf_counter() - t0)  # fmt: skip
