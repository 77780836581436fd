"""Image and pose metrics: PSNR, SSIM, rotation and translation-direction errors (the one angle formula).

PSNR and SSIM take images in [0, 1] (``[H, W, 3]``). Masked variants average over the
masked pixels only, per channel (the Splatt3R "channel-summed" convention, ≈ −4.77 dB,
is an option of the evaluation command, not of these functions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "SsimTarget",
    "angle_between_deg",
    "psnr",
    "rotation_angle_deg",
    "rotation_error_deg",
    "ssim",
    "ssim_map",
    "ssim_target",
    "translation_direction_error_deg",
]


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


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Every channel of ``x`` blurred by the window ``g ⊗ g`` where it fits: two 1-D passes (``w + w`` taps a pixel
    instead of ``w²``), all channels in one grouped call. ``[1, C, H, W]`` → ``[1, C, H − w + 1, W − w + 1]``"""
    c, w = x.shape[1], g.shape[0]
    rows = g.view(1, 1, w, 1).expand(c, 1, w, 1)
    cols = g.view(1, 1, 1, w).expand(c, 1, 1, w)
    return F.conv2d(F.conv2d(x, rows, groups=c), cols, groups=c)


@dataclass(frozen=True)
class SsimTarget:
    """A target image's side of :func:`ssim_map`, blurred once for many predictions (:func:`ssim_target`).

    ``image`` ``[1, C, H, W]``; ``mu``, ``var``: its windowed mean and variance ``[1, C, H − w + 1, W − w + 1]``;
    ``g``: the 1-D window ``[w]``; ``sigma``: the window's σ. All in the target's dtype.
    """

    image: torch.Tensor
    mu: torch.Tensor
    var: torch.Tensor
    g: torch.Tensor
    sigma: float


def ssim_target(target: torch.Tensor, *, window: int = 11, sigma: float = 1.5) -> SsimTarget:
    """The target's statistics of :func:`ssim_map` (a constant photo compared with many renders). ``[H, W, C]``"""
    t = target.permute(2, 0, 1)[None]
    g = _gaussian_window(window, sigma, t.dtype).to(t.device)
    c = t.shape[1]
    mu, tt = _blur(torch.cat([t, t * t], 1), g).split(c, 1)
    return SsimTarget(t, mu, tt - mu**2, g, sigma)


def ssim_map(
    pred: torch.Tensor, target: torch.Tensor | SsimTarget, *, window: int = 11, sigma: float = 1.5
) -> torch.Tensor:
    """Differentiable per-pixel SSIM, averaged over channels. ``[H, W, C]`` → ``[H − w + 1, W − w + 1]``

    Gaussian window (11×11, σ = 1.5), ``C1 = 0.01²``, ``C2 = 0.03²`` for data range 1,
    population statistics, computed where the window fits inside the image (the
    convention of scikit-image's ``structural_similarity``). ``target``: an image, or its
    :func:`ssim_target` (computed once; then ``window`` and ``sigma`` must be its own).
    """
    if not isinstance(target, SsimTarget):
        target = ssim_target(target.to(pred.dtype), window=window, sigma=sigma)
    elif (target.g.shape[0], target.sigma) != (window, sigma):
        raise ValueError(f"ssim_map: window {window}, sigma {sigma} but the target's are {target.g.shape[0]}, "
                         f"{target.sigma}")  # fmt: skip
    dt = pred.dtype
    t, mu_t, s_tt, g = (x.to(dt) for x in (target.image, target.mu, target.var, target.g))
    p = pred.permute(2, 0, 1)[None]
    c = p.shape[1]
    mu_p, pp, pt = _blur(torch.cat([p, p * p, p * t], 1), g).split(c, 1)
    s_pp = pp - mu_p**2
    s_pt = pt - mu_p * mu_t
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mu_p * mu_t + c1) * (2 * s_pt + c2)) / ((mu_p**2 + mu_t**2 + c1) * (s_pp + s_tt + c2))
    return smap[0].mean(0)


def ssim(
    pred: torch.Tensor | np.ndarray,
    target: torch.Tensor | np.ndarray,
    mask: torch.Tensor | np.ndarray | None = None,
    *,
    window: int = 11,
    sigma: float = 1.5,
) -> float:
    """Structural similarity (Wang et al. 2004): :func:`ssim_map` in float64, averaged.

    The map covers the pixels where the window fits (a ``window // 2`` border is
    excluded, as scikit-image does); with ``mask``, only the masked ones. ``[H, W, C]``,
    mask ``[H, W]``; an empty mask gives ``nan``.
    """
    smap = ssim_map(_t(pred), _t(target), window=window, sigma=sigma)
    if mask is not None:
        pad = window // 2
        m = _t(mask).bool()[pad : pad + smap.shape[0], pad : pad + smap.shape[1]]
        if not bool(m.any()):
            return math.nan
        return float(smap[m].mean())
    return float(smap.mean())


# ------------------------------------------------------------------------------------ pose errors
# One formula for every angle in the package: atan2(sine part, cosine part). acos of a
# rounded cosine is off by ~1e-16/θ rad near 0° (percents at θ = 1e-7 rad, and exactly 0 below
# θ ≈ 1e-8 rad, where cos θ rounds to 1), and likewise near 180°; atan2 keeps full relative
# precision over [0°, 180°].
def rotation_angle_deg(R: np.ndarray) -> float:
    """Rotation angle of ``R`` in degrees, in [0, 180]. [3, 3]

    ``atan2(‖vee(R − Rᵀ)‖ / 2, (tr R − 1) / 2)``: the sine and the cosine of the angle, both
    read off ``R`` (accurate for tiny angles, where ``acos`` of the trace gives 0 or noise).
    """
    D = np.asarray(R, dtype=np.float64)
    sin = 0.5 * float(np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]))
    cos = 0.5 * (float(np.trace(D)) - 1.0)
    return math.degrees(math.atan2(sin, cos))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float | np.ndarray:
    """Angle between vectors in degrees, in [0, 180]: ``atan2(‖a × b‖, a · b)``; NaN where either is zero.

    ``a``, ``b``: ``[3]`` (returns a float) or ``[..., 3]`` (broadcast; returns ``[...]``). Any lengths.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim == 1 and b.ndim == 1:
        if not np.any(a) or not np.any(b):
            return math.nan
        return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b))))
    sin = np.linalg.norm(np.cross(a, b), axis=-1)
    cos = np.sum(a * b, axis=-1)
    out = np.degrees(np.arctan2(sin, cos))
    return np.where(np.any(a, axis=-1) & np.any(b, axis=-1), out, np.nan)


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of ``R_estᵀ R_gt`` in degrees, in [0, 180] (:func:`rotation_angle_deg`). [3, 3] each"""
    return rotation_angle_deg(np.asarray(R_est, dtype=np.float64).T @ np.asarray(R_gt, dtype=np.float64))


def translation_direction_error_deg(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Angle between two translation directions in degrees, in [0, 180] (sign matters); NaN if one is zero. [3] each"""
    return float(angle_between_deg(np.asarray(t_est, dtype=np.float64).reshape(3), np.asarray(t_gt).reshape(3)))
