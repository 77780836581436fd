"""The evidence for a relative pose that the pose did not choose: an a contrario test, the pose's own uncertainty, and
model selection between the epipolar geometry and a homography.

All three are measured on the **putative matches gathered before the pose was known** (the filtered matches of the
descriptor tier that produced it), never on matches guided by the pose, which agree with whichever pose guides them.

* **Number of false alarms** (a contrario model validation, Moisan & Stival 2004; ORSA / AC-RANSAC as in Moulon et
  al. 2012). Under the background model, the ``n`` putative matches are independent and uniformly spread over the
  photos, so a match lies within ``ε`` px of an epipolar line with probability at most ``α(ε) = 2 ε D / A``
  (``D`` the photo's diagonal, ``A`` its area; the larger of the two photos' ratios). A pose explaining ``k`` of
  them within ``ε`` has ``NFA(k, ε) = N_out (n − s) C(n, k) C(k, s) α(ε)^(k − s)``: the expected number of poses
  that would do as well by chance among all those a minimal-sample search could test (``s`` matches per sample,
  ``N_out`` models per sample: 5 and 10 for the essential matrix, 7 and 3 when a focal length is estimated too).
  ``ε`` is chosen by the NFA itself (the residuals sorted, the ``k`` that minimises it), up to
  ``MAX_THRESHOLD_PX``. A pose is meaningful when ``NFA < 10^MAX_LOG10_NFA``: under the background model, fewer than
  that many accepted poses per pair are false alarms. Matches behind either camera never count as explained.
* **Uncertainty**: the covariance of the pose's parameters (rotation 3, translation direction 2, and the log focal
  scale of views whose focal length only the matches can tell) from the Gauss–Newton Jacobian of the Sampson
  distances of the NFA's inliers, scaled by their robust variance: ``σ² (JᵀJ)⁻¹``. The rotation's standard
  deviation is the square root of the largest eigenvalue of its block. Small or flat support, a near-degenerate
  configuration and an unobservable focal length all make it large. It is a gate for gross cases, not an error bar:
  right poses are often several σ off the truth (systematic error).
* **GRIC** (Torr 1998): the geometric robust information criterion of the epipolar model and of a homography on the
  putative matches, at the same noise level. When the homography's is lower, the support is near-planar, and the
  matches off the plane get their own NFA. Both are reported, not gated: a rule that tightened the uncertainty
  bound for such a support was measured worse on the tuning split (benchmarks/history/pose.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..types import Matches, TwoViewGeometry, View
from .geometry import epipolar_fit, fundamental_from_pose, homog, hull_share, sampson_distance
from .refit import MAD_TO_STD, pose_jacobian
from .robust import distinct_matches

__all__ = ["PoseEvidence", "epipolar_nfa", "fundamental_residuals", "log10_nfa", "pose_evidence"]

ESSENTIAL_SAMPLE = (5, 10)
"""The essential matrix's minimal sample and the most models one sample gives (the five-point solver)."""
FOCAL_SAMPLE = (7, 3)
"""With a focal length estimated as well: the fundamental matrix's (the seven-point solver), an upper bound."""
HOMOGRAPHY_SAMPLE = (4, 1)
"""A homography's minimal sample and models per sample."""
MIN_NOISE_PX = 0.1
"""The residuals' noise level is at least this (px): keypoints are located to no better than a tenth of a pixel,
and exact synthetic matches would otherwise claim an exact pose."""
MAX_THRESHOLD_PX = 4.0
"""A residual above this (px) is no agreement at any threshold: the NFA's adaptive threshold stays within a few
pose-stage thresholds (at a larger one, the matches near the true epipolar lines agree with any nearby pose better
than chance does)."""
MAX_MATCHES = 2000
"""The uncertainty uses at most this many of the NFA's inliers (a fixed-seed sample)."""
GRIC_LAMBDA3 = 2.0
"""GRIC's bound on a residual's cost, in units of its degrees of freedom (Torr's 2)."""
HOMOGRAPHY_THRESHOLD_PX = 1.5
"""The homography of the GRIC comparison is fitted by RANSAC with this threshold (px)."""


@dataclass
class PoseEvidence:
    """What :func:`pose_evidence` measured.

    Attributes:
        putative: distinct putative matches the test ran on.
        log10_nfa: the pose's log10 number of false alarms (``inf``: too few matches for a test).
        inliers: the matches within the NFA's threshold and in front of both cameras.
        threshold_px: the NFA's adaptive residual threshold (symmetric epipolar distance, px).
        coverage: the share of each photo that the inliers' convex hull covers (the smaller).
        noise_px: the inliers' robust residual level (Sampson distance, px), floored at ``MIN_NOISE_PX``.
        rotation_sigma_deg: the rotation's standard deviation (°; ``inf``: undetermined).
        translation_sigma_deg: the translation direction's standard deviation (°).
        focal_free: the log focal scale was a free parameter of the uncertainty.
        gric_epipolar: GRIC of the epipolar model on the putative matches.
        gric_homography: GRIC of the best homography (``inf``: none could be fitted).
        plane_share: the share of the putative matches the homography explains.
        off_plane: putative matches off that plane.
        off_plane_log10_nfa: the pose's log10 NFA on those alone.
    """

    putative: int
    log10_nfa: float
    inliers: int
    threshold_px: float
    coverage: float
    noise_px: float
    rotation_sigma_deg: float
    translation_sigma_deg: float
    focal_free: bool
    gric_epipolar: float
    gric_homography: float
    plane_share: float
    off_plane: int
    off_plane_log10_nfa: float

    @property
    def planar(self) -> bool:
        """GRIC prefers the homography: the support is near-planar."""
        return self.gric_homography < self.gric_epipolar

    def checks(self) -> dict[str, float]:
        """The measurements, for the report's ``confidence_checks``."""
        return {
            "putative_matches": float(self.putative),
            "log10_nfa": self.log10_nfa,
            "nfa_inliers": float(self.inliers),
            "nfa_threshold_px": self.threshold_px,
            "coverage": self.coverage,
            "residual_noise_px": self.noise_px,
            "rotation_sigma_deg": self.rotation_sigma_deg,
            "translation_sigma_deg": self.translation_sigma_deg,
            "gric_epipolar": self.gric_epipolar,
            "gric_homography": self.gric_homography,
            "plane_share": self.plane_share,
            "off_plane_matches": float(self.off_plane),
            "off_plane_log10_nfa": self.off_plane_log10_nfa,
        }


# ============================================================================================== the NFA
def _log10_factorials(n: int) -> np.ndarray:
    """``log10(k!)`` for k = 0..n. [n + 1]"""
    return np.concatenate([[0.0], np.cumsum(np.log10(np.arange(1, n + 1, dtype=np.float64)))])


def log10_nfa(
    residuals: np.ndarray, alpha_coef: float, alpha_power: int, sample: tuple[int, int], *, min_residual: float = 0.0
) -> tuple[float, int, float]:
    """The smallest log10 NFA of a model over its residual threshold (module docstring).

    Args:
        residuals: each putative match's residual to the model (px; ``inf``: not explained at any threshold). [n]
        alpha_coef, alpha_power: the background probability of a residual below ``ε`` is
            ``min(1, alpha_coef · ε^alpha_power)``.
        sample: ``(s, N_out)``: the minimal sample size and the models per sample.
        min_residual: residuals are floored at this (px) before ``α`` is taken.

    Returns:
        ``(log10 NFA, k, ε)``: the minimum, its inlier count and threshold; ``(inf, 0, nan)`` with ``n ≤ s``.
    """
    s, n_out = sample
    r = np.sort(np.asarray(residuals, np.float64))
    n = len(r)
    k = np.arange(s + 1, n + 1)
    if len(k) == 0:
        return math.inf, 0, math.nan
    eps = np.maximum(r[k - 1], min_residual)
    finite = np.isfinite(eps)
    if not finite.any():
        return math.inf, 0, math.nan
    k, eps = k[finite], eps[finite]
    lf = _log10_factorials(n)
    log_alpha = np.minimum(np.log10(alpha_coef) + alpha_power * np.log10(np.maximum(eps, 1e-300)), 0.0)
    value = (
        math.log10(n_out) + math.log10(n - s)
        + (lf[n] - lf[k] - lf[n - k]) + (lf[k] - lf[s] - lf[k - s])
        + (k - s) * log_alpha
    )  # fmt: skip
    i = int(np.argmin(value))
    return float(value[i]), int(k[i]), float(eps[i])


def _line_alpha(v0: View, v1: View) -> float:
    """``α(ε) / ε`` for an epipolar line: ``2 D / A``, the larger of the two photos'."""
    return max(2.0 * math.hypot(v.width, v.height) / float(v.width * v.height) for v in (v0, v1))


def _epipolar_residuals(g: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance (the larger of the two point-to-line distances, px); ``inf`` for a match that
    triangulates behind a camera. [M]"""
    F = fundamental_from_pose(g.R, g.t, g.K0, g.K1)
    p0, p1 = homog(xy0), homog(xy1)
    l1 = p0 @ F.T  # lines in view 1
    l0 = p1 @ F  # lines in view 0
    e = np.abs(np.sum(p1 * l1, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.maximum(e / np.hypot(l1[:, 0], l1[:, 1]), e / np.hypot(l0[:, 0], l0[:, 1]))
    _, front = epipolar_fit(g.R, g.t, g.K0, g.K1, xy0, xy1)
    return np.where(front & np.isfinite(d), d, np.inf)


def epipolar_nfa(
    v0: View, v1: View, geometry: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray, unknown: tuple[bool, bool]
) -> tuple[float, int, float, np.ndarray]:
    """The pose's smallest log10 NFA on the distinct putative matches ``xy0, xy1`` [M, 2] (module docstring).

    Returns:
        ``(log10 NFA, k, ε, residuals [M])``: as :func:`log10_nfa`, and each match's symmetric epipolar distance
        (``inf``: behind a camera, or farther than :data:`MAX_THRESHOLD_PX`).
    """
    res = _epipolar_residuals(geometry, xy0, xy1) if len(xy0) else np.zeros(0)
    res = np.where(res <= MAX_THRESHOLD_PX, res, np.inf)
    sample = FOCAL_SAMPLE if any(unknown) else ESSENTIAL_SAMPLE
    nfa, k, eps = log10_nfa(res, _line_alpha(v0, v1), 1, sample, min_residual=MIN_NOISE_PX)
    return nfa, k, eps, res


# ============================================================================================== uncertainty
def _uncertainty(
    g: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray, unknown: tuple[bool, bool]
) -> tuple[float, float, float]:
    """``(noise px, rotation σ °, translation direction σ °)`` of the pose on the matches ``xy0, xy1`` [M, 2]."""
    if len(xy0) > MAX_MATCHES:
        keep = np.sort(np.random.default_rng(0).choice(len(xy0), MAX_MATCHES, replace=False))
        xy0, xy1 = xy0[keep], xy1[keep]
    n_par = 6 if any(unknown) else 5
    if len(xy0) <= n_par:
        return math.nan, math.inf, math.inf
    J = pose_jacobian(g.R, g.t, g.K0, g.K1, xy0, xy1, unknown=unknown, n_par=n_par)
    r = np.abs(fundamental_residuals(g, xy0, xy1))
    noise = max(MAD_TO_STD * float(np.median(r)), MIN_NOISE_PX)
    try:
        cov = noise**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return noise, math.inf, math.inf

    def sigma_deg(block: np.ndarray) -> float:
        top = float(np.max(np.linalg.eigvalsh(block)))
        return math.degrees(math.sqrt(top)) if math.isfinite(top) and top >= 0 else math.inf

    return noise, sigma_deg(cov[:3, :3]), sigma_deg(cov[3:5, 3:5])


def fundamental_residuals(g: TwoViewGeometry, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Signed Sampson distances of ``xy0, xy1`` [M, 2] to the pose ``g`` (px). [M]"""
    return sampson_distance(fundamental_from_pose(g.R, g.t, g.K0, g.K1), xy0, xy1)


# ============================================================================================== GRIC
def _gric(e2: np.ndarray, noise: float, d: int, k: int, lambda3: float) -> float:
    """Torr's GRIC of a model of dimension ``d`` with ``k`` parameters, squared residuals ``e2`` [n] (data
    dimension 4: two image points)."""
    n = len(e2)
    rho = np.minimum(e2 / noise**2, lambda3 * (4 - d))
    return float(np.sum(rho) + math.log(4.0) * d * n + math.log(4.0 * max(n, 1)) * k)


def _homography_residuals(xy0: np.ndarray, xy1: np.ndarray, threshold: float) -> np.ndarray | None:
    """Squared 4-D residuals of the best RANSAC homography (the forward and backward transfer errors' mean over
    two: each transfer error carries both points' noise). [n], or None when none is found."""
    if len(xy0) < HOMOGRAPHY_SAMPLE[0] + 1:
        return None
    H, _ = cv2.findHomography(xy0, xy1, cv2.RANSAC, threshold, maxIters=2000, confidence=0.999)
    if H is None or not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12:
        return None
    with np.errstate(divide="ignore", invalid="ignore"):
        fw = homog(xy0) @ H.T
        bw = homog(xy1) @ np.linalg.inv(H).T
        d_f = np.sum((fw[:, :2] / fw[:, 2:3] - xy1) ** 2, axis=1)
        d_b = np.sum((bw[:, :2] / bw[:, 2:3] - xy0) ** 2, axis=1)
    e2 = (d_f + d_b) / 4.0
    return np.where(np.isfinite(e2), e2, np.inf)


# ============================================================================================== the whole
def pose_evidence(
    v0: View, v1: View, geometry: TwoViewGeometry, putative: Matches, unknown: tuple[bool, bool]
) -> PoseEvidence:
    """The a contrario test, uncertainty and GRIC of ``geometry`` on the ``putative`` matches (module docstring).

    Args:
        v0, v1: the two views (their sizes give the background probability).
        geometry: the pose, its intrinsics.
        putative: the matches gathered before the pose was known (the tier's filtered matches).
        unknown: which views' focal lengths only the matches can tell (a free parameter of the uncertainty; the
            NFA then counts the seven-point sample).
    """
    first, _ = distinct_matches(putative.xy0, putative.xy1)
    xy0 = putative.xy0[first].astype(np.float64)
    xy1 = putative.xy1[first].astype(np.float64)
    n = len(xy0)
    nfa, k, eps, res = epipolar_nfa(v0, v1, geometry, xy0, xy1, unknown)
    inl = res <= eps if k else np.zeros(n, bool)
    coverage = min(hull_share(xy0[inl], v0.width, v0.height), hull_share(xy1[inl], v1.width, v1.height))
    noise, rot_sigma, t_sigma = _uncertainty(geometry, xy0[inl], xy1[inl], unknown)
    # GRIC on the putative matches, at the inliers' noise level
    sigma = noise if math.isfinite(noise) else MIN_NOISE_PX
    e2_epi = fundamental_residuals(geometry, xy0, xy1) ** 2 if n else np.zeros(0)
    e2_epi = np.where(np.isfinite(res), e2_epi, np.inf)
    e2_h = _homography_residuals(xy0, xy1, HOMOGRAPHY_THRESHOLD_PX)
    k_epi = 7 if any(unknown) else 5
    if e2_h is None:
        gric_e, gric_h, on_plane = _gric(e2_epi, sigma, 3, k_epi, GRIC_LAMBDA3), math.inf, np.zeros(n, bool)
    else:
        # on the matches either model explains: one neither explains costs each model its cap, which differs by
        # model dimension and would favour the epipolar model by the outlier count alone
        either = (e2_epi / sigma**2 < GRIC_LAMBDA3 * (4 - 3)) | (e2_h / sigma**2 < GRIC_LAMBDA3 * (4 - 2))
        gric_e = _gric(e2_epi[either], sigma, 3, k_epi, GRIC_LAMBDA3)
        gric_h = _gric(e2_h[either], sigma, 2, 8, GRIC_LAMBDA3)
        on_plane = e2_h <= (HOMOGRAPHY_THRESHOLD_PX**2) / 2.0
    off = ~on_plane
    sample = FOCAL_SAMPLE if any(unknown) else ESSENTIAL_SAMPLE
    off_nfa, _, _ = log10_nfa(res[off], _line_alpha(v0, v1), 1, sample, min_residual=MIN_NOISE_PX)
    return PoseEvidence(
        putative=n, log10_nfa=nfa, inliers=int(inl.sum()), threshold_px=eps, coverage=coverage, noise_px=noise,
        rotation_sigma_deg=rot_sigma, translation_sigma_deg=t_sigma, focal_free=any(unknown), gric_epipolar=gric_e,
        gric_homography=gric_h, plane_share=float(on_plane.mean()) if n else 0.0, off_plane=int(off.sum()),
        off_plane_log10_nfa=off_nfa,
    )  # fmt: skip
