"""The one non-linear refit of a relative pose: Levenberg–Marquardt on Cauchy-weighted Sampson distances.

Parameters: the rotation (3, a Rodrigues increment multiplied onto ``R``), the translation direction (2, along two
unit vectors ⟂ ``t``, renormalised) and, optionally, the log of a focal-length scale shared by the views whose
focal is unknown (under a log-normal prior). The Jacobian is a central difference of the Sampson distances, all
``2 · P`` poses in one stacked call. Every user (the pose stage's refinement, the focal sensitivity, the planar
candidates, the confidence's re-fits) calls :func:`refit_pose`, with one of the damping schedules below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from ...camera_math import scale_focal
from .geometry import fundamental_from_inverses, fundamental_from_pose, sampson_distance

__all__ = [
    "CHECK_GN", "MAD_TO_STD", "POSE_LM", "SENSITIVITY_LM", "FocalFit", "Refit", "RefitSchedule", "apply_step",
    "pose_jacobian", "refit_pose",
]  # fmt: skip

MAD_TO_STD = 1.4826
"""The standard deviation of a normal distribution per unit of its median absolute deviation."""


@dataclass(frozen=True)
class RefitSchedule:
    """How :func:`refit_pose` iterates and damps.

    Args:
        iters: outer iterations (one Jacobian each).
        damping: the first damping λ, relative to the diagonal of the normal equations.
        damping_down: λ is divided by this after an accepted step (1: fixed)...
        damping_floor: ...down to this.
        damping_up: λ is multiplied by this after a rejected step.
        tries: steps tried per iteration; none lowering the cost ends the refit.
        min_step: an accepted step shorter than this ends the refit.
        fd_step: the central-difference step of the Jacobian.
    """

    iters: int
    damping: float
    damping_down: float
    damping_floor: float
    damping_up: float
    tries: int
    min_step: float
    fd_step: float = 1e-6


POSE_LM = RefitSchedule(
    iters=30, damping=1e-3, damping_down=3.0, damping_floor=1e-9, damping_up=4.0, tries=10, min_step=1e-10
)
"""The pose stage's refinement: adaptive Levenberg–Marquardt, up to ten tries per iteration."""
SENSITIVITY_LM = replace(POSE_LM, iters=15)
"""The focal sensitivity's refits (two per pose, from a converged pose: fewer iterations suffice)."""
CHECK_GN = RefitSchedule(
    iters=15, damping=1e-6, damping_down=1.0, damping_floor=1e-9, damping_up=1.0, tries=1, min_step=1e-9
)
"""The confidence's re-fits: Gauss–Newton (a fixed tiny damping), stopping at the first step that does not lower
the cost (where the pose's own matches move it, not how far a patient search could)."""


@dataclass(frozen=True)
class FocalFit:
    """Fit the shared log focal scale too.

    Args:
        prior_sigma: std of its log-normal prior around the starting focal.
        noise_floor_px: the residuals' noise level used for its data-only std is at least this.
    """

    prior_sigma: float
    noise_floor_px: float


@dataclass
class Refit:
    """The outcome of :func:`refit_pose`.

    Attributes:
        R: rotation. [3, 3]
        t: translation direction, unit. [3]
        log_focal: the log focal scale (the start when it was not fitted).
        log_focal_std: its data-only standard deviation (the pose marginalised out, at the residuals' robust noise
            level); ``inf`` when it was not fitted or is undetermined.
        residuals: signed Sampson distances of the matches at the result (px). [M]
        noise_px: the residuals' robust noise level at the last iteration, when the focal was fitted.
    """

    R: np.ndarray
    t: np.ndarray
    log_focal: float
    log_focal_std: float
    residuals: np.ndarray
    noise_px: float | None = None


def refit_pose(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, *,
    scale_px: float = 1.0, schedule: RefitSchedule = CHECK_GN, log_focal: float = 0.0,
    unknown: tuple[bool, bool] = (True, True), focal: FocalFit | None = None,
) -> Refit:  # fmt: skip
    """The pose ``(R, t)`` re-fitted on the matches ``xy0, xy1`` [M, 2] (module docstring).

    Args:
        R, t: the start. [3, 3], unit [3]
        K0, K1: the intrinsics; a view whose focal is ``unknown`` has it scaled by ``exp(log_focal)``. [3, 3]
        scale_px: the Cauchy loss's scale (px).
        schedule: the damping schedule.
        log_focal: the (starting) log focal scale.
        focal: fit the log focal scale too, with this prior; None: it stays fixed.

    Returns:
        :class:`Refit`.
    """
    n_par = 6 if focal is not None else 5
    h = schedule.fd_step

    def residuals(R_: np.ndarray, t_: np.ndarray, s_: float) -> np.ndarray:
        return sampson_distance(fundamental_from_pose(R_, t_, *_intrinsics(K0, K1, s_, unknown)), xy0, xy1)

    def jacobian(R_: np.ndarray, t_: np.ndarray, s_: float) -> np.ndarray:
        return pose_jacobian(R_, t_, K0, K1, xy0, xy1, log_focal=s_, unknown=unknown, n_par=n_par, step=h)

    def cost(r_: np.ndarray, s_: float) -> float:
        c = float(np.sum(np.log1p((r_ / scale_px) ** 2)))
        return c + ((s_ / focal.prior_sigma) ** 2 if focal is not None else 0.0)

    lam = schedule.damping
    s = log_focal
    r = residuals(R, t, s)
    current = cost(r, s)
    info_s, noise = 0.0, None
    for _ in range(schedule.iters):
        w = 1.0 / (1.0 + (r / scale_px) ** 2)  # IRLS weights of the Cauchy loss
        J = jacobian(R, t, s)
        H = (J * (w / scale_px**2)[:, None]).T @ J
        g = (J * (w / scale_px**2)[:, None]).T @ r
        if focal is not None:
            noise, info_s = _focal_information(J, w, r, s, H, g, focal)
        improved = False
        for _ in range(schedule.tries):
            try:
                step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            except np.linalg.LinAlgError:
                break
            cand = apply_step(step, R, t, s)
            r_c = residuals(*cand)
            c_c = cost(r_c, cand[2])
            if c_c < current:
                R, t, s = cand
                r, current = r_c, c_c
                lam = max(lam / schedule.damping_down, schedule.damping_floor)
                improved = True
                break
            lam *= schedule.damping_up
        if not improved or np.linalg.norm(step) < schedule.min_step:
            break
    std_s = 1.0 / math.sqrt(info_s) if info_s > 0 else math.inf
    return Refit(R, t, s, std_s, r, noise)


def _intrinsics(K0: np.ndarray, K1: np.ndarray, s: float, unknown: tuple[bool, bool]) -> tuple[np.ndarray, np.ndarray]:
    """``K0, K1`` with the focal of each ``unknown`` view scaled by ``exp(s)``."""
    return (scale_focal(K0, s) if unknown[0] else K0), (scale_focal(K1, s) if unknown[1] else K1)


def apply_step(
    theta: np.ndarray, R: np.ndarray, t: np.ndarray, s: float, basis: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """The pose after the parameter step ``theta`` [5] or [6] (module docstring): ``(R, t, log focal scale)``.
    ``basis``: :func:`_perpendicular` of ``t`` when the caller has it (the same value)."""
    dR, _ = cv2.Rodrigues(theta[:3].reshape(3, 1))
    basis = _perpendicular(t) if basis is None else basis
    t_new = t + theta[3:5] @ basis
    return dR @ R, t_new / np.linalg.norm(t_new), s + (theta[5] if len(theta) > 5 else 0.0)


def _perpendicular(t: np.ndarray) -> np.ndarray:
    """Two unit vectors ⟂ ``t`` [3] (the translation direction's step basis). [2, 3]"""
    return np.linalg.svd(t.reshape(1, 3))[2][1:]


def pose_jacobian(
    R: np.ndarray, t: np.ndarray, K0: np.ndarray, K1: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, *,
    log_focal: float = 0.0, unknown: tuple[bool, bool] = (True, True), n_par: int = 5, step: float = 1e-6,
) -> np.ndarray:  # fmt: skip
    """The Jacobian of the signed Sampson distances of ``xy0, xy1`` [M, 2] over the pose's parameters (rotation 3,
    translation direction 2, and with ``n_par = 6`` the log focal scale of the ``unknown`` views), by central
    differences with ``step``, all ``2 · n_par`` poses in one stacked call. [M, n_par]"""
    steps = np.concatenate([np.eye(n_par), -np.eye(n_par)]) * step
    basis = _perpendicular(t)  # the same for every step: computed once
    inverses: dict[float, tuple[np.ndarray, np.ndarray]] = {}  # per focal scale: K0⁻¹, K1⁻ᵀ

    def fundamental(a: np.ndarray, b: np.ndarray, c: float) -> np.ndarray:
        if c not in inverses:
            k0, k1 = _intrinsics(K0, K1, c, unknown)
            inverses[c] = np.linalg.inv(k0), np.linalg.inv(k1).T
        return fundamental_from_inverses(a, b, *inverses[c])

    Fs = [fundamental(*apply_step(d, R, t, log_focal, basis)) for d in steps]
    r_ = sampson_distance(np.stack(Fs), xy0, xy1)  # [2·n_par, M], central differences
    return ((r_[:n_par] - r_[n_par:]) / (2 * step)).T


def _focal_information(
    J: np.ndarray, w: np.ndarray, r: np.ndarray, s: float, H: np.ndarray, g: np.ndarray, focal: FocalFit
) -> tuple[float, float]:
    """Add the focal prior to the normal equations ``H, g`` (in place) and return ``(noise_px, information)``: the
    residuals' robust noise level, and the information about the log focal from the data alone at that level (the
    Cauchy scale is a tolerance, not a noise estimate), the pose marginalised out (Schur complement)."""
    noise = max(MAD_TO_STD * float(np.median(np.abs(r))), focal.noise_floor_px)
    H_data = (J * (w / noise**2)[:, None]).T @ J
    H[5, 5] += 1.0 / focal.prior_sigma**2
    g[5] += s / focal.prior_sigma**2
    try:
        info_s = float(H_data[5, 5] - H_data[5, :5] @ np.linalg.solve(H_data[:5, :5], H_data[:5, 5]))
    except np.linalg.LinAlgError:
        info_s = 0.0
    return noise, info_s
