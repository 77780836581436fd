"""More than two context views: the pose errors over the context pairs, and the reconstruction's frame aligned
with the ground truth.

A reconstruction of N > 2 photos lives in its own frame (the first registered photo's camera, the first pair's
baseline as unit): a similarity away from the data set's. What is measured must not depend on that gauge.

* **Pose** (:func:`pairwise_pose_errors`): for every pair (i, j) of registered context views, the relative pose
  ``T_j←i = inv(cam_to_world_j) · cam_to_world_i`` of the estimate against the truth: its rotation error and its
  translation-direction error. A similarity ``X ↦ s·Q·X + T`` of the estimated frame leaves the relative rotation
  unchanged and multiplies the relative translation by ``s``, so neither error changes (gauge-free).
* **Frame** (:func:`fit_similarity`): the similarity taking the estimated frame to the data set's,
  ``X_true = s·Q·X_est + T``, from the registered cameras: Umeyama's least squares on the camera centres, with the
  cameras' orientations added to the rotation's cross-covariance. The centres alone leave the rotation about their
  line free when they are collinear (a camera path along a line, common in sequences); the orientations fix it.
  The rotation maximises ``⟨Q, 3·Σ ŷ x̂ᵀ / (σ_x σ_y) + Σ R_true R_estᵀ / M⟩`` (centred centres ``x̂``,
  ``ŷ`` with spreads ``σ``, M cameras; both terms at most 3, one weight each), by SVD with the determinant
  fixed to +1; then ``s = Σ ŷ · Q x̂ / Σ |x̂|²`` (1 for a metric reconstruction) and ``T = ȳ − s·Q·x̄``.
  Exact for exact cameras from two registered views up.
* **Targets** (:func:`aligned_camera`): the true target camera carried into the estimated frame by the inverse
  similarity, in reconstruction units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cameras import Camera
from ..metrics import rotation_error_deg, translation_direction_error_deg

__all__ = ["PairError", "Similarity", "aligned_camera", "fit_similarity", "pairwise_pose_errors"]


@dataclass(frozen=True)
class Similarity:
    """``X_true = scale · Q · X_est + T``: the estimated frame into the data set's.

    Attributes:
        scale: reconstruction units → scene units.
        Q: rotation. [3, 3] float64
        T: translation. [3] float64
    """

    scale: float
    Q: np.ndarray
    T: np.ndarray

    def apply_to_cameras(self, cam_to_world: np.ndarray) -> np.ndarray:
        """Cameras carried by the similarity (the camera frames stay rigid: rotation ``Q·R``, centre
        ``s·Q·C + T``). [M, 4, 4] → [M, 4, 4]"""
        out = np.array(cam_to_world, np.float64, copy=True)
        out[:, :3, :3] = self.Q @ out[:, :3, :3]
        out[:, :3, 3] = self.scale * out[:, :3, 3] @ self.Q.T + self.T
        return out


@dataclass(frozen=True)
class PairError:
    """The relative-pose errors of context views ``i`` and ``j`` (positions in the case's context)."""

    i: int
    j: int
    rotation_deg: float
    translation_deg: float


def _relative(c2w_i: np.ndarray, c2w_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_j←i``: camera i's coordinates into camera j's; rotation [3, 3], translation [3]."""
    R_j, C_j = c2w_j[:3, :3], c2w_j[:3, 3]
    return R_j.T @ c2w_i[:3, :3], R_j.T @ (c2w_i[:3, 3] - C_j)


def pairwise_pose_errors(
    est_cam_to_world: np.ndarray, true_cam_to_world: np.ndarray, positions: list[int] | None = None
) -> list[PairError]:
    """Relative rotation and translation-direction errors of every pair of cameras (module docstring).

    Args:
        est_cam_to_world: the estimated cameras. [M, 4, 4]
        true_cam_to_world: the same cameras' truth. [M, 4, 4]
        positions: each camera's position in the case's context (default 0 … M − 1), for the result's labels.

    Returns:
        One error per pair ``i < j``, M(M − 1)/2 in all.
    """
    est = np.asarray(est_cam_to_world, np.float64)
    true = np.asarray(true_cam_to_world, np.float64)
    pos = positions if positions is not None else list(range(len(est)))
    out = []
    for a in range(len(est)):
        for b in range(a + 1, len(est)):
            R_e, t_e = _relative(est[a], est[b])
            R_t, t_t = _relative(true[a], true[b])
            out.append(
                PairError(pos[a], pos[b], rotation_error_deg(R_e, R_t), translation_direction_error_deg(t_e, t_t))
            )
    return out


def fit_similarity(est_cam_to_world: np.ndarray, true_cam_to_world: np.ndarray, *, fix_scale: bool) -> Similarity:
    """The similarity taking the estimated cameras onto the true ones (module docstring).

    Args:
        est_cam_to_world: the registered cameras as estimated. [M, 4, 4], M ≥ 1
        true_cam_to_world: their truth. [M, 4, 4]
        fix_scale: keep ``scale = 1`` (a metric reconstruction).
    """
    est = np.asarray(est_cam_to_world, np.float64)
    true = np.asarray(true_cam_to_world, np.float64)
    x, y = est[:, :3, 3], true[:, :3, 3]
    xm, ym = x.mean(0), y.mean(0)
    xc, yc = x - xm, y - ym  # [M, 3]
    sx, sy = float(np.sqrt((xc**2).sum())), float(np.sqrt((yc**2).sum()))
    M = np.einsum("mab,mcb->ac", true[:, :3, :3], est[:, :3, :3]) / len(est)  # Σ R_true R_estᵀ / M
    if sx > 0 and sy > 0:
        M = M + 3.0 * (yc.T @ xc) / (sx * sy)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt))) or 1.0])
    Q = U @ D @ Vt
    scale = 1.0
    if not fix_scale and sx > 0:
        scale = float(np.sum(yc * (xc @ Q.T))) / sx**2
        scale = scale if scale > 0 else 1.0
    return Similarity(scale, Q, ym - scale * Q @ xm)


def aligned_camera(
    target: Camera, sim: Similarity, *, width: int, height: int, focal_ratio: tuple[float, float]
) -> Camera:
    """The true target camera in the estimated frame, in reconstruction units.

    Args:
        target: the target's true camera (the data set's frame).
        sim: the estimated frame into the data set's (:func:`fit_similarity`).
        width: render width.
        height: render height.
        focal_ratio: (fx, fy) multipliers of the true focal lengths.
    """
    w2c = np.eye(4)
    w2c[:3, :3] = target.R @ sim.Q
    w2c[:3, 3] = (target.R @ sim.T + target.t) / sim.scale
    K = target.rescaled(width, height).K.copy()
    K[0, 0] *= focal_ratio[0]
    K[0, 1] *= focal_ratio[0]
    K[1, 1] *= focal_ratio[1]
    return Camera(target.name, width, height, K, np.linalg.inv(w2c))
