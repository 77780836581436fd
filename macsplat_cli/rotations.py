"""Quaternions and rotation matrices: every converter macsplat uses, in one place.

**Convention.** Quaternions are Hamilton quaternions stored **(w, x, y, z)** (scalar first), as the
3DGS PLY format, gsplat and COLMAP store them. A rotation ``R`` acts on column vectors (``x' = R x``).
The only other order met in macsplat is Splatt3R's (x, y, z, w) rotation channels, which
:mod:`macsplat_cli.neural.gaussian_head` reorders where it reads them.

NumPy versions (float64, for cameras and poses) and torch versions (differentiable, for the
Gaussian parameters) exist where both are used:

=====================  ===========================  ==========================
conversion             NumPy                        torch
=====================  ===========================  ==========================
matrix → quaternion    :func:`rotmat_to_quat_np`    :func:`rotmat_to_quat`
quaternion → matrix    :func:`quat_to_rotmat_np`    :func:`quat_to_rotmat`
product ``a ⊗ b``      —                            :func:`quat_multiply`
=====================  ===========================  ==========================

All of them take any leading batch shape (``[..., 4]``, ``[..., 3, 3]``).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "nearest_rotation",
    "quat_multiply",
    "quat_to_rotmat",
    "quat_to_rotmat_np",
    "rotmat_to_quat",
    "rotmat_to_quat_np",
]


# ------------------------------------------------------------------------------------ NumPy
def _norm(q: np.ndarray) -> np.ndarray:
    """Euclidean norms, rounded as ``np.linalg.norm`` rounds one vector (a dot product). [..., n] → [..., 1]"""
    return np.sqrt(q[..., None, :] @ q[..., :, None])[..., 0]


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` in the Frobenius norm (``U diag(1, 1, ±1) Vᵀ`` of its SVD). [..., 3, 3] float64

    Orthonormal to a few units of roundoff; for a matrix that is already a rotation to ~1e-9 (what OpenCV's
    decompositions return) it moves each entry by about that much.
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, np.float64))
    Vt[..., 2, :] *= np.sign(np.linalg.det(U @ Vt))[..., None]  # a reflection becomes the nearest rotation
    return U @ Vt


def rotmat_to_quat_np(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z), ``w ≥ 0``, of rotation matrices. [..., 3, 3] → [..., 4] float64

    Uses, for each matrix, the branch of Shepperd's method with the largest pivot (the trace or
    a diagonal entry), so it is accurate for every rotation, including 180° turns (``w = 0``).

    Args:
        R: rotation matrices. [..., 3, 3]

    Returns:
        ``q`` with ``quat_to_rotmat_np(q) ≈ R``. [..., 4]
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape [..., 3, 3], got {list(R.shape)}")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    pivot = np.argmax(np.stack([trace, m00, m11, m22], axis=-1), axis=-1)
    radicand = np.stack(
        [1.0 + trace, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], axis=-1
    )  # 4w², 4x², 4y², 4z²
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(radicand, pivot[..., None], -1)[..., 0], 0.0))  # 4·(pivot)
    a, b, c = m21 - m12, m02 - m20, m10 - m01
    d, e, f = m01 + m10, m02 + m20, m12 + m21
    q_s = 0.25 * s
    with np.errstate(divide="ignore", invalid="ignore"):  # other branches' s may be 0; they are discarded
        cands = np.stack(
            [
                np.stack([q_s, a / s, b / s, c / s], -1),  # s = 4w
                np.stack([a / s, q_s, d / s, e / s], -1),  # s = 4x
                np.stack([b / s, d / s, q_s, f / s], -1),  # s = 4y
                np.stack([c / s, e / s, f / s, q_s], -1),  # s = 4z
            ],
            axis=-2,
        )
    q = np.take_along_axis(cands, pivot[..., None, None], -2)[..., 0, :]
    q = q / _norm(q)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_rotmat_np(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of (w, x, y, z) quaternions, normalised first. [..., 4] → [..., 3, 3] float64

    Args:
        q: non-zero quaternions. [..., 4]
    """
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q / _norm(q), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


# ------------------------------------------------------------------------------------ torch
def quat_to_rotmat(quats: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rotation matrices from (w, x, y, z) quaternions of any non-zero norm. [..., 4] → [..., 3, 3]

    Uses ``R = I + s·(...)`` with ``s = 2 / |q|²``, which equals the usual formula for
    the normalised quaternion. Quaternions with ``|q|² ≤ eps`` give the identity
    with zero gradient instead of the NaN/1e12 gradients of normalising a zero vector.
    """
    w, x, y, z = quats.unbind(-1)
    n2 = (quats * quats).sum(-1)
    ok = n2 > eps
    s = torch.where(ok, 2.0 / torch.where(ok, n2, torch.ones_like(n2)), torch.zeros_like(n2))
    r = torch.stack(
        [
            1 - s * (y * y + z * z),
            s * (x * y - w * z),
            s * (x * z + w * y),
            s * (x * y + w * z),
            1 - s * (x * x + z * z),
            s * (y * z - w * x),
            s * (x * z - w * y),
            s * (y * z + w * x),
            1 - s * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(*quats.shape[:-1], 3, 3)


def rotmat_to_quat(R: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Unit quaternions (w, x, y, z), ``w ≥ 0``, of rotation matrices. [..., 3, 3] → [..., 4]

    The torch twin of :func:`rotmat_to_quat_np` (same branches and arithmetic; in float64 the two
    agree to ~2e-16, the rounding of the final normalisation), on ``R``'s device and in its dtype;
    an array is converted with ``torch.as_tensor`` first. Not meant to be differentiated (the
    branch choice is discrete).
    """
    R = torch.as_tensor(R)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape [..., 3, 3], got {list(R.shape)}")
    m = R.unbind(-1)
    (m00, m10, m20), (m01, m11, m21), (m02, m12, m22) = (c.unbind(-1) for c in m)
    trace = m00 + m11 + m22
    pivot = torch.stack([trace, m00, m11, m22], -1).argmax(-1, keepdim=True)
    radicand = torch.stack([1.0 + trace, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1)
    s = 2.0 * torch.sqrt(torch.gather(radicand, -1, pivot)[..., 0].clamp_min(0.0))
    a, b, c = m21 - m12, m02 - m20, m10 - m01
    d, e, f = m01 + m10, m02 + m20, m12 + m21
    q_s = 0.25 * s
    cands = torch.stack(
        [
            torch.stack([q_s, a / s, b / s, c / s], -1),
            torch.stack([a / s, q_s, d / s, e / s], -1),
            torch.stack([b / s, d / s, q_s, f / s], -1),
            torch.stack([c / s, e / s, f / s, q_s], -1),
        ],
        dim=-2,
    )
    q = torch.gather(cands, -2, pivot[..., None].expand(*pivot.shape[:-1], 1, 4))[..., 0, :]
    q = q / torch.sqrt(q[..., None, :] @ q[..., :, None])[..., 0]
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b`` of (w, x, y, z) quaternions: rotation ``a`` after ``b``. [..., 4]"""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )
