"""What stage 4 hands on: the accepted pose (:class:`PoseResult`), its acceptance (:class:`PoseConfidence`) and the
doubts (:class:`Doubt`), typed. The report's ``pose`` section and the cameras file's ``pose_confidence`` are built
from these fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from ..types import Features, Matches, TwoViewGeometry, View
from .evidence import PoseEvidence

__all__ = ["Doubt", "DoubtCheck", "PoseConfidence", "PoseResult", "Tier"]

Tier = Literal["primary", "fallback", "wide", "wide+plane-tiebreak", "learned"]
"""The descriptor tier whose matches gave the pose: the primary descriptors, the fallback, the wide-baseline tier,
the plane tie-break after the wide tier (its matches guided along the winning plane pose, primary features), or the
learned tier (ALIKED + LightGlue, after the SIFT tiers)."""

WIDE_TIERS: tuple[Tier, ...] = ("wide", "wide+plane-tiebreak")
"""The tiers the report names (``descriptors_tier``)."""

DoubtCheck = Literal["pose", "support", "parallax", "refit", "focal", "evidence", "uncertainty"]
"""Who doubts: the pose stage itself (either backend), the support minimum (verified matches), or a check of
:func:`~.confidence.assess_pose` (parallax over rotation, the re-fit, the focal length), or the evidence
of the putative matches (:func:`~.evidence.pose_evidence`: the a contrario test, the rotation's uncertainty)."""


@dataclass(frozen=True)
class Doubt:
    """One reason to doubt a pose.

    Attributes:
        check: who raised it.
        message: one user-facing line (the first doubt's is the one a refusal names).
    """

    check: DoubtCheck
    message: str

    def __str__(self) -> str:
        return self.message


@dataclass
class PoseConfidence:
    """The outcome of :func:`~.confidence.assess_pose` or :func:`~.confidence.accept_pose`.

    Attributes:
        score: the smallest check score, in [0, 1]; 0.5 at a threshold.
        ok: no doubt.
        doubts: one per failed check, in order.
        checks: the measurements, by name.
        seconds: time spent.
        evidence: the a contrario test, the uncertainty and GRIC on the putative matches, when measured.
        rule: the acceptance rule that was applied, in words (for the cameras file).
    """

    score: float
    ok: bool
    doubts: list[Doubt] = field(default_factory=list)
    checks: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    evidence: PoseEvidence | None = None
    rule: str = ""

    @property
    def reasons(self) -> list[str]:
        """The doubts' messages."""
        return [d.message for d in self.doubts]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: score, ok, reasons, checks."""
        return {"score": self.score, "ok": self.ok, "reasons": self.reasons, "checks": dict(self.checks)}


@dataclass
class PoseResult:
    """Stage 4's output (:class:`~.search.PoseSearch`).

    Attributes:
        geometry: the accepted relative pose and its verified matches.
        views: the two views for the later stages: a view whose prior focal the pose estimated is a new
            :class:`View` (``intrinsics_source="estimated"``, the geometry's ``K``); the others are the given ones.
        tier: the descriptor tier that gave the pose.
        features: the features the pose's matches index. [Features] ×2
        evidence: the tier's filtered matches, on which the pose was first estimated and which the confidence
            checks fit (not the guided ones, which the pose itself selected).
        guided: the epipolar-guided re-matching replaced the tier's pose.
        plane_tiebreak: the plane's candidate poses' scores, best first, when the tie-break gave the pose.
        confidence: the acceptance's checks; None when they are off (``PoseSearchConfig.confidence``).
        doubts: every doubt, in order: the pose stage's, the support minimum's, the checks'.
        accepted_low_confidence: there are doubts, and the scene is built anyway.
        matcher: the descriptors and matcher that gave the pose (``"learned:aliked-n16+learned:lightglue"``); the
            report names it when they are learned ones.
    """

    geometry: TwoViewGeometry
    views: list[View]
    tier: Tier
    features: list[Features]
    evidence: Matches
    guided: bool = False
    plane_tiebreak: list[int] | None = None
    confidence: PoseConfidence | None = None
    doubts: list[Doubt] = field(default_factory=list)
    accepted_low_confidence: bool = False
    matcher: str = ""

    @property
    def fallback_used(self) -> bool:
        """A fallback tier's matches were kept."""
        return self.tier != "primary"

    @property
    def inlier_ratio(self) -> float | None:
        """Verified / candidate matches, as the pose stage reported it."""
        return self.geometry.diagnostics.get("inlier_ratio")

    def report(self) -> dict[str, Any]:
        """The report's ``pose`` section: the pose stage's diagnostics and typed fields, the tier, the acceptance.

        ``descriptors_tier`` and ``plane_tiebreak`` describe the tier's pose: they are left out when the guided
        re-matching replaced it (as the report has always done).
        """
        g = self.geometry
        out = dict(g.diagnostics)
        out["focal_estimated"] = g.focal_estimated
        if g.focal_evidence is not None:
            out["focal_evidence"] = g.focal_evidence
        if g.median_parallax_deg is not None:
            out["median_parallax_deg"] = g.median_parallax_deg
        if not self.guided:
            if self.plane_tiebreak is not None:
                out["plane_tiebreak"] = list(self.plane_tiebreak)
            if self.tier in WIDE_TIERS:
                out["descriptors_tier"] = self.tier
        if self.confidence is not None:
            out["confidence"] = self.confidence.score
            out["confidence_checks"] = self.confidence.checks
            out["evidence"] = self.evidence_summary()
        out["doubts"] = [d.message for d in self.doubts]
        if self.accepted_low_confidence:
            out["accepted_low_confidence"] = True
        if self.matcher.startswith("learned:"):  # the SIFT tiers' reports stay as they were
            out["matcher"] = self.matcher
        return out

    def evidence_summary(self) -> dict[str, Any]:
        """What the acceptance decided on: the tier, its putative matches, the pose's inliers among them, the log10
        NFA, their coverage, the rotation's uncertainty, whether the support is planar, and each check's outcome
        (``passed``: names; ``failed``: the doubts' check names)."""
        out: dict[str, Any] = {"tier": self.tier, "guided": self.guided, "verified": len(self.geometry.inliers)}
        conf = self.confidence
        e = conf.evidence if conf is not None else None
        if e is not None:
            out.update(
                putative_matches=e.putative, inliers=e.inliers, log10_nfa=e.log10_nfa, threshold_px=e.threshold_px,
                coverage=e.coverage, rotation_sigma_deg=e.rotation_sigma_deg, planar_support=e.planar,
            )  # fmt: skip
        if conf is not None:
            out["rule"] = conf.rule
        out["failed"] = sorted({d.check for d in self.doubts})
        return out

    def camera_confidence(self) -> dict[str, Any] | None:
        """The cameras file's ``pose_confidence`` (None when the pose was not assessed and has no doubts):
        ``score`` (None when not assessed), ``log10_nfa`` and ``acceptance_rule`` (when assessed), ``checks``,
        ``doubts`` and ``accepted_low_confidence``."""
        if self.confidence is None and not self.doubts:
            return None
        conf = self.confidence
        assessed = {} if conf is None else {
            "log10_nfa": conf.evidence.log10_nfa if conf.evidence is not None else None, "acceptance_rule": conf.rule,
        }  # fmt: skip
        return {
            "score": conf.score if conf is not None else None,
            **assessed,
            "checks": dict(conf.checks) if conf is not None else {},
            "doubts": [d.message for d in self.doubts],
            "accepted_low_confidence": self.accepted_low_confidence,
        }
