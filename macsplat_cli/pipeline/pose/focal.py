"""Self-calibration of a view whose intrinsics come only from the field-of-view prior.

A fundamental matrix is fitted first (it needs no intrinsics); the focal scale that makes ``K1ᵀ F K0`` closest
to an essential matrix initialises it (Mendonça–Cipolla), and the refit (:mod:`.refit`) refines it with the pose
under a log-normal prior. The estimate replaces the prior only if the matches pin it down: its data-only standard
deviation is below ``FOCAL_MAX_STD`` and that std times the rotation's sensitivity to the focal is below
``FOCAL_MAX_ROTATION_DEG``. Object-centric pairs (both optical axes through one point at equal distances, Sturm's
critical configuration) are the classic case where they do not; then the prior is kept and, when the pose depends
on the focal, a doubt is recorded. Measured: benchmarks/history/pose.md.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ...camera_math import scale_focal
from ...metrics import rotation_angle_deg
from .config import PoseConfig
from .diagnostics import PoseDiagnostics
from .refit import POSE_LM, SENSITIVITY_LM, FocalFit, Refit, refit_pose
from .robust import essential_pose, find_fundamental

__all__ = [
    "FocalOutcome",
    "axes_geometry",
    "focal_fit",
    "focal_rotation_sensitivity",
    "focal_search",
    "initial_focal",
    "refine_at_prior",
    "settle_focal",
]

logger = logging.getLogger(__name__)

FOCAL_PRIOR_SIGMA = 0.5
"""Std of the log focal prior (0.5 ≈ ×/÷ 1.65)."""
FOCAL_MAX_STD = 0.05
"""Largest data-only std of the log focal for the estimate to be used (computed with the residuals' robust noise
level, 1.4826·MAD)."""
FOCAL_MAX_ROTATION_DEG = 0.25
"""The self-calibrated focal is used only if its data-only std times the rotation's sensitivity to the focal stays
below this (°); else the prior is kept and, when the prior's std times that sensitivity exceeds it too, a doubt is
recorded."""
FOCAL_SEARCH_RANGE = (0.4, 2.5)
"""The focal factors over which the essential-matrix defect is searched (ordinary cameras, 20–120° across the long
side, lie within it around the 60° prior)."""
FOCAL_SEARCH_STEPS = 121
"""Grid points of that search (log-spaced: 0.8 % apart)."""
FOCAL_NOISE_FLOOR_PX = 0.02
"""The residuals' noise level used for the focal's data-only std is at least this (px): exact synthetic matches
would claim a perfect focal."""
FOCAL_SENSITIVITY_STEP = 0.1
"""The log-focal step (±) at which the rotation's sensitivity to the focal is measured."""
OBJECT_AXES_GAP = 0.1
"""The doubt names an object-centric pair when the optical axes pass within this many baselines of each other..."""
OBJECT_AXES_ASYMMETRY = 0.3
"""...and their closest points' distances from the two cameras differ by less than this many baselines."""


def focal_search(
    F: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool], cfg: PoseConfig
) -> tuple[float, float]:
    """Focal log-scale ``s`` minimising the essential-matrix defect (σ1 − σ2)/σ1 of Kᵀ F K, on a log grid over
    ``FOCAL_SEARCH_RANGE``. Returns ``(s, defect)``."""
    lo, hi = FOCAL_SEARCH_RANGE
    grid = np.linspace(math.log(lo), math.log(hi), FOCAL_SEARCH_STEPS)
    costs = []
    for s in grid:
        K0s = scale_focal(K0, s) if unknown[0] else K0
        K1s = scale_focal(K1, s) if unknown[1] else K1
        E = K1s.T @ F @ K0s
        sv = np.linalg.svd(E, compute_uv=False)
        costs.append((sv[0] - sv[1]) / max(sv[0], 1e-30))
    k = int(np.argmin(costs))
    return float(grid[k]), float(costs[k])


def initial_focal(
    xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool], diag: PoseDiagnostics,
    cfg: PoseConfig,
) -> float | None:  # fmt: skip
    """The starting log focal scale from a fundamental matrix of the matches (recorded in ``diag``), or None when
    no fundamental matrix with ``min_inliers`` inliers fits (the focal is then not estimated)."""
    F, fmask = find_fundamental(xy0, xy1, cfg)
    if F is None or F.shape != (3, 3) or fmask is None or int(fmask.sum()) < cfg.min_inliers:
        return None
    s, defect = focal_search(F, K0, K1, unknown, cfg)
    diag.focal_search_scale = math.exp(s)
    diag.focal_search_defect = defect
    return s


def focal_rotation_sensitivity(
    R: np.ndarray, t: np.ndarray, s: float, xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
    unknown: tuple[bool, bool], cfg: PoseConfig,
) -> float:  # fmt: skip
    """Degrees the refined rotation moves per unit of log focal: the pose refitted with the focal scaled by
    ``exp(±focal_sensitivity_step)``. About the angle between the views for cameras that look at one point (an
    orbit), ~0 for a sideways translation without rotation (a rectified stereo pair), whose pose no focal changes."""
    step = FOCAL_SENSITIVITY_STEP
    moves = []
    for ds in (-step, step):
        fit = refit_pose(
            R, t, K0, K1, xy0, xy1, scale_px=cfg.threshold_px, schedule=SENSITIVITY_LM, log_focal=s + ds,
            unknown=unknown,
        )  # fmt: skip
        moves.append(rotation_angle_deg(fit.R @ R.T))
    return max(moves) / step


def axes_geometry(R: np.ndarray, t: np.ndarray) -> dict[str, float]:
    """Where the two optical axes meet, relative to the baseline: ``focal_axes_gap`` (their distance) and
    ``focal_axes_asymmetry`` (the difference of the distances from each centre to their closest points). Both
    near 0 (axes meeting at a point equidistant from the cameras, as when photographing an object) is the
    configuration where two views cannot fix a shared focal length (Sturm, 2001); parallel axes too."""
    c1 = -R.T @ t
    base = float(np.linalg.norm(c1))
    a, b = np.array([0.0, 0.0, 1.0]), R[2]
    cos = float(a @ b)
    den = 1.0 - cos**2
    if den < 1e-9 or base < 1e-12:
        return {"focal_axes_gap": math.inf, "focal_axes_asymmetry": math.inf, "focal_axes_angle_deg": 0.0}
    d, e = float(a @ c1), float(b @ c1)
    u0 = (d - cos * e) / den  # along axis 0 from camera 0
    u1 = (cos * d - e) / den  # along axis 1 from camera 1
    gap = float(np.linalg.norm(u0 * a - (c1 + u1 * b))) / base
    return {
        "focal_axes_gap": gap,
        "focal_axes_asymmetry": abs(u0 - u1) / base,
        "focal_axes_angle_deg": math.degrees(math.acos(max(-1.0, min(1.0, cos)))),
    }


FOCAL_DOUBT_START = "the focal length cannot be determined"
"""How the pose stage's doubt about an unobservable focal length begins (:mod:`..multiview` leaves such a pair's
focal to the bundle adjustment of more photos)."""


def _focal_doubt(axes: dict[str, float], cfg: PoseConfig) -> str:
    looking = axes["focal_axes_gap"] < OBJECT_AXES_GAP and axes["focal_axes_asymmetry"] < OBJECT_AXES_ASYMMETRY
    why = " (both cameras look at the same point, as when photographing an object)" if looking else ""
    return (
        f"{FOCAL_DOUBT_START} from these two photos{why}, and the pose depends on it: "
        "give --focal, --intrinsics or photos with EXIF"
    )


@dataclass
class FocalOutcome:
    """The focal decision: whether the matches determine the focal, the log focal scale kept (0: the prior's),
    and the doubts it raises."""

    observable: bool
    log_focal: float
    doubts: list[str] = field(default_factory=list)


def settle_focal(
    fit: Refit, xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool],
    diag: PoseDiagnostics, cfg: PoseConfig,
) -> FocalOutcome:  # fmt: skip
    """Keep the focal that the refit ``fit`` estimated with the pose on the verified matches ``xy0, xy1`` [M, 2],
    or the prior's.

    The estimate is kept when its data-only std is at most ``FOCAL_MAX_STD`` and the rotation uncertainty it leaves
    (the std times the rotation's sensitivity to the focal) at most ``FOCAL_MAX_ROTATION_DEG``; otherwise a doubt is
    raised when the prior's std (or the estimate's) times that sensitivity exceeds the limit. The measurements go
    to ``diag``.
    """
    R, t, s_new, std_s = fit.R, fit.t, fit.log_focal, fit.log_focal_std
    if fit.noise_px is not None:
        diag.focal_noise_px = fit.noise_px
    diag.focal_data_std = std_s
    diag.focal_scale_fitted = math.exp(s_new)
    determined = std_s <= FOCAL_MAX_STD
    # how far the rotation moves per unit of log focal, times how uncertain the focal is: the rotation error the
    # unknown focal may cause
    s_at = s_new if determined else 0.0
    sens = focal_rotation_sensitivity(R, t, s_at, xy0, xy1, K0, K1, unknown, cfg)
    spread = sens * (std_s if determined else FOCAL_PRIOR_SIGMA)
    axes = axes_geometry(R, t)
    diag.focal_rotation_sensitivity_deg, diag.focal_rotation_uncertainty_deg = sens, spread
    diag.focal_axes_gap, diag.focal_axes_asymmetry = axes["focal_axes_gap"], axes["focal_axes_asymmetry"]
    diag.focal_axes_angle_deg = axes["focal_axes_angle_deg"]
    observable = determined and spread <= FOCAL_MAX_ROTATION_DEG
    diag.focal_observable = observable
    doubts = [_focal_doubt(axes, cfg)] if not observable and spread > FOCAL_MAX_ROTATION_DEG else []
    if observable:
        diag.focal_scale = math.exp(s_new)
        return FocalOutcome(True, s_new, doubts)
    logger.debug(
        "focal not determined by the matches (std %.3f, rotation uncertainty %.2f°); keeping the prior", std_s, spread
    )
    return FocalOutcome(False, 0.0, doubts)


def refine_at_prior(
    xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool], cfg: PoseConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The pose verified and refined at the prior's focal, on all the matches ``xy0, xy1`` [M, 2]."""
    R, t, good = essential_pose(xy0, xy1, K0, K1, unknown, 0.0, cfg)
    fit = refit_pose(
        R, t, K0, K1, xy0[good], xy1[good], scale_px=cfg.threshold_px, schedule=POSE_LM, unknown=unknown
    )  # fmt: skip
    return fit.R, fit.t


def focal_fit(cfg: PoseConfig) -> FocalFit:
    """The refit's focal prior of ``cfg``."""
    return FocalFit(FOCAL_PRIOR_SIGMA, FOCAL_NOISE_FLOOR_PX)
