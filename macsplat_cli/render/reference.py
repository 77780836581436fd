"""Plain-PyTorch twin of the Numba compositor: dense, slow, obviously correct.

Every pixel is tested against every Gaussian, so this is for small images and a few
hundred Gaussians: tests use it as the oracle for the compiled kernels (forward values
and gradients, float64 gradcheck). Autograd provides the backward pass.

The rules are those of ``_kernels.py``: alpha = min(0.99, o·exp(−σ)); samples with
σ < 0 or alpha < 1/255 are skipped; a pixel stops before the first sample that would
bring its transmittance to ≤ 1e-4. The support rectangles the kernels use are not needed
here: outside them alpha < 1/255 by construction.
"""

from __future__ import annotations

import torch

from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN

__all__ = ["composite_reference"]


def composite_reference(
    means2d: torch.Tensor,  # [M, 2]
    conics: torch.Tensor,  # [M, 3]
    opacities: torch.Tensor,  # [M]
    features: torch.Tensor,  # [M, C]
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract as :func:`~macsplat_cli.render.composite.composite`. → ([H, W, C], [H, W])"""
    dtype, device = means2d.dtype, means2d.device
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5,
        torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)  # [P, 2]
    d = pix[:, None, :] - means2d[None, :, :]  # [P, M, 2]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy  # [P, M]
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=ALPHA_MAX)
    keep = (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        # The product including sample k; the pixel stops at the first k where it is ≤ T_MIN.
        added = torch.cumprod(1.0 - alpha, dim=1) > T_MIN
    alpha = alpha * added
    one_minus = 1.0 - alpha
    trans_incl = torch.cumprod(one_minus, dim=1)
    trans_excl = torch.cat([torch.ones_like(trans_incl[:, :1]), trans_incl[:, :-1]], dim=1)
    weights = alpha * trans_excl  # [P, M]
    feat = weights @ features  # [P, C]
    trans = trans_incl[:, -1] if trans_incl.shape[1] else torch.ones_like(pix[:, 0])
    return feat.reshape(height, width, -1), trans.reshape(height, width)
