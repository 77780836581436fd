"""Relative pose of two views: robust essential matrix, cheirality, non-linear refinement.

1. Geometric verification: MAGSAC++ (OpenCV USAC) on the filtered matches. Points are
   first mapped through ``K⁻¹`` into one virtual camera whose focal length is the mean of
   the two, so the inlier threshold stays in pixels even when the two images differ.
2. Cheirality: of the four decompositions of E, the one that puts the most points in
   front of both cameras (no distance cut-off, unlike ``cv2.recoverPose``).
3. Refinement: Levenberg–Marquardt on the Sampson distance (pixels) of the inliers with
   Cauchy weights, over the rotation (3 DOF) and the translation direction (2 DOF).
4. Focal length, when a view's intrinsics come only from the 60° field-of-view prior:
   a fundamental matrix is fitted first (it needs no intrinsics), the focal scale that
   makes ``K1ᵀ F K0`` closest to an essential matrix initialises it (Mendonça–Cipolla),
   and LM refines it with the pose under a log-normal prior. The estimate replaces the
   prior only if the matches pin it down: its data-only standard deviation is below
   ``focal_max_std`` and that std times the rotation's sensitivity to the focal (how far the
   refitted rotation moves per unit of log focal) is below ``focal_max_rotation_deg``.
   Object-centric pairs (both optical axes through one point at equal distances, Sturm's
   critical configuration) are the classic case where it is not: the fit there has a small
   apparent std but errors of 10–37 %. Then the prior is kept, ``info["focal_observable"]``
   is False, and when the pose depends on the focal a doubt goes to ``info["doubts"]``.
5. Planar scenes (issue 14): when a homography explains ``planar_fraction`` of the verified
   matches, the essential matrix's pose and the poses of the homography's decomposition (a
   plane fits two) compete: those that explain as many verified matches contend, and all the
   matches decide, the verified ones and those below the confidence gate
   (``Matches.below_gate``): a pose wins with matches it explains (in front of both cameras)
   that the other refutes (behind a camera: the plane's wrong pose often puts part of it
   there; or far off its epipolar lines: points off the plane). Tied evidence is refused.
6. Degeneracies raise :class:`~macsplat_cli.errors.ReconstructionError`: too few (distinct)
   matches or verified matches, matches along one line, identical images, a pure rotation (no
   baseline, so no depth), and an unreliable pose. OpenCV's estimators run only within their
   preconditions (:func:`_robust_fit`): no ``cv2.error`` leaves this module. An unreliable pose:
   two checks, measured on synthetic wide-baseline and textureless failures: fewer than
   ``min_inlier_ratio`` of the matches agree with the pose (wrong poses had 28–37 %, correct
   ones 67–99 %), or a homography explains clearly more
   matches than the pose does (``homography_excess``) — impossible for a correct pose,
   since points on a real plane satisfy its epipolar geometry too.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..errors import NonFiniteError, ReconstructionError
from ..metrics import angle_between_deg, rotation_angle_deg
from ..rotations import nearest_rotation
from .types import Matches, TwoViewGeometry, View

__all__ = [
    "PoseConfig",
    "epipolar_fit",
    "estimate_pose",
    "find_homography",
    "flipped_fraction",
    "sampson_distance",
]

logger = logging.getLogger(__name__)


@dataclass
class PoseConfig:
    """Args:
    threshold_px: inlier threshold on the epipolar (Sampson) distance, working-resolution px.
    confidence: RANSAC confidence.
    max_iters: RANSAC iterations.
    min_inliers: fewer verified matches than this is a failure.
    refine: run the non-linear refinement.
    estimate_focal: self-calibrate views whose intrinsics come from the prior.
    focal_prior_sigma: std of the log focal prior (0.5 ≈ ×/÷ 1.65).
    focal_max_std: largest data-only std of the log focal for the estimate to be used
        (computed with the residuals' robust noise level, 1.4826·MAD).
    focal_max_rotation_deg: the self-calibrated focal is used only if its data-only std times the rotation's
        sensitivity to the focal (:func:`_focal_rotation_sensitivity`) stays below this (°); else, and when the
        focal is not determined at all and the prior's std times that sensitivity exceeds it, the prior is kept
        and a doubt is recorded (``info["doubts"]``). Measured on synthetic orbits (benchmarks/pose_stress.py
        ``--focal``): every pair whose estimated focal was off by > 5 % or rotation by > 2° was at 0.27° or more,
        the good 10–45° pairs at 0.245° or less.
    min_inlier_ratio: smallest fraction of the matches that must agree with the pose.
    homography_excess: the pose is rejected when a homography explains more than this
        many times its inliers (plus 10).
    planar_ambiguity: when a homography explains at least ``planar_fraction`` of the inliers, the poses
        (the essential matrix's and the homography's decompositions: a plane has two) that explain this
        fraction of the best one's verified matches contend (``planar_resolve``); with ``planar_resolve`` off,
        the pose is rejected as soon as another decomposition explains this fraction (the check before issue 14).
    max_flipped: the pair is refused as mirror images when more than this share of the small triangles
        between neighbouring verified matches flips orientation (:func:`flipped_fraction`).
    planar_resolve: when the plane's poses tie on the verified matches, score them on all the matches (the
        rest of the gated ones and ``Matches.below_gate``) by support with positive depth
        (:func:`_resolve_planar`) instead of refusing at once; refuse only when that is tied too.
    planar_min_evidence: fewest matches that the winning pose must explain and each rival refute.
    planar_evidence_ratio: how many times the converse count (explained by the rival, refuted by the winner)
        those must be.
    planar_contend: a plane's pose that explains at least this fraction of the best one's verified matches
        contends: it must be beaten by evidence (:func:`_resolve_planar`), not by a count a few matches short (a
        forward motion over a plane, 0.5 px noise: 74 against 78 matches, and the 78 were 15° off).
    planar_refute_factor: a pose refutes a match that lies behind one of its cameras or farther than this many
        ``threshold_px`` from its epipolar geometry (a band between explained and refuted counts for neither,
        so that noise at the threshold is no evidence).
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


REFERENCE_SIDE = 512
"""Working long side (px) at which :class:`PoseConfig`'s pixel thresholds apply as given; below it they shrink."""


# ----------------------------------------------------------------------------------- geometry
def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _homog(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)


def fundamental_from_pose(R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray) -> np.ndarray:
    """``F = K1⁻ᵀ [t]× R K0⁻¹`` (x1ᵀ F x0 = 0 for pixels). [3, 3]"""
    return np.linalg.inv(K1).T @ _skew(t) @ R @ np.linalg.inv(K0)


def sampson_distance(F: np.ndarray, xy0: np.ndarray, xy1: np.ndarray) -> np.ndarray:
    """Signed first-order geometric distance of each match to ``F`` [3, 3] (or to each of a stack of them,
    ``F: [P, 3, 3]`` → ``[P, M]``: one call for all of a finite-difference Jacobian's poses), in pixels. [M]"""
    p0, p1 = _homog(xy0), _homog(xy1)
    Fp0 = p0 @ np.swapaxes(F, -1, -2)  # [(P,) M, 3]
    Ftp1 = p1 @ F
    e = np.sum(p1 * Fp0, axis=-1)
    denom = Fp0[..., 0] ** 2 + Fp0[..., 1] ** 2 + Ftp1[..., 0] ** 2 + Ftp1[..., 1] ** 2
    return e / np.sqrt(np.maximum(denom, 1e-30))


def triangulate(R: np.ndarray, t: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Midpoint triangulation of normalised rays; points in camera 0. [M, 3] (NaN if parallel)"""
    d0 = x0 / np.linalg.norm(x0, axis=1, keepdims=True)
    d1 = (x1 / np.linalg.norm(x1, axis=1, keepdims=True)) @ R  # ray of camera 1 in camera-0 axes
    c1 = -R.T @ t
    # minimise |a d0 − (c1 + b d1)|²
    b_ = np.sum(d0 * d1, axis=1)
    w0 = c1 @ d0.T
    w1 = d1 @ c1
    den = 1.0 - b_**2
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (w0 - b_ * w1) / den
        b = (b_ * w0 - w1) / den
    p = 0.5 * (a[:, None] * d0 + (c1 + b[:, None] * d1))
    p[den < 1e-12] = np.nan
    return p


def _parallax_deg(R: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Angle between the two viewing rays of each match once the rotation is removed. [M]"""
    return angle_between_deg(x0 @ R.T, x1)


_rotation_angle_deg = rotation_angle_deg  # the one formula (atan2), in macsplat_cli.metrics


# ----------------------------------------------------------------------------------- OpenCV within its preconditions
MIN_POINTS_ESSENTIAL = 5
"""Correspondences the five-point essential-matrix solver needs."""
MIN_POINTS_FUNDAMENTAL = 8
"""Correspondences a fundamental matrix needs (OpenCV's USAC samples 7; the 8-point refit needs 8)."""
MIN_POINTS_HOMOGRAPHY = 4
"""Correspondences a homography needs."""


def distinct_matches(xy0: np.ndarray, xy1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct correspondences among ``xy0, xy1`` [M, 2]: (index of the first occurrence of each [K], which
    of them each match repeats [M]). One keypoint can carry several descriptors (SIFT: one per dominant
    orientation), so the same pair of pixels can be matched more than once."""
    if len(xy0) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, first, inverse = np.unique(
        np.concatenate([xy0, xy1], axis=1), axis=0, return_index=True, return_inverse=True
    )  # fmt: skip
    order = np.argsort(first)  # keep the matches' order: the distinct ones as they first appear
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[np.asarray(inverse).reshape(-1)]


def _robust_fit(
    fit: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray | None, np.ndarray | None]],
    xy0: np.ndarray,
    xy1: np.ndarray,
    min_points: int,
    what: str,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """An OpenCV robust estimator, ``fit(xy0, xy1) → (model, inlier mask)``, run within its preconditions.

    The points go in as contiguous float64 [M, 2]; fewer than ``min_points`` distinct correspondences, or a
    non-finite one, and OpenCV is not called. OpenCV's USAC asserts (``!model.empty()``) when a minimal sample
    is degenerate, which repeated correspondences make likely (issue 23: 441 matches, 396 distinct, at
    ``--size 128``): then the distinct correspondences are fitted instead, and each repeat takes the inlier flag
    of its first occurrence. The full set is tried first so that every input OpenCV accepts keeps its result.

    Returns:
        ``(model, mask)``: the model and the inlier flags [M] bool, or ``(None, None)`` when no model fits.
        Never raises ``cv2.error``.
    """
    a = np.ascontiguousarray(xy0, np.float64).reshape(-1, 2)
    b = np.ascontiguousarray(xy1, np.float64).reshape(-1, 2)
    if len(a) != len(b) or not (np.isfinite(a).all() and np.isfinite(b).all()):
        return None, None
    first, inverse = distinct_matches(a, b)
    if len(first) < min_points:
        return None, None
    subsets = [None] if len(first) == len(a) else [None, first]
    for sub in subsets:
        try:
            model, mask = fit(a, b) if sub is None else fit(a[sub], b[sub])
        except cv2.error as e:
            logger.debug("%s on %d matches (%d distinct): %s", what, len(a), len(first), str(e).strip()[-120:])
            continue
        if model is None or mask is None or model.size == 0 or not np.isfinite(model).all():
            return None, None
        flags = np.asarray(mask).reshape(-1).astype(bool)
        return model, (flags if sub is None else flags[inverse])
    return None, None


def find_homography(
    xy0: np.ndarray, xy1: np.ndarray, threshold_px: float, max_iters: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """MAGSAC++ homography of the matches ``xy0 → xy1`` [M, 2]: ([3, 3], inliers [M] bool), or (None, None) when
    none fits or the matches cannot determine one (:func:`_robust_fit`)."""
    return _robust_fit(
        lambda a, b: cv2.findHomography(a, b, cv2.USAC_MAGSAC, threshold_px, maxIters=max_iters),
        xy0, xy1, MIN_POINTS_HOMOGRAPHY, "homography",
    )  # fmt: skip


def _line_spread_px(xy: np.ndarray) -> float:
    """RMS distance (px) of the points ``xy`` [M, 2] from their best-fitting line (0: collinear)."""
    if len(xy) < 3:
        return 0.0
    s = np.linalg.svd(xy - xy.mean(0), compute_uv=False)
    return float(s[-1]) / math.sqrt(len(xy))


# ----------------------------------------------------------------------------------- estimation
def _scaled_K(K: np.ndarray, s: float, unknown: bool) -> np.ndarray:
    if not unknown or s == 0.0:
        return K
    out = K.copy()
    out[0, 0] *= math.exp(s)
    out[0, 1] *= math.exp(s)
    out[1, 1] *= math.exp(s)
    return out


def _focal_search(F: np.ndarray, K0: np.ndarray, K1: np.ndarray, unknown: tuple[bool, bool]) -> tuple[float, float]:
    """Focal log-scale ``s`` minimising the essential-matrix defect (σ1 − σ2)/σ1 of Kᵀ F K."""
    grid = np.linspace(math.log(0.4), math.log(2.5), 121)
    costs = []
    for s in grid:
        E = _scaled_K(K1, s, unknown[1]).T @ F @ _scaled_K(K0, s, unknown[0])
        sv = np.linalg.svd(E, compute_uv=False)
        costs.append((sv[0] - sv[1]) / max(sv[0], 1e-30))
    k = int(np.argmin(costs))
    return float(grid[k]), float(costs[k])


def _essential(x0v: np.ndarray, x1v: np.ndarray, f_v: float, cfg: PoseConfig) -> tuple[np.ndarray, np.ndarray]:
    Kv = np.array([[f_v, 0.0, 0.0], [0.0, f_v, 0.0], [0.0, 0.0, 1.0]])
    E, inl = _robust_fit(
        lambda a, b: cv2.findEssentialMat(
            a, b, Kv, method=cv2.USAC_MAGSAC, prob=cfg.confidence, threshold=cfg.threshold_px, maxIters=cfg.max_iters
        ),
        x0v, x1v, MIN_POINTS_ESSENTIAL, "essential matrix",
    )  # fmt: skip
    if E is None or E.shape != (3, 3) or inl is None:
        raise ReconstructionError("pose could not be estimated: no essential matrix fits the matches")
    R, t, front = _cheirality(E, x0v[inl] / f_v, x1v[inl] / f_v)
    good = np.zeros_like(inl)
    good[np.flatnonzero(inl)[front]] = True
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T, good


def _cheirality(E: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The decomposition of E that puts most points in front of both cameras.

    Unlike ``cv2.recoverPose``, no distance cut-off: points near infinity (small baselines,
    pure rotations) still count, so the parallax check can report a missing baseline
    instead of a misleading "0 verified matches". ``x0, x1``: normalised coordinates [M, 2].

    Returns:
        ``(R, t, in_front)`` with ``|t| = 1``. [3, 3], [3], [M] bool
    """
    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.ravel() / max(np.linalg.norm(t), 1e-30)
    h0, h1 = _homog(x0), _homog(x1)
    best = None
    for R in (R1, R2):
        for tt in (t, -t):
            X = triangulate(R, tt, h0, h1)
            z1 = X @ R[2] + tt[2]
            front = np.isfinite(X).all(1) & (X[:, 2] > 0) & (z1 > 0)
            if best is None or front.sum() > best[2].sum():
                best = (R, tt, front)
    assert best is not None
    return best


def _decompose_homography(Hn: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The (R, t) candidates of a normalised homography [3, 3], each R the nearest rotation to OpenCV's (its
    rotations are orthonormal only to ~1e-9; Levenberg–Marquardt multiplies small rotations onto R and would keep
    that defect in the returned pose)."""
    _, Rs, ts, _ = cv2.decomposeHomographyMat(Hn, np.eye(3))
    return [nearest_rotation(R) for R in Rs], list(ts)


def _refine(
    R: np.ndarray,
    t: np.ndarray,
    s: float,
    xy0: np.ndarray,
    xy1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    unknown: tuple[bool, bool],
    *,
    with_focal: bool,
    scale: float,
    prior_sigma: float,
    iters: int = 30,
    diag: dict | None = None,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """LM on Cauchy-weighted Sampson distances over (ω, α[, s]). Returns R, t, s, data-only std of s.
    With ``diag``, its ``noise_px`` gets the residuals' robust noise level of the last iteration (the std of s
    scales with it)."""
    n_par = 6 if with_focal else 5

    def residuals(R_: np.ndarray, t_: np.ndarray, s_: float) -> np.ndarray:
        F = fundamental_from_pose(R_, t_, _scaled_K(K0, s_, unknown[0]), _scaled_K(K1, s_, unknown[1]))
        return sampson_distance(F, xy0, xy1)

    def apply(theta: np.ndarray, R_: np.ndarray, t_: np.ndarray, s_: float):  # noqa: ANN202
        dR, _ = cv2.Rodrigues(theta[:3].reshape(3, 1))
        basis = np.linalg.svd(t_.reshape(1, 3))[2][1:]  # two unit vectors ⟂ t
        t_new = t_ + theta[3:5] @ basis
        return dR @ R_, t_new / np.linalg.norm(t_new), s_ + (theta[5] if with_focal else 0.0)

    def jacobian(R_: np.ndarray, t_: np.ndarray, s_: float) -> np.ndarray:
        h = 1e-6
        steps = np.concatenate([np.eye(n_par), -np.eye(n_par)]) * h
        poses = [apply(d, R_, t_, s_) for d in steps]
        Fs = [
            fundamental_from_pose(a, b, _scaled_K(K0, c, unknown[0]), _scaled_K(K1, c, unknown[1])) for a, b, c in poses
        ]
        r = sampson_distance(np.stack(Fs), xy0, xy1)  # [2·n_par, M], central differences
        return ((r[:n_par] - r[n_par:]) / (2 * h)).T

    def cost(r: np.ndarray, s_: float) -> float:
        c = float(np.sum(np.log1p((r / scale) ** 2)))
        return c + ((s_ / prior_sigma) ** 2 if with_focal else 0.0)

    lam = 1e-3
    r = residuals(R, t, s)
    current = cost(r, s)
    info_s = 0.0
    for _ in range(iters):
        w = 1.0 / (1.0 + (r / scale) ** 2)  # IRLS weights of the Cauchy loss
        J = jacobian(R, t, s)
        H = (J * (w / scale**2)[:, None]).T @ J
        g = (J * (w / scale**2)[:, None]).T @ r
        if with_focal:
            # Information about s from the data alone, at the residuals' actual noise level
            # (the Cauchy scale is a tolerance, not a noise estimate), with the pose
            # marginalised out (Schur complement).
            noise = max(1.4826 * float(np.median(np.abs(r))), 0.02)
            if diag is not None:
                diag["noise_px"] = noise
            H_data = (J * (w / noise**2)[:, None]).T @ J
            H[5, 5] += 1.0 / prior_sigma**2
            g[5] += s / prior_sigma**2
            try:
                info_s = float(H_data[5, 5] - H_data[5, :5] @ np.linalg.solve(H_data[:5, :5], H_data[:5, 5]))
            except np.linalg.LinAlgError:
                info_s = 0.0
        improved = False
        for _ in range(10):
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            cand = apply(step, R, t, s)
            r_c = residuals(*cand)
            c_c = cost(r_c, cand[2])
            if c_c < current:
                R, t, s = cand
                r, current = r_c, c_c
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or np.linalg.norm(step) < 1e-10:
            break
    std_s = 1.0 / math.sqrt(info_s) if info_s > 0 else math.inf
    return R, t, s, std_s


def flipped_fraction(
    xy0: np.ndarray, xy1: np.ndarray, depth: np.ndarray | None = None, *, neighbours: int = 2,
    max_points: int = 2000, min_px: float = 4.0, max_depth_ratio: float = 1.2,
) -> float:  # fmt: skip
    """Share of the triangles (a match and its two nearest neighbours in photo 0) whose orientation flips in
    photo 1. Two views of a scene keep the orientation of nearby points (only depth discontinuities flip a
    few); a mirror image flips nearly all. ``xy0, xy1``: matched pixels [N, 2]; neighbours closer than
    ``min_px`` are skipped. ``depth`` [N] (triangulated, any scale): only triangles whose corners lie within
    ``max_depth_ratio`` of each other count — a patch of one surface; a triangle spanning an object and the
    background behind it flips legitimately when the camera orbits the object (when fewer than a quarter of
    the triangles are such patches, the depths are not trusted and all count). 0 for fewer than 3 matches."""
    n = len(xy0)
    if n < neighbours + 1:
        return 0.0
    if n > max_points:
        sel = np.linspace(0, n - 1, max_points).astype(np.int64)
        xy0, xy1, n = xy0[sel], xy1[sel], max_points
        depth = depth[sel] if depth is not None else None
    p = torch.from_numpy(np.ascontiguousarray(xy0, np.float64))
    d = torch.cdist(p, p)  # [N, N]; far faster than a broadcast norm and a full argsort
    d[d < min_px] = math.inf  # itself, and near-duplicate keypoints (affine-simulated SIFT): their triangles are noise
    dist, nn_t = d.topk(neighbours, dim=1, largest=False)  # the nearest first
    nn = nn_t.numpy()  # [N, 2]
    i = np.flatnonzero(np.isfinite(dist.numpy()).all(1))
    j, k = nn[i, 0], nn[i, 1]
    a0, b0 = xy0[j] - xy0[i], xy0[k] - xy0[i]
    a1, b1 = xy1[j] - xy1[i], xy1[k] - xy1[i]
    s0 = a0[:, 0] * b0[:, 1] - a0[:, 1] * b0[:, 0]
    s1 = a1[:, 0] * b1[:, 1] - a1[:, 1] * b1[:, 0]
    # ignore degenerate (nearly collinear) triangles: their sign is noise
    ok = (np.abs(s0) > 0.05 * (np.linalg.norm(a0, axis=1) * np.linalg.norm(b0, axis=1) + 1e-12)) & (
        np.abs(s1) > 0.05 * (np.linalg.norm(a1, axis=1) * np.linalg.norm(b1, axis=1) + 1e-12)
    )
    if depth is not None:
        z = np.stack([depth[i], depth[j], depth[k]], 1)
        surface = ok & (z.min(1) > 0) & (z.max(1) <= max_depth_ratio * z.min(1))
        if surface.sum() >= max(10, 0.25 * ok.sum()):  # else the depths are noise (a wrong pose): all triangles
            ok = surface
    if not ok.any():
        return 0.0
    return float(np.mean(np.sign(s0[ok]) != np.sign(s1[ok])))


def epipolar_fit(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sampson distance (px) of each match to a relative pose, and whether it triangulates in front of both
    cameras. [M], [M] bool"""
    if len(xy0) == 0:
        return np.zeros(0), np.zeros(0, bool)
    d = np.abs(sampson_distance(fundamental_from_pose(R, t, K0, K1), xy0, xy1))
    X = triangulate(R, t, _homog(xy0) @ np.linalg.inv(K0).T, _homog(xy1) @ np.linalg.inv(K1).T)
    with np.errstate(invalid="ignore"):
        front = np.isfinite(X).all(1) & (X[:, 2] > 0) & (X @ R[2] + t[2] > 0)
    return d, front


def _support(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, threshold: float
) -> np.ndarray:
    """Matches a relative pose explains: Sampson distance below ``threshold`` px and triangulated in front of
    both cameras. [M] bool"""
    d, front = epipolar_fit(R, t, K0, K1, xy0, xy1)
    return (d < threshold) & front


def _same_pose(
    Ra: np.ndarray, ta: np.ndarray, Rb: np.ndarray, tb: np.ndarray, *, rot_deg: float = 1.0, dir_deg: float = 5.0
) -> bool:
    return _rotation_angle_deg(Ra @ Rb.T) < rot_deg and angle_between_deg(ta, tb) < dir_deg


def _focal_rotation_sensitivity(
    R: np.ndarray, t: np.ndarray, s: float, xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
    unknown: tuple[bool, bool], cfg: PoseConfig, step: float = 0.1,
) -> float:  # fmt: skip
    """Degrees the refined rotation moves per unit of log focal: the pose refitted with the focal scaled by
    ``exp(±step)``. About the angle between the views for cameras that look at one point (an orbit), ~0 for a
    sideways translation without rotation (a rectified stereo pair), whose pose no focal changes."""
    moves = []
    for ds in (-step, step):
        R2, _, _, _ = _refine(
            R, t, s + ds, xy0, xy1, K0, K1, unknown, with_focal=False, scale=cfg.threshold_px,
            prior_sigma=cfg.focal_prior_sigma, iters=15,
        )  # fmt: skip
        moves.append(_rotation_angle_deg(R2 @ R.T))
    return max(moves) / step


def _axes_geometry(R: np.ndarray, t: np.ndarray) -> dict[str, float]:
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


def _focal_doubt(info: dict) -> str:
    looking = info.get("focal_axes_gap", math.inf) < 0.1 and info.get("focal_axes_asymmetry", math.inf) < 0.3
    why = " (both cameras look at the same point, as when photographing an object)" if looking else ""
    return (
        f"the focal length cannot be determined from these two photos{why}, and the pose depends on it: "
        "give --focal, --intrinsics or photos with EXIF"
    )


def _planar_check(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, cfg: PoseConfig
) -> tuple[int, int, float, list[tuple[np.ndarray, np.ndarray]]]:
    """How the verified matches relate to their dominant plane.

    The homography is fitted robustly (MAGSAC++) to the verified matches: a least-squares fit
    through the few off-plane matches missed the ambiguity of a 75° wide-baseline pair whose
    matches lie almost all on one wall.

    Returns:
        ``(off_plane, rival, agreement_deg, rivals)``: matches off the plane's homography; the most matches
        that a relative pose other than ``(R, t)`` among the homography's decompositions explains (a plane has
        two physical ones); how far ``(R, t)`` is from the nearest decomposition (max of rotation and
        translation-direction/3 differences, °); and those other poses ``(R, t)`` (unit ``t``), distinct from
        each other, that explain at least one match.
    """
    H, hmask = find_homography(xy0, xy1, 1.5 * cfg.threshold_px, cfg.max_iters)
    if H is None or hmask is None:
        return len(xy0), 0, 0.0, []
    off_plane = int(len(xy0) - hmask.sum())
    Hn = np.linalg.inv(K1) @ H @ K0
    Rs, ts = _decompose_homography(Hn)
    best, agreement = 0, math.inf
    rivals: list[tuple[np.ndarray, np.ndarray]] = []
    for Ri, ti in zip(Rs, ts):
        ti = ti.ravel()
        if np.linalg.norm(ti) < 1e-9:
            continue
        ti = ti / np.linalg.norm(ti)
        dr = _rotation_angle_deg(Ri @ R.T)
        dt = angle_between_deg(ti, t)
        agreement = min(agreement, max(dr, dt / 3))
        if dr < 1.0 and dt < 5.0:
            continue  # the same pose
        n_ok = int(_support(Ri, ti, K0, K1, xy0, xy1, cfg.threshold_px).sum())
        best = max(best, n_ok)
        if n_ok > 0 and not any(_same_pose(Ri, ti, Rr, tr) for Rr, tr in rivals):
            rivals.append((Ri, ti))
    return off_plane, best, agreement, rivals


@dataclass
class _PlanarVerdict:
    """The outcome of :func:`_resolve_planar`: the index of the winning candidate (None: tied), each candidate's
    support over all the matches, and (evidence, counter-evidence) of the best candidate's closest duel."""

    winner: int | None
    support: list[int]
    exclusive: tuple[int, int]


def _resolve_planar(
    candidates: list[tuple[np.ndarray, np.ndarray]],
    K0: np.ndarray,
    K1: np.ndarray,
    xy0: np.ndarray,
    xy1: np.ndarray,
    cfg: PoseConfig,
) -> _PlanarVerdict:
    """Tell a plane's relative poses apart by the evidence the plane does not give.

    Every candidate explains the plane's matches equally well; what separates them is the matches off the plane
    (which only the true pose explains) and cheirality (the wrong pose of a plane puts part of it behind a
    camera). Each candidate is scored by the matches it explains with positive depth among ``xy0, xy1`` (all
    matches: the verified ones, the rest of the gated ones and those below the confidence gate). The best wins
    when, against every other candidate, the matches it explains (within ``threshold_px``, in front) and the
    other refutes (behind a camera, or beyond ``planar_refute_factor · threshold_px``) number at least
    ``planar_min_evidence`` and ``planar_evidence_ratio`` times the converse; else the candidates are tied.
    Matches near the threshold of either count for neither: noise there is not evidence.

    Returns:
        the verdict; ``exclusive`` is (evidence, counter-evidence) of the closest duel.
    """
    fits = [epipolar_fit(R, t, K0, K1, xy0, xy1) for R, t in candidates]
    explained = [(d < cfg.threshold_px) & front for d, front in fits]
    refuted = [(d > cfg.planar_refute_factor * cfg.threshold_px) | ~front for d, front in fits]
    support = [int(m.sum()) for m in explained]
    order = np.argsort(support, kind="stable")[::-1]
    if len(candidates) < 2:
        return _PlanarVerdict(int(order[0]) if candidates else None, support, (0, 0))
    # the best must win every duel: matches it explains and the other refutes, against the converse
    worst: tuple[int, int] | None = None
    for k in order[1:]:
        a = int((explained[order[0]] & refuted[k]).sum())
        b = int((explained[k] & refuted[order[0]]).sum())
        if worst is None or a - cfg.planar_evidence_ratio * b < worst[0] - cfg.planar_evidence_ratio * worst[1]:
            worst = (a, b)
    assert worst is not None
    won = worst[0] >= cfg.planar_min_evidence and worst[0] >= cfg.planar_evidence_ratio * worst[1]
    return _PlanarVerdict(int(order[0]) if won else None, support, worst)


def estimate_pose(v0: View, v1: View, matches: Matches, config: PoseConfig | None = None) -> TwoViewGeometry:
    """Relative pose of ``v1`` with respect to ``v0`` from filtered matches.

    Returns:
        :class:`TwoViewGeometry` with unit-norm ``t``, the verified matches (``counts``
        gains ``verified``), possibly refined intrinsics, and diagnostics in ``info``.

    Raises:
        NonFiniteError: a match coordinate or an intrinsic matrix holds NaN/Inf.
        ReconstructionError: too few matches or inliers, identical images, or no baseline.
    """
    cfg = config or PoseConfig()
    side = max(v0.width, v0.height, v1.width, v1.height)
    ref = min(REFERENCE_SIDE, max(*v0.original_size, *v1.original_size))
    if side < ref:
        # The pixel thresholds are set for a 512-px working image. Keypoints are detected on the photo (up to
        # 768 px), so a photo shrunk further to a small working size has keypoints proportionally more precise
        # in its pixels: the thresholds shrink with it. With 1 px at 64 px every match fit a plane both ways and
        # the pair was refused as ambiguous (issue 16). A small photo used at its own size keeps them.
        cfg = dataclasses.replace(cfg, threshold_px=cfg.threshold_px * side / ref)
    for name, a in (
        ("matches.xy0", matches.xy0),
        ("matches.xy1", matches.xy1),
        ("K of view 0", v0.K),
        ("K of view 1", v1.K),
    ):
        if not np.isfinite(a).all():
            raise NonFiniteError(f"{name} holds {int((~np.isfinite(a)).sum())} non-finite value(s) (NaN or Inf)")
    n = len(matches)
    xy0, xy1 = matches.xy0.astype(np.float64), matches.xy1.astype(np.float64)
    distinct, _ = distinct_matches(xy0, xy1)
    need = max(cfg.min_inliers, MIN_POINTS_FUNDAMENTAL)
    if len(distinct) < need:
        repeats = f" ({n} with repeats)" if len(distinct) < n else ""
        raise ReconstructionError(
            f"pose could not be estimated: only {len(distinct)} match{'es' if len(distinct) != 1 else ''} survived "
            f"filtering{repeats}, need at least {need}"
        )
    for k, xy in enumerate((xy0[distinct], xy1[distinct])):
        if _line_spread_px(xy) < cfg.threshold_px:
            raise ReconstructionError(
                f"pose could not be estimated: the {len(distinct)} matches lie along one line in photo {k + 1} "
                "(within the inlier threshold), which leaves the relative pose undetermined"
            )
    if v0.image.shape == v1.image.shape:
        shift = np.median(np.linalg.norm(xy1 - xy0, axis=1))
        if shift < 0.5 and np.mean(np.linalg.norm(xy1 - xy0, axis=1) < 1.0) > 0.8:
            raise ReconstructionError(
                f"the two images show the same view (median match displacement {shift:.2f} px): "
                "move the camera between the photos"
            )
    unknown = (v0.intrinsics_source == "prior", v1.intrinsics_source == "prior")
    K0, K1 = v0.K.copy(), v1.K.copy()
    info: dict[str, float | int | str | bool] = {}

    s = 0.0
    with_focal = cfg.estimate_focal and any(unknown)
    if with_focal:
        F, fmask = _robust_fit(
            lambda a, b: cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, cfg.threshold_px, cfg.confidence, cfg.max_iters),
            xy0, xy1, MIN_POINTS_FUNDAMENTAL, "fundamental matrix",
        )  # fmt: skip
        if F is not None and F.shape == (3, 3) and fmask is not None and int(fmask.sum()) >= cfg.min_inliers:
            s, defect = _focal_search(F, K0, K1, unknown)
            info["focal_search_scale"] = math.exp(s)
            info["focal_search_defect"] = defect
        else:
            with_focal = False

    def verify(s_: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        K0s, K1s = _scaled_K(K0, s_, unknown[0]), _scaled_K(K1, s_, unknown[1])
        f_v = float(np.mean([K0s[0, 0], K0s[1, 1], K1s[0, 0], K1s[1, 1]]))
        x0n = _homog(xy0) @ np.linalg.inv(K0s).T
        x1n = _homog(xy1) @ np.linalg.inv(K1s).T
        T, good = _essential(np.ascontiguousarray(x0n[:, :2] * f_v), np.ascontiguousarray(x1n[:, :2] * f_v), f_v, cfg)
        return T[:3, :3], T[:3, 3], good, x0n, x1n

    R, t, good, x0n, x1n = verify(s)
    n_ransac = int(good.sum())
    info["ransac_inliers"] = n_ransac
    if n_ransac < cfg.min_inliers:
        raise ReconstructionError(
            f"pose could not be estimated: {n_ransac} verified matches, need at least {cfg.min_inliers}"
        )

    if cfg.refine:
        scale = cfg.threshold_px
        diag: dict[str, float] = {}
        R, t, s_new, std_s = _refine(
            R, t, s, xy0[good], xy1[good], K0, K1, unknown,
            with_focal=with_focal, scale=scale, prior_sigma=cfg.focal_prior_sigma, diag=diag,
        )  # fmt: skip
        if with_focal and "noise_px" in diag:
            info["focal_noise_px"] = diag["noise_px"]
        if with_focal:
            info["focal_data_std"] = std_s
            info["focal_scale_fitted"] = math.exp(s_new)
            determined = std_s <= cfg.focal_max_std
            # how far the rotation moves per unit of log focal, times how uncertain the focal is: the rotation
            # error the unknown focal may cause (calibrated on synthetic orbits, see focal_max_rotation_deg)
            s_at = s_new if determined else 0.0
            sens = _focal_rotation_sensitivity(R, t, s_at, xy0[good], xy1[good], K0, K1, unknown, cfg)
            spread = sens * (std_s if determined else cfg.focal_prior_sigma)
            info.update(
                focal_rotation_sensitivity_deg=sens,
                focal_rotation_uncertainty_deg=spread,
                **_axes_geometry(R, t),
            )
            observable = determined and spread <= cfg.focal_max_rotation_deg
            info["focal_observable"] = observable
            if not observable and spread > cfg.focal_max_rotation_deg:
                doubts = info.setdefault("doubts", [])
                assert isinstance(doubts, list)
                doubts.append(_focal_doubt(info))
            if observable:
                s = s_new
                info["focal_scale"] = math.exp(s)
            else:  # the matches do not determine the focal length: keep the prior
                logger.debug(
                    "focal not determined by the matches (std %.3f, rotation uncertainty %.2f°); keeping the prior",
                    std_s, spread,
                )  # fmt: skip
                s = 0.0
                R, t, good, x0n, x1n = verify(0.0)
                R, t, _, _ = _refine(
                    R, t, 0.0, xy0[good], xy1[good], K0, K1, unknown,
                    with_focal=False, scale=scale, prior_sigma=cfg.focal_prior_sigma,
                )  # fmt: skip
    K0s, K1s = _scaled_K(K0, s, unknown[0]), _scaled_K(K1, s, unknown[1])
    info["focal_estimated"] = bool(with_focal and s != 0.0)

    final, d, X, x0n, x1n = _final_inliers(R, t, K0s, K1s, xy0, xy1, cfg)
    H, hmask = find_homography(xy0, xy1, 1.5 * cfg.threshold_px, cfg.max_iters)
    n_h = int(hmask.sum()) if H is not None and hmask is not None else 0
    if cfg.planar_resolve and H is not None and n_h >= max(cfg.planar_fraction * int(final.sum()), cfg.min_inliers):
        # the plane dominates: its two poses, and the essential matrix's, compete on all the evidence
        R, t, refined = _planar_pose(R, t, H, s, K0, K1, unknown, xy0, xy1, matches.below_gate, info, cfg)
        if refined:
            final, d, X, x0n, x1n = _final_inliers(R, t, K0s, K1s, xy0, xy1, cfg)
    n_final = _summarise(R, final, d, x0n, x1n, n, info, cfg)
    flipped = flipped_fraction(xy0[final], xy1[final], X[final, 2])
    info["flipped_triangles"] = flipped
    if flipped > cfg.max_flipped:
        raise ReconstructionError(
            f"the photos are mirror images of each other: {100 * flipped:.0f} % of the small triangles between "
            f"neighbouring verified matches are flipped in the second photo, which no camera motion does "
            "(a mirrored or flipped copy?)"
        )
    info["homography_inliers"] = n_h
    if n_h > cfg.homography_excess * n_final + 10:
        raise ReconstructionError(
            f"pose is unreliable: a homography explains {n_h} matches but the relative pose only {n_final} "
            "(the matches lie on one plane, or the pose is wrong)"
        )
    if not cfg.planar_resolve and n_h >= cfg.planar_fraction * n_final:
        off_plane, rival, agreement, _ = _planar_check(R, t, K0s, K1s, xy0[final], xy1[final], cfg)
        info.update(planar_rival_inliers=rival, off_plane_inliers=off_plane, planar_agreement_deg=agreement)
        if rival >= cfg.planar_ambiguity * n_final:
            raise _ambiguous(n_final, rival)
    logger.debug("pose: %s", info)
    return TwoViewGeometry(R=R, t=t, K0=K0s, K1=K1s, inliers=matches.subset(final, "verified"), info=info)


def _planar_pose(
    R: np.ndarray,
    t: np.ndarray,
    H: np.ndarray,
    s: float,
    K0: np.ndarray,
    K1: np.ndarray,
    unknown: tuple[bool, bool],
    xy0: np.ndarray,
    xy1: np.ndarray,
    below_gate: Matches | None,
    info: dict,
    cfg: PoseConfig,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The relative pose of a pair whose matches lie mostly on one plane (issue 14).

    Candidates: the essential matrix's pose ``(R, t)`` and the poses of the homography ``H``'s decomposition
    (a plane has two physical ones), each refined on the gated matches it explains. Those within
    ``planar_ambiguity`` of the best support on the gated matches ``xy0, xy1`` contend; when more than one does,
    all the matches (gated and ``below_gate``) decide (:func:`_resolve_planar`), and a tie is refused. A
    candidate whose median parallax is below ``min_parallax_deg`` does not contend (a wrong essential matrix on a
    plane can look like a rotation; a true rotation keeps the essential pose and is refused for its baseline).

    Returns:
        ``(R, t, changed)``: the winner, and whether it differs from the given pose.

    Raises:
        ReconstructionError: the contenders are tied on all the evidence.
    """
    K0s, K1s = _scaled_K(K0, s, unknown[0]), _scaled_K(K1, s, unknown[1])
    Ki0, Ki1 = np.linalg.inv(K0s), np.linalg.inv(K1s)
    x0n, x1n = _homog(xy0) @ Ki0.T, _homog(xy1) @ Ki1.T
    candidates: list[tuple[np.ndarray, np.ndarray]] = [(R, t)]
    agreement = math.inf
    Rs, ts = _decompose_homography(Ki1 @ H @ K0s)
    for Ri, ti in zip(Rs, ts):
        ti = ti.ravel()
        if np.linalg.norm(ti) < 1e-9:
            continue
        ti = ti / np.linalg.norm(ti)
        agreement = min(agreement, max(_rotation_angle_deg(Ri @ R.T), angle_between_deg(ti, t) / 3))
        sup = _support(Ri, ti, K0s, K1s, xy0, xy1, cfg.threshold_px)
        if sup.sum() < cfg.min_inliers:
            continue
        if cfg.refine:
            Rr, tr, _, _ = _refine(
                Ri, ti, s, xy0[sup], xy1[sup], K0, K1, unknown,
                with_focal=False, scale=cfg.threshold_px, prior_sigma=cfg.focal_prior_sigma,
            )  # fmt: skip
            collapsed = any(_same_pose(Rr, tr, Rc, tc) for Rc, tc in candidates)
            if not (
                collapsed and not any(_same_pose(Ri, ti, Rc, tc, rot_deg=2.0, dir_deg=10.0) for Rc, tc in candidates)
            ):
                Ri, ti = Rr, tr
            # else: refined, a distinct decomposition slid onto another candidate (the planar valley: a plane with
            # little rotation fits a range of translations). It stays as it was, a rival the evidence must beat
            # (0.25 px noise: a pose 18° off was accepted when the rival, 3° from the truth, merged into it)
        if not any(_same_pose(Ri, ti, Rc, tc) for Rc, tc in candidates):
            candidates.append((Ri, ti))
    masks = [_support(Rc, tc, K0s, K1s, xy0, xy1, cfg.threshold_px) for Rc, tc in candidates]
    gated = [int(m.sum()) for m in masks]
    parallax = [
        float(np.median(_parallax_deg(Rc, x0n[m], x1n[m]))) if m.any() else 0.0 for (Rc, _), m in zip(candidates, masks)
    ]
    usable: list[int] = []
    for k in sorted(range(len(candidates)), key=lambda k: -gated[k]):
        # the same solution twice (the essential matrix's and a decomposition's, a few degrees apart) is no
        # ambiguity: the better supported stands for both
        if parallax[k] >= cfg.min_parallax_deg and not any(
            _same_pose(*candidates[k], *candidates[j], rot_deg=2.0, dir_deg=10.0) for j in usable
        ):
            usable.append(k)
    info.update(
        planar_candidates=len(candidates),
        planar_gated_support=",".join(map(str, gated)),
        planar_rival_inliers=max(gated[1:], default=0),
        planar_agreement_deg=agreement,
    )
    if not usable:
        return R, t, False
    top = max(gated[k] for k in usable)
    contenders = [k for k in usable if gated[k] >= cfg.planar_contend * top]
    if len(contenders) > 1:
        if (
            below_gate is not None
            and len(below_gate)
            and np.isfinite(below_gate.xy0).all()
            and np.isfinite(below_gate.xy1).all()
        ):
            all0 = np.concatenate([xy0, below_gate.xy0.astype(np.float64)])
            all1 = np.concatenate([xy1, below_gate.xy1.astype(np.float64)])
        else:
            all0, all1 = xy0, xy1
        verdict = _resolve_planar([candidates[k] for k in contenders], K0s, K1s, all0, all1, cfg)
        info.update(
            planar_support=",".join(map(str, verdict.support)),
            planar_evidence=verdict.exclusive[0],
            planar_counter_evidence=verdict.exclusive[1],
            planar_matches_scored=len(all0),
        )
        if verdict.winner is None:
            ranked = sorted((gated[k] for k in contenders), reverse=True)
            raise _ambiguous(ranked[0], ranked[1], verdict.exclusive)
        winner = contenders[verdict.winner]
    else:
        winner = contenders[0]
        all0, all1 = xy0, xy1
    info["planar_resolved"] = "essential" if winner == 0 else "homography"
    if winner == 0:
        return R, t, False
    R, t = candidates[winner]
    sup = _support(R, t, K0s, K1s, all0, all1, cfg.threshold_px)
    if cfg.refine:
        R, t, _, _ = _refine(
            R, t, s, all0[sup], all1[sup], K0, K1, unknown,
            with_focal=False, scale=cfg.threshold_px, prior_sigma=cfg.focal_prior_sigma,
        )  # fmt: skip
    return R, t, True


def _ambiguous(n_final: int, rival: int, evidence: tuple[int, int] | None = None) -> ReconstructionError:
    more = f"; no other matches tell them apart ({evidence[0]} against {evidence[1]})" if evidence is not None else ""
    return ReconstructionError(
        f"pose is ambiguous: the {n_final} verified matches lie on one plane, and two different relative "
        f"poses explain them ({rival} and {n_final} matches){more}: photograph more of the scene's depth"
    )


def _final_inliers(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, cfg: PoseConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Final inliers (small epipolar distance, in front of both cameras), Sampson distances, triangulated points
    and normalised coordinates. [M] bool, [M], [M, 3], [M, 3], [M, 3]"""
    F = fundamental_from_pose(R, t, K0, K1)
    d = np.abs(sampson_distance(F, xy0, xy1))
    x0n = _homog(xy0) @ np.linalg.inv(K0).T
    x1n = _homog(xy1) @ np.linalg.inv(K1).T
    X = triangulate(R, t, x0n, x1n)
    z1 = X @ R[2] + t[2]
    final = (d < cfg.threshold_px) & np.isfinite(X).all(1) & (X[:, 2] > 0) & (z1 > 0)
    return final, d, X, x0n, x1n


def _summarise(
    R: np.ndarray, final: np.ndarray, d: np.ndarray, x0n: np.ndarray, x1n: np.ndarray, n: int, info: dict,
    cfg: PoseConfig,
) -> int:  # fmt: skip
    """Record the inlier diagnostics of a pose in ``info`` and raise on too few inliers, no baseline or a low
    inlier ratio. Returns the number of final inliers."""
    n_final = int(final.sum())
    if n_final < cfg.min_inliers:
        raise ReconstructionError(
            f"pose could not be estimated: {n_final} verified matches after refinement, need at least {cfg.min_inliers}"
        )
    parallax = float(np.median(_parallax_deg(R, x0n[final], x1n[final])))
    info.update(
        inliers=n_final,
        inlier_ratio=n_final / n,
        median_sampson_px=float(np.median(d[final])),
        median_parallax_deg=parallax,
        rotation_deg=_rotation_angle_deg(R),
    )
    if parallax < cfg.min_parallax_deg:
        raise ReconstructionError(
            f"no baseline: the median parallax of the {n_final} verified matches is {parallax:.2f}°, below "
            f"{cfg.min_parallax_deg}° (a pure rotation, or a scene too far away): move the camera sideways"
        )
    if n_final < cfg.min_inlier_ratio * n:
        raise ReconstructionError(
            f"pose is unreliable: only {n_final} of {n} matches ({100 * n_final / n:.0f} %) agree with the best "
            f"relative pose, need {100 * cfg.min_inlier_ratio:.0f} % (too little overlap or texture?)"
        )
    return n_final
