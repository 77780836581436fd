"""The classical two-view pose: robust essential matrix, cheirality, non-linear refinement, self-calibration, the
planar resolution and the pose's own checks (the ``pose`` slot's default backend).

1. Geometric verification: MAGSAC++ on the filtered matches in one virtual camera (:func:`~.robust.essential_pose`).
2. Cheirality: of the four decompositions of E, the one that puts the most points in front of both cameras.
3. Refinement: Levenberg–Marquardt on the Sampson distances with Cauchy weights (:mod:`.refit`).
4. Focal length of a view with the prior's intrinsics (:mod:`.focal`).
5. Planar scenes (:mod:`.planar`).
6. Degeneracies and an unreliable pose raise :class:`~macsplat_cli.errors.ReconstructionError` (:mod:`.checks`,
   and here: mirror images, a homography that explains clearly more matches than the pose).

Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ...camera_math import scale_focal
from ...errors import ReconstructionError
from ..types import Matches, TwoViewGeometry, View
from .checks import check_finite, check_matches, final_inliers, flipped_fraction, summarise
from .config import HOMOGRAPHY_FACTOR, RANSAC_MAX_ITERS, PoseConfig
from .diagnostics import PoseDiagnostics
from .focal import focal_fit, initial_focal, refine_at_prior, settle_focal
from .planar import planar_pose
from .refit import POSE_LM, refit_pose
from .robust import essential_pose, find_homography

__all__ = ["at_working_size", "estimate_pose"]

logger = logging.getLogger(__name__)

REFERENCE_SIDE = 512
"""Working long side (px) at which the pixel thresholds apply as given: keypoints come from a photo of up to 768
px, so a smaller working image has proportionally more precise ones."""
PLANAR_FRACTION = 0.8
"""A homography explaining this fraction of the verified matches makes the pair planar (:mod:`.planar`)."""
HOMOGRAPHY_EXCESS = 1.2
"""The pose is rejected when a homography explains more than this many times its inliers (plus
:data:`HOMOGRAPHY_SLACK`): impossible for a correct pose, since a plane's points fit it too."""
HOMOGRAPHY_SLACK = 10
"""Matches a homography may explain beyond :data:`HOMOGRAPHY_EXCESS` times the pose's inliers (a few off-plane
matches count for either on a small set)."""
MAX_FLIPPED = 0.5
"""The pair is refused as mirror images when more than this share of the small triangles between neighbouring
verified matches flips orientation (:func:`~.checks.flipped_fraction`)."""


def at_working_size(cfg: PoseConfig, v0: View, v1: View) -> PoseConfig:
    """``cfg`` with its pixel thresholds shrunk for a working image smaller than :data:`REFERENCE_SIDE` (and than the
    photos): keypoints are detected on the photo, so a photo shrunk further to a small working size has keypoints
    proportionally more precise in its pixels (with 1 px at 64 px every match fit a plane both ways). A small photo
    used at its own size keeps them."""
    side = max(v0.width, v0.height, v1.width, v1.height)
    ref = min(REFERENCE_SIDE, max(*v0.original_size, *v1.original_size))
    if side < ref:
        return dataclasses.replace(cfg, threshold_px=cfg.threshold_px * side / ref)
    return cfg


def _verified_pose(
    xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool], diag: PoseDiagnostics,
    cfg: PoseConfig,
) -> tuple[np.ndarray, np.ndarray, float, bool, list[str]]:  # fmt: skip
    """The verified and refined pose, with the focal self-calibrated where ``unknown``.

    Returns:
        ``(R, t, log_focal, with_focal, doubts)``: the pose, the log focal scale of the unknown views (0: the
        prior's), whether the focal was estimated at all, and the doubts the focal raises.
    """
    s = 0.0
    with_focal = cfg.estimate_focal and any(unknown)
    if with_focal:
        start = initial_focal(xy0, xy1, K0, K1, unknown, diag, cfg)
        if start is None:
            with_focal = False
        else:
            s = start
    R, t, good = essential_pose(xy0, xy1, K0, K1, unknown, s, cfg)
    n_ransac = int(good.sum())
    diag.ransac_inliers = n_ransac
    if n_ransac < cfg.min_inliers:
        raise ReconstructionError(
            f"pose could not be estimated: {n_ransac} verified matches, need at least {cfg.min_inliers}"
        )
    doubts: list[str] = []
    if cfg.refine:
        fit = refit_pose(
            R, t, K0, K1, xy0[good], xy1[good], scale_px=cfg.threshold_px, schedule=POSE_LM, log_focal=s,
            unknown=unknown, focal=focal_fit(cfg) if with_focal else None,
        )  # fmt: skip
        R, t = fit.R, fit.t
        if with_focal:
            outcome = settle_focal(fit, xy0[good], xy1[good], K0, K1, unknown, diag, cfg)
            s, doubts = outcome.log_focal, outcome.doubts
            if not outcome.observable:  # the matches do not determine the focal length: the prior's pose
                R, t = refine_at_prior(xy0, xy1, K0, K1, unknown, cfg)
    return R, t, s, with_focal, doubts


def estimate_pose(v0: View, v1: View, matches: Matches, config: PoseConfig | None = None) -> TwoViewGeometry:
    """Relative pose of ``v1`` with respect to ``v0`` from filtered matches (module docstring).

    Returns:
        :class:`TwoViewGeometry` with unit-norm ``t``, the verified matches (``counts`` gains ``verified``),
        possibly self-calibrated intrinsics (``focal_estimated``), the doubts, and diagnostics for the report.

    Raises:
        NonFiniteError: a match coordinate or an intrinsic matrix holds NaN/Inf.
        ReconstructionError: too few matches or inliers, identical images, no baseline, mirror images, an
            unreliable or ambiguous pose.
    """
    cfg = at_working_size(config or PoseConfig(), v0, v1)
    check_finite(v0, v1, matches)
    xy0, xy1 = matches.xy0.astype(np.float64), matches.xy1.astype(np.float64)
    check_matches(v0, v1, xy0, xy1, cfg)
    unknown = (v0.intrinsics_source == "prior", v1.intrinsics_source == "prior")
    K0, K1 = v0.K.copy(), v1.K.copy()
    diag = PoseDiagnostics()
    R, t, s, with_focal, doubts = _verified_pose(xy0, xy1, K0, K1, unknown, diag, cfg)
    K0s = scale_focal(K0, s) if unknown[0] else K0
    K1s = scale_focal(K1, s) if unknown[1] else K1

    final, d, X, x0n, x1n = final_inliers(R, t, K0s, K1s, xy0, xy1, cfg)
    H, hmask = find_homography(xy0, xy1, HOMOGRAPHY_FACTOR * cfg.threshold_px, RANSAC_MAX_ITERS)
    n_h = int(hmask.sum()) if H is not None and hmask is not None else 0
    if H is not None and n_h >= max(PLANAR_FRACTION * int(final.sum()), cfg.min_inliers):
        # the plane dominates: its two poses, and the essential matrix's, compete on all the evidence
        R, t, refined = planar_pose(
            R, t, H, log_focal=s, K0=K0, K1=K1, unknown=unknown, xy0=xy0, xy1=xy1, below_gate=matches.below_gate,
            diag=diag, cfg=cfg,
        )  # fmt: skip
        if refined:
            final, d, X, x0n, x1n = final_inliers(R, t, K0s, K1s, xy0, xy1, cfg)
    n_final, parallax = summarise(R, final, d, x0n, x1n, len(matches), diag, cfg)
    _check_plausible(xy0, xy1, final, X, n_h, n_final, diag)
    logger.debug("pose: %s", diag)
    return TwoViewGeometry(
        R=R, t=t, K0=K0s, K1=K1s, inliers=matches.subset(final, "verified"), diagnostics=diag.as_dict(), doubts=doubts,
        focal_estimated=bool(with_focal and s != 0.0), median_parallax_deg=parallax,
    )  # fmt: skip


def _check_plausible(
    xy0: np.ndarray, xy1: np.ndarray, final: np.ndarray, X: np.ndarray, n_h: int, n_final: int, diag: PoseDiagnostics
) -> None:
    """Refuse mirror images (the ``final`` inliers' triangles, at the triangulated points ``X`` [M, 3]) and a pose
    that a homography's ``n_h`` matches outnumber; record the measurements in ``diag``.

    Raises:
        ReconstructionError: with the reason.
    """
    flipped = flipped_fraction(xy0[final], xy1[final], X[final, 2])
    diag.flipped_triangles = flipped
    if flipped > MAX_FLIPPED:
        raise ReconstructionError(
            f"the photos are mirror images of each other: {100 * flipped:.0f} % of the small triangles between "
            f"neighbouring verified matches are flipped in the second photo, which no camera motion does "
            "(a mirrored or flipped copy?)"
        )
    diag.homography_inliers = n_h
    if n_h > HOMOGRAPHY_EXCESS * n_final + HOMOGRAPHY_SLACK:
        raise ReconstructionError(
            f"pose is unreliable: a homography explains {n_h} matches but the relative pose only {n_final} "
            "(the matches lie on one plane, or the pose is wrong)"
        )
