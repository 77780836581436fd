"""What the classical pose measured on the way (:func:`~.essential.estimate_pose`), for the report only.

One :class:`PoseDiagnostics` is filled in by the pose's steps (the focal's start and settlement, the RANSAC, the
plane's resolution, the final inliers, the plausibility checks); :meth:`PoseDiagnostics.as_dict` gives the report's
``pose`` keys, only those a step measured, in the order the steps measure them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

__all__ = ["PoseDiagnostics"]


@dataclass
class PoseDiagnostics:
    """The classical pose's measurements; None: the step that measures it did not run.

    Attributes:
        focal_search_scale, focal_search_defect: the focal's start (:func:`~.focal.initial_focal`): the factor on
            the prior's focal and the essential-matrix defect there.
        ransac_inliers: matches the RANSAC verified.
        focal_noise_px, focal_data_std, focal_scale_fitted: the refit with the focal (:func:`~.focal.settle_focal`):
            the residuals' noise (px), the log focal's data-only std, the fitted factor.
        focal_rotation_sensitivity_deg, focal_rotation_uncertainty_deg: the rotation's change per unit of log focal
            (°) and that times the focal's std (°).
        focal_axes_gap, focal_axes_asymmetry, focal_axes_angle_deg: where the optical axes meet, in baselines, and
            their angle (°) (:func:`~.focal.axes_geometry`).
        focal_observable: the matches determine the focal; focal_scale: the factor kept then.
        planar_candidates, planar_gated_support, planar_rival_inliers, planar_agreement_deg: the plane's poses
            (:func:`~.planar.planar_pose`): how many, each one's support on the gated matches (comma-separated),
            the best rival's, and how far the essential pose is from the nearest decomposition (°).
        planar_support, planar_evidence, planar_counter_evidence, planar_matches_scored: the duel on all the matches
            (:func:`~.planar.resolve_planar`), when several poses contended.
        planar_resolved: ``"essential"`` or ``"homography"``: whose pose won.
        inliers, inlier_ratio, median_sampson_px, rotation_deg: the final verified matches, their share of the
            matches, their median Sampson distance (px), the rotation angle (°).
        flipped_triangles: share of the small triangles that flip orientation (:func:`~.checks.flipped_fraction`).
        homography_inliers: matches the dominant homography explains.
    """

    focal_search_scale: float | None = None
    focal_search_defect: float | None = None
    ransac_inliers: int | None = None
    focal_noise_px: float | None = None
    focal_data_std: float | None = None
    focal_scale_fitted: float | None = None
    focal_rotation_sensitivity_deg: float | None = None
    focal_rotation_uncertainty_deg: float | None = None
    focal_axes_gap: float | None = None
    focal_axes_asymmetry: float | None = None
    focal_axes_angle_deg: float | None = None
    focal_observable: bool | None = None
    focal_scale: float | None = None
    planar_candidates: int | None = None
    planar_gated_support: str | None = None
    planar_rival_inliers: int | None = None
    planar_agreement_deg: float | None = None
    planar_support: str | None = None
    planar_evidence: int | None = None
    planar_counter_evidence: int | None = None
    planar_matches_scored: int | None = None
    planar_resolved: str | None = None
    inliers: int | None = None
    inlier_ratio: float | None = None
    median_sampson_px: float | None = None
    rotation_deg: float | None = None
    flipped_triangles: float | None = None
    homography_inliers: int | None = None

    def as_dict(self) -> dict[str, float | int | str | bool]:
        """The measured values by name, in the order the pose's steps measure them (the report's ``pose`` keys)."""
        return {f.name: v for f in dataclasses.fields(self) if (v := getattr(self, f.name)) is not None}
