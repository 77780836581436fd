"""Stage 4, the relative pose of the two views: one package, one module per idea.

==================  ===========================================================================================
module              what it holds
==================  ===========================================================================================
``config``          :class:`PoseConfig`, :class:`PoseSearchConfig`, the constants several modules share
``diagnostics``     :class:`PoseDiagnostics`: what the classical pose measured, for the report
``geometry``        epipolar constraint, Sampson distance, triangulation, cheirality, decompositions
``robust``          OpenCV's MAGSAC++ estimators within their preconditions (essential, fundamental, homography)
``refit``           the one non-linear refit of (R, t[, focal]): LM on Cauchy-weighted Sampson distances
``focal``           self-calibration of a view with the prior's focal
``planar``          a plane's two poses told apart by all the matches
``checks``          degenerate matches, too few inliers, no baseline, mirror images
``essential``       :func:`estimate_pose`, the classical pose (the ``pose`` slot's default)
``pnp``             :func:`pose_from_pointmap`, the neural backend's pose from a point map
``evidence``        :func:`pose_evidence`: the a contrario test (NFA), the pose's uncertainty, GRIC, on the putative
                    matches
``confidence``      :func:`assess_pose`, :func:`accept_pose`: the acceptance of any backend's pose
``tiebreak``        the plane tie-break of the wide-baseline tier
``search``          :class:`PoseSearch`: the tiers, guided re-matching and acceptance as one stage object
``result``          :class:`PoseResult`, :class:`PoseConfidence`, :class:`Doubt`: what the stage hands on
==================  ===========================================================================================

Conventions: ``X_cam1 = R · X_cam0 + t``, ``|t| = 1`` (relative scale) for the classical pose; pixels at the
working resolution, centres at +0.5. Every failure is a :class:`~macsplat_cli.errors.ReconstructionError` whose
message says why; no ``cv2.error`` leaves the package. Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

from .checks import flipped_fraction
from .confidence import accept_pose, assess_pose
from .config import FALLBACK_SIFT, WIDE_SIFT, PoseConfig, PoseSearchConfig
from .diagnostics import PoseDiagnostics
from .essential import estimate_pose
from .evidence import PoseEvidence, pose_evidence
from .geometry import epipolar_fit, fundamental_from_pose, sampson_distance, triangulate
from .pnp import PnPResult, pose_from_pointmap
from .refit import Refit, refit_pose
from .result import Doubt, PoseConfidence, PoseResult, Tier
from .robust import find_homography
from .search import LOW_CONFIDENCE_HINT, PoseSearch, StageTimer
from .tiebreak import PlanePose, dominant_plane, plane_poses, tiebreak_plane_ok, tiebreak_winner_ok

__all__ = [
    "LOW_CONFIDENCE_HINT",
    "Doubt",
    "FALLBACK_SIFT",
    "PlanePose",
    "PnPResult",
    "PoseConfidence",
    "PoseConfig",
    "PoseDiagnostics",
    "PoseEvidence",
    "PoseResult",
    "PoseSearch",
    "PoseSearchConfig",
    "Refit",
    "StageTimer",
    "WIDE_SIFT",
    "Tier",
    "accept_pose",
    "assess_pose",
    "dominant_plane",
    "epipolar_fit",
    "estimate_pose",
    "find_homography",
    "flipped_fraction",
    "fundamental_from_pose",
    "plane_poses",
    "pose_evidence",
    "pose_from_pointmap",
    "refit_pose",
    "sampson_distance",
    "tiebreak_plane_ok",
    "tiebreak_winner_ok",
    "triangulate",
]
