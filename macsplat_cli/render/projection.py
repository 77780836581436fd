"""EWA projection of 3D Gaussians to the image plane (plain PyTorch, differentiable).

The maths follows the 3DGS / gsplat formulation: ``Σ = R S Sᵀ Rᵀ``, the local-affine
(EWA) Jacobian of the pinhole projection evaluated at a clamped position, a 0.3 px²
low-pass dilation of the 2D covariance, and the conic (inverse 2D covariance).

Numerical guards, each applied before the operation it protects:

* Gaussians with a non-finite parameter, or with ``z ≤ near`` or ``z ≥ far``, are culled
  by index selection *before* any division by ``z`` (a ``torch.where`` would still
  back-propagate the masked branch's inf as NaN).
* Quaternions are normalised inside the rotation formula; ``|q| → 0`` gives the identity
  with zero gradient (see :func:`~macsplat_cli.rotations.quat_to_rotmat`).
* The Jacobian is evaluated at ``x/z, y/z`` clamped to the image bounds plus 30 % of the
  half field of view, so Gaussians far off-screen do not get huge skewed footprints.
* Scales are capped so that the projected standard deviation stays below
  ``MAX_SCREEN_STD`` pixels (a Gaussian that wide is flat across any image); this keeps
  every 2D covariance, its determinant and ``exp(log_scale)`` finite in float32.
* The 2D determinant is computed as a sum of squared 2×2 minors (Cauchy–Binet), which is
  never negative, plus the dilation terms, so ``det ≥ eps2d²`` and the conic is finite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..rotations import quat_to_rotmat
from ..sh import eval_sh
from .constants import ALPHA_MIN

__all__ = ["MAX_SCREEN_STD", "Projection", "project_gaussians"]

MAX_SCREEN_STD = 1.0e5
"""Largest projected standard deviation, in pixels (see the module docstring)."""
_BBOX_MARGIN = 1e-2  # pixels: keeps round-off at the support boundary on the safe side


@dataclass
class Projection:
    """Visible Gaussians projected into one camera, sorted front to back.

    Attributes:
        ids: index of each visible Gaussian in the input set. [M] int64
        means2d: centres in pixels; pixel (i, j) has its centre at (j + 0.5, i + 0.5). [M, 2]
        conics: inverse of the dilated 2D covariance, (a, b, c) for [[a, b], [b, c]]. [M, 3]
        depths: camera-space z. [M]
        opacities: sigmoid of the opacity logits. [M]
        colors: SH colours, clamped at 0. [M, 3]
        pixel_rect: inclusive pixel bounds (x0, x1, y0, y1) of the support where
            alpha ≥ 1/255, clipped to the image. [M, 4] int32, no gradient
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    pixel_rect: torch.Tensor

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def project_gaussians(
    means: torch.Tensor,  # [N, 3]
    log_scales: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4]
    opacity_logits: torch.Tensor,  # [N]
    sh: torch.Tensor,  # [N, K, 3]
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """Project Gaussians into a pinhole camera and cull those that cannot be seen.

    Args:
        means: world-space centres. [N, 3]
        log_scales: log standard deviations. [N, 3]
        quats: (w, x, y, z) rotations, any norm. [N, 4]
        opacity_logits: pre-sigmoid opacities. [N]
        sh: SH coefficients, band-major. [N, K, 3]
        viewmat: world-to-camera transform, OpenCV axes. [4, 4]
        K: pinhole intrinsics in pixels (skew allowed). [3, 3]
        width: image width in pixels.
        height: image height in pixels.
        near: Gaussians with ``z ≤ near`` are culled.
        far: Gaussians with ``z ≥ far`` are culled.
        eps2d: dilation added to the 2D covariance diagonal, in px².

    Returns:
        The visible Gaussians, front to back (:class:`Projection`).
    """
    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    K = K.to(dtype)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    ids = _visible_ids(means, log_scales, quats, opacity_logits, sh, R, t, near, far)

    means_c = means[ids] @ R.T + t  # [M, 3]
    x, y, z = means_c.unbind(-1)
    inv_z = 1.0 / z
    fx, skew, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    means2d = torch.stack([(fx * x + skew * y) * inv_z + cx, fy * y * inv_z + cy], dim=-1)
    J = _jacobian(x, y, z, inv_z, K, width, height)
    conics, a_blur, c_blur = _conics(J, R, quats[ids], log_scales[ids], z, K, eps2d)
    opacities = torch.sigmoid(opacity_logits[ids])
    order, rect = _support_rects(means2d, opacities, a_blur, c_blur, z, width, height)

    ids_sorted = ids[order]
    colors = _colors(sh[ids_sorted], means[ids_sorted], R, t)
    return Projection(
        ids=ids_sorted,
        means2d=means2d[order],
        conics=conics[order],
        depths=z[order],
        opacities=opacities[order],
        colors=colors,
        pixel_rect=rect.contiguous(),
    )


@torch.no_grad()
def _visible_ids(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    near: float,
    far: float,
) -> torch.Tensor:
    """The cheap culls, no gradient, before any division: indices [M] of the Gaussians with finite parameters,
    ``near < z < far`` and an opacity of at least ``ALPHA_MIN``."""
    dtype, device = means.dtype, means.device
    finite = torch.isfinite(means).all(1) & torch.isfinite(log_scales).all(1)
    finite &= torch.isfinite(quats).all(1) & torch.isfinite(opacity_logits)
    finite &= torch.isfinite(sh).flatten(1).all(1)
    z = torch.where(finite, means @ R[2] + t[2], torch.zeros((), dtype=dtype, device=device))
    logit_min = math.log(ALPHA_MIN / (1.0 - ALPHA_MIN))
    keep = finite & (z > near) & (z < far) & (opacity_logits >= logit_min)
    return keep.nonzero().squeeze(1)


def _jacobian(
    x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, inv_z: torch.Tensor, K: torch.Tensor, width: int, height: int
) -> torch.Tensor:
    """Jacobian of the pinhole projection at camera points ``(x, y, z)`` [M] each, evaluated at ``x/z, y/z``
    clamped to the image bounds plus 30 % of the half field of view. [M, 2, 3]"""
    fx, skew, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    u = torch.clamp(x * inv_z, -(cx / fx + 0.3 * tan_fovx), (width - cx) / fx + 0.3 * tan_fovx)
    v = torch.clamp(y * inv_z, -(cy / fy + 0.3 * tan_fovy), (height - cy) / fy + 0.3 * tan_fovy)
    zero = torch.zeros_like(z)
    return torch.stack(
        [
            torch.stack([fx * inv_z, skew * inv_z, -(fx * u + skew * v) * inv_z], -1),
            torch.stack([zero, fy * inv_z, -fy * v * inv_z], -1),
        ],
        dim=-2,
    )


def _conics(
    J: torch.Tensor,
    R: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    z: torch.Tensor,
    K: torch.Tensor,
    eps2d: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The dilated 2D covariances of the visible Gaussians (``J`` [M, 2, 3], ``quats`` [M, 4], ``log_scales``
    [M, 3], camera depths ``z`` [M]) as conics [M, 3], with their diagonal ``a + eps2d``, ``c + eps2d`` [M] each."""
    fx, skew, fy = K[0, 0], K[0, 1], K[1, 1]
    # Σ_cam = M Mᵀ with M = R_wc R_q S; the scale cap keeps J·M within MAX_SCREEN_STD px.
    f_max = torch.maximum(fx.abs(), fy.abs()) + skew.abs()
    log_cap = torch.log(z.detach() * (MAX_SCREEN_STD / f_max))
    scales = torch.exp(torch.minimum(log_scales, log_cap[:, None]))
    Mc = (R @ quat_to_rotmat(quats)) * scales[:, None, :]  # [M, 3, 3]
    M2 = J @ Mc  # [M, 2, 3]: cov2d = M2 M2ᵀ
    r0, r1 = M2[:, 0], M2[:, 1]
    a = (r0 * r0).sum(-1)
    b = (r0 * r1).sum(-1)
    c = (r1 * r1).sum(-1)
    minors = torch.stack(
        [
            r0[:, 0] * r1[:, 1] - r0[:, 1] * r1[:, 0],
            r0[:, 0] * r1[:, 2] - r0[:, 2] * r1[:, 0],
            r0[:, 1] * r1[:, 2] - r0[:, 2] * r1[:, 1],
        ],
        -1,
    )
    det = (minors * minors).sum(-1) + eps2d * (a + c) + eps2d * eps2d  # = (a+ε)(c+ε) − b² ≥ ε²
    a_blur = a + eps2d
    c_blur = c + eps2d
    return torch.stack([c_blur / det, -b / det, a_blur / det], dim=-1), a_blur, c_blur


@torch.no_grad()
def _support_rects(
    means2d: torch.Tensor,
    opacities: torch.Tensor,
    a_blur: torch.Tensor,
    c_blur: torch.Tensor,
    z: torch.Tensor,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussians whose support (alpha ≥ 1/255) reaches the image, front to back: ``(order, rect)``, indices
    [S] into the visible set and their inclusive pixel bounds (x0, x1, y0, y1) [S, 4] int32.

    Support where alpha ≥ 1/255: σ = ½ dᵀ Σ⁻¹ d ≤ ln(255·op), an ellipse whose bounding box has half-widths
    sqrt(2 ln(255 op) Σ_xx), sqrt(2 ln(255 op) Σ_yy).
    """
    level = 2.0 * torch.log(opacities * 255.0).clamp_min(0.0)
    rx = torch.sqrt(level * a_blur) + _BBOX_MARGIN
    ry = torch.sqrt(level * c_blur) + _BBOX_MARGIN
    mx, my = means2d[:, 0], means2d[:, 1]
    big = float(4 * max(width, height) + 16)  # keep the float→int conversion in range
    x0 = torch.ceil((mx - rx - 0.5).clamp(-big, big)).clamp_min(0)
    x1 = torch.floor((mx + rx - 0.5).clamp(-big, big)).clamp_max(width - 1)
    y0 = torch.ceil((my - ry - 0.5).clamp(-big, big)).clamp_min(0)
    y1 = torch.floor((my + ry - 0.5).clamp(-big, big)).clamp_max(height - 1)
    on_screen = (x0 <= x1) & (y0 <= y1) & (level > 0)
    sel = on_screen.nonzero().squeeze(1)
    order = sel[torch.argsort(z.detach()[sel], stable=True)]
    return order, torch.stack([x0, x1, y0, y1], -1)[order].to(torch.int32)


def _colors(sh: torch.Tensor, means: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """SH colours seen from the camera centre ``-Rᵀt``, clamped at 0. → [M, 3]"""
    if sh.shape[1] == 1:
        dirs = means  # unused by degree 0
    else:
        campos = -(R.T @ t)
        d = means - campos
        # z > near guarantees |d| ≥ near, so the normalisation is safe.
        dirs = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return torch.clamp_min(eval_sh(sh, dirs), 0.0)
