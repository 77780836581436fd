"""Stage 4 as one object: the search for a relative pose and its acceptance (:class:`PoseSearch`).

1. Descriptor tiers: the primary descriptors → matching → pose; when they verify fewer than
   ``fallback_min_inliers`` matches (or fail), the fallback descriptors, kept when they verify more; when neither
   gives a pose, the wide-baseline descriptors, and when their pose fails, the plane tie-break
   (:func:`~.tiebreak.plane_tiebreak`). A tier's pose that its own putative matches do not support (the a contrario
   test and the uncertainty of :func:`~.confidence.weigh_evidence`) does not stop the search: the later tiers run,
   and the first whose pose their matches support replaces it. Last, the learned tier (ALIKED + LightGlue,
   :mod:`..learned`) when the SIFT tiers' pose still fails or is not supported; it competes the same way.
   When the primary tier's matches show the same view (:class:`~macsplat_cli.errors.SameViewError`), the search
   stops there: two photos of one view stay one view whichever descriptors match them. When a tier's pose stage
   found a plane's two poses tied (:class:`~macsplat_cli.errors.PlaneTieError`), a later tier's pose must win the
   same contest on its own matches (:func:`~.planar.settles_tie`), or the pair is refused with that tie (the plane
   tie-break's pose settled it on dense consistency already).
2. Guided re-matching: with fewer than ``GUIDED_BELOW`` verified matches, every keypoint is matched again along
   the pose's epipolar lines and the pose re-estimated, kept if it verifies more and stays near. Guided matches
   refine a pose; they are never evidence for accepting it.
3. Acceptance (:func:`~.confidence.accept_pose`): the pose stage's doubts, the support minimum, the checks, and the
   evidence of the tier's putative matches (gathered before the pose); a doubted pose is refused unless
   ``accept_low_confidence``.
4. The views whose prior focal the pose estimated become new, self-calibrated :class:`View` objects.

Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

from ...errors import PlaneTieError, ReconstructionError, SameViewError
from ...metrics import rotation_error_deg, translation_direction_error_deg
from ..matching import guided_matches
from ..slots import DescribeStage, MatchStage, PairPass, PoseStage, StageTimer
from ..types import Features, Matches, TwoViewGeometry, View
from .confidence import accept_pose, weigh_evidence
from .config import GUIDED_MAX_CHANGE_DEG, GUIDED_RATIO, PoseConfig, PoseSearchConfig
from .geometry import fundamental_from_pose
from .planar import settles_tie
from .result import Doubt, PoseConfidence, PoseResult, Tier
from .tiebreak import plane_tiebreak

if TYPE_CHECKING:
    from ..learned import LearnedTier

__all__ = ["LOW_CONFIDENCE_HINT", "PoseSearch", "StageTimer", "calibrated_views"]

logger = logging.getLogger(__name__)

WIDE_MIN_INLIERS = 30
"""The wide tier's pose needs this many verified matches (a handful at a wide baseline is a guess that guided
matching would then "confirm")."""
GUIDED_BELOW = 1000
"""The guided re-matching is skipped when the first pose already has this many verified matches."""

LOW_CONFIDENCE_HINT = "use --accept-low-confidence to write the scene anyway"
"""Appended to a refusal for low pose confidence."""

T = TypeVar("T")


def _untimed(stage: str, fn: Callable[[], T]) -> T:
    return fn()


Guard = Callable[[list[Features], Matches, Matches, float | None], list[str]]
"""A matcher's own doubts about a pose its matches gave: ``(features, verified, final, log10_nfa) → messages``
(:meth:`~..learned.LightGlueMatcher.doubts`)."""


@dataclass
class _Attempt:
    """One tier's outcome: its pose (None: failed, ``failure`` says why), the features its matches index, its
    filtered matches, and its matcher's guard (its ``doubts`` method, when it has one: the learned matcher's)."""

    geometry: TwoViewGeometry | None
    failure: ReconstructionError | None
    features: list[Features]
    matches: Matches
    tier: Tier
    plane_tiebreak: list[int] | None = None
    matcher: str = ""
    guard: Guard | None = None


def calibrated_views(views: list[View], geometry: TwoViewGeometry) -> list[View]:
    """The views for the later stages: a view with the prior's focal, when the pose estimated it, as a new
    :class:`View` (``intrinsics_source="estimated"``, the geometry's ``K``); the given views are left as they are."""
    if not geometry.focal_estimated:
        return list(views)
    Ks = (geometry.K0, geometry.K1)
    return [
        dataclasses.replace(v, intrinsics_source="estimated", K=Ks[k]) if v.intrinsics_source == "prior" else v
        for k, v in enumerate(views)
    ]


class PoseSearch:
    """Stage 4: descriptor tiers, plane tie-break, guided re-matching and acceptance (module docstring).

    Args:
        config: the search's settings.
        pose_config: the pose stage's thresholds (the support minimum, the plane's homography).
        describe: the primary descriptors (``(views, pair) → [Features]×2``).
        match: the matcher (``(f0, f1) → Matches``).
        pose: the pose stage (``(v0, v1, matches, pair) → TwoViewGeometry``).
        fallback: the fallback descriptors, or None.
        wide: the wide-baseline descriptors, or None.
        learned: the learned tier (its own descriptors and matcher, :class:`~..learned.LearnedTier`), run last, or
            None.
        warn_doubts: log a kept doubted pose (``accept_low_confidence``) as a warning; off for a caller that judges
            the doubts itself (:mod:`..multiview`).
    """

    def __init__(
        self, config: PoseSearchConfig, pose_config: PoseConfig, *, describe: DescribeStage, match: MatchStage,
        pose: PoseStage, fallback: DescribeStage | None = None, wide: DescribeStage | None = None,
        learned: LearnedTier | None = None, warn_doubts: bool = True,
    ) -> None:  # fmt: skip
        self.config = config
        self.pose_config = pose_config
        self.describe = describe
        self.match = match
        self.pose = pose
        self.fallback = fallback
        self.wide = wide
        self.learned = learned
        self.warn_doubts = warn_doubts

    def __call__(self, views: list[View], pair: PairPass = None, timed: StageTimer | None = None) -> PoseResult:
        """The accepted pose of the two ``views`` (``pair``: the network pass, for backends that have one).

        Raises:
            ReconstructionError: no tier gives a pose (the first failure that stands says why), or the pose is
                doubted and ``accept_low_confidence`` is off.
        """
        timed = timed or _untimed
        found = self._tiers(views, pair, timed)
        assert found.geometry is not None
        geometry, guided = self._guided(views, found.features, found.geometry, pair, timed)
        confidence = self._accept(views, geometry, found.matches, timed, found)
        assessed = self.config.confidence
        return PoseResult(
            geometry=geometry,
            views=calibrated_views(views, geometry),
            tier=found.tier,
            features=found.features,
            evidence=found.matches,
            guided=guided,
            plane_tiebreak=found.plane_tiebreak,
            confidence=confidence if assessed else None,
            doubts=list(confidence.doubts),
            accepted_low_confidence=bool(confidence.doubts),
            matcher=found.matcher,
        )

    # ------------------------------------------------------------------------------------------- the tiers
    def _try_pose(
        self, views: list[View], matches: Matches, pair: PairPass, timed: StageTimer, stage: str
    ) -> tuple[TwoViewGeometry | None, ReconstructionError | None]:
        try:
            return timed(stage, lambda: self.pose(views[0], views[1], matches, pair)), None
        except ReconstructionError as e:
            return None, e

    def _chain(
        self,
        views: list[View],
        pair: PairPass,
        timed: StageTimer,
        describe: DescribeStage,
        tier: Tier,
        suffix: str,
        match: MatchStage | None = None,
    ) -> _Attempt:
        """Descriptors → matching (``match``, default the search's matcher) → pose with ``describe``, its stages
        named with ``suffix``."""
        matcher = match or self.match
        feats = timed(f"descriptors{suffix}", lambda: describe(views, pair))
        matches = timed(f"matching{suffix}", lambda: matcher(feats[0], feats[1]))
        geometry, failure = self._try_pose(views, matches, pair, timed, f"pose{suffix}")
        names = (getattr(stage, "name", type(stage).__name__) for stage in (describe, matcher))
        guard = getattr(matcher, "doubts", None)
        return _Attempt(geometry, failure, feats, matches, tier, matcher="+".join(names), guard=guard)

    def _tiers(self, views: list[View], pair: PairPass, timed: StageTimer) -> _Attempt:
        """The tier whose pose stands (module docstring, 1): the first that gives a pose, unless the putative
        matches do not support it (:func:`~.confidence.weigh_evidence`): then the later tiers run too, and the
        first of them whose pose they support replaces it.

        Raises:
            ReconstructionError: none gives a pose: a tier's plane tie when one found it, else the fallback tier's
                failure when it ran, else the primary's (the wide tier's is only logged).
            SameViewError: the primary tier's matches show the same view; no other tier runs.
            PlaneTieError: a tier found a plane's two poses tied and the later tier's pose that stands does not
                settle that contest on its own matches.
        """
        primary = self._chain(views, pair, timed, self.describe, "primary", "")
        if isinstance(primary.failure, SameViewError):
            raise primary.failure
        tried = [primary]
        best = self._later_tiers(views, pair, timed, primary, tried)
        tie = next((a.failure for a in tried if isinstance(a.failure, PlaneTieError)), None)
        if best.geometry is None:
            assert best.failure is not None
            raise tie or best.failure  # a tie says more than a later tier's too few matches
        settled = best.plane_tiebreak is not None  # the plane tie-break's pose: settled on dense consistency
        if tie is not None and not settled and not settles_tie(best.geometry, best.matches, self.pose_config):
            logger.debug("%s tier's pose does not settle the plane's tie of an earlier tier", best.tier)
            raise tie
        return best

    def _later_tiers(
        self, views: list[View], pair: PairPass, timed: StageTimer, primary: _Attempt, tried: list[_Attempt]
    ) -> _Attempt:
        """The fallback, wide and learned tiers after ``primary`` (:meth:`_tiers`), each attempt appended to
        ``tried``; the attempt that stands (its failure when none gives a pose)."""
        c = self.config
        best = primary
        n_verified = len(best.geometry.inliers) if best.geometry is not None else 0
        doubted = not self._credible(views, best)
        if self.fallback is not None and (n_verified < c.fallback_min_inliers or doubted):
            logger.debug("%d verified matches (< %d) or a pose its matches do not support: retrying with %s",
                         n_verified, c.fallback_min_inliers, self.fallback.name)  # fmt: skip
            alt = self._chain(views, pair, timed, self.fallback, "fallback", " (fallback)")
            tried.append(alt)
            if alt.geometry is not None:
                alt_ok = self._credible(views, alt)
                more = len(alt.geometry.inliers) > n_verified
                if best.geometry is None or (doubted and alt_ok) or (more and (alt_ok or doubted)):
                    best, doubted = alt, not alt_ok
            elif best.geometry is None:
                best = dataclasses.replace(best, failure=alt.failure or best.failure)
        if self.wide is not None and (best.geometry is None or doubted):
            wide = self._wide(views, primary.features, pair, timed)
            tried.append(wide)
            if wide.geometry is not None and (best.geometry is None or self._credible(views, wide)):
                best = wide
                doubted = best.geometry is not None and not self._credible(views, best)
            else:
                logger.debug("wide-baseline tier: %s", wide.failure or "its pose is not supported either")
        if self.learned is not None and (best.geometry is None or doubted):
            best = self._learned(views, pair, timed, best)
        return best

    def _credible(self, views: list[View], attempt: _Attempt) -> bool:
        """The tier's putative matches support its pose (the a contrario test and the uncertainty). True when there
        is no pose, when the acceptance does not weigh evidence, and when the pose stage itself doubts the pose: its
        doubt (an unobservable focal length, a plane's ambiguity) is about the geometry, which another tier's
        matches do not change, and it refuses the pose anyway."""
        if not self.config.confidence or attempt.geometry is None or attempt.geometry.doubts:
            return True
        _, doubts, _ = weigh_evidence(views[0], views[1], attempt.geometry, attempt.matches)
        return not doubts

    def _learned(self, views: list[View], pair: PairPass, timed: StageTimer, best: _Attempt) -> _Attempt:
        """The learned tier after the SIFT tiers (module docstring, 1): its pose replaces ``best`` when ``best`` has
        none, or when its own matches support it; ``best``'s failure stands when it gives none."""
        assert self.learned is not None
        t = self.learned
        logger.debug("SIFT's pose failed or is not supported: retrying with %s", t.name)
        timed("weights (learned)", t.load)
        att = self._chain(views, pair, timed, t.describe, "learned", " (learned)", t.match)
        if att.geometry is not None and (best.geometry is None or self._credible(views, att)):
            return att
        logger.debug("learned tier: %s", att.failure or "its pose is not supported either")
        return best

    def _wide(self, views: list[View], primary: list[Features], pair: PairPass, timed: StageTimer) -> _Attempt:
        """The second fallback tier: wide-baseline descriptors, matching and pose; when that pose fails, the
        plane's poses ranked by dense consistency (on the primary features)."""
        c = self.config
        assert self.wide is not None
        logger.debug("still too few verified matches: retrying with %s", self.wide.name)
        att = self._chain(views, pair, timed, self.wide, "wide", " (wide)")
        if att.geometry is not None and len(att.geometry.inliers) < WIDE_MIN_INLIERS:
            failure = ReconstructionError(
                f"pose could not be estimated: {len(att.geometry.inliers)} verified matches, need at least "
                f"{WIDE_MIN_INLIERS} at a wide baseline"
            )
            att = dataclasses.replace(att, geometry=None, failure=failure)
        if att.geometry is not None or c.plane_tiebreak_margin is None:
            return att
        tied = timed(
            "pose (plane tie-break)",
            lambda: plane_tiebreak(views, primary, att.matches, pair, self.pose, c, self.pose_config),
        )
        if tied is None:
            return att
        return _Attempt(tied[0], None, primary, att.matches, "wide+plane-tiebreak", tied[1])

    # ------------------------------------------------------------------------------------------- refinement
    def _guided(
        self, views: list[View], feats: list[Features], geometry: TwoViewGeometry, pair: PairPass, timed: StageTimer
    ) -> tuple[TwoViewGeometry, bool]:
        """Epipolar-guided re-matching under the pose (module docstring, 2). Returns the pose kept and whether it
        is the guided one."""
        c = self.config
        if c.guided_band_px is None or len(geometry.inliers) >= GUIDED_BELOW:
            return geometry, False
        if geometry.doubts:
            # matches picked within the band of a doubtful pose (e.g. one built on the prior's focal) agree with
            # it: they cannot confirm it, and a refit would drop the pose stage's doubt
            return geometry, False
        band = c.guided_band_px
        F = fundamental_from_pose(geometry.R, geometry.t, geometry.K0, geometry.K1)
        guided = timed(
            "matching (guided)", lambda: guided_matches(feats[0], feats[1], F, band_px=band, ratio=GUIDED_RATIO)
        )
        guided.counts = {**geometry.inliers.counts, **guided.counts}
        guided.counts.pop("verified", None)
        refined, _ = self._try_pose(views, guided, pair, timed, "pose (guided)")
        if (
            refined is not None
            and len(refined.inliers) > len(geometry.inliers)
            and rotation_error_deg(refined.R, geometry.R) <= GUIDED_MAX_CHANGE_DEG[0]
            and translation_direction_error_deg(refined.t, geometry.t) <= GUIDED_MAX_CHANGE_DEG[1]
        ):
            return refined, True
        return geometry, False

    # ------------------------------------------------------------------------------------------- acceptance
    def _accept(
        self, views: list[View], geometry: TwoViewGeometry, evidence: Matches, timed: StageTimer,
        found: _Attempt | None = None,
    ) -> PoseConfidence:  # fmt: skip
        """The acceptance of the final pose (module docstring, 3), on the views as loaded (a view with the prior's
        focal has an unknown focal length) and ``evidence``, the tier's filtered matches; when the matcher of the
        tier that ``found`` the pose (its attempt, before guided re-matching) has a guard, its doubts too: the
        learned matcher's (:mod:`..learned.guard`), in whichever tier it ran (``--matcher auto`` or ``aliked``).

        Raises:
            ReconstructionError: the pose is doubted and ``accept_low_confidence`` is off.
        """
        c = self.config
        conf: PoseConfidence = timed(
            "pose confidence",
            lambda: accept_pose(views[0], views[1], geometry, self.pose_config, c.confidence, evidence=evidence),
        )
        if found is not None and found.guard is not None and found.geometry is not None:
            nfa = conf.checks.get("log10_nfa") if c.confidence else None
            more = found.guard(found.features, found.geometry.inliers, geometry.inliers, nfa)
            conf = dataclasses.replace(conf, ok=conf.ok and not more,
                                       doubts=[*conf.doubts, *(Doubt("evidence", m) for m in more)])  # fmt: skip
        doubts: list[Doubt] = conf.doubts
        if doubts and not c.accept_low_confidence:
            raise ReconstructionError(f"{doubts[0].message} ({LOW_CONFIDENCE_HINT})")
        if doubts and self.warn_doubts:
            logger.warning(
                "the pose may be wrong, the scene is written anyway (--accept-low-confidence): %s", doubts[0].message
            )
        return conf
