"""Multi-view triangulation of feature tracks: a linear DLT per point, vectorised over all points at once.

Each observation ``x`` of a point in camera ``c`` gives the ray ``u = K_c⁻¹ x`` (normalised so that ``u_z = 1``)
and the two independent rows of the cross product ``u × (P_c X) = 0`` with ``P_c = [R_c | t_c]``:
``(u_x P₃ − P₁) X = 0`` and ``(u_y P₃ − P₂) X = 0``. Each point's ``AᵀA`` (4 × 4) is summed over its observations
with :func:`numpy.add.at` and its eigenvector of the smallest eigenvalue, from one batched
:func:`numpy.linalg.eigh`, is the homogeneous point. Two refinements of the textbook DLT:

* the world is first moved and scaled so that the camera centres have zero mean and unit RMS spread (Hartley's
  normalisation of the 3-D side: the fourth column of ``A`` is then of the size of the other three);
* one reweighting pass divides each observation's rows by its depth at the first solution, which turns the algebraic
  error ``z (u − x/z)`` into the error in normalised image coordinates: a point much nearer to one camera than to
  another is no longer pulled towards the far camera's ray (Hartley & Sturm's iterative linear method, one step).

Conventions: OpenCV axes, ``X_cam = R · X_world + t``, pixel ``= K · X_cam / z`` (``K`` encodes the +0.5 pixel
centres). float64 throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import NonFiniteError, ShapeError

__all__ = ["Triangulated", "project", "reprojection_errors", "triangulate_tracks"]


@dataclass
class Triangulated:
    """Triangulated tracks, one row per point id ``0 .. n_points − 1``.

    Args:
        points: world points; NaN where undefined (fewer than 2 observations, or a point at infinity). [P, 3]
        ok: at least 2 observations, in front of every observing camera (``z > 0``), largest reprojection error at
            most ``max_error_px`` and largest ray angle at least ``min_angle_deg``. [P] bool
        reproj_error_px: the largest reprojection error over the point's observations, px; inf where undefined. [P]
        angle_deg: the exact largest angle between any two of the rays from the observing cameras' centres to the
            point, degrees; 0 where undefined. [P]
        n_obs: observations of the point. [P] int
    """

    points: np.ndarray
    ok: np.ndarray
    reproj_error_px: np.ndarray
    angle_deg: np.ndarray
    n_obs: np.ndarray


def project(
    R: np.ndarray, t: np.ndarray, K: np.ndarray, cam_idx: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of observations: ``X`` [O, 3] world points seen by cameras ``cam_idx`` [O] of
    ``R`` [C, 3, 3], ``t`` [C, 3], ``K`` [C, 3, 3]. Returns ``(pixels [O, 2], z [O])``; pixels are inf/NaN where
    ``z == 0``."""
    Xc = np.einsum("oij,oj->oi", R[cam_idx], X) + t[cam_idx]
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pix = np.einsum("oij,oj->oi", K[cam_idx][:, :2, :], Xc) / z[:, None]
    return pix, z


def reprojection_errors(
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    points: np.ndarray,
    cam_idx: np.ndarray,
    point_idx: np.ndarray,
    xy: np.ndarray,
) -> np.ndarray:
    """Reprojection error norm (px) of each observation ``xy`` [O, 2] of ``points[point_idx]`` in camera
    ``cam_idx``. [O]"""
    pix, _ = project(R, t, K, cam_idx, points[point_idx])
    return np.linalg.norm(pix - xy, axis=1)


def _check_inputs(
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    cam_idx: np.ndarray,
    point_idx: np.ndarray,
    xy: np.ndarray,
    n_points: int,
) -> None:
    """Raises ShapeError, NonFiniteError or ValueError (an index out of range)."""
    C = R.shape[0] if R.ndim == 3 else -1
    for name, a, want, shape in (
        ("R", R, "[C, 3, 3]", (C, 3, 3)),
        ("t", t, "[C, 3]", (C, 3)),
        ("K", K, "[C, 3, 3]", (C, 3, 3)),
        ("xy", xy, "[O, 2]", (cam_idx.shape[0], 2)),
        ("cam_idx", cam_idx, "[O]", (xy.shape[0],)),
        ("point_idx", point_idx, "[O]", (xy.shape[0],)),
    ):
        if a.shape != shape:
            raise ShapeError(name, a.shape, want)
    for name, a in (("R", R), ("t", t), ("K", K), ("xy", xy)):
        if not np.isfinite(a).all():
            raise NonFiniteError(f"{name} holds {int((~np.isfinite(a)).sum())} non-finite value(s) (NaN or Inf)")
    if cam_idx.size and (cam_idx.min() < 0 or cam_idx.max() >= C):
        raise ValueError(f"cam_idx must lie in 0..{C - 1}")
    if point_idx.size and (point_idx.min() < 0 or point_idx.max() >= n_points):
        raise ValueError(f"point_idx must lie in 0..{n_points - 1}")


def _normalisation(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """``(c, s)`` with ``X_world = c + s · X'``: the camera centres' mean and RMS distance from it (1 when they
    coincide), so that the normalised centres have unit spread."""
    centres = -np.einsum("cji,cj->ci", R, t)
    c = centres.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((centres - c) ** 2, axis=1))))
    return c, (s if s > 0 else 1.0)


def _solve_dlt(rows: np.ndarray, weight: np.ndarray, point_idx: np.ndarray, n_points: int) -> np.ndarray:
    """Homogeneous points [P, 4] minimising ``Σ w² ‖A X‖²`` over each point's rows ``rows`` [O, 2, 4] weighted by
    ``weight`` [O]: the eigenvector of the smallest eigenvalue of the summed ``AᵀA``."""
    M = np.einsum("oki,okj->oij", rows, rows) * (weight**2)[:, None, None]
    AtA = np.zeros((n_points, 4, 4))
    np.add.at(AtA, point_idx, M)
    _, vecs = np.linalg.eigh(AtA)
    return vecs[:, :, 0]


def _dehomogenise(Xh: np.ndarray, defined: np.ndarray) -> np.ndarray:
    """``Xh[:, :3] / Xh[:, 3]`` [P, 3]; NaN where not ``defined`` or at infinity (``w`` ≈ 0 at float precision)."""
    w = Xh[:, 3]
    finite = defined & (np.abs(w) > 1e-12 * np.linalg.norm(Xh[:, :3], axis=1))
    out = np.full((Xh.shape[0], 3), np.nan)
    out[finite] = Xh[finite, :3] / w[finite, None]
    return out


def _max_ray_angle_deg(
    centres: np.ndarray, X: np.ndarray, cam_idx: np.ndarray, point_idx: np.ndarray, n_obs: np.ndarray
) -> np.ndarray:
    """Exact largest angle (degrees) between the rays from the observing cameras' centres to each point, [P].

    Observations are sorted by point and the points grouped by their observation count ``k``; each group is one
    ``[P_k, k, k]`` batch of pairwise ``atan2(‖a × b‖, a · b)``: the cost is ``Σ_k P_k k²``, with no padding."""
    P = X.shape[0]
    angle = np.zeros(P)
    order = np.argsort(point_idx, kind="stable")
    start = np.concatenate(([0], np.cumsum(n_obs)[:-1]))
    rays = X[point_idx[order]] - centres[cam_idx[order]]  # [O, 3], grouped by point
    for k in np.unique(n_obs[(n_obs >= 2) & np.isfinite(X).all(axis=1)]):
        pts = np.flatnonzero((n_obs == k) & np.isfinite(X).all(axis=1))
        r = rays[start[pts][:, None] + np.arange(k)]  # [P_k, k, 3]
        a, b = np.triu_indices(int(k), 1)
        sin = np.linalg.norm(np.cross(r[:, a], r[:, b]), axis=-1)
        cos = np.sum(r[:, a] * r[:, b], axis=-1)
        angle[pts] = np.degrees(np.arctan2(sin, cos)).max(axis=1)
    return angle


def triangulate_tracks(
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    cam_idx: np.ndarray,
    point_idx: np.ndarray,
    xy: np.ndarray,
    n_points: int,
    *,
    max_error_px: float = 4.0,
    min_angle_deg: float = 1.5,
) -> Triangulated:
    """Triangulate every track with the normalised multi-view DLT (module docstring), all points in one batch.

    Args:
        R: world → camera rotations. [C, 3, 3]
        t: world → camera translations. [C, 3]
        K: intrinsics (pixel centres at +0.5). [C, 3, 3]
        cam_idx: the camera of each observation, in ``0 .. C − 1``. [O]
        point_idx: the point of each observation, in ``0 .. n_points − 1``; a point seen twice by one camera counts
            twice. [O]
        xy: the observed pixels. [O, 2]
        n_points: number of points ``P``; ids without observations come back undefined.
        max_error_px: largest reprojection error (px, any observation) of an ``ok`` point: 4 px lets through the
            linear solution's own error on 1–2 px localisation noise at short baselines, not a mismatched track.
        min_angle_deg: smallest largest-ray-angle of an ``ok`` point: below ~1.5° the depth's relative error is
            over ``σ_px / (f · angle)`` ≈ 5 % at 1 px and f = 800 px, and the point drags a bundle adjustment.

    Returns:
        :class:`Triangulated` with ``P = n_points`` rows.

    Raises:
        ShapeError, NonFiniteError: malformed inputs. ValueError: an index out of range.
    """
    R, t, K, xy = (np.asarray(a, dtype=np.float64) for a in (R, t, K, xy))
    cam_idx, point_idx = np.asarray(cam_idx, dtype=np.int64), np.asarray(point_idx, dtype=np.int64)
    _check_inputs(R, t, K, cam_idx, point_idx, xy, n_points)
    n_obs = np.bincount(point_idx, minlength=n_points)
    defined = n_obs >= 2

    c, s = _normalisation(R, t)
    P_norm = np.concatenate([R * s, (np.einsum("cij,j->ci", R, c) + t)[:, :, None]], axis=2)  # [C, 3, 4]
    u = np.einsum("oij,oj->oi", np.linalg.inv(K)[cam_idx], np.concatenate([xy, np.ones((len(xy), 1))], axis=1))
    u = u[:, :2] / u[:, 2:3]
    Po = P_norm[cam_idx]  # [O, 3, 4]
    rows = u[:, :, None] * Po[:, 2:3, :] - Po[:, :2, :]  # [O, 2, 4]

    Xh = _solve_dlt(rows, np.ones(len(xy)), point_idx, n_points)
    depth = np.abs(np.einsum("oj,oj->o", Po[:, 2, :], Xh[point_idx]))
    scale = np.maximum(depth, 1e-12 * np.linalg.norm(Xh[point_idx], axis=1))  # no division by an exact zero
    Xh = _solve_dlt(rows, 1.0 / scale, point_idx, n_points)
    X = c + s * _dehomogenise(Xh, defined)

    return _assess(R, t, K, cam_idx, point_idx, xy, X, n_obs, max_error_px, min_angle_deg)


def _assess(
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    cam_idx: np.ndarray,
    point_idx: np.ndarray,
    xy: np.ndarray,
    X: np.ndarray,
    n_obs: np.ndarray,
    max_error_px: float,
    min_angle_deg: float,
) -> Triangulated:
    """The checks of :class:`Triangulated` on the points ``X`` [P, 3] (NaN where undefined)."""
    n_points = X.shape[0]
    pix, z = project(R, t, K, cam_idx, X[point_idx])
    err = np.linalg.norm(pix - xy, axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    max_err = np.full(n_points, -np.inf)
    np.maximum.at(max_err, point_idx, err)
    min_z = np.full(n_points, np.inf)
    np.minimum.at(min_z, point_idx, np.where(np.isnan(z), -np.inf, z))
    finite = np.isfinite(X).all(axis=1) & (n_obs >= 2)
    max_err = np.where(finite, max_err, np.inf)

    centres = -np.einsum("cji,cj->ci", R, t)
    angle = _max_ray_angle_deg(centres, X, cam_idx, point_idx, n_obs)
    ok = finite & (min_z > 0) & (max_err <= max_error_px) & (angle >= min_angle_deg)
    return Triangulated(points=X, ok=ok, reproj_error_px=max_err, angle_deg=angle, n_obs=n_obs)
