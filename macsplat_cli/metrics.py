"""Image and pose metrics: PSNR, SSIM, rotation and translation-direction errors.

PSNR and SSIM take images in [0, 1] (``[H, W, 3]``). Masked variants average over the
masked pixels only, per channel (the Splatt3R "channel-summed" convention, ≈ −4.77 dB,
is an option of the evaluation command, not of these functions).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["psnr", "rotation_error_deg", "ssim", "translation_direction_error_deg"]


def _t(x: torch.Tensor | np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).to(torch.float64)


def psnr(
    pred: torch.Tensor | np.ndarray, target: torch.Tensor | np.ndarray, mask: torch.Tensor | np.ndarray | None = None
) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]. ``[H, W, C]``, mask ``[H, W]``.

    The mean squared error is over all channels of the (masked) pixels. Identical images
    give ``inf``; an empty mask gives ``nan``.
    """
    p, t = _t(pred), _t(target)
    err = (p - t) ** 2
    if mask is not None:
        m = _t(mask).bool()
        if not bool(m.any()):
            return math.nan
        err = err[m]
    mse = float(err.mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def _gaussian_window(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(
    pred: torch.Tensor | np.ndarray,
    target: torch.Tensor | np.ndarray,
    mask: torch.Tensor | np.ndarray | None = None,
    *,
    window: int = 11,
    sigma: float = 1.5,
) -> float:
    """Structural similarity (Wang et al. 2004) with an 11×11 Gaussian window, σ = 1.5.

    Constants ``C1 = (0.01)²``, ``C2 = (0.03)²`` for data range 1, population statistics.
    The SSIM map is computed per channel where the window fits inside the image (a
    ``window // 2`` border is excluded, as scikit-image does) and averaged over the
    (masked) pixels and channels. ``[H, W, C]``, mask ``[H, W]``.
    """
    p = _t(pred).permute(2, 0, 1)[None]
    t = _t(target).permute(2, 0, 1)[None]
    c = p.shape[1]
    g = _gaussian_window(window, sigma)
    k = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()
    pad = window // 2

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, k, groups=c)  # 'valid': the map covers the interior pixels

    mu_p, mu_t = blur(p), blur(t)
    s_pp = blur(p * p) - mu_p**2
    s_tt = blur(t * t) - mu_t**2
    s_pt = blur(p * t) - mu_p * mu_t
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mu_p * mu_t + c1) * (2 * s_pt + c2)) / ((mu_p**2 + mu_t**2 + c1) * (s_pp + s_tt + c2))
    smap = smap[0].mean(0)  # [H, W]
    if mask is not None:
        m = _t(mask).bool()[pad : pad + smap.shape[0], pad : pad + smap.shape[1]]
        if not bool(m.any()):
            return math.nan
        return float(smap[m].mean())
    return float(smap.mean())


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of ``R_estᵀ R_gt`` in degrees."""
    c = (np.trace(np.asarray(R_est).T @ np.asarray(R_gt)) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def translation_direction_error_deg(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Angle between two translation directions in degrees (sign matters); nan if one is zero."""
    a, b = np.asarray(t_est, float), np.asarray(t_gt, float)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return math.nan
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))
