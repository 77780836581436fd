"""Real spherical harmonics as used by 3D Gaussian splatting (degrees 0–3).

The basis, its constants and its sign convention are those of the 3DGS
reference implementation and gsplat, so SH coefficients read from any standard
3DGS PLY render the same colours. Colours are ``0.5 + Σ_l Y_l(dir)·coeff_l``
clamped at 0; ``dir`` is the unit vector from the camera centre to the
Gaussian, in world coordinates.
"""

from __future__ import annotations

import torch

__all__ = ["C0", "MAX_SH_DEGREE", "eval_sh", "num_sh_bases", "rgb_to_sh0", "sh0_to_rgb", "sh_degree_from_bases"]

MAX_SH_DEGREE = 3
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree``: ``(degree + 1)²``."""
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    """Inverse of :func:`num_sh_bases`; raises ``ValueError`` if ``k`` is not a square."""
    d = round(k**0.5) - 1
    if d < 0 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per channel is not (degree + 1)^2 for any degree")
    return d


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Colour in [0, 1] → band-0 coefficient. ``rgb: [..., 3]`` → ``[..., 3]``."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """Band-0 coefficient → colour (view-independent part). ``[..., 3]`` → ``[..., 3]``."""
    return sh0 * C0 + 0.5


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH colours. ``sh: [N, K, 3]``, ``dirs: [N, 3]`` unit vectors → ``[N, 3]``.

    Returns ``Σ_l Y_l(dir)·sh_l + 0.5``, *not* clamped (the caller clamps at 0).
    ``K`` must be 1, 4, 9 or 16.
    """
    k = sh.shape[-2]
    degree = sh_degree_from_bases(k)
    if degree > MAX_SH_DEGREE:
        raise ValueError(f"SH degree {degree} > {MAX_SH_DEGREE} is not supported")
    out = C0 * sh[:, 0]
    if degree >= 1:
        x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
        out = out - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
        if degree >= 2:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            out = (
                out
                + C2[0] * xy * sh[:, 4]
                + C2[1] * yz * sh[:, 5]
                + C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
                + C2[3] * xz * sh[:, 7]
                + C2[4] * (xx - yy) * sh[:, 8]
            )
            if degree >= 3:
                out = (
                    out
                    + C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
                    + C3[1] * xy * z * sh[:, 10]
                    + C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
                    + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
                    + C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
                    + C3[5] * z * (xx - yy) * sh[:, 14]
                    + C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
                )
    return out + 0.5
