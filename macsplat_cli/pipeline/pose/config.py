"""The settings of stage 4: the two-view pose (:class:`PoseConfig`), its acceptance (:class:`ConfidenceConfig`) and
the search around it (:class:`PoseSearchConfig`). Every threshold is a named field with a one-line reason; a number
used in several places is one field. Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..descriptors import SiftConfig
from ..learned.config import LearnedConfig

__all__ = ["ConfidenceConfig", "EvidenceConfig", "PoseConfig", "PoseSearchConfig"]


@dataclass
class PoseConfig:
    """Thresholds of the classical two-view pose (:func:`~.essential.estimate_pose`).

    Pixel thresholds apply at a working long side of ``reference_side``; below it they shrink with the image.

    Args:
        threshold_px: inlier threshold on the epipolar (Sampson) distance, working-resolution px.
        confidence: RANSAC confidence.
        max_iters: RANSAC iterations.
        min_inliers: fewer verified matches than this is a failure (and the support every backend's pose needs).
        refine: run the non-linear refinement.
        estimate_focal: self-calibrate views whose intrinsics come from the prior.
        focal_prior_sigma: std of the log focal prior (0.5 ≈ ×/÷ 1.65).
        focal_max_std: largest data-only std of the log focal for the estimate to be used (computed with the
            residuals' robust noise level, 1.4826·MAD).
        min_parallax_deg: a smaller median parallax of the verified matches is no baseline (a pure rotation).
        min_inlier_ratio: smallest fraction of the matches that must agree with the pose (wrong poses had 28–37 %).
        homography_excess: the pose is rejected when a homography explains more than this many times its inliers
            (plus ``homography_slack``): impossible for a correct pose, since a plane's points fit it too.
        planar_fraction: a homography explaining this fraction of the verified matches makes the pair planar.
        planar_ambiguity: with ``planar_resolve`` off, the pose is rejected as soon as another decomposition of
            the homography explains this fraction of its verified matches (the check before issue 14).
        max_flipped: the pair is refused as mirror images when more than this share of the small triangles between
            neighbouring verified matches flips orientation (:func:`~.checks.flipped_fraction`).
        focal_max_rotation_deg: the self-calibrated focal is used only if its data-only std times the rotation's
            sensitivity to the focal stays below this (°); else the prior is kept and, when the prior's std times
            that sensitivity exceeds it too, a doubt is recorded.
        planar_resolve: when the plane's poses tie on the verified matches, score them on all the matches
            (:func:`~.planar.resolve_planar`) instead of refusing at once; refuse only when that is tied too.
        planar_min_evidence: fewest matches that the winning pose must explain and each rival refute.
        planar_evidence_ratio: how many times the converse count (explained by the rival, refuted by the winner)
            those must be.
        planar_contend: a plane's pose that explains at least this fraction of the best one's verified matches
            contends: it must be beaten by evidence, not by a count a few matches short.
        planar_refute_factor: a pose refutes a match behind one of its cameras or farther than this many
            ``threshold_px`` from its epipolar geometry (the band between explained and refuted is no evidence).
        reference_side: working long side (px) at which the pixel thresholds apply as given (keypoints come from
            a photo of up to 768 px, so a smaller working image has proportionally more precise ones).
        homography_factor: a homography's inlier threshold, in ``threshold_px`` (a plane's transfer error adds
            both views' localisation errors, the Sampson distance only their component across the line).
        homography_slack: matches a homography may explain beyond ``homography_excess`` times the pose's inliers
            (a few off-plane matches count for either on a small set).
        same_pose_deg: two poses within this rotation and translation-direction difference (°) are the same.
        same_solution_deg: two poses within this (°) are one solution found twice (a decomposition and the
            essential matrix's pose, or a refit sliding along a plane's valley): no ambiguity between them.
        same_view_shift_px: the median displacement of the matches below which two same-size photos may be one view.
        same_view_still_px: a match that moves less than this (px) has not moved.
        same_view_share: more than this share of matches that have not moved makes the two photos one view.
        focal_search_range: the focal factors over which the essential-matrix defect is searched (ordinary
            cameras, 20–120° across the long side, lie within it around the 60° prior).
        focal_search_steps: grid points of that search (log-spaced: 0.8 % apart).
        focal_noise_floor_px: the residuals' noise level used for the focal's data-only std is at least this
            (exact synthetic matches would claim a perfect focal).
        focal_sensitivity_step: the log-focal step (±) at which the rotation's sensitivity to the focal is measured.
        object_axes_gap: the doubt names an object-centric pair when the optical axes pass within this many
            baselines of each other...
        object_axes_asymmetry: ...and their closest points' distances from the two cameras differ by less than
            this many baselines.
    """

    threshold_px: float = 1.0
    confidence: float = 0.99999
    max_iters: int = 10000
    min_inliers: int = 15
    refine: bool = True
    estimate_focal: bool = True
    focal_prior_sigma: float = 0.5
    focal_max_std: float = 0.05
    min_parallax_deg: float = 0.5
    min_inlier_ratio: float = 0.5
    homography_excess: float = 1.2
    planar_fraction: float = 0.8
    planar_ambiguity: float = 0.95
    max_flipped: float = 0.5
    focal_max_rotation_deg: float = 0.25
    planar_resolve: bool = True
    planar_min_evidence: int = 8
    planar_evidence_ratio: float = 3.0
    planar_contend: float = 0.8
    planar_refute_factor: float = 3.0
    reference_side: int = 512
    homography_factor: float = 1.5
    homography_slack: int = 10
    same_pose_deg: tuple[float, float] = (1.0, 5.0)
    same_solution_deg: tuple[float, float] = (2.0, 10.0)
    same_view_shift_px: float = 0.5
    same_view_still_px: float = 1.0
    same_view_share: float = 0.8
    focal_search_range: tuple[float, float] = (0.4, 2.5)
    focal_search_steps: int = 121
    focal_noise_floor_px: float = 0.02
    focal_sensitivity_step: float = 0.1
    object_axes_gap: float = 0.1
    object_axes_asymmetry: float = 0.3


@dataclass
class EvidenceConfig:
    """Thresholds of :func:`~.evidence.pose_evidence` and the acceptance built on it.

    Args:
        max_log10_nfa: a pose is meaningful when its log10 NFA is below this: at most one false alarm in
            ``10^-max_log10_nfa`` pairs of random matches (a stated rate, not a tuned threshold).
        max_rotation_3sigma_deg: the largest three-sigma rotation uncertainty of an accepted pose estimated from the
            matches (°). Chosen on the tuning split of ``benchmarks.pose_protocol`` among 2° and 5° (the bound of a
            right pose), each run in full: 5° let three poses 13–26° off through at 60° where 2° let the search go
            on to a tier that found the right pose (benchmarks/history/pose.md).
        min_noise_px: the residuals' noise level is at least this (px): keypoints are located to no better than a
            tenth of a pixel, and exact synthetic matches would otherwise claim an exact pose.
        max_threshold_px: a residual above this (px) is no agreement at any threshold: the NFA's adaptive threshold
            stays within a few pose-stage thresholds (at a larger one, the matches near the true epipolar lines
            agree with any nearby pose better than chance does).
        max_matches: the uncertainty uses at most this many of the NFA's inliers (a fixed-seed sample).
        gric_lambda3: GRIC's bound on a residual's cost, in units of its degrees of freedom (Torr's 2).
        homography_threshold_px: the homography of the GRIC comparison is fitted by RANSAC with this threshold.
    """

    max_log10_nfa: float = -3.0
    max_rotation_3sigma_deg: float = 2.0
    min_noise_px: float = 0.1
    max_threshold_px: float = 4.0
    max_matches: int = 2000
    gric_lambda3: float = 2.0
    homography_threshold_px: float = 1.5


@dataclass
class ConfidenceConfig:
    """Thresholds of :func:`~.confidence.assess_pose`.

    Args:
        max_refit_rotation_deg: largest rotation change when the pose is re-fitted on its verified matches.
        focal_probe: relative focal-length change at which the pose is re-fitted (both directions).
        focal_scan: further focal factors at which the pose is re-fitted: a second minimum of the fit there (a
            rise within ``focal_tolerance``) counts with its rotation swing.
        focal_tolerance: relative rise of the median Sampson distance that the matches are taken to reject.
        focal_max_change: the largest focal change considered (ordinary cameras, 40–90° across the long side,
            lie within ±50 % of the 60° prior).
        max_focal_rotation_deg: largest rotation uncertainty left by an unknown focal length.
        min_parallax_to_rotation: smallest median parallax / rotation angle of a pose rotating more than
            ``parallax_check_above_deg`` (a pan of more than 30° with as little parallax is what a homography's
            matches give, not a camera that still sees the same scene).
        parallax_check_above_deg: the parallax check applies above this rotation (a handheld pan at small angles
            has as little parallax and is right).
        min_spread: smallest share of each photo covered by the verified matches' convex hull (0: not checked,
            only reported).
        max_matches: the fits use at most this many verified matches (a fixed-seed random sample).
        evidence_band_px: the matches of ``evidence`` within this Sampson distance of the pose are the fit set.
        min_evidence: fewer such matches than this and the verified matches are the fit set instead (the median of
            fewer residuals is too noisy to see a 10 % rise).
        min_refit_matches: the re-fit checks need at least this many verified matches (a fundamental matrix's
            eight).
        evidence: the a contrario test, the uncertainty and GRIC on the putative matches
            (:func:`~.evidence.pose_evidence`); None: off.
        min_rise: the residual rise is floored at this before the plausible focal change is extrapolated from it
            (no rise at all would claim any focal length fits).
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
    min_refit_matches: int = 8
    min_rise: float = 1e-3
    evidence: EvidenceConfig | None = field(default_factory=EvidenceConfig)


@dataclass
class PoseSearchConfig:
    """The search for the pose (:class:`~.search.PoseSearch`): descriptor tiers, plane tie-break, guided re-matching
    and the acceptance.

    Args:
        fallback_descriptors: when the primary descriptors verify fewer than ``fallback_min_inliers`` matches (or
            the pose fails), the descriptor → matching → pose chain runs again with these (affine-simulated SIFT:
            slower, but it matches across wide baselines); the result with more verified matches is kept. None: off.
        fallback_min_inliers: fewer verified matches than this and the fallback tier runs.
        wide_descriptors: the second fallback tier for wide baselines (affine SIFT with more tilts at a finer
            detection size), run only when the primary and fallback tiers both gave no pose. None: off.
        wide_min_inliers: the wide tier's pose needs this many verified matches (a handful at a wide baseline is a
            guess that guided matching would then "confirm").
        plane_tiebreak_margin: when the wide tier's pose fails, the plane's physical poses are ranked by dense
            consistency (:func:`~.tiebreak.plane_tiebreak`); the best must score this many times the next one's.
            None: off.
        plane_tiebreak_min: ...and at least this (guided matches it explains off the plane).
        plane_tiebreak_plane: the tie-break needs at least this many matches on the dominant plane...
        plane_tiebreak_plane_share: ...and this share of the matches (a "plane" of fewer gave a pose 11° off).
        plane_tiebreak_front: a decomposition that puts less than this share of the plane's matches in front of
            both cameras is not a physical pose.
        plane_tiebreak_off_plane: a guided match is off the plane when its transfer error exceeds this many pose
            thresholds (every candidate explains the plane's own matches: only the others are evidence).
        guided_band_px: after the first pose, all keypoints are matched again within this distance (px) of their
            epipolar lines (:func:`~..matching.guided_matches`) and the pose re-estimated; the result is kept if it
            verifies more matches. None: off.
        guided_ratio: the ratio test among the candidates in the band.
        guided_below: the guided re-matching is skipped when the first pose already has this many verified matches.
        guided_max_change_deg: a guided (or tie-break) pose that moved more than this (rotation, translation
            direction, °) from the pose that guided it is rejected: it refines a pose, it must not jump to another.
        confidence: the checks of the final pose independent of the RANSAC (:func:`~.confidence.assess_pose`);
            None: off (the pose stage's doubts and the support minimum still apply).
        accept_low_confidence: a pose with doubts is written anyway (a warning) instead of refused.
        learned: the learned tier (ALIKED + LightGlue, :mod:`..learned`), run after the SIFT tiers when their pose
            fails or its matches do not support it; None: off (``--matcher sift``; ``presets.configure`` sets it).
        learned_primary: the learned matcher is the primary (and only) tier (``--matcher aliked``): its weight
            files are then required.
    """

    fallback_descriptors: SiftConfig | None = field(
        default_factory=lambda: SiftConfig(affine=True, detect_size=512, max_keypoints=4000)
    )
    fallback_min_inliers: int = 100
    wide_descriptors: SiftConfig | None = field(
        default_factory=lambda: SiftConfig(affine=True, detect_size=640, max_keypoints=8000, max_tilt=4.0)
    )
    wide_min_inliers: int = 30
    plane_tiebreak_margin: float | None = 1.5
    plane_tiebreak_min: int = 100
    plane_tiebreak_plane: int = 30
    plane_tiebreak_plane_share: float = 0.5
    plane_tiebreak_front: float = 0.5
    plane_tiebreak_off_plane: float = 3.0
    guided_band_px: float | None = 2.0
    guided_ratio: float = 0.95
    guided_below: int = 1000
    guided_max_change_deg: tuple[float, float] = (3.0, 10.0)
    confidence: ConfidenceConfig | None = field(default_factory=ConfidenceConfig)
    accept_low_confidence: bool = False
    learned: LearnedConfig | None = None
    learned_primary: bool = False
